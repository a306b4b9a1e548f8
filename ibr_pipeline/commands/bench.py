"""`ibr bench NAME [args...]`: run one benchmark of the table in benchmarks/__init__.py.

The benchmarks live outside the package (benchmarks/, beside ibr_pipeline/); this command is the
one place the package reaches them. Only the table is read to build `ibr bench --help`; a
benchmark's module, and whatever it imports, is loaded when that benchmark runs or its --help is
asked, so `ibr --help` stays fast.
"""
from __future__ import annotations

import argparse

from ..errors import InputError


def _table():
    from benchmarks import BENCHMARKS
    return BENCHMARKS


def register(sub) -> None:
    table = _table()
    width = max(len(b.name) for b in table)
    listing = "\n".join(f"  {b.name:<{width}}  {b.help}" for b in table)
    p = sub.add_parser(
        "bench", help="run a benchmark against synthetic ground truth (`ibr bench --help` lists them)",
        description="Run one benchmark against synthetic ground truth; `ibr bench NAME --help`\n"
        "shows its flags. Measured figures are recorded in docs/BENCHMARKS.md.",
        epilog=f"benchmarks:\n{listing}\n\nexample: ibr bench pipeline mirror_room --stability "
        "--out out/bench", formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bench_name", metavar="NAME", help="the benchmark to run (listed below)")
    p.add_argument("bench_args", nargs=argparse.REMAINDER, metavar="...",
                   help="the benchmark's own arguments (see `ibr bench NAME --help`)")
    p.set_defaults(func=bench_main)


def benchmark_parser(bench):
    """(parser, module) of one benchmark, its module imported here: prog `ibr bench NAME`, the
    module's docstring as description, the module's own flags."""
    import importlib
    mod = importlib.import_module(bench.module)
    parser = argparse.ArgumentParser(prog=f"ibr bench {bench.name}", description=mod.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    mod.add_arguments(parser)
    return parser, mod


def bench_main(args: argparse.Namespace) -> int:
    table = _table()
    bench = next((b for b in table if b.name == args.bench_name), None)
    if bench is None:
        raise InputError(f"bench: unknown benchmark {args.bench_name!r} (choose from "
                         f"{', '.join(b.name for b in table)})")
    parser, mod = benchmark_parser(bench)
    return mod.main(parser.parse_args(args.bench_args))
