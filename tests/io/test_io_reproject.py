"""Moving a block into the project CRS: centres through pyproj, rotations turned by the meridian convergence
(checked against pyproj's own convergence factors), geographic sources via the local east-north-up frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pyproj import CRS, Proj

from oblique_city.core.cli import main
from oblique_city.core.geometry.crs import transform_points
from oblique_city.core.geometry.projection import project
from oblique_city.core.geometry.rotations import rotation_angle
from oblique_city.core.io.formats import write_block
from oblique_city.core.io.reproject import reproject_block


def convergence_deg(code: int, lon: float, lat: float) -> float:
    return Proj(CRS.from_epsg(code)).get_factors(lon, lat).meridian_convergence


def test_etrs89_and_wgs84_utm_are_nearly_the_same(oblique_block):
    out = reproject_block(oblique_block, "EPSG:25832", transform_points)
    assert out.crs == "EPSG:25832" and oblique_block.crs == "EPSG:32632"  # the input is untouched
    xyz = np.array([[500200.0, 5400000.0, 100.0], [500600.0, 5400030.0, 80.0]])
    xyz_dst = transform_points(xyz, "EPSG:32632", "EPSG:25832")
    for iid, img in oblique_block.images.items():
        dst = out.images[iid]
        assert np.abs(dst.pose.C - img.pose.C).max() < 1.0
        assert rotation_angle(dst.pose.R, img.pose.R) < 1e-6
        uv_a, _ = project(oblique_block.camera_of(img), img.pose, xyz)
        uv_b, _ = project(out.camera_of(dst), dst.pose, xyz_dst)
        ok = np.isfinite(uv_a[:, 0])
        assert np.abs(uv_a[ok] - uv_b[ok]).max() < 1e-3
    for name, g in oblique_block.ground_points.items():
        assert np.abs(out.ground_points[name].xyz - g.xyz).max() < 1.0


def test_zone_change_turns_by_the_convergence_difference(oblique_block):
    out = reproject_block(oblique_block, "EPSG:32633", transform_points)
    for iid, img in oblique_block.images.items():
        lon, lat, _ = transform_points(img.pose.C[None], "EPSG:32632", "EPSG:4326")[0]
        expected = np.radians(convergence_deg(32633, lon, lat) - convergence_deg(32632, lon, lat))
        r_rel = out.images[iid].pose.R.T @ img.pose.R  # = Rz(gamma): a turn about the vertical axis
        assert abs(np.arctan2(r_rel[1, 0], r_rel[0, 0]) - expected) < 1e-7
        assert abs(r_rel[2, 2] - 1.0) < 1e-12
        # image "up" follows the transformed direction of a point 100 m along it
        up_src = -img.pose.R[1]
        up_src_h = up_src[:2] / np.linalg.norm(up_src[:2])
        p = transform_points(np.array([img.pose.C, img.pose.C + 100.0 * np.r_[up_src_h, 0.0]]), "EPSG:32632",
                             "EPSG:32633")
        d = (p[1] - p[0])[:2]
        up_dst = -out.images[iid].pose.R[1][:2]
        cross = d[0] * up_dst[1] - d[1] * up_dst[0]
        assert abs(np.arcsin(cross / np.linalg.norm(d) / np.linalg.norm(up_dst))) < 1e-5


def test_geographic_round_trip_and_enu_convergence(oblique_block):
    geo = reproject_block(oblique_block, "EPSG:4326", transform_points)
    for iid, img in oblique_block.images.items():
        lon, lat = geo.images[iid].pose.C[:2]
        assert rotation_angle(geo.images[iid].pose.R, img.pose.R) == pytest.approx(
            np.radians(abs(convergence_deg(32632, lon, lat))), abs=1e-7)
    back = reproject_block(geo, "EPSG:32632", transform_points)
    for iid, img in oblique_block.images.items():
        assert np.abs(back.images[iid].pose.C - img.pose.C).max() < 1e-6
        assert np.abs(back.images[iid].pose.R - img.pose.R).max() < 1e-9


def test_cli_import_reprojects_into_the_workspace_crs(tmp_path: Path, oblique_block):
    write_block("bex", oblique_block, tmp_path / "block.xml")
    ws = tmp_path / "ws"
    assert main(["new", str(ws), "--crs", "EPSG:32633"]) == 0
    assert main(["import", str(ws), str(tmp_path / "block.xml"), "--format", "bex", "-o", "pose=approx"]) == 0
    from oblique_city.core.pipeline import Workspace

    block = Workspace.open(ws).load_block()
    assert block.crs == "EPSG:32633" and len(block.images) == 8 and len(block.ground_points) == 3
    expect = reproject_block(oblique_block, "EPSG:32633", transform_points)
    for iid, img in expect.images.items():
        assert np.abs(block.images[iid].pose.C - img.pose.C).max() < 1e-6


def test_cli_import_error_is_one_line_exit_2(tmp_path: Path, capsys):
    bad = Path(__file__).resolve().parents[1] / "data" / "malformed" / "bex_billion_laughs.xml"
    assert main(["import", str(tmp_path / "ws"), str(bad), "--format", "bex"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bex_billion_laughs.xml:3" in err and "DOCTYPE" in err
    assert not (tmp_path / "ws").exists()  # nothing half-imported


_GEOID_PROBE = """
import json, sys
import numpy as np
from oblique_city.core.errors import InputError
from oblique_city.core.geometry.crs import transform_points
out = {}
for name, lon in (("inside", [9.0, 12.5]), ("outside", [30.0, 9.0])):
    try:
        xyz = transform_points(np.array([[lon[0], 48.0, 300.0], [lon[1], 50.25, 200.0]]), "EPSG:4979",
                               "EPSG:32632+5773", path="events.txt")
        out[name] = xyz[:, 2].tolist()
    except InputError as e:
        out[name] = str(e)
