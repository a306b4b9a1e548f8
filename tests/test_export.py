"""`ibr export` (commands/export.py) and the GLB writer (io/gltf.py).

The GLBs are read back with trimesh and checked where it matters for a user: every texture lands
where its camera saw it (the texture sampled at a vertex's UV is the photo at the vertex's
projection), the layers add up to the photo, the cameras survive the COLMAP and transforms.json
round trips. The workspace is the `tiny` scene's ground-truth one through `reflection` (as
tests/render/test_render_stage.py builds it: ~2 s once the session's scene exists).
"""
import os
import shutil

import numpy as np
import pytest

from ibr_pipeline import cli
from ibr_pipeline.io.gltf import UNLIT, glb_bytes, projective_uvs, textured_mesh, write_glb
from ibr_pipeline.io.images import linear_to_srgb, read_image, srgb_to_linear
from ibr_pipeline.scene import Camera, cameras_from_json

EXPORT = "ibr_pipeline.commands.export"
# the texture is the photo's own 8-bit values (PNG, lossless): what is left is the 8-bit rounding
# of a float image and float32 UVs (1e-7 of the image, far below a texel)
TOL = 2 / 255 + 1e-6


@pytest.fixture(autouse=True)
def export_registered(monkeypatch):
    """`ibr export` in the parser whether or not cli.COMMAND_MODULES lists it yet."""
    if EXPORT not in cli.COMMAND_MODULES:
        monkeypatch.setattr(cli, "COMMAND_MODULES", cli.COMMAND_MODULES + (EXPORT,))


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img (H, W, C) at pixel coordinates (x, y) (centre of the top-left pixel at (0, 0)),
    edge-clamped."""
    H, W = img.shape[:2]
    x, y = np.clip(x, 0, W - 1), np.clip(y, 0, H - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), W - 2), np.minimum(np.floor(y).astype(int), H - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def texture_at(geom, uv: np.ndarray) -> np.ndarray:
    """The loaded mesh's texture at trimesh UVs (origin bottom-left, v up), floats in [0, 1]."""
    tex = np.asarray(geom.visual.material.baseColorTexture.convert("RGB"), np.float64) / 255
    H, W = tex.shape[:2]
    return bilinear(tex, uv[:, 0] * W - 0.5, (1 - uv[:, 1]) * H - 0.5)


def load_glb(path):
    import trimesh
    scene = trimesh.load(path, force="scene")
    nodes = {n: scene.graph[n][1] for n in scene.graph.nodes_geometry}
    return scene, {n: scene.geometry[g] for n, g in nodes.items()}


def check_projective(geom, cam: Camera, image: np.ndarray) -> None:
    """UVs in [0, 1] and the texture at each vertex's UV = `image` at its projection."""
    uv = np.asarray(geom.visual.uv, np.float64)
    assert uv.shape == (len(geom.vertices), 2)
    assert uv.min() >= 0 and uv.max() <= 1
    px, z = cam.project(np.asarray(geom.vertices, np.float64))
    # every vertex of a view's meshes (M1 included) projects into the view: inside the image's
    # area, pixel centres from -0.5 to W - 0.5 (float32 positions put border vertices at -1e-5)
    assert np.all(z > 0)
    assert np.all((px >= -0.5) & (px <= np.array(cam.size) - 0.5))
    err = np.abs(texture_at(geom, uv) - bilinear(image, px[:, 0], px[:, 1]))
    assert err.max() <= TOL, err.max()


# --- io/gltf.py on a hand-made mesh ------------------------------------------------------------
def two_triangles():
    K = Camera.intrinsics_from_fov(40, 30, 60)
    cam = Camera.look_at([0.2, -0.1, 0.3], [0, 3, 0], [0, 0, 1], K, 40, 30)
    px = np.array([[3.3, 4.7], [35.2, 5.1], [20.6, 25.4], [0.0, 29.0]])  # off pixel centres too
    verts = cam.unproject(px, np.array([3.0, 3.2, 2.8, 3.1]))
    return cam, px, verts, np.array([[0, 1, 2], [0, 2, 3]])


