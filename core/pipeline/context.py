"""Run context: progress callback, cancellation flag, executor and log shared by a running job."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from ..errors import Cancelled

ProgressCallback = Callable[[str, int, int, str], None]
"""``callback(stage, done, total, message)``."""

log = logging.getLogger("oblique_city")


@dataclass
class RunContext:
    """What a stage gets besides its workspace and config.

    Attributes
    ----------
    on_progress : called as ``on_progress(stage, done, total, message)``; may be None
    cancel_event : set it (from any thread) to cancel; stages call :meth:`check` in long loops
    executor : runs independent units (see :mod:`.executor`); in-process by default
    stage : name of the running stage (set by the runner)
    """

    on_progress: ProgressCallback | None = None
    cancel_event: threading.Event = field(default_factory=threading.Event)
    executor: object | None = None
    stage: str = ""

    def progress(self, done: int, total: int, message: str = "") -> None:
        """Report progress of the current stage and raise :class:`Cancelled` if cancellation was asked."""
        if self.on_progress is not None:
            self.on_progress(self.stage, int(done), int(total), message)
        self.check()

    @property
    def cancelled(self) -> bool:
        return self.cancel_event.is_set()

    def cancel(self) -> None:
        self.cancel_event.set()

    def check(self) -> None:
        """Raise :class:`Cancelled` if the user asked to stop."""
        if self.cancel_event.is_set():
            raise Cancelled(f"stage '{self.stage}' cancelled" if self.stage else "cancelled")

    def get_executor(self):
        """The executor of this run (an in-process one if none was given)."""
        if self.executor is None:
            from .executor import Executor

            self.executor = Executor("inline")
        return self.executor
