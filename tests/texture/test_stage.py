"""The ``texture`` stage on a workspace: outputs, textures.json consistency with the rings, cancellation."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.buildings.model import load_buildings
from oblique_city.core.errors import Cancelled, WorkspaceError
from oblique_city.core.pipeline import Workspace
from oblique_city.core.pipeline.context import RunContext
from oblique_city.core.pipeline.registry import get_stage, stage_names
from oblique_city.core.texture.atlas import load_textures


def test_stage_is_registered_after_buildings():
    names = stage_names()
    assert names.index("texture") == names.index("buildings") + 1
    assert get_stage("texture").requires == ("buildings",)


def test_stage_writes_atlas_and_textures(workspace):
    stage = get_stage("texture")
    cfg = stage.make_config({"texel": 0.05, "page_size": 1024})
    seen = []
    res = stage.run(workspace, cfg, RunContext(on_progress=lambda s, d, t, m: seen.append((d, t))))
    assert {"texture/textures.json", "texture/atlas_000.png", "texture/atlas_000_seen.png"} <= set(res.outputs)
    assert res.metrics["surfaces_textured"] >= 5 and res.metrics["share_with_source"] > 0.95
    assert seen and seen[-1][0] == seen[-1][1]
    tex = load_textures(workspace.path("texture", "textures.json"))
    models, _ = load_buildings(workspace.path("buildings", "buildings.json"))
    rings = {s.id: len(s.ring) for m in models for s in m.surfaces}
    for sid, st in tex.surfaces.items():
        assert st.uv.shape == (rings[sid], 2)  # one UV per ring vertex, ring order
        assert np.all((st.uv > 0) & (st.uv < 1))
        assert abs(st.texel - 0.05) < 1e-9 and sum(st.sources.values()) == pytest.approx(st.coverage, abs=0.02)
        assert tex.pages[st.page][0].exists()


def test_stage_cancels_and_needs_buildings(workspace, tmp_path):
    stage = get_stage("texture")
    ctx = RunContext()
    ctx.cancel()
    with pytest.raises(Cancelled):
        stage.run(workspace, stage.make_config({}), ctx)
    empty = Workspace.create(tmp_path / "empty", crs="EPSG:25832")
    with pytest.raises(WorkspaceError, match="buildings"):
        stage.run(empty, stage.make_config({}), RunContext())
