"""Boards fitted to a known board size (ccdn.board.fitted_grid, ccdn.sizing): detect(board_size=...) and
`ccdn calibrate` keep the boards the plain detection finds."""

import numpy as np
import pytest
from conftest import stress_scene

from ccdn.board import fitted_grid


def _lattice(rows: range, cols: range) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) (M, 2) of every cell of rows x cols and their positions, 20 px apart."""
    grid = np.array([(r, c) for r in rows for c in cols], np.int64)
    return grid, 20.0 * grid[:, ::-1] + 100.0


def _with(grid: np.ndarray, xy: np.ndarray, cells: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    more = np.array(cells, np.int64)
    return np.concatenate([grid, more]), np.concatenate([xy, 20.0 * more[:, ::-1] + 100.0])


def test_a_stub_line_beyond_the_size_is_cut_off_and_a_full_line_or_a_tie_is_no_board():
    grid, xy = _with(*_lattice(range(6), range(4)), [(6, 0), (6, 1)])  # 2 points beyond a 4 x 6 board's last row
    keep, oriented = fitted_grid(grid, xy, 1.0, (4, 6), False)
    assert keep[:24].all() and not keep[24:].any()
    assert (oriented.max(0) + 1).tolist() == [6, 4]
    assert fitted_grid(grid, xy, 1.0, (6, 4), False) is not None  # either way round
    full, full_xy = _lattice(range(7), range(4))  # a whole line more: a board of another size
    assert fitted_grid(full, full_xy, 1.0, (4, 6), False) is None
    tie, tie_xy = _with(*_lattice(range(5), range(4)), [(-1, 0), (-1, 1), (5, 0), (5, 1)])  # 2 beyond either end
    assert fitted_grid(tie, tie_xy, 1.0, (4, 6), False) is None
    keep, _ = fitted_grid(grid, xy, 1.0, (5, 6), True)  # partial: within 5 columns, the stub still cut
    assert keep[:24].all() and not keep[24:].any()


@pytest.mark.parametrize("subset, seed, size, found, corners", [
    ("low-contrast", 7_060_052, (3, 14), (15, 3), 42),  # a glyph along the outline: one point past the last column
    ("extreme-pose", 7_100_120, (4, 11), (11, 4), 44),  # 26 corners before the magnified look grows it whole
])
def test_a_board_given_its_size_is_the_board_found_without_it(detector, subset, seed, size, found, corners):
    """Fitted inside the search, before the looks, these two boards were dropped whole given their
    true size: one a line too wide (a stub of clutter along its outline), one a 4 x 7 part of a
    steep 4 x 11 board that only the magnified look completes. Found as without the size, then
    fitted, each is its true board, every corner within 0.5 px of its label, indexed right."""
    scene = stress_scene(subset, seed)
    from stress import match_radius, wrongly_indexed  # benchmarks/, on the path once stress_scene ran

    (plain,) = detector.detect(scene.image).boards
    assert (plain.cols, plain.rows) == found
    result = detector.detect(scene.image, board_size=size)
    (board,) = result.boards
    assert (board.cols, board.rows) == size and len(board) == len(result.xy) == corners
    labels = scene.corners.reshape(-1, 2)
    assert np.linalg.norm(board.xy[:, None] - labels[None], axis=2).min(1).max() < 0.5
    assert wrongly_indexed([(board.grid, board.xy)], scene, match_radius(scene)) == (1, 0)


@pytest.mark.parametrize("size", [(0, 0), (1, 5), (9.5, 6), "9x6", (9, 6, 1)])
def test_a_board_size_that_is_no_board_size_is_a_clear_error(detector, examples, size):
    with pytest.raises(ValueError, match="board_size must be"):
        detector.detect(examples["board"]["path"], board_size=size)
