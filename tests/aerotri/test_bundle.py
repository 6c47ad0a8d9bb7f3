"""Bundle adjustment engine on a simulated penta block: poses, sigma0, check points, blunders, datum shift,
self-calibration."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.aerotri.bundle import (
    DETECTION_POWER,
    BundleOptions,
    adjust,
    detectable_shift,
    prior_tests,
    project_obs,
    resected_start,
)
from oblique_city.core.aerotri.problem import build_problem
from oblique_city.core.aerotri.report import mounting
from oblique_city.core.errors import ComputationError
from oblique_city.core.evaluate.aerotri import blunder_scores, check_point_errors, rms_xy_z
from oblique_city.core.geometry.rotations import rotation_angle
from oblique_city.core.simulate.observations import SimulationConfig, simulate_block

pytestmark = pytest.mark.xdist_group("aerotri_sim")  # one worker builds the shared simulated block


def test_iat_recovers_poses_better_than_navigation(sim, iat):
    ids = list(iat.poses)
    assert len(ids) == len(sim.block.images)
    err_adj = np.array([iat.poses[i].C - sim.true_poses[i].C for i in ids])
    err_nav = np.array([sim.block.images[i].pose_approx.C - sim.true_poses[i].C for i in ids])
    # the navigation carries a 6/4/10 cm datum offset plus noise; the adjustment removes the offset
    assert np.sqrt(np.mean(err_adj**2)) < 0.6 * np.sqrt(np.mean(err_nav**2))
    ang_adj = np.degrees([rotation_angle(iat.poses[i].R, sim.true_poses[i].R) for i in ids])
    ang_nav = np.degrees([rotation_angle(sim.block.images[i].pose_approx.R, sim.true_poses[i].R) for i in ids])
    assert np.median(ang_adj) < 0.7 * np.median(ang_nav)
    # the attitude errors agree with the reported precision: |rotation error| against the norm of the three
    # per-axis standard deviations (its RMS), the median ratio of a 3-D normal being about 0.9
    std = np.degrees([np.linalg.norm(iat.image_std[i][:3]) for i in ids])
    assert 0.6 < np.median(ang_adj / std) < 1.4


def test_sigma0_matches_simulated_noise(iat):
    # sigma_px a priori is the simulated 0.3 px: the a posteriori sigma of the tie measurements must be it within 10 %
    # (a tie sigma within BundleOptions.tie_sigma_tolerance of the given one is kept)
    res = iat.runs[0].result
    assert abs(res.sigma0 * res.sigma_px / 0.3 - 1.0) < 0.1 and res.sigma_px == res.sigma_px_given == 0.3


def test_tie_sigma_estimated_from_the_residuals(sim, xyz0, iat):
    """Given 1 px for the simulated 0.3 px, the adjustment estimates the tie sigma from the tie measurements' variance
    component (0.301 px when written) and solves again: the centres and their standard deviations are those of the
    adjustment given 0.3 px (0.044 of a standard deviation apart, the second pass screening its blunders anew; the
    standard deviations within 0.1 % when written). Kept at 1 px, the priors weigh 11
    times too much against the ties: the centres move by about one standard deviation (0.99) and their standard
    deviations come out 0.55-0.62 times too small. The GNSS positions' variance component is the simulated errors'
    spread over their a priori sigmas (1.116 against 1.12; within 3 of its standard deviations, the 5 heads of an
    exposure sharing one GNSS error, so their sigmas are not scaled, see ``BundleOptions.prior_sigma_estimate``)."""
    from oblique_city.core.aerotri.hierarchical import integrated

    ids = list(iat.poses)

    def centres(at):
        return (np.array([at.poses[i].C for i in ids]), np.array([at.image_std[i][3:] for i in ids]))

    c_ref, s_ref = centres(iat)
    est = integrated(sim.block, sim.ties, BundleOptions(sigma_px=1.0), xyz0=xyz0)
    res = est.runs[0].result
    assert res.sigma_px_given == 1.0 and abs(res.sigma_px / 0.3 - 1.0) < 0.03
    assert any("sigma re-estimated 1.000 ->" in line for line in res.log)
    c, s = centres(est)
    assert np.sqrt(np.mean(((c - c_ref) / s_ref) ** 2)) < 0.1
    assert np.all(np.abs(np.median(s / s_ref, 0) - 1.0) < 0.02)
    fixed = integrated(sim.block, sim.ties, BundleOptions(sigma_px=1.0, tie_sigma_estimate=False), xyz0=xyz0)
    assert fixed.runs[0].result.sigma_px == 1.0
    c, s = centres(fixed)
    assert np.sqrt(np.mean(((c - c_ref) / s_ref) ** 2)) > 0.5
    assert np.all(np.median(s / s_ref, 0) < 0.7)
    # the GNSS errors the adjustment sees (the datum offset goes to the datum shift) against their sigmas
    err = np.array([sim.block.images[i].pose_approx.C - sim.true_poses[i].C for i in ids])
    sigma = np.array([sim.block.images[i].sigma_position for i in ids])
    spread = np.sqrt(np.mean(((err - err.mean(0)) / sigma) ** 2))
    gnss = res.variance_components["gnss"]
    assert np.all(res.prior_sigma_scale == 1.0) and abs(gnss.factor - spread) < 0.1 and gnss.factor_std < 0.05


def test_prior_sigmas_estimated_from_their_residuals(sim, xyz0, iat):
    """The block's GNSS/IMU sigmas given 4 times too small: their variance components scale them (the GNSS positions'
    by 4.33, the simulated errors' spread being 4.47 times the given sigmas; the IMU attitudes' by 3.31 for 3.82, a
    component of a misweighted solution being biased towards 1) and the block is adjusted again. The orientations
    and their standard deviations then come out near those with the right sigmas (centres 0.15 of a standard
    deviation apart, standard deviations 0.93 times theirs when written: the IMU's scale is 13 % short). Kept, the
    priors pull the centres 1.16 standard deviations away, and the standard deviations come out 0.48-0.57 times
    theirs."""
    import copy

    from oblique_city.core.aerotri.hierarchical import integrated

    block = copy.deepcopy(sim.block)
    for img in block.images.values():
        img.sigma_position = img.sigma_position / 4
        img.sigma_attitude = img.sigma_attitude / 4
    ids = list(iat.poses)

    def centres(at):
        return (np.array([at.poses[i].C for i in ids]), np.array([at.image_std[i][3:] for i in ids]))

    c_ref, s_ref = centres(iat)
    est = integrated(block, sim.ties, BundleOptions(sigma_px=0.3), xyz0=xyz0)
    res = est.runs[0].result
    err = np.array([block.images[i].pose_approx.C - sim.true_poses[i].C for i in ids])
    sigma = np.array([block.images[i].sigma_position for i in ids])
    spread = np.sqrt(np.mean(((err - err.mean(0)) / sigma) ** 2))
    imu_spread = 4 * iat.runs[0].result.variance_components["imu"].factor
    assert np.all(np.abs(res.prior_sigma_scale[3:] / spread - 1.0) < 0.1)
    assert np.all((0.75 < res.prior_sigma_scale[:3] / imu_spread) & (res.prior_sigma_scale[:3] / imu_spread < 1.05))
    assert any("GNSS position priors: variance factor" in line for line in res.log)
    c, s = centres(est)
    assert np.sqrt(np.mean(((c - c_ref) / s_ref) ** 2)) < 0.3
    assert np.all(np.abs(np.median(s / s_ref, 0) - 1.0) < 0.12)
    kept = integrated(block, sim.ties, BundleOptions(sigma_px=0.3, prior_sigma_estimate=False), xyz0=xyz0)
    assert np.all(kept.runs[0].result.prior_sigma_scale == 1.0)
    c, s = centres(kept)
    assert np.sqrt(np.mean(((c - c_ref) / s_ref) ** 2)) > 0.8
    assert np.all(np.median(s / s_ref, 0) < 0.65)


def test_check_points_near_their_measurement_limit(sim, iat):
    """Check points intersected from the adjusted orientations are about as good as from the true ones: the
    remaining error is the check points' own 0.3 px measurement noise."""
    _, e_adj = check_point_errors(sim.block, iat.poses)
    _, e_true = check_point_errors(sim.block, sim.true_poses)
    xy, z = rms_xy_z(e_adj)
    xy_t, z_t = rms_xy_z(e_true)
    assert len(e_adj) >= 20
    assert xy < 0.3 * sim.gsd and xy < 1.5 * xy_t + 0.003
    assert z < 1.5 * z_t + 0.005
    _, e_nav = check_point_errors(sim.block, {i: im.pose_approx for i, im in sim.block.images.items()})
    assert xy < 0.5 * rms_xy_z(e_nav)[0]


def test_planted_blunders_are_found(sim, iat):
    s = blunder_scores(sim.ties.obs_blunder, iat.obs_rejected)
    assert s["planted"] > 300
    assert s["recall"] >= 0.95
    assert s["false_alarm"] <= 0.01


def test_datum_shift_and_precision(sim, iat):
    res = iat.runs[0].result
    # the GNSS frame is offset by gnss_bias from the control frame: the shift is its negative
    np.testing.assert_allclose(res.datum_shift, -np.array(sim.config.gnss_bias), atol=0.04)
    # reported point precision agrees with the true errors (ratio of RMS within a factor 1.5)
    rc = sim.ties.ray_counts()
    ok = np.isfinite(iat.xyz[:, 0]) & (rc >= 5)
    err = iat.xyz[ok] - sim.true_xyz[ok]
    std = np.sqrt(np.abs(np.diagonal(iat.xyz_cov[ok], axis1=1, axis2=2)))
    good = np.all(np.abs(err) < 5 * std + 0.05, 1)
    assert good.mean() > 0.97
    ratio = np.sqrt(np.mean(err[good] ** 2, 0)) / np.sqrt(np.mean(std[good] ** 2, 0))
    assert np.all(ratio > 0.5) and np.all(ratio < 1.6), ratio


def test_self_calibration_recovers_focal_length(sim, xyz0, monkeypatch):
    """Every head's focal length is given 0.3 % too long; with focal self-calibration on the whole penta block
    (the obliques make focal length and flying height separable) the adjustment returns each within 0.02 %, and
    within 4 of its standard deviations. Those come from our elimination of the points and poses
    (:func:`.bundle.marginal_covariances`) and equal pycolmap's covariance estimation of everything on the same
    solved problem (the reference, to 0.1 %)."""
    import pycolmap

    from oblique_city.core.aerotri import bundle

    reference = {}
    ours = bundle._Round.marginal

    def with_reference(rd, model, calibrated, mount, poses):
        opts = pycolmap.BACovarianceOptions()
        opts.params = pycolmap.BACovarianceOptionsParams.ALL
        cov = pycolmap.estimate_ba_covariance_from_problem(opts, model.rec, rd.problem)
        reference.update({ci: np.asarray(cov.get_other_params_cov(p)) for ci, p in calibrated.items()})
        return ours(rd, model, calibrated, mount, poses)

    monkeypatch.setattr(bundle._Round, "marginal", with_reference)
    block = sim.block
    saved = dict(block.cameras)
    for cid, cam in saved.items():
        block.cameras[cid] = replace(cam, fx=cam.fx * 1.003, fy=cam.fy * 1.003)
    try:
        sub = build_problem(block, sim.ties, list(block.images), xyz0, obs_mask=~sim.ties.obs_blunder)
        res = adjust(sub.problem, BundleOptions(sigma_px=0.3, self_calibration=("focal",), max_rejection_rounds=1,
                                                calibration_max_images=1000))
    finally:
        block.cameras.update(saved)
    assert len(reference) == len(res.cameras) == len(res.calibration)
    scale = (res.sigma_px * res.sigma0) ** 2
    for ci, cam in enumerate(res.cameras):
        assert abs(cam.fx / saved[cam.id].fx - 1.0) < 2e-4, cam.id
        cal = res.calibration[ci]
        assert cal.params == (0, 1) and cal.cov is not None
        assert np.allclose(np.sqrt(np.diag(cal.cov)), np.sqrt(np.diag(reference[ci] * scale)), rtol=1e-3, atol=0)
        err = cal.adjusted - np.array([saved[cam.id].fx, saved[cam.id].fy])
        assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(cal.cov))), (cam.id, err, np.sqrt(np.diag(cal.cov)))
    assert abs(res.sigma0 * res.sigma_px / 0.3 - 1.0) < 0.1


