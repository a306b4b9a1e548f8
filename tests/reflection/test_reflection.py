"""Tests of stage `reflection` (Xu et al. §4.3) against synthetic ground truth."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ibr_pipeline.geometry.grid_warp import apply_warp, solve_grid_warp
from ibr_pipeline.geometry.planes import fit_plane, mirror_matrix, reflector_mask


def test_mirror_matrix_is_an_involution_fixing_the_plane():
    plane = np.array([1.0, 2.0, -0.5, 0.7])
    M = mirror_matrix(plane)
    assert np.allclose(M @ M, np.eye(4))
    n = plane[:3] / np.linalg.norm(plane[:3])
    d = plane[3] / np.linalg.norm(plane[:3])
    p = -d * n + np.cross(n, [0, 0, 1.0])  # a point on the plane
    assert np.allclose((M @ np.r_[p, 1])[:3], p)
    with pytest.raises(ValueError):
        mirror_matrix([0, 0, 0, 1])


def test_fit_plane_recovers_a_noisy_plane():
    rng = np.random.default_rng(0)
    uv = rng.uniform(-1, 1, (500, 2))
    pts = np.c_[uv, 0.76 + 0.001 * rng.standard_normal(500)]
    p = fit_plane(pts)
    p = p * np.sign(p[2])
    assert np.degrees(np.arccos(p[2])) < 0.5 and abs(p[3] + 0.76) < 2e-3


def test_grid_warp_reduces_a_smooth_misalignment():
    """Eq. 5: the GN warp absorbs a sub-pixel error of the flow and lowers the energy."""
    import cv2
    rng = np.random.default_rng(1)
    H, W = 90, 120
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (H, W, 3)).astype(np.float32), (0, 0), 2.0)
    shift = np.array([1.2, -0.7])
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    ref = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    # ref(u) = tex(u - shift): the true flow into tex is u - shift; we give the identity instead
    u = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).astype(np.float64)
    valid = np.zeros((H, W), bool)
    valid[8:-8, 8:-8] = True
    offs, energies = solve_grid_warp(ref, tex, u, valid, gx=8, gy=6, w_r=1.2, w_a=0.5, iterations=5)
    assert energies[-1] < energies[0]
    warped = apply_warp(u[valid], offs, W, H)
    err = np.abs(warped - (u[valid] - shift)).mean()
    assert err < np.abs(shift).mean(), err  # closer to the true flow than the given one
    # the per-cell normal equations against the formed Jacobian's: the same Gauss-Newton steps
    offs_ref, energies_ref = solve_grid_warp(ref, tex, u, valid, gx=8, gy=6, w_r=1.2, w_a=0.5,
                                             iterations=5, reference=True)
    assert np.allclose(offs, offs_ref, atol=1e-9) and np.allclose(energies, energies_ref)


def test_arap_matrix_matches_its_reference_and_vanishes_on_similarities():
    """Eq. 5's ARAP term (Igarashi et al. 2005): zero for a rotation + scale of the rest grid,
    not for a shear; the vectorised, shared matrix equals the one built in loops."""
    from ibr_pipeline.geometry.grid_warp import (arap_matrix, arap_matrix_reference, arap_normal,
                                                 grid_vertices)
    gx, gy, W, H = 7, 5, 22, 11
    V, sx, sy = grid_vertices(W, H, gx, gy)
    A = arap_matrix(gx, gy, sx, sy)
    assert A.shape == (4 * gx * gy, 2 * (gx + 1) * (gy + 1))
    assert (A != arap_matrix_reference(gx, gy, sx, sy)).nnz == 0
    assert abs(arap_normal(gx, gy, sx, sy) - (A.T @ A)).max() < 1e-12
    P = V.reshape(-1, 2)
    c, s = np.cos(0.3), np.sin(0.3)
    S = 1.4 * np.array([[c, -s], [s, c]])
    similar = P @ S.T + [2.0, -1.0] - P
    assert np.abs(A @ similar.reshape(-1)).max() < 1e-9
    shear = P @ np.array([[1.0, 0.4], [0.0, 1.0]]).T - P
    assert np.abs(A @ shear.reshape(-1)).max() > 0.1


def test_grid_warp_normal_equations_match_the_formed_jacobian():
    import scipy.sparse as sp

    from ibr_pipeline.geometry.grid_warp import (arap_matrix_reference, bilinear_weights,
                                                 gauss_newton_system, gauss_newton_terms_reference)
    rng = np.random.default_rng(2)
    W, H, gx, gy, C = 64, 48, 8, 6, 3
    sx, sy = (W - 1) / gx, (H - 1) / gy
    p = rng.random((3000, 2)) * [W - 1, H - 1]
    p[:5] = [[0, 0], [W - 1, H - 1], [W - 1, 0], [-3, 10], [10, 99]]  # corners, clamped points
    p[5:400] = rng.random((395, 2)) * [20, 20]  # crowd one corner: cells without pixels remain
    p = p[(p[:, 0] < 30) | (p[:, 1] < 30)]
    idx, w = bilinear_weights(p, W, H, gx, gy)
    g1, g2, r = (rng.standard_normal((len(p), C)) for _ in range(3))
    L = (gx + 1) * (gy + 1)
    A, b = gauss_newton_system(w, idx, g1, g2, r, gx, gy, sx, sy, 1.2, 0.5)
    JtJ, b0 = gauss_newton_terms_reference(w, idx, g1, g2, r, L)
    Ar = arap_matrix_reference(gx, gy, sx, sy)
    A0 = JtJ + 1.2 * sp.identity(2 * L) + 0.5 * (Ar.T @ Ar)
    assert A.shape == A0.shape == (2 * L, 2 * L)
    assert abs(A - A0).max() < 1e-9 * abs(A0).max() and np.allclose(b, b0, atol=1e-9)


def run_stage(ws, reflectors: dict | None = None, reflection: dict | None = None,
              force: bool = False, jobs: int = 1):
    """Stages `reflectors` and `reflection` on ws (their results, in order)."""
    from ibr_pipeline.executors import LocalExecutor
    from ibr_pipeline.pipeline import load_configs, run, select_stages
    from ibr_pipeline.stages import STAGES
    configs = load_configs(STAGES, ws, {"reflectors": reflectors or {},
                                        "reflection": reflection or {}})
    with LocalExecutor(jobs) as ex:
        return run(STAGES, ws, configs, select_stages(STAGES, "reflectors", "reflection"),
                   force=force, executor=ex, progress=False)


def read_gt(scene, name):
    from ibr_pipeline.render.oracle import GroundTruth
    return GroundTruth(scene).layers(name)


@pytest.fixture(scope="module")
def tiny_ws(tiny_scene, tmp_path_factory):
    from ibr_pipeline.gt_workspace import write_gt_workspace
    scene = tiny_scene[0]
    ws = write_gt_workspace(scene, tmp_path_factory.mktemp("refl") / "ws", "view_mesh", mesh="grid")
    res = run_stage(ws, {"detect": "off"})
    assert [r.result for r in res] == ["ran", "ran"], res
    return scene, ws


def test_reflector_mask_matches_gt_mirror(tiny_ws):
    from ibr_pipeline.scene import cameras_from_json, read_reflectors
    scene, _ = tiny_ws
    cams = cameras_from_json(scene / "cameras.json")
    mirror = [r for r in read_reflectors(scene / "reflectors.json") if r.name == "mirror"][0]
    ious = []
    for name, cam in cams.items():
        depth = np.load(scene / "gt" / "geom" / f"{Path(name).stem}.npz")["depth"]
        m = reflector_mask(cam, mirror.plane, np.asarray(mirror.polygon), depth)
        gt = read_gt(scene, name)[2] > 0.99
        if gt.sum() > 100:
            ious.append((m & gt).sum() / (m | gt).sum())
    assert ious and min(ious) > 0.9, ious


def test_stage_layers_against_ground_truth(tiny_ws):
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.io.mesh import read_ply
    from ibr_pipeline.metrics import psnr
    from ibr_pipeline.scene import cameras_from_json
    scene, ws = tiny_ws
    cams = cameras_from_json(scene / "cameras.json")
    planes = json.loads(ws.path("reflection/planes.json").read_text())
    assert {r["name"] for r in planes["reflectors"]} >= {"mirror"}
    seen = 0
    for name, cam in cams.items():
        rep = json.loads(ws.path(ws.view_file(name, "layers.json")).read_text())
        if rep["reflector"] is None:
            assert not ws.path(ws.view_file(name, "I0.png")).exists()
            continue
        seen += 1
        I = read_image(scene / "images" / name)
        I0 = read_image(ws.path(ws.view_file(name, "I0.png")))
        I1 = read_image(ws.path(ws.view_file(name, "I1.png")))
        beta = np.load(ws.path(ws.view_file(name, "beta.npy")))
        assert beta.shape == I.shape[:2] and beta.dtype == np.float32
        # Eq. 3 holds in the stored values (8-bit rounding of two layers)
        assert np.abs(I0 + beta[..., None] * I1 - I).max() < 3 / 255
        g0, g1, gb = read_gt(scene, name)
        mir = np.isclose(beta, 1.0) & (gb > 0.99)
        if mir.sum() > 100:  # mirror special case: I1 = I, I0 = 0
            assert psnr(I1, g1, mir) > 30
            assert np.abs(I0[mir]).max() < 2 / 255
        # M1 is mirror-world geometry: projected into this view it lands on the beta support
        M1 = read_ply(ws.path(ws.view_file(name, "M1.ply")))
        uv, z = cam.project(M1.vertices.astype(np.float64))
        assert np.all(z > 0)
        x, y = np.rint(uv).astype(int).T
        ok = (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        assert ok.mean() > 0.99 and (beta[y[ok], x[ok]] > 0).mean() > 0.95
        assert read_ply(ws.path(ws.view_file(name, "M0.ply"))).faces.shape[0] > 0
        for r in rep["reflectors"]:  # the image steps (sparse solves) never raise Eq. 7
            h = {x["step"]: x["energy"] for x in r["history"] if x["step"] in ("start", "end")}
            if h:
                assert h["end"] <= h["start"] * (1 + 1e-9), r["history"]
    assert seen >= 1


def test_bad_input_and_config(tiny_ws, tmp_path):
    from ibr_pipeline.config import build_config
    from ibr_pipeline.errors import ConfigError, InputError
    from ibr_pipeline.geometry.reflection_views import Loader, ReflectionConfig
    with pytest.raises(ConfigError, match="reflection.work_scale"):
        build_config(ReflectionConfig, "reflection", {"work_scale": 5.0})
    with pytest.raises(ConfigError, match="reflection.decompose.min_neighbours"):
        build_config(ReflectionConfig, "reflection",
                     {"decompose": {"min_neighbours": 9, "max_neighbours": 2}})
    with pytest.raises(ConfigError, match="reflection.decompose.grid"):
        build_config(ReflectionConfig, "reflection", {"decompose": {"grid": [40]}})
    with pytest.raises(ConfigError, match="did you mean reflection.decompose.min_neighbours"):
        build_config(ReflectionConfig, "reflection", {"min_neighbours": 9})   # a nested one
    scene, ws = tiny_ws
    import shutil
    from ibr_pipeline.workspace import Workspace
    bad = tmp_path / "bad"
    shutil.copytree(ws.root, bad)
    bws = Workspace(bad)
    name = bws.scene().names[0]
    d = np.load(bws.path(bws.view_file(name, "depth.npy")))
    d[3, 3] = np.nan
    np.save(bws.path(bws.view_file(name, "depth.npy")), d)
    with pytest.raises(InputError, match="depth.npy"):
        Loader(bws, bws.scene(), ReflectionConfig()).raw(name)


def test_mirror_points_skip_a_thick_noisy_reflector():
    """A fused G has thickness at the reflector: M1 must come from the scene behind the camera,
    not from the reflector's own surface (else M1 = M0 and the layers cannot be separated)."""
    from ibr_pipeline.geometry.planes import mirror_points
    from ibr_pipeline.geometry.raycast import build_scene
    from ibr_pipeline.scene import Camera

    def quad(x):
        v = np.array([[x, -3, -3], [x, 3, -3], [x, 3, 3], [x, -3, 3]], float)
        return v, np.array([[0, 1, 2], [0, 2, 3]])
    parts = [quad(0.0), quad(0.006), quad(-0.004), quad(2.0)]  # reflector slab + far wall
    V = np.concatenate([p[0] for p in parts])
    F = np.concatenate([p[1] + 4 * i for i, p in enumerate(parts)])
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    cam = Camera.look_at([1.0, 0.1, 0.2], [0.0, 0.0, 0.0], [0, 0, 1], K, 64, 48)
    mask = np.ones((48, 64), bool)
    X1, D1 = mirror_points(cam, [1.0, 0, 0, 0.0], mask, build_scene(V, F))
    ok = D1 > 0
    assert ok.mean() > 0.9
    assert np.allclose(X1[ok][:, 0], -2.0, atol=1e-3)  # mirror image of the wall at x = 2
    X1n, D1n = mirror_points(cam, [1.0, 0, 0, 0.0], mask, build_scene(V, F), min_gap=0.0)
    assert np.abs(X1n[D1n > 0][:, 0]).max() < 0.05  # the old behaviour: M1 on the reflector


