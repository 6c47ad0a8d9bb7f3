"""The observation-only simulator: ray counts, noise, blunder share and navigation errors as configured."""

from __future__ import annotations

import numpy as np

from oblique_city.core.geometry.projection import project
from oblique_city.core.simulate.observations import SimulationConfig, simulate_block


def test_nadir_ray_counts_at_80_60_overlap():
    """80 % forward and 60 % side overlap give 1 / (0.2 * 0.4) = 12.5 nadir images over a point; occlusion
    in the streets removes some: interior points must have about 12 nadir rays."""
    s = simulate_block(SimulationConfig(n_images=300, tie_density=0.0004, p_detect=1.0, facade_share=0.0,
                                        blunder_fraction=0.0, n_ground_points=0, seed=5))
    t = s.ties
    views = np.array([s.block.images[i].view for i in t.image_ids])
    nadir = np.bincount(t.obs_track[views[t.obs_image] == "nadir"], minlength=t.n_tracks)
    c = np.array([s.true_poses[i].C for i in t.image_ids if s.block.images[i].view == "nadir"])
    lo, hi = c[:, :2].min(0) + 250, c[:, :2].max(0) - 250
    inner = np.all((s.true_xyz[:, :2] > lo) & (s.true_xyz[:, :2] < hi), 1)
    assert inner.sum() > 30
    assert 9 <= np.median(nadir[inner]) <= 14
    assert np.all(t.ray_counts() >= 2)


def test_noise_blunders_and_navigation_errors():
    cfg = SimulationConfig(n_images=100, tie_density=0.0004, seed=11)
    s = simulate_block(cfg)
    t, b = s.ties, s.block
    assert abs(t.obs_blunder.mean() - cfg.blunder_fraction) < 0.006
    # measurement noise of the clean observations against the true projections
    res = []
    for k, iid in enumerate(t.image_ids):
        sel = (t.obs_image == k) & ~t.obs_blunder
        if sel.any():
            uv, _ = project(b.camera_of(iid), s.true_poses[iid], s.true_xyz[t.obs_track[sel]])
            res.append(t.obs_uv[sel] - uv)
    res = np.concatenate(res)
    assert abs(res.std() - cfg.noise_px) < 0.02 and abs(res.mean()) < 0.01
    # navigation: centre errors = bias + noise per exposure (all heads of an exposure share them)
    err = np.array([b.images[i].pose_approx.C - s.true_poses[i].C for i in b.images if i.endswith("_nadir")])
    np.testing.assert_allclose(err.mean(0), cfg.gnss_bias, atol=0.03)
    z = (err - err.mean(0)) / np.array(cfg.gnss_sigma)  # pooled over the axes: ~60 samples
    assert 0.7 < z.std() < 1.3
    e0 = b.images["e00003_nadir"].pose_approx.C - s.true_poses["e00003_nadir"].C
    e1 = b.images["e00003_left"].pose_approx.C - s.true_poses["e00003_left"].C
    np.testing.assert_allclose(e0, e1, atol=1e-9)
    assert sum(gp.kind == "check" for gp in b.ground_points.values()) == cfg.n_ground_points // 2
