"""Window detection in one rectified facade texture: darkness against the wall, components, facade grammar.

A facade texture is a texel grid in the wall's own plane (``x`` along the wall, ``y`` down the rows, as the
texture stage samples it: walls upright). Windows of the kind we model are darker than the wall around them
(glass and the shadowed reveal of a recessed opening) and sit in regular rows (floors) and columns.

1. :func:`darkness_map`: relative darkness ``c = (bg - L) / bg`` of the luminance ``L`` against the wall's own
   local level ``bg`` (a median over ``background_m`` metres of the seen texels, so seams between source images,
   shading gradients and dirt do not count as windows).
2. :func:`candidate_boxes`: adaptive threshold (``k_sigma`` robust standard deviations of the wall's darkness,
   at least ``min_contrast``), glazing bars closed (``bar_m``), connected components, filtered by size in metres,
   aspect and fill; each box is refined to sub-texel edges from the integrals of its row and column profiles
   (:func:`refine_box`).
3. :func:`regularise`: facade grammar. Box centres are clustered into rows (floors) and columns; tops and bottoms
   snap to their row's median, left and right edges to their column's median. Boxes much fainter than the
   facade's windows, boxes of a very different size that no row and column can correct, and boxes with neither a
   row nor a column partner (isolated blobs off the grid) are dropped; a facade with fewer than three candidates
   keeps a lone window only when its own score is strong. An empty cell of the grid is filled only when its row
   and column each hold at least ``fill_support`` windows and the cell itself is dark enough.

Boxes are ``(x0, y0, x1, y1)`` in continuous texel coordinates (texel ``(row j, col i)`` covers
``[i, i+1] x [j, j+1]``), so :func:`boxes_to_world` maps them straight to the wall plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WindowOptions:
    """Detector settings (metres where a length).

    min_width, max_width, min_height, max_height : window size limits (m); min_aspect, max_aspect : height/width;
    min_fill : least share of its box a component covers; background_m : size of the wall-level median (m);
    k_sigma : threshold in robust standard deviations of the wall's darkness; min_contrast : least relative
    darkness for a window texel; grow_m : outward shift of every refined edge (m, e.g. a reveal the texture
    hides); row_tol_m, col_tol_m : clustering tolerance of centres into rows and columns (m); size_tol : allowed
    ratio to the facade's median window width/height; fill_support : windows a row and a column need before their
    empty crossing is filled; fill_contrast : least mean darkness of a filled cell, as a share of the row's median;
    isolated_score : least score a lone window on a facade of fewer than three candidates needs;
    min_seen : least share of seen texels in a box; polarity : ``dark`` (windows darker than the wall), ``bright``
    (lighter), ``colour`` (a different colour, :func:`colour_difference_map`) or ``auto`` (per facade, whichever
    finds the larger score-weighted window area, see :func:`detect_windows`); bar_m : glazing bars (mullions,
    transoms) up to this width (m) are bridged, so a window with a bar is one box and not two panes too narrow
    to count
    """

    min_width: float = 0.5
    max_width: float = 3.0
    min_height: float = 0.6
    max_height: float = 3.0
    min_aspect: float = 0.4
    max_aspect: float = 3.5
    min_fill: float = 0.45
    background_m: float = 3.0
    k_sigma: float = 3.0
    min_contrast: float = 0.12
    grow_m: float = 0.06
    row_tol_m: float = 0.5
    col_tol_m: float = 0.5
    size_tol: float = 1.6
    fill_support: int = 2
    fill_contrast: float = 0.5
    isolated_score: float = 0.8
    min_seen: float = 0.6
    polarity: str = "auto"
    bar_m: float = 0.2


@dataclass(frozen=True)
class Detection:
    """One window in a facade texture: ``box (x0, y0, x1, y1)`` continuous texel coordinates, ``score`` in
    [0, 1], mean relative ``contrast`` inside the box and how it was found (``blob`` or ``grid`` filled)."""

    box: tuple[float, float, float, float]
    score: float
    contrast: float
    source: str = "blob"


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 601 luminance ``(h, w)`` float32 of ``rgb (h, w, 3)`` (any numeric type, 0-255)."""
    rgb = np.asarray(rgb, np.float32)
    return 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


