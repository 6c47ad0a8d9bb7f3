"""The ``match`` (tie points from a file) and ``aerotri`` stages through the CLI, with their outputs."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from oblique_city.core.aerotri.strips import flight_strips
from oblique_city.core.cli import main
from oblique_city.core.evaluate.aerotri import check_point_errors
from oblique_city.core.io.geotiff import read_geotiff
from oblique_city.core.model import Pose, TiePoints
from oblique_city.core.pipeline import Workspace
from oblique_city.core.simulate.observations import SimulationConfig, simulate_block


def _simulated_workspace(tmp_path):
    """A 60-image simulated block with its tie points as the match stage's input file."""
    s = simulate_block(SimulationConfig(n_images=60, tie_density=0.0004, seed=2))
    ws = Workspace.create(tmp_path / "ws", "EPSG:32632")
    ws.save_block(s.block)
    ws.stage_dir("matching")
    s.ties.save(str(ws.path("matching/ties.npz")))
    ws.project["stages"] = {"match": {"tie_source": "file"}, "aerotri": {"sigma_px": 0.3}}
    ws.save_project()
    return s, ws


def test_aerotri_cli_hierarchical_writes_block_report_and_layers(tmp_path):
    s, ws = _simulated_workspace(tmp_path)
    assert main(["aerotri", str(ws.root), "--mode", "hierarchical", "--connection", "cba",
                 "--cell-size", "40"]) == 0
    ws = Workspace.open(ws.root)
    assert ws.stage_options("aerotri")["mode"] == "hierarchical"
    block = ws.load_block()
    adjusted = [i for i, im in block.images.items() if im.pose_adjusted is not None]
    assert len(adjusted) > 0.9 * len(block.images)
    err = np.array([block.images[i].pose_adjusted.C - s.true_poses[i].C for i in adjusted])
    nav = np.array([block.images[i].pose_approx.C - s.true_poses[i].C for i in adjusted])
    assert np.sqrt(np.mean(err**2)) < np.sqrt(np.mean(nav**2))
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert report["mode"] == "hierarchical" and report["connection"] == "cba"
    assert [r["name"] for r in report["runs"]][0] == "nadir"
    assert abs(report["sigma0_px"] / 0.3 - 1.0) < 0.1
    assert report["check_points"]["all"]["n"] >= 20
    # the variance components of every run: the ties weighted right (the given 0.3 px kept), the GNSS positions'
    # factor is their simulated errors' spread (the datum offset aside) over their sigmas, within 4 of its std
    err = np.array([im.pose_approx.C - s.true_poses[i].C for i, im in s.block.images.items()])
    sigma = np.array([im.sigma_position for im in s.block.images.values()])
    spread = np.sqrt(np.mean(((err - err.mean(0)) / sigma) ** 2))
    for run in report["runs"]:
        groups = {v["group"]: v for v in run["variance_components"]}
        assert run["sigma_px_given"] == run["sigma0_a_priori_px"] == 0.3
        assert abs(groups["ties"]["factor"] - 1.0) < 0.1 and groups["ties"]["estimated_sigma_px"] > 0.27
        gnss = groups["gnss"]
        assert abs(gnss["factor"] - spread) < 4 * gnss["factor_std"] + 0.05, (run["name"], gnss, spread)
        # the control points' image measurements carry the simulated 0.3 px, their given sigma
        meas = groups["control_measurements"]
        assert meas["count"] > 0 and abs(meas["factor"] - 1.0) < 4 * meas["factor_std"] + 0.05, (run["name"], meas)
    assert "Variance components" in ws.path("aerotri/report.html").read_text()
    # the block's datum shift: the simulated GNSS offset, the nadir run's refined from all control measurements,
    # more precise than the nadir run's own (which saw the nadir measurements only)
    datum, nadir = report["datum"], report["runs"][0]
    assert np.allclose(datum["shift_m"], -np.array(s.config.gnss_bias), atol=0.04)
    assert nadir["std_kind"] == "marginal" and np.all(np.array(datum["std_m"]) < np.array(nadir["datum_shift_std_m"]))
    assert "Datum shift (control frame - GNSS frame)" in ws.path("aerotri/report.html").read_text()
    # per ground point: the check points' differences are those of the RMS above, measurements fit their
    # intersection to the simulated noise, and control points are listed too
    rows = {g["name"]: g for g in report["ground_points"]}
    names, err = check_point_errors(block, {i: block.images[i].pose_adjusted for i in adjusted})
    assert len(names) == report["check_points"]["all"]["n"]
    for name, e in zip(names, err, strict=True):
        assert rows[name]["kind"] == "check" and rows[name]["images"] >= 2
        assert np.allclose([rows[name]["dx_m"], rows[name]["dy_m"], rows[name]["dz_m"]], e, atol=1e-9)
    assert any(g["kind"] == "control" for g in rows.values())
    assert np.median([g["image_rms_px"] for g in rows.values()]) < 1.0
    # per image: every adjusted image, its kept and rejected tie observations as the adjustment flagged them, and
    # residuals whose squares add up to the runs' image RMS (each observation is in one run; within 2 %: a point
    # left with one ray drops out of its run without a rejection)
    table = {r["image"]: r for r in report["images_table"]}
    assert set(table) == set(adjusted)
    ties = TiePoints.load(str(ws.path("aerotri/ties.npz")))
    idx = {iid: k for k, iid in enumerate(ties.image_ids)}
    # each adjusted track's RMS image residual (Blender colours the cloud by it): about the 0.3 px noise, none for a
    # track the adjustment dropped
    res = ties.extra["residual_px"]
    assert 0.25 < np.sqrt(np.nanmean(res**2)) < 0.5
    assert np.all(np.isfinite(res) <= np.isfinite(ties.xyz[:, 0]))
    for iid in adjusted[:10]:
        mine = ties.obs_image == idx[iid]
        assert table[iid]["observations"] == int((mine & ~ties.obs_blunder).sum())
        assert table[iid]["rejected"] == int((mine & ties.obs_blunder).sum())
    sq = sum(r["observations"] * r["rms_px"] ** 2 for r in table.values() if r["rms_px"] is not None)
    run_sq = sum((r["observations"] - r["rejected"]) * (r["rms_image_px"][0] ** 2 + r["rms_image_px"][1] ** 2)
                 for r in report["runs"])
    assert abs(sq / run_sq - 1) < 0.02
    # the camera models are the simulation's: no camera shows systematic residuals (see test_report.py)
    fields = report["image_residual_fields"]
    assert set(fields) == set(block.cameras)
    assert all(f["systematic_rms_px"] < 0.04 for f in fields.values())
    rays = report["tie_point_rays"]
    assert sum(rays["points"]) == int(np.isfinite(ties.xyz[:, 0]).sum()) and rays["mean_rays"] > 3
    html = ws.path("aerotri/report.html").read_text()
    assert "<h2>Ground points" in html
    assert "<h2>Image residuals by position" in html and "<h2>Images</h2>" in html and "<h2>Tie point rays" in html
    assert "data:image/png;base64," in html and "<svg" in html and "src='http" not in html
    rays = read_geotiff(ws.path("aerotri/layers/cba_rays.tif"))
    assert rays.cell == 40.0 and np.nanmax(rays.data) >= 3
    before = read_geotiff(ws.path("aerotri/layers/intersection_error_before.tif")).data
    after = read_geotiff(ws.path("aerotri/layers/intersection_error_after.tif")).data
    assert np.nanmedian(after) < np.nanmedian(before)
    graph = json.loads(ws.path("matching/graph.json").read_text())
    assert graph["edges"] and all(e["matches"] >= 15 for e in graph["edges"])


