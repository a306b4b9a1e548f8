"""Similarity alignment and pose-error metrics (Xu et al. §4.1: RGB-D scans "registered ... using
the iterative closest point (ICP) method"; SfM is up to scale, so it is brought to metres by a
Sim(3) estimated from the depth frames).

* `umeyama`: closed-form least-squares Sim(3) between corresponding points (Umeyama 1991).
* `transform_camera`, `transform_reflector`: a camera / reflector plane under a Sim(3) of the world.
* `depth_scale`: robust metric scale of an SfM model from depth measured at its keypoints.
* `icp_refine`: open3d point-to-point ICP with scale, to refine an initial Sim(3).
* `pose_errors`: rotation / camera-centre errors after aligning estimated cameras to the truth.
"""
from __future__ import annotations

import math

import numpy as np

from ..scene import Camera


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991, Eqs. 40-42)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two (N >= 3, 3) arrays of equal shape, got {src.shape}, {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def transform_camera(cam: Camera, s: float, R: np.ndarray, t: np.ndarray) -> Camera:
    """The camera after mapping the world by x' = s R x + t (the image is unchanged)."""
    Rc, tc = cam.R, cam.t
    # x_cam = Rc x + tc = Rc (R^T (x' - t) / s) + tc  ->  scale the camera frame back to metres
    R_new = Rc @ R.T
    t_new = s * tc - R_new @ t
    T = np.eye(4)
    T[:3, :3] = R_new
    T[:3, 3] = t_new
    return Camera(cam.K, T, cam.width, cam.height)


def transform_reflector(refl, s: float, R: np.ndarray, t: np.ndarray):
    """The reflector after mapping the world by x' = s R x + t: n' = R n, d' = s d - n' . t
    (from n . x + d = 0 with x = R^T (x' - t) / s); the polygon moves with the world. A
    reflector given by its outline in a photograph has no plane yet: pixels need no mapping."""
    import dataclasses
    if refl.plane is None:
        return refl
    n = np.asarray(R, np.float64) @ np.asarray(refl.plane[:3], np.float64)
    d = s * float(refl.plane[3]) - float(n @ np.asarray(t, np.float64))
    poly = None if refl.polygon is None else tuple(
        tuple(float(x) for x in s * np.asarray(R) @ np.asarray(p, np.float64) + t) for p in refl.polygon)
    return dataclasses.replace(refl, plane=(*map(float, n), d), polygon=poly)


def depth_scale(sfm_depths: np.ndarray, sensor_depths: np.ndarray) -> float:
    """Robust metric scale: median of sensor / SfM z-depth over keypoints with both (> 0)."""
    a, b = np.asarray(sfm_depths, np.float64), np.asarray(sensor_depths, np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"need two (N,) arrays, got {a.shape}, {b.shape}")
    ok = (a > 0) & (b > 0) & np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        raise ValueError(f"only {int(ok.sum())} keypoints with both SfM and sensor depth")
    return float(np.median(b[ok] / a[ok]))


def icp_refine(source: np.ndarray, target: np.ndarray, init: np.ndarray | None = None,
               max_distance: float = 0.05, with_scale: bool = True, iterations: int = 30
               ) -> tuple[np.ndarray, float, float]:
    """Refine a 4x4 similarity mapping `source` points onto `target` by point-to-point ICP
    (open3d). Returns (T, fitness, inlier RMSE)."""
    import open3d as o3d

    for name, p in (("source", source), ("target", target)):
        if np.asarray(p).ndim != 2 or np.asarray(p).shape[1] != 3:
            raise ValueError(f"{name} must be (N, 3), got {np.asarray(p).shape}")
    pc = lambda p: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, np.float64)))  # noqa: E731
    est = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=with_scale)
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    res = o3d.pipelines.registration.registration_icp(
        pc(source), pc(target), max_distance, np.eye(4) if init is None else init, est, crit)
    return np.asarray(res.transformation), float(res.fitness), float(res.inlier_rmse)


def rotation_error_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    c = (np.trace(R1 @ R2.T) - 1) / 2
    return math.degrees(math.acos(float(np.clip(c, -1, 1))))


def pose_errors(estimated: dict[str, Camera], truth: dict[str, Camera]) -> dict:
    """Align estimated camera centres to the true ones (Sim(3), Umeyama) and report
    rotation / centre errors over the common views: median, mean, max; plus the Sim(3) scale."""
    names = sorted(set(estimated) & set(truth))
    if len(names) < 3:
        raise ValueError(f"need >= 3 common views to align, got {len(names)}")
    ce = np.array([estimated[n].center for n in names])
    ct = np.array([truth[n].center for n in names])
    s, R, t = umeyama(ce, ct)
    aligned = {n: transform_camera(estimated[n], s, R, t) for n in names}
    rot = np.array([rotation_error_deg(aligned[n].R, truth[n].R) for n in names])
    pos = np.array([np.linalg.norm(aligned[n].center - truth[n].center) for n in names])
    # The rotation of a centres-only Sim(3) inherits the centre noise (8 mm on a 1 m loop tilts it
    # by ~0.4°), so also: the frame rotation from the orientations themselves (chordal L2 mean of
    # R_t^T R_e, Hartley et al. 2013), and the frame-free error of consecutive relative rotations.
    U, _, Vt = np.linalg.svd(sum(truth[n].R.T @ estimated[n].R for n in names))
    Ra = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    rot_o = np.array([rotation_error_deg(estimated[n].R @ Ra.T, truth[n].R) for n in names])
    rel = np.array([rotation_error_deg(estimated[a].R @ estimated[b].R.T, truth[a].R @ truth[b].R.T)
                    for a, b in zip(names, names[1:])])
    stat = lambda x: {"median": float(np.median(x)), "mean": float(x.mean()), "max": float(x.max())}  # noqa: E731
    return {"views": len(names), "scale": s, "rotation_deg": stat(rot), "center_m": stat(pos),
            "rotation_deg_orientation_aligned": stat(rot_o), "relative_rotation_deg_consecutive": stat(rel)}
