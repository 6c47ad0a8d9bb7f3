"""Workspace, runner (skip when unchanged, atomic state, cancellation), executor (inline, processes, Dask)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from oblique_city.core.errors import Cancelled, ConfigError, InputError, WorkspaceError
from oblique_city.core.io.native import read_block, write_block
from oblique_city.core.pipeline import Executor, RunContext, Stage, StageResult, Workspace, registry, run_stages, status
from oblique_city.core.pipeline.atomic import atomic_path, write_text
from oblique_city.core.pipeline.stage import POSITIVE, CheckedOptions, Range, Rule


def test_core_does_not_import_bpy() -> None:
    import subprocess

    code = ("import sys, importlib, pkgutil, oblique_city.core as c\n"
            "for m in pkgutil.walk_packages(c.__path__, 'oblique_city.core.'):\n"
            "    importlib.import_module(m.name)\n"
            "bad = [m for m in ('bpy', 'bmesh', 'mathutils') if m in sys.modules]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], check=True)


@dataclass(frozen=True)
class SquareConfig:
    factor: float = 2.0
    cancel_at: int = -1
    label: str = "x"


def _square_run(ws: Workspace, cfg: SquareConfig, ctx: RunContext) -> StageResult:
    block = ws.load_block()
    out = {}
    for i, img in enumerate(block.images.values()):
        if i == cfg.cancel_at:
            ctx.cancel()
        ctx.progress(i, len(block.images), img.id)
        out[img.id] = float(img.pose_approx.C[2] * cfg.factor)
    from oblique_city.core.pipeline.atomic import write_json

    write_json(ws.stage_dir("square") / "values.json", out)
    return StageResult(outputs=("square/values.json",), metrics={"n": len(out)})


def _double(x: int) -> int:
    return 2 * x


def _touch(path: str) -> str:
    from pathlib import Path

    Path(path).write_text("done")
    return path


def _blas_threads(_: int) -> tuple[list[int], str | None]:
    import os

    import scipy.linalg  # noqa: F401 - loads scipy's own BLAS after the worker started
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"], os.environ.get("OMP_NUM_THREADS")


@pytest.fixture
def square_stage():
    st = Stage("square", _square_run, SquareConfig, requires=("block",), description="test stage")
    registry.register(st)
    yield st
    registry.unregister("square")


def test_native_block_round_trip_is_exact(utm_block, tmp_path) -> None:
    write_block(utm_block, tmp_path / "b.json")
    b = read_block(tmp_path / "b.json")
    for k, img in utm_block.images.items():
        assert np.array_equal(b.images[k].pose_approx.C, img.pose_approx.C)
        assert np.array_equal(b.images[k].pose_approx.R, img.pose_approx.R)
    assert b.cameras["cam"] == utm_block.cameras["cam"]
    assert b.summary() == utm_block.summary()


def test_native_block_errors_name_field(utm_block, tmp_path) -> None:
    write_block(utm_block, tmp_path / "b.json")
    d = json.loads((tmp_path / "b.json").read_text())
    d["images"][1]["pose_approx"]["C"][2] = float("nan")
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"bad.json.*images\[img1\].pose_approx.C.*NaN"):
        read_block(tmp_path / "bad.json")
    (tmp_path / "broken.json").write_text('{"format": \n')
    with pytest.raises(InputError, match=r"broken.json:2"):
        read_block(tmp_path / "broken.json")


def test_runner_skips_unchanged_and_reruns_on_change(utm_block, tmp_path, square_stage) -> None:
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    with pytest.raises(WorkspaceError, match="no block"):
        run_stages(ws, ["square"])
    ws.save_block(utm_block)
    seen = []
    ctx = RunContext(on_progress=lambda s, d, t, m: seen.append((s, d, t)))
    recs = run_stages(ws, ["square"], ctx)
    assert [r.status for r in recs] == ["done"] and seen[0] == ("square", 0, 3)
    values = json.loads((ws.path("square/values.json")).read_text())
    assert values["img0"] == pytest.approx(1600.0)
    assert [r.status for r in run_stages(ws, ["square"])] == ["skipped"]
    ws.project["stages"]["square"] = {"factor": 3.0}
    ws.save_project()
    assert [r.status for r in run_stages(Workspace.open(ws.root), ["square"])] == ["done"]
    assert json.loads(ws.path("square/values.json").read_text())["img0"] == pytest.approx(2400.0)
    # a changed block makes the stage stale
    utm_block.images["img0"].pose_approx = utm_block.images["img1"].pose_approx
    ws.save_block(utm_block)
    assert {r["stage"]: r["status"] for r in status(ws)}["square"] == "stale"


def test_downstream_follows_a_rerun_dependency_and_the_adjusted_block(utm_block, tmp_path, square_stage) -> None:
    """A forced rerun of a stage makes the stages after it stale (same inputs, new outputs) and does not rerun the
    up-to-date stages it requires; an adjusted block
    written by aerial triangulation makes the stages that read it stale, not those that read the imported one."""
    from oblique_city.core.pipeline.workspace import ADJUSTED_BLOCK_FILE

    after = Stage("after", lambda ws, cfg, ctx: StageResult(outputs=()), SquareConfig, requires=("square",))
    before = Stage("before", lambda ws, cfg, ctx: StageResult(outputs=()), SquareConfig, adjusted_block=False)
    for st in (after, before):
        registry.register(st)
    try:
        ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
        ws.save_block(utm_block)
        run_stages(ws, ["before", "square", "after"])
        assert {r.status for r in run_stages(ws, ["before", "square", "after"])} == {"skipped"}
        run_stages(ws, ["square"], force=True)
        assert [r.status for r in run_stages(ws, ["after"])] == ["skipped", "done"]
        # forcing a stage reruns it alone: the stages it requires run only when stale
        assert [r.status for r in run_stages(ws, ["after"], force=True)] == ["skipped", "done"]
        write_block(utm_block, ws.path(ADJUSTED_BLOCK_FILE))
        stat = {r["stage"]: r["status"] for r in status(ws)}
        assert (stat["before"], stat["square"], stat["after"]) == ("done", "stale", "stale")
    finally:
        registry.unregister("after")
        registry.unregister("before")


def test_runner_cancellation_is_recorded_and_leaves_old_outputs(utm_block, tmp_path, square_stage) -> None:
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    ws.save_block(utm_block)
    ws.project["stages"]["square"] = {"cancel_at": 1}
    ws.save_project()
    with pytest.raises(Cancelled):
        run_stages(ws, ["square"])
    assert ws.read_state()["square"]["status"] == "cancelled"
    assert not ws.path("square/values.json").exists()


def test_config_errors(tmp_path, square_stage) -> None:
    with pytest.raises(ConfigError, match="unknown option 'nope'"):
        square_stage.make_config({"nope": 1})
    with pytest.raises(ConfigError, match="should be float"):
        square_stage.make_config({"factor": "big"})
    assert square_stage.make_config({"factor": 3}).factor == 3.0
    assert square_stage.make_config({"label": 3}).label == "3"
    with pytest.raises(ConfigError, match="should be str"):
        square_stage.make_config({"label": True})
    with pytest.raises(ConfigError, match="unknown stage"):
        registry.get_stage("no-such-stage")


def test_atomic_write_keeps_old_file_on_failure(tmp_path) -> None:
    p = tmp_path / "a.txt"
    write_text(p, "old")
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        with open(tmp, "w") as f:
            f.write("half")
        raise RuntimeError("killed")
    assert p.read_text() == "old"
    assert [x.name for x in tmp_path.iterdir()] == ["a.txt"]


def test_workspace_project_round_trip(tmp_path) -> None:
    ws = Workspace.create(tmp_path / "w", crs="32632", name="demo")
    assert ws.crs == "EPSG:32632"
    ws.project["stages"]["aerotri"] = {"mode": "hierarchical", "cell": 25.0, "views": ["north", "east"]}
    ws.save_project()
    again = Workspace.open(tmp_path / "w")
    assert again.project["stages"]["aerotri"] == {"mode": "hierarchical", "cell": 25.0, "views": ["north", "east"]}
    with pytest.raises(WorkspaceError, match="already exists"):
        Workspace.create(tmp_path / "w", crs="EPSG:32632")
    with pytest.raises(InputError, match="unknown coordinate reference system"):
        Workspace.create(tmp_path / "x", crs="EPSG:999999")


@pytest.mark.parametrize("mode", ["inline", "processes"])
def test_executor_local(mode: str) -> None:
    with Executor(mode, workers=2) as ex:
        done = []
        assert ex.map(_double, range(7), on_done=lambda d, t: done.append(d)) == [0, 2, 4, 6, 8, 10, 12]
        assert done[-1] == 7


@pytest.mark.parametrize("mode", ["processes", pytest.param("dask", marks=pytest.mark.xdist_group("dask"))])
def test_executor_runs_units_of_a_generator_as_they_are_drawn(mode: str, tmp_path) -> None:
    """The second item is drawn only once the first unit has run: an executor that drew all items before starting
    any unit would wait here until the time-out."""
    import time

    def items():
        first = tmp_path / "first"
        yield str(first)
        t0 = time.monotonic()
        while not first.exists():
            if time.monotonic() - t0 > 60:
                raise AssertionError("the first unit did not run before the second item was drawn")
            time.sleep(0.05)
        yield str(tmp_path / "second")

    with Executor(mode, workers=2) as ex:
        done = []
        assert ex.map(_touch, items(), on_done=lambda d, t: done.append((d, t)), total=2) == [
            str(tmp_path / "first"), str(tmp_path / "second")]
    assert done[-1] == (2, 2)


def test_process_workers_share_the_cores() -> None:
    """Each local worker gets its part of the cores for BLAS and OpenMP (loaded before or after it started), not
    a thread per core that the other workers' threads then compete with."""
    with Executor("processes", workers=2) as ex:
        out = ex.map(_blas_threads, range(2))
    for threads, omp in out:
        assert threads and all(t == ex.threads_per_worker for t in threads)
        assert omp == str(ex.threads_per_worker)


