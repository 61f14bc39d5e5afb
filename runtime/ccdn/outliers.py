"""Lattice outliers: a flat board's corners that lie off its lattice, fitted again or dropped.

On a flat board (a homography fits its corners within FLAT of a step, median), each
corner's offset from that homography follows its neighbours' where only the lens bends the lines.
A corner whose offset differs from the median of its 8 neighbours' by more than OFF_LATTICE px (or
SPREAD x the board's median such difference, where more), and which a homography through the
corners within LOCAL_REACH rows and columns of it puts as far off, lies where no lattice puts it:
a soft shadow's slope, an occluder's edge or the other board's edges pulled its fit (stress
renders: saddle fits 1-3.3 px off, scored like any other corner; the edge stage moves a corner at
most 1 px). Such a corner is fitted again from that local prediction, with the steps to its
neighbours measured from there (its own are as far off as it is): on the frame levelled around
it (ccdn.shade.refined_across_shadows_edge: the saddle fit, then edge lines; then edge lines
alone), then with the plain saddle fit; the first fit landing within REFIT_AGREES px of the
prediction is taken. Else it keeps its place where the plain fit returns to it within CONFIRMED px
(the image puts it there: a good corner whose neighbours mislead the prediction); else it is
dropped: for a calibration a corner 1-3 px off costs more than one missing.

Measured on the stress benchmark's four samples (exact labels): corners found over 1 px off their
labels 38 -> 5 of ~84 000, over 0.5 px 80 -> 33, 2 corners more missed (CHANGES.md, session 56). The
local predictions (a Python loop) are made for the few candidates only: none on most frames.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .board import Board
from .edges import lattice_steps, median_step
from .lattice import local_homography
from .refine import refine_saddle_points, window_for_spacing
from .shade import refined_across_shadows_edge
from .stats import median, nanmedian_rows, vector_lengths

FLAT = 0.02  # of the median lattice step: a board whose homography residual's median is under this is flat here
# (ccdn.edges.FLAT_BOARD, 0.01, leaves out a noisy frame's boards, 0.014, and steep ones, 0.018: 14 corners 0.5-5 px
# off more fitted again in ~2070 cached renders, none dropped; no flatness test at all dropped 11 good corners)
OFF_LATTICE = 0.6  # px: a corner's offset from the board's homography this far from its neighbours' median ...
SPREAD = 5.0  # ... or this many times the board's median such distance, where more (a real photo's corners scatter
# more: JPEG, print, lens; real-dev at 640x480 up to 0.87 px on a board whose median is 0.18)
REFIT_AGREES = 0.35  # px: a fit from the prediction is taken this close to the prediction
CONFIRMED = 0.1  # px: a saddle fit from the prediction that returns this close to the corner keeps it
REFIT_REACH = 1.5  # px: how far that saddle fit may move from the prediction
LOCAL_REACH = 2  # rows and columns: the corners around one whose local homography predicts it
_NEIGHBOURS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]).T  # (2, 8) rows, columns
_NEIGHBOURS.setflags(write=False)


def off_lattice(gray: np.ndarray, board: Board, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A board's corner positions (M, 2) float32 with its lattice outliers (module docstring) fitted
    again, and which corners to keep (M,) bool (not the outliers that no fit lands near and the
    plain fit does not return to, but a corner alone in its row or column of the board, so that
    dropping never shrinks the board's extent). Boards that are not flat, or under 9 corners, come
    back as they are (the same array). steps: the board's lattice steps (M, 4, 2) (ccdn.edges.lattice_steps;
    the edge stage's, measured before it moved the corners: they set the flatness test's and the fit's
    scale only)."""
    xy = board.xy.astype(np.float64)
    keep = np.ones(len(board), bool)
    if len(board) < 9:
        return board.xy, keep
    grid = board.grid.astype(np.int64)
    homography, _ = cv2.findHomography(grid[:, ::-1].astype(np.float64), xy, 0)
    if homography is None:
        return board.xy, keep
    on_lattice = cv2.perspectiveTransform(grid[None, :, ::-1].astype(np.float64), homography)[0]
    offset = xy - on_lattice
    step = median_step(steps)
    if not median(vector_lengths(offset)) < FLAT * step:
        return board.xy, keep
    canvas = np.full((*(grid.max(0) + 3), 2), np.nan)  # the offsets on the grid, a NaN margin around
    canvas[grid[:, 0] + 1, grid[:, 1] + 1] = offset
    around = canvas[grid[:, :1] + 1 + _NEIGHBOURS[0], grid[:, 1:] + 1 + _NEIGHBOURS[1]]  # (M, 8, 2)
    neighbours = np.nan_to_num(nanmedian_rows(around))  # x and y each; 0 for a corner without neighbours
    apart = vector_lengths(offset - neighbours)
    reach = max(OFF_LATTICE, SPREAD * median(apart))
    outliers = np.nonzero(apart > reach)[0]
    if len(outliers) == 0:
        return board.xy, keep
    predicted = _locally_predicted(grid, xy, outliers)  # from the corners around, the other candidates left out
    off = vector_lengths(predicted - xy[outliers]) > reach
    outliers, predicted = outliers[off], predicted[off]
    if len(outliers) == 0:
        return board.xy, keep
    on_prediction = board.xy.copy()  # the steps from the predictions: an outlier's own steps are as far off as it
    on_prediction[outliers] = predicted
    around = lattice_steps(dataclasses.replace(board, xy=on_prediction))[outliers]
    radius = window_for_spacing(step)
    fits = (refined_across_shadows_edge(gray, predicted, around),  # the saddle fit, then edge lines; ...
            refined_across_shadows_edge(gray, predicted, around, saddle=False),  # ... edge lines alone; ...
            refine_saddle_points(gray, predicted, radius, 0.4 * radius, max_shift=REFIT_REACH))  # ... plainly
    out, taken = board.xy.copy(), np.zeros(len(outliers), bool)
    for fitted, converged in fits:  # the first fit that lands near the prediction
        agrees = ~taken & converged & (vector_lengths(fitted - predicted) <= REFIT_AGREES)
        out[outliers[agrees]] = fitted[agrees]
        taken |= agrees
    again, converged = fits[-1]
    confirmed = converged & (vector_lengths(again - xy[outliers]) <= CONFIRMED)
    keep[outliers] = taken | confirmed | _alone_in_line(grid, outliers)
    return out, keep


def _alone_in_line(grid: np.ndarray, which: np.ndarray) -> np.ndarray:
    """(K,) whether the corners `which` (indices) are the only ones of their row or of their column
    in a board's grid (M, 2)."""
    rows = np.bincount(grid[:, 0])[grid[which, 0]]
    cols = np.bincount(grid[:, 1])[grid[which, 1]]
    return (rows == 1) | (cols == 1)


def _locally_predicted(grid: np.ndarray, xy: np.ndarray, which: np.ndarray) -> np.ndarray:
    """(K, 2): where a homography fitted to the corners within LOCAL_REACH rows and columns of each
    corner `which` (indices), those corners left out, puts it (its own position where fewer than 6
    are there, or the fit is degenerate): two outliers side by side pulled each other's prediction 0.7-1 px off."""
    out = xy[which].copy()
    others = np.ones(len(grid), bool)
    others[which] = False
    around, around_xy = grid[others], xy[others]
    for k, i in enumerate(which):
        if (homography := local_homography(around, around_xy, grid[i], LOCAL_REACH, 6)) is not None:
            out[k] = cv2.perspectiveTransform(grid[None, i : i + 1, ::-1].astype(np.float64), homography)[0, 0]
    return out
