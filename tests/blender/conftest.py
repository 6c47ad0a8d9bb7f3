"""Fixtures for the Blender tests (bpy 5.0.1 from PyPI).

Every test module here carries ``pytest.mark.xdist_group("bpy")`` so that under ``pytest -n 2 --dist loadgroup``
they share one worker and bpy is imported once. Each test starts from factory settings
(``read_homefile(app_template="")``) with the add-on registered by hand, and unregisters it afterwards.
"""

from __future__ import annotations

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

