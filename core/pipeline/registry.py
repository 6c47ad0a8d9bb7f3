"""The stages the runner knows, in pipeline order. Each entry is a module defining ``STAGE``."""

from __future__ import annotations

import importlib

from ..errors import ConfigError
from .stage import Stage

STAGE_MODULES: dict[str, str] = {
    "match": ".matching.stage",
    "aerotri": ".aerotri.stage",
    "dense": ".dense.stage",
    "surface": ".surface.stage",
    "buildings": ".buildings.stage",
    "texture": ".texture.stage",
    "windows": ".windows.stage",
}
"""Stage name -> module (relative to the ``core`` package) that defines ``STAGE``, in pipeline order."""

_extra: dict[str, Stage] = {}


def register(stage: Stage) -> None:
    """Add a stage at run time (plug-ins and tests)."""
    _extra[stage.name] = stage


def unregister(name: str) -> None:
    _extra.pop(name, None)


def stage_names() -> list[str]:
    """All stage names in pipeline order."""
    return list(STAGE_MODULES) + [n for n in _extra if n not in STAGE_MODULES]


def get_stage(name: str) -> Stage:
    if name in _extra:
        return _extra[name]
    if name not in STAGE_MODULES:
        raise ConfigError(f"unknown stage '{name}' (known: {', '.join(stage_names()) or 'none'})")
    core_pkg = __package__.rsplit(".", 1)[0]
    return importlib.import_module(STAGE_MODULES[name], core_pkg).STAGE
