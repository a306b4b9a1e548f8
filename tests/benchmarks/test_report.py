"""`ibr report`: self-contained HTML whose every number traces to a recorded file."""
import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from benchmarks import charts
from ibr_pipeline import report
from ibr_pipeline.cli import main


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
    bench = ws / "bench"
    bench.mkdir()
    rows = [{"scene": "tiny", "setting": s, "group": g, "render_ms": ms, "preprocess_s": pre,
             "mb_per_view": mb, "metrics": {"psnr": q}}
            for s, g, ms, pre, mb, q in [("default", "grid", 30.0, 60.0, 0.5, 28.0),
                                         ("fast", "grid", 10.0, 20.0, 0.2, 25.0),
                                         ("slow_bad", "grid", 50.0, 90.0, 0.9, 24.0),
                                         ("single_layer", "baseline", 25.0, 40.0, 0.4, 26.0)]]
    (bench / "results.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    charts.draw_all(bench / "results.jsonl", bench)
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
                d = d[k]
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


@pytest.mark.skipif(shutil.which("chromium-headless-shell") is None,
                    reason="chromium-headless-shell not installed (make install installs it)")
def test_report_renders_in_headless_chromium(ws, tmp_path):
    from PIL import Image
    html_path = report.write_report(ws)
    shot = tmp_path / "shot.png"
    subprocess.run(["chromium-headless-shell", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={shot}", "--window-size=1200,4000", html_path.as_uri()],
                   check=True, capture_output=True, timeout=120)
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.shape[0] >= 4000 * 0.9
    # matplotlib's default blue (C0 = #1f77b4) of the chart markers is on screen: charts are visible
    blue = (abs(img[..., 0] - 0x1F) < 30) & (abs(img[..., 1] - 0x77) < 30) & (abs(img[..., 2] - 0xB4) < 30)
    assert blue.sum() > 50


def test_report_of_a_non_workspace_is_a_clear_error(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert "not a workspace" in capsys.readouterr().err
