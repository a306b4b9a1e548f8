"""Stage `ingest`: read the input folder in any layout we know, prepare what later stages read,
check every file, write scene.json.

The layout is detected and read by io/inputs.py (COLMAP, COLMAP undistorter output, nerfstudio,
LLFF, TUM RGB-D, ScanNet, a video, cameras.json, a bare folder of images) and logged by name.
Frames that are not already pinhole, upright 8-bit images with millimetre depth are prepared into
`ingest/` of the workspace (io/prepare.py: undistortion with pycolmap's camera models, EXIF
orientation, video frames, depth units); the input folder is never written.

Bad input is caught here, before any expensive stage: an image that does not decode, a camera with
NaNs, a depth frame whose aspect ratio differs from its image, a missing reflector mask. Each raises
InputError naming the file, and scene.json is not written.
"""
from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

from .. import layout as L
from ..config import StageConfig, param
from ..errors import InputError, confined
from ..runner import Stage, StageContext
from ..scene import Scene, View

log = logging.getLogger("ibr_pipeline.ingest")


@dataclass(frozen=True)
class IngestConfig(StageConfig):
    min_views: int = param(2, "fewer images than this is an error", min=1)
    check_pixels: bool = param(True, "decode every image fully (catches truncated files early)")
    colour: str = param("auto", "the images' transfer function: srgb (photographs), linear (our "
                        "synthetic scenes), auto = what the input says (gt/scene.json, the format), "
                        "else srgb", choices=("auto", "srgb", "linear"))
    video_frames: int = param(150, "a video input: this many frames are kept, the sharpest of "
                              "equal windows", min=2, max=100000)


def inputs(ctx: StageContext) -> list[str]:
    from ..io.inputs import input_files
    return [ctx.ws.key(p) for p in input_files(ctx.ws.input_root)]


def outputs(ctx: StageContext) -> list[str]:
    """scene.json and every file it points to under ingest/ (none when nothing was prepared)."""
    keys = [L.SCENE]
    p = ctx.ws.path(L.SCENE)
    if p.is_file():
        try:
            d = json.loads(p.read_text())
            keys += sorted({k for v in d.get("views", []) for k in (v.get("image"), v.get("depth"))
                            if isinstance(k, str) and k.startswith("ingest/")})
            sparse = d.get("sparse")
            if isinstance(sparse, str) and sparse.startswith("ingest/"):
                keys += [ctx.ws.key(f) for f in sorted(ctx.ws.path(sparse).glob("*.txt"))]
        except (json.JSONDecodeError, AttributeError, OSError):
            pass  # a broken scene.json: the stage reruns on "output changed"
    return keys


def _encoding(cfg, cap, root: Path) -> str:
    if cfg.colour != "auto":
        return cfg.colour
    meta = root / "gt" / "scene.json"  # `ibr synth` says how it wrote its images
    if meta.is_file():
        try:
            enc = json.loads(meta.read_text()).get("image_encoding")
            if enc in ("srgb", "linear"):
                return enc
        except (json.JSONDecodeError, AttributeError, OSError):
            pass
    return cap.image_encoding or "srgb"


def _input_key(root: Path, path: Path, what: str) -> str:
    """The `input/...` key of a file a reader named inside the input folder. Lexical, like every
    path check (docs/DESIGN.md "Errors"): a symlinked images/ the folder's owner made is followed."""
    import os
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(root))
    if rel == ".." or rel.startswith(".." + os.sep) or os.path.isabs(rel):
        raise InputError(f"{root}: {what}: {path} is outside the input folder")
    return f"input/{Path(rel).as_posix()}"


def _prepare(ctx, cap, where) -> tuple[list[View], dict]:
    """Each frame as a View, converting what needs it into ingest/ keys (written where `where`
    says: a staging folder until every check passed); counts of what was done."""
    from tqdm import tqdm

    from ..io.images import image_size
    from ..io.prepare import exif_orientation, plan, prepare

    root = ctx.ws.input_root
    video = [f for f in cap.frames if f.video_frame is not None]
    if video:
        from ..io.video import extract_frames
        where(L.INGEST_IMAGES).mkdir(parents=True, exist_ok=True)
        extract_frames(video[0].image, [f.video_frame for f in video], where(L.INGEST_IMAGES),
                       [f.name for f in video])
    done = {"undistorted": 0, "rotated": 0, "depth_converted": 0, "exif_ignored": 0}
    views = []
    for f in tqdm(cap.frames, desc="ingest: preparing frames", unit="img", leave=False,
                  disable=not ctx.progress):
        stem = Path(f.name).with_suffix("").as_posix()
        if f.video_frame is not None:
            key = f"{L.INGEST_IMAGES}/{f.name}"
            size, orient = image_size(where(key)), 1
        else:
            key = _input_key(root, f.image, f"frame {f.name}")
            size, orient = image_size(f.image), exif_orientation(f.image)
        p = plan(f, size, orient)
        image_key = f"{L.INGEST_IMAGES}/{stem}.png" if p.image else key
        depth_key = None
        if f.depth is not None:
            depth_key = (f"{L.INGEST_DEPTH}/{stem}.png" if p.depth else
                         _input_key(root, f.depth, f"depth of frame {f.name}"))
        out_img, out_depth = where(image_key), None if depth_key is None else where(depth_key)
        for path in (out_img, out_depth):
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
        camera = prepare(f, p, out_img if p.image else None, out_depth if p.depth else None)
        done["undistorted"] += p.undistort
        done["rotated"] += p.rotate
        done["depth_converted"] += p.depth
        done["exif_ignored"] += orient != 1 and not p.rotate
        views.append(View(name=f.name, image=image_key, camera=camera, depth=depth_key))
    return views, done