@pytest.mark.xdist_group("dask")
def test_executor_dask_local_cluster() -> None:
    with Executor("dask", workers=2) as ex:
        assert ex.map(_double, range(5)) == [0, 2, 4, 6, 8]


def test_tiepoints_round_trip_and_no_unpickling(tmp_path) -> None:
    from oblique_city.core.model import TiePoints

    t = TiePoints(xyz=np.arange(6.0).reshape(2, 3), obs_track=[0, 0, 1, 1], obs_image=[0, 1, 0, 1],
                  obs_uv=np.ones((4, 2)), image_ids=["a", "b"], extra={"std": np.ones(2)})
    t.save(str(tmp_path / "t.npz"))
    u = TiePoints.load(str(tmp_path / "t.npz"))
    assert u.image_ids == ["a", "b"] and np.array_equal(u.xyz, t.xyz) and np.array_equal(u.extra["std"], [1, 1])
    np.savez(tmp_path / "evil.npz", xyz=np.zeros((1, 3)), image_ids=np.array([object()], dtype=object))
    with pytest.raises(WorkspaceError, match="not a tie point file"):
        TiePoints.load(str(tmp_path / "evil.npz"))


@dataclass(frozen=True)
class RuledConfig(CheckedOptions):
    size: float = 1.0
    count: int = 2
    kind: str = "a"
    kinds: tuple[str, ...] = ("a",)
    z: float = float("nan")
    free: float = 0.5

    RULES: ClassVar[dict[str, Rule]] = {"size": POSITIVE, "count": Range(2.0), "kind": ("a", "b"),
                                        "kinds": ("a", "b")}


