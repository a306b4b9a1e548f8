"""The view geometry and sampling of the two-layer decomposition (Xu et al. §4.3, Eq. 8): what the
image step (decompose.py), the geometry step (geometry_step.py), reflector detection and the
reflected-scene prior share. numpy / scipy only.

`ViewGeom` holds, per view, the surface points X0 (from the refined depth: M0) and the mirror-world
points X1 (the planar-reflection geometry: M1); `DataTerm` is Eq. 8 at one neighbour.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..scene import Camera


@dataclass
class ViewGeom:
    """One view seen at working resolution, for one reflector."""

    name: str
    camera: Camera
    image: np.ndarray  # (H, W, 3) linear [0, 1]
    depth: np.ndarray  # (H, W) z-depth of the surface (M0), 0 = none
    mask: np.ndarray  # (H, W) bool, beta support of the reflector
    X0: np.ndarray  # (H, W, 3) surface points (NaN where none)
    X1: np.ndarray  # (H, W, 3) mirror-world points inside mask (NaN elsewhere)
    D1: np.ndarray  # (H, W) z-depth of X1 in this camera (0 = none)

    def __post_init__(self) -> None:
        H, W = self.camera.height, self.camera.width
        for name, shape in (("image", (H, W, 3)), ("depth", (H, W)), ("mask", (H, W)),
                            ("X0", (H, W, 3)), ("X1", (H, W, 3)), ("D1", (H, W))):
            a = getattr(self, name)
            if np.shape(a) != shape:
                raise ValueError(f"ViewGeom {self.name}: {name} must be {shape}, got {np.shape(a)}")
            if name == "image" and not np.all(np.isfinite(a)):
                raise ValueError(f"ViewGeom {self.name}: image has non-finite values")


def project(camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) world points -> (..., 2) pixel positions and (...) z-depth (NaN propagates)."""
    X = np.asarray(X, np.float64)
    if X.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got {X.shape}")
    shp = X.shape[:-1]
    flat = X.reshape(-1, 3)
    cam = flat @ camera.R.T + camera.t
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam @ camera.K.T)[:, :2] / z[:, None]
    return uv.reshape(shp + (2,)), z.reshape(shp)


def _nearest(img: np.ndarray, pos: np.ndarray, fill=0):
    H, W = img.shape[:2]
    x = np.rint(np.nan_to_num(pos[..., 0], nan=-1)).astype(np.int64)
    y = np.rint(np.nan_to_num(pos[..., 1], nan=-1)).astype(np.int64)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    out = np.full(pos.shape[:-1] + img.shape[2:], fill, dtype=img.dtype)
    out[inside] = img[y[inside], x[inside]]
    return out, inside


def depth_consistent(depth_map: np.ndarray, pos: np.ndarray, z: np.ndarray, tol: float) -> np.ndarray:
    """Occlusion test: the map's depth at `pos` (nearest pixel) equals z within tol * min."""
    d, inside = _nearest(depth_map, pos, 0.0)
    ok = inside & (d > 0) & np.isfinite(z) & (z > 0)
    return ok & (np.abs(d - z) < tol * np.minimum(d, np.where(ok, z, 1.0)))


def pose_distance(a: Camera, b: Camera) -> float:
    """Camera-pose distance used to sort neighbours: centre distance (m) + rotation angle (rad)."""
    cosang = (np.trace(a.R @ b.R.T) - 1) / 2
    return float(np.linalg.norm(a.center - b.center) + math.acos(np.clip(cosang, -1, 1)))


def nearest_by_pose(cameras: list, neighbours: int) -> list[list[int]]:
    """For each of the cameras, the indices of the `neighbours` others with the smallest
    pose_distance, nearest first (ties in list order, as a stable sort). One distance matrix:
    the detection stage asks this of every view of every candidate plane."""
    n = len(cameras)
    if n == 0:
        return []
    C = np.array([c.center for c in cameras], np.float64)
    R = np.array([c.R for c in cameras], np.float64)
    R9 = R.reshape(n, 9)
    cosang = (R9 @ R9.T - 1) / 2  # trace(R_a R_b^T)
    D = np.linalg.norm(C[:, None] - C[None], axis=-1) + np.arccos(np.clip(cosang, -1, 1))
    out = []
    for a in range(n):
        order = np.argsort(D[a], kind="stable")
        out.append([int(b) for b in order if b != a][:neighbours])
    return out