def test_rig_constraint_keeps_heads_on_their_mounting(sim, xyz0, iat):
    """With rig constraints the heads of an exposure keep their calibrated relative orientation (the simulated
    mounting is exact), tighter than the free adjustment, and sigma0 stays at the simulated noise."""
    block = sim.block
    sub = build_problem(block, sim.ties, list(block.images), xyz0)
    assert len(sub.problem.rig_pairs) == 4 * len({im.exposure for im in block.images.values()})
    res = adjust(sub.problem, BundleOptions(sigma_px=0.3, rig=True, rig_sigma_deg=0.001, rig_sigma_m=0.005))
    rig = block.rigs["penta"]
    ids = sub.problem.image_ids

    def rel_errors(rot):
        out = []
        for (i, j) in sub.problem.rig_pairs:
            hi, hj = rig.head(block.images[ids[i]].head), rig.head(block.images[ids[j]].head)
            nominal = hi.sensor_from_rig @ hj.sensor_from_rig.T
            out.append(np.degrees(rotation_angle(rot(i) @ rot(j).T, nominal)))
        return np.array(out)

    with_rig = rel_errors(lambda k: res.r_cam_from_world[k])
    free = rel_errors(lambda k: iat.poses[ids[k]].R)
    assert np.median(with_rig) < 0.002 and np.median(with_rig) < np.median(free)
    assert abs(res.sigma0 * res.sigma_px / 0.3 - 1.0) < 0.1


def test_cba_layers_from_selected_views(sim, iat):
    from oblique_city.core.aerotri.report import quality_layers

    all_v = quality_layers(sim.block, sim.ties, iat, 100.0, "all")
    nadir = quality_layers(sim.block, sim.ties, iat, 100.0, "nadir")
    assert all_v["cba_rays"].data.shape == nadir["cba_rays"].data.shape
    # fewer rays and a weaker height from the nadir views alone than from all views
    assert np.nanmedian(nadir["cba_rays"].data) < np.nanmedian(all_v["cba_rays"].data)
    assert np.nanmedian(nadir["cba_std_z"].data) > np.nanmedian(all_v["cba_std_z"].data)
    # the intersection error after adjustment is below the one from the navigation data
    assert np.nanmedian(all_v["intersection_error_after"].data) < np.nanmedian(
        all_v["intersection_error_before"].data)


def test_linear_solver_follows_observations_per_image(sim, xyz0):
    """'auto' factorises the reduced camera system of a sub-block with many observations per image and solves a
    thinned one (fewer than ``sparse_schur_min_obs_per_image``) by conjugate gradients; the nadir sub-block of
    the test block has several hundred observations per image."""
    from oblique_city.core.aerotri.bundle import linear_solver_kind

    nadir = sim.block.images_by_view()["nadir"]
    sub = build_problem(sim.block, sim.ties, nadir, xyz0)
    p = sub.problem
    active = np.ones(len(p.obs_point), bool)
    per_image = len(p.obs_point) / p.n_images
    opt = BundleOptions(sigma_px=0.3)
    assert linear_solver_kind(p, opt, active) == "sparse_schur"
    assert linear_solver_kind(p, replace(opt, sparse_schur_min_obs_per_image=2 * per_image), active) == \
        "iterative_schur"
    assert linear_solver_kind(p, replace(opt, linear_solver="sparse_schur",
                                         sparse_schur_min_obs_per_image=2 * per_image), active) == "sparse_schur"
    # from explicit_schur_min_images on, the reduced system of a sparse sub-block is solved by conjugate gradients
    # (no factorisation, so no fill-reducing ordering in Ceres' preprocessor), unless cameras or mountings are free
    big = replace(opt, explicit_schur_min_images=p.n_images)
    assert linear_solver_kind(p, big, active) == "explicit_schur"
    assert linear_solver_kind(p, replace(big, self_calibration=("focal",)), active) == "sparse_schur"
    assert linear_solver_kind(p, replace(big, mounting=True), active) == "sparse_schur"
    assert linear_solver_kind(p, replace(big, sparse_schur_min_obs_per_image=2 * per_image), active) == \
        "iterative_schur"
    with pytest.raises(ComputationError, match="unknown linear solver 'cholesky'"):
        linear_solver_kind(p, replace(opt, linear_solver="cholesky"), active)


def test_explicit_schur_solves_as_the_factorisation(sim, xyz0, options):
    """The nadir sub-block adjusted with the reduced camera system solved by conjugate gradients (explicit Schur
    complement, relative residual 1e-5) ends where the factorisation ends: the same iterations and rejections,
    orientations and points within 1 % of their standard deviations (0.1 % measured; with a relative residual of
    1e-3, 1.6 %), sigma0 to 1e-4."""
    sub = build_problem(sim.block, sim.ties, sim.block.images_by_view()["nadir"], xyz0)
    direct = adjust(sub.problem, replace(options, linear_solver="sparse_schur"))
    cg = adjust(sub.problem, replace(options, linear_solver="explicit_schur"))
    assert "linear solver explicit_schur" in cg.log
    assert cg.iterations == direct.iterations
    assert_same_solution(direct, cg, 0.01)


def test_projection_kernel_equals_the_camera_model():
    """``project_obs`` (one compiled pass over the observations) gives the camera model's pixels: rotation into the
    image frame, distortion, calibration; NaN behind the camera."""
    from oblique_city.core.geometry.rotations import rotvec_to_matrix
    from oblique_city.core.model import CameraModel

    rng = np.random.default_rng(2)
    cams = [CameraModel("a", 4000, 3000, 4100.0, 4090.0, 1999.5, 1499.5),
            CameraModel("b", 4000, 3000, 3900.0, 3910.0, 2010.0, 1490.0).with_distortion(-0.05, 0.01, -0.002, 1e-4,
                                                                                         -2e-4)]
    k, n, m = 4, 200, 1000
    image_camera = np.array([0, 1, 1, 0])
    r = np.array([rotvec_to_matrix(v) for v in rng.normal(0.0, 0.3, (k, 3))])
    c = rng.normal(0.0, 20.0, (k, 3)) - [0.0, 0.0, 30.0]
    xyz = rng.normal(0.0, 30.0, (n, 3))
    op, oi = rng.integers(0, n, m), rng.integers(0, k, m)
    got = project_obs(cams, image_camera, r, c, xyz, op, oi)
    xc = np.einsum("mij,mj->mi", r[oi], xyz[op] - c[oi])
    front = xc[:, 2] > 0
    assert 0.2 < front.mean() < 0.95
    want = np.full((m, 2), np.nan)
    for j in range(m):
        if front[j]:
            want[j] = cams[image_camera[oi[j]]].normalized_to_pixel(xc[j:j + 1, :2] / xc[j, 2])[0]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_reserved_heap_takes_the_next_allocations_without_page_faults():
    """After ``reserve_heap`` (in a fresh process: it sets the allocator's thresholds for good) the same amount
    allocated and written again in arrays of 8 MB takes under a tenth of the page faults it takes without the
    reserve (a control process)."""
    import subprocess
    import sys

    code = """
import resource, sys, numpy as np
from oblique_city.core.aerotri.bundle import reserve_heap
n = 256 * 2**20
ok = reserve_heap(n) if sys.argv[1] == "1" else True
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = [np.ones(2**20) for _ in range(n // 2**23)]
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0, n // 4096)
"""
    out = {}
    for mode in ("0", "1"):
        res = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, check=True)
        ok, faults, pages = res.stdout.split()
        assert ok == "True"
        out[mode] = (int(faults), int(pages))
    assert out["1"][0] < 0.1 * out["0"][0]


