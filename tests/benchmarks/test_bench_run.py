"""`ibr bench pipeline` end to end on the tiny scene (slow: it runs every stage)."""
import json

import pytest

from ibr_pipeline.cli import main


@pytest.mark.slow
def test_bench_records_every_figure_and_draws_charts(tmp_path):
    out = tmp_path / "bench"
    assert main(["bench", "pipeline", "tiny", "--out", str(out), "--only", "default",
                 "--only", "blend_2"]) == 0
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


def test_fewer_views_setting_keeps_the_scene_and_its_test_cameras(tmp_path, monkeypatch):
    """`views_50` subsets the default scene's captures (evenly spaced) instead of generating a new
    scene, so its held-out cameras -- half-way between the full path's captures -- are the same."""
    import ibr_pipeline.pipeline as pipeline
    from benchmarks import grid
    from ibr_pipeline.scene import cameras_from_json

    monkeypatch.setattr(pipeline, "run", lambda *a, **k: [])  # only the input preparation is tested
    by_name = {s.name: s for s in grid.settings("full")}
    # views_25 of 8 views would be 2: the grid keeps at least 4
    assert grid.run_setting(by_name["views_25"], "tiny", 0, (160, 120, 8), tmp_path)["views"] == 4
    row = grid.run_setting(by_name["views_50"], "tiny", 0, (160, 120, 8), tmp_path)
    assert row["views"] == 4
    ws_input = (tmp_path / "ws" / "views_50" / "ibr.toml").read_text()
    src = next((tmp_path / "degraded").glob("views_50*"))
    assert str(src.resolve()) in ws_input
    full = next((tmp_path / "scenes").glob("tiny-*"))
    assert (src / "gt" / "test_cameras.json").read_text() == (full / "gt" / "test_cameras.json").read_text()
    kept, every = cameras_from_json(src / "cameras.json"), cameras_from_json(full / "cameras.json")
    assert len(kept) == 4 and set(kept) < set(every)
    for name, cam in kept.items():
        assert abs(cam.cam_from_world - every[name].cam_from_world).max() == 0
