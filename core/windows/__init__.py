"""Window detection on the rectified facade textures of the LOD2 walls.

``detect`` (darkness against the wall, components, sub-texel boxes, facade grammar, back-projection onto the wall
plane), ``facades`` (the wall textures cut from the texture stage's atlas, with their plane frames),
``store`` (``windows/windows.json``) and the ``windows`` stage.
"""
