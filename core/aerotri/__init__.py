"""Aerial triangulation: the bundle adjustment engine, integrated and hierarchical AT, CBA, statistics, report."""
