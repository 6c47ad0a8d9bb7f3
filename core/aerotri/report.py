"""Statistics, quality layers and the report of an aerial triangulation (JSON + self-contained HTML).

* Per run: sigma0 a priori and a posteriori, iterations, rejection rounds, blunder share, RMS of image residuals,
  control point residuals, EO prior residuals, datum shift, median standard deviations of orientations and
  points, wall time, connection points, the estimated mounting corrections; the variance components of its
  observation groups (tie measurements, GNSS, IMU, control points: :func:`variance_table`) and the tie sigma given
  and estimated.
* For the block: check point RMS (all / nadir / oblique views), internal accuracy, the boresight of each head
  estimated from the adjusted orientations of each exposure, each camera's mounting correction when the adjustment
  estimated one (``BundleOptions.mounting``), and the forward intersection error of all tie
  points before (navigation orientation) and after adjustment.
* Per self-calibrated camera its parameters before and after, the corrections with their marginal standard
  deviations and significance, their correlations (the strong ones listed) and how far the calibration moves the
  image of a frame corner (:func:`self_calibration`).
* Per run its internal reliability (:func:`reliability`): the smallest errors the blunder tests find with 80 %
  probability, of tie measurements by their rays, EO priors and each control point, with redundancy numbers; and
  its external reliability: how far such errors move a tie point (:func:`tie_point_shifts`), an image and the
  datum, and Baarda's bias-to-noise ratios of the tie measurements.
* Per control and check point its intersection minus its given coordinates, and what the adjustment rejected of
  it (coordinates, measurements: :func:`.bundle.control_point_tests`). The EO priors (GNSS position, IMU
  attitude) the adjustment rejected (:func:`.bundle.prior_tests`), with their normalised differences; the prior
  residual RMS is over the priors kept.
* Per camera the image residuals by position in the frame (mean residual per cell, what of it noise does not
  explain, a radial profile): an error of the camera model shows as a pattern. Per image its observations kept and
  rejected, residual RMS, orientation standard deviations and its move from the navigation orientation. The
  tie points' ray counts.
* CBA layers over a grid: mean ray count of the tie points per cell and their intersection standard deviation
  XY and Z; and the intersection error map. Written as GeoTIFF (float32, NaN for empty cells) and as coloured
  PNG, embedded in the HTML page as base64.
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..evaluate.aerotri import (
    SPLITS,
    check_point_errors,
    intersect_ground_point,
    rms_xy_z,
    std_xy_z,
    tie_point_std,
)
from ..geometry.projection import project
from ..geometry.rotations import matrix_to_rotvec
from ..matching.targets import SUSPECT_PX
from ..model import CameraModel, ImageBlock, Raster, TiePoints
from . import precision
from .bundle import (
    CALIBRATION_NAMES,
    DETECTION_POWER,
    PRIOR_PART_LABELS,
    PRIOR_PARTS,
    VARIANCE_GROUPS,
    BundleResult,
    image_focals,
)
from .hierarchical import ATResult, Run, camera_runs
from .problem import intersect_ties, pose_arrays
from .strips import flight_strips, strip_check

FIELD_CELLS = 8
"""Cells of the image residual field along the frame's longer side (:func:`residual_field`)."""
FIELD_RINGS = 8
"""Rings of distance from the principal point in the radial profile of the residual field."""
FIELD_MIN_OBS = 20
"""A cell or ring with fewer observations gets no mean residual (it would be mostly noise)."""
RAYS_TOP = 12
"""The ray count histogram's last bin holds the tie points with this many rays or more."""
WORST_IMAGES = 10
"""The HTML page lists this many images with the largest residuals and this many with the fewest observations
(report.json has every image)."""

RAY_CLASSES = (("2", 2, 2), ("3", 3, 3), ("4-5", 4, 5), ("6-9", 6, 9), ("10+", 10, None))
"""Classes of tie points by the rays a run kept of them (label, fewest, most; None: no limit) in :func:`reliability`."""

_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64)


def colourise(values: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """A viridis-like RGB picture ``(rows, cols, 3) uint8`` of a grid; NaN cells are white."""
    v = np.asarray(values, np.float64)
    fin = np.isfinite(v)
    lo = np.nanpercentile(v, 2) if vmin is None and fin.any() else (vmin or 0.0)
    hi = np.nanpercentile(v, 98) if vmax is None and fin.any() else (vmax or 1.0)
    t = np.clip((np.nan_to_num(v, nan=lo) - lo) / max(hi - lo, 1e-12), 0, 1) * (len(_VIRIDIS) - 1)
    i = np.minimum(np.floor(t).astype(int), len(_VIRIDIS) - 2)
    f = (t - i)[..., None]
    rgb = _VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f
    rgb[~fin] = 255
    return rgb.astype(np.uint8)


def grid_layer(xy: np.ndarray, values: np.ndarray, cell: float, crs: str, reduce: str = "mean",
               bounds: tuple[float, float, float, float] | None = None) -> Raster:
    """Aggregate point values ``(n,)`` at ``xy (n, 2)`` into a north-up grid of ``cell`` metres (``mean`` or
    ``median`` per cell; NaN where empty)."""
    ok = np.all(np.isfinite(xy), 1) & np.isfinite(values)
    if bounds is not None:
        ok &= (xy[:, 0] >= bounds[0]) & (xy[:, 0] <= bounds[2]) & (xy[:, 1] >= bounds[1]) & (xy[:, 1] <= bounds[3])
    xy, values = xy[ok], values[ok]
    if bounds is None:
        bounds = (float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max()))
    x0 = np.floor(bounds[0] / cell) * cell
    y0 = np.ceil(bounds[3] / cell) * cell
    cols = int(np.ceil((bounds[2] - x0) / cell)) + 1
    rows = int(np.ceil((y0 - bounds[1]) / cell)) + 1
    c = np.clip(((xy[:, 0] - x0) / cell).astype(int), 0, cols - 1)
    r = np.clip(((y0 - xy[:, 1]) / cell).astype(int), 0, rows - 1)
    key = r * cols + c
    out = np.full(rows * cols, np.nan)
    if reduce == "mean":
        s = np.bincount(key, values, rows * cols)
        n = np.bincount(key, minlength=rows * cols)
        out[n > 0] = s[n > 0] / n[n > 0]
    else:
        order = np.lexsort((values, key))
        ks, vs = key[order], values[order]
        starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
        ends = np.r_[starts[1:], len(ks)]
        out[ks[starts]] = [np.median(vs[a:b]) for a, b in zip(starts, ends)]
    return Raster(data=out.reshape(rows, cols).astype(np.float32), x0=float(x0), y0=float(y0), cell=cell, crs=crs)


def _used(run: Run) -> np.ndarray:
    """The run's observations ``(m,)`` in its final solution (results without ``obs_used``: those not rejected)."""
    used = run.result.obs_used
    return used if len(used) == len(run.obs_rejected) else ~run.obs_rejected


def largest_systematic(fields: dict[str, dict]) -> tuple[str, float] | None:
    """The camera with the largest ``systematic_rms_px`` of :func:`camera_residual_fields` (as in report.json) and
    that figure, or None without one."""
    px = {c: float(f["systematic_rms_px"]) for c, f in fields.items() if f.get("systematic_rms_px") is not None}
    worst = max(px, key=px.get) if px else None
    return (worst, px[worst]) if worst else None


def run_statistics(run: Run) -> dict:
    """Figures of one adjustment run (see the module docstring)."""
    res = run.result
    v = run.obs_residual[_used(run)]
    v = v[np.all(np.isfinite(v), 1)]
    std = np.array(list(run.image_std.values())) if run.image_std else np.zeros((0, 6))
    pt_std = np.sqrt(np.abs(np.diagonal(run.xyz_cov, axis1=1, axis2=2)))
    sxy, sz = std_xy_z(pt_std)
    off = res.prior_rejected if len(res.prior_rejected) == len(res.prior_residual_pos) else \
        np.zeros((len(res.prior_residual_pos), 2), bool)
    pos = res.prior_residual_pos[np.all(np.isfinite(res.prior_residual_pos), 1) & ~off[:, 1]]
    att = res.prior_residual_att[np.all(np.isfinite(res.prior_residual_att), 1) & ~off[:, 0]]
    return {
        "name": run.name, "images": len(run.poses), "points": int(np.isfinite(run.xyz[:, 0]).sum()),
        "observations": int(len(run.obs_index)), "rejected": int(run.obs_rejected.sum()),
        "blunder_percent": float(100.0 * run.obs_rejected.mean()) if len(run.obs_rejected) else 0.0,
        "sigma0_a_priori_px": res.sigma_px, "sigma_px_given": res.sigma_px_given, "sigma0": res.sigma0,
        "prior_sigma_scale": res.prior_sigma_scale.tolist(), "control_sigma_scale": res.control_sigma_scale,
        "sigma0_px": res.sigma0 * res.sigma_px, "variance_components": variance_table(res),
        "redundancy": res.redundancy, "iterations": res.iterations, "rounds": res.rounds,
        "rms_image_px": [float(np.sqrt(np.mean(v[:, 0] ** 2))), float(np.sqrt(np.mean(v[:, 1] ** 2)))]
        if len(v) else [None, None],
        "rms_control_m": np.sqrt(np.mean(res.gcp_residual**2, 0)).tolist() if len(res.gcp_residual) else None,
        "rms_prior_position_m": np.sqrt(np.mean(pos**2, 0)).tolist() if len(pos) else None,
        "rms_prior_attitude_deg": np.degrees(np.sqrt(np.mean(att**2, 0))).tolist() if len(att) else None,
        "datum_shift_m": res.datum_shift.tolist(),
        "datum_shift_std_m": res.datum_shift_std.tolist() if np.all(np.isfinite(res.datum_shift_std)) else None,
        "median_std_attitude_deg": np.degrees(np.nanmedian(std[:, :3], 0)).tolist() if len(std) else None,
        "median_std_position_m": np.nanmedian(std[:, 3:], 0).tolist() if len(std) else None,
        "std_kind": res.image_std_kind,
        "point_std_xy_m": sxy, "point_std_z_m": sz,
        "connection_points": run.connection_count, "wall_s": run.wall_s, "log": res.log,
        "control_points_rejected": list(run.control_rejected),
        "control_measurements_rejected": [list(o) for o in run.control_obs_rejected],
        "priors_rejected": [list(o) for o in run.prior_rejected],
        "mounting": {cam.id: _mounting_entry(res, ci) for ci, cam in enumerate(res.cameras)
                     if np.all(np.isfinite(res.mounting[ci]))},
    }


