"""Block format registry: one reader (and writer) per format name, used by the CLI and the Blender import."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ConfigError, InputError
from ..model import ImageBlock
from . import blocksexchange, colmap, metashape, native, opk, trajectory
from .common import COMMON_OPTIONS

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


READER_OPTIONS: dict[str, dict[str, str]] = {
    "native": {}, "opk": opk.READER_OPTIONS, "bex": blocksexchange.READER_OPTIONS, "colmap": colmap.READER_OPTIONS,
    "metashape": metashape.READER_OPTIONS, "gnssimu": trajectory.READER_OPTIONS}
"""Format name -> its reader's own options with a line of help each; every reader but the native one also takes
:data:`.common.COMMON_OPTIONS`."""


def reader_options(fmt: str) -> dict[str, str]:
    """Every option the reader of ``fmt`` takes, with a line of help each."""
    return dict(READER_OPTIONS[fmt]) if fmt == "native" else {**READER_OPTIONS[fmt], **COMMON_OPTIONS}


def read_block(fmt: str, source: str | Path, **options: Any) -> ImageBlock:
    """Read a block in format ``fmt`` from ``source`` (a file or folder, depending on the format); an option the
    format's reader does not take is refused with the list of those it takes."""
    if fmt not in READERS:
        raise ConfigError(f"unknown block format '{fmt}' (known: {', '.join(sorted(READERS))})")
    _refuse_unknown(fmt, options, sorted(reader_options(fmt)))
    return READERS[fmt](str(source), **options)


def write_block(fmt: str, block: ImageBlock, dest: str | Path, **options: Any) -> None:
    """Write ``block`` in format ``fmt`` to ``dest``; an option the format's writer does not take is refused with
    the list of those it takes."""
    if fmt not in WRITERS:
        raise ConfigError(f"unknown block format '{fmt}' (known: {', '.join(sorted(WRITERS))})")
    _refuse_unknown(fmt, options, list(writer_options(fmt)))
    WRITERS[fmt](block, str(dest), **options)


def _refuse_unknown(fmt: str, options: dict[str, Any], known: list[str]) -> None:
    """ConfigError naming the options not in ``known`` and listing those (a typo never passes silently)."""
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ConfigError(f"unknown option(s) for format '{fmt}': {', '.join(unknown)} (it takes: "
                          f"{', '.join(known) or 'none'})")


def writer_options(fmt: str) -> dict[str, Any]:
    """The options the writer of ``fmt`` takes, with their defaults (its keyword parameters)."""
    import inspect

    params = list(inspect.signature(WRITERS[fmt]).parameters.values())[2:]  # after the block and the destination
    return {p.name: p.default for p in params if p.kind is p.POSITIONAL_OR_KEYWORD}


def detect_format(source: str | Path) -> str:
    """The block format of ``source``, from what it holds: a folder with ``cameras.txt`` or ``.bin`` is a COLMAP
    model; a ``.json`` file the native block; an XML file (``.xml``, ``.xmlz``) BlocksExchange or Metashape by its
    root element; a text list an event list when its header names roll and heading (or it has a ``# heading:``
    line), else an OPK list. :class:`InputError` (naming the file) when it is none of them."""
    p = Path(source)
    if p.is_dir():
        if any((p / f"cameras.{ext}").is_file() for ext in ("txt", "bin")):
            return "colmap"
        raise InputError("a folder without cameras.txt or cameras.bin: not a COLMAP model; give the format",
                         path=source, field="format")
    if not p.is_file():
        raise InputError("file not found", path=source)
    suffix = p.suffix.lower()
    if suffix == ".json":
        return "native"
    if suffix in (".xml", ".xmlz"):
        from .validate import parse_xml

        tag = parse_xml(p).tag
        if tag in ("BlocksExchange", "document"):
            return "bex" if tag == "BlocksExchange" else "metashape"
        raise InputError(f"XML with root element <{tag}>: neither BlocksExchange nor Metashape camera XML; give the "
                         "format", path=source, field="format")
    from .validate import read_text_lines

    lines = [t.strip().lower() for t in read_text_lines(p)[:200] if t.strip()]
    if any(t.startswith("#") and t.lstrip("# ").startswith("heading:") for t in lines):
        return "gnssimu"
    header = next((t for t in lines if not t.startswith("#")), "")
    words = set(header.replace(",", " ").replace(";", " ").replace("\t", " ").split())
    if {"roll", "heading"} <= words:
        return "gnssimu"
    if words & {"omega", "phi", "kappa", "om", "ph", "ka"} or header[:1].isdigit() or len(words) >= 7:
        return "opk"
    raise InputError("cannot tell the block format from the file (not JSON, XML, an OPK list or an event list); "
                     "give the format", path=source, field="format")
