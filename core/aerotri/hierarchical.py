"""Integrated (IAT) and hierarchical (HAT) aerial triangulation, connection point selection (CBA), baselines.

* IAT: all images, all tie points and control points in one adjustment.
* HAT, as in the seed: (1) the nadir sub-block with the datum (GNSS priors, control points, datum shift);
  (2) each cardinal oblique sub-block (north, east, south, west by actual viewing direction) with its own tie
  points plus *connection points*: tie points adjusted in the nadir block and introduced as ground observations
  with their propagated 3x3 covariance. Selection: every tie point with >= k nadir rays (k = 2, 3, 5, 10), or
  CBA: a grid of ``cell`` metres over the block and in each cell the point with the most rays (nadir + that
  view). Control points measured in the view are observations there too (their datum shift is the nadir run's,
  held fixed). The four oblique runs are independent and go through the executor (inline, processes or Dask),
  each with its share of the threads. The oblique blocks start from the nadir corrections propagated to the
  other heads of each exposure; from there their blunders are tested at the start (``BundleOptions.screen_start``)
  instead of by a robust solve, so each oblique run needs one least-squares solve. The first part of that
  screened start (a screening and one resection step, :func:`.bundle.resected_start`) needs no connection point:
  it starts from the nadir run's robust round and runs in a thread of this process while the nadir run finishes
  (:class:`_EarlyStart`, which builds the sub-blocks while the robust round computes); the oblique runs then screen
  once, with their connection points. With workers, each run frees its solver after handing back its result, and
  the nadir run's goes once the workers have the oblique runs (``adjust``'s ``keep``).
  Optionally (``oblique_ties_per_cell``) the oblique runs adjust a thinned, regularly distributed subset of their
  tie points (a production practice); the rest are intersected afterwards with the final orientations.
  (3) Combined statistics by error propagation: a point's information is the nadir information plus each
  oblique block's own contribution (its information minus the connection prior it received); the datum shift is
  refined from all control measurements (the nadir run saw only the nadir ones). (4) The tracks a run held with
  one or two rays (where its tests cannot find a blunder) are tested again over all their rays with the final
  orientations (:func:`weak_tracks`). With rig constraints (``BundleOptions.rig``), between (3) and (4) the heads of
  each exposure, adjusted apart in their runs, are fused into one body on the calibrated rig (:mod:`.rigfusion`).
  GNSS offsets per strip (``BundleOptions.gnss_strips``) are estimated in the nadir run, like the datum shift, and
  held for the other heads of the same exposures (one antenna) in the oblique runs. So are the tie sigma and the
  scales of the GNSS/IMU prior sigmas and of the control measurements' sigmas the nadir run estimated
  (``BundleOptions.tie_sigma_estimate``, ``prior_sigma_estimate``, ``control_sigma_estimate``): the oblique runs
  start from them (one GNSS/IMU system, one way of measuring the targets) and estimate them further.
  With self-calibration (``BundleOptions.self_calibration``) a calibration sub-block comes first: the images of the
  exposures nearest the block's centre, all views, adjusted together (as IAT) with the cameras' parameters free;
  the hierarchical runs then hold the cameras it calibrated. Calibrated in the runs themselves, a nadir run hardly
  tells the focal length from the flying height (on 500 simulated images with every camera imported 0.3 % long in
  focal length its focal length came out with a standard deviation of 1.2 px, against 0.08 px in IAT, and the check
  points' Z RMS was 1.41 GSD against IAT's 0.18), and a head that looks in two directions on crossing strips would be
  calibrated twice, once per view run, each time differently. After a 250-image calibration sub-block HAT's check
  points came out at 0.14 / 0.18 GSD (XY / Z), as IAT's.
* Baselines: direct georeferencing (the navigation orientations) and nadir-only AT whose per-exposure
  corrections are propagated to the oblique images of the same exposure.
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import ConfigError
from ..geometry.views import OBLIQUE_VIEWS
from ..model import ImageBlock, Pose, TiePoints
from ..model.exposures import estimate_rig
from .bundle import (
    PRIOR_PARTS,
    BundleOptions,
    BundleProblem,
    BundleResult,
    adjust,
    frame_poses,
    image_focals,
    refine_points,
    release_heap,
    resected_start,
    reserve_heap,
    screen_points,
)
from .precision import point_jacobians, point_normals, safe_inverse
from .problem import (
    SubProblem,
    build_problem,
    intersect_rays,
    intersect_ties,
    pose_arrays,
    ray_directions,
    restarted,
    result_poses,
    thin_ties,
    track_shares,
)
from .rigfusion import FusionStats, fuse_on_rig, rig_relations
from .strips import Strips, flight_strips, strip_offsets, strip_table

CONNECTIONS = ("cba", "2", "3", "5", "10")


@dataclass(eq=False)
class Run:
    """One adjustment of (a subset of) the block, mapped back to the block's tie arrays.

    Attributes
    ----------
    name : ``iat``, ``nadir``, ``north``...
    poses : adjusted orientations of the images that took part
    image_std : image id -> (6,) std (rotation about world X Y Z in radians, centre in metres)
    track_index : (p,) tracks adjusted; xyz (p, 3); xyz_cov (p, 3, 3)
    obs_index : (m,) observations used; obs_rejected (m,); obs_residual (m, 2)
    result : the bundle result (statistics); connection_count : connection points used (oblique runs)
    frames : the orientations of the frames of those images: with a mounting calibration the images' corrections
        removed (:func:`.bundle.frame_poses`), else the images' own; the navigation data describe these
    control_rejected : control points whose coordinates the run rejected; control_obs_rejected : (control point,
        image) of the measurements it rejected (see :func:`.bundle.control_point_tests`)
    prior_rejected : (image, ``attitude`` or ``position``) of the EO priors it rejected (see
        :func:`.bundle.prior_tests`); prior_w : image -> (2,) the normalised differences of its attitude and position
        prior in the last test (a rejected part's when it was rejected; NaN: untested)
    gnss_strips : strip name -> its GNSS offset and drift as estimated by this run (:func:`.strips.strip_table`;
        empty when the run estimated none)
    control_names : the names of the control points of the run's problem, in the order of its result's arrays
    """

    name: str
    poses: dict[str, Pose]
    image_std: dict[str, np.ndarray]
    track_index: np.ndarray
    xyz: np.ndarray
    xyz_cov: np.ndarray
    obs_index: np.ndarray
    obs_rejected: np.ndarray
    obs_residual: np.ndarray
    result: BundleResult
    connection_count: int = 0
    connection_info: np.ndarray | None = None
    wall_s: float = 0.0
    frames: dict[str, Pose] = field(default_factory=dict)
    control_rejected: tuple[str, ...] = ()
    control_obs_rejected: tuple[tuple[str, str], ...] = ()
    prior_rejected: tuple[tuple[str, str], ...] = ()
    prior_w: dict[str, np.ndarray] = field(default_factory=dict)
    gnss_strips: dict[str, dict] = field(default_factory=dict)
    control_names: tuple[str, ...] = ()


@dataclass(eq=False)
class ATResult:
    """Outcome of IAT or HAT: final poses, combined tie points and every run; ``calibration`` the calibration
    sub-block of HAT with self-calibration (its orientations are not the block's: the runs adjusted them again)."""

    mode: str
    poses: dict[str, Pose]
    image_std: dict[str, np.ndarray]
    xyz: np.ndarray
    xyz_cov: np.ndarray
    obs_rejected: np.ndarray
    runs: list[Run]
    connection: str = ""
    wall_s: float = 0.0
    extra: dict = field(default_factory=dict)
    calibration: Run | None = None

    def calibrating_runs(self) -> list[Run]:
        """The runs that self-calibrated the cameras: HAT's calibration sub-block when it had one, else the runs."""
        return [self.calibration] if self.calibration is not None else self.runs

    def control_rejections(self) -> tuple[set[str], set[tuple[str, str]]]:
        """The control points whose coordinates a run rejected, and the (point, image) measurements rejected."""
        return rejected_control(self.runs)

    def prior_rejections(self) -> set[tuple[str, str]]:
        """The (image, ``attitude`` or ``position``) EO priors a run rejected."""
        return {o for run in self.runs for o in run.prior_rejected}

    def gnss_strips(self) -> dict[str, dict]:
        """The GNSS strip offsets and drifts the runs estimated (IAT's, or HAT's nadir run's), by strip name."""
        return {name: d for run in self.runs for name, d in run.gnss_strips.items()}

    def sigma0_px(self) -> float:
        """The tie measurements' a posteriori sigma over all runs, pixels (:func:`sigma0_px`)."""
        return sigma0_px(self.runs)


def sigma0_px(runs: list[Run]) -> float:
    """The a posteriori sigma of the tie measurements over ``runs``, pixels: each run's sigma0 times its a priori
    sigma (runs may have estimated different ones, see ``BundleOptions.tie_sigma_estimate``), combined by their
    degrees of freedom."""
    dof = sum(r.result.redundancy for r in runs)
    chi = sum((r.result.sigma0 * r.result.sigma_px) ** 2 * r.result.redundancy for r in runs)
    return float(np.sqrt(chi / max(dof, 1)))


def camera_runs(block: ImageBlock, runs: list[Run]) -> dict[str, tuple[Run, int, int]]:
    """Camera id -> the run holding most of its images (in HAT a head that looks in two directions on crossing
    strips takes part in two runs), the camera's index in that run's cameras and its image count there."""
    best: dict[str, tuple[Run, int, int]] = {}
    for run in runs:
        counts = Counter(block.images[iid].camera_id for iid in run.poses)
        for ci, cam in enumerate(run.result.cameras):
            n = counts.get(cam.id, 0)
            if n > (best[cam.id][2] if cam.id in best else 0):
                best[cam.id] = (run, ci, n)
    return best


def rejected_control(runs: list[Run]) -> tuple[set[str], set[tuple[str, str]]]:
    """Over ``runs``: the control points whose coordinates one rejected, and the (point, image) measurements."""
    return {n for run in runs for n in run.control_rejected}, {o for run in runs for o in run.control_obs_rejected}


def _to_run(name: str, sub: SubProblem, res: BundleResult, wall: float) -> Run:
    prob = sub.problem
    poses = result_poses(sub, res)
    std = {iid: res.image_std[k] for k, iid in enumerate(prob.image_ids) if res.image_adjusted[k]}
    r_f, c_f = frame_poses(res.r_cam_from_world, res.c_world, prob.image_camera, res.mounting)
    frames = {iid: Pose(r_f[k], c_f[k]) for k, iid in enumerate(prob.image_ids) if iid in poses}
    return Run(name=name, poses=poses, image_std=std, track_index=sub.track_index, xyz=res.xyz,
               xyz_cov=res.xyz_cov, obs_index=sub.obs_index, obs_rejected=res.obs_rejected,
               obs_residual=res.obs_residual, result=res, wall_s=wall, frames=frames,
               control_rejected=tuple(prob.gcp_names[g] for g in np.flatnonzero(res.gcp_rejected)),
               control_obs_rejected=tuple((prob.gcp_names[prob.gcp_obs_point[k]], prob.image_ids[prob.gcp_obs_image[k]])
                                          for k in np.flatnonzero(res.gcp_obs_rejected)),
               prior_rejected=tuple((prob.image_ids[k], PRIOR_PARTS[part])
                                    for k, part in zip(*np.nonzero(res.prior_rejected))),
               prior_w={iid: res.prior_w[k] for k, iid in enumerate(prob.image_ids)
                        if k < len(res.prior_w) and np.isfinite(res.prior_w[k]).any()},
               gnss_strips=strip_table(prob.strip_names, prob.prior_strip, res.gnss_strip, res.gnss_strip_std),
               control_names=tuple(prob.gcp_names))


def initial_tie_coordinates(block: ImageBlock, ties: TiePoints) -> np.ndarray:
    """Tie coordinates ``(n, 3)`` by multi-ray forward intersection from the approximate orientations."""
    xyz, _ = intersect_ties(block, ties, {i: im.pose_approx for i, im in block.images.items()})
    return xyz


def integrated(block: ImageBlock, ties: TiePoints, opt: BundleOptions,
               progress: Callable[[int, int, str], None] | None = None,
               xyz0: np.ndarray | None = None) -> ATResult:
    """IAT: all images in one adjustment."""
    t0 = time.perf_counter()
    xyz0 = initial_tie_coordinates(block, ties) if xyz0 is None else xyz0
    sub = build_problem(block, ties, list(block.images), xyz0, strips=_strips(block, opt))
    res = adjust(sub.problem, opt, progress)
    run = _to_run("iat", sub, res, time.perf_counter() - t0)
    xyz = np.full((ties.n_tracks, 3), np.nan)
    cov = np.full((ties.n_tracks, 3, 3), np.nan)
    xyz[run.track_index], cov[run.track_index] = run.xyz, run.xyz_cov
    rej = np.zeros(ties.n_obs, bool)
    rej[run.obs_index] = run.obs_rejected
    return ATResult(mode="integrated", poses=run.poses, image_std=run.image_std, xyz=xyz, xyz_cov=cov,
                    obs_rejected=rej, runs=[run], wall_s=time.perf_counter() - t0)


def central_images(block: ImageBlock, n_images: int) -> list[str]:
    """The images of the exposures nearest the block's centre (every head of an exposure; an image without an
    exposure counts as one), the nearest first, until about ``n_images`` (a whole exposure more at most)."""
    exposures: dict[str, list[str]] = {}
    for iid, im in block.images.items():
        if im.pose_approx is not None:
            exposures.setdefault(im.exposure or iid, []).append(iid)
    centre = {e: np.mean([block.images[i].pose_approx.C[:2] for i in ids], 0) for e, ids in exposures.items()}
    if not centre:
        return []
    mid = np.mean(list(centre.values()), 0)
    out: list[str] = []
    for e in sorted(exposures, key=lambda e: float(np.sum((centre[e] - mid) ** 2))):
        if len(out) >= n_images:
            break
        out += exposures[e]
    return out


def _strips(block: ImageBlock, opt: BundleOptions) -> Strips | None:
    """The block's flight strips when the adjustment estimates GNSS offsets per strip."""
    return flight_strips(block) if opt.gnss_strips != "off" else None


def select_connections(xyz: np.ndarray, candidate: np.ndarray, rays: np.ndarray, nadir_rays: np.ndarray,
                       connection: str, cell: float) -> np.ndarray:
    """Connection points for one oblique view.

    Parameters
    ----------
    xyz : (n, 3) tie coordinates from the nadir block (NaN: not adjusted there)
    candidate : (n,) bool tracks seen in the oblique view and adjusted in the nadir block
    rays : (n,) rays of each track counted for CBA (nadir + this view); nadir_rays : (n,) nadir rays
    connection : ``cba`` or a minimum nadir ray count ``2``, ``3``, ``5``, ``10``
    cell : CBA grid cell in metres

    Returns
    -------
    (n,) bool mask of the selected tracks
    """
    if connection not in CONNECTIONS:
        raise ConfigError(f"unknown connection selection '{connection}' (use one of {', '.join(CONNECTIONS)})")
    ok = candidate & np.isfinite(xyz[:, 0]) & (nadir_rays >= 2)
    if connection != "cba":
        return ok & (nadir_rays >= int(connection))
    idx = np.flatnonzero(ok)
    out = np.zeros(len(xyz), bool)
    if len(idx) == 0:
        return out
    ij = np.floor(xyz[idx, :2] / cell).astype(np.int64)
    key = (ij[:, 0] - ij[:, 0].min()) * (ij[:, 1].max() - ij[:, 1].min() + 1) + (ij[:, 1] - ij[:, 1].min())
    order = np.lexsort((-rays[idx], key))
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    out[idx[order[first]]] = True
    return out


HEAP_BYTES_PER_OBSERVATION = 1200
"""Heap an oblique run takes per observation (the 3,000-image block: 0.55-0.6 GB for 548,000, beside its
sub-block), which the workers map while the nadir run computes (:func:`.bundle.reserve_heap`)."""


def _warm_up(item: tuple[float, int]) -> None:
    """Executor unit run once per worker while the nadir run computes, ``(hold_s, heap_bytes)``: imports the solver
    (a second or two per process), loads the compiled kernels of the statistics (numba's start, 0.2 s, on a first
    call), maps ``heap_bytes`` of heap for the oblique runs (:func:`.bundle.reserve_heap`) and holds the worker
    until ``hold_s`` have passed so that the pool spreads these units over all its workers."""
    t0 = time.perf_counter()
    hold_s, heap_bytes = item
    import pyceres  # noqa: F401
    import pycolmap  # noqa: F401

    point_normals(np.zeros((1, 2, 3)), np.ones(1), np.zeros(1, np.int64), 1)
    if heap_bytes > 0:
        reserve_heap(heap_bytes)
    time.sleep(max(0.0, hold_s - (time.perf_counter() - t0)))


def _worker_heap(largest_run_obs: int, workers: int) -> int:
    """Bytes of heap each worker maps for the oblique runs: :data:`HEAP_BYTES_PER_OBSERVATION` per observation of
    the largest run, at most an eighth of the machine's memory shared by the workers (the nadir run still holds its
    own)."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # no sysconf (Windows)
        return 0
    return int(min(HEAP_BYTES_PER_OBSERVATION * largest_run_obs, memory / (8 * max(1, workers))))


RELEASE_DELAY_S = 0.05
"""Seconds a worker waits after an oblique run before it frees the run's solver (:func:`_adjust_unit`): the
result of 500,000 observations (30 MB) is pickled and sent in about 30 ms."""


def _adjust_unit(item: tuple[str, SubProblem, BundleOptions, bool]) -> tuple[str, BundleResult, float]:
    """Executor unit: one oblique sub-block (module-level so process pools and Dask can pickle it). With the
    item's last value (a worker process) the run's solver is freed by a timer thread once the result is on its way
    (``adjust``'s ``keep``): a quarter of a second that the last runs no longer keep the combination waiting for."""
    name, sub, opt, in_worker = item
    t0 = time.perf_counter()
    keep: list | None = [] if in_worker else None
    res = adjust(sub.problem, opt, keep=keep)
    wall = time.perf_counter() - t0
    if keep is not None:
        threading.Timer(RELEASE_DELAY_S, keep.clear).start()
    return name, res, wall


def _resected(prob: BundleProblem, opt: BundleOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`.bundle.resected_start` of an oblique sub-block from its start values (all observations with a start
    point) -> ``r (k, 3, 3)``, ``c (k, 3)``, points ``(p, 3)``, the screening's sigma0."""
    idx = np.flatnonzero(np.isfinite(prob.xyz[prob.obs_point, 0]) & np.all(np.isfinite(prob.obs_uv), 1))
    return resected_start(prob.cameras, prob.image_camera, prob.r_cam_from_world, prob.c_world, prob.xyz,
                          prob.obs_point[idx], prob.obs_image[idx], prob.obs_uv[idx], opt)


def _largest_first(in_runs: dict[str, np.ndarray]) -> list[str]:
    """The views of ``in_runs`` (view -> its observations in the run, ``(m,) bool``), the most observations first
    (the order the oblique runs are started in, so that the last to start is a short one)."""
    return sorted(in_runs, key=lambda v: -int(np.count_nonzero(in_runs[v])))


@dataclass(eq=False)
class _EarlyStart:
    """The oblique runs moved to their inliers (:func:`.bundle.resected_start`: screening with the cameras held,
    one resection step) from the nadir run's robust round, while the nadir run goes on.

    The oblique runs need the final nadir run for their connection points only; their start (the nadir corrections
    propagated to the other heads) serves the blunder tests at the start, for which the robust round's orientations
    are as good (on the 3,000-image block they differ from the final ones by 0.09-0.17 of the final standard
    deviations, median). The tie points start from the nadir run's robust round where it holds them, else from
    their intersection from the navigation data (``xyz0``): the screening's Gauss-Newton step moves them from there
    (intersecting them again from the propagated orientations first took 2 s on the 3,000-image block and changed
    nothing printed: the same 78,599 rejections, check point RMS and standard deviations).

    Called as ``adjust``'s ``on_robust`` hook with the nadir orientations and points. With ``parallel`` (an
    executor with workers) :meth:`begin` starts a thread of this process when the nadir run starts: it builds the
    sub-blocks (their observations do not depend on the nadir run) while the robust round computes, then waits for
    its orientations, restarts the sub-blocks from them and resects them one after the other, the largest first
    (mostly compiled code, which leaves the interpreter to the nadir run, on the core the nadir run leaves idle in
    its single-threaded parts). :meth:`ready` gives them as they are done, taking itself the sub-blocks the thread
    has not started yet, so that the core the nadir run freed does not wait; each can go to the executor's workers
    while the others are still being resected. Inline otherwise (when :meth:`ready` is asked, with the same
    values). Building the sub-blocks only once the robust round had ended left two of the four resections to run
    beside the first two oblique runs, which then took 4.0-4.2 s instead of 3.2-3.3 s (3,000-image block). Sending
    the sub-blocks to the executor's workers instead did not help on 2 cores: the nadir run and the set-up after it
    took 16.4-19.6 s with the thread (3 runs of the 3,000-image block), 19.5 s with one worker, 17.7-19.3 s with
    both."""

    block: ImageBlock
    ties: TiePoints
    views: dict[str, list[str]]
    in_runs: dict[str, np.ndarray]
    nadir_problem: SubProblem
    xyz0: np.ndarray
    opt: BundleOptions
    parallel: bool = False
    before: threading.Thread | None = None
    _start: tuple | None = field(default=None, init=False)
    _thread: threading.Thread | None = field(default=None, init=False)
    _error: BaseException | None = field(default=None, init=False)
    _thread_done: bool = field(default=False, init=False)
    _discarded: bool = field(default=False, init=False)
    _cond: threading.Condition = field(default_factory=threading.Condition, init=False)
    _xyz_start: np.ndarray | None = field(default=None, init=False)
    _todo: list | None = field(default=None, init=False)  # (view, sub-block) not started yet, once set up
    _outs: dict = field(default_factory=dict, init=False)

    def begin(self) -> None:
        """Start the thread (with ``parallel``): the sub-blocks are built while the nadir run computes."""
        if self.parallel:
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()

    def __call__(self, r: np.ndarray, c: np.ndarray, xyz: np.ndarray) -> None:
        with self._cond:
            self._start = (r, c, xyz)
            self._cond.notify_all()

    def _run(self) -> None:
        try:
            if self.before is not None:
                self.before.join()
            subs = self._build()
            with self._cond:
                while self._start is None and not self._discarded:
                    self._cond.wait()
            if not self._discarded:
                self._set_up(subs)
                self._work()
        except BaseException as e:  # noqa: BLE001 - handed to the caller in ready()
            self._error = e
        finally:
            with self._cond:
                self._thread_done = True
                self._cond.notify_all()

    def ready(self) -> Iterator[tuple[str, tuple, np.ndarray]]:
        """The early starts as they are done: view, (image ids, tracks ``(p,)``, ``r (k, 3, 3)``, ``c (k, 3)``,
        points ``(p, 3)``, sigma0), and the start points ``(n, 3)`` of all tracks. Raises what the computation
        raised. Nothing without an early start (the nadir run had no robust round)."""
        given: set[str] = set()
        try:
            if self._start is None:
                return
            if self._thread is None and self._todo is None:
                self._set_up(self._build())
            while True:
                with self._cond:
                    while True:
                        if self._error is not None:
                            raise self._error
                        new = [v for v in self._outs if v not in given]
                        if new or self._todo or self._thread is None or self._thread_done:
                            break
                        self._cond.wait()
                    task = self._todo.pop(0) if not new and self._todo else None
                if task is not None:
                    self._resect(*task)
                elif not new:
                    return
                for v in [v for v in self._outs if v not in given]:
                    given.add(v)
                    yield v, self._outs[v], self._xyz_start
        finally:
            self.discard()

    def discard(self) -> None:
        """Let a running early start end after the sub-block it is on and drop what it has not started (the nadir
        run failed or was cancelled, or the caller has what it needs)."""
        if self._thread is not None:
            with self._cond:
                self._discarded = True
                self._todo = []
                self._cond.notify_all()
            self._thread.join()

    def _build(self) -> list[tuple[str, SubProblem]]:
        """The sub-blocks (the largest first) from the navigation data and ``xyz0``."""
        return [(v, build_problem(self.block, self.ties, self.views[v], self.xyz0, obs_mask=self.in_runs[v],
                                  use_control=False)) for v in _largest_first(self.in_runs)]

    def _set_up(self, subs: list[tuple[str, SubProblem]]) -> None:
        """The start orientations and points; the sub-blocks restarted from them. The start points are finite where
        ``xyz0`` is (the nadir run's tracks are a subset of those), so the sub-blocks keep their observations."""
        r, c, xyz = self._start
        prob_n = self.nadir_problem.problem
        start = nadir_propagation(self.block, {iid: Pose(r[k], c[k]) for k, iid in enumerate(prob_n.image_ids)})
        xyz_start = self.xyz0.copy()
        xyz_start[self.nadir_problem.track_index] = np.where(np.isfinite(xyz[:, :1]), xyz,
                                                             xyz_start[self.nadir_problem.track_index])
        subs = [(v, restarted(sub, self.block, start, xyz_start)) for v, sub in subs]
        with self._cond:
            self._xyz_start = xyz_start
            if self._todo is None and not self._discarded:
                self._todo = subs
            self._cond.notify_all()

    def _work(self) -> None:
        """Resect the sub-blocks not started yet, one after the other (the thread)."""
        while True:
            with self._cond:
                if not self._todo:
                    return
                task = self._todo.pop(0)
            self._resect(*task)

    def _resect(self, v: str, sub: SubProblem) -> None:
        out = (sub.problem.image_ids, sub.track_index, *_resected(sub.problem, self.opt))
        with self._cond:
            self._outs[v] = out
            self._cond.notify_all()


def hierarchical(block: ImageBlock, ties: TiePoints, opt: BundleOptions, connection: str = "cba",
                 cell: float = 50.0, executor=None, progress: Callable[[int, int, str], None] | None = None,
                 xyz0: np.ndarray | None = None, connection_sigma_scale: float = 1.0,
                 oblique_control: bool = True, oblique_tie_grid: int = 8, oblique_ties_per_cell: int = 0,
                 combined_datum: bool = True, calibration_images: int = 500) -> ATResult:
    """HAT as in the module docstring. ``executor`` has ``map(fn, items, on_done)`` (see pipeline.executor);
    ``connection_sigma_scale`` multiplies the propagated connection standard deviations; with
    ``oblique_control`` the control points measured in an oblique view are observations of its run too (with
    the datum shift of the nadir run held fixed), as they are in IAT.

    ``oblique_ties_per_cell > 0`` thins the tie points of the oblique runs (the nadir run keeps all of them) by
    :func:`.problem.thin_ties`: per oblique image a grid of ``oblique_tie_grid`` cells across, in each cell the
    ``oblique_ties_per_cell`` tracks with most rays in the view; connection points always stay. Every tie point
    still gets coordinates: the tracks with thinned observations are intersected afterwards from all their rays
    with the final orientations, with blunder tests (:func:`intersect_and_test`, starting from the combined
    coordinates where a run gave some), and those coordinates replace the combined ones. ``0`` adjusts all tie
    points in the oblique runs.

    With ``combined_datum`` the datum shift, estimated in the nadir run from the nadir measurements of the control
    points alone, is refined in step (3) from all their measurements (:func:`datum_correction`) and the whole
    block is translated by the correction, as IAT estimates the shift from all views at once.

    With ``opt.self_calibration`` the cameras are calibrated first on the sub-block of :func:`central_images` of
    ``calibration_images`` images (the module docstring; its run is :attr:`ATResult.calibration`); the runs then
    hold them. ``0`` calibrates each camera in the runs holding its images instead (the run holding most of its
    images gives the block its camera)."""
    t0 = time.perf_counter()
    if connection not in CONNECTIONS:
        raise ConfigError(f"unknown connection selection '{connection}' (use one of {', '.join(CONNECTIONS)})")
    xyz0 = initial_tie_coordinates(block, ties) if xyz0 is None else xyz0
    calibration = None
    if opt.self_calibration and calibration_images > 0:
        t_c = time.perf_counter()
        ids = central_images(block, calibration_images)
        sub_c = build_problem(block, ties, ids, xyz0, strips=_strips(block, opt))
        res_c = adjust(sub_c.problem, opt, None if progress is None else
                       (lambda d, t, m: progress(0, 2, f"self-calibration on the {len(ids)} central images: {m}")))
        calibration = _to_run("calibration", sub_c, res_c, time.perf_counter() - t_c)
        block = replace(block, cameras={**block.cameras, **{cam.id: cam for cam in res_c.cameras}})
        # the runs start from the tie sigma and the prior and control sigmas' scales the sub-block estimated
        # (BundleOptions.tie_sigma_estimate, prior_sigma_estimate, control_sigma_estimate)
        opt = replace(opt, self_calibration=(), sigma_px=res_c.sigma_px,
                      prior_sigma_scale=tuple(res_c.prior_sigma_scale.tolist()),
                      control_sigma_scale=res_c.control_sigma_scale)
    views = block.images_by_view()
    nadir_ids = views.get("nadir", [])
    if not nadir_ids:
        raise ConfigError("hierarchical AT needs nadir images (none found by viewing direction)")
    # (1) nadir sub-block with the datum
    t1 = time.perf_counter()
    # views as small integer codes (comparing millions of strings per view is slow): 0 nadir, 1.. obliques
    codes = {v: k for k, v in enumerate(("nadir", *OBLIQUE_VIEWS))}
    code_of_image = {iid: codes[v] for v, ids in views.items() if v in codes for iid in ids}
    view_of_obs = np.array([code_of_image.get(i, -1) for i in ties.image_ids], np.int8)[ties.obs_image]
    # the worker processes start, import the solver and map heap for the oblique runs while the nadir run computes
    parallel = executor is not None and getattr(executor, "mode", "inline") != "inline"
    warm = None
    if parallel:
        workers = max(1, int(getattr(executor, "workers", 1)))
        heap = _worker_heap(int(np.bincount(view_of_obs[view_of_obs > 0]).max(initial=0)), workers)
        # (a generator: a list of one unit would run in this process)
        warm = threading.Thread(target=executor.map, args=(_warm_up, iter([(0.5, heap)] * workers)), daemon=True)
        warm.start()
    strips = _strips(block, opt)
    sub_n = build_problem(block, ties, nadir_ids, xyz0, obs_mask=view_of_obs == 0, strips=strips)
    n = ties.n_tracks
    # the oblique views' observations and the thinning, which do not depend on the nadir run
    pre_views = {}
    for v in OBLIQUE_VIEWS:
        ids = views.get(v, [])
        if not ids:
            continue
        in_view = view_of_obs == codes[v]
        rays_v = np.bincount(ties.obs_track[in_view], minlength=n)
        kept = (thin_ties(block, ties, in_view, rays_v, oblique_tie_grid, oblique_ties_per_cell)
                if oblique_ties_per_cell > 0 else None)
        pre_views[v] = (ids, in_view, rays_v, kept)
    early = _EarlyStart(block, ties, views, {v: in_view if kept is None else in_view & kept[ties.obs_track]
                                             for v, (_, in_view, _, kept) in pre_views.items()},
                        sub_n, xyz0, opt, parallel, warm)
    if pre_views:
        early.begin()
    # with workers the nadir run's solver is freed once they have the oblique runs (items below), not before
    nadir_keep: list | None = [] if parallel else None
    try:
        res_n = adjust(sub_n.problem, opt, None if progress is None else
                       (lambda d, t, m: progress(d, t * 2, "nadir: " + m)), on_robust=early if pre_views else None,
                       keep=nadir_keep)
    except BaseException:
        early.discard()
        raise
    nadir = _to_run("nadir", sub_n, res_n, time.perf_counter() - t1)
    xyz_nadir = np.full((n, 3), np.nan)
    cov_nadir = np.full((n, 3, 3), np.nan)
    xyz_nadir[nadir.track_index], cov_nadir[nadir.track_index] = nadir.xyz, nadir.xyz_cov
    nadir_ok_obs = np.zeros(ties.n_obs, bool)
    nadir_ok_obs[nadir.obs_index[~nadir.obs_rejected]] = True
    nadir_rays = np.bincount(ties.obs_track[nadir_ok_obs], minlength=n)
    cov_ok = np.all(np.isfinite(safe_inverse(np.nan_to_num(cov_nadir)).reshape(n, 9)), 1)
    # (2) oblique sub-blocks tied by connection points
    # start values of the oblique blocks: each exposure's nadir correction propagated to its other heads; their
    # tie points start where the nadir run or the navigation data put them (the screening at the start of each
    # oblique run moves them onto its rays with a Gauss-Newton step)
    start_poses = nadir_propagation(block, nadir.frames)
    # the GNSS strip offsets the nadir run estimated hold for the other heads of its exposures (one antenna)
    offsets = strip_offsets(strips, res_n.gnss_strip, list(block.images)) if strips is not None else None
    thinned_obs = np.zeros(ties.n_obs, bool)
    per_view = []
    for v, (ids, in_view, rays_v, kept) in pre_views.items():
        sel = select_connections(xyz_nadir, (rays_v > 0) & cov_ok, nadir_rays + rays_v, nadir_rays, connection, cell)
        # the observations of the view's run: all of the view's, or those of the tracks kept by the thinning
        in_run = in_view
        if kept is not None:
            in_run = in_view & (kept | sel)[ties.obs_track]
            thinned_obs |= in_view & ~in_run
        per_view.append((v, ids, sel, in_run))
    # the oblique runs' items, made as their early starts are done (see _EarlyStart; in order of readiness, the
    # largest first) so that the workers start on the first while the others are resected; without an early start
    # the largest first. Start coordinates of the tracks that enter an oblique run (thinned tracks are intersected
    # at the end): the nadir run's where it adjusted them, else those of the early start, else intersected from
    # the navigation data.
    conn_counts, conn_masks, subs = {}, {}, {}
    # parallel units share the cores: each gets its part of the threads
    threads = opt.threads
    if parallel and len(per_view) > 1:
        threads = max(1, opt.threads // min(len(per_view), max(1, int(getattr(executor, "workers", 1)))))

    def item(v: str, ids: list[str], sel: np.ndarray, in_run: np.ndarray, pre: tuple | None,
             xyz_pre: np.ndarray) -> tuple[str, SubProblem, BundleOptions, bool]:
        prior_xyz = np.where(sel[:, None], xyz_nadir, np.nan)
        prior_cov = np.where(sel[:, None, None], cov_nadir * connection_sigma_scale**2, np.nan)
        opt_v = replace(opt, datum_shift=not oblique_control and opt.datum_shift, screen_start=True,
                        gnss_strips="off", threads=threads, sigma_px=res_n.sigma_px,
                        prior_sigma_scale=tuple(res_n.prior_sigma_scale.tolist()),
                        control_sigma_scale=res_n.control_sigma_scale)
        initial, x_v = start_poses, np.where(np.isfinite(xyz_nadir[:, :1]), xyz_nadir, xyz_pre)
        # (the early start's sigma0 is in units of the given tie sigma, the gate in those of the nadir run's)
        if pre is not None and pre[5] * opt.sigma_px / res_n.sigma_px <= opt.screen_max_sigma0:
            # moved to its inliers already: the run starts there and screens once
            ids_e, tracks_e, r_e, c_e, x_e, _ = pre
            initial = {iid: Pose(r_e[k], c_e[k]) for k, iid in enumerate(ids_e)}
            fin = np.isfinite(x_e[:, 0])
            x_v[tracks_e[fin]] = x_e[fin]
            opt_v = replace(opt_v, screen_resect=False)
        sub = build_problem(block, ties, ids, x_v, obs_mask=in_run, use_control=oblique_control,
                            point_prior_xyz=prior_xyz, point_prior_cov=prior_cov, prior_shift=res_n.datum_shift,
                            initial=initial, prior_offsets=offsets)
        conn_counts[v], conn_masks[v], subs[v] = int(sel.sum()), sel, sub
        return v, sub, opt_v, parallel

    by_view = {v: (ids, sel, in_run) for v, ids, sel, in_run in per_view}

    def items() -> Iterator[tuple[str, SubProblem, BundleOptions, bool]]:
        made = set()
        for v, pre, xyz_pre in early.ready():
            made.add(v)
            yield item(v, *by_view[v], pre, xyz_pre)
        for v in _largest_first({v: by_view[v][2] for v in by_view if v not in made}):
            yield item(v, *by_view[v], None, xyz0)
        # the workers have every run: the nadir run's solver goes, and what it and the set-up freed goes back to the
        # system before the intersection
        if nadir_keep is not None:
            nadir_keep.clear()
        release_heap()

    if warm is not None:
        warm.join()
    done_cb = None if progress is None else (lambda d, t: progress(t + d, 2 * t, f"oblique blocks {d}/{t}"))
    t2 = time.perf_counter()
    setup_wall = t2 - t1 - nadir.wall_s
    outputs = (executor.map(_adjust_unit, items(), done_cb, total=len(per_view)) if executor is not None
               else [_adjust_unit(it) for it in items()])
    by_name = {name: (res, wall) for name, res, wall in outputs}
    oblique_wall = time.perf_counter() - t2
    runs = [nadir]
    for v in by_view:
        run = _to_run(v, subs[v], *by_name[v])
        run.connection_count = conn_counts[v]
        runs.append(run)
    # (3) combination by error propagation
    t3 = time.perf_counter()
    poses = {}
    for run in runs:
        poses.update(run.poses)
    xyz, cov = combine_points(n, runs, conn_masks, cov_nadir, connection_sigma_scale)
    rej = np.zeros(ties.n_obs, bool)
    for run in runs:
        rej[run.obs_index] |= run.obs_rejected
    datum_delta = np.zeros(3)
    datum_cov = np.diag(res_n.datum_shift_std**2)
    run_subs = list(zip(runs, [sub_n, *(subs[v] for v in by_view)]))
    if combined_datum:
        centre_var = {iid: s[3:] ** 2 for run, sub in run_subs
                      for iid, s in zip(sub.problem.image_ids, run.result.image_std_relative)}
        datum_delta, datum_cov = datum_correction(block, poses, *rejected_control(runs), centre_var)
        poses = {i: Pose(p.R, p.C + datum_delta) for i, p in poses.items()}
        xyz = xyz + datum_delta
        for run in runs:
            run.poses = {i: Pose(p.R, p.C + datum_delta) for i, p in run.poses.items()}
            run.xyz = run.xyz + datum_delta
    if res_n.image_std_kind == "marginal" and np.all(np.isfinite(datum_cov)):
        # the datum's uncertainty, common to all images (the oblique runs hold the nadir run's shift): that of the
        # block's shift enters every centre's standard deviations, in place of the nadir run's own
        for run, sub in run_subs:
            run.image_std = datum_std(sub.problem.image_ids, run.result, datum_cov)
    std = {}
    for run in runs:
        std.update(run.image_std)
    combine_wall = time.perf_counter() - t3
    # (3b) on a rig, each exposure's heads fused into one body (module rigfusion)
    fusion = {}
    if opt.rig and block.rigs:
        t_f = time.perf_counter()
        used = np.zeros(ties.n_obs, bool)
        for run in runs:
            used[run.obs_index[run.result.obs_used]] = True
        poses, xyz, fused_std, stats = fuse_heads(block, ties, run_subs, poses, xyz, used, opt.blunder_threshold,
                                                  opt.mounting, opt.threads, progress)
        std.update(fused_std)
        fusion = {"rig_fusion": stats.as_dict(), "rig_fusion_wall_s": time.perf_counter() - t_f}
    # tracks tested over all their rays with the final orientations and intersected from the rays kept, in one
    # pass: those thinned out of the oblique runs, and (4) those a run held with one or two rays (weak_tracks), from
    # scratch (of two rays a run rejects either: their tests are equal)
    t4 = time.perf_counter()
    thinned = np.zeros(n, bool)
    thinned[ties.obs_track[thinned_obs]] = True
    weak = weak_tracks(ties, [run.obs_index for run in runs]) & ~thinned
    in_weak = weak[ties.obs_track]
    xt, ct, rt = intersect_and_test(block, ties, poses, ~rej | in_weak, thinned | weak, sigma0_px(runs), 1.0,
                                    opt.blunder_threshold, executor=executor, xyz_start=xyz)
    ok = weak | (thinned & np.isfinite(xt[:, 0]))
    xyz[ok], cov[ok] = xt[ok], ct[ok]
    final_tests = {"final_test_tracks": int(weak.sum()), "final_test_rejected": int((rt & in_weak & ~rej).sum()),
                   "final_test_restored": int((rej & in_weak & ~rt).sum())}
    rej = np.where(in_weak, rt, rej | rt)
    return ATResult(mode="hierarchical", poses=poses, image_std=std, xyz=xyz, xyz_cov=cov, obs_rejected=rej,
                    runs=runs, connection=connection, wall_s=time.perf_counter() - t0, calibration=calibration,
                    extra={"calibration_wall_s": calibration.wall_s if calibration is not None else 0.0,
                           "nadir_wall_s": nadir.wall_s, "setup_wall_s": setup_wall, "oblique_wall_s": oblique_wall,
                           "combine_wall_s": combine_wall, "intersection_wall_s": time.perf_counter() - t4,
                           "cell": cell, "thinned_observations": int(thinned_obs.sum()), **final_tests,
                           "datum_shift": res_n.datum_shift + datum_delta, "datum_correction": datum_delta,
                           "datum_shift_std": np.sqrt(np.diag(datum_cov)), **fusion})


def runs_rig(block: ImageBlock, poses: dict[str, Pose]) -> ImageBlock:
    """A copy of ``block`` whose rig is the one the runs' orientations ``poses`` give: each head's mounting relative
    to the reference head averaged over the exposures (:func:`.model.exposures.estimate_rig`, outlying exposures
    left out). A mounting calibration (``BundleOptions.mounting``) says the rig's is not known; each run calibrates
    its heads' mountings against the GNSS/IMU priors of its own images only, and on the rendered demo (25
    exposures) that rig made the fusion's attitude worse than the runs' (0.0122 against 0.0096 deg RMS) where the
    averaged one made it better (0.0078; the true rig 0.0080)."""
    images = {iid: replace(img, pose_approx=poses[iid]) for iid, img in block.images.items() if iid in poses}
    rig, _ = estimate_rig(replace(block, images=images))
    return replace(block, images=images, rigs={rig.name: rig})


def fuse_heads(block: ImageBlock, ties: TiePoints, run_subs: list[tuple[Run, SubProblem]], poses: dict[str, Pose],
               xyz: np.ndarray, obs_ok: np.ndarray, gate: float = 4.3,
               calibrating: bool = False, threads: int = 1, progress: Callable[[int, int, str], None] | None = None
               ) -> tuple[dict[str, Pose], np.ndarray, dict[str, np.ndarray], FusionStats]:
    """HAT's step (3b) with ``BundleOptions.rig``: the heads of each exposure fused on the rig
    (:func:`.rigfusion.fuse_on_rig`) from the combined ``poses`` and tie points ``xyz (n, 3)``, with the tie
    measurements ``obs_ok (m,)`` the runs accepted, the runs' GNSS/IMU prior residuals and weights (the parts they
    rejected left out), the control points and measurements they kept, the cameras of the runs holding most of
    their images (:func:`camera_runs`) and the runs' a posteriori tie sigma; ``gate``: the normalised residual above
    which a measurement is left out (``BundleOptions.blunder_threshold``). The rig: the block's, or with
    ``calibrating`` (the runs calibrated the mountings) the one the runs' orientations give (:func:`runs_rig`);
    ``threads`` share the measurements.

    The fused images' standard deviations ``(6,)`` are two-level (:mod:`.rigfusion`): their body's own normal block
    and the block's smooth modes, its translation among them (the nadir run's datum variance is not added again).

    Returns the poses, the tie points, those standard deviations and the statistics."""
    ids = [i for i in ties.image_ids if i in poses]
    index = np.full(len(ties.image_ids), -1, np.int64)
    index[[k for k, i in enumerate(ties.image_ids) if i in poses]] = np.arange(len(ids))
    runs = [run for run, _ in run_subs]
    run_of = {iid: run.name for run in runs for iid in run.poses}
    best = camera_runs(block, runs)
    cam_ids = sorted({block.images[i].camera_id for i in ids})
    cameras = [best[cid][0].result.cameras[best[cid][1]] if cid in best else block.cameras[cid] for cid in cam_ids]
    image_camera = np.array([cam_ids.index(block.images[i].camera_id) for i in ids], np.int64)
    ref, rel_r, rel_b = rig_relations(runs_rig(block, poses) if calibrating else block, ids)
    # the priors as the runs left them: residuals at their poses, weights relative to a tie measurement
    at = {iid: k for k, iid in enumerate(ids)}
    e_run = np.zeros((len(ids), 6))
    info = np.zeros((len(ids), 6))
    for run, sub in run_subs:
        prob, res = sub.problem, run.result
        if len(res.prior_residual_att) == 0:
            continue
        for j, iid in enumerate(prob.image_ids):
            k = at.get(iid)
            if k is None or iid not in run.poses:
                continue
            e_run[k] = np.concatenate([res.prior_residual_att[j], res.prior_residual_pos[j]])
            sig = res.prior_sigma_scale * np.concatenate([prob.prior_sigma_att[j], prob.prior_sigma_pos[j]])
            keep = np.repeat(~res.prior_rejected[j], 3) & np.isfinite(sig) & np.isfinite(e_run[k])
            info[k] = np.where(keep, (res.sigma_px / np.where(keep, sig, 1.0)) ** 2, 0.0)
    use = obs_ok & (index[ties.obs_image] >= 0)
    r = np.array([poses[i].R for i in ids])
    c = np.array([poses[i].C for i in ids])
    # the control points the runs kept, as points with their coordinates observed, and their measurements: without
    # them the steps drift along the block's weak modes towards what the GNSS positions alone give (on the rendered
    # demo the check points' Z RMS grew from 0.011 to 0.037 m in three steps, 0.069 m in twelve)
    sigma_px = runs[0].result.sigma_px
    gone, gone_obs = rejected_control(runs)
    gcps = [gp for gp in block.ground_points.values()
            if gp.kind == "control" and gp.xyz is not None and gp.name not in gone]
    g_obs = [(g, at[i], uv, (sigma_px / gp.sigma_px) ** 2) for g, gp in enumerate(gcps)
             for i, uv in gp.observations.items() if i in at and (gp.name, i) not in gone_obs]
    n_t = len(xyz)
    xyz_all = np.vstack([xyz, np.array([gp.xyz for gp in gcps], np.float64).reshape(-1, 3)])
    prior_xyz = np.vstack([np.full((n_t, 3), np.nan), xyz_all[n_t:]])
    prior_info = np.zeros((len(xyz_all), 3, 3))
    prior_info[n_t:] = [np.diag((sigma_px / np.asarray(gp.sigma, np.float64)) ** 2) for gp in gcps]
    r, c, xyz_all, cof, stats = fuse_on_rig(
        cameras, image_camera, r, c, xyz_all,
        np.concatenate([ties.obs_track[use], [n_t + o[0] for o in g_obs]]).astype(np.int64),
        np.concatenate([index[ties.obs_image[use]], [o[1] for o in g_obs]]).astype(np.int64),
        np.vstack([ties.obs_uv[use], np.array([o[2] for o in g_obs], np.float64).reshape(-1, 2)]), ref, rel_r,
        rel_b, e_run, info, obs_weight=np.concatenate([np.ones(int(use.sum())), [o[3] for o in g_obs]]),
        point_prior_xyz=prior_xyz, point_prior_info=prior_info, gate=gate, threads=threads,
        image_group=np.array([run_of.get(i, "") for i in ids]), progress=progress)
    xyz = xyz_all[:n_t]
    var = sigma0_px(runs) ** 2 * np.diagonal(cof, axis1=1, axis2=2)
    fused_std = {ids[k]: np.sqrt(var[k]) for k in np.flatnonzero(np.isfinite(var[:, 0]))}
    out = dict(poses)
    out.update({iid: Pose(r[k], c[k]) for k, iid in enumerate(ids)})
    return out, xyz, fused_std, stats


def datum_std(image_ids: list[str], res: BundleResult, datum_cov: np.ndarray) -> dict[str, np.ndarray]:
    """Standard deviations ``(6,)`` per adjusted image of a run (ids in the order of its problem) in the control
    frame: those relative to the datum (``BundleResult.image_std_relative``) with the variances of a datum shift of
    covariance ``datum_cov (3, 3)`` added to the centres' (the shift's correlation with the orientations left out)."""
    var = np.diag(datum_cov)
    return {iid: np.concatenate([s[:3], np.sqrt(s[3:] ** 2 + var)])
            for iid, s, adjusted in zip(image_ids, res.image_std_relative, res.image_adjusted) if adjusted}


def weak_tracks(ties: TiePoints, run_obs: list[np.ndarray]) -> np.ndarray:
    """The tracks ``(n,) bool`` that some run holds with one or two rays, or that have an observation no run holds.

    A run sees a track's rays in its own view only. One ray there is not adjusted (nor tested), and two rays test
    only across their epipolar line: a blunder along it moves the point and stays. The other views see most of these
    tracks too (a median of 16 rays in all views for the blunders HAT-CBA missed on the 3,000-image block), so HAT
    tests their observations again over all their rays with the final orientations (:func:`intersect_and_test`).
    Tested from scratch (of two rays a run rejects either: their tests are equal). On the 3,000-image block that is
    23 % of the tracks and 17 % of the observations, 0.4 s on 2 processes; the planted blunders found went from
    98.8 % to 99.84 % (IAT 99.96 %), false alarms from 0.051 % to 0.037 %, and the tie points of 10 rays or more
    came closer to IAT's (RMS difference XY 6.7 -> 3.4 mm, Z 10.6 -> 5.3 mm).

    ``run_obs``: per run the indices ``(k,)`` of its observations."""
    weak = np.zeros(ties.n_tracks, bool)
    held = np.zeros(ties.n_obs, bool)
    for idx in run_obs:
        held[idx] = True
        counts = np.bincount(ties.obs_track[idx], minlength=ties.n_tracks)
        weak |= (counts > 0) & (counts <= 2)
    weak[ties.obs_track[~held]] = True
    return weak


def combine_points(n: int, runs: list[Run], conn_masks: dict[str, np.ndarray], cov_nadir: np.ndarray,
                   conn_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Combined coordinates ``(n, 3)`` and covariances ``(n, 3, 3)`` of all tracks over the runs.

    Information adds up; for a connection point an oblique run's own information is its information minus the
    connection prior (which is the nadir information already counted), applied to the oblique run's estimate."""
    info = np.zeros((n, 3, 3))
    rhs = np.zeros((n, 3))
    xyz_nadir = np.full((n, 3), np.nan)
    for run in runs:
        ok = np.isfinite(run.xyz[:, 0]) & np.all(np.isfinite(run.xyz_cov.reshape(-1, 9)), 1)
        t = run.track_index[ok]
        ni = safe_inverse(run.xyz_cov[ok])
        x = run.xyz[ok]
        if run.name == "nadir":
            xyz_nadir[t] = x
        else:
            conn = conn_masks.get(run.name, np.zeros(n, bool))[t]
            if conn.any():
                tc = t[conn]
                prior_info = safe_inverse(cov_nadir[tc] * conn_scale**2)
                own = ni[conn] - prior_info
                # an own information that is not positive semi-definite (numerical noise) counts as none
                dg = np.diagonal(own, axis1=1, axis2=2)
                minors = dg[:, [0, 0, 1]] * dg[:, [1, 2, 2]] - own[:, [0, 0, 1], [1, 2, 2]] ** 2
                own[(dg < 0).any(1) | (minors < 0).any(1) | (np.linalg.det(own) < 0)] = 0.0
                info[tc] += own
                rhs[tc] += np.einsum("kij,kj->ki", own, x[conn])
                t, ni, x = t[~conn], ni[~conn], x[~conn]
        # a run's tracks are unique, so plain fancy-index additions suffice (np.add.at is slow)
        info[t] += ni
        rhs[t] += np.einsum("kij,kj->ki", ni, x)
    xyz = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    inv = safe_inverse(info)
    ok = np.all(np.isfinite(inv.reshape(n, 9)), 1)
    cov[ok] = inv[ok]
    xyz[ok] = np.einsum("kij,kj->ki", cov[ok], rhs[ok])
    return xyz, cov


def direct_georeferencing(block: ImageBlock) -> dict[str, Pose]:
    """Baseline without AT: the navigation (approximate) orientations."""
    return {i: im.pose_approx for i, im in block.images.items() if im.pose_approx is not None}


def nadir_propagation(block: ImageBlock, nadir_poses: dict[str, Pose]) -> dict[str, Pose]:
    """Baseline: every image gets the correction its exposure's nadir image received in a nadir-only AT.

    The exposure moves as one rigid body: ``R_adj = R_approx R_nadir_approx^T R_nadir_adj`` (the head's mounting
    is kept) and ``C_adj = C_nadir_adj + R_nadir_adj^T R_nadir_approx (C_approx - C_nadir_approx)`` (the lever
    arm between the heads turns with the exposure). Images without an adjusted nadir partner keep their
    navigation orientation."""
    nadir_of_exposure = {}
    for iid, p in nadir_poses.items():
        img = block.images[iid]
        if img.exposure is not None:
            nadir_of_exposure[img.exposure] = (img.pose_approx, p)
    out = {}
    for iid, img in block.images.items():
        if iid in nadir_poses:
            out[iid] = nadir_poses[iid]
            continue
        pair = nadir_of_exposure.get(img.exposure)
        if pair is None or img.pose_approx is None:
            if img.pose_approx is not None:
                out[iid] = img.pose_approx
            continue
        a, b = pair
        out[iid] = Pose(img.pose_approx.R @ a.R.T @ b.R, b.C + b.R.T @ (a.R @ (img.pose_approx.C - a.C)))
    return out


def intersect_and_test(block: ImageBlock, ties: TiePoints, poses: dict[str, Pose], obs_ok: np.ndarray,
                       tracks: np.ndarray, sigma_px: float, sigma0: float, threshold: float, max_rounds: int = 6,
                       executor=None, share_obs: int = 1_000_000, xyz_start: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tie points from the final orientations (cameras fixed) with blunder tests: from a start (``xyz_start (n, 3)``
    where finite, else the multi-ray forward intersection) a Gauss-Newton step on the pixel residuals, then each
    round rejects every track's worst ray whose normalised residual ``|v| / (sigma0 sigma_px sqrt(r))`` (r its
    redundancy number for the point alone) exceeds ``threshold``; only tracks that lost a ray take another step,
    from where they are. With a parallel ``executor`` the tracks are split into shares of at most ``share_obs``
    observations, the same number for every worker (only their observation arrays travel; a unit needs a few
    hundred bytes per observation).

    ``obs_ok : (m,)`` observations allowed; ``tracks : (n,)`` bool tracks to compute. Returns ``xyz (n, 3)`` and
    ``cov (n, 3, 3)`` (NaN for tracks not computed or with fewer than two rays) and the rejected ``(m,)``."""
    n, m = ties.n_tracks, ties.n_obs
    cameras, image_camera, r, c = pose_arrays(block, ties.image_ids, poses)
    use = obs_ok & tracks[ties.obs_track] & np.isfinite(c[ties.obs_image, 0])
    start = np.full((n, 3), np.nan) if xyz_start is None else np.asarray(xyz_start, np.float64)
    parallel = executor is not None and getattr(executor, "mode", "inline") != "inline"
    # a whole number of shares per worker (balanced waves), none above ``share_obs`` observations (memory)
    workers = max(1, int(getattr(executor, "workers", 1))) if parallel else 1
    shares = workers * max(1, -(-int(use.sum()) // (workers * max(share_obs, 1))))
    items, index = [], []
    for idx in track_shares(ties.obs_track, np.flatnonzero(use), shares):
        # tracks of the share numbered 0.. in track order (a rank table instead of a sort)
        seen = np.zeros(n, bool)
        seen[ties.obs_track[idx]] = True
        pts = np.flatnonzero(seen)
        rank = np.cumsum(seen) - 1
        index.append((idx, pts))
        items.append((cameras, image_camera, r, c, rank[ties.obs_track[idx]], ties.obs_image[idx], ties.obs_uv[idx],
                      start[pts], sigma_px, sigma0, threshold, max_rounds))
    outs = executor.map(_intersect_unit, items) if parallel else [_intersect_unit(it) for it in items]
    xyz = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    rejected = np.zeros(m, bool)
    for (idx, pts), (x, q, rej) in zip(index, outs):
        xyz[pts], cov[pts] = x, q
        rejected[idx] = rej
    return xyz, cov, rejected


def _intersect_unit(item: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Executor unit of :func:`intersect_and_test` over arrays: ``(cameras, image_camera (k,), r (k, 3, 3),
    c (k, 3), obs_point (m,), obs_image (m,), obs_uv (m, 2), xyz_start (n, 3), sigma_px, sigma0, threshold,
    max_rounds)`` -> ``xyz (n, 3)``, ``cov (n, 3, 3)``, rejected ``(m,)``. The worker's freed heap is handed back
    afterwards."""
    out = _intersect_share(*item)
    release_heap()
    return out


def _intersect_share(cameras: list, image_camera: np.ndarray, r: np.ndarray, c: np.ndarray, op_all: np.ndarray,
                     oi_all: np.ndarray, uv_all: np.ndarray, xyz_start: np.ndarray, sigma_px: float, sigma0: float,
                     threshold: float, max_rounds: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_intersect_unit` with its arguments spelt out."""
    n = len(xyz_start)
    x = np.array(xyz_start, np.float64)
    missing = ~np.isfinite(x[:, 0])
    if missing.any():
        sel = np.flatnonzero(missing[op_all])
        d = ray_directions(cameras, image_camera, r, oi_all[sel], uv_all[sel], undistort_iterations=4)
        x0, _ = intersect_rays(np.take(c, oi_all[sel], 0), d, op_all[sel], n)
        x[missing] = x0[missing]
    return screen_points(cameras, image_camera, r, c, op_all, oi_all, uv_all, x, sigma_px, sigma0, threshold,
                         max_rounds)[:3]


def datum_correction(block: ImageBlock, poses: dict[str, Pose], rejected: set[str] | None = None,
                     rejected_obs: set[tuple[str, str]] | None = None,
                     centre_var: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Translation ``(3,)`` that best moves the block onto its control points, with its covariance ``(3, 3)``: each
    control point is intersected from all its image measurements with ``poses`` (covariance from its pixel sigma,
    plus the mean of its images' centre variances ``centre_var`` (image -> ``(3,)``, relative to the datum) where
    given: the block's local position error, which the images around a point share), and the differences to the
    given coordinates are averaged with the inverse of (intersection covariance + control covariance). Zero, with an
    infinite covariance, when no control point has two measured rays. All control points are intersected together
    (arrays over their measurements). Control points named in ``rejected`` and the (point, image) measurements in
    ``rejected_obs`` (the adjustment's blunder tests, :meth:`ATResult.control_rejections`) are left out."""
    rejected, rejected_obs = rejected or set(), rejected_obs or set()

    def used(gp, iid: str) -> bool:
        return iid in poses and (gp.name, iid) not in rejected_obs

    gps = [gp for gp in block.ground_points.values()
           if gp.kind == "control" and gp.xyz is not None and gp.name not in rejected
           and sum(used(gp, i) for i in gp.observations) >= 2]
    if not gps:
        return np.zeros(3), np.diag(np.full(3, np.inf))
    image_ids = sorted({i for gp in gps for i in gp.observations if used(gp, i)})
    k_of = {iid: k for k, iid in enumerate(image_ids)}
    obs = [(g, k_of[i], uv) for g, gp in enumerate(gps) for i, uv in gp.observations.items() if used(gp, i)]
    op = np.array([o[0] for o in obs], np.int64)
    oi = np.array([o[1] for o in obs], np.int64)
    uv = np.array([o[2] for o in obs], np.float64).reshape(-1, 2)
    cameras, image_camera, r, c = pose_arrays(block, image_ids, poses)
    d = ray_directions(cameras, image_camera, r, oi, uv)
    x, _ = intersect_rays(c[oi], d, op, len(gps))
    ok_obs = np.isfinite(x[op, 0])
    x = refine_points(cameras, image_camera, r, c, x, op, oi, uv, ok_obs)
    fx, fy = image_focals(cameras, image_camera)
    sigma_px = np.array([gp.sigma_px for gp in gps])
    jp = point_jacobians(r, c, fx, fy, x, op, oi)
    q = safe_inverse(point_normals(np.nan_to_num(jp), np.where(ok_obs, sigma_px[op] ** -2.0, 0.0), op, len(gps)))
    info = np.zeros((3, 3))
    rhs = np.zeros(3)
    for g, gp in enumerate(gps):
        if not np.all(np.isfinite(q[g])) or not np.all(np.isfinite(x[g])):
            continue
        local = [centre_var[i] for i in gp.observations if used(gp, i) and centre_var and i in centre_var]
        w = np.linalg.inv(q[g] + np.diag(np.asarray(gp.sigma, np.float64) ** 2 + (np.mean(local, 0) if local else 0.0)))
        info += w
        rhs += w @ (np.asarray(gp.xyz, np.float64) - x[g])
    if not np.any(info):
        return np.zeros(3), np.diag(np.full(3, np.inf))
    cov = np.linalg.inv(info)
    return cov @ rhs, cov
