"""Texture atlas benchmark on a workspace of the simulated city (e.g. the demo's, with its own aerial triangulation).

    python benchmarks/bench_texture.py --workspace demo/workspace            # truth found via the block's image root
    python benchmarks/bench_texture.py --workspace WS --truth SIM/truth --rerun

Runs the ``texture`` stage if it has not run (or with ``--rerun``), then per surface kind: surfaces wanted and
textured, share of ring texels some image saw, the texture GSD achieved (metres per texel from the atlas UV area
against the 3-D area, :func:`core.evaluate.texture.texture_gsd`) against the block's nadir GSD, and the accuracy
against the simulator's truth (:mod:`core.evaluate.texture`): registration shift between each atlas patch and a
clean rendering of the true city on the same plane (cross-correlation; metres and texels), luminance NCC, and the
colour RMSE after one gain per channel; and the median distance between the reconstructed planes and the true
surfaces with the shift of the surfaces whose plane is within one GSD of the truth (``shift@1GSD``), which separates
the texturing from the geometry it is given. Timing: the stage's seconds and seconds per building. The table is printed
and written as JSON (``--out``, default ``<workspace>/texture/bench_texture.json``).
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
from oblique_city.core.evaluate.texture import colour_rmse, surface_accuracy, texture_gsd  # noqa: E402
from oblique_city.core.pipeline import Workspace  # noqa: E402
from oblique_city.core.pipeline.atomic import output_file, write_json  # noqa: E402
from oblique_city.core.pipeline.context import RunContext  # noqa: E402
from oblique_city.core.pipeline.registry import get_stage  # noqa: E402
from oblique_city.core.texture.atlas import load_textures  # noqa: E402

GROUPS = {"wall": ("wall",), "roof": ("roof",), "overhang": ("overhang_roof", "overhang_fascia",
                                                              "overhang_underside")}
TARGETS = {"share_with_source": 0.9, "gsd_ratio": 1.5, "shift_gsd": 1.0, "ncc": 0.6}
MIN_PEAK = 0.3
"""Surfaces whose patch correlates less than this with the truth at the best shift are not registered."""
"""What a usable atlas should reach: texel share seen, texture GSD / block GSD (walls and roofs), median
registration shift in block GSD, median luminance NCC."""


def block_gsd(ws: Workspace) -> float:
    """Median nadir GSD of the block over the median height of the surface stage's DTM."""
    from oblique_city.core.io.geotiff import read_geotiff
    from oblique_city.core.surface.stage import nadir_gsd

    return nadir_gsd(ws.load_block(), float(np.nanmedian(read_geotiff(ws.path("surface", "dtm.tif")).data)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workspace", required=True)
    ap.add_argument("--truth", help="the simulation's truth folder (default: <block image_root>/truth)")
    ap.add_argument("--rerun", action="store_true", help="run the texture stage even if it ran")
    ap.add_argument("--out", type=output_file, help="JSON output (default <workspace>/texture/bench_texture.json)")
    args = ap.parse_args(argv)
    import cv2

    from oblique_city.core.simulate.render import RenderConfig, Renderer
    from oblique_city.core.simulate.truth import load_truth

    ws = Workspace.open(args.workspace)
    stage_seconds = None
    if args.rerun or not ws.path("texture", "textures.json").exists():
        stage = get_stage("texture")
        t0 = time.perf_counter()
        stage.run(ws, stage.make_config(ws.stage_options("texture")), RunContext())
        stage_seconds = time.perf_counter() - t0
    doc = json.loads(ws.path("texture", "textures.json").read_text())
    tex = load_textures(ws.path("texture", "textures.json"))
    buildings, _ = load_buildings(ws.path("buildings", "buildings.json"))
    pages = [cv2.imread(str(p))[:, :, ::-1] for p, _, _ in tex.pages]
    gsd = block_gsd(ws)
    truth_dir = Path(args.truth) if args.truth else Path(ws.load_block().image_root or ".") / "truth"
    truth = load_truth(truth_dir)
    renderer = Renderer(truth.city, RenderConfig(**truth.config["config"]["render"]))

    t0 = time.perf_counter()
    rows, per_surface, acc_all = [], [], []
    for group, kinds in GROUPS.items():
        surfaces = [(b, s) for b in buildings for s in b.surfaces if s.kind in kinds]
        done = [(b, s) for b, s in surfaces if s.id in tex.surfaces]
        texels = seen = 0
        gsds, acc = [], []
        for b, s in done:
            st = tex.surfaces[s.id]
            rec = doc["surfaces"][s.id]
            ring = b.vertices[list(s.ring)]
            _, w, h = tex.pages[st.page]
            g = texture_gsd(ring, st.uv, (w, h))
            n = rec["rect"][2] * rec["rect"][3]
            gsds.append(g)
            a = surface_accuracy(s.id, s.kind, pages[st.page], rec, ring, renderer)
            if a is not None:
                acc.append(a)
            per_surface.append({"id": s.id, "kind": s.kind, "texture_gsd_m": round(g, 4), "coverage": st.coverage,
                                "sources": len(st.sources),
                                **({"shift_m": round(a.shift_m, 4), "peak": round(a.peak, 3), "ncc": round(a.ncc, 3),
                                    "plane_offset_m": round(a.plane_offset_m, 3)} if a is not None else {})})
            texels += n
            seen += n * st.coverage
        reg = [a for a in acc if np.isfinite(a.shift_m) and a.peak >= MIN_PEAK]
        good = [a.shift_m for a in reg if a.plane_offset_m <= gsd]
        rows.append({
            "kind": group, "surfaces": len(surfaces), "textured": len(done),
            "share_with_source": round(seen / texels, 3) if texels else float("nan"),
            "texture_gsd_m": round(float(np.median(gsds)), 4) if gsds else float("nan"),
            "gsd_ratio": round(float(np.median(gsds)) / gsd, 2) if gsds else float("nan"),
            "compared": len(acc), "registered": len(reg),
            "shift_m": round(float(np.median([a.shift_m for a in reg])), 3) if reg else float("nan"),
            "shift_gsd": round(float(np.median([a.shift_m for a in reg])) / gsd, 2) if reg else float("nan"),
            "plane_offset_m": round(float(np.median([a.plane_offset_m for a in acc])), 3) if acc else float("nan"),
            "good_planes": len(good), "shift_good_m": round(float(np.median(good)), 3) if good else float("nan"),
            "ncc": round(float(np.median([a.ncc for a in acc])), 3) if acc else float("nan"),
            "rmse_dn": round(colour_rmse(acc)[0], 1) if acc else float("nan"),
        })
        acc_all += acc
    eval_seconds = time.perf_counter() - t0
    secs = [v for v in doc["stats"]["seconds_per_building"].values() if v is not None]
    rmse, gains = colour_rmse(acc_all) if acc_all else (float("nan"), np.ones(3))
    summary = {"block_gsd_m": round(gsd, 4), "surfaces_textured": len(tex.surfaces),
               "share_with_source": doc["stats"]["share_with_source"], "pages": len(tex.pages),
               "seconds_per_building_median": round(float(np.median(secs)), 3) if secs else None,
               "seconds_per_building_mean": round(float(np.mean(secs)), 3) if secs else None,
               "stage_seconds": round(stage_seconds, 1) if stage_seconds else None,
               "eval_seconds": round(eval_seconds, 1), "colour_rmse_dn": round(rmse, 1),
               "colour_gain": np.round(gains, 3).tolist(), "targets": TARGETS}

    hdr = (f"{'kind':9s} {'surf':>5s} {'tex':>5s} {'seen':>6s} {'GSD m':>7s} {'/block':>7s} {'cmp':>5s} "
           f"{'reg':>5s} {'shift m':>8s} {'shift GSD':>9s} {'NCC':>6s} {'RMSE DN':>8s} {'plane m':>8s} "
           f"{'good':>5s} {'shift@1GSD':>10s}")
    print(f"Texture atlas on {ws.root} (block nadir GSD {gsd:.3f} m, {len(tex.pages)} pages)")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['kind']:9s} {r['surfaces']:5d} {r['textured']:5d} {r['share_with_source']:6.3f} "
              f"{r['texture_gsd_m']:7.3f} {r['gsd_ratio']:7.2f} {r['compared']:5d} {r['registered']:5d} "
              f"{r['shift_m']:8.3f} {r['shift_gsd']:9.2f} {r['ncc']:6.3f} {r['rmse_dn']:8.1f} "
              f"{r['plane_offset_m']:8.3f} {r['good_planes']:5d} {r['shift_good_m']:10.3f}")
    print(f"all: {summary['surfaces_textured']} surfaces textured, {100 * summary['share_with_source']:.1f}% of "
          f"texels seen, colour RMSE {rmse:.1f} DN; {summary['seconds_per_building_median']} s per building "
          f"(median; mean {summary['seconds_per_building_mean']}), stage {summary['stage_seconds']} s, "
          f"evaluation {summary['eval_seconds']} s")
    out = args.out or ws.path("texture", "bench_texture.json")
    write_json(out, {"summary": summary, "kinds": rows, "surfaces": per_surface})
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
