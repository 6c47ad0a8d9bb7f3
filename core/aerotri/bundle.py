"""The bundle adjustment engine: collinearity with our camera model, solved by Ceres through pycolmap + pyceres.

Observations and unknowns
-------------------------
* Tie point image measurements (sigma ``sigma_px``): pycolmap's reprojection cost on a ``FULL_OPENCV`` camera
  (our Brown model with k4..k6 = 0; COLMAP's pixel origin is the top-left *corner*, so +0.5 on the way in).
* 6-DoF exterior orientation priors (GNSS centre, IMU attitude, with their sigmas):
  ``AbsolutePosePriorCost`` whose residual is (rotation error, centre error) expressed in the camera frame, so
  the world-axis sigmas are rotated into it: ``cov = blockdiag(R S_att R^T, R S_pos R^T)``.
* Ground control points: unknown 3D points with their own image measurements (reprojection cost with the
  points' pixel sigma) and a weighted ground observation of the point plus a 3D translation: the datum shift
  between the GNSS frame and the control frame. All outputs are returned in the control frame (adjusted values
  plus the shift).
* Connection points (hierarchical AT): tie points with a ground observation and its full 3x3 covariance.
* A ground observation is two residual blocks of two rows each (the whitened rows 0-1, then row 2 over a zero
  row, :func:`_prior_rows`), not one of three: with every block on a point two rows high Ceres runs its Schur
  eliminator specialised for 2-row blocks on 3-vector points. One 3-row block makes it fall back to dynamic sizes
  for the whole problem; on 3,000 images that made the integrated adjustment's linear solves a third slower. The
  zero rows are left out of the redundancy. These blocks are Python costs: connection points numerous enough for
  their callbacks to cost more than the specialisation saves go in as pycolmap's 3-row cost
  (:data:`PRIOR_SPLIT_SHARE`).
* Optional self-calibration per camera: focal, principal point, radial (k1 k2 k3), tangential (p1 p2),
  through a ``SubsetManifold`` on the camera's parameter block; the result carries each camera's values before and
  after with their marginal covariance (:class:`Calibration`).
* Optional mounting calibration (``BundleOptions.mounting``): per camera model a correction ``M`` (boresight
  rotation, lever-arm offset) common to all its images, between an image and the frame its GNSS/IMU prior
  describes: ``cam_from_world = M frame_from_world``. The navigation data reach the images through the nominal
  mounting, so a head's fixed misalignment is the same error in the priors of all its images; without ``M`` the
  adjustment takes it for random and the images' weakly determined common mode (a tilt with a shift) follows its
  mean. The EO prior of an image compares ``M^-1 cam_from_world`` with the prior, rig constraints act between
  such frames, and ``M`` has a prior of zero. These costs are Python ones with analytic Jacobians
  (:func:`_cost_classes`): pycolmap's rig reprojection cost, the other way to put ``M`` in, evaluates every tie
  observation's Jacobian by automatic differentiation, 8 times slower than its plain reprojection cost.
* Optional GNSS offsets per flight strip (``BundleOptions.gnss_strips``, strips from :mod:`.strips`): a GNSS position
  is the image's centre plus its strip's offset ``a`` (and drift ``b`` times its along-track position), both with
  priors of zero. The offset is the translation of a strip frame (a pose held at the identity rotation), so that
  pycolmap's relative pose prior between an image and its strip's frame is the image's EO prior with the offset (in
  C++); a drift, or a mounting calibration beside it, goes through the Python cost of the mounting calibration. A
  cost of zero rows (``SchurAnchor`` in :func:`_cost_classes`) keeps the strips' blocks out of Ceres' Schur
  elimination. A trajectory that re-fixes its ambiguities after each turn carries such offsets; unmodelled they
  bend the block against its control (on a 500-image block with 0.3 m per strip: check points 1.09 GSD in XY
  against 0.13 with them estimated).

All costs are scaled to pixel units of ``sigma_px`` (covariances divided by ``sigma_px^2``), so the Ceres cost is
``sigma_px^2 / 2 * chi^2`` and ``sigma0 = sqrt(chi^2 / redundancy)``.

Blunders: a first solve with a Cauchy loss, after which every observation whose normalised residual exceeds the
threshold is rejected; then least-squares rounds, after each of which every tie track's worst observation is
rejected when its normalised residual ``w = |v| / (sigma0 sigma_px sqrt(r))`` (r the redundancy
number, see :mod:`.precision`; ``w^2`` is chi-square with 2 degrees of freedom) exceeds the threshold.
A start already close to the solution (``BundleOptions.screen_start``) replaces the robust solve by tests at the
start with the cameras held (:func:`screen_points`, one resection step of the images from their inliers, the tests
again), so that a single least-squares solve usually remains.
Control points are tested after each round too (:func:`control_point_tests`, ``BundleOptions.control_tests``): a
measurement that does not fit the point's other rays, or coordinates that do not fit the images and the datum shift
of the other control points, leave the next round (a wrong point cannot hide in the shift it helps to estimate).
So are the images' EO priors (:func:`prior_tests`, ``BundleOptions.prior_tests``): a GNSS position or IMU attitude
that does not fit the orientation the image's own tie points give (a loss of the GNSS fix, a time-tag error) leaves
the next round, the other part of the prior staying.
Every test also gives the smallest error it finds with the probability :data:`DETECTION_POWER` (internal reliability,
Baarda's minimal detectable blunder, :func:`detectable_shift`): per tie measurement from its redundancy number, per
control point axis and per EO prior axis from the standard deviation of its tested difference; and of a control
point's error of that size, how far it would move the datum shift (external reliability).
Coordinates are solved around a local origin (the mean prior centre) so UTM magnitudes cost no digits.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import njit

from ..errors import ComputationError
from ..geometry.rotations import matrix_to_rotvec, rotvec_to_matrix, skew
from ..model import CameraModel
from ..model.camera import distort
from . import precision
from .strips import offsets_at

CALIBRATION_GROUPS = {"focal": (0, 1), "principal_point": (2, 3), "radial": (4, 5, 8), "tangential": (6, 7)}
"""Self-calibration groups -> indices in COLMAP's FULL_OPENCV parameter vector."""
CALIBRATION_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
"""The :class:`CameraModel` fields at the indices 0-8 of COLMAP's FULL_OPENCV parameter vector."""

PRIOR_SPLIT_SHARE = 0.01
"""Connection points go in as 2-row blocks (:func:`_prior_rows`, Ceres' specialised Schur eliminator) when they
number at most this share of the tie observations, else as one 3-row block of pycolmap's (dynamic eliminator). The
2-row blocks are Python costs: Ceres calls back into Python for each one at every evaluation, which on 3,000
images with the CBA's 224 points per oblique run is nothing, but with the ">= 3 rays" selection (40,000 points per
run) doubled the oblique runs' time (7.8 -> 14.9 s) where the specialisation saves 0.1-0.3 s."""

PRIOR_PARTS = ("attitude", "position")
"""The parts of an EO prior, in the column order of :attr:`BundleResult.prior_rejected` and ``prior_w``."""

PRIOR_PART_LABELS = ("IMU attitude", "GNSS position")
"""Their names in logs and reports, in the same order."""

PRIOR_SCALE_NOTE = 1.5
"""A robust scale of the EO prior tests (:func:`prior_tests`) above this goes into the adjustment's log: the priors'
sigmas look too small. On the simulated 400-image test block it is 1.0 for the attitude and 1.2-1.3 for the
position, whose 80 exposures drew GNSS errors of 1.22-1.32 times their sigma (median absolute error over 0.6745)."""

DETECTION_POWER = 0.80
"""Probability with which a blunder of the minimal detectable size is found by its test (Baarda's beta0 = 80 %)."""

UNBOUNDED_VARIANCE = 1e12
"""Variance (m^2) that takes the position out of a 6-DoF pose prior whose position a prior test rejected (1000 km
standard deviation: a weight of 1e-12 against the tie points')."""


@dataclass(frozen=True)
class BundleOptions:
    """Adjustment settings.

    Attributes
    ----------
    sigma_px : a priori standard deviation of tie point image measurements, pixels
    robust_scale : Cauchy loss scale of the first solve, in units of ``sigma_px``
    blunder_threshold : normalised residual above which an observation is rejected (4.3 ~ alpha 1e-4)
    control_tests : after each round, test the control points' image measurements and coordinates
        (:func:`control_point_tests`) with ``blunder_threshold``; what fails leaves the next round
    prior_tests : after each round, test each image's GNSS position and IMU attitude prior against the orientation
        its tie points give (:func:`prior_tests`) with ``blunder_threshold``; a part that fails leaves the next round
    max_rejection_rounds : least-squares rounds with rejection after the robust solve
    self_calibration : groups of :data:`CALIBRATION_GROUPS` to estimate
    datum_shift : estimate a 3D shift between the GNSS and the control frame
    rig : constrain the heads of one exposure to their calibrated mounting (boresight ``rig_sigma_deg``,
        lever arm ``rig_sigma_m``) by relative pose priors; the heads so tied share their exposure's one GNSS/IMU
        measurement, each of their priors with its share of the weight (:func:`shared_prior_fraction`)
    mounting : estimate a mounting correction per camera model (see the module docstring) with a prior of zero
        and standard deviations ``mounting_sigma_deg`` (boresight, about each camera axis) and ``mounting_sigma_m``
        (lever arm, along each camera axis); with ``rig`` the rig constraints hold between the frames (each image's
        correction removed), so the heads keep their calibrated, not their nominal, relative mounting
    max_iterations, threads : Ceres settings
    function_tolerance : Ceres' relative cost change that ends the least-squares rounds
    robust_function_tolerance, robust_max_iterations : the same and an iteration limit for the robust (Cauchy)
        round, which only has to separate the blunders: its tail creeps along weakly determined points by 1e-4
        of the cost per iteration without changing which observations are flagged
    ls_trust_region_radius : Ceres' initial trust region radius (Levenberg-Marquardt damping ``1 / radius`` times
        the normal matrix' diagonal) of the least-squares rounds, which start close to the solution (from the
        robust round or the screened start): large, so that their first step is the Gauss-Newton one. Ceres'
        default (1e4, kept for the robust round from the navigation data) damps the weakly determined directions
        (small eigenvalues against the diagonal) of a sub-block tied to connection points by half: on a 600-image
        oblique run of the 3,000-image block the first step left 0.09 of the cost change (2.1 of chi-square) to a
        second one and a third confirmed convergence; from 1e6 up the first step reached the same cost and the
        second confirmed it (3 -> 2 iterations, same final cost to 7 digits)
    linear_solver : ``auto``, ``sparse_schur``, ``iterative_schur`` or ``explicit_schur``; ``auto`` factorises the
        reduced camera system (sparse Schur) while it has at most ``sparse_schur_max_blocks`` non-zero 6x6 blocks
        (image pairs sharing a point, counted on a sample of the tracks) or at most ``sparse_schur_max_neighbours``
        of them per image, and solves it by conjugate gradients (iterative Schur, Schur-Jacobi preconditioner)
        otherwise. The fill-in of the factorisation grows with the neighbours per image. Measured on simulated
        blocks: one-view sub-blocks have 41-58 neighbours per image at any size; sparse Schur solved the 600-image
        nadir one of the 3,000-image block in 10.5 s against 27.8 s iterative, and the 1,608-image nadir one of an
        8,000-image block in 23.0 s against 51.7 s (same rejections); all 3,000 images together have 611 k blocks
        (204 per image), where the factorisation fills in: IAT spent 458 s in Ceres with sparse Schur against 206 s
        iterative. A sub-block with fewer than ``sparse_schur_min_obs_per_image`` observations per image (thinned
        tie points) is solved iteratively too: factorising costs the same per image whatever the observations, while
        each conjugate-gradient product costs in proportion to them. Measured on the one-view oblique runs of the
        3,000-image block (600 images, 54 neighbours per image): at 100 observations per image iterative Schur took
        0.76-0.84 s in Ceres against 1.08-1.16 s sparse (200-image runs of a 1,000-image block: 0.21-0.25 against
        0.26-0.37 s), at 245 per image both the same (2.4-2.7 s), at 777 (the nadir run) sparse is 2.6 times faster.
        ``explicit_schur`` forms the reduced camera system as sparse Schur does and solves it by conjugate gradients
        to a relative residual of ``explicit_schur_eta`` instead of factorising it; ``auto`` takes it in place of
        sparse Schur for a sub-block of at least ``explicit_schur_min_images`` images without camera or mounting
        parameters (global unknowns that couple every image and can slow conjugate gradients down). Ceres orders a
        factorisation's columns by a constrained minimum degree over the whole Jacobian (points included) in its
        preprocessor, once per solve: on the 600-image one-view sub-blocks of the 3,000-image block that ordering
        was about 1.2 s of a 2.6 s preprocessing, while the solves that replace the factorisation cost 0.1-0.3 s
        more, and the steps are as exact (same iterations, same final cost): 4.2-4.6 s in Ceres against 4.7-5.8 s
        (the nadir run: 9.4-10.0 s against 9.9-11.3 s), each run measured alone; whole HAT runs on 2 cores (37-48 s
        here) differed by less than their spread from run to run. Where iterative Schur is chosen it stays: on all
        3,000 images (204 neighbours per image) forming the reduced system costs more than the implicit products
        save (IAT 250 s with it against 149 s), and the thinned oblique runs (100 observations per image) took as
        long or longer with it (1.5-1.9 s in Ceres against 1.3-1.5 s). Nor do Ceres' visibility-clustered
        preconditioners beat Schur-Jacobi on all 3,000 images: IAT's linear solves took 73 s with it against 108 s
        (cluster Jacobi, single linkage), 220 s (cluster Jacobi, canonical views) and 463 s (cluster tridiagonal, single
        linkage), with the same iterations and final costs (to 1e-5)
    settle_stop : a least-squares round solved exactly (sparse Schur, or explicit Schur to ``explicit_schur_eta``, the
        conjugate gradients stopped before their cap) ends after an undamped step (:data:`SETTLE_MIN_RADIUS`, the
        least-squares rounds' ``ls_trust_region_radius``) that :func:`model_settled` accepts: its quadratic model
        foretold the cost so closely that no further step can lower the cost by ``function_tolerance``. Ceres would
        compute that step, find the decrease under its tolerance and discard it, so the result is the same, one linear
        solve and one cost evaluation sooner. On the 600-image sub-blocks of the 3,000-image block the least-squares
        rounds took one step where Ceres computed two and kept one (the model foretold the step's decrease to 1e-6 of
        it; bit-identical orientations and points on one thread): an oblique run on one thread 8.0-8.7 s against
        8.9-11.1 s, the nadir run on two 11.9-13.5 s against 13.1-13.7 s, whole HAT runs on 2 cores 34.7-36.6 s against
        37.3-37.8 s. Not for iterative Schur, whose steps stop short of the model's minimum by design (truncated Newton,
        ``eta`` 0.1); IAT's least-squares round solved by explicit Schur with this stop instead took as long (IAT 142 s
        against 147 s), so IAT keeps iterative Schur
    resolve_tolerance : a least-squares round whose flagged observations carry less than this share of chi-square
        ends the rejection without another solve: they are rejected and only the points that lost them are
        re-estimated (cameras fixed), since a full solve would move the cameras by far less than their precision.
        EO prior parts the round's tests reject count in that share with the chi-square their removal frees, and
        their images move by the step the removal implies (:func:`prior_release`; each image its own group, no
        mounting, strip frames, self-calibration or marginal covariance): one image's IMU prior rejected at 4.3
        made an oblique run of a 6,000-image block solve twice (20.8 s against 12.7 s)
    marginal_max_images : up to this many adjusted images (0: never), the images' standard deviations are the
        marginal ones (:func:`marginal_covariances`: the correlations between images and with the datum, the control and
        the calibrated parameters included); above it the conditional ones (each image's 6 x 6 normal block with the
        points held fixed; with ``rig`` each exposure's heads together, the other exposures held), a lower bound. On the
        simulated 3,000-image block the marginal ones took 51-65 s after a 113-122 s adjustment (peak 4.9 GB for the
        whole run) and fit the true errors: RMS error over standard deviation 0.97-1.01 per axis of attitude, 0.91-0.95
        of centre (with the datum's uncertainty, see :func:`world_pose_std`), where the conditional ones are 5-7 %
        smaller
    calibration_max_images : with ``self_calibration`` or ``mounting``, up to this many adjusted images the
        calibrated parameters' marginal covariance is computed (:func:`marginal_covariances`) for their standard
        deviations and correlations (:attr:`Calibration.cov`, ``BundleResult.mounting_std``): 56 s on 3,000 images
        (the Jacobian evaluated, the points eliminated, the images' sparse reduced system factorised). Computed
        whenever the images' marginal ones are
    screen_start : for a start already close to the solution (HAT's oblique runs start from the adjusted nadir
        orientations propagated to their heads): the robust round is replaced by :func:`screen_points` at the start
        (cameras held, each point re-estimated from its rays with blunder tests, sigma0 estimated robustly), and the
        least-squares rounds follow. When the screening's sigma0 exceeds ``screen_max_sigma0`` (the start is not
        close enough for tests with the cameras held) the robust round runs as usual. ``screen_rounds`` bounds the
        screening's rejection rounds (one ray per track and round; blunders can come several to a track)
    gnss_strips : ``off``, ``shift`` or ``drift``: estimate per flight strip (``BundleProblem.prior_strip``, see
        :mod:`.strips`) an offset of the GNSS positions (3-D), or an offset and a drift along the strip (3-D, per km
        of the image's along-track position), with priors of zero and standard deviations ``gnss_shift_sigma``
        (metres) and ``gnss_drift_sigma`` (metres per km): the GNSS positions are taken as the centres plus
        ``a + along b``. With a datum shift the offsets' common part goes to the shift (their priors hold their mean
        at zero): they are then the strips' offsets from the block's mean
    screen_resect : with ``screen_start``, the images are first moved to their inliers (:func:`resected_start`:
        a screening, one resection step) and the screening that decides runs from there; without it the start is
        taken as resected already (HAT resects its oblique runs while the nadir run finishes) and screened once
    tie_sigma_estimate : the tie measurements' a priori sigma is estimated from their own residuals (their variance
        component, :func:`variance_components`): when it differs from ``sigma_px`` by more than
        ``tie_sigma_tolerance`` (relative), the adjustment is solved again with the estimate, from its solution (its
        orientations, points and cameras; blunders screened there anew), at most ``variance_passes`` times. The
        sigma0 of an adjustment scales the whole covariance, but the priors and the control keep the weights of their
        own sigmas: a tie sigma 3.8 times too large (0.5 px given, 0.13 px matched on the rendered demo) weighs the
        GNSS positions 14 times too much against the ties, and the standard deviations of what they determine come
        out 3.8 times too small. On the demo, self-calibration then moved the exact cameras' focal lengths by -1.9 to
        -2.5 px at t = -3.1 to -3.5, pulled by the random GNSS errors (with the true navigation data: t 0.2-0.3);
        with the tie sigma estimated, -0.2 to -0.75 px at |t| <= 0.5
    prior_sigma_estimate : the GNSS positions' and the IMU attitudes' a priori sigmas are scaled up by their variance
        components as well (:func:`prior_sigma_factors`): a group whose factor exceeds 1 by more than
        ``prior_sigma_tolerance`` (relative) and by more than 3 of the estimate's standard deviations is weighted
        anew in the same passes, once the ties' variance factor is within ``tie_sigma_tolerance`` (the ties' sigma
        is settled first; held wrong, the priors are not scaled: their residuals follow the ties' weight). Sigmas
        given too small make the priors pull the block towards the navigation errors and their standard deviations
        too small. Given too large, they only waste some of the priors' information, and they are kept: a component
        below 1 did not make a safe factor to tighten them by. On the rendered demo, whose sigmas are the largest
        axis's for all three (its simulated errors are 0.62 of them in X and Y), GNSS 0.67 and IMU 0.76, and its
        orientations scaled by them came out worse against the truth, 0.0037 against 0.0030 deg RMS, per axis
        (0.48-0.66 in X and Y) 0.0044. It is not the redundancy numbers' approximation (taken with the marginal
        covariances of all images, the mountings and the datum, the components came out 0.68 and 0.77): with 25
        exposures the estimates scatter, and a weight too large costs more than one too small. The components of a
        misweighted solution are biased towards 1 (a prior weighted too much leaves less of its error in its
        residuals), so the passes approach the right sigmas from below. On 500 simulated images with the sigmas
        given 4 times too small, IAT scaled them by 3.55 (IMU) and 3.90 (GNSS): attitude errors 0.0040 deg RMS, the
        centres' errors 1.2-1.9 times their standard deviations, as with the right sigmas (0.0039, 1.1-1.9), against
        0.0061 and 2.7-3.9 with them kept (the bench's Table 15, ``--prior-sigma 0.25``)
    prior_sigma_scale : (6,) factors applied to every image's prior sigmas (``BundleProblem.prior_sigma_att`` about
        world X Y Z, then ``prior_sigma_pos`` along X Y Z): the passes of ``prior_sigma_estimate`` set them, and HAT
        hands the nadir run's to the other runs (one GNSS/IMU system)
    control_sigma_estimate : the control points' image measurements' sigmas (``BundleProblem.gcp_sigma_px``) are
        scaled by their variance component, either way, in the same passes as the ties' sigma, when it differs from
        1 by more than ``tie_sigma_tolerance`` and by more than 3 of its standard deviations: they are image
        measurements too, of targets (a template fit, or by hand), whose precision the importer seldom gives. On
        the rendered demo the targets were given 0.5 px (component 0.12, from 216 of redundancy), and two passes
        scaled them by 0.088: the orientations came out 0.0025 against 0.0030 deg RMS from the truth, the centres
        8.2 / 7.0 / 7.6 against 9.3 / 8.8 / 9.8 mm, the check points 0.011 against 0.012 m in XY (HAT on its rig:
        0.0052 against 0.0058 deg, check points 0.013 against 0.016 m)
    control_sigma_scale : the factor applied to those sigmas: the passes of ``control_sigma_estimate`` set it, and
        HAT hands the nadir run's to the other runs
    """

    sigma_px: float = 0.5
    robust_scale: float = 3.0
    blunder_threshold: float = 4.3
    max_rejection_rounds: int = 4
    self_calibration: tuple[str, ...] = ()
    datum_shift: bool = True
    rig: bool = False
    rig_sigma_deg: float = 0.002
    rig_sigma_m: float = 0.01
    mounting: bool = False
    mounting_sigma_deg: float = 0.2
    mounting_sigma_m: float = 0.05
    max_iterations: int = 60
    function_tolerance: float = 1e-6
    robust_function_tolerance: float = 1e-4
    robust_max_iterations: int = 10
    ls_trust_region_radius: float = 1e8
    threads: int = 2
    linear_solver: str = "auto"
    sparse_schur_max_blocks: int = 60_000
    sparse_schur_max_neighbours: float = 100.0
    sparse_schur_min_obs_per_image: float = 200.0
    explicit_schur_min_images: int = 300
    explicit_schur_eta: float = 1e-5
    settle_stop: bool = True
    resolve_tolerance: float = 1e-4
    marginal_max_images: int = 0
    calibration_max_images: int = 0
    control_tests: bool = True
    prior_tests: bool = True
    screen_start: bool = False
    screen_max_sigma0: float = 2.0
    screen_rounds: int = 10
    screen_resect: bool = True
    gnss_strips: str = "off"
    gnss_shift_sigma: float = 1.0
    gnss_drift_sigma: float = 1.0
    tie_sigma_estimate: bool = True
    tie_sigma_tolerance: float = 0.1
    variance_passes: int = 2
    prior_sigma_estimate: bool = True
    prior_sigma_tolerance: float = 0.1
    prior_sigma_scale: tuple[float, ...] = (1.0,) * 6
    control_sigma_estimate: bool = True
    control_sigma_scale: float = 1.0


