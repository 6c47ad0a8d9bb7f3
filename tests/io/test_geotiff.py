"""GeoTIFF and PNG writers: exact round trips of data, grid and CRS; refusal of rasters without georeference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from oblique_city.core.errors import InputError
from oblique_city.core.io.geotiff import read_geotiff, write_geotiff, write_png
from oblique_city.core.model import Raster

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("crs", ["EPSG:25832", "EPSG:4326", "EPSG:25832+7837"])
@pytest.mark.parametrize("data", [
    RNG.random((300, 270)).astype(np.float32),
    RNG.random((10, 12)),
    (RNG.random((20, 30, 3)) * 255).astype(np.uint8),
    RNG.random((10, 12, 5)),
], ids=["f32-tiled", "f64", "rgb", "5-band"])
def test_round_trip(tmp_path, crs, data):
    data = data.copy()
    if data.dtype.kind == "f":
        data[0, 0] = np.nan
    r = Raster(data, 500000.5, 5400000.25, 0.25, crs)
    write_geotiff(tmp_path / "r.tif", r)
    q = read_geotiff(tmp_path / "r.tif")
    assert q.data.dtype == data.dtype and q.data.shape == data.shape
    assert np.array_equal(q.data, data, equal_nan=True)
    assert (q.x0, q.y0, q.cell, q.crs) == (500000.5, 5400000.25, 0.25, crs)
    assert list(tmp_path.iterdir()) == [tmp_path / "r.tif"]  # no temporary file left behind


def test_tags_are_standard_geotiff(tmp_path):
    write_geotiff(tmp_path / "r.tif", Raster(np.zeros((4, 5), np.float32), 100.0, 200.0, 0.5, "EPSG:32632"))
    with tifffile.TiffFile(tmp_path / "r.tif") as t:
        g = t.pages[0].geotiff_tags
        nodata = t.pages[0].tags[42113].value
    assert g["ProjectedCSTypeGeoKey"] == 32632 and int(g["GTRasterTypeGeoKey"]) == 1
    assert int(g["GTModelTypeGeoKey"]) == 1
    assert list(g["ModelPixelScale"]) == [0.5, 0.5, 0.0]
    assert list(g["ModelTiepoint"]) == [0.0, 0.0, 0.0, 100.0, 200.0, 0.0]
    assert nodata.strip("\x00") == "nan"


def test_integer_nodata_and_wkt_crs(tmp_path):
    from pyproj import CRS

    wkt = CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=10.3 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m").to_wkt()
    data = np.arange(12, dtype=np.uint16).reshape(3, 4)
    write_geotiff(tmp_path / "r.tif", Raster(data, 1.0, 2.0, 3.0, wkt, nodata=0))
    q = read_geotiff(tmp_path / "r.tif")
    assert q.nodata == 0 and np.array_equal(q.data, data)
    assert CRS.from_user_input(q.crs).equals(CRS.from_user_input(wkt))


def test_float_nodata_value_becomes_nan(tmp_path):
    data = np.array([[1.0, -9999.0], [3.0, 4.0]], np.float32)
    write_geotiff(tmp_path / "r.tif", Raster(data, 0.0, 2.0, 1.0, "EPSG:25832", nodata=-9999.0))
    q = read_geotiff(tmp_path / "r.tif")
    assert np.isnan(q.data[0, 1]) and q.data[1, 1] == 4.0


def test_plain_tiff_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "plain.tif", np.zeros((4, 4), np.float32))
    with pytest.raises(InputError, match="plain.tif.*ModelPixelScaleTag.*missing georeference"):
        read_geotiff(tmp_path / "plain.tif")


def test_not_a_tiff_is_refused(tmp_path):
    (tmp_path / "x.tif").write_text("hello")
    with pytest.raises(InputError, match="not a readable TIFF"):
        read_geotiff(tmp_path / "x.tif")


def test_png_rgb_order(tmp_path):
    rgb = np.zeros((3, 4, 3), np.uint8)
    rgb[..., 0] = 200  # red
    write_png(tmp_path / "a.png", rgb)
    bgr = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert bgr.shape == (3, 4, 3) and np.all(bgr[..., 2] == 200) and np.all(bgr[..., :2] == 0)


def test_large_rasters_get_internal_overviews(tmp_path):
    """Halved levels as reduced-resolution IFDs (GDAL's internal overviews): a float raster averaged over its
    measured cells, a label raster decimated; small rasters get none; reading takes the full resolution."""
    import tifffile

    rng = np.random.default_rng(1)
    dsm = rng.normal(100.0, 3.0, (1500, 1100)).astype(np.float32)
    dsm[0, 0] = np.nan  # one of four cells missing: the overview cell is the mean of the other three
    write_geotiff(tmp_path / "dsm.tif", Raster(dsm, 500000.0, 5400000.0, 0.1, "EPSG:32632"))
    labels = rng.integers(0, 7, (1500, 1100)).astype(np.int16)
    write_geotiff(tmp_path / "labels.tif", Raster(labels, 500000.0, 5400000.0, 0.1, "EPSG:32632", nodata=-1))
    with tifffile.TiffFile(tmp_path / "dsm.tif") as tif:
        shapes = [p.shape for p in tif.pages]
        assert [p.subfiletype for p in tif.pages] == [0, 1, 1, 1]
        level1 = tif.pages[1].asarray()
    assert shapes == [(1500, 1100), (750, 550), (375, 275), (187, 137)]
    assert level1[0, 0] == pytest.approx(np.mean([dsm[0, 1], dsm[1, 0], dsm[1, 1]]), rel=1e-6)
    assert np.allclose(level1[3, 5], dsm[6:8, 10:12].mean(), rtol=1e-6)
    with tifffile.TiffFile(tmp_path / "labels.tif") as tif:
        assert np.array_equal(tif.pages[1].asarray(), labels[::2, ::2])
    back = read_geotiff(tmp_path / "dsm.tif")
    assert back.data.shape == dsm.shape and np.isnan(back.data[0, 0])
    write_geotiff(tmp_path / "small.tif", Raster(dsm[:500, :500], 500000.0, 5400000.0, 0.1, "EPSG:32632"))
    with tifffile.TiffFile(tmp_path / "small.tif") as tif:
        assert len(tif.pages) == 1
