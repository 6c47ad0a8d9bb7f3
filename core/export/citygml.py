"""CityGML 2.0 LoD2 export and offline schema validation.

Each building becomes a ``bldg:Building`` with generic attributes (``gen:doubleAttribute`` / ``gen:stringAttribute``:
the ground and roof heights, areas, volume and roof type of :func:`..buildings.attributes.building_attributes`),
``bldg:measuredHeight``, a ``bldg:lod1Solid`` (the LoD 1.2 block: the footprint extruded to the 70th percentile
roof height), a ``bldg:lod2Solid`` (a ``gml:Solid``
whose exterior references the polygons of the body by ``xlink:href``) and ``bldg:boundedBy`` thematic surfaces
(``RoofSurface``, ``WallSurface``, ``GroundSurface``, ``OuterCeilingSurface`` for the overhang underside) each
holding a ``lod2MultiSurface``. The overhang's roof and fascia are Roof and Wall surfaces outside the solid.
``srsName`` is the project CRS (EPSG codes as OGC URNs).

Detected windows (the ``windows`` stage) are ``bldg:opening/bldg:Window`` members of the WallSurface they were
found on, each with a ``lod3MultiSurface`` rectangle: openings are an LoD3 concept in CityGML 2.0, written here on
the LoD2 walls (the schema allows any LoD's geometry on a boundary surface; LoD2 readers ignore them).

With textures (the ``texture`` stage's atlas), the rings of textured polygons get a ``gml:id`` and the model ends
with an ``app:appearanceMember``: one ``app:Appearance`` (theme ``texture``) with a ``ParameterizedTexture`` per
atlas page, whose ``target``s name the polygons and hold a ``TexCoordList`` (one u v pair per ring position,
closed like the ring).

:func:`validate_citygml` checks a file against the official CityGML 2.0 XSDs without network access, using the
copies shipped in the PyPI package ``citysmith`` and an lxml resolver that maps the schema URLs to them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from lxml import etree

from ..buildings.attributes import building_attributes, lod12_block
from ..errors import ComputationError, InputError
from ..pipeline.atomic import write_bytes
from .textures import copy_pages, textured

NS = {
    "core": "http://www.opengis.net/citygml/2.0",
    "bldg": "http://www.opengis.net/citygml/building/2.0",
    "gml": "http://www.opengis.net/gml",
    "xlink": "http://www.w3.org/1999/xlink",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
    "gen": "http://www.opengis.net/citygml/generics/2.0",
}
APP_NS = "http://www.opengis.net/citygml/appearance/2.0"
APP_SCHEMA = f"{APP_NS} http://schemas.opengis.net/citygml/appearance/2.0/appearance.xsd"
SCHEMA_LOCATION = ("http://www.opengis.net/citygml/2.0 http://schemas.opengis.net/citygml/2.0/cityGMLBase.xsd "
                   "http://www.opengis.net/citygml/building/2.0 "
                   "http://schemas.opengis.net/citygml/building/2.0/building.xsd "
                   "http://www.opengis.net/citygml/generics/2.0 "
                   "http://schemas.opengis.net/citygml/generics/2.0/generics.xsd")
THEMATIC = {"roof": "RoofSurface", "wall": "WallSurface", "ground": "GroundSurface",
            "overhang_roof": "RoofSurface", "overhang_fascia": "WallSurface",
            "overhang_underside": "OuterCeilingSurface"}


def srs_name(crs: str) -> str:
    """``EPSG:25832`` -> ``urn:ogc:def:crs:EPSG::25832``; other CRS texts unchanged."""
    if crs.upper().startswith("EPSG:"):
        return "urn:ogc:def:crs:EPSG::" + crs.split(":", 1)[1]
    return crs


def _q(prefix: str, name: str) -> str:
    return f"{{{APP_NS if prefix == 'app' else NS[prefix]}}}{name}"


def _pos_list(xyz: np.ndarray) -> str:
    ring = np.vstack([xyz, xyz[:1]])
    return " ".join(f"{v:.4f}" for v in ring.ravel())


def citygml_tree(buildings, crs: str, textures=None, page_names: list[str] | None = None,
                 windows: dict | None = None) -> etree._ElementTree:
    """The CityGML document of ``buildings`` (list of :class:`~..buildings.model.BuildingModel`); with
    ``textures`` (a :class:`~..texture.atlas.TextureSet`) and the page file names, its appearance too; with
    ``windows`` (``{surface id: [Window]}``) the openings of the walls."""
    tex = [s for b in buildings for s in b.surfaces if textured(textures, s)]
    root = etree.Element(_q("core", "CityModel"), nsmap={**NS, "app": APP_NS} if tex else NS)
    root.set(_q("xsi", "schemaLocation"), SCHEMA_LOCATION + (" " + APP_SCHEMA if tex else ""))
    allv = np.concatenate([b.vertices for b in buildings]) if buildings else np.zeros((1, 3))
    env = etree.SubElement(etree.SubElement(root, _q("gml", "boundedBy")), _q("gml", "Envelope"),
                           srsName=srs_name(crs), srsDimension="3")
    etree.SubElement(env, _q("gml", "lowerCorner")).text = " ".join(f"{v:.4f}" for v in allv.min(0))
    etree.SubElement(env, _q("gml", "upperCorner")).text = " ".join(f"{v:.4f}" for v in allv.max(0))
    for b in buildings:
        member = etree.SubElement(root, _q("core", "cityObjectMember"))
        bel = etree.SubElement(member, _q("bldg", "Building"))
        bel.set(_q("gml", "id"), b.id)
        attrs = building_attributes(b)
        measured = attrs.pop("measured_height")
        for name, value in attrs.items():
            kind = "stringAttribute" if isinstance(value, str) else "doubleAttribute"
            ga = etree.SubElement(bel, _q("gen", kind), name=name)
            etree.SubElement(ga, _q("gen", "value")).text = value if isinstance(value, str) else repr(float(value))
        etree.SubElement(bel, _q("bldg", "measuredHeight"), uom="m").text = f"{measured:.3f}"
        blk_v, blk_rings, _ = lod12_block(b, attrs["roof_height_70p"])
        lod1 = etree.SubElement(etree.SubElement(bel, _q("bldg", "lod1Solid")), _q("gml", "Solid"))
        lod1.set(_q("gml", "id"), f"{b.id}_lod1")
        comp1 = etree.SubElement(etree.SubElement(lod1, _q("gml", "exterior")), _q("gml", "CompositeSurface"))
        for ring in blk_rings:
            poly = etree.SubElement(etree.SubElement(comp1, _q("gml", "surfaceMember")), _q("gml", "Polygon"))
            lr = etree.SubElement(etree.SubElement(poly, _q("gml", "exterior")), _q("gml", "LinearRing"))
            etree.SubElement(lr, _q("gml", "posList"), srsDimension="3").text = _pos_list(blk_v[ring])
        solid_surfaces = [s for s in b.surfaces if s.in_solid]
        if solid_surfaces:
            solid = etree.SubElement(etree.SubElement(bel, _q("bldg", "lod2Solid")), _q("gml", "Solid"))
            solid.set(_q("gml", "id"), f"{b.id}_solid")
            comp = etree.SubElement(etree.SubElement(solid, _q("gml", "exterior")), _q("gml", "CompositeSurface"))
            for s in solid_surfaces:
                etree.SubElement(comp, _q("gml", "surfaceMember")).set(_q("xlink", "href"), f"#{s.id}_poly")
        for s in b.surfaces:
            bb = etree.SubElement(bel, _q("bldg", "boundedBy"))
            th = etree.SubElement(bb, _q("bldg", THEMATIC[s.kind]))
            th.set(_q("gml", "id"), s.id)
            ms = etree.SubElement(etree.SubElement(th, _q("bldg", "lod2MultiSurface")), _q("gml", "MultiSurface"))
            poly = etree.SubElement(etree.SubElement(ms, _q("gml", "surfaceMember")), _q("gml", "Polygon"))
            poly.set(_q("gml", "id"), f"{s.id}_poly")
            ring = etree.SubElement(etree.SubElement(poly, _q("gml", "exterior")), _q("gml", "LinearRing"))
            if textured(textures, s):
                ring.set(_q("gml", "id"), f"{s.id}_ring")
            pl = etree.SubElement(ring, _q("gml", "posList"), srsDimension="3")
            pl.text = _pos_list(b.vertices[list(s.ring)])
            for w in (windows or {}).get(s.id, []) if s.kind == "wall" else []:
                win = etree.SubElement(etree.SubElement(th, _q("bldg", "opening")), _q("bldg", "Window"))
                win.set(_q("gml", "id"), w.id)
                wms = etree.SubElement(etree.SubElement(win, _q("bldg", "lod3MultiSurface")), _q("gml", "MultiSurface"))
                wp = etree.SubElement(etree.SubElement(wms, _q("gml", "surfaceMember")), _q("gml", "Polygon"))
                wr = etree.SubElement(etree.SubElement(wp, _q("gml", "exterior")), _q("gml", "LinearRing"))
                etree.SubElement(wr, _q("gml", "posList"), srsDimension="3").text = _pos_list(w.corners)
    if tex:
        _appearance(root, tex, textures, page_names or [])
    return etree.ElementTree(root)


def _appearance(root: etree._Element, surfaces: list, textures, page_names: list[str]) -> None:
    """Append the ``app:appearanceMember`` of the textured ``surfaces`` to the CityModel ``root``."""
    app = etree.SubElement(etree.SubElement(root, _q("app", "appearanceMember")), _q("app", "Appearance"))
    etree.SubElement(app, _q("app", "theme")).text = "texture"
    by_page: dict[int, list] = {}
    for s in surfaces:
        by_page.setdefault(textures.surfaces[s.id].page, []).append(s)
    for page, members in sorted(by_page.items()):
        pt = etree.SubElement(etree.SubElement(app, _q("app", "surfaceDataMember")), _q("app", "ParameterizedTexture"))
        etree.SubElement(pt, _q("app", "imageURI")).text = page_names[page]
        etree.SubElement(pt, _q("app", "mimeType")).text = "image/png"
        etree.SubElement(pt, _q("app", "wrapMode")).text = "none"
        for s in members:
            target = etree.SubElement(pt, _q("app", "target"), uri=f"#{s.id}_poly")
            tcl = etree.SubElement(target, _q("app", "TexCoordList"))
            uv = textures.surfaces[s.id].uv
            tc = etree.SubElement(tcl, _q("app", "textureCoordinates"), ring=f"#{s.id}_ring")
            tc.text = " ".join(f"{v:.8f}" for v in np.vstack([uv, uv[:1]]).ravel())


def write_citygml(path: str | Path, buildings, crs: str, textures=None, windows: dict | None = None) -> None:
    """Write a CityGML 2.0 LoD2 file atomically; ``textures`` (optional) adds the appearance and copies the
    atlas pages beside the file, ``windows`` (``{surface id: [Window]}``, optional) the wall openings."""
    names = copy_pages(textures, path) if textures is not None else None
    data = etree.tostring(citygml_tree(buildings, crs, textures, names, windows), xml_declaration=True,
                          encoding="UTF-8", pretty_print=True)
    write_bytes(path, data)


def schema_dir() -> Path:
    """Folder of the offline CityGML 2.0 / GML 3.1.1 / xAL / XLink schemas (from the package ``citysmith``)."""
    try:
        import citysmith
    except ImportError:
        raise ComputationError("CityGML validation needs the package citysmith (pip install citysmith==0.2.0, "
                               "or export with --no-validate)") from None
    d = Path(citysmith.__file__).parent / "data" / "schemas"
    if not (d / "schemas.opengis.net" / "citygml" / "building" / "2.0" / "building.xsd").exists():
        raise ComputationError(f"{d}: the CityGML 2.0 schemas are missing from the citysmith package")
    return d


class _LocalSchemas(etree.Resolver):
    """Maps ``http(s)://host/path`` schema URLs to ``<schema dir>/host/path``; refuses anything else."""

    def __init__(self, root: Path) -> None:
        super().__init__()
        self.root = root

    def resolve(self, url, pubid, context):
        for prefix in ("http://", "https://"):
            if url.startswith(prefix):
                local = self.root / url[len(prefix):]
                if local.exists():
                    return self.resolve_filename(str(local), context)
                raise ComputationError(f"schema {url} has no local copy under {self.root}")
        return None


