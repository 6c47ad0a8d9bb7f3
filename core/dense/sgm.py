"""Semi-global matching of a rectified pair with OpenCV's StereoSGBM, made complete and checked.

OpenCV's StereoSGBM only evaluates columns ``x >= minDisparity + numDisparities - 1`` of the left image; with
the large disparities of aerial pairs this silently drops a wide strip of the overlap. Both images are padded on
the left so the whole overlap is matched. The right disparity map is computed by matching the mirrored pair
(left' = flip(right), right' = flip(left) has the same disparities), and a left-right consistency check removes
occlusions and mismatches. Disparities within a pixel of either end of the search interval are dropped: where the
true disparity lies outside the interval, the best candidate sits at its end (in both maps, so the left-right check
keeps it). Disparities keep SGBM's 1/16 pixel sub-pixel resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
         "hh": cv2.STEREO_SGBM_MODE_HH, "hh4": cv2.STEREO_SGBM_MODE_HH4}


@dataclass(frozen=True)
class SgmConfig:
    """SGBM settings.

    Attributes
    ----------
    block_size : matching window (odd)
    p1, p2 : smoothness penalties per channel and window pixel (OpenCV's P1 = p1 * cn * block_size^2)
    uniqueness : percent margin by which the best cost must win
    speckle_window, speckle_range : OpenCV's speckle filter (0 window disables it)
    mode : ``sgbm`` (5 paths), ``sgbm_3way`` (faster) , ``hh`` (8 paths) or ``hh4``
    pad : pad the left edge so every column of the overlap is matched
    lr_check : run the left-right consistency check
    lr_max_diff : largest left/right disagreement kept, pixels
    """

    block_size: int = 5
    p1: int = 8
    p2: int = 32
    uniqueness: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    mode: str = "sgbm_3way"
    pad: bool = True
    lr_check: bool = True
    lr_max_diff: float = 1.0


def _matcher(d_min: int, num: int, channels: int, cfg: SgmConfig):
    bs = cfg.block_size
    return cv2.StereoSGBM_create(
        minDisparity=d_min, numDisparities=num, blockSize=bs, P1=cfg.p1 * channels * bs * bs,
        P2=cfg.p2 * channels * bs * bs, disp12MaxDiff=-1, uniquenessRatio=cfg.uniqueness,
        speckleWindowSize=cfg.speckle_window, speckleRange=cfg.speckle_range, preFilterCap=63,
        mode=MODES[cfg.mode])


def disparity_search(d_lo: float, d_hi: float) -> tuple[int, int]:
    """OpenCV's ``(minDisparity, numDisparities)`` covering ``[d_lo, d_hi]`` (num a multiple of 16)."""
    d_min = int(np.floor(d_lo))
    num = int(np.ceil((d_hi - d_min + 1) / 16.0)) * 16
    return d_min, max(16, num)


def _raw(left: np.ndarray, right: np.ndarray, d_min: int, num: int, cfg: SgmConfig) -> np.ndarray:
    """SGBM disparity of ``left`` (float32 pixels, NaN invalid), with left padding when configured."""
    pad = max(0, d_min + num - 1) if cfg.pad else 0
    if pad:
        widths = ((0, 0), (pad, 0)) + (((0, 0),) if left.ndim == 3 else ())
        left = np.pad(left, widths)
        right = np.pad(right, widths)
    channels = 1 if left.ndim == 2 else left.shape[2]
    disp = _matcher(d_min, num, channels, cfg).compute(left, right)[:, pad:]
    out = disp.astype(np.float32) / 16.0
    out[disp < d_min * 16] = np.nan
    return out


def lr_consistency(disp_left: np.ndarray, disp_right: np.ndarray, max_diff: float) -> np.ndarray:
    """Mask ``(h, w)`` of left disparities confirmed by the right map: ``|d_L(x) - d_R(x - d_L(x))| <= max_diff``."""
    h, w = disp_left.shape
    xs = np.arange(w)[None, :] - np.nan_to_num(disp_left, nan=-1e6)
    xr = np.rint(xs).astype(np.int64)
    inside = (xr >= 0) & (xr < w) & np.isfinite(disp_left)
    dr = np.full((h, w), np.nan, np.float32)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    dr[inside] = disp_right[rows[inside], xr[inside]]
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(disp_left - dr) <= max_diff)


