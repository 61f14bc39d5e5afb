"""Holes a shrunk pass leaves in a board, filled from the full-resolution network's peaks.

Where an occluder's or a shadow's edge runs along a board's corners, the network on the shrunk
frame often misses them while it finds the board: positions the board holds on two sides or more
along their row and column (ccdn.board.hole_cells: inside it, or in a notch of its outline) where
the image tests of ccdn.grid fail, since something covers part of the corner's quads. The
full-resolution network still peaks on most of them (the 1300 cached stress renders: of the 79
corners the occluded, shadow and two-boards renders missed inside boards the halved frame's pass
found, 69 had a peak within 1.5 px). Sending such frames on to the full-frame pass found 25 corners
more, but at its whole cost (the occluded renders' median time about tripled); here only a box a
step around each hole is scored, and a hole takes the saddle fit of the box's best peak near the
grid's prediction, as the grid's vouching does (ccdn.growth.Grower.vouch): scored at least
HOLE_SCORE x the median of the board's corners in the same boxes, and within HOLE_REACH of a step
of the prediction, which a fit an occluder's edge pulls off the corner leaves. On a board under a
shadow (ccdn.shade) a shadow's edge along the hole pulls that fit off too, or leaves no saddle:
there the fit on the levelled frame is tried, as the detector's edge stage does for such corners.
Measured (1300 renders): 359 -> 308 corners missed (the levelled fit: 323 -> 308), no false
positive more, no render worse; a frame with holes pays 2.1 ms (median over 223 such passes
of 480 renders; mean 3.2), one without 0.04 ms. A hole that a corner of another board fills, which
that board took from this one's lattice, gets it back (settled).
"""

from __future__ import annotations

import cv2
import numpy as np

from .edges import lattice_steps
from .board import Board, hole_cells, indexed_board, largest_first, with_corners
from .grid import MIN_CORNERS, SHADE_SPREAD
from .lattice import inside_margin, local_homography
from .peaks import best_near, best_peak
from .refine import refine, window_for_spacing
from .shade import light_levels, light_spread, refined_across_shadows_edge
from .stats import median, vector_lengths

HOLE_REACH = 0.05  # of the local step: the fit this far from the prediction at most (0.1 took a corner an
# occluder's edge pulled 2.1 px off)
HOLE_SCORE = 0.5  # x the median full-resolution score of the board's corners around the holes
NEAR_CELLS = 2  # a hole's prediction: a homography fitted to the board's corners up to this many cells away


def predicted_holes(board: Board, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The holes (ccdn.board.hole_cells) of a board in a frame of `shape` (H, W), predicted
    (predicted_cells)."""
    return predicted_cells(board.grid, board.xy, hole_cells(board), shape)


def predicted_cells(grid: np.ndarray, xy: np.ndarray, cells: np.ndarray, shape: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions of a board's (corners at (row, col) `grid` (M, 2), positions xy (M, 2)) empty
    `cells` (K, 2) in a frame of `shape` (H, W), each predicted by a homography fitted to the
    board's corners up to NEAR_CELLS cells away: the cells kept (F, 2), their predictions (F, 2) and
    lattice steps there (F, 4, 2: +col, -col, +row, -row, as ccdn.edges.lattice_steps). Cells with
    fewer than 4 such corners, a degenerate fit, or a prediction off the frame (less than
    EDGE_MARGIN inside: ccdn.lattice.inside_margin; a board the frame cuts) are left out."""
    found_cells, preds, steps = [], [], []
    for cell in cells:
        if (homography := local_homography(grid, xy, cell, NEAR_CELLS, 4)) is None:
            continue
        at = np.array([[cell[::-1], cell[::-1] + (1, 0), cell[::-1] + (0, 1)]], np.float64)  # (col, row), like (x, y)
        point, along_row, along_col = cv2.perspectiveTransform(at, homography)[0]
        if not inside_margin(point[None], shape)[0]:
            continue
        u, v = along_row - point, along_col - point
        found_cells.append(cell)
        preds.append(point)
        steps.append((u, -u, v, -v))
    if not found_cells:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 4, 2))
    return np.array(found_cells), np.array(preds), np.array(steps)


