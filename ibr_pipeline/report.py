"""`ibr report WS`: one self-contained HTML page and its Markdown twin, from recorded measurements.

The report only *formats* numbers that stages and benchmarks wrote to disk: every value shown is a
`Fact` carrying the file and key it came from, and `facts.json` next to the report lists them, so a
reader (and the test) can trace each figure to its measurement. Nothing is recomputed here.

Sections (report_sections.py; each left out when its files do not exist), in reading order:
  Scene                  scene.json, global/poses.json (input, scene frame, scale)
  Held-out accuracy      eval/metrics.json summary per method, renders/test*/timings.json ms/frame
  Side by side           eval/side_by_side/*.png, labelled ours | ground truth | single layer | error
  Reflections            views/*/layers.json (kept / discarded per reflector), I0, I1, beta
                         thumbnails, reflection/planes.json candidates, eval/reflection_energy.png
  Cameras and geometry   a top-down plan of global/cameras.json, the held-out and tour cameras over
                         global/mesh.ply
  Fly-through            eval/fly.mp4 (the tour render set)
  DSRNet                 nn/train.json, nn/loss.png (loss and validation curves)
  Time per stage         .ibr/state/<stage>[/<view>].json, .ibr/runs.jsonl
  Speed                  this run's renderers as ms against PSNR, bench/viewer.json (`ibr bench
                         viewer`), the charts and results.jsonl of `ibr bench` folders (--bench)
  Appendix               every recorded key of the stage reports, in a collapsed <details>
Pictures the report draws itself (report_figures.py) land in the report's img/.

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
    """Sections of (title, blocks); a block is ('p', text) | ('h', text) | ('table', header, rows)
    | ('img', path, caption) | ('sbs', path, column labels, caption): one image of equal panels |
    ('row', [(path, label)], caption) | ('video', path, caption) | ('details', summary, blocks).
    Table cells are str or Fact. fig_dir: where the report's own figures go."""

    def __init__(self, ws_root: Path, fig_dir: Path, bench_dirs: list[Path]):
        self.root = ws_root
        self.fig_dir = Path(fig_dir)
        self.bench_dirs = [Path(b) for b in bench_dirs]
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


def reflectors_line(planes: dict | None, found: dict | None) -> str | None:
    """One sentence on the scene's reflectors (`ibr status`): reflection/planes.json's when the
    `reflectors` stage ran, else what global_mesh found in the depth; None when neither exists."""
    if planes is not None:
        refl = planes.get("reflectors", [])
        by = {}
        for r in refl:
            by.setdefault(r.get("source", "?"), []).append(r["name"])
        dropped = sum(not c.get("kept") for c in planes.get("candidates", []))
        names = {"user": "given", "depth": "found in the depth", "detected": "detected on G"}
        parts = [f"{len(v)} {names.get(k, k)} ({', '.join(v)})" for k, v in by.items()]
        return (f"Reflectors: {'; '.join(parts) if parts else 'none'}; {dropped} candidate(s) "
                "dropped (reflection/planes.json says why).")
    if found is not None:
        kept = [r["name"] for r in found.get("reflectors", [])]
        return (f"Reflectors found in the depth by global_mesh: {', '.join(kept) or 'none'} of "
                f"{len(found.get('candidates', []))} candidate(s) (global/found_reflectors.json).")
    return None


def input_line(scene: dict) -> str:
    """One sentence on how the input was read (scene.json; report and `ibr status`)."""
    views = scene.get("views", [])
    posed = sum(v.get("camera") is not None for v in views)
    prepared = sum(str(v.get("image", "")).startswith("ingest/") for v in views)
    return (f"Input: {scene.get('source', '?')} layout, {len(views)} images ({posed} with cameras), "
            f"colour {scene.get('image_encoding', 'linear')}"
            + (f", {prepared} prepared into ingest/ (undistorted, upright or from a video)"
               if prepared else "") + ".")