def test_projective_uvs_convention():
    cam, _, _, _ = two_triangles()
    # pixel centres (0, 0) and (W-1, H-1): trimesh's origin is the bottom-left corner, v up
    corners = cam.unproject(np.array([[0.0, 0.0], [39.0, 29.0]]), np.array([2.0, 5.0]))
    uv = projective_uvs(corners, cam)
    assert np.allclose(uv, [[0.5 / 40, 1 - 0.5 / 30], [39.5 / 40, 0.5 / 30]], atol=1e-12)
    behind = cam.unproject(np.array([[10.0, 10.0]]), np.array([-1.0]))
    assert np.all((projective_uvs(behind, cam) >= 0) & (projective_uvs(behind, cam) <= 1))
    with pytest.raises(ValueError):
        projective_uvs(np.zeros((3, 2)), cam)


def test_glb_of_two_triangles_round_trips(tmp_path):
    import json
    import struct
    cam, px, verts, faces = two_triangles()
    img = np.random.default_rng(0).random((30, 40, 3))
    m = textured_mesh(verts, faces, img, cam, "view")
    assert m.vertex_normals.shape == (4, 3)
    empty = textured_mesh(np.zeros((0, 3)), np.zeros((0, 3), int), img, cam, "nothing")
    write_glb(tmp_path / "t.glb", [("view", m), ("nothing", empty)])
    scene, geoms = load_glb(tmp_path / "t.glb")
    assert set(geoms) == {"view"} and "nothing" in scene.graph.nodes  # a node without geometry
    g = geoms["view"]
    assert np.allclose(g.vertices, verts, atol=1e-6) and len(g.faces) == 2
    check_projective(g, cam, img)
    # ... and the vertices' own pixels, independently of the projection code
    assert np.abs(texture_at(g, g.visual.uv) - bilinear(img, px[:, 0], px[:, 1])).max() <= TOL
    # the file itself: glTF's top-left UV origin, unlit PBR material, normals
    data = (tmp_path / "t.glb").read_bytes()
    tree = json.loads(data[20:20 + struct.unpack("<I", data[12:16])[0]])
    mat = tree["materials"][0]
    assert UNLIT in mat["extensions"] and UNLIT in tree["extensionsUsed"] and mat["doubleSided"]
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0
    prim = tree["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "TEXCOORD_0"} <= set(prim["attributes"])
    vmin = tree["accessors"][prim["attributes"]["TEXCOORD_0"]]["min"][1]
    assert abs(vmin - (4.7 + 0.5) / 30) < 1e-6   # top vertex: small v in the file
    with pytest.raises(ValueError, match="unique"):
        glb_bytes([("a", m), ("a", m)])
    with pytest.raises(ValueError, match="camera"):
        textured_mesh(verts, faces, img[:20], cam, "x")


# --- ibr export on a workspace ------------------------------------------------------------------
@pytest.fixture(scope="module")
def gt_ws(tiny_scene, tmp_path_factory):
    from ibr_pipeline.gt_workspace import write_gt_workspace
    ws = tmp_path_factory.mktemp("export") / "ws"
    write_gt_workspace(tiny_scene[0], ws, "reflection", global_mesh="none")
    return ws


def images_of(ws) -> dict:
    from ibr_pipeline.workspace import Workspace
    w = Workspace(ws)
    return {v.name: w.path(v.image) for v in w.scene().views}


def test_export_glb_and_colmap(gt_ws, tmp_path, capsys):
    from ibr_pipeline.io.colmap import read_colmap_model
    out = tmp_path / "out"
    assert cli.main(["export", str(gt_ws), "--out", str(out), "--what", "colmap,glb",
                     "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert str(out) in text and "8 GLB, 3 with reflection layers" in text
    cams = cameras_from_json(gt_ws / "global" / "cameras.json")
    images = images_of(gt_ws)
    # COLMAP text model = global/cameras.json
    back = read_colmap_model(out / "colmap")
    assert set(back) == set(cams)
    for n, c in cams.items():
        assert np.allclose(back[n].K, c.K, atol=1e-6) and back[n].size == c.size
        assert np.allclose(back[n].cam_from_world, c.cam_from_world, atol=1e-6)
    layered = 0
    for n, cam in cams.items():
        _, geoms = load_glb(out / "views" / f"{os.path.splitext(n)[0]}.glb")
        photo = read_image(images[n])  # the tiny scene is linear; glTF textures are sRGB
        check_projective(geoms["view"], cam, linear_to_srgb(photo))
        if set(geoms) == {"view"}:
            continue
        assert set(geoms) == {"view", "surface", "reflection"}
        layered += 1
        vdir = gt_ws / "views" / n
        check_projective(geoms["surface"], cam, linear_to_srgb(read_image(vdir / "I0.png")))
        beta = np.load(vdir / "beta.npy")[..., None]
        check_projective(geoms["reflection"], cam, linear_to_srgb(beta * read_image(vdir / "I1.png")))
        # surface + reflection, added in linear radiance, is the photo (Eq. 3), to the 8-bit
        # roundings of the layers (linear) and of the textures (sRGB: up to 2.3/255 per step)
        tex = [srgb_to_linear(np.asarray(geoms[k].visual.material.baseColorTexture.convert("RGB")) / 255)
               for k in ("surface", "reflection")]
        assert np.abs(tex[0] + tex[1] - photo).max() <= 6 / 255 + 1e-6
        assert geoms["reflection"].metadata["ibr_texture"] == "beta * I1"  # glTF extras
    assert layered == 3
    # --views: only what was asked
    sub = tmp_path / "sub"
    assert cli.main(["export", str(gt_ws), "--out", str(sub), "--what", "glb",
                     "--views", "0004.png,0001.png", "--no-progress"]) == 0
    assert sorted(p.name for p in (sub / "views").iterdir()) == ["0001.glb", "0004.glb"]
    assert sorted(p.name for p in sub.iterdir()) == ["views"]   # no staging folder left


def test_export_transforms(gt_ws, tmp_path):
    nerfstudio = pytest.importorskip("ibr_pipeline.io.nerfstudio")
    out = tmp_path / "out"
    assert cli.main(["-q", "export", str(gt_ws), "--out", str(out), "--what", "transforms"]) == 0
    images = images_of(gt_ws)
    root = os.path.commonpath([out, *images.values()])   # the reader keeps paths inside a root
    cap = nerfstudio.read_transforms(out / "transforms.json", root)
    cams = cameras_from_json(gt_ws / "global" / "cameras.json")
    by_image = {f.image.resolve(): f for f in cap.frames}
    assert len(by_image) == len(cams)
    for n, c in cams.items():
        f = by_image[images[n].resolve()]
        assert np.allclose(f.cam_from_world, c.cam_from_world, atol=1e-6)
    import json
    paths = [fr["file_path"] for fr in json.loads((out / "transforms.json").read_text())["frames"]]
    assert all(not os.path.isabs(p) for p in paths)   # relative to DIR: they share a folder


def tree(root):
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))} if root.exists() else {}


