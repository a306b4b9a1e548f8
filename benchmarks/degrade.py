"""Degrade one input of a synthetic scene folder at a time, for the stability sweeps (stability.py).

`degrade_input(src, dst, kind, amount, seed)` copies the input folder `src` to `dst` (images,
depth, cameras, reflectors, gt) and applies one degradation. Kinds and the unit of `amount`:
  pose_rot      camera rotation noise, degrees (random axis per view)
  pose_trans    camera-centre noise, metres (random direction per view)
  depth_noise   extra Gaussian noise on the depth frames, metres (sigma)
  depth_holes   fraction of depth pixels set to 0 (in 8x8 blocks, like sensor dropouts)
  views         fraction of capture views kept (evenly spaced along the path)
  textureless   fraction of the wall texture contrast removed (1 = flat walls), in capture and
                held-out ground-truth images alike, using the GT material of every pixel
  reflector_missing  1 = reflectors.json emptied (the pipeline must find the mirror or fall back)
  reflector_wrong    plane offset in metres along its normal (and the same in radians of tilt)
  far_camera    held-out cameras pulled back by this many metres along their viewing direction;
                their ground truth is re-rendered with the synthetic ray tracer
Poses are rewritten into cameras.json and the COLMAP model is dropped, so the pipeline reads the
noisy poses. Everything is seeded: a degradation is reproducible.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ibr_pipeline.errors import InputError

KINDS = ("pose_rot", "pose_trans", "depth_noise", "depth_holes", "views", "textureless",
         "reflector_missing", "reflector_wrong", "far_camera")


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    import cv2
    return cv2.Rodrigues((axis / np.linalg.norm(axis) * angle).reshape(3, 1))[0]


def _perturb_poses(dst: Path, kind: str, amount: float, rng) -> None:
    from ibr_pipeline.scene import Camera, cameras_from_json, cameras_to_json
    cams = cameras_from_json(dst / "cameras.json")
    out = {}
    for name, cam in cams.items():
        T = cam.cam_from_world.copy()
        if kind == "pose_rot":
            T[:3, :3] = _rot(rng.normal(size=3), np.deg2rad(amount)) @ T[:3, :3]
            T[:3, 3] = -T[:3, :3] @ cam.center  # rotate about the camera centre
        else:
            d = rng.normal(size=3)
            c = cam.center + amount * d / np.linalg.norm(d)
            T[:3, 3] = -T[:3, :3] @ c
        out[name] = Camera(cam.K, T, cam.width, cam.height)
    (dst / "cameras.json").write_text(cameras_to_json(out))
    shutil.rmtree(dst / "sparse", ignore_errors=True)


def _degrade_depth(dst: Path, kind: str, amount: float, rng) -> None:
    from ibr_pipeline.io.images import read_depth_png, write_depth_png
    for p in sorted((dst / "depth").glob("*.png")):
        d = read_depth_png(p)
        valid = d > 0
        if kind == "depth_noise":
            d = np.where(valid, np.clip(d + rng.normal(0, amount, d.shape), 0.01, None), 0)
        else:
            h, w = d.shape
            blocks = rng.random(((h + 7) // 8, (w + 7) // 8)) < amount
            d = np.where(np.kron(blocks, np.ones((8, 8)))[:h, :w] > 0, 0, d)
        write_depth_png(p, d.astype(np.float32))


def _keep_views(dst: Path, fraction: float) -> None:
    from ibr_pipeline.scene import cameras_from_json, cameras_to_json
    cams = cameras_from_json(dst / "cameras.json")
    names = sorted(cams)
    n = max(2, int(round(len(names) * fraction)))
    keep = {names[int(i)] for i in np.linspace(0, len(names) - 1, n).round()}
    for name in names:
        if name not in keep:
            (dst / "images" / name).unlink(missing_ok=True)
            (dst / "depth" / f"{Path(name).stem}.png").unlink(missing_ok=True)
    (dst / "cameras.json").write_text(cameras_to_json({k: cams[k] for k in names if k in keep}))
    shutil.rmtree(dst / "sparse", ignore_errors=True)


def _flatten_walls(dst: Path, amount: float) -> None:
    from ibr_pipeline.io.images import read_image, write_image
    mats = json.loads((dst / "gt" / "scene.json").read_text())["materials"]
    walls = [m["index"] for m in mats if m["name"].startswith("wall")]
    pairs = [(p, dst / "gt" / "geom" / f"{p.stem}.npz") for p in (dst / "images").glob("*.png")]
    pairs += [(p, dst / "gt" / "test" / "geom" / f"{p.stem}.npz")
              for p in (dst / "gt" / "test" / "images").glob("*.png")]
    for img_path, geom in pairs:
        img = read_image(img_path)
        with np.load(geom) as z:
            m = np.isin(z["material"], walls)
        if m.any():
            mean = img[m].mean(axis=0)
            img[m] = (1 - amount) * img[m] + amount * mean
            write_image(img_path, img)


def _reflectors(dst: Path, kind: str, amount: float) -> None:
    path = dst / "reflectors.json"
    if not path.is_file():
        return
    d = json.loads(path.read_text())
    if kind == "reflector_missing":
        d["reflectors"] = []
    else:
        for r in d["reflectors"]:
            n = np.array(r["plane"][:3], float)
            axis = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0, 0])
            R = _rot(axis, amount)
            poly = np.array(r["polygon"], float)
            centre = poly.mean(axis=0)
            # the same reflector, shifted by `amount` m along its normal and tilted by `amount` rad
            # about its centre: a plausible user error, with its outline moved along
            poly = (poly - centre) @ R.T + centre + amount * n
            n2 = R @ n
            r["plane"] = [*n2.tolist(), float(-n2 @ poly.mean(axis=0))]
            r["polygon"] = poly.tolist()
            r.pop("masks", None)
    path.write_text(json.dumps(d, indent=1))


def _far_cameras(dst: Path, amount: float, seed: int) -> None:
    from ibr_pipeline.io.images import write_image
    from ibr_pipeline.scene import Camera, cameras_from_json, cameras_to_json
    from ibr_pipeline.synthetic.scenes import build_world
    from ibr_pipeline.synthetic.tracer import Tracer
    from ibr_pipeline.synthetic.writers import compose_8bit, round_depth, save_npz
    gt = json.loads((dst / "gt" / "scene.json").read_text())
    cams = cameras_from_json(dst / "gt" / "test_cameras.json")
    tracer = Tracer(build_world(gt["scene"], gt["seed"]))
    moved = {}
    for name, cam in cams.items():
        T = cam.cam_from_world.copy()
        c = cam.center - amount * cam.viewing_direction
        T[:3, 3] = -T[:3, :3] @ c
        moved[name] = Camera(cam.K, T, cam.width, cam.height)
        r = tracer.trace(moved[name])
        write_image(dst / "gt" / "test" / "images" / name, compose_8bit(r["I0"], r["I1"], r["beta"])[3])
        # the fields and dtypes `ibr synth` writes to gt/test/geom
        save_npz(dst / "gt" / "test" / "geom" / f"{Path(name).stem}.npz", "lzma",
                 depth=round_depth(r["depth"]), normal=r["normal"].astype(np.float16),
                 material=r["material"].astype(np.int16))
    (dst / "gt" / "test_cameras.json").write_text(cameras_to_json(moved))


def degrade_input(src: Path, dst: Path, kind: str, amount: float, seed: int = 0) -> Path:
    """Copy input folder `src` to `dst` and apply one degradation; returns `dst`."""
    if kind not in KINDS:
        raise InputError(f"degrade: unknown kind {kind!r} (one of {', '.join(KINDS)})")
    if not np.isfinite(amount) or amount < 0:
        raise InputError(f"degrade: amount {amount!r} must be a finite number >= 0")
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    rng = np.random.default_rng([seed, KINDS.index(kind), int(amount * 1000)])
    if not (dst / "cameras.json").is_file() and kind in ("pose_rot", "pose_trans", "views"):
        raise InputError(f"{src}: degrade {kind} needs cameras.json")
    if kind in ("pose_rot", "pose_trans"):
        _perturb_poses(dst, kind, amount, rng)
    elif kind in ("depth_noise", "depth_holes"):
        _degrade_depth(dst, kind, amount, rng)
    elif kind == "views":
        _keep_views(dst, amount)
    elif kind == "textureless":
        _flatten_walls(dst, amount)
    elif kind in ("reflector_missing", "reflector_wrong"):
        _reflectors(dst, kind, amount)
    else:
        _far_cameras(dst, amount, seed)
    return dst
