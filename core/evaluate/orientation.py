"""Exterior orientation and ground point errors against ground truth.

* :func:`pose_errors`: per image position errors (m) and attitude errors (omega, phi, kappa and the total rotation
  angle, degrees) of a block against the true block, summarised as RMS per view split (all, nadir, oblique).
  ``align="similarity"`` first removes a 7-parameter transform fitted to the projection centres (for
  free-network or datum-shifted results); ``None`` compares in the block's CRS as it is.
* :func:`point_errors`: RMS of 3-D points against true points in metres and in multiples of the GSD.
"""

from __future__ import annotations

import numpy as np

from ..geometry.rotations import cam_from_world_to_opk, rotation_angle
from ..geometry.views import cardinal_view
from ..model import ImageBlock, Pose

SPLITS = ("all", "nadir", "oblique")


def similarity_transform(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` (Umeyama) from ``(n, 3)`` point pairs -> (s, R (3, 3), t (3,))."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, sv, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ d @ vt
    s = float(np.trace(np.diag(sv) @ d) / max((a ** 2).sum() / len(src), 1e-300))
    return s, r, md - s * r @ ms


def _rms(a: np.ndarray) -> float:
    a = np.asarray(a, np.float64)
    return float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")


def pose_errors(block: ImageBlock, truth: ImageBlock, adjusted: bool = True, align: str | None = None) -> dict:
    """Errors of the images' orientations (adjusted if ``adjusted`` and available, else approximate) against the
    true poses (``truth.images[id].pose_approx``), for the images present in both.

    Returns ``{"images": {id: {"dxyz": [3], "dopk_deg": [3], "angle_deg": float, "view": str}},
    "summary": {split: {"n", "rms_x", "rms_y", "rms_z", "rms_xy", "rms_xyz", "rms_omega_deg", "rms_phi_deg",
    "rms_kappa_deg", "rms_angle_deg", "max_xyz", "max_angle_deg"}}, "alignment": {...} or None}``.
    """
    ids, est, ref = [], [], []
    for iid, img in block.images.items():
        t = truth.images.get(iid)
        p = (img.pose_adjusted or img.pose_approx) if adjusted else img.pose_approx
        if t is None or t.pose_approx is None or p is None:
            continue
        ids.append(iid)
        est.append(p)
        ref.append(t.pose_approx)
    out: dict = {"images": {}, "summary": {}, "alignment": None}
    if not ids:
        return out
    if align == "similarity" and len(ids) >= 3:
        s, r, t = similarity_transform(np.array([p.C for p in est]), np.array([p.C for p in ref]))
        est = [Pose(p.R @ r.T, s * r @ p.C + t) for p in est]
        out["alignment"] = {"scale": s, "rotation": r.tolist(), "translation": t.tolist()}
    rows = []
    for iid, p, q in zip(ids, est, ref, strict=True):
        d = p.C - q.C
        dopk = np.degrees(np.array(cam_from_world_to_opk(p.R)) - np.array(cam_from_world_to_opk(q.R)))
        dopk = (dopk + 180.0) % 360.0 - 180.0
        ang = float(np.degrees(rotation_angle(p.R, q.R)))
        view = cardinal_view(q.R)
        out["images"][iid] = {"dxyz": d.tolist(), "dopk_deg": dopk.tolist(), "angle_deg": ang, "view": view}
        rows.append((view, d, dopk, ang))
    for split in SPLITS:
        sel = [r for r in rows if split == "all" or (split == "nadir") == (r[0] == "nadir")]
        if not sel:
            continue
        d = np.array([r[1] for r in sel])
        o = np.array([r[2] for r in sel])
        a = np.array([r[3] for r in sel])
        out["summary"][split] = {
            "n": len(sel), "rms_x": _rms(d[:, 0]), "rms_y": _rms(d[:, 1]), "rms_z": _rms(d[:, 2]),
            "rms_xy": _rms(np.linalg.norm(d[:, :2], axis=1)), "rms_xyz": _rms(np.linalg.norm(d, axis=1)),
            "rms_omega_deg": _rms(o[:, 0]), "rms_phi_deg": _rms(o[:, 1]), "rms_kappa_deg": _rms(o[:, 2]),
            "rms_angle_deg": _rms(a), "max_xyz": float(np.linalg.norm(d, axis=1).max()),
            "max_angle_deg": float(a.max()),
        }
    return out


def point_errors(xyz: np.ndarray, xyz_true: np.ndarray, gsd: float | None = None) -> dict:
    """RMS errors of points ``xyz : (n, 3)`` against ``xyz_true : (n, 3)`` (rows with NaN are skipped).

    Returns ``n``, ``rms_x``, ``rms_y``, ``rms_z``, ``rms_xy`` (sqrt of the mean of dx^2 + dy^2), ``rms_xyz``,
    ``mean`` (3,), ``max_xyz`` in metres and, when ``gsd`` is given, the same RMS values divided by it
    (``*_gsd`` keys).
    """
    d = np.asarray(xyz, np.float64) - np.asarray(xyz_true, np.float64)
    d = d[np.all(np.isfinite(d), axis=1)]
    out = {"n": len(d), "rms_x": _rms(d[:, 0]), "rms_y": _rms(d[:, 1]), "rms_z": _rms(d[:, 2]),
           "rms_xy": _rms(np.linalg.norm(d[:, :2], axis=1)), "rms_xyz": _rms(np.linalg.norm(d, axis=1)),
           "mean": d.mean(0).tolist() if len(d) else [float("nan")] * 3,
           "max_xyz": float(np.linalg.norm(d, axis=1).max()) if len(d) else float("nan")}
    if gsd:
        for k in ("rms_x", "rms_y", "rms_z", "rms_xy", "rms_xyz"):
            out[k + "_gsd"] = out[k] / gsd
    return out
