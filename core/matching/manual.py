"""Manual image measurements of ground points: the operator's own positions, which override the others.

The automatic target measurement (:mod:`.targets`) misses a target beside a bright edge, a target partly hidden or
painted differently; an imported measurement can be on the wrong spot. Every photogrammetric tool lets the operator
place or correct such a measurement by hand. Here those edits live in one workspace file, :data:`MANUAL_FILE`, which
the ``aerotri`` stage reads last (after the import and ``matching/targets.json``) and whose content enters its
fingerprint, so that a changed measurement makes the adjustment stale:

``{"format": "oblique-city-manual-measurements", "version": 1, "observations": {point: {image: entry}}}``

with ``entry`` either ``{"uv": [u, v], "method": "click" | "target", "score": float | null}`` (pixels, centre of the
top-left pixel at 0, 0; ``target``: the click refined by fitting the target there, with the fit's correlation) or
``null``: the point is not measured in that image (a wrong measurement removed).

:func:`points_in_image` lists what an image shows of the ground points (the prediction from the best orientation
known, the measurement the adjustment will take and where it comes from), for the CLI and the Blender panel, from a
:class:`MeasurementState` read once (a panel keeps it while the files do not change); :func:`set_manual` and
:func:`reset_manual` edit the file atomically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.projection import project
from ..io.validate import read_json
from ..model import ImageBlock
from ..pipeline.atomic import write_json
from .stage import STAGE as MATCH_STAGE
from .stage import read_block_grey, target_shape
from .targets import TARGETS_FILE, TargetShape, apply_targets, measure_target

MANUAL_FILE = "block/manual_measurements.json"
"""The operator's measurements (workspace-relative); an input of the ``aerotri`` stage."""

FORMAT = "oblique-city-manual-measurements"
METHODS = ("click", "target")

SNAP_SEARCH_PX = 6.0
"""How far from the click the target is searched when a click is refined (``method = target``): a click lands
within a few pixels of the target's centre."""

SNAP_MIN_SCORE = 0.75
"""The correlation a refined click needs. Lower than the automatic measurement's 0.9: the operator has said where the
target is, so the fit only has to find its centre near there (on the demo the automatic search's wrong matches
elsewhere reach 0.75 only 8-16 px away from the target, beyond :data:`SNAP_SEARCH_PX`)."""


@dataclass(frozen=True)
class PointInImage:
    """A ground point as one image shows it: ``predicted`` (2,) its projection with the best orientation known
    (adjusted once aerial triangulation has run), ``uv`` (2,) the measurement the adjustment takes (None: none) and
    ``source``: ``imported``, ``targets`` (the ``match`` stage's), ``manual`` or ``removed`` (an operator removed
    it), ``none`` without any."""

    name: str
    kind: str
    predicted: np.ndarray
    uv: np.ndarray | None
    source: str


def read_manual(path: str | Path) -> dict[str, dict[str, dict | None]]:
    """The observations of a manual measurement file (``{}`` when there is none), checked: :class:`InputError`
    naming the file and the field otherwise."""
    path = Path(path)
    if not path.exists():
        return {}
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a manual measurement file (format should be '{FORMAT}')", path, field="format")
    observations = doc.get("observations")
    if not isinstance(observations, dict):
        raise InputError("expected point -> image -> measurement", path, field="observations")
    for name, per_image in observations.items():
        if not isinstance(per_image, dict):
            raise InputError("expected image -> measurement", path, field=f"observations.{name}")
        for iid, entry in per_image.items():
            where = f"observations.{name}.{iid}"
            if entry is None:
                continue
            uv = entry.get("uv") if isinstance(entry, dict) else None
            ok = (isinstance(uv, list) and len(uv) == 2
                  and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in uv))
            if not ok or not np.all(np.isfinite(uv)):
                raise InputError("expected {\"uv\": [u, v], ...} or null", path, field=f"{where}.uv")
            if entry.get("method") not in METHODS:
                raise InputError(f"method should be one of {', '.join(METHODS)}", path, field=f"{where}.method")
    return observations


