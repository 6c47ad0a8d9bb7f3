"""Metashape camera XML: a file built from Metashape's own projection formula in geocentric coordinates, read into
UTM, projects like Metashape; round trips; refusals that name the line."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from pyproj import CRS, Transformer

from oblique_city.core.errors import InputError
from oblique_city.core.geometry.projection import project
from oblique_city.core.io.formats import read_block, write_block

WGS84_WKT = CRS("EPSG:4326").to_wkt("WKT1_GDAL")
CAL = {"f": 1200.0, "cx": 7.25, "cy": -4.5, "b1": 0.8, "k1": -0.08, "k2": 0.02, "k3": -0.004, "p1": 1.2e-3,
       "p2": -0.9e-3}
W, H = 1200, 900


def _metashape_pixel(xyz_cam: np.ndarray) -> np.ndarray:
    """Metashape's frame camera model (manual, appendix C), pixels from the image's top-left corner."""
    x, y = xyz_cam[:, 0] / xyz_cam[:, 2], xyz_cam[:, 1] / xyz_cam[:, 2]
    r2 = x * x + y * y
    radial = 1 + CAL["k1"] * r2 + CAL["k2"] * r2**2 + CAL["k3"] * r2**3
    xd = x * radial + CAL["p1"] * (r2 + 2 * x * x) + 2 * CAL["p2"] * x * y
    yd = y * radial + CAL["p2"] * (r2 + 2 * y * y) + 2 * CAL["p1"] * x * y
    return np.column_stack([W / 2 + CAL["cx"] + xd * (CAL["f"] + CAL["b1"]), H / 2 + CAL["cy"] + yd * CAL["f"]])


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _numbers(a: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(a))


@pytest.fixture
def geocentric_scene(tmp_path):
    """A chunk in WGS 84 with a scaled, rotated internal frame, one camera in a scaled component, 5 markers seen by
    both cameras. Placed 180 km east of UTM 32's central meridian, where its scale factor is 1, near the
    ellipsoid: grid and geocentric geometry differ there by less than 3e-5 of the distances."""
    rng = np.random.default_rng(5)
    geo = Transformer.from_crs("EPSG:32632", "EPSG:4979", always_xy=True)
    ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    lon, lat, h = geo.transform(680500.0, 5320000.0, 30.0)
    p0 = np.array(ecef.transform(lon, lat, h))
    lo, la = np.radians(lon), np.radians(lat)
    east = np.array([-np.sin(lo), np.cos(lo), 0.0])
    north = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
    up = np.cross(east, north)
    offsets = rng.uniform(-25, 25, (5, 2))
    pts_geo = np.array([geo.transform(680500.0 + dx, 5320000.0 + dy, 30.0 + dz)
                        for (dx, dy), dz in zip(offsets, rng.uniform(-5, 15, 5), strict=True)])
    pts = np.array([ecef.transform(*p) for p in pts_geo])
    cams = []
    for c_off in ((50.0, 10.0, 110.0), (-30.0, -45.0, 95.0)):
        c = p0 + c_off[0] * east + c_off[1] * north + c_off[2] * up
        z = (p0 - c) / np.linalg.norm(p0 - c)
        xa = np.cross(north, z)
        xa /= np.linalg.norm(xa)
        r_ecef_from_cam = np.column_stack([xa, np.cross(z, xa), z])
        cams.append((r_ecef_from_cam, c))
    # internal frame: geocentric = s R x + t; a component (scale 0.5) for the second camera
    s_ch, r_ch, t_ch = 2.5, _rotation(rng), p0 + [120.0, -80.0, 40.0]
    s_co, r_co, t_co = 0.5, _rotation(rng), np.array([3.0, -1.0, 2.0])
    chunk_m = np.eye(4)
    chunk_m[:3, :3], chunk_m[:3, 3] = s_ch * r_ch, t_ch
    comp_m = np.eye(4)
    comp_m[:3, :3], comp_m[:3, 3] = s_co * r_co, t_co
    cam_xml, pixels = [], []
    for k, (r, c) in enumerate(cams):
        world = np.eye(4)
        world[:3, :3], world[:3, 3] = r, c
        inner = np.linalg.inv(chunk_m @ (comp_m if k == 1 else np.eye(4))) @ world
        inner[:3, :3] /= np.cbrt(np.linalg.det(inner[:3, :3]))  # the camera transform is rigid in its frame
        comp = ' component_id="0"' if k == 1 else ""
        cam_xml.append(f'<camera id="{k}" sensor_id="0" label="IMG_{k}.JPG"{comp}>'
                       f"<transform>{_numbers(inner)}</transform><orientation>1</orientation></camera>")
        pixels.append(_metashape_pixel((pts - c) @ r))
    markers = "".join(f'<marker id="{j}" label="M{j}"><reference x="{p[0]!r}" y="{p[1]!r}" z="{p[2]!r}" '
                      f'enabled="{"false" if j == 4 else "true"}"/></marker>' for j, p in enumerate(pts_geo))
    locations = "".join(f'<marker marker_id="{j}">' + "".join(
        f'<location camera_id="{k}" pinned="true" x="{pixels[k][j, 0]!r}" y="{pixels[k][j, 1]!r}"/>'
        for k in range(2)) + "</marker>" for j in range(5))
    cal = "".join(f"<{k}>{v!r}</{k}>" for k, v in CAL.items())
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="2.0.0">
  <chunk label="Chunk 1" enabled="true">
    <sensors next_id="1"><sensor id="0" label="UltraCam" type="frame"><resolution width="{W}" height="{H}"/>
      <property name="pixel_width" value="0.004"/><property name="pixel_height" value="0.004"/>
      <calibration type="frame" class="initial"><resolution width="{W}" height="{H}"/><f>1900</f></calibration>
      <calibration type="frame" class="adjusted"><resolution width="{W}" height="{H}"/>{cal}</calibration>
    </sensor></sensors>
    <components next_id="1" active_id="0"><component id="0" label="Component 1"><transform>
      <rotation locked="true">{_numbers(r_co)}</rotation><translation locked="true">{_numbers(t_co)}</translation>
      <scale locked="true">{s_co!r}</scale></transform></component></components>
    <cameras next_id="2" next_group_id="1"><group id="0" label="Flight 1" type="folder">{cam_xml[0]}</group>
      {cam_xml[1]}</cameras>
    <markers next_id="5">{markers}</markers>
    <frames next_id="1"><frame id="0"><markers>{locations}</markers></frame></frames>
    <transform><rotation locked="true">{_numbers(r_ch)}</rotation>
      <translation locked="true">{_numbers(t_ch)}</translation><scale locked="true">{s_ch!r}</scale></transform>
    <reference>{WGS84_WKT}</reference>
  </chunk>
</document>
"""
    path = tmp_path / "cameras.xml"
    path.write_text(xml)
    return path, pixels