GNSS_STRIP_MODES = ("off", "shift", "drift")
"""The values of :attr:`BundleOptions.gnss_strips`."""


@dataclass(eq=False)
class BundleProblem:
    """A bundle adjustment over arrays (independent of the block classes, picklable for worker processes).

    Attributes
    ----------
    image_ids : (n,) names; cameras : camera models; image_camera : (n,) int index into ``cameras``
    r_cam_from_world : (n, 3, 3), c_world : (n, 3) initial orientations
    prior_r : (n, 3, 3), prior_c : (n, 3) EO priors; prior_sigma_att (n, 3) radians about world X Y Z,
        prior_sigma_pos (n, 3) metres; rows of NaN sigma mean "no prior"
    xyz : (p, 3) initial tie point coordinates
    obs_point, obs_image : (m,) int64; obs_uv : (m, 2) pixels (origin at the centre of the top-left pixel)
    point_prior_xyz : (p, 3) ground observations of tie points (connection points), NaN rows for none
    point_prior_cov : (p, 3, 3) their covariances
    gcp_xyz : (g, 3) control point coordinates; gcp_sigma : (g, 3)
    gcp_obs_point, gcp_obs_image : (k,) int64; gcp_obs_uv : (k, 2); gcp_sigma_px : (g,)
    rig_pairs : (q, 2) images (i, j) of one exposure with their calibrated relative pose ``i_from_j``:
        rotation rig_r (q, 3, 3) and translation rig_t (q, 3) (used when ``BundleOptions.rig``)
    prior_strip : (n,) int64 flight strip of each image (index into ``strip_names``, -1: none; empty: no strips);
        prior_along : (n,) its along-track position from the strip's middle, km (used when
        ``BundleOptions.gnss_strips``)
    image_exposure : (n,) int64 the exposure of each image (images of one exposure share one GNSS/IMU
        measurement), -1 for an image of its own; empty: every image its own
    """

    image_ids: list[str]
    cameras: list[CameraModel]
    image_camera: np.ndarray
    r_cam_from_world: np.ndarray
    c_world: np.ndarray
    prior_r: np.ndarray
    prior_c: np.ndarray
    prior_sigma_att: np.ndarray
    prior_sigma_pos: np.ndarray
    xyz: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_uv: np.ndarray
    point_prior_xyz: np.ndarray | None = None
    point_prior_cov: np.ndarray | None = None
    gcp_names: list[str] = field(default_factory=list)
    gcp_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_obs_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gcp_obs_image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gcp_obs_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    gcp_sigma_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rig_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    rig_r: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    rig_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    prior_strip: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    prior_along: np.ndarray = field(default_factory=lambda: np.zeros(0))
    strip_names: list[str] = field(default_factory=list)
    image_exposure: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def n_images(self) -> int:
        return len(self.image_ids)

    @property
    def n_points(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True, eq=False)
class Calibration:
    """One camera's self-calibration in an adjustment (``BundleOptions.self_calibration``).

    Attributes
    ----------
    params : indices of its free parameters in COLMAP's FULL_OPENCV vector (names in :data:`CALIBRATION_NAMES`)
    initial, adjusted : (k,) their values before and after the adjustment, as :class:`CameraModel` holds them
        (focal length and principal point in pixels, the principal point from the centre of the top-left pixel)
    cov : (k, k) their marginal covariance, scaled by the run's sigma0 (the correlations with the orientations, the
        points and the datum included; see :func:`marginal_covariances`), or None where the run computed none
        (``BundleOptions.calibration_max_images``)
    """

    params: tuple[int, ...]
    initial: np.ndarray
    adjusted: np.ndarray
    cov: np.ndarray | None


def _calibration_values(cam: CameraModel, params: tuple[int, ...]) -> np.ndarray:
    """The values ``(k,)`` of the FULL_OPENCV parameters ``params`` of ``cam`` (its :class:`CameraModel` fields)."""
    return np.array([getattr(cam, CALIBRATION_NAMES[i]) for i in params], np.float64)


VARIANCE_GROUPS = {"ties": "tie measurements", "gnss": "GNSS positions", "imu": "IMU attitudes",
                   "control": "control point coordinates", "control_measurements": "control point measurements"}
"""The observation groups of :func:`variance_components`, with their names in words."""


@dataclass(frozen=True)
class VarianceComponent:
    """One observation group's variance component: its weighted squared residuals ``omega`` over its share of the
    redundancy (the sum of its redundancy numbers, ``redundancy``) estimates the square of ``factor``, how many times
    its a priori sigmas the group's errors are (1: weighted as it should be). ``count`` observations (coordinates or
    axes) took part. ``factor_std``: the estimate's standard deviation, ``factor / sqrt(2 redundancy)``."""

    count: int
    redundancy: float
    omega: float

    @property
    def factor(self) -> float:
        return float(np.sqrt(self.omega / self.redundancy)) if self.redundancy > 0 else float("nan")

    @property
    def factor_std(self) -> float:
        return self.factor / float(np.sqrt(2.0 * self.redundancy)) if self.redundancy > 0 else float("nan")


@dataclass(eq=False)
class BundleResult:
    """Adjusted values (control frame) with their precision and statistics.

    Attributes
    ----------
    r_cam_from_world, c_world : (n, 3, 3), (n, 3); image_adjusted : (n,) bool (images with observations)
    image_std : (n, 6) std of rotation about world X Y Z (radians) and of the centre (metres) in the control frame
        (the marginal ones with the datum shift's uncertainty, common to all images); image_std_relative : (n, 6)
        the same relative to the datum (the shift held; equal to ``image_std`` without a marginal covariance or an
        estimated shift); image_std_kind : ``marginal`` or ``conditional`` (see ``BundleOptions.marginal_max_images``)
    cameras : adjusted camera models
    xyz : (p, 3) tie points (NaN for points dropped); xyz_cov : (p, 3, 3) covariance with cameras fixed
    obs_residual : (m, 2) pixels (observed - computed); obs_rejected : (m,) bool; obs_w : (m,) normalised residual
    obs_used : (m,) bool, observations in the final solution (not rejected, their point determined)
    gcp_xyz : (g, 3) adjusted control points; gcp_residual : (g, 3) adjusted - given
    gcp_obs_rejected : (k,) control point measurements rejected by their own test; gcp_rejected : (g,) control
        points whose coordinates were rejected (they left the adjustment with all their measurements); gcp_w :
        (g,) their largest normalised coordinate differences in the last test (:func:`control_point_tests`; NaN:
        untested)
    prior_rejected : (n, 2) bool, the attitude (column 0) and position (column 1) priors of each image rejected by
        :func:`prior_tests`; prior_w : (n, 2) their largest normalised differences in the last test (a rejected
        part's when it was rejected; NaN: untested)
    obs_redundancy : (m,) redundancy number of each tie measurement (per coordinate, see :mod:`.precision`; the
        share of an error that shows in its residual); obs_mdb : (m,) the smallest error of a measurement (pixels)
        its test finds with probability :data:`DETECTION_POWER` (NaN: not in the solution); gcp_redundancy, gcp_mdb
        : (g, 3) the same per control point axis (metres; from the last control point test, NaN: untested);
        prior_mdb : (n, 6) the same per EO prior axis (attitude about world X Y Z in radians, position in metres;
        from the last prior test, at its robust scale; NaN: untested); gcp_datum_effect : (g, 3) how far a control
        point error of the size in gcp_mdb moves the datum shift (external reliability, metres; NaN where untested
        or the shift is held); prior_effect : (n, 6) how far a prior error of the size in prior_mdb moves the
        adjusted orientation along its axis (external reliability, with the points held; NaN: untested)
    datum_shift : (3,) control frame - GNSS frame; datum_shift_std : (3,) its marginal standard deviations (NaN where
        the shift is held or the run computed no marginal covariance, see ``BundleOptions.marginal_max_images``)
    gnss_strip : (s, 6) per strip of ``BundleProblem.strip_names`` its GNSS offset (metres) and drift (metres per
        km) as estimated with ``BundleOptions.gnss_strips`` (NaN: not estimated); gnss_strip_std : (s, 6) their
        standard deviations with the orientations held (conditional, a lower bound), the heads of one exposure
        counting as one GNSS position
    mounting : (k, 6) per camera model its mounting correction ``M`` (``BundleOptions.mounting``): rotation vector
        (radians, camera axes) and the camera centre's offset ``-R_M^T t_M`` from the frame's (metres, camera axes);
        NaN rows for cameras without one; mounting_std : (k, 6) their marginal standard deviations (NaN where the
        run computed none, see ``BundleOptions.calibration_max_images``)
    calibration : camera index -> its :class:`Calibration` (self-calibration; cameras the run adjusted)
    sigma0 : a posteriori, unitless (multiply by sigma_px for pixels); redundancy : degrees of freedom
    sigma_px : the tie measurements' a priori sigma of this solution (pixels): ``sigma_px_given``
        (``BundleOptions.sigma_px``) or, with ``BundleOptions.tie_sigma_estimate``, its estimate
    variance_components : :data:`VARIANCE_GROUPS` -> :class:`VarianceComponent` of this solution
    prior_sigma_scale : (6,) the factors of the attitude (about world X Y Z) and position (X Y Z) prior sigmas of
        this solution (``BundleOptions.prior_sigma_scale``, or with ``BundleOptions.prior_sigma_estimate`` their
        estimate); control_sigma_scale : that of the control points' image measurement sigmas (likewise)
    iterations, rounds, time_s : solver work; timing : seconds spent building the problems (``build_s``),
        in Ceres (``solve_s``, of which ``preprocess_s`` in its preprocessor (ordering, structure; a cost per
        solve whatever the iterations), ``jacobian_s`` evaluating and ``linear_s`` solving) and on residuals,
        precision and rejection (``statistics_s``), over all rounds, and on the marginal covariances at the end
        (``covariance_s``, see ``BundleOptions.marginal_max_images``)
    """

    r_cam_from_world: np.ndarray
    c_world: np.ndarray
    image_adjusted: np.ndarray
    image_std: np.ndarray
    cameras: list[CameraModel]
    xyz: np.ndarray
    xyz_cov: np.ndarray
    obs_residual: np.ndarray
    obs_rejected: np.ndarray
    obs_w: np.ndarray
    gcp_xyz: np.ndarray
    gcp_residual: np.ndarray
    datum_shift: np.ndarray
    sigma0: float
    redundancy: int
    iterations: int
    rounds: int
    time_s: float
    obs_used: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    prior_residual_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    prior_residual_att: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    image_std_kind: str = "conditional"
    mounting: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    mounting_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    calibration: dict[int, Calibration] = field(default_factory=dict)
    datum_shift_std: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    image_std_relative: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    log: list[str] = field(default_factory=list)
    timing: dict[str, float] = field(default_factory=dict)
    gcp_obs_rejected: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    gcp_rejected: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    gcp_w: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior_rejected: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), bool))
    prior_w: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    gnss_strip: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    gnss_strip_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    obs_redundancy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    obs_mdb: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gcp_redundancy: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_mdb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gcp_datum_effect: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    prior_mdb: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    prior_effect: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    sigma_px: float = float("nan")
    sigma_px_given: float = float("nan")
    variance_components: dict[str, VarianceComponent] = field(default_factory=dict)
    prior_sigma_scale: np.ndarray = field(default_factory=lambda: np.ones(6))
    control_sigma_scale: float = 1.0


def _quat_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = np.array([(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4])
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-300))
        q = np.zeros(4)
        q[i] = s / 4
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
        q[3] = (r[k, j] - r[j, k]) / s
    return q / np.linalg.norm(q)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _rigid(r: np.ndarray, c_local: np.ndarray):
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(_quat_xyzw(r)), -r @ c_local)


_PIXEL_ORIGIN = np.array([0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0])
"""Added to the :data:`CALIBRATION_NAMES` values on the way into COLMAP (its pixel origin is the top-left corner)."""


def _colmap_params(cam: CameraModel) -> list[float]:
    return [*(_calibration_values(cam, tuple(range(9))) + _PIXEL_ORIGIN), 0.0, 0.0, 0.0]


def _camera_from_params(cam: CameraModel, p: np.ndarray) -> CameraModel:
    from dataclasses import replace

    return replace(cam, **{n: float(v) for n, v in zip(CALIBRATION_NAMES, np.asarray(p[:9]) - _PIXEL_ORIGIN)})


def project_obs(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                xyz: np.ndarray, obs_point: np.ndarray, obs_image: np.ndarray) -> np.ndarray:
    """Projected pixel positions ``(m, 2)`` of observations (NaN behind the camera): ``xyz (n, 3)`` seen from the
    images ``r (k, 3, 3)``, ``c (k, 3)`` through ``obs_point``, ``obs_image (m,)``, in one compiled pass."""
    out = np.empty((len(obs_image), 2))
    _project(_pixel_params(cameras), np.asarray(image_camera, np.int64), np.asarray(r, np.float64),
             np.asarray(c, np.float64), np.asarray(xyz, np.float64), np.asarray(obs_point, np.int64),
             np.asarray(obs_image, np.int64), out)
    return out


def pixels_from_camera(cameras: list[CameraModel], image_camera: np.ndarray, xyz_cam: np.ndarray,
                       obs_image: np.ndarray) -> np.ndarray:
    """Pixel positions ``(m, 2)`` of points given in the cameras' frames ``xyz_cam (m, 3)`` of the observations'
    images ``obs_image (m,)`` (NaN behind the camera)."""
    out = np.empty((len(obs_image), 2))
    _pixels(_pixel_params(cameras), np.asarray(image_camera, np.int64), np.asarray(xyz_cam, np.float64),
            np.asarray(obs_image, np.int64), out)
    return out


def _pixel_params(cameras: list[CameraModel]) -> np.ndarray:
    """``(k, 9)``: fx, fy, cx, cy, k1, k2, k3, p1, p2 per camera (the distortion of
    :meth:`.CameraModel.distort_normalized`)."""
    return np.array([[cm.fx, cm.fy, cm.cx, cm.cy, cm.k1, cm.k2, cm.k3, cm.p1, cm.p2] for cm in cameras],
                    np.float64).reshape(-1, 9)


@njit(cache=True, nogil=True)
def _pixel(p: np.ndarray, x: float, y: float, z: float, out: np.ndarray) -> None:
    """``out (2,)``: the pixel of the camera-frame point ``(x, y, z)`` with the camera ``p (9,)`` of
    :func:`_pixel_params` (NaN behind the camera)."""
    if not z > 0.0:
        out[0] = out[1] = np.nan
        return
    xd, yd = distort(x / z, y / z, p[4], p[5], p[6], p[7], p[8])
    out[0] = p[0] * xd + p[2]
    out[1] = p[1] * yd + p[3]


@njit(cache=True, nogil=True)
def _pixels(params: np.ndarray, image_camera: np.ndarray, xc: np.ndarray, oi: np.ndarray, out: np.ndarray) -> None:
    """:func:`pixels_from_camera` per observation."""
    for k in range(len(oi)):
        _pixel(params[image_camera[oi[k]]], xc[k, 0], xc[k, 1], xc[k, 2], out[k])


@njit(cache=True, nogil=True)
def _project(params: np.ndarray, image_camera: np.ndarray, r: np.ndarray, c: np.ndarray, xyz: np.ndarray,
             op: np.ndarray, oi: np.ndarray, out: np.ndarray) -> None:
    """:func:`project_obs` per observation."""
    for k in range(len(oi)):
        i, p = oi[k], op[k]
        w0, w1, w2 = xyz[p, 0] - c[i, 0], xyz[p, 1] - c[i, 1], xyz[p, 2] - c[i, 2]
        _pixel(params[image_camera[i]], r[i, 0, 0] * w0 + r[i, 0, 1] * w1 + r[i, 0, 2] * w2,
               r[i, 1, 0] * w0 + r[i, 1, 1] * w1 + r[i, 1, 2] * w2, r[i, 2, 0] * w0 + r[i, 2, 1] * w1 + r[i, 2, 2] * w2,
               out[k])


def _quat_plus_jacobian(q: np.ndarray) -> np.ndarray:
    """``(4, 3)`` Jacobian at zero of Ceres' ``EigenQuaternionManifold`` Plus, ``q' = (delta, 1) q`` for the
    quaternion ``q = (x, y, z, w)``: the increment ``delta`` turns ``R`` into ``exp([2 delta]x) R``. Its columns are
    orthonormal for a unit ``q``, so a Jacobian ``J`` with respect to ``delta`` is ``J P^T`` with respect to ``q``."""
    return np.vstack([q[3] * np.eye(3) - skew(q[:3]), -q[None, :3]])


def _pose_weights(sigma_px: float, sigma_rad, sigma_m) -> np.ndarray:
    """``(6,)`` residual weights of a rotation (radians) and position (metres) error with these standard
    deviations (scalars or per axis), in units of ``sigma_px``."""
    return sigma_px / np.concatenate([np.broadcast_to(sigma_rad, 3), np.broadcast_to(sigma_m, 3)])


def _write_jacobians(jacobians, w: np.ndarray, blocks: tuple) -> None:
    """Fill Ceres' ``jacobians`` of a 6-residual cost (rotation error, then position error, weighted by ``w (6,)``)
    from per-block derivatives ``(x, d_rot, d_pos_rot, d_pos_t)``: ``x`` the parameter block (a quaternion (4), a
    translation (3) or a pose (7) that is both), ``d_rot`` and ``d_pos_rot`` the rotation and position errors'
    3 x 3 derivatives by the block's rotation increment (its quaternion's by ``2 P^T``, :func:`_quat_plus_jacobian`),
    ``d_pos_t`` the position error's by its translation; None where the block has no such part."""
    for jac, (x, d_rot, d_pos_rot, d_pos_t) in zip(jacobians, blocks):
        if jac is None:
            continue
        j = np.zeros((6, len(x)))
        if d_rot is not None:  # a quaternion, alone (4) or at the head of a pose (7)
            p_t = 2.0 * _quat_plus_jacobian(x[:4]).T
            j[:3, :4] = d_rot @ p_t
            j[3:, :4] = d_pos_rot @ p_t
        if d_pos_t is not None:  # a translation, alone (3) or at the tail of a pose (7)
            j[3:, len(x) - 3:] = d_pos_t
        jac[:] = (w[:, None] * j).ravel()


