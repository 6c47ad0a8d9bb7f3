"""The Stage API: one stage = one function over a workspace, with a config dataclass and declared outputs."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..errors import ConfigError


@dataclass(frozen=True)
class StageResult:
    """What a stage returns: the files it wrote (workspace-relative), metrics for the state and reports."""

    outputs: tuple[str, ...] = ()
    metrics: dict[str, Any] = field(default_factory=dict)
    message: str = ""


@dataclass(frozen=True)
class Stage:
    """A pipeline stage.

    Attributes
    ----------
    name : CLI and state name (``match``, ``aerotri``, ...)
    run : ``run(ws, cfg, ctx) -> StageResult``
    config : dataclass type of the stage's configuration (all fields with defaults)
    requires : stages whose outputs this one reads (``block`` is the imported block)
    description : one line for ``--help`` and panels
    version : bump when the algorithm changes so finished runs are redone
    adjusted_block : with ``block`` in ``requires``: the stage reads ``ws.load_block()``, the adjusted block once
        aerial triangulation has written it (False for the stages before and of aerial triangulation)
    inputs : workspace files the operator edits that the stage reads (e.g. manual measurements): their content
        enters its fingerprint when they exist
    """

    name: str
    run: Callable[..., StageResult]
    config: type
    requires: tuple[str, ...] = ("block",)
    description: str = ""
    version: str = "1"
    adjusted_block: bool = True
    inputs: tuple[str, ...] = ()

    def make_config(self, values: dict[str, Any] | None = None, source: str = "project.toml") -> Any:
        """Build the config dataclass from a dict, rejecting unknown keys and wrong types."""
        values = dict(values or {})
        known = {f.name: f for f in dataclasses.fields(self.config)}
        for k in values:
            if k not in known:
                raise ConfigError(f"{source}: [stages.{self.name}] has unknown option '{k}' "
                                  f"(known: {', '.join(sorted(known))})")
        defaults = self.config()
        for k, v in values.items():
            ref = getattr(defaults, k)
            if ref is not None and not isinstance(v, type(ref)) and not (
                    isinstance(ref, float) and isinstance(v, int) and not isinstance(v, bool)):
                if isinstance(ref, tuple) and isinstance(v, list):
                    values[k] = tuple(v)
                    continue
                if isinstance(ref, str) and isinstance(v, (int, float)) and not isinstance(v, bool):
                    values[k] = str(v)  # e.g. --set aerotri.connection=3 arrives as a number
                    continue
                raise ConfigError(f"{source}: [stages.{self.name}] option '{k}' should be "
                                  f"{type(ref).__name__}, got {type(v).__name__} {v!r}")
            if isinstance(ref, float) and isinstance(v, int):
                values[k] = float(v)
        return self.config(**values)
