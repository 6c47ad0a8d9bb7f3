"""Helpers for the Blender tests that start processes of their own (bpy imported there, not in the worker)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


def run_python(args: list[str], env: dict[str, str] | None = None, timeout: float = 120.0):
    """Run ``python args...`` in a subprocess (bpy imported there), returning the CompletedProcess."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=full_env, timeout=timeout)
