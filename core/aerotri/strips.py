"""Flight strips of an image block from its navigation data, for the GNSS offsets per strip of the bundle adjustment.

A GNSS trajectory that is not post-processed as one piece (a float solution, ambiguities fixed again after each turn,
an older differential solution) carries an offset that is constant along a strip and changes from strip to strip, and
often a drift along it. Classic AT programs (BINGO, Match-AT, inpho) estimate a shift, or a shift and a drift, per
strip; :mod:`.bundle` does so with :attr:`.bundle.BundleOptions.gnss_strips`.

With exposure times (every image has one, e.g. an OPK list's time column) the strips follow from them: the exposures
in time order, a new strip after a step of more than :data:`TIME_GAP` median exposure intervals (a turn, or a line
flown in two passes), named in flight order. The along-track position is the time from the strip's middle times the
strip's ground speed (its path length over its duration), so a curved line (a corridor along a river or a road) is
one strip, with positions along its path.

Without times, the strips are found from the approximate orientations: exposures are grouped by heading (strips
flown in opposite directions are apart), then by their position across track (gaps wider than half the base between
exposures), then along track (gaps wider than :data:`ALONG_GAP` bases: one line flown in two passes), so a strip is a
straight line. An exposure is an image's ``exposure`` (all heads of a camera system share one GNSS antenna), or the
image itself. The heading is that of the top of the exposure's nadir
image (its image ``-y`` axis), the flight direction for a camera mounted with the image top forward (the simulator's
and most frame cameras; a camera mounted otherwise reverses the drift's sign, not the strips). The along-track
position in that direction stands for the time (constant speed), measured from the strip's middle, in kilometres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.views import cardinal_view
from ..model import ImageBlock

HEADING_GAP_DEG = 30.0
"""Headings more than this apart (sorted round the circle) start a new group: the strips of a block are flown in a few
headings (two for parallel strips flown both ways, four with cross strips) with a few degrees of crab angle."""

ACROSS_GAP = 0.5
"""A gap across track of more than this share of the base between exposures starts a new strip: the exposures of a
strip lie within a few metres of its line, neighbouring strips of one heading at least a base apart (side overlap
below the forward overlap)."""

ALONG_GAP = 3.0
"""A gap along a line of more than this many bases starts a new strip (the line was flown in two passes)."""

TIME_GAP = 5.0
"""With exposure times: a step of more than this many median exposure intervals starts a new strip. A turn takes a
minute or more against a few seconds between exposures; a pause in the triggering within a line splits it too, and
each part gets its own offset (a little redundancy lost, no bias)."""

TRIGGER_S = 0.05
"""Seconds: time steps up to this long are between images of one trigger (heads of a camera system without their
exposures given), not exposure intervals."""


@dataclass(frozen=True)
class Strips:
    """Flight strips: ``names`` (``L01``, ``L02``, ... by heading, then across track), and per image id its strip
    (index into ``names``) and its along-track position (in the heading, see the module docstring) from the strip's
    middle, in km."""

    names: tuple[str, ...]
    image_strip: dict[str, int]
    image_along_km: dict[str, float]

    def members(self, strip: int) -> list[str]:
        """The image ids of one strip."""
        return [i for i, s in self.image_strip.items() if s == strip]


def _circular_groups(angle: np.ndarray, gap: float) -> np.ndarray:
    """Group labels ``(n,)`` of angles ``(n,)`` (radians) split where sorted neighbours round the circle are more than
    ``gap`` apart."""
    n = len(angle)
    order = np.argsort(angle)
    a = angle[order]
    d = np.diff(np.r_[a, a[0] + 2 * np.pi])
    cuts = np.flatnonzero(d > gap)
    labels = np.zeros(n, np.int64)
    if len(cuts) == 0:
        return labels
    # start after the first wide gap, so that no group straddles the wrap-around
    start = (cuts[0] + 1) % n
    rolled = np.roll(np.arange(n), -start)
    group = np.cumsum(np.r_[0, d[rolled[:-1]] > gap])
    labels[order[rolled]] = group
    return labels


def _split_sorted(x: np.ndarray, gap: float) -> np.ndarray:
    """Labels ``(n,)`` of values ``x (n,)`` split where sorted neighbours are more than ``gap`` apart."""
    order = np.argsort(x)
    labels = np.empty(len(x), np.int64)
    labels[order] = np.cumsum(np.r_[0, np.diff(x[order]) > gap])
    return labels


def flight_strips(block: ImageBlock) -> Strips:
    """The flight strips of ``block`` from its images' approximate orientations (see the module docstring); images
    without one belong to no strip."""
    by_exposure: dict[str, list[str]] = {}
    for iid, img in block.images.items():
        if img.pose_approx is not None:
            by_exposure.setdefault(img.exposure or iid, []).append(iid)
    if not by_exposure:
        return Strips((), {}, {})
    keys = list(by_exposure)
    centre = np.array([np.mean([block.images[i].pose_approx.C for i in by_exposure[key]], axis=0) for key in keys])
    times = [[block.images[i].time for i in by_exposure[key]] for key in keys]
    if len(keys) > 1 and all(t is not None for ts in times for t in ts):
        return _strips_by_time(keys, by_exposure, np.array([np.mean(ts) for ts in times]), centre)
    heading = np.zeros(len(keys))
    for e, key in enumerate(keys):
        poses = [block.images[i].pose_approx for i in by_exposure[key]]
        # the heading of a head that looks down (the nadir one when the exposure has it): the top of its image
        down = [p for p in poses if cardinal_view(p.R) == "nadir"] or [min(poses, key=lambda p: p.R[2, 2])]
        up = -down[0].R[1]
        heading[e] = np.arctan2(up[1], up[0])
    lines = []  # (heading group, across-track position, first along-track position, exposures, their positions)
    for g in np.unique(h_group := _circular_groups(heading, np.radians(HEADING_GAP_DEG))):
        members = np.flatnonzero(h_group == g)
        mean = np.arctan2(np.sin(heading[members]).mean(), np.cos(heading[members]).mean())
        along_dir = np.array([np.cos(mean), np.sin(mean)])
        across = centre[members, :2] @ np.array([-along_dir[1], along_dir[0]])
        along = centre[members, :2] @ along_dir
        # the base: the median distance of an exposure to its nearest one of the group
        base = float(np.median(cKDTree(centre[members, :2]).query(centre[members, :2], k=2)[0][:, 1])) \
            if len(members) > 1 else 1.0
        a_lab = _split_sorted(across, ACROSS_GAP * base)
        for a in np.unique(a_lab):
            line = np.flatnonzero(a_lab == a)
            l_lab = _split_sorted(along[line], ALONG_GAP * base)
            for s in np.unique(l_lab):
                part = members[line[l_lab == s]]
                lines.append((g, float(across[line[l_lab == s]].mean()), float(along[line[l_lab == s]].min()), part,
                              along[line[l_lab == s]]))
    lines.sort(key=lambda t: (t[0], t[1], t[2]))
    image_strip: dict[str, int] = {}
    image_along: dict[str, float] = {}
    for s, (_, _, _, part, along) in enumerate(lines):
        mid = 0.5 * (along.min() + along.max())
        for e, u in zip(part, along):
            for iid in by_exposure[keys[e]]:
                image_strip[iid] = s
                image_along[iid] = float((u - mid) / 1000.0)
    return Strips(tuple(f"L{s + 1:02d}" for s in range(len(lines))), image_strip, image_along)


def _strips_by_time(keys: list[str], by_exposure: dict[str, list[str]], time: np.ndarray, centre: np.ndarray
                    ) -> Strips:
    """The strips of exposures ``keys`` (their images ``by_exposure``) from their times ``(e,)`` (seconds) and centres
    ``(e, 3)``, see the module docstring."""
    order = np.argsort(time, kind="stable")
    step = np.diff(time[order])
    interval = float(np.median(step[step > TRIGGER_S])) if np.any(step > TRIGGER_S) else 1.0
    label = np.cumsum(np.r_[0, step > TIME_GAP * interval])
    image_strip: dict[str, int] = {}
    image_along: dict[str, float] = {}
    for s in range(int(label[-1]) + 1):
        part = order[label == s]
        t = time[part]
        duration = float(t[-1] - t[0])
        path = float(np.sum(np.linalg.norm(np.diff(centre[part, :2], axis=0), axis=1)))
        along = (t - 0.5 * (t[0] + t[-1])) * (path / duration if duration > 0 else 0.0) / 1000.0
        for e, u in zip(part, along):
            for iid in by_exposure[keys[e]]:
                image_strip[iid] = s
                image_along[iid] = float(u)
    return Strips(tuple(f"L{s + 1:02d}" for s in range(int(label[-1]) + 1)), image_strip, image_along)


def offsets_at(values: np.ndarray, strip: np.ndarray, along: np.ndarray) -> np.ndarray:
    """The GNSS offsets ``(n, 3)`` at images of strips ``strip (n,)`` (-1: none) and along-track positions ``along
    (n,)`` (km): the strip's offset plus its drift times the position, from ``values (s, 6)`` (offset, drift per km;
    NaN rows: not estimated, NaN drifts: offsets alone; as :attr:`.bundle.BundleResult.gnss_strip`); zero where the
    strip has none."""
    out = np.zeros((len(strip), 3))
    ok = (strip >= 0) & (strip < len(values))
    ok[ok] = np.isfinite(values[strip[ok], 0])
    v = values[strip[ok]]
    out[ok] = v[:, :3] + along[ok, None] * np.nan_to_num(v[:, 3:])
    return out


def strip_offsets(strips: Strips, values: np.ndarray, image_ids: list[str]) -> dict[str, np.ndarray]:
    """Per image of ``image_ids`` in a strip with estimates its GNSS offset ``(3,)`` (:func:`offsets_at`)."""
    ids = [i for i in image_ids if strips.image_strip.get(i, -1) >= 0 and strips.image_strip[i] < len(values)
           and np.isfinite(values[strips.image_strip[i], 0])]
    out = offsets_at(values, np.array([strips.image_strip[i] for i in ids], np.int64),
                     np.array([strips.image_along_km[i] for i in ids]))
    return dict(zip(ids, out))


def strip_table(names: list[str], prior_strip: np.ndarray, values: np.ndarray, std: np.ndarray) -> dict[str, dict]:
    """The estimated strips as a table for reports: name -> images, offset and drift with their standard deviations
    (drift None when only offsets were estimated), from a problem's ``prior_strip (n,)`` and a result's ``values``,
    ``std (s, 6)`` (see :class:`.bundle.BundleResult`)."""
    out = {}
    for st in np.flatnonzero(np.isfinite(values[:, 0])) if len(values) else []:
        drift = bool(np.isfinite(values[st, 3]))
        out[names[st]] = {"images": int(np.sum(prior_strip == st)),
                          "offset_m": values[st, :3].tolist(), "offset_std_m": std[st, :3].tolist(),
                          "drift_m_per_km": values[st, 3:].tolist() if drift else None,
                          "drift_std_m_per_km": std[st, 3:].tolist() if drift else None}
    return out


STRIP_TEST_THRESHOLD = 4.3
"""A strip whose mean GNSS residual differs from the block's by more than this many of its standard deviations
(per axis) is flagged by :func:`strip_check` (the blunder tests' threshold)."""


def strip_check(strips: Strips, gnss_error: dict[str, np.ndarray], sigma: dict[str, np.ndarray],
                exposure: dict[str, str]) -> dict[str, dict]:
    """Whether the GNSS errors of an adjustment without the strip model share an offset per strip: per strip the mean
    ``(3,)`` of its images' ``gnss_error`` (GNSS minus adjusted centre, metres) from the mean of all strips' images
    (a common part is the datum shift's), and that difference over its standard deviation, ``sigma (3,)`` of an
    image's GNSS position over the square root of the strip's exposures (``exposure``: image id -> exposure; the heads
    of an exposure share one antenna). Returns strip name -> ``images``, ``mean_m``, ``w`` (3 each) and ``flagged``
    (any ``w`` above :data:`STRIP_TEST_THRESHOLD`), for the strips with errors."""
    ids = [i for i in gnss_error if i in strips.image_strip and i in sigma]
    if not ids:
        return {}
    block_mean = np.mean([gnss_error[i] for i in ids], axis=0)
    out = {}
    for st, name in enumerate(strips.names):
        members = [i for i in ids if strips.image_strip[i] == st]
        if not members:
            continue
        mean = np.mean([gnss_error[i] for i in members], axis=0) - block_mean
        std = np.mean([sigma[i] for i in members], axis=0) / np.sqrt(len({exposure.get(i, i) for i in members}))
        w = np.abs(mean) / std
        out[name] = {"images": len(members), "mean_m": mean.tolist(), "w": w.tolist(),
                     "flagged": bool(np.any(w > STRIP_TEST_THRESHOLD))}
    return out
