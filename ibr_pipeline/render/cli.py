"""`ibr render`: not built yet (issue #7). The issue replaces this module."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("render", help="render new views of a workspace [not built yet]")
    p.add_argument("rest", nargs="*", help="arguments (not built yet)")
    p.set_defaults(func=_not_built)


def _not_built(args) -> int:
    print("ibr: error: `ibr render` is not built yet (issue #7)", file=sys.stderr)
    return 2