def test_kept_solver_gives_the_same_solution_and_is_freed_by_the_caller(sim, xyz0, options):
    """With ``keep`` the solver's problem and reconstruction outlive the adjustment (the caller frees them after
    handing the result on): the same solution as without, and nothing of it held once the list is cleared."""
    import weakref

    sub = build_problem(sim.block, sim.ties, sim.block.images_by_view()["nadir"], xyz0)
    freed = adjust(sub.problem, options)
    keep: list = []
    kept = adjust(sub.problem, options, keep=keep)
    assert len(keep) == 2 and hasattr(keep[0], "problem")
    assert kept.iterations == freed.iterations
    assert_same_solution(freed, kept, 0.001)
    refs = [weakref.ref(x) for x in keep]
    keep.clear()
    assert all(r() is None for r in refs)


@pytest.mark.parametrize("solver", ["sparse_schur", "explicit_schur"])
def test_settle_stop_ends_where_ceres_ends(sim, xyz0, options, solver):
    """A least-squares round that stops after the step its quadratic model foretold (BundleOptions.settle_stop)
    ends where Ceres ends without the stop, which computes one more step and discards it: the same iterations and
    rejections, orientations and points within 0.1 % of their standard deviations (1e-7 measured: the two threads'
    summation order)."""
    sub = build_problem(sim.block, sim.ties, sim.block.images_by_view()["nadir"], xyz0)
    full = adjust(sub.problem, replace(options, linear_solver=solver, settle_stop=False))
    settled = adjust(sub.problem, replace(options, linear_solver=solver))
    assert any("ended by the settled model" in line for line in settled.log)
    assert not any("settled" in line for line in full.log)
    assert settled.iterations == full.iterations
    assert_same_solution(full, settled, 0.001)


def test_model_settled_needs_a_foretold_decrease_and_an_exact_solve():
    """The stop's test: the remaining decrease, twice the gap between the actual and the model's decrease plus the
    solve's share of the model's, must be under the function tolerance's part of the cost."""
    from oblique_city.core.aerotri.bundle import model_settled

    # cost 1e4 after the step, tolerance 1e-6: 0.01 may remain
    assert model_settled(1e4, 100.0, 1.0 - 1e-6, 1e-6, 0.0)  # gap 1e-4
    assert not model_settled(1e4, 100.0, 0.999, 1e-6, 0.0)  # gap 0.1: the model was off, another step may pay
    assert model_settled(1e4, 100.0, 1.0, 1e-6, 1e-5)  # explicit Schur's conjugate gradients: 1e-3 may remain
    assert not model_settled(1e4, 100.0, 1.0, 1e-6, 0.1)  # iterative Schur's truncated Newton step: 10
    assert not model_settled(1e4, 0.0, 1.0, 1e-6, 0.0)  # no decrease: Ceres' own tests decide
    assert not model_settled(1e4, 1e-3, -1.0, 1e-6, 0.0)


def test_settle_stop_needs_an_undamped_step_solved_to_its_tolerance():
    """The stop ends a solve only on a step taken at a radius of at least SETTLE_MIN_RADIUS (the radius Ceres reports
    after the previous iteration) and whose conjugate gradients stopped before their cap."""
    from types import SimpleNamespace

    import pyceres

    from oblique_city.core.aerotri.bundle import SETTLE_MIN_RADIUS, _settle_stop_class

    def run(radius: float, cg_iterations: int):
        stop = _settle_stop_class()(1e-6, 1e-5, 500)
        first = SimpleNamespace(iteration=0, trust_region_radius=radius, step_is_successful=True,
                                linear_solver_iterations=0, cost=1e4, cost_change=0.0, relative_decrease=0.0)
        step = SimpleNamespace(iteration=1, trust_region_radius=3 * radius, step_is_successful=True,
                               linear_solver_iterations=cg_iterations, cost=1e4, cost_change=100.0,
                               relative_decrease=1.0 - 1e-7)
        return stop(first), stop(step), stop.settled

    go, end = pyceres.CallbackReturnType.SOLVER_CONTINUE, pyceres.CallbackReturnType.SOLVER_TERMINATE_SUCCESSFULLY
    assert run(SETTLE_MIN_RADIUS, 55) == (go, end, True)
    assert run(SETTLE_MIN_RADIUS / 10, 55) == (go, go, False)  # damped
    assert run(SETTLE_MIN_RADIUS, 500) == (go, go, False)  # conjugate gradients at their cap


def assert_same_solution(ref, other, share: float) -> None:
    """The same rejections, orientations and points within ``share`` of ``ref``'s standard deviations, sigma0 to
    1e-4."""
    from oblique_city.core.geometry.rotations import matrix_to_rotvec

    assert np.array_equal(other.obs_rejected, ref.obs_rejected)
    da = np.array([matrix_to_rotvec(a.T @ b) for a, b in zip(ref.r_cam_from_world, other.r_cam_from_world)])
    assert np.nanmax(np.abs(da) / ref.image_std[:, :3]) < share
    assert np.nanmax(np.abs(other.c_world - ref.c_world) / ref.image_std[:, 3:]) < share
    dx = (other.xyz - ref.xyz) / np.sqrt(np.diagonal(ref.xyz_cov, axis1=1, axis2=2))
    assert np.nanmax(np.abs(dx)) < share
    assert abs(other.sigma0 - ref.sigma0) < 1e-4


def test_marginal_image_std_equals_pycolmap_bounds_the_conditional_and_matches_the_errors(monkeypatch):
    """On a 60-image block the marginal standard deviations of the orientations (our sparse factorisation of the
    solved problem's reduced system, :func:`.bundle.marginal_covariances`) equal those of pycolmap's covariance
    estimation of the poses on the same problem (the reference, to 1e-6), as does the datum shift's, are at least
    the conditional ones (each image alone with the points fixed) and agree with the true errors: RMS error / median
    std between 0.5 and 2 for attitude and centre."""
    import pycolmap

    from oblique_city.core.aerotri import bundle
    from oblique_city.core.aerotri.hierarchical import integrated
    from oblique_city.core.geometry.rotations import matrix_to_rotvec

    reference, ours, shift = {}, bundle._Round.marginal, {}

    def with_reference(rd, model, calibrated, mount, poses):
        got = ours(rd, model, calibrated, mount, poses)
        opts = pycolmap.BACovarianceOptions()
        opts.params = pycolmap.BACovarianceOptionsParams.ALL
        cov = pycolmap.estimate_ba_covariance_from_problem(opts, model.rec, rd.problem)
        for k, c in zip(got[0], got[1]):  # relative to each pose's standard deviations
            d = np.sqrt(np.diag(c))
            reference[k] = np.abs(np.asarray(cov.get_cam_cov_from_world(int(k) + 1)) - c).max() / np.outer(d, d).max()
        shift.update(ours=got[2]["shift",], reference=np.asarray(cov.get_other_params_cov(rd.shift)))
        return got

    monkeypatch.setattr(bundle._Round, "marginal", with_reference)
    s = simulate_block(SimulationConfig(n_images=60, tie_density=0.0006, seed=5, noise_px=0.3))
    cond = integrated(s.block, s.ties, BundleOptions(sigma_px=0.3))
    assert not reference
    marg = integrated(s.block, s.ties, BundleOptions(sigma_px=0.3, marginal_max_images=100))
    res = marg.runs[0].result
    assert cond.runs[0].result.image_std_kind == "conditional" and res.image_std_kind == "marginal"
    assert len(reference) == 60 and max(reference.values()) < 1e-6
    assert np.allclose(shift["ours"], shift["reference"], rtol=1e-6, atol=1e-6 * np.abs(shift["reference"]).max())
    assert np.allclose(res.datum_shift_std, np.sqrt(np.diag(shift["ours"])) * res.sigma_px * res.sigma0, rtol=1e-12)
    sm = np.array(list(marg.image_std.values()))
    sc = np.array(list(cond.image_std.values()))
    assert np.all(np.nanmedian(sm, 0) >= 0.99 * np.nanmedian(sc, 0))
    att = np.array([matrix_to_rotvec(s.true_poses[i].R.T @ p.R) for i, p in marg.poses.items()])
    cen = np.array([p.C - s.true_poses[i].C for i, p in marg.poses.items()])
    ratio_att = np.sqrt(np.mean(att**2)) / np.nanmedian(sm[:, :3])
    ratio_cen = np.sqrt(np.mean(cen**2)) / np.nanmedian(sm[:, 3:])
    assert 0.5 < ratio_att < 2.0 and 0.5 < ratio_cen < 2.0, (ratio_att, ratio_cen)


def test_screened_start_tests_blunders_without_a_robust_solve(sim, xyz0, options):
    """From orientations close to the solution (here the true ones; in HAT the nadir corrections propagated to the
    oblique heads) the blunders are tested at the start with the cameras held and one least-squares solve remains:
    planted blunders found, sigma0 and orientations as from a full adjustment. From the navigation orientations
    the screening's sigma0 is far above 1 and the robust round runs as before."""
    ids = sim.block.images_by_view()["north"]
    opt = replace(options, screen_start=True)
    sub = build_problem(sim.block, sim.ties, ids, xyz0, initial=sim.true_poses)
    res = adjust(sub.problem, opt)
    assert res.log[0].startswith("screening at the start")
    assert abs(float(res.log[0].split("sigma0 ")[1].split(",")[0]) - 1.0) < 0.1
    assert not any("cauchy" in line for line in res.log)
    assert sum(line.startswith("round") and "least squares" in line for line in res.log) == 1
    s = blunder_scores(sim.ties.obs_blunder[sub.obs_index], res.obs_rejected)
    assert s["planted"] > 300 and s["recall"] >= 0.95 and s["false_alarm"] <= 0.01
    assert abs(res.sigma0 * res.sigma_px / 0.3 - 1.0) < 0.1
    # the same orientations as the robust round and data snooping from the same start, well within their std
    ref = adjust(sub.problem, options)
    ang = [np.degrees(rotation_angle(a, b)) for a, b in zip(res.r_cam_from_world, ref.r_cam_from_world)]
    dc = np.linalg.norm(res.c_world - ref.c_world, axis=1)
    std_deg, std_m = np.median(np.degrees(ref.image_std[:, :3])), np.median(ref.image_std[:, 3:])
    assert np.median(ang) < 0.1 * std_deg and np.median(dc) < 0.1 * std_m
    assert np.max(ang) < std_deg and np.max(dc) < std_m
    nav = adjust(build_problem(sim.block, sim.ties, ids, xyz0).problem, opt)
    assert "robust round" in nav.log[0] and any("cauchy" in line for line in nav.log)
    # the robust round's tests divide by the robust sigma0 (the median normalised residual), its log gives it: that
    # of the noise, the blunders in the solution notwithstanding
    robust = [line for line in nav.log if line.startswith("round 0: cauchy")]
    assert len(robust) == 1 and abs(float(robust[0].split("robust sigma0 ")[1].split(" ")[0]) - 1.0) < 0.1


