"""view_depth: the texture-suppressing boundary weight of Eq. 2's colour-edge
cost map (`geodesic.boundary_strength`, half-disc colour gradient) and the masked MVS's `trust_g`
(mask pixels far from G's own edges keep G's depth and are not swept)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ibr_pipeline.geometry import depth_refine as dr
from ibr_pipeline.geometry import geodesic as geo
from ibr_pipeline.geometry.normals import normals_from_depth, points_from_depth
from ibr_pipeline.scene import Camera

W, H = 96, 64
EDGE = 40          # true occlusion edge: foreground (dotted, 1 m) left of it, plain wall (2 m) right


def _cam():
    return Camera(Camera.intrinsics_from_fov(W, H, 60.0), np.eye(4), W, H)


def _dotted_foreground(edge=EDGE, period=5):
    """Linear RGB image: a mid-brown foreground with dark dots (radius 1.5 px, every `period` px)
    left of `edge`, a plain light wall right of it."""
    img = np.empty((H, W, 3), np.float32)
    img[:] = (0.75, 0.72, 0.70)
    img[:, :edge] = (0.30, 0.18, 0.10)
    yy, xx = np.mgrid[0:H, 0:W]
    for cy in range(2, H, period):
        for cx in range(2, edge - 2, period):
            img[(yy - cy) ** 2 + (xx - cx) ** 2 <= 2.25] = (0.02, 0.02, 0.02)
    return img


def test_halfdisc_kernels_are_antisymmetric_and_balanced():
    ks = geo.halfdisc_kernels(4, 8)
    assert len(ks) == 8 and all(k.shape == (9, 9) for k in ks)
    for k in ks:
        assert abs(float(k.sum())) < 1e-6                   # mean minus mean: flat images give 0
        assert np.allclose(k, -k[::-1, ::-1], atol=1e-6)    # the two halves mirror each other
        assert np.isclose(k[k > 0].sum(), 1.0, atol=1e-5)   # each half is a mean
    with pytest.raises(ValueError):
        geo.halfdisc_kernels(0)


def test_boundary_strength_keeps_outlines_and_fades_texture():
    img = _dotted_foreground()
    enc = geo.encode_for_edges(img, 0.0)
    b = geo.boundary_strength(enc, 4)
    outline = b[8:56, EDGE - 1:EDGE + 1].max(axis=1).mean()
    dots = b[8:56, 8:EDGE - 8].max()
    assert outline > 3 * dots                                # texture well below the outline
    plain = geo.colour_edge_map(img)
    weighted = geo.colour_edge_map(img, boundary_radius=4)
    # without the weight, dot rims are full-strength Canny edges like the outline
    assert plain[8:56, 8:EDGE - 8].max() == pytest.approx(1.0)
    assert weighted[8:56, 8:EDGE - 8].max() < 0.5
    assert weighted[8:56, EDGE - 2:EDGE + 2].max(axis=1).min() > 0.9
    with pytest.raises(ValueError):
        geo.boundary_strength(enc[..., 0], 4)


def test_boundary_strength_is_the_max_norm_of_the_half_disc_differences():
    """Reference: per orientation, the Euclidean norm of the filtered colour difference, then the
    maximum; the stage's form (maximum of squared norms, one root) gives the same bits."""
    import cv2
    enc = geo.encode_for_edges(_dotted_foreground(), 0.0)
    for r in (2, 4):
        ref = np.zeros(enc.shape[:2], np.float32)
        for k in geo.halfdisc_kernels(r):
            d = cv2.filter2D(enc, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
            ref = np.maximum(ref, np.sqrt((d * d).sum(axis=2)))
        assert np.array_equal(geo.boundary_strength(enc, r), ref)


def test_eq2_does_not_leak_the_wall_into_a_dotted_foreground():
    """G's edge is 6 px inside the foreground (the wall's depth covers its rim). With plain edges
    every dot costs as much to cross as the outline, so Eq. 2 fills much of the rim from the wall;
    with the boundary weight the rim takes the foreground's depth."""
    cam = _cam()
    truth = np.where(np.arange(W)[None, :] < EDGE, 1.0, 2.0) * np.ones((H, 1))
    init = np.where(np.arange(W)[None, :] < EDGE - 6, 1.0, 2.0) * np.ones((H, 1))
    img = _dotted_foreground()
    region = np.zeros((H, W), bool)
    region[:, EDGE - 16:EDGE + 8] = True
    errs = {}
    for r in (0, 4):
        new, filled, _ = dr.refine(init, cam, img, region, None, 0.05, 15.0, 4, boundary_radius=r)
        assert filled[region].all()
        # wrong-side rim pixels (the outline's own column mixes both sides and is left out)
        errs[r] = float(np.mean(np.abs(new - truth)[:, EDGE - 16:EDGE - 1] > 0.1))
    assert errs[4] < 0.02                   # the rim takes the foreground depth
    assert errs[0] > errs[4] + 0.2          # the texture-blind map leaks the wall into it


def test_trust_g_keeps_g_far_from_its_edges_and_skips_the_sweep(monkeypatch):
    from ibr_pipeline.geometry import mvs

    cam = _cam()
    src = Camera(cam.K, np.array([[1, 0, 0, -0.2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float), W, H)
    g = np.full((H, W), 2.0)
    photo = g * 1.04                     # the MVS is 4 % off everywhere: passes Xu's 5 % check
    swept = {}

    def sweep(*a, mask=None, **k):
        swept["n"] = int(mask.sum())
        return SimpleNamespace(depth=photo, valid=np.ones((H, W), bool))
    monkeypatch.setattr(mvs, "plane_sweep", sweep)
    img = np.zeros((H, W, 3))
    mask = np.ones((H, W), bool)
    trust = np.zeros((H, W), bool)
    trust[:, :48] = True
    kw = dict(guard_px=0, min_change=1.5, check_radius=1)
    plain = dr.masked_mvs(img, cam, g, mask, [img], [src], [g], **kw)
    swept_plain = swept["n"]
    r = dr.masked_mvs(img, cam, g, mask, [img], [src], [g], trust_g=trust, **kw)
    assert swept["n"] == swept_plain - trust.sum()                 # trusted pixels are not swept
    assert r.accepted[trust].all() and np.allclose(r.depth[trust], 2.0)  # ...and keep G exactly
    assert np.allclose(plain.depth[plain.accepted], 2.08)          # without trust: 4 % off kept
    right = r.accepted & ~trust
    assert right.any() and np.allclose(r.depth[right], 2.08)       # untrusted: the MVS as before
    assert r.stats["trusted_g"] == trust.sum()
    with pytest.raises(ValueError):
        dr.masked_mvs(img, cam, g, mask, [img], [src], [g], trust_g=trust[:, :10], **kw)


def test_g_trust_auto_and_config():
    from ibr_pipeline.config import build_config
    from ibr_pipeline.errors import ConfigError
    from ibr_pipeline.stages.view_depth import ViewDepthConfig, g_trust_auto

    assert g_trust_auto(320) == 6 and g_trust_auto(640) == 4
    cfg = ViewDepthConfig()
    assert cfg.g_trust == "far" and cfg.g_trust_px == 0 and cfg.edge_boundary_radius == 4
    assert cfg.ramp_zone_px == 8
    with pytest.raises(ConfigError):
        build_config(ViewDepthConfig, "view_depth", {"g_trust": "always"})
    with pytest.raises(ConfigError):
        build_config(ViewDepthConfig, "view_depth", {"edge_boundary_radius": -1})


def test_between_surfaces_drops_hole_borders():
    from ibr_pipeline.geometry import depth_edges as de

    cam = _cam()
    d = np.full((H, W), 2.0)
    d[:, :30] = 1.0            # an occlusion edge at x = 30
    d[:, 70:] = 0.0            # a hole (no depth) from x = 70
    P = points_from_depth(d, cam.K)
    e = de.depth_edges(P, normals_from_depth(d, cam.K), d)
    px = e.pixels()
    assert px[:, 29:31].all() and px[:, 69:71].all()      # Eq. 1: both are edges
    s = e.between_surfaces(d > 0).pixels()
    assert s[:, 29:31].all() and not s[:, 60:].any()     # only the occlusion edge is left
    with pytest.raises(ValueError):
        e.between_surfaces(np.ones((H, W - 1), bool))


def test_distrust_g_drops_g_depth_on_ramps_but_keeps_mvs_corrections(monkeypatch):
    """Around a rounded step G's ramp lies within mvs_min_change lambda of the MVS depth, so step 3
    would keep it; `distrust_g` sends those pixels (and trusted ones) to Eq. 2 instead, while an
    MVS depth that differs from G stays accepted."""
    from ibr_pipeline.geometry import mvs

    cam = _cam()
    src = Camera(cam.K, np.array([[1, 0, 0, -0.2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float), W, H)
    g = np.full((H, W), 1.0)
    photo = g * 1.002                      # confirms G within 1.5 lambda...
    photo[:, 60:] = 1.03                   # ...except right of x = 60: a 3 cm correction
    monkeypatch.setattr(mvs, "plane_sweep",
                        lambda *a, **k: SimpleNamespace(depth=photo, valid=np.ones((H, W), bool)))
    img = np.zeros((H, W, 3))
    mask = np.ones((H, W), bool)
    trust = np.zeros((H, W), bool)
    trust[:, :20] = True
    zone = np.zeros((H, W), bool)
    zone[:, 10:70] = True
    kw = dict(guard_px=0, min_change=1.5, check_radius=1)
    plain = dr.masked_mvs(img, cam, g, mask, [img], [src], [g], trust_g=trust, **kw)
    r = dr.masked_mvs(img, cam, g, mask, [img], [src], [g], trust_g=trust, distrust_g=zone, **kw)
    assert plain.accepted[:, 10:60].all()                       # without: G kept (trusted / confirmed)
    assert not r.accepted[:, 10:60].any()                       # with: left to Eq. 2
    assert r.accepted[:, :10].all() and np.allclose(r.depth[:, :10], 1.0)   # outside the zone: as before
    corr = r.accepted[:, 60:70]
    assert corr.any() and np.allclose(r.depth[:, 60:70][corr], 1.03)        # MVS corrections stay
    assert r.stats["distrusted_g"] == int((plain.accepted & zone & (plain.depth == g)).sum())
