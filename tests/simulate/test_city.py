"""The synthetic city meets the issue's list and its ground truth agrees with its own mesh."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from oblique_city.core.simulate.city import SEMANTIC, WINDOW_RECESS, City, make_city
from oblique_city.core.simulate.geometry2d import polygon_area, rect_union_outline


def _reflex(ring: np.ndarray) -> np.ndarray:
    """Indices of reflex (concave) vertices of a counter-clockwise ring."""
    a, b, c = np.roll(ring, 1, 0), ring, np.roll(ring, -1, 0)
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - b[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - b[:, 0])
    return np.flatnonzero(cross < 0)


def test_issue_checklist(city):
    bs = city.buildings
    assert len(bs) >= 12
    roofs = {p.roof for b in bs for p in b.parts if p.kind in ("body", "tower")}
    assert {"flat", "gable", "hip", "shed"} <= roofs
    mixed = [b for b in bs if len({p.roof for p in b.parts if p.kind == "body"}) >= 2]
    assert len(mixed) >= 2
    shapes = {}
    for b in bs:
        assert len(b.footprint) == 1, b.name  # one outer ring, no holes
        ring = b.footprint[0]
        assert polygon_area(ring) > 0  # counter-clockwise
        r = _reflex(ring)
        n = len(ring)
        if n == 4:
            shapes.setdefault("rect", []).append(b.name)
        elif n == 6 and len(r) == 1:
            shapes.setdefault("L", []).append(b.name)
        elif n == 8 and len(r) == 2:
            adjacent = (r[1] - r[0]) % n in (1, n - 1)
            shapes.setdefault("U" if adjacent else "T", []).append(b.name)
    assert {"rect", "L", "T", "U"} <= set(shapes), shapes
    # discontinuities: parts of one building with different eaves; a tower; stepped flat roofs
    assert any(len({round(p.eave, 2) for p in b.parts if p.kind == "body"}) >= 2 for b in bs)
    assert any(p.kind == "tower" for b in bs for p in b.parts)
    assert any(sum(p.roof == "flat" for p in b.parts) >= 3 for b in bs)
    kinds = [p.kind for b in bs for p in b.parts]
    assert kinds.count("dormer") >= 3 and kinds.count("chimney") >= 3
    # overhangs on exposed walls span 0.2-1.2 m
    widths = np.array([e["width"] for b in bs for e in b.overhang_edges() if e["exposed"]])
    assert widths.min() >= 0.2 - 1e-9 and widths.max() <= 1.2 + 1e-9
    assert widths.min() <= 0.25 and widths.max() >= 1.15
    assert sum(len(b.windows) for b in bs) > 300
    for code in SEMANTIC.values():
        assert np.any(city.semantic == code)


def test_buildings_are_closed(city):
    for b in city.buildings:
        v, t = city.part_mesh(b.id)
        m = trimesh.Trimesh(v, t, process=False)
        assert m.is_watertight and m.is_winding_consistent, b.name
        assert m.volume > 0, b.name  # outward normals


def test_rect_union_outline():
    rings = rect_union_outline([(0, 0, 10, 5), (6, -8, 10, 0.5)])
    assert len(rings) == 1 and abs(polygon_area(rings[0]) - 82.0) < 1e-12


def test_deterministic_from_seed(city):
    again = make_city(0)
    assert np.array_equal(again.vertices, city.vertices) and np.array_equal(again.triangles, city.triangles)
    assert np.array_equal(again.material, city.material)
    other = make_city(1)
    assert other.vertices.shape != city.vertices.shape or not np.array_equal(other.vertices, city.vertices)


def test_roof_planes_and_windows_match_the_mesh(city):
    for b in city.buildings:
        for p in b.roof_planes:
            assert np.abs(p["polygon"] @ p["normal"] - p["d"]).max() < 1e-6
            assert abs(np.linalg.norm(p["normal"]) - 1) < 1e-12 and p["normal"][2] > 0
    # a ray towards each window's centre from 0.5 m in front of the facade hits a window triangle at the recess
    wins = city.all_windows()
    centre = np.array([w["corners"].mean(0) for w in wins])
    normal = np.array([w["normal"] for w in wins])
    org = centre + 0.5 * normal - city.origin
    rays = np.column_stack([org, -normal]).astype(np.float32)
    r = city.scene().cast_rays(o3d.core.Tensor(rays))
    ids = r["primitive_ids"].numpy().astype(np.int64)
    t = r["t_hit"].numpy()
    assert np.all(city.semantic[ids] == SEMANTIC["window"])
    assert np.all(city.building[ids] == np.array([w["building"] for w in wins]))
    np.testing.assert_allclose(t, 0.5 + WINDOW_RECESS, atol=2e-4)


def test_terrain_function_is_the_mesh(city):
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(city.extent[0] + 1, city.extent[2] - 1, 4000),
                          rng.uniform(city.extent[1] + 1, city.extent[3] - 1, 4000)])
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2] = xy - city.origin[:2]
    rays[:, 2], rays[:, 5] = 1000.0, -1.0
    r = city.scene().cast_rays(o3d.core.Tensor(rays))
    ids = r["primitive_ids"].numpy().astype(np.int64)
    ground = city.semantic[ids] <= SEMANTIC["street"]
    z_mesh = 1000.0 - r["t_hit"].numpy()[ground]
    assert ground.mean() > 0.8
    np.testing.assert_allclose(z_mesh, city.terrain_z(xy[ground]), atol=2e-4)  # float32 casting


def test_save_load_roundtrip(city, tmp_path):
    city.save(tmp_path)
    c2 = City.load(tmp_path)
    assert np.array_equal(c2.vertices, city.vertices) and np.array_equal(c2.semantic, city.semantic)
    assert len(c2.buildings) == len(city.buildings)
    b, b2 = city.buildings[4], c2.buildings[4]
    assert b.parts[1].rect == b2.parts[1].rect and b.parts[0].windows == b2.parts[0].windows
    np.testing.assert_array_equal(b.footprint[0], b2.footprint[0])
    np.testing.assert_allclose(c2.terrain_z(city.targets[:, :2]), city.targets[:, 2])
    head = (tmp_path / "city.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "property int semantic" in head and f"element face {len(city.triangles)}" in head


def test_tiled_city_is_cheap_and_larger():
    big = make_city(3, tiles=(2, 1), ground_cell=6.0)
    assert len(big.buildings) == 30
    assert big.core[2] - big.core[0] > 380 and big.core[3] - big.core[1] > 140
    # the second tile is a different arrangement of the same 15 recipes
    first = [b.name for b in big.buildings[:15]]
    assert sorted(first) == sorted(b.name for b in big.buildings[15:]) and first != [b.name for b in big.buildings[15:]]
    names = {b.name for b in big.buildings}
    assert len(names) == 15
