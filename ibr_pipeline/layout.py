"""The workspace's file contract: every key a stage writes and a later one reads, named once.

Keys are posix paths relative to the workspace ("global/mesh.ply") or, with the prefix "input/",
relative to the input folder (workspace.py maps keys to paths). docs/PIPELINE.md says which stage
writes and which reads each one; a stage module, the renderer and the benchmarks name files only
through this module.
"""
from __future__ import annotations

import hashlib
import json
import re

from .cache import ProcessCache, file_key

# --- ingest --------------------------------------------------------------------------------------
SCENE = "scene.json"                              # the scene manifest
INGEST_IMAGES = "ingest/images"                   # frames prepared from the input (undistorted, upright, video)
INGEST_DEPTH = "ingest/depth"                     # depth frames rewritten as 16-bit mm on the colour camera
INGEST_SPARSE = "ingest/sparse"                   # the input's COLMAP model with undistorted cameras

# --- input folder (read, never written) -----------------------------------------------------------
INPUT = "input/"
USER_REFLECTORS = "input/reflectors.json"         # user-given mirror planes / masks
INPUT_CAMERAS = "input/cameras.json"
INPUT_SPARSE = "input/sparse/0"                   # a COLMAP model given with the images
GT_CAMERAS = "input/gt/cameras.json"              # synthetic captures posed by SfM: the true poses
TEST_CAMERAS = "input/gt/test_cameras.json"       # synthetic scenes: held-out cameras
FLY_CAMERAS = "input/gt/flythrough_cameras.json"  # synthetic scenes: a camera path

# --- poses ---------------------------------------------------------------------------------------
SFM_FILES = ("sfm/cameras.txt", "sfm/images.txt", "sfm/points3D.txt")   # scene frame
REGISTERED_CAMERAS = "global/cameras.json"        # training views: the poses every later stage uses
HELDOUT_CAMERAS = "global/heldout_cameras.json"   # held-out images (poses.holdout_every), scene frame
POSES_REPORT = "global/poses.json"                # scene frame (units, scale), depth ranges, checks
SCENE_REFLECTORS = "global/reflectors.json"       # the input's reflectors in the scene frame
POSED_VIEWS = "global/views.json"                 # SfM estimated a distorted lens: the undistorted images
SFM_IMAGES = "sfm/images"                         # ... written here (and depth frames to sfm/depth)
SFM_DEPTH = "sfm/depth"

# --- global_mesh ---------------------------------------------------------------------------------
GLOBAL_MESH = "global/mesh.ply"                   # G (Xu §4.1)
GLOBAL_REPORT = "global/report.json"
FOUND_REFLECTORS = "global/found_reflectors.json"  # reflectors global_mesh found behind planes
MVS_DEPTH_DIR = "global/mvs"                      # each view's filtered MVS depth (RGB-only captures)

# --- per view: view_file(view, NAME) -------------------------------------------------------------
DEPTH_INIT = "depth_init.npy"    # view_depth: G's depth before refinement
DEPTH = "depth.npy"              # view_depth: refined z-depth
NORMAL = "normal.npy"            # view_depth: world-space normals of the refined depth
EDGES = "edges.png"              # view_depth: Eq. 1 depth edges of the refined depth
REFINE_MASK = "mask.png"         # view_depth: the pixels Eq. 2 refined
DEPTH_REPORT = "depth_report.json"
MESH = "mesh.ply"                # view_mesh: the per-view surface mesh (§4.2.3)
MESH_REPORT = "mesh_report.json"
LAYERS = "layers.json"           # reflection: which reflector, what was kept / discarded
I0, I1, BETA = "I0.png", "I1.png", "beta.npy"   # reflection: Eq. 3 layers and reflectance
M0, M1 = "M0.ply", "M1.ply"      # reflection: surface and mirror-world meshes
TWO_LAYER_FILES = (I0, I1, BETA, M0, M1)

# --- reflection ----------------------------------------------------------------------------------
PLANES = "reflection/planes.json"

# --- render_views / evaluate ---------------------------------------------------------------------
RENDERS = "renders"
RENDER_SETTINGS = "renders/settings.json"  # render_views' RenderSettings, visibility resolved
EVAL_METRICS = "eval/metrics.json"
EVAL_METRICS_PNG = "eval/metrics.png"
EVAL_ENERGY_PNG = "eval/reflection_energy.png"
EVAL_FLY_MP4 = "eval/fly.mp4"
SIDE_BY_SIDE = "eval/side_by_side"

# --- supersample ---------------------------------------------------------------------------------
MODEL = "nn/dsrnet.pt"
TRAIN_JSON = "nn/train.json"
LOSS_PNG = "nn/loss.png"
CHECKPOINT = "nn/checkpoint.pt"
CACHE = "nn/cache"


