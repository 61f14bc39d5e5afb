"""Lattice geometry that ccdn.grid's seed search (ccdn.seeds) and growth (ccdn.growth) share: steps
and their shapes, projections, distances, neighbour counts, the frame's margin, and the tolerances
they are judged by.

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import cv2
import numpy as np

from .checker import pair_differences
from .stats import nanmedian_rows, vector_lengths

TOLERANCE = 0.3  # how far a corner may lie from its prediction: of the shorter local lattice step (growth: or
# of ccdn.growth.SLIVER_REACH x the cell's lesser height, where less)
FLAT_RESIDUAL = 0.05  # of the lattice step: a board whose homography misses a corner by more is not flat
# (lens distortion): looks_flat
MIN_SINE = 0.3  # of the angle between the lattice steps: flatter cells are too sheared to sample
KINK_PX = 2.0  # a turn between steps (bends: ccdn.cleanup.MAX_TURN, ccdn.growth.GROWTH_TURN) counts where it also
# moves the shorter step's end this far (small squares' corner error turns steps)
SHADE_OFFSET = 8.0  # grey levels: PAIR_RATIO and the strict test's evenness and uniformity are judged on
# log(grey + this), where shading, which multiplies grey levels, cancels out; the offset is a black square's
# noise floor, below which the log would magnify noise (measured 3 / 8 / 20: the same within 5 corners of 3800)
SEED_REACH_UNIFORM = 0.25  # the seed's quads are sampled this far (x the quad's diagonals) from their centres:
# a basis (u, v + 2u) passes the colour test like (u, v), but its quads reach into other squares
SEED_AXES = 0.3  # ... and this far along each lattice step: a grid of thin lines passes the diagonal samples
EDGE_MARGIN = 1.5  # px: a corner closer to the frame's edge joins no board: the renders' labels leave such
# corners out too (ccdn_training.synth), their saddle window is mostly off the frame, and where the frame's edge
# cuts a board's outline, its one visible quad pair passes the image test like a corner's
LOOSE_NEIGHBOURS = 2  # completion's loose fits (ccdn.completion.LOOSE_EDGES), vouching and holes: at positions
# with this many filled row/column neighbours: beyond a board's straight
# outline a position has one, and there the plain test's three quads pass on a white margin (all positions:
# 3 corners more on those renders, +0.55 ms a 640x480 real-dev frame, 5 %)


def project_with_steps(homography: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image positions (K, 2) of grid points (col, row) (K, 2) under a homography, and the steps
    to their +col and +row neighbours (u, v)."""
    moved = cv2.perspectiveTransform(np.concatenate([grid, grid + [1, 0], grid + [0, 1]])[None], homography)[0]
    points, right, down = moved.reshape(3, -1, 2)
    return points, right - points, down - points


def looks_flat(homography: np.ndarray, grid: np.ndarray, points: np.ndarray) -> bool:
    """Whether a homography from grid points (col, row) (K, 2) to their image points (K, 2) misses
    none by more than FLAT_RESIDUAL of the shorter step there: the board looks flat, and the fit
    predicts positions beyond it (ccdn.growth, ccdn.bridging)."""
    fitted, u, v = project_with_steps(homography, grid)
    return not (vector_lengths(fitted - points) > FLAT_RESIDUAL * shorter_length(u, v)).any()


def each_where_the_others_put_it(grid: np.ndarray, points: np.ndarray) -> bool:
    """Whether each of the points (K, 2) at grid points (col, row) (K, 2) lies where a homography
    through the others puts it (looks_flat): a piece of a board too small for its lattice to outvote
    one wrong corner holds none (ccdn.grid, MIN_PIECE: a point where another board's outline crosses
    a hidden corner's squares lay 0.11 of a step off, the true corners of such pieces 0.002)."""
    for k in range(len(grid)):
        others = np.arange(len(grid)) != k
        homography, _ = cv2.findHomography(grid[others], points[others], 0)
        if homography is None or not looks_flat(homography, grid[k : k + 1], points[k : k + 1]):
            return False
    return True


