"""Pure functions: optics, textures, quantisation, sensor model, deterministic writers."""
from __future__ import annotations

import numpy as np
import pytest

from ibr_pipeline.synthetic.materials import (FRESNEL_DIELECTRIC, FRESNEL_NONE, FRESNEL_PANE,
                                              fresnel_dielectric, fresnel_pane, fresnel_weight,
                                              reflect, refract)
from ibr_pipeline.synthetic.sensor import noise_sigma, simulate_depth
from ibr_pipeline.synthetic.textures import Texture
from ibr_pipeline.synthetic.writers import compose_8bit, save_npz


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_fresnel_known_values():
    # normal incidence on glass: ((n-1)/(n+1))^2 = 0.04; grazing -> 1
    assert fresnel_dielectric(np.array([1.0]), np.array([1 / 1.5]))[0] == pytest.approx(0.04, abs=1e-9)
    assert fresnel_dielectric(np.array([1e-6]), np.array([1 / 1.5]))[0] > 0.99
    # Brewster angle: p-polarised reflectance vanishes, unpolarised = Rs / 2
    th = np.arctan(1.5)
    F = fresnel_dielectric(np.array([np.cos(th)]), np.array([1 / 1.5]))[0]
    ct = np.cos(np.arcsin(np.sin(th) / 1.5))
    rs = ((np.cos(th) - 1.5 * ct) / (np.cos(th) + 1.5 * ct)) ** 2
    assert F == pytest.approx(rs / 2, rel=1e-9)
    # total internal reflection from inside beyond the critical angle
    crit = np.arcsin(1 / 1.5)
    assert fresnel_dielectric(np.array([np.cos(crit + 0.05)]), np.array([1.5]))[0] == 1.0
    # thin pane: two interfaces, 2R / (1 + R) at normal incidence
    assert fresnel_pane(np.array([1.0]), np.array([1.5]))[0] == pytest.approx(0.08 / 1.04, abs=1e-9)
    w = fresnel_weight(np.array([FRESNEL_NONE, FRESNEL_DIELECTRIC, FRESNEL_PANE]),
                       np.array([1.0, 1.0, 1.0]), np.array([0.0, 1.5, 1.5]))
    assert w == pytest.approx([1.0, 0.04, 0.08 / 1.04])


def test_reflect_and_snell():
    rng = np.random.default_rng(0)
    n = _unit(rng.normal(size=(100, 3)))
    d = _unit(rng.normal(size=(100, 3)))
    d = np.where(np.sum(d * n, axis=1, keepdims=True) > 0, -d, d)  # incoming against n
    r = reflect(d, n)
    assert np.allclose(np.linalg.norm(r, axis=1), 1)
    assert np.allclose(np.sum(r * n, axis=1), -np.sum(d * n, axis=1))
    t, tir = refract(d, n, np.full(100, 1 / 1.5))
    assert not tir.any()
    sin_i = np.linalg.norm(np.cross(d, n), axis=1)
    sin_t = np.linalg.norm(np.cross(t, n), axis=1)
    assert np.allclose(sin_i, 1.5 * sin_t, atol=1e-9)  # Snell: n1 sin_i = n2 sin_t
    assert np.all(np.sum(t * n, axis=1) < 0)  # goes through the surface
    with pytest.raises(ValueError):
        reflect(d[:, :2], n[:, :2])


def test_textures_deterministic_and_rich():
    uv = np.random.default_rng(1).uniform(0, 3, size=(20000, 2))
    rich = Texture("noise", (0.2, 0.3, 0.5), (0.8, 0.7, 0.4), 6.0, seed=5)
    assert np.array_equal(rich.albedo(uv), rich.albedo(uv))
    other = Texture("noise", (0.2, 0.3, 0.5), (0.8, 0.7, 0.4), 6.0, seed=6)
    assert not np.allclose(rich.albedo(uv), other.albedo(uv))
    for kind in ("noise", "planks", "tiles", "plaster", "flat"):
        a = Texture(kind, (0.3, 0.3, 0.3), (0.8, 0.7, 0.6), 5.0, seed=2).albedo(uv)
        assert a.shape == (len(uv), 3) and a.min() >= 0 and a.max() <= 1
    # textured materials vary a lot; plaster ("low-texture wall") only a little
    assert Texture("noise", (0.2, 0.3, 0.5), (0.8, 0.7, 0.4), 6.0, 1).albedo(uv).std() > 0.08
    assert Texture("plaster", (0.7, 0.7, 0.7), (0.7, 0.7, 0.7), 1.5, 1).albedo(uv).std() < 0.03
    with pytest.raises(ValueError):
        rich.albedo(uv[:, :1])


def test_compose_8bit_eq3():
    rng = np.random.default_rng(2)
    I1 = rng.uniform(0, 1, (50, 60, 3))
    beta = rng.uniform(0, 1, (50, 60))
    I0 = (1 - beta)[..., None] * rng.uniform(0, 1, (50, 60, 3))
    q0, q1, qb, img = compose_8bit(I0, I1, beta)
    lhs = img / 255.0
    rhs = q0 / 255.0 + (qb / 255.0)[..., None] * q1 / 255.0
    assert np.abs(lhs - rhs).max() <= 0.5 / 255 + 1e-12
    # and the stored image is close to the exact float composite
    assert np.abs(lhs - (I0 + beta[..., None] * I1)).max() <= 2.0 / 255


def test_sensor_noise_grows_with_distance_and_holes():
    rng = np.random.default_rng(3)
    assert noise_sigma(4.0) > 3 * noise_sigma(1.0)
    H, W = 200, 200
    near = simulate_depth(np.full((H, W), 1.0), np.ones((H, W)), rng)
    far = simulate_depth(np.full((H, W), 4.0), np.ones((H, W)), rng)
    assert np.std(far[far > 0] - 4.0) > 3 * np.std(near[near > 0] - 1.0)
    graze = simulate_depth(np.full((H, W), 2.0), np.full((H, W), 0.05), rng)
    assert (graze == 0).all()
    step = np.full((H, W), 2.0)
    step[:, W // 2:] = 3.0
    out = simulate_depth(step, np.ones((H, W)), rng)
    assert (out[:, W // 2 - 1:W // 2 + 1] == 0).all()  # edge holes
    assert np.allclose(out * 1000, np.round(out * 1000))  # whole millimetres


def test_save_npz_is_deterministic(tmp_path):
    a = np.arange(1000, dtype=np.float32).reshape(10, 100)
    for method in ("deflate", "lzma"):
        save_npz(tmp_path / f"a_{method}.npz", method, x=a, y=a[:3])
        save_npz(tmp_path / f"b_{method}.npz", method, x=a, y=a[:3])
        assert (tmp_path / f"a_{method}.npz").read_bytes() == (tmp_path / f"b_{method}.npz").read_bytes()
        with np.load(tmp_path / f"a_{method}.npz") as z:
            assert np.array_equal(z["x"], a) and np.array_equal(z["y"], a[:3])