def darkness_map(rgb: np.ndarray, seen: np.ndarray, texel: float, background_m: float = 3.0) -> np.ndarray:
    """Relative darkness ``(h, w)`` float32 of a facade texture against its local wall level.

    Parameters
    ----------
    rgb : (h, w, 3) facade texture; seen : (h, w) bool texels that hold wall colour (inside the surface and seen
    by an image); texel : texel size (m); background_m : side of the median window giving the wall level (m)

    Returns ``(bg - L) / bg`` (0 outside ``seen``), positive where darker than the wall.
    """
    lum = luminance(rgb)
    if not seen.any():
        return np.zeros(lum.shape, np.float32)
    bg = _wall_level(lum, seen, texel, background_m)
    c = (bg - lum) / np.maximum(bg, 8.0)
    return np.where(seen, c, 0.0).astype(np.float32)


def _wall_level(values: np.ndarray, seen: np.ndarray, texel: float, background_m: float) -> np.ndarray:
    """The wall's local level ``(h, w)`` of one 0-255 channel ``values (h, w)``: a median over ``background_m``
    metres (odd, at least 3 texels, at most the texture's size), unseen texels filled with the seen ones' median
    first (``seen`` must hold one)."""
    import cv2

    work = np.where(seen, values, float(np.median(values[seen])))
    k = max(3, int(round(background_m / texel)) | 1)
    k = min(k, 2 * (min(work.shape) // 2) + 1) if min(work.shape) >= 3 else 1
    return cv2.medianBlur(np.clip(work, 0, 255).astype(np.uint8), k).astype(np.float32) if k >= 3 else work


def colour_difference_map(rgb: np.ndarray, seen: np.ndarray, texel: float, background_m: float = 3.0) -> np.ndarray:
    """Colour difference ``(h, w)`` float32 of a facade texture from its local wall colour: CIELAB Delta E
    (1976) against the per-channel median over ``background_m`` metres of the seen texels, less its median over
    the wall, divided by 100 (0 outside ``seen``). Dark glass on dark red brick differs little in luminance (15 %,
    under the darkness threshold) but much in colour."""
    import cv2

    img = np.clip(np.asarray(rgb, np.float32), 0, 255).astype(np.uint8)
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB).astype(np.float32)
    if not seen.any():
        return np.zeros(seen.shape, np.float32)
    diff = np.zeros(seen.shape, np.float32)
    for ch, scale in ((0, 100.0 / 255.0), (1, 1.0), (2, 1.0)):
        diff += ((lab[..., ch] - _wall_level(lab[..., ch], seen, texel, background_m)) * scale) ** 2
    de = np.sqrt(diff)
    # a norm of noisy differences sits above zero on the plain wall: its median is taken off, so that the box
    # refinement integrates the windows' profiles from a zero wall level (else boxes grow by half a texel)
    return np.where(seen, (de - float(np.median(de[seen]))) / 100.0, 0.0).astype(np.float32)


def _extent(profile: np.ndarray, lo: int, hi: int, level: float) -> tuple[float, float]:
    """Sub-texel extent of a dark run ``[lo, hi]`` (texel indices) in a 1-D darkness profile: its width is the
    profile's integral over the run and one texel either side divided by the plateau ``level``, centred on the
    profile's centroid there (exact for an area-sampled step edge of that level; continuous coordinates)."""
    a, b = max(lo - 1, 0), min(hi + 2, len(profile))
    p = profile[a:b].astype(np.float64)
    total = float(p.sum())
    if total <= 0 or level <= 0:
        return float(lo), float(hi + 1)
    centre = a + 0.5 + float((p * np.arange(len(p))).sum()) / total
    half = 0.5 * min(total / level, float(b - a))
    return centre - half, centre + half


def refine_box(dark: np.ndarray, label: np.ndarray, k: int, bbox: tuple[int, int, int, int],
               bars: np.ndarray | None = None) -> tuple[tuple[float, float, float, float], float]:
    """Sub-texel box of component ``k`` and its plateau darkness.

    dark : (h, w) float32 darkness; label : (h, w) int32 component labels; bbox : ``(x, y, w, h)`` integer
    bounding box of the component. The plateau is the median darkness of the component; the extents come from
    the mean column profile over the box's inner rows and the mean row profile over its inner columns
    (:func:`_extent`). ``bars`` : (h, w) bool texels the mask's closing added (glazing bars); the component's
    ones count at the plateau.
    """
    x, y, w, h = bbox
    comp = label == k
    level = float(np.median(dark[comp]))
    if bars is not None:
        dark = np.where(comp & bars, np.maximum(dark, level), dark)
    ry = slice(y + 1, y + h - 1) if h > 2 else slice(y, y + h)
    rx = slice(x + 1, x + w - 1) if w > 2 else slice(x, x + w)
    x0, x1 = _extent(dark[ry, :].mean(0), x, x + w - 1, level)
    y0, y1 = _extent(dark[:, rx].mean(1), y, y + h - 1, level)
    return (x0, y0, x1, y1), level


def candidate_boxes(dark: np.ndarray, seen: np.ndarray, texel: float, opt: WindowOptions) -> list[Detection]:
    """Window candidates of a darkness map: threshold, components, size/aspect/fill filter, sub-texel boxes.

    dark : (h, w) float32 from :func:`darkness_map`; seen : (h, w) bool; texel : texel size (m)
    """
    import cv2

    vals = dark[seen]
    if vals.size < 16:
        return []
    med = float(np.median(vals))
    sigma = 1.4826 * float(np.median(np.abs(vals - med)))
    thr = max(opt.min_contrast, med + opt.k_sigma * sigma)
    mask = ((dark >= thr) & seen).astype(np.uint8)
    bars = None
    if opt.bar_m > 0:  # glazing bars: one window, not two narrow panes
        # closings along rows and along columns fill the gaps between dark texels of up to ``size - 1`` texels,
        # not the notches of an outline
        size = 2 * int(np.ceil(opt.bar_m / (2 * texel))) + 1
        closed = (cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((1, size), np.uint8))
                  | cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((size, 1), np.uint8))) & seen.astype(np.uint8)
        bars, mask = (closed > mask), closed
    n, label, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=4)
    out, cut = [], []
    for k in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[k])
        if w * texel > opt.max_width * 1.3 or h * texel > opt.max_height * 1.3 or area < 4:
            continue
        box, level = refine_box(dark, label, k, (x, y, w, h), bars)
        g = opt.grow_m / texel
        box = (box[0] - g, box[1] - g, box[2] + g, box[3] + g)
        bw, bh = (box[2] - box[0]) * texel, (box[3] - box[1]) * texel
        if not (opt.min_width <= bw <= opt.max_width and opt.min_height <= bh <= opt.max_height):
            continue
        if not opt.min_aspect <= bh / bw <= opt.max_aspect:
            continue
        fill = area / float(w * h)
        if fill < opt.min_fill:
            continue
        seen_share = float(seen[y:y + h, x:x + w].mean())
        if seen_share < opt.min_seen:
            continue
        score = float(np.clip(fill, 0, 1) * np.clip(level / (2.0 * thr), 0, 1))
        out.append(Detection(box, score, level))
        # an edge against texels no image saw (the top under an eave): the window may go on beyond it
        cut.append((y == 0 or seen[y - 1, x:x + w].mean() < 0.5,
                    y + h == seen.shape[0] or seen[y + h, x:x + w].mean() < 0.5))
    return _complete_cut(out, np.array(cut, bool).reshape(-1, 2))


