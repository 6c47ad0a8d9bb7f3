"""The ``match`` stage: connectivity graph, SIFT features, guided matching along graph edges, tracks, and
(option ``lsm_refine``) least-squares matching refinement of the track observations. SIFT (one image a unit) and
the pair matching (:data:`PAIRS_PER_UNIT` consecutive edges a unit) go through the run's executor.

Writes ``matching/graph.json`` (nodes, edges with overlap and match counts; weak pairs dropped),
``matching/ties.npz`` (tracks with their image observations), ``matching/features/<n>.npz`` (keypoints and
descriptors per image, reused when the stage reruns with the same feature count) and ``matching/targets.json``
(option ``targets``: the signalised ground points measured in the images, :mod:`.targets`; the ``aerotri`` stage
adjusts with the image measurements it lists).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import InputError, WorkspaceError
from ..io.photos import camera_bits, read_photo
from ..io.validate import resolve_image
from ..model import CameraModel, ImageBlock, Pose
from ..pipeline.atomic import atomic_path, write_json
from ..pipeline.stage import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    CheckedOptions,
    Range,
    Rule,
    Stage,
    StageResult,
)
from .features import BAND_SIGMAS, MatchOptions, guided_match, pose_sigma_px, rms_sigma, sift_features, verify
from .graph import GraphOptions, build_graph
from .navigation import coarse_guided_match, needs_correction
from .targets import SUSPECT_PX, TARGET_MODES, TARGETS_FILE, TargetShape, measure_targets, target_summary
from .tracks import build_tracks

FEATURES_VERSION = 3
"""Version of the cached keypoint files (2: keypoints in the pixel-centre origin; 3: photographs deeper than 8 bits
read by their significant bits); older caches are recomputed."""


def _azimuth_error(value: str) -> str | None:
    """What is wrong with a target azimuth option (degrees, or ``estimate``), or None."""
    if value.strip().lower() == "estimate":
        return None
    try:
        return None if np.isfinite(float(value)) else "degrees or 'estimate'"
    except ValueError:
        return "degrees or 'estimate'"


@dataclass(frozen=True)
class MatchConfig(CheckedOptions):
    """Options of the ``match`` stage (see :class:`GraphOptions` and :class:`MatchOptions`).

    ``z_ref`` is the footprint height and ``z_lo``/``z_hi`` the guided search range; NaN derives them from
    the ground points (or 0 m) and ``height_range`` metres above. ``band_px`` is the least half-width of the
    epipolar band; a pair whose images' prior sigmas move its points farther gets a wider one (:func:`pair_bands`),
    and one more than twice as wide first corrects its second image's pose from a few matches (:mod:`.navigation`).
    ``tie_source``: ``images`` (SIFT and guided matching) or ``file`` (tie points already in
    ``matching/ties.npz``, e.g. from another matcher or the observation simulator: only the graph is built, its
    edges counting the shared tracks). ``lsm_refine``:
    least-squares matching of each track's observations against its most nadir-like one (:mod:`.lsm`);
    observations it cannot confirm are dropped. On the rendered demo block it halved sigma0 (0.326 -> 0.147 px)
    and cut the tracks that miss their true point by 1.5 px from 7.3% to 2.5%, for about 3 minutes.

    ``targets``: measure the ground points' signalised targets in the images (:mod:`.targets`): ``none`` (the
    imported measurements as they are), ``missing`` (measured ones where the import has no measurement of a point
    in an image that sees it; the imported ones are checked against the measured ones) or ``all`` (every point in
    every image, in place of the imported measurements); the targets are a bright disc of ``target_disc_radius_m``
    on a dark square of half side ``target_square_half_m`` (0: a disc alone; a disc of 0: a bright square alone),
    or with ``target_pattern = checker`` a checkerboard square of that half side (the disc radius is not used), or
    with ``target_pattern = cross`` a bright cross whose bars reach that far from the centre, ``target_bar_half_m``
    wide on either side of their axes; the square's sides (the bars) lie at ``target_square_azimuth`` (degrees from
    the grid's x axis, counterclockwise, or ``estimate``, the default: found in each image; on the demo, whose
    targets lie along the grid, both find the same 166 of the 171 in sight), searched up to ``target_search_px``
    around the position the navigation data predict, kept from a correlation of ``target_min_score``."""

    min_overlap: float = 0.2
    max_axis_angle_deg: float = 50.0
    max_neighbours: int = 16
    max_features: int = 6000
    ratio: float = 0.85
    band_px: float = 25.0
    ransac_px: float = 1.5
    min_matches: int = 15
    min_rays: int = 2
    max_tracks_per_image: int = 0
    z_ref: float = float("nan")
    height_range: float = 60.0
    tie_source: str = "images"
    lsm_refine: bool = True
    targets: str = "none"
    target_disc_radius_m: float = 0.5
    target_square_half_m: float = 0.8
    target_square_azimuth: str = "estimate"
    target_pattern: str = "disc"
    target_bar_half_m: float = 0.15
    target_search_px: float = 20.0
    target_min_score: float = 0.9

    RULES: ClassVar[dict[str, Rule]] = {
        "min_overlap": FRACTION, "max_axis_angle_deg": Range(0.0, 180.0), "max_neighbours": AT_LEAST_ONE,
        "max_features": AT_LEAST_ONE, "ratio": Range(0.0, 1.0, lo_open=True), "band_px": POSITIVE,
        "ransac_px": POSITIVE, "min_matches": AT_LEAST_ONE, "min_rays": Range(2.0),
        "max_tracks_per_image": NON_NEGATIVE, "z_ref": Range(nan=True), "height_range": NON_NEGATIVE,
        "tie_source": ("images", "file"), "targets": TARGET_MODES, "target_disc_radius_m": NON_NEGATIVE,
        "target_square_half_m": NON_NEGATIVE, "target_square_azimuth": _azimuth_error,
        "target_pattern": ("disc", "checker", "cross"), "target_bar_half_m": POSITIVE,
        "target_search_px": POSITIVE, "target_min_score": Range(0.0, 1.0, lo_open=True)}


def target_shape(cfg: MatchConfig) -> TargetShape:
    """The signalised targets' shape of the match options; :class:`ConfigError` for sizes that make no target."""
    azimuth = None
    if cfg.target_square_azimuth.strip().lower() != "estimate":
        azimuth = float(cfg.target_square_azimuth)
    disc = 0.0 if cfg.target_pattern in ("checker", "cross") else cfg.target_disc_radius_m
    bar = cfg.target_bar_half_m if cfg.target_pattern == "cross" else 0.0
    return TargetShape(disc, cfg.target_square_half_m, azimuth, cfg.target_pattern, bar)


