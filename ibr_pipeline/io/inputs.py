"""Input folders: which layout a folder has, and the Scene manifest read from it.

The `ingest` stage calls `read_input` (names and cameras only; it checks the pixels itself) and
fingerprints `input_files`. A new input format gets its reader here.
"""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..scene import IMAGE_EXTENSIONS, Camera, Scene, View, cameras_from_json, read_reflectors
from .colmap import read_colmap_model


def read_input(root: Path) -> Scene:
    """Read an input folder into a Scene whose paths are `input/...` workspace keys.

    Accepted layouts (README.md "Inputs"): a COLMAP workspace (`images/` + `sparse/0`, binary or text
    model, read with pycolmap); `images/` + `cameras.json`; or a bare folder of images (in
    `images/` or at the top level; no poses: SfM must run). Optional: `depth/<image stem>.png`
    (16-bit mm) and `reflectors.json`. Only names and cameras are read here; pixel contents are
    checked by the `ingest` stage.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: input folder does not exist")
    img_dir = root / "images" if (root / "images").is_dir() else root
    rel = "images/" if img_dir != root else ""
    files = sorted(p for p in img_dir.rglob("*") if p.suffix.lower() in IMAGE_EXTENSIONS
                   and p.is_file() and not any(part.startswith(".") for part in p.parts))
    if rel == "":  # top-level images only: depth/ and masks must not be taken for views
        files = [p for p in files if p.parent == root]
    if not files:
        raise InputError(f"{root}: no images found (looked for *.png/*.jpg in {img_dir})")
    names = [p.relative_to(img_dir).as_posix() for p in files]

    cameras: dict[str, Camera] = {}
    source = "images"
    sparse = root / "sparse" / "0"
    if sparse.is_dir():
        cameras, source = read_colmap_model(sparse), "colmap"
        unknown = sorted(set(cameras) - set(names))
        if unknown:
            raise InputError(f"{sparse}: model refers to images not in {img_dir}: {unknown[:5]}")
    elif (root / "cameras.json").is_file():
        cameras, source = cameras_from_json(root / "cameras.json"), "cameras.json"
        unknown = sorted(set(cameras) - set(names))
        if unknown:  # names like "../x.png" or "/abs.png" end here too: only listed images are views
            raise InputError(f"{root / 'cameras.json'}: cameras for images not in {img_dir}: "
                             f"{unknown[:5]}" + (f" (+{len(unknown) - 5} more)" if len(unknown) > 5 else ""))

    depth_dir = root / "depth"
    views = []
    for name in names:
        stem = Path(name).with_suffix("").as_posix()
        depth = depth_dir / f"{stem}.png"
        views.append(View(name=name, image=f"input/{rel}{name}", camera=cameras.get(name),
                          depth=f"input/depth/{stem}.png" if depth.is_file() else None))
    with_depth = [v for v in views if v.depth is not None]
    if with_depth and len(with_depth) < len(views):
        # a partial set would silently switch global_mesh from RGB-D fusion to MVS for all views
        missing = [f"depth/{Path(v.name).with_suffix('.png').as_posix()}" for v in views if v.depth is None]
        raise InputError(f"{depth_dir}: {len(with_depth)} of {len(views)} images have a depth frame; "
                         f"missing {', '.join(missing[:3])}" + (f" (+{len(missing) - 3} more)" if len(missing) > 3 else "")
                         + " (add them, or move depth/ away to build geometry from the images alone)")
    reflectors = read_reflectors(root / "reflectors.json") if (root / "reflectors.json").is_file() else ()
    return Scene(tuple(views), reflectors, source)


def input_files(root: Path) -> list[Path]:
    """The files of an input folder that the pipeline reads (what `ingest` fingerprints).

    Images, depth frames, the COLMAP model, cameras.json, reflectors.json and reflector masks;
    not `gt/` or anything else that happens to sit beside them.
    """
    root = Path(root)
    img_dir = root / "images" if (root / "images").is_dir() else root
    found: list[Path] = []
    for folder, recursive in ((img_dir, img_dir != root), (root / "depth", True), (root / "masks", True)):
        if folder.is_dir():
            it = folder.rglob("*") if recursive else folder.glob("*")
            found += [p for p in it if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                      and not any(part.startswith(".") for part in p.relative_to(root).parts)]
    sparse = root / "sparse" / "0"
    if sparse.is_dir():
        found += [p for p in sparse.iterdir() if p.is_file()]
    found += [p for p in (root / "cameras.json", root / "reflectors.json") if p.is_file()]
    return sorted(set(found))
