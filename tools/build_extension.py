"""Build the Blender extension zip with Blender's own extension CLI, then validate it.

    python tools/build_extension.py              # dist/oblique_city-<version>.zip with linux-x64 wheels
    python tools/build_extension.py --no-wheels  # dist/oblique_city-<version>-no-wheels.zip (deps installed apart)

Steps:

1. Resolve the runtime dependencies pinned in ``pyproject.toml`` for CPython 3.11 on manylinux x86_64
   (``pip install --dry-run --report``, metadata only), with ``numpy`` pinned so everything resolves against the
   numpy Blender ships, then ``pip download --no-deps --only-binary=:all:`` every resolved wheel except numpy
   (Blender ships it) and bpy into ``wheels/`` (git-ignored; wheels already there are reused).
2. Copy the source tree to ``build/extension/oblique_city`` and write the wheel list into *that copy's*
   ``blender_manifest.toml`` (``wheels = ["./wheels/..."]``). Blender requires every listed wheel to exist when it
   builds, so the committed manifest keeps ``wheels = []`` and never names files that are not in git.
3. Run ``blender_ext.py build`` (the manifest's ``[build] paths_exclude_pattern`` keeps tests, tools and caches
   out of the zip) and ``blender_ext.py validate`` on the zip, both from the bpy wheel
   (``bpy/<ver>/scripts/addons_core/bl_pkg/cli/blender_ext.py``, tags from
   ``bpy/<ver>/scripts/modules/_bpy_internal/extensions/tags.py``): no Blender binary needed.

With all wheels the zip is large (Open3D alone is a few hundred MB): that is what installing such an add-on
offline takes. Nothing large is committed: ``wheels/``, ``build/`` and ``dist/`` are git-ignored.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXCLUDED_DEPENDENCIES = {"numpy", "bpy"}
"""Not bundled: Blender ships numpy; bpy is Blender itself."""
PLATFORMS = ["manylinux2014_x86_64"] + [f"manylinux_2_{v}_x86_64" for v in (17, 24, 27, 28, 31, 34, 35)]
"""pip tags accepted for Blender's ``linux-x64`` (glibc 2.35 and older, like Blender's own build baseline)."""
TOP_LEVEL_SKIP = {".git", ".ci", "build", "dist", "wheels", "wheels_cache", "demo", "tests", "benchmarks", "tools"}
"""Top-level folders never copied into the build tree (the manifest's ``paths_exclude_pattern`` drops them from
the zip anyway; not copying them keeps test data and outputs from slowing the build)."""
ANYWHERE_SKIP = shutil.ignore_patterns("__pycache__", "*.egg-info", ".pytest_cache", ".ruff_cache", "*.blend1")


def _copy_ignore(folder: str, names: list[str]) -> set[str]:
    skip = set(ANYWHERE_SKIP(folder, names))
    if Path(folder).resolve() == REPO:
        skip |= TOP_LEVEL_SKIP & set(names)
    return skip


def blender_cli() -> tuple[Path, Path]:
    """Paths of ``blender_ext.py`` and ``tags.py`` inside the installed bpy wheel."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        sys.exit("build_extension: bpy is not installed (pip install bpy==5.0.1)")
    root = Path(spec.origin).parent
    clis = sorted(root.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    tags = sorted(root.glob("*/scripts/modules/_bpy_internal/extensions/tags.py"))
    if not clis or not tags:
        sys.exit(f"build_extension: blender_ext.py or tags.py not found under {root}")
    return clis[-1], tags[-1]


def _name(requirement: str) -> str:
    return re.split(r"[\[<>=!~; ]", requirement, maxsplit=1)[0].strip().lower().replace("_", "-")


def runtime_requirements() -> tuple[list[str], str | None]:
    """The pinned runtime dependencies of ``pyproject.toml`` and the numpy pin (for resolution only)."""
    deps = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    numpy_pin = next((d for d in deps if _name(d) == "numpy"), None)
    return [d for d in deps if _name(d) not in EXCLUDED_DEPENDENCIES], numpy_pin


def _pip(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args], check=True)


def _platform_args() -> list[str]:
    args = ["--only-binary=:all:", "--python-version", "3.11", "--implementation", "cp"]
    for p in PLATFORMS:
        args += ["--platform", p]
    return args


