"""The Stage API: one stage = one function over a workspace, with a config dataclass and declared outputs."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ..errors import ConfigError


@dataclass(frozen=True)
class Range:
    """The admissible values of a numeric option: ``lo <= v <= hi`` (``lo < v`` where ``lo_open``), finite, or NaN
    where ``nan`` (NaN: derived from the data)."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    nan: bool = False

    def error(self, v: float) -> str | None:
        """What is wrong with ``v``, or None."""
        if math.isnan(v):
            return None if self.nan else "a number, not NaN"
        if math.isinf(v) or v < self.lo or (self.lo_open and v == self.lo) or v > self.hi:
            return self.describe()
        return None

    def describe(self) -> str:
        lo = "" if self.lo == -math.inf else f"{'>' if self.lo_open else '>='} {self.lo:g}"
        hi = "" if self.hi == math.inf else f"<= {self.hi:g}"
        text = " and ".join(t for t in (lo, hi) if t) or "finite"
        return text + (" (or NaN: from the data)" if self.nan else "")


POSITIVE = Range(0.0, lo_open=True)
NON_NEGATIVE = Range(0.0)
FRACTION = Range(0.0, 1.0)
AT_LEAST_ONE = Range(1.0)


def area_error(value: Any) -> str | None:
    """What is wrong with an area option (empty, or ``[x0, y0, x1, y1]`` with ``x0 < x1`` and ``y0 < y1``), or
    None."""
    what = "empty or [x0, y0, x1, y1] with x0 < x1 and y0 < y1"
    if not isinstance(value, (tuple, list)):
        return what
    if len(value) == 0:
        return None
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    return None if numbers and len(value) == 4 and value[0] < value[2] and value[1] < value[3] else what


def odd_error(value: int) -> str | None:
    """What is wrong with an odd window size option, or None."""
    return None if value >= 1 and value % 2 == 1 else "an odd number >= 1"


Rule = Range | tuple[str, ...] | Callable[[Any], str | None]
"""A rule of an option: a :class:`Range` of numbers, the names a text (or each element of a tuple) may take, or a
function returning what is wrong with a value (None when it is right)."""


def option_error(value: Any, rule: Rule) -> str | None:
    """What is wrong with ``value`` by ``rule``, or None."""
    if isinstance(rule, Range):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return "a number"
        return rule.error(float(value))
    if isinstance(rule, tuple):
        bad = [v for v in (value if isinstance(value, (tuple, list)) else (value,)) if str(v) not in rule]
        return f"one of {', '.join(rule)}" if bad else None
    return rule(value)


class CheckedOptions:
    """Mixin of an options dataclass: every option with a rule in ``RULES`` is checked on construction (numbers
    without a rule must be finite, or NaN where that is their default), so no bad value reaches an algorithm,
    whatever built the options (project.toml, ``--set``, a Blender panel or a script)."""

    RULES: ClassVar[dict[str, Rule]] = {}
    ORDERED: ClassVar[tuple[tuple[str, str, bool], ...]] = ()
    """Pairs of options ``(lower, upper, strict)``: ``upper`` must be at least ``lower`` (greater than it where
    ``strict``); a pair with a NaN is not compared."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            rule = self.RULES.get(f.name)
            if rule is None:
                if not isinstance(v, float):
                    continue
                rule = Range(nan=isinstance(f.default, float) and math.isnan(f.default))
            msg = option_error(v, rule)
            if msg is not None:
                raise ConfigError(f"option '{f.name}' must be {msg}, got {v!r}")
        for lower, upper, strict in self.ORDERED:
            a, b = getattr(self, lower), getattr(self, upper)
            if b < a or (strict and b == a):
                raise ConfigError(f"option '{upper}' must be {'greater than' if strict else 'at least'} {lower} "
                                  f"({a}), got {b}")


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
        try:
            return self.config(**values)
        except ConfigError as e:
            raise ConfigError(f"{source}: [stages.{self.name}] {e}") from None
