"""What every input reader returns: a `Capture` of `Frame`s, before anything is converted.

A reader (io/colmap.py, io/nerfstudio.py, io/llff.py, io/rgbd.py, io/video.py, io/inputs.py's
own cameras.json / bare-folder readers) only *reads*: it names each frame's source file inside
the input folder, its pose (if the format gives one), its lens (if known) and its depth frame with
the format's depth units. The `ingest` stage then prepares what the rest of the pipeline reads
(stages/ingest.py): frames whose lens is distorted are undistorted with pycolmap, video frames are
extracted, EXIF-rotated photos are turned upright and depth in other units is rewritten as 16-bit
millimetres, each into the workspace; the input folder is never written.

Conventions (scene.py): `cam_from_world` is a 4x4 OpenCV-axes world-to-camera matrix in the
input's own units. `Lens` keeps COLMAP's camera model names and parameter order, *and COLMAP's
pixel convention* (the centre of the top-left pixel is (0.5, 0.5)), because pycolmap undistorts
it; `Lens.pinhole_K()` converts to ours.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

# COLMAP camera models (src/colmap/sensor/models.h): parameter names in order
LENS_PARAMS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
    "FOV": ("fx", "fy", "cx", "cy", "omega"),
    "THIN_PRISM_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1"),
}
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True)
class Lens:
    """A COLMAP camera model: `model` name, `params` in COLMAP's order and pixel convention."""

    model: str
    params: tuple[float, ...]
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.model not in LENS_PARAMS:
            raise ValueError(f"unknown camera model {self.model!r} (known: {', '.join(LENS_PARAMS)})")
        want = len(LENS_PARAMS[self.model])
        p = np.asarray(self.params, dtype=np.float64)
        if p.shape != (want,):
            raise ValueError(f"{self.model} takes {want} parameters "
                             f"({', '.join(LENS_PARAMS[self.model])}), got {len(self.params)}")
        if not np.all(np.isfinite(p)):
            raise ValueError(f"{self.model} parameters must be finite, got {list(self.params)}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "params", tuple(float(x) for x in p))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def distorted(self) -> bool:
        """True when straight lines are not straight in the image: it must be undistorted.

        A perspective model whose distortion parameters are all zero is a pinhole; a fisheye
        (equidistant, r = f theta) or FOV model never is.
        """
        if self.model in PINHOLE_MODELS:
            return False
        if "FISHEYE" in self.model or self.model == "FOV":
            return True
        names = LENS_PARAMS[self.model]
        return any(
            v != 0.0 for n, v in zip(names, self.params) if n not in ("f", "fx", "fy", "cx", "cy"))

    def focal(self) -> tuple[float, float]:
        d = dict(zip(LENS_PARAMS[self.model], self.params))
        return (d["f"], d["f"]) if "f" in d else (d["fx"], d["fy"])

    def pinhole_K(self) -> np.ndarray:
        """K in our pixel convention (scene.py); only meaningful when not `distorted`."""
        d = dict(zip(LENS_PARAMS[self.model], self.params))
        fx, fy = self.focal()
        return np.array([[fx, 0, d["cx"] - 0.5], [0, fy, d["cy"] - 0.5], [0, 0, 1.0]])

    @staticmethod
    def from_K(K: np.ndarray, width: int, height: int) -> "Lens":
        """A PINHOLE lens from a K in our pixel convention."""
        K = np.asarray(K, dtype=np.float64)
        return Lens("PINHOLE", (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5), width, height)


@dataclass(frozen=True)
class Frame:
    """One image of a capture, as its format gives it.

    name: the view's name (a relative posix path, unique); also the name its prepared image gets.
    image: the source file (inside the input folder). For a video, the video file, with
      `video_frame` the index of the decoded frame.
    cam_from_world: 4x4, OpenCV axes, the input's units; None when the format gives no pose.
    lens: None when unknown (SfM estimates it).
    depth: a depth frame (16-bit PNG) registered to the image, `depth_units_per_m` units per metre
      (TUM 5000, ScanNet / our own 1000), 0 = no measurement. `depth_lens`: the depth frame's own
      intrinsics when they are not the colour lens scaled to the depth frame's size (ScanNet).
    """

    name: str
    image: Path
    cam_from_world: np.ndarray | None = None
    lens: Lens | None = None
    depth: Path | None = None
    depth_units_per_m: float = 1000.0
    depth_lens: Lens | None = None
    video_frame: int | None = None

    def __post_init__(self) -> None:
        if self.cam_from_world is not None:
            T = np.asarray(self.cam_from_world, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"cam_from_world must be 4x4, got {T.shape}")
            object.__setattr__(self, "cam_from_world", T)
        if not self.depth_units_per_m > 0:
            raise ValueError(f"depth_units_per_m must be > 0, got {self.depth_units_per_m}")


@dataclass(frozen=True)
class Capture:
    """An input folder as read: its frames, what read it, and files that matter for later stages.

    format: the layout's name, as the ingest log and scene.json show it (e.g. "colmap",
      "colmap-undistorted", "nerfstudio", "llff", "tum", "scannet", "video", "cameras.json",
      "images").
    sparse: a COLMAP model folder (inside the input) whose 3D points belong to the given poses, or
      None; the poses stage measures the scene scale from them.
    files: every input file the reader read (the ingest stage fingerprints them).
    image_encoding: "srgb", "linear", or None when the format does not say (photographs: sRGB).
    notes: lines for the ingest log (what was detected, what was ignored and why).
    """

    format: str
    frames: tuple[Frame, ...]
    sparse: Path | None = None
    files: tuple[Path, ...] = ()
    image_encoding: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        names = [f.name for f in self.frames]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"{self.format} input: duplicate frame names {dup[:5]}")
        if self.image_encoding not in (None, "srgb", "linear"):
            raise ValueError(f"image_encoding must be 'srgb', 'linear' or None, got {self.image_encoding!r}")


def lens_from_colmap_camera(cam) -> Lens:
    """A Lens from a pycolmap.Camera."""
    return Lens(cam.model_name, tuple(cam.params), cam.width, cam.height)


def colmap_camera(lens: Lens, camera_id: int = 1):
    """A pycolmap.Camera from a Lens."""
    import pycolmap
    return pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height,
                           params=list(lens.params), camera_id=camera_id)