print(json.dumps(out))
"""


def _geoid_probe(grid_dir: Path) -> dict:
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "PROJ_USER_WRITABLE_DIRECTORY": str(grid_dir), "PROJ_NETWORK": "OFF"}
    run = subprocess.run([sys.executable, "-c", _GEOID_PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_ellipsoidal_heights_take_the_geoid_grid_put_in_the_proj_user_folder(tmp_path: Path):
    """EGM96 heights from ellipsoidal ones need PROJ's ``us_nga_egm96_15.tif`` (old name ``egm96_15.gtx``). Without
    it the transformation is refused, naming the grid and the folder; with a grid there (a synthetic one, undulation
    ``N = 30 + 0.4 lat + 0.2 lon`` metres, exact under bilinear interpolation) heights are ``h - N``, and a point
    outside the grid is refused rather than moved by a ballpark."""
    import struct

    empty = tmp_path / "none"
    empty.mkdir()
    refused = _geoid_probe(empty)
    assert "us_nga_egm96_15.tif" in refused["inside"] and str(empty) in refused["inside"], refused
    grids = tmp_path / "grids"
    grids.mkdir()
    lat = 40.0 + 0.5 * np.arange(41)  # 40..60 N, 0..20 E, every half degree; GTX rows run from the south
    lon = 0.5 * np.arange(41)
    undulation = 30.0 + 0.4 * lat[:, None] + 0.2 * lon[None, :]
    (grids / "egm96_15.gtx").write_bytes(struct.pack(">4d2i", 40.0, 0.0, 0.5, 0.5, 41, 41)
                                         + undulation.astype(">f4").tobytes())
    got = _geoid_probe(grids)
    expected = [300.0 - (30.0 + 0.4 * 48.0 + 0.2 * 9.0), 200.0 - (30.0 + 0.4 * 50.25 + 0.2 * 12.5)]
    np.testing.assert_allclose(got["inside"], expected, atol=1e-3)
    assert "could not be transformed" in got["outside"], got
