"""HAT on the rig: the heads of each exposure fused after the runs.

HAT orients each view in a run of its own, so the five heads of one exposure are adjusted apart, each from its own
tie points, and none of them learns from the others. On a rigid camera system they are not apart: one body carries
them, and their relative orientation is the calibrated mounting. IAT with rig constraints (``BundleOptions.rig``)
uses this, and on the 3,000-image bench block its attitude errors were a fifth of HAT's (0.0008 against 0.0040 deg).

This module gives HAT the same after its runs, by block Gauss-Seidel on the rig-constrained problem, starting from
the runs' solution:

1. Each exposure becomes one body: its reference head's pose (the rig's first head present), the other heads
   placed by the rig (:func:`rig_relations`): the block's calibrated one, or, when the runs calibrate the
   mountings, the one their orientations give (:func:`.hierarchical.runs_rig`).
2. Pose step: each exposure's rotation and centre from the tie measurements of all its heads, the tie points held
   (a Gauss-Newton step of the joint resection; the heads' 6 x 6 normal blocks mapped to the body's parameters,
   ``A^T N A`` with ``A`` moving a head's centre by the body's rotation about the reference head's).
3. Point step: the tie points from all their rays with the poses held, on the same linearisation with the pose
   step applied (the residuals less ``J_pose dpose``).
4. From the second step on, a coarse step first (:func:`_coarse_step`): the bodies' steps restricted to smooth
   fields over the block (polynomials of the bodies' positions, :func:`_coarse_basis`, degree 3 by default) with the
   points free (eliminated point by point). Alternating poses and points settles each body against its rays at
   once but moves the block-wide modes (a slow bend, a common yaw) barely; the coarse step settles those (a
   two-level scheme). The pose step then takes the bodies' gradients with the points where the coarse step puts
   them.
5. Repeat from 2 while an exposure still moves by a noticeable part of its standard deviation, up to a few times.

The steps use the tie measurements the runs accepted (less those that do not fit their solution), each exposure's one
GNSS/IMU measurement (the runs' prior residuals) and the control points the runs kept (measurements and
coordinates); without the control points the steps drifted along the weak modes of a small block.

The exposures' cofactors are two-level as well: each body's normal block with the points free
(:func:`.precision.reduced_image_normals` summed over its heads, the other exposures held: a lower bound) plus what
the coarse system gives the smooth modes beyond those blocks (:func:`_coarse_cofactors`): what the bodies share,
the block's translation among them. The rig is taken as exact.

Measured on four simulated 1,000-image blocks (``benchmarks/bench_at.py --images 1000 --rig --seed 1..4``, CBA):
attitude RMS 0.0008-0.0011 deg, as IAT on the rig (0.00112-0.00151 deg without the coarse step on seeds 1-3);
attitude errors 0.62-1.81 times these standard deviations per block and axis, 1.00 / 1.03 / 1.20 RMS over the
blocks (up to 3.8 times the bodies' own blocks').
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..geometry.rotations import rotation_angle
from ..model.block import ImageBlock
from ..model.camera import CameraModel
from . import precision
from .bundle import image_focals, move_images, pixels_from_camera, project_obs, shared_prior_fraction
from .problem import exposure_heads

CHUNK = 200_000
"""Tie measurements linearised at a time (a few tens of megabytes of temporaries)."""

COARSE_FROM = 2
"""The first step that takes a coarse step. The first settles each body against its rays; a coarse step from the
heads just placed on the rig as well did slightly worse on a 1,000-image block (attitude 0.00109 against 0.00107
deg RMS, the last step 0.63 against 0.24 of a standard deviation) for one more pass over the measurements."""

SETTLED = 0.05
"""An exposure has settled when its last step is less than this share of its standard deviation (the step's
length in the metric of its normal block, in units of the tie sigma)."""


@dataclass(frozen=True)
class FusionStats:
    """What :func:`fuse_on_rig` did.

    exposures : bodies of two or more heads fused; images : the heads in them
    iterations : pose and point steps taken; left_out : measurements that did not fit the runs' solution, left out
    rms_px_before, rms_px_after : RMS image residual of the measurements used (pixels per coordinate) at the start
        (the heads placed on the rig, before the first step) and at the end
    moved_deg, moved_m : RMS change of the fused heads' attitude (degrees) and centres (metres) from the runs'
    last_step : the largest exposure step of the last iteration, in units of its standard deviation
    rms_px_by_group : ``rms_px_after`` per group of images (``image_group`` of :func:`fuse_on_rig`: label -> RMS)
    """

    exposures: int
    images: int
    iterations: int
    left_out: int
    rms_px_before: float
    rms_px_after: float
    moved_deg: float
    moved_m: float
    last_step: float
    rms_px_by_group: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def rig_relations(block: ImageBlock, image_ids: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each image's place on its exposure's body, from the block's rig.

    ``ref (n,) int64``: the index (into ``image_ids``) of the exposure's reference head, the rig's first head among
    the exposure's images (an image of its own when it has no exposure, no rig head or no reference present);
    ``rel_r (n, 3, 3)``, ``rel_b (n, 3)``: ``R = rel_r R_ref`` and ``C = C_ref + R_ref^T rel_b`` (cam_from_world)."""
    n = len(image_ids)
    ref = np.arange(n, dtype=np.int64)
    rel_r = np.tile(np.eye(3), (n, 1, 1))
    rel_b = np.zeros((n, 3))
    heads, exposures = exposure_heads(block, image_ids)
    for members in exposures:
        if len(members) < 2:
            continue
        rig = heads[next(iter(members))][0]
        first = next((h for h in rig.heads if h.name in members), None)
        if first is None:
            continue
        k0 = members[first.name]
        for name, k in members.items():
            rig_k, head = heads[name]
            if k != k0 and rig_k is rig:
                ref[k] = k0
                rel_r[k], rel_b[k] = head.relative_to(first)
    return ref, rel_r, rel_b


