"""io/rgbd.py: TUM RGB-D and ScanNet readers against fixtures written by our own writers."""
import shutil

import numpy as np
import pytest
from PIL import Image

from ibr_pipeline.errors import InputError
from ibr_pipeline.io import rgbd
from ibr_pipeline.io.capture import Lens
from ibr_pipeline.scene import Camera

W, H = 32, 24


def _cameras(n):
    K = Camera.intrinsics_from_fov(W, H, 60.0)
    K[0, 2] += 0.3  # an off-centre principal point catches a wrong pixel convention
    cams = {}
    for i in range(n):
        a = 0.25 * i
        eye = [2.0 * np.sin(a), 0.3 * i - 0.5, -2.0 * np.cos(a)]
        cams[f"v{i:02d}"] = Camera.look_at(eye, [0, 0.2, 0], [0, -1, 0], K, W, H)
    return cams


def _data(cams, seed=0):
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, W), np.linspace(0, 1, H))
    images = {n: np.clip(np.stack([u, v, 1 - u], -1) * 0.5 + 0.5 * rng.random((H, W, 3)), 0, 1)
              for n in cams}
    depths = {n: 1.5 + 0.1 * i + 0.5 * u * v for i, n in enumerate(cams)}
    return images, depths


@pytest.fixture
def tum(tmp_path):
    cams = _cameras(5)
    images, depths = _data(cams)
    root = tmp_path / "seq"
    names = rgbd.write_tum(root, cams, images, depths)
    return root, cams, names, depths


def _edit(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_tum_roundtrip_interpolated_poses_depth_units(tum):
    root, cams, names, depths = tum
    cap = rgbd.read_tum(root)
    assert cap.format == "tum"
    assert [f.name for f in cap.frames] == [names[n] for n in cams]
    assert cap.frames[0].name == "1.000000.png"
    gt = (root / "groundtruth.txt").read_text()
    assert "1.000000 " not in gt  # no groundtruth pose at a frame time: every pose is interpolated
    for f, (n, cam) in zip(cap.frames, cams.items()):
        np.testing.assert_allclose(f.cam_from_world, cam.cam_from_world, atol=1e-6)
        assert f.depth_units_per_m == 5000 and f.depth_lens is None
        assert f.lens.model == "PINHOLE" and (f.lens.width, f.lens.height) == (W, H)
        np.testing.assert_allclose(f.lens.pinhole_K(), cam.K, atol=1e-9)
        raw = np.asarray(Image.open(f.depth))
        assert raw.dtype == np.uint16
        np.testing.assert_allclose(raw / 5000.0, depths[n], atol=0.6 / 5000)
    assert root / "rgb.txt" in cap.files and root / "groundtruth.txt" in cap.files
    assert all(f.image in cap.files and f.depth in cap.files for f in cap.frames)


def test_tum_drops_frames_without_depth_or_pose_with_notes(tum):
    root = tum[0]
    with open(root / "rgb.txt", "a") as fh:
        fh.write("5.000000 rgb/1.000000.png.late\n")   # after the groundtruth span
        fh.write("1.350000 rgb/1.100000.png.nodepth\n")  # 0.045 s from any depth frame
    shutil.copy(root / "rgb/1.000000.png", root / "rgb/1.000000.png.late")
    shutil.copy(root / "rgb/1.100000.png", root / "rgb/1.100000.png.nodepth")
    shutil.copy(root / "depth/1.005000.png", root / "depth/5.001000.png")
    with open(root / "depth.txt", "a") as fh:
        fh.write("5.001000 depth/5.001000.png\n")
    cap = rgbd.read_tum(root)
    names = [f.name for f in cap.frames]
    assert len(names) == 5 and "1.000000.png.late" not in names and "1.100000.png.nodepth" not in names
    notes = " ".join(cap.notes)
    assert "6 of 7 colour frames have a depth frame" in notes
    assert "1 frames dropped" in notes and "outside the groundtruth time span" in notes


def test_tum_pose_gap_is_refused(tum):
    root = tum[0]
    lines = (root / "groundtruth.txt").read_text().splitlines()
    # remove both poses around frame 2 (t = 1.2): its bracketing poses are 1.16 and 1.28 apart
    kept = [ln for ln in lines if not ln.startswith(("1.180000", "1.260000"))]
    assert len(kept) == len(lines) - 2
    (root / "groundtruth.txt").write_text("\n".join(kept) + "\n")
    cap = rgbd.read_tum(root)
    assert "1.200000.png" not in [f.name for f in cap.frames] and len(cap.frames) == 4
    assert any("groundtruth gap" in n for n in cap.notes)


def test_tum_stride_and_unposed(tum):
    root, cams, names, _ = tum
    (root / "groundtruth.txt").unlink()
    cap = rgbd.read_tum(root, stride=2)
    assert [f.name for f in cap.frames] == [names[n] for n in list(cams)[::2]]
    assert all(f.cam_from_world is None for f in cap.frames)
    assert any("unposed" in n for n in cap.notes)
    with pytest.raises(InputError, match="stride"):
        rgbd.read_tum(root, stride=0)


def _associate_py(first, second, max_difference):
    """TUM's associate.py (Sturm et al.), all pairs: the reference for our windowed version."""
    first_keys, second_keys = list(first), list(second)
    potential = sorted((abs(a - b), a, b) for a in first_keys for b in second_keys
                       if abs(a - b) < max_difference)
    matches = []
    for _, a, b in potential:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            matches.append((a, b))
    return sorted(matches)


def test_associate_matches_tum_associate_py():
    rng = np.random.default_rng(4)
    for _ in range(20):
        a = np.round(np.sort(rng.uniform(0, 1, 40)), 6)
        b = np.round(rng.uniform(0, 1, 35), 6)
        got = rgbd._associate(np.unique(a), np.unique(b), 0.02)
        want = _associate_py(np.unique(a), np.unique(b), 0.02)
        assert sorted((np.unique(a)[i], np.unique(b)[j]) for i, j in got.items()) == want


def test_slerp_interpolates_on_the_geodesic():
    q0 = np.array([0.0, 0.0, 0.0, 1.0])
    q1 = np.array([0, 0, np.sqrt(0.5), np.sqrt(0.5)])  # 90 degrees about z
    gt = (np.array([0.0, 0.08]), np.array([[0, 0, 0], [4.0, 0, 0]]), np.stack([q0, -q1]))
    T, _ = rgbd._pose_at(gt, 0.02)  # -q1 is q1: the short way round
    a = np.radians(22.5)
    np.testing.assert_allclose(T[:3, :3], [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0],
                                           [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0, 0])
    assert rgbd._pose_at(gt, 0.09)[0] is None and rgbd._pose_at(gt, 0.08)[0] is not None
    for R in (np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), T[:3, :3]):
        np.testing.assert_allclose(rgbd._quat_to_R(rgbd._R_to_quat(R)), R, atol=1e-12)


