"""`ibr`: the command-line interface. One subcommand per stage, plus init/run/status/stages/synth.

Exit codes: 0 done; 1 a stage failed (its
error is printed, tracebacks are kept under WS/.ibr/logs/); 2 bad input (one line naming the file or
field; nothing written). Heavy libraries are imported only by the code that runs a stage, so
`ibr --help` returns at once.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from .config import describe_fields, nest
from .errors import InputError, write_error

log = logging.getLogger("ibr_pipeline")

EPILOG = """\
workspaces: a folder for one scene's outputs. `ibr init WS --input DIR` (or `ibr run WS --input
DIR`) creates WS/ibr.toml naming the input folder: a COLMAP workspace (images/ + sparse/0), images/ +
cameras.json, or a bare folder of images, optionally with depth/ (16-bit PNG, mm) and reflectors.json.
configs: each stage reads the table [stage] of WS/ibr.toml; `--set stage.field=value` (ibr run) or
`--field value` (ibr STAGE) overrides it. `ibr stages` lists every field with its default.
exit codes: 0 ok, 1 a stage failed, 2 bad input."""


# Commands beyond the stages (ibr_pipeline/commands/): each module's `register(sub)` adds its
# subparsers with a `func` (args -> exit code) and imports nothing heavy, so `ibr --help` is fast.
COMMAND_MODULES = (
    "ibr_pipeline.commands.synth",    # ibr synth
    "ibr_pipeline.commands.render",   # ibr render
    "ibr_pipeline.commands.warp",     # ibr warp
    "ibr_pipeline.commands.report",   # ibr report
    "ibr_pipeline.commands.export",   # ibr export
    "ibr_pipeline.commands.view",     # ibr view (browser viewer)
    "ibr_pipeline.commands.bench",    # ibr bench NAME (benchmarks/)
)


def _stages():
    from .stages import STAGES
    return STAGES


def _add_exec_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true", help="rerun the selected stages even if up to date")
    p.add_argument("--dry-run", action="store_true", help="say what would run and why; run nothing")
    p.add_argument("--jobs", "-j", type=int, default=1, metavar="N",
                   help="worker processes for per-view stages and for the independent pieces of "
                        "whole-scene ones (MVS views, reflector candidates, the held-out scores); "
                        "default 1: this process")
    p.add_argument("--dask-scheduler", metavar="ADDR",
                   help="run per-view tasks on a Dask cluster, e.g. tcp://10.0.0.5:8786 "
                        "(workers need the workspace at the same path)")
    p.add_argument("--dask-local", type=int, default=0, metavar="N",
                   help="start a local Dask cluster with N worker processes for per-view tasks")
    p.add_argument("--dask-timeout", type=float, default=120.0, metavar="S",
                   help="with a Dask cluster: stop with an error when no worker has been connected "
                        "and no view has finished for S seconds (finished views are kept)")
    p.add_argument("--wait", action="store_true",
                   help="when another run holds the workspace, wait for it instead of stopping")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ibr", description="Image-based rendering of indoor scenes with reflections "
        "(Xu et al. 2021; Lochmann et al. 2014).", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("init", help="create a workspace for an input folder")
    p.add_argument("workspace", type=Path, help="workspace folder to create")
    p.add_argument("--input", type=Path, required=True, help="input folder (images, cameras, depth)")
    p.add_argument("--force", action="store_true", help="overwrite an existing ibr.toml")

    p = sub.add_parser("run", help="run every stage that is not up to date, in order")
    p.add_argument("workspace", type=Path, help="workspace folder")
    p.add_argument("--input", type=Path, help="input folder; creates the workspace if needed")
    p.add_argument("--from", dest="from_stage", metavar="STAGE", help="first stage to run")
    p.add_argument("--until", dest="until_stage", metavar="STAGE", help="last stage to run")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.FIELD=VALUE",
                   help="override a config value (repeatable)")
    _add_exec_args(p)

    p = sub.add_parser("status", help="say for every stage whether it would run, and why")
    p.add_argument("workspace", type=Path, help="workspace folder")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.FIELD=VALUE",
                   help="evaluate as if this config value were set (repeatable)")
    p.add_argument("--json", action="store_true", help="machine-readable output")

    sub.add_parser("stages", help="list the stages and every config field with its default")

    for s in _stages():
        p = sub.add_parser(s.name, help=f"stage: {s.help}", description=f"Stage {s.name}: {s.help}.")
        p.add_argument("workspace", type=Path, help="workspace folder")
        for name, typ, default, hlp in describe_fields(s.config):
            p.add_argument(f"--{name.replace('_', '-')}", dest=f"cfg__{name}", metavar=typ.upper(),
                           help=f"{hlp} (default: {default})".replace("%", "%%"))  # argparse formats %
        _add_exec_args(p)

    import importlib
    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(sub)
    return parser


def _parse_overrides(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        stage, dot, name = key.partition(".")
        if not sep or not dot or not stage or not name:
            raise InputError(f"--set {item!r}: expected STAGE.FIELD=VALUE (STAGE.TABLE.FIELD=VALUE "
                             "for nested options)")
        out.setdefault(stage, {})[name] = value
    return {stage: nest(fields) for stage, fields in out.items()}


def _setup_logging(verbose: bool, quiet: bool) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)

    class Fmt(logging.Formatter):
        def format(self, record):
            msg = super().format(record)
            return msg if record.levelno == logging.INFO else f"{record.levelname.lower()}: {msg}"

    handler.setFormatter(Fmt("%(message)s"))
    root = logging.getLogger("ibr_pipeline")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _init_workspace(ws_path: Path, input_path: Path, force: bool):
    from .workspace import CONFIG_FILE, Workspace
    if not input_path.is_dir():
        raise InputError(f"{input_path}: input folder does not exist")
    cfg = ws_path / CONFIG_FILE
    if cfg.exists() and not force:
        raise InputError(f"{cfg}: already exists (use --force to overwrite)")
    ws_path.mkdir(parents=True, exist_ok=True)
    ws = Workspace(ws_path)
    ws.write_text(CONFIG_FILE, f"# ibr_pipeline workspace\n[input]\npath = "
                  f"{json.dumps(str(input_path.resolve()))}\n")
    log.info("workspace %s created for input %s", ws.root, input_path.resolve())
    return Workspace(ws_path)


def _open_workspace(args, create: bool = True):
    """The workspace of `args`; with --input and no ibr.toml yet it is created, unless `create` is
    False (--dry-run): then a workspace that exists only in memory answers what would run."""
    from .workspace import Workspace
    ws_path: Path = args.workspace
    given = getattr(args, "input", None)
    if given is not None:
        if not (ws_path / "ibr.toml").is_file():
            if create:
                return _init_workspace(ws_path, given, force=False)
            if not given.is_dir():
                raise InputError(f"{given}: input folder does not exist")
            return Workspace(ws_path, must_exist=False, config={"input": {"path": str(given.resolve())}})
        ws = Workspace(ws_path)
        if ws.input_root.resolve() != given.resolve():
            raise InputError(f"{ws.config_path}: workspace already uses input {ws.input_root}, "
                             f"not {given.resolve()} (edit ibr.toml or use another workspace)")
        return ws
    ws = Workspace(ws_path)
    if not ws.input_root.is_dir():
        raise InputError(f"{ws.config_path}: input folder {ws.input_root} does not exist")
    return ws


def _cmd_stages(args) -> int:
    for s in _stages():
        print(f"{s.name}: {s.help}")
        for name, typ, default, hlp in describe_fields(s.config):
            print(f"    {name} ({typ}, default {default!r}): {hlp}")
    return 0


def _cmd_status(args) -> int:
    from .pipeline import load_configs, status, status_table
    stages = _stages()
    ws = _open_workspace(args)
    plans = status(stages, ws, load_configs(stages, ws, _parse_overrides(args.overrides)))
    if args.json:
        print(json.dumps([{"stage": p.stage.name, "state": p.state, "reason": p.summary(),
                           "views_todo": p.views_todo, "views_total": p.views_total}
                          for p in plans], indent=1))
    else:
        print(status_table(plans))
        from . import layout as L
        from .report import input_line, scene_frame_line
        if ws.path(L.SCENE).is_file():
            print(input_line(ws.scene().to_dict()))
        frame = L.poses_report(ws)
        if frame.get("units"):
            print(scene_frame_line(frame))
        from .report import reflectors_line
        read = lambda k: json.loads(ws.path(k).read_text()) if ws.path(k).is_file() else None  # noqa: E731
        line = reflectors_line(read(L.PLANES), read(L.FOUND_REFLECTORS))
        if line:
            print(line)
    return 0


def _cmd_run(args, only: str | None = None, overrides: dict | None = None,
             command: tuple[str, ...] = ()) -> int:
    from .executors import make_executor
    from .pipeline import load_configs, run, select_stages, status, status_table, timing_table
    stages = _stages()
    if args.jobs < 1 or args.dask_local < 0 or not args.dask_timeout > 0:
        raise InputError("--jobs must be >= 1, --dask-local >= 0 and --dask-timeout > 0")
    selected = select_stages(stages, getattr(args, "from_stage", None),
                             getattr(args, "until_stage", None), only)
    if args.dry_run:  # reads only: no workspace, lock or record is created
        ws = _open_workspace(args, create=False)
        configs = load_configs(stages, ws, overrides)
        print(status_table(status(stages, ws, configs, args.force, selected)))
        return 0
    ws = _open_workspace(args)
    configs = load_configs(stages, ws, overrides)
    with ws.lock(wait=args.wait), \
            make_executor(args.jobs, args.dask_scheduler, args.dask_local,
                          dask_watchdog_s=args.dask_timeout) as executor:
        results = run(stages, ws, configs, selected, args.force, executor,
                      progress=not args.no_progress, command=command)
    log.info("\n%s", timing_table(results))
    return 1 if any(r.result in ("failed", "blocked") for r in results) else 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    command = tuple(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    _setup_logging(args.verbose, args.quiet)
    try:
        if args.command == "init":
            _init_workspace(args.workspace, args.input, args.force)
            return 0
        if args.command == "stages":
            return _cmd_stages(args)
        if args.command == "status":
            return _cmd_status(args)
        if args.command == "run":
            return _cmd_run(args, overrides=_parse_overrides(args.overrides), command=command)
        if getattr(args, "func", None) is not None:
            return args.func(args)
        cfg = {k[5:]: v for k, v in vars(args).items() if k.startswith("cfg__") and v is not None}
        return _cmd_run(args, only=args.command, overrides={args.command: nest(cfg)}, command=command)
    except InputError as e:
        print(f"ibr: error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # the boundary for writes outside atomic_path (mkdir of a workspace...)
        err = write_error(e, Path(e.filename or "."))
        if err is None:
            raise
        print(f"ibr: error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("ibr: interrupted; finished work is kept, rerun to continue", file=sys.stderr)
        return 130


def entry() -> None:
    sys.exit(main())