def place_heads(r: np.ndarray, c: np.ndarray, ref: np.ndarray, rel_r: np.ndarray, rel_b: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The images' poses ``r (n, 3, 3)``, ``c (n, 3)`` with every head put where its reference head's pose and
    the rig place it (:func:`rig_relations`); reference heads and images of their own keep theirs."""
    r_ref = r[ref]
    return rel_r @ r_ref, c[ref] + np.einsum("kji,kj->ki", r_ref, rel_b)


def _body_map(c: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``A (n, 6, 6)``: a head's step (rotation about the world axes, centre) from its body's step: the same
    rotation, and the centre moved by it about the reference head's, ``dC = dC_ref + [a]x dtheta`` with
    ``a = C - C_ref`` (cam_from_world ``R' = R exp([dtheta]x)``, so ``C' - C_ref' = exp(-[dtheta]x) a``)."""
    a = c - c[ref]
    out = np.tile(np.eye(6), (len(c), 1, 1))
    out[:, 3, 1], out[:, 3, 2] = -a[:, 2], a[:, 1]
    out[:, 4, 0], out[:, 4, 2] = a[:, 2], -a[:, 0]
    out[:, 5, 0], out[:, 5, 1] = -a[:, 1], a[:, 0]
    return out


def _sum_by(values: np.ndarray, index: np.ndarray, n: int) -> np.ndarray:
    """``out[g] = sum of values[k] with index[k] = g``, ``values (m, ...)`` -> ``(n, ...)``."""
    flat = values.reshape(len(values), -1)
    out = np.stack([np.bincount(index, weights=flat[:, i], minlength=n) for i in range(flat.shape[1])], 1)
    return out.reshape((n, *values.shape[1:]))


def fuse_on_rig(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                xyz: np.ndarray, obs_point: np.ndarray, obs_image: np.ndarray, obs_uv: np.ndarray,
                ref: np.ndarray, rel_r: np.ndarray, rel_b: np.ndarray, prior_residual: np.ndarray,
                prior_info: np.ndarray, obs_weight: np.ndarray | None = None,
                point_prior_xyz: np.ndarray | None = None, point_prior_info: np.ndarray | None = None,
                gate: float = 4.3, max_iterations: int = 3, coarse_degree: int | None = 3, threads: int = 1,
                image_group: np.ndarray | None = None, progress: Callable[[int, int, str], None] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, FusionStats]:
    """The exposures' heads fused on the rig (the module docstring).

    ``r (n, 3, 3)``, ``c (n, 3)``: the runs' poses of the images (``image_camera (n,)`` into ``cameras``);
    ``xyz (p, 3)`` tie points (NaN: not used); the accepted tie measurements ``obs_point``, ``obs_image (m,)``,
    ``obs_uv (m, 2)`` (pixels, all of one sigma); the bodies ``ref``, ``rel_r``, ``rel_b`` of :func:`rig_relations`.
    ``prior_residual (n, 6)``: each image's GNSS/IMU prior residual at the given pose (adjusted minus prior: the
    rotation about the world axes with ``R = R_prior exp([theta]x)``, the centre), as its run left it (its datum
    shift, strip offset and mounting correction included); ``prior_info (n, 6)``: the prior's weights relative to a
    tie measurement (``sigma_px^2 / sigma^2`` per axis; 0 for a part without a prior or rejected). A body's heads
    carry one measurement between them, each part ``1 / h`` of its weight over the ``h`` heads that have it
    (:func:`.bundle.shared_prior_fraction`). ``obs_weight (m,)``: the measurements' weights relative to a tie
    measurement (control points' measurements with their own sigma; default 1); ``point_prior_xyz (p, 3)``,
    ``point_prior_info (p, 3, 3)``: ground observations of points in the same units (control points' coordinates;
    NaN rows and zero blocks for none), which enter the point step. A measurement whose residual at the runs' poses
    exceeds ``gate`` robust standard deviations (chi-square with 2 degrees of freedom, its scale from the median) is
    left out: the runs test each track's rays within their view, and a track matched wrongly across views can
    keep rays that fit their runs' points but not each other (on the rendered demo 0.16 % of the accepted
    measurements were 5 px or more off the combined points, and they bent the fusion).

    ``coarse_degree``: the degree of the coarse step's polynomials (None: no coarse step, and cofactors of the
    bodies' own blocks only). ``image_group (n,)``: a label per image (its run, say), for the residuals per group in
    the statistics.

    Returns the poses ``r``, ``c``, the points ``xyz`` (those with fewer than two usable rays keep theirs), each
    fused image's pose cofactor ``(n, 6, 6)`` (two-level, see the module docstring; rotation about the world axes
    and centre, in squared tie sigmas: times ``sigma_px^2`` a covariance; NaN for images not fused) and the
    :class:`FusionStats`."""
    if max_iterations < 1:
        raise ValueError(f"rig fusion takes at least one step, got max_iterations={max_iterations}")
    n = len(r)
    own = ref == np.arange(n)
    fused = ~own
    fused[ref[~own]] = True
    bodies = np.flatnonzero(fused & own)
    r0, c0 = np.array(r, np.float64), np.array(c, np.float64)
    info_run = np.nan_to_num(np.asarray(prior_info, np.float64))
    e_run = np.nan_to_num(np.asarray(prior_residual, np.float64))
    # the exposure's one measurement: each part shared by the heads of the body that have it
    share = shared_prior_fraction(ref, np.stack([info_run[:, 0] > 0, info_run[:, 3] > 0], 1))
    info = info_run * np.repeat(share, 3, axis=1)
    r, c = place_heads(r0, c0, ref, rel_r, rel_b)
    r[~fused], c[~fused] = r0[~fused], c0[~fused]
    xyz = np.array(xyz, np.float64)
    fx, fy = image_focals(cameras, image_camera)
    usable = np.isfinite(xyz[obs_point, 0])
    op, oi, uv = obs_point[usable], obs_image[usable], obs_uv[usable]
    weight = np.ones(len(op)) if obs_weight is None else np.asarray(obs_weight, np.float64)[usable]
    p_info = np.zeros((len(xyz), 3, 3)) if point_prior_info is None else np.nan_to_num(point_prior_info)
    p_xyz = np.zeros((len(xyz), 3)) if point_prior_xyz is None else np.nan_to_num(point_prior_xyz)
    anchored = np.trace(p_info, axis1=1, axis2=2) > 0
    # the measurements in the order of their points, in chunks of whole points (each point's rays in one chunk)
    order = np.argsort(op, kind="stable")
    op, oi, uv, weight = op[order], oi[order], uv[order], weight[order]
    m = len(op)
    cuts = np.unique(np.r_[np.searchsorted(op, op[np.arange(0, m, CHUNK)]), m])
    chunks = [slice(int(lo), int(hi)) for lo, hi in zip(cuts[:-1], cuts[1:])]
    # the measurements that do not fit the runs' solution, left out
    sq = np.zeros(m)

    def gate_part(sl: slice) -> tuple:
        sq[sl] = np.sum((uv[sl] - project_obs(cameras, image_camera, r0, c0, xyz, op[sl], oi[sl])) ** 2, 1)
        return ()

    _chunk_sums(gate_part, chunks, threads)
    sq *= weight
    fin = np.isfinite(sq)
    scale2 = float(np.median(sq[fin])) / (2.0 * np.log(2.0)) if fin.any() else 1.0
    off = ~fin | (sq > gate**2 * scale2)
    weight = np.where(off, 0.0, weight)
    rays = np.bincount(op[~off], minlength=len(xyz))
    cof = np.full((n, 6, 6), np.nan)
    rms_before = float("nan")
    last, it = float("nan"), 0
    # the image Jacobians of the current linearisation (rotation, centre: the centre's are the point's negative),
    # written chunk by chunk (temporaries of a chunk's size only: those of millions of measurements cost more in
    # fresh pages than in arithmetic)
    rows = np.empty((m, 2, 6))
    v = np.empty((m, 2))
    w = np.empty(m)
    # the smooth fields of body steps over the block that the coarse step solves for (see _coarse_basis)
    basis = _coarse_basis(c[ref], fused, coarse_degree)
    move = (rays >= 2) | (anchored & (rays >= 1))
    point_sums: dict[int, tuple] = {}  # per chunk (its start) the points' sums of the linearisation's coarse step
    for it in range(1, max_iterations + 1):
        if progress is not None:
            progress(it - 1, max_iterations, f"rig fusion: step {it}")
        a = _body_map(c, ref)
        coarse = basis is not None and it >= COARSE_FROM

        def linearise_part(sl: slice, coarse: bool = coarse, a: np.ndarray = a) -> tuple:
            v[sl], good, jp, jr = _linearised(cameras, image_camera, r, c, xyz, op[sl], oi[sl], uv[sl], fx, fy)
            w[sl] = good * weight[sl]
            rows[sl] = precision.image_rows(jp, jr)
            out = (precision.sum_outer(rows[sl], w[sl], oi[sl], n),
                   precision.row_sums(rows[sl], v[sl] * w[sl, None], oi[sl], n),
                   precision.sum_outer(jp, w[sl], op[sl], len(xyz)))
            if not coarse:
                return out
            point_sums[sl.start] = _point_sums(jp, w[sl], v[sl], op[sl], p_info, p_xyz, xyz)
            return (*out, *_coarse_point_part(rows[sl], w[sl], a, basis, oi[sl], move, point_sums[sl.start]))

        n_img, g_img, n_pt, *coarse_sums = _chunk_sums(linearise_part, chunks, threads)
        if it == 1:
            rms_before = float(np.sqrt(np.sum(v[w > 0] ** 2) / max(2 * np.sum(w > 0), 1)))
        # the priors at the current poses, from the runs' residuals (first order)
        e_now = e_run + _pose_change(r0, c0, r, c)
        n_img += info[:, :, None] * np.eye(6)
        g_img -= info * e_now
        n_body = _sum_by(np.einsum("kji,kjl,klm->kim", a, n_img, a)[fused], ref[fused], n)
        g_body = _sum_by(np.einsum("kji,kj->ki", a, g_img)[fused], ref[fused], n)
        q_pt = precision.safe_inverse(n_pt + p_info)
        step_body = np.zeros((n, 6))
        if coarse:
            # the coarse step: the smooth field of body steps with the points free; then the bodies' gradients with
            # the points where that step puts them
            step_body = _coarse_step(n_body, g_body, basis, bodies, *coarse_sums)
            step_img = np.einsum("kij,kj->ki", a, step_body[ref])

            def coarse_part(sl: slice, step_img: np.ndarray = step_img) -> tuple:
                return (_coarse_response(rows[sl], w[sl], step_img, oi[sl], move, n, point_sums[sl.start]),)

            g_body -= np.einsum("kij,kj->ki", n_body, step_body)
            g_body -= _sum_by(np.einsum("kji,kj->ki", a, _chunk_sums(coarse_part, chunks, threads)[0])[fused],
                              ref[fused], n)
        q_body = precision.safe_inverse(n_body[bodies])
        step_body[bodies] += np.nan_to_num(np.einsum("kij,kj->ki", q_body, g_body[bodies]))
        last = float(np.sqrt(np.max(np.einsum("ki,kij,kj->k", step_body[bodies], n_body[bodies],
                                              step_body[bodies]), initial=0.0)))
        # the points on the same linearisation, with the heads' steps applied
        step_img = np.where(fused[:, None], np.einsum("kij,kj->ki", a, step_body[ref]), 0.0)

        def point_part(sl: slice, step_img: np.ndarray = step_img) -> tuple:
            dimg = np.take(step_img, oi[sl], 0)
            rows_sl, v_sl = rows[sl], v[sl]
            for i in range(6):
                v_sl -= rows_sl[:, :, i] * dimg[:, i, None]
            return (precision.row_sums(rows_sl[:, :, 3:], v_sl * w[sl, None], op[sl], len(xyz)),)

        g_pt = (np.einsum("kij,kj->ki", p_info, p_xyz - np.nan_to_num(xyz))
                - _chunk_sums(point_part, chunks, threads)[0])
        step_pt = np.einsum("kij,kj->ki", q_pt, g_pt)
        ok = move & np.all(np.isfinite(step_pt), 1)
        xyz[ok] += step_pt[ok]
        move_images(r, c, step_body, bodies)
        placed_r, placed_c = place_heads(r, c, ref, rel_r, rel_b)
        r[fused], c[fused] = placed_r[fused], placed_c[fused]
        if last < SETTLED:
            break
    # the residuals at the end; the bodies' normal blocks with the points free, for their precision, on the last
    # linearisation (the last steps change the Jacobians by far less than a percent), and the coarse system's
    # points' part of that linearisation (its coarse step's, else computed here)
    n_held, h_pt = n_body, coarse_sums[0] if coarse else None
    final_coarse = basis is not None and h_pt is None
    labels, group = np.unique(np.asarray(image_group if image_group is not None else np.full(n, ""), str),
                              return_inverse=True)

    def final_part(sl: slice) -> tuple:
        v_end = uv[sl] - project_obs(cameras, image_camera, r, c, xyz, op[sl], oi[sl])
        ok = np.all(np.isfinite(v_end), 1) & (w[sl] > 0)
        g = group[oi[sl][ok]]
        out = (np.bincount(g, weights=np.sum(v_end[ok] ** 2, 1), minlength=len(labels)),
               2 * np.bincount(g, minlength=len(labels)),
               precision.reduced_image_normals(-rows[sl][:, :, 3:], rows[sl][:, :, :3], w[sl], q_pt, op[sl], oi[sl],
                                               n))
        if not final_coarse:
            return out
        sums = _point_sums(-rows[sl][:, :, 3:], w[sl], v[sl], op[sl], p_info, p_xyz, xyz)
        return (*out, _coarse_point_part(rows[sl], w[sl], a, basis, oi[sl], move, sums)[0])

    sq_group, n_group, n_red, *h_final = _chunk_sums(final_part, chunks, threads)
    total, count = float(sq_group.sum()), int(n_group.sum())
    if final_coarse:
        h_pt = h_final[0]
    n_red = n_red + info[:, :, None] * np.eye(6)
    rms_after = float(np.sqrt(total / max(count, 1)))
    a = _body_map(c, ref)
    n_body = _sum_by(np.einsum("kji,kjl,klm->kim", a, n_red, a)[fused], ref[fused], n)
    q_body = np.full((n, 6, 6), np.nan)
    q_body[bodies] = precision.safe_inverse(n_body[bodies])
    if basis is not None:
        # the smooth modes' variance that the bodies' own blocks (the other exposures held) leave out
        q_body[bodies] += _coarse_cofactors(n_held, n_body, basis, bodies, h_pt)
    cof[fused] = np.einsum("kij,kjl,kml->kim", a[fused], q_body[ref[fused]], a[fused])
    change = _pose_change(r0[fused], c0[fused], r[fused], c[fused])
    stats = FusionStats(exposures=len(bodies), images=int(fused.sum()), iterations=it, left_out=int(off.sum()),
                        rms_px_before=rms_before,
                        rms_px_after=rms_after,
                        moved_deg=float(np.degrees(np.sqrt(np.mean(np.sum(change[:, :3] ** 2, 1))))) if fused.any()
                        else 0.0,
                        moved_m=float(np.sqrt(np.mean(np.sum(change[:, 3:] ** 2, 1)))) if fused.any() else 0.0,
                        last_step=last,
                        rms_px_by_group={str(lab): float(np.sqrt(sq / cnt)) for lab, sq, cnt in
                                         zip(labels, sq_group, n_group) if cnt > 0} if image_group is not None else {})
    return r, c, xyz, cof, stats


def _pose_change(r0: np.ndarray, c0: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``(n, 6)``: the rotation ``theta`` with ``R = R0 exp([theta]x)`` (about the world axes) and the centre's
    change, from poses ``r0``, ``c0`` to ``r``, ``c`` (rotations well below 180 degrees)."""
    d = np.swapaxes(r0, 1, 2) @ r
    a = rotation_angle(d, np.eye(3))
    w = np.stack([d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], 1)
    scale = np.where(a < 1e-12, 0.5, a / (2.0 * np.sin(np.maximum(a, 1e-12))))
    return np.concatenate([w * scale[:, None], c - c0], 1)


def _chunk_sums(fn: Callable[[slice], tuple], chunks: list[slice], threads: int) -> list:
    """The sums over ``chunks`` of the tuples ``fn(chunk)`` returns (arrays or numbers, summed element by element),
    the chunks shared among ``threads`` threads (numpy's arithmetic releases the interpreter; ``fn`` writes only
    its own chunk of shared arrays)."""
    def run(part: list[slice]) -> list | None:
        total = None
        for sl in part:
            out = fn(sl)
            total = list(out) if total is None else [t + o for t, o in zip(total, out)]
        return total

    groups = [chunks[i::threads] for i in range(max(1, min(threads, len(chunks))))]
    if len(groups) == 1:
        parts = [run(groups[0])]
    else:
        with ThreadPoolExecutor(len(groups)) as pool:
            parts = list(pool.map(run, groups))
    parts = [p for p in parts if p is not None]
    return [sum(vals[1:], vals[0]) for vals in zip(*parts)] if parts else []


def _linearised(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                xyz: np.ndarray, op: np.ndarray, oi: np.ndarray, uv: np.ndarray, fx: np.ndarray, fy: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The residuals ``(m, 2)`` (observed - computed; 0 where not finite), which are finite ``(m,)``, and the point
    and rotation Jacobians ``(m, 2, 3)`` of the measurements ``op``, ``oi``, ``uv``."""
    xc, d, jp = precision.ray_geometry(r, c, fx, fy, xyz, op, oi)
    v = uv - pixels_from_camera(cameras, image_camera, xc, oi)
    good = np.all(np.isfinite(v), 1)
    v[~good] = 0.0
    return v, good, jp, precision.rotation_jacobians(d, jp)


def _coarse_basis(c_body: np.ndarray, fused: np.ndarray, degree: int | None) -> np.ndarray | None:
    """``(n, b)``: the monomials ``x^i y^j`` (``i + j <= degree``) of each fused image's body position ``c_body
    (n, 3)`` (its reference head's centre), scaled to [-1, 1] over the fused bodies; zero rows for the others. A
    coarse step moves every body by ``basis[k] @ z`` for ``z (b, 6)``. None without a degree or fused images."""
    if degree is None or not fused.any():
        return None
    xy = c_body[:, :2]
    lo, hi = xy[fused].min(0), xy[fused].max(0)
    s = (xy - (lo + hi) / 2.0) / np.maximum((hi - lo) / 2.0, 1e-9)
    out = np.stack([s[:, 0] ** i * s[:, 1] ** j for i in range(degree + 1) for j in range(degree + 1 - i)], 1)
    out[~fused] = 0.0
    return out


def _segment_sums(values: np.ndarray, starts: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
    """Sums ``(u, d)`` of the rows of ``values (m, d)`` (each times ``scale (m,)`` when given) over the runs that
    begin at ``starts (u,)`` (increasing, the first 0): as a sparse product, ten times faster than ``reduceat`` on
    wide rows."""
    m = len(values)
    data = np.ones(m) if scale is None else scale
    return sp.csr_matrix((data, np.arange(m), np.r_[starts, m]), shape=(len(starts), m)) @ values


def _point_sums(jp: np.ndarray, w: np.ndarray, v: np.ndarray, op: np.ndarray, p_info: np.ndarray,
                p_xyz: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For measurements of whole points sorted by point (``op (m,)``): each measurement's place among the points
    ``(m,)``, the points ``(u,)``, their cofactors ``(u, 3, 3)`` (cameras held; their rays ``jp (m, 2, 3)``,
    weights ``w``, and ground observations ``p_info``, ``p_xyz``) and their gradients ``(u, 3)`` at ``xyz`` with
    the residuals ``v (m, 2)``."""
    u, first, at = np.unique(op, return_index=True, return_inverse=True)
    n_p = _segment_sums((np.swapaxes(jp, 1, 2) @ (jp * w[:, None, None])).reshape(-1, 9), first).reshape(-1, 3, 3)
    g_p = (_segment_sums(np.einsum("mri,mr->mi", jp, v * w[:, None]), first)
           + np.einsum("kij,kj->ki", p_info[u], p_xyz[u] - np.nan_to_num(xyz[u])))
    n_p += p_info[u]
    return at, u, precision.safe_inverse(n_p), g_p


def _coarse_point_part(rows: np.ndarray, w: np.ndarray, a: np.ndarray, basis: np.ndarray, oi: np.ndarray,
                       move: np.ndarray, sums: tuple) -> tuple[np.ndarray, np.ndarray]:
    """What the points of ``move`` (p,) take from the coarse system (:func:`_coarse_step`), from the measurements of
    whole points sorted by point: ``sum G Q G^T`` ``(6 b, 6 b)`` and ``sum G Q g`` ``(6 b,)``, with ``Q`` and ``g``
    a point's cofactor and gradient (``sums``, :func:`_point_sums` of these measurements) and ``G (6 b, 3)`` its
    coupling with the coarse unknowns
    (flattened function by function), ``sum (rows A B)^T w J`` over its rays: ``rows (m, 2, 6)`` the image rows
    (:func:`.precision.image_rows`), ``A`` the body map ``a (n, 6, 6)`` (:func:`_body_map`), ``B = basis[k] (x) I6``
    and ``J = -rows[:, :, 3:]`` the point Jacobian."""
    jp = -rows[:, :, 3:]
    at, u, q, g = sums
    # rows A: A is the identity but for the block that moves the centre by the rotation (a full (m, 6, 6) product
    # took three times as long)
    rb = np.empty((len(oi), 2, 6))
    rb[:, :, 3:] = rows[:, :, 3:]
    rb[:, :, :3] = rows[:, :, :3] + rows[:, :, 3:] @ np.take(a[:, 3:, :3], oi, 0)
    mt = (np.swapaxes(jp * w[:, None, None], 1, 2) @ rb).reshape(len(oi), 18)  # J^T w rows A, (m, 3 x 6)
    b_obs = np.take(basis, oi, 0)
    starts = np.searchsorted(at, np.arange(len(u)))
    # G^T per point (u, 3, 6 b), the coarse unknowns function by function
    gt = np.stack([_segment_sums(mt, starts, b_obs[:, j]).reshape(-1, 3, 6) for j in range(basis.shape[1])], 2)
    gt = gt.reshape(len(u), 3, -1)
    keep = move[u] & np.all(np.isfinite(q.reshape(-1, 9)), 1)
    gt, q, g = gt[keep], q[keep], g[keep]
    qgt = q @ gt
    nc = gt.shape[2]
    return qgt.reshape(-1, nc).T @ gt.reshape(-1, nc), np.einsum("pdc,pd->c", qgt, g)


def _coarse_response(rows: np.ndarray, w: np.ndarray, step_img: np.ndarray, oi: np.ndarray, move: np.ndarray,
                     n: int, sums: tuple) -> np.ndarray:
    """``(n, 6)``: per image ``sum rows^T w J dx`` over its measurements (of whole points sorted by point), with
    ``dx`` the step of the points of ``move`` when the images step by ``step_img (n, 6)``:
    ``dx = Q (g - sum J^T w rows step)`` (``sums``, :func:`_point_sums` of these measurements; zero for the other
    points)."""
    jp = -rows[:, :, 3:]
    at, u, q, g = sums
    rs = np.einsum("mrj,mj->mr", rows, np.take(step_img, oi, 0))
    wts = _segment_sums(np.einsum("mri,mr->mi", jp, rs * w[:, None]), np.searchsorted(at, np.arange(len(u))))
    dx = np.nan_to_num(np.einsum("pde,pe->pd", q, g - wts)) * move[u][:, None]
    return precision.row_sums(rows, np.einsum("mri,mi->mr", jp, dx[at]) * w[:, None], oi, n)


def _coarse_step(n_body: np.ndarray, g_body: np.ndarray, basis: np.ndarray, bodies: np.ndarray,
                 h_pt: np.ndarray, r_pt: np.ndarray) -> np.ndarray:
    """The bodies' steps ``(n, 6)`` (zero off ``bodies``) restricted to the smooth fields ``basis``
    (:func:`_coarse_basis`) with the points free: from the bodies' normal blocks ``n_body (n, 6, 6)`` and gradients
    ``g_body (n, 6)`` (points held), less what the points take (:func:`_coarse_point_part`: ``h_pt``, ``r_pt``)."""
    b = basis[bodies]
    nb = b.shape[1]
    h = _coarse_normals(n_body, b, bodies) - h_pt
    rhs = np.einsum("kj,ka->ja", b, g_body[bodies]).reshape(6 * nb) - r_pt
    z = _scaled_pinv(h) @ rhs
    step = np.zeros((len(n_body), 6))
    step[bodies] = b @ z.reshape(nb, 6)
    return step


def _coarse_normals(n_body: np.ndarray, b: np.ndarray, bodies: np.ndarray) -> np.ndarray:
    """``(6 f, 6 f)``: the bodies' normal blocks ``n_body (n, 6, 6)`` (rows ``bodies``) on the ``f`` smooth fields
    ``b (k, f)`` (:func:`_coarse_basis` at the bodies), ``sum (b_k b_k^T) (x) N_k``, function by function."""
    nc = 6 * b.shape[1]
    return np.einsum("kj,kl,kab->jalb", b, b, n_body[bodies]).reshape(nc, nc)


def _coarse_cofactors(n_held: np.ndarray, n_own: np.ndarray, basis: np.ndarray, bodies: np.ndarray,
                      h_pt: np.ndarray) -> np.ndarray:
    """``(k, 6, 6)``: what the smooth fields ``basis`` (:func:`_coarse_basis`) add to the cofactors of the
    ``bodies``' own blocks ``n_own (n, 6, 6)`` (points free, the other bodies held): ``B (S^-1 - D^-1) B^T`` with
    ``S`` the coarse system of :func:`_coarse_step` (``n_held``, ``h_pt``) and ``D`` the same fields on the own
    blocks alone (the smooth modes' share that those already hold), its negative directions dropped."""
    b = basis[bodies]
    nb = b.shape[1]
    extra = _scaled_pinv(_coarse_normals(n_held, b, bodies) - h_pt) - _scaled_pinv(_coarse_normals(n_own, b, bodies))
    val, vec = np.linalg.eigh((extra + extra.T) / 2.0)
    cov = ((vec * np.maximum(val, 0.0)) @ vec.T).reshape(nb, 6, nb, 6)
    return np.einsum("kj,kl,jalb->kab", b, b, cov)


def _scaled_pinv(h: np.ndarray) -> np.ndarray:
    """The pseudo-inverse of the symmetric ``h (k, k)`` scaled to a unit diagonal first (rotations and centres differ
    by orders of magnitude in it); directions below ``1e-12`` of the largest are left out (monomials that the
    bodies' layout makes dependent, such as two strips in a cross)."""
    d = np.sqrt(np.maximum(np.diag(h), 1e-300))
    hn = (h + h.T) / (2.0 * np.outer(d, d))
    return np.linalg.pinv(hn, rcond=1e-12, hermitian=True) / np.outer(d, d)

