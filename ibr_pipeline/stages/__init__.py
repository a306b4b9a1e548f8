"""The stage table: every stage, once, in order. No import-time registration.

Stage modules keep their config dataclass at the top and import heavy libraries (open3d, torch,
pycolmap, moderngl) inside their functions, so importing this table stays fast (`ibr --help`).
A stage whose `run` is None is planned but not built yet; `ibr status` and `ibr run` say so.
Bump a stage's `version` whenever a change alters what it writes: every view reruns.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..config import StageConfig
from ..runner import Stage
from . import ingest


@dataclass(frozen=True)
class NotBuiltConfig(StageConfig):
    """Placeholder for a stage that does not exist yet: it has no settings."""


def _planned(name: str, help: str, todo: str) -> Stage:
    return Stage(name=name, help=help, config=NotBuiltConfig, version="0", run=None, todo=todo)


STAGES: tuple[Stage, ...] = (
    Stage(name="ingest", help="read the input folder, check every file, write scene.json",
          config=ingest.IngestConfig, version="1", run=ingest.run, needs_scene=False,
          inputs=ingest.inputs, outputs=("scene.json",)),
    _planned("global_mesh", "camera poses (COLMAP) and a global mesh (RGB-D fusion / CPU MVS)",
             "issue #4, Xu et al. §4.1"),
    _planned("view_depth", "depth edges and geodesic depth refinement per view",
             "issue #5, Xu et al. §4.2.1-4.2.2"),
    _planned("view_mesh", "quadric-simplified per-view meshes", "issue #5, Xu et al. §4.2.3"),
    _planned("reflection", "two-layer reflection decomposition", "issue #6, Xu et al. §4.3"),
    _planned("render_views", "view selection and blending into novel views",
             "issue #7, Xu et al. §5.1"),
    _planned("supersample", "DSRNet supersampling", "issue #8, Xu et al. §5.2"),
    _planned("evaluate", "held-out metrics, charts and videos", "issues #7 and #10"),
)


def stage_by_name(name: str) -> Stage:
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(name)
