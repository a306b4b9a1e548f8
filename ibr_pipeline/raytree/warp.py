"""Warping a decoded ray tree to a new camera and compositing it (Lochmann et al. 2014, §3.4-3.5).

  1. diffuse flow of the root node (diffuse.py, §3.4, Fig. 4); the root's colour, positions,
     normals and per-pixel attributes (validity bits, IOR, Fresnel code) are read through it;
  2. specular flow of every first-level reflective / refractive node (specular.py, §3.4);
     deeper nodes reuse their parent's flow (the paper keeps only the first level, §3.4
     "Deeper ray flows": their differences "are not easily observable");
  3. push-pull hole filling per node, skipping invalid pixels (fill.py, §3.5);
  4. compositing: the nodes are added, weighted by the Fresnel terms from the new view position,
     normals and IORs (§3.5): I = D + R where the first surface has no Fresnel model (mirror,
     glossy coat), else I = D + F R + (1 - F) T.
`naive_warp` is the baseline of Fig. 7: the composited old image warped with the first-hit depth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from . import ops
from .decode import DecodeOptions, Decoded, decode, eta_of
from .diffuse import diffuse_flow, projection_matrix
from .encoding import FRESNEL_DIELECTRIC, FRESNEL_NONE, FRESNEL_PANE, REFLECTIVE, RayTree
from .fill import push_pull
from .specular import SpecularOptions, specular_flow


@dataclass
class WarpOptions:
    decode: DecodeOptions = field(default_factory=DecodeOptions)
    specular: SpecularOptions = field(default_factory=SpecularOptions)
    fpi_eps: float = 0.5      # fixed-point convergence threshold, new-image pixels (§3.4)
    rel_tol: float = 0.05     # depth-discontinuity tolerance of the diffuse sampler
    fill: bool = True         # §3.5 push-pull hole filling

    def validate(self) -> None:
        from ..errors import InputError
        s = self.specular
        for name, val, lo, hi in (("steps", s.steps, 0, 1000), ("eps_deg", s.eps_deg, 1e-4, 90),
                                  ("step_scale", s.step_scale, 1e-4, 10),
                                  ("fpi_eps", self.fpi_eps, 1e-3, 10),
                                  ("normal_ksize", self.decode.normal_ksize, 1, 31)):
            if not (lo <= val <= hi):
                raise InputError(f"warp option {name} must be in [{lo}, {hi}], got {val}")


@dataclass
class WarpResult:
    image: np.ndarray                 # (Hn, Wn, 3) composited new view
    nodes: list[np.ndarray]           # per node (Hn, Wn, 3) warped + filled radiance (pre-Fresnel)
    fresnel: np.ndarray               # (Hn, Wn) reflection weight F used (1 where none)
    diffuse_ok: np.ndarray            # (Hn, Wn) diffuse flow defined (else disocclusion hole)
    region: list[np.ndarray]          # per node (Hn, Wn) the node contributes at this new pixel
    defined: list[np.ndarray]         # per node (Hn, Wn) flow found (specular: Delta <= eps)
    history: dict = field(default_factory=dict)   # node -> (pixels (M, 2), Delta (steps+1, M))
    timings: dict = field(default_factory=dict)   # seconds per stage (Table 1)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def fresnel_weight(code: torch.Tensor, cos_i: torch.Tensor, ior: torch.Tensor) -> torch.Tensor:
    """Reflection weight per pixel (1 where the code is FRESNEL_NONE), as
    synthetic.materials.fresnel_weight: exact dielectric Fresnel or thin-pane reflectance."""
    ior = torch.where(ior > 0, ior, torch.ones_like(ior))
    one = torch.ones_like(cos_i)
    return torch.where(code == FRESNEL_DIELECTRIC, ops.fresnel_dielectric(cos_i, 1.0 / ior),
                       torch.where(code == FRESNEL_PANE, ops.fresnel_pane(cos_i, ior), one))


def composite(nodes: list[torch.Tensor], kinds: list[int], region: list[torch.Tensor],
              code: torch.Tensor, cos_i: torch.Tensor, ior: torch.Tensor):
    """§3.5: nodes added with Fresnel weights. Returns (image (H, W, 3), F (H, W))."""
    F = fresnel_weight(code, cos_i, ior)
    none = code == FRESNEL_NONE
    img = nodes[0].clone()
    for i in range(1, len(nodes)):
        wgt = torch.where(none, torch.ones_like(F), F) if kinds[i] == REFLECTIVE else \
            torch.where(none, torch.zeros_like(F), 1 - F)
        img = img + torch.where(region[i][..., None], wgt[..., None] * nodes[i], torch.zeros_like(img))
    return img, F


def _sync_time(dev, t0):
    ops.sync(dev)
    return time.perf_counter() - t0


def warp_decoded(dec: Decoded, camera, options: WarpOptions | None = None,
                 record_history: bool = False) -> WarpResult:
    """Warp a decoded ray tree to `camera` (scene.Camera, any size)."""
    o = options or WarpOptions()
    dev = dec.device
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    tree = dec.tree
    Wn, Hn = camera.width, camera.height
    P_new = projection_matrix(camera.K, camera.cam_from_world, dev)
    c_new = torch.as_tensor(camera.center, dtype=torch.float32, device=dev)
    P_old = projection_matrix(tree.K, tree.cam_from_world, dev)
    n_nodes = tree.n_nodes
    # 1. diffuse flow (§3.4) and the root buffers read through it
    flow = diffuse_flow(dec.pos[0], dec.valid[0], dec.depth[0], P_new, (Wn, Hn), o.fpi_eps, o.rel_tol)
    ok = flow.ok.reshape(-1)
    src = flow.src.reshape(-1, 2)[ok]
    sampler = ops.Sampler(dec.valid[0], dec.depth[0], o.rel_tol)
    taps = sampler.taps(src)
    stack = torch.cat([dec.rgb[0], dec.pos[0], dec.normal[0]], -1)
    vals, _, _ = sampler.sample(stack, src, taps)
    near = taps[4].clamp_min(0)
    # node validity as decoded (e.g. refraction lost to total internal reflection)
    bits_old = sum((dec.valid[i].reshape(-1).long() << i) for i in range(n_nodes))
    N = Hn * Wn
    buf = torch.zeros(N, 9 + 3, device=dev)
    buf[ok, :9] = vals
    buf[ok, 9] = dec.ior.reshape(-1)[near]
    buf[ok, 10] = dec.fresnel.reshape(-1)[near].float()
    bits_new = torch.zeros(N, dtype=torch.long, device=dev)
    bits_new[ok] = bits_old[near]
    tm["warp_diffuse"] = _sync_time(dev, t0)
    # 2. specular flow per first-level node; deeper nodes reuse the parent's flow
    q_node = [flow.src.reshape(-1, 2)] + [None] * (n_nodes - 1)
    node_imgs = [None] * n_nodes
    region = [ok] + [None] * (n_nodes - 1)
    defined = [ok] + [None] * (n_nodes - 1)
    history = {}
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        p = int(tree.parent[i])
        reg = defined[p] & (((bits_new >> i) & 1) > 0)
        region[i] = reg
        q_i = torch.zeros(N, 2, device=dev)
        def_i = torch.zeros(N, dtype=torch.bool, device=dev)
        if p == 0 and bool(reg.any()):
            w = buf[reg, 3:6]
            n = ops.normalize(buf[reg, 6:9])
            eta = None if int(tree.kind[i]) == REFLECTIVE else \
                eta_of(buf[reg, 9], buf[reg, 10].round().long())
            res = specular_flow(w, n, c_new, eta, q_node[0][reg], dec.pos[i], dec.depth[i],
                                dec.valid[i], P_old, o.specular)
            q_i[reg] = res.q
            def_i[reg] = res.defined
            if record_history:
                pix = torch.nonzero(reg.view(Hn, Wn))[:, [1, 0]]
                history[i] = (_np(pix), _np(res.history))
        elif bool(reg.any()):  # deeper node: parent's flow (§3.4 "Deeper ray flows")
            q_i[reg] = q_node[p][reg]
            def_i[reg] = True
        s_i = ops.Sampler(dec.valid[i], dec.depth[i], o.specular.rel_tol)
        img = torch.zeros(N, 3, device=dev)
        if bool(def_i.any()):
            v, _, d_ok = s_i.sample(dec.rgb[i], q_i[def_i])
            def_i[def_i.clone()] = d_ok
            img[def_i] = v[d_ok]
        q_node[i], node_imgs[i], defined[i] = q_i, img, def_i
        name = "warp_reflection" if int(tree.kind[i]) == REFLECTIVE else "warp_refraction"
        tm[name] = tm.get(name, 0.0) + _sync_time(dev, t1)
    # 3. hole filling per node (§3.5)
    t1 = time.perf_counter()
    root = buf.view(Hn, Wn, -1)
    if o.fill:
        extra = torch.stack([((bits_new >> i) & 1).float() for i in range(n_nodes)], -1)
        root = push_pull(torch.cat([root, extra.view(Hn, Wn, -1)], -1), ok.view(Hn, Wn))
        hole = ~ok
        filled_bits = (root[..., 12:] > 0.5).reshape(N, -1)
        for i in range(1, n_nodes):
            region[i] = region[i] | (hole & filled_bits[:, i])
        root = root[..., :12]
    tm["fill_diffuse"] = _sync_time(dev, t1)
    nodes = [root[..., :3]]
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        img = node_imgs[i].view(Hn, Wn, 3)
        if o.fill:
            img = push_pull(img, defined[i].view(Hn, Wn))
        nodes.append(img)
        name = "fill_reflection" if int(tree.kind[i]) == REFLECTIVE else "fill_refraction"
        tm[name] = tm.get(name, 0.0) + _sync_time(dev, t1)
    # 4. Fresnel compositing (§3.5) with the new view direction and the warped normals
    t1 = time.perf_counter()
    pos = root[..., 3:6]
    nrm = ops.normalize(root[..., 6:9])
    view = ops.normalize(pos - c_new)
    cos_i = (view * nrm).sum(-1).abs()
    code = root[..., 10].round().long()
    reg_img = [r.view(Hn, Wn) for r in region]
    img, F = composite(nodes, [int(k) for k in tree.kind], reg_img, code, cos_i, root[..., 9])
    tm["composite"] = _sync_time(dev, t1)
    tm["warp_total"] = _sync_time(dev, t0)
    return WarpResult(image=_np(img), nodes=[_np(x) for x in nodes], fresnel=_np(F),
                      diffuse_ok=_np(ok.view(Hn, Wn)), region=[_np(r) for r in reg_img],
                      defined=[_np(d.view(Hn, Wn)) for d in defined], history=history, timings=tm)


def old_composite(dec: Decoded) -> torch.Tensor:
    """The full image of the old camera composited from the decoded nodes (H, W, 3)."""
    view = dec.dirs[0]
    cos_i = (view * dec.normal[0]).sum(-1).abs()
    nodes = [torch.where(dec.valid[i][..., None], dec.rgb[i], torch.zeros_like(dec.rgb[i]))
             for i in range(dec.tree.n_nodes)]
    img, _ = composite(nodes, [int(k) for k in dec.tree.kind], dec.valid, dec.fresnel, cos_i, dec.ior)
    return img


def naive_warp(dec: Decoded, camera, options: WarpOptions | None = None) -> np.ndarray:
    """Baseline (Fig. 7 left): everything warped with the first-hit depth, holes push-pulled."""
    o = options or WarpOptions()
    dev = dec.device
    Wn, Hn = camera.width, camera.height
    P_new = projection_matrix(camera.K, camera.cam_from_world, dev)
    flow = diffuse_flow(dec.pos[0], dec.valid[0], dec.depth[0], P_new, (Wn, Hn), o.fpi_eps, o.rel_tol)
    sampler = ops.Sampler(dec.valid[0], dec.depth[0], o.rel_tol)
    ok = flow.ok.reshape(-1)
    img = torch.zeros(Hn * Wn, 3, device=dev)
    v, _, _ = sampler.sample(old_composite(dec), flow.src.reshape(-1, 2)[ok])
    img[ok] = v
    img = img.view(Hn, Wn, 3)
    if o.fill:
        img = push_pull(img, flow.ok)
    return _np(img)


def warp(tree: RayTree, camera, options: WarpOptions | None = None, device: str = "cpu",
         record_history: bool = False) -> WarpResult:
    """Decode (§3.3) and warp (§3.4-3.5) in one call; timings of every stage in result.timings."""
    o = options or WarpOptions()
    o.validate()
    t0 = time.perf_counter()
    tm: dict[str, float] = {}
    dec = decode(tree, device, o.decode, tm)
    res = warp_decoded(dec, camera, o, record_history)
    res.timings = {**tm, **res.timings, "total": _sync_time(dec.device, t0)}
    return res
