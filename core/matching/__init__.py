"""Tie point generation: connectivity graph from the approximate orientation, SIFT, guided matching, tracks."""
