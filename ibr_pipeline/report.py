"""`ibr report WS`: one self-contained HTML page and its Markdown twin, from recorded measurements.

The report only *formats* numbers that stages and benchmarks wrote to disk: every value shown is a
`Fact` carrying the file and key it came from, and `facts.json` next to the report lists them, so a
reader (and the test) can trace each figure to its measurement. Nothing is recomputed here.

Sources, each optional (a section is left out when its files do not exist):
  .ibr/state/<stage>[/<view>].json  per-stage status and seconds (the runner's records)
  .ibr/runs.jsonl                   wall time of each `ibr run`
  global/report.json                global_mesh counts, errors, timings
  views/*/depth_report.json, views/*/mesh_report.json, views/*/layers.json   per-view reports
  eval/metrics.json                 held-out metrics; eval/*.png side-by-sides and charts
  renders/**/*.mp4, eval/*.mp4      fly-through video
  bench/*.png, bench/*.jsonl        `ibr bench` charts and results (when the bench wrote here)

HTML: images and the video are embedded as base64 data URIs, so the file opens in a browser from
disk, with no server and no other file. Markdown: images are copied next to it under `img/`.
"""
from __future__ import annotations

import base64
import html
import json
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from statistics import median

from . import layout as L
from .errors import InputError


@dataclass(frozen=True)
class Fact:
    """One number in the report and where it was measured."""

    value: float
    source: str  # workspace-relative file
    key: str     # dotted key path inside that file ('' for the aggregate of a file set)

    def text(self) -> str:
        return fmt(self.value)


