"""Mutation fuzzing of every block reader: a file the writer made, then damaged (a line deleted, repeated or cut,
the file truncated, a number or word replaced by text, NaN, infinity, 1e400, an empty string, XML specials) is
either read or refused with one InputError naming the damaged file's folder; any other exception is a bug."""

from __future__ import annotations

import random
import re
import shutil

import pytest

from oblique_city.core.errors import CityError
from oblique_city.core.io.formats import read_block, write_block

TOKENS = ("abc", "nan", "", "-1", "1e400", "0", "inf", "-0", "9999999999", "1.5", "<", "&amp;", '"', "1,2")
# format -> (what the writer writes, the reader's source inside it, the files to damage, the reader's options)
FORMATS = {
    "opk": ("list.txt", "list.txt", ("list.txt", "list_cameras.toml"), {}),
    "bex": ("block.xml", "block.xml", ("block.xml",), {}),
    "metashape": ("cams.xml", "cams.xml", ("cams.xml",), {}),
    "colmap": ("model", "model", ("model/cameras.txt", "model/images.txt", "model/frames.txt", "model/rigs.txt"),
               {"crs": "EPSG:25832"}),
    "gnssimu": ("events.txt", "events.txt", ("events.txt", "events_cameras.toml"), {}),
    "native": ("block.json", "block.json", ("block.json",), {}),
}
RUNS = 80


def damage(text: str, rng: random.Random) -> str:
    """``text`` with one random mutation."""
    lines = text.split("\n")
    k = rng.randrange(len(lines))
    op = rng.randrange(7)
    if op == 0:
        del lines[k]
    elif op == 1:
        lines.insert(k, lines[k])
    elif op == 2:
        lines[k] = lines[k][: rng.randrange(len(lines[k]) + 1)]
    elif op == 3:
        return text[: rng.randrange(len(text))]
    else:
        tokens = list(re.finditer(r"-?\d+(\.\d+)?(e-?\d+)?|[A-Za-z_]+", lines[k]))
        if tokens:
            t = rng.choice(tokens)
            lines[k] = lines[k][: t.start()] + rng.choice(TOKENS) + lines[k][t.end():]
    return "\n".join(lines)


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_damaged_files_are_read_or_refused_cleanly(penta_block, tmp_path, fmt):
    written, source, files, options = FORMATS[fmt]
    original = tmp_path / "original"
    original.mkdir()
    write_block(fmt, penta_block, original / written)
    assert len(read_block(fmt, original / source, **options).images) == len(penta_block.images)
    rng = random.Random(fmt)
    refused = 0
    for run in range(RUNS):
        work = tmp_path / f"run{run}"
        shutil.copytree(original, work)
        target = work / rng.choice(files)
        target.write_text(damage(target.read_text(), rng))
        try:
            read_block(fmt, work / source, **options)
        except CityError as e:
            refused += 1
            assert str(work) in str(e), f"run {run}: the error names no file: {e}"
        shutil.rmtree(work)
    assert refused > RUNS // 10  # the damage is real: many files are refused


def test_damaged_binary_colmap_models_are_refused(penta_block, tmp_path):
    """A truncated binary COLMAP file (which made pycolmap hang, allocate without bound or read garbage), a count
    too large for its file and a name that is not UTF-8 are refused naming the file; the intact model, with 3D points
    as pycolmap writes them, passes the check."""
    import struct

    import numpy as np
    import pycolmap

    from oblique_city.core.errors import InputError
    from oblique_city.core.io.colmap_binary import check_binary_model

    write_block("colmap", penta_block, tmp_path / "m", binary=True)
    rec = pycolmap.Reconstruction(str(tmp_path / "m"))
    ids = sorted(rec.images)[:3]
    for i in ids:
        rec.images[i].points2D = pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0 + k, 20.0])) for k in range(4)])
    for k in range(4):
        track = pycolmap.Track()
        for i in ids:
            track.add_element(i, k)
        rec.add_point3D(np.array([1.0, 2.0, 3.0 + k]), track, np.array([10, 20, 30], np.uint8))
    rec.write_binary(str(tmp_path / "m"))
    check_binary_model(tmp_path / "m")
    for name in ("cameras.bin", "images.bin", "rigs.bin", "frames.bin", "points3D.bin"):
        full = (tmp_path / "m" / name).read_bytes()
        damaged = [full[: int(len(full) * f)] for f in (0.1, 0.5, 0.9)] + [struct.pack("<Q", 10**12) + full[8:]]
        for data in damaged:
            work = tmp_path / "work"
            shutil.copytree(tmp_path / "m", work)
            (work / name).write_bytes(data)
            with pytest.raises(InputError, match=f"{name}, field '{name[:-4]}': truncated or damaged COLMAP binary"):
                read_block("colmap", work, crs="EPSG:25832")
            shutil.rmtree(work)
    images = (tmp_path / "m" / "images.bin").read_bytes()
    at = images.index(b".jpg\0")
    (tmp_path / "m" / "images.bin").write_bytes(images[:at] + b"\xdc" + images[at + 1:])
    with pytest.raises(InputError, match="a name that is not UTF-8 text"):
        read_block("colmap", tmp_path / "m", crs="EPSG:25832")
