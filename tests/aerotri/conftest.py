"""A small simulated penta block shared by the aerotri tests (module scope: simulated once per module)."""

from __future__ import annotations

import pytest

from oblique_city.core.aerotri.bundle import BundleOptions
from oblique_city.core.aerotri.hierarchical import initial_tie_coordinates
from oblique_city.core.simulate.observations import SimulationConfig, simulate_block

NOISE_PX = 0.3


@pytest.fixture(scope="package")
def sim():
    """About 400 images (80 exposures x 5 heads in 5 strips), 0.3 px noise, 3 % blunders, GNSS/IMU priors with a datum
    offset, 50 ground points."""
    return simulate_block(SimulationConfig(n_images=400, tie_density=0.0004, seed=3, noise_px=NOISE_PX))


@pytest.fixture(scope="package")
def xyz0(sim):
    return initial_tie_coordinates(sim.block, sim.ties)


@pytest.fixture(scope="package")
def options():
    return BundleOptions(sigma_px=NOISE_PX)


@pytest.fixture(scope="package")
def iat(sim, xyz0, options):
    from oblique_city.core.aerotri.hierarchical import integrated

    return integrated(sim.block, sim.ties, options, xyz0=xyz0)
