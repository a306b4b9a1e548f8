"""`ibr export WS [--out DIR] [--what colmap,transforms,glb,web] [--web] [--views NAME,...]`.

Writes a finished workspace's results in formats other tools read, into DIR (default WS/export):

* `colmap/`: a COLMAP text model (cameras.txt, images.txt, empty points3D.txt) of the registered
  cameras (global/cameras.json, scene frame), via io/colmap.py;
* `transforms.json`: the same cameras in nerfstudio's format, via io/nerfstudio.py; each frame's
  `file_path` is the view's image (scene.json's `image` key) relative to DIR when the two share a
  folder below the filesystem root, absolute otherwise (nerfstudio resolves relative paths against
  the folder of transforms.json);
* `views/<view>.glb`: per view, node "view" = the view's mesh (view_mesh's mesh.ply) textured with
  its photo by projective UVs; where `reflection` gave the view two layers, also node "surface" =
  M0 textured with I0 and node "reflection" = M1 textured with beta * I1, the reflection's
  contribution, so that surface + reflection, added, is the photo (Eq. 3: I = I0 + beta I1; I1.png
  alone is the reflected scene before attenuation). The sum holds in linear radiance: layers are
  decoded from the scene's encoding, added there, and the textures written sRGB-encoded, as glTF
  requires of base colours;
* `web/`: the browser viewer's bundle of every registered view (viewer/bundle.py; `ibr view WS`
  writes it too): only with `--what web` or `--web`, not part of the default set.

Everything lands in a staging folder inside DIR first and is moved into place only when all of it
was written: a missing stage output (one line naming the file and the stage to run, exit 2) or a
corrupt file leaves DIR as it was. Light at import time.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import tempfile
from pathlib import Path

WHAT = ("colmap", "transforms", "glb")
EXTRA = ("web",)  # asked for by name only


def register(sub) -> None:
    p = sub.add_parser("export", help="export cameras (COLMAP, nerfstudio transforms.json) and "
                       "textured per-view meshes (GLB) of a workspace",
                       description="Export the registered cameras as a COLMAP text model and a "
                       "nerfstudio transforms.json, and each view's mesh (and reflection layers "
                       "M0/M1, where the reflection stage produced them) as a GLB textured with "
                       "the view's photo (I0, beta*I1) by projective texturing.")
    p.add_argument("workspace", type=Path, help="workspace folder")
    p.add_argument("--out", type=Path, metavar="DIR", help="output folder (default WS/export)")
    p.add_argument("--what", default=",".join(WHAT), metavar="LIST",
                   help=f"comma-separated subset of {','.join(WHAT + EXTRA)} (default: "
                   f"{','.join(WHAT)})")
    p.add_argument("--web", action="store_true", help="only the browser viewer's bundle (DIR/web, "
                   "every registered view): the same as --what web")
    p.add_argument("--views", metavar="NAME,...", help="comma-separated view names to export "
                   "(default: every registered view); applies to every format")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _selected_cameras(ws, views_arg: str | None) -> dict:
    """{view name: Camera} of the registered views, restricted to --views (in cameras.json order)."""
    from .. import layout as L
    from ..errors import InputError
    p = ws.path(L.REGISTERED_CAMERAS)
    if not p.is_file():
        raise InputError(f"{p}: missing: no registered cameras yet (run `ibr poses {ws.root}`)")
    cams = L.registered_cameras(ws)
    if views_arg is None:
        return cams
    want = _csv(views_arg)
    unknown = [n for n in want if n not in cams]
    if unknown or not want:
        shown = ", ".join(list(cams)[:6]) + (", ..." if len(cams) > 6 else "")
        raise InputError(f"--views: {unknown[0] if unknown else views_arg!r} is not a registered "
                         f"view of {p} (registered: {shown})")
    return {n: c for n, c in cams.items() if n in set(want)}


def _image_paths(ws, names) -> dict[str, Path]:
    """{view name: its image file} from scene.json (`image` keys resolved by the workspace;
    the undistorted images when SfM estimated a distorted lens)."""
    from .. import layout as L
    from ..errors import InputError
    scene = L.posed_scene(ws)
    images = {v.name: ws.path(v.image) for v in scene.views}
    for n in names:
        if n not in images:
            raise InputError(f"{ws.path(ws.SCENE)}: registered view {n!r} is not in the scene "
                             f"manifest (rerun `ibr ingest {ws.root}`)")
        if not images[n].is_file():
            raise InputError(f"{images[n]}: image of view {n!r} not found")
    return {n: images[n] for n in names}


def _frame_path(image: Path, out: Path) -> str:
    """An image's path as transforms.json stores it: relative to `out` when they share a folder
    below the root (the pair can move together), else absolute."""
    image, out = Path(os.path.abspath(image)), Path(os.path.abspath(out))
    if os.path.commonpath([image, out]) == os.path.sep:
        return image.as_posix()
    return Path(os.path.relpath(image, out)).as_posix()


def _glb_names(names) -> dict[str, str]:
    """views/<file>.glb for each view: the view name without its extension, made path-safe; a
    name that would collide (a.png and a.jpg, or names differing only in unsafe characters) keeps
    layout.view_key's unique form."""
    from pathlib import PurePosixPath

    from ..layout import view_key
    stems = {n: view_key(str(PurePosixPath(n).with_suffix(""))) for n in names}
    counts: dict[str, int] = {}
    for s in stems.values():
        counts[s] = counts.get(s, 0) + 1
    return {n: f"{s if counts[s] == 1 else view_key(n)}.glb" for n, s in stems.items()}


