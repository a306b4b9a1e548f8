"""The pipeline computes in linear radiance whatever the images' encoding: the tiny scene stored
as linear PNGs and the same scene stored sRGB-encoded (as photographs are) give the same renders
once decoded when the views are blended in linear light (`blend_space = "linear"`), and each
one's metrics in the other's space agree. The default blends the views' colours in the encoding
their files hold (`blend_space = "stored"`: sRGB values for photographs) and still composes
I0 + beta I1 in linear light: a 50/50 blend of linear 0.2 and 0.8 is 0.5, of their sRGB
encodings 0.44 once decoded, so there the two scenes' renders differ where views disagree."""
import json
import shutil

import numpy as np
import pytest

from ibr_pipeline.cli import main
from ibr_pipeline.gt_workspace import write_gt_workspace
from scene_copies import srgb_copy
from ibr_pipeline.io.images import linear_to_srgb, read_image, srgb_to_linear


def test_srgb_round_trip_and_reference_values():
    x = np.linspace(0, 1, 4097, dtype=np.float32)
    assert np.abs(srgb_to_linear(linear_to_srgb(x)) - x).max() < 1e-5
    # IEC 61966-2-1 reference points: 0.5 linear encodes to 0.7354; the linear segment below
    assert abs(float(linear_to_srgb(np.float32(0.5))) - 0.735357) < 1e-5
    assert abs(float(srgb_to_linear(np.float32(0.04))) - 0.04 / 12.92) < 1e-7


@pytest.fixture(scope="module")
def two_encodings(tiny_scene, tmp_path_factory):
    base = tmp_path_factory.mktemp("colour")
    lin, srgb = base / "linear", base / "srgb"
    shutil.copytree(tiny_scene[0], lin)
    srgb_copy(tiny_scene[0], srgb)
    out = {}
    for name, root, space in (("linear", lin, "linear"), ("srgb", srgb, "linear"),
                              ("srgb_stored", srgb, "stored"), ("linear_stored", lin, "stored")):
        ws = base / f"ws_{name}"
        write_gt_workspace(root, ws, "reflection", global_mesh="none")
        with open(ws / "ibr.toml", "a") as f:
            f.write(f'\n[render_views.renderer]\nblend_space = "{space}"\n')
        assert main(["-q", "render_views", str(ws), "--no-progress"]) == 0
        assert main(["-q", "evaluate", str(ws), "--no-progress"]) == 0
        out[name] = ws
    return out


def test_renders_agree_in_linear_radiance(two_encodings):
    ws = two_encodings
    assert json.loads((ws["srgb"] / "scene.json").read_text())["image_encoding"] == "srgb"
    for s in ("test", "test_single", "fly"):
        for p in sorted((ws["linear"] / "renders" / s).glob("*.png")):
            a = read_image(p, "linear")
            b = read_image(ws["srgb"] / "renders" / s / p.name, "srgb")
            err = np.abs(a - b)
            # 8-bit storage of either encoding, twice (inputs and renders): a few levels at most
            assert err.mean() < 1.5 / 255 and np.quantile(err, 0.999) < 8 / 255, (s, p.name, err.mean())


def test_metrics_are_on_the_stored_images_with_the_other_space_named(two_encodings):
    m = {k: json.loads((ws / "eval" / "metrics.json").read_text())["summary"]
         for k, ws in two_encodings.items()}
    assert abs(m["srgb"]["psnr"] - m["linear"]["psnr_srgb"]) < 0.3
    assert abs(m["srgb"]["psnr_linear"] - m["linear"]["psnr"]) < 0.3
    assert abs(m["srgb"]["psnr"] - m["srgb"]["psnr_linear"]) > 0.3  # the spaces differ


def test_stored_blending_is_linear_blending_for_linear_files(two_encodings):
    ws = two_encodings
    for p in sorted((ws["linear"] / "renders" / "test").glob("*.png")):
        assert np.array_equal(read_image(p), read_image(ws["linear_stored"] / "renders" / "test" / p.name))


def test_stored_srgb_blending_is_never_brighter_than_linear_blending(two_encodings):
    """Jensen: decode(mean(encoded)) <= mean(decoded), the sRGB decoding being convex, with
    equality where the blended views agree; the push-pull fill is a weighted mean as well and
    Eq. 3 adds the two layers in linear light. So the stored blend is nowhere brighter than the
    linear one beyond 8-bit rounding, and darker where the views' colours differ."""
    ws = two_encodings
    darker = 0
    for p in sorted((ws["srgb"] / "renders" / "test").glob("*.png")):
        a = read_image(p, "srgb")
        b = read_image(ws["srgb_stored"] / "renders" / "test" / p.name, "srgb")
        assert np.quantile(b - a, 0.999) < 3 / 255, p.name
        darker += int(((a - b) > 4 / 255).sum())
    assert darker > 0