_SCHEMA: etree.XMLSchema | None = None


def citygml_schema() -> etree.XMLSchema:
    """The compiled CityGML 2.0 building, appearance and generics schemas (with core and GML), built once."""
    global _SCHEMA
    if _SCHEMA is None:
        root = schema_dir()
        parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False)
        parser.resolvers.add(_LocalSchemas(root))
        driver = (b'<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" elementFormDefault="qualified">'
                  b'<xs:import namespace="http://www.opengis.net/citygml/building/2.0" '
                  b'schemaLocation="http://schemas.opengis.net/citygml/building/2.0/building.xsd"/>'
                  b'<xs:import namespace="http://www.opengis.net/citygml/2.0" '
                  b'schemaLocation="http://schemas.opengis.net/citygml/2.0/cityGMLBase.xsd"/>'
                  b'<xs:import namespace="http://www.opengis.net/citygml/appearance/2.0" '
                  b'schemaLocation="http://schemas.opengis.net/citygml/appearance/2.0/appearance.xsd"/>'
                  b'<xs:import namespace="http://www.opengis.net/citygml/generics/2.0" '
                  b'schemaLocation="http://schemas.opengis.net/citygml/generics/2.0/generics.xsd"/></xs:schema>')
        doc = etree.fromstring(driver, parser, base_url=str(root / "driver.xsd"))
        _SCHEMA = etree.XMLSchema(doc)
    return _SCHEMA


def validate_citygml(path: str | Path) -> list[str]:
    """Schema errors of a CityGML 2.0 file (empty when valid). DOCTYPEs and entities are rejected."""
    path = Path(path)
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False)
    try:
        doc = etree.parse(str(path), parser)
    except OSError:
        raise InputError("CityGML file not found", path) from None
    except etree.XMLSyntaxError as e:
        raise InputError(f"not well-formed XML ({e.msg})", path, line=e.lineno) from None
    if doc.docinfo.doctype:
        raise InputError("DOCTYPE declarations are not accepted", path, line=1)
    schema = citygml_schema()
    if schema.validate(doc):
        return []
    return [f"{path}:{e.line}: {e.message}" for e in schema.error_log]
