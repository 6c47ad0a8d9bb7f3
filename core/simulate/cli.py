"""``oblique-city simulate OUT``: write a simulated oblique block with its ground truth (the embedded default)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

from ..errors import ConfigError
from .simulator import SimulationConfig


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..cli import TerminalProgress
    from .simulator import simulate

    cfg = SimulationConfig()
    over = {"system": "penta" if args.preset == "default" else args.preset, "seed": args.seed,
            "workers": args.workers, "depth_maps": args.depth, "image_format": args.image_format,
            "target_pattern": args.targets}
    if args.gsd is not None:
        over["gsd"] = args.gsd
    if args.size is not None:
        w, _, h = args.size.lower().partition("x")
        if not (w.isdigit() and h.isdigit()):
            raise ConfigError(f"--size '{args.size}' should be WIDTHxHEIGHT in pixels, e.g. 1400x1050")
        over["width"], over["height"] = int(w), int(h)
    if args.extend is not None:
        over["extend_along_h"] = args.extend
    if args.no_cross:
        over["cross_strips"] = False
    try:
        cfg = replace(cfg, **over)
    except ConfigError as e:
        raise ConfigError(f"simulate: {e}") from None
    progress = TerminalProgress(json_lines=args.json_progress)
    try:
        s = simulate(args.out, cfg, progress=lambda d, t, m: progress("simulate", d, t, m))
    finally:
        progress.close()
    print(f"simulated {s['images']} images ({s['exposures']} exposures, {s['megapixels']:.1f} Mpx, views "
          f"{s['views']}) at GSD {s['gsd_m']:.3f} m from {s['flying_height_m']:.0f} m; "
          f"{s['ground_points']} ground points")
    print(f"rendered in {s['render_seconds']:.1f} s = {s['images_per_second']:.2f} images/s with {s['workers']} "
          f"worker(s) on {s['cpu_count']} CPUs ({s['render_cpu_seconds']:.0f} CPU s; load average "
          f"{s['load_average_1min']:.1f}: other jobs on the machine slow the wall time); total "
          f"{s['total_seconds']:.1f} s -> {args.out}")
    if args.verbose:
        print(json.dumps(s, indent=1))
    return 0


def add_commands(subparsers) -> None:
    s = subparsers.add_parser("simulate", help="render a simulated oblique block over the synthetic city, with "
                                               "ground truth (the embedded default data)")
    s.add_argument("out", help="output folder")
    s.add_argument("--preset", default="default", choices=("default", "penta", "three-head"),
                   help="camera system (default: penta)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--gsd", type=float, help="nadir GSD in metres (default 0.155)")
    s.add_argument("--size", help="image size WxH per head (default 1400x1050)")
    s.add_argument("--extend", type=float, help="strip extension beyond the area, in flying heights (default 1.1)")
    s.add_argument("--no-cross", action="store_true", help="no north-south cross strip")
    s.add_argument("--depth", action="store_true", help="also write per-image depth maps to truth/depth")
    s.add_argument("--workers", type=int, default=2, help="rendering processes")
    s.add_argument("--image-format", choices=("jpg", "png", "tif12"), default="jpg",
                   help="tif12: 16-bit TIFF with 12 significant bits, as aerial cameras deliver them")
    s.add_argument("--targets", choices=("disc", "cross"), default="disc",
                   help="signalised targets: a white disc on a black square, or a white cross")
    s.add_argument("--json-progress", action="store_true", help="progress as JSON lines on stdout")
    s.set_defaults(func=cmd_simulate)
