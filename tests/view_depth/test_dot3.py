"""geometry.normals.dot3: the last-axis dot product written out is numpy's sum, bit for bit,
on strided views as the depth-edge tests use them; and normals_from_points keeps unit normals
that face the camera."""
import numpy as np

from ibr_pipeline.geometry.normals import dot3, normals_from_points


def test_same_bits_as_numpy_sum_on_strided_views():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(40, 50, 3)) * 10.0 ** rng.uniform(-4, 4, size=(40, 50, 1))
    N = rng.normal(size=(40, 50, 3))
    for a, b in ((P, N), (P[:, :-2], N[:, 2:]), (P[1:, ::2], N[:-1, ::2]), (P, P)):
        assert np.array_equal(dot3(a, b), np.sum(a * b, -1))
    assert np.array_equal(np.sqrt(dot3(P, P))[..., None], np.linalg.norm(P, axis=-1, keepdims=True))


def test_normals_are_unit_and_face_the_camera():
    y, x = np.mgrid[0:20, 0:30].astype(float)
    P = np.stack([x - 15, y - 10, 50 + 0.3 * x + 0.1 * y], -1)   # a tilted plane in front
    n = normals_from_points(P, np.ones((20, 30), bool))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-12)
    assert np.all(np.sum(n * P, -1) < 0)
    expect = np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, -1.0])
    np.testing.assert_allclose(n[5:15, 5:25], np.broadcast_to(expect, (10, 20, 3)), atol=1e-9)
