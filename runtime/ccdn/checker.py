"""Image evidence for checker corners: box means of the grey level, the four quads around a corner,
and a ring test for X-junctions (used by ccdn.grid to verify corners and lattices).

Pixel convention: (0, 0) is the centre of the top-left pixel; points are (x, y).
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from .stats import median, nanmedian_rows

MIN_CONTRAST = 2.0  # grey levels: differences below this are noise
CROP_MIN_SAVING = 1_000_000  # pixels a Sampler's crop must spare of the frame to be worth its bounds checks
NOISY_SIGMA = 5.0  # grey levels of image noise from which a frame is noisy: its board corners are refined on their
# edges (ccdn.edges), its seed squares' quads may range more (ccdn.seeds)
NOISE_SAMPLE_PIXELS = 1 << 15  # the noise estimate's median is taken over about this many pixels (1 << 17 made
# the same decisions on 92 real-dev frames and 320 stress renders, in 3x the time)
_LAPLACIAN_PAIR = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]])  # zero on planes; |kernel| = 6


class Sampler:
    """Mean grey level of small boxes, via an integral image (NaN where the centre is off the image).

    Given `around` ((N, 2) points, margin px), the integral covers only the points' bounding box
    grown by the margin, where that spares the frame at least CROP_MIN_SAVING pixels: a 12 Mpx
    frame's whole integral costs ~13 ms. A box reaching past the window grows it (by the margin
    again) and integrates that, so every mean is the same either way."""

    def __init__(self, gray: np.ndarray, around: tuple[np.ndarray, float] | None = None) -> None:
        self._gray = gray
        self._noise: float | None = None  # image_noise(gray), once asked for (noise)
        self.height, self.width = gray.shape
        self._margin = 0.0
        window = (0, self.height, 0, self.width)
        if around is not None and len(around[0]):
            points, self._margin = around
            window = self._grown(*points.min(0), *points.max(0))
        self._integrate(*window)

    def _grown(self, left: float, top: float, right: float, bottom: float) -> tuple[int, int, int, int]:
        """The window (top, bottom, left, right) over pixels left..right, top..bottom grown by the margin,
        or the whole frame where that would spare it fewer than CROP_MIN_SAVING pixels."""
        m = self._margin
        window = (max(math.floor(top - m), 0), min(math.ceil(bottom + m) + 1, self.height),
                  max(math.floor(left - m), 0), min(math.ceil(right + m) + 1, self.width))
        if self._gray.size - (window[1] - window[0]) * (window[3] - window[2]) < CROP_MIN_SAVING:
            return 0, self.height, 0, self.width
        return window

    def _integrate(self, top: int, bottom: int, left: int, right: int) -> None:
        """The integral image of gray[top:bottom, left:right], flat (np.take beats 2-D fancy indexing)."""
        crop = self._gray[top:bottom, left:right]
        # int32 sums where they cannot overflow (crops up to 8.4 Mpx): a third of float64's time
        depth = cv2.CV_32S if crop.size * 255 < 2**31 else cv2.CV_64F
        self._integral = cv2.integral(crop, sdepth=depth).ravel()
        self._window = top, bottom, left, right
        self._cropped = (top, bottom, left, right) != (0, self.height, 0, self.width)

    def noise(self) -> float:
        """The image noise's standard deviation in grey levels (image_noise), estimated once."""
        if self._noise is None:
            self._noise = image_noise(self._gray)
        return self._noise

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(...) whether points (..., 2) round to a pixel of the image."""
        x, y = np.rint(points[..., 0]), np.rint(points[..., 1])
        return (x >= 0) & (y >= 0) & (x < self.width) & (y < self.height)

    def mean(self, points: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Mean over the (2 radius + 1)^2 box around each point (..., 2); radius: int, broadcast
        against points' leading shape."""
        xi = np.rint(points[..., 0]).astype(np.int64)
        yi = np.rint(points[..., 1]).astype(np.int64)
        w1, h1 = self.width - 1, self.height - 1
        # np.minimum / np.maximum: np.clip's Python wrapper costs more than the work on these sizes
        x0, x1 = np.minimum(np.maximum(xi - radius, 0), w1), np.minimum(np.maximum(xi + radius, 0), w1) + 1
        y0, y1 = np.minimum(np.maximum(yi - radius, 0), h1), np.minimum(np.maximum(yi + radius, 0), h1) + 1
        area = (x1 - x0) * (y1 - y0)
        if self._cropped and x0.size:
            top, bottom, left, right = self._window
            low_x, high_x, low_y, high_y = int(x0.min()), int(x1.max()), int(y0.min()), int(y1.max())
            if low_y < top or high_y > bottom or low_x < left or high_x > right:  # grow the window to hold them
                self._integrate(*self._grown(min(low_x, left), min(low_y, top), max(high_x, right) - 1,
                                             max(high_y, bottom) - 1))
            if self._cropped:
                top, _, left, _ = self._window
                x0, x1, y0, y1 = x0 - left, x1 - left, y0 - top, y1 - top
        stride = self._window[3] - self._window[2] + 1  # the integral's row length
        row0, row1 = y0 * stride, y1 * stride
        s = self._integral
        total = s.take(row1 + x1) - s.take(row0 + x1) - s.take(row1 + x0) + s.take(row0 + x0)
        inside = (xi >= 0) & (yi >= 0) & (xi <= w1) & (yi <= h1)
        return np.where(inside, total / area, np.nan)


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