@pytest.mark.parametrize(("values", "message"), [
    ({"size": 0.0}, "option 'size' must be > 0, got 0.0"),
    ({"count": 1}, "option 'count' must be >= 2, got 1"),
    ({"kind": "c"}, "option 'kind' must be one of a, b, got 'c'"),
    ({"kinds": ["a", "c"]}, "option 'kinds' must be one of a, b, got ('a', 'c')"),
    ({"z": float("inf")}, "option 'z' must be finite (or NaN: from the data), got inf"),
    ({"free": float("nan")}, "option 'free' must be a number, not NaN, got nan"),
])
def test_option_rules(values, message) -> None:
    """Options are checked by their rules on construction; numbers without a rule must be finite (NaN only where it
    is the default, meaning "from the data")."""
    stage = Stage("ruled", _square_run, RuledConfig)
    with pytest.raises(ConfigError) as info:
        stage.make_config(values)
    assert str(info.value) == f"project.toml: [stages.ruled] {message}"
    assert stage.make_config({"z": 3.0, "kinds": ["b", "a"]}).kinds == ("b", "a")


def test_every_stage_option_has_a_rule() -> None:
    """Each numeric, text and list option of the built-in stages has a rule (a path and an offset that may be
    negative are the only exceptions), and the defaults pass them."""
    import dataclasses

    free = {("buildings", "footprints"), ("windows", "grow_m")}
    for name in registry.stage_names():
        config = registry.get_stage(name).config
        defaults = config()
        assert isinstance(defaults, CheckedOptions), name
        for f in dataclasses.fields(config):
            v = getattr(defaults, f.name)
            if not isinstance(v, bool) and (name, f.name) not in free:
                assert f.name in config.RULES, (name, f.name)


