"""Oblique City's core: pure Python (numpy, scipy, OpenCV, pycolmap, Open3D, ...), never bpy.

It runs headless from the CLI, batch scripts and Dask workers, and inside Blender behind the add-on's operators.
"""