def test_aerotri_stage_thinned_hierarchical_still_gives_every_tie_point(tmp_path):
    """HAT with thinned oblique runs through the stage options: the orientation improves on the navigation data and
    the thinned tie points still get coordinates (intersected afterwards) close to the true ones."""
    from oblique_city.core.model import TiePoints

    s, ws = _simulated_workspace(tmp_path)
    assert main(["run", str(ws.root), "--stages", "match,aerotri", "--set", "aerotri.mode=hierarchical",
                 "--set", "aerotri.oblique_ties_per_cell=1", "--set", "aerotri.oblique_tie_grid=4"]) == 0
    ws = Workspace.open(ws.root)
    assert ws.stage_options("aerotri")["oblique_ties_per_cell"] == 1
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert report["thinned_observations"] > 0.2 * s.ties.n_obs  # the oblique runs adjusted a subset
    block = ws.load_block()
    adjusted = [i for i, im in block.images.items() if im.pose_adjusted is not None]
    err = np.array([block.images[i].pose_adjusted.C - s.true_poses[i].C for i in adjusted])
    nav = np.array([block.images[i].pose_approx.C - s.true_poses[i].C for i in adjusted])
    assert len(adjusted) > 0.9 * len(block.images) and np.sqrt(np.mean(err**2)) < np.sqrt(np.mean(nav**2))
    ties = TiePoints.load(str(ws.path("aerotri/ties.npz")))  # the stage keeps the tracks with >= 3 rays, in order
    multi = s.ties.ray_counts() >= 3
    assert ties.n_tracks == multi.sum()
    ok = np.isfinite(ties.xyz[:, 0])
    assert ok.mean() > 0.95
    d = np.linalg.norm(ties.xyz[ok] - s.true_xyz[multi][ok], axis=1)
    assert np.median(d) < 0.1


def test_rig_constraint_on_a_block_without_rig_is_refused(tmp_path):
    """``aerotri.rig`` on a block that holds no rig (a BlocksExchange import) would constrain nothing: the stage
    says so instead of running without the constraint."""
    import pytest

    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.errors import ConfigError
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    block.rigs.clear()
    ws.save_block(block)
    with pytest.raises(ConfigError, match="no rig"):
        STAGE.run(ws, AerotriConfig(rig=True), RunContext())


def test_hat_without_exposures_says_which_images_it_could_not_start_from_the_nadir_run(tmp_path):
    """A block imported without its exposures: HAT still runs, and the stage's message and metric count the oblique
    images that started from the navigation data (none with the exposures)."""
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    cfg = AerotriConfig(mode="hierarchical", sigma_px=0.3)
    assert STAGE.run(ws, cfg, RunContext()).metrics["oblique_without_nadir"] == 0
    block = ws.load_block()
    for img in block.images.values():
        img.exposure = None
    block.rigs.clear()
    ws.save_block(block)
    res = STAGE.run(ws, cfg, RunContext())
    oblique = sum(img.view != "nadir" for img in block.images.values())
    assert oblique > 0 and res.metrics["oblique_without_nadir"] == oblique
    sentence = f"{oblique} oblique images have no nadir image in their exposure"
    assert sentence in res.message
    assert json.loads(ws.path("aerotri/report.json").read_text())["oblique_without_nadir"] == oblique
    assert sentence in ws.path("aerotri/report.html").read_text()


