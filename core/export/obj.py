"""Wavefront OBJ of building models: one object per building, one group per building and surface type.

Polygons are written as n-gons over shared vertices (full float64 precision, world coordinates minus an optional
``origin`` noted in a comment so Blender's float32 keeps millimetres); a ``.mtl`` beside the file gives one
material per surface type. With textures (the ``texture`` stage's atlas), every textured surface gets one ``vt``
per ring vertex and the material of its atlas page (``map_Kd``, pages copied beside the file); the rest keep
their surface-type material. Detected windows (the ``windows`` stage) form one more group per building,
``<building>_windows``, with the material ``window``. The atlases are orthographic rectifications of the planar
surfaces, so plain ``vt u v`` coordinates map them exactly (no projective ``w`` needed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..pipeline.atomic import atomic_path, write_text
from .textures import copy_pages, textured

KIND_COLOURS = {"ground": (0.35, 0.3, 0.25), "wall": (0.85, 0.82, 0.75), "roof": (0.7, 0.2, 0.15),
                "overhang_roof": (0.6, 0.18, 0.12), "overhang_fascia": (0.5, 0.45, 0.4),
                "overhang_underside": (0.45, 0.4, 0.35)}
WINDOW_COLOUR = {"window": (0.15, 0.2, 0.28)}


def write_obj(path: str | Path, buildings, origin: np.ndarray | None = None, textures=None,
              windows: dict | None = None) -> None:
    """Write ``buildings`` (list of :class:`~..buildings.model.BuildingModel`) to ``path`` and ``path.mtl``;
    ``textures`` (a :class:`~..texture.atlas.TextureSet`, optional) adds UVs and atlas materials, ``windows``
    (``{surface id: [Window]}``, :func:`..windows.store.windows_by_surface`) a window group per building."""
    path = Path(path)
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    mtl = path.with_suffix(".mtl")
    pages = copy_pages(textures, path) if textures is not None else []
    lines = ["# Oblique City LOD2 buildings", f"# origin {origin[0]!r} {origin[1]!r} {origin[2]!r}",
             f"mtllib {mtl.name}"]
    base, vt_base = 1, 1
    for b in buildings:
        lines.append(f"o {b.id}")
        for v in b.vertices - origin:
            lines.append(f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}")
        vt_of: dict[str, int] = {}
        for s in b.surfaces:
            if textured(textures, s):
                vt_of[s.id] = vt_base
                for u, v in textures.surfaces[s.id].uv:
                    lines.append(f"vt {u:.8f} {v:.8f}")
                vt_base += len(s.ring)
        by_kind: dict[str, list] = {}
        for s in b.surfaces:
            by_kind.setdefault(s.kind, []).append(s)
        for kind, surfaces in by_kind.items():
            lines.append(f"g {b.id}_{kind}")
            current = None
            for s in surfaces:
                mat = f"atlas_{textures.surfaces[s.id].page:03d}" if s.id in vt_of else kind
                if mat != current:
                    lines.append(f"usemtl {mat}")
                    current = mat
                if s.id in vt_of:
                    lines.append("f " + " ".join(f"{base + i}/{vt_of[s.id] + k}" for k, i in enumerate(s.ring)))
                else:
                    lines.append("f " + " ".join(str(base + i) for i in s.ring))
        base += len(b.vertices)
        wins = [w for s in b.surfaces for w in (windows or {}).get(s.id, [])]
        if wins:
            lines.append(f"g {b.id}_windows")
            lines.append("usemtl window")
            for w in wins:
                lines.extend(f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}" for v in w.corners - origin)
                lines.append("f " + " ".join(str(base + k) for k in range(4)))
                base += 4
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
    mats = "".join(f"newmtl {k}\nKd {c[0]} {c[1]} {c[2]}\n\n" for k, c in {**KIND_COLOURS, **WINDOW_COLOUR}.items())
    mats += "".join(f"newmtl atlas_{i:03d}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {name}\n\n"
                    for i, name in enumerate(pages))
    write_text(mtl, mats)


def _records(path: Path, parse) -> None:
    """Call ``parse(parts)`` for every non-empty line of an OBJ file; a line it cannot read raises
    :class:`InputError` naming the file, line and record."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("OBJ file not found", path) from None
    for ln, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            parse(parts)
        except (ValueError, IndexError, OSError):
            raise InputError(f"malformed '{parts[0]}' record", path, line=ln, field=parts[0]) from None


def read_obj(path: str | Path) -> tuple[np.ndarray, dict[str, list[list[int]]], np.ndarray]:
    """Read an OBJ written by :func:`write_obj` (or any polygon OBJ).

    Returns
    -------
    vertices : (n, 3) float64 (the origin comment added back); groups : {group name: faces as 0-based index
    lists}; origin : (3,)
    """
    path = Path(path)
    verts: list[list[float]] = []
    groups: dict[str, list[list[int]]] = {}
    state = {"origin": np.zeros(3), "group": "default"}

    def parse(parts: list[str]) -> None:
        if parts[0] == "#" and len(parts) == 5 and parts[1] == "origin":
            state["origin"] = np.array([float(x) for x in parts[2:5]])
        elif parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] == "g":
            state["group"] = parts[1] if len(parts) > 1 else "default"
        elif parts[0] == "f":
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            groups.setdefault(state["group"], []).append([i - 1 if i > 0 else len(verts) + i for i in idx])

    _records(path, parse)
    origin = state["origin"]
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3) + origin, groups, origin


def read_obj_texcoords(path: str | Path) -> tuple[np.ndarray, dict[str, list[list[int]]], dict[str, str]]:
    """The texture side of an OBJ: ``vt`` coordinates ``(m, 2)``, per group the faces' 0-based ``vt`` indices
    (empty lists for faces without), and the ``map_Kd`` image of every material in the ``.mtl`` files."""
    path = Path(path)
    vts: list[list[float]] = []
    groups: dict[str, list[list[int]]] = {}
    maps: dict[str, str] = {}
    state = {"group": "default"}

    def parse(parts: list[str]) -> None:
        if parts[0] == "vt":
            vts.append([float(x) for x in parts[1:3]])
        elif parts[0] == "g":
            state["group"] = parts[1] if len(parts) > 1 else "default"
        elif parts[0] == "f":
            groups.setdefault(state["group"], []).append([int(p.split("/")[1]) - 1 for p in parts[1:]
                                                          if len(p.split("/")) > 1 and p.split("/")[1]])
        elif parts[0] == "mtllib":
            mat = None
            for mline in (path.parent / parts[1]).read_text(encoding="utf-8").splitlines():
                mp = mline.split()
                if mp and mp[0] == "newmtl":
                    mat = mp[1]
                elif mp and mp[0] == "map_Kd" and mat is not None:
                    maps[mat] = mp[-1]

    _records(path, parse)
    return np.asarray(vts, dtype=np.float64).reshape(-1, 2), groups, maps
