"""A board's part in deep shade, grown from the part the network found.

Where a shadow takes most of the light from part of a board (the stress benchmark's shadow subset:
80-95 %), the network's scores there fall below the peak threshold (one fresh render's 27 missed
corners: 0.27-0.79 x the board's median) and the image tests of ccdn.grid fail along the shadow's
soft edge, so the board is found without that part. None of its corners then lies in shade, so it
is not lit unevenly (ccdn.shade.light_spread), but the shadow's edge runs across corners on its
outline: their two light quads differ by over SHADE_SPREAD x (ccdn.shade.across_shadows_edge; at
the 1.2 x that marks a shadow's edge on a shaded board, two of the latency benchmark's 12 real
photos, lit unevenly, paid 4-36 ms for a look that found nothing). Such a board is grown outwards
on the frame levelled around it (ccdn.shade.levelled), where the shaded squares look lit and the
network scores them like lit ones (those 27: 0.74-1.16 x the median). Round by round, from those
corners and then from the ones taken, each empty position next to them along a row or column that
lies in shade (its lightest quad lit at most 1 / SHADE_SPREAD as brightly as the board's corners'
median) or in its penumbra (its own light quads differ by over SHADOW_EDGE) takes the saddle fit,
on the levelled frame, of the network's best score there within a quarter step of its prediction
(a homography fitted to the corners around it: ccdn.holes.predicted_cells), where that score is at
least HOLE_SCORE x the median of the board's corners scored with it, the fit lies within
HOLE_REACH of a step of the prediction, and its four quads alternate in the board's colours, evenly
(ccdn.growth.PAIR_RATIO), on the levelled frame: beyond a board's outline, where levelling makes the
background look light, they do not. New corners left with fewer than two row/column neighbours are
dropped (lone points on an outline). Without the shade test, 21 outline points of evenly lit
boards in 120 fresh renders were taken; without the alternation test or the lone points' drop, 1-2
outline points in shade with clutter along them. Measured (1300 cached stress renders; 120 fresh
ones): 308 -> 290 corners missed (shadow 71 -> 54), fresh shadow renders 2.38 -> 1.17 %, no false
positive more, the new corners 0.0-0.45 px off their labels; a board pays 0.03 ms for the check, a
shadow render's 5-7 ms (median) for the look.
"""

from __future__ import annotations

import numpy as np

from .checker import Sampler, grid_parity, light_parity, quad_differences
from .edges import median_step
from .board import Board, reoriented, with_corners
from .grid import SHADE_SPREAD
from .growth import PAIR_RATIO
from .holes import hole_boxes, peak_fits, placed, predicted_cells, shorter_step
from .lattice import row_col_neighbours
from .refine import window_for_spacing
from .session import ScoreSession
from .shade import across_shadows_edge, levelled, light_levels
from .stats import median

SHADE_MARGIN = 4  # squares: the levelled frame and the network's scores on it reach this far around the board


def grown_into_shade(gray: np.ndarray, board: Board, steps: np.ndarray, levels: np.ndarray, session: ScoreSession,
                     taken: np.ndarray) -> tuple[Board, np.ndarray, np.ndarray]:
    """The board (its lattice steps (M, 4, 2: ccdn.edges.lattice_steps) and its corners' light
    levels (4, M: ccdn.shade.light_levels)) grown into the deep shade next to it (module docstring)
    where a shadow's edge runs across its corners: the board, its new corners indexed from len(taken)
    on and its indices oriented again (ccdn.board.reoriented), their positions (F, 2) and scores
    (F,: the network's, on the levelled frame).
    taken: (N, 2) the corners found so far, which no new one may lie within half a step of."""
    none = board, np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    lightest = np.fmax.reduce(levels, 0)[np.isfinite(levels).all(0)]
    edge = across_shadows_edge(levels, SHADE_SPREAD)  # a deep shadow's (real photos' uneven light: under 2 x)
    if not edge.any() or len(lightest) == 0:
        return none
    lit, square = median(lightest), median_step(steps)
    h, w = gray.shape
    margin = SHADE_MARGIN * square
    low = np.maximum(np.floor(board.xy.min(0) - margin), 0).astype(int)
    high = np.minimum(np.ceil(board.xy.max(0) + margin), [w - 1, h - 1]).astype(int)
    grid, xy = board.grid.astype(np.int64), board.xy.astype(np.float64)
    cells = _shaded_cells(gray, grid, xy, edge, lit, low + square, high - square)
    if len(cells[0]) == 0:  # no shade next to the board: the look below is not made
        return none
    look = _LevelledLook(gray, board, steps, low, high, square, session)
    if look.sign == 0:
        return none
    found_cells, found_xy, found_scores = [], [], []
    while len(cells[0]):
        ok, fitted, values = look.fits(*cells, xy, np.concatenate([xy, taken.reshape(-1, 2)]))
        if not ok.any():
            break
        grid, xy = np.concatenate([grid, cells[0][ok]]), np.concatenate([xy, fitted[ok]])
        found_cells.append(cells[0][ok])
        found_xy.append(fitted[ok])
        found_scores.append(values[ok])
        cells = _shaded_cells(gray, grid, xy, np.arange(len(grid)) >= len(grid) - ok.sum(), lit, low + square,
                              high - square)
    if not found_cells:
        return none
    held = _held(grid, np.arange(len(grid)) >= len(board))[len(board):]
    cells, points = np.concatenate(found_cells)[held], np.concatenate(found_xy)[held].astype(np.float32)
    grown = reoriented(with_corners(board, cells, points, len(taken)), look.sign) if held.any() else None
    if grown is None:
        return none
    return grown, points, np.concatenate(found_scores)[held].astype(np.float32)


