"""The CLI face of the runner: new, import, run (with --set), status, one-line errors with exit code 2."""

from __future__ import annotations

import subprocess
import sys

import pytest
from test_pipeline import SquareConfig, Stage, _square_run

from oblique_city.core.cli import main
from oblique_city.core.io.native import write_block
from oblique_city.core.pipeline import Workspace, registry


@pytest.fixture
def square():
    registry.register(Stage("square", _square_run, SquareConfig, requires=("block",)))
    yield
    registry.unregister("square")


def test_new_import_run_status(utm_block, tmp_path, capsys, square) -> None:
    ws = tmp_path / "ws"
    assert main(["new", str(ws), "--crs", "EPSG:32632"]) == 0
    write_block(utm_block, tmp_path / "b.json")
    assert main(["import", str(ws), str(tmp_path / "b.json"), "--format", "native"]) == 0
    out = capsys.readouterr().out
    assert "imported 3 images" in out and "No exposures: HAT starts the oblique images" in out  # two are oblique
    assert main(["run", str(ws), "--stages", "square", "--set", "square.factor=0.5"]) == 0
    assert Workspace.open(ws).project["stages"]["square"]["factor"] == 0.5
    out = capsys.readouterr().out
    assert "square" in out and "done" in out
    assert main(["run", str(ws), "--stages", "square"]) == 0
    assert "skipped" in capsys.readouterr().out
    assert main(["status", str(ws)]) == 0
    out = capsys.readouterr().out
    assert "3 images" in out and "square" in out and "done" in out
    assert "No exposures: HAT starts the oblique images" in out  # status says what the block lacks, as import did


@pytest.mark.parametrize("argv,message", [
    (["run", "{ws}", "--stages", "nope"], "unknown stage 'nope'"),
    (["run", "{ws}", "--stages", "square", "--set", "square.bogus=1"], "unknown option 'bogus'"),
    (["run", "{ws}", "--set", "factor=1"], "should name a stage option"),
    (["status", "{tmp}/missing"], "not a workspace"),
    (["new", "{tmp}/other", "--crs", "EPSG:0"], "unknown coordinate reference system"),
    (["simulate", "{tmp}/sim", "--size", "0x0"], "simulate: option 'width' must be >= 16, got 0"),
    (["run", "{ws}", "--executor", "processes", "--workers", "0"], "the executor needs at least one worker, got 0"),
    (["demo", "{tmp}/demo", "--stages", "nosuch"], "unknown stage 'nosuch'"),
    (["simulate", "{tmp}/sim", "--size", "big"], "--size 'big' should be WIDTHxHEIGHT in pixels"),
    (["simulate", "{tmp}/sim", "--gsd", "nan"], "simulate: option 'gsd' must be a number, not NaN"),
    (["simulate", "{tmp}/sim", "--extend", "-1"], "simulate: option 'extend_along_h' must be >= 0"),
])
def test_user_errors_are_one_line_exit_2(utm_block, tmp_path, capsys, square, argv, message) -> None:
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    ws.save_block(utm_block)
    args = [a.format(ws=ws.root, tmp=tmp_path) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith("oblique-city: error:")


def test_module_entry_point_runs() -> None:
    out = subprocess.run([sys.executable, "-m", "oblique_city", "--help"], capture_output=True, text=True,
                         check=True).stdout
    for cmd in ("new", "import", "run", "status", "simulate", "demo"):
        assert cmd in out


def test_status_shows_the_camera_system(penta_block, tmp_path, capsys) -> None:
    """The penta block's exposures and rig, on import (its format told from the file) and in the status."""
    write_block(penta_block, tmp_path / "penta.json")
    assert main(["import", str(tmp_path / "ws"), str(tmp_path / "penta.json")]) == 0  # the format told from the file
    assert main(["status", str(tmp_path / "ws")]) == 0
    out = capsys.readouterr().out
    assert "format: native (told from the file" in out
    assert out.count("245 exposures of 5 heads; rig 'penta' (reference head nadir)") == 2


def test_bad_set_is_refused_and_nothing_is_saved(utm_block, tmp_path, capsys) -> None:
    """A --set the stage's options refuse (a bad value, an unknown stage or option) leaves project.toml as it was,
    even the good --set before it in the same command, and runs nothing."""
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    ws.save_block(utm_block)
    before = (ws.root / "project.toml").read_text()
    for bad, message in (("aerotri.sigma_px=-1", "[stages.aerotri] option 'sigma_px' must be > 0, got -1.0"),
                         ("aerotri.mode=fast", "option 'mode' must be one of integrated, hierarchical, got 'fast'"),
                         ("dense.block_size=4", "option 'block_size' must be an odd number >= 1, got 4"),
                         ("nosuch.x=1", "unknown stage 'nosuch'")):
        assert main(["run", str(ws.root), "--set", "aerotri.cell_size=20", "--set", bad]) == 2
        assert message in capsys.readouterr().err
        assert (ws.root / "project.toml").read_text() == before
        assert not (ws.root / "state.json").exists() or "match" not in (ws.root / "state.json").read_text()
