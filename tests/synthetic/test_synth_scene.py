"""The generated `tiny` scene: layout, ground-truth self-consistency, ray tree, determinism."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ibr_pipeline.io.images import read_depth_png, read_image
from ibr_pipeline.io.inputs import read_input
from ibr_pipeline.scene import cameras_from_json


def _kinds(root: Path) -> np.ndarray:
    mats = json.loads((root / "gt" / "scene.json").read_text())["materials"]
    return np.array([m["kind"] for m in mats])


def _gray8(path: Path) -> np.ndarray:
    from PIL import Image
    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


def test_tiny_is_complete(tiny_scene):
    # (its speed is measured by `ibr bench synth`, not asserted here: see docs/BENCHMARKS.md)
    root, summary, _ = tiny_scene
    scene = read_input(root)
    assert scene.source == "colmap" and len(scene.views) == 8
    assert all(v.camera is not None and v.depth is not None for v in scene.views)
    names = {r.name for r in scene.reflectors}
    assert {"mirror", "tv_screen", "table_top"} <= names
    assert next(r for r in scene.reflectors if r.name == "mirror").beta == 1.0
    for key in ("test_cameras.json", "flythrough_cameras.json", "mesh.ply", "scene.json"):
        assert (root / "gt" / key).is_file()
    test = cameras_from_json(root / "gt" / "test_cameras.json")
    assert len(test) == 2
    for name in test:
        assert (root / "gt" / "test" / "images" / name).is_file()
    assert (root / "contact_sheet.png").is_file()
    # COLMAP model and cameras.json agree
    js = cameras_from_json(root / "cameras.json")
    for v in scene.views:
        assert np.allclose(v.camera.K, js[v.name].K, atol=1e-6)
        assert np.allclose(v.camera.cam_from_world, js[v.name].cam_from_world, atol=1e-6)


def test_test_views_are_held_out_frames_between_capture_frames(tiny_scene):
    """Held-out protocol: each test camera lies on the capture trajectory between two
    consecutive capture frames, on neither of them."""
    root = tiny_scene[0]
    cap = np.array([c.center for c in cameras_from_json(root / "cameras.json").values()])
    for c in cameras_from_json(root / "gt" / "test_cameras.json").values():
        d = np.linalg.norm(cap - c.center, axis=1)
        a, b = np.argsort(d)[:2]
        assert abs(int(a) - int(b)) in (1, len(cap) - 1)  # the two nearest are consecutive
        gap = np.linalg.norm(cap[a] - cap[b])
        assert 0.05 < d[a] < gap and d[b] < gap


def test_test_path_samples_the_capture_trajectory():
    from ibr_pipeline.synthetic.paths import capture_path, test_path
    from ibr_pipeline.synthetic.scenes import build_world

    world = build_world("mirror_room", 0)
    cap = capture_path(world, 24, 64, 48, 0)
    test = test_path(world, 4, 64, 48, 0, n_capture=24)
    # fractional steps of the same trajectory: step 0 and 1 of a 2x denser sampling are capture
    dense = capture_path(world, 24, 64, 48, 0, steps=[0.0, 1.0, 0.5])
    assert np.allclose(dense[0].cam_from_world, cap[0].cam_from_world)
    assert np.allclose(dense[1].cam_from_world, cap[1].cam_from_world)
    assert np.allclose(dense[2].cam_from_world, test[0].cam_from_world)
    centres = np.array([c.center for c in cap])
    for c in test:
        assert np.linalg.norm(centres - c.center, axis=1).min() > 0.05


def test_sensor_depth_format(tiny_scene):
    root = tiny_scene[0]
    scene = read_input(root)
    v = scene.views[0]
    d = read_depth_png(root / "depth" / Path(v.name).with_suffix(".png"))
    W, H = v.camera.size
    assert d.shape[1] < W and d.shape[1] * H == d.shape[0] * W  # smaller, same aspect
    gt = np.load(root / "gt" / "geom" / f"{Path(v.name).stem}.npz")["depth"]
    valid = d > 0
    assert 0.5 < valid.mean() < 1.0  # holes exist, most pixels measured
    # same range of values as the exact depth (ToF: mirrors give farther, reflected depths)
    assert abs(np.median(d[valid]) - np.median(gt)) < 0.5


def test_eq3_holds_in_stored_values(tiny_scene):
    root = tiny_scene[0]
    worst = 0.0
    for p in sorted((root / "images").glob("*.png")):
        I = read_image(p).astype(np.float64)
        I0 = read_image(root / "gt" / "I0" / p.name).astype(np.float64)
        I1 = read_image(root / "gt" / "I1" / p.name).astype(np.float64)
        beta = _gray8(root / "gt" / "beta" / p.name)
        worst = max(worst, np.abs(I - (I0 + beta[..., None] * I1)).max())
    assert worst <= 1.0 / 255 + 1e-6
    # mirror pixels: beta = 1 and I0 = 0 (Xu et al.: I1 = I inside mirrors)
    kinds = _kinds(root)
    for p in sorted((root / "gt" / "geom").glob("*.npz")):
        mat = np.load(p)["material"]
        beta = _gray8(root / "gt" / "beta" / f"{p.stem}.png")
        mirror = kinds[mat] == "mirror"
        if mirror.any():
            assert np.all(beta[mirror] == 1.0)
            assert np.all(read_image(root / "gt" / "I0" / f"{p.stem}.png")[mirror] == 0)
        assert np.all(beta[kinds[mat] == "diffuse"] == 0)


def test_gt_depth_reprojects_diffuse_colours(tiny_scene):
    """Unproject view A with GT depth into view B: co-visible diffuse pixels have the same colour."""
    root = tiny_scene[0]
    scene = read_input(root)
    kinds = _kinds(root)
    errs = []
    views = scene.views
    for a, b in ((a, b) for a in views for b in views if a is not b):
        ga = np.load(root / "gt" / "geom" / f"{Path(a.name).stem}.npz")
        gb = np.load(root / "gt" / "geom" / f"{Path(b.name).stem}.npz")
        Ia, Ib = read_image(root / "images" / a.name), read_image(root / "images" / b.name)
        ca, cb = a.camera, b.camera
        uv = ca.pixel_grid().reshape(-1, 2)
        da = ga["depth"].reshape(-1).astype(np.float64)
        sel = (da > 0) & (kinds[ga["material"].reshape(-1)] == "diffuse")
        X = ca.unproject(uv[sel], da[sel])
        uvb, zb = cb.project(X)
        rb = np.rint(uvb)
        # only projections within 0.05 px of a pixel centre: the textures have sharp spots, so
        # larger offsets would measure texture variation, not GT consistency
        near_centre = np.all(np.abs(uvb - rb) < 0.05, axis=1)
        inside = (zb > 0) & (rb[:, 0] >= 0) & (rb[:, 0] < cb.width) & (rb[:, 1] >= 0) & (rb[:, 1] < cb.height)
        ok = near_centre & inside
        ix, iy = rb[ok, 0].astype(int), rb[ok, 1].astype(int)
        dep_b = gb["depth"][iy, ix]
        vis = np.abs(dep_b - zb[ok]) < 0.005 + 0.002 * zb[ok]
        diff_b = kinds[gb["material"][iy, ix]] == "diffuse"
        keep = vis & diff_b
        src = Ia.reshape(-1, 3)[np.nonzero(sel)[0][ok][keep]]
        errs.append(src - Ib[iy[keep], ix[keep]])
    e = np.concatenate(errs)
    print(f"{len(e)} samples")
    assert len(e) > 100, "too few co-visible pixels to judge"
    psnr = 10 * np.log10(1.0 / np.mean(e ** 2))
    print(f"reprojection PSNR {psnr:.1f} dB over {len(e)} co-visible diffuse pixels")
    assert psnr >= 40.0


def test_mirror_depth_lies_on_reflector_plane(tiny_scene):
    root = tiny_scene[0]
    scene = read_input(root)
    kinds = _kinds(root)
    mirror = next(r for r in scene.reflectors if r.name == "mirror")
    n, d0 = np.asarray(mirror.plane[:3]), mirror.plane[3]
    count = 0
    for v in scene.views:
        g = np.load(root / "gt" / "geom" / f"{Path(v.name).stem}.npz")
        m = kinds[g["material"]] == "mirror"
        if not m.any():
            continue
        X = v.camera.unproject(v.camera.pixel_grid()[m], g["depth"][m].astype(np.float64))
        assert np.abs(X @ n + d0).max() < 1e-3
        count += m.sum()
    assert count > 0, "no view sees the mirror"


def test_ray_tree_composite_and_decoding(tiny_scene):
    import open3d as o3d

    from ibr_pipeline.synthetic.raytree import BIT_R, composite_ray_tree, read_ray_tree, view_directions
    from ibr_pipeline.scene import Camera

    root, summary, _ = tiny_scene
    tree = read_ray_tree(root / "gt" / "raytree" / "pair_00.npz")
    comp = composite_ray_tree(tree)
    err = np.abs(comp - tree["image"].astype(np.float64)).max()
    print(f"ray-tree composite max error {err * 255:.3f}/255")
    assert err <= 1.0 / 255
    # the old camera is a capture view: composite matches the stored image up to 8-bit layers
    old = summary["raytree_pairs"][0]["old_view"]
    assert np.abs(comp - read_image(root / "images" / old)).max() <= 2.5 / 255
    # Lochmann Eq. 1 decoding: w_r = w_d + Z_r * reflect(view dir) lies on the scene surface
    w, h = (int(x) for x in tree["size"])
    cam = Camera(tree["K"], tree["cam_from_world"], w, h)
    r = (tree["valid"] & BIT_R) > 0
    assert r.sum() > 50
    d = view_directions(cam)[r]
    wd = cam.unproject(cam.pixel_grid()[r], tree["D_z"][r].astype(np.float64))
    n = tree["normal"][r].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    refl = d - 2 * np.sum(d * n, axis=1, keepdims=True) * n
    wr = wd + tree["R_z"][r][:, None] * refl
    mesh = o3d.t.io.read_triangle_mesh(str(root / "gt" / "mesh.ply"))
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(mesh)
    dist = rs.compute_distance(o3d.core.Tensor(wr.astype(np.float32))).numpy()
    assert np.percentile(dist, 99) < 2e-3
    # a second camera and its ground truth are there to score a warp
    assert tree["new_image"].shape == tree["image"].shape
    assert not np.allclose(tree["new_cam_from_world"], tree["cam_from_world"])


def test_generation_is_bit_for_bit_deterministic(tiny_scene, tmp_path):
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    root = tiny_scene[0]
    generate(SynthOptions("tiny", seed=3, progress=False), tmp_path / "again")
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(tmp_path / "again") for p in (tmp_path / "again").rglob("*")
                           if p.is_file())
    for f in files:
        assert (root / f).read_bytes() == (tmp_path / "again" / f).read_bytes(), f
    # a different seed gives a different room
    generate(SynthOptions("tiny", seed=4, progress=False, test_views=0, flythrough=0,
                          raytree_pairs=0), tmp_path / "other")
    assert (root / "images" / "0000.png").read_bytes() != (tmp_path / "other" / "images" / "0000.png").read_bytes()
