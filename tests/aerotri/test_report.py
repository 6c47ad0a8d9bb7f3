"""The image residual field of the triangulation report against fields made with known systematic errors."""

from __future__ import annotations

import numpy as np

from oblique_city.core.aerotri.report import residual_field
from oblique_city.core.model import CameraModel

CAMERA = CameraModel(id="c", width=1200, height=900, fx=1100.0, fy=1100.0, cx=600.0, cy=450.0)
NOISE_PX = 0.3


def _observations(n: int = 60_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-0.5, -0.5], [CAMERA.width - 0.5, CAMERA.height - 0.5], (n, 2))
    return uv, rng.normal(0.0, NOISE_PX, (n, 2))


def test_noise_alone_shows_no_systematic_residual():
    """0.3 px noise: 8 x 6 cells of about 1,250 residuals each, whose means scatter by 0.3 sqrt(2 / 1250) = 0.012
    px; the field reports that noise level within 15 % and finds under a third of it systematic (the estimate
    subtracts two figures of that size; its own scatter on 48 cells is about a fifth of the noise level)."""
    uv, v = _observations()
    f = residual_field(uv, v, CAMERA)
    assert f["cells"] == [8, 6] and sum(map(sum, f["count"])) == len(uv)
    expected = NOISE_PX * np.sqrt(2 / (len(uv) / 48))
    assert abs(f["noise_rms_px"] / expected - 1) < 0.15
    assert f["systematic_rms_px"] < expected / 3


def test_a_shift_and_a_radial_error_are_recovered_cell_by_cell_and_ring_by_ring():
    """Residuals of a constant shift (0.1, -0.05) px plus a radial error of 0.2 px at the corners growing with the
    radius: every cell mean is its cell's average of that field within 4 standard errors, the systematic RMS
    is the field's RMS within 0.005 px, and the radial profile follows the radial error ring by ring (the shift
    averages out: the rings are symmetric about the centre of the frame)."""
    uv, v = _observations(seed=1)
    d = uv - [CAMERA.cx, CAMERA.cy]
    r_max = np.hypot(CAMERA.cx + 0.5, CAMERA.cy + 0.5)
    true = np.array([0.1, -0.05]) + 0.2 * d / r_max
    f = residual_field(uv, v + true, CAMERA)
    cols, rows = f["cells"]
    cu = np.clip(((uv[:, 0] + 0.5) * cols / CAMERA.width).astype(int), 0, cols - 1)
    cv = np.clip(((uv[:, 1] + 0.5) * rows / CAMERA.height).astype(int), 0, rows - 1)
    for j in range(rows):
        for i in range(cols):
            sel = (cu == i) & (cv == j)
            se = NOISE_PX / np.sqrt(sel.sum())
            assert np.all(np.abs(np.array(f["mean_px"][j][i]) - true[sel].mean(0)) < 4 * se), (i, j)
    cell_true = np.array([[true[(cu == i) & (cv == j)].mean(0) for i in range(cols)] for j in range(rows)])
    n = np.array(f["count"])
    rms_true = np.sqrt(np.sum(n * np.sum(cell_true**2, 2)) / n.sum())
    assert abs(f["systematic_rms_px"] - rms_true) < 0.005
    ring_r = np.array(f["radial"]["radius_px"])
    assert abs(ring_r[-1] - r_max * 15 / 16) < 1.0  # 8 rings out to the farthest corner
    got = np.array([np.nan if m is None else m for m in f["radial"]["mean_px"]])
    ok = np.isfinite(got)
    assert ok.sum() == 8
    # within 4 standard errors of each ring's mean, plus 0.005 px for the ring's mean radius against its middle
    se = NOISE_PX / np.sqrt(np.array(f["radial"]["count"]))
    assert np.all(np.abs(got - 0.2 * ring_r / r_max) < 4 * se + 0.005)
