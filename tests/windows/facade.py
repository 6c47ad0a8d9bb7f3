"""A synthetic facade with a known window grid: wall plaster with noise, dark windows with a light frame."""

from __future__ import annotations

import numpy as np

WALL = np.array([205.0, 195.0, 175.0])
GLASS = np.array([45.0, 55.0, 70.0])


def window_grid(cols: int = 4, rows: int = 3, x0: float = 1.4, z0: float = 1.0, dx: float = 3.0, dz: float = 3.0,
                w: float = 1.2, h: float = 1.5, missing: tuple[tuple[int, int], ...] = ((1, 2),)
                ) -> list[tuple[float, float, float, float]]:
    """Window rectangles ``(s0, z0, s1, z1)`` in metres (``s`` along the wall, ``z`` up from its bottom), the
    cells ``(row, col)`` in ``missing`` left out."""
    return [(x0 + c * dx, z0 + r * dz, x0 + c * dx + w, z0 + r * dz + h)
            for r in range(rows) for c in range(cols) if (r, c) not in missing]


def render_facade(windows: list[tuple[float, float, float, float]], width_m: float, height_m: float, texel: float,
                  noise: float = 8.0, frame_m: float = 0.0, seed: int = 0,
                  blob: tuple[float, float, float, float] | None = None, wall: np.ndarray = WALL,
                  glass: np.ndarray = GLASS, bar_m: float = 0.0, right_pane: np.ndarray | None = None) -> np.ndarray:
    """Facade texture ``(rows, cols, 3)`` uint8 (row 0 at the top) of ``windows`` (metres, see
    :func:`window_grid`), area-averaged at ``texel`` m (4x4 supersampling), Gaussian noise; ``frame_m`` paints a
    light frame of that width inside every window; ``blob`` ``(s, z, rs, rz)`` a dark green ellipse (a tree);
    ``wall`` and ``glass`` colours (RGB 0-255); ``bar_m`` a vertical glazing bar of that width and the wall's
    colour down the middle of every window; ``right_pane`` another colour for the right half of the glass (a
    reflection)."""
    ss = 4
    ncol, nrow = int(round(width_m / texel)), int(round(height_m / texel))
    s = (np.arange(ncol * ss) + 0.5) * texel / ss
    z = height_m - (np.arange(nrow * ss) + 0.5) * texel / ss
    S, Z = np.meshgrid(s, z)
    img = np.broadcast_to(np.asarray(wall, np.float64), (*S.shape, 3)).copy()
    for a, b, c, d in windows:
        inside = (S >= a) & (S < c) & (Z >= b) & (Z < d)
        glass_in = inside & (S >= a + frame_m) & (S < c - frame_m) & (Z >= b + frame_m) & (Z < d - frame_m)
        img[inside] = 0.8 * np.asarray(wall, np.float64)
        img[glass_in] = glass
        if right_pane is not None:
            img[glass_in & (S >= 0.5 * (a + c))] = right_pane
        img[inside & (np.abs(S - 0.5 * (a + c)) < 0.5 * bar_m)] = wall
    if blob is not None:
        bs, bz, rs, rz = blob
        img[((S - bs) / rs) ** 2 + ((Z - bz) / rz) ** 2 <= 1.0] = (40.0, 70.0, 35.0)
    img = img.reshape(nrow, ss, ncol, ss, 3).mean((1, 3))
    img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
