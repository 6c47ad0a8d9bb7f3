"""Hierarchical AT with connection points against the integrated adjustment; CBA selection; baselines."""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.aerotri.bundle import DETECTION_POWER, control_point_tests
from oblique_city.core.aerotri.hierarchical import (
    ATResult,
    hierarchical,
    integrated,
    nadir_propagation,
    select_connections,
    weak_tracks,
)
from oblique_city.core.aerotri.precision import point_jacobians
from oblique_city.core.aerotri.problem import build_problem, restarted
from oblique_city.core.aerotri.report import reliability, tie_point_shifts, track_residual_rms
from oblique_city.core.aerotri.strips import flight_strips
from oblique_city.core.evaluate.aerotri import blunder_scores, check_point_errors, rms_xy_z
from oblique_city.core.geometry.rotations import rotation_angle
from oblique_city.core.model import Pose
from oblique_city.core.pipeline import Executor

pytestmark = pytest.mark.xdist_group("aerotri_sim")  # one worker builds the shared simulated block


def test_hat_cba_agrees_with_iat(sim, xyz0, options, iat):
    hat = hierarchical(sim.block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0)
    assert [r.name for r in hat.runs] == ["nadir", "north", "east", "south", "west"]
    assert all(r.connection_count > 20 for r in hat.runs[1:])
    # the oblique runs start from the propagated nadir corrections: blunders screened there, no robust solve (a
    # second least-squares solve when the last rejections carry more than resolve_tolerance of chi-square)
    for run in hat.runs[1:]:
        assert run.result.log[0].startswith("screening at the start") and "robust" not in run.result.log[0]
        assert not any("cauchy" in line for line in run.result.log)
        assert sum("least squares" in line for line in run.result.log) <= 2
        # connection points as 2-row blocks: Ceres' Schur eliminator specialised for 2-row blocks, 3-vector
        # points and 6-DoF images (the dynamic one, "d,d,d", is about a third slower on the linear solves)
        assert all("Schur structure 2,3,6" in line for line in run.result.log if "least squares" in line)
    s = blunder_scores(sim.ties.obs_blunder, hat.obs_rejected)
    assert s["recall"] >= 0.99 and s["false_alarm"] <= 0.01
    # the tracks a run held with one or two rays are tested again over all their rays: the runs alone found 92 % of
    # the blunders there (97.4 % of all) with 0.21 % false alarms, the final tests 99.9 % (99.5 % of all) with 0.10 %
    weak = weak_tracks(sim.ties, [r.obs_index for r in hat.runs])[sim.ties.obs_track]
    truth = sim.ties.obs_blunder
    assert hat.extra["final_test_rejected"] > 0
    assert (truth & weak & hat.obs_rejected).sum() > 0.98 * (truth & weak).sum()
    assert (~truth & weak & hat.obs_rejected).sum() < 0.002 * (~truth & weak).sum()
    assert set(hat.poses) == set(iat.poses)
    xy_h, z_h = rms_xy_z(check_point_errors(sim.block, hat.poses)[1])
    xy_i, z_i = rms_xy_z(check_point_errors(sim.block, iat.poses)[1])
    assert xy_h < 1.3 * xy_i + 0.002 and z_h < 1.3 * z_i + 0.005
    # multi-ray tie points agree to a fraction of the GSD, about their own standard deviation
    rays = sim.ties.ray_counts()
    d = np.linalg.norm(hat.xyz - iat.xyz, axis=1)[rays >= 5]
    std = np.sqrt(np.abs(np.trace(iat.xyz_cov, axis1=1, axis2=2)))[rays >= 5]
    assert np.nanmedian(d) < 0.25 * sim.gsd and np.nanpercentile(d, 90) < 0.6 * sim.gsd
    assert np.nanmedian(d / std) < 1.5
    # oblique orientations agree to a few thousandths of a degree
    ang = [np.degrees(rotation_angle(hat.poses[i].R, iat.poses[i].R)) for i in iat.poses]
    assert np.median(ang) < 0.003


def test_hat_scales_the_prior_sigmas_in_the_nadir_run_and_hands_them_on(sim, xyz0, options):
    """The block's GNSS/IMU sigmas given 4 times too small: the nadir run scales them by its variance components
    (IMU 2.48, GNSS 4.36 when written) and the oblique runs start from its scales (one GNSS/IMU system), refining
    the IMU's (3.18-3.26). The centres' errors are then 1.4-1.6 times their standard deviations (RMS per axis; 1.2-1.5
    with the sigmas given right), against 2.9-3.2 with the sigmas kept."""
    block = copy.deepcopy(sim.block)
    for img in block.images.values():
        img.sigma_position = img.sigma_position / 4
        img.sigma_attitude = img.sigma_attitude / 4
    ids = list(block.images)

    def error_over_std(at) -> np.ndarray:
        err = np.array([at.poses[i].C - sim.true_poses[i].C for i in ids])
        return np.sqrt(np.mean((err / np.array([at.image_std[i][3:] for i in ids])) ** 2, 0))

    hat = hierarchical(block, sim.ties, options, xyz0=xyz0)
    nadir = hat.runs[0].result.prior_sigma_scale
    assert np.all(nadir > 2.0) and np.all((3.5 < nadir[3:]) & (nadir[3:] < 5.0))
    for run in hat.runs[1:]:
        assert np.all(run.result.prior_sigma_scale >= nadir)
    kept = hierarchical(block, sim.ties, replace(options, prior_sigma_estimate=False), xyz0=xyz0)
    e_hat, e_kept = error_over_std(hat), error_over_std(kept)
    assert np.all(e_hat < 1.9) and np.all(e_kept > 2.5)


