"""Exposures and the camera system of an imported block: which images one trigger of a multi-head camera took, and
the heads' mounting relative to each other, estimated from the approximate orientations.

Plain OPK lists and most project exports give one orientation per image and no trace of the camera system. Three
parts of the aerial triangulation need it: HAT propagates the nadir run's corrections to the other heads of each
exposure (its oblique runs start there), the rig constraints tie the heads of an exposure to their mounting, and
the GNSS offsets per strip belong to the exposure (one antenna). This module restores it:

* :func:`assign_exposures`: by time (the heads are triggered together: images whose exposure times follow each
  other within a tolerance form one exposure) or by name (a regular expression whose group ``exposure``, else its
  first group, names the exposure, and whose group ``head``, if it has one, names the head). An image without a
  head gets its camera's id: each head of a camera system has its own calibration.
* :func:`estimate_rig`: the heads' mounting relative to a reference head (the one that looks down most often),
  averaged over the exposures that have both (chordal mean of the rotations, mean of the offsets), exposures more
  than :data:`OUTLIER_MADS` robust deviations from the median left out. The rig frame is the reference head's
  frame: its ``sensor_from_rig`` is the identity and its lever arm zero.
* :func:`rig_fit`: how far each exposure's approximate orientations are from a rig. The orientations of one
  exposure from one GNSS/IMU solution through the system's calibrated mounting agree with it to their rounding; an
  orientation from an earlier adjustment spreads by its precision; degrees say the images were not taken by one
  rigid system (or the exposures are wrong).
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.rotations import rotation_angle
from .block import Image, ImageBlock, Rig, RigHead

OUTLIER_MADS = 5.0
"""An exposure whose rotation or offset differs from the median by more than this many robust standard deviations
(1.4826 median absolute deviations) is left out of a head's mounting estimate."""

EXPOSURE_MODES = ("given", "time", "name")


@dataclass(frozen=True)
class HeadFit:
    """How one head's exposures fit a rig: ``exposures`` compared (the reference head's and this head's images both
    oriented), ``left_out`` of them as outliers (estimate only), the RMS rotation difference (degrees) and offset
    difference (metres) of the others from the rig's mounting."""

    head: str
    exposures: int
    left_out: int
    rotation_rms_deg: float
    offset_rms_m: float


def image_head(img: Image) -> str:
    """The head of an image: its own, else its camera's id."""
    return img.head if img.head is not None else img.camera_id


def assign_exposures(block: ImageBlock, by: str, pattern: str | None = None, tolerance_s: float = 0.01,
                     source: str | Path | None = None, lines: dict[str, int] | None = None) -> int:
    """Set every image's ``exposure`` (and ``head`` where it has none) by ``by``: ``time`` or ``name`` (see the
    module docstring; ``pattern`` is the regular expression, matched against the whole image id; ``tolerance_s``
    the largest time step within one exposure). Returns the number of exposures.

    Raises :class:`InputError` naming ``source``, the image's line (``lines``: image id -> line) and the field for
    an image without a time, an id the pattern does not match, or two images of one head in one exposure."""
    if by not in ("time", "name"):
        raise InputError(f"exposures must be one of {', '.join(EXPOSURE_MODES)}, got '{by}'", path=source,
                         field="exposures")
    lines = lines or {}
    images = list(block.images.values())
    heads: dict[str, str] = {}
    if by == "time":
        if not tolerance_s >= 0:
            raise InputError(f"exposure_tolerance must be a non-negative number of seconds, got {tolerance_s}",
                             path=source, field="exposure_tolerance")
        missing = [img for img in images if img.time is None]
        if missing:
            raise InputError(f"image '{missing[0].id}' has no time ({len(missing)} images without one): exposures "
                             "by time need a time column", path=source, line=lines.get(missing[0].id), field="time")
        times = np.array([img.time for img in images], np.float64)
        order = np.argsort(times, kind="stable")
        new = np.r_[True, np.diff(times[order]) > tolerance_s]
        label = np.empty(len(images), np.int64)
        label[order] = np.cumsum(new) - 1
        exposure = {img.id: f"E{label[k] + 1:06d}" for k, img in enumerate(images)}
        where = "time"
    else:
        if not pattern:
            raise InputError("exposures by name need exposure_pattern (a regular expression with a group for the "
                             "exposure)", path=source, field="exposure_pattern")
        try:
            rx = re.compile(pattern)
        except re.error as e:
            raise InputError(f"exposure_pattern is not a regular expression: {e}", path=source,
                             field="exposure_pattern") from None
        if rx.groups == 0:
            raise InputError("exposure_pattern needs a group (the exposure's part of the name), e.g. "
                             r"'(\d+)_\w+'", path=source, field="exposure_pattern")
        group = "exposure" if "exposure" in rx.groupindex else 1
        exposure = {}
        for img in images:
            m = rx.fullmatch(img.id)
            if m is None or m.group(group) is None:
                raise InputError(f"image '{img.id}' does not match exposure_pattern '{pattern}'", path=source,
                                 line=lines.get(img.id), field="name")
            exposure[img.id] = m.group(group)
            if "head" in rx.groupindex and m.group("head"):
                heads[img.id] = m.group("head")
        where = "name"
    seen: dict[tuple[str, str], str] = {}
    for img in images:
        head = heads.get(img.id) or image_head(img)
        key = (exposure[img.id], head)
        if key in seen:
            raise InputError(f"images '{seen[key]}' and '{img.id}' fall in one exposure with the same head "
                             f"'{head}'" + (" (lower exposure_tolerance)" if by == "time" else ""),
                             path=source, line=lines.get(img.id), field=where)
        seen[key] = img.id
    for img in images:
        img.exposure = exposure[img.id]
        img.head = heads.get(img.id) or image_head(img)
    return len(set(exposure.values()))


