"""Whole buildings: paths, closed solids, volumes, overhangs, the model file, detection and the stage."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.buildings.contour import wall_depth
from oblique_city.core.buildings.dormers import DormerConfig
from oblique_city.core.buildings.geometry import distance_to_edges
from oblique_city.core.buildings.model import load_buildings, save_buildings
from oblique_city.core.buildings.reconstruct import ReconstructionConfig, reconstruct_building, solid_check
from oblique_city.core.buildings.synthetic import Part, SyntheticBuilding, parametric_buildings
from oblique_city.core.errors import InputError
from oblique_city.core.evaluate.buildings import BuildingTruth, roof_height_errors, score_building


def _volume(b) -> float:
    """True volume of a synthetic building (parts do not overlap in the volume cases used here)."""
    v = 0.0
    for p in b.parts:
        area = (p.u1 - p.u0) * (p.v1 - p.v0)
        v += area * p.eave + (area * (p.ridge - p.eave) / 2 if p.roof.startswith("gable") else 0.0)
    return v


@pytest.fixture(scope="module")
def models(synthetic):
    return {name: reconstruct_building(xyz, 0.0, dsm, f"B{i:04d}")
            for i, (name, (b, xyz, dsm, _)) in enumerate(synthetic.items())}


@pytest.mark.parametrize("name,path", [("gabled", "2d"), ("hipped", "2d"), ("flat", "2d"),
                                       ("twopart", "volumetric"), ("stepped_flat", "volumetric")])
def test_path_and_closed_solid(models, synthetic, name, path):
    m = models[name]
    assert m.path == path, m.reason
    assert m.info["closed"], m.info["solid_problem"]
    body = [list(s.ring) for s in m.surfaces if s.in_solid]
    ok, vol, _ = solid_check(m.vertices, body)
    assert ok
    b = synthetic[name][0]
    if name != "hipped":
        assert vol == pytest.approx(_volume(b), rel=0.03)


def test_volumetric_fallback_on_stepped_building_gives_the_step(models):
    m = models["stepped_flat"]
    roofs = [m.vertices[list(s.ring), 2].mean() for s in m.surfaces if s.kind == "roof"]
    assert sorted(np.round(roofs, 0)) == [5.0, 10.0]
    walls = [s for s in m.surfaces if s.kind == "wall"]
    assert len(walls) >= 5  # four outer walls and the step wall between the two roofs


def test_scores_against_truth(models, synthetic):
    for name in ("gabled", "hipped", "lshape"):
        s = score_building(BuildingTruth.from_synthetic(synthetic[name][0]), models[name])
        assert s.corner_median < 0.1 and s.normal_median_deg < 1.0
        assert max(s.overhang_errors) <= 0.2
        assert s.roof_rmse < 0.05 and s.roof_coverage == 1.0  # the top surface to the 4 cm noise


def test_wall_direction_error_of_a_turned_outline():
    # an L turned by 1.5 degrees about its corner: each edge of at least 3 m is 1.5 degrees off its true edge; the
    # 2 m ones are left out
    from oblique_city.core.evaluate.buildings import wall_direction_errors

    ring = np.array([[0, 0], [12, 0], [12, 2], [2, 2], [2, 10], [0, 10.0]])
    a = np.radians(1.5)
    turned = ring @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    err, length = wall_direction_errors([ring], turned)
    assert np.allclose(err, 1.5) and np.allclose(sorted(length), [8, 10, 10, 12])


def test_roof_height_error_sees_a_raised_roof_and_a_missing_one(models, synthetic):
    truth = BuildingTruth.from_synthetic(synthetic["stepped_flat"][0])
    m = models["stepped_flat"]
    e0 = roof_height_errors(truth, m)
    raised = replace(m, vertices=m.vertices + np.array([0.0, 0.0, 0.5]))
    assert np.sqrt(np.nanmean((roof_height_errors(truth, raised) - e0 - 0.5) ** 2)) < 1e-9
    low = max((s for s in m.surfaces if s.kind == "roof"), key=lambda s: -m.vertices[list(s.ring), 2].mean())
    gone = replace(m, surfaces=[s for s in m.surfaces if s is not low])
    share = np.isnan(roof_height_errors(truth, gone)).mean()
    assert 0.2 < share < 0.8  # the lower roof's part of the footprint has no roof over it


def test_samples_near_steps_are_found_and_roof_slopes_are_not():
    """A 0.5 m grid over a flat roof at 5 m and one at 10 m beside it (a step at x = 10) and a 65 degree slope (a
    tower's spire): only the samples within 0.75 m of the step are near it; the roof RMSE off steps leaves them
    out."""
    from oblique_city.core.evaluate.buildings import near_steps

    X, Y = np.meshgrid(np.arange(0.25, 20.0, 0.5), np.arange(0.25, 6.0, 0.5))
    xy = np.column_stack([X.ravel(), Y.ravel()])
    flat = np.column_stack([xy, np.where(xy[:, 0] < 10.0, 5.0, 10.0)])
    near = near_steps(flat)
    assert np.array_equal(near, np.abs(xy[:, 0] - 10.0) < 0.75)
    slope = np.column_stack([xy, 20.0 + np.tan(np.radians(65.0)) * xy[:, 0]])
    assert not near_steps(slope).any()


def test_upper_roof_overhangs_the_lower_one_at_a_step():
    """A 10 m flat part beside a 5 m one, each with a 0.4 m overhang: the upper roof reaches 0.4 m over the lower one
    past the step wall (an overhang slab, as at the outline), measured in the DSM like the outline's; the top
    surface then matches the truth's to the noise, overhang band included (but for samples on its very edge)."""
    from oblique_city.core.buildings.attributes import model_top_height
    from oblique_city.core.buildings.synthetic import Part, SyntheticBuilding

    b = SyntheticBuilding("overhang_step", (Part(0, 0, 9, 10, 10, 10, "flat", 0.4),
                                            Part(9, 0, 18, 10, 5, 5, "flat", 0.4)),
                          ((0, 0), (18, 0), (18, 10), (0, 10)), (0.4,) * 4, origin=(60.0, 170.0), angle_deg=25.0,
                          stepped=True)
    rng = np.random.default_rng(7)
    xyz = b.sample(25.0, 0.04, rng)
    dsm, _ = b.dsm(0.1, 0.03, rng)
    m = reconstruct_building(xyz, 0.0, dsm, "B0001")
    assert m.path == "volumetric" and m.info["closed"]
    v = np.linspace(0.5, 9.5, 10)
    under = model_top_height(m, b.to_world(np.column_stack([np.full(10, 9.25), v])))
    beyond = model_top_height(m, b.to_world(np.column_stack([np.full(10, 9.6), v])))
    assert np.all(np.abs(under - 10.0) < 0.1) and np.all(np.abs(beyond - 5.0) < 0.1)
    truth = BuildingTruth.from_synthetic(b)
    s = score_building(truth, m)
    assert s.roof_coverage == 1.0
    # the top surface away from the overhang's edge (a sample on the edge itself is 5 m off for 1 cm)
    far = np.abs(b.to_local(truth.top[:, :2])[:, 0] - 9.4) > 0.05
    assert np.sqrt(np.mean(roof_height_errors(truth, m)[far] ** 2)) < 0.05


def test_overhang_surfaces_and_semantics(models):
    m = models["gabled"]
    kinds = {s.kind for s in m.surfaces}
    assert {"ground", "wall", "roof", "overhang_roof", "overhang_fascia", "overhang_underside"} <= kinds
    assert all(not s.in_solid for s in m.surfaces if s.kind.startswith("overhang"))
    under = [s for s in m.surfaces if s.kind == "overhang_underside"]
    for s in under:  # underside faces down
        p = m.vertices[list(s.ring)]
        c = p - p.mean(0)
        assert np.cross(c, np.roll(c, -1, 0)).sum(0)[2] < 0
    ids = [s.id for s in m.surfaces]
    assert len(set(ids)) == len(ids)


def test_model_file_round_trip_and_errors(models, tmp_path):
    path = tmp_path / "buildings.json"
    save_buildings(path, list(models.values()), "EPSG:25832")
    back, crs = load_buildings(path)
    assert crs == "EPSG:25832" and [b.id for b in back] == [m.id for m in models.values()]
    assert np.array_equal(back[0].vertices, models["gabled"].vertices)
    assert [s.ring for s in back[0].surfaces] == [s.ring for s in models["gabled"].surfaces]
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "oblique-city-buildings", "buildings": [{"id": "X"}]}')
    with pytest.raises(InputError, match="bad.json"):
        load_buildings(bad)


