"""The add-on registers, unregisters and registers again cleanly (bpy from PyPI)."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.xdist_group("bpy")

OPERATORS = ("import_block", "run_stages", "cancel_job", "open_workspace", "build_scene", "view_image")


def _registered(bpy, name: str) -> bool:
    try:
        getattr(bpy.ops.city, name).get_rna_type()
    except KeyError:
        return False
    return True


def test_register_unregister_register():
    import bpy

    import oblique_city
    from oblique_city.addon import classes

    bpy.ops.wm.read_homefile(app_template="")
    for round_ in range(2):
        oblique_city.register()
        assert all(_registered(bpy, op) for op in OPERATORS), round_
        assert all(c.is_registered for c in classes())
        assert hasattr(bpy.types.Scene, "oblique_city") and hasattr(bpy.types.WindowManager, "oblique_city_job")
        assert bpy.context.scene.oblique_city.workspace == ""
        panels = [c.bl_idname for c in classes() if issubclass(c, bpy.types.Panel)]
        assert {"CITY_PT_block", "CITY_PT_job", "CITY_PT_triangulation", "CITY_PT_dense___surfaces",
                "CITY_PT_buildings", "CITY_PT_textures", "CITY_PT_export"} <= set(panels)
        oblique_city.unregister()
        assert not any(_registered(bpy, op) for op in OPERATORS), round_
        assert not any(c.is_registered for c in classes())
        assert not hasattr(bpy.types.Scene, "oblique_city")


def test_file_import_menu_entry(addon):
    bpy = addon
    from oblique_city.operators import menu_import

    assert menu_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
