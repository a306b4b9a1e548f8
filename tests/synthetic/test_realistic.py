"""The phone-camera model of `ibr synth --realistic` (synthetic/realistic.py) and the captures it
writes: each degradation against its stated model, then the generated folder."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.scene import Camera
from ibr_pipeline.synthetic import realistic as R

K = Camera.intrinsics_from_fov(160, 120, 62.0)  # the synthetic scenes' camera at tiny's size


# --- sRGB ---------------------------------------------------------------------------------------
def test_srgb_round_trip_and_monotone():
    x = np.linspace(0.0, 1.0, 200001)
    e = R.srgb_encode(x)
    assert np.abs(R.srgb_decode(e) - x).max() < 1e-6
    assert np.abs(R.srgb_encode(R.srgb_decode(x)) - x).max() < 1e-6
    assert np.all(np.diff(e) > 0) and np.all(np.diff(R.srgb_decode(x)) > 0)
    assert e[0] == 0.0 and abs(e[-1] - 1.0) < 1e-12
    assert abs(R.srgb_encode(0.18) - 0.4613) < 1e-4  # mid-grey: sRGB 118/255
    assert R.srgb_encode(0.002) == pytest.approx(12.92 * 0.002)  # the linear toe
    # the same curve as the display encoder of videos
    from ibr_pipeline.render.video import to_display

    lin = np.random.default_rng(0).random((50, 40, 3))
    assert np.array_equal(np.clip(np.rint(R.srgb_encode(lin) * 255), 0, 255).astype(np.uint8),
                          to_display(lin))


# --- noise --------------------------------------------------------------------------------------
@pytest.mark.parametrize("level, full_well, read", [(0.2, 2000.0, 0.002), (0.02, 2000.0, 0.002),
                                                    (0.5, 300.0, 0.0), (0.1, np.inf, 0.01)])
def test_noise_is_unbiased_with_the_model_variance(level, full_well, read):
    flat = np.full((1000, 1000), level)
    y = R.add_sensor_noise(flat, full_well, read, np.random.default_rng(1))
    var = level / full_well + read ** 2
    assert abs(y.mean() - level) < 5 * np.sqrt(var / flat.size)
    assert y.var() == pytest.approx(var, rel=0.03)


def test_noise_is_seeded_and_checked():
    img = np.full((20, 30, 3), 0.3)
    a = R.add_sensor_noise(img, 2000, 0.002, np.random.default_rng(5))
    assert np.array_equal(a, R.add_sensor_noise(img, 2000, 0.002, np.random.default_rng(5)))
    assert not np.array_equal(a, R.add_sensor_noise(img, 2000, 0.002, np.random.default_rng(6)))
    assert a.shape == img.shape
    with pytest.raises(ValueError):
        R.add_sensor_noise(img, 0, 0.002, np.random.default_rng(0))
    with pytest.raises(ValueError):
        R.add_sensor_noise(np.zeros((4, 4, 2)), 2000, 0.002, np.random.default_rng(0))


# --- vignetting ---------------------------------------------------------------------------------
def test_vignetting_centre_corners_and_shape():
    v = R.vignetting(161, 121, 0.25)
    assert v.shape == (121, 161)
    assert v[60, 80] == 1.0
    for y, x in ((0, 0), (0, 160), (120, 0), (120, 160)):
        assert v[y, x] == pytest.approx(0.75, abs=1e-12)
    assert np.allclose(v, v[::-1]) and np.allclose(v, v[:, ::-1])  # radial about the centre
    diag = v[np.arange(61), np.round(np.arange(61) * 80 / 60).astype(int)]
    assert np.all(np.diff(diag) > 0)  # monotone fall-off towards the corner
    assert np.all(R.vignetting(64, 48, 0.0) == 1.0)
    assert R.vignetting_factor(1.0, 0.4) == pytest.approx(0.6)
    with pytest.raises(ValueError):
        R.vignetting(64, 48, 1.0)


# --- auto-exposure ------------------------------------------------------------------------------
def test_exposure_gains_bounded_smooth_and_seeded():
    n, amp = 120, 0.3
    phase = np.arange(n) / n
    g = R.exposure_gains(phase, amp, np.random.default_rng([7, 404]))
    assert np.all(g >= 1 - amp) and np.all(g <= 1 + amp)
    assert g.max() - g.min() > amp  # uses its range
    assert abs(g.mean() - 1.0) < 1e-12  # the captures' mean exposure is the nominal one
    assert np.abs(np.diff(g)).max() < 0.05  # smooth from frame to frame ...
    assert np.abs(np.diff(g, 2)).max() < 0.005  # ... and in its changes
    assert abs(g[0] - g[-1]) < 0.05  # a closed loop
    assert np.array_equal(g, R.exposure_gains(phase, amp, np.random.default_rng([7, 404])))
    assert not np.allclose(g, R.exposure_gains(phase, amp, np.random.default_rng([8, 404])))
    # the curve does not depend on which phases are asked for
    mid = R.exposure_gains(np.array([0.5, 3.5]) / n, amp, np.random.default_rng([7, 404]))
    assert np.allclose(mid, [(g[0] + g[1]) / 2, (g[3] + g[4]) / 2], atol=0.01)
    assert np.all(R.exposure_gains(phase, 0.0, np.random.default_rng(0)) == 1.0)
    with pytest.raises(ValueError):
        R.exposure_gains(phase, 1.0, np.random.default_rng(0))


# --- lens distortion ----------------------------------------------------------------------------
def _grid():
    u, v = np.meshgrid(np.linspace(0, 159, 33), np.linspace(0, 119, 25))
    return np.stack([u, v], -1).reshape(-1, 2)


@pytest.mark.parametrize("k1, k2", [(-0.15, 0.0), (0.1, 0.0), (-0.1, 0.03), (0.05, -0.02)])
def test_distortion_centre_inverse_and_radial_lines(k1, k2):
    c = K[:2, 2]
    assert np.allclose(R.distort_points(c, K, k1, k2), c, atol=1e-12)
    p = _grid()
    assert np.abs(R.undistort_points(R.distort_points(p, K, k1, k2), K, k1, k2) - p).max() < 0.05
    assert np.abs(R.distort_points(R.undistort_points(p, K, k1, k2), K, k1, k2) - p).max() < 0.05
    # OpenCV's radial model, the same formula
    import cv2

    x = np.c_[(p - c) / K[0, 0], np.ones(len(p))]
    ocv, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), K, np.array([k1, k2, 0.0, 0.0]))
    assert np.abs(ocv.reshape(-1, 2) - R.distort_points(p, K, k1, k2)).max() < 1e-6
    # a straight line through the centre stays straight (and keeps its direction)
    for ang in (0.0, 0.4, 1.3, 2.5):
        d = np.array([np.cos(ang), np.sin(ang)])
        q = R.distort_points(c + np.linspace(-70, 70, 41)[:, None] * d, K, k1, k2) - c
        assert np.abs(q[:, 0] * d[1] - q[:, 1] * d[0]).max() < 1e-9
        assert np.all(np.diff(q @ d) > 0)
    # barrel pulls the corners in, pincushion pushes them out
    corner = R.distort_points(np.array([0.0, 0.0]), K, k1, 0.0)
    assert (np.linalg.norm(corner - c) < np.linalg.norm(c)) == (k1 < 0)


def test_distort_image_moves_a_feature_where_distort_points_says():
    k1, k2, W, H = -0.15, 0.01, 160, 120
    px, py = R.distortion_padding(K, W, H, k1, k2)
    assert px > 0 and py > 0
    Kp = K.copy()
    Kp[0, 2] += px
    Kp[1, 2] += py
    # every source point of the photo lies inside the padded render
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    src = R.undistort_points(np.stack([uu, vv], -1), K, k1, k2) + (px, py)
    assert src[..., 0].min() >= 0 and src[..., 0].max() <= W + 2 * px - 1
    assert src[..., 1].min() >= 0 and src[..., 1].max() <= H + 2 * py - 1
    p = np.array([30.0, 25.0])  # a blob near a corner of the pinhole image
    yy, xx = np.mgrid[0:H + 2 * py, 0:W + 2 * px]
    blob = np.exp(-((xx - p[0] - px) ** 2 + (yy - p[1] - py) ** 2) / (2 * 2.0 ** 2))
    out = R.distort_image(np.repeat(blob[..., None], 3, 2), Kp, k1, k2, K_out=K, size=(W, H))
    assert out.shape == (H, W, 3)
    w = out[..., 0]
    centroid = np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()
    assert np.linalg.norm(centroid - R.distort_points(p, K, k1, k2)) < 0.15
    assert R.distortion_padding(K, W, H, 0.1, 0.0) == (0, 0)  # pincushion needs no margin


def test_distortion_that_folds_over_is_refused():
    with pytest.raises(ValueError, match="folds"):
        R.check_distortion(-0.4, 0.0, R.corner_radius(K, 160, 120))
    R.check_distortion(-0.2, 0.0, R.corner_radius(K, 160, 120))
    with pytest.raises(ValueError):
        R.distort_image(np.zeros((120, 160, 3)), K, -0.4, 0.0)


# --- the whole camera ---------------------------------------------------------------------------
def test_degrade():
    from ibr_pipeline.render.video import to_display

    lin = np.random.default_rng(2).random((48, 64, 3)) * 0.7
    ideal = R.CaptureModel(vignetting=0.0, exposure_range=0.0).noise_scaled(0.0)
    assert np.array_equal(R.degrade(lin, 1.0, ideal, np.random.default_rng(0)), to_display(lin))
    phone = R.CaptureModel()
    a = R.degrade(lin, 1.0, phone, np.random.default_rng(3))
    assert a.dtype == np.uint8 and a.shape == lin.shape
    assert np.array_equal(a, R.degrade(lin, 1.0, phone, np.random.default_rng(3)))
    # decoded, the photo is the vignetted signal plus the model's noise
    resid = R.srgb_decode(a / 255.0) - lin * R.vignetting(64, 48, phone.vignetting)[..., None]
    assert abs(resid.mean()) < 2e-3 and resid.std() < 0.03
    assert R.degrade(lin, 1.3, phone, np.random.default_rng(3)).mean() > a.mean() + 5
    assert np.all(R.degrade(np.full((8, 8, 3), 2.0), 1.0, phone, np.random.default_rng(0)) == 255)
    with pytest.raises(ValueError):
        R.degrade(lin[..., 0], 1.0, phone, np.random.default_rng(0))
    with pytest.raises(ValueError):
        R.degrade(lin, 0.0, phone, np.random.default_rng(0))
    with pytest.raises(ValueError, match="intrinsics"):
        R.degrade(lin, 1.0, R.CaptureModel(k1=-0.1), np.random.default_rng(0))


def test_capture_model_defaults():
    m = R.CaptureModel()
    m.validate()
    assert (m.k1, m.k2) == (0.0, 0.0) and not m.distorted  # the pipeline does not undistort yet
    s = m.noise_scaled(2.0)
    assert s.full_well == m.full_well / 4 and s.read_noise == 2 * m.read_noise
    with pytest.raises(ValueError):
        m.noise_scaled(-1.0)


def test_held_out_steps_are_those_of_test_path():
    from ibr_pipeline.synthetic.generate import held_out_steps
    from ibr_pipeline.synthetic.paths import capture_path, test_path
    from ibr_pipeline.synthetic.scenes import build_world

    world = build_world("tiny", 0)
    a = test_path(world, 3, 64, 48, 0, 8)
    b = capture_path(world, 8, 64, 48, 0, held_out_steps(3, 8))
    for ca, cb in zip(a, b):
        assert np.array_equal(ca.cam_from_world, cb.cam_from_world)


# --- the generated capture ----------------------------------------------------------------------
def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def realistic_tiny(tmp_path_factory):
    from ibr_pipeline.commands import synth as cli

    out = tmp_path_factory.mktemp("real") / "tiny"
    p = argparse.ArgumentParser()
    cli.add_synth_arguments(p)
    assert cli.synth_main(p.parse_args(["tiny", str(out), "--realistic", "--seed", "3",
                                        "--no-progress"])) == 0
    return out


def test_realistic_input_folder_has_images_only(realistic_tiny):
    from ibr_pipeline.io.inputs import read_input
    from ibr_pipeline.scene import cameras_from_json

    root = realistic_tiny
    assert sorted(p.name for p in root.iterdir()) == ["gt", "images"]
    scene = read_input(root)
    assert scene.source == "images" and len(scene.views) == 8 and not scene.reflectors
    assert all(v.camera is None and v.depth is None for v in scene.views)
    gt = cameras_from_json(root / "gt" / "cameras.json")
    assert sorted(gt) == scene.names
    assert len(json.loads((root / "gt" / "reflectors.json").read_text())["reflectors"]) >= 3
    for sub in ("geom", "I0", "I1", "beta", "test/images", "test/linear", "test/geom",
                "flythrough/images", "raytree"):
        assert any((root / "gt" / sub).iterdir()), sub
    summary = json.loads((root / "gt" / "scene.json").read_text())
    assert summary["image_encoding"] == "srgb" and summary["options"]["realistic"] is True
    model = summary["capture_model"]
    assert model["model"]["vignetting"] == R.CaptureModel().vignetting
    assert sorted(model["exposure_gain"]["capture"]) == scene.names
    assert len(model["exposure_gain"]["test"]) == 2


def test_realistic_photos_follow_the_model(realistic_tiny):
    """A held-out photograph, linearised, is its noiseless render times gain and vignetting."""
    from ibr_pipeline.io.images import read_image

    root = realistic_tiny
    gains = json.loads((root / "gt" / "scene.json").read_text())["capture_model"]["exposure_gain"]["test"]
    for name, g in gains.items():
        photo = R.srgb_decode(read_image(root / "gt" / "test" / "images" / name))
        lin = read_image(root / "gt" / "test" / "linear" / name)
        expect = np.clip(lin * g * R.vignetting(160, 120, 0.25)[..., None], 0, 1)
        assert np.median(np.abs(photo - expect)) < 0.02
        assert abs((photo - expect).mean()) < 0.01


def test_realistic_generation_is_deterministic(realistic_tiny, tmp_path):
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    generate(SynthOptions("tiny", seed=3, realistic=True, progress=False), tmp_path / "again")
    a, b = _files(realistic_tiny), _files(tmp_path / "again")
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    generate(SynthOptions("tiny", seed=4, realistic=True, progress=False, test_views=0,
                          flythrough=0, raytree_pairs=0), tmp_path / "other")
    assert a["images/0000.png"] != (tmp_path / "other" / "images" / "0000.png").read_bytes()


def test_realistic_with_distortion_and_without_noise(tmp_path):
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    base = dict(seed=0, width=64, height=48, views=3, test_views=1, flythrough=0,
                raytree_pairs=0, gt_layers=False, progress=False, realistic=True,
                noise_scale=0.0, vignetting=0.0, exposure_range=0.0)
    generate(SynthOptions("tiny", **base), tmp_path / "pin")
    generate(SynthOptions("tiny", distortion=-0.1, **base), tmp_path / "dist")
    pin = read_image(tmp_path / "pin" / "images" / "0001.png")
    dist = read_image(tmp_path / "dist" / "images" / "0001.png")
    assert pin.shape == dist.shape == (48, 64, 3)
    # noiseless, unvignetted, gain 1: the photo is the sRGB encoding of the linear render
    lin = read_image(tmp_path / "pin" / "gt" / "test" / "linear" / "test_000.png")
    photo = R.srgb_decode(read_image(tmp_path / "pin" / "gt" / "test" / "images" / "test_000.png"))
    assert np.abs(photo - lin).max() < 2.5 / 255
    # barrel distortion moves the image off-centre but not the centre; geometry stays pinhole
    assert np.abs(pin - dist)[20:28, 28:36].mean() < np.abs(pin - dist).mean()
    with np.load(tmp_path / "pin" / "gt" / "geom" / "0001.npz") as a, \
            np.load(tmp_path / "dist" / "gt" / "geom" / "0001.npz") as b:
        assert np.array_equal(a["depth"], b["depth"]) and np.array_equal(a["material"], b["material"])
    rec = json.loads((tmp_path / "dist" / "gt" / "scene.json").read_text())["capture_model"]
    assert rec["model"]["k1"] == -0.1 and rec["model"]["full_well"] is None


def test_ideal_scene_record_is_unchanged(tiny_scene):
    root, summary, _ = tiny_scene
    assert not {"realistic", "noise_scale", "distortion"} & set(summary["options"])
    assert summary["image_encoding"] == "linear" and "capture_model" not in summary
    assert not (root / "gt" / "test" / "linear").exists()


def test_realistic_refuses_a_folder_with_exact_inputs(tmp_path):
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "cameras.json").write_text("{}")
    with pytest.raises(InputError, match="cameras.json"):
        generate(SynthOptions("tiny", realistic=True, progress=False), tmp_path / "out")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["cameras.json"]


@pytest.mark.parametrize("argv, flag", [
    (["--realistic", "--noise-scale", "-1"], "--noise-scale"),
    (["--realistic", "--vignetting", "0.95"], "--vignetting"),
    (["--realistic", "--exposure-range", "-0.1"], "--exposure-range"),
    (["--realistic", "--distortion", "-0.4"], "--distortion"),
    (["--realistic", "--distortion", "0.9"], "--distortion"),
    (["--distortion", "-0.1"], "--distortion"),
    (["--noise-scale", "2"], "--noise-scale"),
])
def test_bad_realistic_flags_name_the_flag(argv, flag, tmp_path):
    from ibr_pipeline.commands import synth as cli

    p = argparse.ArgumentParser()
    cli.add_synth_arguments(p)
    with pytest.raises(InputError, match=flag) as e:
        cli.synth_main(p.parse_args(["tiny", str(tmp_path / "out")] + argv))
    assert "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()


def test_help_states_the_model_defaults():
    """commands/synth.py must stay light (no numpy), so its help repeats CaptureModel's defaults."""
    import re

    from ibr_pipeline.commands import synth as cli

    p = argparse.ArgumentParser()
    cli.add_synth_arguments(p)
    helps = {a.dest: a.help for a in p._actions}
    m = R.CaptureModel()
    for dest, value in (("vignetting", m.vignetting), ("exposure_range", m.exposure_range),
                        ("distortion", m.k1)):
        assert float(re.search(r"default ([-0-9.]+)", helps[dest]).group(1)) == value, dest
