"""ccdn.shaded's bookkeeping of the corners a board grows into shade."""

import numpy as np

from ccdn.shaded import _held


def test_lone_new_corners_are_dropped_round_after_round_even_two_cells_beyond_the_board():
    """A 3 x 3 board grown by a line of two new corners off its side: the outer one has one
    neighbour and goes first, then the inner one, left with one; the board's own corners stay.
    A new corner held by the board and by another new one stays (its two neighbours)."""
    board = [(r, c) for r in range(3) for c in range(3)]
    for tail, expected in (([(1, 3), (1, 4)], [False, False]), ([(1, -1), (1, -2)], [False, False]),
                           ([(1, -1), (1, -2), (0, -1)], [True, False, True])):
        grid = np.array(board + tail)
        kept = _held(grid, np.arange(len(grid)) >= len(board))
        assert kept[: len(board)].all() and kept[len(board):].tolist() == expected