def test_reads_metashape_projection_into_utm(geocentric_scene):
    path, pixels = geocentric_scene
    block = read_block("metashape", path, crs="EPSG:32632")
    assert block.crs == "EPSG:32632"
    cam = block.cameras["UltraCam"]
    assert (cam.fx, cam.fy, cam.p1, cam.p2) == (CAL["f"] + CAL["b1"], CAL["f"], CAL["p2"], CAL["p1"])
    assert cam.pixel_size_mm == 0.004
    assert [g.kind for g in block.ground_points.values()] == ["control"] * 4 + ["check"]
    xyz = np.array([g.xyz for g in block.ground_points.values()])
    assert np.all(np.abs(xyz[:, 0] - 680500.0) < 30) and np.all(np.abs(xyz[:, 2] - 35.0) < 11)
    for k in range(2):
        img = block.images[f"IMG_{k}.JPG"]
        uv, _ = project(cam, img.pose, xyz)
        # Metashape's pixels have their origin at the image corner; 0.5 px off or p1/p2 swapped fails by > 0.3 px
        assert np.abs(uv - (pixels[k] - 0.5)).max() < 0.01  # measured 0.002
        for j, g in enumerate(block.ground_points.values()):
            assert np.abs(g.observations[img.id] - (pixels[k][j] - 0.5)).max() < 1e-9


def test_geographic_chunk_needs_a_crs(geocentric_scene):
    with pytest.raises(InputError, match="crs=EPSG") as e:
        read_block("metashape", geocentric_scene[0])
    assert e.value.line is not None and "reference" in str(e.value)


