"""Simulator: a synthetic city with complete ground truth, camera systems, flight plans, navigation errors,
ray-cast rendering of oblique image blocks, and the ground-truth products written beside every simulated block."""