def test_screen_points_sigma0_ignores_blunders_and_tests_single_rays_with_a_ground_observation(sim, options):
    """The robust sigma0 of the screening is that of the noise (the first round's rays of points pulled by blunders
    would inflate it by a third), and a point with one ray and a ground observation has its ray tested."""
    from oblique_city.core.aerotri.bundle import screen_points
    from oblique_city.core.aerotri.problem import pose_arrays

    ties = sim.ties
    cameras, image_camera, r, c = pose_arrays(sim.block, ties.image_ids, sim.true_poses)
    op, oi, uv = ties.obs_track, ties.obs_image, ties.obs_uv
    _, _, rej, s0 = screen_points(cameras, image_camera, r, c, op, oi, uv, sim.true_xyz, options.sigma_px, None,
                                  4.3, 10)
    assert abs(s0 - 1.0) < 0.05
    s = blunder_scores(ties.obs_blunder, rej)
    assert s["recall"] >= 0.95 and s["false_alarm"] <= 0.01
    # one ray of a track with a 10 px blunder, the track's true point as a ground observation (1 cm)
    k = int(np.flatnonzero(~ties.obs_blunder)[0])
    t = op[k]
    uv_bad = uv[k:k + 1] + np.array([[10.0, 0.0]])
    info = np.zeros((len(sim.true_xyz), 3, 3))
    info[t] = np.eye(3) / 0.01**2
    args = (cameras, image_camera, r, c, op[k:k + 1], oi[k:k + 1])
    _, _, rej1, _ = screen_points(*args, uv_bad, sim.true_xyz, options.sigma_px, 1.0, 4.3, 10,
                                  reject_undetermined=False, prior_xyz=sim.true_xyz, prior_info=info)
    _, _, rej0, _ = screen_points(*args, uv[k:k + 1], sim.true_xyz, options.sigma_px, 1.0, 4.3, 10,
                                  reject_undetermined=False, prior_xyz=sim.true_xyz, prior_info=info)
    assert rej1[0] and not rej0[0]


def test_screen_points_from_a_start_far_from_the_rays(sim, options):
    """Start points intersected from coarse navigation data (here moved 10-20 m off) are first settled onto their
    rays: the tests then find the blunders as from the true points, without false alarms (one Gauss-Newton step from
    there left residuals wrong by pixels: 3.6 % false alarms in HAT with 5 m and 0.5 degree navigation errors). A
    start from good navigation data (5 cm off) is left as it was."""
    from oblique_city.core.aerotri.bundle import _settled_points, image_focals, screen_points
    from oblique_city.core.aerotri.problem import pose_arrays

    ties = sim.ties
    cameras, image_camera, r, c = pose_arrays(sim.block, ties.image_ids, sim.true_poses)
    op, oi, uv = ties.obs_track, ties.obs_image, ties.obs_uv
    rng = np.random.default_rng(4)
    way = rng.normal(size=sim.true_xyz.shape)
    way /= np.linalg.norm(way, axis=1, keepdims=True)
    far = sim.true_xyz + way * rng.uniform(10.0, 20.0, (len(way), 1))
    x, _, rej, s0 = screen_points(cameras, image_camera, r, c, op, oi, uv, far, options.sigma_px, None, 4.3, 10,
                                  settle=True)
    s = blunder_scores(ties.obs_blunder, rej)
    assert abs(s0 - 1.0) < 0.05 and s["recall"] >= 0.95 and s["false_alarm"] <= 0.01, (s0, s)
    ok = np.isfinite(x[:, 0])
    assert ok.mean() > 0.95 and np.median(np.linalg.norm(x[ok] - sim.true_xyz[ok], axis=1)) < 0.1
    near = sim.true_xyz + way * 0.05
    fx, fy = image_focals(cameras, image_camera)
    kept = _settled_points(cameras, image_camera, r, c, fx, fy, op, oi, uv, near, options.sigma_px, None, None)
    clean = np.bincount(op[ties.obs_blunder], minlength=len(near)) == 0
    assert np.all(kept[clean] == near[clean], 1).mean() > 0.97  # all but weakly intersected points


def test_model_read_from_binary_equals_the_one_built_through_the_api(sim, xyz0, tmp_path):
    """The reconstruction that holds the tie points is written as a COLMAP binary model and read by pycolmap; it
    is the same, byte for byte once written again, as the one built element by element through pycolmap's API
    (cameras with trivial rigs, images with trivial frames and their poses, points with their tracks), here with
    some observations left out and points with a single ray left out of the reconstruction."""
    import pycolmap

    from oblique_city.core.aerotri.bundle import _colmap_params, _Model, _rigid

    ids = sim.block.images_by_view()["north"] + sim.block.images_by_view()["nadir"]
    p = build_problem(sim.block, sim.ties, ids, xyz0).problem
    ref = np.round(p.c_world.mean(0), 0)
    active = np.random.default_rng(0).random(len(p.obs_point)) > 0.1
    model = _Model(p, ref, active)
    # the reference: built through the API as before
    rec = pycolmap.Reconstruction()
    for ci, cam in enumerate(p.cameras):
        pc = pycolmap.Camera.create_from_model_name(ci + 1, "FULL_OPENCV", cam.fx, cam.width, cam.height)
        pc.params = _colmap_params(cam)
        rec.add_camera_with_trivial_rig(pc)
    counts = np.bincount(p.obs_point[active], minlength=p.n_points)
    in_rec = active & (counts >= 2)[p.obs_point]
    p2d = np.full(len(p.obs_point), -1)
    for k in range(p.n_images):
        sl = np.flatnonzero(in_rec & (p.obs_image == k))
        p2d[sl] = np.arange(len(sl))
        im = pycolmap.Image(name=p.image_ids[k], keypoints=p.obs_uv[sl] + 0.5, camera_id=int(p.image_camera[k]) + 1,
                            image_id=k + 1)
        rec.add_image_with_trivial_frame(im, _rigid(p.r_cam_from_world[k], p.c_world[k] - ref))
    point_ids = np.full(p.n_points, -1)
    for q in np.flatnonzero(counts >= 2):
        track = pycolmap.Track()
        for s in np.flatnonzero(in_rec & (p.obs_point == q)):
            track.add_element(int(p.obs_image[s]) + 1, int(p2d[s]))
        point_ids[q] = rec.add_point3D(p.xyz[q] - ref, track)
    assert np.array_equal(model.in_rec, in_rec)
    assert np.array_equal(model.p2d[in_rec], p2d[in_rec])
    assert np.array_equal(model.point_ids, point_ids)
    (tmp_path / "api").mkdir()
    (tmp_path / "binary").mkdir()
    rec.write_binary(str(tmp_path / "api"))
    model.rec.write_binary(str(tmp_path / "binary"))
    for name in ("cameras.bin", "rigs.bin", "frames.bin", "images.bin", "points3D.bin"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "binary" / name).read_bytes(), name
    # the coordinate views are the reconstruction's own
    q = int(np.flatnonzero(counts >= 2)[0])
    model.xyz_views[q][:] += 1.0
    assert np.allclose(model.rec.point3D(int(point_ids[q])).xyz, p.xyz[q] - ref + 1.0)


def test_compiled_jacobians_and_normals_equal_the_direct_formulas():
    """The Jacobians (compiled, gathered through the observations' indices) and the normal blocks and quadratic
    forms summed from them equal the textbook expressions (projection Jacobian times R, the rotation column as d x j,
    sums of J^T W J)."""
    from oblique_city.core.aerotri import precision

    rng = np.random.default_rng(5)
    m, n = 500, 7
    r = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0]
    c = rng.normal(size=(m, 3))
    xyz = c + np.einsum("mji,mj->mi", r, rng.normal(size=(m, 3)) * [1, 1, 0.1] + [0, 0, 20])  # in front
    fx, fy = rng.uniform(900, 1100, m), rng.uniform(900, 1100, m)
    # each observation its own image and point, then the same through shuffled indices
    jp, jr = precision.collinearity_jacobians(r, c, fx, fy, xyz, np.arange(m), np.arange(m))
    perm_i, perm_p = rng.permutation(m), rng.permutation(m)
    inv_i, inv_p = np.argsort(perm_i), np.argsort(perm_p)
    jp2, jr2 = precision.collinearity_jacobians(r[perm_i], c[perm_i], fx[perm_i], fy[perm_i], xyz[perm_p], inv_p, inv_i)
    assert np.array_equal(jp2, jp) and np.array_equal(jr2, jr)
    xc = np.einsum("mij,mj->mi", r, xyz - c)
    proj = np.zeros((m, 2, 3))
    proj[:, 0, 0], proj[:, 1, 1] = fx / xc[:, 2], fy / xc[:, 2]
    proj[:, 0, 2], proj[:, 1, 2] = -fx * xc[:, 0] / xc[:, 2] ** 2, -fy * xc[:, 1] / xc[:, 2] ** 2
    jp_ref = proj @ r
    assert np.allclose(jp, jp_ref, rtol=1e-12, atol=0)
    assert np.allclose(jr, np.cross((xyz - c)[:, None, :], jp_ref), rtol=1e-10, atol=1e-12)
    w = rng.uniform(0.5, 2.0, m)
    idx = rng.integers(0, n, m)
    rows = np.concatenate([jr, -jp], axis=2)
    n_ref = np.zeros((n, 6, 6))
    np.add.at(n_ref, idx, w[:, None, None] * np.einsum("mri,mrj->mij", rows, rows))
    assert np.allclose(precision.image_normals(jp, jr, w, idx, n), n_ref, rtol=1e-12, atol=0)
    q = np.linalg.inv(n_ref + np.eye(6))
    assert np.allclose(precision.quadratic_forms(precision.image_rows(jp, jr), q, idx),
                       np.einsum("mri,mij,mrj->m", rows, q[idx], rows), rtol=1e-10, atol=0)


