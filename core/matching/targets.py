"""Automatic measurement of signalised ground points (control and check targets) in the images.

A signalised target (:class:`TargetShape`) is a bright disc centred on a dark square laid on the ground (the usual
panel target; the simulator's are a 0.5 m disc on a 1.6 m square, its sides along the grid), a bright disc alone, a
bright square alone (painted on the asphalt), a checkerboard square (two by two fields, measured at its crossing)
or a bright cross (two bars crossing at its centre). A square (a cross) may lie at any azimuth, given or estimated.
For each ground point and each image where its projection from the approximate orientation falls inside the frame:

1. the target is rendered as the image sees it from that orientation (:func:`render_target`): each pixel's shares
   of the square and of the disc (of a checkerboard: of two opposite fields), from the cut of its ray with the
   horizontal plane through the point; a pixel's grey value is modelled as ``c0 + c1 square + c2 disc`` (ground,
   square and disc levels unknown: any exposure);
2. that model is fitted to the image at every integer shift up to ``search_px`` (the error of the navigation
   data's prediction) over the pixels of the target and a two-pixel ring around it, and the best fit (multiple
   correlation, with the innermost element brighter than the ground) is taken;
3. a square of unknown azimuth is turned there to the best fit of :data:`AZIMUTH_STEPS` (a square repeats every 90
   degrees), then of five steps a quarter as wide around it, refined by a parabola through the best and its
   neighbours;
4. from there, least-squares template matching refines the shift (sub-pixel) with the levels, the target rendered
   again at each shifted position (the ellipse an oblique view makes of the disc stays exact); an estimated azimuth
   is estimated again at the sub-pixel position and the fit repeated;
5. the measurement is the predicted position plus that shift, kept when the final correlation reaches
   ``min_score`` (an occluded or missing target does not) with the innermost element (the disc, or a square alone)
   brighter than what surrounds it (a square under a disc may be no darker than the asphalt under it; a
   checkerboard's fields may be either way round), with its standard deviation from the fit.

The shape is the template's: a perspective view is rendered, not assumed round, so the position is that of the
disc's centre itself (the centroid of an oblique ellipse is not).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.projection import intersect_with_plane_z, project
from ..model import CameraModel, ImageBlock, Pose

TARGETS_FILE = "matching/targets.json"
"""Where the ``match`` stage writes the :func:`measure_targets` record, which the ``aerotri`` stage applies."""

TARGET_MODES = ("none", "missing", "all")
"""``none``: keep the imported measurements; ``missing``: measure every point in every image, and adjust with the
imported measurements where there are some and with the measured ones where the import has none (the imported ones
are checked against the measured ones: :func:`target_summary`); ``all``: adjust with the measured ones only."""

RING_PX = 2
"""Pixels of ground around the target's square that the fit takes (the ground level for the pixels the square's
edges cross). On the demo one pixel found one more target (167 of the 171 in sight against 166) but let a wrong match
reach a correlation of 0.81; with two the wrong ones stay below 0.75, well under the 0.9 a measurement needs."""

SUSPECT_PX = 1.0
"""An imported measurement more than this many pixels from the target measured in the same image is counted as
suspect (:func:`target_summary`): a manual measurement on the wrong spot or of the wrong point, or a target matched
wrongly."""


AZIMUTH_STEPS = 6
"""Azimuths of a square tried when its azimuth is estimated: every 15 degrees of the 90 after which a square repeats.
A square 7.5 degrees off (the most between two steps) lowers the fit's correlation by about 0.01 (rendered views of a
disc on a square); the parabola through the best step and its neighbours comes closer."""


PATTERNS = ("disc", "checker", "cross")
"""Target patterns (:class:`TargetShape`): a disc on a square (or either alone), a checkerboard square, a bright
cross."""


@dataclass(frozen=True)
class TargetShape:
    """A target level on the ground. ``pattern`` ``disc``: a bright disc of ``disc_radius_m`` on a dark square of
    half side ``square_half_m``; without a square (``square_half_m = 0``) a bright disc on the ground, without a disc
    (``disc_radius_m = 0``) a bright square. ``checker``: a square of half side ``square_half_m`` in two by two
    fields, opposite ones alike (no disc: ``disc_radius_m = 0``). ``cross``: two bright bars crossing at the centre
    along the square's axes, each reaching ``square_half_m`` from it and ``bar_half_m`` wide on either side of its
    axis (no disc). ``square_azimuth_deg``: the direction of the square's sides (a cross's bars), degrees
    counterclockwise from the grid's x axis (east), or None when unknown (estimated in each image)."""

    disc_radius_m: float = 0.5
    square_half_m: float = 0.8
    square_azimuth_deg: float | None = 0.0
    pattern: str = "disc"
    bar_half_m: float = 0.0

    def __post_init__(self) -> None:
        ok = (self.disc_radius_m >= 0 and self.square_half_m >= 0 and max(self.disc_radius_m, self.square_half_m) > 0
              and (self.square_half_m == 0 or self.disc_radius_m < self.square_half_m))
        if self.pattern not in PATTERNS:
            raise ConfigError(f"target shape: pattern '{self.pattern}' (use one of {', '.join(PATTERNS)})")
        if self.pattern == "checker":
            ok = self.square_half_m > 0 and self.disc_radius_m == 0
        if self.pattern == "cross":
            ok = self.square_half_m > self.bar_half_m > 0 and self.disc_radius_m == 0
        elif self.bar_half_m != 0:
            ok = False
        if not ok:
            raise ConfigError(f"target shape: disc radius {self.disc_radius_m} m, square half side "
                              f"{self.square_half_m} m, bar half width {self.bar_half_m} m (a disc, a square or a disc "
                              "inside a square; a checkerboard square without a disc; a cross's bars narrower than "
                              "they are long, without a disc)")
        if self.square_azimuth_deg is not None and not np.isfinite(self.square_azimuth_deg):
            raise ConfigError(f"target shape: square azimuth {self.square_azimuth_deg} is not a number")

    @property
    def columns(self) -> tuple[bool, bool]:
        """Whether the grey-value model has a square level and an inner one (the disc, a checkerboard's fields or the
        cross)."""
        if self.pattern == "cross":
            return False, True
        return self.square_half_m > 0, self.disc_radius_m > 0 or self.pattern == "checker"


