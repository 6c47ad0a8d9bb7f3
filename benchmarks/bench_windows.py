"""Window detection benchmark on a workspace of the simulated city, against ``truth/windows.json``.

    python benchmarks/bench_windows.py --workspace demo/workspace          # truth via the block's image root
    python benchmarks/bench_windows.py --workspace WS --truth SIM/truth --no-true-walls

Two runs of the same detector (:mod:`core.windows`):

* ``reconstructed``: the ``windows`` stage on the workspace (its LOD2 walls and the texture stage's atlas), so the
  figures carry the geometry's errors (a wall placed 0.3 m off its true plane shifts the facade's texture by the
  parallax of the viewing direction);
* ``true walls``: the true wall planes of the simulated city, rectified by the texture code (same texel size rule,
  occlusion against the true city mesh) from the images with their TRUE orientation: detection alone.

Per true building and overall: true windows, detections, precision, recall, F1, mean IoU of the matches, corner
RMSE in metres and in nadir GSD (one-to-one matching at IoU >= 0.5 on the same facade plane,
:func:`core.evaluate.windows.window_scores`), and the detector's seconds. Detections of the reconstructed run
are assigned to the true building whose footprint contains their reconstructed building. The tables are printed
and written as JSON (``--out``, default ``<workspace>/windows/bench_windows.json``).
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

from oblique_city.core.buildings.model import load_buildings  # noqa: E402
from oblique_city.core.evaluate.windows import building_of, true_walls, truth_windows, window_scores  # noqa: E402
from oblique_city.core.pipeline import Workspace  # noqa: E402
from oblique_city.core.pipeline.atomic import output_file, write_json  # noqa: E402
from oblique_city.core.pipeline.context import RunContext  # noqa: E402
from oblique_city.core.pipeline.registry import get_stage  # noqa: E402
from oblique_city.core.surface.stage import nadir_gsd  # noqa: E402
from oblique_city.core.windows.detect import WindowOptions  # noqa: E402
from oblique_city.core.windows.facades import Facade, detect_facade  # noqa: E402
from oblique_city.core.windows.store import load_windows  # noqa: E402


def true_wall_facades(truth, sim_root: Path) -> list[Facade]:
    """The true walls rectified from the images with their true orientation (texture stage defaults)."""
    from oblique_city.core.texture.compose import ComposeOptions, choose_texel, texture_surface
    from oblique_city.core.texture.occlusion import OcclusionScene
    from oblique_city.core.texture.sources import ImageCache, block_sources, candidate_sources
    from oblique_city.core.texture.stage import TextureConfig

    cfg = TextureConfig()
    block = truth.block
    block.image_root = str(sim_root)
    sources = block_sources(block)
    city = truth.city
    occluder = OcclusionScene([(city.vertices, city.triangles)], np.floor(city.vertices.min(0)))
    cache = ImageCache(cfg.cache_images)
    opt = ComposeOptions(feather=cfg.feather, occlusion_margin=cfg.occlusion_margin, min_cos=cfg.min_cos)
    out = []
    for k, (bid, ring) in enumerate(true_walls(city)):
        from oblique_city.core.texture.plane import plane_frame

        frame = plane_frame(ring)
        cands = candidate_sources(sources, ring, frame.normal, cfg.max_sources, cfg.min_cos)
        if not cands:
            continue
        st = frame.to_plane(ring)
        extent = float((st.max(0) - st.min(0)).max())
        texel = choose_texel(cands[0][1], cfg.texel_factor, cfg.min_texel, cfg.max_texel, extent,
                             cfg.page_size - 2 * cfg.gutter)
        p = texture_surface(f"T{bid}_wall_{k}", str(bid), ring, texel, [c for c, _ in cands], cache, occluder, opt)
        rgb = np.zeros((*p.grid.shape, 3), np.uint8)
        seen = np.zeros(p.grid.shape, bool)
        has = p.weights.sum(0) > 0
        rgb[p.rows, p.cols] = np.clip(np.rint(p.colours()), 0, 255).astype(np.uint8)
        seen[p.rows[has & p.in_ring], p.cols[has & p.in_ring]] = True
        g = p.grid
        out.append(Facade(p.surface_id, str(bid), rgb, seen, g.texel, g.frame.origin, g.frame.e1, g.frame.e2,
                          g.s0, g.t1))
    return out


def score_rows(dets: dict[int, list[np.ndarray]], truth_by: dict[int, list[np.ndarray]], names: dict[int, str],
               seconds: dict[int, float], gsd: float) -> list[dict]:
    """Per true building and overall: counts and scores."""
    rows = []

    def row(label: str, d: list, t: list, sec: float) -> dict:
        s = window_scores(d, t)
        return {"building": label, "true": s.true_windows, "detections": s.detections, "matched": s.matched,
                "precision": s.precision, "recall": s.recall, "f1": s.f1, "iou": s.iou_mean,
                "corner_rmse_m": s.corner_rmse_m, "corner_rmse_gsd": s.corner_rmse_m / gsd, "seconds": sec}

    for bid in sorted(set(truth_by) | set(dets)):
        rows.append(row(f"{bid} {names.get(bid, '?')}", dets.get(bid, []), truth_by.get(bid, []),
                        seconds.get(bid, 0.0)))
    rows.append(row("all", [x for v in dets.values() for x in v], [x for v in truth_by.values() for x in v],
                    sum(seconds.values())))
    return rows


def print_table(title: str, rows: list[dict]) -> None:
    print(f"\n{title}")
    print(f"{'building':<22}{'true':>5}{'det':>5}{'P':>7}{'R':>7}{'F1':>7}{'IoU':>7}{'RMSE m':>8}{'GSD':>6}{'s':>7}")
    for r in rows:
        f = (lambda v, n=3: "   -" if v != v else f"{v:.{n}f}")  # noqa: E731  (nan as a dash)
        print(f"{r['building']:<22}{r['true']:>5}{r['detections']:>5}{f(r['precision']):>7}{f(r['recall']):>7}"
              f"{f(r['f1']):>7}{f(r['iou']):>7}{f(r['corner_rmse_m']):>8}{f(r['corner_rmse_gsd'], 2):>6}"
              f"{r['seconds']:>7.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workspace", required=True)
    ap.add_argument("--truth", help="the simulation's truth folder (default: <block image_root>/truth)")
    ap.add_argument("--no-true-walls", action="store_true", help="skip the run on the true wall planes")
    ap.add_argument("--out", type=output_file, help="JSON output (default <workspace>/windows/bench_windows.json)")
    args = ap.parse_args(argv)
    from oblique_city.core.simulate.truth import load_truth

    ws = Workspace.open(args.workspace)
    truth_dir = Path(args.truth) if args.truth else Path(ws.load_block().image_root or ".") / "truth"
    truth = load_truth(truth_dir)
    gsd = nadir_gsd(truth.block, float(np.nanmedian(truth.dtm.data)))  # true block over the true DTM
    names = {b.id: b.name for b in truth.city.buildings} | {-1: "no true building"}
    truth_by: dict[int, list[np.ndarray]] = {}
    for w, c in zip(truth.windows["windows"], truth_windows(truth.windows), strict=True):
        truth_by.setdefault(int(w["building"]), []).append(c)

    stage = get_stage("windows")
    cfg = stage.make_config(ws.stage_options("windows"))
    t0 = time.perf_counter()
    res = stage.run(ws, cfg, RunContext())
    stage_s = time.perf_counter() - t0
    doc = json.loads(ws.path("windows", "windows.json").read_text())
    buildings, _ = load_buildings(ws.path("buildings", "buildings.json"))
    to_true = {b.id: building_of(b.vertices[:, :2].mean(0), truth.footprints) for b in buildings}
    to_true = {k: -1 if v is None else v for k, v in to_true.items()}  # -1: no true building (false detection)
    dets: dict[int, list[np.ndarray]] = {}
    for w in load_windows(ws.path("windows", "windows.json")):
        dets.setdefault(to_true.get(w.building_id, -1), []).append(w.corners)
    secs: dict[int, float] = {}
    for bid, s in doc["stats"]["seconds_per_building"].items():
        secs[to_true.get(bid, -1)] = secs.get(to_true.get(bid, -1), 0.0) + s
    rec_rows = score_rows(dets, truth_by, names, secs, gsd)
    print(f"nadir GSD {gsd:.3f} m; windows stage {stage_s:.2f} s: {res.message}")
    print_table("reconstructed walls (workspace LOD2 + texture atlas)", rec_rows)
    out = {"workspace": str(ws.root), "truth": str(truth.folder), "gsd_m": gsd, "stage_seconds": stage_s,
           "config": doc["config"], "reconstructed": rec_rows}
    if not args.no_true_walls:
        t0 = time.perf_counter()
        facades = true_wall_facades(truth, truth.folder.parent)
        rect_s = time.perf_counter() - t0
        opt = cfg.detector() if hasattr(cfg, "detector") else WindowOptions()
        tdets: dict[int, list[np.ndarray]] = {}
        tsecs: dict[int, float] = {}
        for f in facades:
            t1 = time.perf_counter()
            _, corners = detect_facade(f, opt)
            tsecs[int(f.building_id)] = tsecs.get(int(f.building_id), 0.0) + time.perf_counter() - t1
            tdets.setdefault(int(f.building_id), []).extend(corners)
        true_rows = score_rows(tdets, truth_by, names, tsecs, gsd)
        print_table(f"true walls ({len(facades)} walls rectified with the true orientation in {rect_s:.1f} s)",
                    true_rows)
        out["true_walls"] = true_rows
        out["true_walls_rectify_seconds"] = rect_s
    path = args.out or ws.path("windows", "bench_windows.json")
    write_json(path, out)
    print(f"\nwritten {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