def test_round_trip(tmp_path, oblique_block, same_block):
    write_block("metashape", oblique_block, tmp_path / "cams.xml")
    back = read_block("metashape", tmp_path / "cams.xml")
    # centres pass through geocentric coordinates (pyproj round trip ~1e-8 m); rotations exactly
    same_block(oblique_block, back, tol_m=5e-8, tol_rad=1e-13, tol_px=1e-5)
    for name, g in oblique_block.ground_points.items():
        assert np.array_equal(back.ground_points[name].sigma, g.sigma)
    assert back.images["img0"].file == "img0"  # labels are image ids; no paths in the format


def test_image_files_found_by_label(tmp_path, oblique_block):
    from PIL import Image as PILImage

    for img in oblique_block.images.values():
        cam = oblique_block.camera_of(img)
        PILImage.new("L", (cam.width, cam.height)).save(tmp_path / f"{img.id}.tif")
    write_block("metashape", oblique_block, tmp_path / "cams.xml")
    back = read_block("metashape", tmp_path / "cams.xml", image_root=str(tmp_path))
    assert back.images["img3"].file == "img3.tif"


@pytest.mark.parametrize(("old", "new", "field"), [
    ("<k1>", "<k4>0.01</k4><k1>", "k4"),
    ("<p1>", "<b2>0.5</b2><p1>", "b2"),
    ('type="frame"><resolution', 'type="fisheye"><resolution', "type"),
    ('sensor_id="0" label="IMG_1.JPG"', 'sensor_id="7" label="IMG_1.JPG"', "sensor_id"),
    ("<orientation>1</orientation>", "<orientation>6</orientation>", "orientation"),
    ('marker_id="2"', 'marker_id="9"', "marker_id"),
])
def test_refusals_name_line_and_field(geocentric_scene, old, new, field):
    path = geocentric_scene[0]
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(InputError) as e:
        read_block("metashape", path, crs="EPSG:32632")
    assert e.value.line is not None and e.value.field.endswith(field), (e.value.field, str(e.value))


def test_local_chunk_and_chunk_choice(tmp_path, oblique_block, same_block):
    """A chunk in a local frame (LOCAL_CS, no geocentric step): its transform gives the block CRS's coordinates
    directly, which -o crs names; a document with two chunks needs -o chunk."""
    write_block("metashape", oblique_block, tmp_path / "geo.xml")
    text = (tmp_path / "geo.xml").read_text()
    # the local chunk: the internal frame is the block CRS itself (identity chunk transform)
    head, rest = text.split("<transform>\n      <rotation", 1)
    chunk_end = rest.index("</transform>") + len("</transform>")
    local_cs = 'LOCAL_CS["Local Coordinates (m)",LOCAL_DATUM["Local Datum",0],UNIT["metre",1]]'
    body = head + rest[chunk_end:]
    body = body[:body.index("<reference>")] + f"<reference>{local_cs}</reference>" + \
        body[body.index("</reference>") + len("</reference>"):]
    cams = []
    for img in oblique_block.images.values():
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = img.pose.R.T, img.pose.C
        cams.append((img.id, " ".join(repr(float(v)) for v in m.ravel())))
    for iid, numbers in cams:
        start = body.index(f'label="{iid}"')
        t0 = body.index("<transform>", start) + len("<transform>")
        body = body[:t0] + numbers + body[body.index("</transform>", t0):]
    (tmp_path / "local.xml").write_text(body)
    with pytest.raises(InputError, match="local frame"):
        read_block("metashape", tmp_path / "local.xml")
    back = read_block("metashape", tmp_path / "local.xml", crs=oblique_block.crs)
    same_block(oblique_block, back, tol_m=1e-6, tol_rad=1e-12, tol_px=1e-5)
    two = body.replace("</document>", "") + body[body.index("<chunk"):]
    (tmp_path / "two.xml").write_text(two)
    with pytest.raises(InputError, match="2 chunks"):
        read_block("metashape", tmp_path / "two.xml", crs=oblique_block.crs)
    assert len(read_block("metashape", tmp_path / "two.xml", crs=oblique_block.crs, chunk=1).images) == 8


def _multi_camera(path, block, master=lambda img: img.exposure + "_nadir", edit=None) -> None:
    """Turn the Metashape XML at ``path`` written from ``block`` into a multi-camera layout: each camera's
    ``master_id`` the id of the camera of ``master(img)`` (the master keeps none); ``edit(cameras_by_label)`` may
    change it further."""
    from lxml import etree

    tree = etree.parse(str(path))
    cams = {c.get("label"): c for c in tree.iter("camera")}
    for label, c in cams.items():
        m = master(block.images[label])
        if m != label:
            c.set("master_id", cams[m].get("id"))
    if edit is not None:
        edit(cams)
    tree.write(str(path))


