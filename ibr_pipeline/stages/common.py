"""Helpers shared by stage modules: the planned-stage placeholder and the registered scene."""
from __future__ import annotations

from dataclasses import dataclass

from ..config import StageConfig
from ..runner import Stage


@dataclass(frozen=True)
class NotBuiltConfig(StageConfig):
    """Placeholder for a stage that does not exist yet: it has no settings."""


def planned(name: str, help: str, todo: str) -> Stage:
    """A row of the stage table for a stage that is not built yet."""
    return Stage(name=name, help=help, config=NotBuiltConfig, version="0", run=None, todo=todo)


REGISTERED_CAMERAS = "global/cameras.json"


def registered_cameras(ws) -> dict:
    """{view name: Camera} of the views `global_mesh` registered (the poses every later stage uses).

    Raises InputError when `global_mesh` has not run yet."""
    from ..errors import InputError
    from ..scene import cameras_from_json
    p = ws.path(REGISTERED_CAMERAS)
    if not p.is_file():
        raise InputError(f"{p}: no registered cameras yet (run `ibr global_mesh` first)")
    return cameras_from_json(p)


def registered_views(ctx) -> list[str]:
    """Stage.views for every stage after global_mesh: registered views, in scene order."""
    cams = registered_cameras(ctx.ws)
    return [n for n in ctx.scene.names if n in cams]
