"""Workspaces whose early stages' outputs are built from a synthetic scene's exact ground truth.

A test or benchmark of one stage needs the stages before it; built from ground truth they are
exact (or honestly perturbed), so what is measured is the stage itself. `ingest` runs for real;
then, up to `through`, the files of layout.py are written from the scene's gt/ folder:

  global_mesh  the `poses` outputs: global/cameras.json = the synthetic cameras, metric frame
               (global/poses.json), the input's reflectors; global/mesh.ply = the GT mesh
               (`global_mesh="gt"`), a TSDF fusion of the exact gt/geom depth at `voxel` metres
               ("tsdf": occlusion edges rounded and misplaced by up to a voxel, as a real fused
               mesh), or none
  view_depth   depth.npy = GT depth (times 1 + a smooth random field of std `depth_noise`:
               MVS-like low-frequency errors), edges.png = its depth jumps
  view_mesh    mesh.ply = the depth's grid mesh ("grid": planes.grid_mesh, every `mesh_step`-th
               pixel) or the oracle's simplified, depth-cut grid mesh ("oracle")
  reflection   layers.json, I0/I1/beta, M0/M1 from the GT layers (render/oracle.py)

Later stages then run as usual on the workspace.
"""
from __future__ import annotations

import json
import shutil
import zlib
from pathlib import Path

import numpy as np

from . import layout as L

THROUGH = ("ingest", "global_mesh", "view_depth", "view_mesh", "reflection")


def gt_depth(scene: Path, name: str) -> np.ndarray:
    """The exact z-depth (float64) of capture view `name` of a synthetic scene."""
    with np.load(Path(scene) / "gt" / "geom" / (Path(name).stem + ".npz")) as z:
        return z["depth"].astype(np.float64)


def tsdf_mesh(scene: Path, voxel: float = 0.03, trunc_vox: float = 4.0, source: str = "gt"):
    """(vertices, faces): open3d VoxelBlockGrid fusion of gt/geom depth ("gt") or of the
    scene's depth/*.png sensor frames ("sensor")."""
    import open3d as o3d
    import open3d.core as o3c

    from .io.images import read_depth_png
    from .scene import cameras_from_json

    scene = Path(scene)
    cams = cameras_from_json(scene / "cameras.json")
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1,), (1,)),
                                        voxel, 8, 50000, o3c.Device("CPU:0"))
    for name, cam in cams.items():
        d = (read_depth_png(scene / "depth" / (Path(name).stem + ".png")) if source == "sensor"
             else gt_depth(scene, name).astype(np.float32))
        c = cam.resized(d.shape[1], d.shape[0])
        img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(np.rint(d * 1000).astype(np.uint16))))
        K, T = o3c.Tensor(c.K, o3c.float64), o3c.Tensor(c.cam_from_world, o3c.float64)
        blocks = vbg.compute_unique_block_coordinates(img, K, T, 1000.0, 8.0, 2 * trunc_vox)
        vbg.integrate(blocks, img, K, T, 1000.0, 8.0, trunc_vox)
    m = vbg.extract_triangle_mesh(weight_threshold=1.0).to_legacy()
    return np.asarray(m.vertices), np.asarray(m.triangles)


