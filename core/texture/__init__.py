"""Perspective-correct, multi-source texture atlases for planar building surfaces.

``plane`` (surface frames and texel grids), ``occlusion`` (Open3D ray casting against buildings and terrain),
``sources`` (candidate images and their per-texel quality), ``compose`` (sampling through the exact camera model,
per-texel source choice with feathered seams, radiometric gains), ``atlas`` (packing, gutters, UVs, the
``texture/textures.json`` file) and the ``texture`` stage.
"""
