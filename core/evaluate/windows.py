"""Window detection scores against ground truth: precision, recall and corner accuracy of facade rectangles.

A window, true or detected, is a planar 3D rectangle ``corners : (4, 3)`` in the facade (the simulator writes the
truth as ``truth/windows.json``). A detection matches a true window when both lie on the same facade plane
(normals within ``max_angle_deg``, the detection's centre within ``max_plane_dist`` metres of the true plane; the
recess of a window may put a detection on the glass or on the wall) and their overlap in that plane has an
intersection over union of at least ``min_iou``. Matching is one-to-one and greedy by decreasing IoU, as in the
usual object detection scores: a true window matched twice counts once, the other detection is a false positive.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..texture.plane import PlaneFrame, plane_frame


@dataclass(frozen=True)
class WindowScores:
    """Scores of a set of detections.

    true_windows, detections, matched : counts; precision = matched / detections; recall = matched / true_windows;
    f1 : harmonic mean; iou_mean : mean IoU of the matches; corner_rmse_m : RMS distance of matched corners (each
    true corner to the nearest detected corner), metres
    """

    true_windows: int
    detections: int
    matched: int
    precision: float
    recall: float
    f1: float
    iou_mean: float
    corner_rmse_m: float

    def as_dict(self) -> dict:
        return asdict(self)


def _box(corners: np.ndarray, frame: PlaneFrame) -> np.ndarray:
    """Axis-aligned 2D box ``(umin, vmin, umax, vmax)`` of corners ``(4, 3)`` in a facade frame (along the wall,
    up)."""
    uv = frame.to_plane(corners)
    return np.concatenate([uv.min(0), uv.max(0)])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    return float(inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter))


def window_scores(detected: list[np.ndarray], truth: list[np.ndarray], min_iou: float = 0.5,
                  max_angle_deg: float = 15.0, max_plane_dist: float = 0.5) -> WindowScores:
    """Precision, recall and accuracy of detected windows.

    Parameters
    ----------
    detected : list of (4, 3) float64 corner arrays (a planar rectangle each, any starting corner)
    truth : list of (4, 3) float64 true window rectangles (``truth/windows.json`` ``corners``)
    min_iou : least intersection over union in the facade plane for a match
    max_angle_deg, max_plane_dist : same-facade test (normal angle, distance of the detection to the true plane)
    """
    det = [np.asarray(d, dtype=np.float64).reshape(4, 3) for d in detected]
    tru = [np.asarray(t, dtype=np.float64).reshape(4, 3) for t in truth]
    cos_max = np.cos(np.radians(max_angle_deg))
    frames = [plane_frame(t) for t in tru]
    det_normals = [plane_frame(d).normal for d in det]
    det_centres = np.array([d.mean(0) for d in det]).reshape(-1, 3)
    pairs = []
    for j, frame in enumerate(frames):
        if not len(det):
            break
        near = np.flatnonzero(np.abs((det_centres - frame.origin) @ frame.normal) <= max_plane_dist)
        tb = _box(tru[j], frame)
        for i in near:
            if abs(det_normals[i] @ frame.normal) < cos_max:
                continue
            iou = _iou(_box(det[i], frame), tb)
            if iou >= min_iou:
                pairs.append((iou, i, j))
    pairs.sort(key=lambda p: -p[0])
    used_d, used_t, ious, d2 = set(), set(), [], []
    for iou, i, j in pairs:
        if i in used_d or j in used_t:
            continue
        used_d.add(i)
        used_t.add(j)
        ious.append(iou)
        dist = np.linalg.norm(tru[j][:, None, :] - det[i][None, :, :], axis=2)
        d2.extend(dist.min(1) ** 2)
    m = len(ious)
    precision = m / len(det) if det else float("nan")
    recall = m / len(tru) if tru else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if m else 0.0
    return WindowScores(len(tru), len(det), m, precision, recall, f1,
                        float(np.mean(ious)) if m else float("nan"),
                        float(np.sqrt(np.mean(d2))) if m else float("nan"))


def truth_windows(doc: dict) -> list[np.ndarray]:
    """The true window rectangles ``(4, 3)`` of a ``truth/windows.json`` document."""
    return [np.asarray(w["corners"], dtype=np.float64) for w in doc.get("windows", [])]


def true_walls(city) -> list[tuple[int, np.ndarray]]:
    """The wall rectangles of every body or tower part of a simulated city (a :class:`~..simulate.city.City`):
    ``(building id, ring (4, 3) float64 world)``, counter-clockwise seen from outside, from the part's base to the
    underside of its roof slab (the planes the true windows lie in)."""
    out = []
    for b in city.buildings:
        for p in b.parts:
            if p.kind not in ("body", "tower"):
                continue
            x0, y0, x1, y1 = p.rect
            fp = b.to_world(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64))
            z0, z1 = p.base, p.eave - p.thickness
            for k in range(4):
                a, c = fp[k], fp[(k + 1) % 4]
                out.append((b.id, np.array([[*a, z0], [*c, z0], [*c, z1], [*a, z1]], np.float64)))
    return out


def building_of(xy: np.ndarray, footprints: dict) -> int | None:
    """The true building (``truth/footprints.json`` id) whose footprint contains the point ``xy (2,)``, else the
    one with the nearest footprint vertex within 5 m, else None."""
    import cv2

    best, best_d = None, 5.0
    for b in footprints.get("buildings", []):
        for ring in b["footprint"]:
            r = np.asarray(ring, np.float64)
            d = cv2.pointPolygonTest((r - xy).astype(np.float32), (0.0, 0.0), True)
            if d >= 0:
                return int(b["id"])
            if -d < best_d:
                best, best_d = int(b["id"]), -d
    return best
