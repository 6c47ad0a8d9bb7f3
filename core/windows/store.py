"""``windows/windows.json``: the detected windows of a workspace, per building and wall surface.

::

    {"format": "oblique-city-windows", "version": 1, "crs": "EPSG:...",
     "buildings": {"B0001": {"B0001_wall_2": [{"id": "B0001_wall_2_w000", "corners": [[x, y, z] x 4],
                                               "score": 0.9, "source": "blob", "width": 1.1, "height": 1.4}]}},
     "config": {...}, "stats": {...}}

Corners are world coordinates on the wall plane, bottom-left, bottom-right, top-right, top-left (counter-clockwise
seen from outside).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.validate import read_json

FORMAT = "oblique-city-windows"
FORMAT_VERSION = 1


@dataclass(frozen=True, eq=False)
class Window:
    """A detected window: ``id``, the wall ``surface_id`` and ``building_id``, ``corners (4, 3)`` float64 world,
    ``score`` in [0, 1] and ``source`` (``blob``: a dark region; ``grid``: filled in from its row and column)."""

    id: str
    surface_id: str
    building_id: str
    corners: np.ndarray
    score: float
    source: str


def window_record(w: Window) -> dict[str, Any]:
    """The JSON record of one window (corners rounded to 0.1 mm)."""
    c = w.corners
    return {"id": w.id, "corners": np.round(c, 4).tolist(), "score": round(float(w.score), 4), "source": w.source,
            "width": round(float(np.linalg.norm(c[1] - c[0])), 3),
            "height": round(float(np.linalg.norm(c[3] - c[0])), 3)}


def write_windows_json(path: str | Path, windows: list[Window], crs: str, extra: dict[str, Any]) -> None:
    """Write ``windows.json`` atomically (``extra``: config and stats members)."""
    from ..pipeline.atomic import write_json

    tree: dict[str, dict[str, list]] = {}
    for w in windows:
        tree.setdefault(w.building_id, {}).setdefault(w.surface_id, []).append(window_record(w))
    write_json(path, {"format": FORMAT, "version": FORMAT_VERSION, "crs": crs, "buildings": tree, **extra}, indent=None)


def load_windows(path: str | Path) -> list[Window]:
    """Read ``windows/windows.json``."""
    path = Path(path)
    doc = read_json(path, "no windows file (run the 'windows' stage first)")
    if doc.get("format") != FORMAT:
        raise InputError("not an Oblique City windows file", path, field="format")
    out = []
    try:
        for bid, surfaces in doc["buildings"].items():
            for sid, recs in surfaces.items():
                for r in recs:
                    c = np.asarray(r["corners"], np.float64)
                    if c.shape != (4, 3):
                        raise ValueError(f"window {r.get('id')} needs 4 corners of 3 coordinates")
                    out.append(Window(str(r["id"]), sid, bid, c, float(r["score"]), str(r.get("source", "blob"))))
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"malformed windows file ({e})", path, field="buildings") from None
    return out


def windows_by_surface(windows: list[Window]) -> dict[str, list[Window]]:
    """Windows grouped by wall surface id (file order)."""
    out: dict[str, list[Window]] = {}
    for w in windows:
        out.setdefault(w.surface_id, []).append(w)
    return out