def test_reduced_image_normals_are_the_diagonal_blocks_of_the_schur_complement():
    """The images' normal blocks with the points free (the prior tests' tie-only poses) equal the diagonal blocks
    of the reduced camera system formed densely (``N_cc - N_cp N_pp^-1 N_pc``, the points' prior information in
    ``N_pp``) on a small random block (an identity of the normal equations: any Jacobians will do), and are below
    the blocks with the points held."""
    from oblique_city.core.aerotri import precision

    rng = np.random.default_rng(11)
    n_img, n_pt = 5, 40
    # every point in 2-4 images, each pair (image, point) once
    pairs = sorted({(int(i), int(p)) for p in range(n_pt) for i in rng.choice(n_img, rng.integers(2, 5), False)})
    oi, op = np.array([a for a, _ in pairs]), np.array([b for _, b in pairs])
    jp, jr = rng.normal(size=(len(oi), 2, 3)), rng.normal(size=(len(oi), 2, 3))
    w = rng.uniform(1.0, 4.0, len(oi))
    prior = np.tile(np.eye(3) * 1e-2, (n_pt, 1, 1))
    q_point = np.linalg.inv(precision.point_normals(jp, w, op, n_pt, prior))
    got = precision.reduced_image_normals(jp, jr, w, q_point, op, oi, n_img)
    # dense normal matrix over 6 parameters per image and 3 per point
    a = np.zeros((len(oi), 2, 6 * n_img + 3 * n_pt))
    rows = precision.image_rows(jp, jr)
    for k in range(len(oi)):
        a[k, :, 6 * oi[k]:6 * oi[k] + 6] = rows[k]
        a[k, :, 6 * n_img + 3 * op[k]:6 * n_img + 3 * op[k] + 3] = jp[k]
    big = np.einsum("kri,k,krj->ij", a, w, a)
    big[6 * n_img:, 6 * n_img:] += np.kron(np.eye(n_pt), np.eye(3) * 1e-2)
    ncc, ncp, npp = big[:6 * n_img, :6 * n_img], big[:6 * n_img, 6 * n_img:], big[6 * n_img:, 6 * n_img:]
    schur = ncc - ncp @ np.linalg.solve(npp, ncp.T)
    for i in range(n_img):
        block = schur[6 * i:6 * i + 6, 6 * i:6 * i + 6]
        assert np.allclose(got[i], block, rtol=1e-7, atol=1e-9 * np.abs(block).max()), i
    held = precision.image_normals(jp, jr, w, oi, n_img)
    assert np.all(np.linalg.eigvalsh(held - got) > -1e-9 * np.abs(held).max())


def test_coupled_inverse_equals_the_dense_inverse():
    """The images' conditional cofactor blocks with rig constraints (:func:`.precision.coupled_inverse`) equal the
    diagonal blocks of the dense inverse of the normal matrix coupled by the pairs' difference observations: two
    exposures of 5 heads (a star on the first), one of 3 (a chain), two images alone, in shuffled order; an
    exposure whose joint matrix is singular gives NaN and leaves the others."""
    from oblique_city.core.aerotri import precision

    rng = np.random.default_rng(5)
    n = 15
    a = rng.normal(size=(n, 6, 9))
    normals = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(6)
    perm = rng.permutation(n)
    pairs = perm[np.array([[0, 1], [0, 2], [0, 3], [0, 4], [5, 6], [5, 7], [5, 8], [5, 9], [10, 11], [11, 12]])]
    weight = np.repeat([1e3, 50.0], 3)
    dense = np.zeros((6 * n, 6 * n))
    for k in range(n):
        dense[6 * k:6 * k + 6, 6 * k:6 * k + 6] = normals[k]
    for i, j in pairs:
        for x, y, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            dense[6 * x:6 * x + 6, 6 * y:6 * y + 6] += sign * np.diag(weight)
    inv = np.linalg.inv(dense)
    want = np.array([inv[6 * k:6 * k + 6, 6 * k:6 * k + 6] for k in range(n)])
    np.testing.assert_allclose(precision.coupled_inverse(normals, pairs, weight), want, rtol=1e-8, atol=1e-12)
    singular = normals.copy()
    singular[perm[:5]] = 0.0  # the first exposure: nothing but its rig, a free body
    got = precision.coupled_inverse(singular, pairs, weight)
    assert np.isnan(got[perm[:5]]).all() and np.allclose(got[perm[5:]], want[perm[5:]], rtol=1e-8, atol=1e-12)


def test_marginal_covariance_equals_the_dense_inverse():
    """The poses' and the globals' marginal covariances and the poses' covariances with chosen globals, from the
    points' elimination and a sparse factorisation, equal the matching blocks of the dense inverse of ``J^T J`` on a
    small random problem of the bundle's structure (6 pose columns per image, globals touched by every image
    measurement of their camera and by priors, 3 columns per point); a point of one ray with nothing else is
    singular and is left out; a global that nothing determines makes it None."""
    from oblique_city.core.aerotri import precision

    rng = np.random.default_rng(3)
    n_img, n_pt, n_glob = 9, 60, 5
    cam = rng.integers(0, 2, n_img)  # globals 0-1 of camera 0, 2-3 of camera 1, 4 common to all
    blocks = []  # (rows, cols, values) per residual block, row numbers local

    def add(cols: list[int], jac: np.ndarray) -> None:
        blocks.append((np.repeat(np.arange(jac.shape[0]), len(cols)), np.tile(cols, jac.shape[0]), jac.ravel()))

    n_pose = 6 * n_img
    for p in range(n_pt):
        for i in rng.choice(n_img, rng.integers(2, 6), replace=False):
            g = [n_pose + 2 * int(cam[i]), n_pose + 2 * int(cam[i]) + 1, n_pose + 4]
            pc = [n_pose + n_glob + 3 * p + k for k in range(3)]
            add([*range(6 * i, 6 * i + 6), *g, *pc], rng.normal(size=(2, 12)))
    for i in range(n_img):  # pose priors
        add(list(range(6 * i, 6 * i + 6)), np.eye(6) * 0.5)
    add(list(range(n_pose, n_pose + n_glob)), np.eye(n_glob) * 0.1)  # the globals' priors
    lone = n_pt  # a point of one ray: singular
    add([0, 1, 2, 3, 4, 5, n_pose + n_glob + 3 * lone, n_pose + n_glob + 3 * lone + 1, n_pose + n_glob + 3 * lone + 2],
        rng.normal(size=(2, 9)))

    rows, cols, vals, n_rows = [], [], [], 0
    for r, c, v in blocks:
        rows.append(r + n_rows)
        cols.append(c)
        vals.append(v)
        n_rows += int(r.max()) + 1
    rows, cols = np.concatenate(rows).astype(np.int32), np.concatenate(cols).astype(np.int32)
    vals = np.concatenate(vals)
    got = precision.marginal_covariance(rows, cols, vals, n_rows, n_pose, n_glob, n_pt + 1, poses=True,
                                        pose_cross=np.array([1, 4]))
    keep = ~np.isin(cols, np.arange(3) + n_pose + n_glob + 3 * lone)
    lone_rows = np.unique(rows[~keep])
    use = ~np.isin(rows, lone_rows)
    jac = np.zeros((n_rows, n_pose + n_glob + 3 * n_pt))
    jac[rows[use], cols[use]] = vals[use]
    full = np.linalg.inv(jac.T @ jac)
    ref = full[n_pose:n_pose + n_glob, n_pose:n_pose + n_glob]
    assert got is not None and np.allclose(got.globals_, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())
    ref_poses = np.array([full[6 * i:6 * i + 6, 6 * i:6 * i + 6] for i in range(n_img)])
    assert np.allclose(got.poses, ref_poses, rtol=1e-8, atol=1e-12 * np.abs(ref_poses).max())
    ref_cross = np.array([full[6 * i:6 * i + 6, [n_pose + 1, n_pose + 4]] for i in range(n_img)])
    assert np.allclose(got.pose_globals, ref_cross, rtol=1e-8, atol=1e-12 * np.abs(ref_poses).max())
    assert precision.marginal_covariance(rows, cols, vals, n_rows, n_pose, n_glob, n_pt + 1).poses is None
    alone = precision.marginal_covariance(rows, cols, vals, n_rows, n_pose, n_glob, n_pt + 1, poses=True)
    assert np.allclose(alone.poses, got.poses, rtol=1e-12) and alone.pose_globals.shape == (n_img, 6, 0)
    # a global no observation touches is not determined: the reduced system is singular
    shifted = np.where(cols >= n_pose + n_glob, cols + 1, cols).astype(np.int32)
    assert precision.marginal_covariance(rows, shifted, vals, n_rows, n_pose, n_glob + 1, n_pt + 1) is None