def variance_table(res: BundleResult) -> list[dict]:
    """The run's variance components (``BundleResult.variance_components``) of the groups that took part: group,
    words, observations, redundancy, factor (how many times its a priori sigmas its errors are) with its standard
    deviation; for the tie measurements also the a priori sigma of the solution and the one their residuals give, for
    the GNSS positions and IMU attitudes the factors their given sigmas were scaled by along world X Y Z, for the
    control point measurements the factor of theirs (``sigma_scale``)."""
    rows = []
    for key, comp in res.variance_components.items():
        if comp.count == 0 or comp.redundancy <= 0:
            continue
        row = {"group": key, "label": VARIANCE_GROUPS[key], "count": comp.count, "redundancy": comp.redundancy,
               "factor": comp.factor, "factor_std": comp.factor_std}
        if key == "ties":
            row |= {"sigma_px": res.sigma_px, "estimated_sigma_px": comp.factor * res.sigma_px}
        elif key in ("imu", "gnss"):
            row["sigma_scale"] = (res.prior_sigma_scale[:3] if key == "imu" else res.prior_sigma_scale[3:]).tolist()
        elif key == "control_measurements":
            row["sigma_scale"] = [res.control_sigma_scale]
        rows.append(row)
    return rows


def tie_point_shifts(run: Run, ties: TiePoints, block: ImageBlock, used: np.ndarray) -> np.ndarray:
    """External reliability of the run's tie measurements ``used (m,)`` (bool over the run's observations, each with
    a smallest detectable error ``obs_mdb``): how far an error of that size, in its worst direction, moves the
    measurement's tie point with the images held (metres, :func:`.precision.point_shifts` with the run's point
    cofactors ``xyz_cov / sigma0^2`` and the weight ``1 / sigma_px^2`` of its solution). The Jacobians use the adjusted
    orientations and the block's focal lengths (a self-calibration changes them by far less than these figures
    are worth). Returns ``(k,)`` for the ``k`` measurements used."""
    res = run.result
    obs = run.obs_index[used]
    row = np.full(ties.n_tracks, -1, np.int64)
    row[run.track_index] = np.arange(len(run.track_index))
    op = row[ties.obs_track[obs]]
    # the images of the block's tie arrays with the run's adjusted orientations (all of those observed)
    cameras, image_camera, r, c = pose_arrays(block, ties.image_ids, run.poses)
    fx, fy = image_focals(cameras, image_camera)
    oi = ties.obs_image[obs]
    jp = precision.point_jacobians(r, c, fx, fy, run.xyz, op, oi)
    q = run.xyz_cov / max(res.sigma0, 1e-12) ** 2
    return precision.point_shifts(jp, q, op) / res.sigma_px**2 * res.obs_mdb[used]


def reliability(run: Run, ties: TiePoints, block: ImageBlock) -> dict:
    """Internal and external reliability of one run: the smallest errors its blunder tests find with probability
    :data:`.bundle.DETECTION_POWER` (Baarda's minimal detectable blunders, see :func:`.bundle.detectable_shift`),
    and what such errors do to the result.

    ``ties``: per class of tie points by the rays the run kept (:data:`RAY_CLASSES`) the measurements, their mean
    redundancy number, the median and 95th percentile of their smallest detectable errors (pixels) and of how far
    such an error moves its tie point (``point_shift_m_median``, ``point_shift_m_p95``: external reliability with
    the images held, :func:`tie_point_shifts`), and the median of Baarda's bias-to-noise ratio
    ``delta0 sqrt((1 - r) / r)`` (``bnr_median``: the most such an error moves any adjusted value, in standard
    deviations of that value, from the redundancy number ``r``); ``priors``:
    of the EO priors tested, per axis the median and largest (``attitude_deg`` about world X Y Z, ``position_m``),
    and how far such an error would move the adjusted orientation (``effect_median``, ``effect_max``: external
    reliability, with the points held);
    ``control_points``: per control point tested its redundancy numbers and smallest detectable errors (metres) per
    axis, the weakest first, and how far such an error would move the datum shift (``datum_effect_m``, external
    reliability; None when the shift is held). Parts with nothing tested are empty."""
    res = run.result
    used = _used(run) & np.isfinite(res.obs_mdb)
    track = ties.obs_track[run.obs_index[used]]
    rays = np.bincount(track, minlength=ties.n_tracks)[track]
    red, mdb = res.obs_redundancy[used], res.obs_mdb[used]
    shift = tie_point_shifts(run, ties, block, used)
    # delta0 sqrt((1 - r) / r), with delta0 = mdb sqrt(r) / (sigma_px sigma0)
    bnr = mdb * np.sqrt(1.0 - red) / (res.sigma_px * max(res.sigma0, 1e-12))
    rows = []
    for label, fewest, most in RAY_CLASSES:
        sel = (rays >= fewest) & (rays <= (most or np.inf))
        if sel.any():
            rows.append({"rays": label, "measurements": int(sel.sum()), "redundancy_mean": float(red[sel].mean()),
                         "mdb_px_median": float(np.median(mdb[sel])), "mdb_px_p95": float(np.percentile(mdb[sel], 95)),
                         "point_shift_m_median": float(np.median(shift[sel])),
                         "point_shift_m_p95": float(np.percentile(shift[sel], 95)),
                         "bnr_median": float(np.median(bnr[sel]))})
    priors = {}
    for key, cols, unit in (("attitude_deg", slice(0, 3), np.degrees), ("position_m", slice(3, 6), np.asarray)):
        ok = np.all(np.isfinite(res.prior_mdb[:, cols]), 1)
        a, e = res.prior_mdb[ok, cols], res.prior_effect[ok, cols]
        if len(a):
            priors[key] = {"images": len(a), "median": unit(np.median(a, 0)).tolist(), "max": unit(a.max(0)).tolist(),
                           "effect_median": unit(np.median(e, 0)).tolist(), "effect_max": unit(e.max(0)).tolist()}
    effect = res.gcp_datum_effect
    control = [{"name": run.control_names[g], "redundancy": res.gcp_redundancy[g].tolist(),
                "mdb_m": res.gcp_mdb[g].tolist(),
                "datum_effect_m": effect[g].tolist() if np.all(np.isfinite(effect[g])) else None}
               for g in np.flatnonzero(np.all(np.isfinite(res.gcp_mdb), 1))]
    control.sort(key=lambda d: -max(d["mdb_m"]))
    return {"power": DETECTION_POWER, "ties": rows, "priors": priors, "control_points": control}


def weakest_control(runs: list[dict]) -> dict | None:
    """Of the runs' :func:`reliability` (as in report.json), the control point axis with the largest smallest
    detectable error: its ``name``, ``run``, ``axis`` (X, Y or Z) and ``mdb_m``; None without one."""
    best = None
    for r in runs:
        for d in (r.get("reliability") or {}).get("control_points") or []:
            axis = int(np.argmax(d["mdb_m"]))
            if best is None or d["mdb_m"][axis] > best["mdb_m"]:
                best = {"name": d["name"], "run": r["name"], "axis": "XYZ"[axis], "mdb_m": float(d["mdb_m"][axis])}
    return best


def _mounting_entry(res, ci: int) -> dict:
    """A camera's mounting correction in a run: boresight (deg) and offset (m), with their marginal standard
    deviations where the run computed them (None otherwise)."""
    m, std = res.mounting[ci], res.mounting_std[ci]
    ok = bool(np.all(np.isfinite(std)))
    return {"boresight_deg": np.degrees(m[:3]).tolist(), "offset_m": m[3:].tolist(),
            "boresight_std_deg": np.degrees(std[:3]).tolist() if ok else None,
            "offset_std_m": std[3:].tolist() if ok else None}


def mounting(block: ImageBlock, at: ATResult) -> dict:
    """Per camera its estimated mounting correction (``BundleOptions.mounting``; boresight rotation vector in
    degrees and centre offset in metres, camera axes, with standard deviations where the run computed marginal
    ones) from the run holding most of its images (in HAT a head that
    looks in two directions on crossing strips takes part in two runs), with that run's name and image count."""
    return {cid: {**_mounting_entry(run.result, ci), "run": run.name, "images": n}
            for cid, (run, ci, n) in camera_runs(block, at.runs).items()
            if np.all(np.isfinite(run.result.mounting[ci]))}


def largest_corner_shift(cameras: dict[str, dict]) -> str | None:
    """Of a report's :func:`self_calibration` (as in report.json), the camera whose corner the calibration moves the
    most, or None without one."""
    return max(cameras, key=lambda c: float(cameras[c]["corner_shift_px"]), default=None)


