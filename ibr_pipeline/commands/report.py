"""`ibr report WS`: the workspace's HTML report and its Markdown twin (ibr_pipeline/report.py)."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("report", help="write a self-contained HTML report (+ Markdown twin) of a "
                       "workspace: timings, stage reports, metrics, charts, side-by-sides, video")
    p.add_argument("workspace", type=Path, help="workspace folder")
    p.add_argument("--out", type=Path, help="output folder (default WS/report)")
    p.add_argument("--bench", type=Path, action="append", metavar="DIR",
                   help="an `ibr bench` output folder whose charts and results to include "
                        "(repeatable; default WS/bench)")
    p.set_defaults(func=report_main)


def report_main(args: argparse.Namespace) -> int:
    import logging

    from ..report import write_report
    path = write_report(args.workspace, args.out, args.bench)
    logging.getLogger("ibr_pipeline").info("report: %s (open it in a browser; Markdown twin: %s)",
                                           path, path.with_name("README.md"))
    return 0
