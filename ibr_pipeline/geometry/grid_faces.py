"""The triangles of a depth image's pixel grid, cut at depth edges (Xu et al. §4.2.3), and their
planar pre-merge (our addition): grid_mesh.py turns these faces into meshes.

`grid_faces`: two triangles per pixel square, none across an Eq. 1 depth edge or a missing depth,
the square's diagonal chosen so that it does not cross an edge where the other one would not.

`quadtree_faces`, the pre-merge:

Xu et al. simplify the full pixel-grid mesh (two triangles per pixel square) with quadrics. On a
640x480 view that is ~600 k faces, and fast-simplification's first pass over them was the largest
cost of the stage. Most of a view is flat (walls, floor, table tops), where the grid's many small
triangles all lie on one plane and quadric simplification can only merge them again. So before the
simplification, square blocks of 2^k x 2^k pixel squares whose vertices lie on one plane are
replaced by a few triangles over the same plane (a quadtree):

* a block qualifies when all its pixel squares are full (both triangles of the grid mesh exist: no
  Eq. 1 cut, no missing depth; so the occlusion edges are untouched), all its four children
  qualify, and its vertices' inverse depth is an affine function of the pixel coordinates within
  `tol_rel` relative depth. For a plane, 1/z is exactly affine in (u, v) (perspective), and a
  triangle's rendered 1/z is the affine interpolation of its corners' 1/z, so every pixel of a
  merged block renders within ~2 tol_rel of its own depth.
* the largest qualifying blocks are kept (quadtree leaves); squares in no leaf keep the grid's own
  two triangles.
* crack-free (no T-junctions): a leaf is triangulated as a fan from its centre vertex through every
  vertex on its boundary that a neighbouring face uses (a corner of a smaller neighbouring leaf, a
  vertex of a neighbouring pixel square); a leaf with only its four corners in use gets two
  triangles. The mesh stays manifold with the same borders (cuts, image frame) as the grid mesh,
  so `preserve_border` simplification behaves as before.

Why hand-written: open3d's `simplify_vertex_clustering` / `merge_close_vertices` and
fast-simplification do not exploit the image grid (the point is to never build the 600 k faces);
this is ~150 lines of numpy plus a small numba kernel for the per-block plane fits.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .depth_edges import PairEdges

def grid_faces(valid: np.ndarray, edges: PairEdges, cells: np.ndarray | None = None) -> np.ndarray:
    """(F, 3) int64 faces over the pixel grid (vertex index = y * W + x), two per pixel square,
    none with a side across a depth edge or a corner without depth. Counter-clockwise as seen by
    the camera (OpenCV: image y down). `cells`: optional (H-1, W-1) bool, only those squares."""
    return CellTriangles(valid, edges).faces(cells)


class CellTriangles:
    """The pixel squares' corner indices (a, b, c, d) and the masks of their four possible
    triangles (a, c, b), (b, c, d) [split along b-c] and (a, c, d), (a, d, b) [split along a-d];
    computed once for grid_faces, full_cells and the quadtree pre-merge."""

    def __init__(self, valid: np.ndarray, edges: PairEdges):
        self.corners, self.masks = _cell_triangles(valid, edges)

    def faces(self, cells: np.ndarray | None = None) -> np.ndarray:
        a, b, c, d = self.corners
        masks = self.masks if cells is None else [m & cells for m in self.masks]
        tris = ((a, c, b), (b, c, d), (a, c, d), (a, d, b))
        faces = [np.stack([t[m] for t in tri], 1) for m, tri in zip(masks, tris)]
        return np.concatenate(faces, 0).astype(np.int64)

    def full(self) -> np.ndarray:
        """(H-1, W-1) bool: pixel squares that get both of their triangles (no cut, all depths)."""
        t1, t2, t3, t4 = self.masks
        return (t1 & t2) | (t3 & t4)


def _cell_triangles(valid: np.ndarray, edges: PairEdges):
    """Corner indices (a, b, c, d) of every pixel square and the masks of its four possible
    triangles (a, c, b), (b, c, d) [split along b-c] and (a, c, d), (a, d, b) [split along a-d]."""
    valid = np.asarray(valid, bool)
    h, w = valid.shape
    if edges.right.shape != (h, w - 1) or edges.down.shape != (h - 1, w):
        raise ValueError(f"edges do not match a {h}x{w} grid")
    y, x = np.mgrid[0:h - 1, 0:w - 1]
    a = y * w + x        # (y, x)
    b = a + 1            # (y, x+1)
    c = a + w            # (y+1, x)
    d = c + 1            # (y+1, x+1)
    va, vb, vc, vd = valid[:-1, :-1], valid[:-1, 1:], valid[1:, :-1], valid[1:, 1:]
    top, bottom = edges.right[:-1, :], edges.right[1:, :]      # a-b, c-d
    left, right = edges.down[:, :-1], edges.down[:, 1:]        # a-c, b-d
    # diagonal b-c (anti) unless it is an edge and a-d (diag) is not
    use_ad = edges.anti & ~edges.diag
    t1 = ~use_ad & va & vb & vc & ~top & ~left & ~edges.anti
    t2 = ~use_ad & vb & vc & vd & ~bottom & ~right & ~edges.anti
    t3 = use_ad & va & vc & vd & ~left & ~bottom & ~edges.diag
    t4 = use_ad & va & vd & vb & ~right & ~top & ~edges.diag
    return (a, b, c, d), (t1, t2, t3, t4)


TOL_REL = 1e-4      # max relative depth deviation of a merged block from its plane (0.2 mm at 2 m)
MAX_BLOCK = 64      # largest block side in pixel squares


def _affine_pinv(s: int) -> np.ndarray:
    """(3, n) pseudo-inverse of X = [1, u, v] over the (s+1)^2 vertices of a block (row-major):
    the least-squares affine fit of values w is c = pinv @ w."""
    v, u = np.mgrid[0:s + 1, 0:s + 1]
    return np.linalg.pinv(np.stack([np.ones(u.size), u.ravel(), v.ravel()], 1).astype(np.float64))


@njit(cache=True)
def _block_fit_max(inv, depth, y0, x0, s, Xp):  # pragma: no cover - compiled
    """Per block (origin y0[i], x0[i], side s): the least-squares affine fit of 1/z over its
    (s+1)^2 vertices (coefficients = Xp @ values, Xp = pinv of [1, u, v]) and the maximum of
    |1/z - fit| * z over them. One pass to fit, one to measure; no window copies."""
    out = np.empty(len(y0))
    for b in range(len(y0)):
        c0 = c1 = c2 = 0.0
        k = 0
        for v in range(s + 1):
            for u in range(s + 1):
                val = inv[y0[b] + v, x0[b] + u]
                c0 += Xp[0, k] * val
                c1 += Xp[1, k] * val
                c2 += Xp[2, k] * val
                k += 1
        m = 0.0
        for v in range(s + 1):
            for u in range(s + 1):
                r = abs(inv[y0[b] + v, x0[b] + u] - (c0 + c1 * u + c2 * v)) * depth[y0[b] + v, x0[b] + u]
                if r > m:
                    m = r
        out[b] = m
    return out


def planar_leaves(depth: np.ndarray, full: np.ndarray, tol_rel: float = TOL_REL,
                  max_block: int = MAX_BLOCK) -> dict[int, np.ndarray]:
    """Quadtree leaves: {side s: (n, 2) int array of block origins (y0, x0) in vertex coordinates}
    for s = 2, 4, ..., max_block; each leaf is an s x s block of full pixel squares whose vertices
    are planar within tol_rel (see module doc), not inside a larger such block."""
    depth = np.asarray(depth, np.float64)
    h, w = depth.shape
    if full.shape != (h - 1, w - 1):
        raise ValueError(f"full cells {full.shape} do not match depth {depth.shape}")
    if not (tol_rel >= 0 and max_block >= 2 and max_block & (max_block - 1) == 0):
        raise ValueError(f"need tol_rel >= 0 and a power-of-two max_block >= 2, got {tol_rel}, {max_block}")
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-12), 0.0)
    ok = {1: np.asarray(full, bool)}
    s = 2
    while s <= max_block:
        nby, nbx = (h - 1) // s, (w - 1) // s
        if nby == 0 or nbx == 0:
            break
        prev = ok[s // 2][:2 * nby, :2 * nbx]
        cand = prev.reshape(nby, 2, nbx, 2).all(axis=(1, 3))
        if cand.any():
            iy, ix = np.nonzero(cand)
            Xp = _affine_pinv(s)
            # max over the block's vertices of |1/z - affine fit| * z = |dz| / z
            rel = _block_fit_max(inv, depth, iy * s, ix * s, s, Xp)
            cand[iy, ix] = rel <= tol_rel
        ok[s] = cand
        s *= 2
    leaves, covered = {}, None
    for s in sorted((k for k in ok if k > 1), reverse=True):
        nby, nbx = ok[s].shape
        cov = np.zeros((nby, nbx), bool)
        if covered is not None:
            up = np.repeat(np.repeat(covered, 2, 0), 2, 1)
            cov[:up.shape[0], :up.shape[1]] = up
        leaf = ok[s] & ~cov
        leaves[s] = np.argwhere(leaf) * s
        covered = cov | leaf
    return dict(sorted(leaves.items()))


def _boundary(s: int) -> np.ndarray:
    """(4s, 2) (dy, dx) of a block's boundary vertices, in the grid mesh's face orientation:
    down the left side, along the bottom, up the right side, back along the top."""
    k = np.arange(s)
    return np.concatenate([np.stack([k, 0 * k], 1), np.stack([0 * k + s, k], 1),
                           np.stack([s - k, 0 * k + s], 1), np.stack([0 * k, s - k], 1)])


def quadtree_faces(depth: np.ndarray, edges: PairEdges, tol_rel: float = TOL_REL,
                   max_block: int = MAX_BLOCK) -> tuple[np.ndarray, np.ndarray, dict]:
    """(F, 3) int64 faces over the pixel grid (vertex index = y * W + x, like grid_faces): planar
    blocks merged (see module doc), every other pixel square as in grid_faces. Also the (H * W,)
    bool mask of the vertices the unmerged grid mesh uses (for grid_mesh_depth) and a small report
    {"leaves": {s: count}, "merged_fraction": share of the full squares inside a leaf}."""
    depth = np.asarray(depth, np.float64)
    h, w = depth.shape
    valid = depth > 0
    cells = CellTriangles(valid, edges)
    full = cells.full()
    leaves = planar_leaves(depth, full, tol_rel, max_block)
    in_leaf = np.zeros((h - 1, w - 1), bool)
    for s, org in leaves.items():
        m = np.zeros(((h - 1) // s, (w - 1) // s), bool)
        m[org[:, 0] // s, org[:, 1] // s] = True
        up = np.repeat(np.repeat(m, s, 0), s, 1)
        in_leaf[:up.shape[0], :up.shape[1]] |= up
    base = cells.faces(~in_leaf)
    active = np.zeros(h * w, bool)
    active[base.reshape(-1)] = True
    grid_used = active.copy()            # + every vertex of a leaf (all full squares)
    corners = np.zeros((h, w), bool)
    corners[:-1, :-1] |= in_leaf
    corners[1:, :-1] |= in_leaf
    corners[:-1, 1:] |= in_leaf
    corners[1:, 1:] |= in_leaf
    grid_used |= corners.reshape(-1)
    for s, org in leaves.items():        # every leaf corner is in use
        for dy, dx in ((0, 0), (0, s), (s, 0), (s, s)):
            active[(org[:, 0] + dy) * w + org[:, 1] + dx] = True
    faces = [base]
    for s, org in leaves.items():
        if len(org) == 0:
            continue
        bnd = _boundary(s)
        idx = (org[:, None, 0] + bnd[None, :, 0]) * w + org[:, None, 1] + bnd[None, :, 1]  # (n, 4s)
        act = active[idx]
        four = act.sum(1) == 4
        a, b = org[four, 0] * w + org[four, 1], org[four, 0] * w + org[four, 1] + s
        c, d = a + s * w, b + s * w
        faces += [np.stack([a, c, b], 1), np.stack([b, c, d], 1)]   # same orientation as the grid
        fan = ~four
        if fan.any():
            rows, cols = np.nonzero(act[fan])             # row-major: boundary order within a leaf
            vid = idx[fan][rows, cols]
            nxt = np.roll(vid, -1)
            last = np.r_[rows[1:] != rows[:-1], True]    # last active vertex of each leaf ...
            first = np.r_[True, rows[1:] != rows[:-1]]
            nxt[last] = vid[first]                       # ... closes the fan with the first
            o = org[fan][rows]
            centre = (o[:, 0] + s // 2) * w + o[:, 1] + s // 2
            faces.append(np.stack([centre, vid, nxt], 1))
    n_full = int(full.sum())
    return np.concatenate(faces, 0).astype(np.int64), grid_used, {
        "grid_faces": int(len(base) + 2 * in_leaf.sum()),
        "leaves": {int(s): int(len(o)) for s, o in leaves.items()},
        "merged_fraction": float(in_leaf.sum() / n_full) if n_full else 0.0}
