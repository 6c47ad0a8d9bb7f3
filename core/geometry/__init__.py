"""Geometry: rotation conventions, projection, views, ray intersection, CRS handling."""
