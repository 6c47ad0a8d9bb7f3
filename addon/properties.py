"""Add-on preferences, persistent scene settings and transient job state.

* :class:`CityPreferences` (``bl_idname`` = the extension's root package, which is ``bl_ext.<repo>.oblique_city``
  inside Blender and ``oblique_city`` outside): how jobs run (child process or thread) and where a stage's
  independent units go (in-process, local processes, a Dask scheduler).
* :class:`CitySceneSettings` on ``Scene.oblique_city``, saved in the .blend: the workspace folder and display
  options. The georeference (CRS, float64 origin) is not here: see :mod:`.georef`.
* :class:`CityJobState` on ``WindowManager.oblique_city_job``, never saved: the running job's progress.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from .jobs import ExecutorSettings

ROOT_PACKAGE = __package__.rpartition(".")[0]
"""The extension's package name, as Blender knows it."""


class CityPreferences(bpy.types.AddonPreferences):
    bl_idname = ROOT_PACKAGE

    job_mode: EnumProperty(
        name="Run Jobs In",
        items=[("subprocess", "Child Process", "Run stages in a separate Python process (a crash in a stage cannot "
                "take Blender down)"),
               ("thread", "Background Thread", "Run stages in a thread of Blender's own process")],
        default="subprocess",
    )
    executor: EnumProperty(
        name="Executor",
        items=[("inline", "In Process", "Independent units one after the other"),
               ("processes", "Local Processes", "A pool of local worker processes"),
               ("dask", "Dask", "A Dask cluster: the scheduler below, or a local cluster when empty")],
        default="inline",
    )
    workers: IntProperty(name="Workers", default=2, min=1, max=256)
    scheduler: StringProperty(name="Dask Scheduler", description="e.g. tcp://10.0.0.5:8786", default="")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "job_mode")
        layout.prop(self, "executor")
        row = layout.row()
        row.prop(self, "workers")
        row.prop(self, "scheduler")


class CitySceneSettings(bpy.types.PropertyGroup):
    workspace: StringProperty(name="Workspace", subtype="DIR_PATH",
                              description="Oblique City workspace folder of this scene")
    undistort_backgrounds: BoolProperty(
        name="Undistort Backgrounds", default=True,
        description="When looking through an image, show it resampled to Blender's distortion-free camera")
    force: BoolProperty(name="Force", default=False, description="Run stages again even if they are up to date")


class CityJobState(bpy.types.PropertyGroup):
    running: BoolProperty(name="Running", default=False)
    stage: StringProperty(name="Stage")
    fraction: FloatProperty(name="Progress", min=0.0, max=1.0, subtype="FACTOR")
    message: StringProperty(name="Message")
    status: StringProperty(name="Status", description="How the last job ended: done, failed or cancelled")


def preferences(context) -> tuple[str, ExecutorSettings]:
    """Job mode and executor settings from the preferences (defaults when the add-on is registered by hand, as
    scripts and tests with bpy from PyPI do, rather than enabled as an extension)."""
    addon = context.preferences.addons.get(ROOT_PACKAGE)
    if addon is None or addon.preferences is None:
        return "subprocess", ExecutorSettings()
    p = addon.preferences
    return p.job_mode, ExecutorSettings(p.executor, p.workers, p.scheduler)


CLASSES = (CityPreferences, CitySceneSettings, CityJobState)


def attach() -> None:
    """Add the pointer properties (after the classes are registered)."""
    bpy.types.Scene.oblique_city = PointerProperty(type=CitySceneSettings)
    bpy.types.WindowManager.oblique_city_job = PointerProperty(type=CityJobState)


def detach() -> None:
    del bpy.types.WindowManager.oblique_city_job
    del bpy.types.Scene.oblique_city