def first_run(report: dict) -> dict:
    """Of a report (as in report.json), the :func:`run_statistics` of its first adjustment: HAT's calibration
    sub-block when it had one, else IAT's run or HAT's nadir run ({} without runs)."""
    runs = report.get("runs") or []
    return report.get("calibration_run") or (runs[0] if runs else {})


def estimated_tie_sigma(report: dict) -> tuple[float, float] | None:
    """Of a report (as in report.json), the tie sigma given and the one its :func:`first_run` estimated and adjusted
    again with (``BundleOptions.tie_sigma_estimate``), pixels; None when it kept the given one, and for reports written
    before the estimate existed."""
    first = first_run(report)
    given, used = first.get("sigma_px_given"), first.get("sigma0_a_priori_px")
    return (float(given), float(used)) if given is not None and used is not None and given != used else None


def estimated_prior_sigma(report: dict) -> dict[str, list[float]]:
    """Of a report (as in report.json), the factors its :func:`first_run` scaled the GNSS/IMU prior sigmas by
    (``BundleOptions.prior_sigma_estimate``): the group's name in words -> its factors along world X Y Z, for the
    groups it scaled ({} when it kept them, and for reports written before the estimate existed)."""
    scale = [float(f) for f in first_run(report).get("prior_sigma_scale") or [1.0] * 6]
    return {label: scale[3 * k:3 * k + 3] for k, label in enumerate(PRIOR_PART_LABELS)
            if any(f != 1.0 for f in scale[3 * k:3 * k + 3])}


def estimated_control_sigma(report: dict) -> float | None:
    """Of a report (as in report.json), the factor its :func:`first_run` scaled the control points' image measurement
    sigmas by (``BundleOptions.control_sigma_estimate``); None when it kept them, and for reports written before the
    estimate existed."""
    scale = float(first_run(report).get("control_sigma_scale") or 1.0)
    return scale if scale != 1.0 else None


def format_scale(factors: list[float]) -> str:
    """A group's sigma scales along X Y Z (:func:`estimated_prior_sigma`) in words: one number when they are equal."""
    return f"{factors[0]:.2f}" if len(set(factors)) == 1 else "/".join(f"{f:.2f}" for f in factors) + " (X/Y/Z)"


MISWEIGHTED_FACTOR = 2.0
"""A group of priors or control measurements whose variance component is off by more than this factor (either way,
and by more than 3 of its standard deviations) is named as weighted wrongly (:func:`misweighted_groups`)."""


def misweighted_groups(run: dict) -> dict[str, float]:
    """Of a run's :func:`run_statistics`, the GNSS, IMU and control measurement groups whose residuals are far from
    their a priori sigmas (:data:`MISWEIGHTED_FACTOR`): their names in words -> their factor. The tie measurements'
    sigma is estimated instead (``BundleOptions.tie_sigma_estimate``)."""
    return {v["label"]: v["factor"] for v in run.get("variance_components") or []
            if v["group"] in ("gnss", "imu", "control_measurements") and v["factor"] > 0.0
            and abs(math.log(v["factor"])) > math.log(MISWEIGHTED_FACTOR)
            and abs(v["factor"] - 1.0) > 3.0 * v["factor_std"]}


SIGNIFICANCE_T = 1.96
"""A self-calibrated parameter's correction is significant when it exceeds this many of its standard deviations
(a two-sided test at 5 %)."""
STRONG_CORRELATION = 0.9
"""Pairs of self-calibrated parameters correlated at least this much are listed (:func:`self_calibration`): the block
hardly tells them apart (k1, k2 and k3 of a lens, whose terms differ little over the frame; the focal length and the
principal point of a head with the flying height and the attitude of its images)."""
CALIBRATION_UNITS = {"fx": "px", "fy": "px", "cx": "px", "cy": "px"}
"""Units of the self-calibrated parameters; the distortion coefficients have none."""


def corner_shift(initial: CameraModel, adjusted: CameraModel) -> tuple[np.ndarray, int]:
    """How the self-calibration moves the image of each frame corner: the pixel ``(4, 2)`` to which ``adjusted``
    projects the ray that ``initial`` sees at the corner, minus the corner (corners top-left, top-right,
    bottom-right, bottom-left, at the outer pixels' centres); and the index of the corner moved the most."""
    w, h = initial.width - 1.0, initial.height - 1.0
    corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    shift = adjusted.normalized_to_pixel(initial.pixel_to_normalized(corners)) - corners
    return shift, int(np.argmax(np.hypot(shift[:, 0], shift[:, 1])))


def self_calibration(block: ImageBlock, at: ATResult) -> dict:
    """Per self-calibrated camera (``BundleOptions.self_calibration``), from HAT's calibration sub-block or else the
    run holding most of its images: its free parameters with their values before and after, the correction with its
    marginal standard deviation and the ratio of the two (``t``, ``significant`` above :data:`SIGNIFICANCE_T`; None
    where the run computed no marginal covariance, ``BundleOptions.calibration_max_images``), their correlation
    matrix and the pairs correlated at least :data:`STRONG_CORRELATION`, and the corner the calibration moves the
    most (:func:`corner_shift`:
    ``corner_shift_px`` its length with the standard deviation ``corner_shift_std_px`` propagated from the
    covariance). The run's name, its image count of the camera, whether its figures are ``marginal``, and the
    ``other_runs`` that calibrated the camera too (HAT calibrating in its runs: their images keep their own
    calibration, which the block does not)."""
    out = {}
    for cid, (run, ci, n) in camera_runs(block, at.calibrating_runs()).items():
        cal = run.result.calibration.get(ci)
        if cal is None:
            continue
        names = [CALIBRATION_NAMES[i] for i in cal.params]
        correction = cal.adjusted - cal.initial
        std = corr = None
        if cal.cov is not None:
            std = np.sqrt(np.abs(np.diag(cal.cov)))
            with np.errstate(divide="ignore", invalid="ignore"):
                corr = cal.cov / np.outer(std, std)
        params = []
        for k, name in enumerate(names):
            t = float(correction[k] / std[k]) if std is not None and std[k] > 0 else None
            params.append({"name": name, "unit": CALIBRATION_UNITS.get(name, ""), "initial": float(cal.initial[k]),
                           "adjusted": float(cal.adjusted[k]), "correction": float(correction[k]),
                           "std": float(std[k]) if std is not None else None, "t": t,
                           "significant": None if t is None else bool(abs(t) > SIGNIFICANCE_T)})
        initial = replace(run.result.cameras[ci], **{nm: float(v) for nm, v in zip(names, cal.initial)})
        adjusted = run.result.cameras[ci]
        shift, worst = corner_shift(initial, adjusted)
        length = float(np.hypot(*shift[worst]))
        shift_std = None
        if cal.cov is not None and length > 0:
            # the corner's displacement length, differentiated by each free parameter (the projection is linear or
            # bilinear in them: a small step is exact enough)
            grad = np.zeros(len(names))
            for k, name in enumerate(names):
                step = 1e-6 * max(abs(float(cal.adjusted[k])), 1.0)
                moved = corner_shift(initial, replace(adjusted, **{name: float(cal.adjusted[k]) + step}))[0][worst]
                grad[k] = (np.hypot(*moved) - length) / step
            shift_std = float(np.sqrt(max(grad @ cal.cov @ grad, 0.0)))
        out[cid] = {"run": run.name, "images": n, "marginal": cal.cov is not None, "parameters": params,
                    "correlation": None if corr is None else np.round(corr, 4).tolist(),
                    "strong_correlations": [] if corr is None else [
                        [names[a], names[b], float(corr[a, b])] for a in range(len(names))
                        for b in range(a + 1, len(names)) if abs(corr[a, b]) >= STRONG_CORRELATION],
                    "corner_shift_px": length, "corner_shift_std_px": shift_std,
                    "corner": ["top-left", "top-right", "bottom-right", "bottom-left"][worst],
                    "other_runs": [r.name for r in at.calibrating_runs() if r is not run and any(
                        cam.id == cid and k in r.result.calibration for k, cam in enumerate(r.result.cameras))]}
    return out


def boresight(block: ImageBlock, poses: dict) -> dict:
    """Per rig head: mean rotation (degrees, rotation vector in the head frame) between the adjusted
    ``R_head R_nadir^T`` of each exposure and the nominal ``sensor_from_rig``."""
    out = {}
    by_exp: dict[str, dict[str, str]] = {}
    for iid, img in block.images.items():
        if img.exposure is not None and img.head is not None and iid in poses:
            by_exp.setdefault(img.exposure, {})[img.head] = iid
    for rig in block.rigs.values():
        ref = rig.heads[0]
        for h in rig.heads[1:]:
            vecs = []
            for heads in by_exp.values():
                if ref.name in heads and h.name in heads:
                    rel = poses[heads[h.name]].R @ poses[heads[ref.name]].R.T
                    nominal = h.relative_to(ref)[0]
                    vecs.append(matrix_to_rotvec(rel @ nominal.T))
            if vecs:
                vecs = np.array(vecs)
                out[h.name] = {"mean_deg": np.degrees(vecs.mean(0)).tolist(),
                               "std_deg": np.degrees(vecs.std(0)).tolist(), "exposures": len(vecs)}
    return out