def view_key(name: str) -> str:
    """A path-safe, unique folder name for a view name such as 'sub/dir/0001.png'."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name)
    if safe == name:
        return safe
    return f"{safe}-{hashlib.sha1(name.encode()).hexdigest()[:6]}"


def view_dir(view: str) -> str:
    return f"views/{view_key(view)}"


def view_file(view: str, filename: str) -> str:
    return f"{view_dir(view)}/{filename}"


def mvs_depth_file(view: str) -> str:
    """The MVS z-depth map (.npy, float32, working resolution, 0 = none) G was fused from."""
    return f"{MVS_DEPTH_DIR}/{view_key(view)}.npy"


def render_file(render_set: str, filename: str) -> str:
    """A file of one render set of `render_views` (renders/<set>/0000.png, cameras.json, ...)."""
    return f"{RENDERS}/{render_set}/{filename}"


def has_two_layers(ws, view: str) -> bool:
    """Whether `reflection` gave the view a reflection layer (layers.json names a reflector)."""
    p = ws.path(view_file(view, LAYERS))
    if not p.is_file():
        return False
    try:
        return json.loads(p.read_text()).get("reflector") is not None
    except (OSError, json.JSONDecodeError, AttributeError):
        return False


def renderer_files(ws, view: str, layers: bool = True) -> list[str]:
    """The per-view keys the IBR renderer (render/ibr.py) reads, besides the view's image: its
    mesh and depth edges, and with `layers` the reflection outputs where `reflection` wrote
    them (a view without a reflector renders single-layer)."""
    keys = [view_file(view, MESH), view_file(view, EDGES)]
    if layers and ws.exists(view_file(view, LAYERS)):
        keys.append(view_file(view, LAYERS))
        if has_two_layers(ws, view):
            keys += [view_file(view, f) for f in TWO_LAYER_FILES]
    return keys


def posed_scene(ws, scene=None):
    """The scene every stage after `poses` reads: scene.json, with each view's image and depth
    replaced by the undistorted ones when SfM estimated a distorted lens (global/views.json)."""
    import dataclasses

    from .errors import InputError
    scene = ws.scene() if scene is None else scene
    p = ws.path(POSED_VIEWS)
    if not p.is_file():
        return scene
    try:
        views = json.loads(p.read_text())["views"]
        keys = {n: (str(d["image"]), d.get("depth")) for n, d in views.items()}
    except (OSError, json.JSONDecodeError, KeyError, TypeError, AttributeError) as e:
        raise InputError(f"{p}: malformed ({e}); rerun `ibr poses {ws.root} --force`") from None
    return dataclasses.replace(scene, views=tuple(
        dataclasses.replace(v, image=keys[v.name][0], depth=keys[v.name][1]) if v.name in keys
        else v for v in scene.views))


def registered_cameras(ws) -> dict:
    """{view name: Camera} of the views `global_mesh` registered (the poses every later stage
    uses). Raises InputError when `poses` has not run yet. Parsed once per version of the file
    in a process, each call given its own copies: a per-view stage's planning and tasks ask for it
    several times per view, and parsing and checking the cameras costs more than copying them."""
    import copy

    from .errors import InputError
    from .scene import cameras_from_json
    p = ws.path(REGISTERED_CAMERAS)
    if not p.is_file():
        raise InputError(f"{p}: no registered cameras yet (run `ibr poses` first)")
    return copy.deepcopy(_CAMERAS.get(file_key(p), lambda: cameras_from_json(p)))


_CAMERAS = ProcessCache(1)  # the last registered_cameras file read in this process


def heldout_cameras(ws) -> dict:
    """{image name: Camera} of the images `poses` held out (empty when none were)."""
    from .scene import cameras_from_json
    p = ws.path(HELDOUT_CAMERAS)
    return cameras_from_json(p) if p.is_file() else {}


def scene_reflectors(ws) -> tuple:
    """The input's reflectors in the scene frame (what `poses` wrote; masks are workspace keys)."""
    from .errors import InputError
    from .scene import Reflector
    p = ws.path(SCENE_REFLECTORS)
    if not p.is_file():
        return ()
    try:
        data = json.loads(p.read_text())
        return tuple(Reflector.from_dict(d, f"{p}: reflector {i}")
                     for i, d in enumerate(data["reflectors"]))
    except (OSError, json.JSONDecodeError, KeyError, TypeError):
        raise InputError(f"{p}: malformed (rerun `ibr poses`)") from None


def outline_depth_key(scene, view: str, dense: str) -> str:
    """The depth an outline-given reflector's plane is fitted to in `view`: the MVS map
    global_mesh fused (dense = mvs), else the view's depth frame."""
    return mvs_depth_file(view) if dense == "mvs" else scene.view(view).depth


def global_dense(ws) -> str:
    """How global_mesh made G ("mvs" or "rgbd", global/report.json)."""
    try:
        return str(json.loads(ws.path(GLOBAL_REPORT).read_text())["dense"])
    except (OSError, KeyError, TypeError, ValueError):
        from .errors import InputError
        raise InputError(f"{ws.path(GLOBAL_REPORT)}: missing or malformed (run `ibr run "
                         f"{ws.root} --from global_mesh`)") from None


def outline_keys(ws, scene) -> list[str]:
    """The depth maps geometry/user_reflectors reads (none when no reflector is given by an
    outline)."""
    views = [r.outline[0] for r in scene_reflectors(ws) if r.plane is None]
    if not views:
        return []
    dense = global_dense(ws)
    return [GLOBAL_REPORT] + [k for v in views if (k := outline_depth_key(scene, v, dense))]


def poses_report(ws) -> dict:
    """global/poses.json: the scene frame (units, scale, transform), depth ranges, checks."""
    from .errors import InputError
    p = ws.path(POSES_REPORT)
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        raise InputError(f"{p}: malformed JSON (rerun `ibr poses`)") from None
