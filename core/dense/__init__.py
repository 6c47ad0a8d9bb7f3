"""Dense matching of oblique blocks: image selection, epipolar rectification, SGM, multi-slave fusion, filters."""