def ground_point_residuals(block: ImageBlock, poses: dict, rejected: set[str] | None = None,
                           rejected_obs: set[tuple[str, str]] | None = None) -> list[dict]:
    """Per control and check point: the images it was measured in with an adjusted orientation, the difference
    of its intersection from all of them to its given coordinates (m; NaN for a coordinate not given) and the RMS
    image residual of that intersection (px). Points with fewer than two such images are left out. The
    measurements the adjustment rejected (``rejected_obs``: (point, image)) are left out of the intersection and
    listed (``rejected_images``); ``rejected_coordinates`` says whether it rejected the point's coordinates (its
    name in ``rejected``), whose difference is then the evidence."""
    rejected, rejected_obs = rejected or set(), rejected_obs or set()
    rows = []
    for gp in block.ground_points.values():
        bad = sorted(i for i in gp.observations if (gp.name, i) in rejected_obs)
        use = {i: p for i, p in poses.items() if i not in bad} if bad else poses
        got = intersect_ground_point(block, use, gp) if gp.xyz is not None else None
        if got is None:
            continue
        xyz, ids = got
        res = [project(block.camera_of(i), poses[i], xyz[None])[0][0] - gp.observations[i] for i in ids]
        d = xyz - gp.xyz
        rows.append({"name": gp.name, "kind": gp.kind, "images": len(ids), "dx_m": float(d[0]),
                     "dy_m": float(d[1]), "dz_m": float(d[2]),
                     "image_rms_px": float(np.sqrt(np.mean(np.sum(np.square(res), axis=1)))),
                     "rejected_coordinates": gp.name in rejected, "rejected_images": bad})
    return rows


def accepted_residuals(at: ATResult) -> tuple[np.ndarray, np.ndarray]:
    """The tie observations the runs kept, as indices ``(k,)`` into the block's tie arrays, and their image
    residuals ``(k, 2)`` in pixels (observed minus the projection with the adjusted orientation and point)."""
    idx, res = [], []
    for run in at.runs:
        ok = _used(run) & np.all(np.isfinite(run.obs_residual), 1)
        idx.append(run.obs_index[ok])
        res.append(run.obs_residual[ok])
    if not idx:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    return np.concatenate(idx), np.concatenate(res)


def track_residual_rms(ties: TiePoints, at: ATResult) -> np.ndarray:
    """Per tie track the RMS length of the image residuals of the observations the runs kept (pixels, see
    :func:`accepted_residuals`) ``(n,)``; NaN for a track without any."""
    idx, v = accepted_residuals(at)
    track = ties.obs_track[idx]
    count = np.bincount(track, minlength=ties.n_tracks)
    sq = np.bincount(track, weights=np.sum(v**2, axis=1), minlength=ties.n_tracks)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, np.sqrt(sq / count), np.nan)


def residual_field(uv: np.ndarray, v: np.ndarray, camera: CameraModel, cells: int = FIELD_CELLS,
                   rings: int = FIELD_RINGS, min_obs: int = FIELD_MIN_OBS) -> dict:
    """Image residuals by position in the frame of one camera: what an adjustment leaves of systematic image
    errors (a distortion, principal point or focal length the camera model lacks shows as a pattern).

    ``uv (k, 2)`` observed pixel positions, ``v (k, 2)`` their residuals (px). The frame is cut into ``cells``
    cells along its longer side (square-ish cells across); per cell the count and the mean residual vector (None
    below ``min_obs`` observations). Their weighted RMS ``cell_mean_rms_px`` holds noise too: a cell mean of ``n``
    residuals of variance ``s^2`` per axis scatters by ``s sqrt(2 / n)``, whose weighted RMS is ``noise_rms_px``;
    ``systematic_rms_px = sqrt(max(cell_mean_rms^2 - noise_rms^2, 0))`` is the part noise does not explain. In
    ``rings`` rings of distance from the principal point, out to the farthest corner, the mean radial residual
    (positive outwards) and the count: a radial distortion error shows as a curve over the radius."""
    w, h = camera.width, camera.height
    cols, rows = (cells, max(1, round(cells * h / w))) if w >= h else (max(1, round(cells * w / h)), cells)
    cu = np.clip((uv[:, 0] + 0.5) * cols / w, 0, cols - 1).astype(np.int64)
    cv = np.clip((uv[:, 1] + 0.5) * rows / h, 0, rows - 1).astype(np.int64)
    cell = cv * cols + cu
    n = np.bincount(cell, minlength=rows * cols)
    s = np.stack([np.bincount(cell, weights=v[:, i], minlength=rows * cols) for i in (0, 1)], 1)
    ss = np.bincount(cell, weights=np.sum(v**2, 1), minlength=rows * cols)
    full = n >= max(min_obs, 2)
    mean = s[full] / n[full, None]
    # unbiased variance of both axes together, of one cell's residuals about their mean
    var = (ss[full] - n[full] * np.sum(mean**2, 1)) / (n[full] - 1)
    mean_rms = float(np.sqrt(np.sum(n[full] * np.sum(mean**2, 1)) / n[full].sum())) if full.any() else None
    noise_rms = float(np.sqrt(np.sum(var) / n[full].sum())) if full.any() else None
    grid = np.full((rows * cols, 2), np.nan)
    grid[full] = mean
    d = uv - [camera.cx, camera.cy]
    r = np.hypot(d[:, 0], d[:, 1])
    r_max = float(np.max(np.hypot(np.array([0.0, w - 1.0]) - camera.cx, np.array([0.0, h - 1.0])[:, None] - camera.cy)))
    ring = np.clip((r / max(r_max, 1e-9) * rings).astype(np.int64), 0, rings - 1)
    radial = np.sum(v * d, 1) / np.maximum(r, 1e-9)
    rn = np.bincount(ring, minlength=rings)
    rs = np.bincount(ring, weights=radial, minlength=rings)
    return {"camera": camera.id, "observations": int(len(uv)), "cells": [cols, rows],
            "cell_px": [w / cols, h / rows], "count": n.reshape(rows, cols).tolist(),
            "mean_px": [[None if not np.isfinite(m[0]) else [float(m[0]), float(m[1])] for m in row]
                        for row in grid.reshape(rows, cols, 2)],
            "cell_mean_rms_px": mean_rms, "noise_rms_px": noise_rms,
            "systematic_rms_px": None if mean_rms is None else float(np.sqrt(max(mean_rms**2 - noise_rms**2, 0.0))),
            "radial": {"radius_px": ((np.arange(rings) + 0.5) * r_max / rings).tolist(), "count": rn.tolist(),
                       "mean_px": [float(a / b) if b >= min_obs else None for a, b in zip(rs, rn)]}}


def camera_residual_fields(block: ImageBlock, ties: TiePoints, obs: np.ndarray, v: np.ndarray) -> dict[str, dict]:
    """Per camera of the block (its current, possibly self-calibrated model) the :func:`residual_field` of the
    observations ``obs (k,)`` (indices into the tie arrays) with residuals ``v (k, 2)``."""
    cam_of_image = np.array([block.images[i].camera_id if i in block.images else "" for i in ties.image_ids],
                            dtype=object)
    cam_obs = cam_of_image[ties.obs_image[obs]]
    return {cid: residual_field(ties.obs_uv[obs[sel]], v[sel], cam)
            for cid, cam in sorted(block.cameras.items()) if (sel := cam_obs == cid).any()}


def image_statistics(block: ImageBlock, ties: TiePoints, at: ATResult, obs: np.ndarray, v: np.ndarray) -> list[dict]:
    """Per adjusted image: its run, its tie observations kept and rejected, the RMS length of its residual
    vectors (px) over those the runs adjusted (``obs (k,)`` with residuals ``v (k, 2)``, see
    :func:`accepted_residuals`; a thinned HAT intersects the others afterwards), the standard deviations of its
    orientation (rotation about X Y Z in degrees, centre in metres), how far the adjustment moved it from its
    navigation orientation (centre in metres, attitude angle in degrees), the normalised differences of its
    attitude and position priors in their last test and the parts rejected (:func:`.bundle.prior_tests`)."""
    n_img = len(ties.image_ids)
    kept = np.bincount(ties.obs_image[~at.obs_rejected], minlength=n_img)
    n_res = np.bincount(ties.obs_image[obs], minlength=n_img)
    vv = np.bincount(ties.obs_image[obs], weights=np.sum(v**2, 1), minlength=n_img)
    rejected = np.bincount(ties.obs_image[at.obs_rejected], minlength=n_img)
    index = {iid: k for k, iid in enumerate(ties.image_ids)}
    run_of = {iid: run.name for run in at.runs for iid in run.poses}
    prior_w = {iid: w for run in at.runs for iid, w in run.prior_w.items()}
    prior_off = {}
    for run in at.runs:
        for iid, part in run.prior_rejected:
            prior_off.setdefault(iid, []).append(part)
    rows = []
    for iid, pose in at.poses.items():
        k = index.get(iid)
        img = block.images[iid]
        std = at.image_std.get(iid)
        nav = img.pose_approx
        rows.append({
            "image": iid, "view": img.view, "run": run_of.get(iid, ""),
            "observations": int(kept[k]) if k is not None else 0,
            "rejected": int(rejected[k]) if k is not None else 0,
            "rms_px": float(np.sqrt(vv[k] / n_res[k])) if k is not None and n_res[k] else None,
            "std_attitude_deg": np.degrees(std[:3]).tolist() if std is not None else None,
            "std_position_m": std[3:].tolist() if std is not None else None,
            "moved_m": float(np.linalg.norm(pose.C - nav.C)) if nav is not None else None,
            "turned_deg": float(np.degrees(np.linalg.norm(matrix_to_rotvec(nav.R.T @ pose.R))))
            if nav is not None else None,
            "prior_w": [None if not np.isfinite(x) else float(x) for x in prior_w[iid]] if iid in prior_w else None,
            "prior_rejected": prior_off.get(iid, [])})
    return rows