def run(ctx: StageContext) -> None:
    import tempfile

    # everything prepared is staged and moved into ingest/ only once every check passed, so that
    # refused input leaves the workspace as it was
    with tempfile.TemporaryDirectory(dir=ctx.ws.root, prefix=".ibrtmp-ingest-") as tmp:
        _run(ctx, Path(tmp))


def _run(ctx: StageContext, staging: Path) -> None:
    import os
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from ..io.images import image_size, read_depth_png, read_image
    from ..io.inputs import read_capture, read_reflectors_file

    ws, cfg = ctx.ws, ctx.config
    root = ws.input_root

    def where(key: str) -> Path:
        return staging / key[len("ingest/"):] if key.startswith("ingest/") else ws.path(key)

    cap = read_capture(root, video_frames=cfg.video_frames)
    log.info("ingest: %s input (%d frames)", cap.format, len(cap.frames))
    for note in cap.notes:
        log.info("ingest: %s", note)
    if len(cap.frames) < cfg.min_views:
        raise InputError(f"{root}: {len(cap.frames)} image(s) found, ingest.min_views is {cfg.min_views}")
    views, done = _prepare(ctx, cap, where)

    def sizes(view):
        path = where(view.image)
        w, h = (read_image(path).shape[1::-1] if cfg.check_pixels else image_size(path))
        return (w, h), (None if view.depth is None else read_depth_png(where(view.depth)).shape)

    # the files are decoded --jobs at a time (the decoders release the GIL); the first bad view
    # in the input's order is the one reported, as when they were read one by one, and the
    # files not yet read then are not read
    pool = ThreadPoolExecutor(max(1, ctx.jobs))
    try:
        checked = zip(views, pool.map(sizes, views))
        for view, ((w, h), dshape) in tqdm(checked, total=len(views), desc="ingest: checking "
                                           "images", unit="img", leave=False,
                                           disable=not ctx.progress):
            path = where(view.image)
            if view.camera is not None and (view.camera.width, view.camera.height) != (w, h):
                raise InputError(f"{path}: image is {w}x{h} but its camera says "
                                 f"{view.camera.width}x{view.camera.height}")
            if dshape is None:
                continue
            dpath = where(view.depth)
            dh, dw = dshape
            if abs(dw / dh - w / h) > 0.01 * (w / h):
                raise InputError(f"{dpath}: depth is {dw}x{dh}, which does not have the aspect "
                                 f"ratio of its {w}x{h} image (depth must cover the same view)")
    finally:
        pool.shutdown(cancel_futures=True)
    sparse = None
    if cap.sparse is not None:
        if done["undistorted"]:
            from ..io.colmap import write_undistorted_model
            write_undistorted_model(cap.sparse, where(L.INGEST_SPARSE))
            sparse = L.INGEST_SPARSE
        else:
            sparse = ws.key(cap.sparse)
    names = {v.name for v in views}
    reflectors = []
    for r in read_reflectors_file(root):
        masks = {}
        for view_name, rel in r.masks.items():
            if view_name not in names:
                raise InputError(f"{root / 'reflectors.json'}: reflector {r.name!r} has a "
                                 f"mask for unknown view {view_name!r}")
            what = f"{root / 'reflectors.json'}: reflector {r.name!r} mask of {view_name!r}"
            confined(root, rel, what)  # a shared reflectors.json must not read outside
            key = f"input/{rel}"
            mw, mh = image_size(ws.path(key))
            iw, ih = image_size(where(next(v.image for v in views if v.name == view_name)))
            if (mw, mh) != (iw, ih):
                raise InputError(f"{ws.path(key)}: mask is {mw}x{mh}, its image is {iw}x{ih}")
            masks[view_name] = key
        if r.outline is not None:
            view_name, pts = r.outline
            what = f"{root / 'reflectors.json'}: reflector {r.name!r} outline"
            if view_name not in names:
                raise InputError(f"{what}: unknown view {view_name!r}")
            iw, ih = image_size(where(next(v.image for v in views if v.name == view_name)))
            if not all(-0.5 <= u <= iw - 0.5 and -0.5 <= v <= ih - 0.5 for u, v in pts):
                raise InputError(f"{what}: a point lies outside the {iw}x{ih} image {view_name!r} "
                                 "(pixel positions, 0-based, x right and y down)")
        reflectors.append(dataclasses.replace(r, masks=masks))
    scene = Scene(tuple(views), tuple(reflectors), cap.format, _encoding(cfg, cap, root), sparse)
    for src in sorted(p for p in staging.rglob("*") if p.is_file()):  # every check passed
        dst = ws.path(f"ingest/{src.relative_to(staging).as_posix()}")
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
    ws.write_text(ws.SCENE, scene.to_json())
    posed = len(scene.posed_views)
    log.info("ingest: %d images (%d with cameras, from %s), %d with depth, %d reflector(s), "
             "colour %s", len(scene.views), posed, scene.source,
             sum(v.depth is not None for v in scene.views), len(scene.reflectors), scene.image_encoding)
    made = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in done.items() if n and k != "exif_ignored")
    if made:
        log.info("ingest: prepared into %s/: %s", ws.path("ingest"), made)
    if done["exif_ignored"]:
        log.info("ingest: EXIF orientation not applied to %d image(s): their cameras describe the "
                 "stored pixels", done["exif_ignored"])
    if posed == 0:
        log.info("ingest: no camera poses given: the poses stage will run SfM")


STAGE = Stage(name="ingest", help="read the input folder (COLMAP, nerfstudio, LLFF, TUM, ScanNet, "
              "video, images), prepare and check every frame, write scene.json",
              config=IngestConfig, version="2", run=run, needs_scene=False,
              inputs=inputs, outputs=outputs)
