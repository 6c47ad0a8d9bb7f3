"""Window detection on synthetic facades: grid recovery with noise, a missing window, an occluding blob."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from oblique_city.core.evaluate.windows import window_scores
from oblique_city.core.windows.detect import WindowOptions, boxes_to_world, darkness_map, detect_windows

from .facade import render_facade, window_grid

TEXEL = 0.15
W, H = 13.0, 10.0


def to_world(boxes: np.ndarray) -> list[np.ndarray]:
    """Texel boxes of the synthetic facade to 3-D corners on the plane y = 0 (x along the wall, z up)."""
    return list(boxes_to_world(boxes, np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), 0.0, H, TEXEL))


def truth_world(windows) -> list[np.ndarray]:
    return [np.array([[a, 0, b], [c, 0, b], [c, 0, d], [a, 0, d]], np.float64) for a, b, c, d in windows]


def test_grid_with_noise_and_a_missing_window():
    wins = window_grid()
    img = render_facade(wins, W, H, TEXEL, noise=10.0)
    dets = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, WindowOptions(grow_m=0.0))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    # 11 windows (one cell of the 4 x 3 grid has none: the grid must not invent it)
    assert s.true_windows == 11 and s.precision == 1.0 and s.recall == 1.0
    assert s.iou_mean > 0.85 and s.corner_rmse_m < 0.5 * TEXEL


def test_frame_is_recovered_by_grow():
    """A light window frame shrinks the dark glass; ``grow_m`` of the frame's width gives the opening back."""
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=6.0, frame_m=0.12, seed=3)
    # the darkness cue without bar closing (the colour cue sees the frame as window, and the closing joins the
    # glass to the frame texels dark enough to pass the threshold)
    opt = WindowOptions(polarity="dark", bar_m=0.0)
    shrunk = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, replace(opt, grow_m=0.0))
    grown = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, replace(opt, grow_m=0.12))
    a = window_scores(to_world(np.array([d.box for d in shrunk])), truth_world(wins))
    b = window_scores(to_world(np.array([d.box for d in grown])), truth_world(wins))
    assert a.recall == b.recall == 1.0 and b.precision == 1.0
    assert b.corner_rmse_m < a.corner_rmse_m and b.corner_rmse_m < 0.6 * TEXEL


def test_occluding_blob_is_rejected_and_the_hidden_window_filled_from_the_grid():
    wins = window_grid(missing=())
    # a dark tree crown over the lower-left window and the wall beside it: one component too big for a window
    img = render_facade(wins, W, H, TEXEL, noise=8.0, seed=1, blob=(2.6, 1.4, 1.2, 0.9))
    opt = WindowOptions(grow_m=0.0)
    dets = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, opt)
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0
    assert sum(d.source == "grid" for d in dets) == 1


def test_isolated_blob_off_the_grid_is_dropped():
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=8.0, seed=2)
    rr, cc = int((H - 2.4) / TEXEL), int(12.2 / TEXEL)  # a small dark stain between columns and floors
    img[rr:rr + 5, cc:cc + 4] = (60, 60, 60)
    dets = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, WindowOptions(grow_m=0.0))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0


def test_unseen_texels_are_not_windows():
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=8.0)
    seen = np.ones(img.shape[:2], bool)
    seen[:, : int(4.0 / TEXEL)] = False  # the left columns hidden
    img[~seen] = 0
    dark = darkness_map(img, seen, TEXEL)
    assert np.all(dark[~seen] == 0)
    dets = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0))
    assert all(d.box[0] >= 4.0 / TEXEL - 1 for d in dets)
    assert window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins)).matched == 9


def test_a_window_with_a_glazing_bar_is_one_window():
    """A 0.2 m bar down the middle leaves two 0.5 m panes (0.45 m dark enough at 0.15 m texels): too narrow."""
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=6.0, bar_m=0.2, seed=4)
    seen = np.ones(img.shape[:2], bool)
    split = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0, bar_m=0.0, polarity="dark"))
    dets = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0))
    assert window_scores(to_world(np.array([d.box for d in split])), truth_world(wins)).matched == 0
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0 and s.corner_rmse_m < 0.5 * TEXEL