def _members(block: ImageBlock) -> dict[str, dict[str, Image]]:
    """Exposure -> head -> image, for the oriented images with an exposure."""
    out: dict[str, dict[str, Image]] = {}
    for img in block.images.values():
        if img.exposure is not None and img.pose_approx is not None:
            out.setdefault(img.exposure, {})[image_head(img)] = img
    return out


def _relative(members: dict[str, dict[str, Image]], ref: str, head: str) -> tuple[np.ndarray, np.ndarray]:
    """Per exposure with both heads, the head's rotation from the reference head's frame ``(k, 3, 3)``
    (``R_head R_ref^T``) and its centre in that frame ``(k, 3)`` (``R_ref (C_head - C_ref)``)."""
    pairs = [(m[ref].pose_approx, m[head].pose_approx) for m in members.values() if ref in m and head in m]
    if not pairs:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    r_ref = np.array([a.R for a, _ in pairs])
    r_head = np.array([b.R for _, b in pairs])
    d = np.array([b.C - a.C for a, b in pairs])
    return r_head @ np.transpose(r_ref, (0, 2, 1)), np.einsum("kij,kj->ki", r_ref, d)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angles ``(k,)`` in degrees of ``a (k, 3, 3)`` against ``b (3, 3)``."""
    return np.degrees(rotation_angle(a, b))


def _chordal_mean(r: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to the mean of ``r (k, 3, 3)``."""
    u, _, vt = np.linalg.svd(r.sum(0))
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def _outliers(x: np.ndarray) -> np.ndarray:
    """Mask of the values of ``x (k,)`` (non-negative differences) more than :data:`OUTLIER_MADS` robust deviations
    above the median."""
    med = np.median(x)
    mad = 1.4826 * np.median(np.abs(x - med))
    return x > med + OUTLIER_MADS * max(mad, 1e-12)


def reference_head(block: ImageBlock) -> str:
    """The head whose images look down most often (the first by name among equals)."""
    counts = Counter(image_head(img) for img in block.images.values() if img.exposure is not None
                     and img.view == "nadir")
    heads = sorted({image_head(img) for img in block.images.values() if img.exposure is not None})
    if not heads:
        raise InputError("the block has no exposures: give them (columns exposure, head) or derive them with "
                         "exposures=time or exposures=name", field="exposures")
    return sorted(heads, key=lambda h: -counts.get(h, 0))[0]  # stable: the first by name among equals


