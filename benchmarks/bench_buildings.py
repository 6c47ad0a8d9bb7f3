"""LOD2 building benchmark on the simulated city: (a) ground-truth point clouds with noise, (b) our dense cloud.

    python benchmarks/bench_buildings.py                          # (a) on make_city(0); (b) if --workspace given
    python benchmarks/bench_buildings.py --workspace demo/workspace
    python benchmarks/bench_buildings.py --make-workspace build/bench_buildings_ws   # (b) from scratch
    make bench-buildings ARGS="--make-workspace build/bench_buildings_ws"

(a) samples the simulator's ground-truth mesh at one point per GSD^2 where a nadir or 45-degree oblique view sees
it, adds Gaussian noise (``--noise``, in GSD), grids the DSM with the surface stage's ``make_dsm`` and takes the
DTM from the simulator's terrain; detection uses the nDSM and the roughness test (no masks). (b) reads a workspace
where the ``dense`` and ``surface`` stages ran on the simulated block of the same city (``dense/points.npz``,
``surface/*.tif``) and runs the ``buildings`` stage's detection (with the surface stage's masks) and
reconstruction on it; ``--make-workspace`` builds such a workspace: the simulator's default block with its true
orientation (so the figures isolate dense matching and reconstruction from aerial triangulation), dense matching
on every ``--dense-step``-th pixel and the surface rasters at that step times the GSD.

Per building and overall: outline corner deviation against the true footprint (median and mean, m and GSD), roof plane
normal error, wall direction error (the RMS over the outline's edges of at least 3 m, weighted by length, of the angle
to the true edge nearest to each edge's middle, deg), roof height RMSE (the model's top surface, roofs and their
overhangs, against the true one on a 0.5 m grid 0.5 m inside the walls, m; 'off steps' leaves out the samples within
0.75 m of a step between roofs, where a step wall placed a decimetre off counts the step's height), overhang width error
(m and DSM pixels), the dormers' walls (how far the model's roof edge across a dormer, 0.3 m behind its front, and
down its middle stands from the true one, overhang included, m; dormers the model does not rise over by 0.3 m are
missed), closed valid solid, path (2D or volumetric) and why, time per building, and the walls no facade
point showed ('walls inf.': placed by the building's median measured overhang, an assumption), and the attributes of a
3D building registry: the 70th percentile roof height over the footprint ('h70 err', model minus truth, m: the LoD 1.2
block's height) and the volume ('vol err', relative). Buildings that failed or were not detected are listed with the
reason. Tables are printed and written as JSON (``--out``, default ``build/bench_buildings.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT.parent) not in sys.path:
    sys.path.insert(0, str(ROOT.parent))

from oblique_city.core.buildings.detect import DetectConfig, building_labels, points_per_building  # noqa: E402
from oblique_city.core.buildings.model import BuildingModel  # noqa: E402
from oblique_city.core.buildings.reconstruct import ReconstructionConfig  # noqa: E402
from oblique_city.core.buildings.stage import reconstruct_unit  # noqa: E402
from oblique_city.core.buildings.synthetic import city_point_cloud  # noqa: E402
from oblique_city.core.evaluate.buildings import BuildingTruth, match_truth, score_building, summary  # noqa: E402
from oblique_city.core.pipeline.atomic import output_file, write_json  # noqa: E402
from oblique_city.core.simulate.city import make_city  # noqa: E402
from oblique_city.core.surface.dsm import DsmConfig, GridSpec, make_dsm  # noqa: E402

TARGETS = {"corner_median_gsd": 2.0, "normal_median_deg": 3.0, "overhang_px": 2.0, "closed_share": 0.9,
           "seconds": 5.0}


def run_case(name: str, xyz: np.ndarray, dsm, dtm, truths: list[BuildingTruth], gsd: float,
             masks: tuple | None = None) -> dict:
    """Detect, reconstruct and score every building of one point cloud."""
    t0 = time.perf_counter()
    bm, vm = masks if masks else (None, None)
    labels, n, stats = building_labels(dsm, dtm, DetectConfig(), bm, vm)
    dets = points_per_building(xyz, labels, dsm, dtm)
    t_detect = time.perf_counter() - t0
    scores, failures, matched = [], [], set()
    for d in dets:
        bid = f"B{d.label:04d}"
        _, md, err = reconstruct_unit((bid, xyz[d.indices], d.ground_z, dsm, ReconstructionConfig(), dtm))
        if md is None:
            c = xyz[d.indices, :2].mean(0)
            failures.append({"id": bid, "at": c.round(1).tolist(), "reason": f"reconstruction failed: {err}"})
            continue
        m = BuildingModel.from_dict(md)
        ti = match_truth(m, truths)
        if ti is None:
            failures.append({"id": bid, "at": m.footprint.mean(0).round(1).tolist(),
                             "reason": "no true building here (false detection)"})
            continue
        if ti in matched:
            failures.append({"id": bid, "truth": truths[ti].name,
                             "reason": "second detection of a building already reconstructed (split)"})
            continue
        matched.add(ti)
        scores.append(score_building(truths[ti], m))
    for i, t in enumerate(truths):
        if i not in matched:
            failures.append({"truth": t.name, "reason": "not detected / not reconstructed"})
    summ = summary(scores, len(truths))
    summ.update(detect_seconds=t_detect, detection=stats, gsd=gsd, dsm_cell=dsm.cell)
    return {"case": name, "summary": summ, "buildings": [s.to_dict() for s in scores], "failures": failures}


def print_case(res: dict) -> None:
    s = res["summary"]
    gsd, px = s["gsd"], s["dsm_cell"]
    print(f"\n=== {res['case']} (GSD {gsd:.3f} m, DSM cell {px:.3f} m) ===")
    hdr = (f"{'building':20s} {'path':10s} {'closed':6s} {'corner med/mean m':>18s} {'(GSD)':>7s} "
           f"{'normal med/max deg':>19s} {'wall deg':>8s} {'roof RMSE m':>11s} {'off steps':>9s} "
           f"{'overhang err m':>15s} {'(px)':>6s} "
           f"{'h70 err m':>9s} {'vol err':>7s} {'time s':>7s} {'walls inf.':>10s}  reason")
    print(hdr)
    print("-" * len(hdr))
    for b in res["buildings"]:
        oh = b["overhang_median"]
        print(f"{b['name']:20s} {b['path']:10s} {'yes' if b['closed'] else 'NO':6s} "
              f"{b['corner_median']:8.2f}/{b['corner_mean']:<8.2f} {b['corner_median'] / gsd:7.1f} "
              f"{b['normal_median_deg']:9.2f}/{b['normal_max_deg']:<8.2f} "
              f"{b.get('wall_direction_deg', float('nan')):8.2f} "
              f"{b.get('roof_rmse', float('nan')):11.2f} "
              f"{b.get('roof_rmse_off_steps', float('nan')):9.2f} "
              f"{oh:15.2f} {oh / px:6.1f} "
              f"{b.get('roof_70p_error', float('nan')):9.2f} {100 * b.get('volume_error', float('nan')):6.1f}% "
              f"{b['seconds']:7.2f} {b.get('walls_inferred', 0):10d}  {b['reason'][:70]}")
    print("-" * len(hdr))
    cm, nm, om = s["corner_median_of_medians"], s["normal_median_deg"], s["overhang_median_error"]

    def f(v, k=1.0):
        return "n/a" if v is None else f"{v * k:.2f}"

    print(f"overall: corner median {f(cm)} m = {f(cm, 1 / gsd)} GSD (target <= {TARGETS['corner_median_gsd']}), "
          f"corner mean {f(s['corner_mean_of_means'])} m; normal median {f(nm)} deg "
          f"(target <= {TARGETS['normal_median_deg']}); wall direction median {f(s.get('wall_direction_median_deg'))} "
          f"deg; roof height RMSE median {f(s.get('roof_rmse_median'))} m, "
          f"mean {f(s.get('roof_rmse_mean'))} m ({f(s.get('roof_rmse_off_steps_mean'))} m off steps); "
          f"70th percentile roof height error median {f(s.get('roof_70p_abs_error_median'))} m, volume error "
          f"median {f(s.get('volume_abs_error_median'), 100)} %; "
          f"overhang median {f(om)} m = {f(om, 1 / px)} px, "
          f"p90 {f(s['overhang_p90_error'])} m (target <= {TARGETS['overhang_px']} px); dormer walls (roof edge, "
          f"overhang included) sides {f(s.get('dormer_side_mean_error'))} m, fronts "
          f"{f(s.get('dormer_front_mean_error'))} m off on average over {s.get('dormers_found', 0)} dormers found, "
          f"{s.get('dormers_missed', 0)} missed")
    print(f"closed valid solids {s['closed_share']:.0%} of reconstructed, {s['closed_share_of_true']:.0%} of true "
          f"(target >= {TARGETS['closed_share']:.0%}); paths {s['paths']}; time per building median "
          f"{f(s['seconds_median'])} s, max {f(s['seconds_max'])} s (target <= {TARGETS['seconds']} s); "
          f"detection {s['detect_seconds']:.1f} s")
    if res["failures"]:
        print("failures:")
        for fl in res["failures"]:
            print("  ", json.dumps(fl))


def case_ground_truth(seed: int, gsd: float, noise_gsd: float, truths, city) -> dict:
    density = 1.0 / gsd ** 2
    xyz, _ = city_point_cloud(city, density, noise_gsd * gsd, seed=seed, area=tuple(city.core))
    grid = GridSpec.around(*city.core, gsd)
    dsm, _ = make_dsm(grid, xyz, city.crs, DsmConfig(cell=gsd))
    X, Y = grid.centers()
    dtm = grid.raster(city.terrain_z(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape), city.crs)
    name = f"(a) ground-truth mesh sampled at {density:.0f} pts/m2, noise {noise_gsd * gsd:.3f} m"
    return run_case(name, xyz, dsm, dtm, truths, gsd)


def surface_rasters(ws_path: Path, xyz: np.ndarray, rgb: np.ndarray):
    """DSM, DTM and masks: the surface stage's files, or (when that stage did not finish) the same functions
    run here on the dense points (DSM, DTM by robust opening, object masks; no true orthophoto)."""
    from oblique_city.core.io.geotiff import read_geotiff
    from oblique_city.core.pipeline import Workspace
    from oblique_city.core.surface.stage import nadir_gsd

    ws = Workspace.open(ws_path)
    z_ground = float(np.percentile(xyz[:, 2], 5))
    gsd = nadir_gsd(ws.load_block(), z_ground)
    sdir = ws_path / "surface"
    if all((sdir / n).exists() for n in ("dsm.tif", "dtm.tif", "buildings.tif", "vegetation.tif")):
        dsm, dtm = read_geotiff(sdir / "dsm.tif"), read_geotiff(sdir / "dtm.tif")
        return (dsm, dtm, read_geotiff(sdir / "buildings.tif").data > 0,
                read_geotiff(sdir / "vegetation.tif").data > 0, gsd, "surface stage files")
    from oblique_city.core.surface.dsm import cell_colours
    from oblique_city.core.surface.dtm import DtmConfig, make_dtm, object_masks

    # the DSM cell follows the dense cloud's sampling: the nadir GSD times the dense stage's pixel step
    cell = gsd * int(ws.stage_options("dense").get("step", 1))
    lo, hi = np.percentile(xyz[:, :2], [0.5, 99.5], axis=0)
    grid = GridSpec.around(lo[0], lo[1], hi[0], hi[1], cell)
    dsm, top = make_dsm(grid, xyz, ws.crs, DsmConfig(cell=cell))
    dcfg = DtmConfig()
    dtm, _, _ = make_dtm(xyz, grid, ws.crs, dcfg)
    bm, vm = object_masks(dsm.data - dtm.data, cell_colours(grid, xyz, rgb, top), cell, dcfg)
    return dsm, dtm, bm, vm, gsd, f"surface functions run here at a {cell:.3f} m cell (the surface stage had not " \
                                  "finished)"


def prepare_workspace(folder: Path, seed: int, step: int) -> Path:
    """Simulate the default block (unless already there), import its true orientation into a workspace and run
    the ``dense`` and ``surface`` stages (the runner skips what is up to date). Returns the workspace path."""
    from oblique_city.core.io.native import read_block
    from oblique_city.core.pipeline import RunContext, Workspace, run_stages
    from oblique_city.core.simulate.simulator import SimulationConfig, simulate

    sim = folder / "simulation"
    if not (sim / "truth" / "block_true.json").exists():
        simulate(sim, SimulationConfig(seed=seed))
    block = read_block(sim / "truth" / "block_true.json")
    block.image_root = str(sim.resolve())
    root = folder / "workspace"
    ws = Workspace.open(root) if (root / "project.toml").exists() else Workspace.create(root, crs=block.crs)
    if not ws.has_block():
        ws.save_block(block)
    city = make_city(seed)
    tz = city.terrain_z(city.core.reshape(2, 2))
    tops = max(p.ridge() for b in city.buildings for p in b.parts)
    ws.project.setdefault("stages", {}).setdefault("dense", {}).update(
        step=step, z_min=float(np.nanmin(tz)) - 10.0, z_max=float(tops) + 10.0)
    gsd = SimulationConfig().gsd
    ws.project["stages"].setdefault("surface", {})["cell"] = gsd * step
    ws.save_project()
    for r in run_stages(ws, ["dense", "surface"], RunContext()):
        print(f"{r.name:8s} {r.status:8s} {r.seconds:7.1f} s  {r.message}")
    return root


def case_workspace(ws_path: Path, truths) -> dict:
    with np.load(ws_path / "dense" / "points.npz") as z:
        kept = z["removed"] == 0
        xyz = z["xyz"][kept].astype(np.float64)
        rgb = z["rgb"][kept]
    dsm, dtm, bm, vm, gsd, source = surface_rasters(ws_path, xyz, rgb)
    name = f"(b) our dense cloud {ws_path} ({len(xyz)} points; rasters: {source})"
    return run_case(name, xyz, dsm, dtm, truths, gsd, masks=(bm, vm))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="city seed (the simulator's default block uses 0)")
    ap.add_argument("--gsd", type=float, default=0.155, help="GSD of case (a), m (the simulator's default)")
    ap.add_argument("--noise", type=float, default=0.5, help="noise of case (a) in GSD")
    ap.add_argument("--workspace", help="workspace with dense + surface outputs of the simulated block (case b)")
    ap.add_argument("--make-workspace", metavar="DIR",
                    help="case (b) from scratch: simulate the default block into DIR, import its true orientation, "
                         "run dense and surface (about 10 min on 2 cores), then evaluate")
    ap.add_argument("--dense-step", type=int, default=2, help="dense pixel step for --make-workspace")
    ap.add_argument("--out", type=output_file, default=ROOT / "build" / "bench_buildings.json", help="JSON output")
    args = ap.parse_args()
    city = make_city(args.seed)
    truths = [BuildingTruth.from_city(b) for b in city.buildings]
    results = [case_ground_truth(args.seed, args.gsd, args.noise, truths, city)]
    print_case(results[0])
    ws_path = Path(args.workspace) if args.workspace else None
    if args.make_workspace:
        ws_path = prepare_workspace(Path(args.make_workspace), args.seed, args.dense_step)
    if ws_path is not None:
        results.append(case_workspace(ws_path, truths))
        print_case(results[-1])
    else:
        print("\n(b) our dense cloud: not run (give --workspace or --make-workspace)")
    write_json(args.out, {"targets": TARGETS, "cases": results}, default=float)
    print(f"\nwritten {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
