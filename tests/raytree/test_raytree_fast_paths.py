"""The speed-ups of ibr_pipeline.raytree give the same values as the straightforward versions."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ibr_pipeline.raytree import ops
from ibr_pipeline.raytree.decode import decode, reconstruct_normals
from ibr_pipeline.raytree.encoding import read_tree
from ibr_pipeline.raytree.fill import push_pull


def _push_pull_reference(img, valid):
    """Full-image push-pull: every level, including the finest, upsampled everywhere."""
    c = img.permute(2, 0, 1)[None] * valid[None, None]
    w = valid[None, None].to(img.dtype)
    levels = [(c, w)]
    while min(c.shape[-2:]) > 1:
        cs, ws = F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(w, 2, ceil_mode=True)
        w = (ws > 0).to(img.dtype)
        c = torch.where(ws > 0, cs / ws.clamp_min(1e-12), torch.zeros_like(cs)) * w
        levels.append((c, w))
    filled = levels[-1][0]
    for c, w in reversed(levels[:-1]):
        up = F.interpolate(filled, size=c.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, c, up)
    return filled[0].permute(1, 2, 0)


def test_push_pull_sparse_finest_push_matches_full():
    g = torch.Generator().manual_seed(0)
    for H, W in ((37, 53), (64, 64), (5, 9)):
        img = torch.rand(H, W, 4, generator=g)
        valid = torch.rand(H, W, generator=g) > 0.7
        assert torch.allclose(push_pull(img, valid), _push_pull_reference(img, valid), atol=1e-6)


def test_sampler_bilinear_and_label_edges():
    H, W = 6, 7
    img = torch.arange(H * W * 2, dtype=torch.float32).view(H, W, 2)
    depth = torch.ones(H, W)
    valid = torch.ones(H, W, dtype=torch.bool)
    q = torch.tensor([[1.25, 2.4], [5.9, 0.1], [0.0, 0.0]])
    s = ops.Sampler(valid, depth)
    v, smooth, ok = s.sample(img, q)
    # the image is linear in x and y: bilinear sampling is exact
    ref = (q[:, 1:] * W + q[:, :1]) * 2 + torch.tensor([0.0, 1.0])
    assert smooth.all() and ok.all() and torch.allclose(v, ref, atol=1e-4)
    # a label change inside the quad (same depth): nearest tap, no blending across it
    label = torch.zeros(H, W, dtype=torch.int32)
    label[:, 2:] = 1
    v2, smooth2, _ = ops.Sampler(valid, depth, label=label).sample(img, q[:1])
    assert not smooth2[0] and torch.equal(v2[0], img[2, 1])   # nearest tap of (1.25, 2.4)
    # a depth discontinuity too
    depth2 = depth.clone()
    depth2[3:] = 2.0
    _, smooth3, _ = ops.Sampler(valid, depth2).sample(img, q[:1])
    assert not smooth3[0]


def test_decode_box_normals_equal_full_image(tiny_scene):
    """Normals are computed on the specular bounding box only: identical to a full pass there."""
    folder, _, _ = tiny_scene
    tree = read_tree(folder / "gt" / "raytree" / "pair_00.npz")
    dec = decode(tree)
    full = reconstruct_normals(dec.pos[0], dec.valid[0], dec.center)
    spec = dec.valid[0] & (dec.valid[1] | dec.valid[2])
    assert spec.any()
    assert torch.allclose(dec.normal[0][spec], full[spec], atol=1e-5)


def test_blur_and_normalize_match_reference():
    g = torch.Generator().manual_seed(1)
    img, mask = torch.rand(23, 31, 3, generator=g), torch.rand(23, 31, generator=g) > 0.3
    k = ops.gaussian_kernel(7, 0.0, "cpu")
    x = torch.cat([(img * mask[..., None]).permute(2, 0, 1), mask[None].float()], 0)[:, None]
    x = F.conv2d(F.pad(x, (3, 3, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, 3, 3), mode="replicate"), k.view(1, 1, -1, 1))[:, 0]
    ref = (x[:-1] / x[-1:].clamp_min(1e-8)).permute(1, 2, 0)
    assert torch.allclose(ops.blur_masked(img, mask, 7), ref, atol=1e-5)
    v = torch.randn(50, 3, generator=g)
    assert torch.allclose(ops.normalize(v), v / v.norm(dim=-1, keepdim=True), atol=1e-6)


def test_quad_table_energy_matches_sampler_and_finite_differences():
    """specular._Energy (one quad-table gather) = angle(omega, bilinear W_s(q) - w) read with
    ops.Sampler; its gradient = central differences of Delta (smooth, curved W_s)."""
    import math

    from ibr_pipeline.raytree.specular import _Energy
    H, W = 9, 11
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                            indexing="ij")
    Ws = torch.stack([0.1 * xx, 0.1 * yy + 0.01 * xx * xx, 3 + 0.02 * yy * yy], -1)
    delta, valid = torch.ones(H, W), torch.ones(H, W, dtype=torch.bool)
    valid[0, 0] = False                      # one invalid pixel: its quad is not smooth
    en = _Energy(Ws, delta, valid, 0.1)
    g = torch.Generator().manual_seed(2)
    M = 40
    q = torch.rand(M, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0])
    w = torch.randn(M, 3, generator=g) * 0.1
    om = ops.normalize(torch.randn(M, 3, generator=g) * 0.2 + torch.tensor([0.3, 0.3, 1.0]))
    wP, oP = w.T.contiguous().unbind(0), om.T.contiguous().unbind(0)
    E, gx, gy, smooth = en(q[:, 0].contiguous(), q[:, 1].contiguous(), wP, oP)
    p, sm, ok = en.sampler.sample(Ws, q)
    assert torch.equal(smooth, sm)
    assert torch.allclose(E, ops.angle(om, p - w), atol=2e-5)
    h = 1e-2
    for d, gd in ((torch.tensor([h, 0.0]), gx), (torch.tensor([0.0, h]), gy)):
        Ep = ops.angle(om, en.sampler.sample(Ws, q + d)[0] - w)
        Em = ops.angle(om, en.sampler.sample(Ws, q - d)[0] - w)
        fd = (Ep - Em) / (2 * h)
        inner = smooth & en.sampler.sample(Ws, q + d)[1] & en.sampler.sample(Ws, q - d)[1]
        assert inner.sum() > 20
        assert torch.allclose(gd[inner], fd[inner], atol=2e-3, rtol=2e-2)
    # non-smooth: the nearest valid tap, zero gradient; outside the image: Delta = pi
    qo = torch.tensor([[0.2, 0.3], [-3.0, 4.0]])
    E2, gx2, gy2, s2 = en(qo[:, 0], qo[:, 1], tuple(x[:2] for x in wP), tuple(x[:2] for x in oP))
    assert not s2.any() and torch.all(gx2 == 0) and torch.all(gy2 == 0)
    assert torch.allclose(E2[0], ops.angle(om[0], en.sampler.sample(Ws, qo[:1])[0][0] - w[0]), atol=2e-5)
    assert E2[1] == math.pi


def test_sampler_slack_loosens_depth_test():
    H, W = 4, 4
    valid = torch.ones(H, W, dtype=torch.bool)
    key = torch.ones(H, W)
    key[:, 2:] = 1.2                                   # a 20 % step between columns 1 and 2
    q = torch.tensor([[1.5, 1.5]])
    assert not ops.Sampler(valid, key, 0.1).taps(q).smooth[0]
    assert ops.Sampler(valid, key, 0.1, slack=torch.full((H, W), 0.1)).taps(q).smooth[0]


def test_diffuse_flow_values_equal_sampling_at_taps(tiny_scene):
    from ibr_pipeline.raytree.diffuse import diffuse_flow, projection_matrix
    from ibr_pipeline.scene import moved_camera
    folder, _, _ = tiny_scene
    tree = read_tree(folder / "gt" / "raytree" / "pair_00.npz")
    dec = decode(tree)
    cam = moved_camera(tree.camera())
    S = ops.Sampler(dec.valid[0], dec.depth[0], 0.05)
    P = projection_matrix(cam.K, cam.cam_from_world, "cpu")
    rgb = S.chw(dec.rgb[0])
    f = diffuse_flow(dec.pos[0], dec.valid[0], dec.depth[0], P, cam.size, sampler=S, extra=rgb)
    ref, _, _ = S.sample(rgb, None, f.taps)
    assert len(f.pix) > 0.9 * f.ok.numel() and torch.equal(f.values, ref)
    assert torch.equal(torch.sort(f.pix).values, torch.nonzero(f.ok.reshape(-1)).squeeze(-1))
    assert torch.allclose(f.taps.q, f.src.reshape(-1, 2)[f.pix])
