"""Atomic writes: a temporary file in the target's folder, then ``os.replace``.

A killed run never leaves a half-written artefact: either the old file or the complete new one is there.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..errors import ConfigError


def _refuse_folder(path: Path) -> None:
    if path.is_dir():
        raise ConfigError(f"{path} is a folder: give a file name")


def output_file(text: str) -> str:
    """An output file's path given on a command line (an ``argparse`` type), unchanged: a folder there is refused
    when the arguments are read (``argparse.ArgumentTypeError``), not when the job that would write it has run."""
    try:
        _refuse_folder(Path(text))
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on error it is removed.

    ``suffix`` defaults to the target's suffix, so writers that pick a format by extension keep working. A folder
    at ``path`` is refused (:class:`ConfigError`): the file would replace nothing and the write would fail at the end.
    """
    path = Path(path)
    _refuse_folder(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, indent: int | None = 1, default: Callable[[Any], Any] | None = None) -> None:
    """Write ``obj`` as JSON atomically (floats keep full precision: Python writes the shortest repr); ``default``
    turns what JSON cannot hold into what it can (``json.dumps``' own, e.g. ``float`` for numpy scalars)."""
    write_text(path, json.dumps(obj, indent=indent, allow_nan=True, default=default) + "\n")