def gnss_strip_check(block: ImageBlock, at: ATResult) -> dict[str, dict]:
    """For an adjustment without GNSS offsets per strip: whether its GNSS errors (navigation minus adjusted frame
    centre, the positions a test rejected left out) share an offset per flight strip (:func:`.strips.strip_check`);
    empty when it estimated the offsets."""
    if at.gnss_strips():
        return {}
    rejected = {iid for iid, part in at.prior_rejections() if part == "position"}
    err, sigma, exposure = {}, {}, {}
    for run in at.runs:
        for iid, frame in run.frames.items():
            img = block.images[iid]
            if img.pose_approx is not None and img.sigma_position is not None and iid not in rejected:
                err[iid] = img.pose_approx.C - frame.C
                sigma[iid] = img.sigma_position
                exposure[iid] = img.exposure or iid
    return strip_check(flight_strips(block), err, sigma, exposure) if err else {}


def ray_counts(ties: TiePoints, at: ATResult, top: int = RAYS_TOP) -> dict:
    """How many rays the adjusted tie points kept: ``points[i]`` tie points with ``rays[i]`` observations not
    rejected (2 .. ``top - 1``, and in the last bin ``top`` or more), their mean, and the share of two-ray points
    (badly constrained: a blunder among two rays cannot be told from the other ray)."""
    n = np.bincount(ties.obs_track[~at.obs_rejected], minlength=ties.n_tracks)
    n = n[(n >= 2) & np.isfinite(at.xyz[:, 0])]
    hist = np.bincount(np.minimum(n, top), minlength=top + 1)[2:]
    return {"rays": list(range(2, top + 1)), "points": hist.tolist(),
            "mean_rays": float(n.mean()) if len(n) else None,
            "two_ray_share": float(np.mean(n == 2)) if len(n) else None}


def block_datum(at: ATResult) -> dict | None:
    """The whole block's datum shift (control frame - GNSS frame, metres) with its standard deviations (None where
    unknown): IAT's as its run estimated it (marginal, see ``BundleOptions.marginal_max_images``); HAT's as the nadir
    run estimated it, refined from all control measurements (:func:`.hierarchical.datum_correction`). None without
    runs."""
    if "datum_shift" in at.extra:
        shift, std = np.asarray(at.extra["datum_shift"]), np.asarray(at.extra["datum_shift_std"])
    elif at.runs:
        shift, std = at.runs[0].result.datum_shift, at.runs[0].result.datum_shift_std
    else:
        return None
    return {"shift_m": shift.tolist(), "std_m": std.tolist() if np.all(np.isfinite(std)) else None}


def block_report(block: ImageBlock, ties: TiePoints, at: ATResult) -> dict:
    """Figures of the whole adjustment (combined over runs)."""
    runs = [run_statistics(r) | {"reliability": reliability(r, ties, block)} for r in at.runs]
    obs, v = accepted_residuals(at)
    obs_ok = ~at.obs_rejected
    chi = sum(r.result.sigma0**2 * r.result.redundancy for r in at.runs)
    dof = sum(r.result.redundancy for r in at.runs)
    sigma0 = float(np.sqrt(chi / max(dof, 1)))
    check = {}
    for split in SPLITS:
        names, err = check_point_errors(block, at.poses, split)
        xy, z = rms_xy_z(err)
        check[split] = {"n": len(names), "rms_xy_m": xy, "rms_z_m": z}
    internal = {}
    for split in SPLITS:
        std = tie_point_std(block, ties, at.poses, at.xyz, obs_ok, 1.0, at.sigma0_px(), split)
        xy, z = std_xy_z(std)
        internal[split] = {"points": int(np.isfinite(std[:, 0]).sum()), "std_xy_m": xy, "std_z_m": z}
    return {"mode": at.mode, "connection": at.connection, "images": len(at.poses), "sigma0": sigma0,
            "sigma0_px": at.sigma0_px(), "runs": runs, "check_points": check, "internal_accuracy": internal,
            "datum": block_datum(at),
            "ground_points": ground_point_residuals(block, at.poses, *at.control_rejections()),
            "weakest_control": weakest_control(runs),
            "boresight": boresight(block, at.poses), "mounting": mounting(block, at),
            "self_calibration": self_calibration(block, at),
            "calibration_run": run_statistics(at.calibration) | {
                "cameras_missing": sorted({block.images[i].camera_id for i in at.poses}
                                          - {block.images[i].camera_id for i in at.calibration.poses})}
            if at.calibration is not None else None,
            "wall_s": at.wall_s,
            "gnss_strips": at.gnss_strips(), "gnss_strip_check": gnss_strip_check(block, at),
            "blunder_percent": float(100.0 * at.obs_rejected.mean()) if ties.n_obs else 0.0,
            "tie_point_rays": ray_counts(ties, at), "image_residual_fields": camera_residual_fields(
                block, ties, obs, v), "images_table": image_statistics(block, ties, at, obs, v)}


def quality_layers(block: ImageBlock, ties: TiePoints, at: ATResult, cell: float,
                   views: str = "all") -> dict[str, Raster]:
    """CBA layers and intersection error maps (see the module docstring).

    ``views``: ``all`` uses the combined adjustment's point covariances and every ray; ``nadir`` or
    ``oblique`` count only those views' rays and intersect the points from them with the adjusted orientations
    held fixed."""
    ok = ~at.obs_rejected
    xyz = at.xyz
    if views == "all":
        rays = np.bincount(ties.obs_track[ok], minlength=ties.n_tracks).astype(np.float64)
        std = np.sqrt(np.abs(np.diagonal(at.xyz_cov, axis1=1, axis2=2)))
    else:
        if views not in SPLITS:
            raise ConfigError(f"layer views '{views}' unknown (use {', '.join(SPLITS)})")
        img_view = np.array([block.images[i].view for i in ties.image_ids], dtype=object)
        in_split = (img_view == "nadir") if views == "nadir" else (img_view != "nadir")
        sel = ok & in_split[ties.obs_image]
        rays = np.bincount(ties.obs_track[sel], minlength=ties.n_tracks).astype(np.float64)
        std = tie_point_std(block, ties, at.poses, xyz, ok, 1.0, at.sigma0_px(), views)
        rays[rays < 2] = np.nan
    fin = np.isfinite(xyz[:, 0])
    # the grid covers the bulk of the points (a few badly determined points far away must not blow it up)
    lo = np.percentile(xyz[fin, :2], 0.5, axis=0) - cell
    hi = np.percentile(xyz[fin, :2], 99.5, axis=0) + cell
    fin &= np.all((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi), axis=1)
    xyz = np.where(fin[:, None], xyz, np.nan)
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    layers = {
        "cba_rays": grid_layer(xyz[:, :2], np.where(fin, rays, np.nan), cell, block.crs, "mean", bounds),
        "cba_std_xy": grid_layer(xyz[:, :2], np.hypot(std[:, 0], std[:, 1]) / np.sqrt(2), cell, block.crs,
                                 "median", bounds),
        "cba_std_z": grid_layer(xyz[:, :2], std[:, 2], cell, block.crs, "median", bounds),
    }
    for name, poses in (("before", {i: im.pose_approx for i, im in block.images.items()}), ("after", at.poses)):
        _, dist = intersect_ties(block, ties, poses, ok)
        per_track = np.sqrt(np.bincount(ties.obs_track[ok], np.nan_to_num(dist[ok]) ** 2, ties.n_tracks)
                            / np.maximum(rays, 1))
        layers[f"intersection_error_{name}"] = grid_layer(xyz[:, :2], np.where(fin & (rays >= 2), per_track,
                                                                                 np.nan), cell, block.crs,
                                                           "median", bounds)
    return layers


def write_layers(layers: dict[str, Raster], folder: Path) -> list[str]:
    """GeoTIFF + coloured PNG per layer (intersection error maps share one colour scale). Returns file names."""
    from ..io.geotiff import write_geotiff, write_png

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    err = [layers[k].data for k in layers if k.startswith("intersection_error")]
    hi = float(np.nanpercentile(np.concatenate([e.ravel() for e in err]), 98)) if err else None
    for name, r in layers.items():
        write_geotiff(folder / f"{name}.tif", r)
        scale = (0.0, hi) if name.startswith("intersection_error") else (None, None)
        write_png(folder / f"{name}.png", colourise(r.data, *scale))
        files += [f"{name}.tif", f"{name}.png"]
    return files


