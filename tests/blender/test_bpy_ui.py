"""Workspace operators (Open Workspace, View Through Image) and the sidebar panels' draw code.

Panels cannot be drawn headless, so their ``draw`` runs against a layout that records what it is asked to show:
this executes every line of the draw code against the real scene, window manager and workspace.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

pytestmark = pytest.mark.xdist_group("bpy")


def valid_icons() -> set[str]:
    import bpy

    return set(bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items.keys())


class RecordingLayout:
    """Stands in for ``bpy.types.UILayout``: records labels, properties and operators, and checks icon names."""

    def __init__(self, log=None):
        self.log = [] if log is None else log
        self.enabled = True
        self.icons = valid_icons()

    def _icon(self, kwargs):
        assert kwargs.get("icon", "NONE") in self.icons, kwargs["icon"]

    def _sub(self, *args, **kwargs):
        return RecordingLayout(self.log)

    row = column = box = _sub

    def label(self, text="", icon="NONE"):
        self._icon({"icon": icon})
        self.log.append(("label", text))

    def prop(self, data, name, **kwargs):
        self._icon(kwargs)
        assert hasattr(data, name), name
        self.log.append(("prop", name))

    def operator(self, idname, **kwargs):
        import bpy

        self._icon(kwargs)
        mod, name = idname.split(".")
        getattr(getattr(bpy.ops, mod), name).get_rna_type()  # raises KeyError for an unregistered operator
        props = SimpleNamespace()
        self.log.append(("operator", idname, props))
        return props

    def progress(self, factor=0.0, text=""):
        self.log.append(("progress", factor, text))


def draw(panel_cls, context) -> list:
    layout = RecordingLayout()
    panel_cls.draw(SimpleNamespace(layout=layout), context)
    return layout.log


def test_open_workspace_and_view_through_image(addon, grid_ws, utm_block):
    bpy = addon
    ws = grid_ws
    import cv2

    assert bpy.ops.city.open_workspace(directory=str(ws.root)) == {"FINISHED"}
    scene = bpy.context.scene
    assert scene.oblique_city.workspace == str(ws.root)
    obj = bpy.data.objects["img1"]
    original = obj.data["oc_background"]
    assert original.endswith("img1.jpg")

    assert bpy.ops.city.view_image(camera="img1") == {"FINISHED"}
    cam = utm_block.camera_of("img1")
    assert scene.camera == obj
    assert (scene.render.resolution_x, scene.render.resolution_y) == (cam.width, cam.height)
    assert scene.render.pixel_aspect_y / scene.render.pixel_aspect_x == pytest.approx(cam.fx / cam.fy, rel=1e-6)
    shown = obj.data["oc_background"]
    assert "block/undistorted" in shown and shown != original
    a, b = cv2.imread(original, cv2.IMREAD_GRAYSCALE), cv2.imread(shown, cv2.IMREAD_GRAYSCALE)
    assert a.shape == b.shape and np.abs(a.astype(int) - b.astype(int)).mean() > 1.0

    # the next build finds the undistorted copy
    assert bpy.ops.city.build_scene() == {"FINISHED"}
    assert bpy.data.objects["img1"].data["oc_background"] == shown


def test_open_workspace_refuses_a_plain_folder(addon, tmp_path):
    bpy = addon
    with pytest.raises(RuntimeError, match="not a workspace"):
        bpy.ops.city.open_workspace(directory=str(tmp_path))


def test_panels_draw(addon, grid_ws):
    ws = grid_ws
    bpy = addon
    from oblique_city import panels
    from oblique_city.core.pipeline.registry import stage_names

    context = bpy.context
    log = draw(panels.CITY_PT_block, context)
    assert ("label", "no workspace") not in log
    assert bpy.ops.city.open_workspace(directory=str(ws.root)) == {"FINISHED"}
    labels = [e[1] for e in draw(panels.CITY_PT_block, context) if e[0] == "label"]
    assert "3 images, 1 cameras, 0 adjusted" in labels
    assert {"    nadir: 1", "    north: 1", "    east: 1"} <= set(labels)
    assert "CRS: EPSG:32632" in labels and any(s.startswith("Origin: 500250.000, 5399760.000") for s in labels)
    assert any(s.startswith("No exposures: HAT starts the oblique images") for s in labels)
    block = ws.load_block()
    for img in block.images.values():  # one trigger of three heads
        img.exposure, img.head = "E1", img.id
    ws.save_block(block)
    labels = [e[1] for e in draw(panels.CITY_PT_block, context) if e[0] == "label"]
    assert "Exposures: 1, rigs: 0" in labels and not any(s.startswith("No exposures") for s in labels)

    registered = set(stage_names())
    for panel in panels.STAGE_PANEL_CLASSES:
        log = draw(panel, context)
        assert panel.bl_options == {"DEFAULT_CLOSED"}
        names = dict(panels.STAGE_PANELS)[panel.bl_label]
        for name in names:
            texts = [e[1] for e in log if e[0] == "label"]
            if name in registered:
                assert any(t.startswith(f"{name}: ") and "not registered" not in t for t in texts)
                assert any(e[0] == "operator" and e[2].stages == name for e in log)
            else:
                assert f"{name}: not registered yet" in texts
    log = draw(panels.CITY_PT_job, context)
    assert [e[2].stages for e in log if e[0] == "operator" and e[1] == "city.run_stages"] == [""]
