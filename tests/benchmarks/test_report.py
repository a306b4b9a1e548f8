"""`ibr report`: self-contained HTML whose every number traces to a recorded file."""
import json
import re

import numpy as np
import pytest

from benchmarks import charts
from ibr_pipeline import report, report_sections
from ibr_pipeline.cli import main


def _bench_results(ws):
    bench = ws / "bench"
    bench.mkdir(exist_ok=True)
    rows = [{"scene": "tiny", "setting": s, "group": g, "render_ms": ms, "preprocess_s": pre,
             "mb_per_view": mb, "metrics": {"psnr": q}}
            for s, g, ms, pre, mb, q in [("default", "grid", 30.0, 60.0, 0.5, 28.0),
                                         ("fast", "grid", 10.0, 20.0, 0.2, 25.0),
                                         ("slow_bad", "grid", 50.0, 90.0, 0.9, 24.0),
                                         ("single_layer", "baseline", 25.0, 40.0, 0.4, 26.0)]]
    (bench / "results.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    charts.draw_all(bench / "results.jsonl", bench)


@pytest.fixture
def ws(tmp_path, sample_scene):
    ws = tmp_path / "ws"
    assert main(["run", str(ws), "--input", str(sample_scene), "--until", "ingest",
                 "--no-progress"]) == 0
    # measurements as later stages record them (the report must only format these)
    (ws / "eval").mkdir()
    (ws / "eval" / "metrics.json").write_text(json.dumps(
        {"summary": {"psnr": 27.123456, "ssim": 0.91234, "flip": 0.0876}}))
    v = ws / "views" / "v0"
    v.mkdir(parents=True)
    (v / "mesh_report.json").write_text(json.dumps({"vertices": 1234, "ms": 56.5}))
    _bench_results(ws)
    return ws


@pytest.fixture(scope="module")
def full_ws(tiny_scene, tmp_path_factory):
    """The tiny scene with ground-truth stages through reflection, then the real render_views and
    evaluate (held-out side-by-sides, the tour video), a DSRNet training record and bench results."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    ws = tmp_path_factory.mktemp("report") / "ws"
    write_gt_workspace(tiny_scene[0], ws, "reflection")
    for stage in ("render_views", "evaluate"):
        assert main(["-q", stage, str(ws), "--no-progress"]) == 0
    (ws / "nn").mkdir()
    (ws / "nn" / "train.json").write_text(json.dumps(
        {"steps": 40, "parameters": 1000, "seconds": {"train": 3.25},
         "validation": {"psnr": 24.5, "psnr_bilinear": 23.75}, "val_curve": [[20, 24.0], [40, 24.5]]}))
    _bench_results(ws)
    return ws


def test_pareto_front_is_the_non_dominated_set():
    pts = [(30, 28), (10, 25), (50, 24), (25, 26), (10, 20)]
    front = set(charts.pareto(pts))
    assert front == {0, 1, 3}
    for i in range(len(pts)):  # every other point is dominated by a front point
        if i not in front:
            assert any(pts[j][0] <= pts[i][0] and pts[j][1] >= pts[i][1] for j in front)


def test_every_number_comes_from_a_recorded_file(ws):
    html_path = report.write_report(ws)
    facts = json.loads((html_path.parent / "facts.json").read_text())
    assert facts, "the report shows no measurements"
    for f in facts:
        src = ws / f["source"]
        assert src.exists(), f
        if src.is_file() and src.suffix == ".json" and ":" not in f["key"] and "(" not in f["key"]:
            d = json.loads(src.read_text())
            for k in f["key"].split("."):
                d = d[int(k)] if isinstance(d, list) else d[k]
            assert d == pytest.approx(f["value"])
    texts = {report.fmt(f["value"]) for f in facts}
    md = (html_path.parent / "README.md").read_text()
    for line in md.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            for cell in line.strip("|").split("|"):
                cell = cell.strip()
                if re.fullmatch(r"-?\d+(\.\d+)?(e[-+]?\d+)?", cell):
                    assert cell in texts, f"{cell!r} in the report has no recorded source"
    assert "27.12" in md and "1234" in md  # the recorded metrics and per-view report appear
    html = html_path.read_text()
    assert "src='data:image/png;base64," in html  # charts embedded: opens with no server


def test_the_full_report_shows_what_a_reader_needs(full_ws):
    html_path = report.write_report(full_ws)
    html = html_path.read_text()
    md = (html_path.parent / "README.md").read_text()
    for title in ("Held-out accuracy", "Held-out views, side by side", "Reflections",
                  "Cameras and geometry", "Fly-through", "DSRNet supersampling", "Time per stage",
                  "Speed", "Appendix: every recorded value"):
        assert f"<h2>{title}</h2>" in html and f"## {title}" in md, title
    assert "`" not in html  # Markdown code spans are <code> in the HTML
    assert html.count("<details>") == 1 and "<details open" not in html  # raw keys collapsed
    for label in report_sections.SBS_LABELS:
        assert f"<span>{label}</span>" in html
    img = html_path.parent / "img"
    for name in ("plan.png", "stage_times.png", "speed_accuracy.png"):
        assert (img / name).stat().st_size > 5000, name
    assert list(img.glob("layers_*_beta.png")) and list(img.glob("layers_*_I1.png"))
    # every number still traces to its file, also with list indices (per_view.0.ours.psnr)
    facts = json.loads((html_path.parent / "facts.json").read_text())
    per_view = [f for f in facts if f["key"].startswith("per_view.")]
    assert per_view
    m = json.loads((full_ws / "eval" / "metrics.json").read_text())
    for f in per_view:
        d = m
        for k in f["key"].split("."):
            d = d[int(k)] if isinstance(d, list) else d[k]
        assert d == pytest.approx(f["value"]) and report.fmt(f["value"]) in html


def test_report_renders_in_headless_chromium(full_ws, browser, tmp_path):
    from PIL import Image
    html_path = report.write_report(full_ws)
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    try:
        page.goto(html_path.as_uri())
        page.wait_for_function("document.querySelector('video').readyState >= 1", timeout=60_000)
        got = page.evaluate("""() => ({
            text: document.body.innerText,
            duration: document.querySelector('video').duration,
            broken: [...document.images].filter(i => !(i.complete && i.naturalWidth > 0)).length,
            images: document.images.length,
            appendixShown: document.querySelector('details table').checkVisibility()})""")
        shot = tmp_path / "shot.png"
        page.screenshot(path=str(shot), full_page=True)
    finally:
        page.close()
    assert "`" not in got["text"]
    for label in ("ours", "ground truth", "single layer", "views kept", "I1 reflection layer"):
        assert label in got["text"], label
    assert got["duration"] >= 3.9  # the tour, not a third of a second
    assert got["images"] >= 10 and got["broken"] == 0
    assert not got["appendixShown"]
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)

    def colour(rgb):
        return ((abs(img[..., 0] - rgb[0]) < 25) & (abs(img[..., 1] - rgb[1]) < 25)
                & (abs(img[..., 2] - rgb[2]) < 25)).sum()
    assert colour((0x1F, 0x77, 0xB4)) > 50  # matplotlib C0: training cameras, chart bars
    assert colour((0xFF, 0x7F, 0x0E)) > 50  # C1: the held-out cameras on the plan


def test_report_of_a_non_workspace_is_a_clear_error(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert "not a workspace" in capsys.readouterr().err


def test_a_bench_folder_without_results_is_a_clear_error(ws, tmp_path, capsys):
    before = sorted(p.name for p in ws.iterdir())
    assert main(["report", str(ws), "--bench", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "results.jsonl" in err
    assert sorted(p.name for p in ws.iterdir()) == before  # nothing written
    assert main(["report", str(ws), "--bench", str(ws / "bench")]) == 0


def test_detection_candidates_are_listed_with_their_evidence(ws):
    """A workspace where `reflectors` scored candidates and kept none (a mirror-free capture): the
    report still has a Reflections section listing each candidate, its verdict and reason, and
    its numbers trace to planes.json."""
    (ws / "reflection").mkdir()
    cands = [{"name": "detected_0", "plane": [0, 0, 1, -1], "views": 12, "kept": False,
              "score": {"surface_error": 0.0312, "mirror_ratio": 4.0, "pairs": 24,
                        "fit_beta": 0.0046, "fit_corr": 0.0016},
              "reason": "surface-warp error 0.0312 > 0.02 but no reflection explains it"},
             {"name": "detected_1", "plane": [0, 1, 0, -2], "views": 1, "kept": False,
              "score": {"surface_error": None, "pairs": 0}, "reason": "seen by 1 view(s), 2 needed"}]
    (ws / "reflection" / "planes.json").write_text(json.dumps(
        {"format": "ibr_pipeline.reflectors/1", "reflectors": [], "candidates": cands}))
    import html as H
    page = report.write_report(ws).read_text()
    assert "Reflections" in page and "2 candidate" in page
    for c in cands:
        assert c["name"] in page and H.escape(c["reason"], quote=False) in page
    facts = json.loads((ws / "report" / "facts.json").read_text())
    keys = {f["key"]: f["value"] for f in facts if f["source"] == "reflection/planes.json"}
    assert keys["candidates.0.score.surface_error"] == 0.0312 and keys["candidates.0.views"] == 12


def test_a_glass_reflector_is_named_as_glass(ws):
    """The per-reflector table says what each layer holds: a pane's I0 is the scene behind it."""
    (ws / "reflection").mkdir()
    refl = [{"name": "pane", "plane": [-1, 0, 0, 3.6], "beta": 0.08, "material": "glass",
             "source": "user"},
            {"name": "mirror", "plane": [1, 0, 0, 0], "beta": 1.0, "material": "mirror",
             "source": "user"}]
    (ws / "reflection" / "planes.json").write_text(json.dumps(
        {"format": "ibr_pipeline.reflectors/1", "reflectors": refl, "candidates": []}))
    (ws / "views" / "v0" / "layers.json").write_text(json.dumps(
        {"reflector": "pane", "reflectors": [{"name": "pane", "beta": 0.08, "mirror": False},
                                             {"name": "mirror", "beta": 1.0, "mirror": True}]}))
    page = report.write_report(ws).read_text()
    assert "glass (I0: the scene behind the pane)" in page
    assert "mirror (colour-less I0)" in page