def test_triangulation_covers_every_polygon(models):
    """The triangles (for Blender and mesh checks) cover each ring exactly: equal areas, no flipped triangle."""
    m = models["lshape"]
    V, T, kinds = m.triangles()
    assert len(T) == len(kinds)
    tri_area = 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1).sum()
    ring_area = 0.0
    for s in m.surfaces:
        p = m.vertices[list(s.ring)]
        c = p - p.mean(0)
        ring_area += 0.5 * np.linalg.norm(np.cross(c, np.roll(c, -1, axis=0)).sum(0))
    assert tri_area == pytest.approx(ring_area, rel=1e-9)
    _, Ts, _ = m.triangles(in_solid_only=True)
    ok, _, why = solid_check(V, [list(t) for t in Ts])
    assert ok, why


def _house_with_dormer(dormer: bool, overhang: float = 0.0, seed: int = 11) -> tuple:
    """A 14 x 10 m gabled house (eaves 4 m, ridge 9.5 m: 48 deg) with, on its south slope, a 2.2 m wide gabled
    dormer whose front stands 1 m inside the eaves (its eaves 6 m, ridge 7.1 m: 0.9 m of wall above the slope), its
    roof ``overhang`` beyond its walls, sampled at 25 points per m^2 with 4 cm noise (the walls too), and its DSM."""
    from oblique_city.core.buildings.synthetic import Part, SyntheticBuilding

    parts = (Part(0, 0, 14, 10, 4.0, 9.5, "gable_u", 0.5),)
    if dormer:
        parts += (Part(4.0, 1.0, 6.2, 4.5, 6.0, 7.1, "gable_v", overhang),)
    b = SyntheticBuilding("dormer", parts, ((0, 0), (14, 0), (14, 10), (0, 10)), (0.5,) * 4, origin=(310.0, 95.0),
                          angle_deg=-20.0)
    rng = np.random.default_rng(seed)
    return b, b.sample(25.0, 0.04, rng), b.dsm(0.1, 0.03, rng)[0]


