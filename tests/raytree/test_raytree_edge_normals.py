"""Edge-aware normal reconstruction (our extension of §3.3, DecodeOptions.normal_edge_rel):
on a synthetic depth step between two planes both sides keep their plane's normal, where the
paper's plain 7x7 blur mixes them; numba and torch agree."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ibr_pipeline.raytree import ops
from ibr_pipeline.raytree.decode import reconstruct_normals

torch.set_num_threads(1)


def _step_scene(W=64, H=48, f=100.0):
    """Camera at the origin looking +z; left half the tilted plane z = 2 + 0.3 x, right half the
    plane z = 3 (a 40 % depth step at column 32). Returns positions (H, W, 3) and the exact
    camera-facing normals."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - W / 2) / f, (v - H / 2) / f, np.ones_like(u)], -1)
    t = np.where(u < W / 2, 2 / (1 - 0.3 * d[..., 0]), 3.0)
    n_left = np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0)
    n_true = np.where((u < W / 2)[..., None], n_left, np.array([0.0, 0.0, -1.0]))
    return (d * t[..., None]).astype(np.float32), n_true, u, v


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(-1) / np.linalg.norm(a, axis=-1), -1, 1)))


def test_edge_aware_normals_keep_both_sides_of_a_depth_step():
    P, n_true, u, v = _step_scene()
    valid = torch.ones(P.shape[:2], dtype=torch.bool)
    band = (np.abs(u - 32) <= 4) & (v > 4) & (v < P.shape[0] - 5)   # the blur's reach, no border
    plain = reconstruct_normals(torch.from_numpy(P), valid, torch.zeros(3), edge_rel=0.0).numpy()
    edge = reconstruct_normals(torch.from_numpy(P), valid, torch.zeros(3), edge_rel=0.02).numpy()
    assert _angle_deg(plain, n_true)[band].max() > 5.0     # the paper's blur mixes the planes
    assert _angle_deg(edge, n_true)[band].max() < 0.2      # both sides keep their own plane
    far = (np.abs(u - 32) > 6) & (u > 4) & (u < 59) & (v > 4) & (v < 43)
    assert np.abs(edge - plain)[far].max() < 1e-4          # away from edges: unchanged


def test_edge_aware_normals_numba_matches_torch():
    pytest.importorskip("numba")
    from ibr_pipeline.raytree import nbkernels as nk
    P, n_true, u, v = _step_scene()
    g = np.random.default_rng(0)
    valid = g.random(P.shape[:2]) > 0.05                    # a few holes as well
    kern = ops.gaussian_kernel(7, 0.0, "cpu").numpy().astype(np.float64)
    for rel in (0.0, 0.02):
        ref = reconstruct_normals(torch.from_numpy(P), torch.from_numpy(valid), torch.zeros(3),
                                  edge_rel=rel).numpy()
        out = np.zeros_like(P)
        nk.normals_box(P, valid, np.zeros(3), 0, P.shape[0], 0, P.shape[1], kern, out, rel)
        inner = valid & (u > 3) & (u < 60) & (v > 3) & (v < 44)   # border handling differs
        assert np.abs(out - ref)[inner].max() < 1e-4, rel
