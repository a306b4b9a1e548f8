"""`ibr synth NAME OUT`: render a synthetic scene into an input folder with exact ground truth.

Layout written (see docs/SYNTHETIC.md):
  OUT/images/NNNN.png  cameras.json  sparse/0/*.txt  depth/NNNN.png  reflectors.json
  OUT/contact_sheet.png
  OUT/gt/scene.json  mesh.ply  test_cameras.json  flythrough_cameras.json
  OUT/gt/geom/NNNN.npz         exact z-depth (float32, m), normal (float16), material (int16)
  OUT/gt/I0/NNNN.png  gt/I1/NNNN.png  gt/beta/NNNN.png   Xu Eq. 3 layers, 8-bit linear
  OUT/gt/test/images/test_NNN.png  gt/test/geom/test_NNN.npz
  OUT/gt/flythrough/images/fly_NNNN.png
  OUT/gt/raytree/pair_NN.npz   Lochmann ray tree of one camera + GT render at a second camera

With `realistic` (a phone capture, `realistic.py`): OUT holds only images/ (sRGB photographs);
the exact cameras and reflectors move to gt/cameras.json and gt/reflectors.json, no depth/ or
sparse/ is written, gt/test/images are photographs of the same camera (their noiseless linear
renders in gt/test/linear/), and the contact sheet is gt/contact_sheet.png.
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene import Camera, cameras_to_json
from .scenes import SCENES

log = logging.getLogger("ibr_pipeline.synthetic")
FORMAT = "ibr_pipeline.synthetic/1"
# name: (width, height, views, test views, fly-through frames)
DEFAULTS = {"mirror_room": (640, 480, 120, 15, 48), "glass_room": (640, 480, 120, 15, 48),
            "curved": (640, 480, 120, 15, 48), "tiny": (160, 120, 8, 2, 4)}


@dataclass(frozen=True)
class SynthOptions:
    """Options of `ibr synth`; None means the scene's default (DEFAULTS)."""

    name: str
    seed: int = 0
    width: int | None = None
    height: int | None = None
    views: int | None = None
    test_views: int | None = None
    flythrough: int | None = None
    depth_scale: float = 0.5     # sensor depth resolution relative to colour
    gt_layers: bool = True       # write gt/I0, gt/I1, gt/beta
    raytree_pairs: int = 1
    jobs: int | None = None      # worker processes (default: min(2, cpu count))
    progress: bool = True
    # a simulated phone capture (realistic.CaptureModel; None = that model's default)
    realistic: bool = False
    noise_scale: float = 1.0     # sensor-noise standard deviations relative to the model's
    vignetting: float | None = None
    exposure_range: float | None = None
    distortion: float | None = None  # radial k1

    def capture_model(self):
        """The realistic.CaptureModel these options describe (noise already scaled)."""
        from ..config import ConfigError
        from .realistic import CaptureModel

        given = {f: getattr(self, k) for k, f in _MODEL_FIELDS.items() if getattr(self, k) is not None}
        model = CaptureModel(**given)
        try:
            model.validate()
        except ConfigError as e:
            flag = _FLAGS[{f: k for k, f in _MODEL_FIELDS.items()}[e.field]]
            raise InputError(f"{flag} {str(e).split(': ', 1)[1]}") from None
        return model.noise_scaled(self.noise_scale)

    def resolved(self) -> "SynthOptions":
        self.validate()
        w, h, v, t, f = DEFAULTS[self.name]
        pick = lambda x, d: d if x is None else x  # noqa: E731
        out = replace(self, width=pick(self.width, w), height=pick(self.height, h),
                      views=pick(self.views, v), test_views=pick(self.test_views, t),
                      flythrough=pick(self.flythrough, f),
                      jobs=pick(self.jobs, min(2, os.cpu_count() or 1)))
        if out.test_views > out.views:  # one held-out frame per gap between capture frames
            raise InputError(f"--test-views ({out.test_views}) must be <= --views ({out.views})")
        return out

    def validate(self) -> None:
        if self.name not in SCENES:
            raise InputError(f"NAME: unknown scene {self.name!r} (choose from {', '.join(SCENES)})")
        for flag, val, lo in (("--width", self.width, 16), ("--height", self.height, 16),
                              ("--views", self.views, 2), ("--test-views", self.test_views, 0),
                              ("--flythrough", self.flythrough, 0), ("--jobs", self.jobs, 1),
                              ("--raytree-pairs", self.raytree_pairs, 0)):
            if val is not None and (not isinstance(val, int) or val < lo):
                raise InputError(f"{flag} must be an integer >= {lo}, got {val!r}")
        if self.width is not None and self.width > 8192 or self.height is not None and self.height > 8192:
            raise InputError("--width/--height must be <= 8192")
        if not (0.05 <= self.depth_scale <= 1.0):
            raise InputError(f"--depth-scale must be in [0.05, 1], got {self.depth_scale}")
        if not (0 <= self.seed < 2 ** 32):
            raise InputError(f"--seed must be in [0, 2^32), got {self.seed}")
        self._validate_realistic()

    def _validate_realistic(self) -> None:
        if not self.realistic:
            for key in ("noise_scale",) + tuple(_MODEL_FIELDS):
                if getattr(self, key) != getattr(SynthOptions, key):
                    raise InputError(f"{_FLAGS[key]} needs --realistic")
            return
        if not (isinstance(self.noise_scale, (int, float)) and 0 <= self.noise_scale <= 10):
            raise InputError(f"--noise-scale must be a number in [0, 10], got {self.noise_scale!r}")
        model = self.capture_model()
        if model.distorted:  # a fold-over would only show at generation: check the real size
            from ..scene import Camera
            from .paths import HFOV_DEG
            from .realistic import check_distortion, corner_radius

            w, h = DEFAULTS[self.name][:2]
            w, h = self.width or w, self.height or h
            try:
                check_distortion(model.k1, model.k2,
                                 corner_radius(Camera.intrinsics_from_fov(w, h, HFOV_DEG), w, h))
            except ValueError as e:
                raise InputError(f"--distortion: {e}") from None


