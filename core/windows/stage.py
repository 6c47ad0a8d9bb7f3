"""The ``windows`` stage: windows detected on every textured wall, written to ``windows/windows.json``.

Reads ``buildings/buildings.json`` and the texture stage's ``texture/textures.json`` with its atlas pages; every
vertical wall's patch is cut from its page (:mod:`.facades`), windows are detected in it (:mod:`.detect`) and
mapped back onto the wall plane as 3-D rectangles with scores (:mod:`.store` describes the file).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from typing import ClassVar

from ..buildings.model import load_buildings
from ..errors import WorkspaceError
from ..pipeline.stage import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    CheckedOptions,
    Range,
    Rule,
    Stage,
    StageResult,
)
from .detect import WindowOptions
from .facades import detect_facade, workspace_facades
from .store import Window, write_windows_json


@dataclass(frozen=True)
class WindowsConfig(WindowOptions, CheckedOptions):
    """Options of the ``windows`` stage (``[stages.windows]`` in project.toml): the detector's
    (:class:`.detect.WindowOptions`) plus min_score : least score of a written window."""

    min_score: float = 0.0

    RULES: ClassVar[dict[str, Rule]] = {
        "min_width": POSITIVE, "max_width": POSITIVE, "min_height": POSITIVE, "max_height": POSITIVE,
        "min_aspect": POSITIVE, "max_aspect": POSITIVE, "min_fill": FRACTION, "background_m": POSITIVE,
        "k_sigma": POSITIVE, "min_contrast": NON_NEGATIVE, "row_tol_m": POSITIVE, "col_tol_m": POSITIVE,
        "size_tol": Range(1.0), "fill_support": AT_LEAST_ONE, "fill_contrast": NON_NEGATIVE,
        "isolated_score": FRACTION, "min_seen": FRACTION, "polarity": ("dark", "bright", "colour", "auto"),
        "bar_m": NON_NEGATIVE, "min_score": FRACTION}
    ORDERED: ClassVar[tuple[tuple[str, str, bool], ...]] = (
        ("min_width", "max_width", False), ("min_height", "max_height", False), ("min_aspect", "max_aspect", False))

    def detector(self) -> WindowOptions:
        """The detector options among these settings."""
        return WindowOptions(**{f.name: getattr(self, f.name) for f in fields(WindowOptions)})


def run(ws, cfg: WindowsConfig, ctx) -> StageResult:
    bpath, tpath = ws.path("buildings", "buildings.json"), ws.path("texture", "textures.json")
    if not bpath.exists():
        raise WorkspaceError(f"{bpath}: no buildings (run the 'buildings' stage)")
    if not tpath.exists():
        raise WorkspaceError(f"{tpath}: no textures (run the 'texture' stage)")
    buildings, _ = load_buildings(bpath)
    facades = workspace_facades(tpath, buildings)
    opt = cfg.detector()
    windows: list[Window] = []
    t0 = time.perf_counter()
    grid = 0
    per_building: dict[str, float] = {}
    for i, f in enumerate(facades):
        ctx.progress(i, len(facades), f"windows on {f.surface_id}")
        t1 = time.perf_counter()
        dets, corners = detect_facade(f, opt)
        per_building[f.building_id] = per_building.get(f.building_id, 0.0) + time.perf_counter() - t1
        k = 0
        for d, c in zip(dets, corners, strict=True):
            if d.score < cfg.min_score:
                continue
            windows.append(Window(f"{f.surface_id}_w{k:03d}", f.surface_id, f.building_id, c, d.score, d.source))
            grid += d.source == "grid"
            k += 1
    ctx.progress(len(facades), len(facades), "windows detected")
    seconds = time.perf_counter() - t0
    with_windows = len({w.surface_id for w in windows})
    stats = {"walls": len(facades), "walls_with_windows": with_windows, "windows": len(windows),
             "grid_filled": grid, "seconds": round(seconds, 3),
             "seconds_per_building": {k: round(v, 4) for k, v in sorted(per_building.items())}}
    write_windows_json(ws.stage_dir("windows") / "windows.json", windows, ws.crs,
                       {"config": asdict(cfg), "stats": stats})
    metrics = {k: v for k, v in stats.items() if k != "seconds_per_building"}
    return StageResult(("windows/windows.json",), metrics,
                       f"{len(windows)} windows on {with_windows} of {len(facades)} textured walls "
                       f"({grid} filled from the facade grid)")


STAGE = Stage(name="windows", run=run, config=WindowsConfig, requires=("buildings", "texture"),
              description="windows detected in the rectified wall textures", version="4")
