"""HAT on the rig: the heads of each exposure fused into one body after the runs (aerotri.rigfusion)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.aerotri.hierarchical import hierarchical
from oblique_city.core.aerotri.rigfusion import place_heads, rig_relations
from oblique_city.core.evaluate.aerotri import check_point_errors, rms_xy_z
from oblique_city.core.geometry.rotations import matrix_to_rotvec

pytestmark = pytest.mark.xdist_group("aerotri_sim")  # one worker builds the shared simulated block


def _arrays(poses: dict, ids: list[str]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([poses[i].R for i in ids]), np.array([poses[i].C for i in ids])


def test_the_rig_places_every_head_of_an_exposure_from_its_reference_head(sim):
    """The simulated rig is exact: from the true nadir poses the rig gives every head's true pose, and so does the
    rig estimated from the true poses."""
    ids = list(sim.block.images)
    ref, rel_r, rel_b = rig_relations(sim.block, ids)
    assert np.sum(ref != np.arange(len(ids))) == 4 * len({im.exposure for im in sim.block.images.values()})
    assert all(sim.block.images[ids[k]].head == "nadir" for k in np.unique(ref))
    r_true, c_true = _arrays(sim.true_poses, ids)
    r, c = place_heads(r_true, c_true, ref, rel_r, rel_b)
    np.testing.assert_allclose(r, r_true, atol=1e-9)
    np.testing.assert_allclose(c, c_true, atol=1e-6)
    # the rig the orientations give (HAT's with a mounting calibration): from the true poses, the true rig
    from oblique_city.core.aerotri.hierarchical import runs_rig

    ref_e, rel_re, rel_be = rig_relations(runs_rig(sim.block, sim.true_poses), ids)
    np.testing.assert_array_equal(ref_e, ref)
    r, c = place_heads(r_true, c_true, ref, rel_re, rel_be)
    np.testing.assert_allclose(r, r_true, atol=1e-9)
    np.testing.assert_allclose(c, c_true, atol=1e-6)


def test_the_body_map_is_the_derivative_of_the_heads_placement(sim):
    """A body's step (rotation about the world axes, centre of its reference head) moves each head as placing the
    heads on the rig does: the same rotation, and the centre also turned about the reference head's (lever arms of
    0.12 m here: a rotation of 1e-5 rad moves a head's centre by about 1.2e-6 m). Finite differences of
    :func:`place_heads` against the linear map, to 2e-8 (the rounding of map coordinates of some 5e6 m)."""
    from oblique_city.core.aerotri.rigfusion import _body_map
    from oblique_city.core.geometry.rotations import rotvec_to_matrix

    ids = list(sim.block.images)
    ref, rel_r, rel_b = rig_relations(sim.block, ids)
    r, c = place_heads(*_arrays(sim.true_poses, ids), ref, rel_r, rel_b)
    a = _body_map(c, ref)
    heads = np.flatnonzero(ref != np.arange(len(ids)))
    assert np.median(np.linalg.norm(c[heads] - c[ref[heads]], axis=1)) > 0.05
    for step in np.diag([1e-5, 1e-5, 1e-5, 1e-3, 1e-3, 1e-3]):
        r2, c2 = r.copy(), c.copy()
        for k in np.unique(ref[heads]):
            r2[k] = r[k] @ rotvec_to_matrix(step[:3])
            c2[k] = c[k] + step[3:]
        r2, c2 = place_heads(r2, c2, ref, rel_r, rel_b)
        d = np.swapaxes(r, 1, 2) @ r2
        moved = np.concatenate([np.stack([d[:, 2, 1], d[:, 0, 2], d[:, 1, 0]], 1), c2 - c], 1)[heads]
        np.testing.assert_allclose(moved, a[heads] @ step, rtol=0, atol=2e-8)


def test_hat_on_the_rig_fuses_the_heads_and_orients_them_better(sim, xyz0, options):
    """HAT adjusts each view apart; with ``rig`` the heads of each exposure are fused into one body after the runs.
    On the shared 400-image block: attitude 0.0049 -> 0.00096 deg RMS against the truth, centres 8.1 / 8.1 / 10.7 ->
    2.7 / 2.4 / 4.8 mm (0.0013 deg and 3.2 / 3.5 / 4.9 mm without the coarse steps). Errors over the fused standard
    deviations (two-level: each body's own block and the block's smooth modes): 0.86 / 0.75 / 0.51 in attitude,
    0.78 / 0.73 / 1.31 in the centres. A smooth mode's error on one block is a few random numbers, so one block's
    ratios scatter: on three 1,000-image blocks they were 0.97-1.07, 0.94-1.04 and 0.79-1.81 in attitude (RMS of
    the four blocks 0.97 / 0.92 / 1.19), hence the wide band."""
    plain = hierarchical(sim.block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0)
    fused = hierarchical(sim.block, sim.ties, replace(options, rig=True), connection="cba", cell=50.0, xyz0=xyz0)
    assert "rig_fusion" not in plain.extra
    stats = fused.extra["rig_fusion"]
    n_exp = len({im.exposure for im in sim.block.images.values()})
    assert stats["exposures"] == n_exp and stats["images"] == 5 * n_exp
    assert stats["rms_px_after"] < stats["rms_px_before"]
    # the residuals after the fusion per run: every view's near the simulated noise, their mean square the whole's
    by_run = stats["rms_px_by_group"]
    assert set(by_run) == {"nadir", "north", "east", "south", "west"}
    assert all(0.8 * options.sigma_px < v < 1.2 * options.sigma_px for v in by_run.values())
    assert min(by_run.values()) <= stats["rms_px_after"] <= max(by_run.values())
    ids = list(fused.poses)

    def errors(at):
        att = np.array([matrix_to_rotvec(sim.true_poses[i].R.T @ at.poses[i].R) for i in ids])
        cen = np.array([at.poses[i].C - sim.true_poses[i].C for i in ids])
        return att, cen

    att0, cen0 = errors(plain)
    att1, cen1 = errors(fused)
    rms = lambda e: np.sqrt(np.mean(e**2, 0))  # noqa: E731
    assert np.linalg.norm(rms(att1)) < 0.3 * np.linalg.norm(rms(att0))
    assert np.all(rms(cen1) < 0.8 * rms(cen0))
    # the fused heads sit on the rig exactly
    ref, rel_r, rel_b = rig_relations(sim.block, ids)
    r, c = _arrays(fused.poses, ids)
    r_p, c_p = place_heads(r, c, ref, rel_r, rel_b)
    np.testing.assert_allclose(r_p, r, atol=1e-9)
    np.testing.assert_allclose(c_p, c, atol=1e-6)
    # the ground is where the runs put it
    xy0, z0 = rms_xy_z(check_point_errors(sim.block, plain.poses)[1])
    xy1, z1 = rms_xy_z(check_point_errors(sim.block, fused.poses)[1])
    assert xy1 < 1.05 * xy0 + 0.001 and z1 < 1.05 * z0 + 0.001
    # the fused standard deviations: smaller than the runs', and telling the errors within a factor of two
    std0 = np.array([plain.image_std[i] for i in ids])
    std1 = np.array([fused.image_std[i] for i in ids])
    assert np.median(std1[:, :3]) < 0.5 * np.median(std0[:, :3])
    ratio_att, ratio_cen = rms(att1 / std1[:, :3]), rms(cen1 / std1[:, 3:])
    assert np.all((ratio_att > 0.4) & (ratio_att < 2.0)) and np.all((ratio_cen > 0.5) & (ratio_cen < 2.0))