def hole_boxes(preds: np.ndarray, steps: np.ndarray, shape: tuple[int, int]) -> list[tuple[int, int, int, int]]:
    """Boxes (top, bottom, left, right) covering one step around each prediction (lattice steps
    (K, 4, 2)): the hole and its neighbours, whose scores are the reference. Overlapping ones are
    merged into the box around both: each box is one network call with its receptive halo
    (ccdn.session.ScoreSession.scores_in), and a board's holes often lie side by side."""
    h, w = shape
    reach = np.ceil(shorter_step(steps) + 1).astype(np.int64)
    x, y = np.rint(preds[:, 0]).astype(np.int64), np.rint(preds[:, 1]).astype(np.int64)
    boxes = [[max(b - r, 0), min(b + r + 1, h), max(a - r, 0), min(a + r + 1, w)] for a, b, r in zip(x, y, reach)]
    merged = []
    while boxes:  # a handful of boxes: each one grows by every box it overlaps until none does
        box = boxes.pop()
        overlapping = [other for other in boxes if other[0] < box[1] and box[0] < other[1] and other[2] < box[3]
                       and box[2] < other[3]]
        if overlapping:
            boxes = [other for other in boxes if other not in overlapping]
            boxes.append([min(b[0] for b in overlapping + [box]), max(b[1] for b in overlapping + [box]),
                          min(b[2] for b in overlapping + [box]), max(b[3] for b in overlapping + [box])])
        else:
            merged.append(tuple(int(v) for v in box))
    return merged