def altitude(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The lesser height of the parallelograms spanned by steps u, v (N, 2): a square's narrowest
    width (0 for zero-length steps)."""
    longest = np.maximum(np.hypot(u[:, 0], u[:, 1]), np.hypot(v[:, 0], v[:, 1]))
    return np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]) / np.maximum(longest, 1e-9)


def quad_levels(sampler: Sampler, p: np.ndarray, u: np.ndarray, v: np.ndarray, reach: float = 0.125,
                axes: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grey levels of the 4 quads around corners p (K, 2), lattice steps u, v: each quad's median,
    lowest and highest sample, (4, K) each, quads +u+v, +u-v, -u+v, -u-v (the first shares the
    corner's row + col parity). A quad is sampled at its centre and centre +- reach (u +- v); with
    axes > 0 also at centre +- axes u and +- axes v, 9 samples in all (a larger reach tells more
    lattices apart, a smaller one tolerates more distortion; the axis samples catch a grid of thin
    lines, whose crossings look like dark quads along the lines' directions only). A quad centre off
    the image is sampled halfway to it; samples off the image are NaN.
    """
    p = np.atleast_2d(p)
    if u.shape != p.shape or v.shape != p.shape:  # broadcast_to's cost shows on these small calls
        u, v = np.broadcast_to(u, p.shape), np.broadcast_to(v, p.shape)
    coefficients = _quad_coefficients(reach, axes)
    steps = _combinations(u, v, coefficients)
    half, quarter, offsets = steps[:4], steps[4:8], steps[8:]  # (4, K, 2), (4, K, 2), (S, K, 2)
    centre = p + half
    off = ~sampler.contains(centre)
    if off.any():
        centre[off] = (p + quarter)[off]
    samples = sampler.mean(centre[:, None] + offsets, box_radius(u, v))  # (4 quads, S samples, K)
    ordered = np.sort(samples, axis=1)  # NaN samples (off the image) last, so all-NaN stays NaN
    # fmax skips NaN samples without nanmax's warnings
    return ordered[:, len(offsets) // 2], ordered[:, 0], np.fmax.reduce(samples, 1)


def quad_means(sampler: Sampler, p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(4, K): the mean grey level of one box at each quad's centre around corners p (K, 2), lattice
    steps u, v (K, 2), in quad_levels' order: a cheaper look than its 5 samples per quad (NaN off
    the image)."""
    return sampler.mean(p + _combinations(u, v, _HALF_STEPS), box_radius(u, v))


def _combinations(u: np.ndarray, v: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """(R, K, 2): the steps given by coefficients (R, 4) over the basis (u + v, u - v, u, v) of lattice
    steps u, v (K, 2), all in one product. Zero coefficients add exact zeros, so a row with one
    nonzero coefficient c gives c (u + v), c (u - v), c u or c v rounded once, and a row (0, 0, +-b,
    +-b) with b a power of 2 gives b (+-u +- v) rounded once: each step as if computed alone."""
    basis = np.concatenate((u + v, u - v, u, v)).reshape(4, -1)
    return (coefficients @ basis).reshape(len(coefficients), len(u), 2)


def box_radius(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) int: the radius of the boxes sampled in quads of steps u, v: well inside a square."""
    return np.floor(0.12 * altitude(u, v)).astype(np.int64)


def pair_differences(levels: np.ndarray) -> np.ndarray:
    """(K, 4): own-parity minus other-parity quad over the 4 edge-adjacent pairs (QUAD_PAIRS) of
    quad levels (4, K) (quad_levels' medians, or any function of them that keeps their order),
    positive when the corner's own-parity quads are light."""
    return (levels.take(_OWN_QUADS, 0) - levels.take(_OTHER_QUADS, 0)).T  # take: a fifth of indexing's cost


def quad_spread(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(K,): the largest range of the samples within one quad (quad_levels' low and high, (4, K)),
    small when they sit inside squares, large when a wrong lattice puts them on edges or in other
    squares."""
    return np.fmax.reduce(high - low, 0)


def quad_differences(sampler: Sampler, p: np.ndarray, u: np.ndarray, v: np.ndarray, reach: float = 0.125,
                     axes: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The grey-level contrast and uniformity of the quads around corners p (quad_levels):
    (pair_differences (K, 4), quad_spread (K,))."""
    median, low, high = quad_levels(sampler, p, u, v, reach, axes)
    return pair_differences(median), quad_spread(low, high)


def light_parity(sampler: Sampler, xy: np.ndarray, grid: np.ndarray, u: np.ndarray, v: np.ndarray) -> float:
    """+1 where the quads of even row + col of a board's grid are light, -1 where dark, 0 where its
    corners do not tell: the sign of the median over its corners xy (M, 2) at grid (M, 2) (row, col)
    of their quad pair differences (lattice steps u, v (M, 2) along +col and +row, NaN where
    unknown) times their parity (grid_parity). A board's orientation turns on it (ccdn.board)."""
    ok = np.isfinite(u[:, 0]) & np.isfinite(v[:, 0])
    diffs, _ = quad_differences(sampler, xy[ok], u[ok], v[ok])
    told = nanmedian_rows(diffs) * grid_parity(grid[ok])
    told = told[np.isfinite(told)]
    return float(np.sign(median(told))) if len(told) else 0.0


def grid_parity(cells: np.ndarray) -> np.ndarray:
    """(K,) +1 for (row, col) of even row + col, -1 for odd."""
    return np.where(cells.sum(1) % 2 == 0, 1.0, -1.0)


# the quads +u+v, +u-v, -u+v, -u-v (0..3): the steps (+-u +- v) / 2 from a corner to their centres over
# _combinations' basis (u + v, u - v, u, v), and the edge-adjacent pairs quad_differences returns, in its
# order: (own-parity quad, other-parity quad)
_HALF_STEPS = np.array([[0, 0, 1, 1], [0, 0, 1, -1], [0, 0, -1, 1], [0, 0, -1, -1]]) / 2
QUAD_PAIRS = np.array([[0, 1], [0, 2], [3, 1], [3, 2]])
_HALF_STEPS.setflags(write=False)
QUAD_PAIRS.setflags(write=False)
PAIRS_WITHOUT = np.array([np.nonzero((QUAD_PAIRS != quad).all(1))[0] for quad in range(4)])  # (4 quads, 2): the
# pairs (pair_differences' columns) that leave each quad out: a corner's pairs where one quad is hidden
PAIRS_WITHOUT.setflags(write=False)
_OWN_QUADS, _OTHER_QUADS = QUAD_PAIRS.T


@lru_cache(maxsize=8)
def _quad_coefficients(reach: float, axes: float) -> np.ndarray:
    """(8 + S, 4): quad_levels' steps over _combinations' basis (u + v, u - v, u, v) (read-only): from
    a corner halfway and a quarter of the way across each quad (its centre, and the one used when
    that is off the image), then from a quad's centre to its S samples."""
    rows = [(0, 0, 0, 0), (reach, 0, 0, 0), (-reach, 0, 0, 0), (0, reach, 0, 0), (0, -reach, 0, 0)]
    if axes > 0:
        rows += [(0, 0, axes, 0), (0, 0, -axes, 0), (0, 0, 0, axes), (0, 0, 0, -axes)]
    coefficients = np.concatenate([_HALF_STEPS, _HALF_STEPS / 2, np.array(rows, np.float64)])
    coefficients.setflags(write=False)
    return coefficients


def axis_pull(sampler: Sampler, p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) for corners p (K, 2) with lattice steps u, v: how far, over their quads, the grey level
    sampled 0.3 of a step from a quad's centre along u and v (4 samples) lies beyond the level 0.25
    of the way to its corners (4 samples), towards the other colour, in units of the corner's
    contrast (the mean of its quad centres' distance from their mean); the largest of its 4 quads.
    A checker square is uniform: ~0. Where a grid of thick lines passes for a board on the lattice
    of its crossings and cells turned 45 degrees, a crossing is dark along the lines, i.e. along its
    quad's diagonals, and light between them: ~1 (NaN where a quad is off the image)."""
    p = np.atleast_2d(p)
    samples = sampler.mean(p + _combinations(u, v, _PULL_STEPS), box_radius(u, v)).reshape(4, 9, -1)
    centre = samples[:, 0]  # (4, K)
    pull = _PULL_WEIGHTS @ samples  # (4, K): the axis samples' mean minus the diagonal ones'
    middle = centre.mean(0)
    contrast = np.abs(centre - middle).mean(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.fmax.reduce(pull * np.sign(middle - centre) / contrast, 0)


def _pull_steps() -> np.ndarray:
    """(36, 4): axis_pull's samples over _combinations' basis (u + v, u - v, u, v), per quad: its
    centre, 0.25 of the way to its 4 corners (along u + v and u - v), 0.3 of a step along +-u, +-v."""
    offsets = np.array([(0, 0, 0, 0), (0.25, 0, 0, 0), (-0.25, 0, 0, 0), (0, 0.25, 0, 0), (0, -0.25, 0, 0),
                        (0, 0, 0.3, 0), (0, 0, -0.3, 0), (0, 0, 0, 0.3), (0, 0, 0, -0.3)])
    steps = (_HALF_STEPS[:, None] + offsets[None]).reshape(-1, 4)
    steps.setflags(write=False)
    return steps


_PULL_STEPS = _pull_steps()
_PULL_WEIGHTS = np.array([0.0] + [-0.25] * 4 + [0.25] * 4)  # a quad's 9 samples: + axis, - diagonal means
_PULL_WEIGHTS.setflags(write=False)

_RING_ANGLES = np.arange(16) * (2 * np.pi / 16)
_RING_COS, _RING_SIN = np.cos(_RING_ANGLES), np.sin(_RING_ANGLES)
_RING_HARMONICS = np.stack([_RING_COS, _RING_SIN, np.cos(2 * _RING_ANGLES), np.sin(2 * _RING_ANGLES)],
                           1)  # (16, 4); zero-mean, so the ring's mean drops out


def x_like(gray: np.ndarray, xy: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(N,) whether the grey level on a ring around each point (radius 0.3 of the `spacing` (N,) to
    its neighbours, 1.5..15 px) alternates twice like at a checker corner: 2nd angular harmonic
    above the 1st and above MIN_CONTRAST."""
    radius = np.clip(0.3 * spacing, 1.5, 15.0)
    mx = (xy[:, :1] + radius[:, None] * _RING_COS).astype(np.float32)
    my = (xy[:, 1:] + radius[:, None] * _RING_SIN).astype(np.float32)
    ring = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    harmonics = ring @ _RING_HARMONICS / 8  # (N, 4): cos, sin parts of the 1st and 2nd harmonic
    first, second = np.hypot(harmonics[:, 0], harmonics[:, 1]), np.hypot(harmonics[:, 2], harmonics[:, 3])
    return (second > first) & (second > MIN_CONTRAST)
