"""Property tests: any pose and camera survives the OPK and BlocksExchange round trips."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.io.formats import read_block, write_block
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose

angle = st.floats(-np.pi, np.pi, allow_nan=False)
coord = st.floats(-1e6, 1e7, allow_nan=False)
coef = st.floats(-0.2, 0.2, allow_nan=False)


@st.composite
def blocks(draw) -> ImageBlock:
    w, h = draw(st.integers(10, 20000)), draw(st.integers(10, 20000))
    cam = CameraModel(id="c", width=w, height=h, fx=draw(st.floats(10, 1e5)), fy=draw(st.floats(10, 1e5)),
                      cx=draw(st.floats(-0.5, w - 0.5)), cy=draw(st.floats(-0.5, h - 0.5)), k1=draw(coef),
                      k2=draw(coef), k3=draw(coef), p1=draw(coef), p2=draw(coef))
    b = ImageBlock(crs="EPSG:25832")
    b.add_camera(cam)
    for i in range(draw(st.integers(1, 4))):
        r = opk_to_cam_from_world(draw(angle), draw(st.floats(-1.5, 1.5)), draw(angle))
        b.add_image(Image(id=f"i{i}", camera_id="c", file=f"i{i}.tif",
                          pose_approx=Pose(r, (draw(coord), draw(coord), draw(st.floats(-100, 9000))))))
    return b


@settings(max_examples=40, deadline=None)
@given(blocks(), st.sampled_from(["opk", "bex"]))
def test_round_trip_any_block(block, fmt):
    with tempfile.TemporaryDirectory() as d:
        write_block(fmt, block, Path(d) / "b.out")
        back = read_block(fmt, Path(d) / "b.out")
    cb, ca = back.cameras["c"], block.cameras["c"]
    for k in ("width", "height", "fx", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
        assert getattr(cb, k) == getattr(ca, k), k
    assert abs(cb.fy - ca.fy) <= 1e-12 * ca.fy  # BlocksExchange stores fy as fx * AspectRatio
    for iid, img in block.images.items():
        assert np.array_equal(back.images[iid].pose.C, img.pose.C)
        assert np.abs(back.images[iid].pose.R - img.pose.R).max() < 1e-12
