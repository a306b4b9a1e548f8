"""The RGBZ ray tree: our one-file encoding of Lochmann et al. 2014, §3.2 "Encoding".

A `RayTree` holds, for one rendered (old) camera:
  nodes      typed nodes in pre-order: kind 0 diffuse (the root), 1 reflective, 2 refractive;
             `parent[i]` is the index of the parent node (-1 for the root). Deeper nodes are
             allowed by the format (their parent is a non-root node); the warper handles the
             first level, as the paper does ("a ray tree with only three nodes", §3.4).
  rgb        (N, H, W, 3) radiance per node, pre-multiplied by every view-independent factor
             (reflectance kr, filter colour / tint) but NOT by the view-dependent Fresnel term
             (§3.2 "Radiance").
  depth      (N, H, W): the root holds the z-depth to the camera (an ordinary depth image, our
             convention scene.py), a child the distance from its parent's hit along its ray
             ("depth is given in world space relative to the parent node", §3.2 "Depth").
  valid      (H, W) uint8 bit mask, bit i set where node i contributed (§3.3 "Validity").
  ior        (H, W) per-pixel index of refraction of the first surface (0 where there is no
             refractive node) (§3.3 "Index of refraction").
  fresnel    (H, W) Fresnel model code of the first surface (synthetic.materials.FRESNEL_*):
             0 none (mirror / glossy coat: the reflective node has weight 1), 1 dielectric
             interface (F, 1 - F), 2 thin pane (thin-sheet F; transmitted rays are not bent).
  K, cam_from_world, size   the old camera (OpenCV conventions); `mvp` is the equivalent 4x4
             model-view-projection matrix in pixel units ([K 0; 0 0 0 1] @ cam_from_world), the
             matrix the paper transmits (§3.3 "Inputs to the decoding are the old MVP matrix").
  normal     optional exact first-hit normals (not transmitted by the paper, which reconstructs
             them from depth, §3.3; kept only for the ablation `normals="exact"`).

File: one .npz (`write_tree` / `read_tree`), key "format" = FORMAT.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

FORMAT = "ibr_pipeline.raytree/1"
DIFFUSE, REFLECTIVE, REFRACTIVE = 0, 1, 2
KIND_NAMES = {DIFFUSE: "diffuse", REFLECTIVE: "reflective", REFRACTIVE: "refractive"}
FRESNEL_NONE, FRESNEL_DIELECTRIC, FRESNEL_PANE = 0, 1, 2  # == synthetic.materials codes


@dataclass(frozen=True, eq=False)
class RayTree:
    kind: np.ndarray            # (N,) int8 node kinds, pre-order, kind[0] == DIFFUSE
    parent: np.ndarray          # (N,) int16, parent[0] == -1
    rgb: np.ndarray             # (N, H, W, 3) float16/float32
    depth: np.ndarray           # (N, H, W) float32
    valid: np.ndarray           # (H, W) uint8 bit mask (bit i = node i)
    ior: np.ndarray             # (H, W) float32
    fresnel: np.ndarray         # (H, W) uint8
    K: np.ndarray               # (3, 3)
    cam_from_world: np.ndarray  # (4, 4)
    normal: np.ndarray | None = None  # (H, W, 3) optional exact normals

    def __post_init__(self) -> None:
        check_tree(self)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.depth.shape[2]), int(self.depth.shape[1])

    @property
    def n_nodes(self) -> int:
        return int(len(self.kind))

    @property
    def mvp(self) -> np.ndarray:
        """4x4 model-view-projection in pixel units: (x, y, z, 1) -> (u z, v z, z, 1)."""
        P = np.eye(4)
        P[:3, :3] = self.K
        return P @ self.cam_from_world

    def camera(self):
        from ..scene import Camera
        return Camera(self.K, self.cam_from_world, *self.size)

    def node_valid(self, i: int) -> np.ndarray:
        return (self.valid & np.uint8(1 << i)) > 0

    def node_index(self, kind: int) -> int | None:
        """Index of the first-level node of `kind` (child of the root), or None."""
        for i in range(1, self.n_nodes):
            if int(self.kind[i]) == kind and int(self.parent[i]) == 0:
                return i
        return None


def check_tree(t: RayTree) -> None:
    """Shape / value checks; raises ValueError naming the field."""
    n = len(t.kind)
    if n < 1 or n > 8 or t.kind.ndim != 1 or t.parent.shape != (n,):
        raise ValueError(f"ray tree: need 1..8 nodes with kind (N,) and parent (N,), got "
                         f"{t.kind.shape}, {t.parent.shape}")
    if int(t.kind[0]) != DIFFUSE or int(t.parent[0]) != -1:
        raise ValueError("ray tree: node 0 must be the diffuse root (parent -1)")
    for i in range(1, n):
        if not 0 <= int(t.parent[i]) < i or int(t.kind[i]) not in (REFLECTIVE, REFRACTIVE):
            raise ValueError(f"ray tree: node {i} needs a reflective/refractive kind and an earlier "
                             f"parent (pre-order), got kind {t.kind[i]}, parent {t.parent[i]}")
    if t.depth.ndim != 3 or t.depth.shape[0] != n:
        raise ValueError(f"ray tree: depth must be (N, H, W) with N={n}, got {t.depth.shape}")
    H, W = t.depth.shape[1:]
    for name, arr, shape in (("rgb", t.rgb, (n, H, W, 3)), ("valid", t.valid, (H, W)),
                             ("ior", t.ior, (H, W)), ("fresnel", t.fresnel, (H, W)),
                             ("K", t.K, (3, 3)), ("cam_from_world", t.cam_from_world, (4, 4))):
        if arr.shape != shape:
            raise ValueError(f"ray tree: {name} must be {shape}, got {arr.shape}")
    if t.normal is not None and t.normal.shape != (H, W, 3):
        raise ValueError(f"ray tree: normal must be {(H, W, 3)}, got {t.normal.shape}")


def transmitted_bits(tree: RayTree) -> int:
    """Uncompressed size of one frame, §3.3 "Transmitted data": P x (N x 40 + D + M) + 12 x 16.

    40 = 8+8+8 bits RGB + 16 bits depth per node; D = bits of the validity mask, one per
    non-root node (the paper: "a single reflection and refraction with a diffuse image: a bit
    mask of two bits"); M = bits of the per-pixel IOR index, ceil(log2(#specular materials))
    ("for two specular materials we have one bit per pixel"); 12 x 16 = the model-view matrix
    as twelve 16-bit floats.
    """
    W, H = tree.size
    n = tree.n_nodes
    d_bits = n - 1
    mats = {(float(i), int(c)) for i, c in zip(tree.ior[tree.ior > 0].ravel(),
                                               tree.fresnel[tree.ior > 0].ravel())}
    m_bits = int(math.ceil(math.log2(len(mats)))) if len(mats) > 1 else 0
    return W * H * (n * 40 + d_bits + m_bits) + 12 * 16


def from_synthetic(pair: dict[str, np.ndarray]) -> RayTree:
    """Convert a synthetic ray tree (synthetic.raytree.ray_tree_from_render / read_ray_tree)."""
    need = ("D", "D_z", "R", "R_z", "T", "T_z", "valid", "ior", "fresnel_code", "K", "cam_from_world")
    missing = [k for k in need if k not in pair]
    if missing:
        raise InputError(f"synthetic ray tree: missing keys {', '.join(missing)}")
    rgb = np.stack([pair["D"], pair["R"], pair["T"]]).astype(np.float16)
    depth = np.stack([pair["D_z"], pair["R_z"], pair["T_z"]]).astype(np.float32)
    normal = pair.get("normal")
    return RayTree(kind=np.array([DIFFUSE, REFLECTIVE, REFRACTIVE], np.int8),
                   parent=np.array([-1, 0, 0], np.int16), rgb=rgb, depth=depth,
                   valid=np.asarray(pair["valid"], np.uint8),  # bits 1/2/4 == nodes 0/1/2
                   ior=np.asarray(pair["ior"], np.float32),
                   fresnel=np.asarray(pair["fresnel_code"], np.uint8),
                   K=np.asarray(pair["K"], np.float64),
                   cam_from_world=np.asarray(pair["cam_from_world"], np.float64),
                   normal=None if normal is None else np.asarray(normal, np.float32))


def write_tree(path: Path, tree: RayTree) -> None:
    """Write one .npz, atomically."""
    from ..workspace import atomic_path
    arrays = dict(format=np.array(FORMAT), kind=tree.kind, parent=tree.parent, rgb=tree.rgb,
                  depth=tree.depth, valid=tree.valid, ior=tree.ior, fresnel=tree.fresnel, K=tree.K,
                  cam_from_world=tree.cam_from_world, mvp=tree.mvp,
                  size=np.array(tree.size), transmitted_bits=np.array(transmitted_bits(tree)))
    if tree.normal is not None:
        arrays["normal"] = tree.normal.astype(np.float16)
    with atomic_path(Path(path)) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zip / pickle / format errors
        raise InputError(f"{path}: cannot read ray tree ({type(e).__name__}: {e})") from None


def read_tree(path: Path) -> RayTree:
    """Read our format, or convert a synthetic pair file (gt/raytree/pair_NN.npz) on the fly."""
    d = _load_npz(path)
    try:
        if "format" not in d and "D_z" in d:
            tree = from_synthetic(d)
        elif "format" in d and str(d["format"]) == FORMAT:
            tree = RayTree(kind=d["kind"].astype(np.int8), parent=d["parent"].astype(np.int16),
                           rgb=d["rgb"], depth=d["depth"].astype(np.float32),
                           valid=d["valid"].astype(np.uint8), ior=d["ior"].astype(np.float32),
                           fresnel=d["fresnel"].astype(np.uint8), K=d["K"].astype(np.float64),
                           cam_from_world=d["cam_from_world"].astype(np.float64),
                           normal=d["normal"].astype(np.float32) if "normal" in d else None)
        else:
            raise InputError(f"{path}: not a ray tree (no format {FORMAT!r} and no synthetic keys)")
    except (ValueError, KeyError) as e:
        raise InputError(f"{path}: invalid ray tree ({e})") from None
    for name in ("rgb", "depth", "ior"):
        if not np.all(np.isfinite(getattr(tree, name))):
            raise InputError(f"{path}: ray tree field {name} contains NaN or infinite values")
    from ..scene import Camera
    try:
        Camera(tree.K, tree.cam_from_world, *tree.size)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    return tree


def read_pair_target(path: Path):
    """(new Camera, GT image (H,W,3) float32, GT depth) of a synthetic pair file, or None."""
    from ..scene import Camera
    d = _load_npz(path)
    if "new_K" not in d:
        return None
    w, h = (int(x) for x in d["new_size"])
    cam = Camera(d["new_K"], d["new_cam_from_world"], w, h)
    return cam, d["new_image"].astype(np.float32), d["new_depth"].astype(np.float32)
