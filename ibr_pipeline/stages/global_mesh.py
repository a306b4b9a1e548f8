"""Stage `global_mesh`: camera poses (COLMAP) and a global mesh (RGB-D fusion / CPU MVS). Not built yet (issue #4, Xu et al. §4.1)."""
from __future__ import annotations

from .common import planned

STAGE = planned('global_mesh', 'camera poses (COLMAP) and a global mesh (RGB-D fusion / CPU MVS)', 'issue #4, Xu et al. §4.1')
