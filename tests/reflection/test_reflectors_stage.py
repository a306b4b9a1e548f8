"""Stage `reflectors` (Xu et al. §4.3, reflector planes once per scene): detection on the sample
mirror_room without the user's planes finds its three reflectors and nothing else, the same
whatever `--jobs`, with a reason for every candidate; the runner's view of it (its own
fingerprint; `reflection` reads its planes.json)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

DETECT = {"use_user_reflectors": False, "work_scale": 0.5}


def _run(ws, stages=("reflectors", "reflection"), jobs=1, force=False, **over):
    from ibr_pipeline.executors import LocalExecutor
    from ibr_pipeline.pipeline import load_configs, run, select_stages
    from ibr_pipeline.stages import STAGES
    configs = load_configs(STAGES, ws, {"reflectors": over})
    with LocalExecutor(jobs) as ex:
        return run(STAGES, ws, configs, select_stages(STAGES, stages[0], stages[-1]),
                   force=force, executor=ex, progress=False)


@pytest.fixture(scope="module")
def detect_ws(sample_scene, tmp_path_factory):
    """The sample's ground-truth workspace through view_mesh, then `reflectors` with detection
    only (2 workers)."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    ws = write_gt_workspace(sample_scene, tmp_path_factory.mktemp("reflectors") / "ws", "view_mesh",
                            mesh="grid")
    res = _run(ws, ("reflectors",), jobs=2, **DETECT)
    assert [r.result for r in res] == ["ran"], res
    return sample_scene, ws


def _angle_deg(a, b):
    na, nb = np.asarray(a[:3], float), np.asarray(b[:3], float)
    return float(np.degrees(np.arccos(min(1.0, abs(na @ nb) / np.linalg.norm(na) / np.linalg.norm(nb)))))


def test_detects_the_three_reflectors_and_nothing_else(detect_ws):
    from ibr_pipeline.scene import read_reflectors
    scene, ws = detect_ws
    planes = json.loads(ws.path("reflection/planes.json").read_text())
    truth = {t.name: t for t in read_reflectors(scene / "reflectors.json")}
    found = {}
    for r in planes["reflectors"]:
        assert r["source"] == "detected"
        best = min(truth.values(), key=lambda t: _angle_deg(r["plane"], t.plane)
                   + abs(abs(r["plane"][3]) - abs(t.plane[3])))
        sign = np.sign(np.dot(r["plane"][:3], best.plane[:3]))
        assert _angle_deg(r["plane"], best.plane) < 0.5, (r["name"], best.name)
        assert abs(sign * r["plane"][3] - best.plane[3]) < 0.02, (r["name"], best.name)
        found[best.name] = r
    assert set(found) == set(truth) and len(planes["reflectors"]) == len(truth), planes["reflectors"]
    assert found["mirror"]["beta"] == 1.0  # told from the mirror warp (§4.3.3 special case)
    for name in ("tv_screen", "table_top"):  # the Eq. 3 fit's reflectance, near the truth
        assert abs(found[name]["beta"] - truth[name].beta) < 0.12, (name, found[name]["beta"])


def test_every_candidate_says_why(detect_ws):
    _, ws = detect_ws
    planes = json.loads(ws.path("reflection/planes.json").read_text())
    kept = {r["name"] for r in planes["reflectors"]}
    assert len(planes["candidates"]) > len(kept)
    for c in planes["candidates"]:
        assert isinstance(c["kept"], bool) and c["reason"], c
        assert c["kept"] == (c["name"] in kept), c
    for c in planes["candidates"]:
        if c["kept"]:
            assert "Eq. 3 fit" in c["reason"] or "mirror warp" in c["reason"], c
        else:
            assert any(k in c["reason"] for k in ("<=", "needed", "same plane", "no reflection")), c


def test_jobs_do_not_change_the_planes(detect_ws, tmp_path):
    from ibr_pipeline.workspace import Workspace
    _, ws = detect_ws
    one = Workspace(shutil.copytree(ws.root, tmp_path / "one"))
    res = _run(one, ("reflectors",), jobs=1, force=True, **DETECT)
    assert res[0].result == "ran"
    a = json.loads(ws.path("reflection/planes.json").read_text())
    b = json.loads(one.path("reflection/planes.json").read_text())
    assert a == b


def test_runner_fingerprint_and_downstream(tiny_scene, tmp_path):
    """`reflectors` reruns when its config changes, and `reflection` then reruns because its
    input planes.json changed; with nothing changed both are up to date."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    from ibr_pipeline.pipeline import load_configs, select_stages, status
    from ibr_pipeline.stages import STAGES
    w = write_gt_workspace(tiny_scene[0], tmp_path / "w", "view_mesh", mesh="grid")
    assert [r.result for r in _run(w)] == ["ran", "ran"]
    assert [r.result for r in _run(w)] == ["up to date", "up to date"]
    sel = select_stages(STAGES, "reflectors", "reflection")  # gt stages before have no records
    plans = {p.stage.name: p for p in status(STAGES, w, load_configs(STAGES, w, {"reflectors": {
        "use_user_reflectors": False}}), selected=sel)}
    assert plans["reflectors"].state == "will run"
    assert any("use_user_reflectors" in r for r in plans["reflectors"].reasons), plans["reflectors"].reasons
    res = _run(w, use_user_reflectors=False)  # tiny's views are too small to detect anything
    assert [r.result for r in res] == ["ran", "ran"], res
    assert json.loads(w.path("reflection/planes.json").read_text())["reflectors"] == []
    assert not any(json.loads(w.path(w.view_file(v, "layers.json")).read_text())["reflector"]
                   for v in w.scene().names)


def test_detects_glass_by_the_scene_behind_it(tmp_path_factory):
    """glass_room's pane shows the room behind it: its surface warp fails and the mirror warp does
    not explain that, the warp of the geometry behind the plane does (material glass); its TV and
    table top are found by the Eq. 3 fit."""
    from ibr_pipeline.gt_workspace import write_gt_workspace
    from ibr_pipeline.scene import read_reflectors
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    root = tmp_path_factory.mktemp("glass")
    generate(SynthOptions("glass_room", width=320, height=240, views=24, test_views=1,
                          flythrough=2, progress=False), root / "scene")
    ws = write_gt_workspace(root / "scene", root / "ws", "view_mesh", mesh="grid")
    assert [r.result for r in _run(ws, ("reflectors",), jobs=2, **DETECT)] == ["ran"]
    planes = json.loads(ws.path("reflection/planes.json").read_text())
    truth = {t.name: t for t in read_reflectors(root / "scene" / "reflectors.json")}
    glass = truth["glass"]
    found = [r for r in planes["reflectors"] if _angle_deg(r["plane"], glass.plane) < 1.0
             and abs(abs(r["plane"][3]) - abs(glass.plane[3])) < 0.02]
    assert len(found) == 1 and found[0]["material"] == "glass", planes["reflectors"]
    assert "seen through the plane" in found[0]["reason"]
    assert len(planes["reflectors"]) == len(truth), planes["reflectors"]
