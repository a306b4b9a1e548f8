"""Decoding of an RGBZ ray tree into position / normal buffers (Lochmann et al. 2014, §3.3).

Per pixel l of the old image:
  W_d(l) = unproject(M_old, (x, y, z))                                  "Diffuse position"
  n_d(l) = (W_d(l + (0,1)) - W_d(l)) x (W_d(l + (1,0)) - W_d(l)),
           smoothed by a 7x7 Gaussian (Fig. 3)                           "Normals"
  w_r    = w_d + delta r_hat, r = reflect(w_d - c_old, n_d)             Eq. 1 "Reflected position"
  w_f    = w_d + delta f_hat, f = refract(w_d - c_old, n_d, eta)        "Refracted position"
Deeper nodes use their parent's positions and normals ("Deeper ray tree decoding"); the normals of
a non-root parent are reconstructed the same way from its positions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from . import ops
from .encoding import FRESNEL_PANE, REFLECTIVE, RayTree
from .types import Decoded, record_decode_timings


@dataclass
class DecodeOptions:
    normals: str = "reconstruct"   # "reconstruct" (§3.3, from depth) or "exact" (ablation)
    normal_ksize: int = 7          # §3.3: "a 7x7 gaussian blur kernel"
    normal_sigma: float = 0.0      # 0: OpenCV's default sigma for the kernel size (1.4 for 7)
    normal_diff: str = "forward"   # "forward": the paper's neighbour differences; "min": the
                                   # shorter of forward/backward difference per axis (fewer
                                   # normals across depth edges; an option, not the default)
    normal_edge_rel: float = 0.02  # our extension: the 7x7 blur of the root normals skips taps
                                   # whose distance to the camera differs from the centre's by
                                   # more than this fraction (edge-stopping: a sphere's rim no
                                   # longer takes the wall's normals); 0: the paper's plain blur


def reconstruct_normals(W: torch.Tensor, valid: torch.Tensor, eye: torch.Tensor | None = None,
                        ksize: int = 7, sigma: float = 0.0, diff: str = "forward",
                        edge_rel: float = 0.02) -> torch.Tensor:
    """Screen-space normals from world positions (H, W, 3), §3.3 "Normals":
    n = (W(l+(0,1)) - W(l)) x (W(l+(1,0)) - W(l)), then a ksize x ksize Gaussian (Fig. 3).
    At the last row/column the backward difference is used. Normals face `eye` when given.
    edge_rel > 0 (with `eye`; our extension): a forward difference across a depth edge (distance
    to the camera changes by > edge_rel) is replaced by the backward one where that one is
    smooth, and the blur is edge-stopping (edge_blur)."""
    ops.check(W, (None, None, 3), "positions")
    ops.check(valid, tuple(W.shape[:2]), "valid")
    if diff not in ("forward", "min"):
        raise ValueError(f"normal_diff must be 'forward' or 'min', got {diff!r}")
    edge = edge_rel > 0 and eye is not None
    z = (W.double() - eye.double()).norm(dim=-1) if edge else None   # distance to the camera

    def diffs(axis: int):
        fwd = torch.zeros_like(W)
        bwd = torch.zeros_like(W)
        if axis == 0:
            fwd[:-1] = W[1:] - W[:-1]
            bwd[1:] = W[1:] - W[:-1]
            fv = torch.zeros_like(valid)
            bv = torch.zeros_like(valid)
            fv[:-1] = valid[1:] & valid[:-1]
            bv[1:] = valid[1:] & valid[:-1]
        else:
            fwd[:, :-1] = W[:, 1:] - W[:, :-1]
            bwd[:, 1:] = W[:, 1:] - W[:, :-1]
            fv = torch.zeros_like(valid)
            bv = torch.zeros_like(valid)
            fv[:, :-1] = valid[:, 1:] & valid[:, :-1]
            bv[:, 1:] = valid[:, 1:] & valid[:, :-1]
        if diff == "forward":
            use_b = ~fv & bv
            if edge:   # our extension: not across a depth edge when the other side is smooth
                jump_f = torch.zeros_like(valid)
                jump_b = torch.zeros_like(valid)
                if axis == 0:
                    jump_f[:-1] = (z[1:] - z[:-1]).abs() > edge_rel * z[:-1]
                    jump_b[1:] = (z[1:] - z[:-1]).abs() > edge_rel * z[1:]
                else:
                    jump_f[:, :-1] = (z[:, 1:] - z[:, :-1]).abs() > edge_rel * z[:, :-1]
                    jump_b[:, 1:] = (z[:, 1:] - z[:, :-1]).abs() > edge_rel * z[:, 1:]
                use_b = use_b | (fv & bv & jump_f & ~jump_b)
        else:
            use_b = bv & (~fv | (bwd.norm(dim=-1) < fwd.norm(dim=-1)))
        return torch.where(use_b[..., None], bwd, fwd), fv | bv

    dy, vy = diffs(0)   # W(l + (0, 1)) - W(l): one row down
    dx, vx = diffs(1)   # W(l + (1, 0)) - W(l): one column right
    n = torch.linalg.cross(dy, dx, dim=-1)
    ok = valid & vx & vy & (n.norm(dim=-1) > 0)
    n = ops.normalize(n)
    if eye is not None:  # orient towards the camera (a backward difference flips the sign)
        flip = ((eye - W) * n).sum(-1, keepdim=True) < 0
        n = torch.where(flip, -n, n)
    if ksize > 1 and edge:
        n = edge_blur(n, ok, z, ksize, sigma, edge_rel)
    elif ksize > 1:  # §3.3: 7x7 Gaussian against discretisation / quantisation errors (Fig. 3)
        n = ops.blur_masked(n, ok, ksize, sigma)
    return ops.normalize(n)


def edge_blur(n: torch.Tensor, ok: torch.Tensor, z: torch.Tensor, ksize: int, sigma: float,
              rel: float) -> torch.Tensor:
    """Edge-stopping version of §3.3's Gaussian normal blur (our extension): pixel i averages the
    defined normals n_j (ok) of its ksize x ksize window with weights g(dx) g(dy), only taps with
    |z_j - z_i| <= rel z_i (z: distance to the camera, float64); taps outside the image have no
    weight. Where no tap passes, the window's defined normals without the depth test. The paper's
    blur mixes both sides of a depth edge, so a sphere's rim (and W_r there, Eq. 1) took the
    background's normals: omega was wrong there and the search could not reach 1 deg (§3.4).
    (H, W, 3) -> (H, W, 3), not normalised. = nbkernels.normals_box with rel > 0."""
    k = ops.gaussian_kernel(ksize, sigma, "cpu", torch.float64).tolist()
    r = ksize // 2
    H, W = ok.shape
    F = torch.nn.functional
    nd = n.double()
    npd = F.pad(nd.permute(2, 0, 1), (r, r, r, r))                     # zero outside
    zp = F.pad(z[None], (r, r, r, r))[0]
    okp = F.pad(ok.double()[None], (r, r, r, r))[0]
    acc, wsum = torch.zeros_like(nd), torch.zeros_like(z)
    acc0, wsum0 = torch.zeros_like(nd), torch.zeros_like(z)
    for a in range(ksize):
        for b in range(ksize):
            w0 = okp[a:a + H, b:b + W] * (k[a] * k[b])
            w = w0 * ((zp[a:a + H, b:b + W] - z).abs() <= rel * z)
            nj = npd[:, a:a + H, b:b + W].permute(1, 2, 0)
            acc += w[..., None] * nj
            wsum += w
            acc0 += w0[..., None] * nj
            wsum0 += w0
    out = torch.where((wsum > 0)[..., None], acc, acc0)
    return out.to(n.dtype)


def decode(tree: RayTree, device: str | torch.device = "cpu", options: DecodeOptions | None = None,
           timings: dict | None = None, backend: str = "auto") -> Decoded:
    """Decode every node in pre-order (§3.3). `timings` (if given) gets seconds per step.
    backend (backend.resolve): "numba" decodes with the fused CPU kernels (warp_nb.decode, same
    buffers) when the tree is supported there (first-level nodes, forward differences)."""
    import time
    opts = options or DecodeOptions()
    if opts.normals not in ("reconstruct", "exact"):
        raise ValueError(f"normals must be 'reconstruct' or 'exact', got {opts.normals!r}")
    if opts.normals == "exact" and tree.normal is None:
        raise ValueError("normals='exact' needs a ray tree with exact normals")
    from .backend import resolve
    if resolve(backend, device) == "numba":
        from . import warp_nb
        if warp_nb.supported(tree, opts):
            return warp_nb.decode(tree, opts, timings)
    dev = torch.device(device)
    f32 = dict(device=dev, dtype=torch.float32)
    tic = time.perf_counter()
    K = torch.as_tensor(tree.K, **f32)
    T = torch.as_tensor(tree.cam_from_world, **f32)
    center = -T[:3, :3].T @ T[:3, 3]
    n_nodes = tree.n_nodes
    rgb = [torch.from_numpy(np.asarray(tree.rgb[0])).to(**f32)]
    depth = [torch.as_tensor(tree.depth[i], **f32) for i in range(n_nodes)]
    bits = torch.as_tensor(tree.valid, device=dev).to(torch.int32)
    valid = [((bits >> i) & 1) > 0 for i in range(n_nodes)]
    valid[0] = valid[0] & (depth[0] > 0)
    # diffuse position: W_d = unproject(M_old, (x, y, z))  (§3.3)
    Wd = ops.unproject(K, T, depth[0])
    ops.sync(dev)
    t1 = time.perf_counter()
    # Normals and specular positions matter only where a specular node exists: compute them on
    # the bounding box of those pixels, grown by the normal stencil (forward difference + the
    # 7x7 blur radius + 1), so the values there are exactly those of a full-image pass.
    H, W = depth[0].shape
    spec = (bits >> 1) > 0
    margin = opts.normal_ksize // 2 + 3
    box = ops.bbox(spec & valid[0], margin) if n_nodes > 1 else None
    if box is None:
        box = (0, 0, 0, 0)
    y0, y1, x0, x1 = box
    crop = (slice(y0, y1), slice(x0, x1))
    nd = torch.zeros(H, W, 3, **f32)
    if opts.normals == "exact":
        nd = ops.normalize(torch.as_tensor(tree.normal, **f32))
    elif y1 > y0 and x1 > x0:
        nd[crop] = reconstruct_normals(Wd[crop], valid[0][crop], center, opts.normal_ksize,
                                       opts.normal_sigma, opts.normal_diff, opts.normal_edge_rel)
    ops.sync(dev)
    t2 = time.perf_counter()
    ior = torch.as_tensor(tree.ior, **f32)
    fres = torch.as_tensor(tree.fresnel, device=dev).long()
    pos = [Wd] + [None] * (n_nodes - 1)
    normal = [nd] + [None] * (n_nodes - 1)
    # incoming directions and the specular nodes' radiance: needed in the box only (zero outside)
    dirs = [torch.zeros(H, W, 3, **f32)] + [None] * (n_nodes - 1)
    dirs[0][crop] = ops.normalize(Wd[crop] - center)
    for i in range(1, n_nodes):
        rgb.append(torch.zeros(H, W, 3, **f32))
        rgb[i][crop] = torch.from_numpy(np.asarray(tree.rgb[i][y0:y1, x0:x1])).to(**f32)
    pos_c = [Wd[crop]] + [None] * (n_nodes - 1)
    nrm_c = [nd[crop]] + [None] * (n_nodes - 1)
    dir_c = [dirs[0][crop]] + [None] * (n_nodes - 1)
    for i in range(1, n_nodes):
        p = int(tree.parent[i])
        d_in, n_p = dir_c[p], nrm_c[p]
        if n_p is None:  # deeper node: reconstruct the parent's normals from its positions
            n_p = reconstruct_normals(pos_c[p], valid[p][crop], None, opts.normal_ksize,
                                      opts.normal_sigma, opts.normal_diff)
            n_p = nrm_c[p] = torch.where(((d_in * n_p).sum(-1, keepdim=True) > 0), -n_p, n_p)
            normal[p] = torch.zeros(H, W, 3, **f32)
            normal[p][crop] = n_p
        if int(tree.kind[i]) == REFLECTIVE:
            r = ops.reflect(d_in, n_p)                                  # §3.3 Eq. 1
            tir = torch.zeros_like(valid[i][crop])
        else:
            eta = eta_of(ior[crop], fres[crop])
            r, tir = ops.refract(d_in, n_p, eta)                        # §3.3 refracted position
        r = ops.normalize(r)
        v = torch.zeros_like(valid[i])
        v[crop] = valid[i][crop] & valid[p][crop] & ~tir & (depth[i][crop] > 0)
        valid[i] = v
        pos_c[i] = pos_c[p] + depth[i][crop][..., None] * r             # w = w_parent + delta r_hat
        dir_c[i] = r
        pos[i] = torch.zeros(H, W, 3, **f32)
        pos[i][crop] = pos_c[i]
        dirs[i] = torch.zeros(H, W, 3, **f32)
        dirs[i][crop] = r
    ops.sync(dev)
    t3 = time.perf_counter()
    record_decode_timings(timings, tic, t1, t2, t3)
    return Decoded(tree, dev, K, T, center, rgb, depth, valid, pos, normal, dirs, ior, fres, box)


def eta_of(ior: torch.Tensor, fresnel: torch.Tensor) -> torch.Tensor:
    """Ratio of IORs for the refracted direction: n_air / n_material (entering from air);
    1 for a thin pane (its two parallel faces cancel the bending) or where no IOR is given."""
    eta = 1.0 / ior.clamp_min(1e-6)
    return torch.where((fresnel == FRESNEL_PANE) | (ior <= 0), torch.ones_like(eta), eta)