def test_a_dormer_becomes_part_of_the_solid_and_the_plain_slope_gets_none():
    """The dormer's block is found on the slope and joined to the body (one closed solid, the body's roof and the
    dormer's faces sharing edges); along its centre line the model's top matches the truth's to 0.1 m RMS, and
    over it to 0.15 m, where the slope alone misses it by more than 0.5 m. The same house without a dormer gets
    none, and a block across its ridge is not taken for one."""
    from oblique_city.core.buildings.attributes import model_top_height

    b, xyz, dsm = _house_with_dormer(True)
    m = reconstruct_building(xyz, 0.0, dsm, "B0001")
    assert m.path == "2d" and m.info["closed"] and m.info["dormers"] == ["gabled"]
    # roofs: the north slope, the south one in two pieces around the dormer (a polygon cannot have a hole), and
    # the dormer's two; walls: the four outer ones, the dormer's front and two sides
    kinds = [s.kind for s in m.surfaces]
    assert kinds.count("roof") == 5 and kinds.count("wall") == 7
    # along the dormer's centre line, from behind its ridge's end to in front of its front wall
    v = np.arange(0.3, 3.6, 0.1)
    line = b.to_world(np.column_stack([np.full(len(v), 5.1), v]))
    err = model_top_height(m, line) - b.height(line)
    assert np.sqrt(np.mean(err[np.abs(v - 1.0) > 0.15] ** 2)) < 0.1  # away from the front wall's own step
    truth = BuildingTruth.from_synthetic(b)
    s = score_building(truth, m)
    assert s.roof_rmse < 0.1 and s.roof_coverage == 1.0
    # over the dormer (inside its walls, in front of where its ridge meets the slope): the model against the
    # truth's top surface, with the dormer and without it (the slope runs under it, up to 1.7 m too low)
    uv = b.to_local(truth.top[:, :2])
    over = (uv[:, 0] > 4.2) & (uv[:, 0] < 6.0) & (uv[:, 1] > 1.2) & (uv[:, 1] < 2.6)
    plain = reconstruct_building(xyz, 0.0, dsm, "B0002", replace(ReconstructionConfig(),
                                                                 dormers=DormerConfig(enabled=False)))
    assert over.sum() >= 8
    assert np.sqrt(np.mean(roof_height_errors(truth, m)[over] ** 2)) < 0.15
    assert np.sqrt(np.mean(roof_height_errors(truth, plain)[over] ** 2)) > 0.5
    b0, xyz0, dsm0 = _house_with_dormer(False)
    m0 = reconstruct_building(xyz0, 0.0, dsm0, "B0003")
    assert m0.info["dormers"] == [] and m0.info["closed"]
    # a 3 x 3 m flat-topped block across the ridge (a lantern) stands on both slopes: no dormer, said why
    from oblique_city.core.buildings.synthetic import Part, SyntheticBuilding

    lantern = SyntheticBuilding("lantern", (b0.parts[0], Part(5.0, 3.5, 8.0, 6.5, 10.5, 10.5, "flat", 0.0)),
                                b0.footprint_local, b0.overhang_local, origin=b0.origin, angle_deg=b0.angle_deg)
    rng = np.random.default_rng(11)
    m1 = reconstruct_building(lantern.sample(25.0, 0.04, rng), 0.0, lantern.dsm(0.1, 0.03, rng)[0], "B0004")
    assert m1.info["dormers"] == [] and m1.info["closed"]
    assert any("more than one roof plane" in r for r in m1.info["dormer_candidates_rejected"])



def test_a_gabled_dormer_shifted_by_the_smear_beside_it_is_centred_on_its_ridge():
    """The dormer house of the test above as a dense cloud sees it: beside the dormer's west side the slope's points
    lifted onto the dormer's roof carried on, 0.6 m wide (the matching's smear), and the last 0.4 m of its roof
    before the east side unseen. The sides fitted to the points both move west, and the west eave, taken on the
    dormer's roof carried on, came out 0.31 m above the slope: the dormer was refused. Its two slopes place its
    ridge (u = 5.1 m); the sides, as far apart as found and centred on it, come within 0.35 m of the true ones (u 4.0
    and 6.2 m) and the dormer is kept."""
    from oblique_city.core.buildings.attributes import model_top_height

    b, xyz, dsm = _house_with_dormer(True)
    body, dormer = b.parts
    uv = b.to_local(xyz[:, :2])
    slope = body.roof_z(uv[:, 0], uv[:, 1])
    west = (np.abs(xyz[:, 2] - slope) < 0.2) & (uv[:, 0] > 3.4) & (uv[:, 0] < 4.0) & (uv[:, 1] > 1.0) & (uv[:, 1] < 2.6)
    x = xyz.copy()
    x[west, 2] = np.maximum(slope[west], dormer.roof_z(uv[west, 0], uv[west, 1]))
    east = (uv[:, 0] > 5.8) & (uv[:, 0] < 6.2) & (uv[:, 1] > 1.0) & (uv[:, 1] < 4.5) & (xyz[:, 2] > slope + 0.2)
    m = reconstruct_building(x[~east], 0.0, dsm, "B0001")
    assert m.info["dormers"] == ["gabled"] and m.info["closed"]
    u = np.arange(3.0, 7.2, 0.02)
    line = b.to_world(np.column_stack([u, np.full(len(u), 1.3)]))  # across it, 0.3 m behind its front
    on = u[model_top_height(m, line) - body.roof_z(u, np.full(len(u), 1.3)) > 0.15]
    assert abs(on.min() - 4.0) < 0.35 and abs(on.max() - 6.2) < 0.35
    assert abs(0.5 * (on.min() + on.max()) - 5.1) < 0.05


