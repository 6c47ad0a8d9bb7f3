"""Rectification of any pair geometry: rows align, disparities are positive, points come back."""

from __future__ import annotations

import dense_scene
import numpy as np
import pytest

from oblique_city.core.dense.pairs import near_is_high
from oblique_city.core.dense.rectify import _to_rect, disparity_range, rectification_frame, rectify_pair
from oblique_city.core.errors import ComputationError
from oblique_city.core.geometry.projection import project
from oblique_city.core.model import CameraModel, Pose

CAM = CameraModel(id="c", width=600, height=400, fx=800.0, fy=801.0, cx=303.0, cy=197.5, k1=-0.04, k2=0.01,
                  p1=1e-4)
O = np.array([500000.0, 5400000.0, 0.0])


def _pose(c, target, up=(0.0, 0.0, 1.0)):
    c = np.asarray(c, float)
    return Pose(dense_scene.look_at(c, np.asarray(target, float), up), c + O)


GEOMETRIES = {
    "nadir_east": (_pose([0, 0, 300], [0, 0, 0], (0, 1, 0)), _pose([80, 0, 300], [80, 0, 0], (0, 1, 0))),
    "nadir_west": (_pose([0, 0, 300], [0, 0, 0], (0, 1, 0)), _pose([-80, 5, 302], [-80, 5, 0], (0, 1, 0))),
    "nadir_vertical_baseline": (_pose([0, 0, 300], [0, 0, 0], (0, 1, 0)), _pose([3, 90, 300], [3, 90, 0], (0, 1, 0))),
    "oblique_cross_strip": (_pose([0, -300, 300], [0, 0, 0]), _pose([70, -300, 300], [70, 0, 0])),
    "oblique_converging": (_pose([0, -300, 300], [0, 0, 0]), _pose([90, -280, 310], [10, 0, 0])),
}


@pytest.mark.parametrize("name", sorted(GEOMETRIES))
def test_rectified_rows_align_and_points_return(name):
    pm, ps = GEOMETRIES[name]
    pair = rectify_pair(CAM, pm, CAM, ps)
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(-60, 120, 400), rng.uniform(-60, 120, 400), rng.uniform(0, 40, 400)]) + O
    uv_m, _ = project(CAM, pm, xyz)
    uv_s, _ = project(CAM, ps, xyz)
    seen = CAM.contains(uv_m) & CAM.contains(uv_s)
    assert seen.sum() > 50
    rm = pair.master_to_rect(CAM, pm, uv_m[seen])
    rs = _to_rect(CAM, ps, uv_s[seen], pair.rect_from_world, pair.f, pair.cx_slave, pair.cy)
    assert np.abs(rm[:, 1] - rs[:, 1]).max() < 1e-6
    d = rm[:, 0] - rs[:, 0]
    assert (d - pair.disparity_offset > 0).all()
    back = pair.triangulate(rm[:, 0], rm[:, 1], d)
    assert np.abs(back - xyz[seen]).max() < 1e-5
    # the remap tables send rectified pixels to the original ones (bilinear table lookup: < 0.05 px)
    ri = np.rint(rm).astype(int)
    inside = (ri[:, 0] >= 0) & (ri[:, 0] < pair.width) & (ri[:, 1] >= 0) & (ri[:, 1] < pair.height)
    assert inside.mean() > 0.9
    back_uv = pair.master_to_rect(CAM, pm, pair.map_master[ri[inside, 1], ri[inside, 0]].astype(np.float64))
    assert np.abs(back_uv - ri[inside]).max() < 0.05
    # the height prior gives a disparity interval holding the true disparities
    lo, hi = disparity_range(pair, O[2], O[2] + 40, CAM, ps)
    assert lo <= d.min() and d.max() <= hi
    # high points are near: their disparity is the larger (the end coarse-to-fine matching keeps)
    assert near_is_high(pair, O[2], O[2] + 40)


def test_forward_motion_is_refused():
    pm = _pose([0, -300, 300], [0, 0, 0])
    ps = _pose([0, -200, 300], [0, 100, 0])
    with pytest.raises(ComputationError):
        rectification_frame(pm, ps, min_angle_deg=50.0)