def _check_glb_inputs(ws, names) -> dict[str, bool]:
    """{view: has reflection layers}; InputError naming the first missing file and its stage."""
    from .. import layout as L
    from ..errors import InputError
    layered = {}
    for n in names:
        mesh = ws.path(L.view_file(n, L.MESH))
        if not mesh.is_file():
            raise InputError(f"{mesh}: missing: the view has no mesh (run `ibr view_mesh {ws.root}`)")
        layered[n] = L.has_two_layers(ws, n)
        if layered[n]:
            for f in L.TWO_LAYER_FILES:
                p = ws.path(L.view_file(n, f))
                if not p.is_file():
                    raise InputError(f"{p}: missing: layers.json names a reflector but the layer "
                                     f"is not there (run `ibr reflection {ws.root} --force`)")
    return layered


def _load_beta(path: Path, shape: tuple[int, int]):
    import numpy as np

    from ..errors import InputError
    try:
        beta = np.load(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read reflectance ({e})") from None
    if beta.shape != shape or not np.all(np.isfinite(beta)):
        raise InputError(f"{path}: expected finite (H, W) = {shape} values, got shape "
                         f"{beta.shape} (rerun `ibr reflection`)")
    return np.clip(beta.astype(np.float32), 0.0, 1.0)


def _view_nodes(ws, name: str, cam, image: Path, layered: bool, enc: str) -> list:
    """[(node name, Trimesh)] of one view's GLB (module docstring)."""
    from .. import layout as L
    from ..errors import InputError
    from ..io.gltf import textured_mesh
    from ..io.images import linear_to_srgb, read_image
    from ..io.mesh import read_ply


    def node(node_name, mesh_file, img, texture, layer_of):
        m = read_ply(ws.path(L.view_file(name, mesh_file)))
        try:  # glTF base-colour textures are sRGB-encoded (glTF 2.0 §3.9.2); img is linear
            t = textured_mesh(m.vertices, m.faces, linear_to_srgb(img), c, node_name)
        except ValueError as e:  # sizes / indices the files disagree on
            raise InputError(f"{ws.path(L.view_file(name, mesh_file))}: {e}") from None
        t.metadata.update({"ibr_view": name, "ibr_texture": texture, "ibr_layer": layer_of})
        return node_name, t

    photo = read_image(image, enc)
    H, W = photo.shape[:2]
    c = cam if cam.size == (W, H) else cam.resized(W, H)  # the camera at the photo's resolution
    nodes = [node("view", L.MESH, photo, "photo", "single")]
    if layered:
        i0 = read_image(ws.path(L.view_file(name, L.I0)), enc)
        i1 = read_image(ws.path(L.view_file(name, L.I1)), enc)
        for key, im in ((L.I0, i0), (L.I1, i1)):
            if im.shape != photo.shape:
                raise InputError(f"{ws.path(L.view_file(name, key))}: {im.shape[1]}x{im.shape[0]}, "
                                 f"the photo is {W}x{H} (rerun `ibr reflection {ws.root} --force`)")
        beta = _load_beta(ws.path(L.view_file(name, L.BETA)), (H, W))
        nodes.append(node("surface", L.M0, i0, "I0", "surface (add to reflection)"))
        nodes.append(node("reflection", L.M1, beta[..., None] * i1, "beta * I1",
                          "reflection (add to surface)"))
    return nodes


@contextlib.contextmanager
def _staged(out: Path):
    """A staging folder inside `out`; its files are moved over `out`'s when the block succeeds,
    and removed (with `out` itself when this created it) when it fails."""
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".ibr-export-", dir=out))
    try:
        yield stage
        for f in sorted(p for p in stage.rglob("*") if p.is_file()):
            target = out / f.relative_to(stage)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(f, target)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if created and not any(out.iterdir()):
            out.rmdir()


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def main(args: argparse.Namespace) -> int:
    import logging

    from tqdm import tqdm

    from .. import layout as L
    from ..errors import InputError
    from ..workspace import Workspace

    log = logging.getLogger("ibr_pipeline.export")
    ws = Workspace(args.workspace)
    what = ["web"] if args.web else _csv(args.what)
    bad = [w for w in what if w not in WHAT + EXTRA]
    if bad or not what:
        raise InputError(f"--what: {bad[0] if bad else args.what!r} is not one of "
                         f"{', '.join(WHAT + EXTRA)}")
    if "web" in what and args.views is not None:
        raise InputError("--views: the web bundle holds every registered view (the viewer selects "
                         "among them); export it without --views")
    cams = _selected_cameras(ws, args.views)
    out = Path(os.path.abspath(args.out or ws.path("export")))
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: --out must be a folder, this is a file")
    images = _image_paths(ws, cams) if {"transforms", "glb"} & set(what) else {}
    layered = _check_glb_inputs(ws, cams) if "glb" in what else {}
    glb_names = _glb_names(cams)

    with _staged(out) as stage:
        if "colmap" in what:
            from ..io.colmap import write_colmap_model
            write_colmap_model(cams, stage / "colmap", text=True)
        if "transforms" in what:
            from ..io.nerfstudio import write_transforms  # io/nerfstudio.py
            # keyed by the path each frame's file_path must hold, so views whose images lie in
            # different folders need no common prefix
            by_path = {_frame_path(images[n], out): c for n, c in cams.items()}
            write_transforms(by_path, stage / "transforms.json", image_prefix="")
        if "glb" in what:
            from ..io.gltf import write_glb
            if not any(ws.exists(L.view_file(n, L.LAYERS)) for n in cams):
                log.info("export: the reflection stage has not run: each GLB holds the 'view' "
                         "node only (run `ibr reflection %s` for the layers)", ws.root)
            enc = ws.scene().image_encoding
            for n in tqdm(list(cams), desc="export", unit="view", disable=args.no_progress):
                write_glb(stage / "views" / glb_names[n], _view_nodes(ws, n, cams[n], images[n],
                                                                     layered[n], enc))

    if "web" in what:
        from ..viewer.bundle import write_bundle
        write_bundle(ws, out / "web", progress=not args.no_progress)
    print(f"export: {out}")
    if "colmap" in what:
        files = sorted((out / "colmap").glob("*.txt"))
        print(f"  colmap/          {len(files)} files, {_size(sum(f.stat().st_size for f in files))} "
              f"({len(cams)} cameras)")
    if "transforms" in what:
        print(f"  transforms.json  {_size((out / 'transforms.json').stat().st_size)} "
              f"({len(cams)} frames)")
    if "glb" in what:
        total = sum((out / "views" / glb_names[n]).stat().st_size for n in cams)
        print(f"  views/           {len(cams)} GLB, {sum(layered.values())} with reflection "
              f"layers, {_size(total)}")
    if "web" in what:
        files = [f for f in (out / "web").iterdir() if f.is_file()]
        print(f"  web/             {len(cams)} views, {len(files)} files, "
              f"{_size(sum(f.stat().st_size for f in files))} (`ibr view {ws.root}` serves it)")
    return 0
