"""Textured exports: OBJ + MTL + atlas round trip, CityGML 2.0 appearance against the official XSDs (offline),
CityJSON appearance structure; untextured when asked."""

from __future__ import annotations

import json

import numpy as np
import pytest

from oblique_city.core.buildings.model import load_buildings
from oblique_city.core.export.citygml import validate_citygml
from oblique_city.core.export.cityjson import check_cityjson, read_cityjson
from oblique_city.core.export.command import export_buildings
from oblique_city.core.export.obj import read_obj, read_obj_texcoords
from oblique_city.core.pipeline.context import RunContext
from oblique_city.core.pipeline.registry import get_stage
from oblique_city.core.texture.atlas import load_textures


@pytest.fixture(scope="module")
def textured_ws(workspace):
    stage = get_stage("texture")
    stage.run(workspace, stage.make_config({"texel": 0.05, "page_size": 1024}), RunContext())
    return workspace


def test_obj_with_atlas_round_trip(textured_ws, tmp_path):
    out = tmp_path / "city.obj"
    assert "textured surfaces" in export_buildings(textured_ws.root, "obj", out)
    tex = load_textures(textured_ws.path("texture", "textures.json"))
    models, _ = load_buildings(textured_ws.path("buildings", "buildings.json"))
    verts, groups, _ = read_obj(out)
    vts, vt_groups, maps = read_obj_texcoords(out)
    assert maps == {"atlas_000": "city_atlas_000.png"} and (tmp_path / "city_atlas_000.png").exists()
    assert (tmp_path / "city_atlas_000.png").read_bytes() == tex.pages[0][0].read_bytes()
    n_tex = 0
    for m in models:
        for kind in {s.kind for s in m.surfaces}:
            surfaces = [s for s in m.surfaces if s.kind == kind]
            for s, vt_idx in zip(surfaces, vt_groups[f"{m.id}_{kind}"], strict=True):
                if s.id in tex.surfaces:
                    assert np.allclose(vts[vt_idx], tex.surfaces[s.id].uv, atol=1e-8)
                    n_tex += 1
                else:
                    assert vt_idx == []
    assert n_tex == len(tex.surfaces) and len(verts) == sum(len(m.vertices) for m in models)
    assert "usemtl atlas_000" in out.read_text() and "usemtl ground" in out.read_text()


def test_citygml_appearance_validates(textured_ws, tmp_path):
    out = tmp_path / "city.gml"
    export_buildings(textured_ws.root, "citygml", out)  # validates, raises on schema errors
    assert validate_citygml(out) == []
    text = out.read_text()
    tex = load_textures(textured_ws.path("texture", "textures.json"))
    assert text.count("<app:target ") == len(tex.surfaces)
    assert "<app:imageURI>city_atlas_000.png</app:imageURI>" in text
    from lxml import etree

    doc = etree.parse(str(out))
    ns = {"app": "http://www.opengis.net/citygml/appearance/2.0", "gml": "http://www.opengis.net/gml"}
    for sid, st in tex.surfaces.items():
        tc = doc.find(f".//app:target[@uri='#{sid}_poly']/app:TexCoordList/app:textureCoordinates", ns)
        assert tc.get("ring") == f"#{sid}_ring"
        uv = np.array(tc.text.split(), float).reshape(-1, 2)
        assert np.allclose(uv[:-1], st.uv) and np.allclose(uv[-1], uv[0])
        ring = doc.find(f".//gml:LinearRing[@gml:id='{sid}_ring']/gml:posList", ns)
        assert len(ring.text.split()) == 3 * len(uv)  # one texture coordinate per ring position


def test_cityjson_appearance(textured_ws, tmp_path):
    out = tmp_path / "city.city.json"
    export_buildings(textured_ws.root, "cityjson", out)
    doc = read_cityjson(out)
    assert check_cityjson(doc) == []
    app = doc["appearance"]
    assert app["textures"] == [{"type": "PNG", "image": "city_atlas_000.png", "wrapMode": "none"}]
    tex = load_textures(textured_ws.path("texture", "textures.json"))
    models, _ = load_buildings(textured_ws.path("buildings", "buildings.json"))
    solid = next(g for g in doc["CityObjects"]["B0001"]["geometry"] if g["lod"] == "2.2")
    values = solid["texture"]["texture"]["values"][0]
    body = [s for s in models[0].surfaces if s.in_solid]
    for s, v in zip(body, values, strict=True):
        if s.id in tex.surfaces:
            assert np.allclose([app["vertices-texture"][i] for i in v[0][1:]], tex.surfaces[s.id].uv, atol=1e-7)
        else:
            assert v == [[None]]
    broken = json.loads(json.dumps(doc))
    next(g for g in broken["CityObjects"]["B0001"]["geometry"] if g["lod"] == "2.2")["texture"]["texture"][
        "values"][0][1][0][1] = 10 ** 6
    assert any("in range" in e for e in check_cityjson(broken))


def test_untextured_on_request(textured_ws, tmp_path):
    out = tmp_path / "plain.obj"
    export_buildings(textured_ws.root, "obj", out, with_textures=False)
    assert "vt " not in out.read_text() and not list(tmp_path.glob("*.png"))
    out = tmp_path / "plain.city.json"
    export_buildings(textured_ws.root, "cityjson", out, with_textures=False)
    assert "appearance" not in read_cityjson(out)


def _glb(path) -> tuple[dict, bytes]:
    """The JSON and binary chunks of a glTF binary file."""
    import struct

    data = path.read_bytes()
    assert data[:4] == b"glTF" and struct.unpack_from("<I", data, 4)[0] == 2
    n_json = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n_json])
    return doc, data[20 + n_json + 8:]


