"""Synthetic test cases for the ray-tree warper (raytree/): a ray tree traced at an old camera, the
exact render at a new camera, and ground-truth masks (for tests and the raytree benchmark).

Cases (a planar mirror, a chrome sphere, refractive slab / sphere):
  mirror   mirror_room: the wall mirror (planar, kr 1)
  chrome   curved: the chrome sphere (kr 0.85)
  crystal  curved: the crystal sphere (dielectric, IOR 1.5, tinted)
  pane     glass_room: the glass partition (thin pane, IOR 1.5: reflection + transmission)
Moves: the new camera is the old one translated `move_cm` to the right (camera x) and yawed
`yaw_deg` about its own vertical axis ("camera moves of 5 cm and 3 deg").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import Camera, moved_camera

# name: (scene, eye, look-at target)
CASES = {
    "mirror": ("mirror_room", (2.3, 2.7, 1.45), (0.025, 2.0, 1.3)),
    "chrome": ("curved", (2.1, 2.1, 1.35), (0.9, 1.2, 1.0)),
    "crystal": ("curved", (2.0, 2.1, 1.35), (3.1, 3.1, 0.98)),
    "pane": ("glass_room", (2.0, 2.5, 1.4), (3.61, 2.2, 1.2)),
}
HFOV_DEG = 62.0  # as the synthetic scenes (synthetic.paths)


@dataclass
class Case:
    name: str
    tree: object            # encoding.RayTree of the old camera
    old: Camera
    new: Camera
    gt_image: np.ndarray    # (H, W, 3) exact render at the new camera
    gt_render: dict         # the tracer's full output at the new camera
    disoccluded: np.ndarray  # (H, W) new pixels whose first hit the old camera does not see
    specular: np.ndarray    # (H, W) new pixels whose first surface is reflective / refractive


def disocclusion_mask(tree, new: Camera, new_depth: np.ndarray, rel: float = 0.01,
                      abs_m: float = 0.01) -> np.ndarray:
    """True where the new view's first-hit point is not seen by the old camera (outside its frame
    or hidden: its old z-depth differs from the old depth image by > rel * z + abs_m)."""
    old = tree.camera()
    W, H = old.size
    valid = new_depth > 0
    X = new.unproject(new.pixel_grid().reshape(-1, 2), new_depth.reshape(-1))
    uv, z = old.project(X)
    t = np.rint(uv).astype(np.int64)
    inside = (t[:, 0] >= 0) & (t[:, 0] < W) & (t[:, 1] >= 0) & (t[:, 1] < H) & (z > 0)
    zo = np.zeros(len(z))
    zo[inside] = tree.depth[0][t[inside, 1], t[inside, 0]]
    seen = inside & (np.abs(zo - z) <= rel * z + abs_m)
    return (~seen).reshape(new_depth.shape) | ~valid


def _box(a: np.ndarray, s: int) -> np.ndarray:
    H, W = a.shape[0] // s, a.shape[1] // s
    return a.reshape(H, s, W, s, *a.shape[2:]).mean(axis=(1, 3))


def _supersampled(render: dict, s: int) -> dict:
    """Anti-aliased render from an s x s supersampled one (s odd): radiance keys are box-averaged
    (invalid samples count as 0, i.e. coverage-weighted), geometry and attributes are taken from
    the centre sample, which lies exactly on the low-resolution pixel centre (Camera.resized)."""
    c = s // 2
    out = {}
    for k, v in render.items():
        if k in ("D", "R", "T", "image", "I0", "I1"):
            out[k] = _box(v, s)
        elif k in ("R", "T"):
            out[k] = _box(v, s)
        else:
            out[k] = v[c::s, c::s]
    # the reflective node carries kr inside ray_tree_from_render: average kr * R, then divide
    kr = _box(render["kr"], s)
    out["R"] = np.where(kr[..., None] > 0, _box(render["kr"][..., None] * render["R"], s) /
                        np.maximum(out["kr"][..., None], 1e-6), 0.0)
    return out


def make_case(name: str, width: int = 320, height: int = 240, move_cm: float = 5.0,
              yaw_deg: float = 3.0, seed: int = 0, tracer=None, supersample: int = 1) -> Case:
    """Trace the case `name` (CASES) at width x height; `supersample` (odd) > 1 renders
    s x s samples per pixel and box-filters radiance (anti-aliased images, as a real renderer
    would deliver) while depth / normals / masks come from the pixel-centre sample."""
    from ..raytree.encoding import from_synthetic
    from .raytree import ray_tree_from_render
    from .scenes import build_world
    from .tracer import Tracer

    if name not in CASES:
        raise ValueError(f"unknown case {name!r} (choose from {', '.join(CASES)})")
    scene, eye, target = CASES[name]
    K = Camera.intrinsics_from_fov(width, height, HFOV_DEG)
    old = Camera.look_at(eye, target, (0, 0, 1), K, width, height)
    new = moved_camera(old, move_cm, yaw_deg)
    tr = tracer or Tracer(build_world(scene, seed))
    if supersample < 1 or supersample % 2 == 0:
        raise ValueError(f"supersample must be odd and >= 1, got {supersample}")
    if supersample > 1:
        s = supersample
        r_old = _supersampled(tr.trace(old.resized(s * width, s * height)), s)
        r_new = _supersampled(tr.trace(new.resized(s * width, s * height)), s)
    else:
        r_old, r_new = tr.trace(old), tr.trace(new)
    tree = from_synthetic(ray_tree_from_render(r_old, old))
    dis = disocclusion_mask(tree, new, r_new["depth"])
    spec = (r_new["kind"] >= 1) & ((r_new["R_range"] > 0) | (r_new["T_range"] > 0))
    return Case(name, tree, old, new, r_new["image"].astype(np.float32), r_new, dis, spec)