def smooth_noise(shape, std: float, seed: int) -> np.ndarray:
    """A smooth random field of standard deviation `std` (correlation ~1/40 of the image)."""
    import cv2
    rng = np.random.default_rng(seed)
    H, W = shape
    small = rng.standard_normal((max(2, H // 40), max(2, W // 40))).astype(np.float32)
    f = cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)
    return std * f / max(float(f.std()), 1e-9)


def write_gt_workspace(scene: Path, ws_dir: Path, through: str = "view_mesh", *,
                       global_mesh: str = "gt", voxel: float = 0.03, depth_noise: float = 0.0,
                       mesh: str = "oracle", mesh_step: int | None = None, check_pixels: bool = True):
    """A workspace over synthetic `scene` whose stages up to `through` are ground truth (module
    docstring); returns its Workspace. `mesh_step` defaults to the oracle's grid step ("oracle")
    or 4 ("grid")."""
    from .io.images import write_image
    from .io.mesh import Mesh, write_ply
    from .pipeline import load_configs, run
    from .render.oracle import GRID_STEP, GroundTruth, depth_edges, simplified_grid_mesh
    from .scene import cameras_to_json
    from .stages import STAGES, ingest
    from .workspace import Workspace

    if through not in THROUGH:
        raise ValueError(f"through must be one of {THROUGH}, got {through!r}")
    if global_mesh not in ("gt", "tsdf", "none") or mesh not in ("oracle", "grid"):
        raise ValueError(f"global_mesh must be gt/tsdf/none and mesh oracle/grid, got "
                         f"{global_mesh!r}, {mesh!r}")
    scene, ws_dir = Path(scene).resolve(), Path(ws_dir)
    ws_dir.mkdir(parents=True, exist_ok=True)
    (ws_dir / "ibr.toml").write_text(f"[input]\npath = {json.dumps(str(scene))}\n")
    ws = Workspace(ws_dir)
    configs = load_configs(STAGES, ws, {"ingest": {"check_pixels": check_pixels}})
    run(STAGES, ws, configs, [ingest.STAGE], progress=False)
    upto = THROUGH.index(through)
    if upto < 1:
        return ws
    gt = GroundTruth(scene)
    ws.write_text(L.REGISTERED_CAMERAS, cameras_to_json(gt.cameras))
    ws.write_text(L.HELDOUT_CAMERAS, cameras_to_json({}))
    ws.write_json(L.POSES_REPORT, {"units": "metres", "scale": 1.0, "pose_source": "gt",
                                   "alignment": {"method": "synthetic ground truth"}})
    sc = ws.scene()
    ws.write_json(L.SCENE_REFLECTORS, {"format": "ibr_pipeline.reflectors/1", "units": "metres",
                                       "reflectors": [r.to_dict() for r in sc.reflectors]})
    if global_mesh == "gt":
        shutil.copyfile(scene / "gt" / "mesh.ply", ws.path(L.GLOBAL_MESH))
    elif global_mesh == "tsdf":
        v, f = tsdf_mesh(scene, voxel)
        write_ply(ws.path(L.GLOBAL_MESH), Mesh(v, f))
    if upto < 2:
        return ws
    step = mesh_step or (GRID_STEP if mesh == "oracle" else 4)
    for name, cam in gt.cameras.items():
        depth = gt.geom(name)["depth"].astype(np.float32)
        if depth_noise > 0:
            stem = Path(name).stem
            depth = (depth * (1 + smooth_noise(depth.shape, depth_noise,
                                               zlib.crc32(stem.encode())))).astype(np.float32)
        with ws.atomic_write(ws.view_file(name, L.DEPTH)) as fh:
            np.save(fh, depth)
        write_image(ws.path(ws.view_file(name, L.EDGES)), depth_edges(depth).astype(np.uint8) * 255)
        if upto < 3:
            continue
        if mesh == "oracle":
            v0, f0 = simplified_grid_mesh(cam, depth, step)
        else:
            from .geometry.planes import depth_points, grid_mesh
            v0, f0 = grid_mesh(depth_points(cam, depth), depth, step=step)
        write_ply(ws.path(ws.view_file(name, L.MESH)), Mesh(v0, f0))
        if upto < 4:
            continue
        vd = gt.view(name, True, step)
        l1 = vd.layers[1]
        ws.write_json(ws.view_file(name, L.LAYERS), {"reflector": None if l1 is None else "gt"})
        if l1 is None:
            continue
        l0 = vd.layers[0]
        write_ply(ws.path(ws.view_file(name, L.M0)), Mesh(l0.vertices, l0.faces))
        write_ply(ws.path(ws.view_file(name, L.M1)), Mesh(l1.vertices, l1.faces))
        write_image(ws.path(ws.view_file(name, L.I0)), l0.rgb, sc.image_encoding)
        write_image(ws.path(ws.view_file(name, L.I1)), l1.rgb, sc.image_encoding)
        with ws.atomic_write(ws.view_file(name, L.BETA)) as fh:
            np.save(fh, l0.beta.astype(np.float32))
    return ws
