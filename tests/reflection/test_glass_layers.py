"""Glass: the base layer is the scene seen through the pane, drawn where it is (behind the plane),
not painted on the pane as a mirror's surface is."""
import json

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.geometry.planes import depth_points
from ibr_pipeline.scene import cameras_from_json
from ibr_pipeline.synthetic.generate import SynthOptions, generate
from ibr_pipeline.synthetic.materials import reflecting_indices


@pytest.fixture(scope="module")
def glass_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("glass")
    generate(SynthOptions("glass_room", width=160, height=120, views=12, test_views=1,
                          flythrough=2, progress=False), root)
    return root


def _behind_fraction(ws, pane) -> float:
    """Of the view-depth points seen through the pane's polygon, the fraction more than 5 cm
    behind its plane."""
    cams = cameras_from_json(ws / "global" / "cameras.json")
    n, d = np.asarray(pane["plane"][:3]), pane["plane"][3]
    lo, hi = np.min(pane["polygon"], 0), np.max(pane["polygon"], 0)
    behind = seen = 0
    for name, cam in cams.items():
        X = depth_points(cam, np.load(ws / "views" / name / "depth.npy")).reshape(-1, 3)
        ray = X - cam.center
        t = -(cam.center @ n + d) / (ray @ n)  # where each pixel's ray meets the plane
        hit = cam.center + ray * t[:, None]
        span = hi - lo > 0.1  # the polygon's two in-plane axes
        through = (t > 0) & np.all((hit > lo + 0.05) & (hit < hi - 0.05) | ~span, axis=1)
        seen += through.sum()
        behind += (through & (X @ n + d < -0.05)).sum()
    assert seen > 2000, seen  # the scene's cameras look through the pane
    return behind / seen


@pytest.mark.parametrize("material", ["glass", None])
def test_view_depth_behind_glass_is_the_transmitted_scene(glass_scene, tmp_path, material):
    refl = json.loads((glass_scene / "reflectors.json").read_text())
    pane = next(r for r in refl["reflectors"] if r["name"] == "glass")
    assert pane["material"] == "glass"  # ibr synth says what the pane is
    src = tmp_path / "input"
    src.mkdir()
    for p in glass_scene.iterdir():
        (src / p.name).symlink_to(p)
    if material is None:  # the same plane given without its material: treated as a mirror
        (src / "reflectors.json").unlink()
        pane_only = dict(pane, material=None)
        (src / "reflectors.json").write_text(json.dumps({"reflectors": [pane_only]}))
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(src), "--until", "view_depth", "--jobs", "1",
                 "--set", "global_mesh.progress=false"]) == 0
    frac = _behind_fraction(ws, pane)
    if material == "glass":
        assert frac > 0.8, frac   # G and every view depth keep the room behind the pane
    else:  # a mirror's depth is its plane (what stays behind it: TSDF rounding at its edges)
        assert frac < 0.2, frac


def test_glass_counts_as_a_reflector_in_evaluation():
    mats = [{"index": 0, "kind": "diffuse", "kr": 0.0}, {"index": 1, "kind": "glossy", "kr": 0.3},
            {"index": 2, "kind": "glass_pane", "kr": 0.0}, {"index": 3, "kind": "mirror", "kr": 1}]
    assert reflecting_indices(mats) == [1, 2, 3]


def test_the_oracle_draws_what_the_pane_transmits(glass_scene):
    """The oracle's M0 behind glass is the GT geometry beyond the pane (its first surface is the
    pane); everywhere else it is the GT depth unchanged."""
    from ibr_pipeline.render.oracle import GroundTruth
    gt = GroundTruth(glass_scene)
    pane = next(r for r in gt.reflectors if r.name == "glass")
    n, d = np.asarray(pane.plane[:3]), pane.plane[3]
    moved = 0
    for name, cam in gt.cameras.items():
        surface = gt.geom(name)["depth"].astype(np.float32)
        through = gt.transmitted_depth(cam, surface)
        changed = np.abs(through - surface) > 1e-4
        X = depth_points(cam, surface)
        on_pane = np.abs(X @ n + d) < 0.02
        assert not (changed & ~on_pane).any()            # only pane pixels move
        if changed.any():                                # and they move behind it
            Y = depth_points(cam, through)[changed]
            assert np.all(Y @ n + d < -1e-4), name
            assert np.all(through[changed] > surface[changed])
        moved += changed.sum()
    assert moved > 2000, moved
