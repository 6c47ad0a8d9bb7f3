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


def test_hat_on_the_rig_fuses_the_heads_and_orients_them_better(sim, xyz0, options):
    """HAT adjusts each view apart; with ``rig`` the heads of each exposure are fused into one body after the runs.
    On the shared 400-image block: attitude 0.0049 -> 0.0013 deg RMS against the truth, centres 8.1 / 8.1 / 10.7 ->
    3.2 / 3.5 / 4.9 mm, check points 11.6 / 19.4 -> 11.3 / 19.0 mm. Errors over the fused standard deviations (a
    lower bound, the other exposures held): 1.21 / 1.47 / 1.56 in attitude, 0.99 / 1.06 / 1.25 in the centres."""
    plain = hierarchical(sim.block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0)
    fused = hierarchical(sim.block, sim.ties, replace(options, rig=True), connection="cba", cell=50.0, xyz0=xyz0)
    assert "rig_fusion" not in plain.extra
    stats = fused.extra["rig_fusion"]
    n_exp = len({im.exposure for im in sim.block.images.values()})
    assert stats["exposures"] == n_exp and stats["images"] == 5 * n_exp
    assert stats["rms_px_after"] < stats["rms_px_before"]
    ids = list(fused.poses)

    def errors(at):
        att = np.array([matrix_to_rotvec(sim.true_poses[i].R.T @ at.poses[i].R) for i in ids])
        cen = np.array([at.poses[i].C - sim.true_poses[i].C for i in ids])
        return att, cen

    att0, cen0 = errors(plain)
    att1, cen1 = errors(fused)
    rms = lambda e: np.sqrt(np.mean(e**2, 0))  # noqa: E731
    assert np.linalg.norm(rms(att1)) < 0.4 * np.linalg.norm(rms(att0))
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
    # the fused standard deviations: smaller than the runs', and a lower bound that is not far off
    std0 = np.array([plain.image_std[i] for i in ids])
    std1 = np.array([fused.image_std[i] for i in ids])
    assert np.median(std1[:, :3]) < 0.5 * np.median(std0[:, :3])
    ratio_att, ratio_cen = rms(att1 / std1[:, :3]), rms(cen1 / std1[:, 3:])
    assert np.all((ratio_att > 0.9) & (ratio_att < 2.0)) and np.all((ratio_cen > 0.8) & (ratio_cen < 1.6))