def _complete_cut(dets: list[Detection], cut: np.ndarray) -> list[Detection]:
    """Windows cut by unseen texels (``cut (n, 2)`` bool: top, bottom edge) made as tall as the facade's whole
    windows (the median height of the candidates cut on neither edge, when there are at least two), keeping the
    edge that was seen."""
    whole = ~cut.any(1)
    if whole.sum() < 2:
        return dets
    full = float(np.median([dets[i].box[3] - dets[i].box[1] for i in np.flatnonzero(whole)]))
    out = []
    for d, (top, bottom) in zip(dets, cut, strict=True):
        x0, y0, x1, y1 = d.box
        if y1 - y0 < full and top != bottom:
            y0, y1 = (y1 - full, y1) if top else (y0, y0 + full)
        out.append(Detection((x0, y0, x1, y1), d.score, d.contrast, d.source))
    return out


def _clusters(values: np.ndarray, tol: float) -> np.ndarray:
    """Labels ``(n,)`` of 1-D values chained into clusters where sorted neighbours are within ``tol``."""
    order = np.argsort(values)
    lab = np.empty(len(values), np.int64)
    cur = 0
    for r, i in enumerate(order):
        if r and values[i] - values[order[r - 1]] > tol:
            cur += 1
        lab[i] = cur
    return lab


