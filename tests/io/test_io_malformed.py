"""Every malformed input gives one InputError naming the file, the line and the field; nothing is imported."""

from __future__ import annotations

from pathlib import Path

import pytest

from oblique_city.core.errors import InputError
from oblique_city.core.io.formats import read_block

DATA = Path(__file__).resolve().parents[1] / "data"
BAD = DATA / "malformed"
CAM = {"cameras": str(BAD / "cameras_ok.toml")}
AB = (DATA / "opk_ab.txt", {"cameras": str(BAD / "cameras_ok.toml")})

# (format, file, options, expected substring of the message: file:line, field and reason)
CASES = [
    ("opk", "opk_missing_column.txt", CAM,
     "opk_missing_column.txt:1, field 'header': missing column(s): kappa"),
    ("opk", "opk_nan.txt", CAM, "opk_nan.txt:3, field 'omega': 'nan' is not a finite number"),
    ("opk", "opk_unknown_unit.txt", CAM, "opk_unknown_unit.txt:1, field 'angles': unknown angle unit 'grads'"),
    ("opk", "opk_unknown_crs.txt", CAM,
     "opk_unknown_crs.txt:1, field 'crs': unknown coordinate reference system 'EPSG:999999'"),
    ("opk", "opk_duplicate_id.txt", CAM,
     "opk_duplicate_id.txt:3, field 'name': duplicate image id 'A' (first on line 1)"),
    ("opk", "opk_wrong_field_count.txt", CAM, "opk_wrong_field_count.txt:2: expected 7 fields"),
    ("opk", "opk_text_in_number.txt", CAM, "opk_text_in_number.txt:2, field 'y': '54O4000' is not a number"),
    ("opk", "opk_zero_sigma.txt", CAM,
     "opk_zero_sigma.txt:3, field 'sphi': a zero standard deviation leaves the attitude exact about the world's Y"),
    ("opk", "opk_unknown_camera.txt", CAM, "opk_unknown_camera.txt:3, field 'camera': unknown camera 'nadir'"),
    ("opk", "opk_missing_image.txt",
     {"cameras": str(DATA / "cameras_small.toml"), "image_root": str(DATA / "images"), "image_ext": ".png"},
     "opk_missing_image.txt:2, field 'file': image file of 'img_missing' not found"),
    ("opk", "opk_wrong_image_size.txt",
     {**CAM, "image_root": str(DATA / "images"), "image_ext": ".png"},
     "opk_wrong_image_size.txt:1, field 'file': image 'img_a' is 40 x 30 px but camera 'cam' says 4000 x 3000"),
    ("opk", "opk_ab.txt", {"cameras": str(BAD / "cameras_missing_focal.toml")},
     "cameras_missing_focal.toml:2, field 'cameras.nadir.focal_px': camera 'nadir' needs focal_px"),
    ("opk", "opk_ab.txt", {"cameras": str(BAD / "cameras_bad_toml.toml")},
     "cameras_bad_toml.toml:3: invalid TOML"),
    ("bex", "bex_malformed.xml", {}, "bex_malformed.xml:6: malformed XML: Opening and ending tag mismatch"),
    ("bex", "bex_billion_laughs.xml", {},
     "bex_billion_laughs.xml:3, field 'DOCTYPE': XML with a DOCTYPE declaring entities is refused"),
    ("bex", "bex_xxe.xml", {}, "bex_xxe.xml:2, field 'DOCTYPE': XML with a DOCTYPE declaring entities is refused"),
    ("bex", "bex_bad_rotation.xml", {}, "bex_bad_rotation.xml:23, field 'Rotation': <Rotation> is not a rotation"),
    ("bex", "bex_heading_pitch_roll.xml", {},
     "bex_heading_pitch_roll.xml:23, field 'Rotation': Heading/Pitch/Roll rotations are not supported"),
    ("bex", "bex_unknown_photo_id.xml", {},
     "bex_unknown_photo_id.xml:38, field 'PhotoId': measurement refers to unknown PhotoId 7"),
    ("bex", "bex_unknown_srs.xml", {},
     "bex_unknown_srs.xml:6, field 'Definition': unknown coordinate reference system 'EPSG:123456789'"),
    ("bex", "bex_text_in_angle.xml", {}, "bex_text_in_angle.xml:23, field 'Rotation/Phi': 'abc' is not a number"),
    ("bex", "bex_missing_dimensions.xml", {},
     "bex_missing_dimensions.xml:12, field 'ImageDimensions': <Photogroup> lacks <ImageDimensions>"),
    ("opk", "gcp_nan.csv", {"gcps": str(BAD / "gcp_nan.csv")},
     "gcp_nan.csv:3, field 'z': 'NaN' is not a finite number"),
    ("opk", "measurements_unknown_image.csv",
     {"gcps": str(DATA / "gcp_ab.csv"), "measurements": str(BAD / "measurements_unknown_image.csv")},
     "measurements_unknown_image.csv:3, field 'image': unknown image id 'nope'"),
    ("opk", "measurements_outside_image.csv",
     {"gcps": str(DATA / "gcp_ab.csv"), "measurements": str(BAD / "measurements_outside_image.csv")},
     "measurements_outside_image.csv:3, field 'u': u = 4100.5 px is outside image 'b' (width 4000)"),
    ("colmap", "colmap_fisheye", {"crs": "EPSG:25832"},
     "colmap_fisheye, field 'cameras': COLMAP camera model OPENCV_FISHEYE (camera 1) cannot be represented"),
]


