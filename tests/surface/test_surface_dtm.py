"""DSM gridding and the DTM by robust morphological opening on synthetic point clouds with known terrain."""

from __future__ import annotations

import numpy as np

from oblique_city.core.surface.dsm import (
    DsmConfig,
    GridSpec,
    fill_small_holes,
    finish_dsm,
    grid_points,
    harmonic_fill,
    make_dsm,
    snap_wall_steps,
)
from oblique_city.core.surface.dtm import (
    ABOVE,
    BELOW,
    LAS_CLASSES,
    ON,
    DtmConfig,
    greenness,
    las_classes,
    make_dtm,
    object_masks,
)

X0, Y0 = 500000.0, 5400000.0


def _terrain(x, y):
    return 200.0 + 0.02 * (x - X0) + 0.01 * (y - Y0) + 1.5 * np.sin((x - X0) / 40.0)


def _city(seed=0):
    """Ground points with 1 % blunders 6 m below, two buildings (one 45 m wide) and a tree blob."""
    rng = np.random.default_rng(seed)
    n = 120_000
    x, y = rng.uniform(X0, X0 + 200, n), rng.uniform(Y0, Y0 + 160, n)
    z = _terrain(x, y) + rng.normal(0, 0.05, n)
    kind = np.zeros(n, int)
    for (bx0, by0, bx1, by1, h) in ((X0 + 30, Y0 + 40, X0 + 75, Y0 + 80, 20.0), (X0 + 120, Y0 + 30, X0 + 150,
                                                                                   Y0 + 60, 9.0)):
        inside = (x > bx0) & (x < bx1) & (y > by0) & (y < by1)
        z[inside] = _terrain(bx0, by0) + h + rng.normal(0, 0.05, inside.sum())
        kind[inside] = 1
    tree = np.hypot(x - X0 - 150, y - Y0 - 120) < 6
    z[tree] += rng.uniform(3, 8, tree.sum())
    kind[tree] = 2
    low = rng.random(n) < 0.01
    z[low & (kind == 0)] -= 6.0
    kind[low & (kind == 0)] = 3
    return np.column_stack([x, y, z]), kind


def test_dtm_by_robust_opening():
    xyz, kind = _city()
    grid = GridSpec.around(X0, Y0, X0 + 200, Y0 + 160, 0.5)
    dtm, classes, _ = make_dtm(xyz, grid, "EPSG:32632", DtmConfig(se_size=60.0))
    xs, ys = grid.centers()
    err = dtm.data - _terrain(xs, ys)
    assert np.sqrt(np.mean(err ** 2)) < 0.15
    assert (classes[kind == 1] == ABOVE).mean() > 0.99
    assert (classes[kind == 0] == ON).mean() > 0.99
    assert (classes[kind == 3] == BELOW).mean() > 0.97  # the opening sags below hill tops of the terrain
    high_tree = (kind == 2) & (xyz[:, 2] - _terrain(xyz[:, 0], xyz[:, 1]) > 2.0)
    assert (classes[high_tree] == ABOVE).mean() > 0.95


def test_plain_minimum_erosion_would_fail():
    """The k-th element erosion is what makes the blunders below ground harmless."""
    xyz, _ = _city()
    grid = GridSpec.around(X0, Y0, X0 + 200, Y0 + 160, 0.5)
    dtm, *_ = make_dtm(xyz, grid, "EPSG:32632", DtmConfig(erosion_rank=0.0))
    xs, ys = grid.centers()
    assert np.sqrt(np.mean((dtm.data - _terrain(xs, ys)) ** 2)) > 0.3


def test_dsm_top_band_takes_roof_not_wall():
    rng = np.random.default_rng(1)
    grid = GridSpec.around(0.0, 0.0, 4.0, 4.0, 1.0)
    roof = np.column_stack([rng.uniform(0, 4, 400), rng.uniform(0, 4, 400), 20 + rng.normal(0, 0.05, 400)])
    wall = np.column_stack([np.full(300, 1.999), rng.uniform(0, 4, 300), rng.uniform(0, 20, 300)])
    roof = roof[roof[:, 0] < 2.0]
    ground = np.column_stack([rng.uniform(2.0, 4, 200), rng.uniform(0, 4, 200), rng.normal(0, 0.05, 200)])
    h, top = grid_points(grid, np.concatenate([roof, wall, ground]), DsmConfig())
    assert np.abs(h[:, :2] - 20.0).max() < 0.1  # column 1 holds the wall: still the roof
    assert np.abs(h[:, 2:]).max() < 0.1
    assert not top[len(roof):len(roof) + len(wall)][wall[:, 2] < 15].any()


