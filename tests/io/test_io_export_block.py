"""``oblique-city export-block``: the workspace's adjusted block (or, asked for, the imported one) in another
software's format, read back equal."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.cli import main
from oblique_city.core.errors import ConfigError
from oblique_city.core.export.command import export_block
from oblique_city.core.io.formats import read_block
from oblique_city.core.model import Pose
from oblique_city.core.pipeline import Workspace
from oblique_city.core.pipeline.workspace import ADJUSTED_BLOCK_FILE


@pytest.fixture
def adjusted_ws(tmp_path, oblique_block):
    ws = Workspace.create(tmp_path / "ws", crs=oblique_block.crs)
    ws.save_block(oblique_block)
    adjusted = read_block("native", ws.root / "block" / "block.json")
    for k, img in enumerate(adjusted.images.values()):
        img.pose_adjusted = Pose(img.pose_approx.R, img.pose_approx.C + [0.01 * k, -0.02, 0.03])
    ws.save_block(adjusted, ADJUSTED_BLOCK_FILE)
    return ws, adjusted


@pytest.mark.parametrize(("fmt", "name"), [("metashape", "cams.xml"), ("bex", "block.xml"), ("colmap", "model")])
def test_export_block_writes_the_adjusted_block(adjusted_ws, same_block, capsys, fmt, name):
    ws, adjusted = adjusted_ws
    out = ws.root.parent / "out" / name
    assert main(["export-block", str(ws.root), "--format", fmt, "--out", str(out)]) == 0
    assert "adjusted block written" in capsys.readouterr().out
    back = read_block(fmt, out, crs=adjusted.crs) if fmt == "colmap" else read_block(fmt, out)
    same_block(adjusted, back, tol_m=5e-8, tol_rad=1e-12, tol_px=1e-5, ground_points=fmt != "colmap",
               camera_ids={"cam": "1", "obl": "2"} if fmt == "colmap" else None)
    assert np.abs(back.images["img7"].pose.C - adjusted.images["img7"].pose_adjusted.C).max() < 1e-7


def test_export_block_imported_and_options(adjusted_ws, oblique_block, same_block):
    ws, _ = adjusted_ws
    out = ws.root.parent / "imported.xml"
    assert main(["export-block", str(ws.root), "--format", "bex", "--out", str(out), "--imported",
                 "-o", "rotation=opk"]) == 0
    same_block(oblique_block, read_block("bex", out), tol_m=1e-9, tol_rad=1e-12, tol_px=1e-5)
    with pytest.raises(ConfigError, match="unknown block format"):
        export_block(ws.root, "laz", out)
