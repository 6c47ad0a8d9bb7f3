"""Accuracy figures of an aerial triangulation: check points, internal precision, tie point agreement.

Views are split as in the seed's tables: ``all`` (every image), ``nadir`` and ``oblique`` (the four cardinal
oblique views), taken from each image's actual viewing direction.

* Check points: forward intersection of the check points' image measurements from the adjusted orientations,
  using the rays of the chosen views only, compared with their given coordinates.
* Internal accuracy: standard deviations of tie points intersected from the rays of the chosen views with the
  adjusted orientations held fixed, ``sigma0^2 (sum J^T W J)^-1``; reported as
  ``sigma_XY = sqrt((sX^2 + sY^2) / 2)`` and ``sigma_Z``.
"""

from __future__ import annotations

import numpy as np

from ..aerotri import precision
from ..geometry.intersection import intersect_rays
from ..geometry.projection import pixel_rays
from ..model import ImageBlock, Pose, TiePoints

SPLITS = ("all", "nadir", "oblique")


def _view_ok(view: str | None, split: str) -> bool:
    if split == "all":
        return view is not None
    if split == "nadir":
        return view == "nadir"
    return view is not None and view != "nadir"


def intersect_ground_point(block: ImageBlock, poses: dict[str, Pose], gp, split: str = "all"
                           ) -> tuple[np.ndarray, list[str]] | None:
    """A ground point intersected from its rays in the split's images of ``poses``: ``(xyz (3,), image ids)``,
    None with fewer than two rays."""
    o, d, ids = [], [], []
    for iid, uv in gp.observations.items():
        p = poses.get(iid)
        if p is None or not _view_ok(block.images[iid].view, split):
            continue
        o.append(p.C)
        d.append(pixel_rays(block.camera_of(iid), p, np.asarray(uv)[None])[0])
        ids.append(iid)
    if len(o) < 2:
        return None
    xyz, _ = intersect_rays(np.array(o), np.array(d))
    return xyz, ids


def check_point_errors(block: ImageBlock, poses: dict[str, Pose], split: str = "all",
                       kind: str = "check") -> tuple[list[str], np.ndarray]:
    """Names and errors ``(k, 3)`` (intersected - given) of the ground points of ``kind`` with at least two
    rays in the split's images."""
    names, errs = [], []
    for gp in block.ground_points.values():
        if gp.kind != kind or gp.xyz is None:
            continue
        got = intersect_ground_point(block, poses, gp, split)
        if got is None:
            continue
        names.append(gp.name)
        errs.append(got[0] - gp.xyz)
    return names, np.array(errs).reshape(-1, 3)


def rms_xy_z(err: np.ndarray) -> tuple[float, float]:
    """RMS of the horizontal error per axis, ``sqrt(mean((dX^2 + dY^2) / 2))``, and of Z; NaN when empty."""
    err = np.asarray(err).reshape(-1, 3)
    err = err[np.all(np.isfinite(err), 1)]
    if len(err) == 0:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean((err[:, 0] ** 2 + err[:, 1] ** 2) / 2))), float(np.sqrt(np.mean(err[:, 2] ** 2)))


def tie_point_std(block: ImageBlock, ties: TiePoints, poses: dict[str, Pose], xyz: np.ndarray,
                  obs_mask: np.ndarray, sigma0: float, sigma_px: float, split: str = "all") -> np.ndarray:
    """Std ``(n, 3)`` of every track intersected from the split's rays with fixed cameras (NaN: < 2 rays)."""
    views = np.array([block.images[i].view for i in ties.image_ids], dtype=object)
    ok_img = np.array([_view_ok(v, split) and i in poses for v, i in zip(views, ties.image_ids)])
    sel = obs_mask & ok_img[ties.obs_image] & np.isfinite(xyz[ties.obs_track, 0])
    oi, op = ties.obs_image[sel], ties.obs_track[sel]
    r = np.zeros((len(ties.image_ids), 3, 3))
    c = np.zeros((len(ties.image_ids), 3))
    fx = np.ones(len(ties.image_ids))
    fy = np.ones(len(ties.image_ids))
    for k, iid in enumerate(ties.image_ids):
        p = poses.get(iid)
        if p is not None:
            r[k], c[k] = p.R, p.C
            cam = block.camera_of(iid)
            fx[k], fy[k] = cam.fx, cam.fy
    jp = precision.point_jacobians(r, c, fx, fy, xyz, op, oi)
    n = precision.point_normals(jp, np.full(len(op), 1.0 / sigma_px**2), op, ties.n_tracks)
    counts = np.bincount(op, minlength=ties.n_tracks)
    q = np.full((ties.n_tracks, 3, 3), np.nan)
    ok = counts >= 2
    q[ok] = precision.safe_inverse(n[ok])
    return np.sqrt(np.abs(np.diagonal(q, axis1=1, axis2=2))) * sigma0


def std_xy_z(std: np.ndarray) -> tuple[float, float]:
    """RMS of ``sqrt((sX^2 + sY^2) / 2)`` and of ``sZ`` over the finite rows of ``std (n, 3)``."""
    s = std[np.all(np.isfinite(std), 1)]
    if len(s) == 0:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean((s[:, 0] ** 2 + s[:, 1] ** 2) / 2))), float(np.sqrt(np.mean(s[:, 2] ** 2)))


def blunder_scores(truth: np.ndarray, flagged: np.ndarray, considered: np.ndarray | None = None) -> dict:
    """Recall and false-alarm rate of blunder detection against planted labels (``(m,)`` bools)."""
    m = np.ones(len(truth), bool) if considered is None else considered
    t, f = truth[m], flagged[m]
    return {"planted": int(t.sum()), "flagged": int(f.sum()),
            "recall": float((t & f).sum() / max(t.sum(), 1)),
            "false_alarm": float((~t & f).sum() / max((~t).sum(), 1))}
