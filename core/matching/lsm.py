"""Least-squares matching (LSM) refinement of tie point observations.

A detector such as SIFT places the same ground feature at slightly different spots in different images (scale
space extrema move with the local image content and the view). LSM makes the observations of a track agree: one
reference observation (the most nadir-like view) keeps its position and its patch is matched into every other
image of the track with an affine geometric and a linear radiometric model,

    f(x) = r0 + r1 * g(A x + t),    x : offsets of the reference patch (pixels),

solved by Gauss-Newton on the intensities (8 parameters: ``A`` 2x2, ``t`` 2, ``r0``, ``r1``). ``t`` is the
refined position in the target image. The affine start comes from the approximate orientations: a plane through
the track's forward intersection, facing the reference camera, maps reference pixels into the target image; its
local Jacobian is ``A``. The reference patch is cut on whole pixels (its sub-pixel fraction goes through ``A``
into the target position), so it is never resampled; the target is resampled (cubic convolution by default:
bilinear interpolation damps sharp texture by a phase-dependent factor and biases matches by a few hundredths of a
pixel) on a grid one pixel wider than the patch, and the image gradients come from central differences of the
warped patch (``dg/dx = grad g . A``).

Observations that do not converge, leave the image, move more than ``max_shift_px`` from their start or correlate
below ``min_corr`` fail: :func:`refine_ties` drops them or keeps their original position (counted either way).
All positions use the core's pixel convention (origin at the centre of the top-left pixel).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from ..geometry.intersection import intersect_tracks
from ..geometry.projection import pixel_rays, project
from ..model import TiePoints


@dataclass(frozen=True)
class LsmOptions:
    """half : patch half size (patch ``2 half + 1`` square); iterations : Gauss-Newton iterations at most;
    tol_px : convergence when the position step is below it; max_shift_px : larger moves from the start fail;
    min_corr : lowest accepted correlation coefficient of the matched patches; min_std : templates with a lower
    grey value standard deviation are not matched (no texture); batch : observations per vectorised batch;
    interpolation : ``bicubic`` (default) or ``bilinear`` resampling of both patches."""

    half: int = 7
    iterations: int = 20
    tol_px: float = 0.01
    max_shift_px: float = 3.0
    min_corr: float = 0.8
    min_std: float = 2.0
    batch: int = 4096
    interpolation: str = "bicubic"


@dataclass
class LsmResult:
    """uv : (n, 2) float64 refined positions (the start where ``ok`` is False); ok : (n,) bool accepted;
    corr : (n,) float64 final correlation coefficient (NaN where not computed); affine : (n, 2, 2) float64;
    iterations : (n,) int64 iterations used."""

    uv: np.ndarray
    ok: np.ndarray
    corr: np.ndarray
    affine: np.ndarray
    iterations: np.ndarray


def _grid(half: int) -> np.ndarray:
    """Offsets ``(p*p, 2)`` (x, y) of a ``p = 2 half + 1`` patch, row-major."""
    r = np.arange(-half, half + 1, dtype=np.float64)
    yy, xx = np.meshgrid(r, r, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], 1)


def _cells(shape: tuple[int, int], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
    """For samples at ``x, y`` in an image of ``shape (h, w)``: the mask of those inside, and the integer cell
    ``x0, y0`` (intp) and float32 fractions ``fx, fy`` of the positions clamped to the image."""
    h, w = shape
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    x = np.clip(x, 0, w - 1.000001)
    y = np.clip(y, 0, h - 1.000001)
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    return inside, x0, y0, (x - x0).astype(np.float32), (y - y0).astype(np.float32)


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``image (h, w)`` at ``x, y`` (any equal shapes; pixel-centre origin).

    Returns the values (float32, the shape of ``x``) and a mask of samples inside the image (outside samples are
    clamped to the border)."""
    w = image.shape[1]
    inside, x0, y0, fx, fy = _cells(image.shape, x, y)
    flat = image.reshape(-1)
    i = y0 * w + x0
    v00 = flat[i].astype(np.float32)
    v01 = flat[i + 1].astype(np.float32)
    v10 = flat[i + w].astype(np.float32)
    v11 = flat[i + w + 1].astype(np.float32)
    top = v00 + fx * (v01 - v00)
    bottom = v10 + fx * (v11 - v10)
    return top + fy * (bottom - top), inside