def _accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"VEC2": 2, "VEC3": 3, "SCALAR": 1}[acc["type"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc["componentType"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, dtype, acc["count"] * width, start).reshape(acc["count"], width)


def test_3dtiles_carry_the_atlas(textured_ws, tmp_path):
    """The glTF tile embeds the atlas page and maps every textured ring vertex to its atlas UV, v flipped to
    glTF's downward v."""
    import cv2

    export_buildings(textured_ws.root, "3dtiles", tmp_path / "tiles")
    tex = load_textures(textured_ws.path("texture", "textures.json"))
    models, _ = load_buildings(textured_ws.path("buildings", "buildings.json"))
    doc, binary = _glb(next((tmp_path / "tiles").glob("*.glb")))
    page = next(m for m in doc["meshes"] if m["name"] == "page0")["primitives"][0]
    uv = _accessor(doc, binary, page["attributes"]["TEXCOORD_0"])
    want = np.concatenate([tex.surfaces[s.id].uv for m in models for s in m.surfaces if s.id in tex.surfaces])
    assert np.abs(uv - np.column_stack([want[:, 0], 1.0 - want[:, 1]])).max() < 1e-6
    material = doc["materials"][page["material"]]
    image = doc["images"][doc["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    png = np.frombuffer(binary, np.uint8, view["byteLength"], view.get("byteOffset", 0))
    got = cv2.imdecode(png, cv2.IMREAD_COLOR)
    assert np.array_equal(got, cv2.imread(str(tex.pages[0][0]), cv2.IMREAD_COLOR))


def _cjval() -> str | None:
    import os
    import shutil

    home = os.path.join(os.environ.get("CARGO_HOME", os.path.expanduser("~/.cargo")), "bin", "cjval")
    return shutil.which("cjval") or (home if os.path.exists(home) else None)


@pytest.mark.skipif(_cjval() is None, reason="cjval (the official CityJSON validator, built by make setup with "
                                             "cargo) is not installed")
def test_official_cityjson_validator_accepts_the_textured_city(textured_ws, tmp_path):
    """cjval checks the schema, parents and children, vertex indices, semantics and texture arrays, and warns of
    duplicate or unused vertices: the textured city with its LoD 1.2 blocks and windows passes without warnings;
    a broken texture index fails."""
    import subprocess

    out = tmp_path / "city.city.json"
    export_buildings(textured_ws.root, "cityjson", out)

    def report(path) -> dict:
        run = subprocess.run([_cjval(), "-r", str(path)], capture_output=True, text=True, timeout=120)
        return json.loads(run.stdout)

    r = report(out)
    assert r["valid"] and not r["has_warnings"], r["checks"]
    doc = json.loads(out.read_text())
    obj = next(o for o in doc["CityObjects"].values() if o["type"] == "Building")
    geom = next(g for g in obj["geometry"] if g["lod"] == "2.2" and "texture" in g)
    geom["texture"]["texture"]["values"][0][0][0][0] = 99  # a texture that does not exist
    (tmp_path / "broken.city.json").write_text(json.dumps(doc))
    assert not report(tmp_path / "broken.city.json")["valid"]


def _gltf_validator() -> tuple[str, str] | None:
    """``(node, module folder)`` of the Khronos glTF validator installed by make setup, or None."""
    import os
    import shutil

    cache = os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache"))
    modules = os.path.join(cache, "oblique-city", "gltf-validator", "node_modules")
    node = shutil.which("node")
    return (node, modules) if node and os.path.isdir(os.path.join(modules, "gltf-validator")) else None


@pytest.mark.skipif(_gltf_validator() is None, reason="the Khronos glTF validator (npm gltf-validator, installed by "
                                                      "make setup where npm is) is not installed")
def test_khronos_validator_accepts_the_3dtiles(textured_ws, tmp_path):
    """Every glTF tile of the textured city passes the Khronos validator without errors or warnings; a tile whose
    texture coordinates point past the buffer fails it."""
    import struct
    import subprocess

    node, modules = _gltf_validator()
    runner = tmp_path / "validate.js"
    runner.write_text(
        "const v = require('gltf-validator'); const fs = require('fs');\n"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])))"
        ".then(r => console.log(JSON.stringify(r.issues)))"
        ".catch(e => { console.log(JSON.stringify({numErrors: 1, error: String(e)})); });\n")

    def issues(path) -> dict:
        run = subprocess.run([node, str(runner), str(path)], capture_output=True, text=True, timeout=120,
                             env={"NODE_PATH": modules, "PATH": "/usr/bin:/bin"})
        return json.loads(run.stdout)

    export_buildings(textured_ws.root, "3dtiles", tmp_path / "tiles")
    tiles = sorted((tmp_path / "tiles").glob("*.glb"))
    assert tiles
    for tile in tiles:
        r = issues(tile)
        assert r["numErrors"] == 0 and r["numWarnings"] == 0, r["messages"][:5]
    doc, binary = _glb(tiles[0])
    page = next(m for m in doc["meshes"] if m["name"] == "page0")["primitives"][0]
    doc["accessors"][page["attributes"]["TEXCOORD_0"]]["count"] *= 100  # reads past its buffer view
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    data = tiles[0].read_bytes()
    n_json = struct.unpack_from("<I", data, 12)[0]
    rest = data[20 + n_json:]
    broken = b"glTF" + struct.pack("<II", 2, 12 + 8 + len(text) + len(rest)) + struct.pack("<I", len(text)) + \
        b"JSON" + text + rest
    (tmp_path / "broken.glb").write_bytes(broken)
    assert issues(tmp_path / "broken.glb")["numErrors"] > 0
