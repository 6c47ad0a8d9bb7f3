"""The extension zip builds (without wheels) with Blender's own CLI, validates, installs into a headless bpy
under a temporary BLENDER_USER_RESOURCES, enables, and its import operator runs from the installed copy."""

from __future__ import annotations

import json
import sys
import textwrap
import zipfile

import pytest
from bpytools import REPO, run_python

from oblique_city.core.io.native import write_block

pytestmark = pytest.mark.xdist_group("bpy")

INSTALL_AND_IMPORT = textwrap.dedent('''
    import json, subprocess, sys
    import bpy

    ZIP, BLOCK, WS = sys.argv[1:4]
    bpy.ops.wm.read_homefile(app_template="")
    result = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default", enable_on_install=True)
    module = sys.modules["bl_ext.user_default.oblique_city"]
    op_module = bpy.types.CITY_OT_import_block.__module__
    bpy.ops.city.import_block(filepath=BLOCK, block_format="native", workspace=WS)
    cams = sorted(o["oc_view"] for o in bpy.data.objects if o.type == "CAMERA" and "oc_view" in o)
    prefs = bpy.context.preferences.addons["bl_ext.user_default.oblique_city"].preferences
    # a job's child process imports the installed copy (and its dependencies) through child_environment()
    from bl_ext.user_default.oblique_city.addon import jobs
    child = subprocess.run([sys.executable, "-c", "import oblique_city.core.cli as m; print(m.__file__)"],
                           env=jobs.child_environment(), capture_output=True, text=True)
    print("RESULT " + json.dumps({"install": sorted(result), "module": module.__file__, "op_module": op_module,
                                  "cameras": cams, "job_mode": prefs.job_mode, "child": child.stdout.strip()}))
''')


def test_extension_builds_validates_installs_and_imports(tmp_path, utm_block):
    build = run_python([str(REPO / "tools" / "build_extension.py"), "--no-wheels", "--output-dir",
                        str(tmp_path / "dist"), "--build-dir", str(tmp_path / "build")])
    assert build.returncode == 0, build.stderr + build.stdout
    zips = list((tmp_path / "dist").glob("oblique_city-*-no-wheels.zip"))
    assert len(zips) == 1 and "built and validated" in build.stdout

    names = zipfile.ZipFile(zips[0]).namelist()
    assert {"blender_manifest.toml", "__init__.py", "addon/__init__.py", "operators/__init__.py",
            "panels/__init__.py", "core/pipeline/runner.py"} <= set(names)
    assert not [n for n in names if n.startswith(("tests/", "tools/", "benchmarks/")) or "__pycache__" in n]

    sys.path.insert(0, str(REPO / "tools"))
    try:
        from build_extension import blender_cli
    finally:
        sys.path.remove(str(REPO / "tools"))
    cli, tags = blender_cli()
    validate = run_python([str(cli), "validate", str(zips[0]), "--valid-tags", str(tags)])
    assert validate.returncode == 0 and "Success" in validate.stdout, validate.stdout + validate.stderr

    write_block(utm_block, tmp_path / "block.json")
    script = tmp_path / "install.py"
    script.write_text(INSTALL_AND_IMPORT)
    user = tmp_path / "blender_user"
    run = run_python([str(script), str(zips[0]), str(tmp_path / "block.json"), str(tmp_path / "ws")],
                     env={"BLENDER_USER_RESOURCES": str(user)})
    lines = [s for s in run.stdout.splitlines() if s.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout + run.stderr
    out = json.loads(lines[0][len("RESULT "):])
    installed = user / "extensions" / "user_default" / "oblique_city"
    assert out["install"] == ["FINISHED"]
    assert out["module"] == str(installed / "__init__.py")
    assert out["op_module"] == "bl_ext.user_default.oblique_city.operators.import_block"
    assert out["cameras"] == sorted(img.view for img in utm_block.images.values())
    assert out["job_mode"] == "subprocess"
    assert out["child"] == str(installed / "core" / "cli.py")
    assert (tmp_path / "ws" / "block" / "block.json").is_file()
