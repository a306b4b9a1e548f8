"""Reflector candidates from geometry *behind* a surface (issue #26, "a planar region whose
MVS/depth shows geometry behind the plane").

Multi-view stereo and depth cameras see the mirror world inside a mirror or a glossy screen: the
reflected room, consistent across views, at the distance of the reflected objects, i.e. behind
the wall the reflector hangs on (Xu et al. §4.1 take the reflectors from the user for that reason;
§4.3 detects them on a mesh that already lacks the mirror world). A piece of a view's depth map
that lies well behind a plane of that view and is enclosed by that plane's own depth is such a
hole through the wall. `behind_outlines` finds them in one depth map and returns each as an
outline in that view's pixels, the form a user gives (`planes.plane_from_outline` then places
it); `merge_candidates` keeps those found at the same place in several views, and
`plane_holes` the holes no single view sees whole, pooled over the views. A window, a
doorway or a niche is also geometry behind a plane: the `reflectors` stage scores every candidate
with the multi-view cue (reflector_detect.py) and keeps only those a reflection explains.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Options, param
from ..scene import Camera
from .planes import fit_plane, ray_plane_hits


@dataclass(frozen=True)
class BehindOptions(Options):
    """Finding reflectors behind planes of the depth; `global_mesh` embeds these as
    [global_mesh.behind] (docs/GLOBAL_MESH.md "Mirrors"). Lengths are fractions of the plane's
    depth or of the image: scale-free."""

    behind: float = param(0.1, "a region is behind a plane when its depth exceeds the plane's "
                          "along the ray by more than this fraction of it", min=0.01, max=10.0)
    enclosed: float = param(0.6, "share of the ring around a region whose depth lies on the plane",
                            min=0.0, max=1.0)
    border: float = param(0.25, "largest share of a region's outline on the image frame",
                          min=0.0, max=1.0)
    min_area: float = param(0.002, "smallest region, fraction of the image", min=0.0, max=1.0)
    max_area: float = param(0.25, "largest region, fraction of the image", min=0.0, max=1.0)
    min_views: float = param(0.25, "a candidate is found in at least this share of the views "
                             "whose frame holds its centre (and in 2)", min=0.0, max=1.0)
    max_views: int = param(12, "views, spread over the capture, a candidate is verified on",
                           min=2, max=10000)
    threshold: float = param(0.02, "verification: median surface-warp error above which the "
                             "plane does not explain the region (linear intensity)",
                             min=1e-4, max=1.0)
    mirror_ratio: float = param(0.5, "verification: mirror-warp / surface-warp error below which "
                                "the mirrored G explains it", min=0.01, max=10.0)
    pooled: bool = param(True, "also look for holes through a plane pooled over the views "
                         "(geometry/plane_holes.py): a reflector no view sees whole")


_D = BehindOptions()


def _odd(n: float) -> int:
    return 2 * max(1, int(round(n / 2))) + 1


def view_planes(camera: Camera, depth: np.ndarray, rel_dist: float = 0.01, max_planes: int = 3,
                min_fraction: float = 0.1, samples: int = 20000, seed: int = 0) -> list[np.ndarray]:
    """The largest planes (4,) of one depth map, camera on the positive side: sequential RANSAC
    (inliers within `rel_dist` of the median depth) on up to `samples` of its points, each plane
    holding at least `min_fraction` of them."""
    from .ransac_nb import best_plane
    from .raycast import pixel_directions
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (h, w), got {depth.shape}")
    h, w = depth.shape
    cam = camera.resized(w, h)
    vs, us = np.nonzero((depth > 0) & np.isfinite(depth))
    if len(us) < 500:
        return []
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(us), min(samples, len(us)), replace=False)
    vs, us = vs[pick], us[pick]
    z = depth[vs, us]
    P = cam.center + pixel_directions(cam, np.c_[us, vs].astype(np.float64)) * z[:, None]
    dist = rel_dist * float(np.median(z))
    n0, out = len(P), []
    for _ in range(max_planes):
        _, idx = best_plane(P, dist, 500, rng)
        if len(idx) < min_fraction * n0:
            break
        pl = fit_plane(P[idx])
        if cam.center @ pl[:3] + pl[3] < 0:
            pl = -pl
        out.append(pl)
        P = np.delete(P, idx, axis=0)
    return out


def behind_outlines(camera: Camera, depth: np.ndarray, plane, *, behind: float = _D.behind,
                    on_plane: float = 0.02, close: float = 0.01, ring: float = 0.02,
                    min_area: float = _D.min_area, max_area: float = _D.max_area,
                    enclosed: float = _D.enclosed, min_ring_depth: float = 0.3,
                    border: float = _D.border) -> list[dict]:
    """Regions of one depth map (h, w) that lie behind `plane` and are enclosed by it.

    Behind: depth beyond the plane's depth along the ray by more than `behind` of it (a mirror
    world is as far behind as the reflected objects are in front; a picture frame, a socket or a
    shallow niche is not). The behind pixels are closed (`close` of the larger side) and each
    outer contour whose area is `min_area`..`max_area` of the image, with at most `border` of
    its outline on the image's frame (a reflector the frame cuts on one side is still found, the
    views' parts joined by `find_candidates`), and whose surrounding ring inside the image
    (`ring` of the larger side) has depth on at least `min_ring_depth` of its pixels, that depth
    on the plane (within `on_plane`) on at least `enclosed` of them, is a candidate. Returns per candidate: outline (K, 2) convex polygon in
    `camera`'s pixels (pixel centres = integers), area (fraction of the image), enclosed (ring
    fraction on the plane), behind (median relative depth behind the plane inside)."""
    import cv2
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (h, w), got {depth.shape}")
    h, w = depth.shape
    cam = camera.resized(w, h)
    valid = (depth > 0) & np.isfinite(depth)
    _, zp = ray_plane_hits(cam, plane)
    front = np.isfinite(zp) & (zp > 0)
    zp = np.where(front, zp, 0.0)
    rel = np.where(valid & front, depth / np.where(front, zp, 1.0) - 1.0, np.nan)
    with np.errstate(invalid="ignore"):
        back = (rel > behind).astype(np.uint8)
        on = np.abs(rel) < on_plane
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (_odd(close * max(h, w)),) * 2)
    closed = cv2.morphologyEx(back, cv2.MORPH_CLOSE, k)
    contours, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    kr = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (_odd(2 * ring * max(h, w)),) * 2)
    sx, sy = camera.width / w, camera.height / h
    out = []
    for c in contours:
        q = c.reshape(-1, 2)
        edge = (q[:, 0] <= 0) | (q[:, 1] <= 0) | (q[:, 0] >= w - 1) | (q[:, 1] >= h - 1)
        if edge.mean() > border:
            continue                                    # mostly cut by the frame: its outline is unseen
        region = np.zeros((h, w), np.uint8)
        cv2.drawContours(region, [c], -1, 1, thickness=cv2.FILLED)
        area = float(region.mean())
        if not min_area <= area <= max_area:
            continue
        inside = region > 0
        around = (cv2.dilate(region, kr) > 0) & ~inside
        seen = around & valid
        if seen.sum() < min_ring_depth * around.sum():
            continue
        enc = float((seen & on).sum() / max(seen.sum(), 1))
        if enc < enclosed:
            continue
        hull = cv2.convexHull(c)
        poly = cv2.approxPolyDP(hull, 0.01 * cv2.arcLength(hull, True), True).reshape(-1, 2)
        if len(poly) < 3:
            continue
        uv = np.c_[(poly[:, 0] + 0.5) * sx - 0.5, (poly[:, 1] + 0.5) * sy - 0.5]
        out.append({"outline": uv, "area": area, "enclosed": enc,
                    "behind": float(np.nanmedian(np.where(inside & (back > 0), rel, np.nan)))})
    return out


def merge_candidates(found: list[dict], same_angle_deg: float = 5.0, same_offset: float = 0.2,
                     min_views: int = 2) -> list[list[dict]]:
    """Groups of per-view candidates that are one reflector: each dict has plane (4,), polygon
    (K, 3) (placed by plane_from_outline), area and view. Two are the same when their normals
    agree within `same_angle_deg`, one's centroid lies off the other's plane by less than
    `same_offset` of the larger polygon's diameter, and the centroids are closer than the smaller
    diameter (scale-free: lengths of the reflector itself). Groups seen in fewer than `min_views`
    views are dropped (one view's depth noise); each group is ordered best first (largest area in
    its view), the groups by view count."""
    groups: list[list[dict]] = []
    for f in sorted(found, key=lambda f: -f["area"]):
        pa, ca = np.asarray(f["plane"], np.float64), np.asarray(f["polygon"]).mean(0)
        da = float(np.ptp(np.asarray(f["polygon"]), axis=0).max())
        for g in groups:
            r = g[0]
            pb, cb = np.asarray(r["plane"], np.float64), np.asarray(r["polygon"]).mean(0)
            db = float(np.ptp(np.asarray(r["polygon"]), axis=0).max())
            cos = float(pa[:3] @ pb[:3])
            if (cos > np.cos(np.radians(same_angle_deg))
                    and abs(ca @ pb[:3] + pb[3]) < same_offset * max(da, db)
                    and np.linalg.norm(ca - cb) < min(da, db)):
                if all(x["view"] != f["view"] for x in g):
                    g.append(f)
                break
        else:
            groups.append([f])
    groups = [g for g in groups if len(g) >= min_views]
    return sorted(groups, key=lambda g: -len(g))


def _hull_on_plane(plane, polygons: list) -> np.ndarray:
    """(K, 3) convex hull, on `plane`, of (K_i, 3) polygons projected onto it: a reflector's
    extent from the parts of it that several views saw behind the wall."""
    from scipy.spatial import ConvexHull

    from .planes import plane_basis
    origin, u, v = plane_basis(plane)
    P = np.concatenate([np.asarray(p, np.float64) for p in polygons])
    Q = np.c_[(P - origin) @ u, (P - origin) @ v]
    try:
        Q = Q[ConvexHull(Q).vertices]
    except Exception:  # scipy's QhullError: all points on a line
        return np.asarray(polygons[0], np.float64)
    return origin + Q[:, :1] * u + Q[:, 1:] * v


def _seen_in(cams: dict, polygon) -> int:
    """Views whose frame holds the polygon's centre (part of it may be out of frame)."""
    from .decompose_terms import project
    seen = 0
    for cam in cams.values():
        p, z = project(cam, np.asarray(polygon, np.float64).mean(0)[None])
        seen += bool(z[0] > 0 and np.all((p >= 0) & (p <= [cam.width - 1, cam.height - 1])))
    return seen