def test_runner_checks_every_stage_before_running_any(utm_block, tmp_path, square_stage) -> None:
    """A bad option of a later stage stops the run before the first stage starts (not after it ran for hours)."""
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    ws.save_block(utm_block)
    registry.register(Stage("ruled", _square_run, RuledConfig, requires=("square",)))
    try:
        ws.project["stages"] = {"ruled": {"size": -1.0}}
        ws.save_project()
        with pytest.raises(ConfigError, match="option 'size' must be > 0"):
            run_stages(ws, ["ruled"])
        assert "square" not in ws.read_state()
    finally:
        registry.unregister("ruled")


def test_atomic_write_refuses_a_folder(tmp_path) -> None:
    """A folder where a file is to be written is refused before anything is written (os.replace raised
    IsADirectoryError at the end, e.g. for 'export-block --out' naming a folder)."""
    (tmp_path / "out").mkdir()
    with pytest.raises(ConfigError, match="out is a folder: give a file name"):
        write_text(tmp_path / "out", "x")
    assert [p.name for p in tmp_path.iterdir()] == ["out"] and not list((tmp_path / "out").iterdir())


def test_an_output_file_named_on_a_command_line_is_checked_when_the_arguments_are_read(tmp_path) -> None:
    """A benchmark's ``--out`` naming a folder is refused by argparse before the run (bench_at wrote its JSON after
    its adjustments and failed there with IsADirectoryError, its results lost); a file path passes unchanged."""
    import argparse

    from oblique_city.core.pipeline.atomic import output_file

    ap = argparse.ArgumentParser(prog="bench")
    ap.add_argument("--out", type=output_file)
    with pytest.raises(SystemExit):
        ap.parse_args(["--out", str(tmp_path)])
    assert ap.parse_args(["--out", str(tmp_path / "a.json")]).out == str(tmp_path / "a.json")
    with pytest.raises(argparse.ArgumentTypeError, match="is a folder: give a file name"):
        output_file(str(tmp_path))