def apply_manual(block: ImageBlock, observations: dict[str, dict[str, dict | None]]) -> tuple[int, int, int]:
    """Give the block's ground points the manual measurements (:func:`read_manual`): an entry replaces the point's
    measurement in that image, ``null`` removes it. Entries of points or images the block does not have (a block
    imported again since) are skipped. Returns the measurements set, removed and skipped."""
    n_set = n_removed = n_skipped = 0
    for name, per_image in observations.items():
        gp = block.ground_points.get(name)
        for iid, entry in per_image.items():
            if gp is None or iid not in block.images:
                n_skipped += 1
                continue
            if entry is None:
                n_removed += gp.observations.pop(iid, None) is not None
            else:
                gp.observations[iid] = np.asarray(entry["uv"], np.float64)
                n_set += 1
    return n_set, n_removed, n_skipped


def apply_measurements(ws, block: ImageBlock) -> tuple[dict | None, tuple[int, int, int], dict]:
    """Give ``block``'s ground points the image measurements the ``aerotri`` stage adjusts with: the ``match``
    stage's record (:data:`.targets.TARGETS_FILE`, over the imported ones), then the operator's (:data:`MANUAL_FILE`).
    Returns the targets record (None without one), :func:`apply_manual`'s counts and the manual observations."""
    targets_path = ws.path(TARGETS_FILE)
    targets = read_json(targets_path) if targets_path.exists() else None
    if targets is not None:
        apply_targets(block, targets, targets_path)
    manual = read_manual(ws.path(MANUAL_FILE))
    return targets, apply_manual(block, manual), manual


def _block_and_sources(ws) -> tuple[ImageBlock, dict[str, dict[str, str]], dict]:
    """The imported block with the measurements the ``aerotri`` stage will take (:func:`apply_measurements`), where
    each comes from (point -> image -> source), and the manual observations."""
    block = ws.load_block(adjusted=False)
    targets, _, manual = apply_measurements(ws, block)
    measured = {} if targets is None or targets.get("mode") == "none" else targets.get("points", {})
    sources = {name: {iid: "targets" if iid in measured.get(name, {}).get("measured", {}) else "imported"
                      for iid in gp.observations} for name, gp in block.ground_points.items()}
    for name, per_image in manual.items():  # (over the others)
        if name in sources:
            sources[name].update({iid: "manual" if e is not None else "removed" for iid, e in per_image.items()})
    return block, sources, manual


@dataclass(frozen=True)
class MeasurementState:
    """What :func:`points_in_image` needs of a workspace, read once (:func:`measurement_state`): the imported block
    with the measurements the ``aerotri`` stage will take, their sources (point -> image -> source), the block with
    the best orientations known (the adjusted one once aerial triangulation has run) and the block file's path."""

    block: ImageBlock
    sources: dict[str, dict[str, str]]
    oriented: ImageBlock
    path: Path


def measurement_state(ws) -> MeasurementState:
    """Read the blocks, the target and the manual measurements of the workspace (see :class:`MeasurementState`)."""
    block, sources, _ = _block_and_sources(ws)
    return MeasurementState(block, sources, ws.load_block(), ws.path("block", "block.json"))


def points_in_image(state: MeasurementState, image_id: str, margin_px: float = 0.0) -> list[PointInImage]:
    """The ground points whose projection falls inside image ``image_id`` (with the best orientation known), or that
    are measured there, in name order."""
    block = state.block
    if image_id not in block.images:
        raise InputError(f"no image '{image_id}' in the block", state.path, field="images")
    img = state.oriented.images.get(image_id, block.images[image_id])
    cam = state.oriented.camera_of(img)
    pose = img.pose
    out = []
    for name, gp in sorted(block.ground_points.items()):
        pred = np.full(2, np.nan)
        if gp.xyz is not None and pose is not None and np.all(np.isfinite(gp.xyz)):
            uv, depth = project(cam, pose, gp.xyz[None])
            if depth[0] > 0:
                pred = uv[0]
        source = state.sources.get(name, {}).get(image_id, "none")
        seen = np.all(np.isfinite(pred)) and cam.contains(pred[None], margin=margin_px)[0]
        if seen or source != "none":
            out.append(PointInImage(name, gp.kind, pred, gp.observations.get(image_id), source))
    return out