def test_hat_oblique_runs_in_worker_processes_give_the_same_result(sim, xyz0, options):
    inline = hierarchical(sim.block, sim.ties, options, connection="10", xyz0=xyz0)
    with Executor("processes", workers=2) as ex:
        par = hierarchical(sim.block, sim.ties, options, connection="10", xyz0=xyz0, executor=ex)
    for iid, p in inline.poses.items():
        np.testing.assert_allclose(par.poses[iid].C, p.C, atol=1e-6)
    assert [r.connection_count for r in par.runs] == [r.connection_count for r in inline.runs]


def test_hat_early_start_shares_its_sub_blocks_with_the_caller(sim, xyz0, options, monkeypatch):
    """With workers, the early start runs in a thread and the set-up, drawing the oblique runs as their early starts
    are done, resects the sub-blocks the thread has not started yet: both take sub-blocks, and the result is the
    inline one."""
    import threading

    import oblique_city.core.aerotri.hierarchical as hat_module

    class Serial:
        """An executor with workers as far as HAT can tell, running its units in this process."""
        mode, workers = "serial", 1

        def map(self, fn, items, on_done=None, total=None):
            return [fn(it) for it in items]

    inline = hierarchical(sim.block, sim.ties, options, connection="cba", xyz0=xyz0)
    resected, taken, caller_came = hat_module._resected, [], threading.Event()

    def shared(prob, opt):
        in_caller = threading.current_thread() is threading.main_thread()
        taken.append(in_caller)
        if in_caller:
            caller_came.set()
        else:  # the thread resects one sub-block, then waits for the caller to take one
            assert caller_came.wait(60) or taken.count(False) == 1
        return resected(prob, opt)

    monkeypatch.setattr(hat_module, "_resected", shared)
    par = hierarchical(sim.block, sim.ties, options, connection="cba", xyz0=xyz0, executor=Serial())
    assert len(taken) == 4 and 1 <= taken.count(True) <= 3
    for iid, p in inline.poses.items():
        np.testing.assert_allclose(par.poses[iid].C, p.C, atol=1e-6)
    # as many rays rejected per track (which of two rays with equal tests goes is decided by rounding in Ceres'
    # threads: two inline runs differ in 1-4 % of the oblique rejections)
    track, n = sim.ties.obs_track, sim.ties.n_tracks
    counts = [np.bincount(track[r.obs_rejected], minlength=n) for r in (par, inline)]
    assert np.sum(counts[0] != counts[1]) <= 0.005 * np.sum(counts[1] > 0)


def test_restarted_sub_block_equals_the_one_built_from_the_new_start(sim, xyz0):
    """The early start builds the oblique sub-blocks from the navigation data while the nadir run computes and
    restarts them from its robust round: the same problem as one built from that start (start values finite where
    ``xyz0`` is)."""
    ids = sim.block.images_by_view()["north"]
    rng = np.random.default_rng(5)
    start = {i: Pose(sim.block.images[i].pose_approx.R, sim.block.images[i].pose_approx.C + rng.normal(0.0, 0.1, 3))
             for i in ids}
    xyz = xyz0 + rng.normal(0.0, 0.5, xyz0.shape)
    direct = build_problem(sim.block, sim.ties, ids, xyz, use_control=False, initial=start)
    again = restarted(build_problem(sim.block, sim.ties, ids, xyz0, use_control=False), sim.block, start, xyz)
    np.testing.assert_array_equal(again.obs_index, direct.obs_index)
    np.testing.assert_array_equal(again.track_index, direct.track_index)
    for name in ("r_cam_from_world", "c_world", "xyz", "obs_point", "obs_image", "obs_uv", "prior_c", "prior_r"):
        np.testing.assert_array_equal(getattr(again.problem, name), getattr(direct.problem, name))
    assert not np.array_equal(again.problem.c_world, build_problem(sim.block, sim.ties, ids, xyz0).problem.c_world)


