"""Run Stage(s) as a cancellable job, and Cancel Job.

``city.run_stages`` takes stage names (comma-separated; empty = every registered stage). Invoked from the UI it
starts a job (see ``addon.jobs``) and a modal timer handler that only drains the job's queue: progress goes to
the status bar, the window's progress indicator and the sidebar; Esc cancels. Called with ``EXEC_DEFAULT``
(scripts, ``blender --background``) it runs the same job and waits for it. Either way the scene objects of the
finished stages are built by the main thread once the job has ended.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, StringProperty

from ..addon import builders, jobs
from ..addon.properties import preferences
from ..core.errors import CityError
from ..core.pipeline import Workspace

TIMER_S = 0.2


def scene_workspace(context) -> str:
    """The scene's workspace folder (absolute), or raise :class:`CityError`."""
    path = context.scene.oblique_city.workspace
    if not path:
        raise CityError("the scene has no workspace: import a block or open a workspace first")
    return bpy.path.abspath(path)


def finish_job(context, job: jobs.Job, report) -> None:
    """On the main thread, after the job's end was drained: build the finished stages' objects and report."""
    jobs.forget_job(job)
    end = job.end
    if end.status == "done":
        try:
            ws = Workspace.open(job.ws_root)
            messages = builders.build_scene(context.scene, ws, stages=job.planned)
        except CityError as e:
            report({"ERROR"}, str(e).splitlines()[0])
            return
        report({"INFO"}, "; ".join(filter(None, [end.message, *messages])) or "done")
    elif end.status == "cancelled":
        report({"WARNING"}, end.message.splitlines()[0] if end.message else "cancelled")
    else:
        report({"ERROR"}, end.message.splitlines()[0] if end.message else "the job failed")


class CITY_OT_run_stages(bpy.types.Operator):
    """Run pipeline stages on the scene's workspace (finished stages whose inputs did not change are skipped)"""

    bl_idname = "city.run_stages"
    bl_label = "Run Stage(s)"

    stages: StringProperty(name="Stages", description="Comma-separated stage names; empty: all stages")
    force: BoolProperty(name="Force", description="Run again even if up to date", default=False)

    def start(self, context) -> jobs.Job:
        mode, executor = preferences(context)
        names = [s.strip() for s in self.stages.split(",") if s.strip()] or None
        state = context.window_manager.oblique_city_job
        job = jobs.start_job(scene_workspace(context), names, force=self.force or context.scene.oblique_city.force,
                             mode=mode, executor=executor)
        state.running, state.fraction, state.status = True, 0.0, ""
        state.stage, state.message = job.planned[0], "starting"
        return job

    def execute(self, context):
        try:
            job = self.start(context)
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        jobs.wait(job, context.window_manager.oblique_city_job)
        finish_job(context, job, self.report)
        return {"FINISHED"} if job.end.status == "done" else {"CANCELLED"}

    def invoke(self, context, event):
        if context.window is None:
            return self.execute(context)
        try:
            self._job = self.start(context)
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(TIMER_S, window=context.window)
        wm.progress_begin(0.0, 1.0)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        wm = context.window_manager
        state = wm.oblique_city_job
        finished = jobs.drain(self._job, state)
        wm.progress_update(state.fraction)
        if context.workspace is not None:
            context.workspace.status_text_set(None if finished else
                                              f"Oblique City {state.fraction:4.0%}  {state.message}  (Esc: cancel)")
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if not finished:
            return {"PASS_THROUGH"}
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        finish_job(context, self._job, self.report)
        return {"FINISHED"} if self._job.end.status == "done" else {"CANCELLED"}


class CITY_OT_cancel_job(bpy.types.Operator):
    """Cancel the running Oblique City job (it stops at the stage's next progress report)"""

    bl_idname = "city.cancel_job"
    bl_label = "Cancel Job"

    @classmethod
    def poll(cls, context):
        job = jobs.active_job()
        return job is not None and not job.finished

    def execute(self, context):
        jobs.active_job().cancel()
        context.window_manager.oblique_city_job.message = "cancelling..."
        return {"FINISHED"}