def estimate_rig(block: ImageBlock, name: str = "system") -> tuple[Rig, list[HeadFit]]:
    """The camera system's rig from the block's exposures and approximate orientations (see the module docstring),
    the reference head first, and each other head's fit. Raises :class:`InputError` when the block has no exposures
    or fewer than two heads, when a head uses more than one camera, or when a head shares no exposure with the
    reference head."""
    ref = reference_head(block)
    cams: dict[str, set[str]] = {}
    for img in block.images.values():
        if img.exposure is not None:
            cams.setdefault(image_head(img), set()).add(img.camera_id)
    for h, ids in cams.items():
        if len(ids) > 1:
            raise InputError(f"head '{h}' takes images with cameras {', '.join(sorted(ids))}: a rig head has one "
                             "camera", field="head")
    if len(cams) < 2:
        raise InputError(f"one head only ('{ref}'): a rig needs at least two", field="head")
    members = _members(block)
    heads = [RigHead(ref, next(iter(cams[ref])), np.eye(3), np.zeros(3))]
    fits = []
    for h in sorted(cams):
        if h == ref:
            continue
        q, o = _relative(members, ref, h)
        if len(q) == 0:
            raise InputError(f"head '{h}' has no oriented exposure with the reference head '{ref}'", field="head")
        r0, o0 = _chordal_mean(q), np.median(o, 0)
        bad = _outliers(_angles_deg(q, r0)) | _outliers(np.linalg.norm(o - o0, axis=1))
        keep = ~bad if (~bad).any() else np.ones(len(q), bool)
        s, lever = _chordal_mean(q[keep]), o[keep].mean(0)
        heads.append(RigHead(h, next(iter(cams[h])), s, lever))
        fits.append(_head_fit(h, q[keep], o[keep], s, lever, int((~keep).sum())))
    return Rig(name, tuple(heads)), fits


def _head_fit(head: str, q: np.ndarray, o: np.ndarray, s: np.ndarray, lever: np.ndarray, left_out: int) -> HeadFit:
    """The fit of a head's exposures ``q (k, 3, 3)``, ``o (k, 3)`` (see :func:`_relative`) to its mounting ``s (3, 3)``,
    ``lever (3,)``."""
    if len(q) == 0:
        return HeadFit(head, 0, left_out, float("nan"), float("nan"))
    return HeadFit(head, len(q), left_out, float(np.sqrt(np.mean(_angles_deg(q, s) ** 2))),
                   float(np.sqrt(np.mean(np.sum((o - lever) ** 2, 1)))))


def rig_fit(block: ImageBlock, rig: Rig) -> list[HeadFit]:
    """For each head of ``rig`` but the first (the reference), how far the block's exposures are from the rig's
    relative mounting (``left_out`` is 0: nothing is left out)."""
    members, ref = _members(block), rig.heads[0]
    return [_head_fit(h.name, *_relative(members, ref.name, h.name), *h.relative_to(ref), 0) for h in rig.heads[1:]]


MISSING_EXPOSURES = ("No exposures: HAT starts the oblique images from the navigation data (import with exposures "
                     "by time or by name)")
"""What the import and the Block panel say of a block with oblique images and no exposures."""


def oblique_without_nadir(block: ImageBlock) -> int:
    """The oriented oblique images without an oriented nadir image in their exposure (none given counts): HAT
    cannot propagate the nadir run's correction to them (:func:`..aerotri.hierarchical.nadir_propagation`)."""
    nadir = {img.exposure for img in block.images.values()
             if img.exposure is not None and img.pose_approx is not None and img.view == "nadir"}
    return sum(1 for img in block.images.values()
               if img.pose_approx is not None and img.view != "nadir" and img.exposure not in nadir)


def describe_system(block: ImageBlock) -> str:
    """One line on the block's exposures and rigs (with the worst head's fit), empty without exposures."""
    n = len({img.exposure for img in block.images.values() if img.exposure is not None})
    if n == 0:
        return ""
    heads = {image_head(img) for img in block.images.values() if img.exposure is not None}
    parts = [f"{n} exposures of {len(heads)} heads"]
    for rig in block.rigs.values():
        fits = [f for f in rig_fit(block, rig) if f.exposures]
        text = f"rig '{rig.name}' (reference head {rig.heads[0].name})"
        if fits:
            text += (f": the orientations fit it within {max(f.rotation_rms_deg for f in fits):.4f} deg and "
                     f"{max(f.offset_rms_m for f in fits):.3f} m RMS")
        parts.append(text)
    return "; ".join(parts)
