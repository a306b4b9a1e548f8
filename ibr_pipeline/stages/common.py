"""What every stage after `global_mesh` shares: the registered views, in scene order."""
from __future__ import annotations

from ..layout import registered_cameras


def registered_views(ctx) -> list[str]:
    """Stage.views for every stage after global_mesh: registered views, in scene order."""
    cams = registered_cameras(ctx.ws)
    return [n for n in ctx.scene.names if n in cams]
