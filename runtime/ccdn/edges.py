"""Edge-line refinement of board corners, for noisy frames.

The saddle fit (ccdn.refine) uses the few pixels where a corner's neighbourhood is a quadric, so its
error grows with the image noise. A board corner is also the crossing of two lattice lines, each
running along two edges between squares; the edges are long, so locating them uses many more
pixels. For each corner with lattice steps to its neighbours (from its board), profiles are sampled
across each of its four half-edges at several distances from the corner; each profile gives the
edge's offset by the area method (the integral of the normalised step, linear in the noise), a
robust least-squares line is fitted to the edge points on either side of the corner (in the
line's own frame, so the neighbours' positions only steer where profiles are taken), likewise for
the other lattice line, and the corner moves to the lines' crossing (a few iterations, each
resampling around the moved corner).

Measured on renders with exact labels (seeds 9_400_000+, disjoint from the stress benchmark's):
against the saddle fit 0.170 -> 0.081 px at ~18 grey levels of noise, 0.064 -> 0.030 px at ~6,
0.031 -> 0.014 px without noise, but 0.041 -> 0.092 px under fisheye lenses (the edges curve) and
0.030 -> 0.036 px at extreme poses (squares a few pixels thin). So the detector uses it only on
frames whose noise (`image_noise`) is at least NOISY_SIGMA grey levels, where the noise dominates
those biases; a gate on the lines' curvature could extend it to clean frames.

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import cv2
import numpy as np

from .grid import Board
from .stats import nanmedian_rows

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
ITERATIONS = 3
MAX_MOVE = 1.0  # px from the saddle-fit position; farther and the corner keeps that position


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


def refine_on_edges(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners xy (M, 2) moved to the crossing of their two edge lines (module docstring), given
    lattice steps (M, 4, 2) from lattice_steps. Returns xy (M, 2) float32 and whether each moved
    (corners whose lines cannot be fitted keep their position)."""
    image = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), SMOOTHING)
    start = xy.astype(np.float64)
    current = start.copy()
    lengths = np.linalg.norm(steps, axis=2)
    moved = np.zeros(len(xy), bool)
    for _ in range(ITERATIONS):
        # the line along the columns (+col / -col steps) is as wide as the row steps are long, and back
        lines = [_edge_line(image, current, steps[:, 0], steps[:, 1], lengths[:, 2:].mean(1)),
                 _edge_line(image, current, steps[:, 2], steps[:, 3], lengths[:, :2].mean(1))]
        normals = np.stack([normal for _, normal in lines], 1)  # (M, 2 lines, 2)
        offsets = np.stack([offset for offset, _ in lines], 1)  # (M, 2)
        solvable = np.isfinite(offsets).all(1) & np.isfinite(normals).all((1, 2))
        solvable[solvable] &= np.abs(np.linalg.det(normals[solvable])) > 0.2  # lines far from parallel
        shift = np.zeros_like(current)
        shift[solvable] = np.linalg.solve(normals[solvable], offsets[solvable][..., None])[..., 0]
        moved = solvable & (np.linalg.norm(current + shift - start, axis=1) <= MAX_MOVE)
        current = np.where(moved[:, None], current + shift, start)
    return current.astype(np.float32), moved


def _edge_line(image: np.ndarray, xy: np.ndarray, forward: np.ndarray, backward: np.ndarray,
               across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lattice line through corners xy along steps `forward` / `backward` (M, 2) (to the two
    neighbours on it; `across`: the step length perpendicular to it): its offset (M,) from xy along
    its unit normal (M, 2), NaN where too few edge profiles are usable."""
    h, w = image.shape
    direction = forward - backward
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    normal = np.stack([-direction[:, 1], direction[:, 0]], 1)
    half = np.minimum(0.3 * across, HALF_WIDTH)  # (M,)
    k = np.arange(-int(HALF_WIDTH / SAMPLE_STEP), int(HALF_WIDTH / SAMPLE_STEP) + 1) * SAMPLE_STEP
    inside = np.abs(k)[None, None] <= half[:, None, None]  # (M, 1, K) samples within the profile
    outer = inside & (np.abs(k)[None, None] >= 0.6 * half[:, None, None])  # its two ends: the squares' levels
    along, offset, usable = [], [], []
    for step in (forward, backward):
        length = np.linalg.norm(step, axis=1)
        unit = step / length[:, None]
        across_unit = np.stack([-unit[:, 1], unit[:, 0]], 1)
        t = np.linspace(*REACH, PROFILES)[None] * length[:, None]  # (M, P)
        centre = xy[:, None] + t[..., None] * unit[:, None]
        points = centre[:, :, None] + k[None, None, :, None] * across_unit[:, None, None]  # (M, P, K, 2)
        px, py = points[..., 0], points[..., 1]
        values = cv2.remap(image, px.reshape(len(xy), -1).astype(np.float32), py.reshape(len(xy), -1).astype(np.float32),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(px.shape)
        low = np.where(outer & (k < 0), values, 0).sum(2) / np.maximum((outer & (k < 0)).sum(2), 1)
        high = np.where(outer & (k > 0), values, 0).sum(2) / np.maximum((outer & (k > 0)).sum(2), 1)
        contrast = high - low
        flat = np.where(contrast == 0, np.nan, contrast)  # no edge: NaN (unusable below), not +-inf
        rise = np.where(inside, (values - low[..., None]) / flat[..., None], 0.0)
        edge = inside.sum(2) * SAMPLE_STEP / 2 - rise.sum(2) * SAMPLE_STEP  # area method: offset along across_unit
        on_image = ((px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)).all(2)
        typical = nanmedian_rows(np.where(on_image, np.abs(contrast), np.nan))[:, None]
        usable.append(on_image & (np.abs(contrast) > 0.5 * typical) & (half[:, None] >= MIN_HALF_WIDTH))
        # the edge point, relative to the corner, in the line's frame (along it, across it)
        point = t[..., None] * unit[:, None] + edge[..., None] * across_unit[:, None]
        along.append((point * direction[:, None]).sum(2))
        offset.append((point * normal[:, None]).sum(2))
    t, s, ok = (np.concatenate(parts, 1) for parts in (along, offset, usable))
    s = np.where(ok, s, 0.0)
    for _ in range(2):  # fit s = a + b t, drop profiles beyond 3 robust sigmas (occluders, clutter), refit
        a, b = _weighted_line(t, s, ok)
        residual = np.abs(s - a[:, None] - b[:, None] * t)
        spread = 1.4826 * nanmedian_rows(np.where(ok, residual, np.nan))[:, None]
        ok &= residual <= 3 * np.maximum(spread, 0.05)
    a, _ = _weighted_line(t, s, ok)
    a[ok.sum(1) < 5] = np.nan
    return a, normal


def _weighted_line(t: np.ndarray, s: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares s = a + b t per row over the `ok` entries; NaN where fewer than two."""
    n = ok.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mt = np.where(ok, t, 0).sum(1) / n
        ms = np.where(ok, s, 0).sum(1) / n
        dt = np.where(ok, t - mt[:, None], 0)
        b = (dt * (s - ms[:, None])).sum(1) / (dt * dt).sum(1)
    return ms - b * mt, b
