"""TSDF fusion of depth frames into the global mesh G (Xu et al. §4.1: "each sequence is fused into
a mesh using the KinectFusion algorithm"), and the reflector handling that keeps G honest.

* `tsdf_fuse`: open3d tensor `VoxelBlockGrid` (Curless & Levoy / KinectFusion TSDF averaging;
  `ScalableTSDFVolume` returns empty meshes in open3d 0.20, docs/DESIGN.md), marching cubes
  (`extract_triangle_mesh`), then small-component cleanup; the mesh comes out in the canonical
  vertex/face order of `io.mesh.canonical_order`, so identical frames give identical bytes.
* Mirrors: a depth sensor (and MVS) sees the virtual "mirror world" behind a reflector.
  `reflector_mask` marks, per depth frame, the pixels inside a reflector's projected polygon whose
  measured surface is at or behind the reflector plane; `apply_reflectors` replaces them with the
  depth of the plane itself (the reflector's surface, which is what G must contain: Xu et al. take
  the mirror geometry from Whelan et al. 2018) or drops them. Pixels in front of the plane (an
  object standing before the mirror) keep their measurement. Glass (`material = "glass"`) is left
  as measured: what is seen behind a pane is the transmitted scene, real geometry that G must
  hold so that the base layer I0 is drawn where it is (Xu et al. §7 name glass, which shows the
  transmitted room and a reflection, as a limitation of their colour-less mirror model).
* `mirror_world_fraction`: how much of a mesh lies behind a reflector, inside its extent: used for
  the warning when no reflectors.json is given and by the benchmark.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from ..cache import ProcessCache
from ..config import Options, param
from ..errors import ConfigError
from ..io.mesh import Mesh, canonical_mesh, canonical_order
from ..scene import Camera, Reflector
from .normals import pixel_rays

log = logging.getLogger("ibr_pipeline.fusion")


# --- reflectors ----------------------------------------------------------------------------------
def _ray_dirs(camera: Camera) -> np.ndarray:
    """`normals.pixel_rays` of the camera, read-only and shared by the cameras with the same
    intrinsics and size: a fusion asks for them per frame and reflector, with one K throughout."""
    key = (np.asarray(camera.K, dtype=np.float64).tobytes(), camera.width, camera.height)

    def rays():
        d = pixel_rays(camera.K, camera.height, camera.width)
        d.setflags(write=False)
        return d
    return _RAYS.get(key, rays)


_RAYS = ProcessCache(4)  # (K bytes, W, H) -> rays: a few camera models per capture


def plane_depth(camera: Camera, plane: Sequence[float]) -> np.ndarray:
    """(H, W) z-depth at which each pixel's ray meets the world plane n.x + d = 0 (inf: no hit in
    front of the camera)."""
    n = np.asarray(plane[:3], dtype=np.float64)
    d0 = float(plane[3])
    n_cam = camera.R @ n                       # plane in camera coordinates: n_cam . x + d_cam = 0
    d_cam = d0 - n_cam @ camera.t
    rays = _ray_dirs(camera)
    denom = rays @ n_cam
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -d_cam / denom
    return np.where(np.isfinite(z) & (z > 0), z, np.inf)


def polygon_mask(camera: Camera, polygon: np.ndarray, near: float = 1e-3) -> np.ndarray:
    """(H, W) bool: pixels inside the projection of a planar world polygon (clipped at z = near)."""
    import cv2

    poly = np.asarray(polygon, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 3 or len(poly) < 3:
        raise ValueError(f"polygon must be (N >= 3, 3), got {poly.shape}")
    cam_pts = poly @ camera.R.T + camera.t
    # Sutherland-Hodgman clip against the near plane z >= near
    clipped = []
    for i in range(len(cam_pts)):
        a, b = cam_pts[i], cam_pts[(i + 1) % len(cam_pts)]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            clipped.append(a)
        if ina != inb:
            s = (near - a[2]) / (b[2] - a[2])
            clipped.append(a + s * (b - a))
    out = np.zeros((camera.height, camera.width), np.uint8)
    if len(clipped) < 3:
        return out.astype(bool)
    pts = np.asarray(clipped) @ camera.K.T
    uv = pts[:, :2] / pts[:, 2:3]
    # cv2 works in fixed point; keep coordinates in a sane range (far-off vertices after clipping)
    lim = 8 * max(camera.width, camera.height)
    uv = np.clip(uv, -lim, lim)
    cv2.fillPoly(out, [np.round(uv * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def reflector_mask(camera: Camera, depth: np.ndarray, reflector: Reflector, rel_tol: float = 0.02,
                   view_mask: np.ndarray | None = None, refuted: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of a depth frame that see `reflector` (or the mirror world through it).

    Returns (mask (H, W) bool, plane z-depth (H, W)). A pixel is masked when it lies inside the
    reflector's extent (its polygon projected into the camera, else the user's per-view mask
    `view_mask`, else the whole image) AND its measured depth is at or behind the plane (depth >=
    plane depth x (1 - rel_tol)) or missing. Objects in front of the reflector are kept, except
    the pixels of `refuted` (H, W) bool inside the extent (`reflector_floaters`: depth in front
    of it that the other frames see through).
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth {depth.shape} does not match camera {camera.height}x{camera.width}")
    zp = plane_depth(camera, reflector.plane)
    if reflector.polygon is not None:
        extent = polygon_mask(camera, np.asarray(reflector.polygon))
    elif view_mask is not None:
        if view_mask.shape != depth.shape:
            raise ValueError(f"view_mask {view_mask.shape} does not match depth {depth.shape}")
        extent = np.asarray(view_mask, bool)
    else:
        extent = np.ones(depth.shape, bool)  # plane only: everything seen behind the plane
    behind = (depth <= 0) | (depth >= zp * (1.0 - rel_tol))
    if refuted is not None:
        if refuted.shape != depth.shape:
            raise ValueError(f"refuted {refuted.shape} does not match depth {depth.shape}")
        behind = behind | refuted
    return extent & np.isfinite(zp) & behind, zp


def apply_reflectors(camera: Camera, depth: np.ndarray, reflectors: Sequence[Reflector],
                     fill: bool = True, view_masks: dict[str, np.ndarray] | None = None,
                     rel_tol: float = 0.02, refuted: dict[str, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, int]:
    """Depth frame with reflector pixels (`reflector_mask`, with `refuted`[reflector name] when
    given) replaced by the plane depth (fill) or 0 (no fill).

    Returns (new depth, number of pixels changed). Reflectors without polygon or mask are skipped
    here only when `fill` is True (filling a whole plane would invent geometry); without fill they
    drop what lies behind the plane. Glass reflectors change nothing (module docstring)."""
    out = np.array(depth, dtype=np.float32, copy=True)
    changed = np.zeros(out.shape, bool)
    for r in reflectors:
        if r.material == "glass":
            continue
        vm = (view_masks or {}).get(r.name)
        if fill and r.polygon is None and vm is None:
            m, zp = reflector_mask(camera, out, r, rel_tol)
            m &= out > 0          # only drop measured mirror-world points, invent nothing
            out[m] = 0
        else:
            m, zp = reflector_mask(camera, out, r, rel_tol, vm, (refuted or {}).get(r.name))
            out[m] = zp[m] if fill else 0
        changed |= m
    return out, int(changed.sum())


def reflector_floaters(frames: dict, reflector: Reflector, rel_tol: float = 0.02,
                       agree: float = 0.05, max_views: int = 24) -> dict[str, np.ndarray]:
    """{frame name: (H, W) bool}: depth in front of `reflector` that the other frames refute.

    `frames`: {name: (depth (H, W), Camera at that size)}. A pixel inside the reflector's polygon
    whose depth lies in front of the plane (by more than `rel_tol`) is a surface point X. Another
    frame that sees X's pixel farther away than X (by more than `agree`, relative) looks through
    X, so X is not there (a free-space violation, as in the stability-based fusion of Merrell et
    al. 2007); one whose depth there is X's (within `agree`) confirms it; a nearer depth or none
    says nothing. A point refuted by more frames than confirm it is flagged: MVS's wrong matches
    of the highlights on a screen float in front of it, where the other views see the screen, and
    an object standing before a mirror is where every view that sees it puts it. Reflectors
    without a polygon, and glass, flag nothing. Each frame is checked against the `max_views`
    others (0 = all) that see most of its points in front (on a sample of up to 256 of them;
    ties in `frames`' order), so the cost grows with the frames, not with their square."""
    if max_views < 0:
        raise ValueError(f"max_views must be >= 0, got {max_views}")
    for name, (depth, cam) in frames.items():
        if np.shape(depth) != (cam.height, cam.width):
            raise ValueError(f"{name}: depth {np.shape(depth)} does not match its camera "
                             f"{cam.height}x{cam.width}")
    out: dict[str, np.ndarray] = {}
    if reflector.polygon is None or reflector.material == "glass":
        return out
    poly = np.asarray(reflector.polygon)
    for name, (depth, cam) in frames.items():
        d = np.asarray(depth, np.float64)
        front = polygon_mask(cam, poly) & (d > 0) & (d < plane_depth(cam, reflector.plane) * (1.0 - rel_tol))
        vs, us = np.nonzero(front)
        if len(vs) == 0:
            continue
        X = cam.unproject(np.c_[us, vs].astype(np.float64), d[vs, us])
        confirm = np.zeros(len(X), np.int32)
        refute = np.zeros(len(X), np.int32)
        others = [o for o in frames if o != name]
        if max_views and len(others) > max_views:
            sample = X[::max(1, len(X) // 256)]
            others = sorted(others, key=lambda o: -np.count_nonzero(_seen(frames[o][1], sample)[0]))
            others = others[:max_views]
        for other in others:
            dj, cj = frames[other]
            ok, iu, iv, z = _seen(cj, X)
            seen = np.zeros(len(X))
            seen[ok] = np.asarray(dj)[iv[ok].astype(int), iu[ok].astype(int)]
            ok &= seen > 0
            confirm += ok & (np.abs(seen - z) <= agree * z)
            refute += ok & (seen > z * (1.0 + agree))
        m = np.zeros(d.shape, bool)
        m[vs, us] = refute > confirm
        out[name] = m
    return out


def _seen(cam: Camera, points: np.ndarray):
    """(ok, column, row, z): which of the (N, 3) points lie in front of `cam` with their nearest
    pixel in its image, that pixel (float, rounded) and their z-depth."""
    uv, z = cam.project(points)
    iu, iv = np.round(uv[:, 0]), np.round(uv[:, 1])
    ok = (z > 0) & (iu >= 0) & (iu < cam.width) & (iv >= 0) & (iv < cam.height)
    return ok, iu, iv, z


def mirror_world_points(points: np.ndarray, reflectors: Sequence[Reflector],
                        cameras: Sequence[Camera], rel_tol: float = 0.02) -> np.ndarray:
    """(N,) bool: points a camera would see *through* a reflector: they project inside the
    reflector's polygon and lie farther along the ray than the reflector plane (by `rel_tol`).
    That is the virtual mirror world, when no real geometry is there (a caller with ground truth
    can intersect with "far from the true surface"). Reflectors without a polygon are ignored, and
    so is glass: what is behind a pane is real."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    out = np.zeros(len(pts), bool)
    for cam in cameras:
        ok, iu, iv, z = _seen(cam, pts)
        idx = np.nonzero(ok)[0]
        iu, iv = iu[idx].astype(int), iv[idx].astype(int)
        for r in reflectors:
            if r.polygon is None or r.material == "glass":
                continue
            inside = polygon_mask(cam, np.asarray(r.polygon))[iv, iu]
            zp = plane_depth(cam, r.plane)[iv, iu]
            out[idx[inside & (z[idx] > zp * (1 + rel_tol))]] = True
    return out


# --- TSDF fusion -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class FusionOptions(Options):
    """TSDF fusion of depth frames; the `global_mesh` stage embeds these as [global_mesh.fusion]."""

    voxel_size: float = param(0.0, "TSDF voxel size in metres (SfM units without a scale); 0 = "
                              "auto_voxel_size: twice the depth frames' pixel footprint at their "
                              "median depth, rounded to 5 mm", min=0.0, max=1.0)
    trunc_voxels: float = param(4.0, "truncation distance in voxels", min=1.0, max=64.0)
    depth_max: float = param(0.0, "ignore depth beyond this (scene units); 0 = the far end of the "
                             "scene points' depth ranges (global/poses.json)", min=0.0, max=1e6)
    weight_threshold: float = param(0.5, "marching cubes only where the summed TSDF weight "
                                    "(frames) reaches this", min=0.0, max=1000.0)
    # 0.02 %, not 0.2 %: a near object (llff_horns' placard) is few voxels but many pixels,
    # and at 0.2 % of a real capture's fragmented MVS surface it went with the noise
    # (docs/GLOBAL_MESH.md, docs/BENCHMARKS.md "Real captures")
    min_component: float = param(0.0002, "drop connected components below this fraction of all "
                                 "faces (fusion noise, floating blobs)", min=0.0, max=0.5)
    block_resolution: int = param(8, "voxels per side of a VoxelBlockGrid block", min=2, max=64)
    block_count: int = param(40000, "VoxelBlockGrid blocks allocated", min=100, max=10**8)
    device: str = param("CPU:0", "open3d device of the grid", affects_output=False)

    def check(self, prefix: str) -> None:
        if 0.0 < self.voxel_size < 1e-4:
            raise ConfigError(prefix + "voxel_size", f"must be 0 (auto) or at least 1e-4, got "
                              f"{self.voxel_size}")


AUTO_VOXEL_FOOTPRINTS = 2.0   # voxel = this many depth-frame pixel footprints
AUTO_VOXEL_STEP_M = 0.005     # rounded to 5 mm (metric units only)
AUTO_VOXEL_RANGE_M = (0.005, 0.05)


def auto_voxel_size(samples: Iterable[tuple[np.ndarray, Camera]], metric: bool = True) -> float:
    """TSDF voxel size matched to the depth frames' sampling (our choice; Xu et al. do not give one).

    samples: (depth (h, w), 0 = none; the frame's camera at any size). A depth pixel at depth z
    covers z / f_x of the surface (f_x at the depth frame's width); the voxel is
    `AUTO_VOXEL_FOOTPRINTS` x the median over frames of that footprint at the frame's median depth,
    so every voxel near the surface gets about two samples per frame: finer voxels leave holes and
    fuse the sensor's noise, coarser ones round occlusion edges into ramps several pixels wide
    (docs/GLOBAL_MESH.md). In metres it is rounded to 5 mm within [5 mm, 5 cm]; in SfM units it is
    returned as is. Raises ValueError when no frame has depth."""
    fp = []
    for depth, cam in samples:
        d = np.asarray(depth, dtype=np.float64)
        if d.ndim != 2:
            raise ValueError(f"depth must be (h, w), got {d.shape}")
        ok = np.isfinite(d) & (d > 0)
        if ok.any():
            fp.append(float(np.median(d[ok])) / cam.resized(d.shape[1], d.shape[0]).K[0, 0])
    if not fp:
        raise ValueError("no depth in any frame: cannot choose a voxel size")
    v = AUTO_VOXEL_FOOTPRINTS * float(np.median(fp))
    if not metric:
        return v
    lo, hi = AUTO_VOXEL_RANGE_M
    return float(np.clip(round(v / AUTO_VOXEL_STEP_M) * AUTO_VOXEL_STEP_M, lo, hi))


def tsdf_fuse(frames: Iterable[tuple[np.ndarray, Camera, np.ndarray | None]],
              options: FusionOptions, progress: bool = False,
              total: int | None = None) -> tuple[Mesh, dict]:
    """Fuse (depth (h, w) metres with 0 = none, camera, colour (H, W, 3) in [0, 1] or None) frames
    with a resolved voxel size (options.voxel_size > 0; 0 means auto, see auto_voxel_size).

    The camera is resized to the depth frame's size (scene.py: a depth frame covers the same view
    as its image); the colour is resized to the depth size. Returns the cleaned mesh (world space,
    per-vertex colours when colour was given) and stats {frames, ms_per_frame, vertices, faces,
    removed_faces}."""
    import time

    import cv2
    import open3d as o3d
    import open3d.core as o3c

    if options.voxel_size <= 0:
        raise ValueError("tsdf_fuse: voxel_size must be > 0 (0 = auto: resolve it with "
                         "auto_voxel_size first)")
    far = options.depth_max if options.depth_max > 0 else 1e6  # 0: no limit (the stage resolves it)
    dev = o3c.Device(options.device)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)), voxel_size=options.voxel_size,
        block_resolution=options.block_resolution, block_count=options.block_count, device=dev)
    n = skipped = 0
    t_int = 0.0
    it = frames
    if progress:
        from tqdm import tqdm
        it = tqdm(frames, total=total, desc="TSDF fusion", unit="frame", leave=False)
    for depth, cam, color in it:
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        if depth.ndim != 2:
            raise ValueError(f"depth must be (h, w), got {depth.shape}")
        h, w = depth.shape
        cam = cam if cam.size == (w, h) else cam.resized(w, h)
        if color is None:
            color = np.full((h, w, 3), 0.5, np.float32)
        elif color.shape[:2] != (h, w):
            color = cv2.resize(np.asarray(color, np.float32), (w, h), interpolation=cv2.INTER_AREA)
        if not np.any((depth > 0) & (depth < far)):
            skipped += 1  # nothing to integrate (all masked or out of range): open3d would abort
            continue
        t0 = time.perf_counter()
        d_img = o3d.t.geometry.Image(o3c.Tensor(depth, device=dev))
        c_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color, np.float32), device=dev))
        K = o3c.Tensor(cam.K, o3c.float64)
        T = o3c.Tensor(cam.cam_from_world, o3c.float64)
        try:
            coords = vbg.compute_unique_block_coordinates(d_img, K, T, 1.0, far,
                                                          options.trunc_voxels)
        except RuntimeError as e:
            # open3d aborts on a frame whose valid pixels touch no voxel block (a handful of
            # depths, e.g. an MVS view with almost no support): nothing to integrate, as above
            if "No block is touched" not in str(e):
                raise
            skipped += 1
            continue
        vbg.integrate(coords, d_img, c_img, K, T, 1.0, far, options.trunc_voxels)
        t_int += time.perf_counter() - t0
        n += 1
    stats = {"frames": n, "skipped_empty_frames": skipped, "ms_per_frame": 1000 * t_int / max(n, 1)}
    if n == 0:
        raise ValueError("tsdf_fuse: no frame has valid depth to fuse"
                         + (f" ({skipped} empty after masking)" if skipped else ""))
    tm = vbg.extract_triangle_mesh(weight_threshold=options.weight_threshold).to_legacy()
    # The VoxelBlockGrid's blocks live in a hash map filled by parallel threads, and marching
    # cubes emits vertices and triangles in that map's order, which depends on thread timing: the
    # same frames give the same surface (the values are deterministic) in a different vertex and
    # face order on every run, so global/mesh.ply's bytes changed and a forced rerun made every
    # later stage stale. Put it in canonical order before anything depends on the order (the
    # vertex-normal sums of clean_mesh included), and once more after the cleanup.
    verts, tris = np.asarray(tm.vertices), np.asarray(tm.triangles)
    cols = np.asarray(tm.vertex_colors) if tm.has_vertex_colors() else None
    vo, canon, _ = canonical_order(verts, tris, cols)
    mesh, _ = clean_mesh(verts[vo], canon, None if cols is None else cols[vo], options.min_component)
    mesh = canonical_mesh(mesh)
    removed = len(tris) - len(mesh.faces)
    stats.update(vertices=len(mesh.vertices), faces=len(mesh.faces), removed_faces=removed)
    return mesh, stats


def triangle_components(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of a triangle mesh, triangles joined where they share an edge (as
    open3d's cluster_connected_triangles, which walks the adjacency one triangle at a time: slow
    on a fused mesh of millions of faces). faces (F, 3) vertex indices. Returns (label (F,) int,
    face count of each label)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    f = np.asarray(faces, np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    nf = len(f)
    if nf == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = e[:, 0] * (int(f.max()) + 1) + e[:, 1]
    o = np.argsort(key, kind="stable")
    face, key = np.tile(np.arange(nf), 3)[o], key[o]
    shared = key[1:] == key[:-1]   # consecutive faces on one edge (also a non-manifold one)
    g = coo_matrix((np.ones(int(shared.sum()), np.int8), (face[:-1][shared], face[1:][shared])),
                   shape=(nf, nf))
    _, label = connected_components(g, directed=False)
    return label, np.bincount(label)


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None,
               min_component: float) -> tuple[Mesh, int]:
    """Remove connected components with fewer than `min_component` x total faces (fusion noise,
    floating blobs), unreferenced vertices and degenerate faces. Returns (mesh, faces removed)."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                  o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    if colors is not None:
        m.vertex_colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors, np.float64), 0, 1))
    nf = len(m.triangles)
    if nf:
        clusters, counts = triangle_components(faces)
        small = counts < max(1, min_component * nf)
        m.remove_triangles_by_mask(small[clusters])
        m.remove_degenerate_triangles()
        m.remove_unreferenced_vertices()
    m.compute_vertex_normals()
    cols = (np.asarray(m.vertex_colors) * 255).round().astype(np.uint8) if m.has_vertex_colors() else None
    return Mesh(np.asarray(m.vertices), np.asarray(m.triangles),
                normals=np.asarray(m.vertex_normals), colors=cols), nf - len(m.triangles)