def sgm_disparity(left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float,
                  cfg: SgmConfig = SgmConfig(), drop_ends: bool = True) -> np.ndarray:
    """Disparity map of the left image of a rectified pair.

    Parameters
    ----------
    left, right : (h, w) or (h, w, 3) uint8 rectified images (same size)
    d_lo, d_hi : disparity search interval, pixels (``d = x_left - x_right``)
    drop_ends : drop disparities within a pixel of either end of the search interval (kept by the coarse search
        of :func:`coarse_range`, to which they say that the scene reaches beyond the interval)

    Returns
    -------
    disparity : (h, w) float32, NaN where invalid, occluded, inconsistent or at an end of the search interval
    """
    d_min, num = disparity_search(d_lo, d_hi)
    disp = _raw(left, right, d_min, num, cfg)
    if cfg.lr_check:
        disp_r = _raw(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), d_min, num,
                      cfg)[:, ::-1]
        disp[~lr_consistency(disp, disp_r, cfg.lr_max_diff)] = np.nan
    if drop_ends:
        with np.errstate(invalid="ignore"):
            disp[(disp <= d_min + 1) | (disp >= d_min + num - 2)] = np.nan
    return disp


def coarse_range(left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float, cfg: SgmConfig = SgmConfig(),
                 levels: int = 2, margin_px: float = 12.0, quantile: float = 0.5, near_high: bool = True
                 ) -> tuple[float, float]:
    """Narrow the far end of a wide disparity interval by matching a reduced pair first (coarse-to-fine search).

    The pair is reduced ``levels`` times by 2 (Gaussian pyramid) and matched over the prior interval; the robust
    far extreme of the coarse disparities (the ``quantile`` in percent from the far side), scaled back and widened
    by ``margin_px``, replaces the prior's far end. Coarse disparities at the end of the interval count: where many
    pixels saturate there, the scene reaches beyond it and the prior's end is kept. The near end (the high end when
    ``near_high``) stays at the prior: a small tall object, a tower top of a few square metres, covers too few
    pixels of the reduced pair to be matched there or to count in its quantiles (on the demo the 99.5th percentile
    put the upper end of the nadir pairs 5-10 m below the church tower's top, whose roof then came from the
    oblique views alone). With too few coarse matches the prior is kept.
    """
    f = 2 ** levels
    lo_img, ro_img = left, right
    for _ in range(levels):
        lo_img, ro_img = cv2.pyrDown(lo_img), cv2.pyrDown(ro_img)
    disp = sgm_disparity(lo_img, ro_img, d_lo / f, d_hi / f, cfg, drop_ends=False)
    ok = np.isfinite(disp)
    if ok.sum() < 0.02 * disp.size or ok.sum() < 100:
        return d_lo, d_hi
    if near_high:
        return max(d_lo, float(np.percentile(disp[ok], quantile)) * f - margin_px), d_hi
    return d_lo, min(d_hi, float(np.percentile(disp[ok], 100.0 - quantile)) * f + margin_px)


def plain_sgbm(left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float,
               cfg: SgmConfig = SgmConfig()) -> np.ndarray:
    """OpenCV StereoSGBM with the same settings as :func:`sgm_disparity` but no padding and no left-right check
    (the reference of the benchmark); NaN where SGBM gives no disparity."""
    d_min, num = disparity_search(d_lo, d_hi)
    return _raw(left, right, d_min, num, SgmConfig(**{**cfg.__dict__, "pad": False, "lr_check": False}))
