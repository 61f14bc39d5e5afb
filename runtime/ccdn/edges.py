"""Edge-line refinement of board corners, for noisy frames.

The saddle fit (ccdn.refine) uses the few pixels where a corner's neighbourhood is a quadric, so its
error grows with the image noise. A board corner is also the crossing of two lattice lines, each
running along two edges between squares; the edges are long, so locating them uses many more
pixels. For each corner with lattice steps to its neighbours (from its board), profiles are sampled
across each of its four half-edges at several distances from the corner; each profile gives the
edge's offset by the area method (the integral of the normalised step, linear in the noise), a
robust least-squares line is fitted to the edge points on either side of the corner (in the
line's own frame, so the neighbours' positions only steer where profiles are taken), likewise for
the other lattice line, and the corner moves to the lines' crossing (ITERATIONS times, each
resampling around the moved corner).

Measured on renders with exact labels (seeds 9_400_000+, disjoint from the stress benchmark's):
against the saddle fit 0.170 -> 0.081 px at ~18 grey levels of noise, 0.064 -> 0.030 px at ~6,
0.031 -> 0.014 px without noise, but 0.041 -> 0.092 px under fisheye lenses (the edges curve) and
0.030 -> 0.036 px at extreme poses (squares a few pixels thin). So the detector uses it on every
corner of frames whose noise (`image_noise`) is at least NOISY_SIGMA grey levels, where the noise
dominates those biases, and elsewhere on the corners `on_straight_lines` picks: of boards whose
lines are straight (a homography fits them), at squares not thin. On the stress benchmark's
renders (exact labels, every board corner found) that took the mean error from 0.036 to 0.024 px
(clean 0.025 -> 0.012, deep shadow 0.091 -> 0.049, fisheye and extreme poses as before); on a
held-out sample of as many renders 0.039 -> 0.027 px (with three fits per corner; two, now, gave 0.023 px
on the benchmark's renders).

ccdn.grid's completion also places corners in shade that no saddle fit finds at their edge lines'
crossing, on the log scale of grey, where half_edge_contrast tells a lattice corner (four half-edges)
from a point on a board's outline (three).

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from .checker import altitude
from .refine import kernel_size
from .stats import median, nanmedian_rows

if TYPE_CHECKING:  # ccdn.grid fits corners on their edges too: imported at run time, Board would be circular
    from .grid import Board

NOISY_SIGMA = 5.0  # grey levels of image noise from which board corners are refined on their edges
NOISE_SAMPLE_PIXELS = 1 << 15  # the noise estimate's median is taken over about this many pixels (1 << 17 made
# the same decisions on 92 real-dev frames and 320 stress renders, in 3x the time)
_LAPLACIAN_PAIR = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]])  # zero on planes; |kernel| = 6
SMOOTHING = 1.0  # px, Gaussian sigma of the image the profiles are sampled on
REACH = (0.1, 0.5)  # profiles from this far to this far along each half-edge (x the step to the neighbour)
PROFILES = 8  # per half-edge
HALF_WIDTH = 2.5  # px, at most (and 0.3 of the perpendicular step): the profile across the edge
MIN_HALF_WIDTH = 1.5  # px: thinner squares (steep poses) keep their saddle-fit position
SAMPLE_STEP = 0.5  # px along a profile
ITERATIONS = 2  # fits, each resampling around the corner the last one moved; later ones drift (four samples of
# stress renders, 88878 corners, mean error after 1 / 2 / 3 / 5 fits: 0.0235 / 0.0225 / 0.0242 / 0.0262 px,
# motion blur 0.021 / 0.019 / 0.026 / 0.038; deep shade 0.051 / 0.055 / 0.054 / 0.054, p95 0.19 / 0.15 / 0.18 / 0.19)
MAX_MOVE = 1.0  # px from the saddle-fit position; farther and the corner keeps that position
FLAT_BOARD = 0.01  # of the median lattice step: a board whose corners a homography fits this well (the median
# residual) has straight lines (stress renders' boards: pinhole lenses <= 0.006, fisheye lenses >= 0.03)
MIN_ASPECT = 0.4  # a corner's narrowest square width over its longer step: thinner squares keep the saddle fit


def image_noise(gray: np.ndarray) -> float:
    """Robust estimate of the image noise's standard deviation in grey levels: the median absolute
    response of a kernel that cancels smooth image content (Immerkaer's), scaled to a Gaussian's
    sigma. Edges and corners are a minority of pixels, so the median ignores them. The response is
    computed only on a strided grid of inner pixels (about NOISE_SAMPLE_PIXELS), not the whole frame."""
    h, w = gray.shape
    if min(h, w) < 3:
        return 0.0
    step = max(1, int(np.ceil(np.sqrt(gray.size / NOISE_SAMPLE_PIXELS))))
    response = np.zeros(((h - 3) // step + 1, (w - 3) // step + 1), np.int16)
    for dr in range(3):
        for dc in range(3):
            response += int(_LAPLACIAN_PAIR[dr, dc]) * gray[dr : h - 2 + dr : step, dc : w - 2 + dc : step].astype(np.int16)
    sample = np.abs(response).ravel()
    counts = np.bincount(sample)  # integer responses: an exact median without sorting
    median = int(np.searchsorted(np.cumsum(counts), (sample.size + 1) / 2))
    return 1.4826 * median / 6.0


def lattice_steps(board: Board) -> np.ndarray:
    """(M, 4, 2) vectors from each board corner to its neighbours at +col, -col, +row, -row; a
    missing neighbour is mirrored from the opposite one, NaN where both are missing."""
    grid = board.grid.astype(np.int64)
    xy = board.xy.astype(np.float64)
    canvas = np.full((grid[:, 0].max() + 3, grid[:, 1].max() + 3, 2), np.nan)
    r, c = grid[:, 0] + 1, grid[:, 1] + 1
    canvas[r, c] = xy
    steps = np.stack([canvas[r, c + 1], canvas[r, c - 1], canvas[r + 1, c], canvas[r - 1, c]], 1) - xy[:, None]
    for a, b in ((0, 1), (1, 0), (2, 3), (3, 2)):
        missing = np.isnan(steps[:, a, 0])
        steps[missing, a] = -steps[missing, b]
    return steps


def median_step(steps: np.ndarray) -> float:
    """The median length (px) of lattice steps (M, 4, 2) from lattice_steps, NaN ones left out: a
    board's typical square."""
    lengths = np.linalg.norm(steps, axis=2)
    return float(median(lengths[np.isfinite(lengths)]))


def on_straight_lines(board: Board, steps: np.ndarray) -> np.ndarray:
    """(M,) which of a board's corners (lattice steps (M, 4, 2) from lattice_steps) lie on straight
    lattice lines, where the edge lines beat the saddle fit even without noise: all corners of a
    board a homography fits within FLAT_BOARD of a step (no lens distortion to bend the lines)
    whose squares are no thinner than MIN_ASPECT (steep views)."""
    if len(board) < 4:
        return np.zeros(len(board), bool)
    grid = board.grid[:, ::-1].astype(np.float64)  # (col, row), like (x, y)
    xy = board.xy.astype(np.float64)
    homography, _ = cv2.findHomography(grid, xy, 0)
    if homography is None:
        return np.zeros(len(board), bool)
    residual = np.linalg.norm(cv2.perspectiveTransform(grid[None], homography)[0] - xy, axis=1)
    lengths = np.linalg.norm(steps, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN steps (no neighbour either way): not picked
        aspect = altitude(steps[:, 0], steps[:, 2]) / np.fmax(lengths[:, 0], lengths[:, 2])
    flat = median(residual) < FLAT_BOARD * median_step(steps)
    return flat & (aspect >= MIN_ASPECT)


def refine_on_edges(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners xy (M, 2) moved to the crossing of their two edge lines (module docstring), given
    lattice steps (M, 4, 2) from lattice_steps. Returns xy (M, 2) float32 and whether each moved
    (corners whose lines cannot be fitted keep their position)."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    image, origin, frame, start, lines = _prepared(gray, xy, steps)
    current = start.copy()
    m = len(xy)
    moved = np.zeros(m, bool)
    for _ in range(ITERATIONS):
        offsets, normals, _ = _edge_lines(image, frame, np.concatenate([current, current]), *lines)
        normals = normals.reshape(2, m, 2).transpose(1, 0, 2)  # (M, 2 lines, 2)
        offsets = offsets.reshape(2, m).T  # (M, 2)
        solvable = np.isfinite(offsets).all(1) & np.isfinite(normals).all((1, 2))
        solvable[solvable] &= np.abs(np.linalg.det(normals[solvable])) > 0.2  # lines far from parallel
        shift = np.zeros_like(current)
        shift[solvable] = np.linalg.solve(normals[solvable], offsets[solvable][..., None])[..., 0]
        moved = solvable & (np.linalg.norm(current + shift - start, axis=1) <= MAX_MOVE)
        current = np.where(moved[:, None], current + shift, start)
    return (current + origin).astype(np.float32), moved


def half_edge_contrast(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(M, 4): the median contrast (absolute) across each of corners xy's (M, 2) four half-edges,
    towards +col, -col, +row, -row (lattice steps (M, 4, 2) as for refine_on_edges), in gray's units,
    NaN where no profile is on the image: a lattice corner has four, a point on a board's outline
    three (the fourth runs into the margin)."""
    if len(xy) == 0:
        return np.zeros((0, 4))
    image, _, frame, start, lines = _prepared(gray, xy, steps)
    _, _, typical = _edge_lines(image, frame, np.concatenate([start, start]), *lines)
    forward, backward = typical.reshape(2, 2, -1)  # (+col, +row) then (-col, -row) half-edges, each (M,)
    return np.stack([forward[0], backward[0], forward[1], backward[1]], 1)


def _prepared(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray):
    """What _edge_lines needs for corners xy (M, 2) with lattice steps (M, 4, 2): the smoothed crop
    (_smoothed_around), its origin and frame, xy in the crop's pixels, and the forward and backward
    steps and widths of both lattice lines of every corner, sampled in one pass (the line along the
    columns, +col / -col steps, is as wide as the row steps are long, and back)."""
    start = xy.astype(np.float64)
    lengths = np.linalg.norm(steps, axis=2)
    image, origin, frame = _smoothed_around(gray, start, lengths)
    forward, backward = np.concatenate([steps[:, 0], steps[:, 2]]), np.concatenate([steps[:, 1], steps[:, 3]])
    across = np.concatenate([lengths[:, 2:].mean(1), lengths[:, :2].mean(1)])
    return image, origin, frame, start - origin, (forward, backward, across)


def _smoothed_around(gray: np.ndarray, xy: np.ndarray, lengths: np.ndarray):
    """The Gaussian-smoothed (SMOOTHING) crop of gray that every profile of corners xy (M, 2) with
    step lengths (M, 4) can reach, its origin (x, y) in gray, and gray's extent in the crop's
    pixels (x_min, y_min, x_max, y_max): smoothing a board's surroundings, not the whole frame
    (at 2000x1500 the frame's smoothing cost more than the fits). The margin covers half the
    longest step, the profile's half-width, MAX_MOVE, the interpolation and the kernel's reach,
    so the crop's values there equal the whole frame's."""
    h, w = gray.shape
    size = kernel_size(SMOOTHING)
    reach = REACH[1] * np.nanmax(lengths, initial=0.0) + HALF_WIDTH + MAX_MOVE + 1 + size // 2
    x0, y0 = (max(0, int(v)) for v in np.floor(xy.min(0) - reach))
    x1, y1 = (int(v) for v in np.minimum(np.ceil(xy.max(0) + reach) + 1, (w, h)))
    x1, y1 = max(x1, x0 + 1), max(y1, y0 + 1)
    image = cv2.GaussianBlur(gray[y0:y1, x0:x1].astype(np.float32), (size, size), SMOOTHING)
    return image, np.array([x0, y0], np.float64), (-x0, -y0, w - 1 - x0, h - 1 - y0)


def _edge_lines(image: np.ndarray, frame: tuple[int, int, int, int], xy: np.ndarray, forward: np.ndarray,
                backward: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lattice lines through points xy along steps `forward` / `backward` (L, 2) (to the two
    neighbours on each; `across`: the step length perpendicular to it), sampled on `image` whose
    frame (x_min, y_min, x_max, y_max) bounds the samples that count: each line's offset (L,)
    from xy along its unit normal (L, 2), NaN where too few edge profiles are usable, and each
    half-edge's median absolute contrast (2L,: the forward half-edges, then the backward ones)."""
    n = len(xy)
    direction = forward - backward
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    normal = np.stack([-direction[:, 1], direction[:, 0]], 1)
    half = np.minimum(0.3 * across, HALF_WIDTH)  # (L,)
    k = np.arange(-int(HALF_WIDTH / SAMPLE_STEP), int(HALF_WIDTH / SAMPLE_STEP) + 1) * SAMPLE_STEP
    # the two half-edges of every line as rows of one (2L, ...) sampling: forward ones, then backward
    # ones; x and y apart, so that every array's last axis is the profile's samples (K)
    step = np.concatenate([forward, backward])
    base, half2 = np.concatenate([xy, xy]), np.concatenate([half, half])
    length = np.linalg.norm(step, axis=1)
    unit = step / length[:, None]
    across_x, across_y = -unit[:, 1], unit[:, 0]  # the unit vector across the half-edge
    t = np.linspace(*REACH, PROFILES)[None] * length[:, None]  # (2L, P)
    px = (base[:, :1] + t * unit[:, :1])[..., None] + k * across_x[:, None, None]  # (2L, P, K)
    py = (base[:, 1:] + t * unit[:, 1:])[..., None] + k * across_y[:, None, None]
    values = cv2.remap(image, px.reshape(2 * n, -1).astype(np.float32), py.reshape(2 * n, -1).astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(px.shape)
    inside = np.abs(k)[None] <= half2[:, None]  # (2L, K) samples within the profile
    outer = inside & (np.abs(k)[None] >= 0.6 * half2[:, None])  # its two ends: the squares' levels
    # sums over a profile's chosen samples as one batched product with the (2L, K) masks
    low_side, high_side = outer & (k < 0), outer & (k > 0)
    low = (values @ low_side[..., None].astype(np.float32))[..., 0] / np.maximum(low_side.sum(1), 1)[:, None]
    high = (values @ high_side[..., None].astype(np.float32))[..., 0] / np.maximum(high_side.sum(1), 1)[:, None]
    contrast = high - low  # (2L, P)
    flat = np.where(contrast == 0, np.nan, contrast)  # no edge: NaN (unusable below), not +-inf
    count = inside.sum(1)[:, None]
    rise = ((values @ inside[..., None].astype(np.float32))[..., 0] - count * low) / flat  # the normalised step's sum
    edge = count * SAMPLE_STEP / 2 - rise * SAMPLE_STEP  # area method: offset along the across unit vector
    x_min, y_min, x_max, y_max = frame
    ends_x, ends_y = px[..., [0, -1]], py[..., [0, -1]]  # a profile is on the image where both its ends are
    on_image = ((ends_x >= x_min) & (ends_x <= x_max) & (ends_y >= y_min) & (ends_y <= y_max)).all(2)
    typical = nanmedian_rows(np.where(on_image, np.abs(contrast), np.nan))[:, None]  # per half-edge
    usable = on_image & (np.abs(contrast) > 0.5 * typical) & (half2[:, None] >= MIN_HALF_WIDTH)
    # the edge point t unit + edge across, relative to the corner, in the line's frame (along it, across it)
    direction2, normal2 = np.concatenate([direction, direction]), np.concatenate([normal, normal])
    along = (t * (unit * direction2).sum(1)[:, None]
             + edge * (across_x * direction2[:, 0] + across_y * direction2[:, 1])[:, None])
    offset = t * (unit * normal2).sum(1)[:, None] + edge * (across_x * normal2[:, 0] + across_y * normal2[:, 1])[:, None]
    t, s, ok = (np.concatenate([part[:n], part[n:]], 1) for part in (along, offset, usable))  # (L, 2P)
    s = np.where(ok, s, 0.0)
    for _ in range(2):  # fit s = a + b t, drop profiles beyond 3 robust sigmas (occluders, clutter), refit
        a, b = _weighted_line(t, s, ok)
        residual = np.abs(s - a[:, None] - b[:, None] * t)
        spread = 1.4826 * nanmedian_rows(np.where(ok, residual, np.nan))[:, None]
        ok &= residual <= 3 * np.maximum(spread, 0.05)
    a, _ = _weighted_line(t, s, ok)
    a[ok.sum(1) < 5] = np.nan
    return a, normal, typical[:, 0]


def _weighted_line(t: np.ndarray, s: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares s = a + b t per row over the `ok` entries; NaN where fewer than two."""
    n = ok.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mt = np.where(ok, t, 0).sum(1) / n
        ms = np.where(ok, s, 0).sum(1) / n
        dt = np.where(ok, t - mt[:, None], 0)
        b = (dt * (s - ms[:, None])).sum(1) / (dt * dt).sum(1)
    return ms - b * mt, b
