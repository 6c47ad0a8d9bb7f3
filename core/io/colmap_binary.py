"""Structural check of COLMAP binary model files before pycolmap reads them.

pycolmap reads a binary model without checking that its counts fit the file: a truncated or damaged file made it
hang (``frames.bin`` cut at a tenth), allocate without bound (``points3D.bin``) or return garbage without a word
(``cameras.bin`` and ``rigs.bin`` cut at nine tenths). :func:`check_binary_model` walks each file's records (little
endian, as COLMAP 3.12 writes them, the layouts checked against files pycolmap writes) and refuses one whose counts
do not fit it or which does not end where its last record does, naming the file and the byte.

* ``cameras.bin``: ``uint64`` count; per camera ``uint32`` id, ``int32`` model, ``uint64`` width and height, the
  model's ``double`` parameters.
* ``images.bin``: ``uint64`` count; per image ``uint32`` id, 7 ``double`` (``qw qx qy qz tx ty tz``), ``uint32``
  camera id, the name (UTF-8, NUL-terminated), ``uint64`` point count, per point 2 ``double`` and a ``uint64``.
* ``rigs.bin``: ``uint64`` count; per rig ``uint32`` id, ``uint32`` sensor count, the reference sensor (``int32``
  type, ``uint32`` id), per other sensor its type, id, a ``uint8`` has-pose flag and, when set, 7 ``double``.
* ``frames.bin``: ``uint64`` count; per frame ``uint32`` id and rig id, 7 ``double``, ``uint32`` data count, per
  datum ``int32`` sensor type, ``uint32`` sensor id, ``uint64`` data id.
* ``points3D.bin``: ``uint64`` count; per point ``uint64`` id, 3 ``double``, 3 ``uint8``, a ``double`` error,
  ``uint64`` track length, per element 2 ``uint32``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

from ..errors import InputError


class _Reader:
    """Little-endian records of one file, every read checked against its end."""

    def __init__(self, path: Path) -> None:
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def fail(self, what: str) -> InputError:
        return InputError(f"truncated or damaged COLMAP binary file: {what} (byte {self.at} of {len(self.data)})",
                          path=self.path, field=self.path.stem)

    def take(self, fmt: str) -> tuple:
        n = struct.calcsize("<" + fmt)
        if self.at + n > len(self.data):
            raise self.fail("a record runs past the end")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += n
        return values

    def skip(self, n: int) -> None:
        if self.at + n > len(self.data):
            raise self.fail("a record runs past the end")
        self.at += n

    def count(self, least_bytes: int, fmt: str = "Q") -> int:
        """A count of items of at least ``least_bytes`` each, refused when they cannot fit in the rest."""
        (n,) = self.take(fmt)
        if n * least_bytes > len(self.data) - self.at:
            raise self.fail(f"a count of {n} items cannot fit")
        return n

    def text(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise self.fail("a name without its end")
        try:
            value = self.data[self.at:end].decode("utf-8")
        except UnicodeDecodeError:
            raise self.fail("a name that is not UTF-8 text") from None
        self.at = end + 1
        return value


def _param_count(model: int) -> int:
    import pycolmap

    try:
        return len(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model), 1.0, 1, 1).params)
    except (ValueError, TypeError, RuntimeError):
        return -1


def _cameras(r: _Reader) -> None:
    for _ in range(r.count(24)):
        _, model, _, _ = r.take("IiQQ")
        n = _param_count(model)
        if n < 0:
            raise r.fail(f"unknown camera model id {model}")
        r.take(f"{n}d")


def _images(r: _Reader) -> None:
    for _ in range(r.count(73)):
        r.take("I7dI")
        r.text()
        r.skip(24 * r.count(24))


def _rigs(r: _Reader) -> None:
    for _ in range(r.count(8)):
        _, sensors = r.take("II")
        if sensors:
            r.take("iI")
        for _ in range(max(sensors - 1, 0)):
            if r.take("iIB")[2]:
                r.take("7d")


def _frames(r: _Reader) -> None:
    for _ in range(r.count(68)):
        r.take("II7d")
        r.skip(16 * r.count(16, "I"))


def _points(r: _Reader) -> None:
    for _ in range(r.count(51)):
        r.take("Q3d3Bd")
        r.skip(8 * r.count(8))


FILES: dict[str, Callable[[_Reader], None]] = {"cameras.bin": _cameras, "images.bin": _images, "rigs.bin": _rigs,
                                               "frames.bin": _frames, "points3D.bin": _points}


def check_binary_model(folder: str | Path) -> None:
    """Refuse (:class:`InputError` naming the file and the byte) a binary model file in ``folder`` whose records do
    not fit it exactly; files that are not there are left to pycolmap."""
    for name, walk in FILES.items():
        path = Path(folder) / name
        if path.exists():
            r = _Reader(path)
            walk(r)
            if r.at != len(r.data):
                raise r.fail("bytes after the last record")
