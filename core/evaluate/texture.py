"""Texture metrics: the texture GSD each surface actually got, and the atlas against ground truth.

Texture GSD: ``sqrt(3-D area / UV area in texels)`` per surface, metres per texel as stored (independent of
how the texture stage chose its texel size).

Accuracy against a simulated city: every texel of a surface's atlas patch is compared with a *clean rendering*
of the true city at the same 3-D point: a ray from the texel, ``offset`` metres in front of the reconstructed
plane, along the plane's inward normal hits the true mesh, which is shaded with the simulator's own albedo and
lighting (sun, cast shadow, sky) and tone curve, but without the per-head exposure, vignetting and sensor noise of
the images. Per surface:

* ``shift_m`` -- geometric registration: the translation between the patch and the clean rendering by
  cross-correlation of their luminance (texels times texel size), i.e. how far the texture sits from where the truth
  has the same content, in the surface plane. It includes the effect of the reconstruction's own geometric
  errors (a wall plane 0.3 m in front of the true one shifts its texture by the parallax of the chosen views),
  which is what a user sees.
* ``ncc`` -- normalised cross-correlation of the luminance (structure, independent of gain and offset).
* ``rmse_dn`` -- colour RMSE in 8-bit DN after one gain per channel for the whole city (the radiometric datum of
  the images is free).

Texels whose truth ray misses or hits farther than ``max_depth`` from the plane are left out (``valid``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..texture.plane import ring_area, texel_grid


def texture_gsd(ring_xyz: np.ndarray, uv: np.ndarray, page_size: tuple[int, int]) -> float:
    """Metres per texel of a surface: ring ``(k, 3)``, its UVs ``(k, 2)``, the page ``(width, height)``."""
    xy = np.asarray(uv, np.float64) * np.asarray(page_size, np.float64)
    x, y = xy[:, 0], xy[:, 1]
    a_uv = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    return float(np.sqrt(ring_area(ring_xyz) / a_uv)) if a_uv > 0 else float("nan")


def patch_texels(ring_xyz: np.ndarray, record: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The texels of one surface's atlas patch from its ``textures.json`` record.

    Returns rows, cols ``(n,)`` int (patch texels inside the ring), world points ``(n, 3)`` and the normal (3,).
    """
    grid = texel_grid(ring_xyz, record["texel"])
    rows, cols = np.nonzero(grid.mask)
    f = record["frame"]
    s = f["s0"] + (cols + 0.5) * record["texel"]
    t = f["t1"] - (rows + 0.5) * record["texel"]
    xyz = np.asarray(f["origin"]) + s[:, None] * np.asarray(f["e1"]) + t[:, None] * np.asarray(f["e2"])
    return rows, cols, xyz, grid.frame.normal


def truth_colours(renderer, xyz: np.ndarray, normal: np.ndarray, texel: float, offset: float = 1.0,
                  max_depth: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clean colours of the true city (see the module docstring) at world points ``(n, 3)`` of a plane with
    outward unit ``normal (3,)``.

    Returns colours ``(n, 3)`` float32 (0-255, display tone curve), ``valid (n,)`` bool and the distance
    ``(n,)`` float32 from each point to the true surface along the inward normal (negative: the truth is in
    front of the plane).
    """
    import open3d as o3d

    city, cfg = renderer.city, renderer.config
    start = (xyz + offset * normal - city.origin).astype(np.float32)
    rays = np.empty((len(xyz), 6), np.float32)
    rays[:, :3] = start
    rays[:, 3:] = -normal
    r = renderer.scene.cast_rays(o3d.core.Tensor(rays))
    t = r["t_hit"].numpy()
    valid = np.isfinite(t) & (t < offset + max_depth)
    out = np.zeros((len(xyz), 3), np.float32)
    depth = (t - offset).astype(np.float32)
    if not valid.any():
        return out, valid, depth
    hi = np.flatnonzero(valid)
    tri = r["primitive_ids"].numpy().astype(np.int64)[hi]
    bary = r["primitive_uvs"].numpy()[hi]
    p = start[hi] - t[hi, None] * normal.astype(np.float32)
    uvc = city.uv[tri]
    uv = uvc[:, 0] * (1 - bary[:, 0:1] - bary[:, 1:2]) + uvc[:, 1] * bary[:, 0:1] + uvc[:, 2] * bary[:, 1:2]
    albedo = renderer.albedo(tri, uv, p, np.full(len(hi), texel, np.float32))  # the simulator's own materials
    n = renderer.normals[tri].copy()
    n[(n @ normal.astype(np.float32)) < 0] *= -1.0
    sun = cfg.sun_direction().astype(np.float32)
    ndl = n @ sun
    vis = np.ones(len(hi), np.float32)
    lit = np.flatnonzero(ndl > 0)
    if cfg.shadows and len(lit):
        sr = np.empty((len(lit), 6), np.float32)
        sr[:, :3] = p[lit] + n[lit] * 0.03
        sr[:, 3:] = sun
        vis[lit[renderer.scene.test_occlusions(o3d.core.Tensor(sr), tnear=0.0, tfar=1e4).numpy()]] = 0.0
    irr = cfg.sun * np.maximum(ndl, 0.0) * vis + cfg.sky * (0.55 + 0.45 * n[:, 2]) + 0.05
    lin = albedo * irr[:, None] * cfg.exposure
    out[hi] = np.clip(lin, 0, 1.5) ** (1 / 2.2) * 255.0
    return out, valid, depth


def _lum(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)


def registration_shift(got: np.ndarray, want: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Translation ``(dx, dy)`` in texels that moves ``want`` onto ``got`` (both (h, w) float grey images,
    compared on ``mask (h, w)``), and the normalised correlation at that shift (0..1).

    Cross-correlation of the mean-free, Hann-windowed images by FFT; the integer peak is refined by a parabola
    through its neighbours along each axis (the images are smooth at the texel scale, so the peak is too).
    """
    import cv2

    win = cv2.createHanningWindow((got.shape[1], got.shape[0]), cv2.CV_64F) * mask
    a = np.where(mask, got - got[mask].mean(), 0.0) * win
    b = np.where(mask, want - want[mask].mean(), 0.0) * win
    c = np.real(np.fft.ifft2(np.fft.fft2(a) * np.conj(np.fft.fft2(b))))
    iy, ix = np.unravel_index(int(np.argmax(c)), c.shape)
    h, w = c.shape

    def sub(m1: float, c0: float, p1: float) -> float:
        den = m1 - 2.0 * c0 + p1
        return 0.5 * (m1 - p1) / den if den < 0 else 0.0

    dx = ix + sub(c[iy, ix - 1], c[iy, ix], c[iy, (ix + 1) % w])
    dy = iy + sub(c[iy - 1, ix], c[iy, ix], c[(iy + 1) % h, ix])
    dx, dy = (dx + w / 2) % w - w / 2, (dy + h / 2) % h - h / 2
    peak = float(c[iy, ix] / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))
    return np.array([dx, dy]), peak


