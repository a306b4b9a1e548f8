"""Charts and tables from `ibr bench pipeline` results (results.jsonl): Pareto fronts and
stability curves.

Only recorded values are plotted. The latest line per (scene, setting) wins, so rerunning one
setting updates its point. Quality axis: held-out PSNR (dB) from the evaluate stage.
"""
from __future__ import annotations

from pathlib import Path

QUALITY = ("psnr", "PSNR on held-out views (dB)")


def load(results: Path) -> list[dict]:
    from ibr_pipeline.report_sections import latest_results
    return latest_results(results)


def quality(r: dict, key: str = "psnr"):
    v = (r.get("metrics") or {}).get(key)
    return v if isinstance(v, (int, float)) else None


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated by another (lower x better, higher y better), by x."""
    idx = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -float("inf")
    for i in idx:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def points(rows: list[dict], axis: str) -> list[tuple[str, float, float, str]]:
    """(label, x, quality, kind) for one chart. kind: 'ours' for every grid setting; for the
    `default` run also its baselines, scored by the evaluate stage on the same held-out views:
    'single' (no decomposition: its own render time, preprocessing without the reflection stage,
    model without the layer textures), 'oracle' (ground-truth geometry and layers: render-time
    chart only, since it has no preprocessing or model of its own) and 'naive' (nearest captured
    view warped with the global mesh's depth, `render/naive.py`: its CPU ms/frame, preprocessing
    = ingest + global_mesh, model = the global mesh per view)."""
    out = []
    for r in rows:
        if r.get("group") not in ("grid", "baseline"):
            continue
        m = r.get("metrics") or {}
        tex = ((r.get("model_bytes") or {}).get("textures") or 0) / 1e6 / max(1, r.get("views") or 1)
        x = {"render": r.get("render_ms"), "preprocess": r.get("preprocess_s"),
             "size": r.get("mb_per_view")}[axis]
        if x is not None and quality(r) is not None:
            out.append((r["setting"], x, quality(r), "ours"))
        if r.get("setting") != "default":
            continue
        secs = r.get("stage_seconds") or {}
        xs = {"render": r.get("render_ms_single"),
              "preprocess": None if r.get("preprocess_s") is None
              else r["preprocess_s"] - secs.get("reflection", 0.0),
              "size": None if r.get("mb_per_view") is None else r["mb_per_view"] - tex}[axis]
        if xs is not None and m.get("single_psnr") is not None:
            out.append(("single layer", xs, m["single_psnr"], "single"))
        if axis == "render" and x is not None and m.get("oracle_psnr") is not None:
            out.append(("oracle", x, m["oracle_psnr"], "oracle"))
        xn = {"render": m.get("naive_ms"),
              "preprocess": None if not secs else secs.get("ingest", 0.0) + secs.get("global_mesh", 0.0),
              "size": r.get("naive_mb_per_view")}[axis]
        if xn is not None and m.get("naive_psnr") is not None:
            out.append(("naive warp", xn, m["naive_psnr"], "naive"))
    return out


STYLE = {"ours": ("o", "C0"), "single": ("s", "C1"), "oracle": ("*", "C2"), "naive": ("v", "C7")}


def _scatter(rows: list[dict], axis: str, xlabel: str, path: Path, logx: bool = False) -> Path | None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = points(rows, axis)
    if not pts:
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    for kind, (marker, color) in STYLE.items():
        sel = [p for p in pts if p[3] == kind]
        if sel:
            ax.scatter([p[1] for p in sel], [p[2] for p in sel], marker=marker, s=40, color=color,
                       label={"ours": "ours (settings)", "single": "single-layer baseline",
                              "oracle": "oracle (GT geometry + layers)",
                              "naive": "naïve diffuse warp (G depth, nearest view)"}[kind])
    for label, x, y, _ in pts:
        ax.annotate(label, (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
    ours = [p for p in pts if p[3] == "ours"]
    front = pareto([(p[1], p[2]) for p in ours])
    if len(front) > 1:
        ax.plot([ours[i][1] for i in front], [ours[i][2] for i in front], "--", color="C3",
                label="Pareto front (ours)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(QUALITY[1])
    if logx:
        ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=7)
    ax.set_title(f"{rows[0].get('scene')}: quality vs {xlabel.split(' (')[0]}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _stability(rows: list[dict], out: Path) -> Path | None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .stability import AXES
    default = next((quality(r) for r in rows if r.get("setting") == "default"), None)
    kinds: dict[str, list] = {}
    for r in rows:
        if r.get("group") == "stability" and r.get("degrade"):
            kinds.setdefault(r["degrade"][0], []).append((r["degrade"][1], quality(r)))
    if not kinds:
        return None
    n = len(kinds)
    fig, axes = plt.subplots(1, n, figsize=(3.0 * n, 3.0), dpi=110, squeeze=False)
    for ax, (kind, pts) in zip(axes[0], sorted(kinds.items())):
        label, x0 = AXES.get(kind, ("degradation", 0.0))
        pts = sorted(pts + ([(x0, default)] if default is not None else []))
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        ax.plot(xs, [y if y is not None else float("nan") for y in ys], "o-")
        for x, y in zip(xs, ys):
            if y is None:
                ax.axvline(x, color="r", alpha=0.4)  # crashed / no metrics
        ax.set_title(kind, fontsize=9)
        ax.set_xlabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(QUALITY[1], fontsize=8)
    fig.tight_layout()
    path = out / "stability.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def _fmt(v, nd=2):
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def tables(rows: list[dict]) -> tuple[str, str]:
    head = ("| setting | group | W×H | views | preprocess s | render ms | PSNR | SSIM | FLIP | "
            "PSNR in reflectors | MB/view |\n|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        if r.get("group") == "stability":
            continue
        m = r.get("metrics") or {}
        lines.append(f"| {r['setting']} | {r.get('group')} | {r.get('width')}×{r.get('height')} | "
                     f"{r.get('views')} | {_fmt(r.get('preprocess_s'), 1)} | "
                     f"{_fmt(r.get('render_ms'), 1)} | {_fmt(m.get('psnr'))} | "
                     f"{_fmt(m.get('ssim'), 3)} | {_fmt(m.get('flip'), 3)} | "
                     f"{_fmt(m.get('psnr_mask'))} | {_fmt(r.get('mb_per_view'), 3)} |")
    default = next((quality(r) for r in rows if r.get("setting") == "default"), None)
    st = ["| degradation | amount | what the pipeline did | PSNR | cost vs default (dB) |",
          "|---|---|---|---|---|"]
    for r in rows:
        if r.get("group") != "stability":
            continue
        q = quality(r)
        if r.get("crashed"):
            did = f"crashed: {r['crashed'][:80]}"
        else:
            bad = [f"{k}: {v}" for k, v in (r.get("stage_results") or {}).items()
                   if v not in ("ran", "up to date")]
            did = "; ".join((r.get("fallbacks") or []) + bad) or "completed normally"
        cost = None if q is None or default is None else q - default
        st.append(f"| {r['degrade'][0]} | {r['degrade'][1]} | {did} | {_fmt(q)} | {_fmt(cost)} |")
    return "\n".join(lines), "\n".join(st) if len(st) > 2 else ""


def draw_all(results: Path, out: Path) -> list[Path]:
    rows = load(results)
    written = [
        _scatter(rows, "render", "render time (ms/frame)", out / "quality_vs_render_ms.png"),
        _scatter(rows, "preprocess", "preprocessing time (s)", out / "quality_vs_preprocess_s.png"),
        _scatter(rows, "size", "model size (MB per view)", out / "quality_vs_model_mb.png"),
        _stability(rows, out),
    ]
    grid, stab = tables(rows)
    (out / "settings.md").write_text("### Settings\n\n" + grid + "\n")
    written.append(out / "settings.md")
    if stab:
        (out / "stability.md").write_text("### Stability\n\n" + stab + "\n")
        written.append(out / "stability.md")
    return [p for p in written if p is not None]