def _candidate(name, view, outline, plane, polygon, views, seen, behind, enclosed, min_views,
               how) -> dict:
    need = max(2, int(np.ceil(min_views * max(seen, 1))))
    return {
        "name": name, "view": view,
        "outline": [[float(u), float(v)] for u, v in outline],
        "plane": [float(x) for x in plane],
        "polygon": [[float(x) for x in p] for p in polygon],
        "views": views, "seen_in": seen, "behind": behind, "enclosed": enclosed,
        "kept": len(views) >= need,
        "reason": (f"depth behind its plane (median {behind:.2f} x the plane's depth), {how}, "
                   f"in {len(views)} of the {seen} views that hold it"
                   + ("" if len(views) >= need else f", {need} needed"))}


def find_candidates(cams: dict, depths: dict, min_views: float = _D.min_views,
                    progress: bool = False, pooled: bool = _D.pooled, **kw) -> list[dict]:
    """Reflector candidates of a capture from its depth maps. cams: name -> Camera; depths:
    name -> (h, w) z-depth (any size, 0 = none). Every view's planes (`view_planes`) and the
    regions behind them (`behind_outlines`, options `kw`) are placed on the surface around them
    (`planes.plane_from_outline`) and grouped (`merge_candidates`); a group is a candidate when
    it was found in at least `min_views` of the views whose frame holds its centre (depth noise
    of a few views is not). With `pooled`, the holes through those planes that no view saw
    whole (`plane_holes.find_plane_holes`, the same limits) are candidates too, unless one of
    the groups is that reflector already. Returns every candidate as a dict: name, view (the
    view it is best seen in), outline there, plane, polygon (the hull of the group's polygons
    on that plane), views (names found in), seen_in (views whose frame holds its centre),
    behind, enclosed, kept, reason."""
    from tqdm import tqdm

    from .decompose_terms import project
    from .planes import plane_from_outline
    found, vplanes = [], {}
    for n in tqdm(list(depths), desc="global_mesh: regions behind planes", unit="view",
                  disable=not progress, leave=False):
        cam, d = cams[n], depths[n]
        vplanes[n] = view_planes(cam, d)
        for pl in vplanes[n]:
            for c in behind_outlines(cam, d, pl, **kw):
                try:
                    plane, poly = plane_from_outline(cam, d, c["outline"])
                except ValueError:
                    continue
                found.append(dict(c, view=n, plane=plane, polygon=poly))
    out = []
    for i, g in enumerate(merge_candidates(found, min_views=2)):
        best = g[0]
        hull = _hull_on_plane(best["plane"], [f["polygon"] for f in g])
        views = sorted({f["view"] for f in g})
        out.append(_candidate(
            f"behind_{i}", best["view"], best["outline"], best["plane"], hull, views,
            max(_seen_in(cams, hull), len(views)), float(np.median([f["behind"] for f in g])),
            float(np.median([f["enclosed"] for f in g])), min_views, "enclosed by it"))
    if not pooled:
        return out
    from .plane_holes import find_plane_holes
    holes = find_plane_holes(cams, depths, vplanes, behind=kw.get("behind", _D.behind),
                             enclosed=kw.get("enclosed", _D.enclosed))
    for h in holes:
        if any(same_reflector(h, c["plane"], c["polygon"]) or
               same_reflector(c, h["plane"], h["polygon"]) for c in out):
            continue  # found by one view already, or a second plane of a hole kept here
        cam = cams[h["view"]]
        uv, _ = project(cam, h["polygon"])
        out.append(_candidate(
            f"hole_{len(out)}", h["view"], uv, h["plane"], h["polygon"], h["views"],
            max(_seen_in(cams, h["polygon"]), len(h["views"])), h["behind"], h["enclosed"],
            min_views, "a hole through it pooled over the views"))
    return out