def _ground_height(block, cfg: MatchConfig) -> float:
    if np.isfinite(cfg.z_ref):
        return cfg.z_ref
    z = [gp.xyz[2] for gp in block.ground_points.values() if gp.xyz is not None]
    return float(np.median(z)) if z else 0.0


def _image_path(block, iid: str) -> str:
    img = block.images[iid]
    if img.file is None:
        raise InputError(f"image '{iid}' has no file", field="file")
    return str(resolve_image(block, img.file))


def read_block_grey(block, iid: str, bits: dict[str, int | None] | None = None) -> np.ndarray:
    """Image ``iid`` of ``block`` as grey values ``(h, w)`` from its file; :class:`InputError` naming it otherwise.
    ``bits``: the block's :func:`.io.photos.camera_bits`, sampled once by a caller that reads many images (else
    sampled here for this image's camera)."""
    cam = block.images[iid].camera_id
    bits = camera_bits(block, {cam}) if bits is None else bits
    return read_photo(_image_path(block, iid), False, iid, bits.get(cam))


def _photos(block, ids, bits: dict[str, int | None]) -> dict[str, tuple[str, int | None]]:
    """Image id -> its file and its camera's significant bits (``bits``: :func:`.io.photos.camera_bits`), for
    ``ids``."""
    return {iid: (_image_path(block, iid), bits.get(block.images[iid].camera_id)) for iid in ids}


def _read_image_of(photos: dict[str, tuple[str, int | None]], iid: str) -> np.ndarray:
    """The grey image ``iid`` from its file in ``photos`` (:func:`_photos`; picklable with
    :func:`functools.partial`: LSM units)."""
    path, bits = photos[iid]
    return read_photo(path, False, iid, bits)


def _cached(path: Path, iid: str, max_features: int, min_bits: int | None) -> bool:
    """Whether ``path`` holds this image's features at this feature count, version and camera depth."""
    if not path.exists():
        return False
    with np.load(path) as z:
        bits = int(z["min_bits"]) if "min_bits" in z.files else -1
        return (str(z["image"]) == iid and int(z["max_features"]) == max_features
                and "version" in z.files and int(z["version"]) == FEATURES_VERSION and bits == (min_bits or -1))


@dataclass(frozen=True)
class FeatureTask:
    """One image whose SIFT features :func:`extract_features` writes to ``out`` (``threads``: OpenCV threads of the
    worker, 0 = OpenCV's default, 1 when images run in parallel processes)."""

    image_id: str
    path: str
    out: str
    max_features: int
    threads: int = 0
    min_bits: int | None = None


