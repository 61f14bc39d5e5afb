"""Peak extraction: thresholds, one detection per corner, the paper's k-means++ outlier removal."""

from __future__ import annotations

import numpy as np

from ccdn.peaks import find_peaks, kmeans_outliers, suppress


def blob_map(points, shape=(60, 80), sigma=1.0, heights=None):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    score = np.zeros(shape, np.float32)
    for i, (x, y) in enumerate(points):
        h = 1.0 if heights is None else heights[i]
        score = np.maximum(score, h * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2)))
    return score.astype(np.float32)


def test_one_detection_per_corner_even_on_a_plateau():
    score = blob_map([(10, 10), (40, 30)])
    score[30, 41] = score[30, 40]  # a two-pixel plateau at the second peak
    xy, values = find_peaks(score)
    assert len(xy) == 2
    assert {tuple(p) for p in xy} == {(10, 10), (40, 30)}


def test_peaks_are_sorted_by_score_and_deterministic():
    score = blob_map([(10, 10), (40, 30), (60, 50)], heights=[0.7, 1.0, 0.9])
    xy, values = find_peaks(score)
    assert xy.tolist() == [[40, 30], [60, 50], [10, 10]]
    assert np.all(np.diff(values) <= 0)


def test_relative_threshold_drops_weak_peaks_and_floor_drops_everything_weak():
    score = blob_map([(10, 10), (40, 30)], heights=[1.0, 0.4])
    assert len(find_peaks(score, relative=0.5)[0]) == 1
    assert len(find_peaks(score, relative=0.3)[0]) == 2
    assert len(find_peaks(score * 0.2, relative=0.5, floor=0.3)[0]) == 0


def test_empty_and_zero_maps_give_no_peaks():
    assert len(find_peaks(np.zeros((10, 10), np.float32))[0]) == 0
    assert len(find_peaks(np.zeros((0, 0), np.float32))[0]) == 0


def test_suppress_keeps_the_stronger_of_two_close_points():
    xy = np.array([[5, 5], [6, 6], [20, 20]])
    assert suppress(xy, radius=2.0).tolist() == [True, False, True]


def test_kmeans_drops_isolated_points_and_keeps_a_grid():
    grid = np.stack(np.meshgrid(np.arange(9) * 20 + 100, np.arange(6) * 20 + 100), -1).reshape(-1, 2)
    outliers = np.array([[5, 5], [600, 10], [10, 450]])
    keep = kmeans_outliers(np.concatenate([grid, outliers]))
    assert keep[: len(grid)].all()
    assert not keep[len(grid) :].any()


def test_kmeans_with_few_points_keeps_a_small_board():
    four = np.array([[10, 10], [30, 10], [10, 30], [30, 30]])
    assert kmeans_outliers(four).all()
    assert kmeans_outliers(np.zeros((0, 2))).shape == (0,)
