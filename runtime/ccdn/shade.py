"""Shadows across a board: how unevenly it is lit, the frame with its light levelled, and the corners
a shadow's edge runs across fitted again there.

A shadow multiplies the grey levels under it; where its edge is soft, the light falls off across
a corner as steeply as the squares differ, and the image tests of ccdn.grid, which compare the four
quads around a corner, fail there even on the log scale (which only turns the shadow's factor into
an offset, not its slope into nothing). Dividing the frame by its light level removes both. The
light level is the lightest squares' envelope: a morphological closing with a box 1.5 lattice
steps across fills the dark squares (no such box fits inside one) but keeps a shadow, far larger,
as it is; it is made on a frame shrunk so the box is about 8 px, then smoothed and brought back up
(on shadow renders a box of 16 or 32 px, or the whole frame, found as many corners within 8 of
6427, no more accurately). Near a shadow's sharp edge the smoothing smears the lit side into the
shade, so the levelled frame has a dark band there: it is a second look, not a replacement.

Across a shadow's edge the light's slope also pulls a corner's saddle fit off its place, and its
edge lines with it (their fit starts there and moves a corner 1 px at most): on the levelled frame
neither is pulled. On the unevenly lit boards the detector found in 100 shadow renders, the ~850
corners across a shadow's edge (across_shadows_edge) were 0.31 px off the truth (mean; p95 1.45, 106
over 1 px); refined on the levelled frame by the saddle fit and then their edge lines, 0.15 px (p95
0.33, 28 over 1 px). Either fit alone there left them 0.22 px off (measured on all 1006 such corners
of those renders' boards).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from .checker import Sampler, quad_means
from .edges import median_step, refine_on_edges
from .refine import refine_saddle_points, window_for_spacing
from .stats import median, quantile, vector_lengths

CLOSING_SQUARES = 1.5  # the closing's box, in squares: dark squares fill, a shadow stays
CLOSING_PX = 8  # the box's size on the shrunk frame the light level is made on
MIN_LIGHT = 4.0  # grey levels: the light level is floored here (black stays black, not noise x 64)
SHADOW_EDGE = 1.2  # a corner's two light quads differing by more than this x lie on both sides of a shadow's edge
LIGHT_SQUARE_PX = 20  # px: light_levels samples squares longer than this on every n-th pixel, n = square // this
SHADE_SHIFT = 2.0  # px: how far the saddle fit on the levelled frame may move a corner across a shadow's edge


def light_levels(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray, sampler: Sampler | None = None) -> np.ndarray:
    """(4, M): the mean grey level of a box at the centre of each of the four quads around board
    corners xy (M, 2) with lattice steps (M, 4, 2) as ccdn.edges.lattice_steps gives them
    (ccdn.checker.quad_means, in its order), NaN where a corner has no step along a row or a column.
    Sampled by `sampler` when given (one of gray), else on the board's own part of gray (an integral
    image of a whole 2000x1500 frame costs ~1 ms)."""
    u, v = steps[:, 0], steps[:, 2]
    ok = np.isfinite(u[:, 0]) & np.isfinite(v[:, 0])
    levels = np.full((4, len(xy)), np.nan)
    if not ok.any():
        return levels
    origin, every = np.zeros(2), 1
    if sampler is None:
        reach = float(np.max(np.abs(u[ok]) + np.abs(v[ok]))) + 1  # past the quads' centres, at (+-u +-v) / 2
        h, w = gray.shape
        x0, y0 = np.maximum(np.floor(xy[ok].min(0) - reach), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(xy[ok].max(0) + reach), [w - 1, h - 1]).astype(int)
        # every n-th pixel of big squares: their boxes still span 5+ of them, at a fraction of the integral's cost
        every = max(1, int(median(vector_lengths(u[ok])) // LIGHT_SQUARE_PX))
        sampler = Sampler(np.ascontiguousarray(gray[y0 : y1 + 1 : every, x0 : x1 + 1 : every]))
        origin = np.array([x0, y0])
    levels[:, ok] = quad_means(sampler, (xy[ok] - origin) / every, u[ok] / every, v[ok] / every)
    return levels


def light_spread(levels: np.ndarray) -> float:
    """How unevenly a board is lit: the 95th over the 5th percentile of its corners' lightest quad
    (light_levels (4, M)); NaN without a measurable corner. Measured on the 1425 boards found in the
    four stress samples' renders of every subset but shadow: 1.0-1.85 (noise, occlusion, glare the
    highest); real-dev: 1.0-1.97, and 3.2 on the one photo with a shadow across its board; 39 of 100
    boards in shadow renders over 2, up to 17."""
    light = np.fmax.reduce(levels, 0)
    light = light[np.isfinite(light)].astype(np.float64)
    if len(light) == 0:
        return float("nan")
    return quantile(light, 0.95) / max(quantile(light, 0.05), 1.0)


def across_shadows_edge(levels: np.ndarray, ratio: float = SHADOW_EDGE) -> np.ndarray:
    """(M,) whether a shadow's edge runs across each corner: its two light quads (light_levels
    (4, M); the quads of one colour are 0 and 3, 1 and 2) differ by more than `ratio` x in grey
    level. Under one light they differ by the print's and the lens's shading only."""
    pairs = np.stack([np.fmax(levels[0], levels[3]), np.fmin(levels[0], levels[3]),
                      np.fmax(levels[1], levels[2]), np.fmin(levels[1], levels[2])])
    lighter = np.where(pairs[0] >= pairs[2], pairs[0] / np.maximum(pairs[1], 1.0), pairs[2] / np.maximum(pairs[3], 1.0))
    return lighter > ratio  # NaN (no steps, quads off the frame): not


def refined_across_shadows_edge(gray: np.ndarray, xy: np.ndarray, steps: np.ndarray, saddle: bool = True
                                ) -> tuple[np.ndarray, np.ndarray]:
    """Board corners xy (M, 2) across a shadow's edge (across_shadows_edge; lattice steps (M, 4, 2))
    refined on the levelled frame (made around them only): the saddle fit (unless not `saddle`), then
    their edge lines (ccdn.edges), where the shadow's slope no longer pulls either. Returns xy (M, 2)
    float32 and whether each moved."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    square = median_step(steps)
    h, w = gray.shape
    margin = 3 * square  # the light level's box and its smoothing reach 1.5 squares, the fits a square
    x0, y0 = np.maximum(np.floor(xy.min(0) - margin), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(xy.max(0) + margin), [w - 1, h - 1]).astype(int)
    origin = np.array([x0, y0])
    flat = levelled(gray[y0 : y1 + 1, x0 : x1 + 1], square)
    radius = window_for_spacing(square)
    start = xy - origin
    begin, converged = start, np.zeros(len(xy), bool)
    if saddle:
        fitted, converged = refine_saddle_points(flat, start, radius, 0.4 * radius, max_shift=SHADE_SHIFT)
        begin = np.where(converged[:, None], fitted, start)
    on_edges, moved = refine_on_edges(flat, begin, steps)
    return (on_edges + origin).astype(np.float32), converged | moved