@dataclass(frozen=True)
class SurfaceAccuracy:
    """Per-surface comparison with the truth: texels compared, registration shift (texels and metres) with its
    correlation peak (NaN when the patch is too small), luminance NCC, the median distance between the
    reconstructed plane and the true surface (the geometric error the texture inherits), and the compared
    colours (n, 3) for the colour RMSE."""

    surface_id: str
    kind: str
    texels: int
    shift_texels: float
    shift_m: float
    peak: float
    ncc: float
    plane_offset_m: float
    got: np.ndarray
    want: np.ndarray


def surface_accuracy(surface_id: str, kind: str, page: np.ndarray, record: dict, ring_xyz: np.ndarray, renderer,
                     min_size: int = 24) -> SurfaceAccuracy | None:
    """Compare one surface's atlas patch with the clean truth rendering; None when fewer than 50 texels can
    be compared. ``page`` is the atlas page (h, w, 3) uint8, ``record`` its ``textures.json`` entry."""
    rows, cols, xyz, normal = patch_texels(ring_xyz, record)
    want, valid, depth = truth_colours(renderer, xyz, normal, record["texel"])
    if valid.sum() < 50:
        return None
    x0, y0 = record["rect"][0], record["rect"][1]
    got = page[y0 + rows, x0 + cols].astype(np.float32)
    gl, wl = _lum(got[valid]), _lum(want[valid])
    gc, wc = gl - gl.mean(), wl - wl.mean()
    ncc = float((gc * wc).sum() / max(np.sqrt((gc ** 2).sum() * (wc ** 2).sum()), 1e-9))
    shift, peak = np.full(2, np.nan), float("nan")
    h, w = rows.max() + 1, cols.max() + 1
    if min(h, w) >= min_size:
        g_img, w_img, m = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32), np.zeros((h, w), bool)
        g_img[rows[valid], cols[valid]] = gl
        w_img[rows[valid], cols[valid]] = wl
        m[rows[valid], cols[valid]] = True
        shift, peak = registration_shift(g_img, w_img, m)
    s = float(np.hypot(*shift))
    return SurfaceAccuracy(surface_id, kind, int(valid.sum()), s, s * record["texel"], peak, ncc,
                           float(np.median(np.abs(depth[valid]))), got[valid], want[valid])


def colour_rmse(results: list[SurfaceAccuracy]) -> tuple[float, np.ndarray]:
    """Colour RMSE (DN) over all compared texels after one least-squares gain per channel; and the gains."""
    got = np.concatenate([r.got for r in results]).astype(np.float64)
    want = np.concatenate([r.want for r in results]).astype(np.float64)
    gain = (got * want).sum(0) / np.maximum((want * want).sum(0), 1e-9)
    return float(np.sqrt(np.mean((got - want * gain) ** 2))), gain
