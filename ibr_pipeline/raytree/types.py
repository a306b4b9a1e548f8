"""The result types both ray-tree backends return (the torch reference in decode.py / warp.py and
the numba kernels of warp_nb.py): a tree decoded by one backend warps with the other."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .encoding import RayTree


@dataclass
class Decoded:
    """Decoded buffers of one ray tree, torch tensors on one device (float32)."""
    tree: RayTree
    device: torch.device
    K: torch.Tensor                 # (3, 3)
    cam_from_world: torch.Tensor    # (4, 4)
    center: torch.Tensor            # (3,) c_old
    rgb: list[torch.Tensor]         # per node (H, W, 3) (specular nodes: zero outside `box`)
    depth: list[torch.Tensor]       # per node (H, W)
    valid: list[torch.Tensor]       # per node (H, W) bool
    pos: list[torch.Tensor]         # per node (H, W, 3) world positions (W_d, W_r, W_f, ...)
    normal: list[torch.Tensor | None]  # per node (H, W, 3) normals (reconstructed) or None
    dirs: list[torch.Tensor | None] = field(default_factory=list)  # per node unit dirs (in `box`)
    ior: torch.Tensor | None = None      # (H, W)
    fresnel: torch.Tensor | None = None  # (H, W) long
    box: tuple | None = None             # (y0, y1, x0, x1): the old pixels with a specular
                                         # node (+ margin); normals / W_s are computed there only
    cache: dict = field(default_factory=dict)  # samplers etc. reused by every warp of this tree

    @property
    def size(self) -> tuple[int, int]:
        return self.tree.size


@dataclass
class WarpResult:
    image: np.ndarray                 # (Hn, Wn, 3) composited new view
    nodes: list[np.ndarray]           # per node (Hn, Wn, 3) warped + filled radiance (pre-Fresnel)
    fresnel: np.ndarray               # (Hn, Wn) reflection weight F used (1 where none)
    diffuse_ok: np.ndarray            # (Hn, Wn) diffuse flow defined (else disocclusion hole)
    region: list[np.ndarray]          # per node (Hn, Wn) the node contributes at this new pixel
    defined: list[np.ndarray]         # per node (Hn, Wn) flow found (specular: Delta <= eps)
    filled: list[np.ndarray] = field(default_factory=list)  # per node (Hn, Wn) undefined pixels
                                      # filled in the position domain (specular.position_fill)
    history: dict = field(default_factory=dict)   # node -> (pixels (M, 2), Delta (steps+1, M)
                                                  # per descent step, final Delta (M,) after
                                                  # the discrete check)
    timings: dict = field(default_factory=dict)   # seconds per stage (Table 1)


def record_decode_timings(timings: dict | None, tic: float, t1: float, t2: float, t3: float) -> None:
    """Table 1's three decode rows from the stage boundaries (both backends)."""
    if timings is not None:
        timings["decode_diffuse"] = t1 - tic
        timings["decode_normal"] = t2 - t1
        timings["decode_specular"] = t3 - t2
