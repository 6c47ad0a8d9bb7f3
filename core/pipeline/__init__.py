"""Stage pipeline: workspace, stage API, runner, progress and cancellation, executor."""

from .context import RunContext
from .executor import Executor
from .runner import run_stages, status
from .stage import Stage, StageResult
from .workspace import Workspace

__all__ = ["Executor", "RunContext", "Stage", "StageResult", "Workspace", "run_stages", "status"]
