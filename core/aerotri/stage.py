"""The ``aerotri`` stage: integrated or hierarchical aerial triangulation of the workspace's block.

Reads the imported block and the tie points of the ``match`` stage (``matching/ties.npz``), with the ground points'
image measurements it leaves (``matching/targets.json``: measured targets, :mod:`..matching.targets`) and the
operator's manual measurements over them (``block/manual_measurements.json``, :mod:`..matching.manual`); writes
``aerotri/block.json`` (the block with ``pose_adjusted`` set, read by later stages through ``ws.load_block()``),
``aerotri/ties.npz`` (adjusted tie coordinates, rejected observations flagged; extras: each track's standard
deviations ``std`` and RMS image residual ``residual_px``), ``aerotri/report.json``,
``aerotri/report.html`` and the quality layers ``aerotri/layers/*.tif|png``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import ConfigError, WorkspaceError
from ..matching.manual import MANUAL_FILE, apply_measurements
from ..matching.targets import target_summary
from ..model import CameraModel, ImageBlock, TiePoints
from ..model.exposures import oblique_without_nadir
from ..pipeline.atomic import write_json, write_text
from ..pipeline.stage import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, CheckedOptions, Range, Rule, Stage, StageResult
from .bundle import CALIBRATION_GROUPS, GNSS_STRIP_MODES, LINEAR_SOLVERS, BundleOptions
from .hierarchical import CONNECTIONS, ATResult, camera_runs, hierarchical, integrated
from .report import (
    accepted_residuals,
    block_report,
    estimated_control_sigma,
    estimated_prior_sigma,
    estimated_tie_sigma,
    first_run,
    format_scale,
    html_report,
    largest_corner_shift,
    largest_systematic,
    misweighted_groups,
    quality_layers,
    track_residual_rms,
    write_layers,
)

MODES = ("integrated", "hierarchical")
TIES_FILE = "matching/ties.npz"


@dataclass(frozen=True)
class AerotriConfig(CheckedOptions):
    """Options of the ``aerotri`` stage.

    Attributes
    ----------
    mode : ``integrated`` (IAT) or ``hierarchical`` (HAT)
    connection : HAT connection points: ``cba`` or a minimum nadir ray count ``2``, ``3``, ``5``, ``10``
    cell_size : CBA grid cell, metres
    oblique_control : HAT: control points measured in oblique images also enter the oblique runs (datum from
        the nadir run)
    oblique_ties_per_cell, oblique_tie_grid : HAT: thin the oblique runs' tie points to this many tracks per cell of
        a grid ``oblique_tie_grid`` cells across each image (connection points kept; the thinned points are
        intersected afterwards with the final orientations); 0 keeps every tie point (the seed's method)
    sigma_px : a priori standard deviation of tie measurements, pixels
    tie_sigma_estimate, tie_sigma_tolerance : estimate the tie measurements' sigma from their residuals (their
        variance component) and adjust again with it when it differs from ``sigma_px`` by more than this share
        (:attr:`.bundle.BundleOptions.tie_sigma_estimate`): a wrong one weighs the priors and the control wrongly
        against the ties and makes the standard deviations and tests of what they determine wrong
    prior_sigma_estimate, prior_sigma_tolerance : scale the GNSS positions' and the IMU attitudes' sigmas up by their
        variance components when these exceed 1 by more than this share (and significantly) and adjust again
        (:attr:`.bundle.BundleOptions.prior_sigma_estimate`): sigmas given too small pull the orientations towards
        the navigation errors and make their standard deviations too small
    control_sigma_estimate : scale the control points' image measurement sigmas by their variance component, either
        way, when it differs from 1 by more than ``tie_sigma_tolerance`` (and significantly) and adjust again
        (:attr:`.bundle.BundleOptions.control_sigma_estimate`)
    self_calibration : any of ``focal``, ``principal_point``, ``radial``, ``tangential``
    datum_shift : estimate a 3D shift between the GNSS frame and the control frame
    rig, rig_sigma_deg, rig_sigma_m : constrain the heads of each exposure to the rig's boresight and lever arms;
        the heads so tied share their exposure's one GNSS/IMU measurement (:func:`.bundle.shared_prior_fraction`),
        where without the rig each head's prior counts in full and the datum's standard deviations come out too
        small. Integrated mode adjusts with these constraints (a relative pose prior per head pair); hierarchical
        mode, whose runs hold one view each, fuses each exposure's heads into one body on the rig after its runs
        (:mod:`.rigfusion`, the rig taken as exact)
    mounting, mounting_sigma_deg, mounting_sigma_m : calibrate each camera's mounting: a boresight rotation and a
        lever-arm offset common to all its images, between the images and their GNSS/IMU priors, with a prior of
        zero and these standard deviations (degrees about, metres along each camera axis); with ``rig`` the heads
        keep their calibrated relative mounting
    blunder_threshold : normalised residual rejection threshold; max_rejection_rounds : rounds after the robust one
    robust_scale : Cauchy loss scale of the first solve in sigmas
    threads : Ceres threads per adjustment
    linear_solver : how Ceres solves the reduced camera system: ``auto`` (by the block's size and structure),
        ``sparse_schur`` (factorisation), ``iterative_schur`` or ``explicit_schur`` (conjugate gradients, see
        :class:`.bundle.BundleOptions`); ``sparse_schur`` is the fallback where conjugate gradients converge slowly
    settle_stop : end an exactly solved least-squares round after the step its quadratic model foretold (one linear
        solve sooner, the same solution; :attr:`.bundle.BundleOptions.settle_stop`); off: Ceres' own tests alone
    layer_cell : cell of the quality layers in metres (0: the CBA cell size)
    layer_views : rays and intersection precision of the CBA layers from ``all``, ``nadir`` or ``oblique`` views
    min_rays : tie tracks with fewer rays are left out (two-ray points are badly constrained and hide blunders)
    marginal_std_max_images : blocks (and HAT runs) of up to this many images report marginal standard deviations
        of their orientations (:func:`.bundle.marginal_covariances`), larger ones the conditional ones, a lower bound
        (0: always the conditional ones). On simulated blocks they took 4.1 s after a 6.2 s HAT oblique run of 600
        images, 51-65 s after a 113-122 s IAT of 3,000 (peak 4.9 GB), 142 s after a 248 s IAT of 6,000 (peak
        10.2 GB)
    calibration_images : HAT with ``self_calibration``: the cameras are calibrated first on the exposures nearest the
        block's centre, about this many images of all views adjusted together, and the hierarchical runs hold them
        (:func:`.hierarchical.hierarchical`); 0: each run calibrates the cameras of its images (a nadir run hardly
        tells the focal length from the flying height)
    calibration_std_max_images : with ``self_calibration`` or ``mounting``, runs of up to this many images compute
        the calibrated parameters' marginal covariance (:func:`.bundle.marginal_covariances`) for their standard
        deviations and correlations in the report, as do runs that compute the images' marginal ones; it took 56 s
        on 3,000 images
    default_sigma_position, default_sigma_attitude_deg : EO prior sigmas (metres, degrees) for images whose
        import carries none (e.g. BlocksExchange); the same for X, Y, Z and for rotations about X, Y, Z
    control_tests : blunder tests of the control points' measurements and coordinates (on by default; see
        :func:`.bundle.control_point_tests`)
    prior_tests : blunder tests of the images' GNSS position and IMU attitude priors (on by default; see
        :func:`.bundle.prior_tests`)
    gnss_strips, gnss_shift_sigma, gnss_drift_sigma : ``off``, ``shift`` or ``drift``: estimate a GNSS offset (and a
        drift along the strip) per flight strip, the strips found from the navigation data (:mod:`.strips`), with
        priors of zero and these standard deviations (metres; metres per km); see
        :attr:`.bundle.BundleOptions.gnss_strips`
    """

    mode: str = "integrated"
    connection: str = "cba"
    cell_size: float = 50.0
    oblique_control: bool = True
    oblique_ties_per_cell: int = 0
    oblique_tie_grid: int = 8
    sigma_px: float = 0.5
    tie_sigma_estimate: bool = True
    tie_sigma_tolerance: float = 0.1
    prior_sigma_estimate: bool = True
    prior_sigma_tolerance: float = 0.1
    control_sigma_estimate: bool = True
    self_calibration: tuple[str, ...] = ()
    datum_shift: bool = True
    rig: bool = False
    rig_sigma_deg: float = 0.002
    rig_sigma_m: float = 0.01
    mounting: bool = False
    mounting_sigma_deg: float = 0.2
    mounting_sigma_m: float = 0.05
    blunder_threshold: float = 4.3
    max_rejection_rounds: int = 4
    robust_scale: float = 3.0
    threads: int = 2
    linear_solver: str = "auto"
    settle_stop: bool = True
    layer_cell: float = 0.0
    layer_views: str = "all"
    min_rays: int = 3
    marginal_std_max_images: int = 3000
    calibration_std_max_images: int = 6000
    calibration_images: int = 500
    default_sigma_position: float = 0.15
    default_sigma_attitude_deg: float = 0.05
    control_tests: bool = True
    prior_tests: bool = True
    gnss_strips: str = "off"
    gnss_shift_sigma: float = 1.0
    gnss_drift_sigma: float = 1.0

    RULES: ClassVar[dict[str, Rule]] = {
        "mode": MODES, "connection": CONNECTIONS, "cell_size": POSITIVE, "oblique_ties_per_cell": NON_NEGATIVE,
        "oblique_tie_grid": AT_LEAST_ONE, "sigma_px": POSITIVE, "tie_sigma_tolerance": POSITIVE,
        "prior_sigma_tolerance": POSITIVE,
        "self_calibration": tuple(CALIBRATION_GROUPS),
        "rig_sigma_deg": POSITIVE, "rig_sigma_m": POSITIVE, "mounting_sigma_deg": POSITIVE,
        "mounting_sigma_m": POSITIVE, "blunder_threshold": POSITIVE, "max_rejection_rounds": NON_NEGATIVE,
        "robust_scale": POSITIVE, "threads": AT_LEAST_ONE, "linear_solver": LINEAR_SOLVERS,
        "layer_cell": NON_NEGATIVE, "layer_views": ("all", "nadir", "oblique"), "min_rays": Range(2.0),
        "marginal_std_max_images": NON_NEGATIVE, "calibration_std_max_images": NON_NEGATIVE,
        "calibration_images": NON_NEGATIVE,
        "default_sigma_position": POSITIVE,
        "default_sigma_attitude_deg": POSITIVE, "gnss_strips": GNSS_STRIP_MODES, "gnss_shift_sigma": POSITIVE,
        "gnss_drift_sigma": POSITIVE}

    def bundle_options(self) -> BundleOptions:
        return BundleOptions(sigma_px=self.sigma_px, robust_scale=self.robust_scale,
                             blunder_threshold=self.blunder_threshold,
                             max_rejection_rounds=self.max_rejection_rounds,
                             self_calibration=tuple(self.self_calibration), datum_shift=self.datum_shift,
                             rig=self.rig, rig_sigma_deg=self.rig_sigma_deg, rig_sigma_m=self.rig_sigma_m,
                             mounting=self.mounting, mounting_sigma_deg=self.mounting_sigma_deg,
                             mounting_sigma_m=self.mounting_sigma_m, threads=self.threads,
                             linear_solver=self.linear_solver, settle_stop=self.settle_stop,
                             marginal_max_images=self.marginal_std_max_images,
                             calibration_max_images=self.calibration_std_max_images, control_tests=self.control_tests,
                             prior_tests=self.prior_tests, gnss_strips=self.gnss_strips,
                             gnss_shift_sigma=self.gnss_shift_sigma, gnss_drift_sigma=self.gnss_drift_sigma,
                             tie_sigma_estimate=self.tie_sigma_estimate, tie_sigma_tolerance=self.tie_sigma_tolerance,
                             prior_sigma_estimate=self.prior_sigma_estimate,
                             prior_sigma_tolerance=self.prior_sigma_tolerance,
                             control_sigma_estimate=self.control_sigma_estimate)


def calibrated_cameras(block: ImageBlock, at: ATResult) -> dict[str, CameraModel]:
    """Camera id -> the camera model as self-calibrated: by HAT's calibration sub-block, else by the run holding most
    of its images."""
    return {cid: run.result.cameras[ci] for cid, (run, ci, _) in camera_runs(block, at.calibrating_runs()).items()}


def run(ws, cfg: AerotriConfig, ctx) -> StageResult:
    block = ws.load_block(adjusted=False)
    ties_path = ws.path(TIES_FILE)
    if not ties_path.exists():
        raise WorkspaceError(f"{ties_path}: no tie points (run the 'match' stage first)")
    if cfg.rig and not (block.rigs and any(img.exposure is not None for img in block.images.values())):
        raise ConfigError(f"aerotri.rig is on, but the block in {ws.path('block', 'block.json')} has no rig "
                          "(heads with boresight and lever arm, images grouped by exposure): import the block with "
                          "its exposures (OPK columns exposure and head, or -o exposures=time or -o exposures=name; "
                          "a rig is then estimated from the orientations), or turn aerotri.rig off")
    ties = _multi_ray(TiePoints.load(str(ties_path)), cfg.min_rays)
    # the ground points' image measurements: the match stage's over the imported ones, the operator's last
    targets, manual, _ = apply_measurements(ws, block)
    for img in block.images.values():
        if img.sigma_position is None or img.sigma_attitude is None:
            img.sigma_position = np.full(3, cfg.default_sigma_position)
            img.sigma_attitude = np.full(3, np.radians(cfg.default_sigma_attitude_deg))
    opt = cfg.bundle_options()
    unpaired = oblique_without_nadir(block) if cfg.mode == "hierarchical" else 0
    ctx.progress(0, 1, "forward intersection")
    if cfg.mode == "integrated":
        at = integrated(block, ties, opt, progress=ctx.progress)
    else:
        at = hierarchical(block, ties, opt, connection=str(cfg.connection), cell=cfg.cell_size,
                          executor=ctx.get_executor(), progress=ctx.progress, oblique_control=cfg.oblique_control,
                          oblique_ties_per_cell=int(cfg.oblique_ties_per_cell),
                          oblique_tie_grid=int(cfg.oblique_tie_grid), calibration_images=int(cfg.calibration_images))
    for iid, pose in at.poses.items():
        block.images[iid].pose_adjusted = pose
    if cfg.self_calibration:  # the adjusted orientations hold only with the cameras calibrated beside them
        block.cameras.update(calibrated_cameras(block, at))
    out = ws.stage_dir("aerotri")
    ws.save_block(block, "aerotri/block.json")
    adj = TiePoints(xyz=at.xyz, obs_track=ties.obs_track, obs_image=ties.obs_image, obs_uv=ties.obs_uv,
                    image_ids=ties.image_ids, obs_blunder=at.obs_rejected, colour=ties.colour,
                    extra={"std": np.sqrt(np.abs(np.diagonal(at.xyz_cov, axis1=1, axis2=2))),
                           "residual_px": track_residual_rms(ties, at)})
    adj.save(str(out / "ties.npz"))
    ctx.progress(1, 2, "statistics and layers")
    report = block_report(block, ties, at)
    report["thinned_observations"] = int(at.extra.get("thinned_observations", 0))
    # HAT's final tests of the tracks a run held with one or two rays (hierarchical.weak_tracks)
    final = ("final_test_tracks", "final_test_rejected", "final_test_restored")
    report["final_tests"] = {k[len("final_test_"):]: int(at.extra[k]) for k in final if k in at.extra} or None
    report["rig_fusion"] = at.extra.get("rig_fusion")
    report["target_measurements"] = (target_summary(targets) if targets is not None and targets.get("mode") != "none"
                                     else None)
    report["manual_measurements"] = {"set": manual[0], "removed": manual[1], "skipped": manual[2]}
    report["oblique_without_nadir"] = unpaired
    layers = quality_layers(block, ties, at, cfg.layer_cell or cfg.cell_size, cfg.layer_views)
    files = write_layers(layers, out / "layers")
    write_json(out / "report.json", report)
    write_text(out / "report.html", html_report(report, layers, accepted_residuals(at)[1]))
    ctx.progress(2, 2, "done")
    check = report["check_points"]["all"]
    worst = largest_systematic(report["image_residual_fields"])
    priors_off = sum(len(r["priors_rejected"]) for r in report["runs"])
    strips = report["gnss_strips"]
    largest = max((float(np.linalg.norm(d["offset_m"])) for d in strips.values()), default=None)
    suspect = {n: d for n, d in report["gnss_strip_check"].items() if d["flagged"]}
    strip = max(suspect, key=lambda n: max(suspect[n]["w"]), default=None)
    weak = report["weakest_control"]
    calib = report["self_calibration"]
    moved = largest_corner_shift(calib)
    estimated = estimated_tie_sigma(report)
    scaled = estimated_prior_sigma(report)
    first = first_run(report)
    off = misweighted_groups(first)
    control_scale = estimated_control_sigma(report)
    return StageResult(
        outputs=("aerotri/block.json", "aerotri/ties.npz", "aerotri/report.json", "aerotri/report.html",
                 *(f"aerotri/layers/{f}" for f in files)),
        metrics={"sigma0": report["sigma0"], "sigma0_px": report["sigma0_px"], "images": report["images"],
                 "check_rms_xy_m": check["rms_xy_m"], "check_rms_z_m": check["rms_z_m"],
                 "blunder_percent": report["blunder_percent"], "wall_s": report["wall_s"],
                 "thinned_observations": report["thinned_observations"],
                 "systematic_residual_px": worst[1] if worst else None, "priors_rejected": priors_off,
                 "gnss_strips": len(strips), "gnss_strip_offset_max_m": largest,
                 "gnss_strips_suspected": len(suspect), "control_mdb_max_m": weak["mdb_m"] if weak else None,
                 "oblique_without_nadir": unpaired, "self_calibrated_cameras": len(calib),
                 "calibration_corner_shift_max_px": calib[moved]["corner_shift_px"] if moved else None,
                 "tie_sigma_px": first["sigma0_a_priori_px"], "control_sigma_scale": control_scale or 1.0},
        message=f"{cfg.mode} AT: {report['images']} images, sigma0 {report['sigma0_px']:.3f} px, "
                f"check RMS XY {check['rms_xy_m']:.3f} m Z {check['rms_z_m']:.3f} m"
                + (f", tie measurements' sigma estimated at {estimated[1]:.3f} px ({estimated[0]:g} px given) and "
                   "adjusted again with it" if estimated is not None else "")
                + (", the " + " and ".join(f"{k} sigmas scaled by {format_scale(f)}" for k, f in scaled.items())
                   + " by their variance components and adjusted again" if scaled else "")
                + (f", the control point measurements' sigmas scaled by {control_scale:.2f} by their variance "
                   "component" if control_scale is not None else "")
                + (", the residuals of the " + " and ".join(f"{k} are {f:.2f} times" for k, f in off.items())
                   + " their a priori sigmas (set realistic ones: see the variance components in report.html)"
                   if off else "")
                + (f", largest systematic image residual {worst[1]:.3f} px ({worst[0]})" if worst else "")
                + (f", {priors_off} GNSS/IMU priors rejected (see report.html)" if priors_off else "")
                + (f", GNSS offsets of {len(strips)} strips estimated (largest {largest:.3f} m)" if strips else "")
                + (f", the GNSS positions of {len(suspect)} strips share an offset (largest in {strip}: "
                   f"{float(np.linalg.norm(suspect[strip]['mean_m'])):.3f} m, {max(suspect[strip]['w']):.1f} sigma): "
                   "estimate it with aerotri.gnss_strips = shift" if suspect else "")
                + (f", {len(calib)} cameras self-calibrated"
                   + (f" on the {report['calibration_run']['images']} central images" if report["calibration_run"]
                      else "")
                   + f" (the largest change moves a corner of {moved} by {calib[moved]['corner_shift_px']:.2f} px)"
                   if moved else "")
                + (f", weakest control point {weak['name']} (errors below {weak['mdb_m']:.3f} m in {weak['axis']} can "
                   "pass its test)" if weak else "")
                + (f"; {unpaired} oblique images have no nadir image in their exposure, so their runs started from "
                   "the navigation data, not the nadir run's corrections (import the exposures: -o exposures=time "
                   "or -o exposures=name)" if unpaired else ""))



def _multi_ray(ties: TiePoints, min_rays: int) -> TiePoints:
    """The tracks with at least ``min_rays`` observations, renumbered."""
    keep = ties.ray_counts() >= min_rays
    sel = keep[ties.obs_track]
    new = np.cumsum(keep) - 1
    return TiePoints(xyz=ties.xyz[keep], obs_track=new[ties.obs_track[sel]], obs_image=ties.obs_image[sel],
                     obs_uv=ties.obs_uv[sel], image_ids=ties.image_ids, obs_blunder=ties.obs_blunder[sel],
                     colour=None if ties.colour is None else ties.colour[keep])


STAGE = Stage(name="aerotri", run=run, config=AerotriConfig, requires=("block", "match"),
              description="aerial triangulation: integrated or hierarchical bundle adjustment with CBA",
              version="23", adjusted_block=False, inputs=(MANUAL_FILE,))
