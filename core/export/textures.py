"""Texture atlases for the exports: the pages copied beside the exported file, and the UVs of a surface.

Pages are copied as ``<stem>_atlas_NNN.png`` next to the output (OBJ, CityGML and CityJSON reference them by that
relative name), so an export folder is self-contained. UVs come from ``texture/textures.json``: one per ring vertex
in ring order, ``u`` right and ``v`` up in [0, 1] of the page.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..pipeline.atomic import write_bytes


def copy_pages(textures, out: str | Path) -> list[str]:
    """Copy the atlas pages of a :class:`~..texture.atlas.TextureSet` beside ``out``; returns their file names
    (page order)."""
    out = Path(out)
    stem = out.name.split(".")[0]
    names = []
    for i, (src, _, _) in enumerate(textures.pages):
        if not Path(src).exists():
            raise InputError("atlas page missing (rerun the 'texture' stage)", src)
        name = f"{stem}_atlas_{i:03d}.png"
        write_bytes(out.parent / name, Path(src).read_bytes())
        names.append(name)
    return names


def textured(textures, surface) -> bool:
    """Whether a surface (``..buildings.model.Surface``) has a texture whose UVs match its ring."""
    if textures is None or surface.id not in textures.surfaces:
        return False
    return len(textures.surfaces[surface.id].uv) == len(surface.ring)
