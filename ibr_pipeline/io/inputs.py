"""Input folders: which layout a folder has, and the `Capture` read from it.

`detect` names the layout from the folder's files alone (cheap: the `ingest` stage fingerprints
`input_files` before it reads anything); `read_capture` calls that layout's reader (io/colmap.py,
io/nerfstudio.py, io/llff.py, io/rgbd.py, io/video.py, or the two plain ones here). The first
layout in `LAYOUTS` that matches wins; any other pose source in the folder is named in the notes
("also present, not used"). A pose source we recognise but cannot use is an error, never a silent
fallback to SfM. docs/PIPELINE.md "Input layouts" is the user's table of these.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..scene import IMAGE_EXTENSIONS, Scene, View, cameras_from_json, read_reflectors
from .capture import Capture, Frame, Lens
from .video import VIDEO_EXTENSIONS


@dataclass(frozen=True)
class Layout:
    """A detected input layout: `name` and the pose-source `path` it was detected from."""

    name: str
    path: Path | None = None
    others: tuple[str, ...] = ()  # other pose sources in the folder, not used


def _image_dir(root: Path) -> Path:
    return root / "images" if (root / "images").is_dir() else root


def _hidden(p: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in p.relative_to(root).parts)


def list_images(root: Path, folder: Path | None = None) -> list[Path]:
    """Image files of `folder` (default: `images/` or the top level), sorted; hidden ones skipped.

    At the top level only the folder's own files count: depth/ and masks/ are not views.
    """
    root = Path(root)
    folder = _image_dir(root) if folder is None else folder
    if not folder.is_dir():
        return []
    it = folder.glob("*") if folder == root else folder.rglob("*")
    return sorted(p for p in it if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()
                  and not _hidden(p, root))


def _videos(root: Path) -> list[Path]:
    return sorted(p for p in root.glob("*") if p.suffix.lower() in VIDEO_EXTENSIONS and p.is_file())


def _colmap_candidates(root: Path) -> list[tuple[str, Path]]:
    """COLMAP model folders a tool would have written: (layout name, model folder)."""
    return [("colmap", root / "sparse" / "0"),                  # COLMAP's automatic reconstructor
            ("colmap-undistorted", root / "sparse"),             # COLMAP's image_undistorter
            ("nerfstudio-colmap", root / "colmap" / "sparse" / "0"),  # ns-process-data
            ("colmap", root / "distorted" / "sparse" / "0")]     # 3DGS convert.py, before undistortion


def detect(root: Path) -> Layout:
    """The input layout of `root` (README "Inputs", docs/PIPELINE.md "Input layouts")."""
    from .colmap import is_model
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: input folder does not exist")
    found: list[Layout] = []
    if (root / "transforms.json").is_file():
        found.append(Layout("nerfstudio", root / "transforms.json"))
    for name, path in _colmap_candidates(root):
        if is_model(path) and not any(f.path == path for f in found):
            found.append(Layout(name, path))
    if (root / "sparse").is_dir() and not any(f.name.startswith("colmap") and f.path.is_relative_to(
            root / "sparse") for f in found):
        subs = sorted(p.name for p in (root / "sparse").iterdir() if p.is_dir())
        raise InputError(f"{root / 'sparse'}: holds no COLMAP model (expected sparse/0/cameras.bin "
                         "or sparse/cameras.bin" + (f"; found sub-folders {subs[:5]}: rename the "
                         "model to use to sparse/0" if subs else "") + ")")
    if (root / "poses_bounds.npy").is_file():
        found.append(Layout("llff", root / "poses_bounds.npy"))
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        found.append(Layout("tum", root / "rgb.txt"))
    if all((root / d).is_dir() for d in ("color", "pose", "intrinsic")):
        found.append(Layout("scannet", root / "pose"))
    if (root / "cameras.json").is_file():
        found.append(Layout("cameras.json", root / "cameras.json"))
    if found:
        first = found[0]
        return Layout(first.name, first.path, tuple(f"{f.name} ({f.path.relative_to(root)})"
                                                    for f in found[1:]))
    if not list_images(root) and _videos(root):
        vids = _videos(root)
        if len(vids) > 1:
            raise InputError(f"{root}: {len(vids)} videos ({', '.join(v.name for v in vids[:4])}); "
                             "give one video per input folder")
        return Layout("video", vids[0])
    return Layout("images")


def _depth_for(root: Path, frames: list[Frame]) -> list[Frame]:
    """Attach `depth/<image stem>.png` (16-bit mm, scene.py) to each frame; a partial set is an
    error, because it would silently switch global_mesh from RGB-D fusion to MVS."""
    import dataclasses
    depth_dir = root / "depth"
    if not depth_dir.is_dir():
        return frames
    out = [dataclasses.replace(f, depth=p) if (p := depth_dir / f"{Path(f.name).with_suffix('').as_posix()}.png"
                                                ).is_file() else f for f in frames]
    missing = [f"depth/{Path(f.name).with_suffix('.png').as_posix()}" for f in out if f.depth is None]
    if len(missing) < len(out) and missing:
        raise InputError(f"{depth_dir}: {len(out) - len(missing)} of {len(out)} images have a depth "
                         f"frame; missing {', '.join(missing[:3])}"
                         + (f" (+{len(missing) - 3} more)" if len(missing) > 3 else "")
                         + " (add them, or move depth/ away to build geometry from the images alone)")
    return out


def _names(root: Path) -> tuple[Path, list[str]]:
    img_dir = _image_dir(root)
    files = list_images(root)
    if not files:
        raise InputError(f"{root}: no images found (looked for *.png/*.jpg in {img_dir}"
                         + (", and for a video" if img_dir == root else "") + ")")
    return img_dir, [p.relative_to(img_dir).as_posix() for p in files]


def _read_colmap(root: Path, layout: Layout) -> Capture:
    import dataclasses
    from .colmap import read_colmap_capture
    img_dir, names = _names(root)
    cap = read_colmap_capture(layout.path, img_dir, layout.name)
    posed = {f.name for f in cap.frames}
    extra = [Frame(name=n, image=img_dir / n) for n in names if n not in posed]
    frames = sorted(cap.frames + tuple(extra), key=lambda f: f.name)
    notes = cap.notes + ((f"{len(extra)} image(s) in {img_dir.name}/ are not in the model "
                          "(no pose: left out)",) if extra else ())
    return dataclasses.replace(cap, frames=tuple(_depth_for(root, frames)), notes=notes)


def _read_cameras_json(root: Path) -> Capture:
    img_dir, names = _names(root)
    cameras = cameras_from_json(root / "cameras.json")
    unknown = sorted(set(cameras) - set(names))
    if unknown:  # names like "../x.png" or "/abs.png" end here too: only listed images are views
        raise InputError(f"{root / 'cameras.json'}: cameras for images not in {img_dir}: "
                         f"{unknown[:5]}" + (f" (+{len(unknown) - 5} more)" if len(unknown) > 5 else ""))
    frames = [Frame(name=n, image=img_dir / n,
                    cam_from_world=None if (c := cameras.get(n)) is None else c.cam_from_world,
                    lens=None if c is None else Lens.from_K(c.K, c.width, c.height)) for n in names]
    return Capture("cameras.json", tuple(_depth_for(root, frames)), files=(root / "cameras.json",))


def _read_images(root: Path) -> Capture:
    img_dir, names = _names(root)
    frames = [Frame(name=n, image=img_dir / n) for n in names]
    return Capture("images", tuple(_depth_for(root, frames)))


def read_capture(root: Path, video_frames: int = 150) -> Capture:
    """Read an input folder (any layout of `detect`) into a Capture; nothing is converted here."""
    import dataclasses
    root = Path(root)
    layout = detect(root)
    if layout.name.startswith("colmap") or layout.name == "nerfstudio-colmap":
        cap = _read_colmap(root, layout)
    elif layout.name == "nerfstudio":
        from .nerfstudio import read_transforms
        cap = read_transforms(layout.path, root)
    elif layout.name == "llff":
        from .llff import read_poses_bounds
        cap = read_poses_bounds(root)
    elif layout.name == "tum":
        from .rgbd import read_tum
        cap = read_tum(root)
    elif layout.name == "scannet":
        from .rgbd import read_scannet
        cap = read_scannet(root)
    elif layout.name == "cameras.json":
        cap = _read_cameras_json(root)
    elif layout.name == "video":
        from .video import read_video
        cap = read_video(layout.path, video_frames)
    else:
        cap = _read_images(root)
    if not cap.frames:
        raise InputError(f"{root}: the {layout.name} input has no frames")
    notes = tuple(f"also present, not used: {o}" for o in layout.others) + cap.notes
    return dataclasses.replace(cap, notes=notes)


def read_reflectors_file(root: Path):
    root = Path(root)
    return read_reflectors(root / "reflectors.json") if (root / "reflectors.json").is_file() else ()


def read_input(root: Path) -> Scene:
    """The Scene of an input folder that needs no preparation (pinhole lenses, 8-bit images in
    place, depth in mm): paths are `input/...` keys. The `ingest` stage handles every layout;
    this is the plain reading for tests and tools."""
    import os
    root = Path(os.path.abspath(root))
    cap = read_capture(root)

    def key(path: Path) -> str:  # lexical: a symlinked images/ inside the folder is followed
        return f"input/{Path(os.path.relpath(os.path.abspath(path), root)).as_posix()}"

    views = []
    for f in cap.frames:
        if f.video_frame is not None or (f.lens is not None and f.lens.distorted) or (
                f.depth is not None and (f.depth_units_per_m != 1000.0 or f.depth_lens is not None)):
            raise InputError(f"{root}: frame {f.name} needs preparation (undistortion, video "
                             "frames or depth units): run the ingest stage")
        cam = None
        if f.cam_from_world is not None and f.lens is not None:
            from ..scene import Camera
            cam = Camera(f.lens.pinhole_K(), f.cam_from_world, f.lens.width, f.lens.height)
        views.append(View(name=f.name, image=key(f.image), camera=cam,
                          depth=None if f.depth is None else key(f.depth)))
    return Scene(tuple(views), read_reflectors_file(root), cap.format)


def input_files(root: Path) -> list[Path]:
    """The files of an input folder that the pipeline reads (what `ingest` fingerprints), from the
    layout alone: images, depth frames, the pose source's files, reflectors.json and masks; not
    `gt/` or anything else that happens to sit beside them."""
    from .colmap import model_files
    root = Path(root)
    layout = detect(root)
    found: list[Path] = []
    folders = [(root / "depth", True), (root / "masks", True)]
    if layout.name == "tum":
        folders += [(root / "rgb", True)]
        found += [p for p in (root / n for n in ("rgb.txt", "depth.txt", "groundtruth.txt",
                                                 "intrinsics.txt")) if p.is_file()]
    elif layout.name == "scannet":
        folders = [(root / d, True) for d in ("color", "depth", "pose", "intrinsic")]
    elif layout.name == "video":
        found.append(layout.path)
    else:
        img_dir = _image_dir(root)
        folders.append((img_dir, img_dir != root))
    for folder, recursive in folders:
        if folder.is_dir():
            it = folder.rglob("*") if recursive else folder.glob("*")
            keep = (lambda p: True) if layout.name == "scannet" and folder.name in ("pose", "intrinsic") \
                else (lambda p: p.suffix.lower() in IMAGE_EXTENSIONS)
            found += [p for p in it if p.is_file() and keep(p) and not _hidden(p, root)]
    if layout.name.startswith("colmap") or layout.name == "nerfstudio-colmap":
        found += model_files(layout.path)
    elif layout.name == "nerfstudio":  # frames may name any folder (images_4/, ...): ask the reader
        from .nerfstudio import read_transforms
        found += read_transforms(layout.path, root).files
    elif layout.name in ("llff", "cameras.json"):
        found.append(layout.path)
        if layout.name == "llff" and (root / "hwf_cxcy.npy").is_file():
            found.append(root / "hwf_cxcy.npy")
    found += [p for p in (root / "reflectors.json",) if p.is_file()]
    return sorted(set(found))
