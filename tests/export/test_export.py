"""Exports: CityGML 2.0 against the official XSD (offline), OBJ round trip, CityJSON structure, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from lxml import etree

from oblique_city.core.buildings.model import save_buildings
from oblique_city.core.buildings.reconstruct import reconstruct_building
from oblique_city.core.buildings.synthetic import parametric_buildings
from oblique_city.core.errors import InputError
from oblique_city.core.export.citygml import validate_citygml, write_citygml
from oblique_city.core.export.cityjson import check_cityjson, cityjson_document
from oblique_city.core.export.obj import read_obj, write_obj

OFFSET = np.array([500000.0, 5400000.0, 100.0])


@pytest.fixture(scope="module")
def models():
    """A gabled building with overhangs (2D path) and a stepped one (volumetric), in UTM coordinates."""
    out = []
    for b in parametric_buildings():
        if b.name in ("gabled", "stepped_flat"):
            rng = np.random.default_rng(1)
            xyz = b.sample(25.0, 0.04, rng) + OFFSET
            dsm, _ = b.dsm(0.1, 0.03, rng)
            dsm.x0 += OFFSET[0]
            dsm.y0 += OFFSET[1]
            dsm.data = dsm.data + OFFSET[2]
            out.append(reconstruct_building(xyz, OFFSET[2], dsm, f"B{len(out) + 1:04d}"))
    return out


def test_citygml_validates_against_the_official_xsd(models, tmp_path):
    path = tmp_path / "city.gml"
    write_citygml(path, models, "EPSG:25832")
    assert validate_citygml(path) == []
    text = path.read_text()
    for tag in ("bldg:RoofSurface", "bldg:WallSurface", "bldg:GroundSurface", "bldg:OuterCeilingSurface",
                "bldg:lod1Solid", "bldg:lod2Solid", 'srsName="urn:ogc:def:crs:EPSG::25832"'):
        assert tag in text
    # the generic attributes and the LoD1 block at the 70th percentile roof height
    doc = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    b = next(doc.iter("{*}Building"))
    attrs = {a.get("name"): a.findtext("{*}value") for a in b if a.tag.endswith("Attribute")}
    assert set(attrs) >= {"ground_height", "roof_height_70p", "volume", "roof_type", "footprint_area"}
    z = np.array([float(v) for e in b.find("{*}lod1Solid").iter("{*}posList") for v in e.text.split()])[2::3]
    assert np.abs(np.unique(np.round(z, 3)) - [float(attrs["ground_height"]), float(attrs["roof_height_70p"])]
                  ).max() < 1e-3


def test_citygml_validation_catches_errors(models, tmp_path):
    path = tmp_path / "city.gml"
    write_citygml(path, models, "EPSG:25832")
    text = path.read_text()
    broken = tmp_path / "broken.gml"
    # the solid before measuredHeight breaks the element order of AbstractBuildingType
    i = text.index("<bldg:measuredHeight")
    j = text.index("</bldg:measuredHeight>") + len("</bldg:measuredHeight>")
    moved = text[:i] + text[j:]
    k = moved.index("</bldg:lod2Solid>") + len("</bldg:lod2Solid>")
    broken.write_text(moved[:k] + text[i:j] + moved[k:])
    errors = validate_citygml(broken)
    assert errors and "measuredHeight" in errors[0]
    doctype = tmp_path / "doctype.gml"
    doctype.write_text('<?xml version="1.0"?><!DOCTYPE x [<!ENTITY e "boom">]>' + text.split("?>", 1)[1])
    with pytest.raises(InputError, match="DOCTYPE"):
        validate_citygml(doctype)


def test_obj_round_trip(models, tmp_path):
    path = tmp_path / "city.obj"
    write_obj(path, models, origin=np.floor(OFFSET))
    verts, groups, origin = read_obj(path)
    assert (tmp_path / "city.mtl").exists()
    assert np.allclose(origin, np.floor(OFFSET))
    base = 0
    for m in models:
        assert np.allclose(verts[base:base + len(m.vertices)], m.vertices, atol=1e-6)
        for kind in {s.kind for s in m.surfaces}:
            want = [[base + i for i in s.ring] for s in m.surfaces if s.kind == kind]
            assert groups[f"{m.id}_{kind}"] == want
        base += len(m.vertices)


def test_cityjson_structure(models, tmp_path):
    doc = cityjson_document(models, "EPSG:25832")
    assert check_cityjson(json.loads(json.dumps(doc))) == []
    geoms = {g["lod"]: g for g in doc["CityObjects"]["B0001"]["geometry"] if g["type"] == "Solid"}
    solid = geoms["2.2"]
    n_body = sum(s.in_solid for s in models[0].surfaces)
    assert len(solid["boundaries"][0]) == n_body == len(solid["semantics"]["values"][0])
    # vertices decode back to the model within the 1 mm quantisation, each listed once
    v = np.asarray(doc["vertices"]) * doc["transform"]["scale"] + doc["transform"]["translate"]
    assert np.abs(v[:len(models[0].vertices)] - models[0].vertices).max() <= 0.0005 + 1e-9
    assert len({tuple(x) for x in doc["vertices"]}) == len(doc["vertices"])
    # the LoD 1.2 block: the footprint from the ground to the 70th percentile roof height, a closed prism
    attrs = doc["CityObjects"]["B0001"]["attributes"]
    block = geoms["1.2"]
    rings = [v[face[0]] for face in block["boundaries"][0]]
    assert len(rings) == len(models[0].footprint) + 2
    z = np.concatenate(rings)[:, 2]
    assert np.abs(np.unique(np.round(z, 3)) - [attrs["ground_height"], attrs["roof_height_70p"]]).max() < 1e-3
    volume = sum(r[0] @ (0.5 * np.cross(r, np.roll(r, -1, 0)).sum(0)) for r in rings) / 3
    height = attrs["roof_height_70p"] - attrs["ground_height"]
    assert volume == pytest.approx(attrs["footprint_area"] * height, rel=1e-3)
    assert attrs["roof_height_min"] <= attrs["roof_height_50p"] <= attrs["roof_height_70p"] <= attrs["roof_height_max"]
    solid["boundaries"][0][0][0][0] = len(doc["vertices"]) + 5
    assert any("out of range" in e for e in check_cityjson(doc))


def test_cityjson_leaves_out_a_surface_the_quantisation_collapses(models):
    """An overhang fascia 0.2 mm wide (as the rendered demo's buildings stage once made one, on an eave segment whose
    two ends nearly met) has two distinct vertices at the 1 mm scale: it is left out, its semantics and texture
    values with it, and the document stays well formed."""
    from dataclasses import replace

    from oblique_city.core.buildings.model import Surface

    b = models[0]
    corner = b.vertices[b.surfaces[0].ring[0]]
    sliver = np.array([corner, corner + [0.0, 0.0002, 0.0001], corner + [0.0, 0.0002, -0.2], corner + [0, 0, -0.2]])
    n = len(b.vertices)
    bad = replace(b, vertices=np.vstack([b.vertices, sliver]),
                  surfaces=[*b.surfaces, Surface("sliver", "overhang_fascia", tuple(range(n, n + 4)), in_solid=False)])
    doc = cityjson_document([bad], "EPSG:25832")
    assert check_cityjson(json.loads(json.dumps(doc))) == []
    loose = [g for g in doc["CityObjects"][b.id]["geometry"] if g["type"] == "MultiSurface"][0]
    kept = [s for s in b.surfaces if not s.in_solid]
    assert len(loose["boundaries"]) == len(loose["semantics"]["values"]) == len(kept)


def test_export_command(models, tmp_path):
    from oblique_city.core.cli import main
    from oblique_city.core.pipeline import Workspace

    ws = Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    save_buildings(ws.path("buildings", "buildings.json"), models, ws.crs)
    for fmt, name in (("citygml", "out.gml"), ("obj", "out.obj"), ("cityjson", "out.city.json")):
        assert main(["export", str(ws.root), "--format", fmt, "--out", str(tmp_path / name)]) == 0
        assert (tmp_path / name).stat().st_size > 1000
    assert main(["export", str(tmp_path / "nothing"), "--format", "obj", "--out", str(tmp_path / "x.obj")]) == 2