def test_linear_solver_option_reaches_the_adjustment_and_is_checked():
    """``aerotri.linear_solver`` forces how Ceres solves the reduced camera system; an unknown name is refused with
    the option's name before anything runs."""
    import pytest

    from oblique_city.core.aerotri.stage import AerotriConfig
    from oblique_city.core.errors import ConfigError

    assert AerotriConfig(linear_solver="explicit_schur").bundle_options().linear_solver == "explicit_schur"
    assert AerotriConfig().bundle_options().linear_solver == "auto"
    with pytest.raises(ConfigError, match="option 'linear_solver' must be one of auto, sparse_schur, .*got 'cholmod'"):
        AerotriConfig(linear_solver="cholmod")


def test_settle_stop_option_reaches_the_adjustment():
    """``aerotri.settle_stop`` (on by default) switches the settle stop of the least-squares rounds."""
    from oblique_city.core.aerotri.stage import AerotriConfig

    assert AerotriConfig().bundle_options().settle_stop
    assert not AerotriConfig(settle_stop=False).bundle_options().settle_stop


def test_self_calibrated_cameras_are_saved_with_the_adjusted_block(tmp_path):
    """The imported focal lengths are 0.3 % off: with ``self_calibration = ["focal"]`` the adjusted block the later
    stages read carries the calibrated cameras (within 0.05 % of the true focal), not the imported ones that the
    adjusted orientations no longer fit."""
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    true_fx = {cid: cam.fx for cid, cam in block.cameras.items()}
    for cid, cam in list(block.cameras.items()):
        block.cameras[cid] = replace(cam, fx=cam.fx * 1.003, fy=cam.fy * 1.003)
    ws.save_block(block)
    STAGE.run(ws, AerotriConfig(self_calibration=("focal",), sigma_px=0.3), RunContext())
    adjusted = Workspace.open(ws.root).load_block()
    for cid, fx in true_fx.items():
        assert abs(adjusted.cameras[cid].fx / fx - 1.0) < 5e-4, (cid, adjusted.cameras[cid].fx, fx)
    assert all(abs(ws.load_block(adjusted=False).cameras[c].fx / fx - 1.003) < 1e-9 for c, fx in true_fx.items())


def test_mounting_calibration_through_the_cli_is_reported(tmp_path):
    """``oblique-city aerotri --mounting`` stores the option and runs HAT with a mounting correction per camera: the
    report (JSON and HTML) lists each camera's correction, with its marginal standard deviations, from the run
    holding most of its images. The simulated heads sit on their nominal mounting, so every boresight is near
    zero: within 0.03 deg (6 images per camera and run on this small block, 0.015 deg at most when written; the
    correction's prior allows 0.2 deg) and within 4 of its standard deviations."""
    s, ws = _simulated_workspace(tmp_path)
    assert main(["aerotri", str(ws.root), "--mode", "hierarchical", "--mounting"]) == 0
    ws = Workspace.open(ws.root)
    assert ws.stage_options("aerotri")["mounting"] is True
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert set(report["mounting"]) == set(ws.load_block().cameras)
    for m in report["mounting"].values():
        assert m["run"] in {r["name"] for r in report["runs"]} and m["images"] > 0
        assert np.all(np.abs(m["boresight_deg"]) < 0.03), m
        assert np.all(np.abs(m["boresight_deg"]) < 4 * np.array(m["boresight_std_deg"])), m
    assert abs(report["sigma0_px"] / 0.3 - 1.0) < 0.1
    assert "Mounting calibration" in ws.path("aerotri/report.html").read_text()


def test_residual_field_shows_a_distortion_error_that_self_calibration_removes(tmp_path):
    """Every camera is imported with k1 0.01 too large (the simulated measurements follow the true k1): 3.4 px at
    the nadir camera's corners, 1.3 px at the obliques' (``f k1 r^3`` with r = 0.67 and 0.42 in normalised units).
    The orientations absorb what they can (a change of height acts as one of focal length); the report's residual
    field shows the rest: systematic residuals above 0.05 px for every camera (with the true models they stay under
    0.04 px, see the hierarchical test above) and a radial profile that turns inwards at the corners. With radial
    self-calibration the field is flat again: every camera under 0.04 px."""
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    for cid, cam in list(block.cameras.items()):
        block.cameras[cid] = replace(cam, k1=cam.k1 + 0.01)
    ws.save_block(block)
    fields = {}
    for calib in ((), ("radial",)):
        STAGE.run(ws, AerotriConfig(self_calibration=calib, sigma_px=0.3), RunContext())
        fields[calib] = json.loads(ws.path("aerotri/report.json").read_text())["image_residual_fields"]
    for cid in block.cameras:
        wrong, calibrated = fields[()][cid], fields[("radial",)][cid]
        assert wrong["systematic_rms_px"] > 0.05, (cid, wrong["systematic_rms_px"])
        assert wrong["radial"]["mean_px"][-1] < -0.1, (cid, wrong["radial"]["mean_px"])
        assert calibrated["systematic_rms_px"] < 0.04, (cid, calibrated["systematic_rms_px"])