def filled_holes(gray: np.ndarray, board: Board, cells: np.ndarray, preds: np.ndarray, steps: np.ndarray,
                 score: np.ndarray, taken: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The holes (cells, preds, lattice steps: predicted_holes) that the full-resolution `score` map
    (scored around them) fills: each hole's peak fit (peak_fits), placed (placed), or, on a board
    lit unevenly (ccdn.shade.light_spread above ccdn.grid.SHADE_SPREAD), the fit on the levelled
    frame where that one fails (a shadow's edge across the corner pulls the saddle fit off it, or
    leaves no saddle: ccdn.shade). Returns their cells (F, 2), positions (F, 2) and scores (F,)."""
    step = shorter_step(steps)
    values, strong, fitted, ok = peak_fits(gray, score, preds, steps, board.xy, window_for_spacing(float(median(step))))
    ok &= placed(fitted, preds, step, gray.shape, taken)
    if (again := strong & ~ok).any() and light_spread(light_levels(gray, board.xy.astype(np.float64),
                                                                    lattice_steps(board))) > SHADE_SPREAD:
        levelled_fit, moved = refined_across_shadows_edge(gray, preds[again], steps[again])
        fitted[again] = levelled_fit
        ok[again] = moved & placed(levelled_fit, preds[again], step[again], gray.shape, taken)
    ok &= strong
    return cells[ok], fitted[ok].astype(np.float32), values[ok].astype(np.float32)


def peak_fits(frame: np.ndarray, score: np.ndarray, preds: np.ndarray, steps: np.ndarray, board_xy: np.ndarray,
              radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For predictions preds (K, 2) with lattice steps (K, 4, 2) on `frame` and its `score` map
    (scored around them; board_xy (M, 2): the board's corners there): each one's best score within a
    quarter step (K,), whether that is >= HOLE_SCORE x the median of the board's corners the scored
    boxes cover (K,), and its saddle fit (window `radius`) on the frame (K, 2) and whether it
    converged (K,)."""
    step = shorter_step(steps)
    peaks, values = zip(*(best_peak(score, p, max(1, int(0.25 * s))) for p, s in zip(preds, step)))
    values = np.array(values)
    own = board_xy[best_near(score, board_xy, 0) > 0]
    strong = values >= HOLE_SCORE * median(best_near(score, own)) if len(own) else np.zeros(len(values), bool)
    fitted, converged = refine(frame, np.array(peaks, np.float64), "saddle", float(0.25 * step.max()), radius)
    return values, strong, fitted, converged


def placed(fitted: np.ndarray, preds: np.ndarray, step: np.ndarray, shape: tuple[int, int],
           taken: np.ndarray) -> np.ndarray:
    """(K,) whether fits lie within HOLE_REACH x the shorter step of their predictions, EDGE_MARGIN
    inside a frame of `shape` (as every board corner: ccdn.lattice.inside_margin) and no closer than
    half a step to a corner already `taken` (M, 2)."""
    ok = (vector_lengths(fitted - preds) <= HOLE_REACH * step) & inside_margin(fitted, shape)
    if len(taken):
        ok &= vector_lengths(fitted[:, None] - taken[None]).min(1) >= 0.5 * step
    return ok


def shorter_step(steps: np.ndarray) -> np.ndarray:
    """(K,) the shorter of the lattice steps (K, 4, 2) along the row and the column."""
    return np.minimum(vector_lengths(steps[:, 0]), vector_lengths(steps[:, 2]))


def settled(boards: tuple[Board, ...], shape: tuple[int, int]) -> tuple[Board, ...]:
    """The boards, where a corner one board holds lies on another board's lattice at one of its holes
    (within HOLE_REACH of a step of that board's prediction there: predicted_holes), moved to that
    board where its own board predicts it worse (relative to its step; no prediction at all: a
    corner with fewer than 4 of its board's corners around it) and keeps its extent and
    MIN_CORNERS without it. Where a small board lies on a large one, growth let the large one take
    a corner of the small one's lattice lying where the large one's own corner hides beneath, and
    the small board's grid then lacked it: a board wrongly indexed (stress two-boards renders
    7121130, 7121346, 7122387; also 7120620 and 7121496, which ccdn.growth.CROWDED keeps right
    already). Measured: the first 240 two-boards renders of the stress set, 4 -> 1 of 458 boards
    wrongly indexed (the one left: a small board whose lattice continues a large one's, merged into
    it); 120 occluded renders: none; the 1300 cached stress renders' corners identical
    but for the one moved (7121130), real-dev identical per image. Cost: a frame of one board none,
    the README sample's 20 two-boards renders 0.13 ms median (0.00-4.7)."""
    if len(boards) < 2:
        return boards
    boards = list(boards)
    for b in range(len(boards)):
        cells, preds, steps = predicted_holes(boards[b], shape)
        for cell, pred, step in zip(cells, preds, shorter_step(steps)):
            for a, board in enumerate(boards):
                k = None if a == b else _claimed(board, pred, step, shape)
                if k is None:
                    continue
                rest = np.arange(len(board)) != k
                boards[b] = with_corners(boards[b], cell[None], board.xy[k : k + 1], int(board.corner_index[k]))
                boards[a] = indexed_board(board.corner_index[rest], board.grid[rest], board.xy[rest])
                break
    return tuple(largest_first(boards))


def _claimed(board: Board, pred: np.ndarray, step: float, shape: tuple[int, int]) -> int | None:
    """The board's corner that another board's hole predicted at `pred` (its shorter step there:
    `step`) claims (settled): the nearest, within HOLE_REACH of that step, where the board keeps
    more than MIN_CORNERS and its extent without it and predicts it worse itself; None otherwise."""
    if len(board) <= MIN_CORNERS:
        return None
    off = vector_lengths(board.xy - pred)
    k = int(off.argmin())
    rest = np.arange(len(board)) != k
    grid = board.grid[rest]
    if off[k] > HOLE_REACH * step or grid.min(0).any() or (grid.max(0) < board.grid.max(0)).any():
        return None
    cells, preds, steps = predicted_cells(grid, board.xy[rest], board.grid[k : k + 1], shape)
    own = vector_lengths(board.xy[k] - preds[0]) / shorter_step(steps)[0] if len(cells) else np.inf
    return k if own > off[k] / step else None
