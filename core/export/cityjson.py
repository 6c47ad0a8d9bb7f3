"""CityJSON 2.0 export (LoD 2.2 Solid with semantic surfaces; overhangs as a MultiSurface; an LoD 1.2 block at the
70th percentile roof height) and a structural check.

Every Building carries the attributes of :func:`..buildings.attributes.building_attributes` (ground and roof
heights, areas, volume, roof type) beside ``measuredHeight``.

Vertices are quantised integers with ``transform`` (scale 1 mm, translate = the minimum corner), each listed once
(the LoD 1.2 block shares the LoD2 model's ground corners); a surface the quantisation leaves with fewer than three
distinct vertices is left out. The official validator, cjval (a Rust program, ``cargo install cjval --features
build-binary``), accepts what we write; the test suite does not build it, so
:func:`check_cityjson` checks the structure the specification prescribes for what we write: top-level members,
object types, geometry types and LoDs, the nesting depth of ``boundaries``, vertex indices in range, closed rings of
at least three distinct vertices, and ``semantics.values`` mirroring the boundaries; with textures,
``texture.values`` mirroring the boundaries with one texture index and one ``vertices-texture`` index per ring
vertex.

Detected windows (the ``windows`` stage) of a building form one child CityObject ``<building>-windows`` of type
``BuildingInstallation`` (``parents``/``children`` linked), an LoD3 ``MultiSurface`` whose surfaces carry the
``Window`` semantic type with the wall surface id (``oc_wall``), window id and score.

With textures (the ``texture`` stage's atlas), the document gets an ``appearance`` (one PNG texture per atlas page,
copied beside the file, and ``vertices-texture`` holding the UVs) and every geometry with a textured surface a
``texture`` member under the theme ``texture``; untextured surfaces there are ``[[null]]``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..buildings.attributes import building_attributes, lod12_block
from ..io.validate import read_json
from ..pipeline.atomic import write_text
from .textures import copy_pages, textured

SEMANTIC_TYPES = {"roof": "RoofSurface", "wall": "WallSurface", "ground": "GroundSurface",
                  "overhang_roof": "RoofSurface", "overhang_fascia": "WallSurface",
                  "overhang_underside": "OuterCeilingSurface"}


def _reference_system(crs: str) -> str:
    if crs.upper().startswith("EPSG:"):
        return "https://www.opengis.net/def/crs/EPSG/0/" + crs.split(":", 1)[1]
    return crs


def cityjson_document(buildings, crs: str, scale: float = 0.001, textures=None,
                      page_names: list[str] | None = None, windows: dict | None = None) -> dict[str, Any]:
    """The CityJSON 2.0 document of ``buildings`` (list of :class:`~..buildings.model.BuildingModel`); with
    ``textures`` (a :class:`~..texture.atlas.TextureSet`) and the page file names, its appearance too; with
    ``windows`` (``{surface id: [Window]}``) a window installation per building."""
    allv = np.concatenate([b.vertices for b in buildings]) if buildings else np.zeros((1, 3))
    translate = np.floor(allv.min(0))
    vertices: list[list[int]] = []
    index_of: dict[tuple[int, int, int], int] = {}
    objects: dict[str, Any] = {}
    uvs: list[list[float]] = []

    def add(xyz: np.ndarray) -> list[int]:
        """Indices of the quantised points ``xyz (n, 3)`` in the shared vertex list (each vertex once)."""
        out = []
        for v in np.round((np.asarray(xyz) - translate) / scale).astype(np.int64).tolist():
            key = (v[0], v[1], v[2])
            if key not in index_of:
                index_of[key] = len(vertices)
                vertices.append(v)
            out.append(index_of[key])
        return out

    def tex_ring(s) -> list:
        if not textured(textures, s):
            return [None]
        st = textures.surfaces[s.id]
        first = len(uvs)
        uvs.extend(np.round(st.uv, 7).tolist())
        return [st.page, *range(first, first + len(s.ring))]

    for b in buildings:
        idx = add(b.vertices)
        attrs = building_attributes(b)
        blk_v, blk_rings, blk_kinds = lod12_block(b, attrs["roof_height_70p"])
        blk = add(blk_v)
        kinds = sorted(set(blk_kinds), key=list(SEMANTIC_TYPES).index)
        geoms = [{"type": "Solid", "lod": "1.2", "boundaries": [[[[blk[i] for i in r]] for r in blk_rings]],
                  "semantics": {"surfaces": [{"type": SEMANTIC_TYPES[k]} for k in kinds],
                                "values": [[kinds.index(k) for k in blk_kinds]]}}]
        for in_solid in (True, False):
            # a surface whose ring quantisation leaves fewer than three distinct vertices (a sliver under the 1 mm
            # scale) is no polygon: left out
            surfaces = [s for s in b.surfaces if s.in_solid == in_solid and len({idx[i] for i in s.ring}) >= 3]
            if not surfaces:
                continue
            kinds = sorted({s.kind for s in surfaces}, key=list(SEMANTIC_TYPES).index)
            sem = {"surfaces": [{"type": SEMANTIC_TYPES[k], "oc_kind": k} for k in kinds],
                   "values": [kinds.index(s.kind) for s in surfaces]}
            faces = [[[idx[i] for i in s.ring]] for s in surfaces]
            if in_solid:
                geoms.append({"type": "Solid", "lod": "2.2", "boundaries": [faces],
                              "semantics": {"surfaces": sem["surfaces"], "values": [sem["values"]]}})
            else:
                geoms.append({"type": "MultiSurface", "lod": "2.2", "boundaries": faces, "semantics": sem})
            if any(textured(textures, s) for s in surfaces):
                values = [[tex_ring(s)] for s in surfaces]
                geoms[-1]["texture"] = {"texture": {"values": [values] if in_solid else values}}
        objects[b.id] = {"type": "Building", "geometry": geoms,
                         "attributes": {"measuredHeight": attrs.pop("measured_height"), **attrs,
                                        "reconstruction_path": b.path, "closed_solid": bool(b.info.get("closed"))}}
        wins = [w for s in b.surfaces if s.kind == "wall" for w in (windows or {}).get(s.id, [])]
        if wins:
            corners = add(np.concatenate([w.corners for w in wins]))
            wid = f"{b.id}-windows"
            objects[b.id]["children"] = [wid]
            objects[wid] = {"type": "BuildingInstallation", "parents": [b.id], "geometry": [{
                "type": "MultiSurface", "lod": "3",
                "boundaries": [[corners[4 * k:4 * k + 4]] for k in range(len(wins))],
                "semantics": {"surfaces": [{"type": "Window", "oc_wall": w.surface_id, "oc_id": w.id,
                                            "oc_score": round(w.score, 4)} for w in wins],
                              "values": list(range(len(wins)))}}]}
    doc = {"type": "CityJSON", "version": "2.0",
           "transform": {"scale": [scale] * 3, "translate": translate.tolist()},
           "metadata": {"referenceSystem": _reference_system(crs),
                        "geographicalExtent": [*allv.min(0).tolist(), *allv.max(0).tolist()]},
           "CityObjects": objects, "vertices": vertices}
    if uvs:
        doc["appearance"] = {"textures": [{"type": "PNG", "image": name, "wrapMode": "none"}
                                          for name in page_names or []], "vertices-texture": uvs}
    return doc


def write_cityjson(path: str | Path, buildings, crs: str, textures=None, windows: dict | None = None) -> None:
    """Write a CityJSON 2.0 file atomically; ``textures`` (optional) adds the appearance and copies the atlas
    pages beside the file, ``windows`` (``{surface id: [Window]}``, optional) the window installations."""
    names = copy_pages(textures, path) if textures is not None else None
    write_text(path, json.dumps(cityjson_document(buildings, crs, textures=textures, page_names=names,
                                                  windows=windows), separators=(",", ":")))


def _check_texture(g: dict[str, Any], n_tex: int, n_uv: int, where: str, errors: list[str]) -> None:
    """Texture values of a geometry: mirror its boundaries, [texture, uv...] per ring or [null]."""
    b = g.get("boundaries") or []
    surfaces = [(f"[{si}][{fi}]", srf) for si, shell in enumerate(b) for fi, srf in enumerate(shell)] \
        if g.get("type") == "Solid" else [(f"[{fi}]", srf) for fi, srf in enumerate(b)]
    for theme, tex in g["texture"].items():
        vals = tex.get("values")
        flat = [v for shell in vals for v in shell] if g.get("type") == "Solid" and isinstance(vals, list) else vals
        if not isinstance(flat, list) or len(flat) != len(surfaces):
            errors.append(f"{where}.texture.{theme}: values do not mirror the boundaries")
            continue
        for (pos, srf), tv in zip(surfaces, flat, strict=True):
            if not isinstance(tv, list) or len(tv) != len(srf):
                errors.append(f"{where}.texture.{theme}{pos}: one entry per ring expected")
                continue
            for ring, tr in zip(srf, tv, strict=True):
                if tr == [None]:
                    continue
                if (not isinstance(tr, list) or len(tr) != len(ring) + 1 or not all(isinstance(i, int) for i in tr)
                        or not 0 <= tr[0] < n_tex or any(i < 0 or i >= n_uv for i in tr[1:])):
                    errors.append(f"{where}.texture.{theme}{pos}: needs [texture, one uv per vertex] in range")


def _check_surface(surface: Any, nv: int, where: str, errors: list[str]) -> None:
    if not isinstance(surface, list) or not surface:
        errors.append(f"{where}: a surface must be a non-empty list of rings")
        return
    for k, ring in enumerate(surface):
        if not isinstance(ring, list) or not all(isinstance(i, int) for i in ring):
            errors.append(f"{where}[{k}]: a ring must be a list of vertex indices")
            continue
        if len(set(ring)) < 3:
            errors.append(f"{where}[{k}]: fewer than three distinct vertices")
        if any(i < 0 or i >= nv for i in ring):
            errors.append(f"{where}[{k}]: vertex index out of range")


def check_cityjson(doc: dict[str, Any]) -> list[str]:
    """Structural errors of a CityJSON 2.0 document (empty when it is well formed)."""
    errors: list[str] = []
    if doc.get("type") != "CityJSON":
        errors.append("type must be 'CityJSON'")
    if doc.get("version") != "2.0":
        errors.append("version must be '2.0'")
    tr = doc.get("transform", {})
    if len(tr.get("scale", [])) != 3 or len(tr.get("translate", [])) != 3:
        errors.append("transform needs 3 scale and 3 translate values")
    verts = doc.get("vertices")
    if not isinstance(verts, list) or not all(isinstance(v, list) and len(v) == 3 and
                                              all(isinstance(c, int) for c in v) for v in verts):
        errors.append("vertices must be a list of integer triplets")
        return errors
    nv = len(verts)
    for oid, obj in doc.get("CityObjects", {}).items():
        if obj.get("type") not in ("Building", "BuildingPart", "BuildingInstallation"):
            errors.append(f"{oid}: unexpected type {obj.get('type')!r}")
        objs = doc.get("CityObjects", {})
        for rel, back in (("parents", "children"), ("children", "parents")):
            for other in obj.get(rel, []):
                if oid not in objs.get(other, {}).get(back, []):
                    errors.append(f"{oid}: {rel} {other!r} does not list it among its {back}")
        lods = ("1", "1.0", "1.1", "1.2", "1.3", "2", "2.0", "2.1", "2.2", "2.3") + (
            ("3", "3.0") if obj.get("type") == "BuildingInstallation" else ())
        for gi, g in enumerate(obj.get("geometry", [])):
            where = f"{oid}.geometry[{gi}]"
            if g.get("lod") not in lods:
                errors.append(f"{where}: lod {g.get('lod')!r} is not an LoD1 or LoD2 value")
            b = g.get("boundaries")
            sem = g.get("semantics")
            if g.get("type") == "Solid":
                if not isinstance(b, list) or not b:
                    errors.append(f"{where}: a Solid needs at least one shell")
                    continue
                for si, shell in enumerate(b):
                    for fi, surface in enumerate(shell):
                        _check_surface(surface, nv, f"{where}.boundaries[{si}][{fi}]", errors)
                if sem is not None and [len(v) for v in sem.get("values", [])] != [len(s) for s in b]:
                    errors.append(f"{where}: semantics.values does not mirror the shells")
            elif g.get("type") == "MultiSurface":
                for fi, surface in enumerate(b or []):
                    _check_surface(surface, nv, f"{where}.boundaries[{fi}]", errors)
                if sem is not None and len(sem.get("values", [])) != len(b or []):
                    errors.append(f"{where}: semantics.values does not mirror the surfaces")
            else:
                errors.append(f"{where}: unexpected geometry type {g.get('type')!r}")
            if "texture" in g:
                app = doc.get("appearance", {})
                _check_texture(g, len(app.get("textures", [])), len(app.get("vertices-texture", [])), where, errors)
            if sem is not None:
                n_sem = len(sem.get("surfaces", []))
                flat = [v for v in (sem.get("values") or []) for v in (v if isinstance(v, list) else [v])]
                if any(v is not None and not (0 <= v < n_sem) for v in flat):
                    errors.append(f"{where}: semantics value out of range")
    return errors


def read_cityjson(path: str | Path) -> dict[str, Any]:
    """Load a CityJSON file (InputError on malformed JSON)."""
    return read_json(path, "CityJSON file not found")