def build(ws_root: Path, fig_dir: Path, bench_dirs: list[Path] | None = None) -> Report:
    """The report of a workspace; figures it draws land in fig_dir."""
    from . import report_sections as S
    ws_root = Path(ws_root)
    if not (ws_root / "ibr.toml").is_file():
        raise InputError(f"{ws_root}: not a workspace (no ibr.toml)")
    for b in bench_dirs or []:
        if not (Path(b) / "results.jsonl").is_file():
            raise InputError(f"{b}: no results.jsonl of `ibr bench` here (make bench writes "
                             "out/bench)")
    rep = Report(ws_root, fig_dir, bench_dirs if bench_dirs is not None else [ws_root / "bench"])
    scene = S.read_json(ws_root / "scene.json") or {}
    views = scene.get("views", [])
    blocks = [("p", f"Workspace `{ws_root}`; {len(views)} input views, "
                    f"{len(scene.get('reflectors', []))} user-given reflector(s)."),
              ("p", input_line(scene))]
    line = reflectors_line(S.read_json(ws_root / L.PLANES), S.read_json(ws_root / L.FOUND_REFLECTORS))
    if line:
        blocks.append(("p", line))
    frame = S.read_json(ws_root / L.POSES_REPORT)
    if isinstance(frame, dict) and "units" in frame:
        src = ws_root / L.POSES_REPORT
        blocks += [("p", scene_frame_line(frame)),
                   ("table", ["quantity", "value"],
                    [["scale (scene units per input unit)", rep.fact(frame["scale"], src, "scale")]]
                    + ([["median scene depth", rep.fact(frame["median_scene_depth"], src,
                                                       "median_scene_depth")]]
                       if frame.get("median_scene_depth") is not None else [])
                    + [[k if k == "images" else f"{k} images", rep.fact(v, src, f"counts.{k}")]
                       for k, v in frame.get("counts", {}).items()])]
    rep.add("Scene", blocks)
    for section in (S.summary, S.side_by_sides, S.reflections, S.plan, S.video, S.dsrnet,
                    S.stage_timings, S.speed, S.appendix):
        section(rep)
    return rep


