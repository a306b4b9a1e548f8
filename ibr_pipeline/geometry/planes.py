"""Planes for reflection decomposition (Xu et al. §4.3.1): RANSAC planes on the global mesh G,
mirroring through a plane, the per-view reflector mask beta (the plane's extent projected into a
view, with occlusion), the mirror-world ("planar reflection") points of a view and grid meshes.

Planes are `n . x + d = 0` in world coordinates with unit `n` (scene.py). All functions are pure
and shape-checked; they raise ValueError naming the offending shape.
"""
from __future__ import annotations

import numpy as np

from ..scene import Camera


def _plane(plane) -> np.ndarray:
    p = np.asarray(plane, dtype=np.float64).reshape(-1)
    if p.shape != (4,) or not np.all(np.isfinite(p)):
        raise ValueError(f"plane must be 4 finite numbers (n, d), got shape {p.shape}")
    n = np.linalg.norm(p[:3])
    if n < 1e-12:
        raise ValueError("plane normal is zero")
    return p / n


def mirror_matrix(plane) -> np.ndarray:
    """4x4 Householder reflection through the plane n.x + d = 0: x' = x - 2 (n.x + d) n."""
    p = _plane(plane)
    n, d = p[:3], p[3]
    M = np.eye(4)
    M[:3, :3] -= 2.0 * np.outer(n, n)
    M[:3, 3] = -2.0 * d * n
    return M


def fit_plane(points: np.ndarray) -> np.ndarray:
    """Least-squares plane (total least squares, SVD) through (N, 3) points -> (a, b, c, d)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"points must be (N>=3, 3), got {pts.shape}")
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[2]
    return np.r_[n, -n @ c]


def same_plane(a, b, angle_deg: float = 5.0, offset: float = 0.05) -> bool:
    """Planes (4,) with normals within `angle_deg` (either orientation) and offsets closer than
    `offset` (scene units)."""
    na, nb = np.asarray(a[:3], np.float64), np.asarray(b[:3], np.float64)
    cos, db = float(na @ nb), float(b[3])
    if cos < 0:
        cos, db = -cos, -db
    return cos > np.cos(np.radians(angle_deg)) and abs(float(a[3]) - db) < offset


def plane_basis(plane) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin on the plane, u axis, v axis): an orthonormal frame of the plane."""
    p = _plane(plane)
    n = p[:3]
    origin = -p[3] * n
    a = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return origin, u, np.cross(n, u)


def ransac_planes(points: np.ndarray, *, distance: float = 0.008, min_points: int = 200,
                  max_planes: int = 12, iterations: int = 1000, cluster_eps: float = 0.06,
                  min_cluster_area: float = 0.05, seed: int = 0) -> list[dict]:
    """Planar segments of a point set (samples of G): repeated RANSAC (`ransac_nb.best_plane`,
    `iterations` 3-point hypotheses per plane, drawn from `seed`), each plane refined by least
    squares on its inliers and split into connected pieces (open3d DBSCAN), each piece's plane
    found again in a band a quarter as thick. Returns [{plane (4,), polygon (K, 3) convex hull
    of the piece, area, count}].
    """
    import open3d as o3d
    from scipy.spatial import ConvexHull, QhullError

    from .ransac_nb import best_plane
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    rng = np.random.default_rng(int(seed))
    refit_rng = np.random.default_rng([int(seed), 1])  # its own stream: the planes' draws stay put
    refit_iterations = max(1, iterations // 4)
    rest = pts
    out = []
    for _ in range(max_planes):
        if len(rest) < min_points:
            break
        _, idx = best_plane(rest, distance, iterations, rng)
        if len(idx) < min_points:
            break
        inl = rest[idx]
        plane = fit_plane(inl)
        keep = np.abs(inl @ plane[:3] + plane[3]) < distance
        inl = inl[keep]
        plane = fit_plane(inl)
        slab = rest[np.abs(rest @ plane[:3] + plane[3]) < 2 * distance]
        rest = np.delete(rest, idx, axis=0)
        labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inl))
                            .cluster_dbscan(cluster_eps, 8))
        origin, u, v = plane_basis(plane)
        slab_uv = np.c_[(slab - origin) @ u, (slab - origin) @ v]
        for lab in range(labels.max() + 1 if len(labels) else 0):
            piece = inl[labels == lab]
            if len(piece) < min_points // 4:
                continue
            uv = np.c_[(piece - origin) @ u, (piece - origin) @ v]
            try:
                hull = ConvexHull(uv)
            except QhullError:
                continue
            if hull.volume < min_cluster_area:  # 2D hull "volume" is its area
                continue
            poly = origin + np.outer(uv[hull.vertices, 0], u) + np.outer(uv[hull.vertices, 1], v)
            # the piece's own plane: RANSAC at a quarter of the inlier distance over the points
            # within 2 x distance of the plane above the piece's hull, then least squares on that
            # band. Two surfaces closer than `distance` (a TV screen 5 mm in front of its body)
            # share one band, and a plane fitted to the band tilts between them. The hull's own
            # half-planes keep its boundary points (polygon_contains' path test may not).
            near = slab[(hull.equations[:, :2] @ slab_uv.T + hull.equations[:, 2:] <= 1e-9).all(0)]
            pl, ii = best_plane(near, 0.25 * distance, refit_iterations, refit_rng)
            if len(ii) < 3:
                near, pl = piece, fit_plane(piece)
            for _ in range(2):
                band = near[np.abs(near @ pl[:3] + pl[3]) < 0.25 * distance]
                if len(band) < 3:
                    break
                pl = fit_plane(band)
            out.append({"plane": pl, "polygon": poly, "area": float(hull.volume),
                        "count": int(len(piece))})
    return out


