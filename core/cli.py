"""The terminal face of the runner: ``oblique-city`` (also ``python -m oblique_city``).

User errors (any :class:`CityError`) print one line and exit with code 2; Ctrl-C cancels the running stage
cleanly (exit 130).
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import Cancelled, CityError, ConfigError

if TYPE_CHECKING:
    from .model import ImageBlock

COMMAND_MODULES: list[str] = [".aerotri.cli", ".matching.cli", ".simulate.cli", ".demo", ".export.command", ".report"]
"""Modules (relative to ``core``) that add sub-commands: each defines ``add_commands(subparsers)`` and sets
``func`` on its parsers with ``parser.set_defaults(func=...)``."""


def parse_options(pairs: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for p in pairs or []:
        if "=" not in p:
            raise ConfigError(f"option '{p}' should look like key=value")
        k, v = p.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


class TerminalProgress:
    """Progress bars on stderr (tqdm), or JSON lines on stdout for a parent process (Blender)."""

    def __init__(self, json_lines: bool = False) -> None:
        self.json_lines = json_lines
        self._bar = None
        self._stage = None

    def __call__(self, stage: str, done: int, total: int, message: str) -> None:
        if self.json_lines:
            print(json.dumps({"stage": stage, "done": done, "total": total, "message": message}), flush=True)
            return
        from tqdm import tqdm

        if self._bar is None or stage != self._stage or total != self._bar.total:
            self.close()
            self._bar = tqdm(total=total, desc=stage, unit="", leave=True, file=sys.stderr, dynamic_ncols=True)
            self._stage = stage
        self._bar.n = done
        self._bar.set_postfix_str(message[:60], refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _ctx(args: argparse.Namespace):
    from .pipeline import Executor, RunContext

    progress = TerminalProgress(json_lines=getattr(args, "json_progress", False))
    ex = Executor(getattr(args, "executor", "inline"), workers=getattr(args, "workers", 2),
                  address=getattr(args, "scheduler", None))
    ctx = RunContext(on_progress=progress, executor=ex)
    signal.signal(signal.SIGINT, lambda *_: ctx.cancel())
    signal.signal(signal.SIGTERM, lambda *_: ctx.cancel())
    return ctx, progress, ex


def cmd_new(args: argparse.Namespace) -> int:
    from .pipeline import Workspace

    ws = Workspace.create(args.workspace, crs=args.crs, name=args.name)
    print(f"created workspace {ws.root} (CRS {ws.crs})")
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from .geometry.crs import normalize_crs
    from .io.formats import detect_format, read_block
    from .pipeline import Workspace

    fmt = args.format
    if fmt == "auto":
        fmt = detect_format(args.source)
        print(f"format: {fmt} (told from the file; --format chooses another)")
    block = read_block(fmt, args.source, **parse_options(args.option))
    root = Path(args.workspace)
    ws = Workspace.open(root) if (root / "project.toml").exists() else Workspace.create(root, crs=block.crs)
    if normalize_crs(block.crs) != normalize_crs(ws.crs):
        from .geometry.crs import transform_points
        from .io.reproject import reproject_block

        block = reproject_block(block, ws.crs, transform_points)
    ws.save_block(block)
    s = block.summary()
    views = ", ".join(f"{k} {v}" for k, v in s["views"].items())
    print(f"imported {s['images']} images ({views}), {s['cameras']} cameras, {s['control_points']} control and "
          f"{s['check_points']} check points into {ws.root} [{ws.crs}]")
    print_system(block)
    return 0


def print_system(block: ImageBlock) -> None:
    """The block's camera system (exposures and rigs), or that HAT will lack it, when there is a line to say."""
    from .model.exposures import MISSING_EXPOSURES, describe_system, oblique_without_nadir

    system = describe_system(block)
    if system:
        print(system)
    elif oblique_without_nadir(block):
        print(MISSING_EXPOSURES)


def cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import Workspace

    ws = Workspace.open(args.workspace)
    for k, v in parse_options(args.set).items():
        stage, _, opt = k.partition(".")
        if not opt:
            raise ConfigError(f"--set '{k}' should name a stage option like aerotri.mode=hierarchical")
        ws.update_stage_options(stage, {opt: v}, f"--set {k}")
    if args.set:
        ws.save_project()
    return run_and_print(ws, [s for s in (args.stages or "").split(",") if s] or None, args, force=args.force)


