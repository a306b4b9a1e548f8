"""A PNG contact sheet of a generated scene, for a person to look at.

Row 1-2: eight capture views spread over the path. Row 3: the most reflective capture view with
its GT depth, sensor depth, normals. Row 4: its layers I0, I1, beta, plus a test and a
fly-through view. Colour tiles are shown with a 1/2.2 display gamma (files stay linear).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from ..io.images import read_depth_png, read_image
from ..workspace import atomic_path

TILE_W = 200


def _colormap(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    import matplotlib

    lo, hi = (np.percentile(x[valid], [1, 99]) if valid.any() else (0.0, 1.0))
    t = np.clip((x - lo) / max(hi - lo, 1e-6), 0, 1)
    rgb = matplotlib.colormaps["turbo"](t)[..., :3]
    return np.where(valid[..., None], rgb, 0.0)


def _tile(arr: np.ndarray, label: str, gamma: bool, size: tuple[int, int]) -> Image.Image:
    a = np.clip(np.asarray(arr, dtype=np.float64), 0, 1)
    if gamma:
        a = a ** (1 / 2.2)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    im = Image.fromarray((a * 255 + 0.5).astype(np.uint8)).resize(size, Image.BILINEAR)
    d = ImageDraw.Draw(im)
    d.rectangle((0, 0, 7 * len(label) + 6, 13), fill=(0, 0, 0))
    d.text((3, 1), label, fill=(255, 255, 255))
    return im


def contact_sheet(root: Path, path: Path) -> None:
    root = Path(root)
    names = sorted(p.name for p in (root / "images").glob("*.png"))
    if not names:
        return
    first = read_image(root / "images" / names[0])
    h, w = first.shape[:2]
    size = (TILE_W, int(round(TILE_W * h / w)))
    tiles: list[Image.Image] = []
    for k in np.linspace(0, len(names) - 1, 8).round().astype(int):
        tiles.append(_tile(read_image(root / "images" / names[k]), names[k], True, size))
    # most reflective view
    best, best_frac = names[0], -1.0
    for n in names:
        p = root / "gt" / "beta" / n
        if p.is_file():
            frac = float((np.asarray(Image.open(p)) > 0).mean())
            if frac > best_frac:
                best, best_frac = n, frac
    stem = Path(best).stem
    geom = np.load(root / "gt" / "geom" / f"{stem}.npz")
    depth = geom["depth"]
    tiles.append(_tile(read_image(root / "images" / best), f"{best} (most reflective)", True, size))
    tiles.append(_tile(_colormap(depth, depth > 0), "GT depth", False, size))
    sd = root / "depth" / f"{stem}.png"
    if sd.is_file():
        s = read_depth_png(sd)
        tiles.append(_tile(_colormap(s, s > 0), "sensor depth", False, size))
    tiles.append(_tile(0.5 + 0.5 * geom["normal"].astype(np.float64), "GT normal", False, size))
    for layer in ("I0", "I1", "beta"):
        p = root / "gt" / layer / best
        if p.is_file():
            tiles.append(_tile(np.asarray(Image.open(p), dtype=np.float64) / 255, f"gt {layer}",
                               layer != "beta", size))
    for sub in ("test", "flythrough"):
        ims = sorted((root / "gt" / sub / "images").glob("*.png"))
        if ims:
            tiles.append(_tile(read_image(ims[0]), f"{sub} {ims[0].name}", True, size))
    cols = 4
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * size[0], rows * size[1] + 18), (30, 30, 30))
    scene = json.loads((root / "gt" / "scene.json").read_text()) if (root / "gt" / "scene.json").is_file() else {}
    ImageDraw.Draw(sheet).text((4, 3), f"{scene.get('scene', root.name)}  seed {scene.get('seed', '?')}"
                               f"  {len(names)} views  {w}x{h}", fill=(255, 255, 255))
    for k, t in enumerate(tiles):
        sheet.paste(t, ((k % cols) * size[0], 18 + (k // cols) * size[1]))
    with atomic_path(Path(path)) as tmp:
        sheet.save(tmp, format="PNG")