def ray_plane_hits(camera: Camera, plane, uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel: world point where its ray meets the plane (H, W, 3) and that point's
    z-depth (H, W) in the camera (<= 0 or inf where the plane is behind / parallel). With `uv`
    (N, 2) pixel positions: the same for those pixels only, (N, 3) and (N,)."""
    from .raycast import pixel_directions
    p = _plane(plane)
    d_world = pixel_directions(camera, uv)  # z = 1 rays
    c = camera.center
    denom = d_world[:, 0] * p[0] + d_world[:, 1] * p[1] + d_world[:, 2] * p[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -(p[:3] @ c + p[3]) / denom  # ray parameter = z-depth since d_cam has z = 1
    z = np.where(np.isfinite(z), z, np.inf)
    X = c + d_world * z[:, None]
    if uv is not None:
        return X, z
    H, W = camera.height, camera.width
    return X.reshape(H, W, 3), z.reshape(H, W)


def polygon_window(camera: Camera, polygon: np.ndarray, near: float = 1e-3) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the pixels whose rays can meet a convex planar polygon at a z-depth
    above `near`: the bounding box of its projection after clipping it to z >= near, widened by
    a pixel and clipped to the image; (0, 0, 0, 0) when there are none. A point of the polygon
    is a convex combination of its vertices, so the clipped polygon holds every such hit."""
    poly = np.asarray(polygon, np.float64)
    if poly.ndim != 2 or poly.shape[1] != 3 or len(poly) < 3:
        raise ValueError(f"polygon must be (K>=3, 3), got {poly.shape}")
    c = poly @ camera.R.T + camera.t
    kept = []  # Sutherland-Hodgman against the plane z = near
    for a, b in zip(c, np.roll(c, -1, axis=0)):
        if a[2] >= near:
            kept.append(a)
        if (a[2] >= near) != (b[2] >= near):
            kept.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    if not kept:
        return (0, 0, 0, 0)
    uv = np.asarray(kept) @ camera.K.T
    uv = uv[:, :2] / uv[:, 2:3]
    x0, y0 = np.floor(uv.min(0) - 1).astype(np.int64)
    x1, y1 = np.ceil(uv.max(0) + 2).astype(np.int64)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, camera.width), min(y1, camera.height)
    if x1 <= x0 or y1 <= y0:
        return (0, 0, 0, 0)
    return int(y0), int(y1), int(x0), int(x1)