@cache
def _cost_classes() -> tuple[type, type, type, type, type]:
    """The Python cost functions of the mounting calibration and the GNSS strip offsets (classes made on first use:
    pyceres loads lazily)."""
    import pyceres

    class NavPrior(pyceres.CostFunction):
        """EO prior of an image: blocks ``cam_from_world`` (7: quaternion x y z w, translation); with ``mounted``
        its camera's mounting correction, quaternion (4) and translation (3); with ``strip`` its strip's GNSS frame
        (7, a pose held at the identity rotation: its translation ``a`` is the strip's offset) and, with ``along``
        (the image's along-track position, km) not None, the strip's drift (3, per km).
        6 residuals, the rotation error ``log(R_prior^T R_M^T R)`` (world axes) and the centre error
        ``-R^T (t - t_M) - (C_prior - a - along b)`` (the GNSS positions are the centres plus the
        strip's error), each divided by its prior standard deviation (world axes) over ``sigma_px``. The Jacobians
        take ``d log(A exp(x)) / dx = I`` (the errors are a few thousandths of a degree)."""

        def __init__(self, r_prior: np.ndarray, c_prior: np.ndarray, w: np.ndarray, mounted: bool = True,
                     strip: bool = False, along: float | None = None) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(6)
            self.set_parameter_block_sizes([7] + [4, 3] * mounted + [7] * strip + [3] * (along is not None))
            self.r_prior, self.c_prior, self.w = r_prior, c_prior, w
            self.mounted, self.strip, self.along = mounted, strip, along

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            pose, rest = parameters[0], list(parameters[1:])
            r = _matrix_from_quat(pose[:4])
            rt = r.T
            rm, tm = np.eye(3), np.zeros(3)
            blocks = []
            if self.mounted:
                qm, tm = rest.pop(0), rest.pop(0)
                rm = _matrix_from_quat(qm)
            u = pose[4:] - tm
            c_prior = self.c_prior
            blocks.append((pose, rt, -rt @ skew(u), -rt))
            if self.mounted:
                blocks += [(qm, -rt, np.zeros((3, 3)), None), (tm, None, None, rt)]
            if self.strip:
                a = rest.pop(0)
                c_prior = c_prior - a[4:]
                blocks.append((a, None, None, np.eye(3)))
            if self.along is not None:
                b = rest.pop(0)
                c_prior = c_prior - self.along * b
                blocks.append((b, None, None, self.along * np.eye(3)))
            residuals[:3] = self.w[:3] * matrix_to_rotvec(self.r_prior.T @ rm.T @ r)
            residuals[3:] = self.w[3:] * (-rt @ u - c_prior)
            if jacobians is not None:
                _write_jacobians(jacobians, self.w, tuple(blocks))
            return True

    class OffsetPrior(pyceres.CostFunction):
        """Prior of zero on a GNSS strip offset or drift: a block of ``size`` (7: a strip frame, its translation;
        3: a drift); residuals its last 3 values divided by their standard deviation over ``sigma_px``."""

        def __init__(self, w: float, size: int) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(3)
            self.set_parameter_block_sizes([size])
            self.w = w
            self.jac = np.zeros((3, size))
            self.jac[:, size - 3:] = w * np.eye(3)

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            residuals[:] = self.w * parameters[0][-3:]
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = self.jac.ravel()
            return True

    class SchurAnchor(pyceres.CostFunction):
        """Two zero rows on a point and a strip's blocks (frame 7, drift 3): no information, only an edge in Ceres'
        graph of the parameter blocks. Ceres eliminates (Schur) a maximal independent set of blocks, the points
        first; a strip's blocks touch only images, so they would join the points, and the eliminator, sized for
        2-row residuals on 3-vector points, falls back to dynamic sizes for the whole problem (a 400-image block's
        linear solves took twice as long). Bound to a point, they stay with the images."""

        def __init__(self, sizes: list[int]) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([3, *sizes])

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            residuals[:] = 0.0
            for jac in jacobians or []:
                if jac is not None:
                    jac[:] = 0.0
            return True

    class MountingPrior(pyceres.CostFunction):
        """Prior of zero on a mounting correction: blocks its quaternion (4) and translation (3); residuals its
        rotation vector and translation divided by their standard deviations over ``sigma_px``."""

        def __init__(self, w: np.ndarray) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(6)
            self.set_parameter_block_sizes([4, 3])
            self.w = w

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            qm, tm = parameters
            residuals[:3] = self.w[:3] * matrix_to_rotvec(_matrix_from_quat(qm))
            residuals[3:] = self.w[3:] * tm
            if jacobians is not None:
                _write_jacobians(jacobians, self.w, ((qm, np.eye(3), np.zeros((3, 3)), None),
                                                     (tm, None, None, np.eye(3))))
            return True

    class MountedRelativePrior(pyceres.CostFunction):
        """Rig constraint through the mounting corrections: the relative pose ``F_i F_j^-1`` of the frames
        ``F = M^-1 cam_from_world`` of two heads of one exposure against the rig's ``i_from_j`` (rotation ``n_r``,
        translation ``n_t``). Blocks: both images' ``cam_from_world`` (7 each), then quaternion (4) and translation
        (3) of the correction of ``i``, then of ``j``; residuals ``log(R_ij n_r^T)`` and ``t_ij - n_t`` divided by
        their standard deviations over ``sigma_px``; Jacobians as in :class:`MountedPrior`."""

        def __init__(self, n_r: np.ndarray, n_t: np.ndarray, w: np.ndarray) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(6)
            self.set_parameter_block_sizes([7, 7, 4, 3, 4, 3])
            self.n_r, self.n_t, self.w = n_r, n_t, w

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            pi, pj, qi, ti, qj, tj = parameters
            rmi_t = _matrix_from_quat(qi).T
            g = _matrix_from_quat(pi[:4]) @ _matrix_from_quat(pj[:4]).T
            a, b = pi[4:] - ti, pj[4:] - tj
            rmj = _matrix_from_quat(qj)
            residuals[:3] = self.w[:3] * matrix_to_rotvec(rmi_t @ g @ rmj @ self.n_r.T)
            residuals[3:] = self.w[3:] * (rmi_t @ (a - g @ b) - self.n_t)
            if jacobians is not None:
                _write_jacobians(jacobians, self.w, (
                    (pi, rmi_t, rmi_t @ skew(g @ b), rmi_t),
                    (pj, -rmi_t @ g, -rmi_t @ g @ skew(b), -rmi_t @ g),
                    (qi, -rmi_t, rmi_t @ skew(a - g @ b), None),
                    (ti, None, None, -rmi_t),
                    (qj, rmi_t @ g, np.zeros((3, 3)), None),
                    (tj, None, None, rmi_t @ g)))
            return True

    return NavPrior, MountingPrior, MountedRelativePrior, OffsetPrior, SchurAnchor


