"""Stage `view_depth`: depth edges and geodesic depth refinement per view. Not built yet (issue #5, Xu et al. §4.2.1-4.2.2)."""
from __future__ import annotations

from .common import planned

STAGE = planned('view_depth', 'depth edges and geodesic depth refinement per view', 'issue #5, Xu et al. §4.2.1-4.2.2')