def polygon_contains(plane, polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) bool: are (N, 3) points on the plane inside the (K, 3) polygon (in plane coords)?"""
    from matplotlib.path import Path as MplPath

    poly = np.asarray(polygon, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 3 or len(poly) < 3:
        raise ValueError(f"polygon must be (K>=3, 3), got {poly.shape}")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    origin, u, v = plane_basis(plane)
    to2 = lambda a: np.c_[(a - origin) @ u, (a - origin) @ v]  # noqa: E731
    return MplPath(to2(poly)).contains_points(to2(pts))


def reflector_mask(camera: Camera, plane, polygon: np.ndarray | None, depth: np.ndarray,
                   rel_tol: float = 0.02, transmits: bool = False) -> np.ndarray:
    """beta support of one reflector in one view (§4.3.1: the plane's extent projected into the
    image): pixels whose ray meets the plane inside `polygon` in front of the camera and whose
    first-surface depth agrees with the plane (|D - z_plane| < rel_tol * z_plane), so occluders in
    front of the reflector are excluded. Without a polygon the plane is unbounded. `transmits`
    (glass): the depth may also lie behind the plane, where the scene seen through the pane is."""
    depth = np.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth must be ({camera.height}, {camera.width}), got {depth.shape}")
    p = _plane(plane)
    if not (camera.center @ p[:3] + p[3]) > 0:  # camera not on the reflecting side (n to it)
        return np.zeros(depth.shape, bool)
    y0, y1, x0, x1 = 0, camera.height, 0, camera.width
    if polygon is not None:  # only the pixels the polygon can cover (exactly the same mask)
        y0, y1, x0, x1 = polygon_window(camera, polygon)
    ok = np.zeros(depth.shape, bool)
    if y1 <= y0 or x1 <= x0:
        return ok
    ys, xs = np.mgrid[y0:y1, x0:x1]
    X, z = ray_plane_hits(camera, p, np.c_[xs.ravel(), ys.ravel()].astype(np.float64))
    d = depth[y0:y1, x0:x1].reshape(-1)
    agree = (d > z * (1 - rel_tol)) if transmits else (np.abs(d - z) < rel_tol * z)
    sel = np.isfinite(z) & (z > 1e-3) & (d > 0) & agree
    if polygon is not None and sel.any():
        sel[sel] = polygon_contains(plane, polygon, X[sel])
    ok[y0:y1, x0:x1] = sel.reshape(y1 - y0, x1 - x0)
    return ok


def plane_from_outline(camera: Camera, depth: np.ndarray, outline: np.ndarray,
                       ring: float = 0.05, gap: float = 0.01, min_points: int = 50,
                       proud: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Plane (4,) and world polygon (K, 3) of a reflector outlined in one photograph.

    `outline` (K, 2): its corners in the camera's pixels; `depth` (h, w): that view's z-depth at
    any size (0 = none). A mirror's or a screen's own depth is the mirror world or noise, the wall
    it hangs on is not: the plane is fitted to the depth in a band outside the outline, from
    `gap` to `gap + ring` of the image's larger side (the frame's few pixels skipped): the
    band's largest plane (RANSAC at 1 % of its median depth), then least squares trimmed to 2.5
    robust sigmas (ten rounds), with the camera on its positive side (§4.3.1: the reflector's
    plane; Xu et al. take it from the user). A reflector may stand proud of that
    surface (a TV's screen): when most of the depth inside the outline lies in a slab up to
    `proud` × depth in front of the plane, with a median offset above 2.5 sigmas of the fit, the
    plane moves by that median. The polygon is the outline's rays on the plane. ValueError when
    fewer than `min_points` depths surround the outline."""
    import cv2
    depth = np.asarray(depth, np.float64)
    uv = np.asarray(outline, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (h, w), got {depth.shape}")
    if uv.ndim != 2 or uv.shape[1] != 2 or len(uv) < 3:
        raise ValueError(f"outline must be (K>=3, 2), got {uv.shape}")
    h, w = depth.shape
    cam = camera.resized(w, h)
    sx, sy = w / camera.width, h / camera.height
    px = np.c_[(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5]  # Camera.resized's pixels
    inner = np.zeros((h, w), np.uint8)
    cv2.fillPoly(inner, [np.round(px).astype(np.int32)], 1)

    def grown(r: float) -> np.ndarray:
        k = 2 * max(1, int(round(r * max(h, w)))) + 1
        return cv2.dilate(inner, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0

    band = grown(gap + ring) & ~grown(gap) & (depth > 0) & np.isfinite(depth)
    vs, us = np.nonzero(band)
    if len(us) < min_points:
        raise ValueError(f"{len(us)} depth samples around the outline, {min_points} needed")
    from .raycast import pixel_directions
    P = cam.center + pixel_directions(cam, np.c_[us, vs].astype(np.float64)) * depth[vs, us][:, None]
    from .ransac_nb import best_plane
    # the band may cross other surfaces (a cabinet below a TV): the wall is the largest plane
    # (RANSAC at 1 % of the band's depth), then least squares on it
    _, idx = best_plane(P, 0.01 * float(np.median(depth[vs, us])), 1000, np.random.default_rng(0))
    keep = np.zeros(len(P), bool)
    keep[idx] = True
    if keep.sum() < min_points:
        keep[:] = True
    for _ in range(10):
        plane = fit_plane(P[keep])
        r = P @ plane[:3] + plane[3]
        sigma = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        keep = np.abs(r) <= max(2.5 * sigma, 1e-12)
    plane = fit_plane(P[keep])
    if camera.center @ plane[:3] + plane[3] < 0:
        plane = -plane
    vi, ui = np.nonzero((cv2.erode(inner, np.ones((3, 3), np.uint8)) > 0) & (depth > 0)
                        & np.isfinite(depth))
    if len(ui) >= min_points:
        zi = depth[vi, ui]
        off = (cam.center + pixel_directions(cam, np.c_[ui, vi].astype(np.float64)) * zi[:, None]) \
            @ plane[:3] + plane[3]                                 # > 0: in front, camera side
        slab = (off > -2.5 * sigma) & (off < proud * zi)
        if slab.mean() > 0.5 and np.median(off[slab]) > 2.5 * sigma:
            plane = np.r_[plane[:3], plane[3] - np.median(off[slab])]
    X, z = ray_plane_hits(cam, plane, px)
    if not np.all(np.isfinite(z) & (z > 0)):
        raise ValueError("an outline corner's ray does not meet the fitted plane in front of the camera")
    return plane, X


def reflector_support(camera: Camera, plane, polygon: np.ndarray | None,
                      occluder_depth: np.ndarray, rel_tol: float = 0.02) -> np.ndarray:
    """A reflector's pixels in a camera that has no depth of its own (a held-out photograph),
    given the z-depth of the scene's other geometry there (G ray-cast, 0 = none): the polygon's
    projection less the pixels where that geometry lies in front of the plane by more than
    `rel_tol`. G may hold nothing, or the mirror world, behind a reflector; neither hides it.
    Without a polygon: `reflector_mask` on the occluder depth (the plane's extent is where G is)."""
    occ = np.asarray(occluder_depth, np.float64)
    if occ.shape != (camera.height, camera.width):
        raise ValueError(f"occluder_depth must be ({camera.height}, {camera.width}), got {occ.shape}")
    if polygon is None:
        return reflector_mask(camera, plane, None, occ, rel_tol)
    _, z = ray_plane_hits(camera, plane)
    on_plane = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    front = (occ > 0) & (occ < on_plane * (1 - rel_tol))
    return reflector_mask(camera, plane, polygon, np.where(front, occ, on_plane), rel_tol)


def mirror_points(camera: Camera, plane, mask: np.ndarray, scene,
                  min_gap: float = 0.03, bounds=None,
                  transmit: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The planar-reflection geometry of a view (§4.3.1 initialisation of M1): for each pixel in
    `mask`, the reflected ray from the plane is cast into G (open3d RaycastingScene `scene`); the
    mirror-world point lies on the camera ray at the total path length. Hits closer than
    `min_gap` to the plane (noise / thickness of a fused G at the reflector) are skipped; rays
    that leave G through a hole end on the box `bounds` = (lo, hi) when given. Returns (H, W, 3) world
    points (NaN where there is none) and their (H, W) z-depth in this camera (0 where none).
    `transmit`: the ray goes on through the plane instead (what a pane of glass shows behind
    it): the points are then the real geometry behind the plane."""
    from .raycast import cast

    H, W = camera.height, camera.width
    mask = np.asarray(mask, bool)
    if mask.shape != (H, W):
        raise ValueError(f"mask must be ({H}, {W}), got {mask.shape}")
    p = _plane(plane)
    pts = np.full((H, W, 3), np.nan)
    zd = np.zeros((H, W))
    ys, xs = np.nonzero(mask)  # the plane hits of the mask's pixels only
    Xm_, zm_ = ray_plane_hits(camera, p, np.c_[xs, ys].astype(np.float64))
    ok = np.isfinite(zm_) & (zm_ > 0)
    sel = np.zeros((H, W), bool)
    sel[ys[ok], xs[ok]] = True
    if not sel.any():
        return pts, zd
    c = camera.center
    P = Xm_[ok]
    z = np.zeros((H, W))
    z[ys[ok], xs[ok]] = zm_[ok]
    r = P - c
    rng0 = np.linalg.norm(r, axis=1)
    r /= rng0[:, None]
    r_ref = r if transmit else r - 2.0 * (r @ p[:3])[:, None] * p[:3]
    # the reflected ray must leave the reflector: a fused (TSDF) G is noisy / has thickness around
    # the plane, so hits within `min_gap` of the plane are skipped (recast from behind them);
    # without this M1 collapses onto the plane (= M0) and the two layers cannot be told apart
    hit = np.zeros(len(P))
    todo = np.arange(len(P))
    for _ in range(4):
        t = cast(scene, P[todo] + (hit[todo] + 1e-4)[:, None] * r_ref[todo], r_ref[todo])["t_hit"]
        hit[todo] += t + 1e-4
        fin = np.isfinite(t)
        Q = P[todo] + np.where(fin, hit[todo], 0.0)[:, None] * r_ref[todo]
        near = fin & (np.abs(Q @ p[:3] + p[3]) < min_gap)
        todo = todo[near]
        if len(todo) == 0:
            break
    hit[todo] = np.inf  # still on the plane: no reflected geometry
    if bounds is not None:  # rays leaving G through a hole: the box of G as a room proxy
        lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
        miss = ~np.isfinite(hit)
        if miss.any():
            d = r_ref[miss]
            with np.errstate(divide="ignore", invalid="ignore"):
                tb = np.where(d > 0, (hi - P[miss]) / d, np.where(d < 0, (lo - P[miss]) / d, np.inf))
            te = tb.min(1)
            hit[np.flatnonzero(miss)[(te > min_gap) & np.isfinite(te)]] = te[(te > min_gap) & np.isfinite(te)]
    good = np.isfinite(hit)
    Xm = c + r * (rng0 + hit)[:, None]
    Xm[~good] = np.nan
    pts[sel] = Xm
    zz = np.where(good, z[sel] * (rng0 + hit) / rng0, 0.0)
    zd[sel] = zz
    return pts, zd


def grid_mesh(points: np.ndarray, depth: np.ndarray, step: int = 1,
              max_rel_jump: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh over an (H, W, 3) grid of world points: two triangles per pixel square
    (Xu §4.2.3) on every `step`-th pixel, skipping squares with a corner of depth <= 0 / NaN or a
    z-depth jump larger than `max_rel_jump` x the smaller depth (occlusion edges are cut).
    Returns (V, 3) float32 vertices and (F, 3) int32 faces."""
    pts = np.asarray(points, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3 or depth.shape != pts.shape[:2]:
        raise ValueError(f"points must be (H, W, 3) and depth (H, W), got {pts.shape}, {depth.shape}")
    P = pts[::step, ::step]
    D = depth[::step, ::step]
    V = (D > 0) & np.isfinite(D) & np.all(np.isfinite(P), axis=2)
    h, w = V.shape
    idx = -np.ones((h, w), np.int64)
    idx[V] = np.arange(V.sum())
    verts = P[V]
    if h < 2 or w < 2 or len(verts) == 0:
        return verts.astype(np.float32), np.zeros((0, 3), np.int32)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    na, nb, nc, nd = D[:-1, :-1], D[:-1, 1:], D[1:, :-1], D[1:, 1:]
    rel = lambda x, y: np.abs(x - y) <= max_rel_jump * np.minimum(x, y)  # noqa: E731
    ok1 = (a >= 0) & (b >= 0) & (c >= 0) & rel(na, nb) & rel(na, nc) & rel(nb, nc)
    ok2 = (b >= 0) & (d >= 0) & (c >= 0) & rel(nb, nd) & rel(nd, nc) & rel(nb, nc)
    f1 = np.stack([a[ok1], c[ok1], b[ok1]], 1)
    f2 = np.stack([b[ok2], c[ok2], d[ok2]], 1)
    return verts.astype(np.float32), np.concatenate([f1, f2]).astype(np.int32)


def depth_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) world points of a z-depth map (NaN where depth <= 0 or not finite)."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth must be ({camera.height}, {camera.width}), got {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    out = np.full(depth.shape + (3,), np.nan)
    if valid.any():  # only the pixels with depth: a reflector's M1 covers a few % of a view
        v, u = np.nonzero(valid)
        out[valid] = camera.unproject(np.stack([u, v], 1).astype(np.float64), depth[valid])
    return out


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniformly distributed on a triangle mesh (area-weighted, deterministic)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if len(F) == 0 or area.sum() <= 0:
        raise ValueError("mesh has no area to sample")
    rng = np.random.default_rng(seed)
    t = rng.choice(len(F), size=int(n), p=area / area.sum())
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s1 = np.sqrt(r1)
    return (1 - s1)[:, None] * a[t] + (s1 * (1 - r2))[:, None] * b[t] + (s1 * r2)[:, None] * c[t]
