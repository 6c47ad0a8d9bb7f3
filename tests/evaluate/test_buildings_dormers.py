"""The benchmark's dormer wall figure (:class:`DormerProbe`) against the simulator's dormers, whose walls and roof
overhangs are known by construction."""

from __future__ import annotations

import numpy as np

from oblique_city.core.evaluate.buildings import BuildingTruth, DormerProbe
from oblique_city.core.simulate.city import make_city


def test_dormer_probes_find_the_simulator_s_dormer_roof_edges():
    # the demo city's dormer house: three gabled dormers 2.2 m wide with 0.15 m roof overhangs at their front and
    # sides (simulate.city._dormer); their roof edge stands 0.15 m beyond each wall
    b = next(x for x in make_city(0).buildings if x.name == "gable_dormers")
    truth = BuildingTruth.from_city(b)
    dormers = [p for p in b.parts if p.kind == "dormer"]
    assert len(truth.dormers) == len(dormers) == 3
    for probe, part in zip(truth.dormers, dormers):
        x0, _, x1, _ = part.rect
        assert np.allclose(probe.sides, [x0 - 0.15, x1 + 0.15], atol=0.015)
        assert abs(probe.front - 0.15) < 0.015


def test_dormer_probe_measures_a_model_s_walls_and_misses_a_flat_roof():
    # a 2 m wide, 1 m high block on a flat roof at 10 m, front at y = 0 (outwards: y < 0), sides at x = 0 and 2
    t_a = np.arange(-1.0, 3.0, 0.01)
    t_f = np.arange(-1.5, 1.0, 0.01)
    probe = DormerProbe(np.column_stack([t_a, np.full(len(t_a), 0.3)]), t_a, np.full(len(t_a), 10.0),
                        np.column_stack([np.ones(len(t_f)), -t_f]), t_f, np.full(len(t_f), 10.0),
                        np.array([0.0, 2.0]), 0.0)

    def block(x0: float, x1: float, y0: float):
        return lambda xy: 10.0 + ((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0)).astype(float)

    sides, front = probe.walls(block(0.2, 2.1, 0.25))  # shifted 0.2 and 0.1 m at the sides, 0.25 m at the front
    assert np.allclose(sides, [0.2, 2.1], atol=0.011) and abs(front - -0.25) < 0.011
    assert probe.walls(lambda xy: np.full(len(xy), 10.0)) is None