def regularise(dets: list[Detection], dark: np.ndarray, seen: np.ndarray, texel: float,
               opt: WindowOptions) -> list[Detection]:
    """Facade grammar over candidate windows of one facade (see the module docstring).

    dets : candidates from :func:`candidate_boxes`; dark, seen : (h, w) maps of the same facade
    """
    if len(dets) >= 3:  # contrast consistency: shadows and stains are fainter than the facade's windows
        level = float(np.median([d.contrast for d in dets]))
        dets = [d for d in dets if d.contrast >= opt.fill_contrast * level]
    if not dets:
        return []
    b = np.array([d.box for d in dets], np.float64)
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    typical = np.ones(len(dets), bool)
    if len(dets) >= 3:  # size consistency with the facade's typical window
        mw, mh = np.median(w), np.median(h)
        typical = ((w <= opt.size_tol * mw) & (w >= mw / opt.size_tol) & (h <= opt.size_tol * mh)
                   & (h >= mh / opt.size_tol))
    row = _clusters(0.5 * (b[:, 1] + b[:, 3]), opt.row_tol_m / texel)
    col = _clusters(0.5 * (b[:, 0] + b[:, 2]), opt.col_tol_m / texel)
    nrow, ncol = np.bincount(row), np.bincount(col)

    def edges(lab: np.ndarray, n: int, lo: int, hi: int) -> np.ndarray:
        """Median (lo, hi) edges of every cluster from its typical members (all members when none is)."""
        out = np.zeros((n, 2))
        for k in range(n):
            m = (lab == k) & typical
            m = m if m.any() else lab == k
            out[k] = np.median(b[m, lo]), np.median(b[m, hi])
        return out

    ry, cx = edges(row, len(nrow), 1, 3), edges(col, len(ncol), 0, 2)
    out = []
    occupied = set()
    for i, d in enumerate(dets):
        r, c = row[i], col[i]
        if nrow[r] < 2 and ncol[c] < 2 and (len(dets) >= 3 or d.score < opt.isolated_score):
            continue  # an isolated blob off the facade's grid (a lone window needs a strong score)
        if not typical[i] and (nrow[r] < 2 or ncol[c] < 2):
            continue  # a blob of the wrong size that the grid cannot correct
        box = (cx[c, 0] if ncol[c] >= 2 else d.box[0], ry[r, 0] if nrow[r] >= 2 else d.box[1],
               cx[c, 1] if ncol[c] >= 2 else d.box[2], ry[r, 1] if nrow[r] >= 2 else d.box[3])
        out.append(Detection(tuple(float(v) for v in box), d.score, d.contrast, d.source))
        occupied.add((r, c))
    for r in np.flatnonzero(nrow >= opt.fill_support):
        row_level = float(np.median([d.contrast for i, d in enumerate(dets) if row[i] == r]))
        for c in np.flatnonzero(ncol >= opt.fill_support):
            if (r, c) in occupied:
                continue
            box = (float(cx[c, 0]), float(ry[r, 0]), float(cx[c, 1]), float(ry[r, 1]))
            xa, ya = max(int(np.floor(box[0])), 0), max(int(np.floor(box[1])), 0)
            xb, yb = min(int(np.ceil(box[2])), dark.shape[1]), min(int(np.ceil(box[3])), dark.shape[0])
            if xb - xa < 1 or yb - ya < 1:
                continue
            sv = seen[ya:yb, xa:xb]
            if sv.mean() < opt.min_seen:
                continue
            level = float(dark[ya:yb, xa:xb][sv].mean())
            if level < opt.fill_contrast * row_level:
                continue
            out.append(Detection(box, float(np.clip(0.5 * level / max(row_level, 1e-6), 0, 1)), level, "grid"))
    return out


