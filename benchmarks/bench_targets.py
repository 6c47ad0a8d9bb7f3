"""Ground point measurement benchmark on a workspace of the simulated city (e.g. the demo's): automatic and clicked.

    python benchmarks/bench_targets.py --workspace demo/workspace            # truth found via the block's image root
    python benchmarks/bench_targets.py --workspace WS --truth SIM/truth --offsets 2,4,6

Against the simulator's truth (true orientations and target centres: the given coordinates carry survey errors),
over the projections of the ground points the simulator marked as targets that it counts in sight (its imported
measurements: visible, 8 px inside the frame):

* automatic: :func:`core.matching.targets.measure_targets` in ``all`` mode from the navigation orientations, as the
  ``match`` stage runs it: found, missed, wrong (more than 1 px from the true projection), RMS and worst error, and
  the measurements made where the simulator sees no target (hidden or at the border);
* refined clicks: an operator's click ``r`` pixels from the true projection in a random direction, refined as
  ``oblique-city measure --refine`` does (:func:`core.matching.manual.set_manual`: the target fitted within
  :data:`core.matching.manual.SNAP_SEARCH_PX` of the click); for every offset of ``--offsets``, over all projections
  in sight and over those the automatic measurement missed;
* the simulator's own measurements (true projections plus its noise) for scale.

Seconds per measurement are printed from the same run. The table is printed and written as JSON (``--out``,
default ``<workspace>/matching/bench_targets.json``).
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT.parent) not in sys.path:
    sys.path.insert(0, str(ROOT.parent))

from oblique_city.core.geometry.projection import project  # noqa: E402
from oblique_city.core.io.photos import camera_bits  # noqa: E402
from oblique_city.core.matching.manual import SNAP_MIN_SCORE, SNAP_SEARCH_PX  # noqa: E402
from oblique_city.core.matching.stage import read_block_grey  # noqa: E402
from oblique_city.core.matching.targets import TargetShape, measure_target, measure_targets  # noqa: E402
from oblique_city.core.pipeline import Workspace  # noqa: E402
from oblique_city.core.pipeline.atomic import output_file, write_json  # noqa: E402
from oblique_city.core.pipeline.executor import Executor  # noqa: E402

WRONG_PX = 1.0
"""A measurement farther than this from the true projection is counted as wrong (a match on something else)."""


def errors_row(label: str, errors: list[float], wanted: int, seconds: float | None = None) -> dict:
    """One table row: measurements found among ``wanted``, wrong ones, RMS and worst of the right ones."""
    e = np.asarray(errors, np.float64)
    ok = e[e <= WRONG_PX]
    return {"case": label, "wanted": wanted, "found": int(len(e)), "wrong": int(np.sum(e > WRONG_PX)),
            "rms_px": round(float(np.sqrt(np.mean(ok**2))), 4) if len(ok) else None,
            "max_px": round(float(ok.max()), 4) if len(ok) else None,
            "seconds_each": None if seconds is None else round(seconds, 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workspace", required=True)
    ap.add_argument("--truth", help="the simulation's truth folder (default: <block image_root>/truth)")
    ap.add_argument("--offsets", default="2,4,6", help="click distances from the true projection, pixels")
    ap.add_argument("--disc-radius", type=float, default=0.5, help="target disc radius, metres")
    ap.add_argument("--square-half", type=float, default=0.8, help="target square half side, metres")
    ap.add_argument("--square-azimuth", default="estimate",
                    help="the squares' azimuth, degrees, or 'estimate' (the match stage's default)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=output_file, help="JSON output (default <workspace>/matching/bench_targets.json)")
    args = ap.parse_args(argv)
    from oblique_city.core.simulate.truth import load_truth

    ws = Workspace.open(args.workspace)
    block = ws.load_block(adjusted=False)
    truth = load_truth(Path(args.truth) if args.truth else Path(block.image_root or ".") / "truth")
    azimuth = None if args.square_azimuth == "estimate" else float(args.square_azimuth)
    if truth.targets.get("pattern", "disc") == "cross":  # the simulation's own cross (oblique-city simulate --targets)
        shape = TargetShape(0.0, float(truth.targets["square_half"]), azimuth, "cross",
                            float(truth.targets["bar_half"]))
    else:
        shape = TargetShape(args.disc_radius, args.square_half, azimuth)
    centres = truth.targets["targets"]  # the targets' true centres (the given coordinates carry survey errors)
    if truth.targets.get("crs") != block.crs:
        raise SystemExit(f"the truth's targets are in {truth.targets.get('crs')}, the block in {block.crs}")
    true_xyz = {name: np.asarray(centres[name], np.float64) for name in block.ground_points if name in centres}

    def true_uv(name: str, iid: str) -> np.ndarray:
        img = truth.block.images[iid]
        return project(truth.block.camera_of(img), img.pose_approx, true_xyz[name][None])[0][0]

    in_sight = [(name, iid) for name, gp in sorted(block.ground_points.items()) if name in true_xyz
                for iid in sorted(gp.observations)]
    simulator = [float(np.hypot(*(block.ground_points[n].observations[i] - true_uv(n, i)))) for n, i in in_sight]

    bits = camera_bits(block)  # the cameras' depths, sampled once for every image read below
    t0 = time.perf_counter()
    with Executor("processes", workers=args.workers) as ex:
        record = measure_targets(block, partial(read_block_grey, block, bits=bits), "all", shape, executor=ex)
    auto_s = time.perf_counter() - t0
    auto, extra, sight = [], [], set(in_sight)
    for name, p in record["points"].items():
        for iid, m in p["measured"].items():  # (a point without a target: every measurement is wrong)
            e = float(np.hypot(*(np.asarray(m["uv"]) - true_uv(name, iid)))) if name in true_xyz else np.inf
            (auto if (name, iid) in sight else extra).append(e)
    measured = {(n, i) for n, p in record["points"].items() for i in p["measured"]}
    missed = [o for o in in_sight if o not in measured]
    n_auto = sum(len(p["measured"]) for p in record["points"].values())
    rows = [errors_row("simulator's measurements", simulator, len(in_sight)),
            errors_row("automatic (in sight)", auto, len(in_sight), auto_s / max(n_auto + len(missed), 1)),
            errors_row("automatic (not in sight, or no target)", extra, 0)]

    rng = np.random.default_rng(args.seed)
    greys: dict[str, np.ndarray] = {}
    for r in [float(x) for x in args.offsets.split(",") if x]:
        for label, cases in (("all in sight", in_sight), ("automatic misses", missed)):
            errors, t0 = [], time.perf_counter()
            for name, iid in cases:
                img = block.images[iid]
                if iid not in greys:
                    greys[iid] = read_block_grey(block, iid, bits)
                a = rng.uniform(0, 2 * np.pi)
                click = true_uv(name, iid) + r * np.array([np.cos(a), np.sin(a)])
                m = measure_target(greys[iid], block.camera_of(img), img.pose_approx, block.ground_points[name].xyz,
                                   shape, SNAP_SEARCH_PX, SNAP_MIN_SCORE, near=click)
                if m is not None:
                    errors.append(float(np.hypot(*(m.uv - true_uv(name, iid)))))
            rows.append(errors_row(f"click {r:g} px off, refined ({label})", errors, len(cases),
                                   (time.perf_counter() - t0) / max(len(cases), 1)))

    hdr = f"{'case':48s} {'wanted':>6s} {'found':>6s} {'wrong':>6s} {'RMS px':>8s} {'max px':>8s} {'s each':>7s}"
    print(f"Ground point measurement on {ws.root}: {len(in_sight)} projections in sight, {len(missed)} missed by the "
          f"automatic measurement; wrong: more than {WRONG_PX:g} px from the true projection")
    print(hdr)
    print("-" * len(hdr))
    for row in rows:
        print(f"{row['case']:48s} {row['wanted']:6d} {row['found']:6d} {row['wrong']:6d} "
              + " ".join(f"{'-' if row[k] is None else format(row[k], '.3f'):>8s}" for k in ("rms_px", "max_px"))
              + f" {'-' if row['seconds_each'] is None else format(row['seconds_each'], '.3f'):>7s}")
    out = args.out or ws.path("matching", "bench_targets.json")
    write_json(out, {"workspace": str(ws.root), "in_sight": len(in_sight),
                     "automatic_missed": [list(o) for o in missed], "rows": rows,
                     "snap_search_px": SNAP_SEARCH_PX, "snap_min_score": SNAP_MIN_SCORE,
                     "args": vars(args)})
    print(f"\nwritten {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
