"""The numba CPU backend of the ray-tree warper: decode (§3.3), warp (§3.4), fill (§3.5) and
compositing with the fused kernels of nbkernels.py / nbsearch.py. Same inputs and outputs as the
torch path (decode.decode, warp.warp_decoded, warp.naive_warp, fill.push_pull), which stays the
reference and the CUDA path; `backend.resolve` chooses between them."""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from . import nbkernels as nk
from . import nbsearch as ns
from . import ops
from .types import Decoded, WarpResult, record_decode_timings
from .encoding import FRESNEL_NONE, REFLECTIVE, RayTree


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(a)


def supported(tree: RayTree, opts) -> bool:
    """The numba decoder handles first-level specular nodes with forward-difference or exact
    normals; other trees (deeper nodes, normal_diff='min') are decoded by the torch code."""
    return (all(int(p) == 0 for p in tree.parent[1:]) and opts.normal_diff == "forward"
            and opts.normal_ksize > 1)


def decode(tree: RayTree, opts, timings: dict | None = None):
    """decode.decode on the CPU with the numba kernels (§3.3); returns types.Decoded."""
    tic = time.perf_counter()
    n = tree.n_nodes
    K = torch.as_tensor(tree.K, dtype=torch.float32)
    T = torch.as_tensor(tree.cam_from_world, dtype=torch.float32)
    center = -T[:3, :3].T @ T[:3, 3]
    depth = _f32(tree.depth)                      # (n, H, W)
    bits = np.asarray(tree.valid)
    valid = nk.unpack_valid(bits, depth)
    H, W = depth[0].shape
    pos = np.zeros((n, H, W, 3), np.float32)
    nk.unproject(depth[0], K.numpy().astype(np.float64), T.numpy().astype(np.float64), pos[0])
    t1 = time.perf_counter()
    margin = opts.normal_ksize // 2 + 3
    box = ops.bbox(torch.from_numpy(valid[1:].any(0) & valid[0]), margin) if n > 1 else None
    box = box or (0, 0, 0, 0)
    y0, y1, x0, x1 = box
    nd = np.zeros((H, W, 3), np.float32)
    c64 = center.numpy().astype(np.float64)
    if opts.normals == "exact":
        nd = ops.normalize(torch.as_tensor(tree.normal, dtype=torch.float32)).numpy()
    elif y1 > y0 and x1 > x0:
        kern = ops.gaussian_kernel(opts.normal_ksize, opts.normal_sigma, "cpu").numpy().astype(np.float64)
        nk.normals_box(pos[0], valid[0], c64, y0, y1, x0, x1, kern, nd, float(opts.normal_edge_rel))
    t2 = time.perf_counter()
    ior = _f32(tree.ior)
    fres = np.asarray(tree.fresnel).astype(np.int32)
    dirs = np.zeros((n, H, W, 3), np.float32)
    valid[1:, :y0] = False
    valid[1:, y1:] = False
    valid[1:, :, :x0] = False
    valid[1:, :, x1:] = False
    if y1 > y0 and x1 > x0:
        nk.decode_box(pos[0], nd, c64, depth, valid, np.asarray(tree.kind, np.int64), ior, fres,
                      y0, y1, x0, x1, dirs, pos)
    rgb = [torch.from_numpy(np.asarray(tree.rgb[0])).float()]   # float16 -> 32: torch is 3x faster
    for i in range(1, n):
        r = torch.zeros(H, W, 3)
        r[y0:y1, x0:x1] = torch.from_numpy(np.asarray(tree.rgb[i][y0:y1, x0:x1]))
        rgb.append(r)
    t3 = time.perf_counter()
    record_decode_timings(timings, tic, t1, t2, t3)
    return Decoded(tree, torch.device("cpu"), K, T, center, rgb, [_t(d) for d in depth],
                   [_t(v) for v in valid], [_t(p) for p in pos], [_t(nd)] + [None] * (n - 1),
                   [_t(d) for d in dirs], _t(ior), _t(fres), box)


def _np(t) -> np.ndarray:
    return np.ascontiguousarray(t.numpy() if isinstance(t, torch.Tensor) else t)


