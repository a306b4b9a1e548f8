"""Bad files in the input folder: images, depth frames, cameras, COLMAP models, reflectors.

Every case: exit 2, one line naming the file (and field), no traceback, input and workspace as
they were. Run as `ibr run WS`, which stops in `ingest` before any expensive stage.
"""
import json
import struct
import zlib

import numpy as np
import pytest
from conftest import refused
from PIL import Image

from ibr_pipeline.cli import main
from ibr_pipeline.scene import cameras_to_json


def _run(ws):
    return ["run", ws, "--no-progress"]


# --- images -----------------------------------------------------------------------------------
def _png_header_only(w, h):
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("kind", ["zero_byte", "truncated", "garbage", "bomb", "sixteen_bit_rgb",
                                  "wrong_size"])
def test_bad_image(capsys, ws, input_dir, kind):
    p = input_dir / "images" / "1.png"
    data = p.read_bytes()
    if kind == "zero_byte":
        p.write_bytes(b"")
    elif kind == "truncated":
        p.write_bytes(data[: len(data) // 2])
    elif kind == "garbage":
        p.write_bytes(b"not an image at all" * 10)
    elif kind == "bomb":  # the header claims 100000x100000: PIL's DecompressionBombError
        p.write_bytes(_png_header_only(100000, 100000))
    elif kind == "sixteen_bit_rgb":
        Image.fromarray(np.zeros((30, 40), np.uint16)).save(p)  # I;16: not a colour photo
    elif kind == "wrong_size":
        Image.fromarray(np.zeros((31, 40, 3), np.uint8)).save(p)
    needle = {"bomb": "too large", "wrong_size": "40x31"}.get(kind, "")
    refused(capsys, _run(ws), input_dir, ws, "1.png", needle)


# --- depth ------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["aspect", "rgb", "missing_one", "corrupt"])
def test_bad_depth(capsys, ws, input_dir, kind):
    p = input_dir / "depth" / "2.png"
    if kind == "aspect":
        Image.fromarray(np.full((20, 20), 3000, np.uint16)).save(p)
    elif kind == "rgb":
        Image.fromarray(np.zeros((15, 20, 3), np.uint8)).save(p)
    elif kind == "missing_one":  # the dense method must not silently change from RGB-D to MVS
        p.unlink()
    elif kind == "corrupt":
        p.write_bytes(p.read_bytes()[:30])
    needle = {"missing_one": "3 of 4 images have a depth frame"}.get(kind, "2.png")
    refused(capsys, _run(ws), input_dir, ws, "depth", needle)


# --- cameras.json -----------------------------------------------------------------------------
def _edit_cameras(input_dir, fn):
    path = input_dir / "cameras.json"
    d = json.loads(path.read_text())
    fn(d["cameras"])
    path.write_text(json.dumps(d))


@pytest.mark.parametrize("kind,needle", [
    ("nan", "NaN"), ("inf", "NaN or infinite"), ("not_rotation", "not a proper rotation"),
    ("text_in_K", "must be numbers"), ("null_K", "3x3 matrix"), ("width_text", "width"),
    ("missing_field", "'K'"), ("not_object", "expected an object"),
    ("unknown_image", "9999.png"), ("escape_image", "../../outside.png"), ("absolute_image", "/etc/x.png"),
])
def test_bad_camera(capsys, ws, input_dir, kind, needle):
    def edit(cams):
        c = cams["1.png"]
        if kind == "nan":
            c["K"][0][0] = float("nan")
        elif kind == "inf":
            c["cam_from_world"][0][3] = float("inf")
        elif kind == "not_rotation":
            c["cam_from_world"][0][0] = 2.0
        elif kind == "text_in_K":
            c["K"][0][0] = "abc"
        elif kind == "null_K":
            c["K"] = None
        elif kind == "width_text":
            c["width"] = "wide"
        elif kind == "missing_field":
            del c["K"]
        elif kind == "not_object":
            cams["1.png"] = [1, 2, 3]
        else:
            name = {"unknown_image": "9999.png", "escape_image": "../../outside.png",
                    "absolute_image": "/etc/x.png"}[kind]
            cams[name] = dict(c)
    _edit_cameras(input_dir, edit)
    line = refused(capsys, _run(ws), input_dir, ws, "cameras.json", needle)
    if kind not in ("unknown_image", "escape_image", "absolute_image"):
        assert "1.png" in line, line


@pytest.mark.parametrize("text", ["{", "[]", '{"cameras": 3}', "\xff\xfe not json"])
def test_broken_cameras_json(capsys, ws, input_dir, text):
    (input_dir / "cameras.json").write_bytes(text.encode("latin-1"))
    refused(capsys, _run(ws), input_dir, ws, "cameras.json")


# --- COLMAP -----------------------------------------------------------------------------------
def _colmap_ws(tmp_path, colmap_dir):
    from ibr_pipeline.cli import main
    ws = tmp_path / "ws_colmap"
    assert main(["init", str(ws), "--input", str(colmap_dir)]) == 0
    return ws


def _set_token(path, index, value):
    """Replace token `index` of the first data line of a COLMAP text file."""
    lines = path.read_text().splitlines()
    i = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    parts = lines[i].split()
    parts[index] = value
    lines[i] = " ".join(parts)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("kind", ["truncated_bin", "text_abc", "text_nan_pose", "text_not_utf8",
                                  "unknown_image"])
def test_broken_colmap(capsys, tmp_path, colmap_dir, kind):
    ws = _colmap_ws(tmp_path, colmap_dir)
    sparse = colmap_dir / "sparse" / "0"
    if kind == "truncated_bin":
        p = sparse / "images.bin"
        p.write_bytes(p.read_bytes()[:40])
        needle = "sparse"
    else:
        from ibr_pipeline.io.colmap import write_colmap_model
        from conftest import cameras
        for f in sparse.iterdir():
            f.unlink()
        cams = cameras()
        if kind == "unknown_image":
            cams["9999.png"] = cams["1.png"]
        write_colmap_model(cams, sparse, text=True)
        p = sparse / "cameras.txt"
        if kind == "text_abc":
            _set_token(p, 4, "abc")  # a camera parameter
            needle = "cameras.txt"
        elif kind == "text_nan_pose":
            _set_token(sparse / "images.txt", 5, "nan")  # a quaternion component
            needle = "images.txt: line"
        elif kind == "text_not_utf8":
            p.write_bytes(p.read_bytes() + b"\xff\xfe\n")
            needle = "cameras.txt"
        else:
            needle = "9999.png"
    refused(capsys, _run(ws), colmap_dir, ws, needle)


# --- reflectors.json and paths named in it ------------------------------------------------------
@pytest.mark.parametrize("mask,needle", [
    ("../x_mask.png", "climbs out"), ("/tmp/x_mask.png", "absolute"), ("masks/none.png", "none.png"),
])
def test_reflector_mask_paths(capsys, ws, input_dir, tmp_path, mask, needle):
    Image.fromarray(np.full((30, 40), 255, np.uint8)).save(tmp_path / "x_mask.png")  # exists outside
    (input_dir / "reflectors.json").write_text(json.dumps(
        [{"name": "m", "plane": [0, 1, 0, -3], "masks": {"1.png": mask}}]))
    refused(capsys, _run(ws), input_dir, ws, "reflectors.json" if needle != "none.png" else "", needle)


def test_a_reflector_mask_of_a_known_view_is_taken(ws, input_dir):
    """The same check that refuses the paths above passes a good mask (and an outline) through."""
    Image.fromarray(np.full((30, 40), 255, np.uint8)).save(input_dir / "m.png")
    (input_dir / "reflectors.json").write_text(json.dumps([
        {"name": "m", "plane": [0, 1, 0, -3], "masks": {"1.png": "m.png"}},
        {"name": "tv", "outline": {"view": "1.png", "points": [[2, 2], [30, 2], [30, 20]]}}]))
    assert main(["run", str(ws), "--until", "ingest", "--no-progress"]) == 0
    refl = json.loads((ws / "scene.json").read_text())["reflectors"]
    assert refl[0]["masks"] == {"1.png": "input/m.png"}
    assert refl[1]["plane"] is None and refl[1]["outline"]["view"] == "1.png"


@pytest.mark.parametrize("body,needle", [
    ('[{"plane": ["a", 1, 0, 0]}]', "'plane'"), ('[{"plane": [0, 0, 0, 1]}]', "normal is zero"),
    ('[{"plane": [0, 1, 0, 1], "beta": 3}]', "'beta'"), ('[{"name": "x"}]', "'plane'"),
    ('[{"plane": [0, 1, 0, 1], "polygon": [["a"]]}]', "'polygon'"),
    ('[{"plane": [0, 1, 0, 1], "masks": {"77.png": "m.png"}}]', "unknown view"), ("{", "reflectors"),
    ('[{"outline": {"view": "77.png", "points": [[1, 1], [9, 1], [9, 9]]}}]', "unknown view"),
    ('[{"outline": {"view": "1.png", "points": [[1, 1], [50, 1], [9, 9]]}}]', "outside the 40x30"),
    ('[{"outline": {"view": "1.png", "points": [[1, 1]]}}]', "'outline' points"),
    ('[{"outline": ["1.png"]}]', "'outline' must be"),
])
def test_bad_reflectors_json(capsys, ws, input_dir, body, needle):
    (input_dir / "reflectors.json").write_text(body)
    refused(capsys, _run(ws), input_dir, ws, "reflectors.json", needle)


def test_cameras_json_given_and_colmap_model_both_unreadable_is_not_a_silent_fallback(capsys, ws, input_dir):
    (input_dir / "cameras.json").write_text(cameras_to_json({}).replace('"cameras": {}', '"cameras": []'))
    refused(capsys, _run(ws), input_dir, ws, "cameras.json", "'cameras' mapping")