def ground_points_in_image(ws, image_id: str, margin_px: float = 0.0) -> list[PointInImage]:
    """:func:`points_in_image` of the workspace ``ws`` (read for this one image)."""
    return points_in_image(measurement_state(ws), image_id, margin_px)


def _write(ws, manual: dict) -> None:
    write_json(ws.path(MANUAL_FILE), {"format": FORMAT, "version": 1, "observations": manual})


def set_manual(ws, point: str, image_id: str, uv: np.ndarray | None, refine: bool = False,
               shape: TargetShape | None = None) -> str:
    """Record the operator's measurement of ground point ``point`` in image ``image_id``: ``uv (2,)`` pixels, or None
    to remove the point's measurement there. With ``refine`` the target is fitted around ``uv`` (searched
    :data:`SNAP_SEARCH_PX` around it in the image's file, with the orientation the adjustment starts from) and its
    centre recorded, or :class:`InputError` when no target of ``shape`` (the match stage's options when None) is
    found there (correlation below :data:`SNAP_MIN_SCORE`). Returns a one-line message. The file is written
    atomically."""
    block, _, manual = _block_and_sources(ws)
    path = ws.path(MANUAL_FILE)
    gp = block.ground_points.get(point)
    if gp is None:
        raise InputError(f"no ground point '{point}' in the block", path, field="point")
    img = block.images.get(image_id)
    if img is None:
        raise InputError(f"no image '{image_id}' in the block", path, field="image")
    entry = None
    if uv is not None:
        uv = np.asarray(uv, np.float64).reshape(2)
        cam = block.camera_of(img)
        if not np.all(np.isfinite(uv)) or not cam.contains(uv[None])[0]:
            raise InputError(f"({uv[0]:.1f}, {uv[1]:.1f}) is outside image '{image_id}' ({cam.width} x "
                             f"{cam.height} px)", path, field="uv")
        entry = {"uv": [round(float(x), 4) for x in uv], "method": "click", "score": None}
        if refine:
            if gp.xyz is None or img.pose_approx is None or img.file is None:
                raise InputError(f"'{point}' cannot be refined in '{image_id}': it needs the point's coordinates, "
                                 "the image's orientation and its file", path, field="uv")
            if shape is None:  # the targets as the match stage's options describe them
                shape = target_shape(MATCH_STAGE.make_config(ws.stage_options("match")))
            m = measure_target(read_block_grey(block, image_id), cam, img.pose_approx, gp.xyz, shape, SNAP_SEARCH_PX,
                               SNAP_MIN_SCORE, near=uv)
            if m is None:
                raise InputError(f"no target of '{point}' found within {SNAP_SEARCH_PX:.0f} px of ({uv[0]:.1f}, "
                                 f"{uv[1]:.1f}) in '{image_id}' (correlation below {SNAP_MIN_SCORE}); measure "
                                 "without refining", path, field="uv")
            entry = {"uv": [round(float(x), 4) for x in m.uv], "method": "target", "score": round(m.score, 4)}
    manual.setdefault(point, {})[image_id] = entry
    _write(ws, manual)
    if entry is None:
        return f"{point} removed from {image_id}"
    return (f"{point} measured in {image_id} at ({entry['uv'][0]:.2f}, {entry['uv'][1]:.2f})"
            + (f", target fitted (correlation {entry['score']:.3f})" if entry["method"] == "target" else ""))


def reset_manual(ws, point: str, image_id: str | None = None) -> str:
    """Drop the operator's measurement of ``point`` in ``image_id`` (in every image when None): the imported or the
    automatic measurement applies again. Returns a one-line message."""
    manual = read_manual(ws.path(MANUAL_FILE))
    per_image = manual.get(point, {})
    dropped = [iid for iid in per_image if image_id is None or iid == image_id]
    for iid in dropped:
        del per_image[iid]
    if not per_image:
        manual.pop(point, None)
    if dropped:
        _write(ws, manual)
    return f"{point}: {len(dropped)} manual measurement{'s' if len(dropped) != 1 else ''} dropped"
