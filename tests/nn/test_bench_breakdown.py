"""benchmarks.dsrnet.error_breakdown: region and band PSNRs on synthetic arrays."""
from types import SimpleNamespace

import cv2
import numpy as np

from benchmarks.dsrnet import error_breakdown


def _sample(rng):
    h, w = 24, 32
    target = cv2.GaussianBlur(rng.random((2 * h, 2 * w, 3)).astype(np.float32), (0, 0), 1.0)
    low = cv2.resize(target, (w, h), interpolation=cv2.INTER_AREA)
    return SimpleNamespace(name="v", target=target, cur=SimpleNamespace(color=low))


def test_breakdown_regions_and_bands():
    rng = np.random.default_rng(0)
    s = _sample(rng)
    depth = np.full(s.target.shape[:2], 2.0, np.float32)
    depth[:, 40:] = 3.0  # one depth edge
    depth[:4, :4] = 0.0  # a hole
    noisy = np.clip(s.target + rng.normal(0, 0.01, s.target.shape).astype(np.float32), 0, 1)
    offset = np.clip(s.target + 0.02, 0, 1)  # a pure low-frequency error
    outs = {"exact": [s.target], "noisy": [noisy], "offset": [offset], "full_res_render": [noisy]}
    r = error_breakdown([s], outs, {"v": depth}, 2)
    assert r["exact"]["all"] > 100  # no error
    assert abs(r["noisy"]["all"] - 40.0) < 1.0  # sigma 0.01 -> 40 dB
    assert r["noisy"]["high_band"] < r["noisy"]["low_band"] - 10  # white noise: mostly high band
    assert r["offset"]["low_band"] < r["offset"]["high_band"] - 10  # an offset: low band only
    share = r["pixel_share"]
    assert abs(share["textured"] + share["flat"] + share["depth_edges"] - 1.0) < 1e-6
    assert 0 < share["depth_edges"] < 0.2 and abs(share["holes"] - 16 / depth.size) < 1e-6
    assert r["input_psnr"]["render_half_res"] > 100  # the input is the exact downsample
    assert r["bicubic_of_gt"]["all"] < r["exact"]["all"]
