"""Video input (format "video"): the sharpest frame of each of `target` equal windows.

Decoding uses the ffmpeg binary bundled with imageio-ffmpeg. Frame indices count decoded frames
in stream order with `-fps_mode passthrough`, so that the count (`probe`), the sharpness pass and
the extraction all enumerate the same frames: ffmpeg's default for a raw pipe is a constant frame
rate, which duplicates or drops frames of variable-frame-rate phone videos. ffmpeg applies the
container's rotation metadata, so frames come out upright.

Frame selection follows the video preprocessing of nerfstudio / instant-ngp (colmap2nerf's
"sharpness"): each frame is scored by the variance of its Laplacian (a blurred frame has little
high-frequency energy), scored on a copy at most `SCORE_WIDTH` pixels wide, and the best frame of
each window is kept.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from .capture import Capture, Frame

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
SCORE_WIDTH = 320  # px: enough to tell motion blur apart, cheap to decode and filter
_COMMON = ["-map", "0:v:0", "-fps_mode", "passthrough"]


def frame_name(index: int) -> str:
    return f"frame_{index:05d}.png"


def _reason(err: Exception) -> str:
    """The useful line of an imageio-ffmpeg error: its stderr is a page of banner and stream info,
    with the reason last (or on a line that says what is wrong)."""
    text = str(err)
    head, _, stderr = text.partition("=== stderr ===")
    lines = [ln.strip() for ln in stderr.splitlines()
             if ln.strip() and not ln.startswith((" ", "\t", "ffmpeg version"))]
    keys = ("invalid", "error", "moov atom", "not found", "no such file", "truncat", "corrupt",
            "matches no streams")
    lines = [re.sub(r"^\[[^\]]* @ 0x[0-9a-f]+\] ", "", ln) for ln in lines]  # "[in#0 @ 0x55..] "
    hits = [ln for ln in lines if any(k in ln.lower() for k in keys)]
    if hits:  # the first says what is wrong ("moov atom not found"), the last what failed
        return "; ".join(dict.fromkeys([hits[0], hits[-1]]))[:300]
    return lines[-1] if lines else head.strip().splitlines()[0] if head.strip() else type(err).__name__


def _check_file(path: Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: video file not found")
    return path


class _ScaledOnPurpose:
    """Drops imageio-ffmpeg's "frame size for reading ... is different from the source" warning:
    our sizes differ because we ask ffmpeg to scale (sharpness pass) or to rotate upright."""

    def filter(self, record) -> bool:
        return "is different from the source frame size" not in record.getMessage()


_SIZE_FILTER = _ScaledOnPurpose()


class _Decoder:
    """Frames of `path` as uint8 arrays (H, W[, 3]) through imageio-ffmpeg, with `meta` (size, fps)
    read on opening; every decoding failure is an InputError naming the file. Use as a context
    manager so that ffmpeg is stopped when the caller stops early."""

    def __init__(self, path: Path, output_params: list[str], grey: bool = False):
        import logging

        import imageio_ffmpeg

        log = logging.getLogger("imageio_ffmpeg")
        if _SIZE_FILTER not in log.filters:
            log.addFilter(_SIZE_FILTER)
        self.path = path
        self._gen = imageio_ffmpeg.read_frames(
            str(path), pix_fmt="gray" if grey else "rgb24", bits_per_pixel=8 if grey else 24,
            output_params=_COMMON + output_params)
        try:
            self.meta = next(self._gen)
        except (OSError, RuntimeError, StopIteration, IndexError, AttributeError) as e:
            # IndexError / AttributeError: imageio-ffmpeg's header parser on a stream it cannot read
            self.close()
            raise self._error(e) from None
        w, h = self.meta["size"]
        self._shape = (h, w) if grey else (h, w, 3)

    def _error(self, e: Exception) -> InputError:
        return InputError(f"{self.path}: cannot decode video ({_reason(e)})")

    def __iter__(self):
        try:
            for buf in self._gen:
                yield np.frombuffer(buf, dtype=np.uint8).reshape(self._shape)
        except (OSError, RuntimeError) as e:
            raise self._error(e) from None

    def close(self) -> None:
        self._gen.close()  # runs imageio-ffmpeg's cleanup: stops the ffmpeg process

    def __enter__(self) -> "_Decoder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def probe(path: Path) -> tuple[int, float, int, int]:
    """(number of frames, frames per second, width, height) of the first video stream, as decoded
    (upright). The count decodes the whole stream: container headers are often wrong (or absent)
    for variable-frame-rate and truncated files."""
    import imageio_ffmpeg

    path = _check_file(path)
    with _Decoder(path, []) as dec:
        meta = dec.meta
    try:
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    except (OSError, RuntimeError) as e:
        raise InputError(f"{path}: cannot decode video ({_reason(e)})") from None
    if not n:
        raise InputError(f"{path}: the video has no decodable frames")
    w, h = meta["size"]
    return int(n), float(meta.get("fps") or 0.0), int(w), int(h)


def _windows(n: int, target: int) -> list[range]:
    edges = np.linspace(0, n, target + 1).round().astype(int)
    return [range(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _sharpness(path: Path) -> tuple[np.ndarray, float]:
    """Variance of the Laplacian of every frame (grey, at most SCORE_WIDTH wide), and the fps."""
    import cv2

    # grey: sharpness needs luminance only; never upscaled; -2 keeps the height even
    with _Decoder(path, ["-vf", f"scale='min({SCORE_WIDTH},iw)':-2"], grey=True) as dec:
        scores = [float(cv2.Laplacian(f, cv2.CV_64F).var()) for f in dec]
        fps = float(dec.meta.get("fps") or 0.0)
    if not scores:
        raise InputError(f"{path}: the video has no decodable frames")
    return np.asarray(scores), fps


def _pick(scores: np.ndarray, target: int) -> list[int]:
    if len(scores) <= target:
        return list(range(len(scores)))
    edges = np.linspace(0, len(scores), target + 1).round().astype(int)
    # argmax takes the first of equal scores: deterministic
    return sorted(int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a)


def _check_target(path: Path, target) -> None:
    if not (isinstance(target, (int, np.integer)) and target >= 1):
        raise InputError(f"{path}: the number of video frames to take must be a whole number "
                         f">= 1, got {target!r}")


def sharp_frames(path: Path, target: int) -> list[int]:
    """Sorted indices of the sharpest frame in each of `target` equal windows of the video (every
    frame when there are no more than `target`). Deterministic: ties go to the earliest frame."""
    path = _check_file(path)
    _check_target(path, target)
    return _pick(_sharpness(path)[0], int(target))


def extract_frames(path: Path, indices, out_dir: Path, names: list[str]) -> None:
    """Decode the video at full size and write frame `indices[k]` as PNG `out_dir / names[k]`
    (atomically: io/images.write_image)."""
    from .images import write_image

    path = _check_file(path)
    indices = [int(i) for i in indices]
    if len(indices) != len(names):
        raise ValueError(f"{len(indices)} indices but {len(names)} names")
    if not indices:
        return
    want: dict[int, list[str]] = {}
    for i, nm in zip(indices, names):
        want.setdefault(i, []).append(nm)
    last, n = max(want), 0
    with _Decoder(path, []) as dec:
        for n, frame in enumerate(dec, 1):
            for nm in want.get(n - 1, ()):
                write_image(Path(out_dir) / nm, frame)
            if n - 1 == last:
                break  # the rest need not be decoded
    if n <= last:
        first_missing = min(i for i in want if i >= n)
        raise InputError(f"{path}: the video ended after {n} frames but frame {first_missing} "
                         "was selected (the file changed or is truncated)")


def read_video(path: Path, target: int) -> Capture:
    """A video as a Capture of its `target` sharpest frames (one per window), unposed."""
    path = _check_file(path)
    _check_target(path, target)
    scores, fps = _sharpness(path)  # one decode: the frame count is the number of scores
    chosen = _pick(scores, int(target))
    frames = tuple(Frame(frame_name(i), path, video_frame=i) for i in chosen)
    notes = (f"video {path.name}: {len(scores)} frames at {fps:g} fps",
             f"{len(chosen)} of {len(scores)} frames chosen (sharpest in each window)")
    return Capture("video", frames, files=(path,), notes=notes)