@pytest.mark.parametrize(("fmt", "name", "options", "expected"), CASES, ids=[c[1] + "-" + c[3][-12:] for c in CASES])
def test_malformed_input(fmt, name, options, expected):
    source = DATA / name if name == "opk_ab.txt" else BAD / name
    if name.startswith(("gcp_", "measurements_")):
        source, base = AB
        options = {**base, **options}
    with pytest.raises(InputError) as info:
        read_block(fmt, source, **options)
    assert expected in str(info.value), str(info.value)


def test_at_least_fifteen_malformed_files():
    files = {c[1] for c in CASES if (BAD / c[1]).exists() and not c[1].startswith("opk_ab")}
    assert len(files) >= 15
    assert files | {"cameras_ok.toml", "cameras_missing_focal.toml", "cameras_bad_toml.toml"} >= {
        p.name for p in BAD.iterdir()}


def _line_of(text: str, needle: str) -> int:
    return next(k for k, t in enumerate(text.splitlines(), 1) if needle in t)


NATIVE_EDITS = [  # (edit of the block's dict, the entry's id, expected field and reason)
    (lambda d: d["images"][1].update(sigma_position=[0.1, 0.1]), "img1",
     "field 'images[img1].sigma_position': expected shape (3,), got (2,)"),
    (lambda d: d["images"][0]["pose_approx"].update(R_cam_from_world=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "img0",
     "field 'images[img0].pose_approx.R_cam_from_world': not a proper rotation matrix"),
    (lambda d: d["images"][2].update(camera_id="nope"), "img2", "refers to unknown camera 'nope'"),
    (lambda d: d["images"][2].update(time="noon"), "img2", "field 'images[img2].time': expected numbers"),
    (lambda d: d["cameras"][0].update(width="1200"), "cam", "field 'cameras[cam].width': must be a positive integer"),
    (lambda d: d["cameras"][0].pop("fx"), "cam", "field 'cameras[cam].fx': missing required key"),
]


@pytest.mark.parametrize(("edit", "entry", "expected"), NATIVE_EDITS, ids=[e[2][7:40] for e in NATIVE_EDITS])
def test_native_block_malformed(utm_block, tmp_path, edit, entry, expected):
    """The workspace's own block file: a wrong value names the file, the line of its entry and the field."""
    import json

    from oblique_city.core.io.native import block_to_dict
    from oblique_city.core.pipeline.atomic import write_json

    d = block_to_dict(utm_block)
    edit(d)
    write_json(tmp_path / "b.json", d)
    line = _line_of((tmp_path / "b.json").read_text(), f'"id": {json.dumps(entry)}')
    with pytest.raises(InputError) as info:
        read_block("native", tmp_path / "b.json")
    assert f"b.json:{line}, " in str(info.value) and expected in str(info.value), str(info.value)


def test_native_block_not_a_list(utm_block, tmp_path):
    from oblique_city.core.io.native import block_to_dict
    from oblique_city.core.pipeline.atomic import write_json

    d = block_to_dict(utm_block)
    d["images"] = {"img0": d["images"][0]}
    write_json(tmp_path / "b.json", d)
    with pytest.raises(InputError, match="field 'images': expected a list of objects"):
        read_block("native", tmp_path / "b.json")


def test_metashape_chunk_transform_without_translation(utm_block, tmp_path):
    """A geocentric chunk transform without its translation puts the cameras near the earth's centre: refused at the
    transform's line, not left to fail in a coordinate transformation."""
    from lxml import etree

    from oblique_city.core.io.formats import write_block

    write_block("metashape", utm_block, tmp_path / "c.xml")
    tree = etree.parse(str(tmp_path / "c.xml"))
    t = tree.getroot().find("chunk/transform")
    t.remove(t.find("translation"))
    tree.write(str(tmp_path / "c.xml"))
    line = etree.parse(str(tmp_path / "c.xml")).getroot().find("chunk/transform").sourceline
    with pytest.raises(InputError) as info:
        read_block("metashape", tmp_path / "c.xml")
    assert f"c.xml:{line}, field 'transform': the chunk's transform puts the aligned cameras 63" in str(info.value)


def test_colmap_rig_sensor_without_mounting(penta_block, tmp_path):
    """A frame's image whose rig sensor lost its sensor_from_rig has no pose: an InputError, not pycolmap's
    'bad optional access'."""
    import re

    from oblique_city.core.io.formats import write_block

    write_block("colmap", penta_block, tmp_path / "m")
    rigs = tmp_path / "m" / "rigs.txt"
    text = rigs.read_text()
    rigs.write_text(re.sub(r"CAMERA 2 1( \S+){7}", "CAMERA 2 0", text, count=1))
    with pytest.raises(InputError, match=r"field 'rigs': image .*: no pose through its frame's rig"):
        read_block("colmap", tmp_path / "m", crs="EPSG:25832")


def test_event_list_position_outside_crs(penta_block, tmp_path):
    """A position the CRS cannot take (an easting of 1e10 m) is refused at its line."""
    from oblique_city.core.io.formats import write_block

    write_block("gnssimu", penta_block, tmp_path / "ev.txt")
    lines = (tmp_path / "ev.txt").read_text().splitlines()
    k = next(k for k, t in enumerate(lines) if t.startswith("S02_E003 "))
    f = lines[k].split()
    lines[k] = " ".join([f[0], "9999999999", *f[2:]])
    (tmp_path / "ev.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as info:
        read_block("gnssimu", tmp_path / "ev.txt")
    assert f"ev.txt:{k + 1}, " in str(info.value) and "could not be transformed (1 of" in str(info.value)


def test_zipped_xml_too_large_or_damaged(tmp_path, monkeypatch):
    """A zip member that would unpack beyond the limit (a zip bomb) is refused before it is unpacked; a damaged
    member gives an InputError, not zlib's error."""
    import zipfile

    from oblique_city.core.io import validate

    data = (DATA / "bex_sample.xml").read_bytes()
    with zipfile.ZipFile(tmp_path / "b.xmlz", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("block.xml", data)
    assert len(read_block("bex", tmp_path / "b.xmlz").images) == len(read_block("bex", DATA / "bex_sample.xml").images)
    monkeypatch.setattr(validate, "MAX_ZIPPED_XML_BYTES", len(data) - 1)
    with pytest.raises(InputError, match="b.xmlz: the zipped block.xml would unpack to"):
        read_block("bex", tmp_path / "b.xmlz")
    monkeypatch.undo()
    raw = bytearray((tmp_path / "b.xmlz").read_bytes())
    raw[60:120] = bytes(60)
    (tmp_path / "bad.xmlz").write_bytes(bytes(raw))
    with pytest.raises(InputError, match="bad.xmlz: broken zip archive"):
        read_block("bex", tmp_path / "bad.xmlz")
