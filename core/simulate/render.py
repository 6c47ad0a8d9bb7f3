"""Ray-cast rendering of the synthetic city (pure core: Open3D ``RaycastingScene`` + numpy).

Per image, one primary ray per pixel (optionally a few jittered sub-pixel rays) is cast through the *undistorted*
direction of the pixel centre (``camera.pixel_to_normalized``), so the image carries exactly the Brown distortion
of :mod:`..model.camera`. Hits are textured procedurally from the triangle's material and its metric texture
coordinates (no texture images), lit by a sun with cast shadows (one shadow ray per lit hit) plus sky light;
misses show the sky. Per-head radiometry (exposure, colour balance, vignetting) and sensor noise follow, then
sRGB-like gamma to 8 bits (or the ``bits`` of :class:`RenderConfig`).

Anti-aliasing of the textures is analytic: every pattern and noise octave is faded out when its period falls
below about two pixel footprints (the footprint comes from the hit distance and incidence), and the signalised
targets' discs are drawn with exact edge coverage, so one ray per pixel gives clean images; ``samples > 1`` adds
jittered rays for geometric edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import CameraModel, Pose
from .city import SEMANTIC, City

KINDS = ("grass", "field", "asphalt", "plaster", "brick", "tiles", "gravel", "metal", "glass", "wood", "tree", "bark")


@dataclass(frozen=True)
class HeadRadiometry:
    """Per-head radiometric differences: exposure gain, colour balance (3,), vignetting (relative fall-off at the
    image corner), dark offset in DN."""

    gain: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.25
    offset: float = 2.0


@dataclass(frozen=True)
class RenderConfig:
    """Lighting and sensor settings.

    sun_azimuth_deg, sun_elevation_deg : sun direction (azimuth clockwise from grid north)
    sun, sky : irradiance of the direct sun (on a surface facing it) and of the sky (on an upward surface)
    exposure : global scale before gamma; noise_dn : read noise (DN, 8 bit); shot : photon noise factor
    samples : rays per pixel (1 = centre ray; more = jittered sub-pixel rays averaged)
    shadows : cast shadow rays
    bits : significant bits of the values (8: uint8; 10 to 16: uint16 up to ``2**bits - 1``, as aerial cameras
    deliver them, the same picture and noise on a finer scale)
    """

    sun_azimuth_deg: float = 155.0
    sun_elevation_deg: float = 48.0
    sun: float = 1.0
    sky: float = 0.38
    exposure: float = 1.25
    noise_dn: float = 1.2
    shot: float = 0.35
    samples: int = 1
    shadows: bool = True
    seed: int = 0
    bits: int = 8

    def sun_direction(self) -> np.ndarray:
        """Unit vector towards the sun (east, north, up)."""
        az, el = np.radians(self.sun_azimuth_deg), np.radians(self.sun_elevation_deg)
        return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


DEFAULT_HEADS = {"nadir": HeadRadiometry(1.0, (1.0, 1.0, 1.0), 0.22),
                 "forward": HeadRadiometry(0.94, (1.02, 1.0, 0.97)),
                 "right": HeadRadiometry(1.05, (0.98, 1.0, 1.03), 0.28),
                 "backward": HeadRadiometry(1.02, (1.0, 0.99, 1.0)),
                 "left": HeadRadiometry(0.97, (1.03, 1.01, 0.98), 0.3)}


# ---------------------------------------------------------------------------------------------------- noise


class _NoiseTexture:
    """A periodic two-channel fractal noise texture with a mip pyramid (texel = 1 unit of texture space)."""

    def __init__(self, size: int = 512, seed: int = 12345) -> None:
        from scipy.ndimage import gaussian_filter

        rng = np.random.default_rng(seed)
        base = np.zeros((size, size, 2))
        for sigma, w in ((0.7, 0.35), (1.5, 0.5), (3.0, 0.6), (6.0, 0.7), (12.0, 0.8), (24.0, 0.9)):
            n = gaussian_filter(rng.standard_normal((size, size, 2)), (sigma, sigma, 0), mode="wrap")
            base += w * n / n.std()
        base /= base.std()
        levels = [base.astype(np.float32)]
        while levels[-1].shape[0] > 4:
            a = levels[-1]
            levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
        self.n_levels = len(levels)
        self.sizes = np.array([a.shape[0] for a in levels], np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes ** 2)[:-1]]).astype(np.int32)
        self.masks = (self.sizes - 1).astype(np.int32)  # sizes are powers of two: modulo by bitwise and
        self.shifts = np.log2(self.sizes).astype(np.int32)
        self.flat = np.concatenate([a.reshape(-1, 2) for a in levels])

    def sample(self, u: np.ndarray, v: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Bilinear lookup at texel coordinates ``(u, v)`` from the mip level matching ``footprint`` (texels);
        returns (n, 2) float32, zero mean, unit-ish variance at level 0."""
        lev = np.clip(np.log2(np.maximum(footprint, 1e-6)).astype(np.int32), 0, self.n_levels - 1)
        inv = np.ldexp(np.float32(1.0), -lev)
        # texel i of level L averages level-0 texels 2^L i .. 2^L (i + 1) - 1, so its centre lies at level-0
        # coordinate 2^L (i + 0.5) - 0.5: without the half-texel terms each level would show the texture shifted by
        # (2^L - 1) / 2 level-0 texels, and views at different distances would see the surface in different places
        x = (u.astype(np.float32) + np.float32(0.5)) * inv - np.float32(0.5)
        y = (v.astype(np.float32) + np.float32(0.5)) * inv - np.float32(0.5)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        mask, off, sh = self.masks[lev], self.offsets[lev], self.shifts[lev]
        ix, iy = x0.astype(np.int32), y0.astype(np.int32)
        i0, i1 = ix & mask, (ix + 1) & mask
        r0, r1 = off + ((iy & mask) << sh), off + (((iy + 1) & mask) << sh)
        t = self.flat
        return (t[r0 + i0] * (1 - fx) + t[r0 + i1] * fx) * (1 - fy) + (t[r1 + i0] * (1 - fx) + t[r1 + i1] * fx) * fy


