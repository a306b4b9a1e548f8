"""Pictures the report draws from recorded files: a top-down plan of the cameras over the global
mesh, per-stage times, the run's speed against accuracy, layer thumbnails.

Pure drawing: each function takes arrays/values already read by `report_sections` and writes one
PNG; none measures anything. Colours are matplotlib's defaults (C0 blue: training cameras, C1
orange: held-out cameras, C2 green: the tour path), which the screenshot test looks for.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

THUMB_WIDTH = 320  # px: report thumbnails (a capture's 4000-px photo would make the HTML huge)


def _figure(w: float, h: float):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt, plt.subplots(figsize=(w, h), dpi=100)


def _save(plt, fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plan_axes(rotations: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(2, 3) world directions of a top-down plan: the floor plane is perpendicular to the mean
    camera up (OpenCV cameras: image y points down, so up = -row 1 of R); its first axis is the
    cameras' principal horizontal spread. rotations (N, 3, 3) world->camera, centres (N, 3)."""
    rotations, centres = np.asarray(rotations, float), np.asarray(centres, float)
    if rotations.ndim != 3 or rotations.shape[1:] != (3, 3) or centres.shape != (len(rotations), 3):
        raise ValueError(f"need (N,3,3) rotations and (N,3) centres, got {rotations.shape}, "
                         f"{centres.shape}")
    up = -rotations[:, 1, :].mean(0)
    up /= np.linalg.norm(up) or 1.0
    flat = centres - centres.mean(0)
    flat -= np.outer(flat @ up, up)
    if len(centres) >= 2 and np.linalg.norm(flat) > 1e-9:
        e1 = np.linalg.svd(flat, full_matrices=False)[2][0]
    else:  # one camera (or all at one spot): its viewing direction on the floor
        e1 = rotations[0, 2, :] - (rotations[0, 2, :] @ up) * up
    e1 -= (e1 @ up) * up
    e1 /= np.linalg.norm(e1) or 1.0
    return np.stack([e1, np.cross(up, e1)])


def top_down(path: Path, mesh_points: np.ndarray | None, cameras: dict[str, list],
             title: str) -> Path:
    """Plan view: mesh vertices as a grey density, each camera as a small frustum (apex at its
    centre, opening along its view direction). cameras: role -> [Camera]; roles 'training',
    'held out', 'tour' (a line)."""
    allcams = [c for cs in cameras.values() for c in cs]
    if not allcams:
        raise ValueError("no cameras to draw")
    A = plan_axes(np.array([c.R for c in allcams]), np.array([c.center for c in allcams]))
    cxy = np.array([c.center for c in allcams]) @ A.T
    lo, hi = cxy.min(0), cxy.max(0)
    plt, (fig, ax) = _figure(6.4, 5.6)
    if mesh_points is not None and len(mesh_points):
        p = np.asarray(mesh_points, float) @ A.T
        plo, phi = np.percentile(p, 1, 0), np.percentile(p, 99, 0)  # far-field outliers cut
        lo, hi = np.minimum(lo, plo), np.maximum(hi, phi)
        keep = np.all((p >= lo) & (p <= hi), 1)
        ax.hist2d(p[keep, 0], p[keep, 1], bins=160, cmap="Greys", cmin=1, norm="log")
    span = float(max(hi - lo)) or 1.0
    size = 0.04 * span
    colours = {"training": "C0", "held out": "C1", "tour": "C2"}
    for role, cams in cameras.items():
        col = colours.get(role, "C3")
        xy = np.array([c.center for c in cams]) @ A.T
        if role == "tour":
            ax.plot(xy[:, 0], xy[:, 1], "-", color=col, lw=1.5, label=f"{role} path")
            continue
        for c, o in zip(cams, xy):
            half = np.arctan2(c.width / 2, c.K[0, 0])
            d = c.R[2] @ A.T
            ang = np.arctan2(d[1], d[0])
            ends = [o + size * np.array([np.cos(ang + s * half), np.sin(ang + s * half)]) / np.cos(half)
                    for s in (-1, 1)]
            ax.fill([o[0], ends[0][0], ends[1][0]], [o[1], ends[0][1], ends[1][1]], color=col,
                    alpha=0.55, lw=0)
        ax.plot(xy[:, 0], xy[:, 1], "o", ms=2.5, color=col, label=f"{role} ({len(cams)})")
    ax.set_aspect("equal")
    ax.set_xlim(lo[0] - 0.08 * span, hi[0] + 0.08 * span)
    ax.set_ylim(lo[1] - 0.08 * span, hi[1] + 0.08 * span)
    ax.set_xlabel("plan axis 1 (scene units)")
    ax.set_ylabel("plan axis 2")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    return _save(plt, fig, path)


def stage_times(path: Path, stages: list[str], seconds: list[float]) -> Path:
    """Horizontal bars: seconds per stage, in pipeline order."""
    if len(stages) != len(seconds) or not stages:
        raise ValueError(f"need one time per stage, got {len(stages)} stages, {len(seconds)} times")
    plt, (fig, ax) = _figure(6.4, 0.35 * len(stages) + 1.2)
    y = np.arange(len(stages))[::-1]
    ax.barh(y, seconds, color="C0")
    ax.set_yticks(y, stages)
    for yi, s in zip(y, seconds):
        ax.text(s, yi, f" {s:.3g} s", va="center", fontsize=8)
    ax.set_xlim(0, max(seconds) * 1.25 or 1)
    ax.set_xlabel("seconds (sum over views; parallel views overlap in wall time)")
    ax.set_title("time per stage", fontsize=10)
    return _save(plt, fig, path)


def speed_accuracy(path: Path, points: list[tuple[str, float, float]], title: str) -> Path:
    """Scatter of (label, ms per frame, PSNR dB), log time axis."""
    if not points:
        raise ValueError("no points")
    plt, (fig, ax) = _figure(6.4, 4.2)
    for i, (label, ms, db) in enumerate(points):
        ax.plot([ms], [db], "o", color=f"C{i % 10}", ms=8)
        ax.annotate(label, (ms, db), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.set_xscale("log")
    ms = [p[1] for p in points]
    ax.set_xlim(min(ms) / 1.3, max(ms) * 2.0)  # room for the labels right of the points
    db = [p[2] for p in points]
    ax.set_ylim(min(db) - 0.5, max(db) + 0.5)
    ax.set_xlabel("ms per frame (median, this machine)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    return _save(plt, fig, path)


def thumbnail(path: Path, image: np.ndarray) -> Path:
    """(H, W, 3) uint8 display image -> PNG at most THUMB_WIDTH wide."""
    from PIL import Image
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"need (H, W, 3) uint8, got {image.shape} {image.dtype}")
    im = Image.fromarray(image)
    if im.width > THUMB_WIDTH:
        im = im.resize((THUMB_WIDTH, max(1, round(im.height * THUMB_WIDTH / im.width))),
                       Image.LANCZOS)
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path)
    return path


def colour_map(values: np.ndarray, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """(H, W) scalars -> (H, W, 3) uint8 through viridis (for beta, in [lo, hi])."""
    import matplotlib
    v = np.asarray(values, float)
    if v.ndim != 2:
        raise ValueError(f"need (H, W), got {v.shape}")
    t = np.clip((np.nan_to_num(v) - lo) / ((hi - lo) or 1.0), 0, 1)
    return (matplotlib.colormaps["viridis"](t)[..., :3] * 255).round().astype(np.uint8)
