"""Readers and writers of block formats, ground point lists, images, point clouds and rasters."""
