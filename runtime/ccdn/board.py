"""Board: one checkerboard's corners with their (row, col) indices, and how those are oriented.

Orientation (deterministic, in this order):
1. Never mirrored: +col x +row > 0 in image coordinates (x right, y down), like +x, +y.
2. Which grid axis is "col": the one fixed by `board_size` when it is given and not square;
   otherwise the axis whose image direction is nearer to horizontal.
3. Which of the two 180-degree-rotated labellings: the one whose quad at (0, 0) (between corners
   (0, 0) and (1, 1)) is light in the image, as cv2.findChessboardCornersSB orders corners (it is
   also right-handed), so that both give the same indices. This decides only when cols + rows is
   odd, e.g. 9 x 6: such a full board's (0, 0) is then the same physical corner in every view
   (unless the board is printed inverted). When cols + rows is even the pattern is symmetric and
   the labelling with +col pointing to image +x is taken, so the same physical corner is not
   guaranteed across views (harmless for calibration: the labellings differ by a rotation of the
   board).
A partial board's indices start at 0 at its first found row and column, not at the true board's.

Fitting a known board size (fitted_grid): a board whose extent is the size, either way round, is
indexed cols x rows. One that spans more lines than the size is cut to the size's window holding
most of its corners, where each line left out holds at most SIZE_STUB of the line inside it: where
clutter along a board's outline continues its pattern (a glyph's strokes against its outer dark
squares, a light shape under them), points beyond its last row or column pass every image test and
lie on its lattice, and the board came out one line too wide (stress renders: fisheye 7010141,
3 points beyond a 6 x 10 board, low-contrast 7060348 and 7060052, 2 and 1 beyond 7 x 9 and 3 x 14
ones), so that given its true size it was dropped whole. A full line beyond it is no stub: such a
board is not of that size. Two windows holding as many corners are ambiguous: no board.

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .lattice import held_on_two_sides
from .stats import vector_lengths

SIZE_STUB = 0.6  # a line beyond a known board size holding at most this share of the line inside it is left out
_ROTATIONS = (((1, 0), (0, 1)), ((0, -1), (1, 0)), ((-1, 0), (0, -1)), ((0, 1), (-1, 0)))  # the 4 proper
# rotations of grid indices, (new_row, new_col) = M (row, col)


@dataclass(frozen=True)
class Board:
    """One board: its corners' indices into the detection's xy, their (row, col) and positions.

    corner_index: (M,) int64; grid: (M, 2) int32 (row, col), row-major order; xy: (M, 2) float32.
    cols, rows: the grid's extent (max index + 1); a missing corner inside it is a hole.
    """

    corner_index: np.ndarray
    grid: np.ndarray
    xy: np.ndarray
    cols: int
    rows: int

    def __len__(self) -> int:
        return len(self.corner_index)

    def to_dict(self) -> dict:
        return {"cols": self.cols, "rows": self.rows, "corners": self.corner_index.tolist(),
                "grid": self.grid.tolist()}


def hole_cells(board: Board) -> np.ndarray:
    """(K, 2) (row, col) of the board's missing corners next to LOOSE_NEIGHBOURS or more of its own
    along their row and column: inside the board or in a notch of its outline, where something hid
    them (an occluder's or a shadow's edge, or a pass that saw them too coarsely); beyond a straight
    outline, where a board simply ends, a position has one."""
    filled = np.zeros((board.rows, board.cols), bool)
    filled[board.grid[:, 0], board.grid[:, 1]] = True
    return held_on_two_sides(filled)


def largest_first(boards) -> list[Board]:
    """Boards ordered largest first; ties: top, then left (their corners' mean position)."""
    return sorted(boards, key=lambda b: (-len(b), float(b.xy[:, 1].mean()), float(b.xy[:, 0].mean())))


def with_corners(board: Board, cells: np.ndarray, xy: np.ndarray, first: int) -> Board:
    """The board with corners at cells (F, 2) (inside its extent, or past it: then reoriented) and
    positions xy (F, 2) added, indexed from `first` on."""
    return indexed_board(np.concatenate([board.corner_index, np.arange(first, first + len(cells))]),
                          np.concatenate([board.grid, cells]), np.concatenate([board.xy, xy]))


def reoriented(board: Board, sign: float, board_size: tuple[int, int] | None = None,
               allow_partial: bool = False) -> Board | None:
    """The board indexed from 0 and oriented again (module docstring), for a
    grid that grew past its extent (indices below 0 or beyond cols / rows), or fitted to board_size
    (fitted_grid; with allow_partial, within it); sign: + where the quads of even row + col of its
    grid are light. None where it does not fit board_size."""
    fitted = fitted_grid(board.grid.astype(np.int64), board.xy, sign, board_size, allow_partial)
    if fitted is None:
        return None
    keep, grid = fitted
    return indexed_board(board.corner_index[keep], grid, board.xy[keep])


def indexed_board(idx: np.ndarray, grid: np.ndarray, points: np.ndarray) -> Board:
    """The read-only Board of corners idx (M,) at (row, col) grid (M, 2) from 0, positions points
    (M, 2), in row-major order."""
    order = np.lexsort((grid[:, 1], grid[:, 0]))
    idx, grid = idx[order], grid[order].astype(np.int32)
    board = Board(idx, grid, points[order].astype(np.float32), int(grid[:, 1].max() + 1), int(grid[:, 0].max() + 1))
    for a in (board.corner_index, board.grid, board.xy):
        a.setflags(write=False)
    return board


def checked_size(board_size) -> tuple[int, int] | None:
    """board_size as (cols, rows) ints (None stays None): a ValueError, not a failure deep inside,
    for anything but two whole numbers of inner corners of at least 2 each."""
    if board_size is None:
        return None
    try:
        cols, rows = (int(n) for n in board_size)
        whole = all(n == int(n) for n in board_size)
    except (TypeError, ValueError):
        raise ValueError(f"board_size must be (cols, rows) inner corners, e.g. (9, 6), got {board_size!r}") from None
    if not whole or cols < 2 or rows < 2:
        raise ValueError(f"board_size must be (cols, rows) whole numbers of inner corners >= 2, got {board_size!r}")
    return cols, rows


def fitted_grid(grid: np.ndarray, xy: np.ndarray, sign: float, board_size: tuple[int, int] | None,
                allow_partial: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """A grid (M, 2) with positions xy (M, 2) fitted to board_size (cols, rows; module docstring):
    (keep (M,) bool, the kept corners' (row, col) (K, 2), oriented: oriented_grid), or None where
    it makes no board of that size (with allow_partial: none within it). Without a size, all kept."""
    oriented = oriented_grid(grid, xy, sign, board_size, allow_partial)
    if oriented is not None:
        return np.ones(len(grid), bool), oriented
    keep = None if board_size is None else _size_window(grid, board_size, allow_partial)
    if keep is None:
        return None
    oriented = oriented_grid(grid[keep], xy[keep], sign, board_size, allow_partial)
    return None if oriented is None else (keep, oriented)


def _size_window(grid: np.ndarray, board_size: tuple[int, int], allow_partial: bool) -> np.ndarray | None:
    """(M,) the corners of a grid (M, 2) inside the one window of board_size's extent (either way
    round; with allow_partial, at most the grid's own along each axis) that holds the most of them,
    where every line of the grid outside it holds at most SIZE_STUB of the line next to it inside;
    None where no window does, or two hold as many corners."""
    rows, cols = (grid - grid.min(0)).T
    filled = np.zeros((rows.max() + 1, cols.max() + 1), bool)
    filled[rows, cols] = True
    line_counts = filled.sum(1), filled.sum(0)
    best: list[tuple[int, int, int, int]] = []
    most = 0
    for size in {tuple(board_size[::-1]), tuple(board_size)}:  # (rows, cols) either way round
        if allow_partial:
            size = tuple(min(n, extent) for n, extent in zip(size, filled.shape))
        if any(n > extent for n, extent in zip(size, filled.shape)) or size == filled.shape:
            continue
        starts = [[s for s in range(extent - n + 1) if _stubs_outside(counts, s, n)]
                  for counts, n, extent in zip(line_counts, size, filled.shape)]
        for r0 in starts[0]:
            for c0 in starts[1]:
                count = int(filled[r0 : r0 + size[0], c0 : c0 + size[1]].sum())
                if count > most:
                    best, most = [], count
                if count == most:
                    best.append((r0, c0, *size))
    if len(best) != 1:
        return None
    r0, c0, n_rows, n_cols = best[0]
    return (rows >= r0) & (rows < r0 + n_rows) & (cols >= c0) & (cols < c0 + n_cols)


def _stubs_outside(counts: np.ndarray, start: int, length: int) -> bool:
    """Whether each line before `start` and from start + length on (counts: corners per line) holds at
    most SIZE_STUB of the line next to it towards the window between."""
    before, after = counts[: start + 1], counts[start + length - 1 :]
    return bool((before[:-1] <= SIZE_STUB * before[1:]).all() and (after[1:] <= SIZE_STUB * after[:-1]).all())


def oriented_grid(grid: np.ndarray, xy: np.ndarray, sign: float, board_size: tuple[int, int] | None,
                  allow_partial: bool) -> np.ndarray | None:
    """(row, col) (M, 2) of a grid (M, 2) with positions xy (M, 2) in the documented orientation (module
    docstring; sign: + where the quads of even row + col are light), or None if the board does not fit
    board_size (cols, rows), or with allow_partial within it."""
    rows, cols = grid[:, 0] - grid[:, 0].min(), grid[:, 1] - grid[:, 1].min()
    canvas = np.full((rows.max() + 2, cols.max() + 2), -1, np.int64)
    canvas[rows, cols] = np.arange(len(grid))

    def mean_step(dr: int, dc: int) -> np.ndarray:
        """The mean unit step in the image from each corner to its (row + dr, col + dc) neighbour."""
        neighbour = canvas[rows + dr, cols + dc]
        has = neighbour >= 0
        steps = xy[neighbour[has]] - xy[has]
        return (steps / vector_lengths(steps)[:, None]).mean(0)

    col_dir, row_dir = mean_step(0, 1).tolist(), mean_step(1, 0).tolist()
    (r_min, c_min), (r_max, c_max) = grid.min(0).tolist(), grid.max(0).tolist()
    extremes = ((r_min, c_min), (r_max, c_max))
    ref_light = sign > 0  # the quad between internal corners (0, 0) and (1, 1) has even parity
    best, best_key = None, None
    for (a, b), (c, d) in _ROTATIONS:  # scalar arithmetic: a handful of numbers per rotation
        rs, cs = [a * r + b * q for r, q in extremes], [c * r + d * q for r, q in extremes]
        r0, c0 = min(rs), min(cs)
        n_rows, n_cols = max(rs) - r0 + 1, max(cs) - c0 + 1
        if board_size is not None:
            bc, br = board_size
            fits = (n_cols, n_rows) == (bc, br) or (allow_partial and n_cols <= bc and n_rows <= br)
            if not fits:
                continue
        # the quad (0, 0)-(1, 1) rotated: its new top-left corner's parity relative to the new origin
        origin_light = ((min(0, a, b, a + b) - r0 + min(0, c, d, c + d) - c0) % 2 == 0) == ref_light
        # the image directions of the new +col and +row: (r, c) = M^T (new_r, new_c)
        new_col = (c * row_dir[0] + d * col_dir[0], c * row_dir[1] + d * col_dir[1])
        new_row = (a * row_dir[0] + b * col_dir[0], a * row_dir[1] + b * col_dir[1])
        horizontal = abs(new_col[0]) / math.hypot(*new_col) >= abs(new_row[0]) / math.hypot(*new_row)
        axis_rank = 0 if (board_size is not None and board_size[0] != board_size[1]) or horizontal else 1
        key = (axis_rank, not origin_light, new_col[0] <= 0)
        if best_key is None or key < best_key:
            best_key = key
            best = np.stack([a * grid[:, 0] + b * grid[:, 1] - r0, c * grid[:, 0] + d * grid[:, 1] - c0], 1)
    return best