def refused(argv, ws, out, capsys, *needles):
    before = tree(ws)
    code = cli.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("ibr: error: "), err
    for n in needles:
        assert n in err[0], err[0]
    assert tree(ws) == before and not out.exists()
    return err[0]


def test_missing_stage_outputs_are_one_line(gt_ws, tmp_path, capsys):
    ws = tmp_path / "ws"
    shutil.copytree(gt_ws, ws)
    out = tmp_path / "out"
    args = ["export", str(ws), "--out", str(out), "--no-progress"]
    refused(args + ["--what", "pdf"], ws, out, capsys, "--what", "pdf")
    refused(args + ["--views", "nope.png"], ws, out, capsys, "--views", "nope.png")
    # a layer file gone: the reflection stage must rerun
    (ws / "views" / "0005.png" / "M1.ply").unlink()
    refused(args, ws, out, capsys, "M1.ply", "ibr reflection")
    # a corrupt mesh is found only while exporting: the staged files go, DIR is not created
    (ws / "views" / "0007.png" / "mesh.ply").write_bytes(b"ply\nnot really\n")
    refused(args + ["--what", "colmap,glb", "--views", "0001.png,0007.png"], ws, out, capsys,
            "0007.png", "mesh.ply")
    (ws / "views" / "0003.png" / "mesh.ply").unlink()
    refused(args, ws, out, capsys, "0003.png", "mesh.ply", "ibr view_mesh")
    (ws / "global" / "cameras.json").unlink()
    refused(args, ws, out, capsys, "cameras.json", "ibr poses")
    # an existing DIR keeps what it held
    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert cli.main(args) == 2
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
