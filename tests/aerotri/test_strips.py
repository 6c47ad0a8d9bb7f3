"""Flight strips from the navigation data, against the simulator's flight plan."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from oblique_city.core.aerotri.strips import flight_strips, strip_offsets
from oblique_city.core.model import Image, ImageBlock, Pose
from oblique_city.core.simulate.flight import Exposure, image_pose


def _plan(block) -> dict[str, str]:
    """Image id -> the simulator's strip (exposures are named ``S<strip>_E<exposure>``)."""
    return {iid: img.exposure.split("_")[0] for iid, img in block.images.items()}


def test_strips_are_the_flight_plans_and_along_track_positions_are_centred(sim):
    """The 5 strips of the test block, flown both ways, are found exactly: every strip is one strip of the plan with
    all its 80 images (16 exposures x 5 heads), and the heads of an exposure share its along-track position. The
    positions run from -s/2 to s/2 over the strip's length s, and along the flight direction for either heading
    (exposure numbers grow with time)."""
    strips = flight_strips(sim.block)
    plan = _plan(sim.block)
    assert len(strips.names) == 5
    assert {(strips.image_strip[i], plan[i]) for i in plan} == {(s, plan[strips.members(s)[0]]) for s in range(5)}
    for s in range(5):
        members = strips.members(s)
        assert len(members) == 80
        along = np.array([strips.image_along_km[i] for i in members])
        assert abs(along.max() + along.min()) < 1e-9
        exposure = np.array([int(sim.block.images[i].exposure.split("_E")[1]) for i in members])
        by_exposure = {e: along[exposure == e] for e in np.unique(exposure)}
        assert all(np.ptp(a) < 1e-9 for a in by_exposure.values())
        first, last = by_exposure[exposure.min()][0], by_exposure[exposure.max()][0]
        ends = [sim.true_poses[next(i for i in members if exposure[members.index(i)] == e)].C[:2]
                for e in (exposure.min(), exposure.max())]
        # from the first exposure's to the last's: forward, by their distance (within the plan's 1 m jitter)
        assert abs((last - first) - np.linalg.norm(ends[1] - ends[0]) / 1000.0) < 0.005


@pytest.mark.parametrize("times", [True, False])
def test_a_line_flown_in_two_passes_and_a_cross_strip_are_strips_of_their_own(sim, times):
    """Dropping the middle exposures of one strip (a gap of 6 bases, and of 6 exposure intervals) splits it into two
    strips; turning another strip by 90 degrees about its middle (a cross strip) keeps it one strip (by time; by
    geometry it is in a heading group of its own). Strip offsets map back to every image of a strip with its drift
    times its along-track position. With the exposures' times and without (straight-line geometry)."""
    block = copy.deepcopy(sim.block)
    if not times:
        for img in block.images.values():
            img.time = None
    plan = _plan(block)
    for iid in [i for i in block.images if plan[i] == "S02" and 6 <= int(block.images[i].exposure[-3:]) <= 11]:
        del block.images[iid]
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    cross = [i for i in block.images if plan[i] == "S04"]
    mid = np.mean([block.images[i].pose_approx.C for i in cross], axis=0)
    for iid in cross:  # the strip turned by 90 degrees about its middle, heading and line
        p = block.images[iid].pose_approx
        block.images[iid].pose_approx = Pose(p.R @ turn.T, mid + turn @ (p.C - mid))
    strips = flight_strips(block)
    assert len(strips.names) == 6
    groups = {}
    for iid, s in strips.image_strip.items():
        groups.setdefault(s, set()).add(plan[iid])
    assert all(len(g) == 1 for g in groups.values())
    assert sorted(sum(1 for g in groups.values() if g == {p}) for p in ("S01", "S02", "S03", "S04", "S05")) \
        == [1, 1, 1, 1, 2]
    values = np.full((len(strips.names), 6), np.nan)
    values[0] = [0.1, -0.2, 0.3, 1.0, 0.0, -2.0]
    values[1, :3] = [0.5, 0.5, 0.5]
    off = strip_offsets(strips, values, list(block.images))
    assert set(off) == set(strips.members(0)) | set(strips.members(1))
    for iid in strips.members(0):
        u = strips.image_along_km[iid]
        assert np.allclose(off[iid], [0.1 + u, -0.2, 0.3 - 2 * u])
    assert all(np.allclose(off[i], 0.5) for i in strips.members(1))