def test_fill_small_holes_only():
    y, x = np.mgrid[0:60, 0:60]
    z = 100 + 0.1 * x + 0.05 * y
    h = z.astype(float)
    h[10:13, 10:13] = np.nan
    h[30:50, 30:50] = np.nan
    f = fill_small_holes(h, 20, 1.0)
    assert np.abs(f[10:13, 10:13] - z[10:13, 10:13]).max() < 0.15
    assert np.isnan(f[30:50, 30:50]).all()
    # an occlusion between a roof (10 m up) and the ground takes the ground's height
    g = np.full((30, 30), 100.0)
    g[:, 15:] = 110.0
    g[10:14, 12:15] = np.nan
    f = fill_small_holes(g, 20, 1.0)
    assert np.allclose(f[10:14, 12:15], 100.0)
    assert np.allclose(fill_small_holes(g, 20, 1.0, plane_tol=0.2)[10:14, 12:15], 100.0)  # a step is no plane


def test_level_hole_beside_a_wall_takes_only_its_own_border():
    """A level hole on the ground one cell from a 10 m wall is filled from its ground border alone: a windowed
    inpainting (OpenCV's, radius 3) lets the roof across the wall in. The harmonic fill keeps a ramp exactly."""
    g = np.full((40, 40), 100.0)
    g[:, 20:] = 110.0
    g[15:25, 12:19] = np.nan            # ground hole; its border column 19 is ground, the roof starts at 20
    f = fill_small_holes(g, 200, 1.0)
    assert np.allclose(f[15:25, 12:19], 100.0, atol=1e-6)
    y, x = np.mgrid[0:30, 0:30]
    ramp = 100.0 + 0.03 * x + 0.02 * y
    hole = np.zeros(ramp.shape, bool)
    hole[8:20, 5:25] = True
    assert np.allclose(harmonic_fill(np.where(hole, np.nan, ramp), hole)[hole], ramp[hole], atol=1e-6)


def test_hole_enclosed_by_roof_is_roof_and_an_occlusion_strip_is_ground():
    """A gap matching left in a roof, open to the ground only at the eave, is bounded by roof on three sides: it
    is filled at roof height (and with ``roof_sides=5``, the ground rule that fills it at 100 m is what would
    apply). A strip beside a wall, bounded by the roof on one side only, is ground hidden behind the wall."""
    g = np.full((60, 60), 100.0)
    g[10:40, 10:40] = 110.0                 # a flat roof 10 m above the ground
    g[10:16, 20:30] = np.nan                # unmatched part of the roof reaching its north eave
    g[10:40, 40:44] = np.nan                # occlusion strip east of the wall
    f = fill_small_holes(g, 400, 1.0)
    assert np.allclose(f[10:16, 20:30], 110.0, atol=1e-6)
    assert np.allclose(f[10:40, 40:44], 100.0, atol=1e-6)
    off = fill_small_holes(g, 400, 1.0, roof_sides=5)
    assert np.allclose(off[10:16, 20:30], 100.0, atol=1e-6)


def test_a_hole_at_a_wall_foot_is_judged_on_its_whole_ring():
    """A one-cell hole on the last ground row before a 7 m wall, with two one-cell holes in the roof diagonally
    next to it, is ground hidden at the wall foot: it takes the ground height. A cell on two rings belongs to both;
    when each ring cell went to one hole only, the roof cell below it went to the later roof holes, its ring held
    ground only, it passed for a level hole and took the 4-neighbour mean, 101.75 m, a height up the wall."""
    g = np.full((20, 20), 100.0)
    g[10:] = 107.0                      # roof from row 10
    g[9, 5] = np.nan
    g[10, 4] = g[10, 6] = np.nan
    assert fill_small_holes(g, 20, 1.0)[9, 5] == 100.0