def test_world_pose_std_propagates_the_tangent_covariance_and_the_datum_shift():
    """The world-axes standard deviations of an image (:func:`.bundle.world_pose_std`) equal those propagated by
    numerical derivatives of the world rotation vector and of the centre in the control frame (``C + shift``) with
    respect to Ceres' tangent parameters of ``cam_from_world`` (a left quaternion increment ``d``: rotation ``2 d``
    in camera axes, an added translation) and the datum shift, for a random joint covariance of pose and shift."""
    from oblique_city.core.aerotri.bundle import world_pose_std
    from oblique_city.core.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix

    rng = np.random.default_rng(11)
    r = rotvec_to_matrix(rng.normal(size=3))
    c = rng.normal(size=3) * 300.0
    a = rng.normal(size=(9, 9)) * np.array([1e-4] * 3 + [0.05] * 3 + [0.01] * 3)
    cov = a @ a.T
    t = -r @ c

    def world(x: np.ndarray) -> np.ndarray:
        r2 = rotvec_to_matrix(2.0 * x[:3]) @ r
        return np.concatenate([matrix_to_rotvec(r.T @ r2),
                               -r2.T @ (t + x[3:6]) + x[6:]])

    h = 1e-7
    jac = np.array([(world(h * e) - world(-h * e)) / (2 * h) for e in np.eye(9)]).T
    want = np.sqrt(np.diag(jac @ cov @ jac.T))
    got = world_pose_std(cov[None, :6, :6], r[None], c[None], cov[6:, 6:], cov[None, :6, 6:])[0]
    assert np.allclose(got, want, rtol=1e-6)
    alone = world_pose_std(cov[None, :6, :6], r[None], c[None])[0]
    assert np.allclose(alone, np.sqrt(np.diag(jac[:, :6] @ cov[:6, :6] @ jac[:, :6].T)), rtol=1e-6)


def test_least_squares_rounds_start_with_the_gauss_newton_step(sim, xyz0, options):
    """The least-squares rounds start from close to the solution, so their first Levenberg-Marquardt step is
    (nearly) undamped (``ls_trust_region_radius``): fewer iterations than with Ceres' default radius of 1e4 (here
    2 against 4: the damping held back the sub-block's weakly determined directions), the same rejections, and
    orientations and points equal to well within their standard deviations (both stop at Ceres' function
    tolerance of 1e-6)."""
    ids = sim.block.images_by_view()["north"]
    sub = build_problem(sim.block, sim.ties, ids, xyz0, initial=sim.true_poses)
    opt = replace(options, screen_start=True)
    new = adjust(sub.problem, opt)
    old = adjust(sub.problem, replace(opt, ls_trust_region_radius=1e4))
    assert new.iterations < old.iterations
    assert not any("settled" in line for line in old.log)  # a damped step is not the model's minimum
    assert_same_solution(old, new, 0.1)


def test_screened_start_in_two_steps_is_the_screened_start(sim, xyz0, options):
    """HAT moves its oblique runs to their inliers early (resected_start) and adjusts them with screen_resect off:
    the same rejections, orientations and points as the screened start in one call (to the rounding of Ceres'
    two threads)."""
    ids = sim.block.images_by_view()["north"]
    p = build_problem(sim.block, sim.ties, ids, xyz0, initial=sim.true_poses).problem
    opt = replace(options, screen_start=True)
    one = adjust(p, opt)
    ok = np.flatnonzero(np.isfinite(p.xyz[p.obs_point, 0]))
    r, c, x, s0 = resected_start(p.cameras, p.image_camera, p.r_cam_from_world, p.c_world, p.xyz, p.obs_point[ok],
                                 p.obs_image[ok], p.obs_uv[ok], opt)
    assert s0 < opt.screen_max_sigma0
    assert np.abs(c - p.c_world).max() > 0  # the images moved
    resected = replace(p, r_cam_from_world=r, c_world=c, xyz=np.where(np.isfinite(x[:, :1]), x, p.xyz))
    two = adjust(resected, replace(opt, screen_resect=False))
    assert np.array_equal(one.obs_rejected, two.obs_rejected)
    np.testing.assert_allclose(two.r_cam_from_world, one.r_cam_from_world, rtol=0, atol=1e-12)
    np.testing.assert_allclose(two.c_world, one.c_world, rtol=0, atol=1e-9)
    np.testing.assert_allclose(two.xyz, one.xyz, rtol=0, atol=1e-9)
    # taken as resected, a start far from the solution (the navigation data) still falls back to the robust round
    nav = adjust(build_problem(sim.block, sim.ties, ids, xyz0).problem, replace(opt, screen_resect=False))
    assert "robust round" in nav.log[0] and any("cauchy" in line for line in nav.log)


@pytest.fixture(scope="module")
def misaligned():
    """250 images whose heads are mounted off their nominal boresight (0.05 deg sigma per axis, 0.01 m lever-arm
    error), the misalignment reaching every attitude prior through the nominal mounting while the priors claim the
    IMU's precision alone (0.004-0.006 deg) -> (config, simulated block, start points, true rig)."""
    from oblique_city.core.aerotri.hierarchical import initial_tie_coordinates
    from oblique_city.core.simulate.flight import NavErrors, perturbed_rig

    cfg = SimulationConfig(n_images=250, tie_density=0.0004, seed=3, noise_px=0.3, boresight_sigma_deg=0.05,
                           lever_arm_sigma=0.01)
    s = simulate_block(cfg)
    for img in s.block.images.values():
        img.sigma_attitude = np.radians(np.array(cfg.imu_sigma_deg))
    true_rig = perturbed_rig(s.block.rigs["penta"], NavErrors(boresight_sigma_deg=0.05, lever_arm_sigma=0.01,
                                                              seed=cfg.seed))
    return cfg, s, initial_tie_coordinates(s.block, s.ties), true_rig


def test_mounting_calibration_recovers_the_boresight_hidden_in_the_priors(misaligned):
    """On the misaligned block (see the fixture), without the mounting calibration the adjustment is pulled (sigma0
    above 1.05, attitude errors of several hundredths of a degree: 0.063 deg RMS when written) unless the IMU
    attitudes' variance component scales their sigmas (by 11.0: the misalignment shows there; attitude errors 0.011
    deg RMS, sigma0 at the noise); with it every head's boresight comes back
    within 0.005 deg per axis (largest error 0.0029 deg when written), the lever-arm offsets within 0.03 m
    (0.012 m), each within 4 of its marginal standard deviations; sigma0 is at the simulated noise, the images'
    attitude within 0.006 deg RMS (0.0045), so are the frames against the true images turned back by their head's
    misalignment, and the priors' attitude residuals are within twice the IMU noise."""
    from oblique_city.core.aerotri.hierarchical import integrated
    from oblique_city.core.geometry.rotations import matrix_to_rotvec

    cfg, s, xyz0, true_rig = misaligned

    def attitude_rms(at):
        ang = [np.linalg.norm(matrix_to_rotvec(s.true_poses[i].R.T @ p.R)) for i, p in at.poses.items()]
        return float(np.degrees(np.sqrt(np.mean(np.square(ang)))))

    plain = integrated(s.block, s.ties, BundleOptions(sigma_px=0.3, prior_sigma_estimate=False), xyz0=xyz0)
    scaled = integrated(s.block, s.ties, BundleOptions(sigma_px=0.3), xyz0=xyz0)
    cal = integrated(s.block, s.ties, BundleOptions(sigma_px=0.3, mounting=True, calibration_max_images=1000),
                     xyz0=xyz0)
    res = cal.runs[0].result
    assert np.all(np.isnan(plain.runs[0].result.mounting))
    nominal = s.block.rigs["penta"]
    for cam, m in zip(res.cameras, res.mounting):
        h = next(h for h in nominal.heads if h.camera_id == cam.id)
        t = true_rig.head(h.name)
        true_deg = np.degrees(matrix_to_rotvec(t.sensor_from_rig @ h.sensor_from_rig.T))
        err = np.concatenate([np.radians(np.degrees(m[:3]) - true_deg),
                              m[3:] - h.sensor_from_rig @ (t.lever_arm - h.lever_arm)])
        assert np.all(np.abs(np.degrees(err[:3])) < 0.005), (cam.id, np.degrees(m[:3]), true_deg)
        assert np.all(np.abs(err[3:]) < 0.03), cam.id
        # and their marginal standard deviations account for the errors
        assert np.all(np.abs(err) < 4 * res.mounting_std[res.cameras.index(cam)]), (cam.id, err)
    # (sigma0 in units of the simulated noise: an adjustment pulled by a model error estimates a larger tie sigma)
    assert abs(cal.sigma0_px() / 0.3 - 1.0) < 0.1 and plain.sigma0_px() / 0.3 > 1.05
    assert attitude_rms(cal) < 0.006 < 3 * 0.006 < attitude_rms(plain)
    assert scaled.runs[0].result.prior_sigma_scale[:3].max() > 5.0
    assert abs(scaled.sigma0_px() / 0.3 - 1.0) < 0.05 and attitude_rms(cal) < attitude_rms(scaled) < 0.015
    # the frames (corrections removed) are the true images turned back by their head's true misalignment
    heads = {h.camera_id: h for h in nominal.heads}
    frame_err = []
    for iid, f in cal.runs[0].frames.items():
        h = heads[s.block.images[iid].camera_id]
        d_true = true_rig.head(h.name).sensor_from_rig @ h.sensor_from_rig.T
        frame_err.append(np.linalg.norm(matrix_to_rotvec((d_true.T @ s.true_poses[iid].R).T @ f.R)))
    assert np.degrees(np.sqrt(np.mean(np.square(frame_err)))) < 0.006
    # the attitude priors' residuals (of the frames, with the correction) are the IMU noise again
    prior_rms = np.degrees(np.sqrt(np.nanmean(res.prior_residual_att**2, 0)))
    assert np.all(prior_rms < 2 * np.array(cfg.imu_sigma_deg)), prior_rms
    # the report lists every camera's correction, from the run that holds its images
    table = mounting(s.block, cal)
    assert set(table) == {cam.id for cam in res.cameras} and {m["run"] for m in table.values()} == {"iat"}
    assert mounting(s.block, plain) == {}


