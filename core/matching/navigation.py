"""Guided matching of an image pair whose navigation data are coarse.

With a low-grade GNSS/IMU (1 degree, 10 m) the epipolar band that holds a pair's matches is hundreds of pixels wide
(:func:`.features.pose_sigma_px`): most of the image. Searching it for every keypoint took twenty times as long as
the 25 px band of survey-grade navigation data, and let more wrong matches in. A pair whose band is wider than
:data:`WIDE_BAND_FACTOR` times ``band_px`` is matched in three steps instead:

1. Coarse matches: up to :data:`COARSE_KEYPOINTS` of A's keypoints (every k-th, so spread over the image) against
   all of B's by descriptor alone (mutual nearest neighbours passing Lowe's ratio test, by matrix products), kept
   where they lie inside the wide band and under a fundamental matrix (:func:`.features.verify`). Fewer than
   :data:`ENOUGH_COARSE` and every keypoint of A is tried; fewer than :data:`MIN_COARSE` still and the pair gets no
   matches (the one such pair among 16 of the demo block had 19 matches in the wide band, none from the true poses).
2. B's pose corrected (:func:`corrected_pose`): the rotation and centre shift of B that bring each coarse match
   onto its epipolar segment (the ray of A's keypoint between the scene's lowest and highest heights, projected
   into B). Gauss-Newton on the 2D offsets from the segments, with Tukey weights, and the pair's prior sigmas as a
   prior on the correction. The prior holds what the matches cannot fix: a shift of B along parallel epipolar lines
   only moves the points' heights within the segments.
3. Fine matches: :func:`.features.guided_match` of every keypoint with the corrected pose, in a band of ``band_px``,
   or three times the correction's residual and posterior standard deviation where that is wider.

On the rendered demo block with each exposure's navigation data 1 degree and 10 m off, 16 sample pairs gave as many
matches as from the true poses in the 25 px band, as often correct, in a twelfth of the wide band's time; the
``match`` stage of the 125 images took 214 s instead of 778 s, with 123,387 tracks instead of 111,825
(``benchmarks/bench_match_nav.py``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..geometry.projection import intersect_with_plane_z, project
from ..geometry.rotations import rotvec_to_matrix
from ..model import CameraModel, Pose
from .features import MatchOptions, epipolar_segments, guided_match, segment_distance, verify

WIDE_BAND_FACTOR = 2.0
"""A pair whose epipolar band is wider than this many times ``band_px`` is matched by :func:`coarse_guided_match`."""


def needs_correction(band: np.ndarray | float, band_px: float) -> np.ndarray | bool:
    """Whether pairs of epipolar band half-widths ``band`` (pixels) are matched by :func:`coarse_guided_match`."""
    return band > WIDE_BAND_FACTOR * band_px

COARSE_KEYPOINTS = 1000
"""Keypoints of A tried first for the coarse matches."""

ENOUGH_COARSE = 24
"""Fewer verified coarse matches from the first keypoints, and every keypoint of A is tried."""

MIN_COARSE = 12
"""Fewest verified coarse matches that correct B's pose (six parameters, two equations a match, outliers)."""

NOISE_FLOOR_PX = 0.5
"""Least residual scale of the correction (pixels): keypoint noise, so that Tukey's weights never cut good matches."""


def descriptor_matches(des_a: np.ndarray, des_b: np.ndarray, ratio: float, rows: int = 1024) -> np.ndarray:
    """Mutual nearest neighbours of ``des_a (n, d)`` among all of ``des_b (m, d)`` (float32) that pass Lowe's ratio
    test: ``(k, 2)`` index pairs. Squared distances by matrix products, ``rows`` rows of A at a time."""
    n, m = len(des_a), len(des_b)
    if n == 0 or m < 2:
        return np.zeros((0, 2), np.int64)
    nb = np.einsum("ij,ij->i", des_b, des_b)
    nearest = np.empty(n, np.int64)
    passed = np.empty(n, bool)
    col_d = np.full(m, np.inf, np.float32)
    col_a = np.full(m, -1, np.int64)
    for r in range(0, n, rows):
        a = des_a[r:r + rows]
        d = np.einsum("ij,ij->i", a, a)[:, None] + nb[None] - 2.0 * (a @ des_b.T)
        np.maximum(d, 0.0, out=d)
        best = np.argmin(d, axis=0)
        best_d = d[best, np.arange(m)]
        better = best_d < col_d
        col_d[better] = best_d[better]
        col_a[better] = best[better] + r
        here = np.arange(len(a))
        near = np.argmin(d, axis=1)
        d1 = d[here, near]
        d[here, near] = np.inf
        nearest[r:r + rows] = near
        passed[r:r + rows] = np.sqrt(d1) <= ratio * np.sqrt(d.min(axis=1))
    mutual = col_a[nearest] == np.arange(n)
    keep = passed & mutual
    return np.stack([np.flatnonzero(keep), nearest[keep]], 1)


def _segment_offsets(p_lo: np.ndarray, p_hi: np.ndarray, uv_b: np.ndarray, cam_b: CameraModel, pose_b: Pose,
                     correction: np.ndarray) -> np.ndarray:
    """Offsets ``(2n,)`` (u, v of each point in turn) of ``uv_b (n, 2)`` from the closest points of the segments
    ``p_lo -> p_hi`` (world, ``(n, 3)``) projected into B, whose pose is corrected by ``correction``: a rotation
    vector in B's camera frame and a shift of its centre (world metres)."""
    pose = Pose(rotvec_to_matrix(correction[:3]) @ pose_b.R, pose_b.C + correction[3:])
    s0, _ = project(cam_b, pose, p_lo)
    s1, _ = project(cam_b, pose, p_hi)
    d = s1 - s0
    t = np.clip(np.sum((uv_b - s0) * d, 1) / np.maximum(np.sum(d * d, 1), 1e-12), 0.0, 1.0)
    return (uv_b - (s0 + t[:, None] * d)).ravel()