@pytest.mark.parametrize("kinect,model", [("freiburg1", "FULL_OPENCV"), ("freiburg2", "FULL_OPENCV"),
                                          ("freiburg3", "PINHOLE")])
def test_tum_published_calibration_from_folder_name(tum, kinect, model):
    root = tum[0]
    (root / "intrinsics.txt").unlink()
    seq = root.rename(root.with_name(f"rgbd_dataset_{kinect}_desk"))
    lens = rgbd.read_tum(seq).frames[0].lens
    c = rgbd.TUM_CALIBRATION[kinect]
    assert lens.model == model
    # TUM publishes OpenCV pixel centres; Lens keeps COLMAP's (+0.5)
    np.testing.assert_allclose(lens.params[:4], [c[0], c[1], c[2] + 0.5, c[3] + 0.5])
    if model == "FULL_OPENCV":
        np.testing.assert_allclose(lens.params[4:], list(c[4:]) + [0, 0, 0])
        assert lens.distorted


def test_tum_intrinsics_file_with_distortion_and_without_any(tum):
    root = tum[0]
    (root / "intrinsics.txt").write_text("# fx fy cx cy d0..d4\n30 31 15.5 11.5 0.1 -0.2 0.001 0.002 0\n")
    lens = rgbd.read_tum(root).frames[0].lens
    assert lens == Lens("OPENCV", (30, 31, 16, 12, 0.1, -0.2, 0.001, 0.002), W, H)
    (root / "intrinsics.txt").unlink()
    with pytest.raises(InputError, match="intrinsics.txt"):
        rgbd.read_tum(root)


@pytest.mark.parametrize("file,old,new,match", [
    ("rgb.txt", "1.100000 rgb/1.100000.png", "1.100000", r"rgb\.txt: line 3: expected 'timestamp filename'"),
    ("rgb.txt", "1.100000 rgb/", "1.1x rgb/", r"rgb\.txt: line 3: '1\.1x' is not a number"),
    ("rgb.txt", "rgb/1.100000.png", "../outside.png",
     r"rgb\.txt: line 3: path '\.\./outside\.png' climbs out"),
    ("depth.txt", "depth/1.105000.png", "depth/gone.png",
     r"gone\.png: file not found \(listed in .*depth\.txt line 3\)"),
    ("groundtruth.txt", "\n1.080000 ", "\n1.080000 nan ",
     r"groundtruth\.txt: line 4: expected .* \(8 numbers\), got 9"),
    ("intrinsics.txt", "\n", "\n7 ", r"intrinsics\.txt: expected 'fx fy cx cy'"),
])
def test_tum_malformed_files_name_file_and_line(tum, file, old, new, match):
    _edit(tum[0] / file, old, new)
    with pytest.raises(InputError, match=match):
        rgbd.read_tum(tum[0])


def _set_token(path, line, index, value):
    lines = path.read_text().splitlines()
    toks = lines[line - 1].split()
    toks[index] = value
    lines[line - 1] = " ".join(toks)
    path.write_text("\n".join(lines) + "\n")


