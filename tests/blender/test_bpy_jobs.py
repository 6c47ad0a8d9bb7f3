"""Jobs: a trivial stage runs through the runner in a thread and in a child process; the queue drains to
completion; cancel works; the Run operator builds the finished stage's layer on the main thread."""

from __future__ import annotations

import sys
import time
from types import SimpleNamespace

import jobstages
import pytest

from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")

LAUNCHER = [sys.executable, "-c", jobstages.LAUNCHER_SNIPPET.format(here=str(jobstages.__file__).rsplit("/", 1)[0])]


@pytest.fixture
def ws(tmp_path, utm_block):
    jobstages.install()
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    yield w
    from oblique_city.addon import jobs
    from oblique_city.core.pipeline.registry import unregister

    unregister("count")
    job = jobs.active_job()
    if job is not None:
        if not job.finished:
            job.cancel()
            jobs.wait(job, new_state(), timeout_s=20)
        jobs.forget_job(job)


class RecordingState(SimpleNamespace):
    """Stands in for the window manager's job state and keeps every progress fraction drained into it."""

    def __setattr__(self, name, value):
        if name == "fraction":
            self.__dict__.setdefault("fractions", []).append(value)
        super().__setattr__(name, value)


def new_state():
    return RecordingState(running=False, stage="", fraction=0.0, message="", status="")


def slow(ws: Workspace, steps: int = 400, sleep_s: float = 0.02) -> None:
    ws.project["stages"]["count"] = {"steps": steps, "sleep_s": sleep_s}
    ws.save_project()


def drain_until(job, state, predicate, timeout_s: float = 30.0) -> None:
    """Drain like the modal operator's timer does, until ``predicate()``."""
    from oblique_city.addon import jobs

    t0 = time.monotonic()
    while not predicate():
        jobs.drain(job, state)
        assert time.monotonic() - t0 < timeout_s, state.message
        time.sleep(0.01)


@pytest.mark.parametrize("mode", ["thread", "subprocess"])
def test_job_runs_and_drains_to_completion(ws, mode):
    from oblique_city.addon import jobs

    slow(ws, steps=6, sleep_s=0.01)
    job = jobs.start_job(ws.root, ["count"], mode=mode, launcher=LAUNCHER)
    assert isinstance(job, jobs.ThreadJob if mode == "thread" else jobs.SubprocessJob)
    state = new_state()
    drain_until(job, state, lambda: job.finished)
    assert job.end.status == "done", job.end.message
    assert state.status == "done" and state.fraction == 1.0 and not state.running
    assert [round(f * 6) for f in state.fractions] == [1, 2, 3, 4, 5, 6, 6]  # 6 progress events, then the end
    assert job.queue.empty()
    assert ws.read_state()["count"]["status"] == "done"
    assert (ws.root / "count" / "count.json").read_text().count("6") == 1


@pytest.mark.parametrize("mode", ["thread", "subprocess"])
def test_cancel_stops_the_stage(ws, mode):
    from oblique_city.addon import jobs

    slow(ws)  # 400 steps x 20 ms = 8 s if not cancelled
    job = jobs.start_job(ws.root, ["count"], mode=mode, launcher=LAUNCHER)
    assert isinstance(job, jobs.ThreadJob if mode == "thread" else jobs.SubprocessJob)
    state = new_state()
    drain_until(job, state, lambda: state.stage == "count" and state.fraction > 0.0)
    t0 = time.monotonic()
    job.cancel()
    drain_until(job, state, lambda: job.finished)
    assert time.monotonic() - t0 < 3.0
    assert job.end.status == "cancelled" and state.status == "cancelled"
    assert job.end.message == "stage 'count' cancelled"
    assert ws.read_state()["count"]["status"] == "cancelled"
    assert not (ws.root / "count" / "count.json").exists()


def test_only_one_job_at_a_time(ws):
    from oblique_city.addon import jobs
    from oblique_city.core.errors import CityError

    slow(ws, steps=100)
    job = jobs.start_job(ws.root, ["count"], mode="thread")
    with pytest.raises(CityError, match="another"):
        jobs.start_job(ws.root, ["count"], mode="thread")
    job.cancel()
    jobs.wait(job, new_state(), timeout_s=20)


def test_runtime_stage_forces_a_thread(ws):
    """A stage registered at run time is unknown to a child process, so the job runs in a thread."""
    from oblique_city.addon import jobs

    job = jobs.start_job(ws.root, ["count"], mode="subprocess")
    assert isinstance(job, jobs.ThreadJob)
    assert jobs.wait(job, new_state(), timeout_s=20).status == "done"


def test_failed_stage_message(ws):
    from oblique_city.addon import jobs

    ws.project["stages"]["count"] = {"steps": "many"}
    ws.save_project()
    job = jobs.start_job(ws.root, ["count"], mode="subprocess", launcher=LAUNCHER)
    state = new_state()
    end = jobs.wait(job, state, timeout_s=30)
    assert end.status == "failed" and state.status == "failed"
    assert "option 'steps' should be int" in end.message and "\n" not in end.message


