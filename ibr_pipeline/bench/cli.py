"""`ibr bench` and `ibr report`: not built yet (issue #10). The issue replaces this module."""
from __future__ import annotations

import sys


def register(sub) -> None:
    for cmd, hlp in (("bench", "speed/accuracy benchmark over a grid of settings"),
                     ("report", "HTML + Markdown report of a workspace")):
        p = sub.add_parser(cmd, help=f"{hlp} [not built yet]")
        p.add_argument("rest", nargs="*", help="arguments (not built yet)")
        p.set_defaults(func=_not_built)


def _not_built(args) -> int:
    print(f"ibr: error: `ibr {args.command}` is not built yet (issue #10)", file=sys.stderr)
    return 2
