"""Block format registry: one reader (and writer) per format name, used by the CLI and the Blender import."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..model import ImageBlock
from . import blocksexchange, colmap, metashape, native, opk, trajectory

Reader = Callable[..., ImageBlock]
Writer = Callable[..., None]

READERS: dict[str, Reader] = {"native": lambda source, **_: native.read_block(source),
                              "opk": opk.read_opk, "bex": blocksexchange.read_bex, "colmap": colmap.read_colmap,
                              "metashape": metashape.read_metashape, "gnssimu": trajectory.read_gnssimu}
"""Format name -> ``reader(source, **options) -> ImageBlock``."""

WRITERS: dict[str, Writer] = {"native": lambda block, dest, **_: native.write_block(block, dest),
                              "opk": opk.write_opk, "bex": blocksexchange.write_bex, "colmap": colmap.write_colmap,
                              "metashape": metashape.write_metashape, "gnssimu": trajectory.write_gnssimu}
"""Format name -> ``writer(block, dest, **options)``."""


def read_block(fmt: str, source: str | Path, **options: Any) -> ImageBlock:
    """Read a block in format ``fmt`` from ``source`` (a file or folder, depending on the format)."""
    if fmt not in READERS:
        raise ConfigError(f"unknown block format '{fmt}' (known: {', '.join(sorted(READERS))})")
    return READERS[fmt](str(source), **options)


def write_block(fmt: str, block: ImageBlock, dest: str | Path, **options: Any) -> None:
    """Write ``block`` in format ``fmt`` to ``dest``."""
    if fmt not in WRITERS:
        raise ConfigError(f"unknown block format '{fmt}' (known: {', '.join(sorted(WRITERS))})")
    WRITERS[fmt](block, str(dest), **options)
