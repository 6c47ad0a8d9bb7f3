"""The block's photographs read as 8-bit grey or colour, whatever their depth: what matching, dense matching,
the true orthophoto and the textures take.

Aerial cameras deliver 16-bit TIFFs whose values use 12 or 14 of the 16 bits. OpenCV's 8-bit reading keeps the top
8 of the 16 bits (the value over 256): a 12-bit image came out with grey values 0 to 15, and SIFT found almost no
features on it. A photograph deeper than 8 bits (a 16-bit TIFF or PNG, a float TIFF) is read as it is and scaled
by the significant bits its file declares (a TIFF's MaxSampleValue tag, a PNG's sBIT chunk), else by the smallest
of 8, 10, 12, 14 or 16 significant bits that holds the largest value of its camera's photographs: a sensor has one
depth, and a dark exposure (a 12-bit one whose brightest value stays under 1024) taken alone would be read as a
10-bit one, four times as bright as its neighbours. The stages take the camera's depth from a sample of its
photographs (:func:`camera_bits`), and a photograph brighter than its sample is scaled by its own. A float image
whose values stay within 0..1 is scaled from that range. 8-bit files are read by OpenCV as before (JPEG, 8-bit TIFF
and PNG), a fourth band (alpha or near infrared) left out of the colour.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model import ImageBlock
from .validate import PNG_SIGNATURE, TIFF_SIGNATURES, resolve_image

SIGNIFICANT_BITS = (8, 10, 12, 14, 16)
"""The bit depths a deep photograph's values are taken to use (the smallest that holds its maximum)."""


def _deep(path: str) -> bool:
    """True for a PNG or TIFF whose samples are deeper than 8 bits (from the file's header)."""
    try:
        with open(path, "rb") as f:
            head = f.read(32)
        if head[:8] == PNG_SIGNATURE:
            return head[24] > 8  # IHDR bit depth
        if head[:4] in TIFF_SIGNATURES:
            import tifffile

            with tifffile.TiffFile(path) as t:
                return t.pages[0].dtype is not None and np.dtype(t.pages[0].dtype).itemsize > 1
    except (OSError, ValueError, struct.error, IndexError):
        return False
    return False


def declared_bits(path: str) -> int | None:
    """The significant bits a deep photograph's file declares for its samples: from a TIFF's MaxSampleValue (tag
    281; the largest over the samples) or a PNG's sBIT chunk (the largest over the colour samples); None where the
    file declares none or cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            if head == PNG_SIGNATURE:
                while True:  # chunks: length, type, data, CRC; sBIT comes before the first IDAT
                    size, kind = struct.unpack(">I4s", f.read(8))
                    if kind == b"sBIT":
                        data = f.read(size)
                        bits = max(data[:3] if len(data) >= 3 else data[:1])
                        return int(bits) if 0 < bits <= 16 else None
                    if kind in (b"IDAT", b"IEND"):
                        return None
                    f.seek(size + 4, 1)
        if head[:4] in TIFF_SIGNATURES:
            import tifffile

            with tifffile.TiffFile(path) as t:
                tag = t.pages[0].tags.get(281)
                if tag is None:
                    return None
                peak = int(np.max(np.atleast_1d(tag.value)))
                return peak.bit_length() if 0 < peak < 2**16 else None
    except (OSError, ValueError, struct.error, IndexError):
        return None
    return None


def holding_bits(peak: float, at_least: int | None = None) -> int:
    """The smallest of :data:`SIGNIFICANT_BITS`, and at least ``at_least``, whose range holds ``peak``."""
    return next((b for b in SIGNIFICANT_BITS if peak < 2**b and b >= (at_least or 0)), SIGNIFICANT_BITS[-1])


def to_8bit(img: np.ndarray, bits: int | None = None, min_bits: int | None = None) -> np.ndarray:
    """``img`` (any depth, ``(h, w)`` or ``(h, w, bands)``) scaled to uint8 (module docstring); integer values by
    ``bits`` significant bits where given (values above ``2**bits - 1`` saturate), else by the smallest depth that
    holds their maximum and is at least ``min_bits`` (the camera's, :func:`camera_bits`)."""
    if img.dtype == np.uint8:
        return img
    peak = float(np.nanmax(img)) if img.size else 0.0
    if img.dtype.kind == "f" and peak <= 1.0:
        full = 1.0
    elif bits is not None and img.dtype.kind in "ui":
        full = float(2**bits - 1)
    else:
        full = float(2 ** holding_bits(peak, min_bits) - 1)
    out = np.clip(np.nan_to_num(img.astype(np.float32), nan=0.0) * (255.0 / full) + 0.5, 0, 255)
    return out.astype(np.uint8)


def camera_bits(block: ImageBlock, cameras: set[str] | None = None, sample: int = 8) -> dict[str, int | None]:
    """Camera id -> the significant bits of its deep photographs that declare none (the ``min_bits`` of
    :func:`read_photo`): the smallest depth holding the largest value of up to ``sample`` of its photographs, spread
    over the block (None for a camera whose photographs are 8-bit, float, declare their bits, or cannot be read:
    :func:`read_photo` reports those). Only ``cameras`` where given."""
    import cv2

    files: dict[str, list[str]] = {}
    for img in block.images.values():
        if img.file is not None and (cameras is None or img.camera_id in cameras):
            files.setdefault(img.camera_id, []).append(str(resolve_image(block, img.file)))
    out: dict[str, int | None] = {}
    for cam, paths in files.items():
        picked = [paths[k] for k in np.unique(np.linspace(0, len(paths) - 1, min(sample, len(paths))).astype(int))]
        peaks = []
        for p in picked:
            if not _deep(p) or declared_bits(p) is not None:
                continue
            img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
            if img is not None and img.dtype.kind in "ui" and img.size:
                peaks.append(float(img.max()))
        out[cam] = holding_bits(max(peaks)) if peaks else None
    return out


def read_photo(path: str | Path, colour: bool, image_id: str | None = None, min_bits: int | None = None
               ) -> np.ndarray:
    """The photograph at ``path`` as uint8 grey ``(h, w)`` or, with ``colour``, BGR ``(h, w, 3)``; an
    :class:`InputError` naming the file (and the image ``image_id``) when it cannot be read. ``min_bits``: its
    camera's depth (:func:`camera_bits`), for a deep photograph that declares none."""
    import cv2

    path = str(path)
    if _deep(path):
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if img is not None:
            img = to_8bit(img, declared_bits(path), min_bits)
            if img.ndim == 3 and img.shape[2] in (2, 4):  # grey or colour with a band beyond (alpha, infrared)
                img = img[:, :, :1] if img.shape[2] == 2 else img[:, :, :3]
            if img.ndim == 3 and img.shape[2] == 1:
                img = img[:, :, 0]
            if colour and img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            elif not colour and img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    else:
        img = cv2.imread(path, cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    if img is None:
        name = f"image '{image_id}'" if image_id is not None else "image"
        raise InputError(f"cannot read {name}", path=path, field="file")
    return img
