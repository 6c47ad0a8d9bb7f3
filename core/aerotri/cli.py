"""CLI command ``oblique-city aerotri WS --mode integrated|hierarchical --connection cba|2|3|5|10 [--rig] [--mounting]
[--no-control-tests] [--no-prior-tests] [--gnss-strips off|shift|drift]``.

A shortcut for ``oblique-city run WS --stages aerotri --set aerotri.mode=... --set aerotri.connection=...``
that stores the options in ``project.toml`` and runs the stage (forced, since the options are the point).
"""

from __future__ import annotations

import argparse

from .bundle import GNSS_STRIP_MODES
from .hierarchical import CONNECTIONS
from .stage import MODES


def cmd_aerotri(args: argparse.Namespace) -> int:
    from ..cli import run_and_print
    from ..pipeline import Workspace

    ws = Workspace.open(args.workspace)
    opts: dict = {}
    for key in ("mode", "connection", "cell_size", "sigma_px", "gnss_strips"):
        value = getattr(args, key)
        if value is not None:
            opts[key] = value
    for key in ("rig", "mounting", "control_tests", "prior_tests", "prior_sigma_estimate", "control_sigma_estimate"):
        if getattr(args, key) is not None:
            opts[key] = getattr(args, key)
    if args.self_calibration is not None:
        opts["self_calibration"] = [g for g in args.self_calibration.split(",") if g]
    ws.update_stage_options("aerotri", opts, "oblique-city aerotri")
    ws.save_project()
    return run_and_print(ws, ["aerotri"], args, force=True)


def add_commands(sub) -> None:
    s = sub.add_parser("aerotri", help="aerial triangulation (integrated or hierarchical with CBA)")
    s.add_argument("workspace")
    s.add_argument("--mode", choices=MODES)
    s.add_argument("--connection", choices=CONNECTIONS)
    s.add_argument("--cell-size", dest="cell_size", type=float, help="CBA grid cell, metres")
    s.add_argument("--sigma-px", dest="sigma_px", type=float, help="a priori tie measurement sigma, pixels")
    s.add_argument("--self-calibration", help="comma-separated: focal,principal_point,radial,tangential")
    s.add_argument("--rig", action=argparse.BooleanOptionalAction,
                   help="tie the heads of each exposure to the block's rig; they then share their exposure's one "
                        "GNSS/IMU measurement (integrated: rig constraints; hierarchical: the heads fused into one "
                        "body after the view runs)")
    s.add_argument("--mounting", action=argparse.BooleanOptionalAction,
                   help="calibrate each camera's boresight and lever arm against the GNSS/IMU priors")
    s.add_argument("--control-tests", dest="control_tests", action=argparse.BooleanOptionalAction,
                   help="test the control points' measurements and coordinates for blunders (on by default)")
    s.add_argument("--prior-tests", dest="prior_tests", action=argparse.BooleanOptionalAction,
                   help="test each image's GNSS position and IMU attitude prior for blunders (on by default)")
    s.add_argument("--prior-sigma-estimate", dest="prior_sigma_estimate", action=argparse.BooleanOptionalAction,
                   help="scale the GNSS and IMU sigmas up by their variance components and adjust again when the "
                        "errors exceed them (on by default)")
    s.add_argument("--control-sigma-estimate", dest="control_sigma_estimate", action=argparse.BooleanOptionalAction,
                   help="scale the control points' image measurement sigmas by their variance component and adjust "
                        "again when their residuals differ from them (on by default)")
    s.add_argument("--gnss-strips", dest="gnss_strips", choices=GNSS_STRIP_MODES,
                   help="estimate a GNSS offset (shift) or an offset and a drift (drift) per flight strip")
    s.add_argument("--executor", choices=("inline", "processes", "dask"), default="inline")
    s.add_argument("--workers", type=int, default=2)
    s.add_argument("--scheduler", help="Dask scheduler address")
    s.add_argument("--json-progress", action="store_true")
    s.set_defaults(func=cmd_aerotri)
