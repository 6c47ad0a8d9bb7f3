"""Write a .blend of a workspace: a fresh scene built with the add-on's own builders.

    python tools/make_blend.py WORKSPACE OUT.blend
    blender --background --factory-startup --python tools/make_blend.py -- WORKSPACE OUT.blend

Used by ``make demo``. The scene gets the workspace's georeference (CRS and float64 origin), one camera per image
in collections by cardinal view, ground points, and the layer of every finished stage that has a builder
(``addon.builders.BUILDERS``). The add-on is registered first so the scene's settings (the workspace path) are
saved with the file. Exit code 2 and one line on stderr for a bad workspace.
"""

from __future__ import annotations

import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: make_blend.py WORKSPACE OUT.blend", file=sys.stderr)
        return 2
    import bpy

    import oblique_city
    from oblique_city.addon import builders
    from oblique_city.core.errors import CityError
    from oblique_city.core.pipeline import Workspace

    bpy.ops.wm.read_homefile(app_template="", use_empty=True)
    oblique_city.register()
    try:
        ws = Workspace.open(argv[0])
        messages = builders.build_scene(bpy.context.scene, ws)
    except CityError as e:
        print(f"make_blend: error: {e}", file=sys.stderr)
        return 2
    out = Path(argv[1]).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(out))
    for m in messages:
        print(f"make_blend: {m}")
    print(f"make_blend: wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]))
