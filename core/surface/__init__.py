"""Surfaces from the dense point cloud: ortho-DSM, DTM by robust morphology, nDSM, masks, true ortho, quality."""
