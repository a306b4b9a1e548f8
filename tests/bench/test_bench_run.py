"""`ibr bench` end to end on the tiny scene (slow: it runs every stage)."""
import json

import pytest

from ibr_pipeline.cli import main


@pytest.mark.slow
def test_bench_records_every_figure_and_draws_charts(tmp_path):
    out = tmp_path / "bench"
    assert main(["bench", "tiny", "--out", str(out), "--only", "default", "--only", "blend_2"]) == 0
    rows = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert [r["setting"] for r in rows] == ["default", "blend_2"]
    for r in rows:
        assert "crashed" not in r
        assert r["stage_results"]["evaluate"] == "ran"
        m = r["metrics"]
        assert 10 < m["psnr"] < 60 and 0 < m["ssim"] <= 1 and 0 <= m["flip"] <= 1
        assert r["render_ms"] > 0 and r["preprocess_s"] > 0 and r["mb_per_view"] > 0
        assert r["machine"]["cpu_count"] >= 1
    # blend_2 reused the default workspace: only render_views and evaluate reran
    assert rows[1]["stage_results"]["view_depth"] == "up to date"
    for name in ("quality_vs_render_ms.png", "quality_vs_preprocess_s.png", "quality_vs_model_mb.png",
                 "settings.md"):
        assert (out / name).stat().st_size > 1000 or name.endswith(".md")
