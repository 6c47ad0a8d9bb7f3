"""Headless faces: the import script (``python script.py`` here; ``blender --background --python script.py --``
works the same way) and ``tools/make_blend.py``, each in its own process."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bpytools import HERE, REPO, run_python

from oblique_city.core.io.native import write_block
from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")


def test_import_script(tmp_path, utm_block):
    write_block(utm_block, tmp_path / "block.json")
    run = run_python([str(HERE / "scripts" / "import_block.py"), str(tmp_path / "block.json"), "--format", "native",
                      "--workspace", str(tmp_path / "ws"), "--blend", str(tmp_path / "out.blend")])
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["cameras"] == 3 and out["crs"] == "EPSG:32632"
    assert out["views"] == {v: 1 for v in ("nadir", "north", "east")}
    assert np.abs(np.array(out["origin"][:2]) - [500250.0, 5399760.0]).max() <= 1.0
    assert (tmp_path / "out.blend").stat().st_size > 0


def test_import_script_bad_input(tmp_path):
    run = run_python([str(HERE / "scripts" / "import_block.py"), str(tmp_path / "missing.json"), "--format",
                      "native", "--workspace", str(tmp_path / "ws")])
    assert run.returncode == 2
    assert "missing.json" in run.stderr and "file not found" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1


def test_make_blend(addon, tmp_path, utm_block):
    bpy = addon
    from oblique_city.addon import cameras, georef

    ws = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    ws.save_block(utm_block)
    run = run_python([str(REPO / "tools" / "make_blend.py"), str(ws.root), str(tmp_path / "city.blend")])
    assert run.returncode == 0, run.stderr
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "city.blend"))
    scene = bpy.context.scene
    assert scene.oblique_city.workspace == str(ws.root)
    assert georef.get_crs(scene) == "EPSG:32632"
    for img in utm_block.images.values():
        obj = bpy.data.objects[img.id]
        assert obj.users_collection[0].name == f"Cameras {img.view}"
        assert np.abs(cameras.pose_of(scene, obj).C - img.pose.C).max() < 1e-3
