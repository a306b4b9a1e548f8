"""Stage `supersample`: DSRNet supersampling. Not built yet (issue #8, Xu et al. §5.2)."""
from __future__ import annotations

from .common import planned

STAGE = planned('supersample', 'DSRNet supersampling', 'issue #8, Xu et al. §5.2')
