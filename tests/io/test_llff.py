"""io/llff.py: poses_bounds.npy, read and written."""
import numpy as np
import pytest

from ibr_pipeline.errors import InputError
from ibr_pipeline.io.images import write_image
from ibr_pipeline.io.llff import read_poses_bounds, write_poses_bounds
from ibr_pipeline.io.nerfstudio import GL_TO_CV, cam_from_c2w
from ibr_pipeline.scene import Camera


def forward_facing(n=4, w=40, h=30):
    K = Camera.intrinsics_from_fov(w, h, 60)
    return {f"{i:03d}.png": Camera.look_at([0.2 * i - 0.3, 0.05 * i, -4], [0, 0, 0], [0, -1, 0], K, w, h)
            for i in range(n)}


def llff_folder(root, cams, size=None, names=None):
    for name, cam in cams.items():
        w, h = size or cam.size
        write_image(root / "images" / (names or {}).get(name, name), np.zeros((h, w, 3)))
    write_poses_bounds(cams, root / "poses_bounds.npy", near_far=(1.5, 8.0))
    return root


def refused(root, *words):
    with pytest.raises(InputError) as e:
        read_poses_bounds(root)
    assert "\n" not in str(e.value)
    for w in words:
        assert w in str(e.value), str(e.value)
    return str(e.value)


def test_round_trip(tmp_path):
    cams = forward_facing()
    cap = read_poses_bounds(llff_folder(tmp_path, cams))
    assert cap.format == "llff" and [f.name for f in cap.frames] == sorted(cams)
    for f in cap.frames:
        assert f.lens.model == "PINHOLE" and f.lens.params[2:] == (20, 15)  # W/2, H/2 in COLMAP's
        np.testing.assert_allclose(f.cam_from_world, cams[f.name].cam_from_world, atol=1e-9)
        np.testing.assert_allclose(f.lens.pinhole_K(), cams[f.name].K, atol=1e-9)
    assert cap.files[0] == tmp_path / "poses_bounds.npy" and len(cap.files) == 5
    assert any("near 1.5" in n and "far 8" in n for n in cap.notes)


def llff_row(c2w_cols, H=30, W=40, focal=50.0, near=1.0, far=9.0):
    P = np.c_[np.asarray(c2w_cols, dtype=float), [H, W, focal]]
    return np.r_[P.ravel(), near, far]


def test_down_right_back_from_first_principles(tmp_path):
    # a camera at (0, 0, 5) looking down world -z with world +y up: right = +x, down = -y, back = +z
    row = llff_row(np.c_[[0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 5]])
    write_image(tmp_path / "images" / "a.png", np.zeros((30, 40, 3)))
    np.save(tmp_path / "poses_bounds.npy", row[None])
    f = read_poses_bounds(tmp_path).frames[0]
    cam = Camera(f.lens.pinhole_K(), f.cam_from_world, 40, 30)
    uv, z = cam.project(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [19.5, 14.5], atol=1e-12)
    assert z[0] == pytest.approx(5) and uv[1, 0] > 19.5 and uv[2, 1] < 14.5
    # NeRF's load_llff.py turns [down, right, back] into OpenGL [right, up, back] with
    # [1, -0, 2]; converted like a transforms.json pose, it must give the same camera
    P = row[:15].reshape(3, 5)
    gl = np.eye(4)
    gl[:3, :4] = np.c_[P[:, 1], -P[:, 0], P[:, 2], P[:, 3]]
    np.testing.assert_allclose(f.cam_from_world, cam_from_c2w(gl @ GL_TO_CV, "x"), atol=1e-12)


def test_rows_pair_with_sorted_images_any_case(tmp_path):
    cams = forward_facing(3)
    names = {"000.png": "A.JPG", "001.png": "b.jpeg", "002.png": "c.png"}
    llff_folder(tmp_path, cams, names=names)
    (tmp_path / "images" / "notes.txt").write_text("not an image")
    (tmp_path / "images" / "sub").mkdir()
    write_image(tmp_path / "images" / "sub" / "z.png", np.zeros((30, 40, 3)))  # sub-folders: not LLFF's
    cap = read_poses_bounds(tmp_path)
    assert [f.name for f in cap.frames] == ["A.JPG", "b.jpeg", "c.png"]
    for f, name in zip(cap.frames, sorted(cams)):
        np.testing.assert_allclose(f.cam_from_world, cams[name].cam_from_world, atol=1e-9)


