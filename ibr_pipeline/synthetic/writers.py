"""Deterministic writers for the synthetic outputs (byte-identical for identical inputs).

np.savez stamps the current time into its zip entries; `save_npz` fixes the timestamp so that a
regenerated scene is bit-for-bit identical. 8-bit layers are quantised here (Xu et al. Eq. 3).
"""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from ..workspace import atomic_path
from .geometry import TriangleSoup


def quantize(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] floats -> uint8 (round to nearest, clamped)."""
    return np.clip(np.rint(np.nan_to_num(np.asarray(x, dtype=np.float64)) * 255.0), 0, 255).astype(np.uint8)


def compose_8bit(I0: np.ndarray, I1: np.ndarray, beta: np.ndarray):
    """Quantise the layers first and define the stored image from them, so that Xu Eq. 3
    I = I0 + beta * I1 holds in the stored 8-bit values to within 0.5/255.

    I0, I1: (H, W, 3); beta: (H, W). Returns uint8 (q0, q1, qbeta, image)."""
    if I0.shape != I1.shape or I0.ndim != 3 or beta.shape != I0.shape[:2]:
        raise ValueError(f"layers must be (H, W, 3) x2 and beta (H, W): {I0.shape} {I1.shape} {beta.shape}")
    q0, q1, qb = quantize(I0), quantize(I1), quantize(beta)
    img = q0 / 255.0 + (qb / 255.0)[..., None] * (q1 / 255.0)
    return q0, q1, qb, quantize(img)


# the per-view ground-truth geometry (gt/geom): deflate, not LZMA, whose compression was a large
# share of `ibr synth`'s time at 640x480 for files a third the size: generation time is what
# users wait for, the disk holds either (docs/SYNTHETIC.md)
GEOM_COMPRESSION = "deflate"


def save_npz(path: Path, method: str = "deflate", **arrays: np.ndarray) -> None:
    """Like np.savez_compressed, with fixed zip timestamps (deterministic bytes), atomically.

    method: 'deflate' (what np.savez_compressed uses), 'lzma' (3-6x smaller on depth maps, still
    read by np.load) or 'store'."""
    comp = {"deflate": zipfile.ZIP_DEFLATED, "lzma": zipfile.ZIP_LZMA, "store": zipfile.ZIP_STORED}[method]
    # deflate level 1, not zlib's 6: the geometry files come out a few per cent larger, and
    # compressing them no longer dominates writing a view (docs/SYNTHETIC.md)
    level = 1 if method == "deflate" else None
    with atomic_path(Path(path)) as tmp, zipfile.ZipFile(tmp, "w", compression=comp) as zf:
        for key, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = comp
            zf.writestr(info, buf.getvalue(), compresslevel=level)


def round_depth(depth: np.ndarray) -> np.ndarray:
    """float32 depth rounded to multiples of 2^-16 m (15 um): exact for every purpose here, and
    the zeroed low mantissa bits make it compress ~6x better."""
    return (np.round(np.asarray(depth, dtype=np.float64) * 65536.0) / 65536.0).astype(np.float32)


def write_ply(path: Path, soup: TriangleSoup, colors: np.ndarray) -> None:
    """Binary PLY of the triangle soup: per-vertex position, normal, colour; per-face material.

    colors: (n_materials, 3) uint8 display colour of each material."""
    tris = soup.tris.reshape(-1, 3).astype(np.float32)
    nrm = soup.corner_normals.reshape(-1, 3).astype(np.float32)
    col = np.repeat(colors[soup.face_material], 3, axis=0).astype(np.uint8)
    nv, nf = len(tris), len(soup.tris)
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                    ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v = np.empty(nv, dtype=vdt)
    for i, k in enumerate(("x", "y", "z")):
        v[k], v["n" + k] = tris[:, i], nrm[:, i]
    v["red"], v["green"], v["blue"] = col[:, 0], col[:, 1], col[:, 2]
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("material", "<i4")])
    f = np.empty(nf, dtype=fdt)
    f["n"] = 3
    f["v"] = np.arange(nv, dtype=np.int32).reshape(-1, 3)
    f["material"] = soup.face_material
    header = (f"ply\nformat binary_little_endian 1.0\ncomment ibr_pipeline synthetic scene\n"
              f"element vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
              f"property float nx\nproperty float ny\nproperty float nz\n"
              f"property uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {nf}\nproperty list uchar int vertex_indices\nproperty int material\n"
              f"end_header\n")
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())
