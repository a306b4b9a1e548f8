"""Cotangent Laplacian of a triangle mesh and a regular control mesh over an image region
(Xu et al. §4.3.2, Eq. 9: "H indicates the Laplacian matrix computed using cotangent weights
[Desbrun et al. 1999]").

Why our own: of the locked dependencies only open3d and scipy touch meshes; open3d 0.20 has
Laplacian *smoothing filters* but does not expose the cotangent matrix, and trimesh / libigl
(which do) are not in requirements.lock. The matrix is a few lines of numpy + scipy.sparse.

Convention: L = the positive semi-definite "stiffness" matrix of linear finite elements,
    L_ij = -(cot a_ij + cot b_ij) / 2  (i != j, a, b the angles opposite edge ij),
    L_ii = -sum_j L_ij,
so that f^T L f = integral of |grad f|^2 over the mesh (the Dirichlet energy of the piecewise
linear function f) for any mesh, obtuse angles included; rows sum to zero, L f = 0 at interior
vertices when f is linear in the coordinates of a flat mesh. Desbrun's mean-curvature normal is
M^-1 L X / 2 with M the (lumped) vertex areas.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """(V, V) scipy.sparse CSR cotangent Laplacian of a mesh with (V, 2|3) vertices and (F, 3)
    int faces (see the module docstring for the sign convention). Degenerate triangles (zero
    area) contribute nothing."""
    import scipy.sparse as sp
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] not in (2, 3):
        raise ValueError(f"vertices must be (V, 2) or (V, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or (F.size and not np.issubdtype(F.dtype, np.integer)):
        raise ValueError(f"faces must be (F, 3) integers, got {F.shape} {F.dtype}")
    n = len(V)
    if F.size and (F.min() < 0 or F.max() >= n):
        raise ValueError("faces index outside the vertices")
    if V.shape[1] == 2:
        V = np.c_[V, np.zeros(n)]
    F = F.astype(np.int64)
    rows, cols, vals = [], [], []
    for k in range(3):  # the angle at corner k is opposite the edge (i, j)
        i, j, o = F[:, (k + 1) % 3], F[:, (k + 2) % 3], F[:, k]
        e1, e2 = V[i] - V[o], V[j] - V[o]
        sin = np.linalg.norm(np.cross(e1, e2), axis=1)
        cos = (e1 * e2).sum(1)
        ok = sin > 1e-12 * np.maximum((e1 ** 2).sum(1) + (e2 ** 2).sum(1), 1e-300)
        w = np.where(ok, 0.5 * cos / np.where(ok, sin, 1.0), 0.0)
        rows += [i, j]
        cols += [j, i]
        vals += [-w, -w]
    if not rows:
        return sp.csr_matrix((n, n))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    off = sp.csr_matrix((v, (r, c)), shape=(n, n))  # duplicates (two triangles per edge) summed
    return (off - sp.diags(np.asarray(off.sum(1)).ravel())).tocsr()


@dataclass
class ControlMesh:
    """A regular triangulated grid of control vertices over an image region: node (i, j) sits at
    pixel (i * cell, j * cell); each used cell is split into two triangles along its diagonal
    (0,1)-(1,0). `index` maps grid nodes to vertex ids (-1 = unused)."""

    cell: int
    index: np.ndarray  # (ny, nx) int64
    xy: np.ndarray     # (V, 2) node pixel positions
    faces: np.ndarray  # (F, 3) int64

    def weights(self, pos: np.ndarray):
        """Sparse (N, V) barycentric (piecewise-linear) interpolation weights at (N, 2) pixel
        positions; rows of positions outside the used cells are empty."""
        import scipy.sparse as sp
        p = np.asarray(pos, np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"positions must be (N, 2), got {p.shape}")
        ny, nx = self.index.shape
        g = np.nan_to_num(p, nan=-1e9) / self.cell
        ci = np.floor(g[:, 0]).astype(np.int64)
        cj = np.floor(g[:, 1]).astype(np.int64)
        fx, fy = g[:, 0] - ci, g[:, 1] - cj
        inside = (ci >= 0) & (cj >= 0) & (ci < nx - 1) & (cj < ny - 1)
        ci, cj = np.where(inside, ci, 0), np.where(inside, cj, 0)
        lower = fx + fy <= 1
        n00, n10 = self.index[cj, ci], self.index[cj, ci + 1]
        n01, n11 = self.index[cj + 1, ci], self.index[cj + 1, ci + 1]
        # lower triangle (00, 10, 01); upper triangle (10, 11, 01)
        ids = np.where(lower[:, None], np.stack([n00, n10, n01], 1), np.stack([n10, n11, n01], 1))
        w = np.where(lower[:, None], np.stack([1 - fx - fy, fx, fy], 1),
                     np.stack([1 - fy, fx + fy - 1, 1 - fx], 1))
        ok = inside[:, None] & np.all(ids >= 0, axis=1, keepdims=True) & np.ones((1, 3), bool)
        rows = np.repeat(np.arange(len(p)), 3).reshape(-1, 3)
        return sp.csr_matrix((w[ok], (rows[ok], ids[ok])), shape=(len(p), len(self.xy)))


def grid_control_mesh(region: np.ndarray, cell: int) -> ControlMesh:
    """Control mesh over the cells of an image grid (spacing `cell` pixels) that contain a pixel
    of the (H, W) bool `region`."""
    region = np.asarray(region, bool)
    if region.ndim != 2:
        raise ValueError(f"region must be (H, W), got {region.shape}")
    if cell < 1:
        raise ValueError(f"cell must be >= 1, got {cell}")
    H, W = region.shape
    nx, ny = (W - 1) // cell + 2, (H - 1) // cell + 2
    ys, xs = np.nonzero(region)
    used = np.zeros((ny - 1, nx - 1), bool)
    used[ys // cell, xs // cell] = True
    node = np.zeros((ny, nx), bool)
    for dj in (0, 1):
        for di in (0, 1):
            node[dj:dj + ny - 1, di:di + nx - 1] |= used
    index = -np.ones((ny, nx), np.int64)
    index[node] = np.arange(node.sum())
    jj, ii = np.nonzero(node)
    xy = np.c_[ii, jj].astype(np.float64) * cell
    cj, ci = np.nonzero(used)
    a, b = index[cj, ci], index[cj, ci + 1]
    c, d = index[cj + 1, ci], index[cj + 1, ci + 1]
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.int64)
    return ControlMesh(int(cell), index, xy, faces)