def corrected_pose(uv_a: np.ndarray, uv_b: np.ndarray, cam_a: CameraModel, pose_a: Pose, cam_b: CameraModel,
                   pose_b: Pose, z_lo: float, z_hi: float, sigma_attitude: float, sigma_position: float,
                   iterations: int = 10) -> tuple[Pose, float]:
    """B's pose corrected so that the matches ``uv_a, uv_b (n, 2)`` lie on their epipolar segments between the heights
    ``z_lo`` and ``z_hi`` (module docstring, step 2), A's pose held.

    ``sigma_attitude`` (radians) and ``sigma_position`` (metres) are the prior sigmas of the correction: the pair's
    relative navigation errors. Returns the corrected pose and the band half-width's standard deviation (pixels):
    the robust residual scale and the posterior standard deviation of the matches' offsets from their segments (RMS
    over the matches), in quadrature."""
    p_lo = intersect_with_plane_z(cam_a, pose_a, uv_a, z_lo)
    p_hi = intersect_with_plane_z(cam_a, pose_a, uv_a, z_hi)
    ok = np.all(np.isfinite(p_lo), axis=1) & np.all(np.isfinite(p_hi), axis=1)  # rays that meet both heights
    p_lo, p_hi, uv_b = p_lo[ok], p_hi[ok], uv_b[ok]
    prior = np.diag(np.r_[np.full(3, max(sigma_attitude, 1e-6) ** -2), np.full(3, max(sigma_position, 1e-3) ** -2)])
    steps = np.r_[np.full(3, 1e-6), np.full(3, 1e-3)]
    x = np.zeros(6)
    normal = prior
    scale = NOISE_FLOOR_PX
    for _ in range(iterations):
        r = _segment_offsets(p_lo, p_hi, uv_b, cam_b, pose_b, x)
        jac = np.stack([(_segment_offsets(p_lo, p_hi, uv_b, cam_b, pose_b, x + np.eye(6)[k] * steps[k]) - r)
                        / steps[k] for k in range(6)], 1)
        norm = np.hypot(r[0::2], r[1::2])
        scale = max(float(np.median(norm)) / 1.1774, NOISE_FLOOR_PX)  # the Rayleigh median: per-axis sigma
        c = 4.685 * scale
        w = np.repeat(np.where(norm < c, (1.0 - (norm / c) ** 2) ** 2, 0.0), 2) / scale**2
        normal = (jac * w[:, None]).T @ jac + prior
        step = -np.linalg.solve(normal, (jac * w[:, None]).T @ r + prior @ x)
        x += step
        if np.all(np.abs(step) < 0.01 * steps):
            break
    # the posterior variance of each match's offset from its segment (along the segment the correction may be
    # undetermined, as the matches' heights are unknown: that moves no point off its segment), RMS over the matches
    rows = jac @ np.linalg.inv(normal)
    shift = float(np.sqrt(np.mean(np.einsum("ij,ij->i", rows, jac)) * 2.0))
    return Pose(rotvec_to_matrix(x[:3]) @ pose_b.R, pose_b.C + x[3:]), float(np.hypot(scale, shift))


def coarse_guided_match(uv_a: np.ndarray, des_a: np.ndarray, uv_b: np.ndarray, des_b: np.ndarray,
                        cam_a: CameraModel, pose_a: Pose, cam_b: CameraModel, pose_b: Pose, opt: MatchOptions,
                        band: float, sigma_attitude: float, sigma_position: float) -> np.ndarray:
    """Matches ``(k, 2)`` of a pair whose navigation data are coarse (module docstring): ``band`` is the wide band
    the prior sigmas give (pixels), ``sigma_attitude`` (radians) and ``sigma_position`` (metres) the pair's relative
    navigation errors. Unverified, like :func:`.features.guided_match`'s."""
    coarse = np.zeros((0, 2), np.int64)
    for stride in dict.fromkeys((max(1, len(uv_a) // COARSE_KEYPOINTS), 1)):  # a subset first, then all
        tried = np.arange(0, len(uv_a), stride)
        coarse = descriptor_matches(des_a[tried], des_b, opt.ratio)
        coarse[:, 0] = tried[coarse[:, 0]]
        if len(coarse):
            s0, s1 = epipolar_segments(uv_a[coarse[:, 0]], cam_a, pose_a, cam_b, pose_b, opt.z_lo, opt.z_hi)
            coarse = coarse[segment_distance(uv_b[coarse[:, 1]], s0, s1) <= band]
        if len(coarse) >= MIN_COARSE:
            coarse = coarse[verify(uv_a[coarse[:, 0]], uv_b[coarse[:, 1]], cam_a, cam_b, opt.ransac_px)]
        if len(coarse) >= ENOUGH_COARSE or stride == 1:
            break
    if len(coarse) < MIN_COARSE:
        return np.zeros((0, 2), np.int64)
    pose, sigma = corrected_pose(uv_a[coarse[:, 0]], uv_b[coarse[:, 1]], cam_a, pose_a, cam_b, pose_b, opt.z_lo,
                                 opt.z_hi, sigma_attitude, sigma_position)
    return guided_match(uv_a, des_a, uv_b, des_b, cam_a, pose_a, cam_b, pose,
                        replace(opt, band_px=max(opt.band_px, 3.0 * sigma)))
