"""A found board fitted to a known board size: what `Detector.detect(board_size=...)` and `ccdn
calibrate` keep of a detection.

The boards are found as without a size, by every pass and look (ccdn.detector), and only then
fitted to it (ccdn.board.reoriented, fitted_grid: as they are, either way round, or cut to it where clutter
along the outline left a stub line beyond it), and indexed cols x rows. Fitted inside the search,
a steep board's part that the magnified look would have grown whole was dropped for its size, and
the board with it (stress extreme-pose renders 7100120 and 7100236: 26 of 44 and 47 of 54 corners
at first); searched for again among the detected corners, as `ccdn calibrate` did, a board that
only the looks or completion had found was lost. On the five stress samples' 1300 renders of one
board (the 15 plain subsets with one), the boards lost given their true size outside the partial
subset (whose boards the frame cuts: `--partial`) went from 10 (detect) and 17 (calibrate) to 4
for both, each a board that an occluder or a shadow cuts short of its size, and none is wrongly
indexed (0 of 1218).
"""

from __future__ import annotations

import numpy as np

from .board import Board, reoriented
from .checker import Sampler, light_parity
from .edges import lattice_steps, median_step


def fitted_board(gray: np.ndarray, board: Board, board_size: tuple[int, int], allow_partial: bool = False
                 ) -> Board | None:
    """The board of a detection on gray fitted to board_size (cols, rows) and indexed cols x rows
    (with allow_partial: within it), or None where it makes no board of that size. Its colours, which
    orient it (ccdn.board), are read from gray (ccdn.checker.light_parity)."""
    steps = lattice_steps(board)
    xy = board.xy.astype(np.float64)
    sampler = Sampler(gray, (xy, median_step(steps)))
    return reoriented(board, light_parity(sampler, xy, board.grid, steps[:, 0], steps[:, 2]), board_size,
                      allow_partial)
