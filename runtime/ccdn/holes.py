"""Holes a shrunk pass leaves in a board, filled from the full-resolution network's peaks.

Where an occluder's or a shadow's edge runs along a board's corners, the network on the shrunk
frame often misses them while it finds the board: positions the board holds on two sides or more
along their row and column (ccdn.grid.hole_cells: inside it, or in a notch of its outline) where
the image tests of ccdn.grid fail, since something covers part of the corner's quads. The
full-resolution network still peaks on most of them (the 1300 cached stress renders: of the 79
corners the occluded, shadow and two-boards renders missed inside boards the halved frame's pass
found, 69 had a peak within 1.5 px). Sending such frames on to the full-frame pass found 25 corners
more, but at its whole cost (the occluded renders' median time about tripled); here only a box a
step around each hole is scored, and a hole takes the saddle fit of the box's best peak near the
grid's prediction, as the grid's vouching does (ccdn.grid._Grower.vouch): scored at least
HOLE_SCORE x the median of the board's corners in the same boxes, and within HOLE_REACH of a step
of the prediction, which a fit an occluder's edge pulls off the corner leaves. On a board under a
shadow (ccdn.shade) a shadow's edge along the hole pulls that fit off too, or leaves no saddle:
there the fit on the levelled frame is tried, as the detector's edge stage does for such corners.
Measured (1300 renders): 359 -> 308 corners missed (the levelled fit: 323 -> 308), no false
positive more, no render worse; a frame with holes pays 2.1 ms (median over 223 such passes
of 480 renders; mean 3.2), one without 0.04 ms.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .edges import lattice_steps
from .grid import SHADE_SPREAD, Board, hole_cells, inside_margin
from .peaks import best_near, best_peak
from .refine import refine, window_for_spacing
from .shade import light_levels, light_spread, refined_across_shadows_edge
from .stats import median, vector_lengths

HOLE_REACH = 0.05  # of the local step: the fit this far from the prediction at most (0.1 took a corner an
# occluder's edge pulled 2.1 px off)
HOLE_SCORE = 0.5  # x the median full-resolution score of the board's corners around the holes
NEAR_CELLS = 2  # a hole's prediction: a homography fitted to the board's corners up to this many cells away


def predicted_holes(board: Board, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The holes (ccdn.grid.hole_cells) of a board in a frame of `shape` (H, W), predicted
    (predicted_cells)."""
    return predicted_cells(board.grid, board.xy, hole_cells(board), shape)


def predicted_cells(grid: np.ndarray, xy: np.ndarray, cells: np.ndarray, shape: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions of a board's (corners at (row, col) `grid` (M, 2), positions xy (M, 2)) empty
    `cells` (K, 2) in a frame of `shape` (H, W), each predicted by a homography fitted to the
    board's corners up to NEAR_CELLS cells away: the cells kept (F, 2), their predictions (F, 2) and
    lattice steps there (F, 4, 2: +col, -col, +row, -row, as ccdn.edges.lattice_steps). Cells with
    fewer than 4 such corners, a degenerate fit, or a prediction off the frame (less than
    EDGE_MARGIN inside: ccdn.grid.inside_margin; a board the frame cuts) are left out."""
    found_cells, preds, steps = [], [], []
    for cell in cells:
        near = (np.abs(grid - cell) <= NEAR_CELLS).all(1)
        if near.sum() < 4:
            continue
        homography, _ = cv2.findHomography(grid[near][:, ::-1].astype(np.float64), xy[near].astype(np.float64), 0)
        if homography is None or abs(np.linalg.det(homography)) < 1e-12:
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
    (scored around them) fills: each hole's best score within a quarter step of its prediction,
    scored >= HOLE_SCORE x the median of the board's corners the boxes cover; its saddle fit within
    HOLE_REACH of a step of the prediction and EDGE_MARGIN inside the frame (as every board corner:
    ccdn.grid.inside_margin), or, on a board lit unevenly (ccdn.shade.light_spread above
    ccdn.grid.SHADE_SPREAD), the fit on the levelled frame where that one fails (a shadow's edge
    across the corner pulls the saddle fit off it, or leaves no saddle: ccdn.shade); no closer than
    half a step to a corner already `taken` (M, 2). Returns their cells (F, 2), positions (F, 2)
    and scores (F,)."""
    none = np.zeros((0, 2), np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    own = board.xy[best_near(score, board.xy, 0) > 0]  # the board's corners the boxes cover
    if len(own) == 0:
        return none
    step = shorter_step(steps)
    peaks, values = [], []
    for pred, reach in zip(preds, step):
        peak, value = best_peak(score, pred, max(1, int(0.25 * reach)))
        peaks.append(peak)
        values.append(value)
    values = np.array(values)
    strong = values >= HOLE_SCORE * median(best_near(score, own))
    fitted, ok = refine(gray, np.array(peaks, np.float64), "saddle", float(0.25 * step.max()),
                        window_for_spacing(float(median(step))))
    ok &= near_prediction(fitted, preds, step, gray.shape)
    if (again := strong & ~ok).any() and light_spread(light_levels(gray, board.xy.astype(np.float64),
                                                                    lattice_steps(board))) > SHADE_SPREAD:
        levelled_fit, moved = refined_across_shadows_edge(gray, preds[again], steps[again])
        fitted[again] = levelled_fit
        ok[again] = moved & near_prediction(levelled_fit, preds[again], step[again], gray.shape)
    ok &= strong
    if len(taken):
        ok &= np.linalg.norm(fitted[:, None] - taken[None], axis=2).min(1) >= 0.5 * step
    return cells[ok], fitted[ok].astype(np.float32), values[ok].astype(np.float32)


def near_prediction(fitted: np.ndarray, preds: np.ndarray, step: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(K,) whether fits lie within HOLE_REACH x the shorter step of their predictions and
    EDGE_MARGIN inside a frame of `shape`."""
    return (vector_lengths(fitted - preds) <= HOLE_REACH * step) & inside_margin(fitted, shape)


def shorter_step(steps: np.ndarray) -> np.ndarray:
    """(K,) the shorter of the lattice steps (K, 4, 2) along the row and the column."""
    return np.minimum(vector_lengths(steps[:, 0]), vector_lengths(steps[:, 2]))


def with_corners(board: Board, cells: np.ndarray, xy: np.ndarray, first: int) -> Board:
    """The board with corners at cells (F, 2) and positions xy (F, 2) added, indexed from `first` on,
    its arrays in row-major order again and read-only."""
    index = np.concatenate([board.corner_index, np.arange(first, first + len(cells))])
    grid = np.concatenate([board.grid, cells.astype(np.int32)])
    points = np.concatenate([board.xy, xy.astype(np.float32)])
    order = np.lexsort((grid[:, 1], grid[:, 0]))
    arrays = index[order], grid[order], points[order]
    for a in arrays:
        a.setflags(write=False)
    return dataclasses.replace(board, corner_index=arrays[0], grid=arrays[1], xy=arrays[2])