def test_cells_on_a_wall_step_take_the_roof_or_the_ground_and_slopes_stay():
    """A line of facade heights between a 12 m roof and the ground (2 and 9 m up the wall) is snapped to the
    nearer side; a 60-degree roof (0.27 m per 0.156 m cell) and a chimney are no wall steps."""
    g = np.full((20, 30), 100.0)
    g[:, 15:] = 112.0
    g[:, 14] = 102.0                     # mid-wall points near the foot
    g[5:10, 14] = 109.0                 # and near the top
    f = snap_wall_steps(g, 1.0)
    assert np.allclose(f[:5, 14], 100.0) and np.allclose(f[5:10, 14], 112.0) and np.allclose(f[10:, 14], 100.0)
    assert np.allclose(f[:, :14], 100.0) and np.allclose(f[:, 15:], 112.0)
    g[:, 13] = np.nan                   # no measured ground beside them: no evidence of a step, nothing changes
    assert np.array_equal(snap_wall_steps(g, 1.0), g, equal_nan=True)
    y, x = np.mgrid[0:20, 0:30]
    roof = 110.0 + np.tan(np.radians(60)) * 0.156 * np.minimum(x, 29 - x)
    roof[10, 10] += 3.0                  # a chimney
    assert np.array_equal(snap_wall_steps(roof, 1.0), roof)


def test_narrow_pit_in_a_roof_is_removed_and_a_gap_between_buildings_kept():
    """A 1 x 1.5 m patch of ground-level blunders inside a 12 m roof is replaced by the roof; a 2 m wide, 5 m
    long passage between two buildings (open at its ends) keeps its ground."""
    rng = np.random.default_rng(1)
    cell = 0.25
    grid = GridSpec(0.0, 40.0, cell, 160, 160)
    x, y = rng.uniform(0, 40, 400_000), rng.uniform(0, 40, 400_000)
    z = np.full(len(x), 100.0)
    roof = (x > 5) & (x < 35) & (y > 5) & (y < 18)
    z[roof] = 112.0
    pit = roof & (x > 15) & (x < 16) & (y > 10) & (y < 11.5)
    z[pit] = 101.0                      # matching slid to the ground
    left, right = (x > 5) & (x < 19) & (y > 25) & (y < 30), (x > 21) & (x < 35) & (y > 25) & (y < 30)
    z[left | right] = 110.0             # two buildings 2 m apart
    xyz = np.column_stack([x, y, z + rng.normal(0, 0.02, len(x))])
    d_on, _ = make_dsm(grid, xyz, "EPSG:25832", DsmConfig(cell=cell))
    d_off, _ = make_dsm(grid, xyz, "EPSG:25832", DsmConfig(cell=cell, pit_size_m=0))
    r, c, _ = grid.cell_index(np.array([[15.5, 10.75]]))
    assert abs(d_off.data[r[0], c[0]] - 101.0) < 0.2          # without the filter the blunder stays
    assert abs(d_on.data[r[0], c[0]] - 112.0) < 0.2
    gap = grid.cell_index(np.array([[20.0, 27.5]]))
    assert abs(d_on.data[gap[0][0], gap[1][0]] - 100.0) < 0.2


def test_fill_hole_in_sloped_roof_by_its_plane():
    """A hole on a 40-degree roof (ring spanning ~2 m) takes the roof plane, not the low side of the ring."""
    y, x = np.mgrid[0:40, 0:40]
    cell = 0.155
    z = 120.0 + np.tan(np.radians(40)) * cell * y + 0.01 * np.sin(x)   # rises 0.13 m per row
    h = z.copy()
    h[15:27, 10:22] = np.nan   # 12 x 12 cells: the ring spans ~1.7 m
    plane = fill_small_holes(h, 200, 1.0, plane_tol=0.2)
    assert np.abs(plane[15:27, 10:22] - z[15:27, 10:22]).max() < 0.03
    low = fill_small_holes(h, 200, 1.0)
    assert np.abs(low[15:27, 10:22] - z[15:27, 10:22]).max() > 0.5   # the old behaviour the plane fill replaces