def test_self_calibration_report_matches_the_true_cameras(tmp_path):
    """Every camera is imported with its focal length 0.3 % long, its principal point 2 px right and k1 0.01 too
    large; IAT self-calibrates focal length, principal point and radial distortion (``marginal_std_max_images`` 0: the
    covariance comes from ``calibration_std_max_images``). The report lists per camera each
    parameter's correction with its marginal standard deviation: every adjusted value lies within 4 of them of the
    truth (35 values: a miss at 4 sigma has odds of 0.2 %), their normalised errors have an RMS between 0.5 and 1.6
    (the standard deviations neither too small nor too large), the planted errors (fx, fy, cx, k1) are significant
    and of the 15 parameters without one at most 3 (a 5 % test on each: 3 or fewer with 99.5 %). k1, k2 and k3 are
    listed as strongly correlated, and the corner the calibration moves the most moves by the truth's amount within
    4 of its standard deviations. Without marginal covariances (``marginal_std_max_images`` and
    ``calibration_std_max_images`` 0) the report gives the corrections alone and says why; that run is given the tie
    sigma 1 px for the simulated 0.3 px and adjusts again from its calibrated cameras with the estimated one, and the
    report keeps the imported values as the ones before."""
    from oblique_city.core.aerotri.report import corner_shift
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    true = dict(block.cameras)
    for cid, cam in true.items():
        block.cameras[cid] = replace(cam, fx=cam.fx * 1.003, fy=cam.fy * 1.003, cx=cam.cx + 2.0, k1=cam.k1 + 0.01)
    ws.save_block(block)
    calib = ("focal", "principal_point", "radial")
    STAGE.run(ws, AerotriConfig(self_calibration=calib, sigma_px=0.3, marginal_std_max_images=0), RunContext())
    report = json.loads(ws.path("aerotri/report.json").read_text())["self_calibration"]
    assert set(report) == set(true)
    z, unplanted = [], []
    for cid, cam in report.items():
        assert cam["marginal"] and cam["run"] == "iat"
        params = {p["name"]: p for p in cam["parameters"]}
        assert list(params) == ["fx", "fy", "cx", "cy", "k1", "k2", "k3"]
        for name, p in params.items():
            err = p["adjusted"] - getattr(true[cid], name)
            assert abs(err) < 4 * p["std"], (cid, name, err, p["std"])
            z.append(err / p["std"])
            assert p["initial"] == getattr(block.cameras[cid], name)
            if name in ("fx", "fy", "cx", "k1"):
                assert p["significant"], (cid, name, p)
            else:
                unplanted.append(p["significant"])
        pairs = {(a, b) for a, b, _ in cam["strong_correlations"]}
        assert {("k1", "k2"), ("k2", "k3")} <= pairs, (cid, pairs)
        shift, worst = corner_shift(block.cameras[cid], true[cid])
        assert abs(cam["corner_shift_px"] - np.hypot(*shift[worst])) < 4 * cam["corner_shift_std_px"], (cid, cam)
    assert 0.5 < np.sqrt(np.mean(np.square(z))) < 1.6, z
    assert sum(unplanted) <= 3, unplanted
    assert "Self-calibration" in ws.path("aerotri/report.html").read_text()

    STAGE.run(ws, AerotriConfig(self_calibration=calib, sigma_px=1.0, marginal_std_max_images=0,
                                calibration_std_max_images=0), RunContext())
    doc = json.loads(ws.path("aerotri/report.json").read_text())
    assert doc["runs"][0]["sigma_px_given"] == 1.0 and abs(doc["runs"][0]["sigma0_a_priori_px"] / 0.3 - 1) < 0.05
    for cid, cam in doc["self_calibration"].items():
        assert not cam["marginal"] and cam["corner_shift_std_px"] is None and cam["correlation"] is None
        assert all(p["std"] is None and p["significant"] is None for p in cam["parameters"])
        assert all(p["initial"] == getattr(block.cameras[cid], p["name"]) for p in cam["parameters"])
        assert abs(next(p for p in cam["parameters"] if p["name"] == "k1")["correction"] + 0.01) < 0.005
    assert "calibration_std_max_images" in ws.path("aerotri/report.html").read_text()


