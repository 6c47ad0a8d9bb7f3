"""The Blender side of Oblique City: registration, preferences and properties, georeference, builders, jobs.

:func:`register` registers one ordered tuple of classes (properties first, then operators, then panels) and adds
the File > Import menu entry; :func:`unregister` undoes it in reverse order, cancelling a running job first.
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


def register() -> None:
    from ..operators import menu_import
    from . import properties

    for cls in classes():
        bpy.utils.register_class(cls)
    properties.attach()
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister() -> None:
    from ..operators import menu_import
    from . import jobs, properties

    job = jobs.active_job()
    if job is not None:
        if not job.finished:
            job.cancel()
        jobs.forget_job(job)
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    properties.detach()
    for cls in reversed(classes()):
        bpy.utils.unregister_class(cls)
