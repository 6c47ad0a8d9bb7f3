"""A trivial stage for the job tests: counts ``steps`` steps, sleeping ``sleep_s`` each, and writes the count.

Imported by the tests (thread jobs) and, through a launcher, by the child process of subprocess jobs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from oblique_city.core.pipeline import Stage, StageResult
from oblique_city.core.pipeline.atomic import write_json
from oblique_city.core.pipeline.registry import register


@dataclass(frozen=True)
class CountConfig:
    steps: int = 5
    sleep_s: float = 0.0


def run_count(ws, cfg: CountConfig, ctx) -> StageResult:
    for i in range(cfg.steps):
        time.sleep(cfg.sleep_s)
        ctx.progress(i + 1, cfg.steps, f"step {i + 1}")
    write_json(ws.stage_dir("count") / "count.json", {"steps": cfg.steps})
    return StageResult(outputs=("count/count.json",), metrics={"steps": cfg.steps}, message=f"{cfg.steps} steps")


STAGE = Stage("count", run=run_count, config=CountConfig, description="count steps (test stage)")


def install() -> None:
    """Register the stage in this process."""
    register(STAGE)


LAUNCHER_SNIPPET = ("import sys; sys.path.insert(0, {here!r}); import jobstages; jobstages.install(); "
                    "from oblique_city.core.cli import main; sys.exit(main(sys.argv[1:]))")
"""``python -c`` code for a child process that knows the ``count`` stage (format with ``here``)."""