def test_masks_split_buildings_and_vegetation():
    rng = np.random.default_rng(4)
    ndsm = np.zeros((60, 60))
    ndsm[5:20, 5:20] = 10.0                                  # grey roof
    ndsm[30:40, 30:40] = 6.0 + rng.uniform(-1.5, 1.5, (10, 10))  # rough green crown
    ndsm[40:55, 5:20] = 8.0                                  # smooth green roof
    rgb = np.full((60, 60, 3), 120.0)
    rgb[30:40, 30:40] = (60, 140, 50)
    rgb[40:55, 5:20] = (60, 140, 50)
    bld, veg = object_masks(ndsm, rgb, 0.5, DtmConfig())
    assert bld[5:20, 5:20].mean() > 0.9 and not bld[30:40, 30:40].any()
    assert veg[30:40, 30:40].mean() > 0.8 and not veg[5:20, 5:20].any()
    assert bld[40:55, 5:20].mean() > 0.9 and not veg[40:55, 5:20].any()
    assert greenness(np.array([60, 140, 50])) > 0.3


def test_green_bumpy_crowns_are_vegetation_and_a_smooth_green_roof_is_not():
    """A green object whose surface is bumpy at the metre scale (the DSM of a crown group: 0.15 m bumps about
    0.6 m wide), too little for the roughness test, is vegetation by its normal variation; the same object
    with a smooth top is a green roof, a building."""
    from scipy import ndimage

    cell = 0.156
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:160, 0:160] * cell
    bumps = ndimage.gaussian_filter(rng.normal(0, 1, x.shape), 2.0)
    bumps *= 0.15 / bumps.std()
    crowns = (x > 2) & (x < 10) & (y > 2) & (y < 10)
    roof = (x > 14) & (x < 22) & (y > 14) & (y < 22)
    ndsm = np.zeros(x.shape)
    ndsm[crowns] = 8.0 + bumps[crowns]
    ndsm[roof] = 8.0
    rgb = np.full(x.shape + (3,), 120.0)
    rgb[crowns | roof] = (60, 140, 50)
    bld, veg = object_masks(ndsm, rgb, cell, DtmConfig())
    inner = (x > 3) & (x < 9) & (y > 3) & (y < 9)
    assert veg[inner].mean() > 0.9 and not bld[inner].any()
    assert bld[roof].mean() > 0.9 and not veg[roof].any()
    bld0, _ = object_masks(ndsm, rgb, cell, DtmConfig(curvature_min=np.inf))  # roughness alone: a building
    assert bld0[inner].mean() > 0.9


def test_cell_top_is_the_highest_supported_point():
    """Per cell: two roof points beat six mismatched ground points under them; a lone high blunder is passed
    over; a cell with a single point keeps it."""
    g = GridSpec(0.0, 3.0, 1.0, 1, 3)
    pts = [(0.5, 2.5, z) for z in (20.0, 20.1)] + [(0.5, 2.5, 10.0 + 0.05 * i) for i in range(6)]
    pts += [(1.5, 2.5, 30.0)] + [(1.5, 2.5, 10.0 + 0.1 * i) for i in range(3)]
    pts += [(2.5, 2.5, 7.0)]
    h, top = grid_points(g, np.array(pts), DsmConfig(cell=1.0, min_support=2, band=0.5))
    assert abs(h[0, 0] - 20.05) < 0.06 and abs(h[0, 1] - 10.1) < 1e-9 and h[0, 2] == 7.0
    assert top[:2].all() and not top[2:8].any() and not top[8] and top[9:12].all()


def test_sparse_roof_wins_through_its_neighbours():
    """One roof point per cell (a dark roof, poorly matched) over three ground-level mismatches per cell: the
    roof points support each other across the 3 x 3 neighbourhood, so the roof is the top of every cell."""
    g = GridSpec(0.0, 4.0, 1.0, 4, 4)
    rng = np.random.default_rng(2)
    pts = []
    for r in range(4):
        for c in range(4):
            x, y = c + 0.5, 4 - r - 0.5
            pts.append((x, y, 15.0 + 0.1 * x + rng.normal(0, 0.05)))               # the sloped roof
            pts += [(x, y, 6.0 + rng.normal(0, 0.1)) for _ in range(3)]             # ground-level blunders
    h, _ = grid_points(g, np.array(pts), DsmConfig(cell=1.0, min_support=2, band=0.5))
    truth = 15.0 + 0.1 * (np.arange(4) + 0.5)[None, :]
    assert np.abs(h - truth).max() < 0.2