class LightEnvelope(NamedTuple):
    """A frame's light level (light_envelope): the lightest squares' envelope, uint8, made on the frame
    shrunk `shrink` times, where the closing's box is `size` px."""

    light: np.ndarray
    shrink: float
    size: int


def levelled(gray: np.ndarray, square: float, envelope: LightEnvelope | None = None) -> np.ndarray:
    """gray (uint8) divided by its light level (module docstring) for squares about `square` px
    across, scaled so the light level maps to 255: uint8, gray's shape. envelope: light_envelope(gray,
    square), where made already (ccdn.grid judges the points' light spread by it first)."""
    light, _, size = light_envelope(gray, square) if envelope is None else envelope
    light = cv2.GaussianBlur(light.astype(np.float32), (0, 0), size / 6)
    if light.shape != gray.shape:
        light = cv2.resize(light, (gray.shape[1], gray.shape[0]), interpolation=cv2.INTER_LINEAR)
    return cv2.divide(gray.astype(np.float32), np.maximum(light, MIN_LIGHT), scale=255.0, dtype=cv2.CV_8U)


def points_light_spread(envelope: LightEnvelope, xy: np.ndarray) -> float:
    """How unevenly points xy (N, 2) are lit, as light_spread judges a board's corners, from the
    light level (light_envelope: the closing, unsmoothed) under each point: for points no board holds
    yet (ccdn.grid.find_boards)."""
    light, shrink, _ = envelope
    cell = np.rint((xy + 0.5) / shrink - 0.5).astype(np.int64)
    x = np.clip(cell[:, 0], 0, light.shape[1] - 1)
    y = np.clip(cell[:, 1], 0, light.shape[0] - 1)
    return light_spread(light[y, x][None])


def light_envelope(gray: np.ndarray, square: float) -> LightEnvelope:
    """The lightest squares' envelope (module docstring) for squares about `square` px across, on
    gray shrunk so its closing box is about CLOSING_PX."""
    h, w = gray.shape
    box = max(3.0, CLOSING_SQUARES * square)
    shrink = max(1.0, box / CLOSING_PX)
    small = gray if shrink == 1.0 else cv2.resize(gray, (max(1, round(w / shrink)), max(1, round(h / shrink))),
                                                  interpolation=cv2.INTER_AREA)
    size = int(round(box / shrink)) | 1
    envelope = cv2.morphologyEx(small, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (size, size)))
    return LightEnvelope(envelope, shrink, size)