def test_mounting_and_strip_costs_jacobians_match_finite_differences():
    """The Python cost functions of the mounting calibration and the GNSS strip offsets: their Jacobians, taken to
    Ceres' tangent spaces (quaternion increments ``q' = (d, 1) q``, translations as they are), agree with central
    differences of their residuals to 1e-3 of the largest entry: the analytic ones take the Jacobian of the rotation
    logarithm as the identity, which is exact to the size of the residual rotation (here up to 6e-4 rad, about 0.03
    deg, the largest misalignment simulated)."""
    from oblique_city.core.aerotri.bundle import _cost_classes, _quat_plus_jacobian, _quat_xyzw
    from oblique_city.core.geometry.rotations import rotvec_to_matrix

    rng = np.random.default_rng(4)
    nav_prior, mounting_prior, mounted_relative, offset_prior, anchor = _cost_classes()

    def rot(scale):
        return rotvec_to_matrix(rng.normal(0, scale, 3))

    def pose(r, t):
        return np.concatenate([_quat_xyzw(r), t])

    def q_plus(q, d):
        n = np.linalg.norm(d)
        dq = np.array([*(np.sin(n) / n * d), np.cos(n)]) if n > 0 else np.array([0.0, 0.0, 0.0, 1.0])
        v1, w1, v2, w2 = dq[:3], dq[3], q[:3], q[3]
        return np.array([*(w1 * v2 + w2 * v1 + np.cross(v1, v2)), w1 * w2 - v1 @ v2])

    def check(cost, params, n_res=6):
        jac = [np.zeros(n_res * len(p)) for p in params]
        res = np.zeros(n_res)
        assert cost.Evaluate([p.copy() for p in params], res, jac)
        for b, p in enumerate(params):
            ja = jac[b].reshape(n_res, len(p))
            quat = len(p) in (4, 7)
            tangent = np.hstack([ja[:, :4] @ _quat_plus_jacobian(p[:4]), ja[:, 4:]]) if quat else ja
            for a in range(tangent.shape[1]):
                d = np.zeros(tangent.shape[1])
                d[a] = 1e-6
                out = []
                for sgn in (1, -1):
                    x = p.copy()
                    if quat:
                        x[:4] = q_plus(p[:4], sgn * d[:3])
                        x[4:] += sgn * d[3:]
                    else:
                        x += sgn * d
                    r = np.zeros(n_res)
                    cost.Evaluate([x if i == b else q for i, q in enumerate(params)], r, None)
                    out.append(r)
                num = (out[0] - out[1]) / 2e-6
                scale = max(np.abs(tangent).max(), 1.0)
                assert np.allclose(tangent[:, a], num, atol=1e-3 * scale, rtol=0), (b, a, tangent[:, a], num)

    w = 0.3 / np.array([1e-4, 1e-4, 1.5e-4, 0.05, 0.05, 0.08])
    r_cam = rot(1.0)
    qm, tm = _quat_xyzw(rot(5e-4)), rng.normal(0, 0.02, 3)
    c = rng.normal(0, 100, 3)
    cam = pose(r_cam, -r_cam @ c)
    check(nav_prior(rot(1e-4) @ r_cam, c + rng.normal(0, 0.05, 3), w), [cam, qm, tm])
    check(mounting_prior(w), [qm, tm])
    frame, drift = np.r_[0.0, 0.0, 0.0, 1.0, rng.normal(0, 0.3, 3)], rng.normal(0, 0.5, 3)
    check(nav_prior(rot(1e-4) @ r_cam, c + rng.normal(0, 0.05, 3), w, False, True, 0.37), [cam, frame, drift])
    check(nav_prior(rot(1e-4) @ r_cam, c + rng.normal(0, 0.05, 3), w, True, True, None), [cam, qm, tm, frame])
    check(offset_prior(0.3, 7), [frame], n_res=3)
    check(offset_prior(0.3, 3), [drift], n_res=3)
    check(anchor([7, 3]), [c, frame, drift], n_res=2)
    r_j = rot(1.0)
    cam_j = pose(r_j, -r_j @ (c + rng.normal(0, 0.3, 3)))
    n_r = r_cam @ r_j.T @ rot(2e-4)
    check(mounted_relative(n_r, rng.normal(0, 0.3, 3), w),
          [cam, cam_j, qm, tm, _quat_xyzw(rot(5e-4)), rng.normal(0, 0.02, 3)])


def test_point_prior_blocks_carry_the_full_information_of_a_ground_observation():
    """A ground observation with a full covariance, split into two 2-row blocks (:func:`_prior_rows`), has the
    information ``cov^-1`` and the chi-square of the 3-row form; the blocks' Jacobians (point and datum shift) are
    their rows, so the shifted residual is ``A (x + s - x_prior)`` exactly."""
    from oblique_city.core.aerotri.bundle import _point_prior_class, _prior_rows

    rng = np.random.default_rng(7)
    m = rng.normal(size=(3, 3))
    cov = m @ m.T + 0.1 * np.eye(3)
    a1, a2 = _prior_rows(cov)
    np.testing.assert_allclose(a1.T @ a1 + a2.T @ a2, np.linalg.inv(cov), rtol=1e-10, atol=1e-10)
    x, s, x0 = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    d = x + s - x0
    chi2 = 0.0
    for a in (a1, a2):
        cost = _point_prior_class()(a, x0, True)
        res, jac = np.zeros(2), [np.zeros(6), np.zeros(6)]
        assert cost.Evaluate([x.copy(), s.copy()], res, jac)
        np.testing.assert_allclose(res, a @ d, atol=1e-12)
        np.testing.assert_allclose(jac[0].reshape(2, 3), a)
        np.testing.assert_allclose(jac[1].reshape(2, 3), a)
        chi2 += res @ res
    assert chi2 == pytest.approx(d @ np.linalg.solve(cov, d), rel=1e-10)


def test_iat_rounds_use_the_specialised_schur_eliminator(iat):
    """Every residual block on a point is two rows high (control points' ground observations included), so Ceres
    specialises its Schur eliminator for 2-row blocks on 3-vector points; the image blocks stay dynamic ("d") as
    the datum shift (3) sits beside the images (6)."""
    rounds = [line for line in iat.runs[0].result.log if line.startswith("round") and "iterations" in line]
    assert rounds and all("Schur structure 2,3,d" in line for line in rounds)


def test_rig_constraints_with_mounting_calibration_hold_the_true_relative_mounting(misaligned):
    """Rig constraints tie the heads of an exposure to their nominal relative mounting; with the mounting
    calibration the constraint holds between the frames (corrections removed), so the heads' relative orientation
    follows the true mounting: median error against it below 0.003 deg (0.0018 when written; 0.0043 with the
    calibration alone), while the rig constraints alone force the nominal mounting (0.16 deg off, sigma0 1.5)."""
    from oblique_city.core.geometry.rotations import rotation_angle

    _, s, xyz0, true_rig = misaligned
    sub = build_problem(s.block, s.ties, list(s.block.images), xyz0)
    ids = sub.problem.image_ids

    def relative_errors(opt):
        res = adjust(sub.problem, opt)
        r = res.r_cam_from_world
        head = [true_rig.head(s.block.images[iid].head) for iid in ids]
        errs = [np.degrees(rotation_angle(r[i] @ r[j].T, head[i].sensor_from_rig @ head[j].sensor_from_rig.T))
                for i, j in sub.problem.rig_pairs]
        return float(np.median(errs)), res.sigma0 * res.sigma_px / 0.3

    both, s0 = relative_errors(BundleOptions(sigma_px=0.3, rig=True, mounting=True))
    rig_only, s0_rig = relative_errors(BundleOptions(sigma_px=0.3, rig=True))
    assert both < 0.003 and rig_only > 0.05 and abs(s0 - 1.0) < 0.1 < s0_rig - 1.0


def _prior_case(seed: int) -> tuple[Callable, np.ndarray]:
    """400 images whose tie points fix the pose to 2 mm and 0.001 deg (their normal blocks) and priors of 0.05 m and
    0.005 deg drawn with those sigmas: ``tested(prior (n, 6))`` runs :func:`prior_tests` with the adjusted poses where
    the ties and ``prior`` meet; returns it and the priors drawn."""
    rng = np.random.default_rng(seed)
    n = 400
    s_att, s_pos = np.full((n, 3), np.radians(0.005)), np.full((n, 3), 0.05)
    q_t = np.diag(np.r_[np.full(3, np.radians(0.001)), np.full(3, 0.002)] ** 2)
    n_ties = np.tile(np.linalg.inv(q_t), (n, 1, 1))
    p = np.diag(1.0 / np.r_[s_att[0], s_pos[0]] ** 2)
    x_t = rng.normal(0.0, 1.0, (n, 6)) * np.sqrt(np.diag(q_t))  # the tie-only poses about the truth (0)

    def tested(prior):
        x = np.linalg.solve(n_ties[0] + p, (n_ties[0] @ x_t.T + p @ prior.T)).T  # where ties and prior meet
        v = x - prior
        return prior_tests(v[:, :3], v[:, 3:], s_att, s_pos, n_ties, np.ones((n, 2), bool), 4.3)

    return tested, rng.normal(0.0, 1.0, (n, 6)) * np.r_[s_att[0], s_pos[0]]


def test_prior_tests_find_a_wrong_prior_and_scale_to_sigmas_that_are_too_small():
    """On :func:`_prior_case`'s 400 images, with the adjusted pose where the ties and the prior meet, the difference of
    the tie-only pose to the prior is recovered (``d = v + N_t^-1 P v``), so a position 0.3, 0.2, 0.35 m off (6, 4,
    7 sigma) and an attitude 0.06 deg off (12 sigma) are rejected, nothing else of the 2,400 axes (4.3 sigma: 0.04
    expected by chance). Priors whose sigmas are stated 3 times too small are tested at the robust scale (3 within
    10 %): no rejection, where the raw differences would have failed over a third of the images."""
    tested, prior = _prior_case(5)
    prior[7, 3:] += [0.3, -0.2, 0.35]
    prior[19, :3] += np.radians([0.06, 0.0, 0.0])
    bad, w, scale, _, _ = tested(prior)
    assert set(zip(*np.nonzero(bad))) == {(7, 1), (19, 0)}
    assert w[7, 1] > 5.5 and w[19, 0] > 9 and np.all(scale < 1.15)
    bad, w, scale, _, _ = tested(prior * 3)  # three times the errors the sigmas state
    assert abs(scale[1] / 3 - 1) < 0.1 and abs(scale[0] / 3 - 1) < 0.1
    assert {(int(k), int(part)) for k, part in zip(*np.nonzero(bad))} <= {(7, 1), (19, 0)}
    assert np.nanmax(np.where(bad, np.nan, w)) < 4.3


