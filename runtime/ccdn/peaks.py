"""Corner candidates from a score map: the paper's section 2.2, vectorised.

1. Threshold: keep pixels scoring at least `relative` x the map's maximum (the paper's half of the
   maximum) and at least the absolute `floor`, so an image without a board returns nothing.
2. Non-maximum suppression: the paper builds 4x4 boxes around candidates and suppresses at IoU 0.5,
   which as written only removes direct neighbours. We keep a pixel only if it is the maximum of
   its 5x5 box (radius 2 px, the reach of a 4x4 box), one dilation for the whole map, then settle
   ties on plateaus greedily in score and raster order, so that one corner gives one detection.
3. Clustering (optional, the paper's): k-means++ with k = 10 on the positions; clusters of <= 2
   points are dropped. With fewer than 3k candidates k shrinks to n // 3 (at least 1), so a small
   board is not shredded into clusters of one or two.
"""

from __future__ import annotations

import cv2
import numpy as np


def find_peaks(score: np.ndarray, relative: float = 0.5, floor: float = 0.3, radius: float = 2.0,
               max_peaks: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Thresholded, suppressed local maxima of `score` (H, W) float32; at most `max_peaks`, the
    strongest, which bounds the cost of later stages on pathological (e.g. pure noise) input.

    Returns xy (N, 2) int32 as (x, y) pixel indices and their scores (N,) float32, highest first.
    """
    top = float(score.max()) if score.size else 0.0
    threshold = max(relative * top, floor)
    if top < threshold or top <= 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    reach = int(radius)
    window = np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)
    local_max = score >= cv2.dilate(score, window)  # the maximum of its own (2r+1)^2 box
    # flat indices: np.nonzero on the 2-D mask costs several times as much
    index = np.flatnonzero(local_max & (score >= threshold))
    ys, xs = np.divmod(index, score.shape[1])
    values = score.take(index)
    order = np.lexsort((xs, ys, -values))[:max_peaks]  # by score, ties in raster order: deterministic
    xy = np.stack([xs[order], ys[order]], 1).astype(np.int32)
    values = values[order]
    keep = suppress(xy, radius)  # only equal scores on a plateau are left to resolve
    return xy[keep], values[keep].astype(np.float32)


def best_near(score: np.ndarray, xy: np.ndarray, reach: int = 1) -> np.ndarray:
    """(N,) the highest score within `reach` px (a square; at the map's edge, clipped to it) of each
    point xy (N, 2), in the score map's pixels."""
    h, w = score.shape
    offsets = np.arange(-reach, reach + 1)
    col = np.clip(np.rint(xy[:, 0]).astype(np.int64)[:, None, None] + offsets[None, None, :], 0, w - 1)
    row = np.clip(np.rint(xy[:, 1]).astype(np.int64)[:, None, None] + offsets[None, :, None], 0, h - 1)
    return score[row, col].reshape(len(xy), -1).max(1)


def best_peak(score: np.ndarray, xy: np.ndarray, reach: int) -> tuple[np.ndarray, float]:
    """The pixel (x, y) of the highest score within `reach` px (a square) of a point xy (on the map),
    and that score."""
    h, w = score.shape
    x, y = int(round(xy[0])), int(round(xy[1]))
    top, left = max(y - reach, 0), max(x - reach, 0)
    window = score[top : min(y + reach + 1, h), left : min(x + reach + 1, w)]
    row, col = np.unravel_index(int(window.argmax()), window.shape)
    return np.array([left + col, top + row], np.float64), float(window[row, col])


def suppress(xy: np.ndarray, radius: float) -> np.ndarray:
    """Greedy NMS on points sorted by descending score: True for points no kept stronger point is near.

    Candidate pairs come from a sweep along x (searchsorted), so memory grows with the number of
    close pairs, not with N^2.
    """
    n = len(xy)
    if n < 2:
        return np.ones(n, bool)
    pts = xy.astype(np.float64)
    by_x = np.argsort(pts[:, 0], kind="stable")
    xs = pts[by_x, 0]
    lo = np.searchsorted(xs, xs - radius, "left")
    hi = np.searchsorted(xs, xs + radius, "right")
    counts = hi - lo
    a = np.repeat(np.arange(n), counts)
    b = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(lo, counts)
    i, j = by_x[a], by_x[b]
    close = (i < j) & (((pts[i] - pts[j]) ** 2).sum(1) <= radius * radius)  # i stronger than j
    # greedy in score order, settled in rounds (as many as the longest chain of close points, usually
    # 1-3): a point is kept once all its stronger neighbours are suppressed, suppressed once one is kept
    i, j = i[close], j[close]
    state = np.zeros(n, np.int8)  # 0 undecided, 1 kept, -1 suppressed
    while True:
        blocked = np.zeros(n, bool)
        blocked[j[state[i] != -1]] = True
        state[(state == 0) & ~blocked] = 1
        beaten = np.zeros(n, bool)
        beaten[j[state[i] == 1]] = True
        state[(state == 0) & beaten] = -1
        if (state != 0).all():
            return state == 1


def kmeans_outliers(xy: np.ndarray, k: int = 10, min_size: int = 3, seed: int = 0, iterations: int = 50) -> np.ndarray:
    """Mask of points kept by the paper's clustering: members of k-means++ clusters of >= min_size."""
    n = len(xy)
    k = min(k, max(1, n // 3))
    if n == 0 or k == 1:
        return np.ones(n, bool)
    pts = xy.astype(np.float64)
    labels = kmeans_pp(pts, k, seed, iterations)
    sizes = np.bincount(labels, minlength=k)
    return sizes[labels] >= min_size


def kmeans_pp(pts: np.ndarray, k: int, seed: int = 0, iterations: int = 50) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding, deterministic for a given seed; returns labels."""
    rng = np.random.default_rng(seed)
    centres = [pts[rng.integers(len(pts))]]
    d2 = ((pts - centres[0]) ** 2).sum(1)
    for _ in range(1, k):
        total = d2.sum()
        idx = rng.choice(len(pts), p=d2 / total) if total > 0 else rng.integers(len(pts))
        centres.append(pts[idx])
        d2 = np.minimum(d2, ((pts - pts[idx]) ** 2).sum(1))
    c = np.array(centres)
    labels = np.zeros(len(pts), np.int64)
    for it in range(iterations):
        labels_new = ((pts[:, None] - c[None]) ** 2).sum(-1).argmin(1)
        if it and np.array_equal(labels_new, labels):
            break
        labels = labels_new
        counts = np.bincount(labels, minlength=k)[:, None]
        sums = np.zeros_like(c)
        np.add.at(sums, labels, pts)
        c = np.where(counts > 0, sums / np.maximum(counts, 1), c)
    return labels
