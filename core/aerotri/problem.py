"""From the block classes to bundle problems and back: image subsets, tie point subsets, initial coordinates."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..model import CameraModel, ImageBlock, Pose, TiePoints
from ..model.block import Rig, RigHead
from .bundle import BundleProblem, BundleResult
from .precision import safe_inverse, sum_outer
from .strips import Strips


def pose_arrays(block: ImageBlock, image_ids: list[str], poses: dict[str, Pose]
                ) -> tuple[list[CameraModel], np.ndarray, np.ndarray, np.ndarray]:
    """The block's cameras and, per image of ``image_ids``, its camera index ``(k,)`` and rotation
    ``(k, 3, 3)`` / centre ``(k, 3)`` from ``poses`` (NaN for images without a pose)."""
    k = len(image_ids)
    cam_ids = list(block.cameras)
    r = np.full((k, 3, 3), np.nan)
    c = np.full((k, 3), np.nan)
    image_camera = np.zeros(k, np.int64)
    for j, iid in enumerate(image_ids):
        image_camera[j] = cam_ids.index(block.images[iid].camera_id)
        if iid in poses:
            r[j], c[j] = poses[iid].R, poses[iid].C
    return [block.cameras[cid] for cid in cam_ids], image_camera, r, c


def ray_directions(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, obs_image: np.ndarray,
                   obs_uv: np.ndarray, undistort_iterations: int = 20) -> np.ndarray:
    """Unit world directions ``(m, 3)`` of the rays of pixel observations ``obs_uv (m, 2)`` in the images
    ``obs_image (m,)`` (rotations ``r (k, 3, 3)`` cam_from_world, NaN rows for images without a pose;
    ``image_camera (k,)`` into ``cameras``): ``R^T (x, y, 1)``, undistorted per camera by
    ``undistort_iterations`` fixed-point steps (20 reach 1e-10 on strongly distorted aerial cameras; rays that
    only start a Gauss-Newton step on the pixel residuals need fewer: 4 leave below 1e-7 px on the simulated
    cameras)."""
    xy = np.full((len(obs_image), 2), np.nan)
    cam_of_obs = image_camera[obs_image]
    for ci, cam in enumerate(cameras):
        sel = cam_of_obs == ci
        if sel.any():
            xy[sel] = cam.pixel_to_normalized(obs_uv[sel], undistort=False)
            if cam.has_distortion:
                xy[sel] = cam.undistort_normalized(xy[sel], iterations=undistort_iterations)
    d = (np.take(r, obs_image, 0).transpose(0, 2, 1) @ np.column_stack([xy, np.ones(len(xy))])[:, :, None])[:, :, 0]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def intersect_rays(o: np.ndarray, d: np.ndarray, track: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection ``(n, 3)`` of rays ``o, d (m, 3)`` (unit ``d``) per ``track (m,)`` (NaN below two
    rays or badly conditioned) and each ray's distance ``(m,)`` to its point. The normal equations
    ``sum (I - d d^T) x = sum (I - d d^T) o`` are summed entry by entry with bincount (no ``(m, 3, 3)``
    temporaries; ``np.add.at`` took seconds per million rays)."""
    ref = o.mean(0) if len(o) else np.zeros(3)
    oo = o - ref
    cnt = np.bincount(track, minlength=n).astype(np.float64)
    a = sum_outer(d[:, None, :], np.ones(len(d)), track, n)
    a = cnt[:, None, None] * np.eye(3) - a
    do = np.einsum("mi,mi->m", d, oo)
    b = np.stack([np.bincount(track, weights=oo[:, i] - d[:, i] * do, minlength=n) for i in range(3)], 1)
    xyz = np.where((cnt >= 2)[:, None], np.einsum("kij,kj->ki", safe_inverse(a), b) + ref, np.nan)
    w = xyz[track] - o
    dist = np.linalg.norm(w - d * np.einsum("mi,mi->m", d, w)[:, None], axis=1)
    return xyz, dist


def track_shares(obs_track: np.ndarray, idx: np.ndarray, shares: int) -> list[np.ndarray]:
    """The observations ``idx`` split into ``shares`` groups by track (``track % shares``), so that every track's
    observations stay together: a list of index arrays into ``obs_track (m,)``, each in ``idx`` order."""
    if shares <= 1:
        return [idx]
    share_of = obs_track[idx] % shares
    return [idx[share_of == s] for s in range(shares)]


