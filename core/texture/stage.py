"""The ``texture`` stage: perspective-correct, multi-source texture atlases of the LOD2 buildings.

Reads ``buildings/buildings.json``, the oriented block (the adjusted poses when aerial triangulation ran) with
its images, and ``surface/dsm.tif`` / ``dtm.tif`` when present (terrain and vegetation occlude); writes
``texture/atlas_NNN.png`` (RGB pages), ``texture/atlas_NNN_seen.png`` (255 where an image gave the texel, 0 where
no image sees it and the colour is filled in) and ``texture/textures.json``: per surface the page, the UV of every
ring vertex (ring order), the texel size, the contributing images with their shares and the share of texels seen;
per image the radiometric gains; surfaces without texture with the reason.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from ..buildings.model import SURFACE_KINDS, load_buildings
from ..errors import WorkspaceError
from ..pipeline.stage import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    CheckedOptions,
    Range,
    Rule,
    Stage,
    StageResult,
)
from .atlas import fill_empty, hole_colours, pack_shelves, ring_uv, write_textures_json
from .compose import ComposeOptions, SurfacePatch, choose_texel, solve_gains, texture_surface
from .occlusion import OcclusionScene, grid_mesh, terrain_without_buildings
from .plane import plane_frame
from .sources import ImageCache, block_sources, candidate_sources


@dataclass(frozen=True)
class TextureConfig(CheckedOptions):
    """Options of the ``texture`` stage (``[stages.texture]`` in project.toml).

    texel : texel size (m), 0 = per surface from the best image resolution on it times ``texel_factor``,
    clipped to [min_texel, max_texel]; page_size : atlas page side (texels); gutter : padding around patches
    (texels); max_sources : candidate images per surface; feather : seam blend sigma (texels);
    occlusion_margin : growth of occluded areas (texels); min_cos : grazing limit (cosine of the angle to the
    normal); radiometric : per-image gains from overlaps; terrain_step : cell of the occluding terrain mesh (m);
    kinds : surface kinds to texture; cache_images : decoded images kept in memory
    """

    texel: float = 0.0
    texel_factor: float = 1.0
    min_texel: float = 0.02
    max_texel: float = 0.5
    page_size: int = 4096
    gutter: int = 4
    max_sources: int = 8
    feather: float = 2.0
    occlusion_margin: int = 2
    min_cos: float = 0.15
    radiometric: bool = True
    terrain_step: float = 0.5
    kinds: tuple[str, ...] = ("wall", "roof", "overhang_roof", "overhang_fascia", "overhang_underside")
    cache_images: int = 40

    RULES: ClassVar[dict[str, Rule]] = {
        "texel": NON_NEGATIVE, "texel_factor": POSITIVE, "min_texel": POSITIVE, "max_texel": POSITIVE,
        "page_size": Range(16.0), "gutter": NON_NEGATIVE, "max_sources": AT_LEAST_ONE, "feather": NON_NEGATIVE,
        "occlusion_margin": NON_NEGATIVE, "min_cos": FRACTION, "terrain_step": POSITIVE, "kinds": SURFACE_KINDS,
        "cache_images": AT_LEAST_ONE}
    ORDERED: ClassVar[tuple[tuple[str, str, bool], ...]] = (("min_texel", "max_texel", False),)


def occluder_scene(ws, buildings, terrain_step: float = 0.5) -> OcclusionScene:
    """All building models plus the terrain (DSM outside the buildings, DTM under them) of a workspace."""
    from ..io.geotiff import read_geotiff

    meshes = [b.triangles()[:2] for b in buildings]
    dsm_p, dtm_p = ws.path("surface", "dsm.tif"), ws.path("surface", "dtm.tif")
    if dsm_p.exists() and dtm_p.exists():
        dsm, dtm = read_geotiff(dsm_p), read_geotiff(dtm_p)
        tops = [b.vertices[list(s.ring), :2] for b in buildings for s in b.surfaces
                if s.kind in ("roof", "overhang_roof", "ground")]
        ground = terrain_without_buildings(dsm, dtm, tops, margin=1.0)
        meshes.append(grid_mesh(ground, max(1, round(terrain_step / dsm.cell))))
    origin = np.floor(buildings[0].vertices[0]) if buildings else None
    return OcclusionScene(meshes, origin)


def texture_buildings(buildings, sources, occluder, cfg: TextureConfig, ctx) -> tuple[list[SurfacePatch], dict]:
    """Texture every wanted surface; returns the patches and the untextured surfaces ``{id: reason}``."""
    opt = ComposeOptions(feather=cfg.feather, occlusion_margin=cfg.occlusion_margin, min_cos=cfg.min_cos)
    cache = ImageCache(cfg.cache_images)
    max_side = cfg.page_size - 2 * cfg.gutter
    patches: list[SurfacePatch] = []
    skipped: dict[str, str] = {}
    order = sorted(buildings, key=lambda b: (round(float(b.vertices[:, 1].mean()) / 100.0),
                                             float(b.vertices[:, 0].mean())))
    for bi, b in enumerate(order):
        ctx.progress(bi, len(order), f"texturing {b.id}")
        t0 = time.perf_counter()
        for s in b.surfaces:
            if s.kind not in cfg.kinds:
                continue
            ctx.check()
            ring = b.vertices[list(s.ring)]
            try:
                frame = plane_frame(ring)
            except ValueError:
                skipped[s.id] = "degenerate ring"
                continue
            cands = candidate_sources(sources, ring, frame.normal, cfg.max_sources, cfg.min_cos)
            if not cands:
                skipped[s.id] = "no image sees it"
                continue
            st = frame.to_plane(ring)
            extent = float((st.max(0) - st.min(0)).max())
            texel = (max(cfg.texel, extent / max_side) if cfg.texel > 0 else
                     choose_texel(cands[0][1], cfg.texel_factor, cfg.min_texel, cfg.max_texel, extent, max_side))
            patch = texture_surface(s.id, b.id, ring, texel, [c for c, _ in cands], cache, occluder, opt)
            if patch.coverage == 0.0:
                skipped[s.id] = "occluded in every image"
                continue
            patches.append(patch)
        b.info["texture_seconds"] = round(time.perf_counter() - t0, 3)
    ctx.progress(len(order), len(order), "textured")
    return patches, skipped


def build_atlas(patches: list[SurfacePatch], gains: dict, cfg: TextureConfig
                ) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """Pack the patches into pages ``(h, w, 3) uint8`` with their seen masks ``(h, w) uint8`` (255 where an image
    gave the texel's colour) and compute the per-surface records of textures.json. Ring texels no image sees take
    the wall's local colour (:func:`.atlas.hole_colours`)."""
    places, sizes = pack_shelves([p.grid.shape for p in patches], cfg.page_size, cfg.gutter)
    pages = [np.zeros((h, w, 3), np.float32) for w, h in sizes]
    covered = [np.zeros((h, w), bool) for w, h in sizes]
    seen = [np.zeros((h, w), np.uint8) for w, h in sizes]
    records = {}
    for p, pl in zip(patches, places, strict=True):
        has = p.weights.sum(0) > 0
        col = p.colours(gains)
        seen[pl.page][pl.y + p.rows[has], pl.x + p.cols[has]] = 255
        fill = has | p.in_ring
        if (fill & ~has).any():
            col[fill & ~has] = hole_colours(col, has, p.rows, p.cols, p.grid.texel)[fill & ~has]
        pages[pl.page][pl.y + p.rows[fill], pl.x + p.cols[fill]] = col[fill]
        covered[pl.page][pl.y + p.rows[fill], pl.x + p.cols[fill]] = True
        rows, cols = p.grid.shape
        records[p.surface_id] = {
            "building": p.building_id, "page": pl.page, "rect": [pl.x, pl.y, cols, rows],
            "uv": np.round(ring_uv(p.grid.ring_xy, pl, sizes[pl.page]), 8).tolist(),
            "texel": p.grid.texel, "coverage": round(p.coverage, 4), "sources": p.source_shares(),
            "frame": {"origin": p.grid.frame.origin.tolist(), "e1": p.grid.frame.e1.tolist(),
                      "e2": p.grid.frame.e2.tolist(), "s0": p.grid.s0, "t1": p.grid.t1},
        }
    out = [np.clip(np.rint(fill_empty(pg, cv)), 0, 255).astype(np.uint8) for pg, cv in zip(pages, covered,
                                                                                            strict=True)]
    return out, seen, records


def run(ws, cfg: TextureConfig, ctx) -> StageResult:
    from ..io.geotiff import write_png

    bpath = ws.path("buildings", "buildings.json")
    if not bpath.exists():
        raise WorkspaceError(f"{bpath}: no buildings (run the 'buildings' stage)")
    buildings, _ = load_buildings(bpath)
    block = ws.load_block()
    sources = block_sources(block)
    if not sources:
        raise WorkspaceError(f"{ws.root}: the block has no oriented images with files to texture from")
    ctx.progress(0, 1, "building the occlusion scene")
    occluder = occluder_scene(ws, buildings, cfg.terrain_step)
    patches, skipped = texture_buildings(buildings, sources, occluder, cfg, ctx)
    pairs = [pr for p in patches for pr in p.pairs]
    gains = solve_gains(pairs) if cfg.radiometric else {}
    pages, seen_pages, records = build_atlas(patches, gains, cfg)
    out = ws.stage_dir("texture")
    files = []
    for i, (page, seen_page) in enumerate(zip(pages, seen_pages, strict=True)):
        write_png(out / f"atlas_{i:03d}.png", page)
        write_png(out / f"atlas_{i:03d}_seen.png", seen_page)
        files.append({"file": f"atlas_{i:03d}.png", "seen": f"atlas_{i:03d}_seen.png", "width": page.shape[1],
                      "height": page.shape[0]})
    kept = {f[k] for f in files for k in ("file", "seen")}
    for stale in out.glob("atlas_*.png"):
        if stale.name not in kept:
            stale.unlink()
    ring_texels = sum(int(p.in_ring.sum()) for p in patches)
    seen = sum(int(((p.weights.sum(0) > 0) & p.in_ring).sum()) for p in patches)
    stats = {"surfaces_textured": len(records), "surfaces_untextured": len(skipped), "pages": len(pages),
             "ring_texels": ring_texels, "share_with_source": round(seen / max(ring_texels, 1), 4),
             "seconds_per_building": {b.id: b.info.get("texture_seconds") for b in buildings},
             "radiometric_pairs": len(pairs)}
    write_textures_json(out / "textures.json", {
        "crs": ws.crs, "pages": files, "surfaces": records, "untextured": skipped,
        "gains": {k: np.round(v, 5).tolist() for k, v in sorted(gains.items())},
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}, "stats": stats})
    metrics = {k: v for k, v in stats.items() if k != "seconds_per_building"}
    return StageResult(("texture/textures.json", *(f"texture/{f[k]}" for f in files for k in ("file", "seen"))),
                       metrics,
                       f"{len(records)} surfaces textured on {len(pages)} atlas pages "
                       f"({100 * stats['share_with_source']:.1f}% of texels seen), {len(skipped)} without texture")


STAGE = Stage(name="texture", run=run, config=TextureConfig, requires=("buildings",),
              description="perspective-correct multi-source texture atlases of the buildings", version="4")
