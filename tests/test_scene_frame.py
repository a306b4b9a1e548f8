"""stages/common.scene_is_input_frame: ground truth in the input's frame (the oracle of evaluate)
is only comparable where the scene frame is the input's own."""
import json
from dataclasses import dataclass

from ibr_pipeline import layout as L
from ibr_pipeline.stages.common import is_identity, scene_is_input_frame
from ibr_pipeline.workspace import Workspace

IDENTITY = {"scale": 1.0, "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0]}


@dataclass
class _Ctx:
    ws: Workspace


def _with_report(tmp_path, report):
    (tmp_path / L.POSES_REPORT).parent.mkdir(parents=True, exist_ok=True)
    ws = Workspace(tmp_path)
    (tmp_path / L.POSES_REPORT).write_text(json.dumps(report))
    return _Ctx(ws)


def test_only_given_unchanged_poses_keep_the_input_frame(tmp_path):
    assert is_identity(None) and is_identity(IDENTITY)
    assert not is_identity({**IDENTITY, "scale": 0.08})
    given = _with_report(tmp_path / "a", {"pose_source": "cameras.json", "transform": IDENTITY})
    normalised = _with_report(tmp_path / "b", {"pose_source": "cameras.json",
                                               "transform": {**IDENTITY, "scale": 1.956}})
    sfm = _with_report(tmp_path / "c", {"pose_source": "sfm", "transform": IDENTITY})
    assert scene_is_input_frame(given)
    assert not scene_is_input_frame(normalised)   # RGB-only with given poses: rescaled
    assert not scene_is_input_frame(sfm)
