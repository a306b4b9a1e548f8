"""`ibr warp`: not built yet (issue #9). The issue replaces this module."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("warp", help="warp an RGBZ ray tree to a new camera (Lochmann et al. 2014) [not built yet]")
    p.add_argument("rest", nargs="*", help="arguments (not built yet)")
    p.set_defaults(func=_not_built)


def _not_built(args) -> int:
    print("ibr: error: `ibr warp` is not built yet (issue #9)", file=sys.stderr)
    return 2
