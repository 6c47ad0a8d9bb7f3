"""DSM / DTM accuracy against ground-truth rasters: RMSE, robust spreads and completeness, per semantic class.

The estimate is sampled (bilinear; taken as is on the same grid) at the reference raster's cell centres, so any
grid works. Completeness is the
fraction of reference cells (inside the mask) where the estimate has a value. Robust figures: NMAD
(``1.4826 * median(|e - median(e)|)``) and the 95th percentile of ``|e|``, as in DSM benchmarks.
"""

from __future__ import annotations

import numpy as np

from ..model import Raster

GROUND_CLASSES = ("ground", "street")


def _resample(est: Raster, ref: Raster) -> np.ndarray:
    """``est`` on ``ref``'s cell centres: the data itself when the grids coincide, else bilinear."""
    if est.shape == ref.shape and (est.x0, est.y0, est.cell) == (ref.x0, ref.y0, ref.cell):
        return np.asarray(est.data, np.float64)
    xs, ys = ref.cell_centers()
    gx, gy = np.meshgrid(xs, ys)
    return est.sample(np.column_stack([gx.ravel(), gy.ravel()])).reshape(ref.shape)


def raster_errors(est: Raster, ref: Raster, mask: np.ndarray | None = None, outlier: float | None = None) -> dict:
    """Errors ``est - ref`` over the reference cells where ``ref`` is finite and ``mask`` (rows, cols) is True.

    Returns ``n_ref``, ``completeness``, ``rmse``, ``mean``, ``median``, ``nmad``, ``p95_abs``, ``max_abs`` and,
    when ``outlier`` (m) is given, ``outlier_fraction`` (|e| > outlier) and ``rmse_inliers``.
    """
    r = np.asarray(ref.data, np.float64)
    m = np.isfinite(r) if mask is None else (np.isfinite(r) & np.asarray(mask, bool))
    if ref.nodata is not None:
        m &= r != ref.nodata
    e_full = _resample(est, ref) - r
    n_ref = int(m.sum())
    valid = m & np.isfinite(e_full)
    e = e_full[valid]
    out = {"n_ref": n_ref, "completeness": float(valid.sum() / n_ref) if n_ref else float("nan")}
    if len(e) == 0:
        out.update({k: float("nan") for k in ("rmse", "mean", "median", "nmad", "p95_abs", "max_abs")})
        return out
    med = float(np.median(e))
    out.update({"rmse": float(np.sqrt(np.mean(e ** 2))), "mean": float(e.mean()), "median": med,
                "nmad": float(1.4826 * np.median(np.abs(e - med))), "p95_abs": float(np.percentile(np.abs(e), 95)),
                "max_abs": float(np.abs(e).max())})
    if outlier is not None:
        inl = np.abs(e) <= outlier
        out["outlier_fraction"] = float(1.0 - inl.mean())
        out["rmse_inliers"] = float(np.sqrt(np.mean(e[inl] ** 2))) if inl.any() else float("nan")
    return out


def class_masks(classes: Raster, semantic: dict[str, int]) -> dict[str, np.ndarray]:
    """Boolean masks per semantic class name from a class raster (e.g. ``truth/classes.tif``), plus ``building``
    (roof, roof installation, roof edge, wall) and ``ground`` (ground and street)."""
    c = np.asarray(classes.data)
    out = {name: c == code for name, code in semantic.items()}
    out["building"] = np.isin(c, [semantic[k] for k in ("roof", "roof_installation", "roof_edge", "wall")
                                  if k in semantic])
    out["ground"] = np.isin(c, [semantic[k] for k in GROUND_CLASSES if k in semantic])
    return out


def errors_by_class(est: Raster, ref: Raster, classes: Raster, semantic: dict[str, int],
                    outlier: float | None = None) -> dict:
    """:func:`raster_errors` over all cells and per class mask of :func:`class_masks` (classes with no cells are
    left out); the class raster must be on the reference grid."""
    out = {"all": raster_errors(est, ref, None, outlier)}
    for name, m in class_masks(classes, semantic).items():
        if m.any():
            out[name] = raster_errors(est, ref, m, outlier)
    return out


def dtm_errors(est_dtm: Raster, ref_dtm: Raster, classes: Raster, semantic: dict[str, int],
               outlier: float | None = None) -> dict:
    """DTM errors on open ground (ground and street cells of the class raster: under buildings and trees the
    terrain is interpolated by any DTM method, so those cells are reported separately as ``covered``)."""
    masks = class_masks(classes, semantic)
    return {"open_ground": raster_errors(est_dtm, ref_dtm, masks["ground"], outlier),
            "covered": raster_errors(est_dtm, ref_dtm, ~masks["ground"], outlier)}
