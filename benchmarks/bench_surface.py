"""Benchmark of the dense and surface stages on the default simulated block against its ground truth.

    python benchmarks/bench_surface.py [--sim DIR] [--out DIR] [--orientation true|approx|aerotri]
    python benchmarks/bench_surface.py --sim demo/simulation --workspace demo/workspace   # an existing run

Prints a table and writes ``<out>/bench_surface.json``:

* Middlebury (scikit-image's Motorcycle pair): bad-2.0 and end-point error of the SGM stage (padding + left-right
  check) beside plain OpenCV StereoSGBM with the same settings;
* DSM RMSE / NMAD / completeness on roofs, wall cells and open ground, against the simulator's GT DSM;
* DTM RMSE against the true terrain; share of building/vegetation points classified above, ground points on;
* facade point density from the oblique views; mixed-pixel filter effect (removed, error before/after);
* true-ortho displacement of roof edges against a reference true ortho rendered by the simulator;
* forward intersection error with the orientation used and with the approximate one (quality maps);
* dense matching throughput (Mpx/s per pair) and the speed-up of 2 processes over 1 on the same pairs.

The orientation used for matching is, by default, the simulator's true orientation (as the result of a perfect
aerial triangulation); ``--orientation aerotri`` runs the project's ``aerotri`` stage first, ``approx`` uses the
GNSS/IMU orientation; ``--workspace`` evaluates a workspace where the stages already ran on the simulated block
(e.g. the demo's, with the project's own aerial triangulation). Timings come from a shared 2-core machine with
other jobs running: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from oblique_city.core.dense.pairs import PairTask, match_pair
from oblique_city.core.dense.sgm import SgmConfig, plain_sgbm, sgm_disparity
from oblique_city.core.evaluate.surface import (
    classification_shares,
    error_shares,
    filter_effect,
    height_stats,
    roof_edge_displacement,
    surface_table,
    wall_cells,
    wall_error,
)
from oblique_city.core.io.geotiff import read_geotiff
from oblique_city.core.io.native import read_block
from oblique_city.core.io.pointcloud import read_las
from oblique_city.core.io.validate import resolve_image
from oblique_city.core.pipeline import Executor, RunContext, Workspace
from oblique_city.core.pipeline.runner import run_stages
from oblique_city.core.surface.dtm import LAS_CLASSES

ROOF = (3, 7, 8)       # roof, roof installation, roof edge (codes of core.simulate.city.SEMANTIC)
GROUND = (0, 1)        # ground, street
TREE = 6
WALL = (2, 5)          # wall, window


def middlebury() -> dict:
    from skimage.data import stereo_motorcycle

    left, right, gt = stereo_motorcycle()
    out = {}
    for name, fn in (("sgm_stage", sgm_disparity), ("plain_sgbm", plain_sgbm)):
        t0 = time.perf_counter()
        d = fn(left, right, 0, 80, SgmConfig())
        secs = time.perf_counter() - t0
        m = np.isfinite(gt)
        v = m & np.isfinite(d)
        err = np.abs(d - gt)
        out[name] = {"bad2_all": float((~v[m] | (err[m] > 2)).mean()), "bad2_matched": float((err[v] > 2).mean()),
                     "epe_matched_px": float(err[v].mean()), "coverage": float(v.sum() / m.sum()), "seconds": secs}
    return out


def setup_workspace(sim: Path, root: Path, orientation: str, truth) -> Workspace:
    block = read_block(sim / "block.json")
    block.image_root = str(sim.resolve())
    if orientation == "true":
        for iid, img in block.images.items():
            img.pose_adjusted = truth.block.images[iid].pose_approx
    ws = Workspace.create(root, block.crs, exist_ok=True)
    ws.save_block(block)
    d = truth.dsm
    rows, cols = d.shape
    aoi = [d.x0, d.y0 - rows * d.cell, d.x0 + cols * d.cell, d.y0]
    ws.project["stages"]["dense"] = {"aoi": aoi}
    ws.project["stages"]["surface"] = {"aoi": aoi}
    ws.save_project()
    return ws


def pair_tasks(ws: Workspace, n: int, threads: int) -> list[PairTask]:
    """The first ``n`` pairs of the dense run, rebuilt from ``dense/selection.json`` (for the speed-up)."""
    from oblique_city.core.dense.stage import DenseConfig, height_prior, master_step

    block = ws.load_block()
    cfg = DenseConfig()
    z0, z1, _ = height_prior(ws, block, cfg)
    doc = json.loads(ws.path("dense", "selection.json").read_text())
    view = {m["master"]: m["view"] for m in doc["masters"]}
    tasks = []
    for p in doc["pairs"][:n]:
        m, s = block.images[p["master"]], block.images[p["slave"]]
        tasks.append(PairTask(m.id, s.id, block.camera_of(m), m.pose, block.camera_of(s), s.pose,
                              str(resolve_image(block, m.file)), str(resolve_image(block, s.file)), z0, z1,
                              master_step(cfg, view[m.id]), cfg.scale,
                              SgmConfig(block_size=cfg.block_size, mode=cfg.sgm_mode), threads=threads))
    return tasks


def speedup(ws: Workspace, n_pairs: int) -> dict:
    """Pairs in 1 process with one OpenCV thread, in 2 processes with one thread each, and in 1 process with
    OpenCV's own threads (which parallelise SGBM inside a pair)."""
    import cv2

    load = os.getloadavg()
    one = pair_tasks(ws, n_pairs, threads=1)
    default_threads = cv2.getNumThreads()
    t0 = time.perf_counter()
    res = Executor("inline").map(match_pair, one)
    t1 = time.perf_counter() - t0
    cv2.setNumThreads(default_threads)
    with Executor("processes", workers=2) as ex:
        ex.map(match_pair, one[:2])  # start the pool (spawn + imports) outside the timing
        t0 = time.perf_counter()
        ex.map(match_pair, one)
        t2 = time.perf_counter() - t0
    t0 = time.perf_counter()
    Executor("inline").map(match_pair, pair_tasks(ws, n_pairs, threads=0))
    t3 = time.perf_counter() - t0
    mpx = sum(r.megapixels for r in res)
    return {"pairs": len(one), "megapixels": mpx, "seconds_1_process": t1, "seconds_2_processes": t2,
            "seconds_1_process_opencv_threads": t3, "speedup": t1 / t2, "speedup_opencv_threads": t1 / t3,
            "mpx_per_s_1_thread": mpx / t1, "load_average_before": list(load), "cpu_count": os.cpu_count()}