def test_hat_early_start_agrees_with_the_start_from_the_final_nadir_run(sim, xyz0, options, monkeypatch):
    """The oblique runs moved to their inliers from the nadir run's robust round (while the nadir run goes on) end
    where the start from the final nadir run leads (the previous computation, without the adjust hook): the same
    rejections per track, orientations within a small fraction of their standard deviations."""
    import oblique_city.core.aerotri.hierarchical as hat_module
    from oblique_city.core.geometry.rotations import matrix_to_rotvec

    early = hierarchical(sim.block, sim.ties, options, connection="cba", xyz0=xyz0)
    adjust = hat_module.adjust
    monkeypatch.setattr(hat_module, "adjust", lambda prob, opt, progress=None, on_robust=None, keep=None:
                        adjust(prob, opt, progress, keep=keep))
    final = hierarchical(sim.block, sim.ties, options, connection="cba", xyz0=xyz0)
    # as many rays rejected per track (which of two rays with equal tests goes is a matter of rounding: 1 % of the
    # rejections here, all in tracks whose rejection counts agree)
    track, n = sim.ties.obs_track, sim.ties.n_tracks
    counts = [np.bincount(track[r.obs_rejected], minlength=n) for r in (early, final)]
    assert np.sum(counts[0] != counts[1]) <= 0.005 * np.sum(counts[1] > 0)
    assert abs(int(early.obs_rejected.sum()) - int(final.obs_rejected.sum())) <= 0.005 * final.obs_rejected.sum()
    ids = [i for i in final.poses if i not in final.runs[0].poses]
    dc = np.array([(early.poses[i].C - final.poses[i].C) / final.image_std[i][3:] for i in ids])
    da = np.array([matrix_to_rotvec(final.poses[i].R.T @ early.poses[i].R) / final.image_std[i][:3] for i in ids])
    assert np.median(np.abs(dc)) < 0.05 and np.median(np.abs(da)) < 0.05
    assert np.abs(dc).max() < 0.5 and np.abs(da).max() < 0.5
    s_e, s_f = (blunder_scores(sim.ties.obs_blunder, r.obs_rejected) for r in (early, final))
    assert s_e["recall"] >= s_f["recall"] - 0.005 and s_e["false_alarm"] <= s_f["false_alarm"] + 0.001