def _prior_rows(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The whitening ``L (3, 3)`` of a ground observation with covariance ``cov (3, 3)`` (``L^T L = cov^-1``,
    upper triangular) as two ``(2, 3)`` row pairs: rows 0-1, then row 2 over a zero row. Two residual blocks of two
    rows each carry the observation's full weight and keep every residual block on a point two rows high, so that
    Ceres runs its Schur eliminator specialised for 2-row blocks on 3-vector points (a 3-row block anywhere makes
    it fall back to dynamic sizes for the whole problem)."""
    w = np.linalg.cholesky(np.linalg.inv(cov)).T
    return w[:2].copy(), np.vstack([w[2], np.zeros(3)])


@cache
def _point_prior_class() -> type:
    """The Python cost of a ground observation on a point (made on first use: pyceres loads lazily)."""
    import pyceres

    class PointPrior(pyceres.CostFunction):
        """Two whitened rows ``A (2, 3)`` of a ground observation ``x_prior`` of a point: blocks the point (3) and,
        with ``shifted``, the datum shift (3) added to it; residuals ``A (x + shift - x_prior)``."""

        def __init__(self, a: np.ndarray, x_prior: np.ndarray, shifted: bool) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([3, 3] if shifted else [3])
            self.a, self.x_prior = a, np.asarray(x_prior, dtype=np.float64)

        def Evaluate(self, parameters, residuals, jacobians) -> bool:  # noqa: N802 - pyceres' name
            d = parameters[0] - self.x_prior
            if len(parameters) > 1:
                d = d + parameters[1]
            residuals[:] = self.a @ d
            if jacobians is not None:
                for jac in jacobians:
                    if jac is not None:
                        jac[:] = self.a.ravel()
            return True

    return PointPrior


def _scratch_dir() -> str | None:
    """A folder in memory for short-lived files where there is one (``/dev/shm``), else the system's default."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def write_colmap_model(folder: Path, prob: BundleProblem, poses: list, by_image: np.ndarray, starts: np.ndarray,
                       p2d: np.ndarray, point_ids: np.ndarray, xyz_local: np.ndarray, by_point: np.ndarray) -> None:
    """Write the tie points of ``prob`` as a COLMAP binary model (pycolmap 4.2: ``cameras.bin``, ``rigs.bin``,
    ``frames.bin``, ``images.bin``, ``points3D.bin``, little-endian) for pycolmap to read in C++: building it
    through the Python API cost one call per track element (0.5-0.8 s for 500 k observations against 0.2 s).

    Camera ``k + 1`` (FULL_OPENCV) with a trivial rig ``k + 1`` per camera model ``k``; image and frame ``k + 1``
    per image ``k`` with ``poses[k]`` (``pycolmap.Rigid3d`` cam_from_world); ``by_image (q,)`` the observations
    held, sorted by image, ``starts (n + 1,)`` each image's first one in it (its keypoints in that order, at
    ``obs_uv + 0.5``); ``p2d (m,)`` each observation's keypoint index; ``point_ids (p,)`` point ids (-1: none, the
    others 1.. in point order) with ``xyz_local (k, 3)`` their coordinates; ``by_point (q,)`` the observations held,
    sorted by point (the track elements)."""
    n, n_cam = prob.n_images, len(prob.cameras)
    cam = np.zeros(n_cam, [("id", "<u4"), ("model", "<i4"), ("w", "<u8"), ("h", "<u8"), ("params", "<f8", 12)])
    cam["id"] = np.arange(1, n_cam + 1)
    cam["model"] = 6  # FULL_OPENCV
    cam["w"] = [c.width for c in prob.cameras]
    cam["h"] = [c.height for c in prob.cameras]
    cam["params"] = [_colmap_params(c) for c in prob.cameras]
    # a rig per camera: its id, one sensor (the reference: type camera = 0, the camera's id)
    rig = np.zeros(n_cam, [("id", "<u4"), ("sensors", "<u4"), ("type", "<i4"), ("sensor", "<u4")])
    rig["id"] = rig["sensor"] = cam["id"]
    rig["sensors"] = 1
    quat = np.array([p.rotation.quat for p in poses]).reshape(n, 4)  # x y z w
    pose = np.zeros(n, [("q", "<f8", 4), ("t", "<f8", 3)])
    pose["q"] = quat[:, [3, 0, 1, 2]]  # stored w x y z
    pose["t"] = np.array([p.translation for p in poses]).reshape(n, 3)
    frame = np.zeros(n, [("id", "<u4"), ("rig", "<u4"), ("pose", pose.dtype), ("data", "<u4"), ("type", "<i4"),
                         ("sensor", "<u4"), ("image", "<u8")])
    frame["id"] = frame["image"] = np.arange(1, n + 1)
    frame["rig"] = frame["sensor"] = prob.image_camera + 1
    frame["pose"] = pose
    frame["data"] = 1
    for name, table in (("cameras.bin", cam), ("rigs.bin", rig), ("frames.bin", frame)):
        (folder / name).write_bytes(np.uint64(len(table)).tobytes() + table.tobytes())
    # images: id, pose, camera id, name + NUL, keypoint count, keypoints (x, y, point id; -1 for none)
    head = np.zeros(n, [("id", "<u4"), ("pose", pose.dtype), ("camera", "<u4")])
    head["id"] = frame["id"]
    head["pose"] = pose
    head["camera"] = prob.image_camera + 1
    kp = np.zeros(len(by_image), [("xy", "<f8", 2), ("point", "<i8")])
    kp["xy"] = prob.obs_uv[by_image] + 0.5
    kp["point"] = point_ids[prob.obs_point[by_image]]
    parts = [np.uint64(n).tobytes()]
    for k in range(n):
        parts += [head[k].tobytes(), prob.image_ids[k].encode() + b"\0", np.uint64(starts[k + 1] - starts[k]).tobytes(),
                  kp[starts[k]:starts[k + 1]].tobytes()]
    (folder / "images.bin").write_bytes(b"".join(parts))
    # points: id, xyz, colour, error, track length, then (image id, keypoint index) per element; the records
    # differ in length, so both kinds are scattered into one byte buffer at their offsets
    pts = np.flatnonzero(point_ids >= 0)
    length = np.bincount(prob.obs_point[by_point], minlength=prob.n_points)[pts]
    ph = np.zeros(len(pts), [("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("length", "<u8")])
    ph["id"] = point_ids[pts]
    ph["xyz"] = xyz_local
    ph["error"] = -1.0
    ph["length"] = length
    el = np.zeros(len(by_point), [("image", "<u4"), ("p2d", "<u4")])
    el["image"] = prob.obs_image[by_point] + 1
    el["p2d"] = p2d[by_point]
    hs, es = ph.dtype.itemsize, el.dtype.itemsize
    before = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)  # elements before each point
    offset = 8 + np.arange(len(pts)) * hs + before * es
    buf = np.empty(8 + len(pts) * hs + len(el) * es, np.uint8)
    buf[:8] = np.frombuffer(np.uint64(len(pts)).tobytes(), np.uint8)
    buf[(offset[:, None] + np.arange(hs)).ravel()] = ph.view(np.uint8)
    e_off = np.repeat(offset + hs - before * es, length) + np.arange(len(el)) * es
    buf[(e_off[:, None] + np.arange(es)).ravel()] = el.view(np.uint8)
    (folder / "points3D.bin").write_bytes(buf.tobytes())


class _Model:
    """The tie points as a pycolmap reconstruction, built once per adjustment and kept across the rejection
    rounds: its poses, points and cameras hold the current estimates (Ceres solves them in place) and the
    observations that leave the solution are deleted from it, so a round only rebuilds the Ceres problem (in
    C++) and the small extra costs, never the per-observation Python objects.

    The images and points start from ``start = (r (n, 3, 3), c (n, 3), xyz (p, 3))``, by default the problem's
    start values. Tracks with at least two active observations are pycolmap points; ``in_rec (m,)`` marks the
    observations they hold and ``point_ids (p,)`` their ids (-1 for points not in the reconstruction)."""

    def __init__(self, prob: BundleProblem, ref: np.ndarray, active: np.ndarray,
                 start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, mounting: bool = False,
                 gnss_strips: str = "off") -> None:
        import pycolmap

        self.prob = prob
        r0, c0, xyz0 = (prob.r_cam_from_world, prob.c_world, prob.xyz) if start is None else start
        counts = np.bincount(prob.obs_point[active], minlength=prob.n_points)
        self.in_rec = active & (counts >= 2)[prob.obs_point]
        idx = np.flatnonzero(self.in_rec)
        # the observations in the reconstruction by image (keypoint index = rank within the image) and by point
        by_image = idx[np.argsort(prob.obs_image[idx], kind="stable")]
        starts = np.searchsorted(prob.obs_image[by_image], np.arange(prob.n_images + 1))
        self.p2d = np.full(len(prob.obs_point), -1, np.int64)
        self.p2d[by_image] = np.arange(len(by_image)) - np.repeat(starts[:-1], np.diff(starts))
        # observations of every point (all of them, in or out of the reconstruction)
        self.obs_order = np.argsort(prob.obs_point, kind="stable")
        self.obs_starts = np.searchsorted(prob.obs_point[self.obs_order], np.arange(prob.n_points + 1))
        self.track_len = np.where(counts >= 2, counts, 0)
        pts = np.flatnonzero(counts >= 2)
        self.point_ids = np.full(prob.n_points, -1, np.int64)
        self.point_ids[pts] = np.arange(1, len(pts) + 1)
        poses = [_rigid(r0[k], c0[k] - ref) for k in range(prob.n_images)]
        with tempfile.TemporaryDirectory(dir=_scratch_dir()) as tmp:
            write_colmap_model(Path(tmp), prob, poses, by_image, starts, self.p2d, self.point_ids, xyz0[pts] - ref,
                               self.obs_order[self.in_rec[self.obs_order]])
            self.rec = rec = pycolmap.Reconstruction()
            rec.read_binary(tmp)
        if rec.num_images() != prob.n_images or rec.num_points3D() != len(pts):
            raise ComputationError(f"pycolmap read {rec.num_images()} images and {rec.num_points3D()} points of the "
                                   f"{prob.n_images} and {len(pts)} written (binary model format changed?)")
        # point -> view of its coordinates in the reconstruction (stable until deleted)
        self.xyz_views = {p: rec.point3D(pid).xyz for p, pid in zip(pts.tolist(), range(1, len(pts) + 1))}
        self.frame_params = [rec.frame(rec.image(k + 1).frame_id).rig_from_world.params
                             for k in range(prob.n_images)]
        self.cam_params = {ci: rec.camera(ci + 1).params for ci in range(len(prob.cameras))}
        # per camera its mounting correction (quaternion x y z w, translation), kept across the rounds
        self.mount = ({ci: (np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3)) for ci in range(len(prob.cameras))}
                      if mounting else {})
        self.mount_used: set[int] = set()
        # per strip its GNSS frame (a pose of identity rotation whose translation is the offset) and drift (None for
        # offsets alone), kept across the rounds
        strips = np.unique(prob.prior_strip[prob.prior_strip >= 0]) if gnss_strips != "off" else []
        self.strip_blocks = {int(st): (np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
                                       np.zeros(3) if gnss_strips == "drift" else None) for st in strips}
        self.strip_used: set[int] = set()

    def keep_only(self, active: np.ndarray) -> None:
        """Delete the observations not in ``active (m,)`` from the reconstruction; a point left with fewer than
        two observations is deleted."""
        prob, rec = self.prob, self.rec
        for s in np.flatnonzero(self.in_rec & ~active):
            if not self.in_rec[s]:
                continue
            p = int(prob.obs_point[s])
            if self.track_len[p] > 2:
                rec.delete_observation(int(prob.obs_image[s]) + 1, int(self.p2d[s]))
                self.track_len[p] -= 1
                self.in_rec[s] = False
            else:
                rec.delete_point3D(int(self.point_ids[p]))
                self.point_ids[p] = -1
                del self.xyz_views[p]
                self.track_len[p] = 0
                self.in_rec[self.obs_order[self.obs_starts[p]:self.obs_starts[p + 1]]] = False

    def read(self, ref: np.ndarray, r: np.ndarray, c: np.ndarray, xyz: np.ndarray, cam_params: np.ndarray) -> None:
        """Copy the current estimates into ``r (n, 3, 3)``, ``c (n, 3)``, ``xyz (p, 3)`` (points in the
        reconstruction only) and ``cam_params (k, 12)``, world frame (``ref`` added back)."""
        for k, fp in enumerate(self.frame_params):
            r[k] = _matrix_from_quat(fp[:4])
            c[k] = -r[k].T @ fp[4:] + ref
        if self.xyz_views:
            xyz[list(self.xyz_views)] = np.array(list(self.xyz_views.values())) + ref
        for ci, p in self.cam_params.items():
            cam_params[ci] = p

    def strip_offsets(self) -> np.ndarray:
        """The GNSS strip offsets ``(n, 3)`` of the last round at each image (offset plus drift times its
        along-track position: the error of its GNSS position; zero for images without one)."""
        prob = self.prob
        if not len(prob.prior_strip):  # a problem without strips
            return np.zeros((prob.n_images, 3))
        return offsets_at(self.strips(), prob.prior_strip, prob.prior_along)

    def strips(self) -> np.ndarray:
        """The GNSS strip offsets and drifts ``(s, 6)`` of the last round as in :class:`BundleResult`."""
        out = np.full((len(self.prob.strip_names), 6), np.nan)
        for st in self.strip_used:
            frame, drift = self.strip_blocks[st]
            out[st, :3] = frame[4:]
            if drift is not None:
                out[st, 3:] = drift
        return out

    def mounting(self) -> np.ndarray:
        """The mounting corrections ``(k, 6)`` of the last round as in :class:`BundleResult`."""
        out = np.full((len(self.prob.cameras), 6), np.nan)
        for ci in self.mount_used:
            q, t = self.mount[ci]
            rm = _matrix_from_quat(q)
            out[ci] = [*matrix_to_rotvec(rm), *(-rm.T @ t)]
        return out


class _Round:
    """One Ceres problem over the model's current state: pycolmap's reprojection costs (Cauchy loss in the
    robust round) plus the priors, connection points, single-ray connection points and control points."""

    def __init__(self, model: _Model, opt: BundleOptions, ref: np.ndarray, xyz: np.ndarray, gcp_xyz: np.ndarray,
                 shift: np.ndarray, active: np.ndarray, robust: bool, gcp_obs_ok: np.ndarray,
                 prior_off: np.ndarray, prior_frac: np.ndarray) -> None:
        import pyceres
        import pycolmap
        import pycolmap.cost_functions as cf

        prob, rec = model.prob, model.rec
        sp = opt.sigma_px
        has_prior_pt = np.zeros(prob.n_points, bool)
        if prob.point_prior_xyz is not None:
            has_prior_pt = np.isfinite(prob.point_prior_xyz[:, 0])
        counts = np.bincount(prob.obs_point[active], minlength=prob.n_points)
        # single-ray points with a ground observation (connection points) are added beside pycolmap's tracks
        single = has_prior_pt & (counts == 1)
        single_obs = np.flatnonzero(single[prob.obs_point] & active)
        s_op, s_oi, s_uv = prob.obs_point[single_obs], prob.obs_image[single_obs], prob.obs_uv[single_obs]
        self.point_used = (model.point_ids >= 0) | single
        image_has_obs = np.bincount(prob.obs_image[model.in_rec], minlength=prob.n_images) > 0

        options = pycolmap.BundleAdjustmentOptions()
        options.refine_focal_length = False
        options.refine_principal_point = False
        options.refine_extra_params = False
        options.print_summary = False
        if robust:
            options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
            options.ceres.loss_function_scale = opt.robust_scale * sp
        config = pycolmap.BundleAdjustmentConfig()
        for k in np.flatnonzero(image_has_obs):
            config.add_image(int(k) + 1)
        self.ba = pycolmap.create_default_ceres_bundle_adjuster(options, config, rec)
        problem = self.problem = self.ba.problem
        self.frame_params = {}
        self.adjusted = np.zeros(prob.n_images, bool)
        for k, fp in enumerate(model.frame_params):
            if problem.has_parameter_block(fp):
                self.frame_params[k] = fp
                self.adjusted[k] = True
        # self-calibration on the camera blocks
        cam_params = model.cam_params
        free = sorted({i for g in opt.self_calibration for i in CALIBRATION_GROUPS[g]})
        if free:
            const = [i for i in range(12) if i not in free]
            for p in cam_params.values():
                if problem.has_parameter_block(p):
                    problem.set_parameter_block_variable(p)
                    problem.set_manifold(p, pyceres.SubsetManifold(12, const))
        # 6-DoF EO priors, through the cameras' mounting corrections when they are estimated
        self.costs = []  # the Python cost functions Ceres calls (kept alive with the problem)
        classes = _cost_classes() if model.mount or model.strip_blocks else (None,) * 5
        nav_prior, self._mounting_prior, mounted_relative, self._offset_prior, self._anchor = classes
        # the point that keeps the strips' blocks out of Ceres' elimination (see SchurAnchor): one of fewest rays
        self._anchor_point = None
        if model.strip_blocks and model.xyz_views:
            in_rec = np.flatnonzero(model.point_ids >= 0)
            self._anchor_point = model.xyz_views[int(in_rec[np.argmin(model.track_len[in_rec])])]
        model.mount_used = set()
        model.strip_used = set()
        # a part (attitude, position) a prior test rejected (prior_off) adds no information: the mounted cost gets
        # zero weights and the attitude-only prior an unbounded position variance, their rows counted as padding
        self.padded_rows = 0  # zero rows that pad costs (the priors' blocks, rejected parts; out of the redundancy)
        for k, fp in self.frame_params.items():
            if prior_off[k].all():
                continue
            # a head's share of its exposure's GNSS/IMU measurement: its sigmas over sqrt(share)
            s_att, s_pos = prob.prior_sigma_att[k], prob.prior_sigma_pos[k]
            if not (np.all(np.isfinite(s_att)) and np.all(np.isfinite(s_pos))):
                continue
            s_att, s_pos = s_att / np.sqrt(prior_frac[k, 0]), s_pos / np.sqrt(prior_frac[k, 1])
            rp = prob.prior_r[k]
            st = int(prob.prior_strip[k]) if model.strip_blocks and not prior_off[k, 1] else -1
            if model.mount or (st >= 0 and opt.gnss_strips == "drift"):
                blocks = [fp]
                if model.mount:
                    blocks += self._mount_blocks(problem, model, int(prob.image_camera[k]), opt)
                along = None
                if st >= 0:
                    frame, drift = self._strip_blocks(problem, model, st, opt)
                    blocks.append(frame)
                    if drift is not None:
                        blocks.append(drift)
                        along = float(prob.prior_along[k])
                w = _pose_weights(sp, s_att, s_pos) * np.repeat(~prior_off[k], 3)
                self.costs.append(nav_prior(rp, prob.prior_c[k] - ref, w, bool(model.mount), st >= 0, along))
                problem.add_residual_block(self.costs[-1], None, blocks)
                self.padded_rows += 3 * int(prior_off[k].sum())
                continue
            if prior_off[k, 0] and st < 0:  # the position alone (world frame)
                cost = cf.AbsolutePosePositionPriorCost(np.diag(s_pos**2) / sp**2, prob.prior_c[k] - ref)
                problem.add_residual_block(cost, None, [fp])
                continue
            # pycolmap's pose priors (C++): the absolute one, or with a strip offset the relative one to the strip's
            # frame (the GNSS position is the centre in that frame); a rejected part gets an unbounded variance
            cov = np.zeros((6, 6))
            cov[:3, :3] = rp @ np.diag(s_att**2) @ rp.T if not prior_off[k, 0] else np.eye(3) * UNBOUNDED_VARIANCE
            cov[3:, 3:] = rp @ np.diag(s_pos**2) @ rp.T if not prior_off[k, 1] else np.eye(3) * UNBOUNDED_VARIANCE
            prior = _rigid(rp, prob.prior_c[k] - ref)
            if st >= 0:
                frame, _ = self._strip_blocks(problem, model, st, opt)
                problem.add_residual_block(cf.RelativePosePriorCost(cov / sp**2, prior), None, [fp, frame])
            else:
                problem.add_residual_block(cf.AbsolutePosePriorCost(cov / sp**2, prior), None, [fp])
            self.padded_rows += 3 * int(prior_off[k].sum())
        # rig constraints: relative pose priors between the heads of one exposure
        if opt.rig and len(prob.rig_pairs):
            cov = np.diag([np.radians(opt.rig_sigma_deg) ** 2] * 3 + [opt.rig_sigma_m**2] * 3) / sp**2
            w = _pose_weights(sp, np.radians(opt.rig_sigma_deg), opt.rig_sigma_m)
            for (i, j), rr, tt in zip(prob.rig_pairs, prob.rig_r, prob.rig_t):
                if int(i) not in self.frame_params or int(j) not in self.frame_params:
                    continue
                if model.mount:  # the frames' relative pose, each image's correction removed
                    ci, cj = int(prob.image_camera[i]), int(prob.image_camera[j])
                    if ci == cj:
                        raise ComputationError(f"images {prob.image_ids[i]} and {prob.image_ids[j]} of one exposure "
                                               "share a camera model: the mounting calibration needs one per head")
                    self.costs.append(mounted_relative(rr, tt, w))
                    problem.add_residual_block(self.costs[-1], None, [
                        self.frame_params[int(i)], self.frame_params[int(j)],
                        *self._mount_blocks(problem, model, ci, opt), *self._mount_blocks(problem, model, cj, opt)])
                else:
                    prior = pycolmap.Rigid3d(pycolmap.Rotation3d(_quat_xyzw(rr)), tt)
                    problem.add_residual_block(cf.RelativePosePriorCost(cov, prior), None,
                                               [self.frame_params[int(i)], self.frame_params[int(j)]])
        # connection points: ground observations with their covariance, in 2-row blocks when they are few (see
        # PRIOR_SPLIT_SHARE), else pycolmap's 3-row alignment cost through an identity similarity held constant
        point_prior = _point_prior_class()
        self.sim_const = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
        conn_in_rec = np.flatnonzero(has_prior_pt & (model.point_ids >= 0))
        split = len(conn_in_rec) + len(single_obs) <= PRIOR_SPLIT_SHARE * int(model.in_rec.sum())

        def add_prior(x: np.ndarray, cov: np.ndarray, x_prior: np.ndarray, shift_block: np.ndarray | None) -> None:
            if shift_block is None and not split:
                problem.add_residual_block(cf.Point3DAlignmentCost(cov, x_prior), None, [x, self.sim_const])
                problem.set_parameter_block_constant(self.sim_const)
                return
            for rows in _prior_rows(cov):
                self.costs.append(point_prior(rows, x_prior, shift_block is not None))
                problem.add_residual_block(self.costs[-1], None, [x] if shift_block is None else [x, shift_block])
                self.padded_rows += int(not rows[1].any())

        self.point_views = []  # the parameter blocks Ceres holds pointers to (views into the reconstruction)
        for p in conn_in_rec:
            xv = model.xyz_views[p]
            self.point_views.append(xv)
            add_prior(xv, prob.point_prior_cov[p] / sp**2, prob.point_prior_xyz[p] - ref, None)
        cam_model = pycolmap.CameraModelId.FULL_OPENCV
        self.single_points = s_op
        self.single_x = np.array(xyz[s_op] - ref, dtype=np.float64).reshape(-1, 3)
        for j in range(len(s_op)):
            p, k = int(s_op[j]), int(s_oi[j])
            if k not in self.frame_params:
                continue
            cost = cf.ReprojErrorCost(cam_model, s_uv[j] + 0.5)
            problem.add_residual_block(cost, None, [self.single_x[j], self.frame_params[k],
                                                    cam_params[int(prob.image_camera[k])]])
            add_prior(self.single_x[j], prob.point_prior_cov[p] / sp**2, prob.point_prior_xyz[p] - ref, None)
        # control points: reprojection + ground observation through the datum shift (a 3D translation)
        self.shift = np.array(shift, dtype=np.float64)
        self.gcp_x = gcp_x = np.array(gcp_xyz - ref, dtype=np.float64)
        gcp_seen = np.zeros(len(gcp_x), bool)
        for k_obs in np.flatnonzero(gcp_obs_ok):
            g, k = int(prob.gcp_obs_point[k_obs]), int(prob.gcp_obs_image[k_obs])
            if k not in self.frame_params:
                continue
            s = prob.gcp_sigma_px[g] / sp
            cost = cf.ReprojErrorCost(cam_model, np.eye(2) * s**2, prob.gcp_obs_uv[k_obs] + 0.5)
            problem.add_residual_block(cost, None, [gcp_x[g], self.frame_params[k],
                                                    cam_params[int(prob.image_camera[k])]])
            gcp_seen[g] = True
        for g in np.flatnonzero(gcp_seen):
            add_prior(gcp_x[g], np.diag(prob.gcp_sigma[g] ** 2) / sp**2, prob.gcp_xyz[g] - ref, self.shift)
        if gcp_seen.any() and not opt.datum_shift:
            problem.set_parameter_block_constant(self.shift)
        self.gcp_seen = gcp_seen

    def _mount_blocks(self, problem, model: _Model, ci: int, opt: BundleOptions) -> list[np.ndarray]:
        """Camera ``ci``'s mounting correction (quaternion, translation) as parameter blocks of the problem, added
        with their prior of zero on first use."""
        import pyceres

        q, t = model.mount[ci]
        if ci not in model.mount_used:
            model.mount_used.add(ci)
            problem.add_parameter_block(q, 4)
            problem.set_manifold(q, pyceres.EigenQuaternionManifold())  # wrapped: the problem owns it
            problem.add_parameter_block(t, 3)
            w = _pose_weights(opt.sigma_px, np.radians(opt.mounting_sigma_deg), opt.mounting_sigma_m)
            self.costs.append(self._mounting_prior(w))
            problem.add_residual_block(self.costs[-1], None, [q, t])
        return [q, t]

    def _strip_blocks(self, problem, model: _Model, st: int, opt: BundleOptions
                      ) -> tuple[np.ndarray, np.ndarray | None]:
        """Strip ``st``'s GNSS frame and drift (None for offsets alone) as parameter blocks of the problem, added
        with their priors of zero and their :class:`SchurAnchor` on first use."""
        import pyceres

        frame, drift = model.strip_blocks[st]
        if st not in model.strip_used:
            model.strip_used.add(st)
            problem.add_parameter_block(frame, 7)
            problem.set_manifold(frame, pyceres.SubsetManifold(7, [0, 1, 2, 3]))  # the rotation held at identity
            blocks = [frame] if drift is None else [frame, drift]
            for x, sigma in zip(blocks, (opt.gnss_shift_sigma, opt.gnss_drift_sigma)):
                if len(x) == 3:
                    problem.add_parameter_block(x, 3)
                self.costs.append(self._offset_prior(opt.sigma_px / sigma, len(x)))
                problem.add_residual_block(self.costs[-1], None, [x])
            if self._anchor_point is not None:
                self.costs.append(self._anchor([len(x) for x in blocks]))
                problem.add_residual_block(self.costs[-1], None, [self._anchor_point, *blocks])
                self.padded_rows += 2
        return frame, drift

    def marginal(self, model: _Model, calibrated: dict[int, np.ndarray],
                 mount: dict[int, tuple[np.ndarray, np.ndarray]],
                 poses: bool) -> tuple[np.ndarray, np.ndarray | None, dict[tuple, np.ndarray], np.ndarray | None
                                       ] | None:
        """The marginal covariances (unit weight, tangent space) of the solved problem, by
        :func:`marginal_covariances`: the adjusted images ``(n,)``, with ``poses`` their poses' ``(n, 6, 6)`` (else
        None), the global parameters' (per camera of ``calibrated`` (camera -> its parameter block)
        ``("camera", ci)``, per mounting correction of ``mount`` ``("mount_q", ci)`` and ``("mount_t", ci)``, per
        strip ``("strip", st)`` and ``("drift", st)``, the datum shift ``("shift",)``), and with ``poses`` and an
        estimated datum shift the poses' covariances with it ``(n, 6, 3)`` (else None). None when the problem holds
        variable blocks this does not know (the count of blocks disagrees) or the reduced system is singular."""
        problem = self.problem

        def variable(b: np.ndarray) -> bool:
            return problem.has_parameter_block(b) and not problem.is_parameter_block_constant(b)

        images = [k for k, fp in self.frame_params.items() if variable(fp)]
        glob: dict[tuple, np.ndarray] = {("camera", ci): p for ci, p in calibrated.items()}
        for ci, (q, t) in mount.items():
            glob["mount_q", ci], glob["mount_t", ci] = q, t
        for st in sorted(model.strip_used):
            frame, drift = model.strip_blocks[st]
            glob["strip", st] = frame
            if drift is not None:
                glob["drift", st] = drift
        if variable(self.shift):
            glob["shift",] = self.shift
        points = [v for v in model.xyz_views.values() if variable(v)]
        points += [x for x in self.single_x if variable(x)]
        points += [self.gcp_x[g] for g in np.flatnonzero(self.gcp_seen) if variable(self.gcp_x[g])]
        held = [b for b in (*self.frame_params.values(), *model.cam_params.values(), self.sim_const, self.shift)
                if problem.has_parameter_block(b) and problem.is_parameter_block_constant(b)]
        if len(images) + len(glob) + len(points) + len(held) != problem.num_parameter_blocks():
            return None
        cross = list(glob).index(("shift",)) if ("shift",) in glob else None
        got = marginal_covariances(problem, [self.frame_params[k] for k in images], list(glob.values()), points,
                                   poses, cross)
        if got is None:
            return None
        return np.array(images, np.int64), got[0], dict(zip(glob, got[1])), got[2]

    def solve(self, opt: BundleOptions, kind: str, robust: bool):
        import pyceres

        so = pyceres.SolverOptions()
        solve_share = 0.0  # of the model decrease a step may miss (see model_settled): none for a factorisation
        if kind == "sparse_schur":
            so.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
        else:
            so.linear_solver_type = pyceres.LinearSolverType.ITERATIVE_SCHUR
            so.preconditioner_type = pyceres.PreconditionerType.SCHUR_JACOBI
            if kind == "explicit_schur":
                so.use_explicit_schur_complement = True
                so.eta = solve_share = opt.explicit_schur_eta
        so.num_threads = opt.threads
        so.max_num_iterations = opt.robust_max_iterations if robust else opt.max_iterations
        so.function_tolerance = opt.robust_function_tolerance if robust else opt.function_tolerance
        if not robust:
            so.initial_trust_region_radius = opt.ls_trust_region_radius
        so.gradient_tolerance = 1e-10
        so.parameter_tolerance = 1e-8
        stop = None
        if opt.settle_stop and not robust and kind != "iterative_schur":
            stop = _settle_stop_class()(opt.function_tolerance, solve_share, so.max_linear_solver_iterations)
            so.callbacks = [stop]
        summary = pyceres.SolverSummary()
        pyceres.solve(so, self.problem, summary)
        self.settled = stop is not None and stop.settled
        if not summary.IsSolutionUsable():
            raise ComputationError(f"bundle adjustment failed: {summary.message}")
        return summary


def model_settled(cost: float, cost_change: float, relative_decrease: float, function_tolerance: float,
                  solve_share: float) -> bool:
    """Whether a successful least-squares step, solved for the minimum of its quadratic (Gauss-Newton) model up
    to ``solve_share`` of the model's decrease, leaves no step that can lower ``cost`` (after the step) by more
    than ``function_tolerance`` of it. ``cost_change`` is the step's actual decrease, ``relative_decrease`` the
    actual over the model's.

    With F the cost, m the model and e = F - m, the step's end x1 and the minimum x* of F: F(x1) - F(x*) is at most
    |e(x1)| + |e(x*)| + ``solve_share`` times the model's decrease, since x1 minimises m up to that share. |e(x1)|
    is the measured gap between the actual and the model's decrease; x* lies within the next, tiny, step of x1, so
    e(x*) is taken as e(x1): the remaining decrease is at most twice the gap plus the solve's share."""
    if not (cost_change > 0.0 and relative_decrease > 0.0):
        return False
    predicted = cost_change / relative_decrease
    return 2.0 * abs(cost_change - predicted) + solve_share * predicted <= function_tolerance * cost


SETTLE_MIN_RADIUS = 1e8
"""The least trust region radius of a step the settle stop (:attr:`BundleOptions.settle_stop`) may end on. The bound of
:func:`model_settled` holds for the model's minimum, and a Levenberg-Marquardt step falls short of it in the
directions whose eigenvalue is small against the damping (``1 / radius`` of the normal matrix' diagonal): at Ceres'
default of 1e4 the first step of an 80-image oblique sub-block lowered the cost by 26.73 where the undamped one
lowered it by 27.30, with the model as exact (to about 1e-6) for both. At 1e8 the weakest directions of the simulated
sub-blocks (eigenvalues 1e-4 of the diagonal) are shortened by 1e-4, their share of the decrease by 1e-8."""


@cache
def _settle_stop_class() -> type:
    """The Ceres iteration callback of :attr:`BundleOptions.settle_stop` (a class made on first use: pyceres is
    imported late)."""
    import pyceres

    class SettleStop(pyceres.IterationCallback):
        """Ends the solve after a step :func:`model_settled` accepts, taken with a trust region radius of at least
        :data:`SETTLE_MIN_RADIUS` and, by conjugate gradients, in fewer than ``max_linear_iterations`` (else they
        stopped at the cap, short of ``solve_share``); ``settled`` tells whether it did."""

        def __init__(self, function_tolerance: float, solve_share: float, max_linear_iterations: int) -> None:
            super().__init__()
            self.function_tolerance, self.solve_share, self.settled = function_tolerance, solve_share, False
            self.max_linear_iterations = max_linear_iterations
            self.radius = 0.0  # the radius the next step is computed with (Ceres reports it after each iteration)

        def __call__(self, s) -> object:
            step_radius, self.radius = self.radius, s.trust_region_radius
            if (s.iteration >= 1 and s.step_is_successful and step_radius >= SETTLE_MIN_RADIUS
                    and s.linear_solver_iterations < self.max_linear_iterations and model_settled(
                        s.cost, s.cost_change, s.relative_decrease, self.function_tolerance, self.solve_share)):
                self.settled = True
                return pyceres.CallbackReturnType.SOLVER_TERMINATE_SUCCESSFULLY
            return pyceres.CallbackReturnType.SOLVER_CONTINUE

    return SettleStop


def camera_blocks(obs_point: np.ndarray, obs_image: np.ndarray, n_points: int, n_images: int,
                  sample_obs: int = 300_000) -> int:
    """Image pairs sharing a tie point (the non-zero off-diagonal 6x6 blocks of the reduced camera system), from
    every k-th track so that about ``sample_obs`` observations are looked at (a lower bound, close for pairs
    sharing many points). ``obs_point``, ``obs_image`` : (m,) int64."""
    import scipy.sparse as sps

    step = max(1, int(np.ceil(len(obs_point) / max(sample_obs, 1))))
    sel = obs_point % step == 0
    a = sps.csr_matrix((np.ones(int(sel.sum()), np.float32), (obs_point[sel], obs_image[sel])),
                       shape=(n_points, n_images))
    a.data[:] = 1.0
    return int((a.T @ a).nnz - n_images)


LINEAR_SOLVERS = ("auto", "sparse_schur", "iterative_schur", "explicit_schur")


def linear_solver_kind(prob: BundleProblem, opt: BundleOptions, active: np.ndarray) -> str:
    """``sparse_schur``, ``iterative_schur`` or ``explicit_schur`` for ``opt.linear_solver`` (see
    :class:`BundleOptions`)."""
    if opt.linear_solver not in LINEAR_SOLVERS:
        raise ComputationError(f"unknown linear solver '{opt.linear_solver}' (use {', '.join(LINEAR_SOLVERS)})")
    if opt.linear_solver != "auto":
        return opt.linear_solver
    blocks = camera_blocks(prob.obs_point[active], prob.obs_image[active], prob.n_points, prob.n_images)
    sparse = blocks <= opt.sparse_schur_max_blocks or blocks <= opt.sparse_schur_max_neighbours * prob.n_images
    sparse &= int(active.sum()) >= opt.sparse_schur_min_obs_per_image * prob.n_images
    if not sparse:
        return "iterative_schur"
    explicit = prob.n_images >= opt.explicit_schur_min_images and not opt.self_calibration and not opt.mounting
    return "explicit_schur" if explicit else "sparse_schur"


def adjust(prob: BundleProblem, opt: BundleOptions = BundleOptions(),
           progress: Callable[[int, int, str], None] | None = None,
           on_robust: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None,
           keep: list | None = None) -> BundleResult:
    """Adjust a bundle problem (see the module docstring). ``progress(done, total, message)`` is called per
    round and may raise to cancel. ``on_robust(r (n, 3, 3), c (n, 3), xyz (p, 3))`` receives the orientations
    and points of the robust round (control frame, copies; the orientations of the frames, see
    :func:`frame_poses`) as soon as it is solved, before its statistics (HAT starts its oblique runs from there
    while the nadir run goes on). ``keep``: the solver's last Ceres problem and reconstruction are appended to it
    instead of being freed before the return (millions of small C++ allocations: a quarter of a second for 500,000
    observations), so that the caller can hand the result on first and free them by clearing the list; the heap
    they free is then not handed back to the system (:func:`release_heap`), for the caller's next work. With
    ``opt.tie_sigma_estimate`` the adjustment is solved again with the tie measurements' estimated sigma while it
    differs from the one used by more than ``opt.tie_sigma_tolerance`` (see :class:`BundleOptions`); the result's
    ``sigma_px`` is the sigma of its solution."""
    res = _adjust_pass(prob, opt, progress, on_robust, keep)
    given = opt.sigma_px
    heads = measurement_heads(prob)
    estimates = opt.tie_sigma_estimate or opt.prior_sigma_estimate or opt.control_sigma_estimate
    for _ in range(opt.variance_passes if estimates else 0):
        f_obs = res.variance_components["ties"].factor
        ties_off = bool(np.isfinite(f_obs) and abs(f_obs - 1.0) > opt.tie_sigma_tolerance)
        f_ties = f_obs if ties_off and opt.tie_sigma_estimate else 1.0
        f_control = control_sigma_factor(res.variance_components, opt.tie_sigma_tolerance) \
            if opt.control_sigma_estimate else 1.0
        # the priors' components are taken once the ties' sigma is right: the ties hold most of the redundancy, and
        # with their sigma wrong the priors' residuals follow it (the ties given 1 px for 0.3, the IMU attitudes'
        # factor came out 0.70 on the simulated 400-image block of the tests, against 0.95 with the ties given 0.3):
        # scaled to it, the priors would be weighted wrongly against the ties by more
        f_prior = prior_sigma_factors(res.variance_components, opt.prior_sigma_tolerance, heads) \
            if opt.prior_sigma_estimate and not ties_off else np.ones(6)
        if ties_off and opt.prior_sigma_estimate and not opt.tie_sigma_estimate:
            res.log.append(f"GNSS/IMU prior sigmas not estimated: the tie measurements' variance factor is {f_obs:.3f} "
                           "and their sigma is held (BundleOptions.tie_sigma_estimate)")
        if f_ties == 1.0 and f_control == 1.0 and np.all(f_prior == 1.0):
            break
        # from this solution (GNSS frame, as the problem's start values) and its cameras (self-calibrated ones: the
        # screening holds them)
        shift = res.datum_shift
        start = replace(prob, r_cam_from_world=res.r_cam_from_world, c_world=res.c_world - shift,
                        xyz=np.where(np.isfinite(res.xyz[:, :1]), res.xyz - shift, prob.xyz), cameras=res.cameras)
        log, iterations, time_s, timing = res.log, res.iterations, res.time_s, res.timing
        if f_ties != 1.0:
            log.append(f"tie measurements: variance factor {f_ties:.3f}, their sigma re-estimated {res.sigma_px:.3f} "
                       f"-> {res.sigma_px * f_ties:.3f} px")
        if f_control != 1.0:
            log.append(f"control point measurements: variance factor {f_control:.3f}, their sigmas scaled by "
                       f"{res.control_sigma_scale * f_control:.3f} in all")
        scale = tuple(float(v) for v in res.prior_sigma_scale * f_prior)
        for k, part in enumerate(PRIOR_PART_LABELS):
            if f_prior[3 * k] != 1.0:
                log.append(f"{part} priors: variance factor {f_prior[3 * k]:.3f}, their sigmas scaled by "
                           f"{scale[3 * k]:.3f} in all")
        log.append("adjusted again from this solution, its blunders screened anew")
        # the solution is the closest start there is: blunders screened there (BundleOptions.screen_start), no robust
        # round (from a converged solution of the rendered demo's oblique runs, with a quarter of their measurements
        # wrong matches, the Cauchy round ran out of iterations far off and rejected correct control and priors)
        opt = replace(opt, sigma_px=res.sigma_px * f_ties, prior_sigma_scale=scale,
                      control_sigma_scale=res.control_sigma_scale * f_control, screen_start=True, screen_resect=False)
        del res  # (the previous solution's covariances and solver go before the next pass: peak memory)
        if keep is not None:
            keep.clear()
            release_heap()
        res = _adjust_pass(start, opt, None if progress is None else (
            lambda d, t, m, s=opt.sigma_px: progress(d, t, f"with the sigmas estimated (ties {s:.3f} px): {m}")), None,
            keep)
        res.log[:0] = log
        res.iterations += iterations
        res.time_s += time_s
        res.timing = {k: v + timing.get(k, 0.0) for k, v in res.timing.items()}
        # a calibration's values before the adjustment are the imported ones
        res.calibration = {ci: replace(cal, initial=_calibration_values(prob.cameras[ci], cal.params))
                           for ci, cal in res.calibration.items()}
    res.sigma_px_given = given
    return res


def significant_factor(comp: VarianceComponent | None, tolerance: float, heads: float = 1.0,
                       up_only: bool = False) -> float:
    """``comp``'s variance factor where it differs from 1 by more than ``tolerance`` (relative) and by more than 3 of
    its standard deviations (``sqrt(heads)`` times the component's: ``heads`` observations with one error, see
    :func:`measurement_heads`), above 1 only with ``up_only``; else 1 (and without a component)."""
    if comp is None or comp.redundancy <= 0:
        return 1.0
    f = comp.factor
    off = f - 1.0 if up_only else abs(f - 1.0)
    return f if np.isfinite(f) and off > max(tolerance, 3.0 * comp.factor_std * np.sqrt(heads)) else 1.0


def prior_sigma_factors(components: dict[str, VarianceComponent], tolerance: float, heads: float = 1.0
                        ) -> np.ndarray:
    """The factors ``(6,)`` by which the attitude (IMU, about world X Y Z) and position (GNSS, X Y Z) prior sigmas are
    to be scaled (see ``BundleOptions.prior_sigma_estimate``): a group's variance factor on its three axes where it
    exceeds 1 significantly (:func:`significant_factor`), else 1. ``heads``: the images that share one GNSS/IMU
    measurement (:func:`measurement_heads`): their errors are one, so the estimate's standard deviation is
    ``sqrt(heads)`` times the component's."""
    return np.repeat([significant_factor(components.get(key), tolerance, heads, up_only=True)
                      for key in ("imu", "gnss")], 3)


def control_sigma_factor(components: dict[str, VarianceComponent], tolerance: float) -> float:
    """The factor by which the control points' image measurement sigmas are to be scaled (see
    ``BundleOptions.control_sigma_estimate``): their variance factor where it differs from 1 significantly, either
    way (:func:`significant_factor`), else 1."""
    return significant_factor(components.get("control_measurements"), tolerance)


def measurement_heads(prob: BundleProblem) -> float:
    """The mean number of images of ``prob`` whose priors come from one GNSS/IMU measurement: the heads per exposure
    (1 without exposures). The variance components count each head's prior, with or without rig constraints (on the
    400-image test block the GNSS component's redundancy was 1,180 without and 1,200 with them, for 240 independent
    errors), so the heads scale the components' standard deviations."""
    exposure = prob.image_exposure[prob.image_exposure >= 0] if len(prob.image_exposure) else prob.image_exposure
    return len(exposure) / len(np.unique(exposure)) if len(exposure) else 1.0


def _adjust_pass(prob: BundleProblem, opt: BundleOptions, progress: Callable[[int, int, str], None] | None,
                 on_robust: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None,
                 keep: list | None = None) -> BundleResult:
    """One adjustment with ``opt.sigma_px``, ``opt.prior_sigma_scale`` and ``opt.control_sigma_scale`` (see
    :func:`adjust`)."""
    import pyceres

    t0 = time.perf_counter()
    for g in opt.self_calibration:
        if g not in CALIBRATION_GROUPS:
            raise ComputationError(f"unknown self-calibration group '{g}' (use {', '.join(CALIBRATION_GROUPS)})")
    if opt.gnss_strips not in GNSS_STRIP_MODES:
        raise ComputationError(f"unknown GNSS strip model '{opt.gnss_strips}' (use {', '.join(GNSS_STRIP_MODES)})")
    sigma_scale = np.asarray(opt.prior_sigma_scale, np.float64)
    if np.any(sigma_scale != 1.0):
        prob = replace(prob, prior_sigma_att=prob.prior_sigma_att * sigma_scale[:3],
                       prior_sigma_pos=prob.prior_sigma_pos * sigma_scale[3:])
    if opt.control_sigma_scale != 1.0:
        prob = replace(prob, gcp_sigma_px=prob.gcp_sigma_px * opt.control_sigma_scale)
    has_prior = np.all(np.isfinite(prob.prior_c), axis=1)
    ref = np.round(prob.prior_c[has_prior].mean(0) if has_prior.any() else prob.c_world.mean(0), 0)
    r = np.array(prob.r_cam_from_world, dtype=np.float64)
    c = np.array(prob.c_world, dtype=np.float64)
    xyz = np.array(prob.xyz, dtype=np.float64)
    cam_params = np.array([_colmap_params(cm) for cm in prob.cameras])
    gcp_xyz = np.array(prob.gcp_xyz, dtype=np.float64)
    shift = np.zeros(3)
    m = len(prob.obs_point)
    active = np.isfinite(xyz[prob.obs_point, 0]) & np.all(np.isfinite(prob.obs_uv), axis=1)
    rejected = np.zeros(m, bool)
    # control points: their measurements in use, their coordinates in use (a rejected point leaves with its
    # measurements), the largest normalised coordinate differences of the last test
    gcp_obs_ok = np.ones(len(prob.gcp_obs_point), bool)
    gcp_obs_bad = np.zeros(len(prob.gcp_obs_point), bool)
    gcp_ok = np.ones(len(prob.gcp_xyz), bool)
    gcp_w = np.full(len(prob.gcp_xyz), np.nan)
    # the last test's standard deviations of the differences and influences on the datum shift
    gcp_sd = np.full((len(prob.gcp_xyz), 3), np.nan)
    gcp_infl = np.full((len(prob.gcp_xyz), 3), np.nan)
    # EO priors: the parts (attitude, position) rejected, the largest normalised differences of the last test
    prior_ok = has_prior & np.all(np.isfinite(prob.prior_sigma_att), 1) & np.all(np.isfinite(prob.prior_sigma_pos), 1)
    prior_off = np.zeros((prob.n_images, 2), bool)
    prior_w = np.full((prob.n_images, 2), np.nan)
    prior_sd = np.full((prob.n_images, 6), np.nan)
    prior_share = np.full((prob.n_images, 6), np.nan)
    iterations = 0
    log: list[str] = []
    total_rounds = opt.max_rejection_rounds + 1
    timing = {"build_s": 0.0, "solve_s": 0.0, "statistics_s": 0.0, "preprocess_s": 0.0, "jacobian_s": 0.0,
              "linear_s": 0.0, "covariance_s": 0.0}
    clock = [time.perf_counter()]

    def lap(key: str) -> None:
        now = time.perf_counter()
        timing[key] += now - clock[0]
        clock[0] = now

    rnd = 0
    if opt.screen_start:
        # blunders tested at the start with the cameras held (no robust round), see BundleOptions.screen_start
        idx = np.flatnonzero(active)
        pt_prior = {}
        if prob.point_prior_xyz is not None:
            has = np.isfinite(prob.point_prior_xyz[:, 0])
            info = np.zeros((prob.n_points, 3, 3))
            info[has] = np.nan_to_num(precision.safe_inverse(prob.point_prior_cov[has]))
            pt_prior = {"prior_xyz": prob.point_prior_xyz, "prior_info": info}
        obs = (prob.obs_point[idx], prob.obs_image[idx], prob.obs_uv[idx])
        start, go = xyz, True
        if opt.screen_resect:
            # the images moved to their inliers first; the tests that decide run from there
            r, c, x1, s0_s = resected_start(prob.cameras, prob.image_camera, r, c, xyz, *obs, opt, **pt_prior)
            go = s0_s <= opt.screen_max_sigma0
            start = np.where(np.isfinite(x1[:, :1]), x1, xyz)
        if go:
            x_s, _, bad_s, s0_s = screen_points(prob.cameras, prob.image_camera, r, c, *obs, start, opt.sigma_px,
                                                None, opt.blunder_threshold, opt.screen_rounds,
                                                reject_undetermined=False, **pt_prior)
            # a start taken as resected already is tested once: too far from the solution, the robust round runs
            go = opt.screen_resect or s0_s <= opt.screen_max_sigma0
        if go:
            xyz = np.where(np.isfinite(x_s[:, :1]), x_s, start)
            rejected[idx[bad_s]] = True
            active &= ~rejected
            rnd = 1
            log.append(f"screening at the start: sigma0 {s0_s:.3f}, rejected {int(bad_s.sum())} observations")
        else:
            log.append(f"screening at the start: sigma0 {s0_s:.3f} above {opt.screen_max_sigma0}: robust round")
        lap("statistics_s")
    model = _Model(prob, ref, active, (r, c, xyz), mounting=opt.mounting,
                   gnss_strips=opt.gnss_strips if len(prob.prior_strip) else "off")
    solver = linear_solver_kind(prob, opt, active)
    log.append(f"linear solver {solver}")
    # the images sharing one GNSS/IMU measurement; without the rig, the exposures whose heads count it several times
    group = rig_groups(prob, opt)
    with_prior = prob.image_exposure[prior_ok & (prob.image_exposure >= 0)] if len(prob.image_exposure) else []
    multiple = int(np.sum(np.bincount(with_prior) > 1)) if not (opt.rig and len(prob.rig_pairs)) else 0
    if multiple:
        log.append(f"{multiple} exposures give several heads their GNSS/IMU priors, each counted in full without rig "
                   "constraints: the datum shift's standard deviations are too small by up to the square root of the "
                   "heads (see shared_prior_fraction)")
    while True:
        if progress is not None:
            progress(rnd, total_rounds, f"bundle adjustment round {rnd + 1}")
        model.keep_only(active)
        rd = None  # the previous round's Ceres problem goes before the next one is built (peak memory)
        prior_frac = shared_prior_fraction(group, prior_ok[:, None] & ~prior_off)
        rd = _Round(model, opt, ref, xyz, gcp_xyz, shift, active, robust=(rnd == 0), gcp_obs_ok=gcp_obs_ok,
                    prior_off=prior_off, prior_frac=prior_frac)
        lap("build_s")
        summary = rd.solve(opt, solver, robust=(rnd == 0))
        lap("solve_s")
        timing["preprocess_s"] += summary.preprocessor_time_in_seconds
        timing["jacobian_s"] += summary.jacobian_evaluation_time_in_seconds
        timing["linear_s"] += summary.linear_solver_time_in_seconds
        iterations += summary.num_successful_steps + summary.num_unsuccessful_steps
        # read back (local frame, before the datum shift)
        model.read(ref, r, c, xyz, cam_params)
        xyz[rd.single_points] = rd.single_x + ref
        gcp_xyz = np.where(rd.gcp_seen[:, None], rd.gcp_x + ref, gcp_xyz)
        shift = rd.shift.copy()
        if rnd == 0 and on_robust is not None:
            r_f, c_f = frame_poses(r, c, prob.image_camera, model.mounting())
            on_robust(r_f, c_f + shift, xyz + shift)
        point_used = rd.point_used
        active &= point_used[prob.obs_point]
        redundancy = int(summary.num_residuals_reduced - summary.num_effective_parameters_reduced
                         - rd.padded_rows)
        # the robust round's cost is the Cauchy one: its chi-square needs the plain residuals, evaluated (single-
        # threaded: the Python costs hold the interpreter) only when that round ends the adjustment; its tests take
        # the robust sigma0 below (0.4 s of the 3,000-image bench's nadir run, 1.9-2.0 s of its IAT)
        chi2 = sigma0 = None
        if rnd > 0:
            chi2 = 2.0 * summary.final_cost / opt.sigma_px**2
        elif opt.max_rejection_rounds == 0:
            eo = pyceres.EvaluateOptions()
            eo.apply_loss_function = False
            chi2 = float(np.sum(np.square(rd.problem.evaluate_residuals(eo)))) / opt.sigma_px**2
        if chi2 is not None:
            sigma0 = float(np.sqrt(chi2 / max(redundancy, 1)))
        # residuals, precision, normalised residuals
        cams = [_camera_from_params(cm, cam_params[i]) for i, cm in enumerate(prob.cameras)]
        uv_hat = project_obs(cams, prob.image_camera, r, c, xyz, prob.obs_point, prob.obs_image)
        v = prob.obs_uv - uv_hat
        q_point, q_image, red, n_ties = _precision(prob, opt, r, c, xyz, cams, active, prior_off, prior_frac)
        vv = np.sum(v**2, axis=1)
        t_unscaled = vv / (opt.sigma_px**2 * red)
        robust_s0 = robust_sigma0(t_unscaled[active])
        s0_test = robust_s0 if rnd == 0 else sigma0
        w = np.sqrt(t_unscaled) / max(s0_test, 1e-9)
        lap("statistics_s")
        s0_text = [f"sigma0 {sigma0:.3f} ({sigma0 * opt.sigma_px:.3f} px)"] if sigma0 is not None else []
        if rnd == 0:
            s0_text.append(f"robust sigma0 {robust_s0:.3f} ({robust_s0 * opt.sigma_px:.3f} px, from the median "
                           "normalised residual)")
        log.append(f"round {rnd}: {'cauchy' if rnd == 0 else 'least squares'}, "
                   f"{summary.num_successful_steps + summary.num_unsuccessful_steps} iterations, "
                   f"{', '.join(s0_text)}, {int(active.sum())} observations, "
                   f"Schur structure {summary.schur_structure_used}"
                   + (", ended by the settled model (see BundleOptions.settle_stop)" if rd.settled else ""))
        if rnd >= opt.max_rejection_rounds:
            break
        gcp_bad = False
        if opt.control_tests and len(prob.gcp_xyz):
            bad_go, bad_g, gcp_w, gcp_sd, gcp_infl = control_point_tests(
                cams, prob.image_camera, r, c, prob.gcp_xyz, prob.gcp_sigma, prob.gcp_sigma_px, prob.gcp_obs_point,
                prob.gcp_obs_image, prob.gcp_obs_uv, gcp_obs_ok & rd.adjusted[prob.gcp_obs_image], gcp_ok, shift,
                opt.datum_shift, opt.blunder_threshold)
            for k_obs in np.flatnonzero(bad_go):
                log.append(f"round {rnd}: control point {prob.gcp_names[prob.gcp_obs_point[k_obs]]}: measurement in "
                           f"{prob.image_ids[prob.gcp_obs_image[k_obs]]} rejected")
            for g in np.flatnonzero(bad_g):
                log.append(f"round {rnd}: control point {prob.gcp_names[g]}: coordinates rejected (normalised "
                           f"difference {gcp_w[g]:.1f} to the others' shift)")
            gcp_ok &= ~bad_g
            gcp_obs_bad |= bad_go
            gcp_obs_ok &= ~bad_go & gcp_ok[prob.gcp_obs_point]
            gcp_bad = bool(bad_go.any() or bad_g.any())
        prior_bad = False
        if opt.prior_tests and prior_ok.any():
            att_v, pos_v = _prior_residuals(prob, *frame_poses(r, c, prob.image_camera, model.mounting()),
                                            model.strip_offsets())
            bad_p, w_p, scale, sd_p, share_p = prior_tests(
                att_v, pos_v, prob.prior_sigma_att, prob.prior_sigma_pos, n_ties,
                prior_ok[:, None] & ~prior_off & rd.adjusted[:, None], opt.blunder_threshold, prior_frac, group)
            prior_w = np.where(prior_off, prior_w, w_p)
            prior_sd = np.where(np.repeat(prior_off, 3, axis=1), prior_sd, sd_p)
            prior_share = np.where(np.repeat(prior_off, 3, axis=1), prior_share, share_p)
            for part in np.flatnonzero(scale > PRIOR_SCALE_NOTE):
                log.append(f"round {rnd}: the {PRIOR_PART_LABELS[part]} priors differ from the tie "
                           f"points' orientations by {scale[part]:.1f} times their sigmas (robust): tested at that "
                           "scale; check their a priori sigmas")
            for k, part in zip(*np.nonzero(bad_p)):
                log.append(f"round {rnd}: {PRIOR_PART_LABELS[part]} prior of {prob.image_ids[k]} "
                           f"rejected (normalised difference {w_p[k, part]:.1f} to its tie points' orientation)")
            in_use_p = prior_ok[:, None] & ~prior_off & rd.adjusted[:, None]
            prior_off |= bad_p
            prior_bad = bool(bad_p.any())
        if rnd == 0:
            # the robust solution is not pulled by the blunders: reject every flagged observation at once
            bad = active & np.isfinite(w) & (w > opt.blunder_threshold)
        else:
            bad = worst_per_track(w, prob.obs_point, active, opt.blunder_threshold)
        bad |= active & ~np.isfinite(w)
        if bad.sum() > 0.5 * active.sum():
            raise ComputationError(
                f"bundle adjustment did not converge: round {rnd + 1} flags {int(bad.sum())} of "
                f"{int(active.sum())} observations (sigma0 {s0_test * opt.sigma_px:.2f} px); check the "
                "approximate orientations, the tie points and the a priori sigmas")
        if not bad.any() and rnd > 0 and not gcp_bad and not prior_bad:
            break
        removed = float(np.sum(vv[bad])) / opt.sigma_px**2
        # rejected EO prior parts: their images move by the step the prior's removal implies (prior_release), where
        # each image is a group of its own and the other parts keep their weight (no mounting, no strip frames), and
        # no covariance is taken from the Ceres problem afterwards (it still holds those priors)
        release = None
        if (prior_bad and rnd > 0 and not gcp_bad and not model.mount and not model.strip_blocks
                and not opt.self_calibration and int(rd.adjusted.sum()) > opt.marginal_max_images
                and np.all(np.bincount(group)[group[bad_p.any(1)]] == 1)):
            release = prior_release(att_v, pos_v, prob.prior_sigma_att, prob.prior_sigma_pos, n_ties, in_use_p,
                                    bad_p, prior_frac, group)
            if release is not None:
                removed += release[1]
        if (rnd > 0 and removed < opt.resolve_tolerance * chi2 and not gcp_bad
                and (not prior_bad or release is not None)):
            # negligible: reject without another solve, re-estimate only the points that lost an observation (and
            # those of the images whose prior left)
            rejected |= bad
            active &= ~bad
            touched = np.zeros(prob.n_points, bool)
            touched[prob.obs_point[bad]] = True
            if release is not None:
                moved = np.flatnonzero(np.any(release[0] != 0.0, axis=1))
                move_images(r, c, release[0], moved)
                touched[prob.obs_point[active & np.isin(prob.obs_image, moved)]] = True
                redundancy -= 3 * int(bad_p.sum())
            counts = np.bincount(prob.obs_point[active], minlength=prob.n_points)
            has_pt_prior = (np.isfinite(prob.point_prior_xyz[:, 0]) if prob.point_prior_xyz is not None
                            else np.zeros(prob.n_points, bool))
            point_used = point_used & ((counts >= 2) | (has_pt_prior & (counts == 1)))
            active &= point_used[prob.obs_point]
            xyz = refine_points(cams, prob.image_camera, r, c, xyz, prob.obs_point, prob.obs_image, prob.obs_uv,
                                active & touched[prob.obs_point])
            if release is not None:  # the precision of the moved images without the priors that left
                q_point, q_image, red, n_ties = _precision(prob, opt, r, c, xyz, cams, active, prior_off, prior_frac)
            chi2 -= removed
            redundancy -= 2 * int(bad.sum())
            sigma0 = float(np.sqrt(chi2 / max(redundancy, 1)))
            log.append(f"round {rnd}: rejected {int(bad.sum())} observations"
                       + (f" and {int(bad_p.sum())} EO prior parts (their images moved by the step their removal "
                          "implies)" if release is not None else "")
                       + f" ({removed / chi2:.1e} of chi-square: points re-estimated, no new solve), "
                         f"sigma0 {sigma0:.3f}")
            lap("statistics_s")
            break
        rejected |= bad
        active &= ~bad
        log.append(f"round {rnd}: rejected {int(bad.sum())} observations")
        rnd += 1
    adjusted = rd.adjusted
    image_std = np.sqrt(np.abs(np.diagonal(q_image, axis1=1, axis2=2))) * sigma0
    image_std_relative = image_std
    image_std_kind = "conditional"
    mounting_std = np.full((len(prob.cameras), 6), np.nan)
    # the cameras the run self-calibrated: their parameter blocks are variables of the problem
    calibrated = {ci: p for ci, p in model.cam_params.items()
                  if rd.problem.has_parameter_block(p) and not rd.problem.is_parameter_block_constant(p)}
    camera_cov: dict[int, np.ndarray] = {}
    mount = {ci: model.mount[ci] for ci in model.mount_used}
    shift_std = np.full(3, np.nan)
    want_poses = 0 < adjusted.sum() <= opt.marginal_max_images
    lap("statistics_s")
    if want_poses or ((calibrated or mount) and 0 < adjusted.sum() <= opt.calibration_max_images):
        t_cov = time.perf_counter()
        marg = rd.marginal(model, calibrated, mount, want_poses)
        if marg is None:
            log.append("marginal covariance: none (the reduced system is singular, or the problem holds parameters "
                       "the estimate does not know)")
        else:
            k_cov, pose_cov, glob, pose_shift = marg
            scale = (opt.sigma_px * sigma0) ** 2
            if pose_cov is not None:
                image_std[k_cov] = world_pose_std(pose_cov, r[k_cov], c[k_cov] - ref) * np.sqrt(scale)
                image_std_relative = image_std.copy()
                if ("shift",) in glob:
                    image_std[k_cov] = world_pose_std(pose_cov, r[k_cov], c[k_cov] - ref, glob["shift",],
                                                      pose_shift) * np.sqrt(scale)
                image_std_kind = "marginal"
            camera_cov = {key[1]: cov * scale for key, cov in glob.items() if key[0] == "camera"}
            if ("shift",) in glob:
                shift_std = np.sqrt(np.abs(np.diag(glob["shift",])) * scale)
            for ci, (q, _) in mount.items():
                rm = _matrix_from_quat(q)
                mounting_std[ci] = np.sqrt(np.concatenate([4.0 * np.abs(np.diag(glob["mount_q", ci])),
                                                           np.abs(np.diag(rm.T @ glob["mount_t", ci] @ rm))]) * scale)
            log.append(f"marginal covariance ({'images and ' if want_poses else ''}global parameters) in "
                       f"{time.perf_counter() - t_cov:.1f} s")
    lap("covariance_s")
    free = tuple(sorted({i for g in opt.self_calibration for i in CALIBRATION_GROUPS[g]}))
    calibration = {ci: Calibration(free, _calibration_values(prob.cameras[ci], free),
                                   _calibration_values(cams[ci], free), camera_cov.get(ci)) for ci in calibrated}
    mounting = model.mounting()
    offsets, strips = model.strip_offsets(), model.strips()
    strips_std = _strip_std(prob, opt, strips, prior_ok & ~prior_off[:, 1] & adjusted, sigma0)
    if model.strip_used:
        log.append("GNSS strip offsets (m) and drifts (m/km): " + "; ".join(
            f"{prob.strip_names[st]} {np.round(strips[st, :3], 3).tolist()} {np.round(strips[st, 3:], 3).tolist()}"
            for st in sorted(model.strip_used)))
    if opt.mounting:
        log.append("mounting corrections (boresight deg, offset m, camera axes): " + "; ".join(
            f"{prob.cameras[ci].id} {np.round(np.degrees(mounting[ci, :3]), 4).tolist()} "
            f"{np.round(mounting[ci, 3:], 4).tolist()}" for ci in sorted(model.mount_used)))
    lap("statistics_s")
    # the reconstruction and the Ceres problem are millions of small C++ allocations: hand their pages back (or to
    # the caller, see adjust's keep)
    if keep is not None:
        keep += [rd, model]
    del rd, model
    if keep is None:
        release_heap()
    # final values in the control frame
    xyz_cov = q_point * sigma0**2
    pt_ok = point_used & np.isfinite(xyz[:, 0])
    xyz_out = np.where(pt_ok[:, None], xyz + shift, np.nan)
    gcp_out = gcp_xyz + shift
    # prior residuals (adjusted - prior), world frame; with a mounting correction those of the frame it leaves
    r_f, c_f = frame_poses(r, c, prob.image_camera, mounting)
    att_res, pos_res = _prior_residuals(prob, r_f, c_f, offsets)
    # the smallest detectable errors: tie measurements tested on 2 degrees of freedom, coordinates on 1 per axis
    delta_obs, delta = detectable_shift(opt.blunder_threshold, 2), detectable_shift(opt.blunder_threshold)
    gcp_mdb, prior_mdb = delta * gcp_sd, delta * prior_sd
    in_use6 = np.repeat(prior_ok[:, None] & ~prior_off & adjusted[:, None], 3, axis=1)
    gcp_red = prob.gcp_sigma**2 / gcp_sd**2
    meas_v, meas_red = _control_measurements(prob, cams, r, c, gcp_xyz, gcp_obs_ok & gcp_ok[prob.gcp_obs_point]
                                             & adjusted[prob.gcp_obs_image], gcp_ok)
    components = variance_components(
        v, red, active, opt.sigma_px, np.concatenate([att_res, pos_res], 1),
        np.concatenate([prob.prior_sigma_att, prob.prior_sigma_pos], 1), np.where(in_use6, 1.0 - prior_share, np.nan),
        gcp_out - prob.gcp_xyz, prob.gcp_sigma, np.where(gcp_ok[:, None], gcp_red, np.nan), meas_v,
        prob.gcp_sigma_px[prob.gcp_obs_point], meas_red)
    return BundleResult(
        r_cam_from_world=r, c_world=c + shift, image_adjusted=adjusted, image_std=image_std, cameras=cams,
        xyz=xyz_out, xyz_cov=xyz_cov, obs_residual=v, obs_rejected=rejected,
        obs_w=w, gcp_xyz=gcp_out, gcp_residual=gcp_out - prob.gcp_xyz, datum_shift=shift, datum_shift_std=shift_std,
        sigma0=sigma0, image_std_kind=image_std_kind, image_std_relative=image_std_relative, mounting=mounting,
        mounting_std=mounting_std, calibration=calibration,
        redundancy=redundancy, iterations=iterations, rounds=rnd + 1, time_s=time.perf_counter() - t0,
        prior_residual_pos=pos_res, prior_residual_att=att_res, obs_used=active.copy(), log=log,
        timing=timing, gcp_obs_rejected=gcp_obs_bad, gcp_rejected=~gcp_ok, gcp_w=gcp_w,
        prior_rejected=prior_off, prior_w=prior_w, gnss_strip=strips, gnss_strip_std=strips_std,
        obs_redundancy=red, obs_mdb=np.where(active, delta_obs * opt.sigma_px * sigma0 / np.sqrt(red), np.nan),
        gcp_redundancy=gcp_red, gcp_mdb=gcp_mdb, gcp_datum_effect=gcp_mdb * gcp_infl,
        prior_mdb=prior_mdb, prior_effect=prior_mdb * prior_share, sigma_px=opt.sigma_px,
        variance_components=components, prior_sigma_scale=sigma_scale, control_sigma_scale=opt.control_sigma_scale)


def _strip_std(prob: BundleProblem, opt: BundleOptions, strips: np.ndarray, in_use: np.ndarray,
               sigma0: float) -> np.ndarray:
    """Standard deviations ``(s, 6)`` of the GNSS strip offsets and drifts ``strips (s, 6)`` (NaN where not
    estimated) with the orientations held: per strip and axis the inverse of the information of its images' position
    priors in use (``in_use (n,)``) and of its own priors, times ``sigma0``.

    The heads of one exposure (``BundleProblem.image_exposure``) share one GNSS position, so their priors count as
    one: each of the ``h`` in use carries ``1 / h`` of its weight. Counted per image, the 5 heads of a penta camera
    made the offsets and drifts look sqrt(5) times more precise than they are: on 4 simulated 400-image blocks
    (IAT, 5 strips of 16 exposures, planted offsets and drifts) their errors were 1.4-2.8 times (RMS per axis) the
    standard deviations counted per image."""
    out = np.full(strips.shape, np.nan)
    exposure = prob.image_exposure if len(prob.image_exposure) else np.full(prob.n_images, -1)
    for st in np.flatnonzero(np.isfinite(strips[:, 0])):
        sel = in_use & (prob.prior_strip == st)
        e = exposure[sel]
        heads = np.ones(len(e))
        heads[e >= 0] = np.bincount(e[e >= 0])[e[e >= 0]]
        w = 1.0 / (prob.prior_sigma_pos[sel] ** 2 * heads[:, None])
        u = prob.prior_along[sel, None]
        drift = bool(np.isfinite(strips[st, 3]))
        for ax in range(3):
            info = np.array([[w[:, ax].sum() + opt.gnss_shift_sigma**-2, (w[:, ax] * u[:, 0]).sum()],
                             [(w[:, ax] * u[:, 0]).sum(), (w[:, ax] * u[:, 0] ** 2).sum() + opt.gnss_drift_sigma**-2]])
            if not drift:
                out[st, ax] = sigma0 / np.sqrt(info[0, 0])
                continue
            cov = np.linalg.inv(info)
            out[st, ax], out[st, 3 + ax] = sigma0 * np.sqrt(np.diag(cov))
    return out


def frame_poses(r_cam_from_world: np.ndarray, c_world: np.ndarray, image_camera: np.ndarray,
                mounting: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames of images ``r_cam_from_world (n, 3, 3)``, ``c_world (n, 3)``: their cameras' mounting
    corrections ``mounting (k, 6)`` (see :class:`BundleResult`) removed, ``R_F = R_M^T R`` and
    ``C_F = C - R^T R_M o`` (a copy; an image whose camera has a NaN row is its own frame). The GNSS/IMU priors
    describe these frames, and HAT propagates their corrections from the nadir to the other heads."""
    r_f, c_f = np.array(r_cam_from_world, np.float64), np.array(c_world, np.float64)
    for ci, m in enumerate(mounting):
        sel = np.flatnonzero(image_camera == ci)
        if len(sel) and np.all(np.isfinite(m)):
            rm = rotvec_to_matrix(m[:3])
            c_f[sel] -= np.einsum("kji,jl,l->ki", r_f[sel], rm, m[3:])
            r_f[sel] = rm.T @ r_f[sel]
    return r_f, c_f


def world_pose_std(pose_cov: np.ndarray, r_cam_from_world: np.ndarray, c_local: np.ndarray,
                   shift_cov: np.ndarray | None = None, pose_shift_cov: np.ndarray | None = None) -> np.ndarray:
    """Standard deviations ``(n, 6)`` (rotation about world X Y Z in radians, centre in metres) of images from the
    covariances ``pose_cov (n, 6, 6)`` of their ``cam_from_world`` in Ceres' tangent space: the quaternion's
    increment ``d`` applied on the left (its quaternion manifold: a rotation by the vector ``2 d`` in camera axes,
    ``R' = exp([2d]x) R``) and an added translation ``dt``. With ``C = -R^T t`` that is the world-axes rotation
    ``2 R^T d`` (``R' = R exp([2 R^T d]x)``, the convention of :mod:`.precision`) and the centre change
    ``-2 R^T [t]x d - R^T dt``.

    With an estimated datum shift ``s`` (the centre in the control frame is ``C + s``) its covariance
    ``shift_cov (3, 3)`` and each pose's covariances with it ``pose_shift_cov (n, 6, 3)`` enter the centres': the
    shift's uncertainty is common to all images. On a simulated 6,000-image block the centres' errors had a common
    part of 2.6 / 4.5 / 4.6 mm (X Y Z, their mean) and were 1.11 / 1.34 / 1.32 times the standard deviations without
    the shift, 1.02 / 1.24 / 1.13 times those with it.

    r_cam_from_world : (n, 3, 3); c_local : (n, 3) centres in the problem's local frame
    """
    rt = np.transpose(r_cam_from_world, (0, 2, 1))
    t = -np.einsum("nij,nj->ni", r_cam_from_world, c_local)
    n = len(rt)
    with_shift = shift_cov is not None
    j = np.zeros((n, 6, 9 if with_shift else 6))
    j[:, :3, :3] = 2.0 * rt
    j[:, 3:, :3] = -2.0 * rt @ np.array([skew(v) for v in t]).reshape(-1, 3, 3)
    j[:, 3:, 3:6] = -rt
    cov = pose_cov
    if with_shift:
        j[:, 3:, 6:] = np.eye(3)
        cov = np.zeros((n, 9, 9))
        cov[:, :6, :6] = pose_cov
        cov[:, :6, 6:] = pose_shift_cov
        cov[:, 6:, :6] = np.transpose(pose_shift_cov, (0, 2, 1))
        cov[:, 6:, 6:] = shift_cov
    return np.sqrt(np.abs(np.einsum("nij,njk,nik->ni", j, cov, j)))


def marginal_covariances(problem, poses: list[np.ndarray], globals_: list[np.ndarray], points: list[np.ndarray],
                         pose_blocks: bool, cross: int | None = None
                         ) -> tuple[np.ndarray | None, list[np.ndarray], np.ndarray | None] | None:
    """Marginal covariances (unit weight, in each block's tangent space) of the solved Ceres ``problem``, whose
    variable blocks are the images' ``poses`` (tangent size 6), the global parameter blocks ``globals_`` and the
    ``points`` (3): with ``pose_blocks`` each pose's ``(n, 6, 6)`` (else None), each global block's, and with
    ``pose_blocks`` and ``cross`` (an index into ``globals_``) each pose's covariances ``(n, 6, t)`` with that global
    block (else None), by :func:`.precision.marginal_covariance` on the problem's Jacobian. The lists must hold every
    variable block of the problem (one left out would count as known and the covariances come out too small). None
    when the reduced system is singular.

    The reference is pycolmap's covariance estimation: the globals' standard deviations agree with those of its
    estimate of everything to 4 digits on simulated blocks of 240 and 1,000 images with 5 self-calibrated cameras
    (which took it 3.6 s and 74 s, and grows faster than the cube of the images), the images' with its estimate of
    the poses (tests). The Jacobian is evaluated on one thread: the Python costs hold the interpreter's lock, which
    Ceres' other threads would wait for."""
    import pyceres

    eo = pyceres.EvaluateOptions()
    eo.set_parameter_blocks([*poses, *globals_, *points])
    eo.num_threads = 1
    jac = problem.evaluate_jacobian(eo)
    rows, cols, values = jac.to_tuple()
    tangent = [problem.parameter_block_tangent_size(b) for b in globals_]
    if any(problem.parameter_block_tangent_size(b) != 6 for b in poses):
        raise ComputationError("an image's pose block is held in part: the covariance needs 6 free parameters")
    n_pose = 6 * len(poses)
    if jac.num_cols != n_pose + sum(tangent) + 3 * len(points):
        raise ComputationError(f"the Jacobian has {jac.num_cols} columns, not the {n_pose + sum(tangent)} of the "
                               f"poses and globals plus 3 per point ({len(points)} points)")
    edges = np.cumsum([0, *tangent])
    got = precision.marginal_covariance(rows, cols, values, jac.num_rows, n_pose, sum(tangent), len(points),
                                        pose_blocks, None if cross is None else np.arange(edges[cross],
                                                                                          edges[cross + 1]))
    if got is None:
        return None
    return (got.poses, [got.globals_[a:b, a:b] for a, b in zip(edges[:-1], edges[1:])],
            got.pose_globals if cross is not None else None)


def release_heap() -> None:
    """Return freed heap pages to the operating system (glibc's ``malloc_trim``; nothing elsewhere). After an
    adjustment of 1.25 M observations the process still held 1.15 GB of freed C++ allocations (pycolmap's
    reconstruction, Ceres' problem) as resident memory: 1.70 GB resident before the call, 0.55 GB after it."""
    import ctypes

    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError, TypeError):  # not glibc (macOS has no malloc_trim; Windows no CDLL(None))
        pass


HEAP_CHUNK_BYTES = 16 * 2**20
"""The pieces :func:`reserve_heap` touches: under glibc's largest mmap threshold (32 MB), so they come from the
heap."""


def reserve_heap(nbytes: int) -> bool:
    """Map about ``nbytes`` of heap pages into this process and keep them for its next allocations (glibc: the mmap
    threshold fixed at twice :data:`HEAP_CHUNK_BYTES`, the trim threshold above ``nbytes``; the pages written once).
    A fresh worker process otherwise takes its first adjustment's page faults inside it: on the 3,000-image block
    an oblique run took 0.4 s longer as the first run of its process than as the second. Returns whether it could
    (not glibc: nothing done)."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # not glibc (see release_heap)
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    if not (mallopt(m_mmap_threshold, 2 * HEAP_CHUNK_BYTES) and mallopt(m_trim_threshold, nbytes + HEAP_CHUNK_BYTES)):
        return False
    pieces = [np.ones(HEAP_CHUNK_BYTES // 8) for _ in range(max(0, nbytes) // HEAP_CHUNK_BYTES)]
    del pieces
    return True


def image_focals(cameras: list[CameraModel], image_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Focal lengths ``fx, fy`` in pixels, shaped like ``image_camera`` (indices into ``cameras``)."""
    return (np.array([cm.fx for cm in cameras])[image_camera], np.array([cm.fy for cm in cameras])[image_camera])


def refine_points(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                  xyz: np.ndarray, obs_point: np.ndarray, obs_image: np.ndarray, obs_uv: np.ndarray,
                  mask: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Points re-estimated from their image observations with the cameras fixed (Gauss-Newton on the pixel
    residuals, pinhole Jacobians). ``xyz (p, 3)``; the observations ``mask (m,)`` of ``obs_point``,
    ``obs_image (m,)``, ``obs_uv (m, 2)`` are used; points with fewer than two of them keep their value.
    Returns a new ``(p, 3)`` array."""
    xyz = np.array(xyz, dtype=np.float64)
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return xyz
    op, oi = obs_point[idx], obs_image[idx]
    pts, local = np.unique(op, return_inverse=True)
    ok = np.bincount(local, minlength=len(pts)) >= 2
    fx, fy = image_focals(cameras, image_camera)
    for _ in range(iterations):
        uv_hat = project_obs(cameras, image_camera, r, c, xyz, op, oi)
        v = obs_uv[idx] - uv_hat
        good = np.all(np.isfinite(v), 1)
        jp = precision.point_jacobians(r, c, fx, fy, xyz, op, oi)
        w = good.astype(np.float64)
        n = precision.point_normals(jp, w, local, len(pts))
        g = precision.row_sums(jp[good], v[good], local[good], len(pts))
        q = precision.safe_inverse(n)
        step = np.einsum("kij,kj->ki", q, g)
        upd = ok & np.all(np.isfinite(step), 1)
        xyz[pts[upd]] += step[upd]
    return xyz


def robust_sigma0(t: np.ndarray) -> float:
    """sigma0 from the median of ``t (m,)``, the squared normalised residuals of 2-D measurements for unit sigma0
    (chi-square with 2 degrees of freedom, whose median is 2 ln 2), blunders notwithstanding; NaN ignored, 1 for
    none."""
    return float(np.sqrt(np.nanmedian(t) / (2 * np.log(2)))) if len(t) else 1.0


def screen_points(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                  op_all: np.ndarray, oi_all: np.ndarray, uv_all: np.ndarray, xyz_start: np.ndarray, sigma_px: float,
                  sigma0: float | None, threshold: float, max_rounds: int, reject_undetermined: bool = True,
                  prior_xyz: np.ndarray | None = None, prior_info: np.ndarray | None = None, settle: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Points from fixed cameras with blunder tests: from ``xyz_start (n, 3)`` (finite for every point observed) a
    Gauss-Newton step on the pixel residuals of the observations ``op_all``, ``oi_all (m,)``, ``uv_all (m, 2)``
    (images with ``r (k, 3, 3)``, ``c (k, 3)``, ``image_camera (k,)`` into ``cameras``), then each round rejects
    every track's worst ray whose normalised residual ``|v| / (sigma0 sigma_px sqrt(r))`` (r its redundancy number
    for the point alone, from the linearised residuals after the step) exceeds ``threshold``; only tracks that
    lost a ray take another step, from where they are, up to ``max_rounds`` rounds. ``sigma0=None`` estimates it
    robustly (the median of ``w^2``, chi-square with 2 degrees of freedom) from all rays in use after each round
    (at first, rays of points pulled by blunders inflate it) and every track is tested again with it. With
    ``reject_undetermined`` the rays of a point left undetermined (fewer than two rays, badly conditioned, behind a
    camera) count as rejected too; without it they are only left untested. ``prior_xyz (n, 3)`` and
    ``prior_info (n, 3, 3)`` are ground observations of points (connection points; NaN rows and zero blocks for
    none) with their inverse covariances: they enter each point's step, so a point with one ray and a ground
    observation is tested too. With ``settle`` the points far from their rays are first moved onto them
    (:func:`_settled_points`: a start intersected from the navigation data).

    Returns ``xyz (n, 3)`` and ``cov (n, 3, 3)`` (NaN for points with fewer than two rays or badly conditioned),
    the rejected observations ``(m,)`` and the sigma0 used."""
    m, n = len(op_all), len(xyz_start)
    fx, fy = image_focals(cameras, image_camera)
    x = np.array(xyz_start, np.float64)
    if settle:
        x = _settled_points(cameras, image_camera, r, c, fx, fy, op_all, oi_all, uv_all, x, sigma_px, prior_xyz,
                            prior_info)
    xyz = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    use = np.ones(m, bool)
    rejected = np.zeros(m, bool)
    todo = np.ones(n, bool)
    t_all = np.full(m, np.nan)  # squared normalised residuals for unit sigma0
    robust = sigma0 is None
    s0 = 1.0 if sigma0 is None else sigma0
    for _ in range(max_rounds):
        idx = np.flatnonzero(use & todo[op_all])
        if len(idx) == 0:
            break
        # the points of this round numbered 0.. (after the first round only those that lost a ray)
        pts = np.flatnonzero(todo)
        rank = np.cumsum(todo) - 1
        op, oi = rank[op_all[idx]], oi_all[idx]
        x_pts = x[pts]
        # one Gauss-Newton step on the pixel residuals; the test uses the linearised residuals after it
        step, q, v, jp, good, _ = _point_step(cameras, image_camera, r, c, fx, fy, op, oi, uv_all[idx], x_pts,
                                              sigma_px, None if prior_info is None else prior_info[pts],
                                              None if prior_xyz is None else prior_xyz[pts])
        solved = np.all(np.isfinite(step), 1)  # fewer than two rays or badly conditioned: no point
        dx = np.take(np.nan_to_num(step), op, 0)
        v1 = v - np.stack([jp[:, k, 0] * dx[:, 0] + jp[:, k, 1] * dx[:, 1] + jp[:, k, 2] * dx[:, 2]
                           for k in range(2)], 1)
        red = np.clip(1.0 - precision.quadratic_forms(jp, q, op) / sigma_px**2 / 2.0, 0.02, 1.0)
        t_all[idx] = np.where(good & solved[op], np.sum(v1**2, 1) / red / sigma_px**2, np.nan)
        if robust:
            # from every ray still in use, each with its point's latest step
            t_use = t_all[use & np.isfinite(t_all)]
            s0 = robust_sigma0(t_use)
        w = np.where(use, np.sqrt(t_all) / max(s0, 1e-9), np.nan)
        x[pts[solved]] = x_pts[solved] + step[solved]
        xyz[pts] = np.where(solved[:, None], x[pts], np.nan)
        cov[pts] = q
        cur = np.zeros(m, bool)
        cur[idx] = True
        bad = worst_per_track(w, op_all, use, threshold)
        if reject_undetermined:
            bad |= cur & ~np.isfinite(w)
        if not bad.any():
            break
        rejected |= bad
        use &= ~bad
        todo = np.zeros(n, bool)
        todo[op_all[bad]] = True
    return xyz, cov * s0**2, rejected, s0


def _point_step(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray, fx: np.ndarray,
                fy: np.ndarray, op: np.ndarray, oi: np.ndarray, uv: np.ndarray, x_pts: np.ndarray, sigma_px: float,
                info_pts: np.ndarray | None, prior_pts: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """One Gauss-Newton step of points ``x_pts (p, 3)`` on the pixel residuals of their rays ``op`` (into
    ``x_pts``), ``oi``, ``uv (m, 2)`` with the cameras held (``info_pts``, ``prior_pts``: ground observations of the
    points, as in :func:`screen_points`). Returns the step ``(p, 3)`` (NaN where undetermined), the points'
    cofactors ``(p, 3, 3)``, the residuals ``(m, 2)`` (0 where not finite), their point Jacobians ``(m, 2, 3)``, the
    rays with finite residuals ``(m,)`` and each ray's length ``(m,)``."""
    xc, d, jp = precision.ray_geometry(r, c, fx, fy, x_pts, op, oi)
    v = uv - pixels_from_camera(cameras, image_camera, xc, oi)
    del xc
    good = np.all(np.isfinite(v), 1)
    q = precision.safe_inverse(precision.point_normals(jp, np.where(good, sigma_px**-2, 0.0), op, len(x_pts),
                                                       info_pts))
    v[~good] = 0.0
    g = precision.row_sums(jp, v, op, len(x_pts)) * sigma_px**-2
    if info_pts is not None:
        g += np.einsum("kij,kj->ki", info_pts, np.nan_to_num(prior_pts - x_pts))
    return np.einsum("kij,kj->ki", q, g), q, v, jp, good, np.linalg.norm(d, axis=1)


SETTLE_TOLERANCE = 0.03
"""Pixels: a start point takes Gauss-Newton steps with the cameras held before :func:`screen_points` tests its rays
while its last step ``s`` leaves more than this in its residuals, ``f s^2 / L^2`` (f its cameras' focal length in
pixels, L its ray length: one step from an error ``s`` leaves an error of about ``s^2 / L``)."""


def _settled_points(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                    fx: np.ndarray, fy: np.ndarray, op_all: np.ndarray, oi_all: np.ndarray, uv_all: np.ndarray,
                    xyz_start: np.ndarray, sigma_px: float, prior_xyz: np.ndarray | None,
                    prior_info: np.ndarray | None, max_steps: int = 6) -> np.ndarray:
    """``xyz_start (n, 3)`` with the points far from their rays moved onto them: Gauss-Newton steps with the
    cameras held (all rays, up to ``max_steps``) while a point's step leaves more than :data:`SETTLE_TOLERANCE`
    pixels (mean over its rays). A start intersected from coarse navigation data (5 m, 0.5 degrees) lies that far,
    and the tests after one step took 3.6 % of the good rays of a HAT block for blunders (0.17 % with this); a start
    from good navigation data stays as it was, but for weakly intersected points (1 % of those without a blunder,
    a fifth of those with one on the 400-image test block)."""
    x = np.array(xyz_start, np.float64)
    todo = np.zeros(len(x), bool)
    todo[op_all] = True
    for _ in range(max_steps):
        idx = np.flatnonzero(todo[op_all])
        if len(idx) == 0:
            break
        pts = np.flatnonzero(todo)
        op, oi = (np.cumsum(todo) - 1)[op_all[idx]], oi_all[idx]
        step, _, _, _, _, length = _point_step(
            cameras, image_camera, r, c, fx, fy, op, oi, uv_all[idx], x[pts], sigma_px,
            None if prior_info is None else prior_info[pts], None if prior_xyz is None else prior_xyz[pts])
        rays = np.maximum(np.bincount(op, minlength=len(pts)), 1)
        focal_by_length = np.bincount(op, weights=np.sqrt(fx[oi] * fy[oi]) / length**2, minlength=len(pts)) / rays
        far = np.all(np.isfinite(step), 1) & (np.sum(step**2, 1) * focal_by_length > SETTLE_TOLERANCE)
        x[pts[far]] += step[far]
        todo = np.zeros(len(x), bool)
        todo[pts[far]] = True
    return x


class ControlTests(NamedTuple):
    """The outcome of :func:`control_point_tests`.

    obs_rejected : (k,) the measurements rejected; rejected : (g,) the points whose coordinates were rejected;
    w : (g,) each point's largest normalised coordinate difference; sd : (g, 3) the standard deviations of its
    differences per axis (metres; w and sd a rejected point's when it was rejected; NaN where untested);
    datum_influence : (g, 3) with the shift estimated from the control points, how far an error along each axis of a
    point moves that shift, per metre of the error (NaN where untested or the shift is held)
    """

    obs_rejected: np.ndarray
    rejected: np.ndarray
    w: np.ndarray
    sd: np.ndarray
    datum_influence: np.ndarray


def control_point_tests(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                        given: np.ndarray, sigma: np.ndarray, sigma_px: np.ndarray, op: np.ndarray, oi: np.ndarray,
                        uv: np.ndarray, obs_ok: np.ndarray, point_ok: np.ndarray, shift: np.ndarray,
                        shift_free: bool, threshold: float) -> ControlTests:
    """Blunder tests of control points with the images held at ``r (n, 3, 3)``, ``c (n, 3)`` (frame of the
    navigation data; ``shift (3,)`` takes it to the control frame).

    Control points ``given (g, 3)`` with standard deviations ``sigma (g, 3)`` (m) are measured ``uv (k, 2)`` in
    images ``oi (k,)`` (point ``op (k,)``, pixel sigma ``sigma_px (g,)``); ``obs_ok (k,)`` and ``point_ok (g,)``
    mark what is still in use.

    1. Image measurements: of a point with at least three measurements in use, the worst ray is rejected while its
       normalised residual (intersection with the images held, :func:`screen_points` with sigma0 1) exceeds
       ``threshold`` (two rays cannot tell which is wrong).
    2. Coordinates: each point is intersected from its measurements in use (covariance ``C`` from its pixel sigma)
       and compared with its given coordinates after the shift: with ``shift_free`` (the adjustment estimates the
       shift from the control points) the shift of the *other* points (their differences averaged with the
       inverse of ``C + diag(sigma^2)``), so a wrong point cannot hide in the shift; otherwise ``shift``. The
       normalised difference of an axis is the difference over its standard deviation (``C``, ``sigma`` and the
       shift's); while a point is above ``threshold``, the worst one is rejected and the others are tested again
       without it (data snooping; the images stay where they are).

    3. With ``shift_free``, each point kept gets its influence on the shift: the columns of ``S W_i`` (``S`` the
       shift's covariance from all points kept, ``W_i`` the point's weight), how far its error moves the shift."""
    from .problem import intersect_rays, ray_directions  # problem builds on this module

    g = len(given)
    bad_obs = np.zeros(len(op), bool)
    use = obs_ok & point_ok[op]
    rays = np.bincount(op[use], minlength=g)
    # the points start where their rays meet (a wrong coordinate is no start), else at their given place
    x0, _ = intersect_rays(c[oi[use]], ray_directions(cameras, image_camera, r, oi[use], uv[use]), op[use], g)
    start = np.where(np.isfinite(x0), x0, np.nan_to_num(given - shift))
    for s_px in np.unique(sigma_px):
        sel = np.flatnonzero(use & (rays >= 3)[op] & (sigma_px[op] == s_px))
        if len(sel):
            _, _, rej, _ = screen_points(cameras, image_camera, r, c, op[sel], oi[sel], uv[sel], start, float(s_px),
                                         1.0, threshold, 10, reject_undetermined=False)
            bad_obs[sel[rej]] = True
    use &= ~bad_obs
    x = np.full((g, 3), np.nan)
    cov = np.full((g, 3, 3), np.nan)
    for s_px in np.unique(sigma_px):
        sel = np.flatnonzero(use & (sigma_px[op] == s_px))
        if len(sel):
            x_s, c_s, _, _ = screen_points(cameras, image_camera, r, c, op[sel], oi[sel], uv[sel], start, float(s_px),
                                           1.0, np.inf, 2)
            pts = np.unique(op[sel])
            x[pts], cov[pts] = x_s[pts], c_s[pts]
    ok = point_ok & np.all(np.isfinite(x), 1) & np.all(np.isfinite(cov.reshape(g, 9)), 1) \
        & np.all(np.isfinite(given), 1)
    w_pt = np.full(g, np.nan)
    sd_pt = np.full((g, 3), np.nan)
    influence = np.full((g, 3), np.nan)
    if not ok.any():
        return ControlTests(bad_obs, np.zeros(g, bool), w_pt, sd_pt, influence)
    total = cov + np.einsum("gi,ij->gij", np.nan_to_num(sigma) ** 2, np.eye(3))
    diff = given - x  # each point's own estimate of the shift
    weight = np.zeros((g, 3, 3))
    weight[ok] = np.linalg.inv(total[ok])
    info_all = weight[ok].sum(0)
    rhs_all = np.einsum("gij,gj->i", weight[ok], diff[ok])
    bad_pt = np.zeros(g, bool)
    w_bad = np.full(g, np.nan)  # a rejected point's figures when it was rejected
    sd_bad = np.full((g, 3), np.nan)
    while True:
        w_pt[:] = np.nan
        sd_pt[:] = np.nan
        for i in np.flatnonzero(ok):
            if shift_free:
                info = info_all - weight[i]
                if np.linalg.cond(info) > 1e12:
                    continue  # no other control point: the shift rests on this one alone
                s_cov = np.linalg.inv(info)
                s_i = s_cov @ (rhs_all - weight[i] @ diff[i])
            else:
                s_cov, s_i = np.zeros((3, 3)), shift
            var = np.diagonal(total[i] + s_cov)
            if np.any(var <= 0):
                continue  # numerically undetermined (an ill-conditioned point or shift): untested
            sd_pt[i] = np.sqrt(var)
            w_pt[i] = float(np.max(np.abs(diff[i] - s_i) / sd_pt[i]))
        worst = int(np.argmax(np.where(np.isfinite(w_pt), w_pt, -1.0)))
        if not (np.isfinite(w_pt[worst]) and w_pt[worst] > threshold):
            kept = np.flatnonzero(np.isfinite(w_pt))
            if shift_free and len(kept) and np.linalg.cond(info_all) < 1e12:
                influence[kept] = np.linalg.norm(np.linalg.inv(info_all) @ weight[kept], axis=1)
            return ControlTests(bad_obs, bad_pt, np.where(bad_pt, w_bad, w_pt),
                                np.where(bad_pt[:, None], sd_bad, sd_pt), influence)
        # the worst goes, and the others are tested again without it (its error no longer in their shift)
        bad_pt[worst], ok[worst], w_bad[worst], sd_bad[worst] = True, False, w_pt[worst], sd_pt[worst]
        info_all = info_all - weight[worst]
        rhs_all = rhs_all - weight[worst] @ diff[worst]


def _prior_residuals(prob: BundleProblem, r_frame: np.ndarray, c_frame: np.ndarray, offsets: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Adjusted minus prior of each image's frame (``r_frame (n, 3, 3)``, ``c_frame (n, 3)``, the navigation frame):
    the rotation about the world axes ``(n, 3)`` (radians, ``R = R_prior exp([theta]x)``) and the centre ``(n, 3)``
    from the prior corrected by its GNSS strip offset ``offsets (n, 3)`` (the prior minus it); NaN rows for images
    without a prior."""
    has = np.all(np.isfinite(prob.prior_c), axis=1)
    att = np.full((prob.n_images, 3), np.nan)
    for k in np.flatnonzero(has):
        att[k] = matrix_to_rotvec(prob.prior_r[k].T @ r_frame[k])
    return att, np.where(has[:, None], c_frame - prob.prior_c + offsets, np.nan)


class PriorTests(NamedTuple):
    """The outcome of :func:`prior_tests`.

    rejected : (n, 2) the parts (attitude, position) rejected; w : (n, 2) the parts' largest normalised differences
    (NaN: not tested); scale : (2,) the two robust scales (1 where not above it); sd : (n, 6) the standard
    deviations of the differences times their part's scale (the unit of the test; NaN: not tested); share : (n, 6)
    the share of an error in a prior axis that enters the adjusted orientation along that axis with the points held
    (``[(N_t + P)^-1 P]_ii``, one minus its redundancy number; NaN: not tested)
    """

    rejected: np.ndarray
    w: np.ndarray
    scale: np.ndarray
    sd: np.ndarray
    share: np.ndarray


def _prior_terms(att_res: np.ndarray, pos_res: np.ndarray, sigma: np.ndarray, n_ties: np.ndarray,
                 fraction: np.ndarray | None, group: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The EO priors' terms per image and group, as :func:`prior_tests` and :func:`prior_release` weigh them: the
    residuals ``v (n, 6)`` (NaN as 0), the weights ``p (n, 6)`` (the share ``fraction (n, 2)`` of ``1 / sigma**2``,
    ``sigma (n, 6)``; world axes, diagonal), the images' groups ``g (n,)`` and the groups' tie normal blocks summed
    ``(G, 6, 6)``."""
    n = len(att_res)
    frac = np.ones((n, 2)) if fraction is None else fraction
    g = np.arange(n) if group is None else group
    n_g = np.zeros((int(g.max(initial=-1)) + 1, 6, 6))
    np.add.at(n_g, g, np.nan_to_num(n_ties))
    return (np.nan_to_num(np.concatenate([att_res, pos_res], 1)), np.repeat(frac, 3, axis=1) / sigma**2, g, n_g)


def prior_tests(att_res: np.ndarray, pos_res: np.ndarray, sigma_att: np.ndarray, sigma_pos: np.ndarray,
                n_ties: np.ndarray, in_use: np.ndarray, threshold: float,
                fraction: np.ndarray | None = None, group: np.ndarray | None = None) -> PriorTests:
    """Blunder tests of the images' EO priors (GNSS position, IMU attitude), each against the orientation the
    image's own tie observations give (a resection, in which the prior takes no part), the other images held.

    ``att_res, pos_res (n, 3)``: adjusted minus prior (world axes, see :func:`_prior_residuals`); ``sigma_att,
    sigma_pos (n, 3)`` the priors' standard deviations; ``n_ties (n, 6, 6)`` the normal blocks of the images from
    their tie observations alone (rotation about the world axes, centre; weights of the measurements' a priori
    sigma), with the points free (:func:`.precision.reduced_image_normals`; held points overstate what the ties
    tell of the pose, most in a weak sub-block); ``in_use (n, 2)`` the parts (attitude, position) still in the
    adjustment; ``fraction (n, 2)`` the share of its weight each part has in the adjustment and ``group (n,)`` the
    images moving as one body (the heads of an exposure tied by the rig share one measurement,
    :func:`shared_prior_fraction`, :func:`rig_groups`; None: all of the weight, each image its own group).

    The adjusted pose of a group minimises its tie and prior terms, so ``x = N^-1 (N_t x_t + sum_i P_i x_i)`` with
    ``N = N_t + sum_i P_i`` (``N_t`` the sum of its images' tie normals, rotations and centres in world axes, the
    lever arms' coupling left out; ``P_i`` an image's prior weight in the adjustment); the tie-only pose differs
    from an image's prior by ``d = x_t - x_i = v + N_t^-1 sum_j P_j v_j`` (v the priors' residuals), with the
    covariance ``N_t^-1 + S`` (S the prior's own covariance, whatever share of it the adjustment weighs). An axis's
    normalised difference is ``|d| / std``, over the part's robust scale when that exceeds one: the median absolute
    normalised difference of all its tested axes over 0.6745 (the normal one's), as data snooping assumes few
    blunders among correctly weighted observations, and priors whose sigmas are too small (a GNSS accuracy taken from
    a better survey) would otherwise fail by the dozen. A part whose largest exceeds ``threshold`` is rejected. A
    group whose ties do not determine its pose (``N_t`` singular) is not tested. Per image, the nadir head's own ties
    against the exposure's full prior, the tests of a block on a tight rig took the attitude priors for 1.6 times too
    optimistic and rejected a good one (``tests/aerotri/test_bundle.py``). Returns a :class:`PriorTests`."""
    n = len(att_res)
    use6 = np.repeat(in_use, 3, axis=1)
    sigma = np.concatenate([sigma_att, sigma_pos], 1)
    v, p, g, n_g = _prior_terms(att_res, pos_res, sigma, n_ties, fraction, group)
    v, p = np.where(use6, v, 0.0), np.where(use6, p, 0.0)
    pv_g, p_g = np.zeros((len(n_g), 6)), np.zeros((len(n_g), 6))
    np.add.at(pv_g, g, p * v)
    np.add.at(p_g, g, p)
    q_t = precision.safe_inverse(n_g)
    d = v + np.einsum("nij,nj->ni", q_t, pv_g)[g]
    sd = np.sqrt(np.diagonal(q_t, axis1=1, axis2=2)[g] + sigma**2)
    w6 = np.abs(d) / sd
    w6 = np.where(use6 & np.isfinite(w6), w6, np.nan).reshape(n, 2, 3)
    scale = np.ones(2)
    for part in range(2):
        a = w6[:, part][np.isfinite(w6[:, part])]
        if len(a):
            scale[part] = max(1.0, float(np.median(a)) / 0.6745)
    w6 = w6 / scale[None, :, None]
    w = np.full((n, 2), np.nan)
    tested = np.isfinite(w6).any(2)
    w[tested] = np.nanmax(w6[tested], axis=1)
    ok6 = np.isfinite(w6.reshape(n, 6))
    sd = np.where(ok6, sd * np.repeat(scale, 3), np.nan)
    share = np.where(ok6, np.diagonal(precision.safe_inverse(n_g + p_g[:, :, None] * np.eye(6)),
                                      axis1=1, axis2=2)[g] * p, np.nan)
    return PriorTests(tested & (np.nan_to_num(w) > threshold), w, scale, sd, share)


def prior_release(att_res: np.ndarray, pos_res: np.ndarray, sigma_att: np.ndarray, sigma_pos: np.ndarray,
                  n_ties: np.ndarray, in_use: np.ndarray, off: np.ndarray, fraction: np.ndarray | None = None,
                  group: np.ndarray | None = None) -> tuple[np.ndarray, float] | None:
    """What leaving out the EO prior parts ``off (n, 2)`` (attitude, position; among ``in_use (n, 2)``) changes in a
    least-squares solution, without a new solve: the orientation steps ``(n, 6)`` (rotation about the world axes,
    centre; zero for the groups that keep all their parts) and the decrease of chi-square. Arguments as in
    :func:`prior_tests` (``n_ties`` the tie normal blocks with the points free; the priors weighted diagonally in
    world axes, as the tests weigh them).

    At the solution the tie and prior terms of a group balance; without the parts ``P_off`` the remaining terms
    ``H = N_t + P_on`` are left with the gradient ``P_off v_off`` (``v`` adjusted minus prior), so the Gauss-Newton
    step is ``dx = H^-1 P_off v_off`` and chi-square falls by ``v_off^T P_off v_off + (P_off v_off)^T dx``. Exact for
    the linearised problem with the other images held. None when the ties and the remaining parts do not determine a
    moved group's orientation (``H`` singular): a new solve is needed."""
    v, p, g, h = _prior_terms(att_res, pos_res, np.concatenate([sigma_att, sigma_pos], 1), n_ties, fraction, group)
    p_on = np.where(np.repeat(in_use & ~off, 3, axis=1), p, 0.0)
    p_off = np.where(np.repeat(in_use & off, 3, axis=1), p, 0.0)
    b, d_on = np.zeros((len(h), 6)), np.zeros((len(h), 6))
    np.add.at(b, g, p_off * v)
    np.add.at(d_on, g, p_on)
    moved = np.any(b != 0.0, axis=1)
    dx = np.zeros((len(h), 6))
    if moved.any():
        q = precision.safe_inverse(h[moved] + d_on[moved, :, None] * np.eye(6))
        dx[moved] = np.einsum("gij,gj->gi", q, b[moved])
        if not np.all(np.isfinite(dx[moved])):
            return None
    return dx[g], float(np.sum(p_off * v**2) + np.sum(b * dx))


def variance_components(v: np.ndarray, red: np.ndarray, used: np.ndarray, sigma_px: float, prior_v: np.ndarray,
                        prior_sigma: np.ndarray, prior_red: np.ndarray, gcp_v: np.ndarray, gcp_sigma: np.ndarray,
                        gcp_red: np.ndarray, meas_v: np.ndarray, meas_sigma_px: np.ndarray,
                        meas_red: np.ndarray) -> dict[str, VarianceComponent]:
    """The variance components (:class:`VarianceComponent`) of an adjustment's observation groups
    (:data:`VARIANCE_GROUPS`).

    ``v (m, 2)``: the tie measurements' residuals (pixels), ``red (m,)`` their redundancy numbers (per coordinate),
    ``used (m,)`` those in the solution, ``sigma_px`` their a priori sigma; ``prior_v (n, 6)``: the EO priors'
    residuals (attitude about world X Y Z in radians, position in metres), ``prior_sigma (n, 6)`` their sigmas,
    ``prior_red (n, 6)`` their redundancy numbers (NaN: not in the solution or not tested); ``gcp_v, gcp_sigma,
    gcp_red (g, 3)``: the same for the control points' coordinates; ``meas_v (k, 2), meas_sigma_px (k,), meas_red
    (k,)``: the same for their image measurements (redundancy per coordinate, NaN: not in the solution, see
    :func:`_control_measurements`). The redundancy numbers are those of the blunder tests: the ties' leave out the
    coupling of points and images (about 1 %, see :mod:`.precision`), the priors' are taken with the other images
    held (:func:`prior_tests`), the control points' (coordinates and measurements) with the images held."""
    ok = used & np.isfinite(red) & np.all(np.isfinite(v), 1)
    out = {"ties": VarianceComponent(2 * int(ok.sum()), float(2.0 * red[ok].sum()),
                                     float(np.sum(v[ok] ** 2)) / sigma_px**2)}
    for name, vv, sg, rr in (("imu", prior_v[:, :3], prior_sigma[:, :3], prior_red[:, :3]),
                             ("gnss", prior_v[:, 3:], prior_sigma[:, 3:], prior_red[:, 3:]),
                             ("control", gcp_v, gcp_sigma, gcp_red)):
        sel = np.isfinite(vv) & np.isfinite(sg) & np.isfinite(rr) & (sg > 0)
        out[name] = VarianceComponent(int(sel.sum()), float(rr[sel].sum()), float(np.sum((vv[sel] / sg[sel]) ** 2)))
    ok = np.isfinite(meas_red) & np.all(np.isfinite(meas_v), 1) & (meas_sigma_px > 0)
    out["control_measurements"] = VarianceComponent(2 * int(ok.sum()), float(2.0 * meas_red[ok].sum()),
                                                    float(np.sum(meas_v[ok] ** 2 / meas_sigma_px[ok, None] ** 2)))
    return out


def _control_measurements(prob: BundleProblem, cams: list[CameraModel], r: np.ndarray, c: np.ndarray,
                          gcp_xyz: np.ndarray, use: np.ndarray, gcp_ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The control points' image measurements after an adjustment: residuals ``(k, 2)`` (pixels) and redundancy numbers
    ``(k,)`` per coordinate with the images held (each point from its measurements ``use (k,)`` and, where ``gcp_ok``,
    its given coordinates; NaN for those not in use). ``r, c, gcp_xyz``: the adjustment's frame."""
    op, oi = prob.gcp_obs_point, prob.gcp_obs_image
    v = prob.gcp_obs_uv - project_obs(cams, prob.image_camera, r, c, gcp_xyz, op, oi)
    fx, fy = image_focals(cams, prob.image_camera)
    jp = precision.point_jacobians(r, c, fx, fy, gcp_xyz, op, oi)
    w = np.where(use, 1.0 / prob.gcp_sigma_px[op] ** 2, 0.0)
    prior = np.zeros((len(gcp_xyz), 3, 3))
    ok = gcp_ok & np.all(np.isfinite(prob.gcp_sigma), 1)
    prior[ok] = np.einsum("gi,ij->gij", 1.0 / prob.gcp_sigma[ok] ** 2, np.eye(3))
    q = precision.safe_inverse(precision.point_normals(np.nan_to_num(jp), w, op, len(gcp_xyz), prior))
    red = 1.0 - precision.quadratic_forms(np.nan_to_num(jp), q, op) * w / 2.0
    return v, np.where(use & np.isfinite(red), red, np.nan)


@cache
def detectable_shift(threshold: float, dof: int = 1, power: float = DETECTION_POWER) -> float:
    """Baarda's non-centrality ``delta0``: a blunder of ``delta0`` standard deviations (of the tested difference,
    along one axis of it) makes a test of ``dof`` degrees of freedom (the normalised difference's norm against
    ``threshold``; 1: a coordinate, 2: an image measurement) exceed the threshold with probability ``power``.
    From the non-central chi-square distribution: 5.14 for 4.3 and 80 % on one degree of freedom (4.13 for
    Baarda's 3.29 and 80 %), 5.03 on two. (``scipy.special.chndtrinc``: importing ``scipy.stats`` for its ``ncx2``
    took 0.5-1.5 s of each adjustment's process.)"""
    from scipy.special import chndtrinc

    return float(np.sqrt(chndtrinc(threshold**2, dof, 1.0 - power)))


def resected_start(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                   xyz: np.ndarray, op: np.ndarray, oi: np.ndarray, uv: np.ndarray, opt: BundleOptions,
                   prior_xyz: np.ndarray | None = None, prior_info: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A start moved to its inliers (the first part of ``BundleOptions.screen_start``): the observations ``op``,
    ``oi (m,)``, ``uv (m, 2)`` screened at the start ``r (n, 3, 3)``, ``c (n, 3)``, ``xyz (p, 3)`` with the cameras
    held (:func:`screen_points`, its points settled first, sigma0 estimated robustly; ``prior_xyz``, ``prior_info`` as
    there), then one
    resection step of the images from the inliers with the points held (:func:`resect_images`).

    Returns the new ``r``, ``c`` (the given ones when the screening's sigma0 is above ``opt.screen_max_sigma0``:
    the start is too far for tests with the cameras held), the screened points ``(p, 3)`` (NaN where undetermined)
    and that sigma0."""
    x_s, _, bad, s0 = screen_points(cameras, image_camera, r, c, op, oi, uv, xyz, opt.sigma_px, None,
                                    opt.blunder_threshold, opt.screen_rounds, reject_undetermined=False,
                                    prior_xyz=prior_xyz, prior_info=prior_info, settle=True)
    if s0 <= opt.screen_max_sigma0:
        ok = ~bad & np.isfinite(x_s[op, 0])
        r, c = resect_images(cameras, image_camera, r, c, x_s, op[ok], oi[ok], uv[ok])
    return r, c, x_s, s0


def resect_images(cameras: list[CameraModel], image_camera: np.ndarray, r: np.ndarray, c: np.ndarray,
                  xyz: np.ndarray, obs_point: np.ndarray, obs_image: np.ndarray, obs_uv: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton step per image on the pixel residuals of its observations ``obs_point``, ``obs_image``
    ``(m,)``, ``obs_uv (m, 2)`` with the points ``xyz (p, 3)`` held (each image's 6 x 6 normal block: rotation
    about the world axes, centre). Returns new ``r (n, 3, 3)``, ``c (n, 3)``; images without a determined step
    keep theirs."""
    fx, fy = image_focals(cameras, image_camera)
    # the points in the cameras' frames serve the projection and the Jacobians
    xc, d, jp = precision.ray_geometry(r, c, fx, fy, xyz, obs_point, obs_image)
    v = obs_uv - pixels_from_camera(cameras, image_camera, xc, obs_image)
    good = np.all(np.isfinite(v), 1)
    oi = obs_image
    if not good.all():
        oi, v, d, jp = oi[good], v[good], d[good], jp[good]
    jr = precision.rotation_jacobians(d, jp)
    del xc
    n = len(r)
    q = precision.safe_inverse(precision.image_normals(jp, jr, np.ones(len(oi)), oi, n))
    step = np.einsum("kij,kj->ki", q, precision.row_sums(precision.image_rows(jp, jr), v, oi, n))
    r, c = r.copy(), c.copy()
    move_images(r, c, step, np.flatnonzero(np.all(np.isfinite(step), 1)))
    return r, c


def move_images(r: np.ndarray, c: np.ndarray, step: np.ndarray, images: np.ndarray) -> None:
    """Move the ``images (k,) int64`` of ``r (n, 3, 3)`` (camera from world) and ``c (n, 3)``, in place, by their
    steps ``step (n, 6)``: a rotation about the world axes (rotation vector) and a shift of the centre, the
    parameters of the images' 6 x 6 normal blocks here (:func:`resect_images`, :func:`prior_release`)."""
    for k in images:
        r[k] = r[k] @ rotvec_to_matrix(step[k, :3])
    c[images] += step[images, 3:]


def worst_per_track(w: np.ndarray, obs_point: np.ndarray, active: np.ndarray, threshold: float) -> np.ndarray:
    """Mask of each track's largest normalised residual among active observations when above ``threshold``."""
    idx = np.flatnonzero(active & np.isfinite(w) & (w > threshold))
    out = np.zeros(len(w), bool)
    if len(idx) == 0:
        return out
    order = idx[np.lexsort((-w[idx], obs_point[idx]))]
    first = np.ones(len(order), bool)
    first[1:] = obs_point[order][1:] != obs_point[order][:-1]
    out[order[first]] = True
    return out


def shared_prior_fraction(group: np.ndarray, in_use: np.ndarray) -> np.ndarray:
    """The share ``(n, 2)`` of its weight each image's EO prior part (attitude, position; ``in_use (n, 2)``) carries
    in the adjustment: ``1 / h`` for the ``h`` images of one ``group (n,)`` (:func:`rig_groups`: the heads of one
    exposure tied by rig constraints) whose part is in use, 1 for an image of its own.

    The heads of one exposure do not have five GNSS/IMU measurements but one, seen through the calibrated rig, so
    their priors' errors are the same. Counted in full they told the adjustment the exposure's pose five times: on
    six simulated 250-image penta blocks (rig constraints of 0.0002 deg and 1 mm, the simulated rig being exact) the
    datum shift's errors were 1.90 / 1.72 / 1.15 times its standard deviations (RMS of the z-scores, X Y Z) and the
    centres' 1.38 / 1.28 / 1.19 times theirs; with each head's share 1.02 / 0.92 / 0.64 and 1.08 / 1.04 / 1.12, and
    the centres more accurate (3.5 / 3.6 / 4.3 mm RMS against 4.2 / 4.1 / 4.4). Without the rig the heads are
    separate images whose priors count in full: their relative orientation then rests on those priors, and a share
    of the weight would lose it (the centres 5-10 % less accurate on five of six blocks). On the bench's 3,000-image
    block (``bench_at.py --rig``) IAT on the rig oriented the images to 0.0008 deg and 1.8-1.9 mm RMS, against
    0.0037 deg and 5.8-6.6 mm without it, the check points unchanged (0.100 / 0.112 GSD)."""
    out = np.ones((len(group), 2))
    for part in range(2):
        sel = np.flatnonzero(in_use[:, part])
        out[sel, part] = 1.0 / np.bincount(group[sel])[group[sel]]
    return out


def rig_groups(prob: BundleProblem, opt: BundleOptions) -> np.ndarray:
    """The images' groups ``(n,) int64`` (0 .. g-1) sharing one GNSS/IMU measurement: the heads of one exposure
    tied by rig constraints (``opt.rig``), every other image a group of its own."""
    group = np.arange(prob.n_images) + prob.n_images
    if opt.rig and len(prob.rig_pairs) and len(prob.image_exposure):
        tied = np.zeros(prob.n_images, bool)
        tied[prob.rig_pairs.ravel()] = True
        tied &= prob.image_exposure >= 0
        group[tied] = prob.image_exposure[tied]
    return np.unique(group, return_inverse=True)[1].astype(np.int64)


def _precision(prob: BundleProblem, opt: BundleOptions, r: np.ndarray, c: np.ndarray, xyz: np.ndarray,
               cams: list[CameraModel], active: np.ndarray, prior_off: np.ndarray, prior_frac: np.ndarray):
    """Cofactor blocks of points ``(p, 3, 3)`` and images ``(n, 6, 6)`` (the priors' parts in ``prior_off (n, 2)``
    left out, the others with their share ``prior_frac (n, 2)`` of the weight; with ``opt.rig`` the heads of an
    exposure held together by their rig constraints, :func:`.precision.coupled_inverse`), redundancy numbers
    ``(m,)`` and, for the prior tests, the images' normal blocks from their tie observations alone with the points
    free (:func:`.precision.reduced_image_normals`, ``(n, 6, 6)``; None without ``opt.prior_tests``)."""
    fx, fy = image_focals(cams, prob.image_camera)
    op, oi = prob.obs_point, prob.obs_image
    jp, jr = precision.collinearity_jacobians(r, c, fx, fy, xyz, op, oi)
    w_obs = np.where(active, 1.0 / opt.sigma_px**2, 0.0)
    prior_pt = None
    if prob.point_prior_xyz is not None:
        has = np.isfinite(prob.point_prior_xyz[:, 0])
        prior_pt = np.zeros((prob.n_points, 3, 3))
        prior_pt[has] = np.nan_to_num(precision.safe_inverse(prob.point_prior_cov[has]))
    n_p = precision.point_normals(jp, w_obs, op, prob.n_points, prior_pt)
    prior_im = np.zeros((prob.n_images, 6, 6))
    ok = np.all(np.isfinite(prob.prior_sigma_att), 1) & np.all(np.isfinite(prob.prior_sigma_pos), 1)
    idx = np.arange(3)
    k = np.flatnonzero(ok)[:, None]
    prior_im[k, idx, idx] = np.where(prior_off[ok, :1], 0.0, prior_frac[ok, :1] / prob.prior_sigma_att[ok] ** 2)
    prior_im[k, idx + 3, idx + 3] = np.where(prior_off[ok, 1:], 0.0, prior_frac[ok, 1:] / prob.prior_sigma_pos[ok] ** 2)
    q_point = precision.safe_inverse(n_p)
    n_image = precision.image_normals(jp, jr, w_obs, oi, prob.n_images) + prior_im
    if opt.rig and len(prob.rig_pairs):
        q_image = precision.coupled_inverse(n_image, prob.rig_pairs, np.repeat(
            [np.radians(opt.rig_sigma_deg) ** -2, opt.rig_sigma_m**-2], 3))
    else:
        q_image = precision.safe_inverse(n_image)
    red = precision.redundancy_numbers(jp, jr, 1.0 / opt.sigma_px**2 * np.ones(len(op)), q_point, q_image, op, oi)
    n_ties = precision.reduced_image_normals(jp, jr, w_obs, q_point, op, oi, prob.n_images) if opt.prior_tests else None
    return q_point, q_image, red, n_ties