@dataclass(frozen=True)
class TargetMeasurement:
    """One target measured in one image: ``uv`` (2,) pixels (centre of the top-left pixel at 0, 0), ``predicted``
    (2,) from the approximate orientation, ``score`` the multiple correlation of the final fit (the grey-value model
    against the image), ``std_px`` the standard deviation of the position from the fit (the larger axis),
    ``azimuth_deg`` the square's azimuth the fit took (0 to 90; None without a square)."""

    uv: np.ndarray
    predicted: np.ndarray
    score: float
    std_px: float
    azimuth_deg: float | None = None


def render_target(camera: CameraModel, pose: Pose, centre: np.ndarray, shape: TargetShape, u: np.ndarray,
                  v: np.ndarray, azimuth_deg: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The target as the image sees it at pixels ``u``, ``v`` (any equal shapes, floats): the shares of each pixel on
    the square and on the inner element, ``(square, inner)`` (zeros for an element the shape does not have): the disc,
    of a checkerboard the fields in the square's first and third quadrants, or the cross. The square's sides lie at
    ``azimuth_deg`` (the shape's own when None; 0 when the shape's is unknown).

    A pixel's share of a shape is ``0.5 + s`` clipped to 0..1, with ``s`` the signed distance of the pixel's centre
    from the shape's edge in pixels (the ground distance over the rate at which it changes across the image, from the
    ray's cut with the ground plane and its derivatives): an edge crossing a pixel covers it in proportion, and the
    shares change smoothly with the target's position, which the least-squares fit needs. The square's share is the
    product of its two sides' (exact but at the corners); a checkerboard field's, the product of the shares on the
    two half-planes through the centre that bound it, within the square; a cross's, that of its two bars (each a
    rectangle, as the square) less their overlap."""
    shp = np.shape(u)
    uv = np.column_stack([np.ravel(u), np.ravel(v)]).astype(np.float64)
    z = float(centre[2])
    step = 0.5
    g = intersect_with_plane_z(camera, pose, uv, z)[:, :2] - np.asarray(centre, np.float64)[:2]
    gu = (intersect_with_plane_z(camera, pose, uv + [step, 0.0], z)[:, :2] - centre[:2] - g) / step
    gv = (intersect_with_plane_z(camera, pose, uv + [0.0, step], z)[:, :2] - centre[:2] - g) / step

    def share(dist: np.ndarray, grad_u: np.ndarray, grad_v: np.ndarray) -> np.ndarray:
        """Share inside ``dist >= 0`` (metres) with its derivatives along the image axes (metres per pixel)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.clip(0.5 + dist / np.hypot(grad_u, grad_v), 0.0, 1.0)

    az = np.radians(azimuth_deg if azimuth_deg is not None else shape.square_azimuth_deg or 0.0)
    turn = np.array([[np.cos(az), np.sin(az)], [-np.sin(az), np.cos(az)]])  # grid -> the square's axes
    ga, gua, gva = g @ turn.T, gu @ turn.T, gv @ turn.T

    def band(half: float, ax: int) -> np.ndarray:
        """Share within ``half`` of the centre along the square's axis ``ax``."""
        sign = np.sign(ga[:, ax])
        return share(half - np.abs(ga[:, ax]), -sign * gua[:, ax], -sign * gva[:, ax])

    sides = [band(shape.square_half_m, ax) for ax in range(2)]
    if shape.pattern == "cross":
        # each bar within its length along its axis and within its width across it
        bars = [sides[ax] * band(shape.bar_half_m, 1 - ax) for ax in range(2)]
        cross = bars[0] + bars[1] - bars[0] * bars[1]
        return np.zeros(shp), np.nan_to_num(cross).reshape(shp)
    square = sides[0] * sides[1] if shape.square_half_m > 0 else np.zeros(len(g))
    if shape.pattern == "checker":
        half_x, half_y = (share(ga[:, ax], gua[:, ax], gva[:, ax]) for ax in range(2))  # shares on x >= 0, y >= 0
        fields = square * (half_x * half_y + (1.0 - half_x) * (1.0 - half_y))
        return np.nan_to_num(square).reshape(shp), np.nan_to_num(fields).reshape(shp)
    r = np.hypot(g[:, 0], g[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        nx, ny = g[:, 0] / r, g[:, 1] / r
    disc = share(shape.disc_radius_m - r, -(nx * gu[:, 0] + ny * gu[:, 1]), -(nx * gv[:, 0] + ny * gv[:, 1]))
    return np.nan_to_num(square).reshape(shp), np.nan_to_num(disc).reshape(shp)


def _design(camera: CameraModel, pose: Pose, centre: np.ndarray, shape: TargetShape, u: np.ndarray,
            v: np.ndarray, azimuth_deg: float | None = None) -> np.ndarray:
    """The grey-value model's design ``(n, k)`` at pixels ``u``, ``v`` ``(n,)``: background, then square and inner
    element as the shape has them (a pixel's grey value is ``c0 + c1 square + c2 inner``, with its shares on them)."""
    sq, inner = render_target(camera, pose, centre, shape, u, v, azimuth_deg)
    has = shape.columns
    return np.column_stack([np.ones_like(sq)] + [x for x, h in zip((sq, inner), has, strict=True) if h])


def _brighter_inside(c: np.ndarray, shape: TargetShape) -> np.ndarray:
    """Whether fitted levels ``c (k, ...)`` (:func:`_design`'s order) make the innermost element brighter than what
    surrounds it: the disc than the square and the ground (a square may be as dark as the asphalt), or a square alone
    than the ground. A checkerboard's fields differ either way round."""
    square, disc = shape.columns
    if shape.pattern == "checker":
        return c[-1] != 0
    if not disc:
        return c[1] > 0
    d = c[-1]
    return (d > 0) & (d + c[1] > 0) if square else d > 0


def measure_target(grey: np.ndarray, camera: CameraModel, pose: Pose, centre: np.ndarray,
                   shape: TargetShape = TargetShape(), search_px: float = 20.0, min_score: float = 0.9,
                   iterations: int = 10, near: np.ndarray | None = None) -> TargetMeasurement | None:
    """Measure the target at world point ``centre (3,)`` in the grey image ``grey (h, w)`` seen from the approximate
    orientation ``pose`` (see the module docstring). The search spans ``search_px`` around the projection, or around
    ``near (2,)`` pixels when given (an operator's click: the target is rendered as the orientation sees it and
    searched there). None when the target's window is not inside the image (the shifts of the search that leave the
    image are not tried), the target spans less than two pixels across, or the match fails, moves more than 1.5 px
    from the best integer shift or scores below ``min_score``."""
    centre = np.asarray(centre, np.float64)
    pred, depth = project(camera, pose, centre[None])
    pred = pred[0]
    if depth[0] <= 0 or not np.all(np.isfinite(pred)):
        return None
    # the target's outline: the square's corners, or points round its circle when its azimuth is unknown, or the disc
    if shape.square_half_m > 0 and shape.square_azimuth_deg is not None:
        radius = shape.square_half_m * np.sqrt(2.0)
        angles = np.radians(shape.square_azimuth_deg + 45.0 + 90.0 * np.arange(4))
    else:
        radius, angles = max(shape.square_half_m * np.sqrt(2.0), shape.disc_radius_m), np.arange(8) * np.pi / 4
    corners = centre + radius * np.column_stack([np.cos(angles), np.sin(angles), np.zeros(len(angles))])
    cuv, _ = project(camera, pose, corners)
    if not np.all(np.isfinite(cuv)):
        return None
    half = int(np.ceil(np.abs(cuv - pred).max())) + 2
    if half < 3:
        return None
    s = int(np.ceil(search_px))
    p0 = np.round(pred).astype(int)
    # the search's centre as a whole-pixel shift from the projection
    base = np.zeros(2, int) if near is None else np.round(np.asarray(near, np.float64) - pred).astype(int)
    rows, cols = grey.shape[:2]
    q0 = p0 + base
    if not (0 <= q0[0] < cols and 0 <= q0[1] < rows):
        return None
    # the search window, NaN beyond the image's border (the shifts that reach there are not tried)
    x0, y0 = q0[0] - half - s - 2, q0[1] - half - s - 2
    img = np.full((2 * (half + s + 2) + 1,) * 2, np.nan)
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + img.shape[1], cols), min(y0 + img.shape[0], rows)
    img[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0] = grey[cy0:cy1, cx0:cx1]
    gu, gv = np.meshgrid(np.arange(-half, half + 1) + p0[0], np.arange(-half, half + 1) + p0[1])
    def support(azimuth_deg: float | None = None, circle_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The pixels ``u``, ``v`` the target covers at the prediction with a ring of RING_PX pixels around it, its
        square at ``azimuth_deg`` or replaced by a circle of radius ``circle_m`` (a square of unknown azimuth)."""
        sq, inner = render_target(camera, pose, centre, shape, gu, gv, azimuth_deg)
        if circle_m is not None:
            sq = render_target(camera, pose, centre, TargetShape(circle_m, 0.0), gu, gv)[1]
        near = (sq > 0) | (inner > 0)
        for _ in range(RING_PX):
            near[1:] |= near[:-1]
            near[:-1] |= near[1:]
            near[:, 1:] |= near[:, :-1]
            near[:, :-1] |= near[:, 1:]
        return gu[near].astype(np.float64), gv[near].astype(np.float64)

    unknown = shape.square_half_m > 0 and shape.square_azimuth_deg is None
    # a square of unknown azimuth is searched over its inscribed circle (the part every azimuth covers), so that a
    # target near the border is not lost to the corners a wrong azimuth puts beyond it
    u, v = support(circle_m=shape.square_half_m if unknown else None)
    # integer search: how well the grey-value model fits (multiple correlation) at every shift; a checkerboard or a
    # cross of unknown azimuth at each azimuth step (its fields or bars at the wrong azimuth do not correlate), other
    # shapes at 0 (the disc or the square's bulk finds them at any azimuth)
    turned = shape.pattern in ("checker", "cross") and shape.square_azimuth_deg is None
    azimuths = [k * 90.0 / AZIMUTH_STEPS for k in range(AZIMUTH_STEPS)] if turned else [shape.square_azimuth_deg or 0.0]
    iy, ix = v.astype(int) - y0, u.astype(int) - x0
    shifts = base + np.array([(dx, dy) for dy in range(-s, s + 1) for dx in range(-s, s + 1)])
    patches = img[iy[:, None] + shifts[None, :, 1], ix[:, None] + shifts[None, :, 0]]
    inside = np.all(np.isfinite(patches), axis=0)
    patches = np.nan_to_num(patches)
    centred = patches - patches.mean(0)
    total = np.maximum(np.einsum("ij,ij->j", centred, centred), 1e-12)
    best, azimuth = np.full(len(shifts), -1.0), azimuths[0]
    for az in azimuths:
        a = _design(camera, pose, centre, shape, u, v, az)
        if np.linalg.matrix_rank(a) < a.shape[1]:
            return None
        coef = np.linalg.lstsq(a, patches, rcond=None)[0]
        resid = patches - a @ coef
        r2 = 1.0 - np.einsum("ij,ij->j", resid, resid) / total
        r2[~inside | ~_brighter_inside(coef, shape)] = -1.0
        if r2.max() > best.max():
            azimuth = az
        best = np.maximum(best, r2)
    k = int(np.argmax(best))
    if best[k] < (0.8 * min_score) ** 2:  # far from a target even before the sub-pixel fit
        return None
    shift = shifts[k]
    obs = patches[:, k]
    if unknown:
        # the azimuth from the circle round the square (where its corners are), the pixels of it in the image
        cu, cv = support(circle_m=shape.square_half_m * np.sqrt(2.0))
        found = img[cv.astype(int) - y0 + shift[1], cu.astype(int) - x0 + shift[0]]
        seen = np.isfinite(found)
        azimuth = _best_azimuth(camera, pose, centre, shape, cu[seen], cv[seen], found[seen])
        # from here the square as it lies: its own pixels and ring
        u, v = support(azimuth)
        obs = img[v.astype(int) - y0 + shift[1], u.astype(int) - x0 + shift[0]]
        if not np.all(np.isfinite(obs)):
            return None
    su, sv = u + shift[0], v + shift[1]
    # least-squares template matching from there: the shift and the grey levels
    d = shift.astype(np.float64)
    eps = 0.05

    def model(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a0 = _design(camera, pose, centre, shape, su - d[0], sv - d[1], azimuth)
        c = np.linalg.lstsq(a0, obs, rcond=None)[0]
        au = _design(camera, pose, centre, shape, su - d[0] - eps, sv - d[1], azimuth)
        av = _design(camera, pose, centre, shape, su - d[0], sv - d[1] - eps, azimuth)
        jac = np.column_stack([(au - a0) @ c / eps, (av - a0) @ c / eps, a0])
        return obs - a0 @ c, jac, c

    # an azimuth estimated at the whole-pixel shift is estimated again at the sub-pixel position the fit reaches (a
    # thin bar half a pixel off turns the azimuth that fits best), and the fit runs again from there
    for rnd in range(2 if unknown else 1):
        if rnd:
            azimuth = _best_azimuth(camera, pose, centre, shape, su - d[0], sv - d[1], obs)
        for _ in range(iterations):
            res, jac, _ = model(d)
            step = np.linalg.lstsq(jac, res, rcond=None)[0]
            d += step[:2]
            if np.abs(d - shift).max() > 1.5:
                return None
            if np.abs(step[:2]).max() < 1e-3:
                break
    res, jac, c = model(d)
    if not _brighter_inside(c, shape):
        return None
    centred = obs - obs.mean()
    score = float(np.sqrt(max(0.0, 1.0 - float(res @ res) / max(float(centred @ centred), 1e-12))))
    if score < min_score:
        return None
    try:
        cov = np.linalg.inv(jac.T @ jac) * float(res @ res) / max(len(obs) - jac.shape[1], 1)
    except np.linalg.LinAlgError:
        return None
    std = float(np.sqrt(max(cov[0, 0], cov[1, 1])))
    return TargetMeasurement(uv=pred + d, predicted=pred, score=score, std_px=std,
                             azimuth_deg=float(azimuth % 90.0) if shape.square_half_m > 0 else None)


def _best_azimuth(camera: CameraModel, pose: Pose, centre: np.ndarray, shape: TargetShape, u: np.ndarray,
                  v: np.ndarray, obs: np.ndarray) -> float:
    """The square's azimuth (degrees, 0 to 90) that best fits the grey values ``obs (n,)`` of the target's pixels at
    the prediction ``u``, ``v`` ``(n,)`` (taken from the image at the best whole-pixel shift): the best of
    :data:`AZIMUTH_STEPS`, then the best of five steps a quarter as wide around it, then the vertex of the parabola
    through that and its neighbours (the steps repeat after 90 degrees). The finer steps serve the shapes whose fit
    falls off within a step (a cross's bars: their width over their length)."""

    def misfit(az: float) -> float:
        a = _design(camera, pose, centre, shape, u, v, az)
        res = obs - a @ np.linalg.lstsq(a, obs, rcond=None)[0]
        return float(res @ res)

    step = 90.0 / AZIMUTH_STEPS
    coarse = [misfit(k * step) for k in range(AZIMUTH_STEPS)]
    best = int(np.argmin(coarse)) * step
    fine = step / 4.0
    offsets = fine * np.arange(-2, 3)
    fits = [misfit(best + o) for o in offsets]
    k = int(np.clip(np.argmin(fits), 1, len(fits) - 2))
    lo, mid, hi = fits[k - 1], fits[k], fits[k + 1]
    curve = lo - 2 * mid + hi
    offset = 0.5 * (lo - hi) / curve if curve > 0 else 0.0
    return float((best + offsets[k] + float(np.clip(offset, -1.0, 1.0)) * fine) % 90.0)


def _measure_image(item: tuple) -> list[TargetMeasurement | None]:
    """Executor unit: the targets of one image, ``(read_grey, image id, camera, pose, centres (k, 3), shape,
    search_px, min_score)`` -> a measurement or None per target."""
    read_grey, iid, camera, pose, centres, shape, search_px, min_score = item
    grey = read_grey(iid)
    return [measure_target(grey, camera, pose, c, shape, search_px, min_score) for c in centres]


def measure_targets(block: ImageBlock, read_grey: Callable[[str], np.ndarray], mode: str = "missing",
                    shape: TargetShape = TargetShape(), search_px: float = 20.0, min_score: float = 0.9,
                    margin_px: float = 2.0, progress: Callable[[int, int, str], None] | None = None,
                    executor=None) -> dict:
    """Measure the block's ground points with coordinates (control and check) in its images (``mode``, see
    :data:`TARGET_MODES`; ``none`` measures nothing and keeps the imported measurements). ``read_grey(image_id)``
    gives an image as ``(h, w)`` grey values (picklable, e.g. a :func:`functools.partial`, for an ``executor`` with
    worker processes: one unit per image). ``progress(done, total, message)`` is called per image and may raise to
    cancel.

    Returns a JSON-ready record: ``mode``, ``shape``, ``search_px``, ``min_score``; ``points``: per point name its
    ``kind``, ``imported`` (images measured by the import), ``measured`` (image -> ``uv``, ``predicted``, ``score``,
    ``std_px`` and, where the import measured it there too, ``imported_difference_px``) and ``missed`` (images
    where its projection lies in the frame and no target was found: occluded, outside the search or too small);
    ``observations``: per point the image measurements to adjust with (the measured ones in ``all`` mode, the
    imported ones plus those measured where the import had none in ``missing`` mode: there every point is measured in
    every image all the same, so that the imported measurements are checked)."""
    if mode not in TARGET_MODES:
        raise ConfigError(f"unknown target measurement mode '{mode}' (use one of {', '.join(TARGET_MODES)})")
    points = {name: gp for name, gp in block.ground_points.items()
              if gp.xyz is not None and np.all(np.isfinite(gp.xyz))}
    record: dict = {"mode": mode, "shape": {"disc_radius_m": shape.disc_radius_m,
                                            "square_half_m": shape.square_half_m,
                                            "square_azimuth_deg": shape.square_azimuth_deg,
                                            "pattern": shape.pattern, "bar_half_m": shape.bar_half_m},
                    "search_px": search_px, "min_score": min_score,
                    "points": {name: {"kind": gp.kind, "imported": sorted(gp.observations), "measured": {},
                                      "missed": []} for name, gp in points.items()}}
    todo: dict[str, list[str]] = {}
    if mode != "none" and points:
        names = list(points)
        xyz = np.array([points[n].xyz for n in names], np.float64)
        for iid, img in block.images.items():
            if img.pose_approx is None or img.file is None:
                continue
            cam = block.camera_of(img)
            uv, depth = project(cam, img.pose_approx, xyz)
            inside = (depth > 0) & cam.contains(np.nan_to_num(uv, nan=-1e9), margin=margin_px)
            want = [names[k] for k in np.flatnonzero(inside)]
            if want:
                todo[iid] = want
    items = [(read_grey, iid, block.camera_of(block.images[iid]), block.images[iid].pose_approx,
              np.array([points[n].xyz for n in want], np.float64), shape, search_px, min_score)
             for iid, want in todo.items()]

    def done(d: int, t: int) -> None:
        if progress is not None:
            progress(d, t, f"targets: {d}/{t} images")

    if executor is not None:
        found = executor.map(_measure_image, items, done)
    else:
        found = []
        for it in items:
            done(len(found), len(items))
            found.append(_measure_image(it))
    for (iid, want), results in zip(todo.items(), found, strict=True):
        for name, m in zip(want, results, strict=True):
            entry = record["points"][name]
            if m is None:
                entry["missed"].append(iid)
                continue
            entry["measured"][iid] = {"uv": m.uv.tolist(), "predicted": m.predicted.tolist(),
                                      "score": round(m.score, 4), "std_px": round(m.std_px, 4),
                                      **({} if m.azimuth_deg is None else {"azimuth_deg": round(m.azimuth_deg, 2)})}
            imported = points[name].observations.get(iid)
            if imported is not None:
                entry["measured"][iid]["imported_difference_px"] = round(float(np.hypot(*(m.uv - imported))), 4)
    done(len(items), len(items))
    observations = {}
    for name, gp in points.items():
        measured = {iid: d["uv"] for iid, d in record["points"][name]["measured"].items()}
        kept = {} if mode == "all" else {iid: list(map(float, uv)) for iid, uv in gp.observations.items()}
        observations[name] = {**measured, **kept}
    record["observations"] = observations
    return record


def target_summary(record: dict) -> dict:
    """The figures of a :func:`measure_targets` record: ``mode``, the measurements made (``measured``), the points'
    images where none was found (``missed``), the median correlation (``score_median``), the RMS difference to
    the imported measurements of the same points in the same images (``imported_rms_px``; None without any) and
    those imported measurements more than :data:`SUSPECT_PX` from the measured ones (``suspect``: ``[point, image,
    pixels]``, the largest first)."""
    entries = [(name, iid, e) for name, p in record.get("points", {}).items()
               for iid, e in p.get("measured", {}).items()]
    scores = [e["score"] for _, _, e in entries]
    diffs = [(name, iid, e["imported_difference_px"]) for name, iid, e in entries if "imported_difference_px" in e]
    return {"mode": record.get("mode"), "measured": len(entries),
            "missed": sum(len(p.get("missed", [])) for p in record.get("points", {}).values()),
            "score_median": float(np.median(scores)) if scores else None,
            "imported_rms_px": float(np.sqrt(np.mean(np.square([d for *_, d in diffs])))) if diffs else None,
            "suspect": sorted(([n, i, d] for n, i, d in diffs if d > SUSPECT_PX), key=lambda x: -x[2])}


def apply_targets(block: ImageBlock, record: dict, path: str | Path | None = None) -> int:
    """Give the block's ground points the image measurements of a :func:`measure_targets` record (its
    ``observations``; a point it does not name keeps its own). Returns the number of measurements set. A record
    that is not one raises :class:`InputError` naming ``path`` and the field."""
    observations = record.get("observations") if isinstance(record, dict) else None
    if not isinstance(observations, dict):
        raise InputError("not a target measurement record", path, field="observations")
    n = 0
    for name, obs in observations.items():
        gp = block.ground_points.get(name)
        if gp is None:
            continue
        if not isinstance(obs, dict):
            raise InputError("expected image measurements (image -> [u, v])", path, field=f"observations.{name}")
        new = {}
        for iid, uv in obs.items():
            ok = isinstance(uv, list) and len(uv) == 2 and all(isinstance(x, (int, float)) for x in uv)
            value = np.asarray(uv, np.float64) if ok else None
            if value is None or not np.all(np.isfinite(value)):
                raise InputError("expected a pixel position [u, v]", path, field=f"observations.{name}.{iid}")
            if iid in block.images:
                new[iid] = value
        gp.observations = new
        n += len(new)
    return n
