"""Toy stages for runner tests: small, observable, and importable by worker processes.

`listing` (whole-scene) reads input/data/*.txt and writes toy/views.json; `upper` (per-view) writes
views/<v>/out.txt = upper-cased input + suffix, in two chunks with a pause in between (so a kill can
land mid-write), and appends "<view>" to WS/ranlog.txt each time it runs a view.
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ibr_pipeline.config import StageConfig, param
from ibr_pipeline.runner import Stage, StageContext


@dataclass(frozen=True)
class ListingConfig(StageConfig):
    pattern: str = param("*.txt", "which input files are views")


@dataclass(frozen=True)
class UpperConfig(StageConfig):
    suffix: str = param("!", "appended to every output")
    sleep: float = param(0.0, "seconds to pause mid-write", min=0.0)
    fail_on: str = param("", "comma-separated views that raise")
    repeat: int = param(1, "times the text is repeated", min=1, max=1000)


def listing_inputs(ctx: StageContext) -> list[str]:
    data = ctx.ws.path("input/data")
    return sorted(f"input/data/{p.name}" for p in data.glob(ctx.config.pattern))


def listing_run(ctx: StageContext) -> None:
    names = [k.rsplit("/", 1)[1][:-4] for k in listing_inputs(ctx)]
    ctx.ws.write_json("toy/views.json", names)


def upper_views(ctx: StageContext) -> list[str]:
    return json.loads(ctx.ws.path("toy/views.json").read_text())


def upper_run(ctx: StageContext, view: str) -> None:
    cfg = ctx.config
    with open(ctx.ws.path("ranlog.txt"), "a") as f:
        f.write(view + "\n")
    if view in cfg.fail_on.split(","):
        raise ValueError(f"toy failure for {view}")
    text = ctx.ws.path(f"input/data/{view}.txt").read_text().upper() * cfg.repeat + cfg.suffix
    with ctx.ws.atomic_write(ctx.ws.view_file(view, "out.txt"), "w") as f:
        f.write(text[: len(text) // 2])
        f.flush()
        time.sleep(cfg.sleep)
        f.write(text[len(text) // 2:] + "\nEND\n")


def missing_output_run(ctx: StageContext) -> None:
    """A buggy stage: declares an output it never writes."""


def make_toy_workspace(root: Path, n_views: int = 6) -> Path:
    """An input folder with n text 'views' and a workspace pointing at it."""
    data = root / "input" / "data"
    data.mkdir(parents=True)
    for i in range(n_views):
        (data / f"v{i:02d}.txt").write_text(f"view number {i}\n")
    ws = root / "ws"
    ws.mkdir()
    (ws / "ibr.toml").write_text(f'[input]\npath = "{(root / "input").as_posix()}"\n')
    return ws


STAGES = (
    Stage(name="listing", help="list views", config=ListingConfig, version="1", run=listing_run,
          needs_scene=False, inputs=listing_inputs, outputs=("toy/views.json",)),
    Stage(name="upper", help="upper-case each view", config=UpperConfig, version="1", run=upper_run,
          per_view=True, needs_scene=False, inputs=("toy/views.json",),
          view_inputs=("input/data/{view}.txt",), view_outputs=("{view_dir}/out.txt",),
          views=upper_views),
)


def main(ws_root: str, sleep: str) -> None:
    """Run the toy pipeline in this process (used by the kill-and-resume test)."""
    from ibr_pipeline.pipeline import load_configs, run
    from ibr_pipeline.workspace import Workspace

    ws = Workspace(ws_root)
    configs = load_configs(STAGES, ws, {"upper": {"sleep": sleep}})
    run(STAGES, ws, configs, STAGES[:2], progress=False)
    os.write(1, b"done\n")


if __name__ == "__main__":
    main(*sys.argv[1:3])
