"""Least-squares matching: known affine maps and sub-pixel shifts on analytic textures, radiometric invariance,
and the tie point refinement on rendered views of a textured plane."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.geometry.projection import intersect_with_plane_z, project
from oblique_city.core.matching.lsm import (
    LsmOptions,
    choose_references,
    extract_patches,
    initial_affines,
    lsm_match,
    refine_ties,
    sample_bicubic,
    sample_bilinear,
)
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose, TiePoints
from oblique_city.core.simulate.observations import look_rotation


def texture(x: np.ndarray, y: np.ndarray, seed: int = 0, w_max: float = 1.0, n: int = 60) -> np.ndarray:
    """A band-limited grey texture (sum of cosines, frequencies below ``w_max`` rad/px) at exact positions."""
    r = np.random.default_rng(seed)
    w = r.uniform(0.05, w_max, n)
    th = r.uniform(0, 2 * np.pi, n)
    ph = r.uniform(0, 2 * np.pi, n)
    a = r.uniform(5, 15, n)
    v = np.full(np.shape(x), 128.0)
    for k in range(n):
        v += a[k] * np.cos(w[k] * (np.cos(th[k]) * x + np.sin(th[k]) * y) + ph[k])
    return v


def _pair(gain: float = 1.0, offset: float = 0.0):
    """Source image, target image ``target(y) = gain * source(M y + o) + offset``, and the true map."""
    h, w = 200, 240
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    src = texture(xx, yy)
    m = np.array([[0.9, 0.15], [-0.1, 1.1]])
    o = np.array([3.37, -2.71])
    tgt = gain * texture(m[0, 0] * xx + m[0, 1] * yy + o[0], m[1, 0] * xx + m[1, 1] * yy + o[1]) + offset
    return src.astype(np.float32), tgt.astype(np.float32), m, o


@pytest.mark.parametrize("gain,offset", [(1.0, 0.0), (1.4, -30.0), (0.6, 25.0)])
def test_lsm_recovers_affine_and_subpixel_shift(gain, offset):
    src, tgt, m, o = _pair(gain, offset)
    rng = np.random.default_rng(1)
    s = np.round(rng.uniform(40, 160, (300, 2)))  # reference points on whole pixels (as refine_ties cuts them)
    m_inv = np.linalg.inv(m)
    truth = (s - o) @ m_inv.T
    start = truth + rng.uniform(-1.0, 1.0, truth.shape)  # SIFT-like starts, off by up to a pixel
    tmpl, inside = extract_patches(src, s, 7)
    assert inside.all()
    for affine0 in (np.broadcast_to(m_inv, (300, 2, 2)), None):  # predicted affine, identity
        res = lsm_match(tmpl, tgt, start, affine0)
        assert res.ok.mean() > 0.95
        err = np.abs(res.uv - truth)[res.ok]
        assert err.max() < 0.02, err.max()
        assert np.abs(err.mean(0)).max() < 0.005  # no bias from the radiometric gain and offset
        np.testing.assert_allclose(res.affine[res.ok], np.broadcast_to(m_inv, (res.ok.sum(), 2, 2)), atol=0.01)
    assert np.abs(start - truth).max() > 0.9


def test_bilinear_option_and_failures():
    src, tgt, m, o = _pair()
    rng = np.random.default_rng(2)
    s = np.round(rng.uniform(40, 160, (200, 2)))
    truth = (s - o) @ np.linalg.inv(m).T
    start = truth + rng.uniform(-1.0, 1.0, truth.shape)
    tmpl, _ = extract_patches(src, s, 7, "bilinear")
    res = lsm_match(tmpl, tgt, start, np.broadcast_to(np.linalg.inv(m), (200, 2, 2)),
                    LsmOptions(interpolation="bilinear"))
    assert res.ok.mean() > 0.95 and np.abs(res.uv - truth)[res.ok].max() < 0.08
    # flat templates, starts outside the image and wrong places fail and keep their start
    flat = np.full((3, 15, 15), 100.0, np.float32)
    bad = lsm_match(np.concatenate([flat, tmpl[:2]]), tgt,
                    np.array([[50.0, 50.0]] * 3 + [[-30.0, 50.0], [100.0, 100.0]]))
    assert not bad.ok[:4].any()
    np.testing.assert_array_equal(bad.uv[:4], [[50.0, 50.0]] * 3 + [[-30.0, 50.0]])
    with pytest.raises(ValueError):
        lsm_match(tmpl, tgt, start, None, LsmOptions(interpolation="nearest"))


def test_samplers_interpolate_exactly_on_pixels_and_linear_ramps():
    img = np.add.outer(np.arange(20.0) * 2.0, np.arange(30.0) * 3.0).astype(np.float32)  # 2 y + 3 x
    x = np.array([0.0, 4.25, 10.5, 28.9])
    y = np.array([0.0, 7.75, 3.5, 18.1])
    for f in (sample_bilinear, sample_bicubic):
        v, inside = f(img, x, y)
        np.testing.assert_allclose(v[1:3], 2 * y[1:3] + 3 * x[1:3], atol=1e-4)
        assert inside.all()
    _, inside = sample_bilinear(img, np.array([-0.1, 29.0, 29.5]), np.array([0.0, 19.0, 0.0]))
    assert inside.tolist() == [False, True, False]


def test_refine_ties_on_rendered_views_of_a_textured_plane():
    """Three views of a plane (analytic texture, exact rendering): SIFT-like perturbed observations of one ground
    point each come back to a consistent position (the reference's point) within a few hundredths of a pixel."""
    cam = CameraModel(id="c", width=400, height=300, fx=500.0, fy=500.0, cx=199.5, cy=149.5, k1=-0.02)
    down = np.array([0.0, 0.0, -1.0])
    poses = [Pose(look_rotation(down, np.array([0.0, -1.0, 0.0])), [0.0, 0.0, 100.0]),
             Pose(look_rotation(np.array([0.5, 0.0, -1.0]), np.array([0.0, -1.0, 0.0])), [-40.0, 5.0, 100.0]),
             Pose(look_rotation(np.array([0.0, -0.6, -1.0]), np.array([0.0, -1.0, 0.0])), [5.0, 50.0, 100.0])]
    uv_grid = np.stack(np.meshgrid(np.arange(400.0), np.arange(300.0)), -1).reshape(-1, 2)
    images = {}
    block = ImageBlock(crs="EPSG:25832")
    block.add_camera(cam)
    for k, p in enumerate(poses):
        g = intersect_with_plane_z(cam, p, uv_grid, 0.0)
        images[f"i{k}"] = texture(g[:, 0] * 4.0, g[:, 1] * 4.0, w_max=0.8).reshape(300, 400).astype(np.float32)
        block.add_image(Image(id=f"i{k}", camera_id="c", pose_approx=p))
    rng = np.random.default_rng(5)
    uv0 = rng.uniform([120, 90], [280, 210], (150, 2))
    ground = intersect_with_plane_z(cam, poses[0], uv0, 0.0)
    true_uv = np.stack([project(cam, p, ground)[0] for p in poses], 1)  # (150, 3, 2)
    ok = np.all((true_uv > 12) & (true_uv < [388, 288]), (1, 2))
    true_uv = true_uv[ok]
    n = len(true_uv)
    obs_uv = true_uv + rng.uniform(-0.6, 0.6, true_uv.shape)
    ties = TiePoints(xyz=np.full((n, 3), np.nan), obs_track=np.repeat(np.arange(n), 3),
                     obs_image=np.tile(np.arange(3), n), obs_uv=obs_uv.reshape(-1, 2), image_ids=["i0", "i1", "i2"])
    ref = choose_references(ties, block)
    assert np.all(ties.obs_image[ref] == 0)  # the nadir view
    aff = initial_affines(ties, block, ref)
    assert np.all(np.abs(np.linalg.det(aff[ties.obs_image == 1]) - 1.0) > 0.05)  # a real foreshortening
    done = []
    out, stats = refine_ties(ties, block, images.__getitem__, progress=lambda a, b, m: done.append((a, b)))
    assert done[-1][0] == done[-1][1]
    assert stats.references == n and stats.matched > 0.95 * 2 * n
    # every kept observation is consistent with its reference: the reference's ground point projects there
    ref_uv = out.obs_uv[out.obs_image == 0]
    g = intersect_with_plane_z(cam, poses[0], ref_uv, 0.0)
    for k in (1, 2):
        sel = out.obs_image == k
        pred, _ = project(cam, poses[k], g[out.obs_track[sel]])
        err = np.abs(out.obs_uv[sel] - pred)
        assert np.median(err) < 0.01 and err.max() < 0.05, (k, err.max())
    before = np.abs(obs_uv[:, 1] - project(cam, poses[1], intersect_with_plane_z(cam, poses[0], obs_uv[:, 0], 0.0))[0])
    assert np.median(before) > 0.2
    # the target images as units in two worker processes: the same tie points, progress to the end
    from oblique_city.core.pipeline.executor import Executor

    done.clear()
    with Executor("processes", workers=2) as ex:
        par, par_stats = refine_ties(ties, block, images.__getitem__, progress=lambda a, b, m: done.append((a, b)),
                                     executor=ex)
    # the same up to rounding: the workers' BLAS runs one thread, which sums the normal equations in another order
    assert done[-1][0] == done[-1][1]
    assert replace(par_stats, mean_shift_px=0.0) == replace(stats, mean_shift_px=0.0)
    assert par_stats.mean_shift_px == pytest.approx(stats.mean_shift_px, rel=1e-9)
    for f in ("obs_track", "obs_image"):
        assert np.array_equal(getattr(par, f), getattr(out, f))
    assert np.abs(par.obs_uv - out.obs_uv).max() < 1e-6