def test_run_operator_builds_the_stage_layer(addon, ws):
    """``city.run_stages`` (EXEC, as from a script) runs the job, and the main thread then runs the builder
    registered for the stage."""
    bpy = addon
    from oblique_city.addon import builders, scene_tree

    def build_count(scene, w):
        coll = scene_tree.layer_collection(scene, "count", "Count")
        obj = bpy.data.objects.new("count-marker", None)
        obj["steps"] = w.read_state()["count"]["metrics"]["steps"]
        coll.objects.link(obj)
        return "1 marker"

    builders.register_builder("count", build_count)
    try:
        bpy.context.scene.oblique_city.workspace = str(ws.root)
        assert bpy.ops.city.run_stages(stages="count") == {"FINISHED"}
        assert bpy.data.objects["count-marker"]["steps"] == 5
        assert bpy.context.window_manager.oblique_city_job.status == "done"
        assert bpy.ops.city.build_scene() == {"FINISHED"}
        assert len([o for o in bpy.data.objects if o.name.startswith("count-marker")]) == 1
        assert len([o for o in bpy.data.objects if "oc_image_id" in o]) == 3
    finally:
        builders.unregister_builder("count")


def test_panels_read_status(addon, ws):
    from oblique_city.addon import jobs
    from oblique_city.panels import block_summary, stage_state

    assert block_summary(ws.root)["images"] == 3
    assert stage_state(ws.root) == {}
    jobs.wait(jobs.start_job(ws.root, ["count"], mode="thread"), new_state(), timeout_s=20)
    assert stage_state(ws.root)["count"]["status"] == "done"


def test_no_workspace_is_an_error_report(addon):
    bpy = addon
    with pytest.raises(RuntimeError, match="no workspace"):
        bpy.ops.city.run_stages(stages="count")



def test_an_undrained_finished_job_does_not_block_the_next(ws):
    from oblique_city.addon import jobs

    first = jobs.start_job(ws.root, ["count"], mode="thread")
    first.thread.join(timeout=20)
    assert not first.finished  # its end is still in the queue: nobody drained it
    second = jobs.start_job(ws.root, ["count"], mode="thread", force=True)
    assert first.finished and first.end.status == "done"
    assert jobs.wait(second, new_state(), timeout_s=20).status == "done"


def test_loading_a_file_cancels_the_running_job(addon, ws):
    bpy = addon
    from oblique_city.addon import jobs

    slow(ws)
    job = jobs.start_job(ws.root, ["count"], mode="thread")
    state = new_state()
    drain_until(job, state, lambda: state.fraction > 0.0)
    bpy.ops.wm.read_homefile(app_template="")
    assert job.ctx.cancelled  # set by the add-on's load_pre handler
    drain_until(job, state, lambda: job.finished, timeout_s=5)
    assert job.end.status == "cancelled"


class FakeWindowManager:
    """The real window manager's job state, with the window-only calls (timers, cursor progress) recorded."""

    def __init__(self, wm):
        self.oblique_city_job = wm.oblique_city_job
        self.calls = []

    def progress_update(self, value):
        self.calls.append(("progress", value))

    def progress_end(self):
        self.calls.append(("progress_end",))

    def event_timer_remove(self, timer):
        self.calls.append(("timer_remove", timer))


@pytest.mark.parametrize("cancel", [False, True])
def test_modal_handler_drains_cancels_and_finishes(addon, ws, cancel):
    """The modal operator's handler, fed timer and Esc events as Blender would (modal events do not fire
    headless): it only drains the queue, Esc cancels, and the end is handled on this (the main) thread."""
    bpy = addon
    from oblique_city.addon import jobs
    from oblique_city.operators.run import CITY_OT_run_stages

    slow(ws, steps=400 if cancel else 5, sleep_s=0.02 if cancel else 0.0)
    wm = FakeWindowManager(bpy.context.window_manager)
    context = SimpleNamespace(scene=bpy.context.scene, window_manager=wm, workspace=None, screen=None)
    reports = []
    op = SimpleNamespace(_job=jobs.start_job(ws.root, ["count"], mode="subprocess", launcher=LAUNCHER),
                         _timer="timer", report=lambda kind, msg: reports.append((kind, msg)))
    timer = SimpleNamespace(type="TIMER", value="NOTHING")
    assert CITY_OT_run_stages.modal(op, context, SimpleNamespace(type="MOUSEMOVE", value="NOTHING")) == \
        {"PASS_THROUGH"}
    t0 = time.monotonic()
    result = CITY_OT_run_stages.modal(op, context, timer)
    while result == {"PASS_THROUGH"}:
        assert time.monotonic() - t0 < 30
        if cancel and wm.oblique_city_job.fraction > 0.0 and not op._job.cancel_time:
            assert CITY_OT_run_stages.modal(op, context, SimpleNamespace(type="ESC", value="PRESS")) == \
                {"RUNNING_MODAL"}
        time.sleep(0.02)
        result = CITY_OT_run_stages.modal(op, context, timer)
    assert result == ({"CANCELLED"} if cancel else {"FINISHED"})
    assert ("timer_remove", "timer") in wm.calls and wm.calls[-1] == ("progress_end",)
    if cancel:  # Esc came after some progress had been shown
        assert any(c[0] == "progress" and 0.0 < c[1] < 1.0 for c in wm.calls)
    assert jobs.active_job() is None
    assert reports[-1][0] == ({"WARNING"} if cancel else {"INFO"})
    assert ws.read_state()["count"]["status"] == ("cancelled" if cancel else "done")
