"""DSRNet training data (Xu et al. §5.2, §6): leave-one-out low-resolution renders of the capture
views paired with the captured full-resolution images; consecutive capture views give the previous
frame; 90 % / 10 % split, the held-out views are never trained on (neither as target nor as input).

The low-resolution renderer is any callable `renderer(name, camera_lr) -> (color (h,w,3) float32
linear, depth (h,w) float32, 0 = hole)` that renders the capture view `name` *without using that
view* at the given (low-resolution) camera: render/low_res.py has the real one and a stand-in.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..scene import Camera
from .warp import depth_motion

Renderer = Callable[[str, Camera], tuple]


@dataclass
class LowRes:
    """A low-resolution render: colour (h,w,3) float32, depth (h,w) float32 (0 = hole), camera."""

    color: np.ndarray
    depth: np.ndarray
    camera: Camera

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        self.color = np.asarray(self.color, dtype=np.float32)
        self.depth = np.asarray(self.depth, dtype=np.float32)
        if self.color.shape != (h, w, 3) or self.depth.shape != (h, w):
            raise ValueError(f"render must be colour ({h}, {w}, 3) and depth ({h}, {w}) for a "
                             f"{w}x{h} camera, got {self.color.shape} and {self.depth.shape}")
        if not (np.all(np.isfinite(self.color)) and np.all(np.isfinite(self.depth))):
            raise ValueError("low-resolution render contains NaN or infinite values")


@dataclass
class Sample:
    """One training/evaluation pair: current + previous low-res frames, M_d, full-res target."""

    name: str
    prev_name: str
    cur: LowRes
    prev: LowRes
    flow: np.ndarray  # (h, w, 2) M_d at the current frame's pixels
    target: np.ndarray  # (H, W, 3) full resolution, H = scale*h


def supersampled_size(width: int, height: int, scale: int) -> tuple[int, int]:
    """(W, H) of what supersampling reconstructs: the image less the < scale columns and rows at
    its right and bottom that a 1/scale render cannot cover exactly (a phone's 498x373 -> 498x372)."""
    if scale < 1:
        raise ValueError(f"scale must be >= 1, got {scale}")
    return width - width % scale, height - height % scale


def low_res_camera(camera: Camera, scale: int) -> Camera:
    """The camera of the 1/scale render: the image cropped to `supersampled_size` (a crop at the
    right and bottom keeps K), then resized exactly."""
    w, h = supersampled_size(camera.width, camera.height, scale)
    crop = Camera(camera.K, camera.cam_from_world, w, h)
    return crop.resized(w // scale, h // scale)


def split_views(names: Sequence[str], val_fraction: float = 0.1) -> tuple[list[str], list[str]]:
    """(train, val) in the given order: §6 "90% of the captured images as the training dataset and
    the remaining 10% as the validation set"; the validation views are spread evenly along the
    sequence so they are not one block of the path."""
    names = list(names)
    if len(names) < 2:
        raise ValueError(f"need at least 2 views to train, got {len(names)}")
    if len(names) < 3:  # too few to hold one out: train on both, validate on none
        return names, []
    n_val = min(len(names) - 2, max(1, int(round(len(names) * val_fraction))))
    val_idx = {int((k + 0.5) * len(names) / n_val) for k in range(n_val)}
    val = [n for i, n in enumerate(names) if i in val_idx]
    return [n for i, n in enumerate(names) if i not in val_idx], val


def sequence_pairs(order: Sequence[str], targets: Sequence[str]) -> list[tuple[str, str]]:
    """(current, previous) pairs: each target view with its neighbours in `order` (consecutive
    capture views; both neighbours are used as 'previous frame', which doubles the pairs)."""
    order = list(order)
    pos = {n: i for i, n in enumerate(order)}
    pairs = []
    for n in targets:
        i = pos[n]
        for j in (i - 1, i + 1):
            if 0 <= j < len(order):
                pairs.append((n, order[j]))
    return pairs


def make_sample(name: str, prev_name: str, frames: dict, target: np.ndarray) -> Sample:
    cur, prev = frames[name], frames[prev_name]
    flow, _ = depth_motion(cur.depth, cur.camera, prev.camera, prev.depth)
    h, w = cur.depth.shape
    if target.ndim != 3 or target.shape[2] != 3 or target.shape[0] % h or target.shape[1] % w:
        raise ValueError(f"target {target.shape} is not a multiple of the render size {(h, w)}")
    return Sample(name, prev_name, cur, prev, flow, np.asarray(target, dtype=np.float32))


def capture_low_res(image: np.ndarray, render: LowRes) -> LowRes:
    """The captured full-resolution image area-downsampled to the low-resolution render's camera,
    with the depth of that render (same camera: the leave-one-out render of the view itself).

    A *capture pair* (this as input, the capture as target) teaches real super-resolution on real
    detail: input and target differ only by the downsampling, whereas in a render pair they also
    differ by the IBR reconstruction's error (our extension beyond §6, docs/DSRNET.md)."""
    import cv2

    h, w = render.depth.shape
    img = np.asarray(image, np.float32)
    if img.shape[0] % h or img.shape[1] % w:
        raise ValueError(f"capture {img.shape} is not a multiple of the render size {(h, w)}")
    color = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return LowRes(np.clip(color, 0.0, 1.0), render.depth, render.camera)


def capture_pairs(pairs: Sequence[tuple[str, str]], frames: dict, targets: dict) -> list[Sample]:
    """Capture-pair samples for (current, previous) view pairs: both frames are the captures
    area-downsampled (`capture_low_res`), the target is the current capture. Only the views named
    in `pairs` are read: pass training pairs only, so no validation view is ever trained on."""
    low = {}
    for n in {v for pair in pairs for v in pair}:
        low[n] = capture_low_res(targets[n], frames[n])
    return [make_sample(c, p, low, targets[c]) for c, p in pairs]


def nearest_views(cameras: dict[str, Camera], names: Sequence[str], k: int) -> dict[str, list]:
    """{name: the k other views of `cameras` whose optical centres are nearest to name's}."""
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    allv = list(cameras)
    centres = np.array([cameras[n].center for n in allv], dtype=np.float64).reshape(-1, 3)
    out = {}
    for n in names:
        d = np.linalg.norm(centres - np.asarray(cameras[n].center, np.float64), axis=1)
        order = [allv[i] for i in np.argsort(d, kind="stable") if allv[i] != n]
        out[n] = order[:k]
    return out


def render_low_res(names: Sequence[str], cameras: dict[str, Camera], renderer: Renderer,
                   scale: int, progress: bool = False, cache: Callable | None = None) -> dict:
    """{name: LowRes} for every name, rendered at 1/scale resolution with `renderer`.

    cache: optional (name, compute) -> (color, depth) memoiser (the stage keeps renders on disk so
    an interrupted run does not render again)."""
    from tqdm import tqdm

    out = {}
    for n in tqdm(list(names), desc="supersample: low-res renders", unit="view", disable=not progress,
                  leave=False):
        cam = low_res_camera(cameras[n], scale)
        compute = (lambda n=n, cam=cam: renderer(n, cam))
        color, depth = cache(n, compute) if cache is not None else compute()
        out[n] = LowRes(color, depth, cam)
    return out


# --- batches -----------------------------------------------------------------------------------
def to_tensors(samples: Sequence[Sample], crop: int | None = None, rng=None, flip: bool = False):
    """Stack samples into the DSRNet input tensors (optionally a random crop of `crop` low-res
    pixels and a random horizontal flip per sample). Returns a dict of torch tensors."""
    import torch

    keys = ("cur", "depth", "prev", "depth_prev", "flow", "target")
    out = {k: [] for k in keys}
    for s in samples:
        h, w = s.cur.depth.shape
        f = s.target.shape[0] // h
        arrs = {"cur": s.cur.color, "depth": s.cur.depth[..., None], "prev": s.prev.color,
                "depth_prev": s.prev.depth[..., None], "flow": s.flow}
        tgt = s.target
        if crop is not None and crop < min(h, w):
            y = int(rng.integers(0, h - crop + 1))
            x = int(rng.integers(0, w - crop + 1))
            arrs = {k: a[y:y + crop, x:x + crop] for k, a in arrs.items()}
            tgt = tgt[y * f:(y + crop) * f, x * f:(x + crop) * f]
        if flip and rng is not None and rng.random() < 0.5:
            arrs = {k: a[:, ::-1] for k, a in arrs.items()}
            arrs["flow"] = arrs["flow"] * np.array([-1.0, 1.0], np.float32)  # u points the other way
            tgt = tgt[:, ::-1]
        for k, a in arrs.items():
            out[k].append(np.ascontiguousarray(a.transpose(2, 0, 1)))
        out["target"].append(np.ascontiguousarray(tgt.transpose(2, 0, 1)))
    return {k: torch.from_numpy(np.stack(v).astype(np.float32)) for k, v in out.items()}