# --- writers -------------------------------------------------------------------------------------
def _cell(c) -> str:
    return c.text() if isinstance(c, Fact) else str(c)


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:2px 8px;text-align:left}
th{background:#f2f2f2}td.n{text-align:right;font-variant-numeric:tabular-nums}
figure{display:inline-block;margin:.5em;vertical-align:top;max-width:100%}figure img,video{max-width:100%}
figcaption{font-size:.85em;color:#555}h2{border-bottom:1px solid #ddd;margin-top:1.6em}
.sbs{display:block}.labels{display:grid;font-size:.85em;font-weight:600;text-align:center}
.row{display:grid;grid-template-columns:repeat(4,1fr);gap:.4em}.row figure{margin:0}
.row img{width:100%}video{width:640px}
details{margin:1em 0}summary{cursor:pointer;font-weight:600}code{background:#f4f4f4;padding:0 3px}"""


def _inline(text: str) -> str:
    """Escaped HTML of a paragraph, its `code` spans as <code> (Markdown keeps the backticks)."""
    parts = html.escape(text).split("`")
    if len(parts) % 2 == 0:  # an unpaired backtick stays text
        parts[-2:] = ["`".join(parts[-2:])]
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def _img(path: Path, alt: str) -> str:
    return f"<img src='{_data_uri(path, 'image/png')}' alt='{html.escape(alt)}'>"


def _html_blocks(blocks: list, out: list) -> None:
    for b in blocks:
        kind = b[0]
        if kind == "p":
            out.append("<pre>" + html.escape(b[1]) + "</pre>" if "\n" in b[1]
                       else f"<p>{_inline(b[1])}</p>")
        elif kind == "h":
            out.append(f"<h3>{_inline(b[1])}</h3>")
        elif kind == "table":
            out.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in b[1]) + "</tr>")
            for row in b[2]:
                out.append("<tr>" + "".join(
                    f"<td class='n'>{_cell(c)}</td>" if isinstance(c, Fact)
                    else f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>")
            out.append("</table>")
        elif kind == "img":
            out.append(f"<figure>{_img(b[1], b[2])}<figcaption>{_inline(b[2])}</figcaption></figure>")
        elif kind == "sbs":  # one image of len(labels) equal panels, each labelled above
            labels = "".join(f"<span>{html.escape(x)}</span>" for x in b[2])
            out.append(f"<figure class='sbs'><div class='labels' style='grid-template-columns:"
                       f"repeat({len(b[2])},1fr)'>{labels}</div>{_img(b[1], b[3])}"
                       f"<figcaption>{_inline(b[3])}</figcaption></figure>")
        elif kind == "row":
            cells = "".join(f"<figure>{_img(p, label)}<figcaption>{html.escape(label)}</figcaption>"
                            f"</figure>" for p, label in b[1])
            out.append(f"<figure><div class='row'>{cells}</div><figcaption>{_inline(b[2])}"
                       f"</figcaption></figure>")
        elif kind == "video":
            out.append(f"<figure><video controls loop muted autoplay src='"
                       f"{_data_uri(b[1], 'video/mp4')}'></video><figcaption>"
                       f"{_inline(b[2])}</figcaption></figure>")
        elif kind == "details":
            out.append(f"<details><summary>{html.escape(b[1])}</summary>")
            _html_blocks(b[2], out)
            out.append("</details>")


def to_html(rep: Report) -> str:
    out = ["<!doctype html><html><head><meta charset='utf-8'><title>ibr report</title>",
           f"<style>{CSS}</style></head><body><h1>ibr_pipeline report</h1>",
           f"<p>Generated {html.escape(time.strftime('%Y-%m-%d %H:%M'))}. Every number below is read "
           f"from a file the pipeline wrote; <code>facts.json</code> lists each one with its source."
           f"</p>"]
    for title, blocks in rep.sections:
        out.append(f"<h2>{html.escape(title)}</h2>")
        _html_blocks(blocks, out)
    out.append("</body></html>")
    return "\n".join(out)


def _md_file(rep: Report, path: Path, img_dir: Path) -> str:
    """A Markdown link target for path: figures drawn into img_dir as they are, workspace files
    copied there."""
    path = Path(path)
    if path.parent.resolve() != img_dir.resolve():
        rel = path.relative_to(rep.root).as_posix().replace("/", "__")
        shutil.copyfile(path, img_dir / rel)
        path = img_dir / rel
    return f"{img_dir.name}/{path.name}"


def _md_blocks(rep: Report, blocks: list, img_dir: Path, out: list) -> None:
    for b in blocks:
        kind = b[0]
        if kind == "p":
            out += [b[1], ""]
        elif kind == "h":
            out += [f"### {b[1]}", ""]
        elif kind == "table":
            out.append("| " + " | ".join(b[1]) + " |")
            out.append("|" + "---|" * len(b[1]))
            out += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in b[2]]
            out.append("")
        elif kind == "img":
            out += [f"![{b[2]}]({_md_file(rep, b[1], img_dir)})", ""]
        elif kind == "sbs":
            out += [f"![{b[3]}]({_md_file(rep, b[1], img_dir)})", "",
                    f"{' | '.join(b[2])}: {b[3]}", ""]
        elif kind == "row":
            out += [" ".join(f"![{label}]({_md_file(rep, p, img_dir)})" for p, label in b[1]), "",
                    f"{' | '.join(label for _, label in b[1])}: {b[2]}", ""]
        elif kind == "video":
            out += [f"[{b[2]}]({_md_file(rep, b[1], img_dir)})", ""]
        elif kind == "details":
            out += [f"<details><summary>{b[1]}</summary>", ""]
            _md_blocks(rep, b[2], img_dir, out)
            out += ["</details>", ""]


def to_markdown(rep: Report, img_dir: Path) -> str:
    out = ["# ibr_pipeline report", "",
           "Every number is read from a file the pipeline wrote; `facts.json` lists each source.", ""]
    for title, blocks in rep.sections:
        out += [f"## {title}", ""]
        _md_blocks(rep, blocks, img_dir, out)
    return "\n".join(out)


def write_report(ws_root: Path, out_dir: Path | None = None,
                 bench_dirs: list[Path] | None = None) -> Path:
    """Write index.html, README.md (+ img/) and facts.json; returns the HTML path."""
    from .workspace import atomic_path
    ws_root = Path(ws_root)
    out_dir = Path(out_dir) if out_dir else ws_root / "report"
    img_dir = out_dir / "img"
    rep = build(ws_root, img_dir, bench_dirs)
    img_dir.mkdir(parents=True, exist_ok=True)
    md = to_markdown(rep, img_dir)
    for name, text in (("index.html", to_html(rep)), ("README.md", md),
                       ("facts.json", json.dumps([f.__dict__ for f in rep.facts], indent=1))):
        with atomic_path(out_dir / name) as tmp:
            tmp.write_text(text)
    return out_dir / "index.html"