def png_base64(rgb: np.ndarray) -> str:
    """An RGB image ``(rows, cols, 3)`` uint8 as base64 PNG text (for ``data:`` URIs)."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    return base64.b64encode(buf.tobytes()).decode("ascii") if ok else ""


def format_value(v) -> str:
    """A value for an HTML table cell: 4 significant digits, lists joined, text escaped, None as '-'."""
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return ", ".join(format_value(x) for x in v)
    return html.escape(str(v))


def _bars_svg(counts: np.ndarray, title: str, first: str, last: str) -> str:
    """A bar chart of ``counts (b,)`` as inline SVG, ``first`` and ``last`` written under the outer bars."""
    w, hh, b = 420, 160, len(counts)
    top = max(int(counts.max()), 1) if b else 1
    bars = "".join(f'<rect x="{30 + i * (w - 40) / b:.1f}" y="{hh - 20 - 120 * c / top:.1f}" '
                   f'width="{(w - 40) / b - 1:.1f}" height="{120 * c / top:.1f}" fill="#3b528b"/>'
                   for i, c in enumerate(counts))
    return (f'<svg width="{w}" height="{hh}" xmlns="http://www.w3.org/2000/svg"><text x="30" y="14" '
            f'font-size="12">{html.escape(title)}</text>{bars}<text x="30" y="{hh - 4}" font-size="10">'
            f'{html.escape(first)}</text><text x="{w - 60}" y="{hh - 4}" font-size="10">{html.escape(last)}</text>'
            '</svg>')


def _histogram_svg(values: np.ndarray, title: str, bins: int = 30) -> str:
    v = values[np.isfinite(values)]
    if len(v) == 0:
        return ""
    h, e = np.histogram(v, bins=bins, range=(0, float(np.percentile(v, 99)) or 1.0))
    return _bars_svg(h, title, "0", f"{e[-1]:.3g}")


def _field_svg(field: dict, width: int = 300) -> str:
    """The residual field of one camera as inline SVG: per cell an arrow from its centre along the mean residual,
    the longest drawn as nine tenths of a cell."""
    cols, rows = field["cells"]
    cw, ch = field["cell_px"]
    scale_img = width / (cols * cw)
    height = int(round(rows * ch * scale_img))
    means = [(i, j, m) for j, row in enumerate(field["mean_px"]) for i, m in enumerate(row) if m is not None]
    longest = max((float(np.hypot(*m)) for _, _, m in means), default=0.0)
    k = 0.9 * min(cw, ch) * scale_img / longest if longest > 0 else 0.0
    grid = "".join(f'<line x1="{i * width / cols:.1f}" y1="0" x2="{i * width / cols:.1f}" y2="{height}" '
                   'stroke="#ddd"/>' for i in range(1, cols))
    grid += "".join(f'<line x1="0" y1="{j * height / rows:.1f}" x2="{width}" y2="{j * height / rows:.1f}" '
                    'stroke="#ddd"/>' for j in range(1, rows))
    arrows = ""
    for i, j, (du, dv) in means:
        x, y = (i + 0.5) * width / cols, (j + 0.5) * height / rows
        arrows += (f'<circle cx="{x:.1f}" cy="{y:.1f}" r="1.5" fill="#440154"/><line x1="{x:.1f}" y1="{y:.1f}" '
                   f'x2="{x + k * du:.1f}" y2="{y + k * dv:.1f}" stroke="#440154" stroke-width="1.5"/>')
    return (f'<svg width="{width}" height="{height + 16}" xmlns="http://www.w3.org/2000/svg">'
            f'<rect width="{width}" height="{height}" fill="none" stroke="#888"/>{grid}{arrows}'
            f'<text x="2" y="{height + 12}" font-size="10">longest arrow {longest:.3f} px</text></svg>')


def _rejection_text(g: dict) -> str:
    """What the adjustment rejected of a ground point (its coordinates, measurements in images), for a table cell."""
    parts = (["coordinates"] if g.get("rejected_coordinates") else []) + \
        [f"measurement in {i}" for i in g.get("rejected_images", [])]
    return html.escape("; ".join(parts)) if parts else "-"


def _image_rows(images: list[dict]) -> str:
    return "".join(f"<tr><td>{html.escape(str(r['image']))}</td><td>{html.escape(str(r['view']))}</td>"
                   f"<td>{html.escape(r['run'])}</td><td>{r['observations']}</td><td>{r['rejected']}</td>"
                   f"<td>{format_value(r['rms_px'])}</td><td>{format_value(r['std_position_m'])}</td>"
                   f"<td>{format_value(r['moved_m'])}</td><td>{format_value(r['turned_deg'])}</td></tr>"
                   for r in images)


def _report_extras(report: dict) -> list[str]:
    """The HTML of the image residual fields, the images with the largest residuals and fewest observations, and
    the tie points' ray counts (the parts of :func:`block_report` beyond the run tables)."""
    parts = []
    fields = report.get("image_residual_fields") or {}
    if fields:
        rows = "".join(f"<tr><td>{html.escape(c)}</td><td>{f['observations']}</td>"
                       f"<td>{format_value(f['cell_mean_rms_px'])}</td><td>{format_value(f['noise_rms_px'])}</td>"
                       f"<td>{format_value(f['systematic_rms_px'])}</td>"
                       f"<td>{format_value(f['radial']['mean_px'])}</td></tr>" for c, f in fields.items())
        parts.append("<h2>Image residuals by position in the frame</h2><p>Per camera the mean residual (observed "
                     "minus adjusted projection) in cells of the frame. Noise alone gives cell means of the RMS in "
                     "'noise'; 'systematic' is what it does not explain (an error of the camera model). The radial "
                     "profile is the mean residual away from the principal point in rings out to the corners.</p>"
                     "<table><tr><th>camera</th><th>observations</th><th>cell means RMS [px]</th><th>noise [px]</th>"
                     f"<th>systematic [px]</th><th>radial profile [px]</th></tr>{rows}</table>")
        parts.extend(f"<figure>{_field_svg(f)}<figcaption>{html.escape(c)}</figcaption></figure>"
                     for c, f in fields.items())
    images = report.get("images_table") or []
    if images:
        head = ("<tr><th>image</th><th>view</th><th>run</th><th>observations</th><th>rejected</th><th>RMS [px]</th>"
                "<th>std centre [m]</th><th>moved [m]</th><th>turned [deg]</th></tr>")
        worst = sorted((r for r in images if r["rms_px"] is not None), key=lambda r: -r["rms_px"])[:WORST_IMAGES]
        fewest = sorted(images, key=lambda r: r["observations"])[:WORST_IMAGES]
        parts.append(f"<h2>Images</h2><p>{len(images)} adjusted images (every one in report.json). Moved and turned: "
                     "from the navigation orientation to the adjusted one.</p><h3>Largest residuals</h3>"
                     f"<table>{head}{_image_rows(worst)}</table><h3>Fewest observations</h3>"
                     f"<table>{head}{_image_rows(fewest)}</table>")
    rejected = [(r, part) for r in images for part in r.get("prior_rejected") or []]
    if rejected:
        rows = "".join(f"<tr><td>{html.escape(str(r['image']))}</td><td>{html.escape(r['run'])}</td>"
                       f"<td>{PRIOR_PART_LABELS[PRIOR_PARTS.index(part)]}</td>"
                       f"<td>{format_value(r['prior_w'][PRIOR_PARTS.index(part)])}</td>"
                       f"<td>{format_value(r['moved_m'])}</td><td>{format_value(r['turned_deg'])}</td></tr>"
                       for r, part in rejected)
        parts.append("<h2>Rejected EO priors</h2><p>Priors that do not fit the orientation the image's own tie points "
                     "give (normalised difference above the blunder threshold): the image was adjusted without "
                     "them. Moved and turned: from the navigation orientation to the adjusted one.</p><table><tr>"
                     "<th>image</th><th>run</th><th>prior</th><th>normalised difference</th><th>moved [m]</th>"
                     f"<th>turned [deg]</th></tr>{rows}</table>")
    strips = report.get("gnss_strips") or {}
    if strips:
        drift = any(d["drift_m_per_km"] is not None for d in strips.values())

        def triple(v: list[float] | None, sd: list[float] | None) -> str:
            return "".join(f"<td>{format_value(a)} &plusmn; {format_value(b)}</td>" for a, b in zip(v, sd)) if v \
                else "<td></td>" * 3

        rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{d['images']}</td>"
                       + triple(d["offset_m"], d["offset_std_m"])
                       + (triple(d["drift_m_per_km"], d["drift_std_m_per_km"]) if drift else "") + "</tr>"
                       for n, d in strips.items())
        parts.append("<h2>GNSS offsets per strip</h2><p>The error of each flight strip's GNSS positions (GNSS minus "
                     "adjusted centre), estimated in the adjustment; with a datum shift, from the block's mean "
                     "(which the shift takes). Standard deviations with the orientations held, the heads of one "
                     "exposure counted as one GNSS position.</p><table><tr>"
                     "<th>strip</th><th>images</th><th>offset X [m]</th><th>offset Y [m]</th><th>offset Z [m]</th>"
                     + ("<th>drift X [m/km]</th><th>drift Y [m/km]</th><th>drift Z [m/km]</th>" if drift else "")
                     + f"</tr>{rows}</table>")
    check = {n: d for n, d in (report.get("gnss_strip_check") or {}).items() if d["flagged"]}
    if check:
        rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{d['images']}</td>"
                       + "".join(f"<td>{format_value(m)} ({format_value(w)})</td>" for m, w in zip(d["mean_m"], d["w"]))
                       + "</tr>" for n, d in check.items())
        parts.append("<h2>GNSS offsets per strip suspected</h2><p>The GNSS errors (navigation minus adjusted centre) "
                     "of these strips share an offset from the block's mean, in brackets in standard deviations of a "
                     "strip's mean: the trajectory was probably not processed as one piece. Estimate an offset per "
                     "strip (aerotri.gnss_strips = shift, or drift).</p><table><tr><th>strip</th><th>images</th>"
                     f"<th>X [m]</th><th>Y [m]</th><th>Z [m]</th></tr>{rows}</table>")
    parts.extend(_reliability_html(report.get("runs") or []))
    rays = report.get("tie_point_rays")
    if rays and rays["mean_rays"] is not None:
        parts.append(f"<h2>Tie point rays</h2><p>Mean {rays['mean_rays']:.2f} rays per adjusted tie point; "
                     f"{100 * rays['two_ray_share']:.1f} % have two.</p>"
                     + _bars_svg(np.array(rays["points"]), "tie points per number of kept rays", "2",
                                 f"{rays['rays'][-1]}+"))
    return parts


