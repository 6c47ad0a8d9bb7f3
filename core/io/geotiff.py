"""GeoTIFF rasters (DSM, DTM, true ortho, quality layers) and PNG pictures of coloured layers.

A :class:`Raster` is written with tifffile and these GeoTIFF tags (GeoTIFF 1.1, OGC 19-008r4):

* ``ModelPixelScaleTag`` (33550) ``(cell, cell, 0)`` and ``ModelTiepointTag`` (33922)
  ``(0, 0, 0, x0, y0, 0)``: raster (0, 0) is the outer corner of the top-left cell, which is where
  ``Raster.x0/y0`` are, because the raster type is ``PixelIsArea``;
* ``GeoKeyDirectoryTag`` (34735) with ``GTModelTypeGeoKey`` (1 projected / 2 geographic),
  ``GTRasterTypeGeoKey`` = 1 (PixelIsArea), ``ProjectedCSTypeGeoKey`` (3072) or ``GeographicTypeGeoKey`` (2048)
  holding the EPSG code, ``VerticalCSTypeGeoKey`` (4096) for the vertical part of a compound EPSG CRS, and, for a
  CRS without EPSG code, the user-defined code 32767 with the WKT in ``GTCitationGeoKey`` (``GeoAsciiParamsTag``
  34737, read back by this module; GDAL will see a user-defined CRS);
* ``GDAL_NODATA`` (42113) as ASCII text when the raster has a no-data value (``nan`` for float rasters).

Supported data: float32/float64/uint8/uint16/int16/int32 with one band, or several bands (``(rows, cols, bands)``;
three or four uint8 bands are written as RGB/RGBA, e.g. orthophotos). Writes are atomic and deflate-compressed,
tiled (256 x 256) from 256 cells a side. Rasters larger than :data:`OVERVIEW_MIN` cells a side also get internal
overviews (further IFDs with ``NewSubfileType`` 1, halved until :data:`OVERVIEW_MIN` / 4: what GDAL and QGIS read
as overviews): colour bands averaged, float rasters averaged over their measured cells, other integer rasters
(masks, labels) taken every second cell.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.crs import parse_crs
from ..model import Raster
from ..pipeline.atomic import atomic_path

TAG_PIXEL_SCALE = 33550
TAG_TIEPOINT = 33922
TAG_TRANSFORMATION = 34264
TAG_GEOKEYS = 34735
TAG_GEO_DOUBLES = 34736
TAG_GEO_ASCII = 34737
TAG_GDAL_NODATA = 42113

KEY_MODEL_TYPE = 1024
KEY_RASTER_TYPE = 1025
KEY_CITATION = 1026
KEY_GEOGRAPHIC = 2048
KEY_PROJECTED = 3072
KEY_PROJ_LINEAR_UNITS = 3076
KEY_VERTICAL = 4096
KEY_VERTICAL_UNITS = 4099

MODEL_PROJECTED = 1
MODEL_GEOGRAPHIC = 2
RASTER_PIXEL_IS_AREA = 1
RASTER_PIXEL_IS_POINT = 2
USER_DEFINED = 32767
UNIT_METRE = 9001

SUPPORTED_DTYPES = (np.uint8, np.uint16, np.int16, np.int32, np.float32, np.float64)
OVERVIEW_MIN = 1024


def overview_levels(data: np.ndarray, rgb: bool) -> list[np.ndarray]:
    """The halved copies of ``data (rows, cols[, bands])`` for the overviews (none for small rasters)."""
    import cv2

    out = []
    level = data
    if max(data.shape[:2]) <= OVERVIEW_MIN:
        return out
    while max(level.shape[:2]) > OVERVIEW_MIN // 4:
        rows, cols = level.shape[0] // 2, level.shape[1] // 2
        if rgb:
            level = cv2.resize(level, (cols, rows), interpolation=cv2.INTER_AREA)
        elif level.dtype.kind == "f":
            blocks = level[:2 * rows, :2 * cols].reshape(rows, 2, cols, 2, *level.shape[2:])
            with np.errstate(invalid="ignore"):
                finite = np.isfinite(blocks)
                level = (np.nansum(blocks, axis=(1, 3)) / finite.sum(axis=(1, 3))).astype(level.dtype)
        else:
            level = level[:2 * rows:2, :2 * cols:2]
        out.append(np.ascontiguousarray(level))
    return out


def _crs_keys(crs_text: str) -> tuple[list[tuple[int, int, int, int]], str]:
    """GeoKey entries ``(key, location, count, value)`` and the GeoAsciiParams text for a CRS."""
    crs = parse_crs(crs_text)
    keys: list[tuple[int, int, int, int]] = []
    ascii_params = ""
    horizontal, vertical = crs, None
    if crs.is_compound:
        subs = crs.sub_crs_list
        horizontal = subs[0]
        vertical = subs[1] if len(subs) > 1 else None
    code = horizontal.to_epsg(min_confidence=90)
    model = MODEL_GEOGRAPHIC if horizontal.is_geographic else MODEL_PROJECTED
    keys.append((KEY_MODEL_TYPE, 0, 1, model))
    keys.append((KEY_RASTER_TYPE, 0, 1, RASTER_PIXEL_IS_AREA))
    if code is None:
        # No EPSG code: user-defined, the whole CRS as WKT in the citation (read back by read_geotiff).
        ascii_params = "WKT:" + crs.to_wkt() + "|"
        keys.append((KEY_CITATION, TAG_GEO_ASCII, len(ascii_params), 0))
        keys.append((KEY_GEOGRAPHIC if model == MODEL_GEOGRAPHIC else KEY_PROJECTED, 0, 1, USER_DEFINED))
        return keys, ascii_params
    keys.append((KEY_GEOGRAPHIC if model == MODEL_GEOGRAPHIC else KEY_PROJECTED, 0, 1, code))
    if model == MODEL_PROJECTED:
        keys.append((KEY_PROJ_LINEAR_UNITS, 0, 1, UNIT_METRE))
    if vertical is not None:
        vcode = vertical.to_epsg(min_confidence=90)
        if vcode is not None:
            keys.append((KEY_VERTICAL, 0, 1, vcode))
            keys.append((KEY_VERTICAL_UNITS, 0, 1, UNIT_METRE))
    return keys, ascii_params


def _geokey_directory(keys: list[tuple[int, int, int, int]]) -> tuple[int, ...]:
    """The GeoKeyDirectoryTag SHORT array (header 1, 1, 0, n, then the keys sorted by id).

    At most one key points into GeoAsciiParamsTag (the WKT citation), always at offset 0.
    """
    out = [1, 1, 0, len(keys)]
    for key, loc, count, value in sorted(keys):
        out += [key, loc, count, value]
    return tuple(out)


def write_geotiff(path: str | Path, raster: Raster, compress: bool = True) -> None:
    """Write ``raster`` as a GeoTIFF at ``path`` (atomically).

    ``raster.data`` : (rows, cols) or (rows, cols, bands), one of the dtypes in ``SUPPORTED_DTYPES``.
    """
    import tifffile

    data = np.asarray(raster.data)
    if data.dtype.type not in SUPPORTED_DTYPES:
        raise InputError(f"unsupported raster dtype {data.dtype} (use one of "
                         f"{', '.join(np.dtype(t).name for t in SUPPORTED_DTYPES)})", path=path, field="data")
    if data.ndim not in (2, 3):
        raise InputError(f"raster data must be (rows, cols) or (rows, cols, bands), got shape {data.shape}",
                         path=path, field="data")
    if not (math.isfinite(raster.cell) and raster.cell > 0):
        raise InputError(f"cell size must be positive, got {raster.cell}", path=path, field="cell")
    keys, ascii_params = _crs_keys(raster.crs)
    extratags = [
        (TAG_PIXEL_SCALE, "d", 3, (float(raster.cell), float(raster.cell), 0.0), True),
        (TAG_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, float(raster.x0), float(raster.y0), 0.0), True),
    ]
    directory = _geokey_directory(keys)
    extratags.append((TAG_GEOKEYS, "H", len(directory), directory, True))
    if ascii_params:
        extratags.append((TAG_GEO_ASCII, "s", 0, ascii_params, True))
    nodata = raster.nodata
    if nodata is None and data.dtype.kind == "f":
        nodata = float("nan")
    if nodata is not None:
        text = "nan" if isinstance(nodata, float) and math.isnan(nodata) else repr(nodata)
        extratags.append((TAG_GDAL_NODATA, "s", 0, text, True))
    rgb = data.ndim == 3 and data.shape[2] in (3, 4) and data.dtype == np.uint8
    kwargs: dict = {
        "photometric": "rgb" if rgb else "minisblack",
        "extratags": extratags,
        "compression": "zlib" if compress else None,
        "metadata": None,
    }
    if data.ndim == 3:
        kwargs["planarconfig"] = "contig"
        if rgb and data.shape[2] == 4:
            kwargs["extrasamples"] = ("unassalpha",)
    if data.shape[0] >= 256 and data.shape[1] >= 256:
        kwargs["tile"] = (256, 256)
    with atomic_path(path, suffix=".tif") as tmp, tifffile.TiffWriter(tmp) as tif:
        tif.write(data, **kwargs)
        overview = {k: v for k, v in kwargs.items() if k not in ("extratags", "metadata", "tile")}
        for level in overview_levels(data, rgb):
            tile = (256, 256) if min(level.shape[:2]) >= 256 else None
            tif.write(level, subfiletype=1, tile=tile, metadata=None, **overview)


def _tag(page, code: int):
    t = page.tags.get(code)
    return None if t is None else t.value


def _parse_geokeys(directory, ascii_params: str | None, path: str) -> dict[int, int | str]:
    d = [int(v) for v in directory]
    if len(d) < 4 or len(d) < 4 + 4 * d[3]:
        raise InputError("GeoKeyDirectoryTag is truncated", path=path, field="GeoKeyDirectoryTag")
    out: dict[int, int | str] = {}
    for i in range(d[3]):
        key, loc, count, value = d[4 + 4 * i: 8 + 4 * i]
        if loc == 0:
            out[key] = value
        elif loc == TAG_GEO_ASCII and ascii_params is not None:
            out[key] = ascii_params[value: value + count].rstrip("|\x00")
    return out


def _crs_from_geokeys(keys: dict[int, int | str], path: str) -> str:
    model = keys.get(KEY_MODEL_TYPE)
    key = KEY_GEOGRAPHIC if model == MODEL_GEOGRAPHIC else KEY_PROJECTED
    code = keys.get(key)
    if code is None:
        raise InputError("no CRS code in the GeoKey directory", path=path,
                         field="GeographicTypeGeoKey" if key == KEY_GEOGRAPHIC else "ProjectedCSTypeGeoKey")
    if code == USER_DEFINED:
        citation = keys.get(KEY_CITATION)
        if isinstance(citation, str) and citation.startswith("WKT:"):
            return citation[4:]
        raise InputError("user-defined CRS without a WKT citation (write the file with an EPSG code)",
                         path=path, field="GTCitationGeoKey")
    crs = f"EPSG:{code}"
    vcode = keys.get(KEY_VERTICAL)
    if isinstance(vcode, int) and 0 < vcode != USER_DEFINED:
        crs = f"EPSG:{code}+{vcode}"
    parse_crs(crs, path, field="GeoKeyDirectoryTag")
    return crs


def read_geotiff(path: str | Path) -> Raster:
    """Read a north-up GeoTIFF written by :func:`write_geotiff` (or by GDAL with an EPSG code).

    Raises :class:`InputError` naming the tag when the georeference is missing, rotated or unsupported.
    """
    import tifffile

    path = str(path)
    if not Path(path).is_file():
        raise InputError("file not found", path=path)
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            data = page.asarray()
            scale = _tag(page, TAG_PIXEL_SCALE)
            tie = _tag(page, TAG_TIEPOINT)
            matrix = _tag(page, TAG_TRANSFORMATION)
            directory = _tag(page, TAG_GEOKEYS)
            ascii_params = _tag(page, TAG_GEO_ASCII)
            nodata_text = _tag(page, TAG_GDAL_NODATA)
    except (tifffile.TiffFileError, ValueError, OSError) as e:
        raise InputError(f"not a readable TIFF ({e})", path=path) from None
    if matrix is not None and (scale is None or tie is None):
        raise InputError("ModelTransformationTag (rotated or sheared grid) is not supported; only north-up "
                         "rasters with ModelPixelScale + ModelTiepoint", path=path, field="ModelTransformationTag")
    if scale is None:
        raise InputError("missing georeference", path=path, field="ModelPixelScaleTag")
    if tie is None:
        raise InputError("missing georeference", path=path, field="ModelTiepointTag")
    if directory is None:
        raise InputError("missing CRS", path=path, field="GeoKeyDirectoryTag")
    sx, sy = float(scale[0]), float(scale[1])
    if not (sx > 0 and abs(sx - sy) <= 1e-9 * sx):
        raise InputError(f"only square cells are supported, got {sx} x {sy}", path=path, field="ModelPixelScaleTag")
    if len(tie) < 6:
        raise InputError("ModelTiepointTag needs 6 values", path=path, field="ModelTiepointTag")
    keys = _parse_geokeys(directory, ascii_params if isinstance(ascii_params, str) else None, path)
    crs = _crs_from_geokeys(keys, path)
    i, j = float(tie[0]), float(tie[1])
    x0 = float(tie[3]) - i * sx
    y0 = float(tie[4]) + j * sy
    if keys.get(KEY_RASTER_TYPE, RASTER_PIXEL_IS_AREA) == RASTER_PIXEL_IS_POINT:
        # PixelIsPoint: the tie point refers to the centre of the cell; move to its outer corner.
        x0 -= 0.5 * sx
        y0 += 0.5 * sy
    nodata: float | None = None
    if nodata_text is not None:
        try:
            nodata = float(str(nodata_text).strip().strip("\x00"))
        except ValueError:
            raise InputError(f"GDAL_NODATA is not a number: '{nodata_text}'", path=path,
                             field="GDAL_NODATA") from None
    if nodata is not None and data.dtype.kind == "f":
        if not math.isnan(nodata):
            data = np.where(data == nodata, np.nan, data).astype(data.dtype)
        nodata = None
    elif nodata is not None and float(nodata).is_integer():
        nodata = int(nodata)
    return Raster(data=data, x0=x0, y0=y0, cell=sx, crs=crs, nodata=nodata)


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an RGB (rows, cols, 3) or grey (rows, cols) uint8/uint16 picture as PNG, atomically.

    ``rgb`` is in RGB order (OpenCV's BGR swap happens here).
    """
    import cv2

    img = np.asarray(rgb)
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"PNG needs uint8 or uint16 data, got {img.dtype}", path=path, field="rgb")
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    elif img.ndim != 2:
        raise InputError(f"PNG needs (rows, cols), (rows, cols, 3) or (rows, cols, 4), got {img.shape}",
                         path=path, field="rgb")
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(tmp, np.ascontiguousarray(img)):
            raise InputError("OpenCV could not write the PNG", path=path)
