"""Oblique-aware image selection for dense matching: masters per cardinal view and slaves per master.

Images are grouped by the view they actually look in (``nadir``, ``north``, ...). In each view, masters are
chosen greedily so that their footprints cover the area of interest with a chosen overlap between neighbouring
masters (each master "owns" the ground seen by the central part of its image, the window shrunk by
``1 - overlap``; the greedy set cover adds the image whose owned part covers most uncovered ground). For each
master, slaves of the same view are ranked by footprint overlap, base-to-height ratio, intersection angle and
the angle between baseline and viewing direction (planar rectification distorts little when they are
perpendicular); pairs whose baseline runs nearly along the viewing direction cannot be rectified and are left
out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.projection import intersect_with_plane_z
from ..model.block import ImageBlock


@dataclass(frozen=True)
class SelectionConfig:
    """Attributes
    ----------
    master_overlap : overlap between neighbouring masters' footprints (0.35 = 35%)
    slaves_per_master : slaves matched with each master
    min_overlap : least footprint overlap of a slave with its master (fraction of the master's footprint)
    base_height_ideal : preferred base-to-height ratio
    base_height_min, base_height_max : accepted base-to-height range
    max_angle_deg : largest intersection angle at the footprint centre
    min_baseline_view_angle_deg : least angle between baseline and mean viewing direction (rectifiable pairs)
    grid_cell : cell of the coverage grid, metres
    views : views to reconstruct
    """

    master_overlap: float = 0.35
    slaves_per_master: int = 4
    min_overlap: float = 0.3
    base_height_ideal: float = 0.3
    base_height_min: float = 0.05
    base_height_max: float = 0.9
    max_angle_deg: float = 45.0
    min_baseline_view_angle_deg: float = 35.0
    grid_cell: float = 2.0
    views: tuple[str, ...] = ("nadir", "north", "east", "south", "west")


@dataclass(frozen=True)
class MasterSelection:
    """One master with its slaves (image ids) and its cardinal view."""

    master: str
    slaves: tuple[str, ...]
    view: str


def _footprint_masks(block: ImageBlock, ids: list[str], z_ref: float, aoi: tuple[float, float, float, float],
                     cell: float, shrink: float = 1.0) -> np.ndarray:
    """(n, rows, cols) bool footprints on the plane ``Z = z_ref`` over the AOI grid of the images' central parts:
    the image window scaled by ``shrink`` about the principal point (1 = the whole image)."""
    x0, y0, x1, y1 = aoi
    cols, rows = max(1, int(np.ceil((x1 - x0) / cell))), max(1, int(np.ceil((y1 - y0) / cell)))
    out = np.zeros((len(ids), rows, cols), bool)
    s = np.linspace(0.0, 1.0, 8, endpoint=False)
    for i, iid in enumerate(ids):
        img = block.images[iid]
        cam = block.camera_of(img)
        w, h = cam.width - 1.0, cam.height - 1.0
        border = np.concatenate([np.stack([s * w, 0 * s], 1), np.stack([w + 0 * s, s * h], 1),
                                 np.stack([w - s * w, h + 0 * s], 1), np.stack([0 * s, h - s * h], 1)])
        pp = np.array([cam.cx, cam.cy])
        xyz = intersect_with_plane_z(cam, img.pose, pp + (border - pp) * shrink, z_ref)
        poly = xyz[np.isfinite(xyz[:, 0]), :2]
        if len(poly) < 3:
            continue
        pix = np.stack([(poly[:, 0] - x0) / cell, (y1 - poly[:, 1]) / cell], 1)
        m = np.zeros((rows, cols), np.uint8)
        cv2.fillPoly(m, [np.round(pix * 16).astype(np.int32)], 1, shift=4)
        out[i] = m.astype(bool)
    return out


def area_of_interest(block: ImageBlock, z_ref: float) -> tuple[float, float, float, float]:
    """Bounding box ``(x0, y0, x1, y1)`` of the ground seen by the nadir images (all images if none is nadir),
    taken as the image-centre points' hull widened by half a footprint."""
    by_view = block.images_by_view()
    ids = by_view.get("nadir") or [i for v in by_view.values() for i in v]
    pts = []
    for iid in ids:
        img = block.images[iid]
        cam = block.camera_of(img)
        pts.append(intersect_with_plane_z(cam, img.pose, np.array([[cam.cx, cam.cy]]), z_ref)[0, :2])
    pts = np.array(pts)
    return (float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max()))


