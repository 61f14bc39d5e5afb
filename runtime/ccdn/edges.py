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
corner of frames whose noise (ccdn.checker.image_noise) is at least ccdn.checker.NOISY_SIGMA grey
levels, where the noise dominates those biases, and elsewhere on the corners `on_straight_lines`
picks: of boards whose lines are straight (a homography fits them), at squares not thin. On the stress benchmark's
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

from typing import NamedTuple

import cv2
import numpy as np

from .board import Board
from .checker import altitude
from .refine import kernel_size
from .stats import median, nanmedian_rows, vector_lengths

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


def _frozen(array: np.ndarray) -> np.ndarray:
    """array made read-only: a module constant that every call shares."""
    array.flags.writeable = False
    return array


_ACROSS = _frozen(np.arange(-int(HALF_WIDTH / SAMPLE_STEP), int(HALF_WIDTH / SAMPLE_STEP) + 1) * SAMPLE_STEP)  # (K,)
_ABS_ACROSS = _frozen(np.abs(_ACROSS))  # px: a profile's samples' offsets across its edge, and their distances
_ALONG = _frozen(np.linspace(*REACH, PROFILES))  # (P,) the profiles' places along a half-edge, x its step


def lattice_steps(board: Board) -> np.ndarray:
    """(M, 4, 2) vectors from each board corner to its neighbours at +col, -col, +row, -row; a
    missing neighbour is mirrored from the opposite one, NaN where both are missing."""
    grid = board.grid.astype(np.int64)
    xy = board.xy.astype(np.float64)
    canvas = np.full((*(grid.max(0) + 3), 2), np.nan)
    r, c = grid[:, 0] + 1, grid[:, 1] + 1
    canvas[r, c] = xy
    steps = canvas[r[:, None] + (0, 0, 1, -1), c[:, None] + (1, -1, 0, 0)] - xy[:, None]  # +col, -col, +row, -row
    return np.where(np.isnan(steps[..., :1]), -steps[:, [1, 0, 3, 2]], steps)  # missing: the opposite one, reversed


def median_step(steps: np.ndarray) -> float:
    """The median length (px) of lattice steps (M, 4, 2) from lattice_steps, NaN ones left out: a
    board's typical square."""
    lengths = vector_lengths(steps)
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
    residual = vector_lengths(cv2.perspectiveTransform(grid[None], homography)[0] - xy)
    flat = median(residual) < FLAT_BOARD * median_step(steps)
    return flat & wide_squares(steps[:, 0], steps[:, 2])


def wide_squares(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) whether the squares of lattice steps u, v (K, 2) are no thinner than MIN_ASPECT of the
    longer step, wide enough for edge profiles across them (NaN steps: not)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return altitude(u, v) / np.fmax(vector_lengths(u), vector_lengths(v)) >= MIN_ASPECT