def _variance_html(runs: list[dict]) -> list[str]:
    """The HTML of the runs' :func:`variance_table`."""
    rows = "".join(f"<tr><td>{html.escape(r['name'])}</td><td>{html.escape(v['label'])}</td><td>{v['count']}</td>"
                   f"<td>{format_value(v['redundancy'])}</td><td>{format_value(v['factor'])} &plusmn; "
                   f"{format_value(v['factor_std'])}</td><td>{format_value(v.get('sigma_px'))}</td>"
                   f"<td>{format_value(v.get('estimated_sigma_px'))}</td>"
                   f"<td>{' / '.join(format_value(f) for f in v['sigma_scale']) if 'sigma_scale' in v else ''}</td>"
                   "</tr>"
                   for r in runs for v in r.get("variance_components") or [])
    if not rows:
        return []
    return ["<h2>Variance components</h2><p>Per group of observations, how many times its a priori sigmas its "
            "residuals show its errors to be (the weighted squares of its residuals over its share of the "
            "redundancy), with the estimate's standard deviation: 1 means weighted as it should be. The tie "
            "measurements' sigma is estimated and the adjustment solved again with it when they differ by more "
            "than aerotri.tie_sigma_tolerance (sigma_px_given in the runs table is the one configured); so are "
            "the GNSS positions' and IMU attitudes' sigmas, scaled up by their group's factor when it exceeds 1 by "
            "more than aerotri.prior_sigma_tolerance and by more than 3 of its standard deviations (never tightened: "
            "on a small block a factor below 1 scatters, and a weight too large costs more than one too small), and "
            "the control points' image measurements' sigmas, scaled by their factor either way when it is off by "
            "more than aerotri.tie_sigma_tolerance. The scales applied in all (X / Y / Z for the GNSS and IMU) are "
            "in the last column, and a scaled group's factor is then near 1. A group still far "
            "from 1 is weighted wrongly against the others, and the standard deviations and tests of what it "
            "determines are off by about that factor: scale its sigmas (GNSS and IMU: the images' sigma_position, "
            "sigma_attitude or aerotri.default_sigma_*; control points: the sigmas of their coordinates, and of "
            "their image measurements with aerotri.control_sigma_estimate off). With a redundancy of a few tens "
            "the estimate itself is rough. The redundancy "
            "numbers are those of the blunder tests (the priors' with the other images held, the control points' "
            "with the images held).</p><table><tr><th>run</th><th>group</th><th>observations</th>"
            "<th>redundancy</th><th>factor</th><th>a priori sigma [px]</th>"
            f"<th>estimated sigma [px]</th><th>sigma scale X / Y / Z</th></tr>{rows}</table>"]


def _reliability_html(runs: list[dict]) -> list[str]:
    """The HTML of the runs' :func:`reliability`: tie measurements by rays, EO priors, control points."""
    rel = [(r["name"], r["reliability"]) for r in runs if r.get("reliability")]
    if not any(x["ties"] or x["priors"] or x["control_points"] for _, x in rel):
        return []
    power = 100 * rel[0][1]["power"]
    parts = [f"<h2>Reliability</h2><p>The smallest error each blunder test finds with {power:.0f} % probability at the "
             "rejection threshold (internal reliability, Baarda's minimal detectable blunder), and redundancy "
             "numbers: the share of an error that shows in the residual. Smaller errors can pass undetected; below "
             "a redundancy of 0.1 an observation is hardly controlled by the others.</p>"]
    rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{t['rays']}</td><td>{t['measurements']}</td>"
                   f"<td>{format_value(t['redundancy_mean'])}</td><td>{format_value(t['mdb_px_median'])}</td>"
                   f"<td>{format_value(t['mdb_px_p95'])}</td><td>{format_value(t['point_shift_m_median'])}</td>"
                   f"<td>{format_value(t['point_shift_m_p95'])}</td><td>{format_value(t['bnr_median'])}</td>"
                   "</tr>" for n, x in rel for t in x["ties"])
    if rows:
        parts.append("<h3>Tie measurements</h3><p>An undetected error of the detectable size, in its worst direction, "
                     "moves its tie point by the distance given (the images held); the bias-to-noise ratio is the most "
                     "it moves any adjusted value, in that value's standard deviations.</p>"
                     "<table><tr><th>run</th><th>rays</th><th>measurements</th>"
                     "<th>mean redundancy</th><th>detectable error, median [px]</th><th>95 % [px]</th>"
                     "<th>moves its point, median [m]</th><th>95 % [m]</th><th>bias-to-noise ratio, median</th></tr>"
                     f"{rows}</table>")
    rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{label}</td><td>{p['images']}</td>"
                   f"<td>{format_value(p['median'])}</td><td>{format_value(p['max'])}</td>"
                   f"<td>{format_value(p['effect_median'])}</td><td>{format_value(p['effect_max'])}</td></tr>"
                   for n, x in rel for key, label in (("position_m", "GNSS position [m]"),
                                                      ("attitude_deg", "IMU attitude [deg]"))
                   if (p := x["priors"].get(key)))
    if rows:
        parts.append("<h3>EO priors</h3><table><tr><th>run</th><th>prior</th><th>images</th>"
                     "<th>detectable error X Y Z, median</th><th>largest</th>"
                     f"<th>its effect on the orientation, median</th><th>largest</th></tr>{rows}</table>")
    rows = "".join(f"<tr><td>{html.escape(d['name'])}</td><td>{html.escape(n)}</td>"
                   f"<td>{format_value(d['redundancy'])}</td><td>{format_value(d['mdb_m'])}</td>"
                   f"<td>{format_value(d.get('datum_effect_m'))}</td></tr>"
                   for n, x in rel for d in x["control_points"])
    if rows:
        parts.append("<h3>Control points</h3><p>Moves the datum: how far an undetected error of the detectable size "
                     "on each axis would shift the whole block.</p><table><tr><th>point</th><th>run</th>"
                     "<th>redundancy X Y Z</th><th>detectable error X Y Z [m]</th><th>moves the datum [m]</th></tr>"
                     f"{rows}</table>")
    return parts


def _calibration_html(cameras: dict[str, dict], sub_block: dict | None) -> list[str]:
    """The HTML of the report's :func:`self_calibration`: a table of parameters per camera, its strong correlations
    and the corner it moves the most; ``sub_block`` the :func:`run_statistics` of HAT's calibration sub-block."""
    if not cameras:
        return []
    source = "the run holding most of its images" if sub_block is None else (
        f"the calibration sub-block ({sub_block['images']} images of all views nearest the block's centre, adjusted "
        f"together before the hierarchical runs, which held the cameras; sigma0 {format_value(sub_block['sigma0'])}, "
        f"{sub_block['rejected']} of {sub_block['observations']} observations rejected, "
        f"{format_value(sub_block['wall_s'])} s)")
    if sub_block is not None and sub_block.get("cameras_missing"):
        source += (" (" + ", ".join(html.escape(c) for c in sub_block["cameras_missing"]) + ": no image in the "
                   "sub-block, held at the imported calibration)")
    parts = [f"<h2>Self-calibration</h2><p>Per camera, from {source}: the parameters before "
             "and after the adjustment, the correction with its marginal standard deviation, and t, the correction "
             f"in standard deviations (significant above {SIGNIFICANCE_T:g}: a two-sided test at 5 %). Principal "
             "point in pixels from the centre of the top-left pixel. Significant is not the same as large: with "
             "hundreds of thousands of measurements a correction can be significant while it changes the residuals "
             "by hundredths of a pixel, and parameters strongly correlated with one another or with the "
             "orientations (a focal length with the flying height, an oblique head's principal point with its "
             "boresight) move together, so that the corner shift overstates what the images see; judge a "
             "calibration by the check points too.</p>"]
    for cid, c in cameras.items():
        rows = "".join(f"<tr><td>{p['name']}</td><td>{p['unit']}</td><td>{format_value(p['initial'])}</td>"
                       f"<td>{format_value(p['adjusted'])}</td><td>{format_value(p['correction'])}</td>"
                       f"<td>{format_value(p['std'])}</td><td>{format_value(p['t'])}</td>"
                       f"<td>{'-' if p['significant'] is None else ('yes' if p['significant'] else 'no')}</td></tr>"
                       for p in c["parameters"])
        shift = format_value(c["corner_shift_px"]) + (
            "" if c["corner_shift_std_px"] is None else f" &plusmn; {format_value(c['corner_shift_std_px'])}")
        notes = [f"Run {html.escape(c['run'])}, {c['images']} images. The calibrated camera moves the image of the "
                 f"{c['corner']} corner by {shift} px."]
        if c.get("other_runs"):
            notes.append("Its images in the runs " + ", ".join(html.escape(r) for r in c["other_runs"]) + " were "
                         "adjusted with their own calibration of it, which the block does not keep (set "
                         "aerotri.calibration_images to calibrate once, before the runs).")
        if not c["marginal"]:
            notes.append("No standard deviations: the run has more images than aerotri.calibration_std_max_images "
                         "(raise it for the marginal covariance, which took about a minute on 3,000 images), or its "
                         "covariance could not be estimated.")
        if c["strong_correlations"]:
            notes.append("Strongly correlated (the block hardly tells them apart): " + ", ".join(
                f"{a} and {b} ({r:+.2f})" for a, b, r in c["strong_correlations"]) + ".")
        parts.append(f"<h3>{html.escape(cid)}</h3><p>{' '.join(notes)}</p><table><tr><th>parameter</th><th>unit</th>"
                     "<th>before</th><th>after</th><th>correction</th><th>std</th><th>t</th><th>significant</th>"
                     f"</tr>{rows}</table>")
    return parts


