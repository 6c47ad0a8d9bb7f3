"""The Blender side of Oblique City: registration, preferences and properties, georeference, builders, jobs.

:func:`register` registers one ordered tuple of classes (properties first, then operators, then panels) and adds
the File > Import and File > Export menu entries, a ``load_pre`` handler that cancels a running job and the ground
point overlay's draw handler of the 3D view;
:func:`unregister` undoes it in reverse order, cancelling a running job first.
This package and the modules it registers are the only ones that import bpy; ``core`` never does.
"""

from __future__ import annotations

import bpy


def classes() -> tuple:
    """Every class to register, in registration order."""
    from ..operators import CLASSES as OPERATOR_CLASSES
    from ..panels import CLASSES as PANEL_CLASSES
    from .properties import CLASSES as PROPERTY_CLASSES

    return (*PROPERTY_CLASSES, *OPERATOR_CLASSES, *PANEL_CLASSES)


@bpy.app.handlers.persistent
def cancel_job_on_load(*_args) -> None:
    """``load_pre`` handler: a running job is cancelled when another file is loaded (its modal operator ends)."""
    from . import jobs

    jobs.cancel_active()


def register() -> None:
    from ..operators import menu_export, menu_import
    from ..panels import overlay
    from . import properties

    for cls in classes():
        bpy.utils.register_class(cls)
    properties.attach()
    bpy.types.TOPBAR_MT_file_import.append(menu_import)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)
    bpy.app.handlers.load_pre.append(cancel_job_on_load)
    overlay.add_handler()


def unregister() -> None:
    from ..operators import menu_export, menu_import
    from ..panels import overlay
    from . import jobs, properties

    jobs.cancel_active()
    job = jobs.active_job()
    if job is not None:
        jobs.forget_job(job)
    overlay.remove_handler()
    bpy.app.handlers.load_pre.remove(cancel_job_on_load)
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    properties.detach()
    for cls in reversed(classes()):
        bpy.utils.unregister_class(cls)
