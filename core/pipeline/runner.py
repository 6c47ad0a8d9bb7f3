"""The runner: the single entry point that runs stages for the CLI, batch scripts, Blender jobs and tests.

A stage is skipped when its fingerprint (stage version, config, the fingerprints and finishing times of the stages
it requires, the block it reads: the imported one and, once aerial triangulation has written it, the adjusted one,
and the operator's files it reads, such as manual measurements) matches the last successful run recorded in
``state.json`` and its outputs still exist. A dependency that ran again (forced, or after a change of its own
inputs) therefore makes every stage after it stale.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
import traceback
from dataclasses import dataclass

from ..errors import Cancelled, CityError, WorkspaceError
from .context import RunContext, log
from .registry import get_stage, stage_names
from .workspace import ADJUSTED_BLOCK_FILE, BLOCK_FILE, Workspace


@dataclass(frozen=True)
class StageRecord:
    """The outcome of one stage in a run: ``done``, ``skipped``, ``failed`` or ``cancelled``."""

    name: str
    status: str
    seconds: float
    message: str = ""


def _file_digest(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def fingerprint(ws: Workspace, name: str, state: dict) -> str:
    """The input fingerprint of a stage given the current state of its dependencies."""
    stage = get_stage(name)
    cfg = stage.make_config(ws.stage_options(name))
    doc = {"stage": name, "version": stage.version, "config": dataclasses.asdict(cfg), "crs": ws.crs, "deps": {}}
    for dep in stage.requires:
        if dep == "block":
            doc["deps"]["block"] = _file_digest(ws.path(BLOCK_FILE)) if ws.has_block() else None
            if stage.adjusted_block and ws.path(ADJUSTED_BLOCK_FILE).exists():
                doc["deps"]["adjusted_block"] = _file_digest(ws.path(ADJUSTED_BLOCK_FILE))
        else:
            rec = state.get(dep, {})
            doc["deps"][dep] = [rec.get("fingerprint"), rec.get("finished")]
    for rel in stage.inputs:  # (absent: the fingerprint of a workspace without the file is unchanged)
        if ws.path(rel).exists():
            doc["deps"][f"file:{rel}"] = _file_digest(ws.path(rel))
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def plan(names: list[str] | None) -> list[str]:
    """The stages to consider, in pipeline order, with the stages they require added."""
    order = stage_names()
    wanted = set(order if not names else names)
    for n in list(wanted):
        get_stage(n)  # raises ConfigError for unknown names
    changed = True
    while changed:
        changed = False
        for n in list(wanted):
            for dep in get_stage(n).requires:
                if dep != "block" and dep not in wanted:
                    wanted.add(dep)
                    changed = True
    return [n for n in order if n in wanted]


def is_up_to_date(ws: Workspace, name: str, state: dict) -> bool:
    rec = state.get(name)
    if not rec or rec.get("status") != "done":
        return False
    if rec.get("fingerprint") != fingerprint(ws, name, state):
        return False
    return all(ws.path(p).exists() for p in rec.get("outputs", []))


def run_stages(ws: Workspace, names: list[str] | None = None, ctx: RunContext | None = None,
               force: bool = False) -> list[StageRecord]:
    """Run the given stages (all when None) and the stages they require, skipping up-to-date ones; ``force`` reruns
    the given stages even when up to date (the stages they require still only when stale: re-running AT with new
    options does not redo the matching).

    Raises the first stage's :class:`CityError` after recording it in ``state.json``; a :class:`Cancelled`
    is recorded as ``cancelled`` and re-raised.
    """
    ctx = ctx or RunContext()
    if not ws.has_block():
        raise WorkspaceError(f"{ws.root}: no block imported yet (run 'oblique-city import')")
    records: list[StageRecord] = []
    # every stage's options checked (its config built) before any stage runs
    configs = {name: get_stage(name).make_config(ws.stage_options(name)) for name in plan(names)}
    for name in configs:
        state = ws.read_state()
        forced = force and (names is None or name in names)
        if not forced and is_up_to_date(ws, name, state):
            records.append(StageRecord(name, "skipped", 0.0, "up to date"))
            log.info("%s: up to date", name)
            continue
        stage = get_stage(name)
        for dep in stage.requires:
            if dep != "block" and state.get(dep, {}).get("status") != "done":
                raise WorkspaceError(f"stage '{name}' needs '{dep}', which has not finished")
        cfg = configs[name]
        fp = fingerprint(ws, name, state)
        state[name] = {"status": "running", "fingerprint": None, "started": time.time()}
        ws.write_state(state)
        ctx.stage = name
        t0 = time.perf_counter()
        try:
            ctx.check()
            result = stage.run(ws, cfg, ctx)
        except Cancelled as e:
            secs = time.perf_counter() - t0
            _record(ws, name, {"status": "cancelled", "fingerprint": None, "seconds": secs, "message": str(e)})
            records.append(StageRecord(name, "cancelled", secs, str(e)))
            raise
        except CityError as e:
            secs = time.perf_counter() - t0
            _record(ws, name, {"status": "failed", "fingerprint": None, "seconds": secs, "message": str(e)})
            raise
        except Exception as e:
            secs = time.perf_counter() - t0
            _record(ws, name, {"status": "failed", "fingerprint": None, "seconds": secs,
                               "message": f"internal error: {e!r}", "traceback": traceback.format_exc()})
            raise
        secs = time.perf_counter() - t0
        _record(ws, name, {"status": "done", "fingerprint": fp, "seconds": secs, "outputs": list(result.outputs),
                           "metrics": result.metrics, "message": result.message, "finished": time.time()})
        records.append(StageRecord(name, "done", secs, result.message))
        log.info("%s: done in %.1f s %s", name, secs, result.message)
    return records


def _record(ws: Workspace, name: str, rec: dict) -> None:
    state = ws.read_state()
    state[name] = rec
    ws.write_state(state)


def status(ws: Workspace) -> list[dict]:
    """One row per known stage: name, status (``done``, ``stale``: its inputs changed or a stage it requires is not
    done, ``failed``, ``cancelled``, ``pending``), seconds and message."""
    state = ws.read_state()
    rows = []
    not_done: set[str] = set()
    for name in stage_names():
        rec = state.get(name)
        if rec is None:
            st = "pending"
        elif rec.get("status") == "done":
            fresh = ws.has_block() and is_up_to_date(ws, name, state)
            st = "done" if fresh and not not_done.intersection(get_stage(name).requires) else "stale"
        else:
            st = rec.get("status", "pending")
        if st != "done":
            not_done.add(name)
        rows.append({"stage": name, "status": st, "seconds": rec.get("seconds") if rec else None,
                     "message": rec.get("message", "") if rec else ""})
    return rows
