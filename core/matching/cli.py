"""CLI command ``oblique-city measure WS IMAGE [--point P (--uv U V [--refine] | --remove | --reset)]``.

Without ``--point``, lists the ground points image ``IMAGE`` shows: their projection, the measurement the adjustment
will take and where it comes from. With it, records the operator's measurement of that point in that image
(:mod:`.manual`); the next ``run`` redoes the ``aerotri`` stage with it.
"""

from __future__ import annotations

import argparse

from ..errors import ConfigError
from .manual import ground_points_in_image, reset_manual, set_manual


def _xy(uv) -> str:
    return "-" if uv is None else f"{uv[0]:9.2f} {uv[1]:9.2f}"


def cmd_measure(args: argparse.Namespace) -> int:
    from ..pipeline import Workspace

    ws = Workspace.open(args.workspace)
    if args.point is None:
        if args.uv is not None or args.remove or args.reset or args.refine:
            raise ConfigError("--uv, --refine, --remove and --reset need --point")
        rows = ground_points_in_image(ws, args.image)
        print(f"{args.image}: {len(rows)} ground points in the frame or measured there")
        print(f"{'point':<12} {'kind':<8} {'predicted u':>9} {'v':>9}  {'measured u':>9} {'v':>9}  source")
        for r in rows:
            print(f"{r.name:<12} {r.kind:<8} {_xy(r.predicted)}  {_xy(r.uv)}  {r.source}")
        return 0
    chosen = sum(bool(x) for x in (args.uv is not None, args.remove, args.reset))
    if chosen != 1:
        raise ConfigError("give one of --uv U V, --remove or --reset with --point")
    if args.refine and args.uv is None:
        raise ConfigError("--refine goes with --uv")
    if args.reset:
        print(reset_manual(ws, args.point, args.image))
    else:
        print(set_manual(ws, args.point, args.image, None if args.remove else args.uv, refine=args.refine))
    return 0


def add_commands(sub) -> None:
    s = sub.add_parser("measure", help="list or set the ground points' image measurements of one image by hand")
    s.add_argument("workspace")
    s.add_argument("image", help="image id")
    s.add_argument("--point", help="ground point name")
    s.add_argument("--uv", type=float, nargs=2, metavar=("U", "V"),
                   help="pixel position (centre of the top-left pixel at 0 0)")
    s.add_argument("--refine", action="store_true",
                   help="fit the point's target around --uv and record its centre")
    s.add_argument("--remove", action="store_true", help="the point is not measured in this image")
    s.add_argument("--reset", action="store_true",
                   help="drop the manual measurement: the imported or automatic one applies again")
    s.set_defaults(func=cmd_measure)
