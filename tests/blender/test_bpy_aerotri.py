"""Results of ``aerotri`` in Blender: the tie point cloud coloured by ray count or residual, the Triangulation panel's
figures and Open Report.

Tie points are written with the core's own :class:`TiePoints` writer at UTM coordinates: tracks with 2 to 7
observations, some observations flagged as blunders (not counted as rays), some tracks never intersected (left
out). Checked: the point count, world positions within 1 mm, the ``rays`` attribute against the counts, the
colours against the ramp, the subsample, and the panel lines against the report.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_bpy_ui import draw

from oblique_city.core.model import TiePoints
from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")

N = 400


@pytest.fixture
def ws(tmp_path, utm_block):
    rng = np.random.default_rng(3)
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    xyz = np.c_[rng.uniform(500000, 500300, N), rng.uniform(5400000, 5400200, N), rng.uniform(290, 340, N)]
    xyz[::37] = np.nan  # never intersected
    per_track = rng.integers(2, 8, N)
    obs_track = np.repeat(np.arange(N), per_track)
    blunder = rng.random(len(obs_track)) < 0.1
    residual = rng.uniform(0.0, 1.2, N)  # RMS image residuals (px), some beyond 3 sigma0 (0.888 px)
    residual[::53] = np.nan  # no residual kept
    ties = TiePoints(xyz=xyz, obs_track=obs_track, obs_image=np.zeros(len(obs_track), np.int64),
                     obs_uv=np.zeros((len(obs_track), 2)), image_ids=["img0"], obs_blunder=blunder,
                     extra={"residual_px": residual})
    ties.save(str(w.stage_dir("aerotri") / "ties.npz"))
    rays = np.bincount(obs_track[~blunder], minlength=N)
    report = {"mode": "hierarchical", "connection": "5", "images": 12, "sigma0": 0.987, "sigma0_px": 0.296,
              "check_points": {"all": {"n": 4, "rms_xy_m": 0.0312, "rms_z_m": 0.0457}}, "blunder_percent": 1.25,
              "mounting": {"nadir": {"boresight_deg": [0.01, 0.0, 0.0]}, "left": {"boresight_deg": [0.03, 0.0, -0.04]}},
              "image_residual_fields": {"nadir": {"systematic_rms_px": 0.012}, "left": {"systematic_rms_px": 0.0841},
                                        "right": {"systematic_rms_px": None}},
              "ground_points": [{"name": "G1", "rejected_coordinates": True, "rejected_images": []},
                                {"name": "G2", "rejected_coordinates": False, "rejected_images": ["a", "b"]},
                                {"name": "C3"}],
              "runs": [{"name": "nadir", "priors_rejected": [["n1", "position"], ["n2", "attitude"]],
                        "sigma_px_given": 0.5, "sigma0_a_priori_px": 0.3,
                        "control_sigma_scale": 0.088,
                        "reliability": {"priors": {"position_m": {"effect_max": [0.01, 0.02, 0.1273]},
                                                   "attitude_deg": {"effect_max": [0.002, 0.0201, 0.001]}}}},
                       {"name": "north", "priors_rejected": [["o1", "position"]],
                        "reliability": {"priors": {"position_m": {"effect_max": [0.05, 0.03, 0.04]}}}},
                       {"name": "east"}],
              "gnss_strips": {"L01": {"offset_m": [0.1, -0.2, 0.05]}, "L02": {"offset_m": [0.0, 0.3, -0.4]}},
              "gnss_strip_check": {"L01": {"mean_m": [0.0, 0.0, 0.12], "w": [0.1, 0.2, 5.0], "flagged": True},
                                   "L02": {"mean_m": [0.3, 0.0, 0.4], "w": [2.0, 0.1, 4.2], "flagged": False},
                                   "L03": {"mean_m": [0.0, 0.0, -0.2], "w": [0.0, 0.3, 8.0], "flagged": True}},
              "weakest_control": {"name": "G2", "run": "nadir", "axis": "Z", "mdb_m": 0.1364},
              "oblique_without_nadir": 40,
              "rig_fusion": {"exposures": 25, "images": 125, "iterations": 3, "left_out": 12, "rms_px_before": 0.17,
                             "rms_px_after": 0.1, "moved_deg": 0.0102, "moved_m": 0.0539, "last_step": 2.5},
              "datum": {"shift_m": [-0.0612, 0.0398, -0.1003], "std_m": [0.003, 0.003, 0.0046]},
              "self_calibration": {
                  "nadir": {"corner_shift_px": 1.234, "corner_shift_std_px": 0.05,
                            "parameters": [{"significant": True}, {"significant": False}]},
                  "left": {"corner_shift_px": 6.789, "corner_shift_std_px": 0.21,
                           "parameters": [{"significant": True}, {"significant": True}, {"significant": None}]}}}
    (w.stage_dir("aerotri") / "report.json").write_text(json.dumps(report))
    (w.stage_dir("aerotri") / "report.html").write_text("<html><body>report</body></html>")
    w.write_state({"aerotri": {"status": "done"}})
    return w, xyz, rays


def test_tie_points(addon, ws):
    bpy = addon
    from oblique_city.addon import georef, layers_aerotri

    w, xyz, rays = ws
    scene = bpy.context.scene
    valid = np.all(np.isfinite(xyz), axis=1)
    summary = layers_aerotri.build_tie_points(scene, w)
    assert summary.startswith(f"{valid.sum()} tie points shown")
    obj = bpy.data.objects["Tie points"]
    assert len(obj.data.vertices) == valid.sum() == N - len(range(0, N, 37))
    assert np.abs(georef.mesh_vertices_world(scene, obj) - xyz[valid]).max() < 1e-3
    got = np.empty(len(obj.data.vertices), np.int32)
    obj.data.attributes["rays"].data.foreach_get("value", got)
    assert np.array_equal(got, rays[valid])
    col = np.empty(len(got) * 4, np.float32)
    obj.data.color_attributes["Col"].data.foreach_get("color_srgb", col)
    col = col.reshape(-1, 4)[:, :3]
    assert np.abs(col - layers_aerotri.ray_colours(got)).max() < 1 / 255 + 1e-6
    assert np.abs(col[got <= 2] - [0.10, 0.25, 0.90]).max() < 1 / 255 + 1e-6  # two rays: blue
    assert obj.modifiers["Points"].type == "NODES"


def test_tie_points_coloured_by_residual(addon, ws):
    """Colour Tie Points (the Triangulation panel's row) recolours the cloud by each point's RMS image residual in
    units of the report's sigma0 (0.296 px): the ``residual_px`` attribute holds the file's values, the colours
    follow the ramp (grey without a residual, red at 3 sigma0 and more), and Ray Count brings the ray colours back.
    Without a tie point cloud the operator refuses."""
    bpy = addon
    from oblique_city.addon import layers_aerotri

    w, xyz, rays = ws
    scene = bpy.context.scene
    scene.oblique_city.workspace = str(w.root)
    with pytest.raises(RuntimeError, match="no tie points in the scene"):
        bpy.ops.city.colour_tie_points(colouring="residual")
    layers_aerotri.build_tie_points(scene, w)
    obj = bpy.data.objects["Tie points"]
    valid = np.all(np.isfinite(xyz), axis=1)
    residual = TiePoints.load(str(w.path("aerotri/ties.npz"))).extra["residual_px"][valid]
    got = np.empty(len(obj.data.vertices), np.float32)
    obj.data.attributes["residual_px"].data.foreach_get("value", got)
    assert np.allclose(got, residual, equal_nan=True, atol=1e-6)

    def colours():
        col = np.empty(len(obj.data.vertices) * 4, np.float32)
        obj.data.color_attributes["Col"].data.foreach_get("color_srgb", col)
        return col.reshape(-1, 4)[:, :3]

    assert bpy.ops.city.colour_tie_points(colouring="residual") == {"FINISHED"}
    col = colours()
    ok = np.isfinite(residual)
    expected = layers_aerotri.ramp_colours(residual / 0.296, layers_aerotri.RESIDUAL_RAMP)
    assert np.abs(col - expected).max() < 1 / 255 + 1e-6
    assert np.abs(col[~ok] - layers_aerotri.NO_VALUE_COLOUR).max() < 1 / 255 + 1e-6
    high = ok & (residual >= 3 * 0.296)
    assert high.sum() > 10 and np.abs(col[high] - [0.90, 0.15, 0.10]).max() < 1 / 255 + 1e-6
    assert bpy.ops.city.colour_tie_points(colouring="rays") == {"FINISHED"}
    assert np.abs(colours() - layers_aerotri.ray_colours(rays[valid])).max() < 1 / 255 + 1e-6


def test_large_tie_sets_are_subsampled(addon, ws, monkeypatch):
    bpy = addon
    from oblique_city.addon import georef, layers_aerotri

    w, xyz, rays = ws
    monkeypatch.setattr(layers_aerotri, "MAX_TIE_POINTS", 100)
    assert layers_aerotri.build_tie_points(bpy.context.scene, w).startswith("100 of ")
    obj = bpy.data.objects["Tie points"]
    world = georef.mesh_vertices_world(bpy.context.scene, obj)
    d = np.linalg.norm(world[:, None, :] - np.nan_to_num(xyz, nan=0.0)[None], axis=2)
    idx = d.argmin(1)  # each shown point is one of the tracks, each at most once, with its own ray count
    assert len(world) == 100 and d.min(1).max() < 1e-3 and len(set(idx)) == 100
    got = np.empty(100, np.int32)
    obj.data.attributes["rays"].data.foreach_get("value", got)
    assert np.array_equal(got, rays[idx])


def test_build_scene_after_aerotri(addon, ws):
    bpy = addon
    from oblique_city.addon import builders

    w = ws[0]
    messages = builders.build_scene(bpy.context.scene, w)
    # state.json has no fingerprint: the adjustment is not current, the imported block is shown, no tie points
    assert messages[0].startswith("aerotri: ") and "cameras" in messages[0]
    assert not any(m.startswith("block:") for m in messages)
    assert "Tie points" not in bpy.data.objects


def test_build_scene_with_a_current_adjustment(addon, ws, utm_block):
    bpy = addon
    from dataclasses import dataclass

    from oblique_city.addon import builders
    from oblique_city.core.pipeline import Stage, StageResult
    from oblique_city.core.pipeline.registry import register, unregister
    from oblique_city.core.pipeline.runner import fingerprint
    from oblique_city.core.pipeline.workspace import ADJUSTED_BLOCK_FILE

    @dataclass(frozen=True)
    class NoConfig:
        pass

    w, xyz, _ = ws
    register(Stage("aerotri", run=lambda ws, cfg, ctx: StageResult(), config=NoConfig))
    try:
        w.save_block(utm_block, ADJUSTED_BLOCK_FILE)
        w.write_state({"aerotri": {"status": "done", "fingerprint": fingerprint(w, "aerotri", {}),
                                   "outputs": [ADJUSTED_BLOCK_FILE]}})
        messages = builders.build_scene(bpy.context.scene, w)
        n = int(np.all(np.isfinite(xyz), axis=1).sum())
        assert messages[0].startswith("aerotri: ") and f"; {n} tie points shown" in messages[0]
        assert len(bpy.data.objects["Tie points"].data.vertices) == n
        (w.root / "aerotri" / "ties.npz").write_bytes(b"broken")
        messages = builders.build_scene(bpy.context.scene, w)
        assert "tie points not built (" in messages[0] and "ties.npz" in messages[0]
    finally:
        unregister("aerotri")


def test_triangulation_panel_and_open_report(addon, ws, monkeypatch):
    bpy = addon
    import webbrowser

    from oblique_city.panels import STAGE_PANEL_CLASSES

    w = ws[0]
    bpy.context.scene.oblique_city.workspace = str(w.root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Triangulation")
    log = draw(panel, bpy.context)
    labels = [e[1] for e in log if e[0] == "label"]
    assert "Mode: hierarchical (5), 12 images" in labels
    assert "Sigma0: 0.987 (0.296 px)" in labels
    assert "Tie sigma estimated: 0.300 px (0.5 px given)" in labels
    assert "Control point measurement sigmas scaled by 0.09 (variance component)" in labels
    assert "Check points (4): RMS XY 0.031 m, Z 0.046 m" in labels
    assert "Datum shift: -0.061 +- 0.003, 0.040 +- 0.003, -0.100 +- 0.005 m" in labels
    assert "Rejected observations: 1.25 %" in labels
    assert "40 oblique images without a nadir image in their exposure: import the exposures" in labels
    assert "Heads of 25 exposures fused on the rig (moved 0.0102 deg, 0.054 m RMS)" in labels
    assert "Mounting calibrated for 2 cameras, largest boresight 0.0500 deg (left)" in labels
    assert "Self-calibrated 2 cameras: a corner of left moves 6.79 +- 0.21 px; 3 of 4 corrections significant" in labels
    assert "Largest systematic image residual: 0.084 px (left)" in labels
    assert "Rejected control: 1 points (G1), 2 measurements" in labels
    assert "Rejected priors: 2 GNSS positions, 1 IMU attitudes (n1, n2, o1)" in labels
    assert "GNSS offsets of 2 strips, largest 0.500 m (L02)" in labels
    assert "GNSS positions of 2 strips share an offset (L03: 0.200 m): try Shift per strip" in labels
    assert "Weakest control point: G2, errors below 0.136 m in Z pass its test" in labels
    assert "Prior errors the tests miss move an image by at most: GNSS 0.127 m, IMU 0.0201 deg" in labels
    assert any(e[0] == "operator" and e[1] == "city.open_report" for e in log)
    assert sum(e[0] == "operator" and e[1] == "city.colour_tie_points" for e in log) == 2

    opened = []
    monkeypatch.setattr(webbrowser, "open", lambda url: opened.append(url) or True)
    assert bpy.ops.city.open_report() == {"FINISHED"}
    assert opened == [(w.root / "aerotri" / "report.html").resolve().as_uri()]
    (w.root / "aerotri" / "report.html").unlink()
    with pytest.raises(RuntimeError, match="no triangulation report"):
        bpy.ops.city.open_report()

    # the project report: written into the workspace, then opened; the Block panel has its button
    from oblique_city.panels import CITY_PT_block

    assert any(e[0] == "operator" and e[1] == "city.open_project_report" for e in draw(CITY_PT_block, bpy.context))
    assert bpy.ops.city.open_project_report() == {"FINISHED"}
    assert opened[-1] == (w.root / "report.html").resolve().as_uri()
    assert "<h2>Processing</h2>" in (w.root / "report.html").read_text()


def test_triangulation_options_round_trip_through_project_toml(addon, ws):
    """The Triangulation panel edits ``[stages.aerotri]``: mode, connection, the linear solver and the GNSS strip
    model as choices, the
    control tests and the mounting calibration as switches, the self-calibration groups as toggles (a list in the
    file); what it writes is what the stage's config reads."""
    import tomllib

    from oblique_city.addon.properties import option_fields
    from oblique_city.core.pipeline.registry import get_stage
    from oblique_city.panels import STAGE_PANEL_CLASSES

    bpy = addon
    w = ws[0]
    scene = bpy.context.scene
    scene.oblique_city.workspace = str(w.root)
    fields = option_fields("aerotri")
    assert {"mode", "connection", "cell_size", "mounting", "control_tests", "linear_solver",
            "self_calibration"} <= set(fields)
    opts = scene.oblique_city.stage_options.aerotri
    assert opts.mode == "integrated" and opts.connection == "cba" and opts.control_tests
    assert opts.self_calibration == set()
    assert opts.gnss_strips == "off"
    opts.mode, opts.connection, opts.control_tests, opts.cell_size = "hierarchical", "5", False, 40.0
    opts.gnss_strips = "drift"
    opts.self_calibration = {"radial", "focal"}
    doc = tomllib.loads((w.root / "project.toml").read_text(encoding="utf-8"))["stages"]["aerotri"]
    assert doc["mode"] == "hierarchical" and doc["connection"] == "5" and doc["control_tests"] is False
    assert doc["self_calibration"] == ["focal", "radial"]
    cfg = get_stage("aerotri").make_config(Workspace.open(w.root).stage_options("aerotri"))
    assert (cfg.mode, cfg.connection, cfg.control_tests, cfg.cell_size) == ("hierarchical", "5", False, 40.0)
    assert doc["gnss_strips"] == "drift" and cfg.bundle_options().gnss_strips == "drift"
    assert not cfg.bundle_options().control_tests
    assert tuple(cfg.bundle_options().self_calibration) == ("focal", "radial")
    assert opts.self_calibration == {"focal", "radial"}
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Triangulation")
    props = [e[1] for e in draw(panel, bpy.context) if e[0] == "prop"]
    assert {"mode", "connection", "control_tests"} <= set(props)