# SynthOptions field -> CaptureModel field, and the flag of each realistic option
_MODEL_FIELDS = {"vignetting": "vignetting", "exposure_range": "exposure_range", "distortion": "k1"}
_FLAGS = {"noise_scale": "--noise-scale", "vignetting": "--vignetting",
          "exposure_range": "--exposure-range", "distortion": "--distortion"}


def sensor_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Sensor resolution with exactly the colour aspect ratio (both sides divided by the same g)."""
    g = int(np.gcd(width, height))
    k = max(1, int(round(g * scale)))
    return int(width // g * k), int(height // g * k)


def _names(opts: SynthOptions) -> tuple[list[str], list[str], list[str]]:
    return ([f"{i:04d}.png" for i in range(opts.views)],
            [f"test_{i:03d}.png" for i in range(opts.test_views)],
            [f"fly_{i:04d}.png" for i in range(opts.flythrough)])


def _raytree_cameras(world, capture: list[Camera], n: int) -> list[tuple[Camera, Camera]]:
    """Pairs (old, new): the capture views looking most directly at a reflector, and a nearby
    new camera (8 cm right, 3 cm up, 3 degrees of yaw) to warp to."""
    targets = [np.mean(r["polygon"], axis=0) for r in world.reflectors] + \
              [np.asarray(o["center"]) for o in world.objects]
    if world.objects:  # prefer curved objects where present
        targets = targets[len(world.reflectors):] + targets[:len(world.reflectors)]
    pairs, used = [], set()
    for k in range(n):
        tgt = targets[k % len(targets)]
        score = [np.dot(c.viewing_direction, (tgt - c.center) / np.linalg.norm(tgt - c.center))
                 if i not in used else -2 for i, c in enumerate(capture)]
        i = int(np.argmax(score))
        used.add(i)
        old = capture[i]
        a = np.radians(3.0)
        Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        T = old.cam_from_world.copy()
        T[:3, :3] = Ry @ T[:3, :3]
        center = old.center + 0.08 * old.R[0] - 0.03 * old.R[1]
        T[:3, 3] = -T[:3, :3] @ center
        pairs.append((old, Camera(old.K, T, old.width, old.height)))
    return pairs


def _material_colors(world) -> np.ndarray:
    cols = []
    for m in world.soup.materials:
        if m.texture is not None:
            c = 0.5 * (np.asarray(m.texture.color_a) + np.asarray(m.texture.color_b))
        else:
            c = {"mirror": (0.8, 0.8, 0.85), "glass_pane": (0.7, 0.85, 0.9)}.get(m.kind, (0.8, 0.9, 0.9))
        cols.append(np.asarray(c))
    return np.clip(np.rint(np.array(cols) * 255), 0, 255).astype(np.uint8)


def _scene_json(world, opts: SynthOptions, sensor_wh) -> dict:
    # the realistic fields are left out of an ideal scene's record, which stays what it always was
    skip = {"progress", "jobs"} | (set() if opts.realistic else {"realistic", *_FLAGS})
    return {
        "format": FORMAT, "scene": opts.name, "seed": opts.seed,
        "options": {k: v for k, v in asdict(opts).items() if k not in skip},
        "world_frame": "right-handed, +z up, floor at z = 0, metres",
        "image_encoding": "srgb" if opts.realistic else "linear",
        "image_size": [opts.width, opts.height],
        "depth_sensor_size": None if opts.realistic else list(sensor_wh),
        "materials": [{"index": i, "name": m.name, "kind": m.kind, "kr": m.kr,
                       "ior": m.ior if m.kind in ("glass_pane", "dielectric") else None,
                       "tint": list(m.tint)} for i, m in enumerate(world.soup.materials)],
        "lights": [{"position": p.tolist(), "power": float(q)}
                   for p, q in zip(world.lights, world.light_power)],
        "ambient": world.ambient, "objects": list(world.objects),
        "reflectors": list(world.reflectors),
    }


# --- realistic captures ---------------------------------------------------------------------
EXPOSURE_SEED, CAPTURE_NOISE_SEED, TEST_NOISE_SEED = 404, 405, 406


def held_out_steps(n_test: int, n_capture: int) -> np.ndarray:
    """The fractional capture-frame indices at which paths.test_path takes its held-out views."""
    return np.floor(np.arange(n_test) * n_capture / max(n_test, 1)) + 0.5


def _exposure(opts: SynthOptions, model, cap_names, test_names) -> dict[str, dict[str, float]]:
    """Auto-exposure gain of every photograph. A held-out view is a frame of the same walk, so it
    gets the capture's smooth gain curve at its place along the loop (what the captures on either
    side of it got, interpolated)."""
    from .realistic import exposure_gains

    phase = np.concatenate([np.arange(opts.views), held_out_steps(opts.test_views, opts.views)]) / opts.views
    g = exposure_gains(phase, model.exposure_range, np.random.default_rng([opts.seed, EXPOSURE_SEED]))
    return {"capture": dict(zip(cap_names, g[:opts.views].tolist())),
            "test": dict(zip(test_names, g[opts.views:].tolist()))}


def _realistic_task(args) -> dict:
    """One job of a realistic scene: capture and test views are photographed (tasks._run renders
    the fly-through and the ray trees, which stay exact)."""
    from ..io.images import write_image
    from . import tasks
    from .realistic import degrade, distortion_padding
    from .writers import GEOM_COMPRESSION, compose_8bit, save_npz

    kind, i, name, cam, out, seed, gt_layers, model, gain = args
    if kind not in ("capture", "test"):
        return tasks._run((kind, i, name, cam, out, seed, None, gt_layers))
    out, stem = Path(out), Path(name).stem
    W, H = cam.width, cam.height
    px, py = distortion_padding(cam.K, W, H, model.k1, model.k2) if model.distorted else (0, 0)
    K = cam.K.copy()
    K[0, 2] += px
    K[1, 2] += py
    shot = Camera(K, cam.cam_from_world, W + 2 * px, H + 2 * py)  # covers what the lens pulls in
    r = tasks._TRACER.trace(shot)
    gt = {k: r[k][py:py + H, px:px + W] for k in ("I0", "I1", "beta", "depth", "normal", "material")}
    q0, q1, qb, img = compose_8bit(gt["I0"], gt["I1"], gt["beta"])
    eq3 = float(np.abs(img / 255.0 - (q0 / 255.0 + (qb / 255.0)[..., None] * q1 / 255.0)).max())
    rng = np.random.default_rng([seed, CAPTURE_NOISE_SEED if kind == "capture" else TEST_NOISE_SEED, i])
    photo = degrade(r["image"], gain, model, rng, K=shot.K, K_out=cam.K, size=(W, H))
    stats = {"kind": kind, "eq3_err": eq3, "reflective": float((gt["beta"] > 0).mean()),
             "saturated": float((photo == 255).any(axis=2).mean())}
    if kind == "capture":
        write_image(out / "images" / name, photo)
        save_npz(out / "gt" / "geom" / f"{stem}.npz", GEOM_COMPRESSION, **tasks._geom(gt))
        if gt_layers:
            write_image(out / "gt" / "I0" / f"{stem}.png", q0)
            write_image(out / "gt" / "I1" / f"{stem}.png", q1)
            write_image(out / "gt" / "beta" / f"{stem}.png", qb)
    else:
        write_image(out / "gt" / "test" / "images" / name, photo)
        write_image(out / "gt" / "test" / "linear" / name, img)
        save_npz(out / "gt" / "test" / "geom" / f"{stem}.npz", GEOM_COMPRESSION, **tasks._geom(gt))
    return stats


def _run_realistic_jobs(opts: SynthOptions, out: Path, jobs: list[tuple], model,
                        gains: dict[str, dict[str, float]]) -> list[dict]:
    """tasks.run_jobs with `_realistic_task` (every job a pure function of its arguments)."""
    from . import tasks

    args = [(k, i, n, c, str(out), opts.seed, opts.gt_layers, model, gains.get(k, {}).get(n, 1.0))
            for k, i, n, c in jobs]
    return tasks.run_tasks(opts, _realistic_task, args, f"synth {opts.name} (realistic)")


def _model_record(model, opts: SynthOptions, gains) -> dict:
    """What gt/scene.json says about the simulated camera (enough to undo or score it)."""
    m = model.to_dict()
    m["full_well"] = None if not np.isfinite(model.full_well) else m["full_well"]  # None: no shot noise
    return {
        "realistic": True, "model": m, "noise_scale": opts.noise_scale,
        "order": "distortion, vignetting, exposure gain, Poisson-Gaussian noise, clip to [0, 1], "
                 "sRGB (IEC 61966-2-1), 8-bit",
        "photographs": ["images/", "gt/test/images/"],
        "linear": ["gt/test/linear/", "gt/I0/", "gt/I1/", "gt/flythrough/images/",
                   "gt/raytree/"],
        "distortion_model": "x_d = x_u (1 + k1 r^2 + k2 r^4) on normalised coordinates "
                            "(COLMAP RADIAL); gt/cameras.json and every gt/ raster are of the "
                            "undistorted pinhole camera",
        "vignetting_model": "(1 + c rho^2)^-2, rho = 1 at the corners, c = (1 - a)^-1/2 - 1",
        "noise_seeds": f"numpy default_rng([seed, {CAPTURE_NOISE_SEED}, view]) for capture view "
                       f"`view`, [seed, {TEST_NOISE_SEED}, j] for test view j",
        "exposure_gain": gains,
    }


def generate(opts: SynthOptions, out: Path) -> dict:
    """Render scene `opts.name` into folder `out`; returns a summary (also in gt/scene.json)."""
    from ..io.colmap import write_colmap_model
    from . import tasks
    from .contact import contact_sheet
    from .paths import capture_path, flythrough_path, test_path
    from .scenes import build_world
    from .writers import write_ply

    opts = opts.resolved()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"OUT: {out} exists and is not a folder")
    if opts.realistic:  # left-overs of an ideal scene would hand the pipeline exact poses and depth
        stale = [n for n in ("cameras.json", "sparse", "depth", "reflectors.json") if (out / n).exists()]
        if stale:
            raise InputError(f"OUT: {out} holds {', '.join(stale)} of an earlier generation; "
                             "remove the folder before generating a realistic capture")
    out.mkdir(parents=True, exist_ok=True)
    world = build_world(opts.name, opts.seed)
    W, H = opts.width, opts.height
    cap = capture_path(world, opts.views, W, H, opts.seed)
    test = test_path(world, opts.test_views, W, H, opts.seed, opts.views)
    fly = flythrough_path(world, opts.flythrough, W, H)
    cap_names, test_names, fly_names = _names(opts)
    sw, sh = sensor_size(W, H, opts.depth_scale)
    log.info("scene %s seed %d: %d views + %d test + %d fly-through at %dx%d, %s",
             opts.name, opts.seed, opts.views, opts.test_views, opts.flythrough, W, H,
             "realistic capture" if opts.realistic else f"depth {sw}x{sh}")

    cams = dict(zip(cap_names, cap))
    reflectors = json.dumps({"reflectors": list(world.reflectors)}, indent=1)
    gt = out / "gt"
    if opts.realistic:  # the pipeline must find poses and reflectors itself, as with photos
        gt.mkdir(exist_ok=True)
        (gt / "cameras.json").write_text(cameras_to_json(cams))
        (gt / "reflectors.json").write_text(reflectors)
    else:
        (out / "cameras.json").write_text(cameras_to_json(cams))
        write_colmap_model(cams, out / "sparse" / "0", text=True)
        (out / "reflectors.json").write_text(reflectors)
        gt.mkdir(exist_ok=True)
    (gt / "test_cameras.json").write_text(cameras_to_json(dict(zip(test_names, test))))
    (gt / "flythrough_cameras.json").write_text(cameras_to_json(dict(zip(fly_names, fly))))
    write_ply(gt / "mesh.ply", world.soup, _material_colors(world))

    jobs = [("capture", i, n, c) for i, (n, c) in enumerate(zip(cap_names, cap))]
    jobs += [("test", i, n, c) for i, (n, c) in enumerate(zip(test_names, test))]
    jobs += [("fly", i, n, c) for i, (n, c) in enumerate(zip(fly_names, fly))]
    pairs = _raytree_cameras(world, cap, opts.raytree_pairs)
    jobs += [("raytree", k, f"pair_{k:02d}.npz", p) for k, p in enumerate(pairs)]
    if opts.realistic:
        model = opts.capture_model()
        gains = _exposure(opts, model, cap_names, test_names)
        stats = _run_realistic_jobs(opts, out, jobs, model, gains)
    else:
        stats = tasks.run_jobs(opts, out, jobs, (sw, sh))

    eq3 = max((s.get("eq3_err", 0.0) for s in stats), default=0.0)
    summary = _scene_json(world, opts, (sw, sh))
    summary["raytree_pairs"] = [{"file": f"gt/raytree/pair_{k:02d}.npz",
                                 "old_view": cap_names[[c is p[0] for c in cap].index(True)]}
                                for k, p in enumerate(pairs)]
    summary["checks"] = {"eq3_max_abs_error_8bit": eq3,
                         "raytree_max_abs_error": max((s.get("raytree_err", 0.0) for s in stats),
                                                      default=0.0),
                         "reflective_pixel_fraction": float(np.mean(
                             [s["reflective"] for s in stats if s["kind"] == "capture"]))}
    if opts.realistic:
        summary["checks"]["saturated_pixel_fraction"] = float(np.mean(
            [s["saturated"] for s in stats if s["kind"] == "capture"]))
        summary["capture_model"] = _model_record(model, opts, gains)
    (gt / "scene.json").write_text(json.dumps(summary, indent=1))
    contact_sheet(out, (gt if opts.realistic else out) / "contact_sheet.png")
    log.info("wrote %s (Eq. 3 max error %.2f/255)", out, eq3 * 255)
    return summary