def fmt(v) -> str:
    """The one number format of the report (so a test can match figures to their sources)."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        if math.isinf(v):
            return "inf"
        a = abs(v)
        if a != 0 and (a >= 1e5 or a < 1e-3):
            return f"{v:.3g}"
        return f"{v:.4g}"
    return str(v)


class Report:
    """Sections of (title, blocks); a block is ('p', text) | ('table', header, rows) | ('img', path,
    caption) | ('video', path, caption). Table cells are str or Fact."""

    def __init__(self, ws_root: Path):
        self.root = ws_root
        self.sections: list[tuple[str, list]] = []
        self.facts: list[Fact] = []

    def fact(self, value, source: Path, key: str):
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return str(value)
        f = Fact(value, source.relative_to(self.root).as_posix(), key)
        self.facts.append(f)
        return f

    def add(self, title: str, blocks: list) -> None:
        if blocks:
            self.sections.append((title, blocks))


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _flatten(d, prefix: str = "") -> dict:
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, (int, float, str, bool)) or d is None:
        out[prefix] = d
    return out


# --- sections --------------------------------------------------------------------------------------
def _timings(rep: Report) -> None:
    state = rep.root / ".ibr" / "state"
    if not state.is_dir():
        return
    from .stages import STAGES
    rows = []
    for s in STAGES:
        whole = state / f"{s.name}.json"
        per_view = sorted((state / s.name).glob("*.json")) if (state / s.name).is_dir() else []
        recs = [(p, _read_json(p)) for p in ([whole] if whole.is_file() else []) + per_view]
        recs = [(p, r) for p, r in recs if r]
        if not recs:
            continue
        ok = sum(r.get("status") == "ok" for _, r in recs)
        secs = [r.get("seconds", 0.0) for _, r in recs]
        total = sum(secs)
        src = whole if whole.is_file() else state / s.name
        rows.append([s.name, f"{ok}/{len(recs)} ok",
                     rep.fact(round(total, 3), src, "sum(seconds)"),
                     rep.fact(round(median(secs), 3), src, "median(seconds)")
                     if per_view else "-"])
    blocks = [("table", ["stage", "records", "seconds (sum)", "s/view (median)"], rows)] if rows else []
    runs = rep.root / ".ibr" / "runs.jsonl"
    if runs.is_file():
        lines = [json.loads(x) for x in runs.read_text().splitlines() if x.strip()]
        if lines:
            last = lines[-1]
            run_rows = [[e["stage"], e["result"], rep.fact(e["seconds"], runs, f"[-1].{e['stage']}.seconds")]
                        for e in last["stages"]]
            blocks += [("p", f"Last `ibr run` finished {last['finished']}:"),
                       ("table", ["stage", "result", "wall seconds"], run_rows)]
    rep.add("Timings", blocks)


def _json_table(rep: Report, path: Path, title: str, skip=("config",)) -> None:
    d = _read_json(path)
    if not isinstance(d, dict):
        return
    flat = {k: v for k, v in _flatten(d).items() if not any(k.startswith(s) for s in skip)}
    rows = [[k, rep.fact(v, path, k)] for k, v in flat.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)]
    rows += [[k, str(v)] for k, v in flat.items() if isinstance(v, str) and len(v) < 80]
    if rows:
        rep.add(title, [("p", f"From `{path.relative_to(rep.root)}`."),
                        ("table", ["quantity", "value"], rows[:60])])


def _per_view(rep: Report, name: str, title: str) -> None:
    files = sorted((rep.root / "views").glob(f"*/{name}"))
    vals: dict[str, list[float]] = {}
    for f in files:
        for k, v in _flatten(_read_json(f) or {}).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                vals.setdefault(k, []).append(float(v))
    if not vals:
        return
    src = rep.root / "views"
    rows = [[k, rep.fact(len(v), src, f"*/{name}:{k}:count"),
             rep.fact(round(median(v), 6), src, f"*/{name}:{k}:median"),
             rep.fact(round(min(v), 6), src, f"*/{name}:{k}:min"),
             rep.fact(round(max(v), 6), src, f"*/{name}:{k}:max")] for k, v in vals.items()]
    rep.add(title, [("p", f"Aggregated over {len(files)} views (`views/*/{name}`)."),
                    ("table", ["field", "views", "median", "min", "max"], rows)])


def _media(rep: Report) -> None:
    imgs = sorted((rep.root / "eval").rglob("*.png"), key=lambda p: (len(p.parts), p)) \
        if (rep.root / "eval").is_dir() else []
    blocks = [("img", p, p.relative_to(rep.root / "eval").with_suffix("").as_posix()
               .replace("_", " ")) for p in imgs[:16]]
    vids = sorted(rep.root.glob("eval/*.mp4")) + sorted(rep.root.glob("renders/**/*.mp4"))
    if vids:
        blocks.append(("video", vids[0], f"fly-through ({vids[0].relative_to(rep.root)})"))
    rep.add("Images and video", blocks)


def latest_results(results: Path) -> list[dict]:
    """The rows of an `ibr bench` results.jsonl, the latest per (scene, setting)."""
    latest: dict[tuple, dict] = {}
    for line in Path(results).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            latest[(r.get("scene"), r.get("setting"))] = r
    return list(latest.values())


def _bench(rep: Report) -> None:
    bench = rep.root / "bench"
    results = bench / "results.jsonl"
    if not results.is_file():
        return
    blocks: list = [("img", p, p.stem.replace("_", " ")) for p in sorted(bench.glob("*.png"))]
    rows, stab = [], []
    for r in latest_results(results):
        m = r.get("metrics") or {}
        key = f"{r.get('scene')}/{r.get('setting')}"
        f = lambda v, k: "-" if v is None else rep.fact(v, results, f"{key}.{k}")  # noqa: E731
        if r.get("group") == "stability":
            did = r.get("crashed") or "; ".join(r.get("fallbacks") or []) or "completed"
            stab.append([r["setting"], did, f(m.get("psnr"), "metrics.psnr")])
        else:
            rows.append([r["setting"], r.get("group", ""), f(r.get("preprocess_s"), "preprocess_s"),
                         f(r.get("render_ms"), "render_ms"), f(m.get("psnr"), "metrics.psnr"),
                         f(m.get("ssim"), "metrics.ssim"), f(m.get("flip"), "metrics.flip"),
                         f(m.get("psnr_mask"), "metrics.psnr_mask"),
                         f(r.get("mb_per_view"), "mb_per_view")])
    if rows:
        blocks.append(("table", ["setting", "group", "preprocess s", "render ms", "PSNR", "SSIM",
                                 "FLIP", "PSNR in reflectors", "MB/view"], rows))
    if stab:
        blocks.append(("table", ["degradation", "what the pipeline did", "PSNR"], stab))
    rep.add("Benchmark (ibr bench)", blocks)


def scene_frame_line(frame: dict) -> str:
    """One sentence on the scene frame of global/poses.json (report and `ibr status`)."""
    units = frame.get("units")
    how = (frame.get("alignment") or {}).get("method", "?")
    if units == "normalised":
        what = (f"normalised: no metric scale in the capture, so the input was scaled by "
                f"{frame['scale']:.4g} to a median scene depth of {frame.get('median_scene_depth', 0):.3g} "
                "(lengths in the settings are relative to a room seen from that distance)")
    else:
        what = f"metres (x{frame['scale']:.4g} from the input; {how})"
    c = frame.get("counts", {})
    held = f", {c['heldout']} held out" if c.get("heldout") else ""
    return f"Scene frame: {what}. Poses from {frame.get('pose_source', '?')}{held}."


def input_line(scene: dict) -> str:
    """One sentence on how the input was read (scene.json; report and `ibr status`)."""
    views = scene.get("views", [])
    posed = sum(v.get("camera") is not None for v in views)
    prepared = sum(str(v.get("image", "")).startswith("ingest/") for v in views)
    return (f"Input: {scene.get('source', '?')} layout, {len(views)} images ({posed} with cameras), "
            f"colour {scene.get('image_encoding', 'linear')}"
            + (f", {prepared} prepared into ingest/ (undistorted, upright or from a video)"
               if prepared else "") + ".")


def build(ws_root: Path) -> Report:
    ws_root = Path(ws_root)
    if not (ws_root / "ibr.toml").is_file():
        raise InputError(f"{ws_root}: not a workspace (no ibr.toml)")
    rep = Report(ws_root)
    scene = _read_json(ws_root / "scene.json") or {}
    views = scene.get("views", [])
    rep.add("Scene", [("p", f"Workspace `{ws_root}`; {len(views)} input views, "
                            f"{len(scene.get('reflectors', []))} user-given reflector(s)."),
                      ("p", input_line(scene))])
    frame = _read_json(ws_root / L.POSES_REPORT)
    if isinstance(frame, dict) and "units" in frame:
        src = ws_root / L.POSES_REPORT
        rep.add("Scene frame (poses)", [
            ("p", scene_frame_line(frame)),
            ("table", ["quantity", "value"],
             [["scale (scene units per input unit)", rep.fact(frame["scale"], src, "scale")]]
             + ([["median scene depth", rep.fact(frame["median_scene_depth"], src,
                                                "median_scene_depth")]]
                if frame.get("median_scene_depth") is not None else [])
             + [[f"{k} images", rep.fact(v, src, f"counts.{k}")] for k, v in
                frame.get("counts", {}).items()])])
    _timings(rep)
    _json_table(rep, ws_root / L.POSES_REPORT, "Poses (poses)",
                skip=("config", "transform", "depth_ranges", "gt_to_scene.R"))
    _json_table(rep, ws_root / "global" / "report.json", "Global mesh (global_mesh)")
    _per_view(rep, L.DEPTH_REPORT, "Per-view depth refinement (view_depth)")
    _per_view(rep, L.MESH_REPORT, "Per-view meshes (view_mesh)")
    _per_view(rep, L.LAYERS, "Reflection layers (reflection)")
    _json_table(rep, ws_root / "eval" / "metrics.json", "Held-out evaluation (evaluate)")
    _json_table(rep, ws_root / "nn" / "train.json", "DSRNet training (supersample)")
    _media(rep)
    _bench(rep)
    return rep


# --- writers -------------------------------------------------------------------------------------
def _cell(c) -> str:
    return c.text() if isinstance(c, Fact) else str(c)


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}
th{background:#f2f2f2}td.n{text-align:right;font-variant-numeric:tabular-nums}
figure{display:inline-block;margin:.5em;vertical-align:top}figure img,video{max-width:100%}
figcaption{font-size:.85em;color:#555}h2{border-bottom:1px solid #ddd;margin-top:1.6em}"""


