"""The main job on the embedded default data: simulate the default block, import it, run every stage.

``oblique-city demo OUT`` writes::

    OUT/simulation/   the simulated block (images, BlocksExchange XML, ground points) and its ground truth
    OUT/workspace/    the workspace: imported block and one folder per stage's outputs
    OUT/summary.json  what ran, how long it took, and each stage's metrics
    OUT/workspace/report.html  the project report (:mod:`.report`)
    OUT/export/       the city as CityGML 2.0, CityJSON 2.0, OBJ (textured, with windows), 3D Tiles 1.1 and GeoJSON
                      footprints, and the adjusted block as BlocksExchange and Metashape XML (once the stages they
                      need are done)

Every step is resumable: an existing simulation is reused, an unchanged block is not re-imported, and the runner
skips finished stages. ``make demo`` then writes ``OUT/city.blend`` with the add-on's builders (a bpy process).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .pipeline import RunContext, Workspace, run_stages
from .pipeline.atomic import write_json
from .pipeline.runner import plan

SIMULATION = "simulation"
WORKSPACE = "workspace"
EXPORT = "export"


def _simulate_if_missing(sim: Path, progress: Callable[[int, int, str], None] | None) -> dict | None:
    """Simulate the default block into ``sim`` unless a complete one is there (its truth is written last)."""
    from .simulate.simulator import SimulationConfig, simulate

    if (sim / "block.xml").exists() and (sim / "truth").is_dir() and any((sim / "truth").iterdir()):
        return None
    return simulate(sim, SimulationConfig(), progress=progress)


def _import_block(ws: Workspace, sim: Path) -> bool:
    """Import the simulated BlocksExchange block through the real import path, its exposures from the image names
    (the format does not carry them; a rig is estimated from the orientations); False if already identical."""
    from .io.formats import read_block
    from .io.native import block_to_dict
    from .simulate.flight import IMAGE_NAME_PATTERN

    block = read_block("bex", sim / "block.xml", image_root=str(sim), check_images=True, exposures="name",
                       exposure_pattern=IMAGE_NAME_PATTERN)
    if ws.has_block() and block_to_dict(ws.load_block(adjusted=False)) == block_to_dict(block):
        return False
    ws.save_block(block)
    return True


def _set_demo_options(ws: Workspace, sim: Path) -> None:
    """The demo's stage options; a value the user already set in ``project.toml`` is kept.

    * Dense matching and surfaces cover the simulated city (the planned flight area plus its inset), not the whole
      ground under the extended strips.
    * The triangulation calibrates each camera's mounting: the simulated heads are mounted off their nominal
      boresight, as real ones are, and the imported block has one camera per head. It ties the heads of each
      exposure by rig constraints between their calibrated mountings, so that the exposure's one GNSS/IMU
      measurement counts once (:func:`.aerotri.bundle.shared_prior_fraction`): on the demo the orientations' errors
      against the truth halved (attitude 0.0064 -> 0.0031 deg RMS, centres 16-19 -> 9-10 mm).
    * The GNSS/IMU priors get the sigmas of the simulated navigation system (its specification, as an operator enters
      it; the imported BlocksExchange block carries none): the largest of its GNSS sigmas and of its IMU sigmas (the
      boresight error is the mounting calibration's). With the stage's defaults (0.15 m, 0.05 deg) their variance
      components came out at 0.38 and 0.15.
    * The control and check points are measured in the images (the rendered targets, ``match.targets = all``): the
      simulator's own image measurements (true projections plus noise) serve only to compare with."""
    doc = json.loads((sim / "truth" / "simulation.json").read_text())
    x0, y0, x1, y1 = doc["summary"]["area"]
    m = float(doc["config"]["area_inset"])
    aoi = [x0 - m, y0 - m, x1 + m, y1 + m]
    stages = ws.project.setdefault("stages", {})
    changed = False
    for name in ("dense", "surface"):
        opts = stages.setdefault(name, {})
        if not opts.get("aoi"):
            opts["aoi"] = aoi
            changed = True
    for key in ("mounting", "rig"):
        if key not in stages.setdefault("aerotri", {}):
            stages["aerotri"][key] = True
            changed = True
    nav = doc["config"].get("nav") or {}
    for key, spec in (("default_sigma_position", "gnss_sigma"), ("default_sigma_attitude_deg", "imu_sigma_deg")):
        if spec in nav and key not in stages["aerotri"]:
            stages["aerotri"][key] = float(max(nav[spec]))
            changed = True
    if "targets" not in stages.setdefault("match", {}):
        stages["match"]["targets"] = "all"
        changed = True
    if changed:
        ws.save_project()


def run_demo(out: str | Path, ctx: RunContext | None = None,
             stages: list[str] | None = None) -> dict:
    """Run the main job into folder ``out`` and return its summary (also written to ``out/summary.json``)."""
    ctx = ctx or RunContext()
    plan(stages)  # unknown stage names are refused before the simulation renders for minutes
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def sim_progress(done: int, total: int, message: str) -> None:
        ctx.stage = "simulate"
        ctx.progress(done, total, message)

    sim_summary = _simulate_if_missing(out / SIMULATION, sim_progress)
    t_sim = time.perf_counter() - t0
    from .io.formats import read_block

    crs = read_block("bex", out / SIMULATION / "block.xml", image_root=str(out / SIMULATION),
                     check_images=False).crs
    root = out / WORKSPACE
    ws = Workspace.open(root) if (root / "project.toml").exists() else Workspace.create(root, crs=crs,
                                                                                        name="oblique-city-demo")
    imported = _import_block(ws, out / SIMULATION)
    _set_demo_options(ws, out / SIMULATION)
    records = run_stages(ws, stages, ctx)
    state = ws.read_state()
    summary = {
        "simulation": {"folder": str(out / SIMULATION), "reused": sim_summary is None, "seconds": t_sim,
                       "summary": sim_summary},
        "workspace": str(ws.root),
        "imported": imported,
        "block": ws.load_block().summary(),
        "stages": [{"name": r.name, "status": r.status, "seconds": r.seconds, "message": r.message,
                    "metrics": state.get(r.name, {}).get("metrics", {})} for r in records],
        "total_seconds": time.perf_counter() - t0,
    }
    summary.update(deliverables(ws, out / EXPORT))
    write_json(out / "summary.json", summary)
    return summary


def deliverables(ws: Workspace, folder: Path) -> dict[str, Any]:
    """The demo's deliverables: into ``folder`` the city in every format once the buildings exist and the block
    (adjusted once aerial triangulation ran) for other photogrammetry software, and the project report into the
    workspace. Returns ``{"exports": [one line per file], "report": path}``."""
    from .export.command import export_block, export_buildings
    from .report import write_project_report

    done = []
    if ws.read_state().get("buildings", {}).get("status") == "done":
        for fmt, name in (("citygml", "city.gml"), ("cityjson", "city.city.json"), ("obj", "city.obj"),
                          ("3dtiles", "tiles"), ("geojson", "footprints.geojson")):
            done.append(export_buildings(ws.root, fmt, folder / name))
    for fmt, name in (("bex", "block.xml"), ("metashape", "cameras.xml")):
        done.append(export_block(ws.root, fmt, folder / name))
    return {"exports": done, "report": str(write_project_report(ws.root))}


def cmd_demo(args: argparse.Namespace) -> int:
    from .cli import _ctx

    ctx, progress, ex = _ctx(args)
    try:
        s = run_demo(args.out, ctx, [x for x in (args.stages or "").split(",") if x] or None)
    finally:
        progress.close()
        ex.close()
    sim = s["simulation"]
    print(f"simulation: {'reused' if sim['reused'] else 'rendered'} {sim['folder']} ({sim['seconds']:.1f} s)")
    b = s["block"]
    print(f"block: {b['images']} images {b['views']}, {b['control_points']} control / {b['check_points']} check "
          f"points, {b['crs']}")
    for st in s["stages"]:
        print(f"{st['name']:10s} {st['status']:9s} {st['seconds']:8.1f} s  {st['message']}")
    for line in s["exports"]:
        print(f"export: {line}")
    print(f"workspace: {s['workspace']}; summary: {Path(args.out) / 'summary.json'}; report: {s['report']} "
          f"({s['total_seconds']:.1f} s in all)")
    return 0


def add_commands(subparsers) -> None:
    s = subparsers.add_parser("demo", help="simulate the default block, import it and run every stage into OUT")
    s.add_argument("out", nargs="?", default="demo", help="output folder (default: demo)")
    s.add_argument("--stages", help="comma-separated stages (default: all)")
    # the demo uses the machine: a local process pool, a worker per core (at most four)
    s.add_argument("--executor", choices=("inline", "processes", "dask"), default="processes")
    s.add_argument("--workers", type=int, default=max(1, min(4, os.cpu_count() or 1)))
    s.add_argument("--scheduler", help="Dask scheduler address")
    s.add_argument("--json-progress", action="store_true", help="progress as JSON lines on stdout")
    s.set_defaults(func=cmd_demo)