def test_cba_picks_the_point_with_most_rays_per_cell():
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 200, 500), rng.uniform(0, 100, 500), np.zeros(500)])
    rays = rng.integers(2, 30, 500)
    nadir = rng.integers(0, 12, 500)
    cand = rng.random(500) < 0.8
    sel = select_connections(xyz, cand, rays, nadir, "cba", 25.0)
    ok = cand & (nadir >= 2)
    cell = (xyz[:, 0] // 25).astype(int) * 100 + (xyz[:, 1] // 25).astype(int)
    for c in np.unique(cell[ok]):
        members = np.flatnonzero(ok & (cell == c))
        chosen = np.flatnonzero(sel & (cell == c))
        assert len(chosen) == 1 and rays[chosen[0]] == rays[members].max()
    assert not (sel & ~ok).any()
    k5 = select_connections(xyz, cand, rays, nadir, "5", 25.0)
    np.testing.assert_array_equal(k5, cand & (nadir >= 5))


def test_nadir_propagation_is_exact_for_rigid_heads(sim):
    """The simulator's navigation errors are per exposure (rigid heads): propagating the true nadir
    orientations to the other heads of each exposure gives their true orientations."""
    nadir = {i: sim.true_poses[i] for i, im in sim.block.images.items() if im.head == "nadir"}
    out = nadir_propagation(sim.block, nadir)
    for iid, p in out.items():
        np.testing.assert_allclose(p.R, sim.true_poses[iid].R, atol=1e-9)
        np.testing.assert_allclose(p.C, sim.true_poses[iid].C, atol=1e-6)


def test_hat_with_thinned_oblique_ties_keeps_accuracy_and_gives_every_tie_point_coordinates(sim, xyz0, options, iat):
    hat = hierarchical(sim.block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0,
                       oblique_tie_grid=8, oblique_ties_per_cell=1)
    assert hat.extra["thinned_observations"] > 0.3 * sim.ties.n_obs
    oblique_obs = sum(len(r.obs_index) for r in hat.runs[1:])
    assert oblique_obs < 0.5 * (sim.ties.n_obs - len(hat.runs[0].obs_index))
    # every tie point IAT determines is determined here too (thinned ones by intersection)
    assert np.isfinite(hat.xyz[np.isfinite(iat.xyz[:, 0]), 0]).mean() > 0.999
    xy_h, z_h = rms_xy_z(check_point_errors(sim.block, hat.poses)[1])
    xy_i, z_i = rms_xy_z(check_point_errors(sim.block, iat.poses)[1])
    assert xy_h < 1.3 * xy_i + 0.002 and z_h < 1.3 * z_i + 0.005
    # blunders among the thinned observations are found by the intersection tests
    truth = sim.ties.obs_blunder
    assert (truth & hat.obs_rejected).sum() > 0.9 * truth.sum()
    assert (~truth & hat.obs_rejected).sum() < 0.01 * (~truth).sum()


def test_thin_ties_keeps_the_best_track_per_image_cell(sim):
    from oblique_city.core.aerotri.problem import thin_ties

    ties = sim.ties
    rays = ties.ray_counts()
    keep = thin_ties(sim.block, ties, np.ones(ties.n_obs, bool), rays, 4, 1)
    assert 0 < keep.sum() < ties.n_tracks
    # in every image, the best-ranked observed track of each cell is kept: no image is left without kept tracks
    per_image = np.bincount(ties.obs_image[keep[ties.obs_track]], minlength=len(ties.image_ids))
    assert (per_image[np.bincount(ties.obs_image, minlength=len(ties.image_ids)) > 0] >= 4).all()


def test_intersections_in_shares_match_one_piece_and_the_truth(sim, options):
    """Forward intersection in track shares and the intersection with blunder tests in shares of a few
    observations give what one piece gives; from the true orientations they find the planted blunders and land
    on the true points within the measurement noise (0.3 px: a few hundredths of the GSD per ray, more for the
    many two- and three-ray points)."""
    from oblique_city.core.aerotri.hierarchical import intersect_and_test
    from oblique_city.core.aerotri.problem import intersect_ties

    ties = sim.ties
    whole, dist = intersect_ties(sim.block, ties, sim.true_poses)
    parts, dist_parts = intersect_ties(sim.block, ties, sim.true_poses, chunk_obs=ties.n_obs // 7)
    np.testing.assert_allclose(parts, whole, atol=1e-9)
    np.testing.assert_allclose(dist_parts, dist, atol=1e-9)
    clean = np.bincount(ties.obs_track[ties.obs_blunder], minlength=ties.n_tracks) == 0
    ok = clean & np.isfinite(whole[:, 0])
    assert np.median(np.linalg.norm(whole[ok] - sim.true_xyz[ok], axis=1)) < 0.5 * sim.gsd
    tracks, obs_ok = np.ones(ties.n_tracks, bool), np.ones(ties.n_obs, bool)
    one = intersect_and_test(sim.block, ties, sim.true_poses, obs_ok, tracks, options.sigma_px, 1.0, 4.3)
    many = intersect_and_test(sim.block, ties, sim.true_poses, obs_ok, tracks, options.sigma_px, 1.0, 4.3,
                              share_obs=ties.n_obs // 5)
    np.testing.assert_allclose(many[0], one[0], atol=1e-9)
    np.testing.assert_array_equal(many[2], one[2])
    truth = ties.obs_blunder
    assert (truth & one[2]).sum() > 0.95 * truth.sum()
    assert (~truth & one[2]).sum() < 0.01 * (~truth).sum()
    good = np.isfinite(one[0][:, 0])
    assert np.median(np.linalg.norm(one[0][good] - sim.true_xyz[good], axis=1)) < 0.5 * sim.gsd
    # from start coordinates a few centimetres off (as the combined run coordinates are) the same points and
    # rejections as from the forward intersection; tracks without a start are intersected
    rng = np.random.default_rng(1)
    start = sim.true_xyz + rng.normal(0.0, 0.05, sim.true_xyz.shape)
    start[::3] = np.nan
    from_start = intersect_and_test(sim.block, ties, sim.true_poses, obs_ok, tracks, options.sigma_px, 1.0, 4.3,
                                    xyz_start=start)
    both = good & np.isfinite(from_start[0][:, 0])
    assert both.sum() > 0.99 * good.sum()
    assert np.median(np.linalg.norm(from_start[0][both] - one[0][both], axis=1)) < 0.01 * sim.gsd
    assert (from_start[2] != one[2]).sum() < 1e-3 * one[2].sum()


def _iat_finds(block, sim, xyz0, options, iat, found: Callable[[ATResult], bool]) -> tuple[ATResult, tuple]:
    """IAT of ``block`` (the simulated one with blunders planted): ``found`` holds for it, and its check points are
    within 3 % of those of the clean block's IAT ``iat``. Returns it and the clean check point RMS XY, Z."""
    clean = rms_xy_z(check_point_errors(sim.block, iat.poses)[1])
    at = integrated(block, sim.ties, options, xyz0=xyz0)
    assert found(at)
    xy, z = rms_xy_z(check_point_errors(block, at.poses)[1])
    assert xy < 1.03 * clean[0] and z < 1.03 * clean[1]
    return at, clean


def test_control_point_blunders_are_found_and_leave_the_adjustment(sim, xyz0, options, iat):
    """One control point's X is given 0.25 m wrong and one measurement of another is 7.2 px off: 25 and 24 times
    their standard deviations (0.01 m, 0.3 px), far above the 4.3 of the tests. IAT and HAT reject exactly those
    two, and the check points come out as on the clean block (within 3 % in IAT, 5 % in HAT against the clean
    IAT); without the tests the wrong coordinate pulls the datum and the check points' XY RMS grows by a fifth.
    On the clean block none of the 25 control points or their measurements is rejected."""
    assert iat.control_rejections() == (set(), set())
    block = copy.deepcopy(sim.block)
    wrong, clicked = [g for g in block.ground_points.values() if g.kind == "control" and len(g.observations) >= 4][:2]
    wrong.xyz = wrong.xyz + np.array([0.25, 0.0, 0.0])
    image = next(iter(clicked.observations))
    clicked.observations[image] = clicked.observations[image] + np.array([6.0, -4.0])
    planted = ({wrong.name}, {(clicked.name, image)})
    _, (xy0, z0) = _iat_finds(block, sim, xyz0, options, iat, lambda at: at.control_rejections() == planted)
    untested = integrated(block, sim.ties, replace(options, control_tests=False), xyz0=xyz0)
    assert rms_xy_z(check_point_errors(block, untested.poses)[1])[0] > 1.2 * xy0
    hat = hierarchical(block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0)
    assert hat.control_rejections() == planted
    xy, z = rms_xy_z(check_point_errors(block, hat.poses)[1])
    assert xy < 1.05 * xy0 and z < 1.05 * z0


def test_control_point_detectable_errors_are_found_at_the_stated_power(sim, xyz0, options, iat):
    """IAT's control point test run again with its adjusted images gives the standard deviations behind the result's
    smallest detectable errors. Each tested axis of the control points in turn, given an error of that size (both
    signs, 150 cases), is found in 80 % of the cases (here 76 %; binomial standard deviation 3.3 %); at half that
    size in 6 % (4 % expected), at 1.5 times in 149."""
    prob = build_problem(sim.block, sim.ties, list(sim.block.images), xyz0).problem
    res = iat.runs[0].result

    def rejected(given):
        return control_point_tests(res.cameras, prob.image_camera, res.r_cam_from_world, res.c_world - res.datum_shift,
                                   given, prob.gcp_sigma, prob.gcp_sigma_px, prob.gcp_obs_point, prob.gcp_obs_image,
                                   prob.gcp_obs_uv, ~res.gcp_obs_rejected, ~res.gcp_rejected, res.datum_shift,
                                   options.datum_shift, options.blunder_threshold).rejected

    tested = np.flatnonzero(np.all(np.isfinite(res.gcp_mdb), 1))
    assert len(tested) >= 20 and not rejected(prob.gcp_xyz).any()
    found = {}
    for factor in (0.5, 1.0, 1.5):
        hits = []
        for g, axis, sign in np.ndindex(len(tested), 3, 2):
            given = prob.gcp_xyz.copy()
            given[tested[g], axis] += (2 * sign - 1) * factor * res.gcp_mdb[tested[g], axis]
            hits.append(rejected(given)[tested[g]])
        found[factor] = float(np.mean(hits))
    assert abs(found[1.0] - DETECTION_POWER) < 0.12 and found[0.5] < 0.15 and found[1.5] > 0.97


def test_control_point_datum_effect_is_what_the_adjustment_does(sim, xyz0, options, iat):
    """External reliability: the weakest control point's coordinates are given an error of their smallest detectable
    size in Z, then in X, with the tests off. IAT's datum shift moves by 1.0-1.3 times what the report foretold (the
    test holds the images; the adjustment also tilts them a little): here 4.5 mm against 4.0 and 2.5 against 2.3."""
    run = iat.runs[0]
    res = run.result
    assert not run.control_rejected  # the clean adjustment is the one without the tests
    g = int(np.nanargmax(res.gcp_mdb.max(axis=1)))
    name = run.control_names[g]
    for axis in (2, 0):
        block = copy.deepcopy(sim.block)
        block.ground_points[name].xyz = block.ground_points[name].xyz + res.gcp_mdb[g, axis] * np.eye(3)[axis]
        moved = integrated(block, sim.ties, replace(options, control_tests=False), xyz0=xyz0).runs[0].result
        ratio = np.linalg.norm(moved.datum_shift - res.datum_shift) / res.gcp_datum_effect[g, axis]
        assert 0.8 < ratio < 1.5


def test_prior_effect_is_what_the_adjustment_does(sim, xyz0, options, iat):
    """External reliability of the EO priors: the GNSS position of the image whose undetected error would move it
    most gets an error of its smallest detectable size in Z, with the prior tests off. Its adjusted centre moves by
    what the report foretold, within 0.8-1.25 times (the model holds the points, which the adjustment moves a
    little along): here 0.52 m of error moves it by 7.3 mm against 7.1 foretold."""
    res = iat.runs[0].result
    ids = list(sim.block.images)
    k = int(np.nanargmax(res.prior_effect[:, 5]))
    iid = ids[k]
    assert np.isfinite(res.prior_mdb[k, 5]) and res.prior_effect[k, 5] < res.prior_mdb[k, 5]
    block = copy.deepcopy(sim.block)
    img = block.images[iid]
    img.pose_approx = Pose(img.pose_approx.R, img.pose_approx.C + [0.0, 0.0, res.prior_mdb[k, 5]])
    moved = integrated(block, sim.ties, replace(options, prior_tests=False), xyz0=xyz0)
    ratio = (moved.poses[iid].C[2] - iat.poses[iid].C[2]) / res.prior_effect[k, 5]
    assert 0.8 < ratio < 1.25
    # the report's largest effect of a GNSS error in Z is this one
    priors = reliability(iat.runs[0], sim.ties, sim.block)["priors"]
    assert priors["position_m"]["effect_max"][2] == res.prior_effect[k, 5]


def test_tie_redundancy_numbers_follow_the_rays(sim, iat, options):
    """A tie point of k rays, its images held, leaves 2k - 3 of its 2k measured coordinates redundant: IAT's mean
    redundancy numbers of 2- and 3-ray points are 0.25 and 0.5 within 0.02 (the images' own uncertainty takes a little:
    here 0.243 and 0.494), and the smallest detectable errors shrink as the rays grow (3.1 px for 2 rays, 1.6 for
    10 and more at 0.3 px), and so do their effects: the shift of the point (median 2.5 m for 2 rays, 0.012 m for 10
    and more) and the bias-to-noise ratio (8.9 and 1.3)."""
    rows = reliability(iat.runs[0], sim.ties, sim.block)["ties"]
    by_rays = {r["rays"]: r for r in rows}
    for k in (2, 3):
        assert abs(by_rays[str(k)]["redundancy_mean"] - (2 * k - 3) / (2 * k)) < 0.02
    assert [r["rays"] for r in rows] == ["2", "3", "4-5", "6-9", "10+"]
    for key in ("mdb_px_median", "point_shift_m_median", "bnr_median"):
        values = [r[key] for r in rows]
        assert values == sorted(values, reverse=True), key


def test_track_residual_rms_is_that_of_the_adjusted_rays(sim, iat):
    """The RMS image residual per tie track (written with the adjusted tie points, coloured in Blender) is that of
    the observations IAT kept, each the measured position minus the projection of the adjusted point with the
    adjusted orientation (to 1e-6 px on 300 tracks); a track with none kept has none. Over the block the mean square
    is about twice the noise variance times the mean redundancy number (0.3 px noise, redundancy 0.8-0.9: 0.38-0.40
    px RMS): here 0.37 px."""
    from oblique_city.core.geometry.projection import project

    rms = track_residual_rms(sim.ties, iat)
    ties = sim.ties
    kept = ~iat.obs_rejected
    tracks = np.flatnonzero(np.isfinite(rms))[:300]
    for t in tracks:
        obs = np.flatnonzero((ties.obs_track == t) & kept)
        v = [ties.obs_uv[o] - project(sim.block.cameras[sim.block.images[iid].camera_id], iat.poses[iid],
                                      iat.xyz[t][None])[0][0]
             for o in obs for iid in [ties.image_ids[ties.obs_image[o]]]]
        assert abs(np.sqrt(np.mean(np.sum(np.square(v), axis=1))) - rms[t]) < 1e-6
    assert not np.any(np.isfinite(rms[np.bincount(ties.obs_track[kept], minlength=ties.n_tracks) == 0]))
    assert 0.33 < np.sqrt(np.nanmean(rms**2)) < 0.43


def test_tie_point_shift_is_what_the_adjustment_does(sim, xyz0, options, iat):
    """External reliability of the tie measurements: a measurement of a 3-ray point (the one at the 90th percentile
    of their foretold point shifts) gets 0.6 times its smallest detectable error, in the direction that moves its
    point most. The test keeps it (its normalised residual stays below the threshold), and IAT moves the point by
    what the report foretold within 10 % (the model holds the images, which the adjustment moves a little): here
    1.21 m against 1.20."""
    run = iat.runs[0]
    res = run.result
    used = res.obs_used & np.isfinite(res.obs_mdb)
    shift = tie_point_shifts(run, sim.ties, sim.block, used)
    idx = np.flatnonzero(used)
    track = sim.ties.obs_track[run.obs_index[idx]]
    rays = np.bincount(track, minlength=sim.ties.n_tracks)[track]
    three = np.flatnonzero(rays == 3)
    k = three[np.argsort(shift[three])[len(three) * 9 // 10]]
    j, o, t = idx[k], run.obs_index[idx[k]], track[k]
    # the worst direction: the largest eigenvector of J Q^2 J^T (Q the point's cofactor block)
    p = int(np.flatnonzero(run.track_index == t)[0])
    iid = sim.ties.image_ids[sim.ties.obs_image[o]]
    cam = sim.block.cameras[sim.block.images[iid].camera_id]
    pose = run.poses[iid]
    jp = point_jacobians(pose.R[None], pose.C[None], np.array([cam.fx]), np.array([cam.fy]), run.xyz[p][None],
                         np.zeros(1, np.int64), np.zeros(1, np.int64))[0]
    q = run.xyz_cov[p] / res.sigma0**2
    direction = np.linalg.eigh(jp @ q @ q @ jp.T)[1][:, -1]
    ties = copy.deepcopy(sim.ties)
    ties.obs_uv[o] += 0.6 * res.obs_mdb[j] * direction
    moved = integrated(sim.block, ties, options, xyz0=xyz0).runs[0]
    assert not moved.obs_rejected[j]
    assert 0.9 < np.linalg.norm(moved.xyz[p] - run.xyz[p]) / (0.6 * shift[k]) < 1.1
    assert shift[k] > 0.5  # metres: far beyond what the other measurements' noise moves the point between runs


def test_gnss_and_imu_prior_blunders_are_found_and_leave_the_adjustment(sim, xyz0, options, iat):
    """One exposure's GNSS position is 1.2, -0.9, 1.5 m off (a lost fix: 18-24 times its 0.05/0.08 m sigma) and
    another's IMU attitude 0.06 deg off in roll (10-15 sigma), on all five heads of each. IAT and HAT reject
    exactly those priors (the position of the first five images, the attitude of the second five) and nothing on
    the other 390 images or on the clean block. The images keep the orientation their tie points give: the GNSS
    images' centres come out 0.002 m (IAT) and 0.008 m (HAT) from their clean IAT ones (RMS; HAT and IAT differ by
    their method), against 0.035 m with the tests off, and the check points as on the clean block (within 3 % in IAT,
    5 % in HAT)."""
    from oblique_city.core.geometry.rotations import rotvec_to_matrix
    assert iat.prior_rejections() == set()
    block = copy.deepcopy(sim.block)
    gnss = sorted(i for i in block.images if i.startswith("S02_E008_"))
    imu = sorted(i for i in block.images if i.startswith("S03_E005_"))
    assert len(gnss) == len(imu) == 5
    for i in gnss:
        p = block.images[i].pose_approx
        block.images[i].pose_approx = Pose(p.R, p.C + np.array([1.2, -0.9, 1.5]))
    for i in imu:
        p = block.images[i].pose_approx
        block.images[i].pose_approx = Pose(p.R @ rotvec_to_matrix(np.radians([0.06, 0.0, 0.0])), p.C)
    planted = {(i, "position") for i in gnss} | {(i, "attitude") for i in imu}

    def centre_rms(at):
        return float(np.sqrt(np.mean([np.sum((at.poses[i].C - iat.poses[i].C) ** 2) for i in gnss])))

    at, (xy0, z0) = _iat_finds(block, sim, xyz0, options, iat, lambda at: at.prior_rejections() == planted)
    untested = integrated(block, sim.ties, replace(options, prior_tests=False), xyz0=xyz0)
    assert untested.prior_rejections() == set()
    assert centre_rms(at) < 0.005 and centre_rms(untested) > 0.02
    hat = hierarchical(block, sim.ties, options, connection="cba", cell=50.0, xyz0=xyz0)
    assert hat.prior_rejections() == planted
    assert centre_rms(hat) < 0.5 * centre_rms(untested)
    xy, z = rms_xy_z(check_point_errors(block, hat.poses)[1])
    assert xy < 1.05 * xy0 and z < 1.05 * z0



def test_a_prior_rejected_after_the_solve_moves_its_image_without_a_new_solve(sim, xyz0, options, iat):
    """One image's IMU roll 0.02 deg off (3-4 times its sigma) is rejected by the tests after the least-squares
    solve. Leaving it out without a new solve (``resolve_tolerance`` 1: the image moved by the step its removal
    implies, :func:`.bundle.prior_release`, its points re-estimated, its precision computed without the prior) gives
    what the new solve gives (``resolve_tolerance`` 0): the image within 0.2 of its standard deviations per axis
    (measured 0.0007 deg in roll against 0.007, 1.4 mm against 17 mm; the shortcut for observations alone moves
    other images by up to 1 mm as well), the standard deviations themselves (roll and pitch twice
    those with the prior)
    and sigma0 as the solve's. On a 6,000-image block such a rejection made one oblique run of four solve twice
    (20.8 -> 12.7 s)."""
    from oblique_city.core.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix
    block = copy.deepcopy(sim.block)
    img = "S03_E005_nadir"
    p = block.images[img].pose_approx
    block.images[img].pose_approx = Pose(p.R @ rotvec_to_matrix(np.radians([0.02, 0.0, 0.0])), p.C)
    quick = integrated(block, sim.ties, replace(options, resolve_tolerance=1.0), xyz0=xyz0)
    solved = integrated(block, sim.ties, replace(options, resolve_tolerance=0.0), xyz0=xyz0)
    assert quick.prior_rejections() == solved.prior_rejections() == {(img, "attitude")}
    assert any("1 EO prior parts (their images moved" in line for line in quick.runs[0].result.log)
    assert sum("least squares" in line for line in quick.runs[0].result.log) == 1
    std_q, std_s = quick.runs[0].image_std[img], solved.runs[0].image_std[img]
    assert np.allclose(std_q, std_s, rtol=0.01)
    assert np.all(std_q[:2] > 1.5 * iat.runs[0].image_std[img][:2])  # the clean block's, with the prior
    # (rotation about the world axes, as the standard deviations)
    theta = matrix_to_rotvec(solved.poses[img].R.T @ quick.poses[img].R)
    assert np.all(np.abs(theta) < 0.2 * std_s[:3])
    assert np.all(np.abs(quick.poses[img].C - solved.poses[img].C) < 0.2 * std_s[3:])
    assert abs(quick.sigma0_px() - solved.sigma0_px()) < 1e-3 * solved.sigma0_px()

STRIP_OFFSETS = {"S01": (0.25, -0.15, 0.30), "S02": (-0.20, 0.25, -0.10), "S03": (0.10, 0.20, -0.30),
                 "S04": (-0.30, -0.10, 0.20), "S05": (0.15, -0.25, 0.10)}
"""GNSS offsets (m) planted per strip of the test block: 3.75-6 times the GNSS sigmas (0.05, 0.05, 0.08 m)."""


def test_gnss_strip_offsets_are_estimated_and_correct_the_orientations(sim, xyz0, options, iat):
    """Each strip's GNSS positions get an offset of 0.1-0.3 m per axis (:data:`STRIP_OFFSETS`). IAT and HAT with
    ``gnss_strips="shift"`` find the 5 strips and estimate the offsets, taken from their mean (which the datum shift
    takes), to within 0.05 m: 2.5 times the standard deviation of a strip's mean GNSS error in Z (0.08 m over its 16
    exposures; measured 0.031 m IAT, 0.030 m HAT). The image centres (RMS against the truth) come out at 0.42 (IAT)
    and 0.62 (HAT) of their error with the offsets unmodelled, HAT's within 1.1 times IAT's, and the check points
    better in XY (0.012 m against 0.024 m IAT, 0.016 m HAT). ``drift`` adds a drift per strip and keeps the offsets
    as well. Without the model the report's check (:func:`gnss_strip_check`) flags all 5 strips, and none on the
    clean block.

    The offsets' and drifts' standard deviations count the 5 heads of an exposure as one GNSS position: the errors
    of the offsets (taken from their mean) and of the drifts (none planted) are 0.87 and 1.07 of them (RMS over strips
    and axes; 0.89 and 1 expected), IAT's offsets as precise as HAT's (whose nadir run has one head per exposure).
    The test takes 0.5-1.4 and 0.5-1.6 (95 % of a chi-square of 12 and 15 degrees of freedom lies within 0.54-1.25
    and 0.64-1.34); counted per image they were sqrt(5) times smaller, giving 1.9 and 2.4.

    The unmodelled runs keep the GNSS sigmas as given (``prior_sigma_estimate`` off): scaled by their variance
    component, which the offsets inflate, the GNSS positions weigh less and the IAT's centres came out at 0.0143 m
    RMS, against 0.0141 m with the offsets modelled."""
    from oblique_city.core.aerotri.report import gnss_strip_check
    block = copy.deepcopy(sim.block)
    for img in block.images.values():
        img.pose_approx = Pose(img.pose_approx.R, img.pose_approx.C + STRIP_OFFSETS[img.exposure[:3]])

    def centre_rms(at):
        return float(np.sqrt(np.mean([np.sum((at.poses[i].C - sim.true_poses[i].C) ** 2) for i in at.poses])))

    strips = flight_strips(block)
    planted = np.array([STRIP_OFFSETS[block.images[strips.members(k)[0]].exposure[:3]] for k in range(5)])

    def check_xy(at):
        return rms_xy_z(check_point_errors(block, at.poses)[1])[0]

    def offset_error(at):
        est = at.gnss_strips()
        assert sorted(est) == sorted(strips.names)
        e = np.array([est[n]["offset_m"] for n in strips.names])
        return np.abs((e - e.mean(0)) - (planted - planted.mean(0))).max()

    def offset_std(at):
        return np.array([at.gnss_strips()[n]["offset_std_m"] for n in strips.names])

    def offset_z(at):
        e = np.array([at.gnss_strips()[n]["offset_m"] for n in strips.names])
        return float(np.sqrt(np.mean((((e - e.mean(0)) - (planted - planted.mean(0))) / offset_std(at)) ** 2)))

    kept = replace(options, prior_sigma_estimate=False)
    off = integrated(block, sim.ties, kept, xyz0=xyz0)
    assert sum(d["flagged"] for d in gnss_strip_check(block, off).values()) == 5
    assert not any(d["flagged"] for d in gnss_strip_check(sim.block, iat).values())
    shift = integrated(block, sim.ties, replace(options, gnss_strips="shift"), xyz0=xyz0)
    # the strips' blocks stay out of Ceres' elimination: the eliminator keeps its fixed sizes (see SchurAnchor)
    assert all("Schur structure 2,3,d" in line for line in shift.runs[0].result.log if "Schur structure" in line)
    assert offset_error(shift) < 0.05 and gnss_strip_check(block, shift) == {}
    assert centre_rms(shift) < 0.5 * centre_rms(off)
    assert check_xy(shift) < check_xy(off)
    hat_off = hierarchical(block, sim.ties, kept, connection="cba", cell=50.0, xyz0=xyz0)
    hat = hierarchical(block, sim.ties, replace(options, gnss_strips="shift"), connection="cba", cell=50.0, xyz0=xyz0)
    assert offset_error(hat) < 0.05
    assert 0.5 < offset_z(shift) < 1.4 and 0.5 < offset_z(hat) < 1.4
    assert np.all(np.abs(offset_std(shift) / offset_std(hat) - 1.0) < 0.2)
    assert centre_rms(hat) < 0.7 * centre_rms(hat_off) and centre_rms(hat) < 1.2 * centre_rms(shift)
    assert check_xy(hat) < check_xy(hat_off)
    drift = integrated(block, sim.ties, replace(options, gnss_strips="drift"), xyz0=xyz0)
    assert offset_error(drift) < 0.05
    assert all(d["drift_m_per_km"] is not None for d in drift.gnss_strips().values())
    drift_z = np.array([np.array(d["drift_m_per_km"]) / d["drift_std_m_per_km"] for d in drift.gnss_strips().values()])
    assert 0.5 < offset_z(drift) < 1.4 and 0.5 < float(np.sqrt(np.mean(drift_z**2))) < 1.6


def test_hat_on_a_plain_opk_list_with_exposures_found_by_time(tmp_path, sim, options, plain_opk):
    """A penta block exchanged as a plain OPK list (no exposure or head column, times only): with the exposures found
    by time HAT gives the native block's result; without them its oblique runs cannot start from the nadir
    corrections propagated to their heads, and each needs a robust round. (The native block gets the attitude sigmas
    the list carries: an oblique image's, as its angles', cannot hold every set of sigmas about the world's axes.)"""
    from oblique_city.core.io.formats import read_block

    plain_opk(sim.block, tmp_path / "plain.txt")
    native_block = copy.deepcopy(sim.block)
    for by, screened in (("time", True), ("given", False)):
        block = read_block("opk", str(tmp_path / "plain.txt"), exposures=by)
        assert list(block.images) == list(sim.block.images)
        if by == "time":
            for iid, img in native_block.images.items():
                img.sigma_attitude = block.images[iid].sigma_attitude
            native = hierarchical(native_block, sim.ties, options, connection="cba")
        block.ground_points = sim.block.ground_points
        hat = hierarchical(block, sim.ties, options, connection="cba")
        logs = [r.result.log[0] for r in hat.runs[1:]]
        if screened:
            assert all("robust" not in t for t in logs)
            assert max(np.linalg.norm(hat.poses[i].C - p.C) for i, p in native.poses.items()) < 1e-6
            assert max(rotation_angle(hat.poses[i].R, p.R) for i, p in native.poses.items()) < 1e-9
        else:
            assert all(t.endswith("robust round") for t in logs)