def test_multi_camera_layout_gives_exposures_and_rig(tmp_path, penta_block):
    """Metashape's multi-camera layout (slaves name their master camera by ``master_id``): every system is one
    exposure, each sensor a head, and the rig estimated from the orientations is the penta camera's (the navigation
    orientations follow it exactly: within 1e-9 degrees, and 1e-7 m as the centres pass through geocentric
    coordinates)."""
    from oblique_city.core.model.exposures import rig_fit

    write_block("metashape", penta_block, tmp_path / "cams.xml")
    plain = read_block("metashape", tmp_path / "cams.xml")
    assert all(img.exposure is None for img in plain.images.values()) and not plain.rigs
    _multi_camera(tmp_path / "cams.xml", penta_block)
    back = read_block("metashape", tmp_path / "cams.xml")
    for iid, img in penta_block.images.items():
        got = back.images[iid]
        assert got.exposure == img.exposure + "_nadir" and got.head == img.camera_id
    (rig,) = back.rigs.values()
    assert rig.heads[0].name == "penta_nadir" and len(rig.heads) == 5
    assert all(f.rotation_rms_deg < 1e-9 and f.offset_rms_m < 1e-7 for f in rig_fit(back, rig))
    nominal = {h.camera_id: h for h in penta_block.rigs["penta"].heads}
    for h in rig.heads[1:]:
        rot, off = h.relative_to(rig.heads[0])
        rot0, off0 = nominal[h.camera_id].relative_to(nominal["penta_nadir"])
        assert np.abs(rot - rot0).max() < 1e-9 and np.abs(off - off0).max() < 1e-6


@pytest.mark.parametrize(("edit", "message"), [
    (lambda cams: cams["S01_E001_forward"].set("master_id", "99999"), "unknown master_id 99999"),
    (lambda cams: cams["S01_E002_forward"].set("master_id", cams["S01_E001_nadir"].get("id")),
     "are both sensor 'penta_forward' of the multi-camera system of 'S01_E001_nadir'"),
])
def test_multi_camera_layout_refusals(tmp_path, penta_block, edit, message):
    write_block("metashape", penta_block, tmp_path / "cams.xml")
    _multi_camera(tmp_path / "cams.xml", penta_block, edit=edit)
    with pytest.raises(InputError, match=message) as e:
        read_block("metashape", tmp_path / "cams.xml")
    assert e.value.field == "master_id" and e.value.line is not None


def _reference_xml(tmp_path, cameras: list[str]) -> str:
    """A WGS 84 chunk with one pinhole sensor (1200 x 900, f 1000 px) and the given ``<camera>`` elements."""
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="2.0.0"><chunk label="Chunk 1">
  <sensors><sensor id="0" label="cam" type="frame"><resolution width="{W}" height="{H}"/>
    <calibration type="frame" class="adjusted"><resolution width="{W}" height="{H}"/><f>1000</f></calibration>
  </sensor></sensors>
  <cameras>{"".join(cameras)}</cameras>
  <reference>{WGS84_WKT}</reference>