def test_thin_fattened_fringe_of_a_roof_is_passed_over():
    """A roof (5 points per cell) whose edge a matching window fattened by two cells (one roof-height point per
    cell) beside ground seen by 5 points per cell: with the default support the outer fringe cell takes the
    ground (the inner one borrows support from the roof beside it: one cell, within a wall's tolerance), with a
    support of 2 both take the roof."""
    rng = np.random.default_rng(4)
    g = GridSpec(0.0, 20.0, 1.0, 20, 20)
    pts = []
    for r in range(20):
        for c in range(20):
            x, y = c + 0.5, 19.5 - r
            z = 110.0 if c < 10 else 100.0
            pts += [(x + dx, y + dy, z + dz) for dx, dy, dz in rng.uniform(-0.3, 0.3, (5, 3)) * [1, 1, 0.1]]
            if c in (10, 11):
                pts.append((x, y, 110.0))
    h8, _ = grid_points(g, np.array(pts), DsmConfig(cell=1.0))
    h2, _ = grid_points(g, np.array(pts), DsmConfig(cell=1.0, min_support=2))
    assert np.allclose(h8[:, 11:], 100.0, atol=0.1) and np.allclose(h8[:, :10], 110.0, atol=0.1)
    assert np.allclose(h2[:, 10:12], 110.0, atol=0.1)


def test_wall_points_at_a_roof_edge_are_judged_by_the_surroundings():
    """Facade points 5 m up a 23 m wall, measured in the roof's first row over 10 cells (the tower of the demo
    church: its textureless wall matched, its steep roof edge not). Emptied and filled as a hole enclosed by the
    roof on three sides, the row is roof; snapped to the nearer neighbour it was ground. The same heights along a
    whole wall line, open to the ground at both ends, stay ground."""
    g = np.full((100, 100), 107.0)
    g[30:60, 30:60] = 130.0
    g[30, 40:50] = 112.0
    f = finish_dsm(g, 0.156)
    assert np.allclose(f[30, 40:50], 130.0, atol=1e-6)
    assert np.allclose(snap_wall_steps(g, 1.0)[30, 40:50], 107.0)
    g[30, 30:60] = 112.0                 # the whole north row: a wall line between the ground and the roof
    f = finish_dsm(g, 0.156)
    assert np.allclose(f[30, 32:58], 107.0, atol=1e-6)


def test_las_classes_of_ground_building_facade_tree_and_blunder():
    grid = GridSpec(0.0, 20.0, 0.5, 40, 40)
    building = np.zeros((40, 40), bool)
    building[10:20, 10:20] = True  # x 5-10 m, y 10-15 m
    veg = np.zeros_like(building)
    veg[25:35, 25:35] = True  # x 12.5-17.5 m, y 2.5-7.5 m
    dtm = np.full((40, 40), 100.0)
    xyz = np.array([[2.0, 2.0, 100.0], [7.0, 12.0, 108.0], [4.6, 12.0, 104.0], [4.6, 12.0, 104.0],
                    [3.0, 12.0, 104.0], [15.0, 5.0, 106.0], [15.0, 5.0, 101.6], [1.0, 18.0, 103.0],
                    [2.0, 3.0, 97.0], [30.0, 30.0, 110.0]])
    horizontal, up = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    normal = np.array([up, up, horizontal, up, horizontal, up, up, up, up, up])
    classes = np.array([ON, ABOVE, ABOVE, ABOVE, ABOVE, ABOVE, ABOVE, ABOVE, BELOW, ABOVE])
    got = las_classes(classes, xyz, normal, grid, building, veg, dtm)
    c = LAS_CLASSES
    # ground; roof; facade 0.4 m outside the roof; a raised non-facade point there; a facade point 2 m out;
    # crown; low branch; a raised thing elsewhere; a blunder below the ground; a point beyond the grid
    assert got.tolist() == [c["ground"], c["building"], c["building"], c["unclassified"], c["unclassified"],
                            c["high_vegetation"], c["medium_vegetation"], c["unclassified"], c["low_point"],
                            c["unclassified"]]
