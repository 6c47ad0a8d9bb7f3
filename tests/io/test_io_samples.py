"""Hand-written sample files in every format, read and checked value by value against hand computations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer

from oblique_city.core.errors import InputError
from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.io.formats import read_block
from oblique_city.core.io.validate import image_size

DATA = Path(__file__).resolve().parents[1] / "data"
GON = np.pi / 200.0


def test_opk_sample_semicolon_gon_header_two_cameras():
    b = read_block("opk", DATA / "opk_sample.txt", cameras=str(DATA / "opk_sample_cameras.toml"), angles="gon",
                   gcps=str(DATA / "gcp_sample.csv"), measurements=str(DATA / "measurements_sample.txt"),
                   measurement_origin="corner", measurement_delimiter="whitespace")
    assert b.crs == "EPSG:25832" and list(b.images) == ["N_0001", "N_0002", "F_0001"]
    nadir, fwd = b.cameras["nadir"], b.cameras["forward"]
    assert nadir.fx == pytest.approx(100.5 / 0.0046, abs=1e-9) and nadir.pixel_size_mm == pytest.approx(0.0046)
    assert (nadir.cx, nadir.cy) == pytest.approx((5803.5 + 10.0, 4353.5 - 5.0), abs=1e-9)  # ppx/ppy in mm
    assert (fwd.cx, fwd.cy) == (4999.5, 3499.5)  # pixel_origin = corner
    assert nadir.k1 == -1.5e-3 and nadir.name == "Nadir head, 100 mm"
    img = b.images["N_0001"]
    assert img.camera_id == "nadir" and img.file == "N_0001"
    assert np.array_equal(img.pose.C, [512000.125, 5404000.250, 1050.5])
    assert np.allclose(img.pose.R, opk_to_cam_from_world(0.125 * GON, -0.05 * GON, 100.0 * GON), atol=1e-15)
    assert np.array_equal(img.sigma_position, [0.05, 0.05, 0.10])
    assert b.images["F_0001"].sigma_position is None and b.images["F_0001"].view in ("north", "south")
    assert b.images["N_0001"].view == "nadir"
    g = b.ground_points
    assert [g[n].kind for n in ("G1", "G2", "C1")] == ["control", "control", "check"]
    assert np.array_equal(g["G1"].sigma, [0.02, 0.02, 0.03])
    assert np.array_equal(g["G1"].observations["N_0001"], [6200.0, 4100.0])  # corner -> centre: -0.5
    assert set(g["G1"].observations) == {"N_0001", "N_0002"} and not g["G2"].observations


def test_opk_sample_whitespace_json_cameras_assign():
    b = read_block("opk", DATA / "opk_sample2.txt")  # finds opk_sample2_cameras.json beside it
    assert b.images["N_0001"].camera_id == "nadir" and b.images["F_0001"].camera_id == "forward"
    assert np.allclose(b.images["F_0001"].pose.R, opk_to_cam_from_world(0.78540, 0.0, 0.0), atol=1e-15)
    assert b.cameras["nadir"].cx == (11608 - 1) / 2


def test_bex_sample():
    b = read_block("bex", DATA / "bex_sample.xml")
    assert b.crs == "EPSG:2154"
    assert b.image_root == r"D:\data\Paris2012sample\Images"
    ucx, obl = b.cameras["UCX"], b.cameras["Oblique"]
    assert ucx.fx == pytest.approx(100.735601903992 / (103.896 / 14430), rel=1e-14)
    assert (ucx.cx, ucx.cy) == (4683.755692, 7223.0141002)  # centre-of-pixel origin: unchanged
    assert (ucx.p1, ucx.p2) == (0.0001, -0.0002)
    # XRightYUp: xmm right, ymm up -> +5 px in u, -10 px in v from the sensor centre
    assert (obl.cx, obl.cy) == pytest.approx((2999.5 + 5.0, 1999.5 - 10.0), abs=1e-9)
    assert list(b.images) == ["071_2810", "071_2811", "071_2812", "N_0001"]
    assert b.images["071_2812"].pose is None
    assert b.images["N_0001"].file == "oblique/N_0001.tif"
    # the specification's matrix and its omega/phi/kappa describe the same rotation
    r_matrix, r_opk = b.images["071_2810"].pose.R, b.images["071_2811"].pose.R
    assert np.abs(r_matrix - r_opk).max() < 1e-9
    # omega = phi = kappa = 0 in XRightYUp: camera looks straight down, image top to the north
    assert np.allclose(b.images["N_0001"].pose.R, np.diag([1.0, -1.0, -1.0]), atol=1e-15)
    assert b.images["N_0001"].view == "nadir" and b.images["071_2810"].view == "nadir"
    cp = b.ground_points
    assert cp["Control point #1"].kind == "control" and cp["Control point #2"].kind == "check"
    assert np.array_equal(cp["Control point #2"].sigma, [0.01, 0.01, 0.10])
    assert np.array_equal(cp["Control point #1"].observations["071_2810"], [7270.31, 6599.44])
    # mm measurement relative to the principal point, XRightYUp: +1.2 mm right, -0.6 mm (down) -> +200, +100 px
    assert np.allclose(cp["Control point #1"].observations["N_0001"], [3004.5 + 200.0, 1989.5 + 100.0])
    h = cp["Control point #3"]
    assert np.isnan(h.xyz[2]) and h.sigma[2] == np.inf and h.xyz[0] == 652365.1205012415
    ref = Transformer.from_crs("EPSG:4326", "EPSG:2154", always_xy=True).transform(2.2945, 48.8584)
    assert np.allclose(cp["Tower top"].xyz[:2], ref, atol=1e-6) and cp["Tower top"].xyz[2] == pytest.approx(330.0)


def test_bex_image_id_modes():
    b = read_block("bex", DATA / "bex_sample.xml", image_id="id")
    assert list(b.images) == ["146", "147", "148", "200"]
    b = read_block("bex", DATA / "bex_sample.xml", image_id="name")
    assert "N_0001.tif" in b.images


def test_bex_swapped_tangential_option():
    b = read_block("bex", DATA / "bex_sample.xml", tangential="swapped")
    assert (b.cameras["UCX"].p1, b.cameras["UCX"].p2) == (-0.0002, 0.0001)


def test_colmap_sample_text_model():
    b = read_block("colmap", DATA / "colmap_sample", crs="EPSG:25832")
    c1, c2 = b.cameras["1"], b.cameras["2"]
    assert (c1.fx, c1.fy, c1.cx, c1.cy, c1.k1) == (2559.69, 2559.69, 1535.5, 1151.5, -0.0218531)
    assert (c2.fx, c2.fy, c2.cx, c2.cy) == (2560.56, 2561.0, 1530.0, 1149.75)
    assert set(b.images) == {"P1180141", "P1180142"} and b.images["P1180142"].file == "sub/P1180142.JPG"
    img = b.images["P1180142"]  # identity rotation, t = (-1, 2, 3) -> C = -t
    assert np.array_equal(img.pose.R, np.eye(3)) and np.array_equal(img.pose.C, [1.0, -2.0, -3.0])


@pytest.mark.parametrize(("name", "size"), [("img_a.png", (40, 30)), ("img_b.jpg", (40, 30))])
def test_image_size_from_header(name, size):
    assert image_size(DATA / "images" / name) == size


def test_image_size_tiff(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "a.tif", np.zeros((21, 33, 3), np.uint8), photometric="rgb")
    assert image_size(tmp_path / "a.tif") == (33, 21)


def test_image_files_checked(tmp_path):
    b = read_block("opk", DATA / "opk_ab.txt", cameras=str(DATA / "cameras_small.toml"),
                   image_root=str(DATA / "images"), image_ext=".png", check_images="false")
    assert b.image_root == str((DATA / "images").resolve())


@pytest.mark.parametrize(("options", "message"), [
    ({"exposure_pattern": "(.+)_(.+)"}, "exposure_pattern is used only with -o exposures=name"),
    ({"exposures": "time", "exposure_pattern": "(.+)_(.+)"}, "exposure_pattern is used only with -o exposures=name"),
    ({"exposure_tolerance": 0.1}, "exposure_tolerance is used only with -o exposures=time"),
    ({"gcp_sigma": 0.05}, "gcp_sigma is used only with -o gcps=..."),
    ({"measurement_origin": "corner"}, "measurement_origin is used only with -o measurements=..."),
])
def test_an_option_without_the_one_it_serves_is_refused(options, message):
    """An option that does something only with another one (a forgotten -o exposures=name) is refused, naming it."""
    with pytest.raises(InputError, match=message):
        read_block("bex", DATA / "bex_sample.xml", **options)


def test_unknown_option_is_refused():
    """A typo is refused with the options the format takes; the native format takes none."""
    from oblique_city.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"unknown option\(s\) for format 'opk': angle \(it takes: angles, "):
        read_block("opk", DATA / "opk_sample2.txt", angle="gon")
    with pytest.raises(ConfigError, match="format 'native': gcps \\(it takes: none\\)"):
        read_block("native", DATA / "nowhere.json", gcps="gcp.csv")


def test_every_option_a_reader_takes_is_listed():
    """Each reader module's options (every ``options.pop("...")`` in its source, the shared ones in ``common``) are
    declared, so ``read_block`` passes them and ``oblique-city import --help`` lists them, with their help."""
    import re

    from oblique_city.core.cli import reader_options_help
    from oblique_city.core.io import blocksexchange, colmap, common, metashape, opk, trajectory
    from oblique_city.core.io.formats import READER_OPTIONS, reader_options

    popped = re.compile(r'opt(?:ion)?s\.(?:pop|get)\("(\w+)"')
    modules = {"opk": [opk], "bex": [blocksexchange], "colmap": [colmap], "metashape": [metashape],
               "gnssimu": [trajectory, opk]}
    shared = set(popped.findall(Path(common.__file__).read_text()))
    assert shared == set(common.COMMON_OPTIONS)
    for fmt, mods in modules.items():
        own = set().union(*(popped.findall(Path(m.__file__).read_text()) for m in mods)) - shared
        assert own <= set(READER_OPTIONS[fmt]), (fmt, own - set(READER_OPTIONS[fmt]))
    text = reader_options_help()
    assert all(f"    {name} " in text for fmt in READER_OPTIONS for name in reader_options(fmt))


def test_image_files_present_and_right_size():
    b = read_block("opk", DATA / "malformed" / "opk_wrong_image_size.txt", cameras=str(DATA / "cameras_small.toml"),
                   image_root=str(DATA / "images"), image_ext=".png")
    assert b.images["img_a"].file == "img_a.png"


def test_ground_points_in_another_crs(tmp_path):
    (tmp_path / "g.txt").write_text("name x y z\nT1 9.01 48.75 300.5\n")  # longitude, latitude, height
    b = read_block("opk", DATA / "opk_ab.txt", cameras=str(DATA / "malformed" / "cameras_ok.toml"),
                   gcps=str(tmp_path / "g.txt"), gcp_crs="EPSG:4326", gcp_kind="check", gcp_sigma="0.05")
    ref = Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True).transform(9.01, 48.75)
    g = b.ground_points["T1"]
    assert np.allclose(g.xyz, [*ref, 300.5], atol=1e-6) and g.kind == "check" and np.all(g.sigma == 0.05)


def test_whitespace_delimiter_is_not_sniffed(tmp_path):
    """Names containing semicolons stay whole when the delimiter is given as whitespace."""
    (tmp_path / "b.txt").write_text("a;1 512000 5404000 1000 0 0 0\nb;2 512100 5404000 1000 0 0 0\n")
    b = read_block("opk", tmp_path / "b.txt", cameras=str(DATA / "malformed" / "cameras_ok.toml"),
                   delimiter="whitespace")
    assert list(b.images) == ["a;1", "b;2"]


def test_bex_xmlz(tmp_path):
    import zipfile

    with zipfile.ZipFile(tmp_path / "b.xmlz", "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.write(DATA / "bex_sample.xml", "block.xml")
    b = read_block("bex", tmp_path / "b.xmlz")
    assert len(b.images) == 4 and b.crs == "EPSG:2154"


def test_writer_options_listed_are_taken(tmp_path, penta_block):
    """``oblique-city export-block --help`` lists each writer's keyword options with their defaults: every writer
    takes them (given explicitly) and refuses others."""
    from oblique_city.core.errors import ConfigError
    from oblique_city.core.io.formats import WRITERS, write_block, writer_options

    assert writer_options("opk") == {"angles": "deg", "delimiter": "whitespace", "cameras": None, "sigmas": True}
    for fmt in WRITERS:
        given = {k: v for k, v in writer_options(fmt).items() if v is not None}
        write_block(fmt, penta_block, tmp_path / fmt / "out", **given)
        with pytest.raises(ConfigError, match=f"unknown option\\(s\\) for format '{fmt}': bogus \\(it takes: "):
            write_block(fmt, penta_block, tmp_path / fmt / "again", bogus="1")


def test_format_told_from_the_file(tmp_path, penta_block):
    """Every format as its writer writes it is told from the file (also an OPK list without its header and a zipped
    BlocksExchange file); a folder or an XML of no known kind is refused, naming the file."""
    import zipfile

    from oblique_city.core.io.formats import WRITERS, detect_format, write_block

    names = {"native": "b.json", "opk": "b.txt", "bex": "b.xml", "colmap": "sparse", "metashape": "cams.xml",
             "gnssimu": "events.csv"}
    for fmt in WRITERS:
        write_block(fmt, penta_block, tmp_path / names[fmt])
        assert detect_format(tmp_path / names[fmt]) == fmt
    lines = (tmp_path / "b.txt").read_text().splitlines()
    (tmp_path / "bare.txt").write_text("\n".join(t for t in lines if not t.startswith(("#", "name"))) + "\n")
    assert detect_format(tmp_path / "bare.txt") == "opk"
    with zipfile.ZipFile(tmp_path / "b.xmlz", "w") as z:
        z.write(tmp_path / "b.xml", "b.xml")
    assert detect_format(tmp_path / "b.xmlz") == "bex"
    (tmp_path / "other.xml").write_text("<kml/>")
    (tmp_path / "empty").mkdir()
    for bad, reason in (("other.xml", "root element <kml>"), ("empty", "not a COLMAP model")):
        with pytest.raises(InputError, match=reason) as e:
            detect_format(tmp_path / bad)
        assert e.value.path == str(tmp_path / bad)
