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
