"""The one error family of Oblique City's core.

Every failure a user can cause (bad input files, a broken workspace, a cancelled job) raises a subclass of
:class:`CityError`. Front ends (CLI, Blender operators) catch ``CityError`` and show its message in one line;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class CityError(Exception):
    """Root of all errors the core raises on purpose."""


class InputError(CityError):
    """Bad input data: the message names the file, the line (when there is one) and the field.

    Parameters
    ----------
    message : what is wrong, in words a user understands
    path : the offending file, if any
    line : 1-based line number in that file, if known
    field : the column, element or key that is wrong, if known
    """

    def __init__(
        self,
        message: str,
        path: str | Path | None = None,
        line: int | None = None,
        field: str | None = None,
    ) -> None:
        self.path = None if path is None else str(path)
        self.line = line
        self.field = field
        self.reason = message
        where = []
        if self.path is not None:
            where.append(self.path + (f":{line}" if line is not None else ""))
        elif line is not None:
            where.append(f"line {line}")
        if field is not None:
            where.append(f"field '{field}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class WorkspaceError(CityError):
    """The workspace is missing, inconsistent, or lacks the outputs a stage needs."""


class ConfigError(CityError):
    """An unknown stage, option or value in a configuration."""


class Cancelled(CityError):
    """The user cancelled a running job; partial outputs were discarded."""


class ComputationError(CityError):
    """An algorithm could not produce a result from valid input (e.g. too few observations)."""