def _shaded_cells(gray: np.ndarray, grid: np.ndarray, xy: np.ndarray, around: np.ndarray, lit: float,
                  low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The empty cells next to the board's corners `around` (M,) (of grid (M, 2), xy (M, 2)) predicted
    between (x, y) `low` and `high` (ccdn.holes.predicted_cells: cells, predictions, lattice steps)
    in shade: whose lightest quad is lit at most 1 / SHADE_SPREAD as brightly as `lit`, the board's
    corners' median, or across which a shadow's edge runs (ccdn.shade.across_shadows_edge: the
    penumbra). The board grows from the corners a shadow's edge runs across, then from those it took."""
    cells, preds, steps = predicted_cells(grid, xy, _next_to(grid, around), gray.shape)
    keep = ((preds >= low) & (preds <= high)).all(1)
    levels = light_levels(gray, preds[keep], steps[keep])
    keep[keep] = (np.fmax.reduce(levels, 0) * SHADE_SPREAD <= lit) | across_shadows_edge(levels)
    return cells[keep], preds[keep], steps[keep]


class _LevelledLook:
    """The frame levelled around a board (between (x, y) `low` and `high`; squares `square` px
    across), the board's colours there (sign: ccdn.checker.light_parity) and the network's scores
    on it, asked for a step around the positions looked at only (as ccdn.holes does: on the whole
    levelled part of a shadow render's frame the network cost 11-66 ms)."""

    def __init__(self, gray: np.ndarray, board: Board, steps: np.ndarray, low: np.ndarray, high: np.ndarray,
                 square: float, session: ScoreSession) -> None:
        self.origin, self.session = low, session
        self.flat = levelled(gray[low[1] : high[1] + 1, low[0] : high[0] + 1], square)
        self.sampler = Sampler(self.flat)
        self.sign = light_parity(self.sampler, board.xy - low, board.grid, steps[:, 0], steps[:, 2])
        self.radius = window_for_spacing(square)
        self.shape = gray.shape

    def fits(self, cells: np.ndarray, preds: np.ndarray, steps: np.ndarray, board_xy: np.ndarray,
             taken: np.ndarray):
        """For cells (K, 2) predicted at preds (K, 2) with lattice steps (K, 4, 2): whether each takes
        its fit (module docstring; the board's median score: that of its corners board_xy (M, 2) the
        scored boxes cover; none within half a step of `taken` (N, 2)), the fits (K, 2) and their
        scores (K,)."""
        score = self.session.scores_in(self.flat, hole_boxes(preds - self.origin, steps, self.flat.shape))
        values, strong, fitted, ok = peak_fits(self.flat, score, preds - self.origin, steps, board_xy - self.origin,
                                               self.radius)
        fitted = fitted + self.origin
        ok &= strong & placed(fitted, preds, shorter_step(steps), self.shape, taken)
        ok &= _alternating(self.sampler, fitted - self.origin, steps, cells, self.sign)
        return ok, fitted, values


def _next_to(grid: np.ndarray, around: np.ndarray) -> np.ndarray:
    """(K, 2) the empty (row, col) next to the board's corners `around` (M,) of those at `grid` (M, 2)
    along a row or a column, also beyond its extent (indices may fall below 0)."""
    filled, low = _canvas(grid)
    centres, _ = _canvas(grid[around], low, filled.shape)
    return np.argwhere((row_col_neighbours(centres) > 0) & ~filled) + low


def _held(grid: np.ndarray, new: np.ndarray) -> np.ndarray:
    """(M,) the corners at `grid` (M, 2) kept once the `new` ones (M,) left with fewer than two
    row/column neighbours are dropped, round after round (lone points on the outline, as ccdn.grid
    drops them)."""
    kept = np.ones(len(grid), bool)
    filled, low = _canvas(grid)  # every cell's canvas: a dropped one may lie beyond the kept ones' margin
    at = tuple((grid - low).T)
    while True:
        lone = kept & new & (row_col_neighbours(filled)[at] < 2)
        if not lone.any():
            return kept
        kept &= ~lone
        filled[tuple((grid[lone] - low).T)] = False


def _canvas(grid: np.ndarray, low: np.ndarray | None = None, shape: tuple[int, ...] | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """A bool canvas of cells `grid` (M, 2) and the (row, col) of its (0, 0): by default with a free
    cell around them, else from `low`, of `shape`."""
    if low is None:
        low = grid.min(0) - 1
        shape = tuple(grid.max(0) - low + 2)
    filled = np.zeros(shape, bool)
    filled[tuple((grid - low).T)] = True
    return filled, low


def _alternating(sampler: Sampler, xy: np.ndarray, steps: np.ndarray, cells: np.ndarray, sign: float) -> np.ndarray:
    """(K,) whether the four quads around points xy (K, 2; lattice steps (K, 4, 2)) at `cells` alternate
    in the board's colours (sign: ccdn.checker.light_parity), the weakest pair at least PAIR_RATIO x
    the strongest."""
    diffs, _ = quad_differences(sampler, xy, steps[:, 0], steps[:, 2])
    signed = diffs * (grid_parity(cells) * sign)[:, None]
    with np.errstate(invalid="ignore"):
        return (signed.min(1) > 0) & (signed.min(1) >= PAIR_RATIO * signed.max(1))


