"""Headless import of an oriented image block through the add-on's operator; prints a JSON summary line.

With bpy from PyPI (the add-on registered from this repository, installed as ``oblique_city``)::

    python tests/blender/scripts/import_block.py SOURCE --format bex --workspace WS [--option crs=EPSG:25832]
        [--blend OUT.blend]

In a real Blender, the same script after ``--`` (the extension enabled, or this repository importable as
``oblique_city``, e.g. ``PYTHONPATH`` pointing at the folder that holds a checkout named ``oblique_city``)::

    blender --background --factory-startup --python tests/blender/scripts/import_block.py -- SOURCE --format bex \
        --workspace WS

It calls ``bpy.ops.city.import_block`` exactly as File > Import does, so the block ends up in the workspace and
the scene has one camera per image grouped by cardinal view; ``--blend`` saves the scene. Exit code 2 and one
line on stderr when the import fails.
"""

from __future__ import annotations

import argparse
import json
import sys


def operator_available(bpy) -> bool:
    try:
        bpy.ops.city.import_block.get_rna_type()
    except KeyError:
        return False
    return True


def main(argv: list[str]) -> int:
    import bpy

    p = argparse.ArgumentParser(prog="import_block.py", description=__doc__.split("\n\n")[0])
    p.add_argument("source")
    p.add_argument("--format", required=True)
    p.add_argument("--workspace", required=True)
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--blend", help="save the scene to this .blend")
    args = p.parse_args(argv)

    if not operator_available(bpy):
        import oblique_city

        oblique_city.register()
    try:
        bpy.ops.city.import_block(filepath=args.source, block_format=args.format, workspace=args.workspace,
                                  options="; ".join(args.option))
    except RuntimeError as e:
        print(f"import_block.py: {str(e).strip().splitlines()[0]}", file=sys.stderr)
        return 2
    scene = bpy.context.scene
    views: dict[str, int] = {}
    for obj in scene.objects:
        if obj.type == "CAMERA" and "oc_view" in obj:
            views[obj["oc_view"]] = views.get(obj["oc_view"], 0) + 1
    if args.blend:
        bpy.ops.wm.save_as_mainfile(filepath=args.blend)
    print(json.dumps({"cameras": sum(views.values()), "views": views, "crs": scene.get("oblique_city_crs"),
                      "origin": list(scene.get("oblique_city_origin", [])),
                      "workspace": scene.oblique_city.workspace}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]))