def root_tables(dec, rel_tol: float) -> dict:
    """Per-tree constants of the root (cached in Decoded.cache): flat buffers, node bits and the
    quad smoothness with the node-set / Fresnel label (as warp._root_tables)."""
    key = ("nb_root", rel_tol)
    if key not in dec.cache:
        H, W = dec.valid[0].shape
        fres = _np(dec.fresnel).astype(np.int32)
        vs = np.stack([_np(v) for v in dec.valid])
        bits, label = nk.root_labels(vs, fres)
        v0, d0 = vs[0], _np(dec.depth[0]).astype(np.float32)
        qok = nk.quad_ok(v0, d0, rel_tol, label, np.zeros((0, 0, 3), np.float32), 0.0)
        dec.cache[key] = dict(
            W=W, H=H, qok=qok, valid=v0.reshape(-1), bits=bits,
            pos=_np(dec.pos[0]).reshape(-1, 3), normal=_np(dec.normal[0]).reshape(-1, 3),
            rgb=_np(dec.rgb[0]).reshape(-1, 3), ior=_np(dec.ior).reshape(-1),
            fres=fres.reshape(-1))
    return dec.cache[key]


def node_tables(dec, i: int, rel_tol: float, div_tol: float) -> dict:
    """Node i cropped to Decoded.box (as warp._node_tables): W_s, delta, valid, rgb, the quad
    smoothness with the ray-spread slack, the crop origin and the lower median of delta."""
    key = ("nb_node", i, rel_tol, div_tol)
    if key not in dec.cache:
        y0, y1, x0, x1 = dec.box
        c = (slice(y0, y1), slice(x0, x1))
        valid = _np(dec.valid[i][c])
        delta = _np(dec.depth[i][c]).astype(np.float32)
        dirs = _np(dec.dirs[i][c]) if div_tol > 0 else np.zeros((0, 0, 3), np.float32)
        qok = nk.quad_ok(valid, delta, rel_tol, np.zeros((0, 0), np.int32), dirs, float(div_tol))
        dv = delta[valid]
        med = float(np.partition(dv, (len(dv) - 1) // 2)[(len(dv) - 1) // 2]) if len(dv) else 0.0
        h, w = valid.shape
        dec.cache[key] = dict(W=w, H=h, x0=x0, y0=y0, qok=qok, valid=valid.reshape(-1),
                              Ws=_np(dec.pos[i][c]).reshape(-1, 3), delta=delta.reshape(-1),
                              rgb=_np(dec.rgb[i][c]).reshape(-1, 3), med=med, has_med=len(dv) > 0)
    return dec.cache[key]


def push_pull(img: np.ndarray, valid: np.ndarray, inplace: bool = False) -> np.ndarray:
    """fill.push_pull with the numba kernels (§3.5): (H, W, C) float32, valid (H, W) bool;
    inplace: fill the holes of `img` itself (a C-contiguous float32 array)."""
    if valid.all():
        return img
    if not valid.any():
        return np.zeros_like(img)
    img = _f32(img)
    levels = []
    w0 = valid.astype(np.float32)
    c, w = img, w0
    while min(c.shape[:2]) > 1:
        c, w = ns.pull(c, w)
        levels.append((c, w))
    if not levels:
        return img * valid[..., None]
    filled = levels[-1][0]
    for c, w in reversed(levels[:-1]):
        filled = ns.push(filled, c, w, False, valid)
    return ns.push(filled, img if inplace else img.copy(), w0, True, valid)


def _flow(dec, R, camera, o, extra, out, c0):
    from .diffuse import projection_matrix
    Wn, Hn = camera.width, camera.height
    P_new = projection_matrix(camera.K, camera.cam_from_world, "cpu").numpy().astype(np.float64)
    uv, keys, direct = nk.project_splat(R["pos"], R["valid"], P_new, Wn, Hn)
    filled = nk.closest_3x3(keys, direct, Wn, Hn)
    return nk.fixed_point(uv, direct, filled, R["qok"], R["valid"], extra, R["W"], R["H"], Wn, Hn,
                          float(o.fpi_eps), True, out, c0)


def _position_fill(qc, dfn, v, pix, T, Wn, Hn, s) -> np.ndarray:
    """Our extension (specular.position_fill): undefined pixels of one node's search take q
    from the affine fit of their defined neighbours' q and read the node there; qc and v are
    updated in place. Returns the filled mask (the node had a valid tap there)."""
    filled = np.zeros(len(qc), bool)
    if s.fill_radius <= 0 or s.fill_rounds <= 0 or dfn.all() or not dfn.any():
        return filled
    qf, fl = ns.position_fill(qc, dfn, pix.astype(np.int64), Wn, Hn, int(s.fill_radius), int(s.fill_rounds))
    fi = np.flatnonzero(fl)
    vf, ok = ns.sample_points(qf[fi], T["qok"], T["valid"], T["rgb"], T["W"], T["H"])
    fi = fi[ok]
    qc[fi], v[fi], filled[fi] = qf[fi], vf[ok], True
    return filled


def warp_decoded(dec, camera, o, record_history: bool = False):
    """warp._warp_decoded with the numba kernels; returns types.WarpResult."""
    from .diffuse import projection_matrix
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    tree = dec.tree
    Wn, Hn = camera.width, camera.height
    N = Hn * Wn
    n_nodes = tree.n_nodes
    kinds = [int(k) for k in tree.kind]
    c_new = np.asarray(camera.center, np.float32).astype(np.float64)
    P_old = projection_matrix(tree.K, tree.cam_from_world, "cpu").numpy().astype(np.float64)
    R = root_tables(dec, o.rel_tol)
    # 1. diffuse flow (§3.4); the root radiance goes straight into the fill buffer (channels
    #    0-2), the per-node compositing weights into channels 3.. (push-pulled together)
    root = np.zeros((N, 3 + n_nodes - 1), np.float32)
    src, ok, near = _flow(dec, R, camera, o, R["rgb"], root, 0)
    pix_s = nk.specular_pixels(ok, near, R["bits"])
    wn, ior_s, code_s, bits_s, F_s = nk.root_attrs(pix_s, src, R["qok"], R["valid"], R["pos"], R["normal"],
                                                   R["ior"], R["fres"], R["bits"], c_new, R["W"], R["H"])
    none = code_s == FRESNEL_NONE
    tm["warp_diffuse"] = time.perf_counter() - t0
    # 2. specular flow per first-level node (§3.4); deeper nodes reuse the parent's flow
    Ms = len(pix_s)
    q_node = [src[pix_s]] + [None] * (n_nodes - 1)
    def_node = [np.ones(Ms, bool)] + [None] * (n_nodes - 1)
    val_node = [None] * n_nodes
    fill_node = [np.zeros(Ms, bool)] * n_nodes
    history = {}
    s = o.specular
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        p = int(tree.parent[i])
        T = node_tables(dec, i, s.rel_tol, s.div_tol)
        off = np.array([T["x0"], T["y0"]], np.float32)
        reg = def_node[p] & (((bits_s >> i) & 1) > 0)
        ri = np.flatnonzero(reg)
        q_i = np.zeros((Ms, 2), np.float32)
        def_i = np.zeros(Ms, bool)
        fl_i = np.zeros(Ms, bool)
        val_i = np.zeros((Ms, 3), np.float32)
        if p == 0 and len(ri):
            refl = kinds[i] == REFLECTIVE
            eta = np.ones(len(ri), np.float32)
            if not refl:
                eta = np.where((code_s[ri] == 2) | (ior_s[ri] <= 0), 1.0,
                               1.0 / np.maximum(ior_s[ri], 1e-6)).astype(np.float32)
            P_c = P_old.copy()   # the old projection in crop pixel coordinates
            P_c[0] -= T["x0"] * P_old[2]
            P_c[1] -= T["y0"] * P_old[2]
            qc, E, dfn, v, hist, _, _ = ns.specular_search(
                np.ascontiguousarray(wn[ri, :3]), np.ascontiguousarray(wn[ri, 3:]), eta, refl,
                q_node[0][ri] - off, T["Ws"], T["delta"], T["valid"], T["qok"], T["rgb"], T["W"], T["H"],
                P_c, c_new, T["med"], T["has_med"], s.steps, math.radians(s.eps_deg), float(s.step_scale),
                float(s.max_step_px), float(s.min_step_px), int(s.snap_radius), record_history)
            if record_history:
                pp = pix_s[ri]
                history[i] = (np.stack([pp % Wn, pp // Wn], -1), hist, E)
            fl_i[ri] = _position_fill(qc, dfn, v, pix_s[ri], T, Wn, Hn, s)
            dfn = dfn | fl_i[ri]
        elif len(ri):  # deeper node: parent's flow (§3.4 "Deeper ray flows")
            qc = q_node[p][ri] - off
            v, d_ok = ns.sample_points(qc, T["qok"], T["valid"], T["rgb"], T["W"], T["H"])
            dfn = def_node[p][ri] & d_ok
            v[~dfn] = 0
        if len(ri):
            q_i[ri] = qc + off
            def_i[ri] = dfn
            val_i[ri] = v
        q_node[i], def_node[i], val_node[i] = q_i, def_i, val_i   # def_node: has a value
        fill_node[i] = fl_i
        rw = np.where(none, 1.0, F_s) if kinds[i] == REFLECTIVE else np.where(none, 0.0, 1.0 - F_s)
        root[pix_s, 2 + i] = np.where(reg, rw, 0.0)
        name = "warp_reflection" if kinds[i] == REFLECTIVE else "warp_refraction"
        tm[name] = tm.get(name, 0.0) + time.perf_counter() - t1
    # 3. hole filling (§3.5): root radiance + compositing weights over the diffuse holes
    t1 = time.perf_counter()
    okv = ok.reshape(Hn, Wn)
    if o.fill:
        root = push_pull(root.reshape(Hn, Wn, -1), okv, inplace=True).reshape(N, -1)
    tm["fill_diffuse"] = time.perf_counter() - t1
    img = root[:, :3].copy()
    F_full = np.ones(N, np.float32)
    F_full[pix_s] = F_s
    nodes_np, region_np, defined_np = [root[:, :3].reshape(Hn, Wn, 3)], [okv], [okv]
    filled_np = [np.zeros((Hn, Wn), bool)]
    for i in range(1, n_nodes):
        t1 = time.perf_counter()
        use, ubox = ns.positive(root, 2 + i, Wn)   # the node contributes (incl. filled holes)
        d_full = np.zeros(N, bool)
        d_full[pix_s] = def_node[i]
        node = np.zeros((N, 3), np.float32)
        node[pix_s] = val_node[i]
        nv, dv = node.reshape(Hn, Wn, 3), d_full.reshape(Hn, Wn)
        ps = pix_s[def_node[i]]
        if len(ps):   # bounding box of use | defined
            ys, xs = ps // Wn, ps % Wn
            ubox = (min(ubox[0], ys.min()), max(ubox[1], ys.max() + 1),
                    min(ubox[2], xs.min()), max(ubox[3], xs.max() + 1))
        if ubox[1] > ubox[0] and o.fill:
            by0, by1, bx0, bx1 = (int(b) for b in ubox)
            nv[by0:by1, bx0:bx1] = push_pull(nv[by0:by1, bx0:bx1], np.ascontiguousarray(dv[by0:by1, bx0:bx1]))
        name = "fill_reflection" if kinds[i] == REFLECTIVE else "fill_refraction"
        tm[name] = tm.get(name, 0.0) + time.perf_counter() - t1
        t1 = time.perf_counter()   # 4. compositing (§3.5): nodes added with their Fresnel weights
        ns.add_weighted(img, root, 2 + i, node, use)
        nodes_np.append(nv)
        region_np.append(use.reshape(Hn, Wn))
        f_full = np.zeros(N, bool)
        f_full[pix_s] = fill_node[i]
        defined_np.append(dv & ~f_full.reshape(Hn, Wn))   # found by the search (Delta <= eps)
        filled_np.append(f_full.reshape(Hn, Wn))
        tm["composite"] = tm.get("composite", 0.0) + time.perf_counter() - t1
    tm.setdefault("composite", 0.0)
    tm["warp_total"] = time.perf_counter() - t0
    return WarpResult(image=img.reshape(Hn, Wn, 3), nodes=nodes_np, fresnel=F_full.reshape(Hn, Wn),
                      diffuse_ok=okv, region=region_np, defined=defined_np, filled=filled_np,
                      history=history, timings=tm)


def naive_warp(dec, camera, o) -> np.ndarray:
    """warp.naive_warp with the numba kernels: the old composite warped with the first-hit depth
    (the same diffuse-flow kernels as ours), holes push-pulled."""
    R = root_tables(dec, o.rel_tol)
    key = "nb_old_composite"
    if key not in dec.cache:
        n = dec.tree.n_nodes
        dec.cache[key] = nk.old_composite(np.stack([_np(r) for r in dec.rgb]),
                                          np.stack([_np(v) for v in dec.valid]), _np(dec.dirs[0]),
                                          _np(dec.normal[0]), np.asarray(dec.tree.kind[:n], np.int64),
                                          _np(dec.fresnel).astype(np.int64), _np(dec.ior))
    Wn, Hn = camera.width, camera.height
    img = np.zeros((Hn * Wn, 3), np.float32)
    _, ok, _ = _flow(dec, R, camera, o, dec.cache[key], img, 0)
    img = img.reshape(Hn, Wn, 3)
    return push_pull(img, ok.reshape(Hn, Wn)) if o.fill else img