def resolve(requirements: list[str], numpy_pin: str | None) -> list[str]:
    """``name==version`` of every wheel the requirements need on linux-x64 / CPython 3.11, numpy and bpy left
    out."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        _pip("install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report), "--target",
             str(Path(tmp) / "target"), *_platform_args(), *requirements, *([numpy_pin] if numpy_pin else []))
        items = json.loads(report.read_text(encoding="utf-8"))["install"]
    pins = [f"{i['metadata']['name']}=={i['metadata']['version']}" for i in items]
    return sorted(p for p in pins if _name(p) not in EXCLUDED_DEPENDENCIES)


def download_wheels(pins: list[str], dest: Path) -> list[Path]:
    """Download the pinned wheels into ``dest`` (reusing those already there); the wheel files, sorted."""
    dest.mkdir(parents=True, exist_ok=True)
    _pip("download", "--no-deps", "--quiet", "--dest", str(dest), *_platform_args(), *pins)
    wanted = {_name(p): p.split("==")[1] for p in pins}
    wheels = []
    for f in sorted(dest.glob("*.whl")):
        dist, version = f.name.split("-")[:2]
        if wanted.get(_name(dist)) == version:
            wheels.append(f)
    missing = set(wanted) - {_name(f.name.split("-")[0]) for f in wheels}
    if missing:
        sys.exit(f"build_extension: wheels missing after download: {', '.join(sorted(missing))}")
    return wheels


def set_manifest_wheels(manifest: Path, wheels: list[str]) -> None:
    """Replace the ``wheels = [...]`` entry of a manifest (text edit, comments and layout kept)."""
    text = manifest.read_text(encoding="utf-8")
    entry = "wheels = [\n" + "".join(f'  "{w}",\n' for w in wheels) + "]" if wheels else "wheels = []"
    new, n = re.subn(r"(?ms)^wheels\s*=\s*\[.*?\]", lambda _: entry, text, count=1)
    if n != 1:
        sys.exit(f"build_extension: no 'wheels = [...]' entry in {manifest}")
    manifest.write_text(new, encoding="utf-8")


def stage_source(build_dir: Path, wheels: list[Path]) -> Path:
    """A clean copy of the tree at ``build_dir/oblique_city`` with the wheels and the rewritten manifest."""
    src = build_dir / "oblique_city"
    if src.exists():
        shutil.rmtree(src)
    shutil.copytree(REPO, src, ignore=_copy_ignore)
    if wheels:
        (src / "wheels").mkdir()
        for w in wheels:
            target = src / "wheels" / w.name
            try:
                os.link(w, target)
            except OSError:
                shutil.copy2(w, target)
    set_manifest_wheels(src / "blender_manifest.toml", [f"./wheels/{w.name}" for w in wheels])
    return src


def build(no_wheels: bool = False, output_dir: Path = REPO / "dist", build_dir: Path = REPO / "build" / "extension",
          wheels_dir: Path = REPO / "wheels") -> Path:
    """Build and validate the extension zip; returns its path."""
    cli, tags = blender_cli()
    wheels: list[Path] = []
    if not no_wheels:
        requirements, numpy_pin = runtime_requirements()
        wheels = download_wheels(resolve(requirements, numpy_pin), wheels_dir)
    src = stage_source(build_dir, wheels)
    version = tomllib.loads((src / "blender_manifest.toml").read_text(encoding="utf-8"))["version"]
    output_dir.mkdir(parents=True, exist_ok=True)
    out = output_dir / f"oblique_city-{version}{'-no-wheels' if no_wheels else ''}.zip"
    if out.exists():
        out.unlink()
    subprocess.run([sys.executable, str(cli), "build", "--source-dir", str(src), "--output-filepath", str(out),
                    "--valid-tags", str(tags)], check=True)
    subprocess.run([sys.executable, str(cli), "validate", str(out), "--valid-tags", str(tags)], check=True)
    size_mb = out.stat().st_size / 1e6
    print(f"build_extension: {out} ({size_mb:.1f} MB, {len(wheels)} wheels) built and validated")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--no-wheels", action="store_true", help="leave the Python wheels out (a light zip for tests)")
    p.add_argument("--output-dir", type=Path, default=REPO / "dist")
    p.add_argument("--build-dir", type=Path, default=REPO / "build" / "extension")
    p.add_argument("--wheels-dir", type=Path, default=REPO / "wheels")
    args = p.parse_args(argv)
    build(args.no_wheels, args.output_dir, args.build_dir, args.wheels_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