@contextmanager
def _opencv_threads(n: int) -> Iterator[None]:
    """OpenCV uses ``n`` threads inside the block (0: leave them as they are)."""
    import cv2

    before = cv2.getNumThreads()
    if n > 0:
        cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def extract_features(task: FeatureTask) -> None:
    """Executor unit of the ``match`` stage: SIFT of one image, written to its feature cache file."""
    with _opencv_threads(task.threads):
        u, d = sift_features(read_photo(task.path, False, task.image_id, task.min_bits), task.max_features)
    with atomic_path(Path(task.out), suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, uv=u, des=d, image=task.image_id, max_features=task.max_features, version=FEATURES_VERSION,
                 min_bits=task.min_bits or -1)


PAIRS_PER_UNIT = 12
"""Graph edges per executor unit of the pair matching. The edges of an image with its neighbours follow each other
in the graph, so a unit of consecutive edges reads about as many feature files as it has edges."""


@dataclass(frozen=True)
class PairBatch:
    """Consecutive graph edges matched by one executor unit (:func:`match_pairs`).

    edges : ``(k, 2)`` image indices; features, cameras, poses : the feature cache file, camera and approximate
    pose of each image index the edges use; bands : each edge's epipolar band half-width ``(k,)`` (pixels);
    sigmas : each edge's relative navigation errors ``(k, 2)``, attitude (radians) and position (metres)
    (:func:`pair_sigmas`); threads : OpenCV threads of the worker (0 = OpenCV's default)
    """

    edges: np.ndarray
    features: dict[int, str]
    cameras: dict[int, CameraModel]
    poses: dict[int, Pose]
    opt: MatchOptions
    bands: np.ndarray
    sigmas: np.ndarray
    threads: int = 0


def match_pairs(batch: PairBatch) -> list[np.ndarray]:
    """Executor unit of the ``match`` stage: guided matching and verification of a few graph edges, each image's
    keypoints and descriptors read once from its feature cache file (nothing large is pickled to the worker).
    Returns the verified ``(k, 2)`` index pairs of each edge, in edge order."""
    feats = {}
    for k, path in batch.features.items():
        with np.load(path) as z:
            feats[k] = z["uv"], z["des"]
    out = []
    with _opencv_threads(batch.threads):
        for (a, b), band, (sig_att, sig_pos) in zip(batch.edges, batch.bands, batch.sigmas, strict=True):
            (uv_a, des_a), (uv_b, des_b) = feats[a], feats[b]
            ca, cb = batch.cameras[a], batch.cameras[b]
            if needs_correction(band, batch.opt.band_px):
                m = coarse_guided_match(uv_a, des_a, uv_b, des_b, ca, batch.poses[a], cb, batch.poses[b], batch.opt,
                                        float(band), float(sig_att), float(sig_pos))
            else:
                m = guided_match(uv_a, des_a, uv_b, des_b, ca, batch.poses[a], cb, batch.poses[b],
                                 replace(batch.opt, band_px=float(band)))
            if len(m):
                m = m[verify(uv_a[m[:, 0]], uv_b[m[:, 1]], ca, cb, batch.opt.ransac_px)]
            out.append(m)
    return out


def pair_bands(block: ImageBlock, ids: list[str], edges: np.ndarray, band_px: float, z_ground: float) -> np.ndarray:
    """Each edge's epipolar band half-width ``(k,)``: ``band_px``, or :data:`.features.BAND_SIGMAS` times the two
    images' navigation errors in pixels (:func:`.features.pose_sigma_px` at the distance along each one's viewing
    direction to the ground ``z_ground``) where that is wider."""
    sig = np.zeros(len(ids))
    for k, iid in enumerate(ids):
        img = block.images[iid]
        p = img.pose_approx
        down = -p.R[2, 2]  # the viewing direction's downward component
        distance = (p.C[2] - z_ground) / down if down > 0.1 else p.C[2] - z_ground
        sig[k] = pose_sigma_px(block.camera_of(img), img.sigma_position, img.sigma_attitude, float(distance))
    if len(edges) == 0:
        return np.zeros(0)
    return np.maximum(band_px, BAND_SIGMAS * np.hypot(sig[edges[:, 0]], sig[edges[:, 1]]))


def pair_sigmas(block: ImageBlock, ids: list[str], edges: np.ndarray) -> np.ndarray:
    """Each edge's relative navigation errors ``(k, 2)``: the two images' prior attitude sigmas (radians) and
    position sigmas (metres), each the RMS over the axes, added in quadrature; 0 where the images have none."""
    sig = np.array([[rms_sigma(block.images[iid].sigma_attitude), rms_sigma(block.images[iid].sigma_position)]
                    for iid in ids]).reshape(len(ids), 2)
    return np.hypot(sig[edges[:, 0]], sig[edges[:, 1]]) if len(edges) else np.zeros((0, 2))