def test_hat_self_calibrates_on_a_central_sub_block_first(tmp_path):
    """HAT with self-calibration calibrates the cameras on the 30 images nearest the block's centre (whole
    exposures, all views) before its runs, which hold them. The cameras imported with the errors of the test above
    come out within 4 standard deviations of the truth, from the run ``calibration``, and the check points within
    the issue's 1.2 times IAT's with self-calibration (the seed's target for HAT-CBA against IAT). Calibrated in the
    runs instead (``calibration_images = 0``), the report names the other run that calibrated each oblique head."""
    from oblique_city.core.aerotri.hierarchical import central_images
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    ids = central_images(block, 30)
    exposures = {block.images[i].exposure for i in ids}
    assert len(ids) == 30 and len(exposures) == 6
    assert sorted(ids) == sorted(i for i, im in block.images.items() if im.exposure in exposures)
    centre = {e: np.mean([im.pose_approx.C[:2] for im in block.images.values() if im.exposure == e], 0)
              for e in {im.exposure for im in block.images.values()}}
    mid = np.mean(list(centre.values()), 0)
    far = max(float(np.linalg.norm(centre[e] - mid)) for e in exposures)
    assert all(float(np.linalg.norm(c - mid)) >= far for e, c in centre.items() if e not in exposures)
    true = dict(block.cameras)
    for cid, cam in true.items():
        block.cameras[cid] = replace(cam, fx=cam.fx * 1.003, fy=cam.fy * 1.003, cx=cam.cx + 2.0, k1=cam.k1 + 0.01)
    ws.save_block(block)
    calib = ("focal", "principal_point", "radial")
    checks = {}
    for mode in ("integrated", "hierarchical"):
        result = STAGE.run(ws, AerotriConfig(mode=mode, self_calibration=calib, sigma_px=0.3, calibration_images=30),
                           RunContext())
        report = json.loads(ws.path("aerotri/report.json").read_text())
        checks[mode] = report["check_points"]["all"]
    assert "5 cameras self-calibrated on the 30 central images" in result.message
    assert report["calibration_run"]["images"] == 30 and report["calibration_run"]["cameras_missing"] == []
    assert {r["name"] for r in report["runs"]} == {"nadir", "north", "east", "south", "west"}
    for cid, cam in report["self_calibration"].items():
        assert cam["run"] == "calibration" and cam["marginal"]
        for p in cam["parameters"]:
            assert abs(p["adjusted"] - getattr(true[cid], p["name"])) < 4 * p["std"], (cid, p)
    adjusted = Workspace.open(ws.root).load_block()
    assert all(adjusted.cameras[c].fx == next(p["adjusted"] for p in cam["parameters"] if p["name"] == "fx")
               for c, cam in report["self_calibration"].items())
    for key in ("rms_xy_m", "rms_z_m"):
        assert checks["hierarchical"][key] <= 1.2 * checks["integrated"][key], (key, checks)
    assert "calibration sub-block" in ws.path("aerotri/report.html").read_text()
    assert all(not cam["other_runs"] for cam in report["self_calibration"].values())
    # calibrated in the runs instead, an oblique head looking two ways on crossing strips is calibrated twice: said
    STAGE.run(ws, AerotriConfig(mode="hierarchical", self_calibration=calib, sigma_px=0.3, calibration_images=0),
              RunContext())
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert report["calibration_run"] is None
    twice = {c for c, cam in report["self_calibration"].items() if cam["other_runs"]}
    assert twice == set(true) - {"penta_nadir"}, twice
    assert "own calibration of it" in ws.path("aerotri/report.html").read_text()


def test_a_wrong_control_point_is_rejected_and_reported(tmp_path):
    """A control point given 0.3 m too high (20 times its 0.015 m sigma): the aerotri stage rejects its coordinates,
    says so in the report (JSON: the run and the ground point row; HTML: the ground points table), and the check
    points come out within 5 % of those of the clean block (on which nothing is rejected). With
    ``--no-control-tests`` the point stays in and the check points' Z RMS is worse."""
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    reports, results = [], []
    for lift in (0.0, 0.3):
        s, ws = _simulated_workspace(tmp_path / f"lift{lift}")
        block = ws.load_block()
        gp = max((g for g in block.ground_points.values() if g.kind == "control"), key=lambda g: len(g.observations))
        gp.xyz = gp.xyz + np.array([0.0, 0.0, lift])
        ws.save_block(block)
        results.append(STAGE.run(ws, AerotriConfig(sigma_px=0.3), RunContext()))
        reports.append(json.loads(ws.path("aerotri/report.json").read_text()))
    clean, report = reports
    # the reliability of the clean block: 0.3 m is above the lifted point's smallest detectable error in Z, and the
    # weakest control point reaches the stage's metric, message and the HTML page
    points = {d["name"]: d for d in clean["runs"][0]["reliability"]["control_points"]}
    assert points[gp.name]["mdb_m"][2] < 0.3
    assert 0.0 < points[gp.name]["datum_effect_m"][2] < 0.5 * points[gp.name]["mdb_m"][2]  # the others hold the datum
    weak = clean["weakest_control"]
    assert weak["mdb_m"] == max(max(d["mdb_m"]) for d in points.values())
    assert results[0].metrics["control_mdb_max_m"] == weak["mdb_m"]
    assert f"weakest control point {weak['name']}" in results[0].message
    assert not any(g["rejected_coordinates"] or g["rejected_images"] for g in clean["ground_points"])
    assert report["runs"][0]["control_points_rejected"] == [gp.name]
    row = next(g for g in report["ground_points"] if g["name"] == gp.name)
    assert row["rejected_coordinates"] and abs(row["dz_m"] + 0.3) < 0.05
    assert not any(g["rejected_coordinates"] or g["rejected_images"] for g in report["ground_points"] if g is not row)
    for key in ("rms_xy_m", "rms_z_m"):
        assert report["check_points"]["all"][key] < 1.05 * clean["check_points"]["all"][key]
    html = ws.path("aerotri/report.html").read_text()
    assert f"<td>{gp.name}</td><td>control</td>" in html and "<td>coordinates</td>" in html
    assert "<h2>Reliability</h2>" in html and "<h3>Control points</h3>" in html
    # switched off from the command line: stored in the project, nothing rejected, the wrong point pulls the block
    assert main(["aerotri", str(ws.root), "--no-control-tests"]) == 0
    assert Workspace.open(ws.root).stage_options("aerotri")["control_tests"] is False
    untested = json.loads(ws.path("aerotri/report.json").read_text())
    assert not any(g["rejected_coordinates"] for g in untested["ground_points"])
    assert untested["weakest_control"] is None  # untested: nothing to say of their reliability
    assert untested["check_points"]["all"]["rms_z_m"] > report["check_points"]["all"]["rms_z_m"]


