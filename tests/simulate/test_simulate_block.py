"""End to end: a small simulated block through the real writers and readers, its truth, and the metrics."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.evaluate.orientation import point_errors, pose_errors, similarity_transform
from oblique_city.core.evaluate.rasters import dtm_errors, errors_by_class, raster_errors
from oblique_city.core.geometry.projection import project
from oblique_city.core.geometry.rotations import rotation_angle
from oblique_city.core.io.formats import read_block
from oblique_city.core.model import Pose, Raster
from oblique_city.core.simulate.city import SEMANTIC
from oblique_city.core.simulate.flight import IMAGE_NAME_PATTERN
from oblique_city.core.simulate.simulator import SimulationConfig, simulate
from oblique_city.core.simulate.truth import load_truth


@pytest.fixture(scope="module")
def small(city, tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    cfg = SimulationConfig(width=200, height=150, gsd=1.0, workers=1, depth_maps=True, truth_cell=1.0)
    summary = simulate(out, cfg, city=city)
    return out, summary


def test_outputs_and_import_path(small):
    out, s = small
    assert s["images"] == len(list((out / "images").glob("*.jpg"))) and s["images"] >= 20
    assert set(s["views"]) == {"nadir", "north", "east", "south", "west"}
    for name in ("city_overview", "head_nadir", "head_forward", "head_right", "head_backward", "head_left"):
        assert (out / "preview" / f"{name}.png").stat().st_size > 1000
    block = read_block("bex", out / "block.xml", image_root=str(out), check_images=True)
    truth = load_truth(out)
    assert set(block.images) == set(truth.block.images)
    assert truth.targets["pattern"] == "disc" and truth.targets["square_half"] == 0.8
    assert len(block.ground_points) == len(truth.targets["targets"])
    # approximate poses are close to the truth but not equal (GNSS/IMU errors, boresight, lever arm)
    e = pose_errors(block, truth.block, adjusted=False)["summary"]["all"]
    assert 0.02 < e["rms_xyz"] < 0.6 and 1e-3 < e["rms_angle_deg"] < 0.2
    # image measurements of the control points agree with the true orientation to the measurement noise
    res = []
    for g in block.ground_points.values():
        xyz = np.array(truth.targets["targets"][g.name])
        for iid, uv in g.observations.items():
            img = truth.block.images[iid]
            res.append(uv - project(truth.block.camera_of(img), img.pose_approx, xyz[None])[0][0])
    assert len(res) > 30 and np.sqrt(np.mean(np.square(res))) < 0.5
    # the navigation solution per exposure with the heads' mounting gives the same orientations, with the camera
    # system's exposures and rig, and the images found
    events = read_block("gnssimu", out / "events.txt", image_root=str(out), check_images=True,
                        gcps=str(out / "gcp.csv"), measurements=str(out / "gcp_measurements.csv"))
    assert set(events.images) == set(block.images) and len(events.ground_points) == len(block.ground_points)
    for iid, img in block.images.items():
        assert np.abs(events.images[iid].pose_approx.C - img.pose_approx.C).max() < 1e-6
        assert rotation_angle(events.images[iid].pose_approx.R, img.pose_approx.R) < 1e-8
    assert len({img.exposure for img in events.images.values()}) * 5 == len(events.images)
    assert [h.name for h in events.rigs["system"].heads] == ["nadir", "forward", "right", "backward", "left"]
    # the BlocksExchange block carries no exposures: the image names give them back (as the demo imports it)
    named = read_block("bex", out / "block.xml", exposures="name", exposure_pattern=IMAGE_NAME_PATTERN)
    assert {(i, img.exposure, img.head) for i, img in named.images.items()} == \
        {(i, img.exposure, img.head) for i, img in truth.block.images.items()}


def test_truth_rasters_and_depth(small):
    out, _ = small
    truth = load_truth(out / "truth")
    dsm, dtm, cls = truth.dsm, truth.dtm, truth.classes
    assert dsm.shape == dtm.shape == cls.shape
    ground = np.isin(cls.data, [SEMANTIC["ground"], SEMANTIC["street"]])
    np.testing.assert_allclose(dsm.data[ground], dtm.data[ground], atol=2e-3)
    roofs = cls.data == SEMANTIC["roof"]
    assert roofs.sum() > 1000 and np.all(dsm.data[roofs] > dtm.data[roofs] + 2.0)
    iid = next(iter(truth.block.images))
    d = truth.depth(iid)
    cam = truth.block.camera_of(iid)
    assert d.shape == (cam.height, cam.width) and np.isfinite(d).mean() > 0.99
    # rasters metrics: the truth against itself is perfect; a 0.3 m offset is measured as such
    assert raster_errors(dsm, dsm)["rmse"] == 0.0
    shifted = Raster(dtm.data + 0.3, dtm.x0, dtm.y0, dtm.cell, dtm.crs)
    m = dtm_errors(shifted, dtm, cls, SEMANTIC)
    assert abs(m["open_ground"]["rmse"] - 0.3) < 1e-5 and m["open_ground"]["completeness"] == 1.0
    holes = Raster(np.where(roofs, np.nan, dsm.data), dsm.x0, dsm.y0, dsm.cell, dsm.crs)
    by = errors_by_class(holes, dsm, cls, SEMANTIC)
    assert by["roof"]["completeness"] == 0.0 and by["ground"]["completeness"] == 1.0
    assert 0 < by["all"]["completeness"] < 1


def test_orientation_metrics():
    rng = np.random.default_rng(0)
    from oblique_city.core.model import CameraModel, Image, ImageBlock

    truth, est = ImageBlock("EPSG:25832"), ImageBlock("EPSG:25832")
    cam = CameraModel("c", 100, 100, 100.0, 100.0, 49.5, 49.5)
    truth.add_camera(cam)
    est.add_camera(cam)
    s, r, t = 1.0005, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([10.0, -5.0, 2.0])
    for i in range(12):
        c = rng.uniform(-300, 300, 3) + [0, 0, 500]
        p = Pose(np.diag([1.0, -1.0, -1.0]), c)
        truth.add_image(Image(f"i{i}", "c", pose_approx=p))
        est.add_image(Image(f"i{i}", "c", pose_approx=Pose(p.R @ r.T, s * r @ c + t)))  # a similarity of the truth
    raw = pose_errors(est, truth, adjusted=False)["summary"]["all"]
    assert raw["rms_xyz"] > 10 and abs(raw["rms_angle_deg"] - 90.0) < 1e-9
    al = pose_errors(est, truth, adjusted=False, align="similarity")
    assert al["summary"]["all"]["rms_xyz"] < 1e-6 and al["summary"]["all"]["rms_angle_deg"] < 1e-6
    s2, r2, _ = similarity_transform(np.array([p.C for p in [x.pose_approx for x in truth.images.values()]]),
                                     np.array([x.pose_approx.C for x in est.images.values()]))
    assert abs(s2 - s) < 1e-9 and np.allclose(r2, r)
    pe = point_errors(np.array([[0.1, 0.0, 0.2], [0.0, -0.1, -0.2]]), np.zeros((2, 3)), gsd=0.1)
    assert abs(pe["rms_z"] - 0.2) < 1e-12 and abs(pe["rms_xy_gsd"] - 1.0) < 1e-12