def run_and_print(ws, stages: list[str] | None, args: argparse.Namespace, force: bool = False) -> int:
    """Run stages with terminal progress and the executor chosen by ``args``; print one line per stage."""
    from .pipeline import run_stages

    ctx, progress, ex = _ctx(args)
    try:
        records = run_stages(ws, stages, ctx, force=force)
    finally:
        progress.close()
        ex.close()
    for r in records:
        print(f"{r.name:10s} {r.status:9s} {r.seconds:8.1f} s  {r.message}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from .pipeline import Workspace, status

    ws = Workspace.open(args.workspace)
    if ws.has_block():
        block = ws.load_block()
        s = block.summary()
        print(f"block: {s['images']} images {s['views']}, {s['control_points']} control / {s['check_points']} "
              f"check points, CRS {s['crs']}")
        print_system(block)
    else:
        print("block: not imported")
    for row in status(ws):
        secs = "" if row["seconds"] is None else f"{row['seconds']:.1f} s"
        print(f"{row['stage']:10s} {row['status']:9s} {secs:>10s}  {row['message']}")
    return 0


def reader_options_help(width: int = 100) -> str:
    """The import command's epilog: every format's reader options, then those every reader but the native one
    takes, a line of help each."""
    import textwrap

    from .io.common import COMMON_OPTIONS
    from .io.formats import READER_OPTIONS

    def rows(options: dict[str, str]) -> list[str]:
        return [textwrap.fill(text, width, initial_indent=f"    {name:22s} ", subsequent_indent=" " * 27)
                for name, text in options.items()]

    out = ["reader options (-o KEY=VALUE):"]
    for fmt, options in sorted(READER_OPTIONS.items()):
        out += [f"  {fmt}:", *(rows(options) or ["    none"])]
    out += ["  every format but native:", *rows(COMMON_OPTIONS)]
    return "\n".join(out)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="oblique-city", description="City modelling from oblique aerial imagery.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("new", help="create a workspace")
    s.add_argument("workspace")
    s.add_argument("--crs", required=True, help="EPSG:nnnn or WKT of the project (projected, metres)")
    s.add_argument("--name")
    s.set_defaults(func=cmd_new)

    from .io.formats import READERS

    s = sub.add_parser("import", help="import an oriented image block into a workspace (created if missing)",
                       epilog=reader_options_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("workspace")
    s.add_argument("source", help="block file or folder")
    s.add_argument("--format", default="auto", choices=["auto", *sorted(READERS)],
                   help="the block's format (default auto: told from the file, see io.formats.detect_format)")
    s.add_argument("-o", "--option", action="append", metavar="KEY=VALUE",
                   help="reader option (e.g. angles=gon, cameras=cam.toml, gcps=gcp.txt; the list below)")
    s.set_defaults(func=cmd_import)

    s = sub.add_parser("run", help="run stages (all by default); finished stages whose inputs did not change "
                                   "are skipped")
    s.add_argument("workspace")
    s.add_argument("--stages", help="comma-separated stage names")
    s.add_argument("--force", action="store_true",
                   help="rerun the given stages (all without --stages) even if up to date; the stages they require "
                        "still run only when stale")
    s.add_argument("--set", action="append", metavar="STAGE.OPTION=VALUE", help="set a stage option")
    s.add_argument("--executor", choices=("inline", "processes", "dask"), default="inline")
    s.add_argument("--workers", type=int, default=2)
    s.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://10.0.0.5:8786")
    s.add_argument("--json-progress", action="store_true", help="progress as JSON lines on stdout")
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("status", help="show the block and the state of each stage")
    s.add_argument("workspace")
    s.set_defaults(func=cmd_status)

    core_pkg = __package__
    for mod in COMMAND_MODULES:
        importlib.import_module(mod, core_pkg).add_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return int(args.func(args) or 0)
    except Cancelled as e:
        print(f"oblique-city: {e}", file=sys.stderr)
        return 130
    except CityError as e:
        print(f"oblique-city: error: {e}", file=sys.stderr)
        return 2