def test_tum_zero_quaternion_nan_and_missing_files(tum):
    root = tum[0]
    gt = root / "groundtruth.txt"
    good = gt.read_text()
    _set_token(gt, 4, 2, "nan")
    with pytest.raises(InputError, match=r"groundtruth\.txt: line 4: 'nan' is not a finite number"):
        rgbd.read_tum(root)
    gt.write_text(good)
    for i in range(4, 8):
        _set_token(gt, 4, i, "0")
    with pytest.raises(InputError, match=r"groundtruth\.txt: line 4: quaternion .* not a unit"):
        rgbd.read_tum(root)
    (root / "rgb" / "1.200000.png").unlink()
    (root / "groundtruth.txt").unlink()
    with pytest.raises(InputError, match=r"1\.200000\.png: file not found \(listed in .*rgb\.txt line 4\)"):
        rgbd.read_tum(root)
    (root / "rgb.txt").unlink()
    with pytest.raises(InputError, match=r"rgb\.txt: file not found"):
        rgbd.read_tum(root)


# --- ScanNet ------------------------------------------------------------------------------------
@pytest.fixture
def scannet(tmp_path):
    cams = _cameras(12)  # > 10: numeric order differs from name order
    images, depths = _data(cams, seed=1)
    root = tmp_path / "scene0000_00"
    return root, cams, rgbd.write_scannet(root, cams, images, depths), depths


def test_scannet_roundtrip_depth_lens_and_units(scannet):
    root, cams, names, depths = scannet
    cap = rgbd.read_scannet(root)
    assert cap.format == "scannet"
    assert [f.name for f in cap.frames] == [f"{i}.jpg" for i in range(12)] == list(names.values())
    cam0 = next(iter(cams.values()))
    for f, (n, cam) in zip(cap.frames, cams.items()):
        np.testing.assert_allclose(f.cam_from_world, cam.cam_from_world, atol=1e-6)
        np.testing.assert_allclose(f.lens.pinhole_K(), cam.K, atol=1e-9)
        assert (f.lens.width, f.lens.height) == (W, H)
        assert f.depth_units_per_m == 1000
        assert (f.depth_lens.width, f.depth_lens.height) == (W // 2, H // 2)
        np.testing.assert_allclose(f.depth_lens.pinhole_K(), cam0.resized(W // 2, H // 2).K, atol=1e-9)
        raw = np.asarray(Image.open(f.depth))
        assert raw.dtype == np.uint16 and raw.shape == (H // 2, W // 2)
        np.testing.assert_allclose(raw / 1000.0, depths[n][::2, ::2], atol=0.02)


def test_scannet_invalid_pose_is_dropped_with_note(scannet):
    root = scannet[0]
    (root / "pose" / "3.txt").write_text("-inf -inf -inf -inf\n" * 4)
    (root / "pose" / "7.txt").write_text("nan nan nan nan\n" * 4)
    cap = rgbd.read_scannet(root)
    assert [f.name for f in cap.frames] == [f"{i}.jpg" for i in range(12) if i not in (3, 7)]
    assert any("2 frames dropped: invalid pose" in n and "3.jpg" in n for n in cap.notes)


def test_scannet_malformed_files(scannet):
    root = scannet[0]
    pose = (root / "pose" / "5.txt").read_text()
    (root / "pose" / "5.txt").write_text(pose.replace(pose.split()[1], "abc", 1))
    with pytest.raises(InputError, match=r"pose/5\.txt: line 1: 'abc' is not a number"):
        rgbd.read_scannet(root)
    M = np.eye(4)
    M[0, 0] = 2.0
    np.savetxt(root / "pose" / "5.txt", M)
    with pytest.raises(InputError, match=r"pose/5\.txt: rotation part is not a rotation"):
        rgbd.read_scannet(root)
    (root / "pose" / "5.txt").write_text(pose)
    (root / "depth" / "4.png").unlink()
    with pytest.raises(InputError, match=r"depth/4\.png: file not found"):
        rgbd.read_scannet(root)
    (root / "intrinsic" / "intrinsic_color.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match=r"intrinsic_color\.txt: expected a 4x4"):
        rgbd.read_scannet(root)


def test_fixture_writers_refuse_mixed_intrinsics(tmp_path):
    cams = _cameras(2)
    a, b = cams.values()
    cams["v01"] = b.resized(W * 2, H * 2)
    images, depths = _data(_cameras(2))
    for write in (rgbd.write_tum, rgbd.write_scannet):
        with pytest.raises(ValueError, match="same K"):
            write(tmp_path / "x", cams, images, depths)


def test_quaternion_conversions_roundtrip():
    rng = np.random.default_rng(2)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = rgbd._quat_to_R(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(abs(rgbd._R_to_quat(R) @ q), 1.0, atol=1e-12)
    R = rgbd._axis_angle_R([0, 0, 1], 90.0)
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
