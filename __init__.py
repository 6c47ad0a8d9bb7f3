"""Oblique City: city modelling from oblique aerial imagery, as a Blender extension.

Outside Blender this package imports as ``oblique_city`` and never touches bpy (the core is pure Python); inside
Blender it loads as ``bl_ext.<repo>.oblique_city`` and :func:`register` hands over to ``addon``, which imports bpy.
"""


def register() -> None:
    from . import addon

    addon.register()


def unregister() -> None:
    from . import addon

    addon.unregister()
