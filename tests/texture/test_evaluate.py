"""Texture metrics: texture GSD from UVs, cross-correlation registration with a known shift."""

from __future__ import annotations

import numpy as np

from oblique_city.core.evaluate.texture import registration_shift, texture_gsd


def test_texture_gsd_from_uv_area():
    ring = np.array([[0, 0, 0], [10, 0, 0], [10, 0, 6], [0, 0, 6]], float) + [500000, 5400000, 100]
    uv = np.array([[0, 0], [200, 0], [200, 120], [0, 120]], float) / [1024, 512]  # 200 x 120 texels
    assert abs(texture_gsd(ring, uv, (1024, 512)) - 0.05) < 1e-12
    assert np.isnan(texture_gsd(ring, np.zeros((4, 2)), (1024, 512)))


def test_registration_recovers_a_known_shift():
    import cv2

    rng = np.random.default_rng(2)
    base = cv2.GaussianBlur(rng.normal(size=(160, 200)).astype(np.float32), (0, 0), 2.0)
    m = np.float32([[1, 0, 2.5], [0, 1, -1.25]])  # content moves 2.5 texels right, 1.25 up
    moved = cv2.warpAffine(base, m, (200, 160), borderMode=cv2.BORDER_REFLECT)
    mask = np.ones(base.shape, bool)
    mask[:20, :30] = False
    shift, peak = registration_shift(moved, base, mask)
    assert np.allclose(shift, [2.5, -1.25], atol=0.15) and peak > 0.3
    shift0, _ = registration_shift(base, base, mask)
    assert np.allclose(shift0, 0, atol=1e-6)