def test_detectable_shift_is_baardas_and_found_at_its_power():
    """Baarda's textbook value (3.29, one degree of freedom, 80 %: 4.13) and ours (4.3: 5.14); on two degrees of
    freedom (an image measurement's test) 400,000 draws of a 2-D normal shifted by it exceed 4.3 in 80.0 % of cases
    (binomial standard deviation 0.06 %)."""
    assert abs(detectable_shift(3.29) - 4.13) < 0.005 and abs(detectable_shift(4.3) - 5.14) < 0.005
    delta = detectable_shift(4.3, 2)
    x = np.random.default_rng(1).normal(0.0, 1.0, (400_000, 2)) + [delta, 0.0]
    assert abs(np.mean(np.linalg.norm(x, axis=1) > 4.3) - DETECTION_POWER) < 0.003


def test_prior_detectable_errors_are_found_at_the_stated_power():
    """Each of :func:`_prior_case`'s 2,400 prior axes in turn is given an error of its smallest detectable size (the
    standard deviation of its test times 5.14), of a random sign: 80 % of them are rejected (here 81.0 %; binomial
    standard deviation 0.8 %); at half that size 4.8 % (P(|N(2.57, 1)| > 4.3) = 4 %, and the chance of the other
    axes), at 1.5 times all."""
    tested, prior = _prior_case(7)
    bad, _, _, sd, _ = tested(prior)
    assert not bad.any()
    mdb = detectable_shift(4.3) * sd * np.random.default_rng(8).choice([-1.0, 1.0], prior.shape)
    found = {}
    for factor in (0.5, 1.0, 1.5):
        hits = []
        for k, axis in np.ndindex(*prior.shape):
            planted = prior.copy()
            planted[k, axis] += factor * mdb[k, axis]
            hits.append(tested(planted)[0][k, axis // 3])
        found[factor] = float(np.mean(hits))
    assert abs(found[1.0] - DETECTION_POWER) < 0.04 and found[0.5] < 0.1 and found[1.5] > 0.99


def test_heads_tied_by_the_rig_share_their_exposures_prior(sim, xyz0):
    """With rig constraints the 5 heads of an exposure carry a fifth of its GNSS/IMU prior each (a quarter for the 4
    whose position is still in use when one head's is rejected), without them each its full prior."""
    from oblique_city.core.aerotri.bundle import rig_groups, shared_prior_fraction

    prob = build_problem(sim.block, sim.ties, list(sim.block.images), xyz0).problem
    in_use = np.ones((prob.n_images, 2), bool)
    np.testing.assert_array_equal(shared_prior_fraction(rig_groups(prob, BundleOptions()), in_use), 1.0)
    frac = shared_prior_fraction(rig_groups(prob, BundleOptions(rig=True)), in_use)
    np.testing.assert_allclose(frac, 0.2)
    k = int(prob.rig_pairs[0, 1])
    in_use[k, 1] = False
    frac = shared_prior_fraction(rig_groups(prob, BundleOptions(rig=True)), in_use)
    mates = prob.image_exposure == prob.image_exposure[k]
    np.testing.assert_allclose(frac[mates & (np.arange(prob.n_images) != k), 1], 0.25)
    np.testing.assert_allclose(frac[:, 0], 0.2)
    np.testing.assert_allclose(frac[~mates], 0.2)


def test_shared_priors_are_one_measurement_per_exposure(sim, xyz0, iat):
    """Under a tight rig (0.0002 deg, 1 mm; the simulated rig is exact) the heads' shares of their exposure's prior
    are the textbook model of one GNSS/IMU measurement per exposure, the adjustment in which only the reference
    (nadir) head holds the prior, in full. They differ only in the weak prior weight on the heads' relative poses,
    which the rig holds: the same datum shift (written: within 0.0001 of its standard deviation; asserted 0.02), the
    same standard deviations of it and of the images (0.3 %; 1 %), the same centres (0.003 of their standard
    deviations; 0.02); the log does not say that the priors counted in full, as it does without the rig. The prior
    tests, taken per exposure (the heads move as one body), reject no prior in either: per image, the nadir head's
    own ties against the full prior of the exposure, they rejected an attitude prior and took the attitude priors
    1.6 times too optimistic."""
    opt = BundleOptions(sigma_px=0.3, rig=True, rig_sigma_deg=0.0002, rig_sigma_m=0.001, marginal_max_images=1000,
                        prior_sigma_estimate=False)  # (the two models, not the priors' variance components)
    sub = build_problem(sim.block, sim.ties, list(sim.block.images), xyz0, obs_mask=~sim.ties.obs_blunder)
    shared = adjust(sub.problem, opt)
    prob = sub.problem
    ref = np.zeros(prob.n_images, bool)
    ref[prob.rig_pairs[:, 0]] = True
    one = replace(prob, prior_sigma_att=np.where(ref[:, None], prob.prior_sigma_att, np.nan),
                  prior_sigma_pos=np.where(ref[:, None], prob.prior_sigma_pos, np.nan))
    single = adjust(one, opt)
    assert shared.image_std_kind == single.image_std_kind == "marginal"
    assert np.all(np.abs(shared.datum_shift - single.datum_shift) < 0.02 * single.datum_shift_std)
    np.testing.assert_allclose(shared.datum_shift_std, single.datum_shift_std, rtol=0.01)
    np.testing.assert_allclose(shared.image_std, single.image_std, rtol=0.01)
    dc = np.abs(shared.c_world - single.c_world) / single.image_std[:, 3:]
    assert np.all(dc < 0.02), dc.max()
    assert not shared.prior_rejected.any() and not single.prior_rejected.any()
    # without the rig (the fixture's IAT) the log says that each head's prior counted in full
    full = "each counted in full without rig constraints"
    assert any(full in line for line in iat.runs[0].result.log) and not any(full in line for line in shared.log)


def test_prior_tests_per_exposure_recover_the_tie_only_pose_of_the_rig():
    """400 exposures of 5 heads moving as one body, each head's ties fixing the pose to 2 mm and 0.001 deg, the
    exposure's one prior drawn with 0.05 m and 0.005 deg, each head carrying a fifth of it: the tests taken per
    exposure give the tie-only pose's difference to the prior, 1.01 and 0.97 times its standard deviation (RMS over
    the attitude and position axes; 1,200 independent axes each, so within 10 % is over 3 standard errors), at a
    robust scale of 1 (below 1.1), and reject nothing; a position 0.3 m off in one head's copy of the prior
    (6 sigma) is rejected in that head alone."""
    rng = np.random.default_rng(11)
    n_exp, heads = 400, 5
    n = n_exp * heads
    group = np.repeat(np.arange(n_exp), heads)
    sig = np.r_[np.full(3, np.radians(0.005)), np.full(3, 0.05)]
    q_t = np.diag(np.r_[np.full(3, np.radians(0.001)), np.full(3, 0.002)] ** 2)
    n_ties = np.tile(np.linalg.inv(q_t), (n, 1, 1))
    x_t = rng.normal(0.0, 1.0, (n_exp, 6)) * np.sqrt(np.diag(q_t) / heads)  # the exposures' tie-only poses
    prior = np.repeat(rng.normal(0.0, 1.0, (n_exp, 6)) * sig, heads, axis=0)
    frac = np.full((n, 2), 1.0 / heads)

    def tested(prior):
        p = np.diag(1.0 / sig**2) / heads  # each head's share
        n_t = heads * np.linalg.inv(q_t)
        x = np.empty((n, 6))
        for e in range(n_exp):
            k = group == e
            x[k] = np.linalg.solve(n_t + heads * p, n_t @ x_t[e] + p @ prior[k].sum(0))
        v = x - prior
        s = np.tile(sig[None], (n, 1))
        return prior_tests(v[:, :3], v[:, 3:], s[:, :3], s[:, 3:], n_ties, np.ones((n, 2), bool), 4.3, frac, group)

    bad, w, scale, sd, _ = tested(prior)
    assert not bad.any() and np.all(scale < 1.1)
    z = (x_t[group] - prior) / sd
    rms = np.sqrt(np.mean(z.reshape(n, 2, 3) ** 2, axis=(0, 2)))
    assert np.all(np.abs(rms - 1.0) < 0.1), rms
    planted = prior.copy()
    planted[7, 3:] += [0.3, -0.2, 0.35]
    bad, w, _, _, _ = tested(planted)
    assert set(zip(*np.nonzero(bad))) == {(7, 1)}


def test_control_measurement_sigmas_estimated_from_their_residuals(sim, xyz0, iat):
    """The control points' image measurements given 4 times their simulated noise: their variance component scales
    their sigmas (to 0.26 of the given ones, the right one being 0.25) and the block is adjusted again: their
    component then comes out near 1, and the datum shift within 0.2 mm of the one with the right sigmas. Given
    right (the fixture's block), they are not scaled; with the estimate off, kept."""
    import copy

    from oblique_city.core.aerotri.hierarchical import integrated

    assert iat.runs[0].result.control_sigma_scale == 1.0
    block = copy.deepcopy(sim.block)
    for gp in block.ground_points.values():
        gp.sigma_px = 4 * 0.3
    est = integrated(block, sim.ties, BundleOptions(sigma_px=0.3), xyz0=xyz0).runs[0].result
    assert 0.2 < est.control_sigma_scale < 0.32
    comp = est.variance_components["control_measurements"]
    assert abs(comp.factor - 1.0) < max(0.1, 3 * comp.factor_std)
    assert any("control point measurements: variance factor" in line for line in est.log)
    ref = iat.runs[0].result
    assert np.all(np.abs(est.datum_shift - ref.datum_shift) < 0.002)  # 0.2 mm here; the control sigmas are 2 cm
    kept = integrated(block, sim.ties, BundleOptions(sigma_px=0.3, control_sigma_estimate=False),
                      xyz0=xyz0).runs[0].result
    assert kept.control_sigma_scale == 1.0
    assert kept.variance_components["control_measurements"].factor < 0.35
