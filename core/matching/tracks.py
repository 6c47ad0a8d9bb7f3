"""Tracks across images from pairwise matches (union-find), preferring multi-ray points.

A node is one keypoint of one image. Verified matches join nodes; each connected set is a track. A track that
holds two different keypoints of the same image is inconsistent and dropped. Two-ray points are badly
constrained, so when ``max_per_image`` caps the tracks an image keeps, the longest tracks win.
"""

from __future__ import annotations

import numpy as np

from ..model import TiePoints


def union_find(n: int, pairs: np.ndarray) -> np.ndarray:
    """Component label ``(n,)`` of each node joined by ``pairs (k, 2)`` (path halving, union by index)."""
    parent = np.arange(n)

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in pairs:
        ra, rb = find(int(a)), find(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    return np.array([find(i) for i in range(n)])


def build_tracks(keypoints: list[np.ndarray], matches: dict[tuple[int, int], np.ndarray], image_ids: list[str],
                 min_rays: int = 2, max_per_image: int = 0) -> TiePoints:
    """Tracks from keypoints per image ``uv (n_i, 2)`` and verified matches ``{(i, j): (k, 2) index pairs}``.

    Returns tie points with NaN coordinates (forward intersection comes later)."""
    offset = np.concatenate([[0], np.cumsum([len(k) for k in keypoints])])
    pairs = [np.stack([offset[i] + m[:, 0], offset[j] + m[:, 1]], 1) for (i, j), m in matches.items() if len(m)]
    n_nodes = int(offset[-1])
    if not pairs or n_nodes == 0:
        return TiePoints(xyz=np.zeros((0, 3)), obs_track=np.zeros(0), obs_image=np.zeros(0),
                         obs_uv=np.zeros((0, 2)), image_ids=image_ids)
    pairs = np.concatenate(pairs)
    used = np.unique(pairs)
    label = union_find(n_nodes, pairs)[used]
    node_image = np.searchsorted(offset, used, side="right") - 1
    _, track = np.unique(label, return_inverse=True)
    # drop tracks with two keypoints in one image
    key = track * len(image_ids) + node_image
    _, first, counts = np.unique(key, return_index=True, return_counts=True)
    bad = np.zeros(track.max() + 1, bool)
    bad[track[first[counts > 1]]] = True
    rays = np.bincount(track)
    good = ~bad & (rays >= min_rays)
    if max_per_image > 0:
        keep = np.zeros_like(good)
        for img in range(len(image_ids)):
            t = np.unique(track[(node_image == img) & good[track]])
            keep[t[np.argsort(-rays[t], kind="stable")[:max_per_image]]] = True
        good &= keep
    sel = good[track]
    new = np.cumsum(good) - 1
    uv = np.concatenate(keypoints)[used[sel]]
    order = np.lexsort((node_image[sel], new[track[sel]]))
    return TiePoints(xyz=np.full((int(good.sum()), 3), np.nan), obs_track=new[track[sel]][order],
                     obs_image=node_image[sel][order], obs_uv=uv[order], image_ids=image_ids)
