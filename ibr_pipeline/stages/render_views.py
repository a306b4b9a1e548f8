"""Stage `render_views`: view selection and blending into novel views. Not built yet (issue #7, Xu et al. §5.1)."""
from __future__ import annotations

from .common import planned

STAGE = planned('render_views', 'view selection and blending into novel views', 'issue #7, Xu et al. §5.1')