def test_windows_cut_by_unseen_texels_get_the_facade_window_height():
    """No image saw the wall above 7.7 m (under an eave): the top row shows 0.7 m of its 1.5 m windows. They
    keep their seen bottom edge and get the height of the facade's whole windows."""
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=6.0, seed=5)
    seen = np.ones(img.shape[:2], bool)
    seen[: int(round((H - 7.7) / TEXEL))] = False
    img[~seen] = 0
    dets = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0 and s.corner_rmse_m < 0.5 * TEXEL


def test_boxes_to_world_lie_on_the_wall_plane_counter_clockwise():
    origin = np.array([500000.0, 5400000.0, 100.0])
    e1 = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    e2 = np.array([0.0, 0.0, 1.0])
    normal = np.cross(e1, e2)
    c = boxes_to_world(np.array([[10.0, 20.0, 18.0, 30.0]]), origin, e1, e2, -5.0, 8.0, 0.1)[0]
    assert c.shape == (4, 3)
    assert np.allclose((c - origin) @ normal, 0.0, atol=1e-9)
    assert np.allclose((c - origin) @ e1, [-4.0, -3.2, -3.2, -4.0])  # s = s0 + x texel
    assert np.allclose(c[:, 2] - origin[2], [5.0, 5.0, 6.0, 6.0])  # t = t1 - y texel: bottom first
    n = np.cross(c[1] - c[0], c[2] - c[1])
    assert n @ normal > 0  # counter-clockwise seen from outside


@pytest.mark.parametrize("texel", [0.1, 0.2])
def test_window_size_limits_in_metres(texel):
    """Windows smaller than ``min_width`` are not reported, whatever the texel size (by the darkness cue: the
    colour cue measures these 0.35 m windows, under two 0.2 m texels, 0.51-0.54 m wide)."""
    wins = window_grid(w=0.35, h=0.5, missing=())
    img = render_facade(wins, W, H, texel, noise=4.0)
    assert detect_windows(img, np.ones(img.shape[:2], bool), texel, WindowOptions(grow_m=0.0, polarity="dark")) == []


def test_blue_glass_on_dark_red_brick_is_found_by_its_colour():
    # the glass is only 12 % darker than the brick, under the darkness threshold, but far from it in colour
    wins = window_grid()
    img = render_facade(wins, W, H, TEXEL, noise=8.0, wall=np.array([120.0, 35.0, 25.0]),
                        glass=np.array([35.0, 50.0, 110.0]))
    seen = np.ones(img.shape[:2], bool)
    assert detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0, polarity="dark")) == []
    dets = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0 and s.iou_mean > 0.8


def test_whole_windows_outweigh_the_panes_a_weaker_cue_finds():
    """Dark glass with a reflection on its right pane, on brick: the darkness finds the left panes only (none
    matches a window at IoU 0.5), the colour difference the whole windows. Their score sums are close (10.8 and
    11.6); the window areas they cover are not, and the whole windows are kept."""
    wins = window_grid(missing=())
    img = render_facade(wins, W, H, TEXEL, noise=6.0, seed=2, wall=np.array([120.0, 35.0, 25.0]),
                        glass=np.array([25.0, 30.0, 60.0]), right_pane=np.array([90.0, 60.0, 90.0]))
    seen = np.ones(img.shape[:2], bool)
    panes = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0, polarity="dark"))
    assert len(panes) == 12
    assert window_scores(to_world(np.array([d.box for d in panes])), truth_world(wins)).matched == 0
    dets = detect_windows(img, seen, TEXEL, WindowOptions(grow_m=0.0))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0


def test_light_windows_on_a_dark_wall_are_found_in_the_negative():
    wins = window_grid()
    img = render_facade(wins, W, H, TEXEL, noise=6.0, wall=np.array([60.0, 55.0, 50.0]),
                        glass=np.array([190.0, 195.0, 200.0]))
    dets = detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, WindowOptions(grow_m=0.0, polarity="bright"))
    s = window_scores(to_world(np.array([d.box for d in dets])), truth_world(wins))
    assert s.precision == 1.0 and s.recall == 1.0


def test_unknown_polarity_is_refused():
    img = render_facade(window_grid(), W, H, TEXEL)
    with pytest.raises(ValueError, match="polarity"):
        detect_windows(img, np.ones(img.shape[:2], bool), TEXEL, WindowOptions(polarity="light"))
