"""RGB-D sequences: TUM RGB-D (format "tum") and ScanNet's SensReader export (format "scannet").

TUM RGB-D (Sturm et al. 2012; vision.in.tum.de/data/datasets/rgbd-dataset, "File Formats" and
"Intrinsic Camera Calibration of the Kinect"): `rgb.txt` / `depth.txt` list "timestamp filename",
`groundtruth.txt` lists "timestamp tx ty tz qx qy qz qw" = world_from_camera of the colour camera's
optical frame (OpenCV axes), metres, Hamilton quaternion with the scalar last; depth PNGs are 16-bit
with 5000 units per metre. Colour and depth are paired by TUM's associate.py rule and poses are
interpolated to the colour timestamps. Intrinsics come from `intrinsics.txt` ("fx fy cx cy
[d0 d1 d2 d3 d4]", OpenCV pixel convention and distortion order k1 k2 p1 p2 k3, as TUM publishes
them) or from the published calibration of the Kinect named in the folder (freiburg1/2/3).

ScanNet (Dai et al. 2017; github.com/ScanNet/ScanNet, SensReader/python/reader.py export):
`color/<i>.jpg`, `depth/<i>.png` (16-bit mm), `pose/<i>.txt` (4x4 camera-to-world, OpenCV axes;
"-inf" rows mark frames the tracker lost), `intrinsic/intrinsic_color.txt` and
`intrinsic_depth.txt` (4x4, top-left 3x3 = K, OpenCV pixel convention). The depth frame has its
own size and K, so it is given as `Frame.depth_lens`.

Readers only read (io/capture.py); `write_tum` / `write_scannet` make test fixtures.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError, confined, input_text
from .capture import Capture, Frame, Lens

TUM_DEPTH_UNITS = 5000.0     # TUM "File Formats": a pixel value of 5000 is 1 m
SCANNET_DEPTH_UNITS = 1000.0  # SensReader writes millimetres
MAX_DEPTH_DT = 0.02  # s: associate.py's default --max_difference
MAX_POSE_GAP = 0.1   # s: the mocap runs at 100 Hz; a longer gap is a tracking dropout, not motion
_ROTATION_TOL = 1e-3  # files store rotations with ~6 decimals; worse than this is not a rotation

# TUM "Intrinsic Camera Calibration of the Kinect": colour camera, OpenCV convention,
# (fx, fy, cx, cy, k1, k2, p1, p2, k3). freiburg3 images were undistorted before publication.
TUM_CALIBRATION = {
    "freiburg1": (517.306408, 516.469215, 318.643040, 255.313989,
                  0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
    "freiburg2": (520.908620, 521.007327, 325.141442, 249.701764,
                  0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
    "freiburg3": (535.4, 539.2, 320.1, 247.6, 0.0, 0.0, 0.0, 0.0, 0.0),
}


# --- text parsing -------------------------------------------------------------------------------
def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each non-blank, non-comment line."""
    out = []
    for n, line in enumerate(input_text(path).splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((n, s.split()))
    return out


def _float(tok: str, path: Path, n: int, finite: bool = True) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise InputError(f"{path}: line {n}: {tok!r} is not a number") from None
    if finite and not math.isfinite(v):
        raise InputError(f"{path}: line {n}: {tok!r} is not a finite number")
    return v


def _read_list(path: Path) -> list[tuple[int, float, str]]:
    """TUM "timestamp filename" lines as (line number, timestamp, filename)."""
    out, seen = [], {}
    for n, toks in _data_lines(path):
        if len(toks) != 2:
            raise InputError(f"{path}: line {n}: expected 'timestamp filename', got {' '.join(toks)!r}")
        if toks[1] in seen:
            raise InputError(f"{path}: line {n}: {toks[1]!r} is listed twice (also line {seen[toks[1]]})")
        seen[toks[1]] = n
        out.append((n, _float(toks[0], path, n), toks[1]))
    return out


def _listed_file(root: Path, listing: Path, n: int, rel: str) -> Path:
    p = confined(root, rel, f"{listing}: line {n}")
    if not p.is_file():
        raise InputError(f"{p}: file not found (listed in {listing} line {n})")
    return p


def _read_matrix(path: Path, finite: bool = True) -> np.ndarray:
    """A whitespace-separated numeric matrix (rows = lines)."""
    rows = [[_float(t, path, n, finite) for t in toks] for n, toks in _data_lines(path)]
    if not rows or any(len(r) != len(rows[0]) for r in rows):
        raise InputError(f"{path}: expected a matrix of numbers, one row per line")
    return np.array(rows, dtype=np.float64)


def _rotation(R: np.ndarray, what: str) -> np.ndarray:
    """`R` snapped to the nearest rotation: files store ~6 decimals and Camera checks to 1e-5."""
    if not (np.allclose(R @ R.T, np.eye(3), atol=_ROTATION_TOL) and np.linalg.det(R) > 0):
        raise InputError(f"{what}: rotation part is not a rotation matrix")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def _invert_rigid(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


# --- quaternions (x, y, z, w), Hamilton -----------------------------------------------------------
def _quat_to_R(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _R_to_quat(R: np.ndarray) -> np.ndarray:
    """(x, y, z, w) with w >= 0 (Shepperd's method: stable for every rotation)."""
    tr = np.trace(R)
    i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], tr]))
    if i == 3:
        w = math.sqrt(1 + tr) / 2
        q = np.array([(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
                      (R[1, 0] - R[0, 1]) / (4 * w), w])
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        v = np.zeros(3)
        v[i] = math.sqrt(1 + R[i, i] - R[j, j] - R[k, k]) / 2
        v[j] = (R[j, i] + R[i, j]) / (4 * v[i])
        v[k] = (R[k, i] + R[i, k]) / (4 * v[i])
        q = np.array([*v, (R[k, j] - R[j, k]) / (4 * v[i])])
    return q if q[3] >= 0 else -q


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    d = float(q0 @ q1)
    if d < 0:  # q and -q are the same rotation: take the short way round
        q1, d = -q1, -d
    if d > 1 - 1e-12:
        q = q0 + a * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


# --- TUM ----------------------------------------------------------------------------------------
def _associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> dict[int, int]:
    """associate.py: all pairs closer than max_dt, taken greedily by smallest difference, each
    entry of either list used once. Only the few neighbours within the window are candidates,
    so this is O(n log n) instead of associate.py's all-pairs loop (same result)."""
    order = np.argsort(b, kind="stable")
    bs = b[order]
    cands = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(bs, t - max_dt, "left"), np.searchsorted(bs, t + max_dt, "right")
        for j in order[lo:hi]:
            d = abs(t - b[j])
            if d < max_dt:
                cands.append((d, t, b[j], i, int(j)))
    cands.sort()  # (difference, a time, b time) like associate.py; indices break exact ties
    used_a, used_b, out = set(), set(), {}
    for _, _, _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out[i] = j
    return out


def _read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted times (N,), positions (N, 3), unit quaternions (N, 4) of world_from_camera."""
    times, pos, quats = [], [], []
    for n, toks in _data_lines(path):
        if len(toks) != 8:
            raise InputError(f"{path}: line {n}: expected 'timestamp tx ty tz qx qy qz qw' "
                             f"(8 numbers), got {len(toks)}")
        v = [_float(t, path, n) for t in toks]
        q = np.array(v[4:])
        norm = np.linalg.norm(q)
        # published files round to 4 decimals; a norm far from 1 is a mangled line, not rounding
        if not abs(norm - 1) < 0.1:
            raise InputError(f"{path}: line {n}: quaternion {v[4:]} is not a unit quaternion "
                             f"(norm {norm:.3g})")
        times.append(v[0])
        pos.append(v[1:4])
        quats.append(q / norm)
    if not times:
        raise InputError(f"{path}: no poses (lines 'timestamp tx ty tz qx qy qz qw')")
    order = np.argsort(times, kind="stable")
    return np.array(times)[order], np.array(pos)[order], np.array(quats)[order]


def _pose_at(gt, t: float) -> tuple[np.ndarray | None, str]:
    """world_from_camera at `t` (lerp + slerp between the bracketing poses), or None and why."""
    times, pos, quats = gt
    k = int(np.searchsorted(times, t, "right"))
    if k > 0 and times[k - 1] == t:
        p, q = pos[k - 1], quats[k - 1]
    elif k == 0 or k == len(times):
        return None, "outside the groundtruth time span"
    else:
        t0, t1 = times[k - 1], times[k]
        if t1 - t0 > MAX_POSE_GAP:
            return None, f"in a {t1 - t0:.3f} s groundtruth gap"
        a = (t - t0) / (t1 - t0)
        p = (1 - a) * pos[k - 1] + a * pos[k]
        q = _slerp(quats[k - 1], quats[k], a)
    T = np.eye(4)
    T[:3, :3] = _quat_to_R(q)
    T[:3, 3] = p
    return T, ""


def opencv_lens(fx, fy, cx, cy, dist, width: int, height: int) -> Lens:
    """A Lens from OpenCV intrinsics (top-left pixel centre at (0, 0)) and OpenCV distortion
    (k1, k2, p1, p2[, k3]); COLMAP's OPENCV / FULL_OPENCV share that order and put the pixel
    centre at (0.5, 0.5)."""
    d = [float(x) for x in dist] + [0.0] * (5 - len(dist))
    base = (fx, fy, cx + 0.5, cy + 0.5)
    if not any(d):
        return Lens("PINHOLE", base, width, height)
    if d[4] == 0:
        return Lens("OPENCV", base + tuple(d[:4]), width, height)
    return Lens("FULL_OPENCV", base + tuple(d) + (0.0, 0.0, 0.0), width, height)


def _tum_lens(root: Path, width: int, height: int) -> tuple[Lens, Path | None, str]:
    path = root / "intrinsics.txt"
    if path.is_file():
        toks = [(n, t) for n, ts in _data_lines(path) for t in ts]
        if len(toks) not in (4, 9):
            raise InputError(f"{path}: expected 'fx fy cx cy' or 'fx fy cx cy d0 d1 d2 d3 d4' "
                             f"(OpenCV convention), got {len(toks)} numbers")
        v = [_float(t, path, n) for n, t in toks]
        if not (v[0] > 0 and v[1] > 0):
            raise InputError(f"{path}: focal lengths must be > 0, got fx={v[0]} fy={v[1]}")
        return opencv_lens(*v[:4], v[4:], width, height), path, "intrinsics from intrinsics.txt"
    name = Path(root).resolve().name
    for kinect, c in TUM_CALIBRATION.items():
        if kinect in name:
            return (opencv_lens(*c[:4], c[4:], width, height), None,
                    f"intrinsics: TUM's published {kinect} colour calibration (folder name)")
    raise InputError(f"{root}: TUM sequence without intrinsics: the folder name names no "
                     "freiburg1/2/3 Kinect; add intrinsics.txt with 'fx fy cx cy [d0 d1 d2 d3 d4]' "
                     "(OpenCV convention)")


def read_tum(root: Path, stride: int = 1) -> Capture:
    """A TUM RGB-D sequence folder; `stride` keeps every k-th associated frame."""
    from .images import image_size

    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: input folder does not exist")
    if not (isinstance(stride, (int, np.integer)) and stride >= 1):
        raise InputError(f"TUM stride must be a whole number >= 1, got {stride!r}")
    rgb_txt, depth_txt, gt_txt = root / "rgb.txt", root / "depth.txt", root / "groundtruth.txt"
    if not rgb_txt.is_file():
        raise InputError(f"{rgb_txt}: file not found (a TUM sequence lists its colour frames there)")
    files, notes = [rgb_txt], []
    rgb = _read_list(rgb_txt)
    if not rgb:
        raise InputError(f"{rgb_txt}: lists no frames")

    if depth_txt.is_file():
        files.append(depth_txt)
        depth = _read_list(depth_txt)
        match = _associate(np.array([t for _, t, _ in rgb]), np.array([t for _, t, _ in depth]),
                           MAX_DEPTH_DT)
        keep = sorted(match, key=lambda i: (rgb[i][1], i))
        if not keep:
            raise InputError(f"{depth_txt}: no depth frame lies within {MAX_DEPTH_DT} s of any "
                             f"colour frame of {rgb_txt}")
        notes.append(f"tum: {len(keep)} of {len(rgb)} colour frames have a depth frame within "
                     f"{MAX_DEPTH_DT} s (TUM associate.py); the others are dropped")
    else:
        depth, match = [], {}
        keep = sorted(range(len(rgb)), key=lambda i: (rgb[i][1], i))
        notes.append(f"tum: {len(rgb)} colour frames; no depth.txt: no depth")
    if stride > 1:
        keep = keep[::stride]
        notes.append(f"stride {stride}: {len(keep)} frames kept")

    gt = None
    if gt_txt.is_file():
        files.append(gt_txt)
        gt = _read_groundtruth(gt_txt)
    else:
        notes.append("no groundtruth.txt: frames are unposed")

    frames, dropped = [], []
    for i in keep:
        n, t, rel = rgb[i]
        image = _listed_file(root, rgb_txt, n, rel)
        dpath = None
        if i in match:
            dn, _, drel = depth[match[i]]
            dpath = _listed_file(root, depth_txt, dn, drel)
        pose = None
        if gt is not None:
            wfc, why = _pose_at(gt, t)
            if wfc is None:
                dropped.append(f"{rel} ({why})")
                continue
            pose = _invert_rigid(wfc)
        name = image.relative_to(root).as_posix()
        frames.append((name.removeprefix("rgb/"), image, pose, dpath))
    if dropped:
        notes.append(f"{len(dropped)} frames dropped without a groundtruth pose: "
                     + ", ".join(dropped[:3]) + (" ..." if len(dropped) > 3 else ""))
    if not frames:
        raise InputError(f"{gt_txt}: no colour frame of {rgb_txt} lies within the groundtruth "
                         f"(gaps <= {MAX_POSE_GAP} s); is it the trajectory of this sequence?")
    lens, lens_file, lens_note = _tum_lens(root, *image_size(frames[0][1]))
    notes.append(lens_note + (" (distorted: undistorted at ingest)" if lens.distorted else ""))
    files += [lens_file] if lens_file else []
    if depth:
        notes.append(f"depth: {TUM_DEPTH_UNITS:g} units per metre, registered to the colour frames")
    out = tuple(Frame(nm, im, pose, lens, dp, TUM_DEPTH_UNITS) for nm, im, pose, dp in frames)
    files += [f.image for f in out] + [f.depth for f in out if f.depth is not None]
    return Capture("tum", out, files=tuple(files), notes=tuple(notes))


# --- ScanNet ------------------------------------------------------------------------------------
def _scannet_K(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: file not found (ScanNet intrinsics, 4x4 with K top-left)")
    M = _read_matrix(path)
    if M.shape not in ((4, 4), (3, 3)):
        raise InputError(f"{path}: expected a 4x4 (or 3x3) matrix, got {M.shape[0]}x{M.shape[1]}")
    K = M[:3, :3]
    if not (K[0, 0] > 0 and K[1, 1] > 0) or K[0, 1] != 0 or np.any(K[2] != [0, 0, 1]) or K[1, 0] != 0:
        raise InputError(f"{path}: not a pinhole K without skew: {K.tolist()}")
    return K


def read_scannet(root: Path) -> Capture:
    """A ScanNet scene exported by SensReader (color/, depth/, pose/, intrinsic/)."""
    from .images import image_size

    root = Path(root)
    color_dir = root / "color"
    if not color_dir.is_dir():
        raise InputError(f"{root}: no color/ folder (ScanNet SensReader export)")
    by_index: dict[int, Path] = {}
    ignored = []
    for p in sorted(color_dir.iterdir()):
        if p.name.startswith(".") or not p.is_file():
            continue
        if p.suffix.lower() not in (".jpg", ".jpeg", ".png") or not p.stem.isdigit():
            ignored.append(p.name)
            continue
        i = int(p.stem)
        if i in by_index:
            raise InputError(f"{p}: frame {i} also exists as {by_index[i].name}")
        by_index[i] = p
    if not by_index:
        raise InputError(f"{color_dir}: no frames (<index>.jpg)")
    notes = [f"scannet: {len(by_index)} frames in color/"]
    if ignored:
        notes.append(f"color/: ignored {len(ignored)} files not named <index>.jpg: {ignored[:3]}")

    intr = root / "intrinsic"
    files = [intr / "intrinsic_color.txt"]
    first = by_index[min(by_index)]
    lens = Lens.from_K(_scannet_K(intr / "intrinsic_color.txt"), *image_size(first))
    depth_dir, pose_dir = root / "depth", root / "pose"
    depth_lens = None
    if depth_dir.is_dir():
        files.append(intr / "intrinsic_depth.txt")
        Kd = _scannet_K(intr / "intrinsic_depth.txt")
        d0 = depth_dir / f"{min(by_index)}.png"
        if not d0.is_file():
            raise InputError(f"{d0}: file not found (depth frame of {first.name})")
        depth_lens = Lens.from_K(Kd, *image_size(d0))
        notes.append(f"depth: {SCANNET_DEPTH_UNITS:g} units per metre, "
                     f"{depth_lens.width}x{depth_lens.height} with intrinsic_depth.txt")
    else:
        notes.append("no depth/ folder: no depth")
    if not pose_dir.is_dir():
        notes.append("no pose/ folder: frames are unposed")

    frames, invalid = [], []
    for i in sorted(by_index):
        image = by_index[i]
        pose = None
        if pose_dir.is_dir():
            pf = pose_dir / f"{i}.txt"
            if not pf.is_file():
                raise InputError(f"{pf}: file not found (pose of {image.name})")
            M = _read_matrix(pf, finite=False)  # -inf / nan rows are ScanNet's "no pose"
            if M.shape != (4, 4):
                raise InputError(f"{pf}: expected a 4x4 camera-to-world matrix, got "
                                 f"{M.shape[0]}x{M.shape[1]}")
            if not np.all(np.isfinite(M)):
                invalid.append(image.name)
                continue
            if not np.allclose(M[3], [0, 0, 0, 1]):
                raise InputError(f"{pf}: last row must be 0 0 0 1, got {M[3].tolist()}")
            M[:3, :3] = _rotation(M[:3, :3], str(pf))
            pose = _invert_rigid(M)
            files.append(pf)
        dpath = None
        if depth_lens is not None:
            dpath = depth_dir / f"{i}.png"
            if not dpath.is_file():
                raise InputError(f"{dpath}: file not found (depth frame of {image.name})")
            files.append(dpath)
        files.append(image)
        frames.append(Frame(image.name, image, pose, lens, dpath, SCANNET_DEPTH_UNITS, depth_lens))
    if invalid:
        notes.append(f"{len(invalid)} frames dropped: invalid pose (-inf/nan in pose/): "
                     + ", ".join(invalid[:3]) + (" ..." if len(invalid) > 3 else ""))
    if not frames:
        raise InputError(f"{pose_dir}: every pose is invalid (-inf/nan): nothing to read")
    return Capture("scannet", tuple(frames), files=tuple(files), notes=tuple(notes))


# --- fixture writers ----------------------------------------------------------------------------
def _same_K(cameras: dict) -> np.ndarray:
    cams = list(cameras.values())
    if not cams or any(not np.allclose(c.K, cams[0].K) or c.size != cams[0].size for c in cams):
        raise ValueError("fixture writers need at least one camera, all with the same K and size")
    return cams[0].K


def _axis_angle_R(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    A = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = math.radians(deg)
    return np.eye(3) + math.sin(th) * A + (1 - math.cos(th)) * A @ A  # Rodrigues


def write_tum(root: Path, cameras: dict, images: dict, depths: dict | None = None) -> dict[str, str]:
    """Write {name: Camera} (same K), colour (H, W, 3) floats and metric depth as a TUM sequence.

    Frame i is at 1.0 + 0.1 i s, its depth 5 ms later. groundtruth.txt has no pose at the frame
    times: two per frame, at t - 0.02 and t + 0.06, rotated by -d and +3d about a fixed axis and
    moved by -e and +3e, so interpolation (a = 0.25) gives back the camera only if it slerps.
    Returns {camera name: TUM frame name}.
    """
    from .images import write_depth_png, write_image

    root = Path(root)
    K = _same_K(cameras)
    D = _axis_angle_R((0.3, 0.5, 0.8), 8.0)
    step = np.array([0.01, -0.02, 0.015])
    rgb_lines, depth_lines, names = ["# color images"], ["# depth maps"], {}
    gt_lines = ["# timestamp tx ty tz qx qy qz qw"]
    for i, (name, cam) in enumerate(cameras.items()):
        t = 1.0 + 0.1 * i
        stamp = f"{t:.6f}"
        write_image(root / "rgb" / f"{stamp}.png", images[name])
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        if depths is not None:
            td = f"{t + 0.005:.6f}"
            # write_depth_png writes mm: metres x 5 come out in TUM's 1/5000 m units
            scaled = np.asarray(depths[name], dtype=np.float64) * (TUM_DEPTH_UNITS / 1000)
            write_depth_png(root / "depth" / f"{td}.png", scaled)
            depth_lines.append(f"{td} depth/{td}.png")
        R, c = cam.world_from_cam[:3, :3], cam.center
        for dt, p, Rp in ((-0.02, c - step, R @ D.T), (0.06, c + 3 * step, R @ D @ D @ D)):
            gt_lines.append(f"{t + dt:.6f} " + " ".join(f"{v:.17g}" for v in (*p, *_R_to_quat(Rp))))
        names[name] = f"{stamp}.png"
    root.mkdir(parents=True, exist_ok=True)
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    if depths is not None:
        (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    (root / "intrinsics.txt").write_text(
        "# fx fy cx cy (OpenCV convention)\n"
        + " ".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])) + "\n")
    return names


def write_scannet(root: Path, cameras: dict, images: dict, depths: dict | None = None) -> dict[str, str]:
    """Write {name: Camera} (same K, even size) as a SensReader export: JPEG colour (quality 95),
    depth at half resolution (2x2 means; 0 where any is missing) with the half-size K.
    Returns {camera name: ScanNet frame name}."""
    from PIL import Image

    from ..workspace import atomic_path
    from .images import to_uint8, write_depth_png

    root = Path(root)
    K = _same_K(cameras)
    cam0 = next(iter(cameras.values()))
    w, h = cam0.size
    Kd = cam0.resized(w // 2, h // 2).K
    (root / "intrinsic").mkdir(parents=True, exist_ok=True)
    for fname, M3 in (("intrinsic_color.txt", K), ("intrinsic_depth.txt", Kd)):
        M = np.eye(4)
        M[:3, :3] = M3
        np.savetxt(root / "intrinsic" / fname, M, fmt="%.17g")
    for fname in ("extrinsic_color.txt", "extrinsic_depth.txt"):
        np.savetxt(root / "intrinsic" / fname, np.eye(4), fmt="%g")
    names = {}
    (root / "pose").mkdir(exist_ok=True)
    for i, (name, cam) in enumerate(cameras.items()):
        with atomic_path(root / "color" / f"{i}.jpg") as tmp:
            Image.fromarray(to_uint8(images[name])).save(tmp, format="JPEG", quality=95)
        if depths is not None:
            d = np.asarray(depths[name], dtype=np.float64)
            blocks = d[:h // 2 * 2, :w // 2 * 2].reshape(h // 2, 2, w // 2, 2)
            valid = np.all(np.isfinite(blocks) & (blocks > 0), axis=(1, 3))
            half = np.where(valid, np.nan_to_num(blocks).mean(axis=(1, 3)), 0.0)
            write_depth_png(root / "depth" / f"{i}.png", half)  # mm, as SensReader
        np.savetxt(root / "pose" / f"{i}.txt", cam.world_from_cam, fmt="%.17g")
        names[name] = f"{i}.jpg"
    return names