def intersect_ties(block: ImageBlock, ties: TiePoints, poses: dict[str, Pose],
                   obs_mask: np.ndarray | None = None, chunk_obs: int = 2_000_000,
                   undistort_iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Multi-ray forward intersection of all tracks from ``poses``, in shares of tracks of about ``chunk_obs``
    observations (the rays cost about 200 bytes per observation while they exist); ``undistort_iterations`` as in
    :func:`ray_directions` (fewer for coordinates that only start a Gauss-Newton step).

    Returns ``xyz (n, 3)`` (NaN for tracks with fewer than two usable rays) and the ray distances ``(m,)``
    (NaN for observations not used).
    """
    idx_all = np.arange(ties.n_obs) if obs_mask is None else np.flatnonzero(obs_mask)
    cameras, image_camera, r, c = pose_arrays(block, ties.image_ids, poses)
    xyz = np.full((ties.n_tracks, 3), np.nan)
    out = np.full(ties.n_obs, np.nan)
    for idx in track_shares(ties.obs_track, idx_all, max(1, -(-len(idx_all) // max(chunk_obs, 1)))):
        o = np.take(c, ties.obs_image[idx], 0)
        d = ray_directions(cameras, image_camera, r, ties.obs_image[idx], ties.obs_uv[idx], undistort_iterations)
        ok = np.isfinite(o[:, 0])
        x, dist = intersect_rays(o[ok], d[ok], ties.obs_track[idx[ok]], ties.n_tracks)
        done = np.isfinite(x[:, 0])
        xyz[done] = x[done]
        out[idx[ok]] = dist
    return xyz, out


@dataclass(eq=False)
class SubProblem:
    """A bundle problem over a subset of a block, with the maps back to the block's arrays.

    Attributes
    ----------
    problem : the arrays for :func:`.bundle.adjust`
    track_index : (p,) tie track (in ``TiePoints``) of each problem point
    obs_index : (m,) observation (in ``TiePoints``) of each problem observation
    """

    problem: BundleProblem
    track_index: np.ndarray
    obs_index: np.ndarray


def build_problem(block: ImageBlock, ties: TiePoints, image_ids: list[str], xyz_init: np.ndarray,
                  obs_mask: np.ndarray | None = None, use_control: bool = True,
                  point_prior_xyz: np.ndarray | None = None, point_prior_cov: np.ndarray | None = None,
                  prior_shift: np.ndarray | None = None, initial: dict[str, Pose] | None = None,
                  strips: Strips | None = None, prior_offsets: dict[str, np.ndarray] | None = None) -> SubProblem:
    """Bundle problem for the images ``image_ids`` with the tie observations among them.

    Parameters
    ----------
    xyz_init : (n, 3) initial coordinates of all tie tracks (NaN: track not used)
    obs_mask : (m,) observations allowed (e.g. not rejected), all by default
    point_prior_xyz, point_prior_cov : (n, 3), (n, 3, 3) ground observations of tracks (connection points)
    prior_shift : (3,) added to the GNSS centres (a datum shift known from an earlier adjustment)
    initial : starting orientations (default: the images' approximate ones)
    strips : the flight strips, for GNSS offsets per strip (:attr:`.bundle.BundleOptions.gnss_strips`)
    prior_offsets : image id -> (3,) error of its GNSS centre, subtracted from it (strip offsets known from an earlier
        adjustment)
    """
    index = {iid: k for k, iid in enumerate(ties.image_ids)}
    sub = np.array([index.get(i, -1) for i in image_ids])
    local = np.full(len(ties.image_ids), -1, np.int64)
    local[sub[sub >= 0]] = np.flatnonzero(sub >= 0)
    # the tests run over the observations allowed only (a view's share of the block when a mask is given)
    cand = np.arange(ties.n_obs) if obs_mask is None else np.flatnonzero(obs_mask)
    in_sub = np.zeros(len(ties.image_ids), bool)
    in_sub[local >= 0] = True
    obs_index = cand[in_sub[ties.obs_image[cand]] & np.isfinite(xyz_init[ties.obs_track[cand], 0])]
    # the tracks used, numbered 0.. in track order (a rank table: np.unique sorted the observations, 2.5x slower)
    seen = np.zeros(ties.n_tracks, bool)
    seen[ties.obs_track[obs_index]] = True
    tracks = np.flatnonzero(seen)
    obs_point = (np.cumsum(seen) - 1)[ties.obs_track[obs_index]]
    n = len(image_ids)
    cams = list(block.cameras)
    pr = np.zeros((n, 3, 3))
    pc = np.full((n, 3), np.nan)
    s_att = np.full((n, 3), np.nan)
    s_pos = np.full((n, 3), np.nan)
    shift = np.zeros(3) if prior_shift is None else np.asarray(prior_shift)
    r0, c0 = start_poses(block, image_ids, initial)
    for k, iid in enumerate(image_ids):
        img = block.images[iid]
        if img.pose_approx is not None:
            pr[k], pc[k] = img.pose_approx.R, img.pose_approx.C + shift - (prior_offsets or {}).get(iid, 0.0)
            if img.sigma_position is not None and img.sigma_attitude is not None:
                s_pos[k], s_att[k] = img.sigma_position, img.sigma_attitude
    prob = BundleProblem(
        image_ids=list(image_ids), cameras=[block.cameras[c] for c in cams],
        image_camera=np.array([cams.index(block.images[i].camera_id) for i in image_ids]),
        r_cam_from_world=r0, c_world=c0, prior_r=pr, prior_c=pc, prior_sigma_att=s_att, prior_sigma_pos=s_pos,
        xyz=xyz_init[tracks], obs_point=obs_point.astype(np.int64),
        obs_image=local[ties.obs_image[obs_index]], obs_uv=ties.obs_uv[obs_index])
    if point_prior_xyz is not None:
        prob.point_prior_xyz = point_prior_xyz[tracks]
        prob.point_prior_cov = point_prior_cov[tracks]
    _add_rig_pairs(block, image_ids, prob)
    exposures = {e: k for k, e in enumerate(sorted({block.images[i].exposure for i in image_ids} - {None}))}
    prob.image_exposure = np.array([exposures.get(block.images[i].exposure, -1) for i in image_ids], np.int64)
    if strips is not None:
        prob.strip_names = list(strips.names)
        prob.prior_strip = np.array([strips.image_strip.get(i, -1) for i in image_ids], np.int64)
        prob.prior_along = np.array([strips.image_along_km.get(i, 0.0) for i in image_ids])
    if use_control:
        kidx = {iid: k for k, iid in enumerate(image_ids)}
        names, gxyz, gsig, gsp, op, oi, ouv = [], [], [], [], [], [], []
        for gp in block.ground_points.values():
            if gp.kind != "control" or gp.xyz is None:
                continue
            obs = [(kidx[i], uv) for i, uv in gp.observations.items() if i in kidx]
            if not obs:
                continue
            g = len(names)
            names.append(gp.name)
            gxyz.append(gp.xyz)
            gsig.append(gp.sigma)
            gsp.append(gp.sigma_px)
            for k, uv in obs:
                op.append(g)
                oi.append(k)
                ouv.append(uv)
        if names:
            prob.gcp_names = names
            prob.gcp_xyz = np.array(gxyz)
            prob.gcp_sigma = np.array(gsig)
            prob.gcp_sigma_px = np.array(gsp)
            prob.gcp_obs_point = np.array(op, np.int64)
            prob.gcp_obs_image = np.array(oi, np.int64)
            prob.gcp_obs_uv = np.array(ouv, np.float64)
    return SubProblem(problem=prob, track_index=tracks, obs_index=obs_index)


def start_poses(block: ImageBlock, image_ids: list[str], initial: dict[str, Pose] | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The orientations a bundle problem starts the images ``image_ids`` from, ``r (k, 3, 3)``, ``c (k, 3)``: their
    poses in ``initial``, else their approximate ones; raises :class:`~..errors.InputError` for an image with
    neither."""
    r0 = np.zeros((len(image_ids), 3, 3))
    c0 = np.zeros((len(image_ids), 3))
    for k, iid in enumerate(image_ids):
        start = (initial or {}).get(iid) or block.images[iid].pose_approx
        if start is None:
            raise InputError(f"image '{iid}' has no approximate orientation: aerial triangulation needs one "
                             "(GNSS/IMU or imported exterior orientation)", field="pose")
        r0[k], c0[k] = start.R, start.C
    return r0, c0


def restarted(sub: SubProblem, block: ImageBlock, initial: dict[str, Pose] | None, xyz_init: np.ndarray
              ) -> SubProblem:
    """``sub`` (from :func:`build_problem`) starting from the orientations ``initial`` (as there) and the track
    coordinates ``xyz_init (n, 3)``, which must be finite for the tracks of ``sub`` (the observations stay those it
    was built with)."""
    r0, c0 = start_poses(block, sub.problem.image_ids, initial)
    return replace(sub, problem=replace(sub.problem, r_cam_from_world=r0, c_world=c0, xyz=xyz_init[sub.track_index]))


def exposure_heads(block: ImageBlock, image_ids: list[str]
                   ) -> tuple[dict[str, tuple[Rig, RigHead]], list[dict[str, int]]]:
    """The block's rig heads by name, each with its rig, and per exposure the indices (into ``image_ids``) of its
    images by head name (images without an exposure or a rig head left out)."""
    heads = {h.name: (rig, h) for rig in block.rigs.values() for h in rig.heads}
    by_exp: dict[str, dict[str, int]] = {}
    for k, iid in enumerate(image_ids):
        img = block.images[iid]
        if img.exposure is not None and img.head in heads:
            by_exp.setdefault(img.exposure, {})[img.head] = k
    return heads, list(by_exp.values())


def _add_rig_pairs(block: ImageBlock, image_ids: list[str], prob: BundleProblem) -> None:
    """Pairs (reference head, other head) of each exposure among ``image_ids`` with their calibrated relative
    pose from the rig: ``i_from_j = (S_i S_j^T, S_i (l_j - l_i))`` (S sensor_from_rig, l lever arm)."""
    heads, exposures = exposure_heads(block, image_ids)
    pairs, rots, trans = [], [], []
    for members in exposures:
        for name, j in members.items():
            rig, hj = heads[name]
            ref_name = rig.heads[0].name
            if name == ref_name or ref_name not in members:
                continue
            rot, offset = hj.relative_to(heads[ref_name][1])
            pairs.append((members[ref_name], j))
            rots.append(rot.T)
            trans.append(offset)
    if pairs:
        prob.rig_pairs = np.array(pairs, np.int64)
        prob.rig_r = np.array(rots)
        prob.rig_t = np.array(trans)


def result_poses(sub: SubProblem, result: BundleResult) -> dict[str, Pose]:
    """Adjusted poses of the images that took part (had observations)."""
    return {iid: Pose(result.r_cam_from_world[k], result.c_world[k])
            for k, iid in enumerate(sub.problem.image_ids) if result.image_adjusted[k]}


def thin_ties(block: ImageBlock, ties: TiePoints, obs_sel: np.ndarray, priority: np.ndarray, grid: int,
              per_cell: int) -> np.ndarray:
    """Tie point reduction to a regular distribution per image (as production AT thins its tie points, e.g. a
    per-image point limit or Gruber-like grid): each image of ``obs_sel`` is divided into ``grid`` cells across
    its width (and as many square-ish cells down its height), and in each cell the ``per_cell`` tracks of highest
    ``priority`` are kept. A track stays when any of its images keeps it.

    ``obs_sel : (m,)`` bool observations considered; ``priority : (n,)`` per track (e.g. its ray count).
    Returns the kept tracks as an ``(n,)`` bool mask."""
    idx = np.flatnonzero(obs_sel)
    keep = np.zeros(ties.n_tracks, bool)
    if len(idx) == 0 or per_cell <= 0:
        return keep
    cams = [block.cameras[block.images[i].camera_id] for i in ties.image_ids]
    w = np.array([c.width for c in cams], np.float64)[ties.obs_image[idx]]
    h = np.array([c.height for c in cams], np.float64)[ties.obs_image[idx]]
    gy = np.maximum(1, np.round(grid * h / w)).astype(np.int64)
    uv = ties.obs_uv[idx]
    cx = np.clip(np.floor((uv[:, 0] + 0.5) / w * grid), 0, grid - 1).astype(np.int64)
    cy = np.clip(np.floor((uv[:, 1] + 0.5) / h * gy), 0, gy - 1).astype(np.int64)
    key = (ties.obs_image[idx].astype(np.int64) * (grid * (gy.max() + 1)) + cy * grid + cx)
    tr = ties.obs_track[idx]
    order = np.lexsort((tr, -priority[tr], key))
    k = key[order]
    start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    rank = np.arange(len(k)) - np.repeat(start, np.diff(np.r_[start, len(k)]))
    keep[tr[order[rank < per_cell]]] = True
    return keep