def _sample_np(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    import cv2

    p = np.nan_to_num(pos, nan=-10).astype(np.float32)
    return cv2.remap(img.astype(np.float32), p[..., 0], p[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def remap_points(img: np.ndarray, pos: np.ndarray, width: int = 1024) -> np.ndarray:
    """_sample_np at (N, 2) positions: (N, C) samples, the same values as sampling the positions
    laid out as an image (cv2.remap's maps are 2D and limited to 32767 rows or columns, so the
    points are laid out in rows of `width`)."""
    pos = np.asarray(pos)
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise ValueError(f"pos must be (N, 2), got {pos.shape}")
    n = len(pos)
    rows = max(1, -(-n // width))
    grid = np.full((rows * width, 2), np.nan)
    grid[:n] = pos
    out = _sample_np(img, grid.reshape(rows, width, 2))
    return out.reshape((rows * width,) + out.shape[2:])[:n]


@dataclass
class DataTerm:
    """Eq. 8 at one neighbour: its pixels q (in its beta), target colours I_k'(q), positions a_q
    (surface layer) and b_q (reflection layer) in the reference view, all valid."""

    name: str
    target: np.ndarray  # (N, 3)
    a: np.ndarray  # (N, 2)
    b: np.ndarray  # (N, 2)
    X1: np.ndarray  # (N, 3) mirror-world points of q (for the (R, T) step)
    X0: np.ndarray | None = None  # (N, 3) surface points of q (M0's vertex offsets)


def bilinear_matrix(pos: np.ndarray, W: int, H: int):
    """Sparse (N, H*W) matrix of bilinear interpolation weights at (N, 2) pixel positions,
    positions clamped to the image (= torch grid_sample, align_corners=True, border padding)."""
    import scipy.sparse as sp
    p = np.asarray(pos, np.float64)
    x = np.clip(np.nan_to_num(p[:, 0], nan=0.0), 0, W - 1)
    y = np.clip(np.nan_to_num(p[:, 1], nan=0.0), 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(H - 2, 0))
    ax, ay = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    N = len(p)
    rows = np.repeat(np.arange(N), 4)
    cols = np.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], 1).reshape(-1)
    vals = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], 1).reshape(-1)
    return sp.csr_matrix((vals, (rows, cols)), shape=(N, H * W))


def bilinear_cells(pos: np.ndarray, H: int, W: int):
    """The cell of each (N, 2) position (clamped to the image): x0, y0, x1, y1 and the (N, 1)
    fractions ax, ay — shared by the sampler and its exact gradient (geometry_step.py)."""
    x = np.clip(pos[:, 0], 0, W - 1)
    y = np.clip(pos[:, 1], 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(H - 2, 0))
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    return x0, y0, np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1), ax, ay


def sample_bilinear(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(N, C) bilinear samples of an (H, W, C) image at (N, 2) positions (clamped). Float64
    positions into a float32/float64 colour image go through the numba kernel (the same bits);
    other inputs through `sample_bilinear_np`."""
    img, pos = np.asarray(img), np.asarray(pos)
    if (img.ndim == 3 and img.shape[0] > 0 and img.shape[1] > 0
            and img.dtype in (np.float32, np.float64) and pos.dtype == np.float64
            and pos.ndim == 2 and pos.shape[1] == 2 and np.isfinite(pos).all()):
        from .bilinear_nb import sample_bilinear_nb
        return sample_bilinear_nb(np.ascontiguousarray(img), np.ascontiguousarray(pos))
    return sample_bilinear_np(img, pos)


def sample_bilinear_np(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """`sample_bilinear` in numpy: the reference, and the path for any other input."""
    x0, y0, x1, y1, ax, ay = bilinear_cells(pos, *img.shape[:2])
    return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x1])
            + ay * ((1 - ax) * img[y1, x0] + ax * img[y1, x1]))


def all_last(b: np.ndarray) -> np.ndarray:
    """np.all(b, axis=-1) for a short last axis (x, y, z or RGB): numpy reduces along a short
    trailing axis several times slower than it ANDs the columns, and the detection stage does it
    on every view's full image per candidate plane."""
    b = np.asarray(b, bool)
    if b.ndim < 1 or b.shape[-1] == 0:
        raise ValueError(f"all_last: need a non-empty last axis, got shape {b.shape}")
    out = b[..., 0].copy()
    for k in range(1, b.shape[-1]):
        out &= b[..., k]
    return out


def any_last(b: np.ndarray) -> np.ndarray:
    """np.any(b, axis=-1), the same way as all_last."""
    return ~all_last(~np.asarray(b, bool))


def nanmedian0(a: np.ndarray) -> np.ndarray:
    """np.nanmedian(a, axis=0), bit for bit, for a small first axis (views): numpy takes a
    masked-array path there that was the largest single cost of reflector detection. NaNs sort
    last, so the median of the n valid values sits at (n - 1) // 2 and n // 2; NaN where n = 0."""
    a = np.asarray(a)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    if a.ndim < 1 or a.shape[0] == 0:
        raise ValueError(f"nanmedian0: need a non-empty first axis, got shape {a.shape}")
    s = np.sort(a, axis=0)
    n = (~np.isnan(a)).sum(0)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(s, (n // 2)[None], 0)[0]
    with np.errstate(invalid="ignore"):
        med = (lo + np.where(n % 2 == 1, lo, hi)) / 2
    return np.where(n > 0, med, np.nan).astype(a.dtype, copy=False)


def rodrigues(w: np.ndarray) -> np.ndarray:
    """3x3 rotation of the axis-angle vector `w` (Rodrigues' formula)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = np.asarray(w, np.float64) / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx
