"""Bridging: a board's pieces on the far side of something in front of it (ccdn.growth's Grower, mixed in).

Growth walks from corner to corner and jumps one missing position at most; where another board or an
occluder hides a band of a board's rows or columns, the part beyond it is lost when it is too small
to be a board of its own (a strip one corner wide, a few corners). A board that looks flat
(ccdn.lattice.looks_flat: the homography through its 4 outermost corners misses none of the others
by more than FLAT_RESIDUAL of the step) predicts that part well: the free corners within
BRIDGE_REACH of the shorter step of a lattice position up to BRIDGE_SPAN x the board's longer side
beyond it (a strip reaches across as far as along) that pass the image test join it where they
form a piece of at least BRIDGE_PIECE of those positions along its rows and columns (a lone corner
or a pair on a lattice position is as likely clutter), none of them beside the board, diagonally
neither: there growth would have taken them, and what it left there is its outline, which its
cleanup dropped (ccdn.cleanup; bridged, a low-contrast render's board took 3 such points).
ccdn.grid bridges once its search is done, among the corners no board holds (stress renders: 23
corners more in 4 of 1360, beyond a front board or an occluder; nothing else changed on ~1800)."""

from __future__ import annotations

import cv2
import numpy as np

from .lattice import first_of_each_cell, looks_flat, project_with_steps, shorter_length
from .stats import vector_lengths

BRIDGE_REACH = 0.15  # x the shorter projected step: how far a corner beyond a gap may lie from its lattice position
BRIDGE_SPAN = 2  # x the board's longer side: how far beyond it a piece may lie
BRIDGE_PIECE = 3  # lattice positions a piece beyond a gap holds, 4-connected, at least
_DIAGONALS = np.array([[1.0, 1.0], [1.0, -1.0]])  # (col, row) -> (col + row, col - row): the outermost corners


class Bridging:
    """Grower's step across a gap: a mixin that uses its canvas (idx, origin, _filled), free corners and
    image test (_accepts, _crowded)."""

    def bridge(self) -> bool:
        """Join the pieces of this board that lie beyond a gap (module docstring); whether any joined."""
        free = np.nonzero(self.free)[0]
        if len(free) < BRIDGE_PIECE:
            return False
        _, grid, points = self._filled()  # (col, row), like (x, y)
        # the homography through the board's 4 outermost corners (a least-squares fit cost 0.3 ms a frame),
        # checked for flatness only where a piece is found
        diagonals = grid @ _DIAGONALS  # (K, 2): col + row, col - row
        ends = np.concatenate([diagonals.argmin(0), diagonals.argmax(0)])
        corners, at = grid[ends].astype(np.float32), points[ends].astype(np.float32)
        homography = cv2.getPerspectiveTransform(corners, at)
        # collinear ends give a degenerate fit, which puts no corner near its lattice or fails looks_flat below
        lattice = cv2.perspectiveTransform(self.xy[free][None], cv2.getPerspectiveTransform(at, corners))[0]
        cells = np.rint(lattice)  # (col, row) in board coordinates
        lo, hi = grid.min(0), grid.max(0)
        reach = BRIDGE_SPAN * ((hi - lo).max() + 1)  # a strip of a board reaches as far across as along
        near = ((cells >= lo - reach) & (cells <= hi + reach)).all(1)  # NaN fails
        free, cells = free[near], cells[near]
        if len(free) < BRIDGE_PIECE:
            return False
        preds, u, v = project_with_steps(homography, cells)
        dist = vector_lengths(preds - self.xy[free])
        on = dist < BRIDGE_REACH * shorter_length(u, v)
        free, cells, dist, u, v = free[on], cells[on].astype(np.int64), dist[on], u[on], v[on]
        if len(free) < BRIDGE_PIECE:
            return False
        rc = cells[:, ::-1] + self.origin  # canvas (row, col), possibly off the canvas
        inside = ((rc >= 0) & (rc < self.idx.shape)).all(1)
        touching = cv2.dilate((self.idx >= 0).astype(np.uint8), np.ones((3, 3), np.uint8))
        apart = np.ones(len(rc), bool)  # beyond a gap: no cell of the board beside it, diagonals too
        apart[inside] = touching[rc[inside, 0], rc[inside, 1]] == 0
        keep = np.nonzero(apart)[0]
        keep = keep[np.argsort(dist[keep], kind="stable")]
        keep = keep[first_of_each_cell(rc[keep])]  # one corner a cell
        if len(_in_pieces(cells[keep], BRIDGE_PIECE, keep)) == 0 or not looks_flat(homography, grid, points):
            return False
        keep = keep[self._accepts(rc[keep], self.xy[free[keep]], u[keep], v[keep],
                                  crowded=self._crowded(free[keep], u[keep], v[keep]))]
        keep = _in_pieces(cells[keep], BRIDGE_PIECE, keep)
        if len(keep) == 0:
            return False
        self._ensure_margin(rc[keep])
        self._place(cells[keep, ::-1], free[keep])
        return True


def _in_pieces(cells: np.ndarray, least: int, index: np.ndarray) -> np.ndarray:
    """The entries of `index` whose cells (K, 2) lie in 4-connected pieces of at least `least` cells."""
    if len(cells) < least:
        return index[:0]
    low = cells.min(0)
    shifted = cells - low + 1
    mask = np.zeros(tuple(shifted.max(0) + 2), np.uint8)
    mask[shifted[:, 0], shifted[:, 1]] = 1
    count, labels = cv2.connectedComponents(mask, connectivity=4)
    label = labels[shifted[:, 0], shifted[:, 1]]
    sizes = np.bincount(label, minlength=count)
    return index[sizes[label] >= least]