def test_a_dormer_roof_overhanging_its_front_wall_ends_where_the_roof_does():
    """The dormer house with the dormer's roof 0.15 or 0.3 m beyond its walls, its walls' points standing under the
    eaves: along the dormer's centre line the model's top rises over the slope within 0.06 m of where the true roof
    does, on three samplings each. Those points, from the slope's height up to the eaves', are no roof edge: taken
    with the roof's points they drew the front 0.07-0.15 m behind the roof's edge on three of the six (to the wall,
    or behind it). The points under the top surface are left out where they form a wall (a compact column across
    the edge; the matching's smear is a ramp and stays, see the test above). The dormer's front wall stands on
    those points, within 0.05 m of the true wall, and its roof overhangs it (the block's front stood at the roof's
    edge before, 0.10-0.33 m in front of the wall)."""
    from oblique_city.core.buildings.attributes import model_top_height

    def front_walls(b, m) -> list[float]:  # v of the model's walls facing the dormer's front, in front of the slope
        out = []
        for s in m.surfaces:
            uv = b.to_local(np.asarray(m.vertices)[list(s.ring), :2])
            if s.kind == "wall" and np.ptp(uv[:, 1]) < 0.02 and 3.5 < uv[:, 0].mean() < 6.7 and 0.3 < uv[:, 1].mean():
                out.append(float(uv[:, 1].mean()))
        return out

    v = np.arange(0.3, 1.8, 0.01)
    for overhang in (0.15, 0.3):
        for seed in (11, 12, 13):
            b, xyz, dsm = _house_with_dormer(True, overhang, seed)
            m = reconstruct_building(xyz, 0.0, dsm, f"B{seed}")
            assert m.info["dormers"] == ["gabled"] and m.info["closed"]
            line = b.to_world(np.column_stack([np.full(len(v), 5.1), v]))
            slope = b.parts[0].roof_z(np.full(len(v), 5.1), v) + b.ground
            front_model = v[np.argmax(model_top_height(m, line) - slope > 0.5)]
            front_true = v[np.argmax(b.height(line) - slope > 0.5)]
            assert abs(front_true - (1.0 - overhang)) < 0.02
            assert abs(front_model - front_true) < 0.06, (overhang, seed, front_model, front_true)
            walls = front_walls(b, m)
            assert len(walls) == 1 and abs(walls[0] - 1.0) < 0.05, walls
            assert sum(s.kind == "overhang_roof" for s in m.surfaces) == 10  # 8 at the outline, 2 over the front


def test_points_under_the_top_surface_and_a_wall_among_them():
    """``on_top``: the points of a wall under an eave lie under the top surface, the roof's and the slope's away
    from it on it. ``_wall_span``: a facade's points across its edge (4 cm noise) form a wall, their quartiles about
    its line; a ramp of the matching's smear 0.8 m wide does not, nor do a few points."""
    from oblique_city.core.buildings.dormers import _wall_span, on_top

    rng = np.random.default_rng(3)
    roof = np.column_stack([rng.uniform(-2.0, 0.0, 400), rng.uniform(0.0, 2.0, 400), np.full(400, 2.0)])
    slope = np.column_stack([rng.uniform(0.0, 2.0, 400), rng.uniform(0.0, 2.0, 400), np.zeros(400)])
    wall = np.column_stack([np.zeros(100), rng.uniform(0.0, 2.0, 100), rng.uniform(0.2, 1.4, 100)])
    xyz = np.vstack([roof, slope, wall])
    top = on_top(xyz[:, :2], xyz[:, 2], 0.25, 0.5)
    assert not top[800:].any()
    assert top[:400][roof[:, 0] < -0.3].all() and top[400:800][slope[:, 0] > 0.3].all()
    cfg = DormerConfig()
    span = _wall_span(rng.normal(1.0, 0.04, 40), cfg)
    assert span is not None and span[0] < 1.0 < span[1] and span[1] - span[0] < 0.1
    assert _wall_span(rng.uniform(0.6, 1.4, 40), cfg) is None
    assert _wall_span(rng.normal(1.0, 0.04, cfg.wall_min_points - 1), cfg) is None


def test_a_layer_parallel_to_the_slope_is_no_shed_dormer():
    """On the plain house, the roof points of a 2.5 m x 3.5 m patch of the south slope lifted by a wedge (0.6 m at
    its front, 1 m inside the eaves, down to nothing at its back: the matching's smear beside a dormer) fit one roof
    plane 4 deg flatter than the 48-degree slope. That is no shed dormer (``min_shed_drop_deg`` 10; the old bound,
    0.05 in height per metre, let it through) and the reason is said. Lifted instead into a 15-degree shed roof
    1.4 m above the slope at its front, the same patch is a shed dormer."""
    b, xyz, dsm = _house_with_dormer(False)
    part = b.parts[0]
    uv = b.to_local(xyz[:, :2])
    slope = part.roof_z(uv[:, 0], uv[:, 1])
    patch = ((np.abs(xyz[:, 2] - slope) < 0.2) & (uv[:, 0] > 4.0) & (uv[:, 0] < 6.5) & (uv[:, 1] > 1.0)
             & (uv[:, 1] < 4.5))
    wedge = 0.6 * (4.5 - uv[:, 1]) / 3.5
    shed = np.maximum(part.roof_z(uv[:, 0], np.ones(len(uv))) + 1.4 + np.tan(np.radians(15)) * (uv[:, 1] - 1.0)
                      - slope, 0.0)
    found = {}
    for name, lift in (("wedge", wedge), ("shed", shed)):
        x = xyz.copy()
        x[patch, 2] += lift[patch]
        found[name] = reconstruct_building(x, 0.0, dsm, name)
    assert found["wedge"].info["dormers"] == [] and found["wedge"].info["closed"]
    assert any("of the slope's pitch" in r for r in found["wedge"].info["dormer_candidates_rejected"])
    assert found["shed"].info["dormers"] == ["shed"] and found["shed"].info["closed"]


