"""Matching and triangulation of the rendered demo block from coarse navigation data.

The demo's images are rendered from the true poses; this script moves each exposure's navigation data (all its
heads together) by a random rotation and shift of the given sigmas, as a low-grade GNSS/IMU would, and runs the
``match`` (without least-squares refinement) and ``aerotri`` stages twice: with those sigmas as the images' priors
(each pair whose band they widen beyond twice ``band_px`` corrects its pose from a few matches first,
:mod:`oblique_city.core.matching.navigation`) and without sigmas (the fixed ``band_px`` around the navigation data's
epipolar lines). Prints a table, writes JSON.

    python benchmarks/bench_match_nav.py --simulation demo/simulation --deg 1 --metres 10 --out nav.json

Needs a rendered simulation (``make demo`` or ``oblique-city simulate``).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import numpy as np

from oblique_city.core.geometry.rotations import rotvec_to_matrix
from oblique_city.core.io.formats import read_block
from oblique_city.core.model import ImageBlock, Pose
from oblique_city.core.pipeline import Executor, RunContext, Workspace, run_stages
from oblique_city.core.pipeline.atomic import output_file, write_json
from oblique_city.core.simulate.flight import IMAGE_NAME_PATTERN


def coarse_block(simulation: Path, deg: float, metres: float, seed: int, sigmas: bool) -> ImageBlock:
    """The simulation's block with each exposure's navigation data turned and moved (normal, ``deg`` about each
    axis, ``metres`` along each), and those sigmas as priors when ``sigmas``."""
    block = read_block("bex", simulation / "block.xml", image_root=str(simulation), exposures="name",
                       exposure_pattern=IMAGE_NAME_PATTERN)
    rng = np.random.default_rng(seed)
    exposures: dict[str, list] = {}
    for img in block.images.values():
        exposures.setdefault(img.exposure, []).append(img)
    for images in exposures.values():
        turn = rotvec_to_matrix(np.radians(rng.normal(0.0, deg, 3)))
        shift = rng.normal(0.0, metres, 3)
        centre = np.mean([img.pose_approx.C for img in images], 0)
        for img in images:
            p = img.pose_approx
            img.pose_approx = Pose(p.R @ turn.T, centre + turn @ (p.C - centre) + shift)
            if sigmas:
                img.sigma_position = np.full(3, metres)
                img.sigma_attitude = np.radians(np.full(3, deg))
    return block


def run(simulation: Path, deg: float, metres: float, seed: int, sigmas: bool, workers: int) -> dict:
    """Match and triangulate in a temporary workspace; the stages' metrics."""
    block = coarse_block(simulation, deg, metres, seed, sigmas)
    root = Path(tempfile.mkdtemp(prefix="bench_match_nav_"))
    try:
        ws = Workspace.create(root / "ws", crs=block.crs)
        ws.save_block(block)
        ws.update_stage_options("match", {"lsm_refine": False}, "bench_match_nav")
        ws.update_stage_options("aerotri", {"default_sigma_position": metres, "default_sigma_attitude_deg": deg},
                                "bench_match_nav")
        ws.save_project()
        executor = Executor("processes", workers=workers)
        try:
            records = run_stages(ws, ["match", "aerotri"], RunContext(executor=executor))
        finally:
            executor.close()
        state = ws.read_state()
        return {r.name: {"seconds": r.seconds, **{k: v for k, v in state[r.name].get("metrics", {}).items()
                                                   if not isinstance(v, (dict, list))}} for r in records}
    finally:
        shutil.rmtree(root, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--simulation", default="demo/simulation", type=Path)
    ap.add_argument("--deg", type=float, default=1.0, help="attitude error per axis (1 sigma), degrees")
    ap.add_argument("--metres", type=float, default=10.0, help="position error per axis (1 sigma), metres")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=output_file, help="JSON output (none by default)")
    args = ap.parse_args(argv)
    if not (args.deg > 0 and args.metres > 0):
        ap.error("--deg and --metres must be > 0: they are also the prior sigmas of the run with sigmas")
    rows = {name: run(args.simulation, args.deg, args.metres, args.seed, name == "with sigmas", args.workers)
            for name in ("with sigmas", "without sigmas")}
    print(f"Navigation data off by {args.deg} deg and {args.metres} m per axis (1 sigma, per exposure)")
    print(f"{'variant':18s} {'match s':>8s} {'pairs':>6s} {'corrected':>9s} {'tracks':>8s} {'obs':>8s} {'images':>7s}"
          f" {'sigma0 px':>9s}"
          f" {'check XY m':>10s} {'check Z m':>9s}")
    for name, r in rows.items():
        m, a = r["match"], r["aerotri"]
        print(f"{name:18s} {m['seconds']:8.0f} {m['edges']:6d} {m['corrected_pairs']:9d} {m['tracks']:8d} "
              f"{m['observations']:8d} "
              f"{a['images']:7d} {a['sigma0_px']:9.3f} {a['check_rms_xy_m']:10.3f} {a['check_rms_z_m']:9.3f}")
    if args.out:
        write_json(args.out, {"config": {k: str(v) for k, v in vars(args).items()}, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