def test_planted_strip_errors_are_an_offset_and_a_drift_per_strip(sim):
    """The simulator's strip errors (:func:`plant_strip_errors`) move each GNSS centre by the error it
    returns; all heads of an exposure share it, and per strip it is an offset plus a drift times the along-track
    position found by :func:`flight_strips`: a straight-line fit leaves less than 0.1 mm of errors up to 0.5 m (the
    simulator takes the strip's axis from its first and last exposure, flight_strips from the headings, a few
    milliradians apart: metres of jitter across track shift the positions along it by millimetres, 2 m/km of drift
    turns them into hundredths of a millimetre), and the drift's sign follows the flight direction, which both take."""
    from oblique_city.core.simulate.observations import plant_strip_errors

    block = copy.deepcopy(sim.block)
    err = plant_strip_errors(block, 0.3, 2.0, seed=5)
    moved = {i: block.images[i].pose_approx.C - sim.block.images[i].pose_approx.C for i in block.images}
    assert max(float(np.abs(moved[i] - err[i]).max()) for i in block.images) < 1e-8  # UTM rounding
    strips = flight_strips(block)
    offsets = []
    for s in range(len(strips.names)):
        members = strips.members(s)
        u = np.array([strips.image_along_km[i] for i in members])
        e = np.array([err[i] for i in members])
        a = np.c_[np.ones(len(u)), u]
        fit = np.linalg.lstsq(a, e, rcond=None)[0]
        assert np.abs(a @ fit - e).max() < 1e-4
        offsets.append(fit[0])
        by_exposure = {}
        for i in members:
            by_exposure.setdefault(block.images[i].exposure, []).append(err[i])
        assert all(np.ptp(np.array(v), axis=0).max() == 0 for v in by_exposure.values())
    assert 0.05 < np.std(offsets) < 0.6
    assert plant_strip_errors(copy.deepcopy(sim.block), 0.0, 0.0, seed=5)[members[0]].tolist() == [0.0, 0.0, 0.0]


def test_a_curved_line_is_one_strip_by_time_with_positions_along_its_path(penta_block):
    """A corridor flown along a quarter circle of 1.5 km radius and back, 90 s of turn between: by the exposures'
    times it is two strips of all their exposures, in flight order, and the along-track positions follow the arc (each
    step the 60 m between exposures within 0.1 %, centred); without times the straight-line geometry cuts the arc into
    pieces."""
    rig = penta_block.rigs["penta"]
    radius, base, speed = 1500.0, 60.0, 60.0
    steps = int(radius * math.pi / 2 / base)
    block = ImageBlock(crs=penta_block.crs, cameras=penta_block.cameras)
    t = 0.0
    for p, angles in enumerate((np.arange(steps + 1) * base / radius, (np.arange(steps + 1) * base / radius)[::-1])):
        for k, a in enumerate(angles):
            yaw = -a if p == 0 else math.pi - a  # the tangent, counter-clockwise then back
            ex = Exposure(f"P{p}_E{k:03d}", p, k, np.array([radius * math.cos(a), radius * math.sin(a), 800.0]),
                          yaw, 0.0, 0.0, t)
            for h in rig.heads:
                block.add_image(Image(f"{ex.name}_{h.name}", h.camera_id, head=h.name, exposure=ex.name, time=t,
                                      pose_approx=image_pose(ex, h)))
            t += base / speed
        t += 90.0
    strips = flight_strips(block)
    assert len(strips.names) == 2
    for s in range(2):
        members = strips.members(s)
        assert {m.split("_")[0] for m in members} == {f"P{s}"} and len(members) == 5 * (steps + 1)
        along = np.array([strips.image_along_km[f"P{s}_E{k:03d}_nadir"] for k in range(steps + 1)]) * 1000.0
        assert np.allclose(np.diff(along), base, rtol=1e-3) and abs(along[0] + along[-1]) < 1e-6
    for img in block.images.values():
        img.time = None
    assert len(flight_strips(block).names) > 4


def test_strips_by_time_of_heads_without_their_exposures(sim):
    """Without exposures each image counts alone, and the heads' trigger times scatter by milliseconds: the strips
    are still the flight plan's, the heads of one trigger in one strip."""
    block = copy.deepcopy(sim.block)
    rng = np.random.default_rng(3)
    for img in block.images.values():
        img.exposure = None
        img.time += rng.uniform(-0.002, 0.002)
    strips = flight_strips(block)
    plan = _plan(sim.block)
    assert len(strips.names) == 5
    assert all(len({plan[i] for i in strips.members(s)}) == 1 for s in range(5))