def test_the_demo_dormer_house_slope_lifted_by_a_dormer_stays_one_plane():
    """The demo's gable_dormers house from the project's own dense cloud with its DTM (``tests/data/
    gable_dormers_dense_dtm.npz``: the points the buildings benchmark gave B0001 from the demo workspace's dense
    cloud, float32 about an offset, and the DTM window under them). Region growing labels the west slope in two
    parts; the northern one, holding a dormer and the matching's smear beside it, got a plane 0.38 m above the
    truth, and the topology check called the 0.49 m between the planes a step: the model went volumetric without
    its dormers, 0.38 m RMS off the true roof. The northern part's points lie closer to the southern part's plane
    than to their own, so the slope is one plane: the 2D model with the three dormers, within 0.2 m RMS of the
    truth's roof (the matching rounds the dormers)."""
    from pathlib import Path

    from oblique_city.core.model import Raster
    from oblique_city.core.simulate.city import make_city

    d = np.load(Path(__file__).parents[1] / "data" / "gable_dormers_dense_dtm.npz")
    gz = float(d["ground_z"])
    xyz = np.column_stack([d["xyz"][:, :2] + d["offset"], d["xyz"][:, 2] + gz]).astype(np.float64)
    dtm = Raster(d["dtm"], float(d["dtm_x0"]), float(d["dtm_y0"]), float(d["dtm_cell"]), "EPSG:25832")
    m = reconstruct_building(xyz, gz, None, "B0001", dtm=dtm)
    assert m.path == "2d" and m.info["closed"] and m.info["dormers"] == ["gabled"] * 3
    assert m.reason == "topology and plane intersections agree"
    truth = next(BuildingTruth.from_city(b) for b in make_city(0).buildings if b.name == "gable_dormers")
    s = score_building(truth, m)
    assert s.roof_rmse < 0.2 and s.corner_median < 0.1


def test_a_spurious_step_on_a_dormer_house_keeps_the_2d_model_and_its_dormers():
    """The demo's gable_dormers house from the project's own dense cloud (``tests/data/gable_dormers_dense.npz``:
    the stage's points of B0001 at ae417dd, float32 about an offset). A 11.5 m^2 patch of its west slope, 0.34 m
    below it at the south gable end, is labelled apart and the topology check calls it a step. The 2D hull with
    the three dormers fits the roof points better than the volumetric hull by more than half the noise level and
    is kept, with the reason said; forced volumetric, the model loses the dormers and fits worse. The patch comes
    with the outline of the fragments' own direction; squared to the facade points' direction (the default) the
    topology agrees and the 2D model with its dormers is taken at once."""
    from pathlib import Path

    from oblique_city.core.buildings.contour import ContourConfig

    d = np.load(Path(__file__).parents[1] / "data" / "gable_dormers_dense.npz")
    gz = float(d["ground_z"])
    xyz = np.column_stack([d["xyz"][:, :2] + d["offset"], d["xyz"][:, 2] + gz]).astype(np.float64)
    cfg = replace(ReconstructionConfig(), contour=replace(ContourConfig(), facade_direction=False))
    m = reconstruct_building(xyz, gz, None, "B0001", cfg)
    assert "height discontinuity" in m.reason and "fits the roof points better" in m.reason
    assert m.path == "2d" and m.info["closed"] and m.info["dormers"] == ["gabled"] * 3
    assert m.info["roof_fit_2d"] < m.info["roof_fit_volumetric"] - 0.5 * m.info["noise"]
    forced = reconstruct_building(xyz, gz, None, "B0002", replace(cfg, force_path="volumetric"))
    assert forced.path == "volumetric" and forced.info.get("dormers", []) == []
    default = reconstruct_building(xyz, gz, None, "B0003")
    assert default.reason == "topology and plane intersections agree"
    assert default.path == "2d" and default.info["closed"] and default.info["dormers"] == ["gabled"] * 3


def test_tree_crowns_are_refused_and_buildings_fit_their_roof_points(models):
    """Tree crowns of the simulator's city (seed 2) that the roughness test let through as one blob in case (a) of the
    benchmark (``tests/data/tree_crowns_sampled.npz``: every second point of B0001, float32 about an offset): the model
    the reconstruction gets misses the crowns by 1 m on average (each miss capped at 1 m; the demo's buildings miss
    their roof points by 0.07-0.26 m) and is refused with the reason, without a volumetric model tried for the miss
    (voxels follow the crowns: 0.43 m); with the gate off it is kept. The parametric buildings (4 cm noise) miss theirs
    by 0.11-0.18 m: the roof points include the top metre of the walls inside the outline."""
    from pathlib import Path

    d = np.load(Path(__file__).parents[1] / "data" / "tree_crowns_sampled.npz")
    gz = float(d["ground_z"])
    xyz = np.column_stack([d["xyz"][:, :2] + d["offset"], d["xyz"][:, 2] + gz]).astype(np.float64)
    with pytest.raises(ValueError, match="not a building"):
        reconstruct_building(xyz, gz, None, "B0001")
    kept = reconstruct_building(xyz, gz, None, "B0001", ReconstructionConfig(max_roof_fit=0.0))
    assert kept.info["roof_fit_2d"] > 0.9
    for m in models.values():
        assert m.info["roof_fit"] < 0.2


