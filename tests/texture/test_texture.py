"""Texture core on a synthetic scene with a known answer: plane frames, texel grids, packing, per-texel source
choice with occlusion, perspective-correct sampling with distortion, radiometric gains, UV/ring consistency."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.pipeline.context import RunContext
from oblique_city.core.texture.atlas import fill_empty, hole_colours, pack_shelves
from oblique_city.core.texture.compose import solve_gains
from oblique_city.core.texture.occlusion import OcclusionScene
from oblique_city.core.texture.plane import plane_frame, texel_grid
from oblique_city.core.texture.sources import block_sources
from oblique_city.core.texture.stage import TextureConfig, build_atlas, texture_buildings

from .scene import GREEN, OFFSET, buildings, make_block, pattern


def test_plane_frames_are_upright_and_keep_the_ring_orientation():
    b = buildings()[0]
    for s in b.surfaces:
        ring = b.vertices[list(s.ring)]
        f = plane_frame(ring)
        assert np.allclose(np.cross(f.e1, f.e2), f.normal)
        st = f.to_plane(ring)
        area = 0.5 * np.sum(st[:, 0] * np.roll(st[:, 1], -1) - st[:, 1] * np.roll(st[:, 0], -1))
        assert area > 0  # counter-clockwise seen from outside stays counter-clockwise in (s, t)
        assert np.allclose(f.to_world(st), ring)
        if s.kind == "wall":
            assert np.allclose(f.e2, [0, 0, 1]) and abs(f.e1[2]) < 1e-12
        if s.kind == "roof":
            assert np.allclose(f.e1, [1, 0, 0]) and np.allclose(f.e2, [0, 1, 0])


def test_texel_grid_covers_the_ring():
    b = buildings()[0]
    ring = b.vertices[list(b.surfaces[1].ring)]  # south wall, 10 x 6 m
    g = texel_grid(ring, 0.1)
    assert g.shape == (60, 100)
    assert g.mask.sum() == 6000
    assert np.allclose(g.texel_xy(ring), g.ring_xy)
    assert np.allclose(sorted(g.ring_xy[:, 0]), [0, 0, 100, 100])
    c = g.centres(np.array([0]), np.array([0]))[0]
    assert np.allclose(c, OFFSET + [0.05, 0.0, 5.95])


def test_shelf_packing_keeps_patches_apart():
    rng = np.random.default_rng(3)
    sizes = [(int(h), int(w)) for h, w in rng.integers(5, 300, size=(60, 2))]
    places, pages = pack_shelves(sizes, 512, 3)
    occ = [np.zeros((h, w), np.int32) for w, h in pages]
    for (h, w), p in zip(sizes, places, strict=True):
        assert p.x >= 3 and p.y >= 3 and p.x + w + 3 <= pages[p.page][0] and p.y + h + 3 <= pages[p.page][1]
        occ[p.page][p.y - 3:p.y + h + 3, p.x - 3:p.x + w + 3] += 1
    assert max(o.max() for o in occ) == 1  # gutters included, nothing overlaps
    assert all(w & (w - 1) == 0 and h & (h - 1) == 0 for w, h in pages)


def test_gains_recover_exposure_ratios():
    d = np.log(np.array([1.25, 1.25, 1.25]))  # b is 1.25 times brighter than a
    gains = solve_gains([("a", "b", d, 1000), ("b", "c", -np.log([0.8, 0.8, 0.8]), 1000)], prior=1e-3)
    assert np.allclose(gains["a"] / gains["b"], 1.25, rtol=1e-3)
    assert np.allclose(gains["c"] / gains["b"], 0.8, rtol=1e-3)


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    """The scene textured at 4 cm texels: (patches by id, pages, records, block)."""
    block = make_block(tmp_path_factory.mktemp("images"))
    models = buildings()
    occ = OcclusionScene([m.triangles()[:2] for m in models], np.floor(OFFSET))
    cfg = TextureConfig(texel=0.04, page_size=1024)
    patches, skipped = texture_buildings(models, block_sources(block), occ, cfg, RunContext())
    from oblique_city.core.texture.compose import solve_gains as sg

    gains = sg([pr for p in patches for pr in p.pairs])
    pages, seen, records = build_atlas(patches, gains, cfg)
    return {p.surface_id: p for p in patches}, pages, records, skipped, gains, seen


def _atlas_at(pages, rec, xyz):
    """Bilinear atlas colours at world points through the surface's stored frame and UVs (the way a renderer
    reads the texture)."""
    import cv2

    f = rec["frame"]
    d = xyz - np.asarray(f["origin"])
    s, t = d @ np.asarray(f["e1"]), d @ np.asarray(f["e2"])
    x = rec["rect"][0] + (s - f["s0"]) / rec["texel"]
    y = rec["rect"][1] + (f["t1"] - t) / rec["texel"]
    page = pages[rec["page"]].astype(np.float32)
    mx, my = (x - 0.5).astype(np.float32)[None], (y - 0.5).astype(np.float32)[None]
    return cv2.remap(page, mx, my, cv2.INTER_LINEAR)[0]


def test_atlas_reproduces_the_pattern(textured):
    patches, pages, records, skipped, gains, _ = textured
    assert "B0001_ground_0" not in records  # never textured: it faces the terrain
    assert skipped["B0001_wall_3"] == "no image sees it"  # the north wall: every camera is south of it
    rng = np.random.default_rng(0)
    for sid in ("B0001_wall_1", "B0001_roof_5", "B0001_wall_4"):
        p = patches[sid]
        rec = records[sid]
        b = buildings()[0]
        ring = b.vertices[list(next(s for s in b.surfaces if s.id == sid).ring)]
        # random interior points (0.15 m from the edges: seams with the ground and the sky stay out)
        f = plane_frame(ring)
        st = f.to_plane(ring)
        lo, hi = st.min(0) + 0.15, st.max(0) - 0.15
        xyz = f.to_world(rng.uniform(lo, hi, size=(3000, 2)))
        got = _atlas_at(pages, rec, xyz)
        want = pattern(xyz)
        # one gain per channel for the whole surface: the radiometric datum is free
        scale = (got * want).sum(0) / (want * want).sum(0)
        err = np.abs(got - want * scale)
        assert np.all(np.abs(scale - 1) < 0.2), (sid, scale)
        # the west wall is seen at 63 deg only (9 cm pixels for 4 cm texels): bilinear interpolation of the
        # 1.1 m sine costs a few DN there
        assert np.median(err) < 3 and np.percentile(err, 95) < 10, (sid, np.median(err), np.percentile(err, 95))
        # x 4.3..5 m, z < 2.5 m of the south wall is hidden from both cameras that face it (3 %)
        assert p.coverage > (0.95 if sid == "B0001_wall_1" else 0.98), (sid, p.coverage)
    # UVs of the ring vertices are the patch corners on the page
    rec = records["B0001_wall_1"]
    w, h = (pages[rec["page"]].shape[1], pages[rec["page"]].shape[0])
    uv = np.asarray(rec["uv"])
    x, y = uv[:, 0] * w, (1 - uv[:, 1]) * h
    assert np.allclose(sorted(set(np.round(x, 6))), [rec["rect"][0], rec["rect"][0] + 250])
    assert np.allclose(sorted(set(np.round(y, 6))), [rec["rect"][1], rec["rect"][1] + 150])


def test_occluded_part_comes_from_the_other_image(textured):
    patches, pages, records, _, gains, _ = textured
    p = patches["B0001_wall_1"]
    k_south, k_sw = p.source_ids.index("south"), p.source_ids.index("southwest")
    # the south camera sees the occluder in front of x 1.6..5 m, z < 2.6 m of the south wall; the south-west
    # camera sees x < 4.3 m there
    xyz = p.grid.centres(p.rows, p.cols) - OFFSET
    behind = (xyz[:, 0] > 2.0) & (xyz[:, 0] < 4.0) & (xyz[:, 2] < 2.2) & p.in_ring
    assert behind.sum() > 1000
    assert np.all(p.weights[k_south, behind] == 0)
    assert np.all(p.weights[k_sw, behind] > 0.99)
    assert p.weights[k_south, ~behind & p.in_ring].mean() > 0.5  # the best view elsewhere
    col = p.colours(gains)[behind]
    # never the occluder's green: the pattern's green channel stays below 150 before the gains
    assert np.percentile(np.abs(col - GREEN * 1.0).sum(1), 1) > 60
    # the radiometric adjustment sees the 1.25 exposure ratio of the two images
    assert abs(gains["south"][1] / gains["southwest"][1] - 1.25) < 0.05


def test_stored_texel_rebuilds_every_rect(textured):
    """The texel size stored for a surface rebuilds its texel grid at exactly the atlas rect's size (the windows
    stage reads the facades back that way; a rounded texel flips ceil() at a grid boundary)."""
    _, _, records, _, _, _ = textured
    rings = {s.id: b.vertices[list(s.ring)] for b in buildings() for s in b.surfaces}
    for sid, rec in records.items():
        assert texel_grid(rings[sid], rec["texel"]).shape == (rec["rect"][3], rec["rect"][2]), sid


def test_texels_no_image_sees_are_marked_in_the_seen_mask(textured):
    """x 4.3..5 m, z < 2.5 m of the south wall is hidden from both cameras that face it: the seen mask is 0 there,
    255 on the texels an image gave."""
    patches, pages, records, _, gains, seen = textured
    p, rec = patches["B0001_wall_1"], records["B0001_wall_1"]
    has = p.weights.sum(0) > 0
    hole = p.in_ring & ~has
    assert hole.sum() > 100
    mask = seen[rec["page"]]
    r, c = rec["rect"][1] + p.rows, rec["rect"][0] + p.cols
    assert np.all(mask[r[has], c[has]] == 255) and np.all(mask[r[hole], c[hole]] == 0)


def test_unseen_band_under_an_eave_takes_the_local_wall_colour():
    """A 12 x 8 m wall at 0.2 m texels, shaded darker towards its top, with rows of dark 1.2 x 1.5 m windows; no
    image saw the top 1 m, which cuts the top row's windows. The fill is the wall's colour at that height (within
    12 DN), where the nearest seen colour would carry the glass up to the roof."""
    texel, h, w = 0.2, 40, 60
    rows, cols = np.mgrid[0:h, 0:w]
    z = 8.0 - (rows + 0.5) * texel
    wall = np.stack([200 - 6 * (8 - z)] * 3, -1)  # 200 DN at the top, 152 at the bottom
    x = (cols + 0.5) * texel
    glass = ((x % 3.0) > 0.9) & ((x % 3.0) < 2.1) & (((z - 0.5) % 3.0) < 1.5)
    img = np.where(glass[..., None], 50.0, wall).astype(np.float32)
    has = z < 7.0
    assert (glass & ~has).any()  # the top row is cut
    got = hole_colours(img.reshape(-1, 3), has.ravel(), rows.ravel(), cols.ravel(), texel).reshape(h, w, 3)
    band = ~has
    assert np.all(np.abs(got[band] - wall[band]) < 12)
    nearest = fill_empty(np.where(has[..., None], img, 0), has)
    assert np.abs(nearest[band] - wall[band]).max() > 100
