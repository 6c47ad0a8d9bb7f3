"""Jobs: core stages running outside Blender's UI thread, reporting through a queue the UI drains.

Two ways to run, one interface (:class:`Job`: ``start``, ``cancel``, ``queue``):

* :class:`SubprocessJob` (the default): ``python -c "...core.cli.main()" run WS --stages ... --json-progress`` in
  a child process that speaks JSON lines on stdout. It works the same with bpy from PyPI and in a real Blender:
  the child is started with ``sys.executable`` (Blender >= 2.92 points it at its bundled Python) and gets the
  parent's ``sys.path`` through ``PYTHONPATH``, plus the folder that holds this extension, so it imports the same
  ``oblique_city`` package and the wheels Blender installed for it. A crash in native code (Open3D, pycolmap,
  OpenCV) ends the child, never Blender; the GIL of Blender's UI is never held by a stage; and cancelling is
  a SIGTERM, which the CLI turns into ``RunContext.cancel()`` so the stage stops at its next ``ctx.progress`` and
  records ``cancelled`` in ``state.json`` (a child that does not stop within :data:`KILL_AFTER_S` is killed).
  The child imports the package as plain ``oblique_city``, so the ``processes`` and ``dask`` executors can pickle
  its functions by name; inside Blender's process they would be ``bl_ext.<repo>.oblique_city...``, a name no
  worker process can import.
* :class:`ThreadJob`: the runner in a background thread of this process. Needed for stages registered at run
  time with ``core.pipeline.registry.register`` (plug-ins, tests), which a child process does not know; cancel
  sets the :class:`RunContext` cancel event.

Either way only the main thread touches bpy: the modal operator calls :func:`drain` on a timer, which copies
progress into the window manager's job state, and builds the scene objects itself when the job has ended.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

from ..core.errors import Cancelled, CityError
from ..core.pipeline import Executor, RunContext, Workspace, run_stages
from ..core.pipeline.registry import STAGE_MODULES, stage_names
from ..core.pipeline.runner import plan

KILL_AFTER_S = 10.0
"""Seconds a cancelled child process gets to stop cleanly before it is killed."""

CLI_SNIPPET = "import sys; from oblique_city.core.cli import main; sys.exit(main(sys.argv[1:]))"


@dataclass(frozen=True)
class ExecutorSettings:
    """Where a stage's independent units run (see ``core.pipeline.executor``)."""

    mode: str = "inline"
    workers: int = 2
    scheduler: str = ""


@dataclass
class JobEnd:
    """How a job ended: ``done``, ``failed`` or ``cancelled``, with a one-line message."""

    status: str
    message: str = ""


@dataclass
class Job(ABC):
    """A running set of stages. Events in :attr:`queue` are dicts: ``{"event": "progress", "stage", "done",
    "total", "message"}`` and, last, ``{"event": "end", "status", "message"}``."""

    ws_root: Path
    stages: list[str] | None
    force: bool = False
    executor: ExecutorSettings = field(default_factory=ExecutorSettings)
    queue: queue.Queue = field(default_factory=queue.Queue)
    planned: list[str] = field(default_factory=list)
    end: JobEnd | None = None

    @abstractmethod
    def start(self) -> None:
        """Start running; events arrive in :attr:`queue`."""

    @abstractmethod
    def cancel(self) -> None:
        """Ask the job to stop; it ends with status ``cancelled`` (or ``done`` if it finished first)."""

    @abstractmethod
    def poll(self) -> None:
        """Called by :func:`drain` on every tick, in the main thread."""

    @property
    def finished(self) -> bool:
        return self.end is not None

    def _put_progress(self, stage: str, done: int, total: int, message: str) -> None:
        self.queue.put({"event": "progress", "stage": stage, "done": done, "total": total, "message": message})

    def _put_end(self, status: str, message: str) -> None:
        self.queue.put({"event": "end", "status": status, "message": message})