def _keys(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Weights of the 4 taps at offsets -1, 0, 1, 2 of Keys' cubic convolution (a = -0.5) for fractions ``t``."""
    t2, t3 = t * t, t * t * t
    return (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2)


def sample_bicubic(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic convolution samples (Keys, a = -0.5) of ``image (h, w)`` at ``x, y``, as :func:`sample_bilinear`.

    Bilinear interpolation damps the image by a factor that depends on the sub-pixel phase, which pulls a match
    towards pixel centres by a few hundredths of a pixel on sharp texture; the cubic kernel keeps that below 0.01
    px. Samples within one pixel of the border use clamped taps."""
    h, w = image.shape
    inside, x0, y0, fx, fy = _cells(image.shape, x, y)
    wx, wy = _keys(fx), _keys(fy)
    flat = image.reshape(-1)
    out = np.zeros(x.shape, np.float32)
    cols = [np.clip(x0 + d, 0, w - 1) for d in (-1, 0, 1, 2)]
    for j, dy in enumerate((-1, 0, 1, 2)):
        row = np.clip(y0 + dy, 0, h - 1) * w
        acc = wx[0] * flat[row + cols[0]]
        for i in range(1, 4):
            acc += wx[i] * flat[row + cols[i]]
        out += wy[j] * acc
    return out, inside


def _sampler(interpolation: str) -> Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    if interpolation not in ("bilinear", "bicubic"):
        raise ValueError(f"interpolation '{interpolation}' unknown (use bilinear or bicubic)")
    return sample_bicubic if interpolation == "bicubic" else sample_bilinear


def extract_patches(image: np.ndarray, uv: np.ndarray, half: int = 7,
                    interpolation: str = "bicubic") -> tuple[np.ndarray, np.ndarray]:
    """Patches ``(n, p, p) float32`` (``p = 2 half + 1``) of ``image (h, w)`` centred on ``uv (n, 2)``, and a mask
    ``(n,)`` of patches entirely inside the image."""
    g = _grid(half)
    x = uv[:, 0:1] + g[None, :, 0]
    y = uv[:, 1:2] + g[None, :, 1]
    v, inside = _sampler(interpolation)(image, x, y)
    p = 2 * half + 1
    return v.reshape(-1, p, p), inside.all(1)


def lsm_match(template: np.ndarray, image: np.ndarray, uv0: np.ndarray, affine0: np.ndarray | None = None,
              opt: LsmOptions = LsmOptions()) -> LsmResult:
    """Match reference patches into one target image by least squares (module docstring).

    Parameters
    ----------
    template : (n, p, p) float32 reference patches (``p = 2 opt.half + 1``), centred on the reference points
    image : (h, w) target image (uint8 or float)
    uv0 : (n, 2) float64 start positions in the target image
    affine0 : (n, 2, 2) float64 start of ``A`` (reference pixel offsets -> target pixel offsets), identity if None
    """
    n = len(uv0)
    if affine0 is None:
        affine0 = np.broadcast_to(np.eye(2), (n, 2, 2))
    out = LsmResult(uv=np.array(uv0, np.float64, copy=True), ok=np.zeros(n, bool), corr=np.full(n, np.nan),
                    affine=np.array(affine0, np.float64, copy=True), iterations=np.zeros(n, np.int64))
    for s in range(0, n, opt.batch):
        sl = slice(s, min(s + opt.batch, n))
        _lsm_batch(template[sl], image, out, sl, opt)
    return out


def _lsm_batch(template: np.ndarray, image: np.ndarray, out: LsmResult, sl: slice, opt: LsmOptions) -> None:
    sample = _sampler(opt.interpolation)
    half = opt.half
    p = 2 * half + 1
    ge = _grid(half + 1)  # extended grid for central differences
    gi = _grid(half)  # (N, 2) inner grid
    f = template.reshape(len(template), -1).astype(np.float64)
    f_std = f.std(1)
    t = out.uv[sl].copy()
    a = out.affine[sl].copy()
    start = t.copy()
    m = len(t)
    r0 = np.zeros(m)
    r1 = np.ones(m)
    active = f_std >= opt.min_std
    converged = np.zeros(m, bool)
    failed = ~active
    iters = np.zeros(m, np.int64)
    first = True
    for _ in range(opt.iterations):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        ai, ti = a[idx], t[idx]
        pos = ti[:, None, :] + ge @ ai.transpose(0, 2, 1)  # (k, N, 2): A applied to every grid offset
        g_ext, inside = sample(image, pos[..., 0], pos[..., 1])
        g_ext = g_ext.reshape(len(idx), p + 2, p + 2).astype(np.float64)
        out_of_image = ~inside.all(1)
        g = g_ext[:, 1:-1, 1:-1].reshape(len(idx), -1)
        dgx = ((g_ext[:, 1:-1, 2:] - g_ext[:, 1:-1, :-2]) * 0.5).reshape(len(idx), -1)
        dgy = ((g_ext[:, 2:, 1:-1] - g_ext[:, :-2, 1:-1]) * 0.5).reshape(len(idx), -1)
        det = ai[:, 0, 0] * ai[:, 1, 1] - ai[:, 0, 1] * ai[:, 1, 0]
        bad_det = np.abs(det) < 1e-6
        det = np.where(bad_det, 1.0, det)
        inv = np.stack([np.stack([ai[:, 1, 1], -ai[:, 0, 1]], 1), np.stack([-ai[:, 1, 0], ai[:, 0, 0]], 1)], 1)
        inv /= det[:, None, None]
        # image gradient at the warped positions: [gu, gv] = [dgx, dgy] A^-1
        gu = dgx * inv[:, 0, 0, None] + dgy * inv[:, 1, 0, None]
        gv = dgx * inv[:, 0, 1, None] + dgy * inv[:, 1, 1, None]
        if first:
            gs = g.std(1)
            r1[idx] = np.where(gs > 1e-6, f_std[idx] / np.maximum(gs, 1e-6), 1.0)
            r0[idx] = f[idx].mean(1) - r1[idx] * g.mean(1)
            first = False
        q1 = r1[idx, None]
        e = f[idx] - (r0[idx, None] + q1 * g)
        x, y = gi[None, :, 0], gi[None, :, 1]
        ju, jv = q1 * gu, q1 * gv
        jac = np.stack([ju, jv, ju * x, ju * y, jv * x, jv * y, np.ones_like(g), g], 2)  # (k, N, 8)
        jac_t = jac.transpose(0, 2, 1)
        nmat = jac_t @ jac  # batched BLAS products: a tenth of the time of the equivalent einsum
        bvec = (jac_t @ e[:, :, None])[:, :, 0]
        nmat += np.eye(8)[None] * 1e-9 * np.trace(nmat, axis1=1, axis2=2)[:, None, None]
        try:
            dp = np.linalg.solve(nmat, bvec[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            dp = np.zeros((len(idx), 8))
            for k in range(len(idx)):
                try:
                    dp[k] = np.linalg.solve(nmat[k], bvec[k])
                except np.linalg.LinAlgError:
                    dp[k] = np.nan
        bad = out_of_image | bad_det | ~np.all(np.isfinite(dp), 1)
        dp[bad] = 0.0
        t[idx] += dp[:, 0:2]
        a[idx, 0, 0] += dp[:, 2]
        a[idx, 0, 1] += dp[:, 3]
        a[idx, 1, 0] += dp[:, 4]
        a[idx, 1, 1] += dp[:, 5]
        r0[idx] += dp[:, 6]
        r1[idx] += dp[:, 7]
        iters[idx] += 1
        moved = np.linalg.norm(t[idx] - start[idx], axis=1)
        fail_now = bad | (moved > opt.max_shift_px)
        failed[idx[fail_now]] = True
        done = ~fail_now & (np.abs(dp[:, 0:2]).max(1) < opt.tol_px)
        converged[idx[done]] = True
        active[idx[fail_now | done]] = False
    # final correlation at the solution
    idx = np.flatnonzero(converged & ~failed)
    corr = np.full(m, np.nan)
    if len(idx):
        pos = t[idx][:, None, :] + gi @ a[idx].transpose(0, 2, 1)
        g, inside = sample(image, pos[..., 0], pos[..., 1])
        g = g.astype(np.float64)
        fc = f[idx] - f[idx].mean(1, keepdims=True)
        gc = g - g.mean(1, keepdims=True)
        den = np.sqrt((fc * fc).sum(1) * (gc * gc).sum(1))
        c = np.where(den > 0, (fc * gc).sum(1) / np.maximum(den, 1e-12), 0.0)
        c[~inside.all(1)] = 0.0
        corr[idx] = c
    ok = converged & ~failed & (np.nan_to_num(corr, nan=-1.0) >= opt.min_corr)
    uv = out.uv[sl].copy()
    uv[ok] = t[ok]
    aff = out.affine[sl].copy()
    aff[ok] = a[ok]
    out.uv[sl] = uv
    out.affine[sl] = aff
    out.ok[sl] = ok
    out.corr[sl] = corr
    out.iterations[sl] = iters


def choose_references(ties: TiePoints, block, image_ids: list[str] | None = None) -> np.ndarray:
    """Index ``(n_tracks,)`` into the observations of each track's reference: the most nadir-like ray (the
    steepest look direction), -1 for tracks without observations. Uses the approximate orientations."""
    ids = ties.image_ids if image_ids is None else image_ids
    steep = np.full(ties.n_obs, -np.inf)
    for k, iid in enumerate(ids):
        sel = np.flatnonzero(ties.obs_image == k)
        if len(sel) == 0:
            continue
        img = block.images[iid]
        d = pixel_rays(block.camera_of(iid), img.pose_approx, ties.obs_uv[sel])
        steep[sel] = -d[:, 2]
    order = np.lexsort((-steep, ties.obs_track))
    first = np.r_[True, ties.obs_track[order][1:] != ties.obs_track[order][:-1]]
    ref = np.full(ties.n_tracks, -1, np.int64)
    ref[ties.obs_track[order[first]]] = order[first]
    return ref


def initial_affines(ties: TiePoints, block, ref: np.ndarray, step_px: float = 2.0) -> np.ndarray:
    """Affine starts ``(n_obs, 2, 2)``: the Jacobian of reference pixel -> target pixel through a plane through
    the track's forward intersection (approximate orientations) facing the reference camera. Identity for the
    references themselves and where the geometry fails."""
    ids = ties.image_ids
    n = ties.n_obs
    origins = np.zeros((n, 3))
    dirs = np.zeros((n, 3))
    for k, iid in enumerate(ids):
        sel = np.flatnonzero(ties.obs_image == k)
        if len(sel) == 0:
            continue
        pose = block.images[iid].pose_approx
        origins[sel] = pose.C
        dirs[sel] = pixel_rays(block.camera_of(iid), pose, ties.obs_uv[sel])
    xyz, _ = intersect_tracks(origins, dirs, ties.obs_track, ties.n_tracks)
    ref_obs = ref[ties.obs_track]
    c_ref = origins[ref_obs]
    normal = c_ref - xyz[ties.obs_track]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    uv_ref = ties.obs_uv[ref_obs]
    img_ref = ties.obs_image[ref_obs]
    # plane points of the reference pixel offsets (+-step along u and v), per reference image
    offsets = np.array([[step_px, 0.0], [-step_px, 0.0], [0.0, step_px], [0.0, -step_px]])
    world = np.full((n, 4, 3), np.nan)
    for k, iid in enumerate(ids):
        sel = np.flatnonzero(img_ref == k)
        if len(sel) == 0:
            continue
        pose = block.images[iid].pose_approx
        cam = block.camera_of(iid)
        pts = (uv_ref[sel][:, None, :] + offsets[None]).reshape(-1, 2)
        d = pixel_rays(cam, pose, pts).reshape(len(sel), 4, 3)
        x0 = xyz[ties.obs_track[sel]]
        nn = normal[sel]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("ki,ki->k", x0 - pose.C, nn)[:, None] / np.einsum("kji,ki->kj", d, nn)
        world[sel] = pose.C + d * s[:, :, None]
    aff = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    for k, iid in enumerate(ids):
        sel = np.flatnonzero((ties.obs_image == k) & (np.arange(n) != ref_obs))
        if len(sel) == 0:
            continue
        uv, _ = project(block.camera_of(iid), block.images[iid].pose_approx, world[sel].reshape(-1, 3))
        uv = uv.reshape(len(sel), 4, 2)
        col_u = (uv[:, 0] - uv[:, 1]) / (2 * step_px)
        col_v = (uv[:, 2] - uv[:, 3]) / (2 * step_px)
        jac = np.stack([col_u, col_v], 2)  # (k, 2 (target u, v), 2 (ref u, v))
        good = np.all(np.isfinite(jac), (1, 2))
        det = np.linalg.det(np.where(good[:, None, None], jac, np.eye(2)))
        good &= (np.abs(det) > 0.05) & (np.abs(det) < 20.0)
        aff[sel[good]] = jac[good]
    return aff


@dataclass
class RefineStats:
    """Counts of :func:`refine_ties`: ``matched`` non-reference observations accepted, ``failed`` the others
    (no texture, out of the image, no convergence, low correlation), ``references`` one per track,
    ``dropped_obs``/``dropped_tracks`` removed (failed observations and tracks left with fewer than two rays
    when ``drop_failed``); ``mean_shift_px`` the mean move of the accepted ones."""

    matched: int = 0
    failed: int = 0
    references: int = 0
    dropped_obs: int = 0
    dropped_tracks: int = 0
    mean_shift_px: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True, eq=False)
class LsmUnit:
    """The observations of one target image for :func:`lsm_unit`: ``read_image(image_id)`` gives the image (a
    picklable callable when units run in worker processes); ``templates (n, p, p)``, ``start (n, 2)``,
    ``affine (n, 2, 2)`` as :func:`lsm_match` takes them."""

    read_image: Callable[[str], np.ndarray]
    image_id: str
    templates: np.ndarray
    start: np.ndarray
    affine: np.ndarray
    opt: LsmOptions


def lsm_unit(unit: LsmUnit) -> LsmResult:
    """Executor unit of :func:`refine_ties`: the reference patches matched into one target image."""
    return lsm_match(unit.templates.astype(np.float32), unit.read_image(unit.image_id), unit.start, unit.affine,
                     unit.opt)


def template_unit(item: tuple[Callable[[str], np.ndarray], str, np.ndarray, LsmOptions]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Executor unit of :func:`refine_ties`: the reference patches ``(n, p, p)`` (uint8 for uint8 images) of one
    reference image ``(read_image, image_id, centres (n, 2) on whole pixels, options)`` and their inside mask."""
    read_image, iid, centres, opt = item
    img = read_image(iid)
    patch, ok = extract_patches(img, centres, opt.half, opt.interpolation)
    return (np.rint(patch).astype(np.uint8) if img.dtype == np.uint8 else patch), ok


def refine_ties(ties: TiePoints, block, read_image: Callable[[str], np.ndarray], opt: LsmOptions = LsmOptions(),
                progress: Callable[[int, int, str], None] | None = None,
                drop_failed: bool = True, executor=None) -> tuple[TiePoints, RefineStats]:
    """Refine every non-reference observation of ``ties`` by LSM (module docstring); the reference patches are
    cut on whole pixels around the rounded reference position and the fraction is carried by the affine map.

    ``read_image(image_id)`` returns the grey image ``(h, w)``; each image is read twice (once as a reference,
    once as a target). The reference images (:func:`template_unit`) and then the target images (:class:`LsmUnit`
    items for :func:`lsm_unit`) go through ``executor`` (``map(fn, items, on_done)``, see pipeline.executor) when
    one is given, one after the other here otherwise; memory holds an image per worker and the templates
    ``(n_tracks, p, p)`` (uint8 for uint8 images) twice while the units exist. Returns new tie points (refined
    ``obs_uv``) and the counts. ``drop_failed`` removes the observations LSM could not confirm (on the demo block
    most of them are mismatches: 2.5% of the tracks miss their true point by 1.5 px afterwards against 6.5% when
    they keep their SIFT position) and the tracks left with one ray; else they keep their position."""
    ids = ties.image_ids
    ref = choose_references(ties, block)
    aff = initial_affines(ties, block, ref)
    p = 2 * opt.half + 1
    templates: np.ndarray | None = None  # uint8 for uint8 images: whole-pixel templates are the pixel values
    tmpl_ok = np.zeros(ties.n_tracks, bool)
    has = ref >= 0
    ref_img = np.full(ties.n_tracks, -1, np.int64)
    ref_img[has] = ties.obs_image[ref[has]]
    total = 2 * len(ids)
    # templates on whole pixels (no resampling of the reference); the fraction goes into the target position
    centre = np.zeros((ties.n_tracks, 2))
    centre[has] = np.round(ties.obs_uv[ref[has]])
    frac = np.zeros((ties.n_tracks, 2))
    frac[has] = ties.obs_uv[ref[has]] - centre[has]
    def run(fn: Callable, items: list, offset: int, what: str) -> list:
        def done(d: int, t: int) -> None:
            if progress:
                progress(offset + d * len(ids) // max(t, 1), total, f"LSM {what} {d}/{t} images")

        if executor is not None:
            return executor.map(fn, items, on_done=done)
        out = []
        for it in items:
            out.append(fn(it))
            done(len(out), len(items))
        return out

    refs = [(k, np.flatnonzero(ref_img == k)) for k in range(len(ids))]
    refs = [(k, tr) for k, tr in refs if len(tr)]
    for (_, tr), (patch, ok) in zip(refs, run(template_unit, [(read_image, ids[k], centre[tr], opt)
                                                               for k, tr in refs], 0, "templates"), strict=True):
        if templates is None:
            templates = np.zeros((ties.n_tracks, p, p), patch.dtype)
        templates[tr], tmpl_ok[tr] = patch, ok
    uv = ties.obs_uv.copy()
    ref_obs = ref[ties.obs_track]
    is_ref = np.arange(ties.n_obs) == ref_obs
    accepted = np.zeros(ties.n_obs, bool)
    sels, units = [], []
    for k, iid in enumerate(ids):
        sel = np.flatnonzero((ties.obs_image == k) & ~is_ref & tmpl_ok[ties.obs_track])
        if len(sel) == 0:
            continue
        start = uv[sel] - np.einsum("kij,kj->ki", aff[sel], frac[ties.obs_track[sel]])
        sels.append(sel)
        units.append(LsmUnit(read_image, iid, templates[ties.obs_track[sel]], start, aff[sel], opt))

    for sel, res in zip(sels, run(lsm_unit, units, len(ids), "matching"), strict=True):
        d = frac[ties.obs_track[sel]]
        ok = res.ok
        uv[sel[ok]] = res.uv[ok] + np.einsum("kij,kj->ki", res.affine[ok], d[ok])
        accepted[sel] = ok
    if progress:
        progress(total, total, "LSM done")
    shift = np.linalg.norm(uv - ties.obs_uv, axis=1)
    stats = RefineStats(matched=int(accepted.sum()), failed=int((~is_ref).sum() - accepted.sum()),
                        references=int(is_ref.sum()),
                        mean_shift_px=float(shift[accepted].mean()) if accepted.any() else 0.0)
    if not drop_failed:
        out = TiePoints(xyz=ties.xyz.copy(), obs_track=ties.obs_track, obs_image=ties.obs_image, obs_uv=uv,
                        image_ids=list(ids), obs_blunder=ties.obs_blunder, colour=ties.colour,
                        extra=dict(ties.extra))
        return out, stats
    keep = accepted | (is_ref & tmpl_ok[ties.obs_track])
    rays = np.bincount(ties.obs_track[keep], minlength=ties.n_tracks)
    keep &= rays[ties.obs_track] >= 2
    good = rays >= 2
    new = np.cumsum(good) - 1
    out = TiePoints(xyz=ties.xyz[good], obs_track=new[ties.obs_track[keep]], obs_image=ties.obs_image[keep],
                    obs_uv=uv[keep], image_ids=list(ids), obs_blunder=ties.obs_blunder[keep],
                    colour=None if ties.colour is None else ties.colour[good])
    stats.dropped_obs = int(ties.n_obs - keep.sum())
    stats.dropped_tracks = int(ties.n_tracks - good.sum())
    return out, stats
