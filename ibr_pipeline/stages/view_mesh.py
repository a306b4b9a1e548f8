"""Stage `view_mesh`: quadric-simplified per-view meshes. Not built yet (issue #5, Xu et al. §4.2.3)."""
from __future__ import annotations

from .common import planned

STAGE = planned('view_mesh', 'quadric-simplified per-view meshes', 'issue #5, Xu et al. §4.2.3')
