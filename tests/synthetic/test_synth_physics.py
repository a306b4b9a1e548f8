"""Image formation of the reflective parts, checked against the optics formulas at low resolution."""
from __future__ import annotations

import numpy as np
import pytest

from ibr_pipeline.scene import Camera
from ibr_pipeline.synthetic.materials import fresnel_dielectric, fresnel_pane
from ibr_pipeline.synthetic.paths import camera_from_angles
from ibr_pipeline.synthetic.raytree import BIT_T, composite_ray_tree, ray_tree_from_render, view_directions
from ibr_pipeline.synthetic.scenes import build_world
from ibr_pipeline.synthetic.tracer import Tracer


def _look(eye, target, w=96, h=72):
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    f = target - eye
    yaw, pitch = np.arctan2(f[1], f[0]), np.arcsin(f[2] / np.linalg.norm(f))
    return camera_from_angles(eye, yaw, pitch, 0.0, Camera.intrinsics_from_fov(w, h, 50), w, h)


@pytest.fixture(scope="module")
def curved():
    return Tracer(build_world("curved", 0))


def test_glass_pane_layers_follow_fresnel():
    tr = Tracer(build_world("glass_room", 0))
    cam = _look((2.2, 2.2, 1.3), (3.61, 2.3, 1.1))
    r = tr.trace(cam)
    glass = r["kind"] == 3
    assert glass.mean() > 0.3
    cos = np.abs(np.sum(view_directions(cam) * r["normal"], axis=2))[glass]
    assert np.allclose(r["beta"][glass], fresnel_pane(cos, 1.5), atol=1e-9)
    assert 0.07 < r["beta"][glass].min() and r["beta"][glass].max() < 0.3
    # surface layer = transmitted light weighted by (1 - F); the composite is Eq. 3
    T = r["T"][glass]
    assert np.allclose(r["I0"][glass], (1 - r["beta"][glass])[:, None] * T, atol=1e-12)
    assert np.allclose(r["image"], r["I0"] + r["beta"][..., None] * r["I1"], atol=1e-12)
    assert r["image"].max() <= 1.0


def test_chrome_and_crystal_spheres(curved):
    r = curved.trace(_look((2.2, 2.0, 1.4), (3.1, 3.1, 0.98)))
    crystal = r["kind"] == 4
    assert crystal.mean() > 0.1
    cam = _look((2.2, 2.0, 1.4), (3.1, 3.1, 0.98))
    cos = np.abs(np.sum(view_directions(cam) * r["normal"], axis=2))[crystal]
    assert np.allclose(r["beta"][crystal], fresnel_dielectric(cos, 1 / 1.5), atol=1e-9)
    # light went through the sphere: a non-zero refracted node with its path length inside
    assert (r["T"][crystal].max(axis=1) > 0.05).mean() > 0.9
    assert np.median(r["T_range"][crystal]) < 2 * 0.28 + 1e-3
    r2 = curved.trace(_look((2.0, 1.8, 1.4), (0.9, 1.2, 1.0)))
    chrome = r2["kind"] == 2
    assert chrome.mean() > 0.1 and np.allclose(r2["beta"][chrome], 0.85)
    assert np.all(r2["I0"][chrome] == 0)


def test_ray_tree_composite_with_refraction(curved):
    cam = _look((2.2, 2.0, 1.4), (3.1, 3.1, 0.98))
    r = curved.trace(cam)
    tree = ray_tree_from_render(r, cam)
    assert ((tree["valid"] & BIT_T) > 0).mean() > 0.1
    assert set(np.unique(tree["ior"])) <= {0.0, 1.5}
    err = np.abs(composite_ray_tree(tree) - r["image"]).max()
    assert err <= 1.0 / 255
    # Fresnel really is view-dependent here: dropping it breaks the composite
    wrong = tree["D"].astype(float) + tree["R"].astype(float) + tree["T"].astype(float)
    assert np.abs(wrong - r["image"]).max() > 5.0 / 255


def test_sensor_sees_mirror_reflection_depth():
    tr = Tracer(build_world("tiny", 0))
    cam = _look((1.6, 2.0, 1.35), (0.0, 2.0, 1.35), 64, 48)
    s = tr.sensor_range(cam)
    r = tr.trace(cam)
    mirror = r["kind"] == 2
    assert mirror.mean() > 0.3
    # the sensor reports the reflected (virtual) depth, beyond the mirror plane
    assert np.all(s["depth"][mirror][s["depth"][mirror] > 0] > r["depth"][mirror][s["depth"][mirror] > 0] + 0.3)
