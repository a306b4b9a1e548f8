"""Stage `reflection`: two-layer reflection decomposition. Not built yet (issue #6, Xu et al. §4.3)."""
from __future__ import annotations

from .common import planned

STAGE = planned('reflection', 'two-layer reflection decomposition', 'issue #6, Xu et al. §4.3')
