"""The stage table: every stage, once, in order. No import-time registration.

Each stage lives in its own module `stages/<name>.py`, which defines `STAGE` (a runner.Stage) and
keeps its config dataclass at the top. Heavy libraries (open3d, torch, pycolmap, moderngl) are
imported inside the stage's functions, so importing this table stays fast (`ibr --help`).
Bump a stage's `version` whenever a change alters what it writes: every view reruns.
The files each stage reads and writes are listed in docs/PIPELINE.md.
"""
from __future__ import annotations

from ..runner import Stage
from . import (evaluate, global_mesh, ingest, poses, reflection, reflectors, render_views,
               supersample, view_depth, view_mesh)

STAGES: tuple[Stage, ...] = (
    ingest.STAGE,
    poses.STAGE,
    global_mesh.STAGE,
    view_depth.STAGE,
    view_mesh.STAGE,
    reflectors.STAGE,
    reflection.STAGE,
    render_views.STAGE,
    supersample.STAGE,
    evaluate.STAGE,
)


def stage_by_name(name: str) -> Stage:
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(name)
