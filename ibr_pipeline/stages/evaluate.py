"""Stage `evaluate`: held-out metrics, charts and videos. Not built yet (issues #7 and #10)."""
from __future__ import annotations

from .common import planned

STAGE = planned('evaluate', 'held-out metrics, charts and videos', 'issues #7 and #10')