def test_a_tower_its_nave_planes_absorb_is_built_volumetrically():
    """The church of the simulated city of seed 5 from the project's own dense cloud
    (``tests/data/church_tower_seed5_dense.npz``: the stage's points of B0006 at 63157ef, millimetres about an offset).
    Its tower's steep pyramid (65 degree faces; eaves 22 m and peak 28.4 m above the ground in the simulator) gives no
    roof plane of its own: its cells join the nave's two slopes and the topology agrees with them. That 2D model
    leaves the tower 8 m too low and misses the roof points by over 3 times their noise; the volumetric model fits
    them better by more than a quarter of the noise and is taken, said why: over the tower's roof points it lies
    within 0.3 m of them (median) and its top within 1 m of the true peak. With the rule off the 2D model is kept.
    That is on the roof outline the rule was measured on (the coverage test's margin fixed at 1.2 m, as it was); on
    the facade ring the default margin now accepts, the topology already disagrees (a node 3.6 m off) and the
    volumetric model is as good."""
    from pathlib import Path

    from oblique_city.core.buildings.attributes import model_top_height

    d = np.load(Path(__file__).parents[1] / "data" / "church_tower_seed5_dense.npz")
    gz = float(d["ground_z"])
    xyz = np.column_stack([d["xyz_mm"][:, :2] / 1000.0 + d["offset"], d["xyz_mm"][:, 2] / 1000.0 + gz])
    tower = xyz[xyz[:, 2] > gz + 19.0]  # above the nave's ridge (15 m): the tower's top
    cfg = ReconstructionConfig()
    outline = replace(cfg, contour=replace(cfg.contour, cover_slack=-np.inf))
    for c in (cfg, outline):
        m = reconstruct_building(xyz, gz, None, "B0006", c)
        assert m.path == "volumetric" and m.info["closed"]
        assert abs(np.nanmedian(model_top_height(m, tower[:, :2]) - tower[:, 2])) < 0.3
        assert abs(m.vertices[:, 2].max() - gz - 28.4) < 1.0
    assert m.info["contour_source"].startswith("roof outline") and "misses its roof points" in m.reason
    noise = m.info["noise"]
    assert m.info["roof_fit_2d"] > 3.0 * noise
    assert m.info["roof_fit_volumetric"] < m.info["roof_fit_2d"] - 0.25 * noise
    kept = reconstruct_building(xyz, gz, None, "B0006", replace(outline, misfit_2d=0.0))
    assert kept.path == "2d" and kept.reason == "topology and plane intersections agree"
    assert np.nanmedian(model_top_height(kept, tower[:, :2]) - tower[:, 2]) < -5.0


def _outline_error(footprint: np.ndarray, truth: np.ndarray) -> float:
    """The largest distance from a corner of either outline to the other's edges (m): a corner sliding along a true
    wall, as the corners of a misplaced wall between two parallel ones do, is caught from the true corner."""
    return float(max(distance_to_edges(footprint, truth).max(), distance_to_edges(truth, footprint).max()))


