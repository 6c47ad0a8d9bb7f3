"""Atlas pages: shelf packing of surface patches, gutters filled by edge dilation, UVs, ``textures.json``.

Patches are packed as axis-aligned rectangles (never rotated or scaled, so one texel stays one texel) with a gutter
of ``gutter`` texels on every side, tallest first, in shelves across pages of at most ``page_size`` texels; a page
is then trimmed to the smallest power-of-two size that holds its shelves. Ring texels no image sees take the
wall's local colour (:func:`hole_colours`); every other atlas pixel that no surface texel covers (gutters,
free space) takes the colour of the nearest covered texel, so bilinear filtering and mip-mapping never pull in
background colour. A grey page beside each (``seen``) marks the texels an image saw.

UVs follow OBJ / CityGML / CityJSON: ``u`` to the right and ``v`` up, both in [0, 1] of the page, texel centres at
half-texel positions (``u = x / width``, ``v = 1 - y / height`` with ``x, y`` continuous texel coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ComputationError, InputError
from ..io.validate import read_json

FORMAT = "oblique-city-textures"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class Placement:
    """Where a patch of ``(rows, cols)`` texels sits: page index and the top-left texel ``(x, y)`` of the patch
    (inside its gutter)."""

    page: int
    x: int
    y: int


def pack_shelves(sizes: list[tuple[int, int]], page_size: int, gutter: int) -> tuple[list[Placement],
                                                                                    list[tuple[int, int]]]:
    """Shelf packing of patch sizes ``(rows, cols)``.

    Returns the placement of each patch (input order) and each page's size ``(width, height)``, powers of two.
    """
    order = sorted(range(len(sizes)), key=lambda i: (-sizes[i][0], -sizes[i][1]))
    place: list[Placement | None] = [None] * len(sizes)
    pages: list[list[int]] = []  # per page: [shelf y, shelf height, cursor x, used width, used height]
    for i in order:
        h, w = sizes[i][0] + 2 * gutter, sizes[i][1] + 2 * gutter
        if h > page_size or w > page_size:
            raise ComputationError(f"a patch of {sizes[i][1]}x{sizes[i][0]} texels does not fit a {page_size} page")
        target = None
        for k, st in enumerate(pages):
            if st[2] + w <= page_size and st[0] + max(st[1], h) <= page_size and (h <= st[1] or st[2] == 0):
                target = k
                break
            if st[0] + st[1] + h <= page_size:  # open a new shelf on this page
                st[0], st[1], st[2] = st[0] + st[1], 0, 0
                target = k
                break
        if target is None:
            pages.append([0, 0, 0, 0, 0])
            target = len(pages) - 1
        p, st = target, pages[target]
        place[i] = Placement(p, st[2] + gutter, st[0] + gutter)
        st[1] = max(st[1], h)
        st[2] += w
        st[3] = max(st[3], st[2])
        st[4] = max(st[4], st[0] + st[1])
    size = [(_pow2(st[3]), _pow2(st[4])) for st in pages]
    return [p for p in place if p is not None], size


def _pow2(n: int) -> int:
    return 1 << max(int(np.ceil(np.log2(max(n, 1)))), 2)


def fill_empty(rgb: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Give every uncovered pixel of ``rgb (h, w, 3)`` the colour of the nearest covered one (``covered (h, w)``
    bool); an all-empty page stays as it is."""
    from scipy.ndimage import distance_transform_edt

    if covered.all() or not covered.any():
        return rgb
    _, (iy, ix) = distance_transform_edt(~covered, return_indices=True)
    return rgb[iy, ix]


def hole_colours(col: np.ndarray, has: np.ndarray, rows: np.ndarray, cols: np.ndarray, texel: float,
                 size_m: float = 3.0) -> np.ndarray:
    """Colours ``(n, 3)`` for the texels of one surface that no image sees: the local wall colour, a median over
    ``size_m`` metres of the texture with every unseen texel first given its nearest seen colour. The nearest
    colour alone would stretch a window under an eave up to the roof; the median keeps the shade of the wall
    around the hole and drops the windows (they cover less than half of a wall).

    col : (n, 3) float32 texel colours; has : (n,) bool seen by an image (one at least); rows, cols : (n,) int
    texel positions in the surface's grid; texel : texel size (m)
    """
    import cv2

    h, w = int(rows.max()) + 1, int(cols.max()) + 1
    img = np.zeros((h, w, 3), np.float32)
    seen = np.zeros((h, w), bool)
    img[rows[has], cols[has]] = col[has]
    seen[rows[has], cols[has]] = True
    filled = np.clip(np.rint(fill_empty(img, seen)), 0, 255).astype(np.uint8)
    k = max(3, int(round(size_m / texel)) | 1)
    k = min(k, 2 * ((min(h, w) - 1) // 2) + 1)
    out = cv2.medianBlur(filled, k) if k >= 3 else filled
    return out[rows, cols].astype(np.float32)


def ring_uv(ring_xy: np.ndarray, place: Placement, page_size: tuple[int, int]) -> np.ndarray:
    """UVs ``(k, 2)`` of ring vertices from their continuous texel coordinates ``(k, 2)`` in the patch."""
    w, h = page_size
    return np.stack([(place.x + ring_xy[:, 0]) / w, 1.0 - (place.y + ring_xy[:, 1]) / h], axis=1)


def write_textures_json(path: str | Path, doc: dict[str, Any]) -> None:
    """Write ``textures.json`` atomically (``doc`` as built by the texture stage)."""
    from ..pipeline.atomic import write_json

    write_json(path, {"format": FORMAT, "version": FORMAT_VERSION, **doc}, indent=None)


@dataclass(frozen=True)
class SurfaceTexture:
    """The texture of one surface: atlas page index, UV per ring vertex ``(k, 2)``, texel size (m), the
    contributing images with their shares and the share of texels some image saw."""

    surface_id: str
    building_id: str
    page: int
    uv: np.ndarray
    texel: float
    sources: dict[str, float]
    coverage: float


@dataclass(frozen=True)
class TextureSet:
    """A workspace's textures: page image files (absolute paths) with sizes, and textures by surface id."""

    pages: list[tuple[Path, int, int]]
    surfaces: dict[str, SurfaceTexture]


def load_textures(path: str | Path) -> TextureSet:
    """Read ``texture/textures.json``; page files are resolved beside it."""
    path = Path(path)
    doc = read_json(path, "no textures file (run the 'texture' stage first)")
    if doc.get("format") != FORMAT:
        raise InputError("not an Oblique City textures file", path, field="format")
    try:
        pages = [(path.parent / p["file"], int(p["width"]), int(p["height"])) for p in doc["pages"]]
        surfaces = {sid: SurfaceTexture(sid, str(s["building"]), int(s["page"]),
                                        np.asarray(s["uv"], np.float64).reshape(-1, 2), float(s["texel"]),
                                        {k: float(v) for k, v in s["sources"].items()}, float(s["coverage"]))
                    for sid, s in doc["surfaces"].items()}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"malformed textures file ({e})", path, field=str(e) if isinstance(e, KeyError) else None
                         ) from None
    for s in surfaces.values():
        if not 0 <= s.page < len(pages):
            raise InputError(f"surface {s.surface_id} refers to page {s.page}", path, field="page")
    return TextureSet(pages, surfaces)