def pair_batches(block: ImageBlock, ids: list[str], edges: np.ndarray, feature_files: list[str], opt: MatchOptions,
                 bands: np.ndarray, threads: int = 0, size: int = PAIRS_PER_UNIT) -> list[PairBatch]:
    """The edges cut into units of ``size`` consecutive edges (their order kept), with what each unit needs
    (``bands``: each edge's band half-width, :func:`pair_bands`)."""
    sigmas = pair_sigmas(block, ids, edges)
    out = []
    for k in range(0, len(edges), size):
        e = edges[k:k + size]
        used = [int(i) for i in np.unique(e)]
        imgs = {i: block.images[ids[i]] for i in used}
        out.append(PairBatch(e, {i: feature_files[i] for i in used}, {i: block.camera_of(imgs[i]) for i in used},
                             {i: imgs[i].pose_approx for i in used}, opt, bands[k:k + size], sigmas[k:k + size],
                             threads))
    return out


def run(ws, cfg: MatchConfig, ctx) -> StageResult:
    block = ws.load_block(adjusted=False)
    z0 = _ground_height(block, cfg)
    graph = build_graph(block, GraphOptions(min_overlap=cfg.min_overlap, max_axis_angle_deg=cfg.max_axis_angle_deg,
                                            z_ref=z0, max_neighbours=cfg.max_neighbours))
    ids = graph.image_ids
    out = ws.stage_dir("matching")
    bits = camera_bits(block)
    target_metrics = _measure_targets(ws, block, cfg, ctx, bits)
    if cfg.tie_source == "file":
        return _graph_from_ties(ws, block, graph, cfg, ctx, target_metrics)
    feat_dir = out / "features"
    feat_dir.mkdir(parents=True, exist_ok=True)
    executor = ctx.get_executor()
    threads = 1 if getattr(executor, "mode", "inline") != "inline" else 0  # one OpenCV thread per process
    files = [str(feat_dir / f"{k:06d}.npz") for k in range(len(ids))]
    cam_bits = [bits.get(block.images[iid].camera_id) for iid in ids]
    todo = [FeatureTask(iid, _image_path(block, iid), files[k], cfg.max_features, threads, cam_bits[k])
            for k, iid in enumerate(ids) if not _cached(Path(files[k]), iid, cfg.max_features, cam_bits[k])]
    total = 2 * len(ids)
    ctx.progress(len(ids) - len(todo), total, f"features: {len(todo)} images to extract")
    executor.map(extract_features, todo,
                 on_done=lambda d, t: ctx.progress(len(ids) - t + d, total, f"features {d}/{t}"))
    uv = []
    for f in files:
        with np.load(f) as z:
            uv.append(z["uv"])
    opt = MatchOptions(max_features=cfg.max_features, ratio=cfg.ratio, band_px=cfg.band_px, z_lo=z0 - 5.0,
                       z_hi=z0 + cfg.height_range, ransac_px=cfg.ransac_px, min_matches=cfg.min_matches)
    bands = pair_bands(block, ids, graph.edges, cfg.band_px, z0)
    batches = pair_batches(block, ids, graph.edges, files, opt, bands, threads)
    found = executor.map(match_pairs, batches, on_done=lambda d, t: ctx.progress(
        len(ids) + d * len(ids) // t, total, f"matched {d}/{t} units of {PAIRS_PER_UNIT} pairs"))
    matches = {}
    for e, ((a, b), m) in enumerate(zip(graph.edges, [m for ms in found for m in ms], strict=True)):
        graph.matches[e] = len(m)
        if len(m) >= opt.min_matches:
            matches[(int(a), int(b))] = m
    corrected = int(np.sum(needs_correction(bands, cfg.band_px) & (graph.matches >= opt.min_matches)))
    dropped = graph.drop_weak(opt.min_matches)
    ties = build_tracks(uv, matches, ids, min_rays=cfg.min_rays, max_per_image=cfg.max_tracks_per_image)
    lsm_metrics = {}
    if cfg.lsm_refine and ties.n_obs:
        from .lsm import refine_ties

        ties, st = refine_ties(ties, block, partial(_read_image_of, _photos(block, ids, bits)), progress=ctx.progress,
                               executor=executor)
        lsm_metrics = {"lsm_" + k: v for k, v in st.as_dict().items()}
    ties.save(str(out / "ties.npz"))
    write_json(out / "graph.json", graph.to_dict(block))
    rays = ties.ray_counts()
    ctx.progress(1, 1, "done")
    return StageResult(
        outputs=("matching/graph.json", "matching/ties.npz", TARGETS_FILE),
        metrics={"edges": len(graph.edges), "dropped_edges": dropped,
                 "corrected_pairs": corrected, "tracks": ties.n_tracks,
                 "observations": ties.n_obs, "mean_rays": float(rays.mean()) if len(rays) else 0.0, **lsm_metrics,
                 **target_metrics},
        message=f"{len(graph.edges)} pairs ({dropped} weak dropped"
                + (f", {corrected} matched after correcting coarse navigation data" if corrected else "")
                + f"), {ties.n_tracks} tracks, "
                f"{ties.n_obs} observations" + _targets_message(target_metrics))


def _measure_targets(ws, block, cfg: MatchConfig, ctx, bits: dict[str, int | None]) -> dict:
    """Measure the signalised ground points (option ``targets``), write :data:`.targets.TARGETS_FILE`, return its
    figures (:func:`.targets.target_summary`) as metrics, none when nothing was to be measured."""
    shape = target_shape(cfg)
    measuring = cfg.targets != "none"
    photos = _photos(block, [iid for iid, img in block.images.items() if measuring and img.file is not None], bits)
    record = measure_targets(block, partial(_read_image_of, photos), cfg.targets, shape, cfg.target_search_px,
                             cfg.target_min_score, progress=ctx.progress,
                             executor=ctx.get_executor() if measuring else None)
    write_json(ws.path(TARGETS_FILE), record)
    if cfg.targets == "none":
        return {}
    summary = target_summary(record)
    return {"targets_measured": summary["measured"], "targets_missed": summary["missed"],
            "targets_score_median": summary["score_median"], "targets_imported_rms_px": summary["imported_rms_px"],
            "targets_suspect": len(summary["suspect"])}


def _targets_message(metrics: dict) -> str:
    if not metrics:
        return ""
    text = f"; {metrics['targets_measured']} target measurements ({metrics['targets_missed']} not found"
    if metrics["targets_imported_rms_px"] is not None:
        text += f", {metrics['targets_imported_rms_px']:.2f} px RMS from the imported ones"
    if metrics["targets_suspect"]:
        text += f", {metrics['targets_suspect']} imported ones more than {SUSPECT_PX:g} px off"
    return text + ")"


def _graph_from_ties(ws, block, graph, cfg: MatchConfig, ctx, target_metrics: dict) -> StageResult:
    """Graph edges weighted by the tracks two images share in existing tie points."""
    from ..model import TiePoints

    path = ws.path("matching/ties.npz")
    if not path.exists():
        raise WorkspaceError(f"{path}: match.tie_source is 'file' but there are no tie points")
    ties = TiePoints.load(str(path))
    ctx.progress(0, 1, "graph from tie points")
    graph.matches = pair_counts(ties, graph.image_ids, graph.edges)
    dropped = graph.drop_weak(cfg.min_matches)
    write_json(ws.path("matching/graph.json"), graph.to_dict(block))
    ctx.progress(1, 1, "done")
    return StageResult(outputs=("matching/graph.json", "matching/ties.npz", TARGETS_FILE),
                       metrics={"edges": len(graph.edges), "dropped_edges": dropped, "tracks": ties.n_tracks,
                                "observations": ties.n_obs, **target_metrics},
                       message=f"{len(graph.edges)} pairs ({dropped} weak dropped), {ties.n_tracks} tracks "
                               "from matching/ties.npz" + _targets_message(target_metrics))


def pair_counts(ties, image_ids: list[str], edges: np.ndarray) -> np.ndarray:
    """Number of tracks observed in both images of each edge ``(e, 2)`` (indices into ``image_ids``)."""
    from scipy.sparse import csr_matrix

    index = {iid: k for k, iid in enumerate(image_ids)}
    col = np.array([index.get(i, -1) for i in ties.image_ids])[ties.obs_image]
    ok = col >= 0
    m = csr_matrix((np.ones(ok.sum()), (ties.obs_track[ok], col[ok])), shape=(ties.n_tracks, len(image_ids)))
    m.data[:] = 1.0
    co = (m.T @ m).tocsr()
    return np.asarray(co[edges[:, 0], edges[:, 1]]).ravel().astype(np.int64) if len(edges) else np.zeros(0, np.int64)


STAGE = Stage(name="match", run=run, config=MatchConfig, requires=("block",),
              description="connectivity graph, SIFT, guided matching along graph edges, tracks, LSM refinement, "
                          "signalised targets",
              version="7",
              adjusted_block=False)