def _mass(dets: list[Detection]) -> float:
    """Score-weighted window area (texels) of a cue's detections: whole windows outweigh the parts of them (a
    frame, one pane) that a weaker cue finds."""
    return sum(d.score * (d.box[2] - d.box[0]) * (d.box[3] - d.box[1]) for d in dets)


def detect_windows(rgb: np.ndarray, seen: np.ndarray, texel: float,
                   opt: WindowOptions = WindowOptions()) -> list[Detection]:
    """Windows of one facade texture.

    Parameters
    ----------
    rgb : (h, w, 3) facade texture (walls upright: row 0 at the top); seen : (h, w) bool texels inside the wall
    that an image saw; texel : texel size (m)

    With ``opt.polarity`` ``auto`` the facade is searched for dark windows, in its negative (``255 - rgb``) for
    light ones and in its colour difference from the wall, and another cue replaces the darkness when its
    score-weighted window area (:func:`_mass`) is over 1.25 times larger: on dark red brick the dark blue glass
    differs from the wall in colour far more than in luminance (four of the fifteen buildings of the seed-3 city,
    where the darkness alone found 1 of 153 windows), and the darkness finds one pane of a window with a bar.
    """
    if opt.polarity not in ("dark", "bright", "colour", "auto"):
        raise ValueError(f"window polarity '{opt.polarity}': use dark, bright, colour or auto")
    out: list[Detection] = []
    for polarity in ("dark", "bright", "colour"):
        if opt.polarity not in (polarity, "auto"):
            continue
        if polarity == "colour":
            dark = colour_difference_map(rgb, seen, texel, opt.background_m)
        else:
            dark = darkness_map(rgb if polarity == "dark" else 255.0 - np.asarray(rgb, np.float32), seen, texel,
                                opt.background_m)
        found = regularise(candidate_boxes(dark, seen, texel, opt), dark, seen, texel, opt)
        # another cue replaces the darkness only when it finds clearly more window area (a few extra blobs on a
        # light wall are no reason to)
        if _mass(found) > (1.0 if not out or polarity == "dark" else 1.25) * _mass(out):
            out = found
    return out


def boxes_to_world(boxes: np.ndarray, origin: np.ndarray, e1: np.ndarray, e2: np.ndarray, s0: float, t1: float,
                   texel: float) -> np.ndarray:
    """3-D rectangles ``(n, 4, 3)`` on the wall plane of texel boxes ``(n, 4)`` ``(x0, y0, x1, y1)``.

    The plane frame (``origin (3,)``, unit ``e1`` along the wall and ``e2`` up, both ``(3,)``) and the grid's
    top-left plane coordinates ``s0, t1`` are those of the texture stage's texel grid: ``s = s0 + x texel``,
    ``t = t1 - y texel``. Corners run bottom-left, bottom-right, top-right, top-left: counter-clockwise seen from
    the outside (``e1 x e2`` is the outward normal).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    s_lo, s_hi = s0 + boxes[:, 0] * texel, s0 + boxes[:, 2] * texel
    t_hi, t_lo = t1 - boxes[:, 1] * texel, t1 - boxes[:, 3] * texel
    st = np.stack([np.stack([s_lo, t_lo], 1), np.stack([s_hi, t_lo], 1), np.stack([s_hi, t_hi], 1),
                   np.stack([s_lo, t_hi], 1)], axis=1)
    return (np.asarray(origin, np.float64) + st[..., :1] * np.asarray(e1, np.float64)
            + st[..., 1:2] * np.asarray(e2, np.float64))