def local_homography(grid: np.ndarray, xy: np.ndarray, cell: np.ndarray, reach: int, least: int
                     ) -> np.ndarray | None:
    """The homography from lattice (col, row) to image positions fitted to a board's corners (at
    (row, col) grid (M, 2), positions xy (M, 2)) up to `reach` rows and columns from `cell` (row, col):
    what the lattice around a position puts there (ccdn.holes, ccdn.outliers). None with fewer than
    `least` such corners or a degenerate fit."""
    near = (np.abs(grid - cell) <= reach).all(1)
    if near.sum() < least:
        return None
    homography, _ = cv2.findHomography(grid[near][:, ::-1].astype(np.float64), xy[near].astype(np.float64), 0)
    return None if homography is None or abs(np.linalg.det(homography)) < 1e-12 else homography


def first_of_each_cell(cells: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of each distinct grid cell in cells (K, 2) int (row, col), in
    (row, col) order: np.unique(axis=0, return_index=True) on one integer key per cell, without its
    slow row-wise path (any cells: negative ones, or off a canvas, too)."""
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    shifted = cells - cells.min(0)
    return np.unique(shifted[:, 0] * (shifted[:, 1].max() + 1) + shifted[:, 1], return_index=True)[1]


def distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K, M) distances between points a (K, 2) and b (M, 2): np.linalg.norm(a[:, None] - b[None], axis=2)
    to the last bit, an order of magnitude faster (its sum over an axis of length 2 is slow)."""
    dx = a[:, :1] - b[:, 0]
    dy = a[:, 1:] - b[:, 1]
    dx *= dx
    dy *= dy
    dx += dy
    return np.sqrt(dx, out=dx)


def quad_contrast(levels: np.ndarray, sign: np.ndarray, log: bool = False) -> np.ndarray:
    """(K,) the median difference of the quad pairs (pair_differences) of quad levels (4, K) in the
    board's sign (K,) at each corner, on the grey scale or (log) the log scale (SHADE_OFFSET); NaN
    where no pair is on the image."""
    if log:
        levels = np.log(levels + SHADE_OFFSET)
    return nanmedian_rows(pair_differences(levels) * sign[:, None])


def inside_margin(xy: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(N,) whether points xy (N, 2) lie at least EDGE_MARGIN px inside a frame of `shape` (H, W)."""
    h, w = shape[:2]
    return ((xy >= EDGE_MARGIN) & (xy <= np.array([w - 1, h - 1]) - EDGE_MARGIN)).all(1)


def shorter_length(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) the shorter of each pair of steps."""
    return np.minimum(np.hypot(u[:, 0], u[:, 1]), np.hypot(v[:, 0], v[:, 1]))


def square_enough(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(...) whether the cells spanned by steps u, v (..., 2) are no flatter than a seed square may
    be: the sine of the steps' angle above MIN_SINE (seeds and every growth step)."""
    return unsheared(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0], np.hypot(u[..., 0], u[..., 1]),
                      np.hypot(v[..., 0], v[..., 1]))


def unsheared(cross: np.ndarray, lu: np.ndarray, lv: np.ndarray) -> np.ndarray:
    """square_enough from the steps' cross product and lengths (np.hypot's), where these are at hand."""
    return np.abs(cross) > MIN_SINE * lu * lv


def bends(a: np.ndarray, b: np.ndarray, cos_limit: float) -> np.ndarray:
    """(...) whether steps a and b (..., 2) differ in direction by more than the angle of cos_limit
    and by more than KINK_PX where the shorter of them ends (2 sin(angle / 2) x its length): on
    squares a few pixels wide the corners' own error turns steps by up to 30 degrees. NaN steps (empty
    cells): False."""
    la, lb = np.hypot(a[..., 0], a[..., 1]), np.hypot(b[..., 0], b[..., 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (a * b).sum(-1) / (la * lb)
        return (cos < cos_limit) & (np.minimum(la, lb) ** 2 * (2 - 2 * cos) > KINK_PX**2)


def row_col_neighbours(filled: np.ndarray) -> np.ndarray:
    """How many of each cell's 4 row/column neighbours are filled."""
    count = np.zeros(filled.shape, np.int64)
    count[1:] += filled[:-1]
    count[:-1] += filled[1:]
    count[:, 1:] += filled[:, :-1]
    count[:, :-1] += filled[:, 1:]
    return count


def held_on_two_sides(filled: np.ndarray) -> np.ndarray:
    """(K, 2) (row, col) of the empty cells of a grid (filled: (R, C) bool) with LOOSE_NEIGHBOURS or
    more filled row/column neighbours: inside a board or in a notch of its outline."""
    return np.argwhere((row_col_neighbours(filled) >= LOOSE_NEIGHBOURS) & ~filled)
