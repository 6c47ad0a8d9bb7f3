"""The wall textures of a workspace: each wall's patch cut from the texture stage's atlas, with its plane frame.

The texture stage samples every planar surface on its own texel grid (:mod:`..texture.plane`: ``e1`` along the
wall, ``e2`` up, row 0 at the top) and packs the grid unchanged into an atlas page at ``rect``; ``textures.json``
keeps the frame (``origin``, ``e1``, ``e2``, ``s0``, ``t1``) and the texel size. Cutting ``rect`` out of the page
therefore gives back the rectified facade, and the frame maps texel coordinates to the wall plane exactly. The
page's seen mask limits the search to the texels an image saw (the texture stage fills the others, e.g. under an
eave, with the wall's colour).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.validate import read_json
from ..texture.plane import texel_grid
from .detect import Detection, WindowOptions, boxes_to_world, detect_windows


@dataclass(frozen=True, eq=False)
class Facade:
    """One rectified wall.

    surface_id, building_id : ids; rgb : (h, w, 3) uint8 texture (row 0 at the top); seen : (h, w) bool texels
    inside the wall ring that an image saw; texel : texel size (m); origin, e1, e2 : (3,) float64 plane frame
    (``e1`` along the wall, ``e2`` up); s0, t1 : plane coordinates of the grid's top-left corner
    """

    surface_id: str
    building_id: str
    rgb: np.ndarray
    seen: np.ndarray
    texel: float
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    s0: float
    t1: float

    def to_world(self, boxes: np.ndarray) -> np.ndarray:
        """3-D corners ``(n, 4, 3)`` of texel boxes ``(n, 4)`` on this wall's plane."""
        return boxes_to_world(boxes, self.origin, self.e1, self.e2, self.s0, self.t1, self.texel)


def detect_facade(facade: Facade, opt: WindowOptions = WindowOptions()) -> tuple[list[Detection], np.ndarray]:
    """Windows of one facade: the detections and their world corners ``(n, 4, 3)``."""
    dets = detect_windows(facade.rgb, facade.seen, facade.texel, opt)
    corners = facade.to_world(np.array([d.box for d in dets], np.float64).reshape(-1, 4))
    return dets, corners


def workspace_facades(textures_json: str | Path, buildings, kinds: tuple[str, ...] = ("wall",)) -> list[Facade]:
    """The facades of ``buildings`` (list of :class:`~..buildings.model.BuildingModel`) textured in
    ``texture/textures.json`` (surfaces of the given kinds; walls must be vertical within 10 degrees)."""
    import cv2

    path = Path(textures_json)
    doc = read_json(path, "no textures file (run the 'texture' stage first)")
    pages: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    out = []
    for b in buildings:
        for s in b.surfaces:
            rec = doc.get("surfaces", {}).get(s.id)
            if s.kind not in kinds or rec is None:
                continue
            try:
                x, y, w, h = (int(v) for v in rec["rect"])
                fr = rec["frame"]
                origin, e1, e2 = (np.asarray(fr[k], np.float64) for k in ("origin", "e1", "e2"))
                texel, s0, t1, page = float(rec["texel"]), float(fr["s0"]), float(fr["t1"]), int(rec["page"])
                files = doc["pages"][page]
                page_file, seen_file = path.parent / files["file"], path.parent / files["seen"]
            except (KeyError, TypeError, ValueError, IndexError) as e:
                raise InputError(f"malformed surface record {s.id} ({e}; rerun the 'texture' stage if the atlas "
                                 "predates seen masks)", path, field="surfaces") from None
            if abs(e2[2]) < np.cos(np.radians(10.0)):
                continue
            if page not in pages:
                img = cv2.imread(str(page_file), cv2.IMREAD_COLOR)
                seen = cv2.imread(str(seen_file), cv2.IMREAD_GRAYSCALE)
                for f, a in ((page_file, img), (seen_file, seen)):
                    if a is None:
                        raise InputError("atlas page missing or unreadable (rerun the 'texture' stage)", f)
                if seen.shape != img.shape[:2]:
                    raise InputError(f"seen mask {seen.shape} does not match its page {img.shape[:2]} (rerun the "
                                     "'texture' stage)", seen_file)
                pages[page] = (img[:, :, ::-1], seen > 0)
            grid = texel_grid(b.vertices[list(s.ring)], texel)
            if grid.shape != (h, w):
                raise InputError(f"surface {s.id}: texel grid {grid.shape} does not match its atlas rect {h}x{w} "
                                 "(buildings changed after texturing: rerun the 'texture' stage)", path, field="rect")
            rgb, seen = pages[page]
            out.append(Facade(s.id, b.id, np.ascontiguousarray(rgb[y:y + h, x:x + w]),
                              grid.mask & seen[y:y + h, x:x + w], texel, origin, e1, e2, s0, t1))
    return out