def test_a_wrong_gnss_position_is_rejected_and_reported(tmp_path):
    """One image's GNSS position 1.5 m too high (19 times its 0.08 m sigma): the aerotri stage rejects that prior
    alone and reports it (JSON: the run and the image's row; HTML: the rejected priors table; the stage's message),
    and the image's adjusted centre stays within 0.03 m of the truth (its tie points alone fix it to about 0.02 m
    on this 60-image block). ``--no-prior-tests`` is stored in the project and keeps the prior, whose residual then
    enters the RMS of the prior residuals."""
    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    iid = sorted(i for i in block.images if i.endswith("_nadir"))[len(block.images) // 10]
    pose = block.images[iid].pose_approx
    block.images[iid].pose_approx = Pose(pose.R, pose.C + np.array([0.0, 0.0, 1.5]))
    ws.save_block(block)
    result = STAGE.run(ws, AerotriConfig(sigma_px=0.3), RunContext())
    assert "1 GNSS/IMU priors rejected" in result.message and result.metrics["priors_rejected"] == 1
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert report["runs"][0]["priors_rejected"] == [[iid, "position"]]
    row = next(r for r in report["images_table"] if r["image"] == iid)
    assert row["prior_rejected"] == ["position"] and row["prior_w"][1] > 10
    assert not any(r["prior_rejected"] for r in report["images_table"] if r is not row)
    html = ws.path("aerotri/report.html").read_text()
    assert "Rejected EO priors" in html and f"<td>{iid}</td><td>iat</td><td>GNSS position</td>" in html
    adjusted = ws.load_block(adjusted=True).images[iid].pose_adjusted.C
    assert float(np.linalg.norm(adjusted - s.true_poses[iid].C)) < 0.03
    assert main(["aerotri", str(ws.root), "--no-prior-tests"]) == 0
    assert Workspace.open(ws.root).stage_options("aerotri")["prior_tests"] is False
    untested = json.loads(ws.path("aerotri/report.json").read_text())
    assert untested["runs"][0]["priors_rejected"] == []
    # the prior residuals' RMS is over the priors kept: 1.5 m among 60 images adds 0.19 m to Z when kept
    assert report["runs"][0]["rms_prior_position_m"][2] < 0.12 < 0.15 < untested["runs"][0]["rms_prior_position_m"][2]


def test_gnss_strip_offsets_from_the_cli_are_estimated_and_reported(tmp_path):
    """The second of the 60-image block's two strips gets its GNSS positions 0.4 m higher. ``aerotri --gnss-strips
    shift`` stores the model in the project, finds the simulated strips and estimates their offsets: their difference
    within 0.12 m of the planted 0.4 m (measured 0.067 m; 2.5 times the 0.046 m standard deviation of the difference
    of two strips' mean GNSS errors in Z, 0.08 m over 6 exposures each). They are in report.json, report.html, the
    message and the metrics (without the model: the offsets are suspected, and the message says how to estimate
    them), and the image centres come out closer to the truth than without the offsets (RMS 0.021
    against 0.023 m: the block's 25 control points hold it already)."""
    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block()
    strips = sorted({img.exposure[:3] for img in block.images.values()})
    planted = {name: 0.4 * (k % 2) for k, name in enumerate(strips)}
    for img in block.images.values():
        img.pose_approx = Pose(img.pose_approx.R, img.pose_approx.C + np.array([0.0, 0.0, planted[img.exposure[:3]]]))
    ws.save_block(block)

    def centre_rms() -> float:
        adjusted = ws.load_block(adjusted=True)
        return float(np.sqrt(np.mean([np.sum((img.pose_adjusted.C - s.true_poses[i].C) ** 2)
                                      for i, img in adjusted.images.items() if img.pose_adjusted is not None])))

    assert main(["aerotri", str(ws.root)]) == 0
    plain = centre_rms()
    # without the model the report flags the offsets and the message points to it
    state = json.loads(ws.path("state.json").read_text())["aerotri"]
    assert state["metrics"]["gnss_strips_suspected"] >= 1 and "aerotri.gnss_strips = shift" in state["message"]
    assert "GNSS offsets per strip suspected" in ws.path("aerotri/report.html").read_text()
    assert main(["aerotri", str(ws.root), "--gnss-strips", "shift"]) == 0
    assert Workspace.open(ws.root).stage_options("aerotri")["gnss_strips"] == "shift"
    report = json.loads(ws.path("aerotri/report.json").read_text())
    est = report["gnss_strips"]
    assert len(est) == len(strips) >= 2
    first_of = {n: next(i for i, img in block.images.items() if img.exposure[:3] == n) for n in strips}
    found = flight_strips(block)
    z = {n: est[found.names[found.image_strip[first_of[n]]]]["offset_m"][2] for n in strips}
    for a, b in zip(strips, strips[1:]):
        assert abs((z[b] - z[a]) - (planted[b] - planted[a])) < 0.12
    assert "GNSS offsets per strip" in ws.path("aerotri/report.html").read_text()
    state = json.loads(ws.path("state.json").read_text())["aerotri"]
    assert state["metrics"]["gnss_strips"] == len(strips)
    assert f"GNSS offsets of {len(strips)} strips" in state["message"]
    assert centre_rms() < plain


def test_aerotri_adjusts_with_the_ground_point_measurements_the_match_stage_leaves(tmp_path):
    """The match stage writes ``matching/targets.json`` (here nothing measured: the import's measurements); the
    aerotri stage takes the ground points' image measurements from it: a check point the file leaves without
    measurements is not checked, the adjusted block keeps the file's measurements, and the report (JSON and HTML)
    tells what was measured in the images once something was to be measured. A malformed file is refused with its
    name and the field."""
    import pytest

    from oblique_city.core.aerotri.stage import STAGE, AerotriConfig
    from oblique_city.core.errors import InputError
    from oblique_city.core.pipeline import RunContext

    s, ws = _simulated_workspace(tmp_path)
    assert main(["run", str(ws.root), "--stages", "match"]) == 0
    record = json.loads(ws.path("matching/targets.json").read_text())
    assert record["mode"] == "none"
    block = ws.load_block(adjusted=False)
    assert {n: sorted(o) for n, o in record["observations"].items()} == {
        n: sorted(g.observations) for n, g in block.ground_points.items()}
    check = sorted(n for n, g in block.ground_points.items() if g.kind == "check" and len(g.observations) >= 2)
    STAGE.run(ws, AerotriConfig(sigma_px=0.3), RunContext())
    report = json.loads(ws.path("aerotri/report.json").read_text())
    n_before = report["check_points"]["all"]["n"]
    assert report["target_measurements"] is None  # nothing measured: the report says nothing of it
    record["observations"][check[0]] = {}
    record["mode"] = "all"
    record["points"][check[0]]["missed"] = sorted(block.ground_points[check[0]].observations)
    image = sorted(block.ground_points[check[1]].observations)[0]
    record["points"][check[1]]["measured"] = {image: {"uv": [1.0, 2.0], "predicted": [1.0, 2.0], "score": 0.95,
                                                      "std_px": 0.02, "imported_difference_px": 2.5}}
    ws.path("matching/targets.json").write_text(json.dumps(record))
    STAGE.run(ws, AerotriConfig(sigma_px=0.3), RunContext())
    report = json.loads(ws.path("aerotri/report.json").read_text())
    assert report["check_points"]["all"]["n"] == n_before - 1
    missed = len(block.ground_points[check[0]].observations)
    assert report["target_measurements"] == {"mode": "all", "measured": 1, "missed": missed, "score_median": 0.95,
                                             "imported_rms_px": 2.5, "suspect": [[check[1], image, 2.5]]}
    html = ws.path("aerotri/report.html").read_text()
    assert f"{missed} projections inside an image where no target was found" in html
    assert "1 imported measurements lie more than 1 px from the target measured in the same image" in html
    assert f"{check[1]} in {image} (2.5 px)" in html
    assert ws.load_block().ground_points[check[0]].observations == {}
    record["observations"][check[1]] = {next(iter(block.images)): [1.0]}
    ws.path("matching/targets.json").write_text(json.dumps(record))
    with pytest.raises(InputError, match=f"targets.json.*observations.{check[1]}"):
        STAGE.run(ws, AerotriConfig(sigma_px=0.3), RunContext())


def test_manual_measurements_override_the_others_and_make_the_adjustment_stale(tmp_path, capsys):
    """The operator's measurements (``oblique-city measure``, :mod:`oblique_city.core.matching.manual`) come last: a
    check point's imported measurement moved 36 px off spoils its intersection (measured: image RMS 9.5 px over its 11
    images, 0.17 m off in XY); measured by hand at its true projection it is as good as its other measurements again
    (0.34 px with the simulated 0.3 px noise, 0.013 m; the test takes 1 px and 3 GSD), and removed it no longer
    counts. Each edit
    makes the ``aerotri`` stage stale (the file enters its fingerprint); the report, its HTML and the listing say
    where each measurement comes from; entries of points or images the block does not have are skipped and
    counted. A malformed file is refused naming the field."""
    import pytest

    from oblique_city.core.geometry.projection import project
    from oblique_city.core.matching.manual import MANUAL_FILE
    from oblique_city.core.pipeline.runner import status

    s, ws = _simulated_workspace(tmp_path)
    block = ws.load_block(adjusted=False)
    name, gp = max(((n, g) for n, g in block.ground_points.items() if g.kind == "check"),
                   key=lambda ng: len(ng[1].observations))
    image, other = sorted(gp.observations)[:2]
    img = block.images[image]
    true_uv = project(block.camera_of(img), s.true_poses[image], gp.xyz[None])[0][0]
    gp.observations[image] = true_uv + [30.0, -20.0]
    ws.save_block(block)

    def check_point() -> tuple[dict, dict]:
        assert main(["run", str(ws.root), "--stages", "aerotri"]) == 0
        report = json.loads(ws.path("aerotri/report.json").read_text())
        return report, next(g for g in report["ground_points"] if g["name"] == name)

    report, bad = check_point()
    assert bad["image_rms_px"] > 5.0 and report["manual_measurements"] == {"set": 0, "removed": 0, "skipped": 0}
    assert {r["stage"]: r["status"] for r in status(Workspace.open(ws.root))}["aerotri"] == "done"
    assert main(["measure", str(ws.root), image, "--point", name, "--uv", *map(str, true_uv)]) == 0
    assert {r["stage"]: r["status"] for r in status(Workspace.open(ws.root))}["aerotri"] == "stale"
    report, good = check_point()
    assert good["image_rms_px"] < 1.0 and good["images"] == bad["images"]
    err = np.hypot(good["dx_m"], good["dy_m"]), np.hypot(bad["dx_m"], bad["dy_m"])
    assert err[0] < err[1] and err[0] < 3 * s.gsd
    assert report["manual_measurements"] == {"set": 1, "removed": 0, "skipped": 0}
    assert "1 set by the operator, 0 removed" in ws.path("aerotri/report.html").read_text()
    capsys.readouterr()
    assert main(["measure", str(ws.root), image]) == 0
    row = next(line.split() for line in capsys.readouterr().out.splitlines() if line.startswith(name + " "))
    assert row[-1] == "manual" and np.allclose([float(x) for x in row[4:6]], true_uv, atol=0.01)
    assert main(["measure", str(ws.root), "no-such-image"]) == 2
    assert "no image 'no-such-image' in the block" in capsys.readouterr().err
    assert main(["measure", str(ws.root), other, "--point", name, "--remove"]) == 0
    report, removed = check_point()
    assert removed["images"] == good["images"] - 1
    assert report["manual_measurements"] == {"set": 1, "removed": 1, "skipped": 0}
    assert main(["measure", str(ws.root), image, "--point", name, "--reset"]) == 0
    assert main(["measure", str(ws.root), other, "--point", name, "--reset"]) == 0
    assert json.loads(ws.path(MANUAL_FILE).read_text())["observations"] == {}
    report, again = check_point()
    assert again["image_rms_px"] == pytest.approx(bad["image_rms_px"], rel=1e-6)
    # entries of a point or an image the block does not have (imported again since) are skipped, and reported
    ws.path(MANUAL_FILE).write_text(json.dumps({"format": "oblique-city-manual-measurements", "version": 1,
                                                "observations": {"NOPE": {image: {"uv": [1.0, 2.0], "method": "click"}},
                                                                 name: {"gone": None}}}))
    report, _ = check_point()
    assert report["manual_measurements"] == {"set": 0, "removed": 0, "skipped": 2}
    assert "2 skipped: their points or images are not in the block" in ws.path("aerotri/report.html").read_text()
    ws.path(MANUAL_FILE).write_text(json.dumps({"format": "oblique-city-manual-measurements", "version": 1,
                                                "observations": {name: {image: {"uv": [1.0], "method": "click"}}}}))
    capsys.readouterr()
    assert main(["measure", str(ws.root), image]) == 2
    assert f"manual_measurements.json, field 'observations.{name}.{image}.uv'" in capsys.readouterr().err


def test_rig_through_the_cli_shares_each_exposures_prior(tmp_path):
    """``oblique-city aerotri --rig`` stores the option and ties the heads: the run's log no longer says that each
    head's prior counted in full, as the run without it does, and the datum shift's standard deviations grow by
    the shares (the heads' priors were counted five times; the control points' part stays, so by less than
    sqrt(5) = 2.24: 1.92-2.05 when written, asserted between 1.1 and 2.24)."""
    _, ws = _simulated_workspace(tmp_path)
    full = "each counted in full without rig constraints"

    def run(*flags: str) -> dict:
        assert main(["aerotri", str(ws.root), "--mode", "integrated", *flags]) == 0
        return json.loads(Workspace.open(ws.root).path("aerotri/report.json").read_text())

    free = run()
    tied = run("--rig")
    assert Workspace.open(ws.root).stage_options("aerotri")["rig"] is True
    assert any(full in line for line in free["runs"][0]["log"])
    assert not any(full in line for line in tied["runs"][0]["log"])
    ratio = np.array(tied["datum"]["std_m"]) / np.array(free["datum"]["std_m"])
    assert np.all((ratio > 1.1) & (ratio < np.sqrt(5))), ratio
    assert tied["rig_fusion"] is None
    # HAT with the stored option fuses each exposure's heads after its runs, and its report says so
    assert main(["aerotri", str(ws.root), "--mode", "hierarchical"]) == 0
    ws = Workspace.open(ws.root)
    fused = json.loads(ws.path("aerotri/report.json").read_text())["rig_fusion"]
    block = ws.load_block()
    assert fused["exposures"] == len({im.exposure for im in block.images.values()})
    assert fused["rms_px_after"] <= fused["rms_px_before"]
    assert "Rig fusion: the heads of" in ws.path("aerotri/report.html").read_text()