def _hash01(a: np.ndarray, b: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer pair."""
    h = (a.astype(np.int64) * 374761393 + b.astype(np.int64) * 668265263 + seed * 982451653) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return ((h ^ (h >> 16)) & 0xFFFFFF) / float(0x1000000)


def _fade(period: float | np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Weight of a pattern of ``period`` metres seen with pixel footprint ``fp`` metres: 1 when the period spans
    4+ pixels, 0 below 2 pixels."""
    return np.clip(period / (2.0 * fp) - 1.0, 0.0, 1.0)


def _cell_contrast(width: float | np.ndarray, height: float | np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Standard-deviation factor of an independent random value per cell of ``width x height`` metres averaged
    over a pixel footprint of ``fp`` metres: 1 while a cell covers the footprint, ``sqrt(cell area) / fp`` when
    the footprint averages several cells (a random field keeps contrast under averaging, unlike a periodic one)."""
    return np.minimum(1.0, np.sqrt(width * height) / np.maximum(fp, 1e-6))


def _lines(x: np.ndarray, period: float, width: float, fp: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] of lines of ``width`` repeating every ``period`` along ``x``, band-limited: fades to the
    mean coverage ``width / period`` when the footprint grows."""
    f = np.mod(x, period)
    d = np.minimum(f, period - f)
    sharp = np.clip(0.5 + (0.5 * width - d) / np.maximum(fp, 1e-4), 0.0, 1.0)
    w = _fade(period, fp)
    return w * sharp + (1 - w) * (width / period)


# ---------------------------------------------------------------------------------------------------- renderer


class Renderer:
    """Renders images of one city; build once (one ``RaycastingScene``), call :meth:`render` per image."""

    def __init__(self, city: City, config: RenderConfig = RenderConfig(),
                 heads: dict[str, HeadRadiometry] | None = None) -> None:
        from scipy.spatial import cKDTree

        self.city, self.config = city, config
        self.heads = dict(DEFAULT_HEADS if heads is None else heads)
        self.scene = city.scene()
        self.normals = city.face_normals().astype(np.float32)
        mats = city.materials
        self.kind = np.array([KINDS.index(m.kind) for m in mats], np.int8)[city.material]
        self.col1 = np.array([m.color for m in mats], np.float32)
        self.col2 = np.array([m.color2 for m in mats], np.float32)
        self.mscale = np.array([m.scale for m in mats], np.float32)
        self.mseed = np.array([m.seed for m in mats], np.float32)
        self.mparam = np.array([m.param for m in mats], np.float64)
        self.maxis = np.array([m.axis for m in mats], np.int8)
        self.noise = _NoiseTexture()
        self.targets_local = city.targets[:, :2] - city.origin[:2]
        self.target_tree = cKDTree(self.targets_local) if len(self.targets_local) else None
        # coarse 2 m grid flagging cells near a target, so only a few hits are tested exactly
        self._tg0 = self.targets_local.min(0) - 4.0 if len(self.targets_local) else np.zeros(2)
        if len(self.targets_local):
            span = np.ceil((self.targets_local.max(0) + 4.0 - self._tg0) / 2.0).astype(int) + 1
            self._tgrid = np.zeros((span[0], span[1]), bool)
            for tx, ty in self.targets_local:
                i, j = int((tx - self._tg0[0]) / 2.0), int((ty - self._tg0[1]) / 2.0)
                self._tgrid[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
        self._dirs: dict[tuple, np.ndarray] = {}

    # ------------------------------------------------------------------ rays

    def _camera_dirs(self, camera: CameraModel, samples: int, seed: int) -> np.ndarray:
        """Camera-frame ray directions ``(samples, h*w, 3)`` with z = 1 (so t_hit is the z-depth)."""
        key = (camera, samples, seed)
        if key not in self._dirs:
            vv, uu = np.mgrid[0:camera.height, 0:camera.width]
            uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
            rng = np.random.default_rng(seed)
            # the centre ray first (it gives the depth), then jittered rays whose offsets average to zero: the
            # same offsets serve every pixel, so a non-zero mean would shift the whole image by it
            jit = np.zeros((samples, 2))
            if samples > 1:
                jit[1:] = rng.uniform(-0.5, 0.5, (samples - 1, 2))
                jit[1:] -= jit[1:].mean(axis=0)
            out = []
            for s in range(samples):
                xy = camera.pixel_to_normalized(uv + jit[s])
                out.append(np.column_stack([xy, np.ones(len(xy))]).astype(np.float32))
            if len(self._dirs) > 8:
                self._dirs.clear()
            self._dirs[key] = np.stack(out)
        return self._dirs[key]

    def cast(self, pose: Pose, dirs_cam: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays from the pose's centre along camera-frame directions ``(n, 3)``; returns Open3D's arrays
        (``t_hit`` in units of the direction, so z-depth when ``dirs_cam[:, 2] == 1``)."""
        import open3d as o3d

        d_world = dirs_cam.astype(np.float64) @ pose.R
        o = (pose.C - self.city.origin).astype(np.float32)
        rays = np.empty((len(d_world), 6), np.float32)
        rays[:, :3] = o
        rays[:, 3:] = d_world
        r = self.scene.cast_rays(o3d.core.Tensor(rays))
        return {"t_hit": r["t_hit"].numpy(), "ids": r["primitive_ids"].numpy().astype(np.int64),
                "bary": r["primitive_uvs"].numpy(), "d_world": d_world}

    def trace(self, camera: CameraModel, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Z-depth (distance along the optical axis, float32, +inf where the ray misses) and the index of the hit
        triangle (int64, -1 for none) of every pixel's centre ray, both (h, w)."""
        r = self.cast(pose, self._camera_dirs(camera, 1, 0)[0])
        t = r["t_hit"].reshape(camera.height, camera.width)
        ids = np.where(np.isfinite(t), r["ids"].reshape(t.shape), -1)
        return t, ids

    # ------------------------------------------------------------------ shading

    def _radiance(self, camera: CameraModel, pose: Pose, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear RGB ``(n, 3)`` for camera-frame rays ``dirs (n, 3)``, and the z-depth ``(n,)``."""
        import open3d as o3d

        cfg = self.config
        r = self.cast(pose, dirs)
        t, ids = r["t_hit"], r["ids"]
        hit = np.isfinite(t)
        out = np.empty((len(t), 3), np.float32)
        # sky: brighter and paler towards the horizon
        dn = r["d_world"][~hit]
        el = dn[:, 2] / np.linalg.norm(dn, axis=1)
        hz = np.clip(1.0 - el, 0.0, 1.0)[:, None]
        out[~hit] = (np.array([0.35, 0.5, 0.85]) * (1 - hz) + np.array([0.8, 0.85, 0.92]) * hz) * 1.1
        if not hit.any():
            return out, t
        hi = np.flatnonzero(hit)
        tri = ids[hi]
        d = r["d_world"][hi].astype(np.float32)
        dlen = np.sqrt(np.einsum("ij,ij->i", d, d))
        th = t[hi]
        p_local = (pose.C - self.city.origin).astype(np.float32) + d * th[:, None]
        n = self.normals[tri]
        cosi = np.einsum("ij,ij->i", n, d) / dlen
        n[cosi > 0] *= -1.0  # back faces (inside of hidden parts, trunk bottoms): shade as facing the camera
        fp = th * dlen / np.float32(camera.fx) / np.maximum(np.abs(cosi), np.float32(0.25))
        bary = r["bary"][hi]
        uvc = self.city.uv[tri]
        uv = (uvc[:, 0] * (1 - bary[:, 0:1] - bary[:, 1:2]) + uvc[:, 1] * bary[:, 0:1]
              + uvc[:, 2] * bary[:, 1:2])
        albedo = self.albedo(tri, uv, p_local, fp)
        # lighting
        sun = cfg.sun_direction().astype(np.float32)
        ndl = n @ sun
        lit = ndl > 0
        vis = np.ones(len(hi), np.float32)
        if cfg.shadows and lit.any():
            li = np.flatnonzero(lit)
            org = p_local[li] + n[li] * 0.03
            rays = np.empty((len(li), 6), np.float32)
            rays[:, :3] = org
            rays[:, 3:] = sun
            occ = self.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1e4).numpy()
            vis[li[occ]] = 0.0
        irr = cfg.sun * np.maximum(ndl, 0.0) * vis + cfg.sky * (0.55 + 0.45 * n[:, 2]) + 0.05
        out[hi] = albedo * irr[:, None]
        return out, t

    def albedo(self, tri: np.ndarray, uv: np.ndarray, p: np.ndarray, fp: np.ndarray) -> np.ndarray:
        """Procedural albedo ``(n, 3)`` of hits on triangles ``tri`` with texture coordinates ``uv`` (metres),
        local positions ``p`` and pixel footprints ``fp`` (metres): the simulator's own materials, public so that
        evaluations can compare textures with them."""
        mat = self.city.material[tri]
        kind = self.kind[tri]
        c1, c2 = self.col1[mat], self.col2[mat]
        scale = self.mscale[mat]
        seed_off = (self.mseed[mat] * np.float32(97.31))[:, None]
        out = np.empty((len(tri), 3), np.float32)
        for k in np.unique(kind):
            s = np.flatnonzero(kind == k)
            name = KINDS[k]
            u, v, f, sc = uv[s, 0], uv[s, 1], fp[s], scale[s]
            a, b = c1[s], c2[s]
            if name == "tree":
                u, v = p[s, 0] + 0.6 * p[s, 2], p[s, 1] - 0.5 * p[s, 2]
            nz = self.noise.sample((u + seed_off[s, 0]) / 0.12, (v - seed_off[s, 0]) / 0.12, f / 0.12)
            nz2 = self.noise.sample((u + seed_off[s, 0]) / 1.5 + 100.0, (v + seed_off[s, 0]) / 1.5, f / 1.5)
            big = self.noise.sample(u / 9.0 + 300.0, v / 9.0, f / 9.0)
            mix = np.clip(0.5 + 0.35 * nz2[:, 1:2] + 0.25 * big[:, 0:1], 0, 1)
            col = a * (1 - mix) + b * mix
            lum = 1.0 + 0.16 * nz[:, 0] + 0.14 * nz2[:, 0] + 0.08 * big[:, 1]
            if name == "tiles":  # rows of 1.1 x scale, tiles 0.73 x scale wide, staggered
                rh, tw = 1.1 * sc, 0.73 * sc
                row = np.floor(v / rh)
                tile = _hash01(row, np.floor((u + 0.5 * tw * (row % 2)) / tw), 7)
                lum *= 1.0 + _cell_contrast(tw, rh, f) * 0.25 * (tile - 0.5)
                lum *= 1.0 - 0.35 * _lines(v, rh, 0.18 * rh, f)
                patch = _hash01(np.floor(u / 1.3), np.floor(v / 0.99), 3)  # replaced tiles / moss patches
                lum *= 1.0 + 0.18 * (patch - 0.5) * _fade(1.0, f)
            elif name == "brick":  # bricks of length ``scale``, courses of 0.3 x scale
                ch = 0.3 * sc
                row = np.floor(v / ch)
                brick = _hash01(row, np.floor((u + 0.5 * sc * (row % 2)) / sc), 11)
                lum *= 1.0 + 0.3 * (brick - 0.5) * _cell_contrast(sc, ch, f)
                lum *= 1.0 - 0.3 * _lines(v, ch, 0.16 * ch, f)
                lum *= 1.0 + 0.12 * nz2[:, 1]
            elif name == "plaster":
                lum *= 1.0 + 0.08 * big[:, 0] + 0.05 * nz2[:, 1]
                lum *= 1.0 - 0.25 * _lines(v, 3.0, 0.18, f)  # floor cornices
            elif name == "glass":
                au, av = np.abs(u), np.abs(v)
                frame = np.maximum.reduce([np.clip((au - 0.86) * 8, 0, 1), np.clip((av - 0.88) * 8, 0, 1),
                                           np.clip((0.07 - au) * 14, 0, 1) * _fade(0.6, f),
                                           np.clip((0.05 - np.abs(v - 0.35)) * 20, 0, 1) * _fade(0.6, f)])
                sky = (0.6 + 0.5 * (v + 1)[:, None] * np.array([0.5, 0.6, 0.9])) * a
                col = sky * (1 - frame[:, None]) + b * frame[:, None]
                lum = 1.0 + 0.15 * nz2[:, 0]
            elif name == "asphalt":
                across = np.where(self.maxis[self.city.material[tri[s]]] == 0, p[s, 1], p[s, 0])
                along = np.where(self.maxis[self.city.material[tri[s]]] == 0, p[s, 0], p[s, 1])
                centre = self.mparam[self.city.material[tri[s]]]
                line = np.where(np.isfinite(centre), 1.0, 0.0)
                dd = np.abs(across - np.nan_to_num(centre))
                cov_line = np.clip(0.5 + (0.08 - dd) / np.maximum(f, 1e-3), 0, 1) * (np.mod(along, 9.0) < 3.0)
                side = np.clip(0.5 + (0.1 - np.abs(dd - 3.2)) / np.maximum(f, 1e-3), 0, 1)
                mark = np.clip(line * (cov_line + side), 0, 1)
                lum *= 1.0 + 0.25 * nz[:, 0] * _fade(0.3, f) + 0.2 * big[:, 0]
                col = col * (1 - mark[:, None]) + np.array([0.75, 0.75, 0.72]) * mark[:, None]
            elif name == "grass":
                clump = np.clip((nz2[:, 1] - 0.7) * 2.0, 0.0, 1.0)  # darker tufts and bare patches
                lum *= (1.0 + 0.3 * nz[:, 1] + 0.18 * big[:, 0]) * (1.0 - 0.35 * clump)
            elif name == "field":
                fid = _hash01(np.floor(p[s, 0] / sc), np.floor(p[s, 1] / (0.75 * sc)), 5)  # fields of scale
                palette = np.array([[0.30, 0.22, 0.12], [0.22, 0.32, 0.10], [0.45, 0.38, 0.16], [0.18, 0.26, 0.09]])
                col = palette[(fid * 4).astype(int) % 4] * (1.0 + 0.25 * mix - 0.12)
                ang = fid * np.pi
                furrow = _lines(p[s, 0] * np.cos(ang) + p[s, 1] * np.sin(ang), 1.5, 0.5, f)
                lum *= (1.0 - 0.3 * furrow * (1.0 + 0.4 * nz2[:, 1])) * (1.0 + 0.15 * big[:, 0])
            elif name == "wood":  # boards of width ``scale``
                lum *= 1.0 - 0.3 * _lines(v, sc, 0.15 * sc, f)
            elif name == "metal":  # standing seams every ``scale``
                lum *= 1.0 - 0.35 * _lines(u, sc, 0.1 * sc, f)
            elif name == "gravel":
                lum *= 1.0 + 0.2 * nz[:, 0] + 0.1 * big[:, 1]
                vent = _hash01(np.floor(u / 4.0), np.floor(v / 4.0), 13) > 0.8
                lum *= np.where(vent, 1.0 - 0.3 * _fade(4.0, f), 1.0)
            elif name == "tree":
                lum *= 0.9 + 0.35 * nz[:, 0] + 0.2 * nz2[:, 1]
            elif name == "bark":
                lum *= 1.0 + 0.2 * nz[:, 0]
            out[s] = col * np.clip(lum, 0.2, 2.0)[:, None]
        self._paint_targets(tri, p, fp, out)
        return out

    def _paint_targets(self, tri: np.ndarray, p: np.ndarray, fp: np.ndarray, out: np.ndarray) -> None:
        """Signalised targets: a 1.6 m black square with a white disc of radius ``City.TARGET_RADIUS`` on the
        ground, or a white cross (``City.target_pattern``), drawn with exact edge coverage."""
        if self.target_tree is None:
            return
        cell = np.floor((p[:, :2] - self._tg0) / 2.0).astype(np.int64)
        inside = ((cell[:, 0] >= 0) & (cell[:, 0] < self._tgrid.shape[0]) & (cell[:, 1] >= 0)
                  & (cell[:, 1] < self._tgrid.shape[1]))
        g = np.flatnonzero(inside)
        g = g[self._tgrid[cell[g, 0], cell[g, 1]] & (self.city.semantic[tri[g]] <= SEMANTIC["street"])]
        if len(g) == 0:
            return
        half = self.city.TARGET_HALF
        if len(self.targets_local) <= 64:
            gi, ti = [], []
            for k, (tx, ty) in enumerate(self.targets_local):
                m = np.flatnonzero((np.abs(p[g, 0] - tx) < 1.2 * half) & (np.abs(p[g, 1] - ty) < 1.2 * half))
                gi.append(g[m])
                ti.append(np.full(len(m), k))
            g, idx = np.concatenate(gi), np.concatenate(ti)
            dist = np.linalg.norm(p[g, :2] - self.targets_local[idx], axis=1)
        else:
            dist, idx = self.target_tree.query(p[g, :2], distance_upper_bound=1.5 * half)
            near = np.isfinite(dist)
            g, idx, dist = g[near], idx[near], dist[near]
        if len(g) == 0:
            return
        rel = p[g, :2] - self.targets_local[idx]
        f = np.maximum(fp[g], 1e-3)
        if self.city.target_pattern == "cross":
            length = [np.clip(0.5 + (half - np.abs(rel[:, k])) / f, 0, 1) for k in (0, 1)]
            width = [np.clip(0.5 + (self.city.TARGET_BAR - np.abs(rel[:, k])) / f, 0, 1) for k in (0, 1)]
            bar_x, bar_y = length[0] * width[1], length[1] * width[0]
            cover = bar_x + bar_y - bar_x * bar_y
            out[g] = out[g] * (1 - cover[:, None]) + 0.85 * cover[:, None]
            return
        sq = np.clip(0.5 + (half - np.abs(rel[:, 0])) / f, 0, 1) * np.clip(0.5 + (half - np.abs(rel[:, 1])) / f, 0, 1)
        disc = np.clip(0.5 + (self.city.TARGET_RADIUS - dist) / f, 0, 1)
        target = (0.03 + 0.82 * disc)[:, None] * np.ones(3)
        out[g] = out[g] * (1 - sq[:, None]) + target * sq[:, None]

    # ------------------------------------------------------------------ images

    def render(self, camera: CameraModel, pose: Pose, head: str | None = None, seed: int = 0,
               depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Render one image.

        Returns
        -------
        rgb : (h, w, 3) uint8 (uint16 for ``bits`` above 8)
        depth : (h, w) float32 z-depth of the centre ray (+inf for sky) when ``depth``, else None
        """
        cfg = self.config
        dirs = self._camera_dirs(camera, max(1, cfg.samples), cfg.seed)
        acc = None
        z = None
        for k in range(len(dirs)):
            rad, t = self._radiance(camera, pose, dirs[k])
            acc = rad if acc is None else acc + rad
            if k == 0:
                z = t
        lin = acc / len(dirs)
        hr = self.heads.get(head or "", HeadRadiometry())
        h, w = camera.height, camera.width
        vv, uu = np.mgrid[0:h, 0:w]
        r2 = (((uu - (w - 1) / 2) / (w / 2)) ** 2 + ((vv - (h - 1) / 2) / (h / 2)) ** 2).ravel() / 2.0
        vig = (1.0 - hr.vignetting * r2).astype(np.float32)
        lin = lin * (cfg.exposure * hr.gain * vig)[:, None] * np.asarray(hr.tint, np.float32)
        k = (2.0**cfg.bits - 1.0) / 255.0  # digital numbers per 8-bit one
        disp = np.clip(lin, 0, 1.5) ** (1 / 2.2) * (255.0 * k)
        rng = np.random.default_rng(seed)
        sigma = np.sqrt((cfg.noise_dn * k) ** 2 + cfg.shot * k * disp)
        img = disp + hr.offset * k + rng.standard_normal(disp.shape, dtype=np.float32) * sigma
        dtype = np.uint8 if cfg.bits <= 8 else np.uint16
        rgb = np.clip(np.rint(img), 0, 2.0**cfg.bits - 1.0).astype(dtype).reshape(h, w, 3)
        return rgb, (z.reshape(h, w) if depth else None)
