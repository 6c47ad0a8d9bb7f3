"""Simulator benchmark: render the default block (or a variant) and print the figures of the issue.

    python benchmarks/bench_simulate.py                    # the default block (125 images, 1.47 MP each)
    python benchmarks/bench_simulate.py --size 800x600     # smaller images
    python benchmarks/bench_simulate.py --workers 1

Table 1: images, megapixels, render wall seconds, render CPU seconds (this process and its workers), images/s,
and the machine's 1-minute load average during the run (the machine is shared: wall time grows with the load,
CPU seconds much less). Table 2: coverage per view (median rays per ground cell, share of cells with >= 2 and
>= 3 images). Table 3: matchability of the textures: SIFT keypoints per image and matches between image pairs of
the same head (next exposure), with the share of matches that agree with the ground-truth geometry to 2 px
(the point of the first image's GT depth, projected into the second image).

Writes everything as JSON (``--json``, default ``<out>/bench_simulate.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT.parent) not in sys.path:
    sys.path.insert(0, str(ROOT.parent))

from oblique_city.core.geometry.projection import backproject_depth, project  # noqa: E402
from oblique_city.core.matching.features import sift_features  # noqa: E402
from oblique_city.core.simulate.render import Renderer  # noqa: E402
from oblique_city.core.simulate.simulator import SimulationConfig, simulate  # noqa: E402
from oblique_city.core.simulate.truth import load_truth  # noqa: E402


def sift_pairs(out: Path, n_pairs: int = 2) -> list[dict]:
    """SIFT matches between consecutive exposures of each head, checked against the true geometry."""
    import cv2

    truth = load_truth(out)
    block = truth.block
    renderer = Renderer(truth.city)
    rows = []
    by_head: dict[str, list[str]] = {}
    for iid, img in block.images.items():
        by_head.setdefault(img.head, []).append(iid)
    for head, ids in by_head.items():
        mid = len(ids) // 4
        for a, b in [(ids[mid + k], ids[mid + k + 1]) for k in range(n_pairs)]:
            ia, ib = block.images[a], block.images[b]
            ga = cv2.imread(str(out / ia.file), cv2.IMREAD_GRAYSCALE)
            gb = cv2.imread(str(out / ib.file), cv2.IMREAD_GRAYSCALE)
            ka, da = sift_features(ga, 8000)
            kb, db = sift_features(gb, 8000)
            m = cv2.BFMatcher().knnMatch(da, db, k=2)
            good = [x[0] for x in m if len(x) == 2 and x[0].distance < 0.8 * x[1].distance]
            ua = ka[[g.queryIdx for g in good]].reshape(-1, 2)
            ub = kb[[g.trainIdx for g in good]].reshape(-1, 2)
            cam_a, cam_b = block.camera_of(ia), block.camera_of(ib)
            depth, _ = renderer.trace(cam_a, ia.pose_approx)
            r = np.clip(np.rint(ua).astype(int), 0, [cam_a.width - 1, cam_a.height - 1])
            z = depth[r[:, 1], r[:, 0]].astype(np.float64)
            ok = np.isfinite(z)
            xyz = backproject_depth(cam_a, ia.pose_approx, ua[ok], z[ok])
            uvb, _ = project(cam_b, ib.pose_approx, xyz)
            err = np.linalg.norm(uvb - ub[ok], axis=1)
            rows.append({"head": head, "pair": [a, b], "keypoints": [len(ka), len(kb)], "matches": len(good),
                         "gt_inliers_2px": int(np.sum(err < 2.0)),
                         "inlier_share": float(np.mean(err < 2.0)) if len(err) else float("nan"),
                         "median_error_px": float(np.median(err[err < 2.0])) if np.any(err < 2.0) else float("nan")})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", help="simulation folder (default: a temporary folder)")
    ap.add_argument("--size", help="image size WxH (default 1400x1050)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--preset", default="penta", choices=("penta", "three-head"))
    ap.add_argument("--json", help="JSON output path")
    args = ap.parse_args()
    cfg = replace(SimulationConfig(), workers=args.workers, system=args.preset)
    if args.size:
        w, _, h = args.size.partition("x")
        cfg = replace(cfg, width=int(w), height=int(h))
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_sim_"))
    t0 = time.perf_counter()
    s = simulate(out, cfg)
    print(f"\nSimulated block in {out} ({time.perf_counter() - t0:.1f} s in all)\n")
    print("| images | Mpx total | Mpx/image | render s (wall) | render CPU s | images/s | workers | load avg |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {s['images']} | {s['megapixels']:.1f} | {s['megapixels'] / s['images']:.2f} | "
          f"{s['render_seconds']:.1f} | {s['render_cpu_seconds']:.1f} | {s['images_per_second']:.2f} | "
          f"{s['workers']} | {s['load_average_1min']:.1f} |")
    print("\n| view | images | median images per cell | cells >= 2 | cells >= 3 |")
    print("|---|---:|---:|---:|---:|")
    import oblique_city.core.io.geotiff as gt

    cov = gt.read_geotiff(out / "truth" / "coverage.tif").data.reshape(-1, 5)
    cover = {}
    for k, v in enumerate(("nadir", "north", "east", "south", "west")):
        cover[v] = {"images": s["views"][v], "median": float(np.median(cov[:, k])),
                    "ge2": float(np.mean(cov[:, k] >= 2)), "ge3": float(np.mean(cov[:, k] >= 3))}
        c = cover[v]
        print(f"| {v} | {c['images']} | {c['median']:.0f} | {c['ge2']:.0%} | {c['ge3']:.0%} |")
    pairs = sift_pairs(out)
    print("\n| head | pair | keypoints | matches (ratio 0.8) | GT-consistent (< 2 px) | share | median err px |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in pairs:
        print(f"| {r['head']} | {r['pair'][0]} / {r['pair'][1]} | {r['keypoints'][0]} / {r['keypoints'][1]} | "
              f"{r['matches']} | {r['gt_inliers_2px']} | {r['inlier_share']:.0%} | {r['median_error_px']:.2f} |")
    result = {"summary": s, "coverage": cover, "sift_pairs": pairs, "config": {"size": [cfg.width, cfg.height],
                                                                                "workers": cfg.workers,
                                                                                "preset": cfg.system}}
    path = Path(args.json) if args.json else out / "bench_simulate.json"
    path.write_text(json.dumps(result, indent=1))
    print(f"\nJSON: {path}")


if __name__ == "__main__":
    main()
