"""Structure from motion with pycolmap (Xu et al. §4.1 computes poses with RealityCapture; we use
COLMAP: Schönberger & Frahm 2016). SIFT extraction (ALIKED aborts the process, docs/DESIGN.md), sequential
or exhaustive matching, incremental mapping; known intrinsics are fixed when the input gives them.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from ..scene import Camera

log = logging.getLogger("ibr_pipeline.sfm")


@dataclass
class SfMResult:
    cameras: dict[str, Camera]      # registered views, our conventions, SfM frame and units
    reconstruction: object          # the pycolmap.Reconstruction (largest model)
    stats: dict


def _camera_from_image(image) -> Camera:
    from ..io.colmap import _camera_K
    T = np.eye(4)
    T[:3, :] = image.cam_from_world().matrix()
    cam = image.camera
    return Camera(_camera_K(cam), T, cam.width, cam.height)


def run_sfm(image_dir: Path, names: Sequence[str], work_dir: Path, matching: str = "sequential",
            intrinsics: Camera | None = None, overlap: int = 10, threads: int = 1,
            max_image_size: int = 3200, init_min_inliers: int = 50, abs_pose_min_inliers: int = 15,
            init_min_tri_angle: float = 8.0, peak_threshold: float | None = None,
            close_loop: bool = True, single_camera: bool = True,
            camera_model: str = "SIMPLE_PINHOLE") -> SfMResult:
    """Run SIFT + matching + incremental mapping on `names` (paths relative to `image_dir`).

    intrinsics: one Camera whose K is shared by all images and kept fixed (PINHOLE); None lets
    COLMAP estimate a SIMPLE_PINHOLE focal length: one shared camera (`single_camera`), else
    one per image (images of different sizes or cameras). `camera_model` is the COLMAP model then
    estimated: with a distorted one (SIMPLE_RADIAL, ...) `cameras` hold only the pinhole part and
    the reconstruction the lens; the caller undistorts. Returns the largest
    reconstruction; work_dir receives database.db and the mapper's models.

    Mapper thresholds are relaxed from COLMAP's defaults (initial pair 100 inliers and 16°,
    image registration 30 inliers) for sparse or low-resolution captures, whose neighbouring
    views share few SIFT matches: `init_min_inliers`, `abs_pose_min_inliers`, `init_min_tri_angle`
    (degrees). `close_loop` (sequential only): also match the first and the last images whose
    circular index distance is <= overlap (a capture walking round a room ends where it started; a
    loop closure without a vocabulary tree, overlap²/2 extra pairs). Matching is guided (epipolar-constrained second pass), and with known intrinsics
    neither bundle adjustment nor absolute-pose estimation refines them.
    """
    import pycolmap

    if matching not in ("sequential", "exhaustive"):
        raise ValueError(f"matching must be 'sequential' or 'exhaustive', got {matching!r}")
    # COLMAP's per-image glog lines drown the progress output
    # (errors still show; the summary is logged by us, below)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, 2)
    try:
        return _run_sfm(pycolmap, image_dir, names, work_dir, matching, intrinsics, overlap, threads,
                        max_image_size, init_min_inliers, abs_pose_min_inliers, init_min_tri_angle,
                        peak_threshold, close_loop, single_camera, camera_model)
    finally:
        pycolmap.logging.minloglevel = level


def _run_sfm(pycolmap, image_dir, names, work_dir, matching, intrinsics, overlap, threads,
             max_image_size, init_min_inliers, abs_pose_min_inliers, init_min_tri_angle,
             peak_threshold, close_loop, single_camera=True,
             camera_model="SIMPLE_PINHOLE") -> SfMResult:
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    if db.exists():
        db.unlink()
    stats: dict = {"images": len(names), "matching": matching}
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is not None:
        K = intrinsics.K
        reader.camera_model = "PINHOLE"
        # COLMAP's pixel-centre convention is (0.5, 0.5) (scene.py)
        reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    else:
        reader.camera_model = camera_model
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = threads
    extract.max_image_size = max_image_size
    if peak_threshold is not None:  # DoG contrast threshold (COLMAP 0.0067): lower = more features
        extract.sift.peak_threshold = peak_threshold
    extract.use_gpu = False
    t0, c0 = time.perf_counter(), time.process_time()
    pycolmap.extract_features(db, image_dir, image_names=list(names),
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera
                              else pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                              extraction_options=extract, device=pycolmap.Device.cpu)
    stats["extract_s"], stats["extract_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = threads
    mopt.use_gpu = False
    mopt.guided_matching = True
    t0, c0 = time.perf_counter(), time.process_time()
    if matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pycolmap.match_sequential(db, matching_options=mopt, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
        wrap = loop_pairs(names, overlap) if close_loop else []
        if wrap:
            pairs = work_dir / "loop_pairs.txt"
            pairs.write_text("".join(f"{x} {y}\n" for x, y in wrap))
            imported = pycolmap.ImportedPairingOptions()
            imported.match_list_path = str(pairs)
            pycolmap.match_image_pairs(db, matching_options=mopt, pairing_options=imported,
                                       device=pycolmap.Device.cpu)
        stats["loop_pairs"] = len(wrap)
    else:
        pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
    stats["match_s"], stats["match_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.mapper.init_min_num_inliers = init_min_inliers
    opts.mapper.abs_pose_min_num_inliers = abs_pose_min_inliers
    opts.mapper.init_min_tri_angle = init_min_tri_angle
    if intrinsics is not None:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    t0, c0 = time.perf_counter(), time.process_time()
    models = pycolmap.incremental_mapping(db, image_dir, work_dir / "models", opts)
    stats["map_s"], stats["map_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    if not models:
        raise InputError(f"{image_dir}: structure from motion registered no images "
                         f"(too little texture or overlap?)")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    cams = {img.name: _camera_from_image(img) for img in rec.images.values() if img.has_pose}
    stats.update(registered=len(cams), models=len(models),
                 model_sizes=sorted((m.num_reg_images() for m in models.values()), reverse=True),
                 points=rec.num_points3D(),
                 reprojection_error_px=float(rec.compute_mean_reprojection_error()))
    log.info("sfm: %d/%d images registered in %d model(s), %d points, %.2f px reprojection error, "
             "%.1f s", len(cams), len(names), len(models), stats["points"],
             stats["reprojection_error_px"], stats["extract_s"] + stats["match_s"] + stats["map_s"])
    return SfMResult(cams, rec, stats)


def loop_pairs(names: Sequence[str], overlap: int) -> list[tuple[str, str]]:
    """Pairs of a closed sequence that sequential matching misses: last and first images whose
    circular index distance is <= overlap (and whose linear distance exceeds it)."""
    n = len(names)
    return [(names[n - a], names[b]) for a in range(1, overlap + 1) for b in range(overlap + 1 - a)
            if n - a > b + overlap]


def keypoint_depths(rec, name: str) -> tuple[np.ndarray, np.ndarray]:
    """For image `name` of a pycolmap reconstruction: (N, 2) keypoint pixels (our convention) of
    its triangulated observations and their SfM z-depths (N,)."""
    image = next(i for i in rec.images.values() if i.name == name)
    T = image.cam_from_world().matrix()
    uv, z = [], []
    for p2d in image.points2D:
        if not p2d.has_point3D():
            continue
        X = rec.points3D[p2d.point3D_id].xyz
        uv.append(np.asarray(p2d.xy) - 0.5)
        z.append(float(T[2, :3] @ X + T[2, 3]))
    return np.array(uv).reshape(-1, 2), np.array(z)


def sparse_points(rec) -> np.ndarray:
    """(N, 3) 3D points of a reconstruction."""
    pts = [p.xyz for p in rec.points3D.values()]
    return np.array(pts).reshape(-1, 3)