def refine_on_edges(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners xy (M, 2) moved to the crossing of their two edge lines (module docstring), given
    lattice steps (M, 4, 2) from lattice_steps. Returns xy (M, 2) float32 and whether each moved
    (corners whose lines cannot be fitted keep their position)."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    image, origin, extent, start, half_edges = _prepared(gray, xy, steps)
    inverse = _crossing_inverse(half_edges.normal)
    current = start
    for _ in range(ITERATIONS):
        offsets = _edge_lines(image, extent, current, half_edges)  # (M, 2 lines)
        shifted = current + (inverse * offsets[:, None]).sum(2)  # NaN where no crossing
        moved = vector_lengths(shifted - start) <= MAX_MOVE
        current = np.where(moved[:, None], shifted, start)
    return (current + origin).astype(np.float32), moved


def half_edge_contrast(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(M, 4): the median contrast (absolute) across each of corners xy's (M, 2) four half-edges,
    towards +col, -col, +row, -row (lattice steps (M, 4, 2) as for refine_on_edges), in gray's units,
    NaN where no profile is on the image: a lattice corner has four, a point on a board's outline
    three (the fourth runs into the margin)."""
    if len(xy) == 0:
        return np.zeros((0, 4))
    image, _, extent, start, half_edges = _prepared(gray, xy, steps)
    _, contrast = _profiles(image, extent, start, half_edges)
    return nanmedian_rows(contrast).reshape(-1, 4)


class _HalfEdges(NamedTuple):
    """How the profiles across M corners' four half-edges (+col, -col, +row, -row) are sampled and
    read: all but the corners' positions, so built once per call and reused by every fit as the
    corners move. P profiles per half-edge, K samples per profile; (4M, ...) rows run over the
    corners, then their half-edges; (2M, ...) rows over the corners, then their lattice lines
    (along the columns: the +col / -col half-edges; along the rows)."""

    normal: np.ndarray  # (M, 2 lines, 2) each lattice line's unit normal (x, y)
    centres: np.ndarray  # (2 x/y, M, 4, P) each profile's centre relative to its corner
    samples: np.ndarray  # (2 x/y, M, 4, 1, K) each sample's offset from its profile's centre
    inside: np.ndarray  # (4M, K, 1) float32: 1 on the samples within the profile's half-width
    low: np.ndarray  # (4M, K, 1) float32: 1 on its outer samples on the negative side (a square's level)
    high: np.ndarray  # (4M, K, 1) float32: likewise on the positive side
    count: np.ndarray  # (4M, 1) how many samples `inside` picks
    low_count: np.ndarray  # (4M, 1) how many `low` picks, at least 1
    high_count: np.ndarray  # (4M, 1) how many `high` picks, at least 1
    half_span: np.ndarray  # (4M, 1) px: half the profile's extent, count SAMPLE_STEP / 2
    wide: np.ndarray  # (4M, 1) whether the profile is at least MIN_HALF_WIDTH
    centres_in_line: np.ndarray  # (2 along/across, 2M, 2 half-edges, P) the profiles' centres in their line's frame
    across_in_line: np.ndarray  # (2 along/across, 2M, 2 half-edges, 1) the unit vector across a profile, likewise


def _prepared(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray):
    """What the fits need for corners xy (M, 2) with lattice steps (M, 4, 2): the smoothed crop
    (_smoothed_around), its origin, gray's extent in it, xy in the crop's pixels and the
    half-edges' sampling (_half_edges)."""
    start = xy.astype(np.float64)
    lengths = vector_lengths(steps)
    image, origin, extent = _smoothed_around(gray, start, lengths)
    return image, origin, extent, start - origin, _half_edges(steps, lengths)


def _half_edges(steps: np.ndarray, lengths: np.ndarray) -> _HalfEdges:
    """The sampling of the half-edges of corners with lattice steps (M, 4, 2) and their lengths
    (M, 4). Each lattice line runs through the corner from its backward to its forward neighbour,
    and is as wide as the perpendicular steps are long (the line along the columns spans the row
    steps, and back)."""
    m = len(steps)
    lines = steps.reshape(m, 2, 2, 2).transpose(3, 0, 1, 2)  # (x/y, corner, line, forward/backward)
    direction = lines[..., 0] - lines[..., 1]  # (2, M, 2 lines)
    (dx, dy), (ux, uy) = direction / vector_lengths(direction, axis=0), lines / lengths.reshape(m, 2, 2)
    line_frame = np.array([[dx, dy], [-dy, dx]])  # (along, normal; x/y; M, 2 lines)
    half_edge_frame = np.array([[ux, uy], [-uy, ux]])  # (along, across; x/y; M, 2 lines, 2 half-edges)
    # each half-edge's along and across unit vectors in its line's frame: (along, across; along, normal; M, 2, 2, 1)
    in_line = (half_edge_frame[:, None] * line_frame[..., None]).sum(2)[..., None]
    t = lengths.reshape(m, 2, 2, 1) * _ALONG  # (M, 2, 2, P) px from the corner
    width = lengths.reshape(m, 2, 2).sum(2)[:, ::-1] / 2  # (M, 2 lines): the perpendicular steps' mean
    half = np.repeat(np.minimum(0.3 * width, HALF_WIDTH), 2)[:, None]  # (4M, 1) px, the profile's half-width
    inside = _ABS_ACROSS <= half  # (4M, K)
    outer = inside & (_ABS_ACROSS >= 0.6 * half)  # its two ends: the squares' levels
    masks = np.array([inside, outer & (_ACROSS < 0), outer & (_ACROSS > 0)])  # inside, low, high: (3, 4M, K)
    count, *side_counts = masks.sum(2)[..., None]
    low_count, high_count = np.maximum(side_counts, 1)
    inside_mask, low_mask, high_mask = masks[..., None].astype(np.float32)
    return _HalfEdges(
        normal=line_frame[1].transpose(1, 2, 0),
        centres=(t * half_edge_frame[0][..., None]).reshape(2, m, 4, -1),
        samples=(_ACROSS * half_edge_frame[1][..., None, None]).reshape(2, m, 4, 1, -1),
        inside=inside_mask, low=low_mask, high=high_mask, count=count, low_count=low_count, high_count=high_count,
        half_span=count * SAMPLE_STEP / 2, wide=half >= MIN_HALF_WIDTH,
        centres_in_line=(t * in_line[0]).reshape(2, 2 * m, 2, -1), across_in_line=in_line[1].reshape(2, 2 * m, 2, 1))


def _smoothed_around(gray: np.ndarray, xy: np.ndarray, lengths: np.ndarray):
    """The Gaussian-smoothed (SMOOTHING) crop of gray that every profile of corners xy (M, 2) with
    step lengths (M, 4) can reach, its origin (x, y) in gray, and gray's extent in the crop's
    pixels ((x_min, y_min), (x_max, y_max)): smoothing a board's surroundings, not the whole frame
    (at 2000x1500 the frame's smoothing cost more than the fits). The margin covers half the
    longest step, the profile's half-width, MAX_MOVE, the interpolation and the kernel's reach,
    so the crop's values there equal the whole frame's."""
    h, w = gray.shape
    size = kernel_size(SMOOTHING)
    reach = REACH[1] * np.fmax.reduce(lengths, None, initial=0.0) + HALF_WIDTH + MAX_MOVE + 1 + size // 2  # NaN: none
    x0, y0 = (max(0, int(v)) for v in np.floor(xy.min(0) - reach))
    x1, y1 = (int(v) for v in np.minimum(np.ceil(xy.max(0) + reach) + 1, (w, h)))
    x1, y1 = max(x1, x0 + 1), max(y1, y0 + 1)
    image = cv2.GaussianBlur(gray[y0:y1, x0:x1].astype(np.float32), (size, size), SMOOTHING)
    return image, np.array([x0, y0], np.float64), np.array([[-x0, -y0], [w - 1 - x0, h - 1 - y0]], np.float64)


def _profiles(image: np.ndarray, extent: np.ndarray, xy: np.ndarray, half_edges: _HalfEdges):
    """The profiles across half_edges at corners xy (M, 2), sampled on image whose extent ((x_min,
    y_min), (x_max, y_max)) bounds the samples that count: each one's edge offset along the unit
    vector across it by the area method (the integral of the normalised step), and its absolute
    contrast, NaN where the profile is not on the image (an end outside extent); each (4M, P)."""
    m = len(xy)
    centres = xy.T[:, :, None, None] + half_edges.centres  # (2 x/y, M, 4, P)
    # the samples' x and y maps for remap: float64 sums rounded to float32, with no float64 array of them
    maps = np.empty((2, 4 * m, PROFILES * len(_ACROSS)), np.float32)
    np.add(centres[..., None], half_edges.samples, out=maps.reshape(centres.shape + (-1,)), casting="unsafe")
    values = cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    values = values.reshape(4 * m, PROFILES, -1)  # (4M, P, K)
    # sums over a profile's chosen samples as one batched product with the (4M, K, 1) masks
    low = (values @ half_edges.low)[..., 0] / half_edges.low_count
    high = (values @ half_edges.high)[..., 0] / half_edges.high_count
    contrast = high - low  # (4M, P)
    flat = np.where(contrast == 0, np.nan, contrast)  # no edge: NaN (unusable), not +-inf
    rise = ((values @ half_edges.inside)[..., 0] - half_edges.count * low) / flat  # the normalised step's sum
    edge = half_edges.half_span - rise * SAMPLE_STEP  # area method: offset along the across unit vector
    first, last = centres + half_edges.samples[..., 0], centres + half_edges.samples[..., -1]  # the profile's ends
    lowest, highest = extent[..., None, None, None]
    on_image = (np.minimum(first, last) >= lowest) & (np.maximum(first, last) <= highest)
    on_image = (on_image[0] & on_image[1]).reshape(edge.shape)
    return edge, np.where(on_image, np.abs(contrast), np.nan)


def _edge_lines(image: np.ndarray, extent: np.ndarray, xy: np.ndarray, half_edges: _HalfEdges) -> np.ndarray:
    """(M, 2) the offsets from corners xy (M, 2) of their lattice lines (along the columns, along
    the rows) along the lines' unit normals (half_edges.normal): robust lines through the edge
    points of the usable profiles (_profiles) of both their half-edges, fitted in the line's own
    frame; NaN where too few profiles are usable."""
    edge, contrast = _profiles(image, extent, xy, half_edges)
    typical = nanmedian_rows(contrast)[:, None]  # per half-edge
    usable = (contrast > 0.5 * typical) & half_edges.wide  # NaN contrast (off the image): False
    # the edge points (the profile's centre + edge x the unit vector across it) relative to the
    # corner, in their line's frame: (along it, across it), each (2M lines, 2P profiles)
    edge = edge.reshape(2 * len(xy), 2, -1)
    along, offset = (half_edges.centres_in_line + edge * half_edges.across_in_line).reshape(2, 2 * len(xy), -1)
    return _robust_intercepts(along, offset, usable.reshape(along.shape)).reshape(-1, 2)


def _robust_intercepts(t: np.ndarray, s: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per row, the intercept a of s = a + b t fitted over the `ok` entries, then refitted twice, each
    time without those beyond 3 robust sigmas of the last fit (occluders, clutter); NaN where fewer
    than 5 remain."""
    s = np.where(ok, s, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):  # rows with fewer than two entries: NaN
        for _ in range(2):
            a, b, _ = _weighted_line(t, s, ok)
            residual = np.abs(s - a[:, None] - b[:, None] * t)
            spread = 1.4826 * nanmedian_rows(np.where(ok, residual, np.nan))[:, None]
            ok = ok & (residual <= 3 * np.maximum(spread, 0.05))
        a, _, n = _weighted_line(t, s, ok)
    a[n < 5] = np.nan
    return a


def _weighted_line(t: np.ndarray, s: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares s = a + b t per row over the `ok` entries, and how many there are: a, b and n
    (each (rows,)), NaN where fewer than two (numpy's warnings for that: the caller's to silence)."""
    n = ok.sum(1)
    mt = np.where(ok, t, 0).sum(1) / n
    ms = np.where(ok, s, 0).sum(1) / n
    dt = np.where(ok, t - mt[:, None], 0)
    b = (dt * (s - ms[:, None])).sum(1) / (dt * dt).sum(1)
    return ms - b * mt, b, n


def _crossing_inverse(normal: np.ndarray) -> np.ndarray:
    """(M, 2, 2) the inverses of each corner's two line normals (M, 2 lines, 2) as rows: the shift
    that moves a corner by its lines' offsets o (M, 2) is inverse @ o. NaN where the lines are
    near parallel (|det| <= 0.2) or a normal is NaN (no lines to cross)."""
    (a, b), (c, d) = normal.transpose(1, 2, 0)
    det = a * d - b * c
    det = np.where(np.abs(det) > 0.2, det, np.nan)  # lines far from parallel
    return np.array([[d, -b], [-c, a]]).transpose(2, 0, 1) / det[:, None, None]