def same_reflector(cand: dict, plane, polygon, angle_deg: float = 5.0) -> bool:
    """Is candidate `cand` (plane, polygon) the reflector (plane (4,), polygon (K, 3) or None)
    given already? Planes within `angle_deg` and the candidate's centre, put on that plane,
    inside its polygon (anywhere on it without one) and off it by less than the candidate's
    diameter."""
    from .planes import polygon_contains
    pa, pb = np.asarray(cand["plane"], np.float64), np.asarray(plane, np.float64)
    if abs(float(pa[:3] @ pb[:3])) < np.cos(np.radians(angle_deg)):
        return False
    poly = np.asarray(cand["polygon"], np.float64)
    c = poly.mean(0)
    off = float(c @ pb[:3] + pb[3])
    if abs(off) > np.ptp(poly, axis=0).max():
        return False
    return polygon is None or bool(polygon_contains(pb, np.asarray(polygon), (c - off * pb[:3])[None])[0])


def verify_candidate(cand: dict, cams: dict, images: dict, scene, bounds, *,
                     threshold: float = _D.threshold, mirror_ratio: float = _D.mirror_ratio,
                     min_pairs: int = 4, min_mask: int = 100, min_gap: float = 0.01,
                     max_views: int = _D.max_views,
                     g_depth: dict | None = None) -> tuple[bool, str, dict]:
    """Is the region behind a plane a reflection? The multi-view cue of reflector_detect.py on
    the mesh fused without it (`scene`: its open3d RaycastingScene, `bounds` its box): each view's
    pixels inside the polygon where that mesh lies on or behind the plane are warped to the
    nearest views on the plane (a surface there) and on the mirrored mesh (a reflection of the
    room). Kept only when the surface warp fails (> `threshold`) and the mirror warp explains it
    (mirror/surface error < `mirror_ratio`): real geometry behind a gap in a wall or a ceiling
    (what a doorway or the space above ceiling panels is) does not mirror the room. images:
    name -> (H, W, 3) linear float at the cameras' size; min_gap: of the plane's median depth.
    At most `max_views` of the views that see it, evenly spread in capture order, are scored:
    a reflection's motion between nearest views grows with their distance, so a dense capture
    scored on all its views would see its reflections barely move (the same TV, mirror/surface
    0.35 on every other photo of LLFF room and 0.57 on all of them); the spread keeps the
    baseline, and the cost, the same however densely it was photographed. g_depth: a dict the
    mesh's depth per view is kept in between candidates. Returns (kept, why, score)."""
    from .decompose_terms import ViewGeom
    from .planes import depth_points, mirror_points, polygon_contains, ray_plane_hits
    from .raycast import render_depth
    from .reflector_detect import decision, score_candidate
    plane, poly = np.asarray(cand["plane"]), np.asarray(cand["polygon"])
    masks = {}
    for n, cam in cams.items():
        X, zp = ray_plane_hits(cam, plane)
        front = np.isfinite(zp) & (zp > 0)
        if not front.any():
            continue
        g_depth = {} if g_depth is None else g_depth
        if n not in g_depth:
            g_depth[n] = render_depth(scene, cam).astype(np.float32)
        d = g_depth[n].astype(np.float64)
        m = front & ((d == 0) | (d >= zp * 0.98))
        if m.sum() < min_mask:
            continue
        m[m] = polygon_contains(plane, poly, X[m])
        if m.sum() >= min_mask:
            masks[n] = (m, zp, d)
    names = list(masks)
    if len(names) > max_views:
        names = [names[i] for i in np.round(np.linspace(0, len(names) - 1, max_views)).astype(int)]
    views = []
    for n in names:
        cam, (m, zp, d) = cams[n], masks[n]
        zs = np.where(m, zp, d)
        _, D1 = mirror_points(cam, plane, m, scene, min_gap=min_gap * float(np.median(zp[m])),
                              bounds=bounds)
        views.append(ViewGeom(n, cam, np.asarray(images[n], np.float64), zs, m,
                              depth_points(cam, np.where(m, zp, 0.0)), depth_points(cam, D1), D1))
    score = score_candidate(views) if len(views) >= 2 else {"surface_error": None, "pairs": 0}
    kept, why = decision(score, threshold, min_pairs, None, 1.0, mirror_ratio)
    return kept, why, score
