"""`ibr bench real`'s coverage figures read from the per-view depth reports."""
import json

from benchmarks.real import _coverage


def test_coverage_averages_the_views_reports(tmp_path):
    (tmp_path / "global").mkdir()
    (tmp_path / "global" / "report.json").write_text(json.dumps({"mvs_valid_fraction": 0.6}))
    for name, front, empty, valid in (("a.png", 120, 0.3, 1.0), ("b.png", 0, 0.1, 0.9)):
        (tmp_path / "views" / name).mkdir(parents=True)
        (tmp_path / "views" / name / "depth_report.json").write_text(json.dumps(
            {"size": [40, 30], "mvs_in_front": front, "empty_in_g": empty, "valid_fraction": valid}))
    cov = _coverage(tmp_path)
    assert cov["mvs_valid_fraction"] == 0.6
    assert abs(cov["mvs_in_front_fraction"] - (120 / 1200) / 2) < 1e-12
    assert abs(cov["g_empty_fraction"] - 0.2) < 1e-12
    assert abs(cov["depth_valid_fraction"] - 0.95) < 1e-12 and cov["depth_valid_min"] == 0.9