def reference_ortho(truth, grid_raster) -> np.ndarray:
    """The ideal true ortho on the DSM grid: the simulator's renderer with a camera 20 km up and a focal length
    giving the cell size (relief displacement below 1 mm), sun and shadows as in the images."""
    from oblique_city.core.model import CameraModel, Pose
    from oblique_city.core.simulate.render import Renderer

    rows, cols = grid_raster.shape
    h = 20000.0
    cam = CameraModel("ortho", cols, rows, h / grid_raster.cell, h / grid_raster.cell, (cols - 1) / 2, (rows - 1) / 2)
    cx = grid_raster.x0 + cols * grid_raster.cell / 2
    cy = grid_raster.y0 - rows * grid_raster.cell / 2
    ground = float(np.nanmedian(truth.dtm.data))
    pose = Pose(np.diag([1.0, -1.0, -1.0]), [cx, cy, ground + h])
    rgb, _ = Renderer(truth.city).render(cam, pose)
    return rgb


def point_truth(truth, xyz: np.ndarray, sample: int, seed: int = 0) -> dict:
    """Distance of (a sample of) points to the true city mesh and the semantic class of the closest triangle."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(xyz), size=min(sample, len(xyz)), replace=False))
    q = (xyz[idx] - truth.city.origin).astype(np.float32)
    scene = truth.city.scene()
    r = scene.compute_closest_points(o3d.core.Tensor(q))
    closest = r["points"].numpy().astype(np.float64)
    tri = r["primitive_ids"].numpy().astype(np.int64)
    return {"index": idx, "dist": np.linalg.norm(closest - q, axis=1), "semantic": truth.city.semantic[tri],
            "terrain": truth.city.terrain_z(xyz[idx, :2])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sim", default="benchmarks/out/sim", help="simulated block folder (simulated if missing)")
    ap.add_argument("--out", default="benchmarks/out/surface", help="workspace and results folder")
    ap.add_argument("--orientation", choices=("true", "approx", "aerotri"), default="true")
    ap.add_argument("--speedup-pairs", type=int, default=4)
    ap.add_argument("--force", action="store_true", help="rerun stages that are up to date")
    ap.add_argument("--workspace", help="evaluate this workspace (dense and surface done) instead of running one")
    ap.add_argument("--sample", type=int, default=300_000, help="points compared with the true mesh")
    args = ap.parse_args()
    sim, out = Path(args.sim), Path(args.out)
    results: dict = {"orientation": args.orientation}

    print("Middlebury Motorcycle (scikit-image), disparity search 0..80, block 5, SGBM_3WAY")
    results["middlebury"] = middlebury()

    if not (sim / "truth").is_dir():
        from oblique_city.core.simulate.simulator import SimulationConfig, simulate

        print(f"simulating the default block into {sim} ...")
        simulate(sim, SimulationConfig())
    from oblique_city.core.simulate.truth import load_truth

    truth = load_truth(sim)
    stages = ["aerotri", "dense", "surface"] if args.orientation == "aerotri" else ["dense", "surface"]
    t0 = time.perf_counter()
    if args.workspace:
        ws = Workspace.open(args.workspace)
        results["orientation"] = "workspace " + args.workspace
        stages = [s for s in stages if s in ws.read_state()]
    else:
        ws = setup_workspace(sim, out / "ws", args.orientation, truth)
        ctx = RunContext(executor=Executor("processes", workers=2))
        run_stages(ws, stages, ctx, force=args.force)
        ctx.executor.close()
    state = ws.read_state()
    results["stage_seconds"] = {name: state[name]["seconds"] for name in stages}
    dm, sm = state["dense"]["metrics"], state["surface"]["metrics"]
    results["dense_metrics"], results["surface_metrics"] = dm, sm
    print(f"stages done in {time.perf_counter() - t0:.0f} s")

    # ---- DSM / DTM against truth, on the GT grid's area at our cell size
    dsm = read_geotiff(ws.path("surface", "dsm.tif"))
    dtm = read_geotiff(ws.path("surface", "dtm.tif"))
    from oblique_city.core.simulate.truth import gt_dtm, gt_surface

    rows, cols = dsm.shape
    bbox = np.array([dsm.x0, dsm.y0 - rows * dsm.cell, dsm.x0 + cols * dsm.cell, dsm.y0])
    t_dsm, t_cls, t_bid = gt_surface(truth.city, bbox, dsm.cell)
    t_dtm = gt_dtm(truth.city, bbox, dsm.cell)
    assert t_dsm.shape == dsm.shape, (t_dsm.shape, dsm.shape)
    from scipy import ndimage

    gsd = sm["cell"]
    walls = wall_cells(t_dsm.data) & ndimage.binary_dilation(t_bid.data >= 0)
    near_wall = ndimage.binary_dilation(walls, iterations=2)
    cls = t_cls.data
    classes = {"roofs": np.isin(cls, ROOF) & ~near_wall, "walls": walls,
               "open_ground": np.isin(cls, GROUND) & ~near_wall
               & ~ndimage.binary_dilation(cls == TREE, iterations=4), "aoi": np.ones(cls.shape, bool)}
    tol = 3 * gsd
    results["dsm"] = surface_table(dsm.data, t_dsm.data, classes, tol)
    results["dsm"]["tolerance_m"] = tol
    # which buildings the roof and wall errors come from (a wall cell belongs to the building within 2 cells)
    bid = t_bid.data
    names = {b.id: b.name for b in truth.city.buildings}
    owners = {"roofs": (dsm.data - t_dsm.data, bid),
              "walls": (wall_error(dsm.data, t_dsm.data, walls),
                        ndimage.grey_dilation(np.where(bid >= 0, bid, -1), size=5))}
    results["dsm_by_building"] = {}
    for k, (e, o) in owners.items():
        shares = error_shares(e, classes[k], o)
        rows_k = [{"building": names.get(b, str(b)), **v} for b, v in shares.items()]
        rest = classes[k] & np.isfinite(e) & (o != next(iter(shares), -2))
        results["dsm_by_building"][k] = {"buildings": rows_k,
                                         "rmse_without_largest_m": float(np.sqrt(np.mean(e[rest] ** 2)))}
    results["dtm"] = {"all": height_stats(dtm.data, t_dtm.data, np.ones(cls.shape, bool), 0.3).as_dict(),
                      "open_ground": height_stats(dtm.data, t_dtm.data, classes["open_ground"], 0.3).as_dict()}

    # ---- points against the true mesh
    with np.load(ws.path("dense", "points.npz")) as z:
        pts = {k: z[k] for k in z.files}
    pt = point_truth(truth, pts["xyz"], args.sample)
    idx = pt["index"]
    removed = pts["removed"][idx]
    results["mixed_pixel_filter"] = filter_effect(pt["dist"][removed != 2], removed[removed != 2] == 1)
    results["outlier_filter"] = filter_effect(pt["dist"][removed != 1], removed[removed != 1] == 2)
    kept = removed == 0
    point_classes = np.load(ws.path("surface", "point_classes.npy"))
    kept_index = np.cumsum(pts["removed"] == 0) - 1
    on_surface = pt["dist"] < 0.5
    height = pts["xyz"][idx, 2] - pt["terrain"]
    sem = pt["semantic"]
    is_object = kept & on_surface & (height > 2.0) & (np.isin(sem, ROOF + WALL) | (sem == TREE))
    is_ground = kept & on_surface & np.isin(sem, GROUND) & (height < 0.3)
    pc = np.zeros(len(idx), np.int8)
    pc[kept] = point_classes[kept_index[idx[kept]]]
    results["point_classification"] = classification_shares(pc, is_object, is_ground)
    tree_pts = kept & on_surface & (sem == TREE) & (height > 2.0)
    results["point_classification"]["tree_points_above"] = float((pc[tree_pts] == 1).mean()) if tree_pts.any() \
        else float("nan")
    # ASPRS classes of the classified LAS (kept points, same order) against the true surface each point lies on,
    # inside the surface grid (the area of interest: beyond it raised points have no masks)
    las = read_las(ws.path("surface", "points_classified.laz")).classification
    lc = np.zeros(len(idx), np.uint8)
    lc[kept] = las[kept_index[idx[kept]]]
    p_xy = pts["xyz"][idx, :2]
    in_aoi = (p_xy[:, 0] >= bbox[0]) & (p_xy[:, 0] < bbox[2]) & (p_xy[:, 1] > bbox[1]) & (p_xy[:, 1] <= bbox[3])
    base = kept & on_surface & in_aoi
    truth_sets = {"ground": base & np.isin(sem, GROUND) & (height < 0.3),
                  "roofs": base & np.isin(sem, ROOF) & (height > 2.0),
                  "walls": base & np.isin(sem, WALL) & (height > 2.0),
                  "trees": base & (sem == TREE) & (height > 2.0)}
    expected = {"ground": [LAS_CLASSES["ground"]], "roofs": [LAS_CLASSES["building"]],
                "walls": [LAS_CLASSES["building"]],
                "trees": [LAS_CLASSES["medium_vegetation"], LAS_CLASSES["high_vegetation"]]}
    results["las_classification"] = {
        k: {"points": int(m.sum()), "correct": float(np.isin(lc[m], expected[k]).mean()) if m.any() else float("nan"),
            "classes": {int(v): int(n) for v, n in zip(*np.unique(lc[m], return_counts=True), strict=True)}}
        for k, m in truth_sets.items()}
    every = np.zeros(len(idx), bool)
    for m in truth_sets.values():
        every |= m
    hit = np.zeros(len(idx), bool)
    for k, m in truth_sets.items():
        hit |= m & np.isin(lc, expected[k])
    results["las_classification"]["overall"] = float(hit.sum() / every.sum()) if every.any() else float("nan")
    # facade density: points from oblique masters on true walls, per m2 of wall in the AOI (sample scaled up)
    v = truth.city.vertices
    tri = truth.city.triangles
    is_wall = np.isin(truth.city.semantic, WALL)
    cen = v[tri].mean(axis=1)
    inside = (cen[:, 0] >= bbox[0]) & (cen[:, 0] <= bbox[2]) & (cen[:, 1] >= bbox[1]) & (cen[:, 1] <= bbox[3])
    above = cen[:, 2] > truth.city.terrain_z(cen[:, :2]) + 0.2
    area = 0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1)
    wall_area = float(area[is_wall & inside & above].sum())
    scale = len(pts["xyz"]) / len(idx)
    oblique = pts["view"][idx] > 0
    on_wall = kept & (pt["dist"] < 0.3) & np.isin(sem, WALL)
    results["facades"] = {"wall_area_m2": wall_area,
                          "points_per_m2_oblique": float((on_wall & oblique).sum() * scale / wall_area),
                          "points_per_m2_nadir": float((on_wall & ~oblique).sum() * scale / wall_area),
                          "share_of_wall_points_from_obliques":
                              float((on_wall & oblique).sum() / max(on_wall.sum(), 1))}

    # ---- true ortho: roof edge displacement against a reference ortho from the renderer
    ortho = read_geotiff(ws.path("surface", "ortho.tif")).data
    ref = reference_ortho(truth, dsm)
    edges = walls & np.isin(cls, ROOF)
    shift = roof_edge_displacement(ortho, ref, edges, window=32, search=16)
    results["true_ortho"] = {"edge_windows": int(len(shift)),
                             "median_shift_gsd": float(np.median(shift)) if len(shift) else None,
                             "mean_shift_gsd": float(np.mean(shift)) if len(shift) else None,
                             "p90_shift_gsd": float(np.percentile(shift, 90)) if len(shift) else None,
                             "coverage": float((ortho[..., 3] > 0).mean())}

    # ---- throughput and speed-up
    results["speedup"] = speedup(ws, args.speedup_pairs)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_surface.json").write_text(json.dumps(results, indent=1, default=float))
    print_table(results)
    print(f"\nJSON: {out / 'bench_surface.json'}")


def print_table(r: dict) -> None:
    mb = r["middlebury"]
    print("\n== Middlebury Motorcycle: SGM stage vs plain OpenCV SGBM (same settings)")
    print(f"{'':14}{'bad-2.0 all':>12}{'bad-2.0 matched':>16}{'EPE px':>8}{'coverage':>10}{'s':>7}")
    for k in ("sgm_stage", "plain_sgbm"):
        m = mb[k]
        print(f"{k:14}{m['bad2_all']:12.3f}{m['bad2_matched']:16.3f}{m['epe_matched_px']:8.2f}{m['coverage']:10.3f}"
              f"{m['seconds']:7.2f}")
    gsd = r["surface_metrics"]["cell"]
    print(f"\n== DSM against truth (cell = nadir GSD {gsd:.3f} m; completeness = share within "
          f"{r['dsm']['tolerance_m']:.2f} m; walls: one cell of position tolerance)")
    print(f"{'class':12}{'cells':>8}{'RMSE m':>8}{'RMSE/GSD':>9}{'NMAD m':>8}{'mean m':>8}{'complete':>9}{'filled':>8}")
    for k in ("roofs", "walls", "open_ground", "aoi"):
        s = r["dsm"][k]
        print(f"{k:12}{s['cells']:8d}{s['rmse']:8.3f}{s['rmse'] / gsd:9.2f}{s['nmad']:8.3f}{s['mean']:8.3f}"
              f"{s['completeness']:9.3f}{s['filled']:8.3f}")
    print("   targets: RMSE <= 1.5 GSD, completeness >= 0.90 of the AOI")
    for k, by in r["dsm_by_building"].items():
        rows = by["buildings"]
        if rows:
            print(f"   {k} error by building: " + ", ".join(f"{b['building']} {100 * b['share']:.0f} % (RMSE "
                  f"{b['rmse']:.2f} m)" for b in rows[:3]) + f"; without {rows[0]['building']}: "
                  f"{by['rmse_without_largest_m'] / gsd:.2f} GSD")
    d = r["dtm"]
    print(f"\n== DTM: RMSE {d['all']['rmse']:.3f} m over the AOI, {d['open_ground']['rmse']:.3f} m on open ground "
          "(target <= 0.3 m)")
    c = r["point_classification"]
    print(f"   building/vegetation points classified above: {c['object_above']:.3f} ({c['object_points']} sampled); "
          f"trees alone {c['tree_points_above']:.3f}; ground points on the ground: {c['ground_on']:.3f}")
    lc = r["las_classification"]
    print("   classified LAS (ASPRS codes) against the surface each sampled point lies on, inside the AOI: "
          + ", ".join(f"{k} {lc[k]['correct']:.3f} of {lc[k]['points']}" for k in ("ground", "roofs", "walls", "trees"))
          + f"; overall {lc['overall']:.3f}")
    f = r["facades"]
    print(f"\n== Facades: {f['points_per_m2_oblique']:.1f} points/m2 from oblique masters, "
          f"{f['points_per_m2_nadir']:.1f} from nadir masters ({f['wall_area_m2']:.0f} m2 of wall in the AOI)")
    for name in ("mixed_pixel_filter", "outlier_filter"):
        m = r[name]
        print(f"== {name}: removed {m['removed']} of {m['points']} sampled ({m['removed_share']:.3f}; "
              f"{m['removed_over_1m_share']:.2f} of them > 1 m off); RMSE to the true surface "
              f"{m['before']['rmse']:.3f} -> {m['after']['rmse']:.3f} m, p95 {m['before']['p95']:.3f} -> "
              f"{m['after']['p95']:.3f} m, share > 1 m {m['before']['share_over_1m']:.4f} -> "
              f"{m['after']['share_over_1m']:.4f}")
    t = r["true_ortho"]
    print(f"\n== True ortho: roof edge displacement median {t['median_shift_gsd']:.2f} GSD, "
          f"mean {t['mean_shift_gsd']:.2f}, p90 {t['p90_shift_gsd']:.2f} ({t['edge_windows']} windows; "
          f"target <= 2 GSD); coverage {t['coverage']:.3f}")
    dm, sm = r["dense_metrics"], r["surface_metrics"]
    qa, qp = sm.get("quality_adjusted_mean_m"), sm.get("quality_approx_mean_m")
    print(f"\n== Quality maps: mean forward intersection error {qa:.3f} m with the orientation used "
          f"({r['orientation']}), {qp:.3f} m with the approximate (GNSS/IMU) one")
    s = r["speedup"]
    print(f"\n== Dense matching: {dm['pairs']} pairs, {dm['masters']} masters, {dm['points']} points; "
          f"{dm['matching_mpx_per_s_per_pair']:.2f} Mpx/s per pair (rectified pixels, both directions of the LR check)")
    print(f"   speed-up on {s['pairs']} pairs ({s['megapixels']:.1f} Mpx): {s['seconds_1_process']:.1f} s in 1 "
          f"process with 1 OpenCV thread ({s['mpx_per_s_1_thread']:.2f} Mpx/s), {s['seconds_2_processes']:.1f} s in "
          f"2 processes = x{s['speedup']:.2f}; 1 process with OpenCV's threads "
          f"{s['seconds_1_process_opencv_threads']:.1f} s = x{s['speedup_opencv_threads']:.2f}")
    print(f"   (shared machine: load average {s['load_average_before'][0]:.1f} on {s['cpu_count']} CPUs before the "
          "timing, other agents were running)")
    print(f"   stage seconds: {', '.join(f'{k} {v:.0f}' for k, v in r['stage_seconds'].items())}")


if __name__ == "__main__":
    main()