class ThreadJob(Job):
    """The runner in a daemon thread of this process."""

    def start(self) -> None:
        self.ctx = RunContext(on_progress=self._put_progress)
        self.thread = threading.Thread(target=self._run, name="oblique-city-job", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        ex = None
        try:
            ex = Executor(self.executor.mode, workers=self.executor.workers,
                          address=self.executor.scheduler or None)
            self.ctx.executor = ex
            records = run_stages(Workspace.open(self.ws_root), self.stages, self.ctx, force=self.force)
        except Cancelled as e:
            self._put_end("cancelled", str(e))
        except CityError as e:
            self._put_end("failed", str(e))
        except Exception as e:  # a bug: keep Blender alive, say what happened
            self._put_end("failed", f"internal error: {e!r}")
        else:
            self._put_end("done", "; ".join(f"{r.name} {r.status} ({r.seconds:.1f} s)" for r in records))
        finally:
            if ex is not None:
                ex.close()

    def cancel(self) -> None:
        self.ctx.cancel()

    def poll(self) -> None:
        """Nothing to escalate: a thread cannot be stopped from outside, the stage stops at its next
        ``ctx.progress`` or ``ctx.check``."""


def child_environment() -> dict[str, str]:
    """The child's environment: this process's import path (and the folder holding the extension) as
    ``PYTHONPATH``, so it imports the same ``oblique_city`` and the same dependencies."""
    root = Path(__file__).resolve().parents[1]
    extension_dir = [str(root.parent)] if root.name == "oblique_city" else []  # an editable checkout needs none
    paths = extension_dir + [p for p in sys.path if p and os.path.isdir(p)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env["PYTHONUNBUFFERED"] = "1"
    return env


class SubprocessJob(Job):
    """The CLI in a child process, progress as JSON lines on its stdout."""

    launcher: list[str] | None = None

    def command(self) -> list[str]:
        launcher = self.launcher or [sys.executable, "-c", CLI_SNIPPET]
        cmd = [*launcher, "run", str(self.ws_root), "--json-progress", "--executor", self.executor.mode,
               "--workers", str(self.executor.workers)]
        if self.stages:
            cmd += ["--stages", ",".join(self.stages)]
        if self.force:
            cmd.append("--force")
        if self.executor.mode == "dask" and self.executor.scheduler:
            cmd += ["--scheduler", self.executor.scheduler]
        return cmd

    def start(self) -> None:
        self.cancel_time: float | None = None
        self.stdout_lines: list[str] = []
        self.stderr_lines: list[str] = []
        self.proc = subprocess.Popen(self.command(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env=child_environment(), cwd=str(self.ws_root))
        readers = [threading.Thread(target=self._read_stdout, daemon=True),
                   threading.Thread(target=self._read_stderr, daemon=True)]
        for t in readers:
            t.start()
        threading.Thread(target=self._wait, args=(readers,), daemon=True).start()

    def _read_stdout(self) -> None:
        for line in self.proc.stdout:
            line = line.strip()
            try:
                ev = json.loads(line)
            except json.JSONDecodeError:
                ev = None
            if isinstance(ev, dict) and {"stage", "done", "total"} <= ev.keys():
                self._put_progress(str(ev["stage"]), int(ev["done"]), int(ev["total"]), str(ev.get("message", "")))
            elif line:
                self.stdout_lines.append(line)

    def _read_stderr(self) -> None:
        for line in self.proc.stderr:
            if line.strip():
                self.stderr_lines.append(line.rstrip())

    def _wait(self, readers: list[threading.Thread]) -> None:
        code = self.proc.wait()
        for t in readers:
            t.join()
        said = [s.removeprefix("oblique-city: ").removeprefix("error: ") for s in self.stderr_lines
                if s.startswith("oblique-city:")]  # the CLI's one-line messages
        if code == 0:
            self._put_end("done", "; ".join(" ".join(s.split()[:4]) for s in self.stdout_lines))
        elif code == 130 or self.cancel_time is not None:
            self._put_end("cancelled", said[-1] if said else "cancelled")
        else:
            last = said[-1] if said else (self.stderr_lines[-1] if self.stderr_lines else f"exit code {code}")
            self._put_end("failed", last)

    def cancel(self) -> None:
        if self.proc.poll() is None:
            self.cancel_time = time.monotonic()
            self.proc.terminate()

    def poll(self) -> None:
        if (self.cancel_time is not None and self.proc.poll() is None
                and time.monotonic() - self.cancel_time > KILL_AFTER_S):
            with contextlib.suppress(ProcessLookupError):
                self.proc.kill()


# --- the one active job ----------------------------------------------------------------------------------
_active: Job | None = None


def active_job() -> Job | None:
    """The job started last, until its end has been handled."""
    return _active


def start_job(ws_root: str | Path, stages: list[str] | None, force: bool = False, mode: str = "subprocess",
              executor: ExecutorSettings | None = None, launcher: list[str] | None = None) -> Job:
    """Start stages on a workspace. ``mode`` is ``subprocess`` or ``thread``; stages registered at run time force
    ``thread`` (a child process would not know them), unless a ``launcher`` (the command before ``run WS ...``)
    is given, which must then register them in the child itself. Raises :class:`CityError` for unknown stages, a missing
    block, or when another job is running."""
    global _active
    if _active is not None and not _active.finished and not drain(_active, SimpleNamespace()):
        raise CityError("another Oblique City job is running (cancel it first)")
    ws = Workspace.open(ws_root)
    if not ws.has_block():
        raise CityError(f"{ws.root}: no block imported yet")
    try:
        planned = plan(stages)
    except ImportError as e:  # a registered stage whose module or dependencies are missing
        raise CityError(f"a stage cannot be loaded: {e}") from e
    if not planned:
        raise CityError("no stages are registered yet")
    runtime_only = set(stage_names()) - set(STAGE_MODULES)
    if mode == "thread" or (launcher is None and runtime_only & set(planned)):
        job: Job = ThreadJob(ws.root, stages, force, executor or ExecutorSettings())
    else:
        job = SubprocessJob(ws.root, stages, force, executor or ExecutorSettings())
        job.launcher = launcher
    job.planned = planned
    job.start()
    _active = job
    return job


def cancel_active() -> None:
    """Cancel the active job, if it is running (when Blender loads another file or the add-on is disabled, the
    operator that would have drained it is gone)."""
    if _active is not None and not _active.finished:
        _active.cancel()


def forget_job(job: Job) -> None:
    """Drop ``job`` as the active job (after its end was handled)."""
    global _active
    if _active is job:
        _active = None


def drain(job: Job, state) -> bool:
    """Move the job's queued events into ``state`` (the window manager's job state, or any object with the
    attributes ``running``, ``stage``, ``fraction``, ``message``, ``status``). True once the end was seen.

    Overall progress counts finished planned stages plus the running stage's fraction. Never blocks.
    """
    job.poll()
    while True:
        try:
            ev = job.queue.get_nowait()
        except queue.Empty:
            return job.finished
        if ev["event"] == "progress":
            n = max(1, len(job.planned))
            i = job.planned.index(ev["stage"]) if ev["stage"] in job.planned else 0
            frac = ev["done"] / ev["total"] if ev["total"] > 0 else 0.0
            state.stage = ev["stage"]
            state.fraction = min(1.0, (i + min(1.0, frac)) / n)
            state.message = f"{ev['stage']}: {ev['done']}/{ev['total']} {ev['message']}".strip()
            state.running = True
        else:
            job.end = JobEnd(ev["status"], ev["message"])
            state.status = ev["status"]
            state.message = ev["message"]
            state.running = False
            if ev["status"] == "done":
                state.fraction = 1.0
            return True


def wait(job: Job, state, timeout_s: float | None = None, tick_s: float = 0.05) -> JobEnd:
    """Drain until the job ends (scripts and ``execute`` without a UI). Cancels the job on timeout."""
    t0 = time.monotonic()
    cancelled = False
    while not drain(job, state):
        if timeout_s is not None and not cancelled and time.monotonic() - t0 > timeout_s:
            job.cancel()
            cancelled = True
        time.sleep(tick_s)
    return job.end
