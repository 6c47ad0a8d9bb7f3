"""Builder of the ``texture`` stage: building objects get the atlas UVs (one per ring vertex, ring order) and the
page's image material on textured polygons; untextured polygons keep their surface-type material."""

from __future__ import annotations

import numpy as np
import pytest
from test_bpy_buildings import box_building

from oblique_city.core.buildings.model import save_buildings
from oblique_city.core.io.geotiff import write_png
from oblique_city.core.pipeline import Workspace
from oblique_city.core.texture.atlas import write_textures_json

pytestmark = pytest.mark.xdist_group("bpy")


@pytest.fixture
def ws(tmp_path, utm_block):
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    models = [box_building("B0001", 0.0, "2d", True)]
    save_buildings(w.stage_dir("buildings") / "buildings.json", models, utm_block.crs)
    rng = np.random.default_rng(0)
    write_png(w.stage_dir("texture") / "atlas_000.png", rng.integers(0, 255, (64, 128, 3), dtype=np.uint8))
    surfaces = {}
    for k, s in enumerate(models[0].surfaces[1:4]):  # three walls
        uv = np.array([[0.1, 0.1], [0.3, 0.1], [0.3, 0.5], [0.1, 0.5]]) + [0.3 * k, 0.0]
        surfaces[s.id] = {"building": "B0001", "page": 0, "uv": uv.tolist(), "texel": 0.1, "coverage": 1.0,
                          "sources": {"img0": 1.0}}
    write_textures_json(w.path("texture", "textures.json"),
                        {"pages": [{"file": "atlas_000.png", "width": 128, "height": 64}], "surfaces": surfaces})
    w.write_state({"buildings": {"status": "done"}, "texture": {"status": "done"}})
    return w, models, surfaces


def test_texture_layer(addon, ws):
    bpy = addon
    from oblique_city.addon import builders

    w, models, surfaces = ws
    messages = builders.build_scene(bpy.context.scene, w)
    assert messages[-1] == "texture: 3 textured surfaces on 1 atlas pages"
    mesh = bpy.data.objects["B0001"].data
    uv = np.zeros(2 * len(mesh.loops), np.float32)
    mesh.uv_layers["Atlas"].data.foreach_get("uv", uv)
    uv = uv.reshape(-1, 2)
    for poly, s in zip(mesh.polygons, models[0].surfaces, strict=True):
        mat = mesh.materials[poly.material_index]
        if s.id in surfaces:
            assert np.allclose(uv[poly.loop_start:poly.loop_start + poly.loop_total], surfaces[s.id]["uv"],
                               atol=1e-6)
            assert mat.name == "Oblique City atlas 000"
            img = mat.node_tree.nodes["Atlas"].image
            assert img.filepath.endswith("atlas_000.png") and tuple(img.size) == (128, 64)
        else:
            assert not mat.name.startswith("Oblique City atlas")
    # building only the texture layer builds the buildings it needs
    bpy.data.objects.remove(bpy.data.objects["B0001"])
    assert builders.build_scene(bpy.context.scene, w, stages=["texture"]) == [
        "texture: 3 textured surfaces on 1 atlas pages"]
    assert "Atlas" in bpy.data.objects["B0001"].data.uv_layers