def test_smaller_images_scale_the_focal(tmp_path):
    cams = forward_facing(2, 40, 30)
    cap = read_poses_bounds(llff_folder(tmp_path, cams, size=(20, 15)))
    f = cap.frames[0]
    assert f.lens.params == pytest.approx((cams["000.png"].K[0, 0] / 2,) * 2 + (10, 7.5))
    assert (f.lens.width, f.lens.height) == (20, 15)
    assert any("focal scaled by 0.5" in n for n in cap.notes)


def test_other_aspect_is_refused(tmp_path):
    refused(llff_folder(tmp_path, forward_facing(2), size=(40, 40)), "aspect", "000.png")


def test_count_mismatch_is_refused(tmp_path):
    llff_folder(tmp_path, forward_facing(3))
    (tmp_path / "images" / "002.png").unlink()
    refused(tmp_path, "3 poses", "2 images")


@pytest.mark.parametrize("data, words", [
    (np.zeros((3, 15)), ["N x 17", "(3, 15)"]),
    (np.zeros((0, 17)), ["N x 17"]),
    (np.zeros(17), ["N x 17"]),
    (np.full((1, 17), np.nan), ["row 0", "NaN"]),
    (np.array([["a"] * 17]), ["float"]),
    (np.array([[{"x": 1}] * 17], dtype=object), ["readable"]),  # never unpickled
])
def test_bad_arrays_are_refused(tmp_path, data, words):
    write_image(tmp_path / "images" / "a.png", np.zeros((30, 40, 3)))
    np.save(tmp_path / "poses_bounds.npy", data, allow_pickle=True)
    refused(tmp_path, str(tmp_path / "poses_bounds.npy"), *words)


def test_garbage_and_missing_files_are_refused(tmp_path):
    write_image(tmp_path / "images" / "a.png", np.zeros((30, 40, 3)))
    refused(tmp_path, "poses_bounds.npy", "not found")
    (tmp_path / "poses_bounds.npy").write_bytes(b"\x93NUMPY garbage")
    refused(tmp_path, "poses_bounds.npy", "readable")


def test_bad_rows_are_refused(tmp_path):
    write_image(tmp_path / "images" / "a.png", np.zeros((30, 40, 3)))
    np.save(tmp_path / "poses_bounds.npy", llff_row(2 * np.eye(3, 4))[None])
    refused(tmp_path, "row 0", "a.png", "not a rotation")
    np.save(tmp_path / "poses_bounds.npy", llff_row(np.eye(3, 4), focal=0)[None])
    refused(tmp_path, "row 0", "focal")


def test_no_images_folder(tmp_path):
    np.save(tmp_path / "poses_bounds.npy", llff_row(np.eye(3, 4))[None])
    refused(tmp_path, "images/")


def test_write_refuses_what_llff_cannot_store(tmp_path):
    cam = forward_facing(1)["000.png"]
    off = cam.K.copy()
    off[0, 2] += 1
    with pytest.raises(ValueError, match="principal point"):
        write_poses_bounds({"a.png": Camera(off, cam.cam_from_world, 40, 30)}, tmp_path / "p.npy")
    rect = cam.K.copy()
    rect[1, 1] *= 1.1
    with pytest.raises(ValueError, match="square"):
        write_poses_bounds({"a.png": Camera(rect, cam.cam_from_world, 40, 30)}, tmp_path / "p.npy")
    with pytest.raises(ValueError, match="near"):
        write_poses_bounds({"a.png": cam}, tmp_path / "p.npy", near_far=(2, 1))
    assert not (tmp_path / "p.npy").exists()


def test_nex_layout(tmp_path):
    """NeX's N x 14 rows with hwf_cxcy.npy give the same poses, and its own (fx, fy, cx, cy),
    scaled with the images."""
    cams = forward_facing()
    root = llff_folder(tmp_path, cams, size=(20, 15))  # images at half the poses' size
    full = np.load(root / "poses_bounds.npy")
    P = full[:, :15].reshape(-1, 3, 5)
    np.save(root / "poses_bounds.npy", np.c_[P[:, :, :4].reshape(-1, 12), full[:, 15:]])
    np.save(root / "hwf_cxcy.npy", np.array([[30.0], [40.0], [51.0], [52.0], [21.0], [14.0]]))
    cap = read_poses_bounds(root)
    for f in cap.frames:
        np.testing.assert_allclose(f.cam_from_world, cams[f.name].cam_from_world, atol=1e-9)
        assert f.lens.params == (25.5, 26.0, 10.5, 7.0) and (f.lens.width, f.lens.height) == (20, 15)
    assert any("NeX" in n for n in cap.notes) and root / "hwf_cxcy.npy" in cap.files
    (root / "hwf_cxcy.npy").unlink()  # 14 columns without the intrinsics: refused, naming both
    refused(root, "poses_bounds.npy", "hwf_cxcy.npy")
