"""What every stage after `poses` shares: the registered views, cameras of the input in the scene
frame."""
from __future__ import annotations

from .. import layout as L


def registered_views(ctx) -> list[str]:
    """Stage.views for every stage after poses: registered training views, in scene order."""
    cams = L.registered_cameras(ctx.ws)
    return [n for n in ctx.scene.names if n in cams]


def eq1_lambda(ctx, view: str) -> float:
    """Eq. 1's lambda_rel for `view` in a stage whose config has lambda_rel (Xu's) and
    lambda_rel_mvs: the latter when G came from multi-view stereo (global_mesh wrote the view's
    MVS depth map, which such a stage then lists among its inputs)."""
    cfg = ctx.config
    return cfg.lambda_rel_mvs if ctx.ws.exists(L.mvs_depth_file(view)) else cfg.lambda_rel


def is_identity(m: dict | None) -> bool:
    """A poses-report similarity ({scale, R, t}) that changes nothing (None: no map)."""
    import numpy as np
    return not m or (m["scale"] == 1.0 and np.allclose(m["R"], np.eye(3)) and not np.any(m["t"]))


def scene_is_input_frame(ctx) -> bool:
    """The scene frame is the input's own (given poses, kept as they are): what lives in the
    input's frame (its ground truth) can be rendered with the scene's cameras."""
    frame = L.poses_report(ctx.ws)
    return frame.get("pose_source") != "sfm" and is_identity(frame.get("transform"))


def input_cameras(ctx, key: str) -> dict:
    """{name: Camera} of an input camera file (gt/test_cameras.json, ...) mapped into the scene
    frame: by the Sim(3) from the true to the SfM frame when the poses came from SfM and the
    input has its true cameras (gt/cameras.json), else by the input -> scene map of `poses`."""
    import numpy as np

    from ..geometry.align import transform_camera
    from ..scene import cameras_from_json
    p = ctx.ws.path(key)
    if not p.is_file():
        return {}
    cams = cameras_from_json(p)
    frame = L.poses_report(ctx.ws)
    m = frame.get("gt_to_scene") if frame.get("pose_source") == "sfm" else frame.get("transform")
    if is_identity(m):
        return cams
    R, t = np.asarray(m["R"], np.float64), np.asarray(m["t"], np.float64)
    return {n: transform_camera(c, float(m["scale"]), R, t) for n, c in cams.items()}
