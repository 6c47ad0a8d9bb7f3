"""Fixtures of the dense tests: a rendered synthetic block with known geometry (see ``dense_scene``)."""

from __future__ import annotations

import dense_scene
import pytest


@pytest.fixture(scope="session")
def nadir_oblique_block(tmp_path_factory):
    """Six nadir images and three north obliques of the synthetic scene: ``(block, scene)``."""
    folder = tmp_path_factory.mktemp("dense_block")
    return dense_scene.make_block(folder, dense_scene.nadir_poses() + dense_scene.oblique_poses("north"))
