"""The scene's collection tree: one "Oblique City" collection with one child collection per layer.

Collections are found by a custom property (``oc_role``), not by name: Blender names are global across scenes and
get ``.001`` suffixes, roles do not. A layer's collection is cleared (objects, sub-collections and the data they
leave unused) before its builder fills it again, so rebuilding never duplicates objects.
"""

from __future__ import annotations

ROOT_NAME = "Oblique City"
ROLE_KEY = "oc_role"


def child_collection(parent, role: str, name: str):
    """The child of ``parent`` with ``role`` (created with ``name`` if missing)."""
    for c in parent.children:
        if c.get(ROLE_KEY) == role:
            return c
    import bpy

    c = bpy.data.collections.new(name)
    c[ROLE_KEY] = role
    parent.children.link(c)
    return c


def root_collection(scene):
    """The scene's "Oblique City" collection (created on first use)."""
    return child_collection(scene.collection, "root", ROOT_NAME)


def layer_collection(scene, role: str, name: str, clear: bool = True):
    """The collection of one layer (``role``) under the root; with ``clear`` it is emptied first."""
    coll = child_collection(root_collection(scene), role, name)
    if clear:
        clear_collection(coll)
    return coll


def clear_collection(coll) -> None:
    """Delete the objects and sub-collections of ``coll``, and the object data nothing else uses."""
    import bpy

    for child in list(coll.children):
        clear_collection(child)
        bpy.data.collections.remove(child)
    datas = {obj.data for obj in coll.objects if obj.data is not None}
    bpy.data.batch_remove(list(coll.objects))
    bpy.data.batch_remove([d for d in datas if d.users == 0])