def to_html(rep: Report) -> str:
    out = ["<!doctype html><html><head><meta charset='utf-8'><title>ibr report</title>",
           f"<style>{CSS}</style></head><body><h1>ibr_pipeline report</h1>",
           f"<p>Generated {html.escape(time.strftime('%Y-%m-%d %H:%M'))}. Every number below is read "
           f"from a file the pipeline wrote; <code>facts.json</code> lists each one with its source."
           f"</p>"]
    for title, blocks in rep.sections:
        out.append(f"<h2>{html.escape(title)}</h2>")
        for b in blocks:
            if b[0] == "p":
                out.append("<pre>" + html.escape(b[1]) + "</pre>" if "\n" in b[1]
                           else f"<p>{html.escape(b[1])}</p>")
            elif b[0] == "table":
                out.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in b[1])
                           + "</tr>")
                for row in b[2]:
                    out.append("<tr>" + "".join(
                        f"<td class='n'>{_cell(c)}</td>" if isinstance(c, Fact)
                        else f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>")
                out.append("</table>")
            elif b[0] == "img":
                out.append(f"<figure><img src='{_data_uri(b[1], 'image/png')}' "
                           f"alt='{html.escape(b[2])}'><figcaption>{html.escape(b[2])}"
                           f"</figcaption></figure>")
            elif b[0] == "video":
                out.append(f"<figure><video controls loop muted autoplay src='"
                           f"{_data_uri(b[1], 'video/mp4')}'></video><figcaption>"
                           f"{html.escape(b[2])}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)


def to_markdown(rep: Report, img_dir: Path) -> str:
    out = ["# ibr_pipeline report", "",
           "Every number is read from a file the pipeline wrote; `facts.json` lists each source.", ""]
    for title, blocks in rep.sections:
        out += [f"## {title}", ""]
        for b in blocks:
            if b[0] == "p":
                out += [b[1], ""]
            elif b[0] == "table":
                out.append("| " + " | ".join(b[1]) + " |")
                out.append("|" + "---|" * len(b[1]))
                out += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in b[2]]
                out.append("")
            elif b[0] in ("img", "video"):
                rel = b[1].relative_to(rep.root).as_posix().replace("/", "__")
                shutil.copyfile(b[1], img_dir / rel)
                link = f"{img_dir.name}/{rel}"
                out += [f"![{b[2]}]({link})" if b[0] == "img" else f"[{b[2]}]({link})", ""]
    return "\n".join(out)


def write_report(ws_root: Path, out_dir: Path | None = None) -> Path:
    """Write index.html, README.md (+ img/) and facts.json; returns the HTML path."""
    from .workspace import atomic_path
    ws_root = Path(ws_root)
    rep = build(ws_root)
    out_dir = Path(out_dir) if out_dir else ws_root / "report"
    img_dir = out_dir / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    md = to_markdown(rep, img_dir)
    for name, text in (("index.html", to_html(rep)), ("README.md", md),
                       ("facts.json", json.dumps([f.__dict__ for f in rep.facts], indent=1))):
        with atomic_path(out_dir / name) as tmp:
            tmp.write_text(text)
    return out_dir / "index.html"