</chunk></document>
"""
    path = tmp_path / "cameras.xml"
    path.write_text(xml)
    return str(path)


def test_camera_references_orient_unaligned_cameras(tmp_path):
    """Cameras without a transform take their ``<reference>`` (WGS 84, angles as Metashape's reference rotation):
    the centre is pyproj's, and ground points found along geodesics from it (pyproj's Geod, true north) appear where
    the angles point: with yaw 0 and pitch 0 a point due north lies straight above the image centre; with yaw 90 and
    pitch 45 a point due east at the camera's height below appears at the centre; with roll 10 a nadir view looks 10
    degrees to the west of the image's top. In UTM 32, 97 km east of its central meridian, true north is 0.97
    degrees from grid north: without the grid convergence the point due north would be 0.34 m (0.7 px) off the
    image's centre line, against the 0.01 px tolerance. The others' 0.3 px allow for UTM's scale factor there
    (0.99972: the 500 m to the east point 0.14 m short, 0.14 px)."""
    from pyproj import Geod

    lon, lat, h = 10.3, 48.0, 500.0
    cams = [(0.0, 0.0, 0.0), (90.0, 45.0, 0.0), (0.0, 0.0, 10.0)]
    xml = [f'<camera id="{k}" sensor_id="0" label="c{k}"><reference x="{lon}" y="{lat}" z="{h}" yaw="{y}" '
           f'pitch="{p}" roll="{r}" enabled="true" rotation_enabled="false"/></camera>'
           for k, (y, p, r) in enumerate(cams)]
    xml.append(f'<camera id="3" sensor_id="0" label="c3"><reference x="{lon}" y="{lat}" z="{h}" enabled="true"/>'
               "</camera>")
    block = read_block("metashape", _reference_xml(tmp_path, xml), crs="EPSG:32632")
    utm = Transformer.from_crs("EPSG:4979", "EPSG:32632", always_xy=True)
    centre = np.array(utm.transform(lon, lat, h))
    geod = Geod(ellps="WGS84")

    def ground(azimuth: float, distance: float) -> np.ndarray:
        lo, la, _ = geod.fwd(lon, lat, azimuth, distance)
        return np.array(utm.transform(lo, la, 0.0))

    cam = block.cameras["cam"]
    for k in range(3):
        assert np.abs(block.images[f"c{k}"].pose.C - centre).max() < 1e-6
    north, _ = project(cam, block.images["c0"].pose, ground(0.0, 20.0)[None])
    assert abs(north[0, 0] - cam.cx) < 0.01 and north[0, 1] < cam.cy - 30
    east, _ = project(cam, block.images["c1"].pose, ground(90.0, h)[None])
    assert np.abs(east[0] - [cam.cx, cam.cy]).max() < 0.3
    west, _ = project(cam, block.images["c2"].pose, ground(270.0, h * np.tan(np.radians(10.0)))[None])
    assert np.abs(west[0] - [cam.cx, cam.cy]).max() < 0.3  # roll turns about the image's top axis
    assert block.images["c3"].pose is None  # a position alone orients nothing


def test_orientation_reference_replaces_the_alignment(geocentric_scene):
    """``orientation=reference`` takes the navigation data for every camera that has it, the alignment otherwise."""
    path, _ = geocentric_scene
    text = path.read_text().replace('<camera id="1"', '<camera id="1"', 1)
    text = text.replace("<orientation>1</orientation></camera>",
                        '<orientation>1</orientation><reference x="9.4" y="48.0" z="600" yaw="0" pitch="0" '
                        'roll="0"/></camera>', 1)
    path.write_text(text)
    aligned = read_block("metashape", path, crs="EPSG:32632")
    nav = read_block("metashape", path, crs="EPSG:32632", orientation="reference")
    utm = Transformer.from_crs("EPSG:4979", "EPSG:32632", always_xy=True)
    assert np.abs(nav.images["IMG_0.JPG"].pose.C - utm.transform(9.4, 48.0, 600.0)).max() < 1e-6
    assert np.abs(aligned.images["IMG_0.JPG"].pose.C - utm.transform(9.4, 48.0, 600.0)).max() > 1e3
    assert np.array_equal(nav.images["IMG_1.JPG"].pose.C, aligned.images["IMG_1.JPG"].pose.C)
    with pytest.raises(InputError, match="orientation must be alignment or reference"):
        read_block("metashape", path, crs="EPSG:32632", orientation="gnss")


def test_navigation_data_round_trip(tmp_path, penta_block):
    """The writer puts each approximate pose (the navigation data) into its camera's ``<reference>``, the best pose
    into ``<transform>``: read with ``orientation=reference`` the penta block's navigation poses come back (1e-9 m,
    2e-12 rad), its 45-degree heads and the 2-degree grid convergence included; an adjusted pose stays the
    alignment."""
    from oblique_city.core.model import Pose

    block = copy.deepcopy(penta_block)
    img = block.images["S01_E002_forward"]
    img.pose_adjusted = Pose(img.pose_approx.R, img.pose_approx.C + [0.3, -0.2, 0.1])
    write_block("metashape", block, tmp_path / "cams.xml")
    nav = read_block("metashape", tmp_path / "cams.xml", orientation="reference")
    aligned = read_block("metashape", tmp_path / "cams.xml")
    for iid, im in block.images.items():
        assert np.abs(nav.images[iid].pose.C - im.pose_approx.C).max() < 1e-9
        assert np.abs(nav.images[iid].pose.R - im.pose_approx.R).max() < 2e-12
    assert np.abs(aligned.images["S01_E002_forward"].pose.C - img.pose_adjusted.C).max() < 5e-8
