"""Fixtures for the Blender tests (bpy 5.0.1 from PyPI).

Every test module here carries ``pytest.mark.xdist_group("bpy")`` so that under ``pytest -n 2 --dist loadgroup``
they share one worker and bpy is imported once. Each test starts from factory settings
(``read_homefile(app_template="")``) with the add-on registered by hand, and unregisters it afterwards.
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def addon():
    """A fresh scene with Oblique City registered; yields the ``bpy`` module."""
    import bpy

    import oblique_city

    bpy.ops.wm.read_homefile(app_template="")
    oblique_city.register()
    try:
        yield bpy
    finally:
        oblique_city.unregister()



@pytest.fixture
def grid_ws(tmp_path, utm_block):
    """A workspace of the three-image UTM block (distorted camera) with grid images (white lines every 50 px)."""
    import cv2

    from oblique_city.core.pipeline import Workspace

    images = tmp_path / "images"
    images.mkdir()
    for img in utm_block.images.values():
        cam = utm_block.camera_of(img)
        canvas = np.zeros((cam.height, cam.width), np.uint8)
        canvas[::50, :] = 255  # a grid: undistortion bends it, so the copy differs from the original
        canvas[:, ::50] = 255
        cv2.imwrite(str(images / img.file), canvas)
    utm_block.image_root = str(images)
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    return w
