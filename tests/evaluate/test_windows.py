"""Window detection scores against hand-made truth: exact, shifted, duplicated, missing and spurious windows."""

import numpy as np
import pytest

from oblique_city.core.evaluate.windows import truth_windows, window_scores


def _window(x0: float, z0: float, w: float = 1.2, h: float = 1.4, y: float = 0.0, angle: float = 0.0) -> np.ndarray:
    """A window rectangle in a facade through (0, y) turned by ``angle`` degrees about Z (normal -y at 0)."""
    a = np.radians(angle)
    u = np.array([np.cos(a), np.sin(a), 0.0])
    base = np.array([0.0, y, 0.0])
    return np.array([base + x0 * u + [0, 0, z0], base + (x0 + w) * u + [0, 0, z0],
                     base + (x0 + w) * u + [0, 0, z0 + h], base + x0 * u + [0, 0, z0 + h]])


def _grid(angle: float = 0.0) -> list[np.ndarray]:
    return [_window(2.0 + 3.0 * i, 1.0 + 3.2 * j, angle=angle) for i in range(4) for j in range(3)]


@pytest.mark.parametrize("angle", [0.0, 37.0])
def test_exact_detections_score_one(angle):
    truth = _grid(angle)
    det = [np.roll(t, 2, axis=0) for t in truth]  # corner order does not matter
    s = window_scores(det, truth)
    assert (s.matched, s.precision, s.recall, s.f1) == (12, 1.0, 1.0, 1.0)
    assert s.iou_mean == pytest.approx(1.0) and s.corner_rmse_m == pytest.approx(0.0, abs=1e-12)


def test_small_shift_still_matches_and_measures_the_corner_error():
    truth = _grid()
    det = [t + [0.1, 0.0, 0.05] for t in truth]  # 10 cm along the wall, 5 cm up
    s = window_scores(det, truth)
    assert s.recall == 1.0 and s.precision == 1.0
    assert s.corner_rmse_m == pytest.approx(np.hypot(0.1, 0.05), rel=1e-9)
    # IoU of two 1.2 x 1.4 boxes shifted by (0.1, 0.05)
    inter = 1.1 * 1.35
    assert s.iou_mean == pytest.approx(inter / (2 * 1.2 * 1.4 - inter), rel=1e-9)


def test_recessed_detection_on_the_glass_matches_but_another_facade_does_not():
    truth = _grid()
    on_glass = [t + [0.0, 0.12, 0.0] for t in truth]  # 12 cm behind the wall plane
    assert window_scores(on_glass, truth).recall == 1.0
    parallel_wall = [t + [0.0, 3.0, 0.0] for t in truth]  # the facade across a courtyard
    assert window_scores(parallel_wall, truth).matched == 0
    turned = _grid(angle=30.0)  # same place, a facade 30 degrees off
    assert window_scores(turned, truth, max_plane_dist=10.0).matched < 12


def test_duplicates_spurious_and_missing():
    truth = _grid()
    det = truth[:8] + [truth[0] + [0.02, 0, 0]] + [_window(20.0, 1.0), _window(25.0, 1.0)]
    s = window_scores(det, truth)
    assert s.matched == 8
    assert s.precision == pytest.approx(8 / 11)
    assert s.recall == pytest.approx(8 / 12)
    assert s.f1 == pytest.approx(2 * (8 / 11) * (8 / 12) / (8 / 11 + 8 / 12))


def test_half_overlap_is_below_the_iou_threshold():
    truth = [_window(0.0, 0.0)]
    half = [_window(0.6, 0.0)]  # IoU = 0.6 / 1.8 = 1/3
    assert window_scores(half, truth).matched == 0
    assert window_scores(half, truth, min_iou=0.3).matched == 1


def test_empty_inputs_and_truth_document():
    assert window_scores([], _grid()).recall == 0.0
    assert np.isnan(window_scores([], _grid()).precision)
    doc = {"windows": [{"corners": t.tolist()} for t in _grid()]}
    assert len(truth_windows(doc)) == 12 and truth_windows(doc)[0].shape == (4, 3)
