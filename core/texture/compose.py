"""Texturing one surface: sample every candidate image at every texel, choose and blend, adjust radiometry.

Every texel's 3-D point on the surface plane is projected into each candidate image through the exact camera
model (pose, focal, principal point, Brown distortion) and the image is sampled bilinearly there: the texture is
a true orthographic rectification of the surface, never an affine warp of image triangles. Per texel the image
of highest quality (:func:`.sources.image_quality`) that sees the point unoccluded is chosen; the label map is
feathered with a Gaussian so seams between sources blend over a few texels, but a source only ever contributes
where it is itself valid (occluded parts never leak). Occlusion masks are grown by a margin, because the
occluder models are only as good as the reconstruction.

Radiometry: each image gets one gain per channel, solved in the log domain from the colour ratios of all pairs
of images that see the same texels (median of per-texel log ratios per pair, weighted by the square root of the
shared texel count, a weak pull of every gain towards 1 fixes the datum).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .occlusion import OcclusionScene
from .plane import TexelGrid, texel_grid
from .sources import ImageCache, ImageSource, image_quality


@dataclass(frozen=True)
class ComposeOptions:
    """Per-texel choice and blending.

    feather : Gaussian sigma of the seam blend (texels); occlusion_margin : growth of occluded areas (texels);
    ray_offset : start of the occlusion rays off the surface (m); min_cos : grazing limit (cosine);
    centre_weight : quality loss at image corners; min_overlap : shared texels for a radiometric pair
    """

    feather: float = 2.0
    occlusion_margin: int = 2
    ray_offset: float = 0.1
    min_cos: float = 0.15
    centre_weight: float = 0.25
    min_overlap: int = 50


@dataclass(eq=False)
class SurfacePatch:
    """The sampled texture of one surface before packing.

    surface_id, building_id : ids; grid : its texel grid; source_ids : the K candidate image ids;
    rows, cols : (n,) int texels sampled (the ring's texels grown by one); samples : (K, n, 3) uint8 colours
    per source; weights : (K, n) float32 blend weights (rows sum to 1 or 0 where no source sees the texel);
    in_ring : (n,) bool texel centre inside the ring; quality : (n,) float32 best quality (px per m)
    """

    surface_id: str
    building_id: str
    grid: TexelGrid
    source_ids: list[str]
    rows: np.ndarray
    cols: np.ndarray
    samples: np.ndarray
    weights: np.ndarray
    in_ring: np.ndarray
    quality: np.ndarray
    pairs: list[tuple[str, str, np.ndarray, int]] = field(default_factory=list)

    @property
    def coverage(self) -> float:
        """Share of the ring's texels that have a source."""
        has = self.weights.sum(0) > 0
        return float(has[self.in_ring].mean()) if self.in_ring.any() else 0.0

    def source_shares(self) -> dict[str, float]:
        """Image id -> share of the ring's texels it contributes (blend weights summed)."""
        if not self.in_ring.any():
            return {}
        w = self.weights[:, self.in_ring].sum(1) / self.in_ring.sum()
        return {sid: round(float(v), 4) for sid, v in zip(self.source_ids, w, strict=True) if v > 0}

    def colours(self, gains: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Blended colours ``(n, 3)`` float32 (0-255) after per-image gains ``{image id: (3,)}``."""
        out = np.zeros((len(self.rows), 3), np.float32)
        for k, sid in enumerate(self.source_ids):
            g = np.ones(3, np.float32) if gains is None else np.asarray(gains.get(sid, np.ones(3)), np.float32)
            w = self.weights[k]
            nz = w > 0
            out[nz] += w[nz, None] * np.clip(self.samples[k, nz].astype(np.float32) * g, 0, 255)
        return out


def sample_image(img: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """Bilinear colours ``(n, 3)`` uint8 of an image ``(h, w, 3)`` at pixel positions ``(n, 2)`` (centre of the
    top-left pixel at 0); outside positions give 0."""
    import cv2

    n = len(uv_px)
    width = 1024
    pad = (-n) % width
    m = np.nan_to_num(np.concatenate([uv_px, np.full((pad, 2), -10.0)]), nan=-10.0).astype(np.float32)
    mx, my = m[:, 0].reshape(-1, width), m[:, 1].reshape(-1, width)
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, img.shape[2])[:n]


def _grow(mask: np.ndarray, r: int) -> np.ndarray:
    import cv2

    if r <= 0 or not mask.any():
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def texture_surface(surface_id: str, building_id: str, ring_xyz: np.ndarray, texel: float,
                    candidates: list[ImageSource], cache: ImageCache, occluder: OcclusionScene | None,
                    opt: ComposeOptions = ComposeOptions()) -> SurfacePatch:
    """Sample, choose and blend the candidate images of one planar surface.

    Parameters
    ----------
    ring_xyz : (k, 3) float64 world ring (counter-clockwise from outside); texel : texel size (m)
    candidates : images to consider (see :func:`.sources.candidate_sources`); occluder : scene of all
    occluding geometry (None: no occlusion test)
    """
    import cv2

    grid = texel_grid(ring_xyz, texel)
    region = _grow(grid.mask, 1)
    rows, cols = np.nonzero(region)
    in_ring = grid.mask[rows, cols]
    xyz = grid.centres(rows, cols)
    normal = grid.frame.normal
    n, kk = len(rows), len(candidates)
    q = np.zeros((kk, n))
    samples = np.zeros((kk, n, 3), np.uint8)
    for k, src in enumerate(candidates):
        qk, uv = image_quality(src, xyz, normal, opt.min_cos, opt.centre_weight)
        ok = qk > 0
        if occluder is not None and ok.any():
            vis = occluder.visible(xyz[ok], normal, src.pose.C, opt.ray_offset)
            hidden = np.zeros(grid.shape, bool)
            hidden[rows[ok][~vis], cols[ok][~vis]] = True
            ok &= ~_grow(hidden, opt.occlusion_margin)[rows, cols]
        if not ok.any():
            continue
        q[k] = np.where(ok, qk, 0.0)
        rng = float(np.median(np.linalg.norm(src.pose.C - xyz[ok], axis=1)))
        level = max(0, int(np.floor(np.log2(max(src.camera.fx * texel / rng, 1.0) / 1.5 + 1e-12))))
        level = min(level, 4)
        uv_l = (uv[ok] + 0.5) / (1 << level) - 0.5
        samples[k, ok] = sample_image(cache.get(src, level), uv_l)
    has = q.max(0) > 0 if kk else np.zeros(n, bool)
    label = np.argmax(q, axis=0) if kk else np.zeros(n, np.int64)
    weights = np.zeros((kk, n), np.float32)
    for k in range(kk):
        sel = has & (label == k)
        if not sel.any():
            continue
        ind = np.zeros(grid.shape, np.float32)
        ind[rows[sel], cols[sel]] = 1.0
        if opt.feather > 0:
            ind = cv2.GaussianBlur(ind, (0, 0), opt.feather, borderType=cv2.BORDER_REPLICATE)
        weights[k] = ind[rows, cols] * (q[k] > 0)
    total = weights.sum(0)
    fallback = has & (total <= 1e-6)
    weights[label[fallback], np.flatnonzero(fallback)] = 1.0
    total = weights.sum(0)
    weights[:, total > 0] /= total[total > 0]
    patch = SurfacePatch(surface_id, building_id, grid, [c.id for c in candidates], rows, cols, samples, weights,
                         in_ring, q.max(0).astype(np.float32) if kk else np.zeros(n, np.float32))
    patch.pairs = overlap_pairs(patch, q > 0, opt.min_overlap)
    return patch


def overlap_pairs(patch: SurfacePatch, valid: np.ndarray, min_overlap: int) -> list[tuple[str, str, np.ndarray, int]]:
    """Radiometric observations of a patch: ``(image a, image b, d (3,), count)`` with ``d`` the median per-texel
    ``log(b) - log(a)`` per channel over the ring texels both images see (well exposed in both)."""
    out = []
    kk = len(patch.source_ids)
    logs = np.log(patch.samples.astype(np.float32) + 1.0)
    usable = valid & np.all((patch.samples > 8) & (patch.samples < 247), axis=2) & patch.in_ring
    for a in range(kk):
        for b in range(a + 1, kk):
            both = usable[a] & usable[b]
            c = int(both.sum())
            if c >= min_overlap:
                d = np.median(logs[b, both] - logs[a, both], axis=0)
                out.append((patch.source_ids[a], patch.source_ids[b], d, c))
    return out


def solve_gains(pairs: list[tuple[str, str, np.ndarray, int]], prior: float = 0.05) -> dict[str, np.ndarray]:
    """Per-image gains ``{id: (3,)}`` so that ``gain_a * colour_a = gain_b * colour_b`` on shared texels in the
    least-squares sense (log domain, weights sqrt(count), each log gain pulled to 0 with weight ``prior`` times
    the mean observation weight)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import lsqr

    ids = sorted({p[0] for p in pairs} | {p[1] for p in pairs})
    if not ids:
        return {}
    index = {s: i for i, s in enumerate(ids)}
    m = len(pairs)
    w = np.sqrt(np.array([p[3] for p in pairs], np.float64))
    rows = np.repeat(np.arange(m), 2)
    cols = np.array([[index[a], index[b]] for a, b, _, _ in pairs]).ravel()
    vals = np.stack([w, -w], 1).ravel()
    mat = coo_matrix((vals, (rows, cols)), shape=(m, len(ids))).tocsr()
    d = np.array([p[2] for p in pairs], np.float64)  # (m, 3): log b - log a = g_a - g_b
    damp = prior * float(w.mean())
    g = np.stack([lsqr(mat, w * d[:, c], damp=damp)[0] for c in range(3)], axis=1)
    return {s: np.exp(g[i]) for s, i in index.items()}


def choose_texel(best_quality: float, factor: float, min_texel: float, max_texel: float, extent: float,
                 max_side: int) -> float:
    """Texel size (m): the best image resolution on the surface (``1 / quality``, metres per pixel in the worst
    direction) times ``factor``, clipped to ``[min_texel, max_texel]`` and enlarged so the surface's larger
    extent (m) fits ``max_side`` texels."""
    t = factor / best_quality if best_quality > 0 else max_texel
    return float(max(np.clip(t, min_texel, max_texel), extent / max_side))
