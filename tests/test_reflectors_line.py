"""The one-line reflector summary of `ibr status` and the report (report.reflectors_line)."""
from ibr_pipeline.report import reflectors_line


def test_it_names_each_reflector_by_where_it_came_from():
    planes = {"reflectors": [{"name": "tv", "source": "depth"}, {"name": "m", "source": "user"}],
              "candidates": [{"kept": True}, {"kept": False}, {"kept": False}]}
    line = reflectors_line(planes, None)
    assert "1 found in the depth (tv)" in line and "1 given (m)" in line
    assert "2 candidate(s) dropped" in line


def test_before_the_reflectors_stage_it_says_what_global_mesh_found():
    found = {"reflectors": [{"name": "behind_2"}], "candidates": [{}, {}, {}]}
    assert "behind_2 of 3 candidate(s)" in reflectors_line(None, found)
    assert "none of 0" in reflectors_line(None, {"reflectors": [], "candidates": []})
    assert reflectors_line(None, None) is None