def test_detect_auto_only_without_user_reflectors(tiny_ws):
    from ibr_pipeline.config import build_config
    from ibr_pipeline.errors import ConfigError
    from ibr_pipeline.geometry.reflection_views import ReflectorsConfig, detect_enabled
    _, ws = tiny_ws
    assert ws.exists("input/reflectors.json")

    def cfg(**kw):
        return build_config(ReflectorsConfig, "reflectors", kw)
    assert ReflectorsConfig().detect == "auto"
    assert not detect_enabled(ws, cfg())  # user planes given: the expensive detection is skipped
    assert detect_enabled(ws, cfg(use_user_reflectors=False))
    assert detect_enabled(ws, cfg(detect="on")) and not detect_enabled(ws, cfg(detect="off"))
    with pytest.raises(ConfigError, match="reflectors.detect"):
        build_config(ReflectorsConfig, "reflectors", {"detect": "maybe"})


def test_loader_footprints_and_simplified_m1(tiny_ws):
    """The Loader keeps per-view footprints and rebuilds full ViewGeoms from them (bounded
    memory): the rebuilt M1 points equal the ray-cast mirror points. The stored M1 is the
    quadric-simplified grid: fewer triangles, same depth where it covers the view."""
    from ibr_pipeline.config import build_config
    from ibr_pipeline.geometry.grid_mesh import render_depth
    from ibr_pipeline.geometry.planes import mirror_points
    from ibr_pipeline.io.mesh import read_ply
    from ibr_pipeline.geometry.reflection_views import Loader, ReflectionConfig
    _, ws = tiny_ws
    loader = Loader(ws, ws.scene(), build_config(ReflectionConfig, "reflection", {}))
    loader.reflectors = json.loads(ws.path("reflection/planes.json").read_text())["reflectors"]
    refl = [r for r in loader.reflectors if r["name"] == "mirror"][0]
    checked = rendered = 0
    for name in loader.names:
        if loader.mask(name, refl).sum() < 100:
            continue
        g = loader.geom(name, refl)
        X1, D1 = mirror_points(g.camera, refl["plane"], g.mask, loader.scene,
                               min_gap=loader.cfg.min_gap,
                               bounds=(loader.G.vertices.min(0), loader.G.vertices.max(0)))
        assert np.array_equal(np.isnan(X1), np.isnan(g.X1))
        ok = ~np.isnan(X1)
        assert np.abs(X1[ok] - g.X1[ok]).max() < 1e-5  # float32 footprint depth, metres
        rep = json.loads(ws.path(ws.view_file(name, "layers.json")).read_text())
        r = [r for r in rep["reflectors"] if r["name"] == "mirror"]
        if r and r[0].get("m1_simplify"):
            s = r[0]["m1_simplify"]
            assert s["faces"] <= s["grid_faces"]
            if len(rep["reflectors"]) == 1 and not any(r[0]["pose"]):
                M1 = read_ply(ws.path(ws.view_file(name, "M1.ply")))
                d = render_depth(M1.vertices.astype(np.float64), M1.faces, g.camera)
                both = (d > 0) & (D1 > 0)
                assert both.sum() > 0.8 * (D1 > 0).sum()
                assert np.median(np.abs(d - D1)[both] / D1[both]) < 0.005
                rendered += 1
        checked += 1
    assert checked >= 1 and rendered >= 1
    assert len(loader._full) <= loader.GEOM_CACHE


def test_multiview_second_pass_runs(tiny_ws, tmp_path):
    """§4.3.3's second pass (decompose.multiview, off by default): non-mirror reflectors are
    decomposed twice, the second time against the neighbours' first-pass layers (Eqs. 11-13)."""
    import shutil

    from ibr_pipeline.workspace import Workspace
    _, ws = tiny_ws
    ws2 = Workspace(shutil.copytree(ws.root, tmp_path / "mv"))
    res = run_stage(ws2, {"detect": "off"}, {"decompose": {"multiview": True}})
    assert res[-1].result == "ran", res
    passes = set()
    for layers in (ws2.root / "views").glob("*/layers.json"):
        for r in json.loads(layers.read_text())["reflectors"]:
            if not r.get("mirror") and r.get("history"):
                passes |= {h.get("pass") for h in r["history"]}
    assert passes == {1, 2}
    for R in (ws2.root / "views").glob("*/*.npy"):
        assert np.isfinite(np.load(R)).all(), R