@pytest.mark.parametrize("side", range(4))
def test_a_wall_no_facade_point_shows_stands_under_the_eaves_not_on_their_edge(side):
    # the gabled test house (0.6 m overhang) with one wall's points taken away: its facade ring closes over that
    # wall along the occupancy's edge, which the eaves make; before the wall was moved in by the eaves' reach beyond
    # the walls seen, it stood 0.63-0.91 m off the true outline (the eave line), now 0.01-0.36 m (two seeds)
    b = next(b for b in parametric_buildings() if b.name == "gabled")
    xyz = b.sample(25.0, 0.04, np.random.default_rng(7))
    uv, fp = b.to_local(xyz[:, :2]), b.to_local(b.footprint)
    lo, hi = fp.min(0), fp.max(0)
    across = [np.abs(uv[:, 1] - lo[1]), np.abs(uv[:, 0] - hi[0]), np.abs(uv[:, 1] - hi[1]), np.abs(uv[:, 0] - lo[0])]
    m = reconstruct_building(xyz[~((across[side] < 0.15) & (xyz[:, 2] > 0.2))], 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert m.info["walls_inferred"] == 1
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.45


@pytest.mark.parametrize("roof", ["flat", "gable"])
def test_a_courtyard_wall_no_facade_point_shows_is_moved_into_the_building(roof):
    # a U whose courtyard end wall shows no facade point: the ring closes it along the occupancy's edge, the eaves'
    # edge over the courtyard, and the wall lies on the building's side of it; moved the other way (along the
    # direction out of the building at a wing's end), it stood 0.86-0.93 m into the courtyard, now 0.11-0.18 m off
    ridge, wings, body = (8.0, "flat", "flat") if roof == "flat" else (11.0, "gable_v", "gable_u")
    b = SyntheticBuilding("u", (Part(0, 0, 6, 16, 8, ridge, wings, 0.6), Part(6, 10, 16, 16, 8, ridge, body, 0.6),
                                Part(16, 0, 22, 16, 8, ridge, wings, 0.6)),
                          ((0, 0), (6, 0), (6, 10), (16, 10), (16, 0), (22, 0), (22, 16), (0, 16)), (0.6,) * 8,
                          origin=(300.0, 100.0), angle_deg=12.0)
    xyz = b.sample(25.0, 0.04, np.random.default_rng(7))
    uv = b.to_local(xyz[:, :2])
    end_wall = (np.abs(uv[:, 1] - 10) < 0.15) & (uv[:, 0] > 6) & (uv[:, 0] < 16) & (xyz[:, 2] > 0.2)
    m = reconstruct_building(xyz[~end_wall], 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert m.info["walls_inferred"] == 1
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.4


def _raised_before_unseen_wall(name: str, width: float):
    """The parametric house ``name`` (seed 7) with its south wall's points taken away and the ground before that
    wall raised 1.1 m over ``width`` m: the building, its points ``(n, 3)`` and the raised band's test over local
    coordinates ``(m, 2) -> (m,) bool``."""
    b = next(b for b in parametric_buildings() if b.name == name)
    fp = b.to_local(b.footprint)
    lo, hi = fp.min(0), fp.max(0)
    xyz = b.sample(25.0, 0.04, np.random.default_rng(7))
    uv = b.to_local(xyz[:, :2])
    keep = ~((np.abs(uv[:, 1] - lo[1]) < 0.15) & (xyz[:, 2] > 0.2))
    xyz, uv = xyz[keep], uv[keep]

    def raised(uv: np.ndarray) -> np.ndarray:
        return ((uv[:, 1] < lo[1]) & (uv[:, 1] > lo[1] - width)
                & (np.abs(uv[:, 0] - fp[:, 0].mean()) < (hi[0] - lo[0]) / 2 - 0.5))

    xyz[(xyz[:, 2] < 0.2) & raised(uv), 2] += 1.1
    return b, xyz, raised


@pytest.mark.parametrize("name", ["gabled", "hipped"])
def test_an_unseen_wall_behind_raised_ground_is_not_put_on_the_ground(name):
    # the ground before a wall no facade point shows raised 1.1 m over 3 m (a sloping street above the building's
    # ground height): its cells enter the occupancy, and the wall closed along the occupancy's edge stood on the
    # raised ground's far side, 2.4-2.7 m out; the edge is now taken where the roof points end
    b, xyz, _ = _raised_before_unseen_wall(name, 3.0)
    m = reconstruct_building(xyz, 0.0, None, "B0001")
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.5


@pytest.mark.parametrize("name", ["gabled", "hipped"])
def test_an_unseen_wall_behind_raised_ground_under_its_eaves_stands_on_the_terrain(name):
    # the ground before a wall no facade point shows raised 1.1 m over 1.5 m, under the eaves: taken over one
    # ground height, the raised ground is facade points to the wall's placement and the wall stood 0.77-0.84 m
    # out; taken over the terrain (the DTM), 0.06-0.21 m
    from oblique_city.core.model.raster import Raster

    b, xyz, raised = _raised_before_unseen_wall(name, 1.5)
    x0, y0, cell = xyz[:, 0].min() - 5.0, xyz[:, 1].max() + 5.0, 0.25
    cols, rows = int((xyz[:, 0].max() + 5.0 - x0) / cell), int((y0 - xyz[:, 1].min() + 5.0) / cell)
    cx, cy = np.meshgrid(x0 + (np.arange(cols) + 0.5) * cell, y0 - (np.arange(rows) + 0.5) * cell)
    terrain = np.where(raised(b.to_local(np.column_stack([cx.ravel(), cy.ravel()]))), 1.1, 0.0).reshape(cx.shape)
    m = reconstruct_building(xyz, 0.0, None, "B0001", dtm=Raster(terrain, x0, y0, cell, "EPSG:32632"))
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.35


@pytest.mark.parametrize(("ramp", "n_wall"), [(1.0, 200), (1.5, 200), (1.5, 400)])
def test_a_wall_is_placed_below_its_level_eave_where_the_ground_rises_along_it(ramp, n_wall):
    # a wall 0.6 m inside its roof edge, the eave level at 3.6 m, the ground rising ``ramp`` m over the wall's first
    # 5 m; the roof points far outnumber the facade's, as in a dense cloud. With the eave taken as a height over the
    # terrain, the facade band's top rose with the ground above the eave at the uphill end, the roof's edge there
    # entered it, and the wall came out 0.13-0.24 m inside the edge (seed 5's gable_dormers: 0.2 m out)
    rng = np.random.default_rng(7)
    length, depth, eave = 16.0, 0.6, 3.6

    def ground(t: np.ndarray) -> np.ndarray:
        return ramp * np.clip((5.0 - t) / 3.4, 0.0, None)

    t = rng.uniform(0, length, n_wall)
    pts = [np.column_stack([t, -depth + rng.normal(0, 0.03, n_wall), rng.uniform(ground(t), eave)])]
    t, off = rng.uniform(0, length, 20000), rng.uniform(-3.0, 0.0, 20000)
    pts.append(np.column_stack([t, off, eave - 0.7 * off + rng.normal(0, 0.03, 20000)]))
    t, off = rng.uniform(0, length, 3000), rng.uniform(0.0, 4.0, 3000)
    pts.append(np.column_stack([t, off, ground(t) + rng.normal(0, 0.03, 3000)]))
    xyz = np.vstack(pts)
    d = wall_depth(np.zeros(2), np.array([length, 0.0]), np.array([0.0, 1.0]), xyz, ground(xyz[:, 0]))
    assert abs(d - depth) < 0.05


def _three_steps() -> SyntheticBuilding:
    """Three flat parts, each 1 m narrower and 4 m lower than the one before, with 0.3 m eaves (a stepped_flat)."""
    parts = (Part(0, 0, 10.5, 12, 15, 15, "flat", 0.3), Part(10, 1, 20, 11, 11, 11, "flat", 0.3),
             Part(19.5, 2, 29, 10, 7, 7, "flat", 0.3))
    return SyntheticBuilding("stepped", parts,
                             ((0, 0), (10.5, 0), (10.5, 1), (20, 1), (20, 2), (29, 2), (29, 10), (20, 10), (20, 11),
                              (10.5, 11), (10.5, 12), (0, 12)), (0.3,) * 12, origin=(300.0, 100.0), angle_deg=-8.0)


@pytest.mark.parametrize("seed", [7, 8])
def test_the_wall_at_a_step_between_offset_walls_stands_on_its_own_facade_points(seed):
    # the short walls at the steps were placed where the eaves step, which the outer part's eave moves past its end
    # wall (0.08-0.21 m off here; 0.2-0.4 m on stepped_flat of the benchmark cities); on their own facade points, 0.01 m
    b = _three_steps()
    m = reconstruct_building(b.sample(25.0, 0.04, np.random.default_rng(seed)), 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.05


def test_the_upper_roof_overhangs_the_lower_one_where_a_step_wall_continues_an_outline_wall():
    # the steps' walls inside the outline lie on the planes of the outline's short walls, continued; the upper roof's
    # 0.3 m overhang over the lower one was not built there (its edge stood on the wall), and is now
    from oblique_city.core.buildings.attributes import model_top_height

    b = _three_steps()
    rng = np.random.default_rng(7)
    dsm, dtm = b.dsm(0.15, 0.02, rng)
    m = reconstruct_building(b.sample(25.0, 0.04, rng), 0.0, dsm, "B0001", dtm=dtm)
    v = np.linspace(3.0, 9.0, 7)
    for u, upper in ((10.65, 15.0), (20.15, 11.0)):  # 0.15 m beyond each step's wall, under the upper eave
        z = model_top_height(m, b.to_world(np.column_stack([np.full_like(v, u), v])))
        assert np.all(np.abs(z - upper) < 0.2)


@pytest.mark.parametrize("seed", [7, 8])
def test_outline_walls_on_one_plane_keep_the_roofs_labelled(seed):
    # each step's short walls on both sides lie on one plane; the volumetric hull keeps one plane of such edges, which
    # shifted the labels of the faces after it: the top part's roof was taken for a wall, and the model "missed" its
    # roof points by 0.52 m and was refused as clutter. Each part's roof now within 0.05 m (0.04 m noise)
    from oblique_city.core.buildings.attributes import model_top_height

    b = _three_steps()
    m = reconstruct_building(b.sample(25.0, 0.04, np.random.default_rng(seed)), 0.0, None, "B0001",
                             ReconstructionConfig(force_path="volumetric"))
    v = np.linspace(3.0, 9.0, 7)
    for u, height in ((5.0, 15.0), (15.0, 11.0), (25.0, 7.0)):
        z = model_top_height(m, b.to_world(np.column_stack([np.full_like(v, u), v])))
        assert np.all(np.abs(z - height) < 0.05)


@pytest.mark.parametrize("overhang", [1.2, 1.5])
def test_wide_eaves_keep_the_facade_ring(overhang):
    # an alpine house whose eaves reach beyond the coverage test's fixed margin (1.2 m; the occupancy spreads a
    # little further still): the ring on its facades is the true outline to 6 mm, and the margin now grows with the
    # occupancy's own reach beyond the walls seen; with the fixed margin the ring was refused for the roof outline
    b = SyntheticBuilding("alpine", (Part(0, 0, 12, 10, 5, 9, "gable_u", overhang),),
                          ((0, 0), (12, 0), (12, 10), (0, 10)), (overhang,) * 4, origin=(200.0, 100.0), angle_deg=-14.0)
    xyz = b.sample(25.0, 0.04, np.random.default_rng(7))
    m = reconstruct_building(xyz, 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.05
    cfg = ReconstructionConfig()
    fixed = replace(cfg, contour=replace(cfg.contour, cover_slack=-np.inf))
    assert reconstruct_building(xyz, 0.0, None, "B0001", fixed).info["contour_source"].startswith("roof outline")


@pytest.mark.parametrize("seed", [7, 8])
def test_eaves_wider_on_one_side_keep_the_facade_ring(seed):
    # a gabled house with 1.4 m eaves along one side and 0.3 m on the others: the mask's median reach beyond the
    # walls is the narrow eaves', and the margin from it left 3 % of the occupancy outside the true outline, which
    # was refused for the roof outline (0.034-0.041 m off; seed 5's shed_house, 1 m eaves: 0.124 m); the widest
    # reach along a long wall widens the margin, and the ring is the outline to 0.01 m
    b = SyntheticBuilding("one_wide", (Part(0, 0, 12, 8, 5, 8, "gable_u", 1.4),), ((0, 0), (12, 0), (12, 8), (0, 8)),
                          (0.3, 0.3, 1.4, 0.3), origin=(200.0, 100.0), angle_deg=-14.0)
    xyz = b.sample(25.0, 0.04, np.random.default_rng(seed))
    uv = b.to_local(xyz[:, :2])
    narrow = (xyz[:, 2] > 0.3) & ((uv[:, 0] < -0.3) | (uv[:, 0] > 12.3) | (uv[:, 1] > 8.3))
    m = reconstruct_building(xyz[~narrow], 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.02


@pytest.mark.parametrize("wing", [0, 1])
def test_an_unseen_wing_end_takes_the_eaves_of_the_walls_beside_it(wing):
    # a U whose main block has 0.8 m eaves and whose wings 0.2 m; a wing's end wall shows no facade point. Placed by
    # the occupancy's reach beyond all the walls seen (the main block's long eaves among them) it stood 0.28-0.33 m
    # inside; placed from the eave over the gap by the roof points' reach beyond the wing's own walls, 0.04-0.07 m
    b = SyntheticBuilding("u", (Part(0, 0, 8, 9.5, 7, 7, "flat", 0.2), Part(0, 9, 26, 16, 8, 11, "gable_u", 0.8),
                                Part(18, 0, 26, 9.5, 7, 7, "flat", 0.2)),
                          ((0, 0), (8, 0), (8, 9), (18, 9), (18, 0), (26, 0), (26, 16), (0, 16)),
                          (0.2, 0.2, 0.8, 0.2, 0.2, 0.2, 0.8, 0.8), origin=(300.0, 100.0), angle_deg=12.0)
    xyz = b.sample(25.0, 0.04, np.random.default_rng(8))
    uv = b.to_local(xyz[:, :2])
    end = (np.abs(uv[:, 1]) < 0.15) & ((uv[:, 0] < 8) if wing == 0 else (uv[:, 0] > 18)) & (xyz[:, 2] > 0.2)
    m = reconstruct_building(xyz[~end], 0.0, None, "B0001")
    assert m.info["contour_source"] == "facades"
    assert m.info["walls_inferred"] == 1
    assert _outline_error(np.asarray(m.footprint), b.footprint) < 0.2
