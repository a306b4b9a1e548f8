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
from .backend import resolve
from .decode import DecodeOptions, Decoded, decode, eta_of
from .diffuse import diffuse_flow, projection_matrix
from .encoding import FRESNEL_DIELECTRIC, FRESNEL_NONE, FRESNEL_PANE, REFLECTIVE, RayTree
from .fill import push_pull
from .specular import SpecularOptions, position_fill, quad_table, specular_flow
from .types import WarpResult


@dataclass
class WarpOptions:
    decode: DecodeOptions = field(default_factory=DecodeOptions)
    specular: SpecularOptions = field(default_factory=SpecularOptions)
    fpi_eps: float = 0.5      # fixed-point convergence threshold, new-image pixels (§3.4)
    rel_tol: float = 0.05     # depth-discontinuity tolerance of the diffuse sampler
    fill: bool = True         # §3.5 push-pull hole filling
    backend: str = "auto"     # "torch" (eager reference, CPU / CUDA), "numba" (fused CPU kernels,
                              # warp_nb.py) or "auto": numba for CPU tensors when it imports

    def validate(self) -> None:
        from ..errors import InputError
        from .backend import BACKENDS
        if self.backend not in BACKENDS:
            raise InputError(f"warp option backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        s = self.specular
        for name, val, lo, hi in (("steps", s.steps, 0, 1000), ("eps_deg", s.eps_deg, 1e-4, 90),
                                  ("step_scale", s.step_scale, 1e-4, 10),
                                  ("fpi_eps", self.fpi_eps, 1e-3, 10),
                                  ("fill_radius", s.fill_radius, 0, 16), ("fill_rounds", s.fill_rounds, 0, 64),
                                  ("normal_ksize", self.decode.normal_ksize, 1, 31)):
            if not (lo <= val <= hi):
                raise InputError(f"warp option {name} must be in [{lo}, {hi}], got {val}")


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


def _root_tables(dec: Decoded, rel_tol: float):
    """Per-tree constants of the root, built once per decoded tree (Decoded.cache): its sampler,
    the (1, 6, h, w) table of positions + normals in Decoded.box, the node validity bits (P,) and the
    (1, 3, H, W) radiance."""
    key = ("root", rel_tol)
    if key not in dec.cache:
        n_nodes = dec.tree.n_nodes
        bits = torch.zeros_like(dec.valid[0], dtype=torch.int32)
        for i in range(n_nodes):
            bits |= dec.valid[i].to(torch.int32) << i
        label = bits * 4 + dec.fresnel.to(torch.int32)   # node set + Fresnel model per pixel
        sampler = ops.Sampler(dec.valid[0], dec.depth[0], rel_tol, label)
        y0, y1, x0, x1 = dec.box   # positions + normals are only read at specular pixels
        table = torch.cat([dec.pos[0][y0:y1, x0:x1], dec.normal[0][y0:y1, x0:x1]], -1)
        table = table.permute(2, 0, 1)[None].contiguous()
        dec.cache[key] = (sampler, table, bits.reshape(-1), sampler.chw(dec.rgb[0]))
    return dec.cache[key]


def _sample_box(table: torch.Tensor, box, t: ops.Taps, W: int) -> torch.Tensor:
    """Sample a (1, C, h, w) table covering box = (y0, y1, x0, x1) of the old image with the
    full-image taps `t` (every tap involved lies in the box): bilinear where t.smooth, else the
    nearest valid tap, exactly as ops.Sampler.sample on the full image."""
    y0, y1, x0, x1 = box
    hc, wc = y1 - y0, x1 - x0
    C = table.shape[1]
    if len(t.q) == 0:
        return torch.zeros(0, C, device=table.device)
    qx, qy = t.q[:, 0] - x0, t.q[:, 1] - y0
    gx = qx * (2.0 / (wc - 1)) - 1 if wc > 1 else torch.zeros_like(qx)
    gy = qy * (2.0 / (hc - 1)) - 1 if hc > 1 else torch.zeros_like(qy)
    out = torch.nn.functional.grid_sample(table, torch.stack([gx, gy], -1).view(1, 1, -1, 2),
                                          mode="bilinear", padding_mode="border",
                                          align_corners=True)[0, :, 0].T.contiguous()
    rough = torch.nonzero(~t.smooth).squeeze(-1)
    if len(rough):
        nn = t.nearest[rough].clamp_min(0)
        ny = (nn // W - y0).clamp(0, hc - 1)
        nx = (nn % W - x0).clamp(0, wc - 1)
        out[rough] = table[0].reshape(C, -1)[:, ny * wc + nx].T
    return out


def _node_tables(dec: Decoded, i: int, rel_tol: float, div_tol: float = 0.0):
    """Node i cropped to the specular bounding box (Decoded.box): sampler, W_s, delta, valid,
    rgb, the crop origin (x0, y0) and the bilinear quad table of (W_s, delta) (specular.quad_table). Outside the box the node is invalid (with a margin), so
    searching / sampling in the crop is the same as in the full image."""
    key = ("node", i, rel_tol, div_tol)
    if key not in dec.cache:
        y0, y1, x0, x1 = dec.box
        c = (slice(y0, y1), slice(x0, x1))
        valid, delta = dec.valid[i][c].contiguous(), dec.depth[i][c].contiguous()
        slack = None
        if div_tol > 0:   # depth-discontinuity slack from the spread of the node's rays
            d = dec.dirs[i][c].permute(2, 0, 1)[None]
            dp = torch.nn.functional.pad(d, (0, 1, 0, 1), mode="replicate")[0]
            h, w = valid.shape
            ch1 = (dp[:, :h, :w] - dp[:, 1:, 1:]).square().sum(0)
            ch2 = (dp[:, :h, 1:] - dp[:, 1:, :w]).square().sum(0)
            slack = div_tol * torch.maximum(ch1, ch2).sqrt()   # chord ~ angle (radians)
        sampler = ops.Sampler(valid, delta, rel_tol, slack=slack)
        Ws = dec.pos[i][c].contiguous()
        dec.cache[key] = (sampler, Ws, delta, valid, sampler.chw(dec.rgb[i][c]), (x0, y0),
                          quad_table(Ws, delta))
    return dec.cache[key]


def warp_decoded(dec: Decoded, camera, options: WarpOptions | None = None,
                 record_history: bool = False) -> WarpResult:
    """Warp a decoded ray tree to `camera` (scene.Camera, any size); options.backend chooses the
    torch code (below) or the numba kernels (warp_nb.warp_decoded, CPU)."""
    if resolve((options or WarpOptions()).backend, dec.device) == "numba":
        from . import warp_nb
        return warp_nb.warp_decoded(dec, camera, options or WarpOptions(), record_history)
    with torch.inference_mode():
        return _warp_decoded(dec, camera, options, record_history)


def _warp_decoded(dec: Decoded, camera, options: WarpOptions | None, record_history: bool) -> WarpResult:
    o = options or WarpOptions()
    dev = dec.device
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    tree = dec.tree
    Wn, Hn = camera.width, camera.height
    N = Hn * Wn
    P_new = projection_matrix(camera.K, camera.cam_from_world, dev)
    c_new = torch.as_tensor(camera.center, dtype=torch.float32, device=dev)
    P_old = projection_matrix(tree.K, tree.cam_from_world, dev)
    n_nodes = tree.n_nodes
    kinds = [int(k) for k in tree.kind]
    # 1. diffuse flow (§3.4); every root buffer is read bilinearly at the sub-pixel fixed-point
    #    location (nearest valid tap across depth discontinuities), reusing the flow's taps
    sampler, table, bits_old, rgb0 = _root_tables(dec, o.rel_tol)
    flow = diffuse_flow(dec.pos[0], dec.valid[0], dec.depth[0], P_new, (Wn, Hn), o.fpi_eps, o.rel_tol,
                        sampler=sampler, extra=rgb0)
    pix, taps = flow.pix, flow.taps
    rgb_k = flow.values   # the root radiance, read in the fixed-point step's bilinear pass
    near = taps.nearest.clamp_min(0)
    bits_k = bits_old[near]
    # only pixels whose first surface is specular need positions, normals, IOR, Fresnel
    sk = torch.nonzero((bits_k >> 1) != 0).squeeze(-1)
    pix_s, near_s, bits_s = pix[sk], near[sk], bits_k[sk]
    pn = _sample_box(table, dec.box, taps[sk], sampler.W)
    w_s, n_s = pn[:, :3], ops.normalize(pn[:, 3:])
    ior_s = dec.ior.reshape(-1)[near_s]
    code_s = dec.fresnel.reshape(-1)[near_s]
    # Fresnel weights from the new view position, the warped normals and the IOR (§3.5)
    cos_i = (ops.normalize(w_s - c_new) * n_s).sum(-1).abs()
    F_s = fresnel_weight(code_s, cos_i, ior_s)
    none = code_s == FRESNEL_NONE
    tm["warp_diffuse"] = _sync_time(dev, t0)
    # 2. specular flow per first-level node; deeper nodes reuse the parent's flow
    Ms = len(sk)
    q_node = [flow.src.reshape(-1, 2)[pix_s]] + [None] * (n_nodes - 1)   # per specular pixel
    def_node = [torch.ones(Ms, dtype=torch.bool, device=dev)] + [None] * (n_nodes - 1)
    val_node = [None] * n_nodes
    wgt_node = [None] * n_nodes
    fill_node = [torch.zeros(Ms, dtype=torch.bool, device=dev)] * n_nodes
    history = {}
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        p = int(tree.parent[i])
        s_i, Ws_c, delta_c, valid_c, rgb_c, (x0, y0), quad_c = _node_tables(dec, i, o.specular.rel_tol, o.specular.div_tol)
        off = torch.tensor([x0, y0], dtype=torch.float32, device=dev)
        reg = def_node[p] & (((bits_s >> i) & 1) > 0)
        ri = torch.nonzero(reg).squeeze(-1)
        q_i = torch.zeros(Ms, 2, device=dev)
        def_i = torch.zeros(Ms, dtype=torch.bool, device=dev)
        fill_i = torch.zeros(Ms, dtype=torch.bool, device=dev)
        val_i = torch.zeros(Ms, 3, device=dev)
        if p == 0 and len(ri):
            w, n = w_s[ri], n_s[ri]
            eta = None if kinds[i] == REFLECTIVE else eta_of(ior_s[ri], code_s[ri])
            P_c = P_old.clone()   # the old projection in crop pixel coordinates
            P_c[0] -= x0 * P_old[2]
            P_c[1] -= y0 * P_old[2]
            res = specular_flow(w, n, c_new, eta, q_node[0][ri] - off, Ws_c, delta_c, valid_c, P_c,
                                o.specular, s_i, record_history, quad_c)
            qc, dfn = res.q, res.defined
            if record_history:
                pp = pix_s[ri]
                history[i] = (_np(torch.stack([pp % Wn, pp // Wn], -1)), _np(res.history),
                              _np(res.energy))
            so = o.specular
            if so.fill_radius > 0 and so.fill_rounds > 0 and bool(dfn.any()) and not bool(dfn.all()):
                # our extension: undefined pixels take q from their defined neighbours' flow
                qc, fl = position_fill(qc, dfn, pix_s[ri], (Wn, Hn), so.fill_radius, so.fill_rounds)
                fill_i[ri] = fl   # kept below only where the node has a valid tap at q
                dfn = dfn | fl
        elif len(ri):  # deeper node: parent's flow (§3.4 "Deeper ray flows")
            qc, dfn = q_node[p][ri] - off, def_node[p][ri]
        if len(ri):
            dsel = torch.nonzero(dfn).squeeze(-1)
            v, _, d_ok = s_i.sample(rgb_c, qc[dsel])
            dd = torch.zeros_like(dfn)
            dd[dsel] = d_ok
            if bool(fill_i[ri].any()):   # a filled pixel without a valid tap: undefined again
                fi = fill_i[ri]
                qc = torch.where((fi & ~dd)[:, None], res.q, qc)
                fill_i[ri] = fi & dd
            q_i[ri] = qc + off
            def_i[ri] = dd
            val_i[ri[dsel]] = v
        q_node[i], def_node[i], val_node[i] = q_i, def_i, val_i   # def_node: has a value
        fill_node[i] = fill_i
        rw = torch.where(none, torch.ones_like(F_s), F_s) if kinds[i] == REFLECTIVE else \
            torch.where(none, torch.zeros_like(F_s), 1 - F_s)
        wgt_node[i] = torch.where(reg, rw, torch.zeros_like(rw))
        name = "warp_reflection" if kinds[i] == REFLECTIVE else "warp_refraction"
        tm[name] = tm.get(name, 0.0) + _sync_time(dev, t1)
    # 3. hole filling (§3.5): the root's radiance and the per-node compositing weights are
    #    push-pulled over the diffuse holes together; each node over its own undefined pixels
    t1 = time.perf_counter()
    root = torch.zeros(N, 3 + n_nodes - 1, device=dev)
    root[pix, :3] = rgb_k
    for i in range(1, n_nodes):
        root[pix_s, 2 + i] = wgt_node[i]
    root = root.view(Hn, Wn, -1)
    if o.fill:
        root = push_pull(root, flow.ok)
    root = root.reshape(N, -1)
    tm["fill_diffuse"] = _sync_time(dev, t1)
    img = root[:, :3].clone()
    F_full = torch.ones(N, device=dev)
    F_full[pix_s] = F_s
    nodes_np = [_np(root[:, :3].view(Hn, Wn, 3))]
    region_np = [_np(flow.ok)]
    defined_np = [_np(flow.ok)]
    filled_np = [np.zeros((Hn, Wn), bool)]
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        wi = root[:, 2 + i]
        use = wi > 0                                   # contributes (incl. filled diffuse holes)
        d_full = torch.zeros(N, dtype=torch.bool, device=dev)
        d_full[pix_s] = def_node[i]
        node = torch.zeros(N, 3, device=dev)
        node[pix_s] = val_node[i]
        box = ops.bbox((use | d_full).view(Hn, Wn))
        if box is not None and o.fill:
            by0, by1, bx0, bx1 = box
            nv = node.view(Hn, Wn, 3)
            nv[by0:by1, bx0:bx1] = push_pull(nv[by0:by1, bx0:bx1].contiguous(),
                                             d_full.view(Hn, Wn)[by0:by1, bx0:bx1].contiguous())
        name = "fill_reflection" if kinds[i] == REFLECTIVE else "fill_refraction"
        tm[name] = tm.get(name, 0.0) + _sync_time(dev, t1)
        # 4. compositing (§3.5): nodes added with their Fresnel weights, at their pixels only
        t1 = time.perf_counter()
        ui = torch.nonzero(use).squeeze(-1)
        img[ui] += wi[ui, None] * node[ui]
        nodes_np.append(_np(node.view(Hn, Wn, 3)))
        region_np.append(_np(use.view(Hn, Wn)))
        f_full = torch.zeros(N, dtype=torch.bool, device=dev)
        f_full[pix_s] = fill_node[i]
        defined_np.append(_np((d_full & ~f_full).view(Hn, Wn)))   # found by the search
        filled_np.append(_np(f_full.view(Hn, Wn)))
        tm["composite"] = tm.get("composite", 0.0) + _sync_time(dev, t1)
    tm.setdefault("composite", 0.0)
    out = _np(img.view(Hn, Wn, 3))
    tm["warp_total"] = _sync_time(dev, t0)
    return WarpResult(image=out, nodes=nodes_np, fresnel=_np(F_full.view(Hn, Wn)),
                      diffuse_ok=_np(flow.ok), region=region_np, defined=defined_np,
                      filled=filled_np, history=history, timings=tm)


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
    if resolve(o.backend, dev) == "numba":   # the same flow / fill kernels as warp_nb.warp_decoded
        from . import warp_nb
        return warp_nb.naive_warp(dec, camera, o)
    with torch.inference_mode():
        P_new = projection_matrix(camera.K, camera.cam_from_world, dev)
        sampler = _root_tables(dec, o.rel_tol)[0]
        flow = diffuse_flow(dec.pos[0], dec.valid[0], dec.depth[0], P_new, (Wn, Hn), o.fpi_eps,
                            o.rel_tol, sampler=sampler)
        img = torch.zeros(Hn * Wn, 3, device=dev)
        v, _, _ = sampler.sample(old_composite(dec), None, flow.taps)
        img[flow.pix] = v
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
    dec = decode(tree, device, o.decode, tm, backend=o.backend)
    t1 = time.perf_counter()
    if resolve(o.backend, dec.device) == "numba":
        from . import warp_nb
        warp_nb.root_tables(dec, o.rel_tol)
        for i in range(1, tree.n_nodes):
            warp_nb.node_tables(dec, i, o.specular.rel_tol, o.specular.div_tol)
    else:
        with torch.inference_mode():   # per-tree tables (samplers, channel-first buffers), §3.3
            _root_tables(dec, o.rel_tol)
            for i in range(1, tree.n_nodes):
                _node_tables(dec, i, o.specular.rel_tol, o.specular.div_tol)
    tm["decode_tables"] = _sync_time(dec.device, t1)
    res = warp_decoded(dec, camera, o, record_history)
    res.timings = {**tm, **res.timings, "total": _sync_time(dec.device, t0)}
    return res
