"""Fixtures for the Blender tests (bpy 5.0.1 from PyPI).

Every test module here carries ``pytest.mark.xdist_group("bpy")`` so that under ``pytest -n 2 --dist loadgroup``
they share one worker and bpy is imported once. Each test starts from factory settings
(``read_homefile(app_template="")``) with the add-on registered by hand, and unregisters it afterwards.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


@pytest.fixture
def addon():
    """A fresh scene with Oblique City registered; yields the ``bpy`` module."""
    import bpy

    import oblique_city

    bpy.ops.wm.read_homefile(app_template="")
    oblique_city.register()
    try:
        yield bpy
    finally:
        oblique_city.unregister()


@pytest.fixture
def image_files(tmp_path, utm_block) -> Path:
    """Real 1200 x 900 image files for the images of ``utm_block`` in ``tmp_path/images``; returns the folder."""
    import cv2

    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for img in utm_block.images.values():
        cam = utm_block.camera_of(img)
        cv2.imwrite(str(folder / img.file), rng.integers(0, 255, (cam.height, cam.width, 3), dtype=np.uint8))
    return folder


def run_python(args: list[str], env: dict[str, str] | None = None, timeout: float = 120.0):
    """Run ``python args...`` in a subprocess (bpy imported there), returning the CompletedProcess."""
    import os
    import subprocess

    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=full_env, timeout=timeout)