def select_pairs(block: ImageBlock, z_ref: float, aoi: tuple[float, float, float, float] | None = None,
                 cfg: SelectionConfig = SelectionConfig()) -> list[MasterSelection]:
    """Masters and slaves for every view in ``cfg.views``.

    Parameters
    ----------
    z_ref : mean terrain height, metres (footprints are taken on this plane)
    aoi : ``(x0, y0, x1, y1)`` area to cover; by default :func:`area_of_interest`
    """
    aoi = aoi or area_of_interest(block, z_ref)
    out: list[MasterSelection] = []
    for view, ids in block.images_by_view().items():
        if view not in cfg.views or len(ids) < 2:
            continue
        full = _footprint_masks(block, ids, z_ref, aoi, cfg.grid_cell)
        owned = _footprint_masks(block, ids, z_ref, aoi, cfg.grid_cell, shrink=1.0 - cfg.master_overlap)
        covered = np.zeros(full.shape[1:], bool)
        masters: list[int] = []
        while True:
            gain = (owned & ~covered).sum(axis=(1, 2))
            gain[masters] = 0
            best = int(np.argmax(gain))
            if gain[best] <= 0.02 * owned[best].sum():
                break
            masters.append(best)
            covered |= owned[best]
        for m in masters:
            slaves = _rank_slaves(block, ids, m, full, z_ref, cfg)
            if slaves:
                out.append(MasterSelection(ids[m], tuple(slaves), view))
    return out


def _rank_slaves(block: ImageBlock, ids: list[str], m: int, full: np.ndarray, z_ref: float,
                 cfg: SelectionConfig) -> list[str]:
    img_m = block.images[ids[m]]
    cam_m = block.camera_of(img_m)
    centre = intersect_with_plane_z(cam_m, img_m.pose, np.array([[cam_m.cx, cam_m.cy]]), z_ref)[0]
    area_m = max(1, int(full[m].sum()))
    scored = []
    for j, sid in enumerate(ids):
        if j == m:
            continue
        p_s = block.images[sid].pose
        overlap = (full[m] & full[j]).sum() / area_m
        b = p_s.C - img_m.pose.C
        nb = float(np.linalg.norm(b))
        if overlap < cfg.min_overlap or nb <= 0:
            continue
        height = 0.5 * (np.linalg.norm(centre - img_m.pose.C) + np.linalg.norm(centre - p_s.C))
        bh = nb / height
        r1, r2 = centre - img_m.pose.C, centre - p_s.C
        angle = np.degrees(np.arccos(np.clip(r1 @ r2 / np.linalg.norm(r1) / np.linalg.norm(r2), -1, 1)))
        view_dir = img_m.pose.R[2] + p_s.R[2]
        view_dir /= np.linalg.norm(view_dir)
        along = np.degrees(np.arccos(min(1.0, abs(float(view_dir @ b)) / nb)))
        if not (cfg.base_height_min <= bh <= cfg.base_height_max) or angle > cfg.max_angle_deg:
            continue
        if along < cfg.min_baseline_view_angle_deg:
            continue
        # perpendicular baselines rectify with little distortion: prefer them
        score = overlap * np.exp(-0.5 * ((bh - cfg.base_height_ideal) / 0.15) ** 2) * np.sin(np.radians(along))
        scored.append((score, sid))
    scored.sort(reverse=True)
    return [s for _, s in scored[: cfg.slaves_per_master]]