def html_report(report: dict, layers: dict[str, Raster], residuals_px: np.ndarray) -> str:
    """A self-contained HTML page: tables of the report, layer pictures and a residual histogram."""
    parts = [f"<h1>Aerial triangulation: {html.escape(report['mode'])}"
             f"{' (' + html.escape(report['connection']) + ')' if report.get('connection') else ''}</h1>",
             f"<p>{report['images']} images; sigma0 {report['sigma0']:.3f} "
             f"({report['sigma0_px']:.3f} px); wall time {report['wall_s']:.1f} s; "
             f"rejected {report['blunder_percent']:.2f} % of the observations.</p>"]
    datum = report.get("datum")
    if datum:
        std = datum["std_m"]
        parts.append("<p>Datum shift (control frame - GNSS frame): "
                     + ", ".join(f"{a} {v:.3f}" + (f" &plusmn; {sd:.3f}" if std else "")
                                 for a, v, sd in zip("XYZ", datum["shift_m"], std or [0.0] * 3))
                     + " m." + (" The orientations' marginal standard deviations (std_kind in the runs table) "
                                "include its uncertainty, common to all images." if std else "") + "</p>")
    if report.get("final_tests"):
        ft = report["final_tests"]
        parts.append(f"<p>{ft['tracks']} tie points that a run held with one or two rays (where its tests cannot "
                     f"find a blunder) were tested again over all their rays with the final orientations: "
                     f"{ft['rejected']} more observations rejected, {ft['restored']} a run had rejected kept.</p>")
    if report.get("rig_fusion"):
        rf = report["rig_fusion"]
        parts.append(f"<p>Rig fusion: the heads of {rf['exposures']} exposures ({rf['images']} images), adjusted apart "
                     f"in their view runs, were fused into one body each on the calibrated rig ({rf['iterations']} "
                     f"steps of the poses and the tie points, from the second on with a coarse step that settles the "
                     f"block's smooth modes; the last moved an exposure by at most "
                     f"{rf['last_step']:.2f} of its standard deviation). The heads moved by {rf['moved_deg']:.4f} deg "
                     f"and {rf['moved_m']:.3f} m RMS from their runs' orientations; the tie residuals went from "
                     f"{rf['rms_px_before']:.3f} to {rf['rms_px_after']:.3f} px RMS ({rf['left_out']} measurements "
                     "that did not fit the runs' solution left out)"
                     + ("; per run: " + ", ".join(f"{k} {v:.3f}" for k, v in rf["rms_px_by_group"].items())
                        if rf.get("rms_px_by_group") else "")
                     + ". The fused images' standard deviations hold "
                     "their body's own block and the block's smooth modes, its translation among them, with the rig "
                     "taken as exact. The runs' statistics below are those of the runs, before the fusion.</p>")
    if report.get("oblique_without_nadir"):
        parts.append(f"<p>{report['oblique_without_nadir']} oblique images have no nadir image in their exposure: "
                     "their runs started from the navigation data, not from the nadir run's corrections, and needed "
                     "a robust round. Import the block with its exposures (OPK columns exposure and head, or "
                     "<code>-o exposures=time</code> or <code>-o exposures=name</code>).</p>")
    keys = ["images", "points", "observations", "connection_points", "sigma_px_given", "sigma0_a_priori_px", "sigma0",
            "sigma0_px", "iterations", "rounds",
            "blunder_percent", "rms_image_px", "rms_control_m", "rms_prior_position_m", "rms_prior_attitude_deg",
            "datum_shift_m", "datum_shift_std_m", "median_std_attitude_deg", "median_std_position_m", "std_kind",
            "point_std_xy_m", "point_std_z_m", "wall_s"]
    head = "".join(f"<th>{html.escape(r['name'])}</th>" for r in report["runs"])
    rows = "".join(f"<tr><td>{k}</td>" + "".join(f"<td>{format_value(r.get(k))}</td>" for r in report["runs"]) + "</tr>"
                   for k in keys)
    parts.append(f"<h2>Runs</h2><table><tr><th></th>{head}</tr>{rows}</table>")
    parts.extend(_variance_html(report["runs"]))
    rows = "".join(f"<tr><td>{s}</td><td>{c['n']}</td><td>{format_value(c['rms_xy_m'])}</td>"
                   f"<td>{format_value(c['rms_z_m'])}</td>"
                   f"<td>{format_value(report['internal_accuracy'][s]['std_xy_m'])}</td>"
                   f"<td>{format_value(report['internal_accuracy'][s]['std_z_m'])}</td></tr>"
                   for s, c in report["check_points"].items())
    parts.append("<h2>Accuracy</h2><table><tr><th>views</th><th>check points</th><th>RMS XY [m]</th>"
                 f"<th>RMS Z [m]</th><th>tie std XY [m]</th><th>tie std Z [m]</th></tr>{rows}</table>")
    if report.get("ground_points"):
        rows = "".join(f"<tr><td>{html.escape(g['name'])}</td><td>{g['kind']}</td><td>{g['images']}</td>"
                       f"<td>{format_value(g['dx_m'])}</td><td>{format_value(g['dy_m'])}</td>"
                       f"<td>{format_value(g['dz_m'])}</td><td>{format_value(g['image_rms_px'])}</td>"
                       f"<td>{_rejection_text(g)}</td></tr>" for g in report["ground_points"])
        t = report.get("target_measurements")
        measured = "" if not t else (
            f"<p>Image measurements: {t['measured']} measured in the images (signalised targets, mode {t['mode']}, "
            f"median correlation {format_value(t['score_median'])}); {t['missed']} projections inside an image where "
            "no target was found" + ("" if t["imported_rms_px"] is None else
                                     f"; {format_value(t['imported_rms_px'])} px RMS from the imported measurements")
            + "." + ("" if not t.get("suspect") else
                     f" {len(t['suspect'])} imported measurements lie more than {SUSPECT_PX:g} px from the target "
                     "measured in the same image (the wrong spot or point, or a wrong match): "
                     + ", ".join(f"{html.escape(n)} in {html.escape(i)} ({d:.1f} px)" for n, i, d in t["suspect"][:10])
                     + ("..." if len(t["suspect"]) > 10 else "") + ".") + "</p>")
        m = report.get("manual_measurements") or {}
        if m.get("set") or m.get("removed") or m.get("skipped"):
            measured += (f"<p>Manual measurements (block/manual_measurements.json): {m['set']} set by the operator, "
                         f"{m['removed']} removed" + (f"; {m['skipped']} skipped: their points or images are not in "
                                                      "the block" if m.get("skipped") else "") + ".</p>")
        parts.append("<h2>Ground points (intersected from every image with its adjusted orientation, minus the "
                     f"given coordinates)</h2>{measured}<table><tr><th>point</th><th>kind</th><th>images</th>"
                     "<th>dX [m]</th><th>dY [m]</th><th>dZ [m]</th><th>image RMS [px]</th>"
                     f"<th>rejected by the adjustment</th></tr>{rows}</table>")
    if report.get("boresight"):
        rows = "".join(f"<tr><td>{h}</td><td>{format_value(b['mean_deg'])}</td>"
                       f"<td>{format_value(b['std_deg'])}</td></tr>"
                       for h, b in report["boresight"].items())
        parts.append("<h2>Boresight from adjusted orientations [deg]</h2><table><tr><th>head</th><th>mean</th>"
                     f"<th>std</th></tr>{rows}</table>")
    if report.get("mounting"):
        rows = "".join(f"<tr><td>{html.escape(c)}</td><td>{format_value(m['boresight_deg'])}</td>"
                       f"<td>{format_value(m.get('boresight_std_deg'))}</td><td>{format_value(m['offset_m'])}</td>"
                       f"<td>{format_value(m.get('offset_std_m'))}</td><td>{html.escape(m['run'])}</td><td>{m['images']}</td>"
                       "</tr>" for c, m in report["mounting"].items())
        parts.append("<h2>Mounting calibration (camera axes)</h2><table><tr><th>camera</th><th>boresight [deg]</th>"
                     "<th>std [deg]</th><th>centre offset [m]</th><th>std [m]</th><th>run</th><th>images</th></tr>"
                     f"{rows}</table>")
    parts.extend(_calibration_html(report.get("self_calibration") or {}, report.get("calibration_run")))
    parts.append("<h2>Image residuals</h2>" + _histogram_svg(np.linalg.norm(residuals_px, axis=1),
                                                             "|v| [px] of accepted observations"))
    parts.extend(_report_extras(report))
    parts.append("<h2>Layers</h2>")
    for name, r in layers.items():
        d = r.data[np.isfinite(r.data)]
        rng = f"{d.min():.3g} to {d.max():.3g}" if len(d) else "empty"
        parts.append(f"<figure><img alt='{name}' src='data:image/png;base64,{png_base64(colourise(r.data))}' "
                     f"style='image-rendering:pixelated;width:320px'><figcaption>{name} ({rng}; cell {r.cell} m)"
                     "</figcaption></figure>")
    style = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}td,th{border:1px solid #ccc;"
             "padding:3px 8px;text-align:right}figure{display:inline-block;margin:8px}")
    return f"<!DOCTYPE html><html><head><meta charset='utf-8'><style>{style}</style></head><body>" + \
        "".join(parts) + "</body></html>"
