"""Grid recovery: unordered corners -> boards with (row, col) indices, without knowing the board size.

How: seeds are tried in order of score, first the corners whose surroundings look like a checker
corner (on a small ring around it the grey level alternates twice: the ring's second angular
harmonic beats its first, as it does not at an edge or a T-junction), then at most 200 others (a
cheap filter that keeps clutter from costing a seed attempt per point). A seed is a corner p with
two neighbours p + u, p + v whose sum p + u + v is also a corner (one square of the lattice) and
whose four corners pass the image test below, with uniform grey inside each sampled quad, sampled
out to a quarter of its diagonals (a wrong lattice samples edges; a sheared one such as (u, v + 2u),
whose quad centres are square centres too, reaches into other squares); of the passing bases the
shortest is taken. With uneven_seeds=1 (the detector's full-frame pass) a second round over the
seeds left after that one lets one of a square's four corners have non-uniform quads (an occluder's
edge or a mark printed in a square crossing them; held-out stress renders: a small occluded board
found, 13 corners; tried before the strict round, or on shrunk frames, it changed which boards those
find). Once a board is found, a last round over the seeds left lets two of a square's corners have
non-uniform quads (BEHIND_UNEVEN): where one board lies in front of another, its outline crosses the
quads of two corners of every square of the one behind along it, and what is left visible of that
one may be an L or a strip (stress two-boards renders, README sample: 28 -> 16 corners missed; the
other subsets and real-dev unchanged; on every pass, without a board found first it changed which
boards the shrunk passes find: extreme pose 18 -> 64 missed). The board then grows, first
ring-at-once while it looks flat: a homography fitted to the grid so far predicts every cell up to
the grid's own extent beyond it, and the free corners within 0.3 of the shorter lattice step of a
prediction that pass the image test join where they connect to the grid along rows and columns (a 9
x 9 board fills in ~3 such rounds; a fit off by more than 5 % of a step anywhere, as under lens
distortion, stops this). Then position by position: each empty neighbour of the grid is predicted
from the grid (along a row or column from the previous two or three corners, e.g. 2 p1 - p2, also
across a hole, and from parallelograms with diagonal neighbours; the median of the predictions), and
the nearest free corner within 0.3 of the shorter local lattice step (or of 1.5 x the cell's lesser
height, where that is less: SLIVER_REACH) is taken if it passes the image test. No corner is taken
where the local steps are flatter than a seed's may be (the sine of their angle at most MIN_SINE, in
every growth step): on the slivers of boards tilted 60-75 degrees the tips where two squares of one
colour nearly touch score like corners, and a lattice of such tips passed the image test (a stress
render: 16 of a board's 25 corners 2-4 px off). Nor do these rounds or completion take one that
turns a row or column sharply at it or its neighbours (GROWTH_TURN); once grown, corners are dropped
until no line turns by more than MAX_TURN (_Grower.unkink): perspective keeps lines straight, lens
distortion bends them gently, and tips so scored let growth wander off the true lattice one
tolerated step at a time. When nothing more can be added, growth may jump over one missing position
along a row or column (a hole, not the end of the board). Corners left with fewer than two
row/column neighbours are then dropped (lone points on the outline), except, completing, one whose
other neighbours something in front of the board hides: its row and its column each hold a corner of
two neighbours or more, and its four half-edges are even (_Grower._hidden_around; the four stress
samples' 1440 renders: 323 -> 281 corners missed, occluded 110 -> 76, two-boards 101 -> 95, 20 false
positives either way; 280 fresh renders of 7 subsets: occluded 59 -> 29, two-boards 42 -> 39, the
others unchanged); a corner so kept counts as such a corner in prune's later rounds (before, where
its neighbour lost its other neighbour, the next round dropped both, each one's line holding only
the other: the 300 occluded, two-boards and shadow renders of four stress samples, 6 corners more in
3, nothing else changed). Completing, the network then vouches for corners at the positions the pruned
board holds on two sides or more (_Grower.vouch): a free corner within VOUCH_REACH (0.05) of the
shorter step of the grid's prediction, scored at least VOUCH_SCORE (0.5) x the board's median, joins
without the image test. Where an occluder or the other board covers part of a corner's quads every
image test fails, while the network, trained on renders with occluders, still finds it (1300 cached
renders: three samples of 340 and 280 fresh occluded, two-boards, shadow and partial ones: 25
corners more, no false positive more, each 0.01-0.34 px off the truth but one, 1.4 px, in a
penumbra. Within 0.15 of a step: 5 more on the 1140 looked at first, but 8 of those it took lay
1-3.7 px off, pulled by an occluder's edge 1-3 px away; before prune, an outline point growth took
lent a position its second side: 7 false positives).
An outermost row or column that is a stub of the line inside it (at most 0.3 of its length) is
dropped too, unless the frame cuts it (clutter continuing the pattern beyond an edge). An inner row
or column that holds at most BRIDGE of the corners of each line beside it, where those three lines
are no one lattice, joins two boards: where one board lies in front of another, points on its
outline alternate like corners where the one behind shows through, and growth walked over them onto
the other's lattice (a wrongly indexed board); the grid is cut there and the larger side kept
(_Grower.split_at_bridge). A grid of at least 2 x 3 positions and 8 corners is a
board (two rows or columns: the strip of a board that another hides; 3 x 3 before, which lost two
such strips of 9 and 18 corners in the four stress samples' 1440 renders and changed nothing else
there, on real-dev or its perturbed photos); its corners are removed and the search repeats for
further boards. Corners in no board are dropped, and no corner closer than EDGE_MARGIN to the
frame's edge joins one (where the frame cuts a board's outline, its one visible quad pair alternates
like a corner's). Local predictions make this tolerant of perspective and strong radial/fisheye
distortion.

Completion (complete=True): where no given corner lies near a predicted position, the image itself
is asked: where the image test, made as strict as the seed's (its evenness and uniformity on the log
scale below), passes at the prediction, a saddle point is fitted there (ccdn.refine, within the same
tolerance) and taken if it passes the ring test and the strict image test, with at least two of its
quad pairs on the image (one pair alone, at the frame's edge, is what a board's outline shows too).
Where the strict test fails but growth's plain one passes (one quad may be hidden: an occluder or
the other board covers part of the corner's surroundings) at a position the board holds on two sides
or more (LOOSE_NEIGHBOURS), the fit is taken if the plain test passes at it and its four half-edges
each show LOOSE_EDGES of the strongest one's contrast on the log scale (on a board's outline one
runs into the margin): with the prune change above, four stress samples' 1140 renders: 311 -> 292
corners missed, 17 -> 15 false positives, the gains all in the occluded, two-boards and shadow
subsets. This recovers the corners the network scored too low (shadowed, blurred, or first found on
a downscaled frame); such corners get indices >= len(xy), in order of addition. A slope in the grey
levels shifts a saddle fit's point by slope / contrast, so under a soft shadow, whose light falls
off across a corner faster than the shaded squares differ, the fit found no saddle: where it fails
at a prediction whose quads look like the board's in shade (lower contrast than the seed's, yet a
larger share of the board's on the log scale than on the grey scale: shade multiplies grey levels, a
board's outline against a mid-grey background loses both alike), it is fitted again on the log scale
of grey, where the shade's factor is an offset and the squares keep the lit ones' contrast (stress
shadow renders: 150 -> 109 of 3819 corners missed over 60 renders, those found 0.13 px off the truth
(median); 1440 renders of the other subsets: 3 occluded corners more, no false positive more;
without the log-scale share, a board's outline took a false corner). Where neither scale's fit finds
a saddle (a shadow's blurred edge through the corner curves the grey levels more than a quadric
holds), the corner is the crossing of its lattice lines fitted to its squares' edges on the log
scale (ccdn.edges), taken where each of its four half-edges shows at least EVEN_EDGES of the
strongest one's contrast (on a board's outline one runs into the margin: without this test a radial
and a two-boards render took 2 false corners each): shadow renders 109 -> 92 missed, 1440 others
unchanged; the ring test (x_like) does not judge such a crossing: the shadow's edge across the
corner puts the ring's first harmonic above its second, on the log scale too (stress shadow renders,
README sample: 21 -> 7 corners missed; held-out 8 either way; no false positive more). A prediction
that fails the strict test itself, in a gap of the board (filled neighbours on both sides along its
row or column) where its quads look like the board's in shade (a shadow's edge across the corner
leaves a quad half lit, or a lit dark square lighter than a shaded light one), goes to the edge-line
fit directly and is judged by its half-edges instead (shadow renders 92 -> 81 missed, occluded
renders 2 fewer, no false positive more; also with two neighbours at a right angle: 12 fewer still,
but a board's outline next to clutter took 2 false corners). When that adds nothing, completion also
asks the image two positions beyond the frontier along rows and columns, where the four quads
alternate in the board's sign at their centres (one box each, a cheap look before the strict test):
a shadow's sharp edge along a line of corners darkens two quads of each, so that line fails the
test, and the board past it was lost (stress shadow renders: 15 of 165 missed corners over 60
renders found; 1440 renders of the other subsets unchanged); the line left between stays holes
unless completion then fills it.

Shade (complete=True): a board whose lightest quads differ across it by more than SHADE_SPREAD
(ccdn.shade.light_spread: a shadow over part of it) is searched for again, from the same corners,
on the frame divided by its light level (ccdn.shade.levelled). There the corners along a soft
shadow's edge, whose light falls off across them as steeply as their squares differ (no scale of
grey evens that out), pass the image tests; the second search's boards are kept where they hold
more corners (stress shadow renders: 190 -> 96 of 6427 corners missed over 100 renders, all found
0.060 -> 0.065 px off the truth (mean), the 99 new ones 0.41 px, until ccdn.detector fitted the
corners across a shadow's edge again on the levelled frame: 0.044 px; 1440 renders of the other
subsets and real-dev unchanged). With shade_unfound (the detector's full-frame pass), where no board
is found and at least MIN_CORNERS corner-like points (ccdn.checker.x_like) are lit more unevenly
than SHADE_SPREAD (ccdn.shade.points_light_spread), the search runs on the levelled frame too, their
median gap taken for the square: a shadow's edge across a small board crosses a quad of every seed
square's corners (1300 cached stress renders: 3 such boards of 12-20 corners, 48 corners more, no
false positive more; asked on every pass where no board was found before, it cost a boardless
frame a quarter more time; now 4-14 %, and nothing where a board is found).

Image test: at a checker corner the four squares around it alternate dark/light. The mean grey
level is sampled at the four quad centres p +- u/2 +- v/2 (u, v: the local lattice steps; halfway
to a centre that is off the image) and all four edge-adjacent quad pairs must differ with the
board's sign (fixed at its seed: quads with even row + col are all dark or all light), their median
by at least 0.05 of the seed's contrast (a board's part in deep shade keeps a fifth to a twentieth
of it) and the weakest by 0.15 of the strongest, on a log scale of grey (SHADE_OFFSET): a shadow
multiplies grey levels, and where its edge crosses a corner two quads darken, which evened out the
weakest pair on the grey scale but not that ratio. This rejects false corners and points on the
board's outline (where two outside quads are alike; alike on either scale). The quads
must also be uniform where a seed's are sampled (SEED_REACH_UNIFORM, SEED_AXES; their samples may
vary by at most WIDE_SPREAD x the contrast) at a corner with another detected one closer than
CROWDED x the shorter step, i.e. inside its cells: there a sublattice of another board passed, its
quad centres on square centres (steps (2, 1) and (-1, 2) of its squares; in a stress render a board
of 45 px squares grew onto 16 corners of its 21 px-square neighbour), and so did tips near a steep
board's corners. An occluder
(or another board) over one quad's centre fails that test at a corner the image still shows: a
corner the network proposed that fails it gets a second chance where the three other quads' pairs
pass and the four quads alternate close to the corner, sampled 0.36 of the way to their centres,
with the strict test's even contrast and uniform quads (on the stress benchmark's renders and as
many held-out ones, 640 in all: 22 of 531 misses fewer, all occluded or behind another board, no
false positive more; also giving it to completion's corners found 5 more and added 2 false
positives, on a board's outline next to another board). A crowded corner whose wide-sampled quads
are not uniform gets none either: a denser lattice's corner, of a smaller board lying on this one,
passes it around itself (fresh stress renders: a board took 4 such corners next to its own hidden
ones, 1 now; audits of 154 two-boards boards, the third sample and fresh ones: 3 wrongly indexed,
1 now, for 3 corners fewer of 86115 on 1300 cached renders; before, only points within 0.5 of a
step got none, a rule this one makes redundant).

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

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from .checker import (MIN_CONTRAST, QUAD_PAIRS, Sampler, altitude, pair_differences, quad_differences, quad_levels,
                      quad_means, quad_spread, x_like)
from .edges import half_edge_contrast, lattice_steps, median_step, refine_on_edges
from .refine import refine_saddle_points, window_for_spacing
from .shade import levelled, light_levels, light_spread, points_light_spread
from .stats import median, nanmedian_rows, vector_lengths

MIN_CORNERS = 8
MIN_EXTENT = 2  # rows and columns a board spans, at least: a strip of a board behind another (module docstring)
SEED_NEIGHBOURS = 12  # a seed's square is sought among these nearest corners ...
SEED_REACH = 24  # ... and its fourth corner among these
SEED_CHUNK = 256  # seeds checked at once
FEW_SQUARES = 3  # seed squares up to this many (one seed's first round) are sampled at all 4 corners in one call:
# a call costs as much as 20-50 corners, while the seed corner alone fails ~4 in 5 of many seeds' squares (clutter)
MAX_PLAIN_SEEDS = 200  # seeds tried among the corners that fail the ring test
TOLERANCE = 0.3  # of the shorter local lattice step ...
SLIVER_REACH = 1.5  # ... or of this x the cell's lesser height (altitude), where less: on a sheared sliver
# (steps 12-16 px, 4-5 px across) a tip where two squares of one colour nearly touch lies within 0.3 of the
# step of a true corner, and position-by-position growth took tips the network scored as corners, one
# after another (extreme-pose stress render 7100011 once its narrow squares completed: a wrongly indexed board
# and 38 false corners; 1.0 lost corners elsewhere, 2.0 still took the tips)
NARROW_ALTITUDE = 2.0  # squares narrower than this many fit windows get the narrow window's second fit (refine):
# 1.5 left completion unable to fit the 4.5-6 px wide squares of steep views (stress extreme-pose renders: 820 ->
# 681 missed of 5449 corners over 80 renders, together with SLIVER_REACH; 2.5 the same as 2.0)
MIN_SINE = 0.3  # of the angle between the lattice steps: flatter cells are too sheared to sample
MAX_TURN = 15.0  # degrees between consecutive steps along a row or column: a sharper turn is a wrong corner ...
KINK_PX = 2.0  # ... where it also moves the shorter step's end this far (small squares' corner error turns steps)
GROWTH_TURN = 20.0  # growth's own limit, looser: a wrong corner taken first must not keep out the true one
BEHIND_UNEVEN = 2  # corners of a seed square with non-uniform quads in the last round (module docstring)
MIN_SQUARE_PX = 3.5  # the seed square's smaller height: below it quad centres cannot be sampled
RELATIVE_CONTRAST = 0.05  # of the seed's median contrast: a board's part in deep shade keeps a fifth to a
# twentieth of its lit part's (stress shadow renders, 0.2 before: 12.2 -> 10.5 % missed; every other render the same)
SEED_REACH_UNIFORM = 0.25  # the seed's quads are sampled this far (x the quad's diagonals) from their centres:
# a basis (u, v + 2u) passes the colour test like (u, v), but its quads reach into other squares
SEED_AXES = 0.3  # ... and this far along each lattice step: a grid of thin lines passes the diagonal samples
FLAT_RESIDUAL = 0.05  # of the lattice step: a worse homography fit stops the ring-at-once growth
PAIR_RATIO = 0.15  # weakest over strongest quad pair at a corner, on the log scale (a board outline has a ~0 pair)
SHADE_OFFSET = 8.0  # grey levels: PAIR_RATIO and the strict test's evenness and uniformity are judged on
# log(grey + this), where shading, which multiplies grey levels, cancels out; the offset is a black square's
# noise floor, below which the log would magnify noise (measured 3 / 8 / 20: the same within 5 corners of 3800)
WIDE_SPREAD = 1.5  # growth's image test: quads sampled as widely as a seed's vary by at most this x their contrast ...
CROWDED = 0.75  # ... at a corner with another this close (x the shorter lattice step): other corners in its cells
OUTLINE_STUB = 0.3  # an outermost line this short against the line inside it is an outline artefact
BRIDGE = 0.4  # an inner line this short against both lines beside it joins two boards (_Grower.split_at_bridge) ...
MIN_BRIDGED = 4  # ... where each of those holds this many corners ...
SEAM_RESIDUAL = 0.1  # ... and a homography fitted to the three lines misses one by this x the shorter step
COMPLETION_MIN_PAIRS = 2  # quad pairs on the image a completed corner needs: one pair alone, at the frame's edge,
# is an edge (a board's outline there took indices: held-out stress renders 3 false positives fewer, 2 corners
# 1.5-2 px from the frame's edge fewer; the benchmark's renders 2 such corners fewer)
EDGE_MARGIN = 1.5  # px: a corner closer to the frame's edge joins no board: the renders' labels leave such
# corners out too (ccdn_training.synth), their saddle window is mostly off the frame, and where the frame's edge
# cuts a board's outline, its one visible quad pair passes the image test like a corner's
NEAR_QUADS = 0.36  # share of the way to the quad centres where the image test's second chance samples
HIDDEN_EDGES = 0.6  # prune keeps a corner whose neighbours are hidden if its half-edges are this even (_hidden_around)
LOOSE_EDGES = 0.6  # completion's fits where only growth's plain test passes: half-edges this even (0.75 found
# 10 instead of 16 corners on the 300 occluded, two-boards and shadow renders of four stress samples, the same
# false positives) ...
LOOSE_NEIGHBOURS = 2  # ... at positions with this many filled row/column neighbours: beyond a board's straight
# outline a position has one, and there the plain test's three quads pass on a white margin (all positions:
# 3 corners more on those renders, +0.55 ms a 640x480 real-dev frame, 5 %)
VOUCH_REACH = 0.05  # a free corner this close (x the shorter local step) to the prediction at a position held on
# LOOSE_NEIGHBOURS sides or more joins the pruned board without the image test where its network score is ...
VOUCH_SCORE = 0.5  # ... at least this x the board's median (_Grower.vouch)
EVEN_EDGES = 0.5  # completion's edge-line fit in shade: each half-edge's log-scale contrast >= this x the strongest's
SHADED_CONTRAST = 0.85  # completion's strict test also passes on the quads sampled NEAR_QUADS of the way where
# their grey-level contrast is below this x the seed's (or above 1 / this): a corner in other light than the seed's
_LOG_GREY = (255 * np.log1p(np.arange(256) / SHADE_OFFSET) / np.log1p(255 / SHADE_OFFSET)).astype(np.float32)
_LOG_GREY.setflags(write=False)  # grey level -> log(grey + SHADE_OFFSET), stretched back onto 0..255 so that
# the saddle fit's min_saddle (grey levels / px^2) keeps its meaning: completion's fit in shade (module docstring)
_PAIRS_WITHOUT = np.array([np.nonzero((QUAD_PAIRS != quad).all(1))[0] for quad in range(4)])  # (4 quads, 2):
# the pairs (quad_differences' columns) that leave each quad out
_DIRECTIONS = ((0, -1), (0, 1), (-1, 0), (1, 0))
_ROTATIONS = (((1, 0), (0, 1)), ((0, -1), (1, 0)), ((-1, 0), (0, -1)), ((0, 1), (-1, 0)))  # the 4 proper
# rotations of grid indices, (new_row, new_col) = M (row, col)
_DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
_NEARBY = sorted(((i, j) for i in range(-3, 4) for j in range(-3, 4)), key=lambda q: (abs(q[0]) + abs(q[1]), q))
_REACH = 4  # a position's prediction and axes use filled positions up to this many steps away
_AXES_SHIFTS = ((0, 0), (0, 1), (0, 2), (1, 0), (2, 0))  # _axes reads the _NEARBY cells, then them shifted 1
# and 2 steps along +col and along +row, in one gather
_AXES_R = np.array([[dr + q[0] for dr, _ in _AXES_SHIFTS for q in _NEARBY]])
_AXES_C = np.array([[dc + q[1] for _, dc in _AXES_SHIFTS for q in _NEARBY]])
SHADE_SPREAD = 2.0  # a board lit more unevenly (ccdn.shade.light_spread) is searched for again, levelled: 1.5 found
# the same corners on shadow renders; every board (0) 7 more of 6427, for a second search on every frame
CANVAS_START = 16  # a new canvas holds this many cells each way from its seed (padding it costs more than its size)
CANVAS_MARGIN = 8  # empty grid cells kept around a growing board: lookups from the frontier (or a
# position beyond a hole, 2 cells out) reach 3 + 2 cells further, and must stay on the canvas
_AROUND_R = np.array([[0] * 5 + [-2, -1, 0, 1, 2]])  # a cell's row, then its column, 2 cells each way
_AROUND_C = np.array([[-2, -1, 0, 1, 2] + [0] * 5])
_PRED_R = np.array([[k * dr for k in (1, 2, 3) for dr, _ in _DIRECTIONS]
                    + [dr for dr, _ in _DIAGONALS] + [0] * 4 + [dr for dr, _ in _DIAGONALS]])
_PRED_C = np.array([[k * dc for k in (1, 2, 3) for _, dc in _DIRECTIONS]
                    + [0] * 4 + [dc for _, dc in _DIAGONALS] + [dc for _, dc in _DIAGONALS]])


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
    return _held_on_two_sides(filled)


def largest_first(boards) -> list[Board]:
    """Boards ordered largest first; ties: top, then left (their corners' mean position)."""
    return sorted(boards, key=lambda b: (-len(b), float(b.xy[:, 1].mean()), float(b.xy[:, 0].mean())))


def with_corners(board: Board, cells: np.ndarray, xy: np.ndarray, first: int) -> Board:
    """The board with corners at cells (F, 2) (inside its extent, or past it: then reoriented) and
    positions xy (F, 2) added, indexed from `first` on."""
    return indexed_board(np.concatenate([board.corner_index, np.arange(first, first + len(cells))]),
                          np.concatenate([board.grid, cells]), np.concatenate([board.xy, xy]))


def reoriented(board: Board, sign: float, board_size: tuple[int, int] | None = None) -> Board | None:
    """The board indexed from 0 and oriented again as find_boards does (module docstring), for a
    grid that grew past its extent (indices below 0 or beyond cols / rows); sign: + where the quads
    of even row + col of its grid are light. None where it no longer fits board_size."""
    grid = _orient(board.grid.astype(np.int64), board.xy, sign, board_size, False)
    return None if grid is None else indexed_board(board.corner_index, grid, board.xy)


def indexed_board(idx: np.ndarray, grid: np.ndarray, points: np.ndarray) -> Board:
    """The read-only Board of corners idx (M,) at (row, col) grid (M, 2) from 0, positions points
    (M, 2), in row-major order."""
    order = np.lexsort((grid[:, 1], grid[:, 0]))
    idx, grid = idx[order], grid[order].astype(np.int32)
    board = Board(idx, grid, points[order].astype(np.float32), int(grid[:, 1].max() + 1), int(grid[:, 0].max() + 1))
    for a in (board.corner_index, board.grid, board.xy):
        a.setflags(write=False)
    return board


class _Grower:
    """Grows one board from a seed square over the free corners."""

    def __init__(self, xy: np.ndarray, free: np.ndarray, sampler: Sampler, gaps: np.ndarray,
                 gray: np.ndarray | None = None, first_added: int = 0, occupied: np.ndarray | None = None,
                 score: np.ndarray | None = None) -> None:
        self.xy, self.free, self.sampler = xy, free.copy(), sampler
        self.score = score  # the corners' network scores (find_boards' score): vouch() needs them
        self.gaps = gaps  # each corner's distance to the nearest other one (find_boards' nearest_neighbours)
        self.gray = gray  # given: complete the grid from the image (module docstring)
        self.log_gray: np.ndarray | None = None  # gray on the log scale, made when completion needs it
        self.occupied = np.zeros((0, 2)) if occupied is None else occupied  # earlier boards' corners
        self.first_added = first_added  # index of this grower's first added corner
        self.added: list[np.ndarray] = []
        self.pos = self.idx = self.stale = self.tried = self.origin = None  # the canvas, made by _place
        self.sign = 1.0
        self.contrast = self.threshold = MIN_CONTRAST

    def points(self, idx: np.ndarray) -> np.ndarray:
        """Positions (K, 2) of corners idx (K,): given ones, or ones this grower added."""
        out = self.xy[np.minimum(idx, len(self.xy) - 1)]
        mine = idx >= len(self.xy)
        if mine.any():
            out[mine] = np.asarray(self.added)[idx[mine] - self.first_added]
        return out

    def seed(self, corners: np.ndarray, sign: float, contrast: float) -> None:
        """Start the grid from a verified square (_seed_squares): corners (0,0), (0,1), (1,0), (1,1)."""
        self.sign = sign  # + : quads of even row + col are light
        self.contrast = contrast
        self.threshold = max(MIN_CONTRAST, RELATIVE_CONTRAST * contrast)
        self._place(np.array([(0, 0), (0, 1), (1, 0), (1, 1)]), np.asarray(corners, np.int64))

    # --- the lattice canvas: positions of the grid cells, NaN where empty -------------------------

    def _ensure_margin(self, rc: np.ndarray) -> None:
        """Keep CANVAS_MARGIN empty cells around the filled ones, growing the canvas as needed; rc
        (K, 2): the cells just filled (the others already have their margin)."""
        if len(rc) == 0:
            return
        (top, left), (bottom, right) = rc.min(0), rc.max(0)
        h, w = self.idx.shape
        before = (max(0, CANVAS_MARGIN - top), max(0, CANVAS_MARGIN - left))
        after = (max(0, bottom + CANVAS_MARGIN + 1 - h), max(0, right + CANVAS_MARGIN + 1 - w))
        if any(before) or any(after):
            grow = ((before[0] + 8 * bool(before[0]), after[0] + 8 * bool(after[0])),
                    (before[1] + 8 * bool(before[1]), after[1] + 8 * bool(after[1])))
            self.pos = np.pad(self.pos, grow + ((0, 0),), constant_values=np.nan)
            self.idx = np.pad(self.idx, grow, constant_values=-1)
            self.stale = np.pad(self.stale, grow)
            self.tried = np.pad(self.tried, grow)
            self.origin += np.array([grow[0][0], grow[1][0]])

    def _place(self, cells: np.ndarray, idx: np.ndarray) -> None:
        """Fill cells (K, 2) (canvas-relative to origin) with corners idx (K,)."""
        if self.pos is None:  # room for CANVAS_START cells each way from the seed before any padding
            size = 2 * CANVAS_START + 2
            self.pos = np.full((size, size, 2), np.nan)
            self.idx = np.full((size, size), -1, np.int64)
            self.stale = np.zeros((size, size), bool)
            self.tried = np.zeros((size, size), bool)
            self.origin = np.array([CANVAS_START, CANVAS_START])
        rc = cells + self.origin
        self.idx[rc[:, 0], rc[:, 1]] = idx
        self.pos[rc[:, 0], rc[:, 1]] = self.points(idx)
        given = idx[idx < len(self.free)]
        self.free[given] = False
        stale, tried = self.stale.any(), self.tried.any()  # none before the local rounds: nothing to clear
        if stale or tried:
            near = np.zeros(self.idx.shape, np.uint8)  # failed positions near a change may pass now
            near[rc[:, 0], rc[:, 1]] = 1
            if stale:
                self.stale &= cv2.dilate(near, np.ones((2 * _REACH + 1,) * 2, np.uint8)) == 0
            if tried:  # a completion fit that failed next to a new corner is tried again: its prediction now
                # has more support (a hole first predicted from one side fits once its other sides are filled)
                self.tried &= cv2.dilate(near, np.ones((3, 3), np.uint8)) == 0
        self._ensure_margin(rc)

    def _gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Positions (..., 2) at canvas cells (rows, cols), NaN where empty (the canvas margin keeps
        every lookup from the frontier on the canvas)."""
        return self.pos[rows, cols]

    def _axes(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lattice steps along +col (u) and +row (v) nearest to each canvas cell (K, 2): from the
        nearest filled pair (_NEARBY order), or across a hole (halved); NaN without one."""
        gathered = self._gather(cells[:, 0:1] + _AXES_R, cells[:, 1:2] + _AXES_C)
        by_shift = gathered.reshape(len(cells), len(_AXES_SHIFTS), len(_NEARBY), 2)
        a, *beyond = np.moveaxis(by_shift, 1, 0)  # each (K, 49, 2)
        steps = []
        for one, two in (beyond[0:2], beyond[2:4]):  # along +col, then +row
            diff = np.concatenate([one - a, (two - a) / 2], 1)  # (K, 98, 2): all one-step pairs first, nearest first
            valid = np.isfinite(diff[..., 0])
            first = valid.argmax(1)
            found = diff[np.arange(len(cells)), first]
            found[~valid.any(1)] = np.nan
            steps.append(found)
        return steps[0], steps[1]

    def _predict(self, cells: np.ndarray) -> np.ndarray:
        """Predicted positions (K, 2) of canvas cells from the grid: along each row/column from the
        previous two or three corners (or across a hole), and parallelograms with diagonal
        neighbours; the median of the predictions, NaN without any."""
        p = self._gather(cells[:, 0:1] + _PRED_R, cells[:, 1:2] + _PRED_C)  # (K, 24, 2)
        p1, p2, p3 = p[:, 0:4], p[:, 4:8], p[:, 8:12]  # k = 1, 2, 3 steps along the 4 directions
        line = np.where(np.isfinite(p3), 3 * p1 - 3 * p2 + p3, 2 * p1 - p2)
        line = np.where(np.isfinite(p2), line, 1.5 * p1 - 0.5 * p3)
        diagonal = p[:, 12:16] + p[:, 16:20] - p[:, 20:24]
        return nanmedian_rows(np.concatenate([line, diagonal], 1))

    def _accepts(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray,
                 strict: bool = False, min_pairs: int = 1, crowded: np.ndarray | None = None,
                 near: bool = False) -> np.ndarray:
        """The image test (K,) at points for canvas cells with lattice steps u, v (quads off the
        image are not counted; steps flatter than a seed's fail: MIN_SINE); strict (for corners the
        network did not propose): also the seed's test of even contrast and uniform quads (here on
        the log scale: _alternate), which points on a board's outline next to clutter fail, with at
        least min_pairs of the 4 quad pairs on the image; without it, a point that fails gets the
        module docstring's second chance, and the crowded points ((K,) bool; none when not given)
        must have quads uniform where a seed's are sampled (WIDE_SPREAD) to pass with or without it:
        a corner of a denser lattice (a smaller board in front of this one) passes the second chance
        around itself.
        near (strict only): the strict test also passes where it does on quads sampled NEAR_QUADS
        of the way to their centres, for a corner in other light than the seed's (SHADED_CONTRAST)."""
        sign = self._signs(cells)
        square = _square_enough(u, v)
        if strict:  # the strict test (completion's corners, prune's lone ones) gets no second chance
            levels = quad_levels(self.sampler, points, u, v)
            on_image = np.isfinite(pair_differences(levels[0])).sum(1) >= min_pairs
            ok = self._alternate(levels, sign, strict)
            if near and (again := ~ok & on_image & square).any():
                levels = quad_levels(self.sampler, points[again], NEAR_QUADS * u[again], NEAR_QUADS * v[again])
                contrast = _contrast(levels[0], sign[again]) / self.contrast
                shaded = (contrast < SHADED_CONTRAST) | (contrast > 1 / SHADED_CONTRAST)
                ok[again] = self._alternate(levels, sign[again], strict) & shaded
            return ok & on_image & square
        # the second chance (module docstring), sampled in the same call: one quad may be hidden,
        # the corner's surroundings may not
        k = len(points)
        levels = quad_levels(self.sampler, np.concatenate([points, points]), np.concatenate([u, NEAR_QUADS * u]),
                             np.concatenate([v, NEAR_QUADS * v]))
        far = tuple(part[:, :k] for part in levels)
        plain = self._alternate(far, sign, False)
        # crowded points: quads uniform where a seed's are sampled (a NaN contrast does not refuse), or no pass
        # and no second chance either: the second chance passes a corner of a denser lattice around itself
        mixed = np.zeros(k, bool)
        if crowded is not None and crowded.any():
            wide_diffs, wide_spread = quad_differences(self.sampler, points[crowded], u[crowded], v[crowded],
                                                       SEED_REACH_UNIFORM, SEED_AXES)
            mixed[crowded] = wide_spread > WIDE_SPREAD * np.abs(nanmedian_rows(wide_diffs))
            plain &= ~mixed
        far_diffs = pair_differences(far[0]) * sign[:, None]
        three = (np.fmin.reduce(far_diffs[:, _PAIRS_WITHOUT], 2) > max(MIN_CONTRAST, self.threshold)).any(1)
        retry = ~plain & ~mixed & three
        if retry.any():  # the second chance, for the points with three quads that failed the plain test
            near = tuple(part[:, k:][:, retry] for part in levels)
            plain[retry] = self._alternate(near, sign[retry], True)
        return plain & square

    def _alternate(self, levels: tuple[np.ndarray, ...], sign: np.ndarray, strict: bool) -> np.ndarray:
        """(K,) whether the quads (quad_levels) alternate in the board's sign (K,) of each corner:
        their median pair by the board's threshold and their weakest pair by MIN_CONTRAST and, on
        the log scale (SHADE_OFFSET), by PAIR_RATIO of the strongest; strict: also evenly (the
        weakest pair at least 0.4 of the median) with uniform quads (their samples' range under
        half the median), both on the log scale, so that a shadow across the corner, which
        darkens two of its quads, does not fail it."""
        middle, low, high = levels
        diffs = pair_differences(middle) * sign[:, None]
        typical = nanmedian_rows(diffs)  # NaN where every quad pair is off the image: then not ok
        log_diffs = pair_differences(np.log(middle + SHADE_OFFSET)) * sign[:, None]
        log_low = np.fmin.reduce(log_diffs, 1)  # over the pairs on the image
        ok = ((typical > self.threshold) & (np.fmin.reduce(diffs, 1) > MIN_CONTRAST)
              & (log_low > PAIR_RATIO * np.fmax.reduce(log_diffs, 1)))
        if strict:
            log_typical = nanmedian_rows(log_diffs)
            log_spread = quad_spread(np.log(low + SHADE_OFFSET), np.log(high + SHADE_OFFSET))
            ok &= (log_low > 0.4 * log_typical) & (log_spread < 0.5 * log_typical)
        return ok

    def _straight(self, cells: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(K,) whether corners at points in canvas cells (K, 2) keep the grid's lines straight: no
        row or column turning by more than GROWTH_TURN at them or at their neighbours (_bends)."""
        near = self._gather(cells[:, 0:1] + _AROUND_R, cells[:, 1:2] + _AROUND_C)  # (K, 2 x 5, 2)
        near[:, [2, 7]] = points[:, None]
        steps = np.diff(near.reshape(-1, 5, 2), axis=1)  # the corner's row, then its column, it at 2
        turns = _bends(steps[:, :-1], steps[:, 1:], math.cos(math.radians(GROWTH_TURN)))
        return ~turns.reshape(len(cells), 6).any(1)

    def _frontier(self) -> np.ndarray:
        """Empty canvas cells next to a filled one along a row or column, (K, 2)."""
        filled = self.idx >= 0
        return np.argwhere((row_col_neighbours(filled) > 0) & ~filled)

    def _match(self, cells: np.ndarray, preds: np.ndarray, tol: np.ndarray, u: np.ndarray,
               v: np.ndarray, local: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """For cells, the free corners nearest their predictions that pass the image test with
        lattice steps u, v (one corner per cell, the nearest cell wins a contested corner) and, for
        local predictions (not a homography's), keep the grid's lines straight: which cells (indices
        into cells) and their corners."""
        none = np.zeros(0, np.int64)
        if len(cells) == 0 or (nearest := self._nearest_free(preds)) is None:
            return none, none
        candidate, dist = nearest
        ok = np.nonzero((dist < tol) & np.isfinite(u).all(1) & np.isfinite(v).all(1))[0]  # the test needs both steps
        if len(ok) == 0:
            return none, none
        crowded = self.gaps[candidate[ok]] < CROWDED * _shorter(u[ok], v[ok])
        ok = ok[self._accepts(cells[ok], self.xy[candidate[ok]], u[ok], v[ok], crowded=crowded)]
        if local:
            ok = ok[self._straight(cells[ok], self.xy[candidate[ok]])]
        ok = _nearest_cell_wins(ok, dist, candidate)
        return ok, candidate[ok]

    def _nearest_free(self, preds: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Each prediction's (K, 2) nearest free corner and its distance: (corners (K,), distances
        (K,)); None when no corner is free."""
        free = np.nonzero(self.free)[0]
        if len(free) == 0:
            return None
        d = _distances(preds, self.xy[free])
        nearest = d.argmin(1)
        return free[nearest], d[np.arange(len(preds)), nearest]

    def _take(self, cells: np.ndarray, preds: np.ndarray, tol: np.ndarray, u: np.ndarray,
              v: np.ndarray) -> np.ndarray:
        """Fill cells with their matching free corners (_match); (K,) which were filled."""
        ok, corners = self._match(cells, preds, tol, u, v)
        self._place(cells[ok] - self.origin, corners)
        filled = np.zeros(len(cells), bool)
        filled[ok] = True
        return filled

    def _grow_by_homography(self) -> None:
        """Fill whole rings at once while the board looks flat: a homography fitted to the filled
        cells maps each free corner to its nearest cell; cells up to the filled extent beyond the
        grid (at most CANVAS_MARGIN) take their matching corners (_match: within TOLERANCE of the
        cell's projection, the image test with the projected steps) where these connect to the
        grid along rows and columns. Stops when nothing is added or the fit's worst residual
        exceeds FLAT_RESIDUAL of the shorter step (lens distortion: the local rounds of grow()
        take over). A 9 x 9 board fills in 3 rounds instead of ~12 local ones."""
        while True:
            free = np.nonzero(self.free)[0]
            if len(free) == 0:
                return
            taken = self.idx >= 0
            filled = np.argwhere(taken)
            grid = (filled - self.origin)[:, ::-1].astype(np.float64)  # (col, row), like (x, y)
            points = self.pos[filled[:, 0], filled[:, 1]]
            homography, _ = cv2.findHomography(grid, points, 0)
            if homography is None or abs(np.linalg.det(homography)) < 1e-12:
                return
            fitted, u, v = _project_with_steps(homography, grid)
            if (vector_lengths(fitted - points) > FLAT_RESIDUAL * _shorter(u, v)).any():
                return
            inverse = cv2.perspectiveTransform(self.xy[free][None], np.linalg.inv(homography))[0]
            cells = np.rint(inverse[:, ::-1] + self.origin)  # (row, col) on the canvas
            lo, hi = filled.min(0), filled.max(0)
            reach = np.minimum(hi - lo + 1, CANVAS_MARGIN)
            # NaN fails both comparisons, infinity one: no finiteness test needed
            near = ((cells >= np.maximum(lo - reach, 0))
                    & (cells <= np.minimum(hi + reach, np.array(taken.shape) - 1))).all(1)
            cells = cells[near].astype(np.int64)
            hit = np.zeros(taken.shape, bool)  # each empty cell once, in (row, col) order (np.unique's)
            hit[cells[:, 0], cells[:, 1]] = True
            cells = np.argwhere(hit & ~taken)
            if len(cells) == 0:
                return
            preds, u, v = _project_with_steps(homography, (cells - self.origin)[:, ::-1].astype(np.float64))
            ok, corners = self._match(cells, preds, TOLERANCE * _shorter(u, v), u, v, False)
            if len(ok) == 0:
                return
            # the grid is one 4-connected component (the seed square, grown by joined cells only): the
            # cells its flood fill reaches through the matched ones join it
            mask = taken.astype(np.uint8)
            mask[cells[ok, 0], cells[ok, 1]] = 1
            cv2.floodFill(mask, None, (int(filled[0, 1]), int(filled[0, 0])), 2, flags=4)
            joined = mask[cells[ok, 0], cells[ok, 1]] == 2
            if not joined.any():
                return
            self._place(cells[ok[joined]] - self.origin, corners[joined])

    def _complete(self, cells: np.ndarray, support: tuple[np.ndarray, ...]) -> bool:
        """One round of completion over the frontier `cells` (with their _support): the image's
        saddle points near the predictions (one vectorised fit; in shade also the crossings of their
        edge lines), added where they pass the image test; True if any was."""
        untried = ~self.tried[cells[:, 0], cells[:, 1]]
        if not untried.any():
            return False
        cells = cells[untried]
        self.tried[cells[:, 0], cells[:, 1]] = True
        preds, tol, u, v = (part[untried] for part in support)
        h, w = self.gray.shape
        ok = (np.isfinite(tol) & (preds[:, 0] >= 0) & (preds[:, 0] <= w - 1) & (preds[:, 1] >= 0)
              & (preds[:, 1] <= h - 1))
        # the strict image test at the predictions first: a saddle fit costs ~30x more, and around a
        # board most predictions fall on its margin, where no quads alternate evenly; predictions that
        # fail it on a shadow's edge (_on_shadows_edge) are fitted on their edge lines alone
        strict = ok.copy()
        strict[ok] = self._accepts(cells[ok], preds[ok], u[ok], v[ok], True, COMPLETION_MIN_PAIRS, near=True)
        edge_only = ok & ~strict
        if edge_only.any():
            edge_only[edge_only] = self._on_shadows_edge(cells[edge_only], preds[edge_only], u[edge_only],
                                                         v[edge_only])
        # predictions that fail it where something in front of the board covers a quad, at positions the
        # board holds on two sides or more: growth's plain test (one quad may be hidden), the fit then
        # judged by its half-edges (LOOSE_EDGES)
        loose = ok & ~strict & ~edge_only
        loose &= row_col_neighbours(self.idx >= 0)[cells[:, 0], cells[:, 1]] >= LOOSE_NEIGHBOURS
        if loose.any():
            loose[loose] = self._accepts(cells[loose], preds[loose], u[loose], v[loose])
        tried = strict | edge_only | loose
        cells, preds, tol, u, v, edge_only, loose = (part[tried]
                                                     for part in (cells, preds, tol, u, v, edge_only, loose))
        if len(cells) == 0:
            return False
        typical = float(median(tol))
        radius = window_for_spacing(typical / TOLERANCE)
        narrow = altitude(u, v) < NARROW_ALTITUDE * radius
        fit = {"max_shift": float(tol.max()), "wide": int(np.clip(typical, radius + 2, 8))}
        saddle = ~edge_only
        points, good = preds.copy(), np.zeros(len(preds), bool)
        points[saddle], good[saddle] = refine_saddle_points(self.gray, preds[saddle], radius, 0.4 * radius,
                                                            narrow=narrow[saddle], **fit)
        shaded = saddle & ~good
        if shaded.any():  # failed fits where the quads look like the board's in shade: again on the log scale
            shaded[shaded] = self._in_shade(cells[shaded], preds[shaded], u[shaded], v[shaded])
        if shaded.any():
            points[shaded], good[shaded] = refine_saddle_points(self._log_gray(), preds[shaded], radius, 0.4 * radius,
                                                                narrow=narrow[shaded], **fit)
        if (on_edges := (shaded & ~good) | edge_only).any():  # no saddle on either scale: its edge lines' crossing
            points[on_edges], good[on_edges] = self._on_edge_lines(preds[on_edges], u[on_edges], v[on_edges])
        shift = vector_lengths(points - preds)
        # not just two quad pairs that differ; the edge lines' crossing is judged by its half-edges instead
        # (_on_edge_lines, module docstring)
        good &= (shift <= tol) & (x_like(self.gray, points, tol / TOLERANCE) | on_edges)
        good &= inside_margin(points, self.gray.shape)
        # edge_only's are judged by their half-edges instead (_on_edge_lines), loose ones by theirs below
        if (again := good & saddle & ~loose).any():
            good[again] = self._accepts(cells[again], points[again], u[again], v[again], True, COMPLETION_MIN_PAIRS,
                                        near=True)
        if (even := good & loose).any():
            good[even] = self._even_edges(points[even], u[even], v[even], LOOSE_EDGES) & self._accepts(
                cells[even], points[even], u[even], v[even])
        good[good] &= self._straight(cells[good], points[good])
        taken = np.concatenate([self.pos[self.idx >= 0], self.occupied])  # a corner belongs to one board
        if len(taken):
            good &= _distances(points, taken).min(1) >= tol
        keep = []
        for k in np.nonzero(good)[0][np.argsort(shift[good], kind="stable")]:  # two cells, one point: once
            if all(np.linalg.norm(points[k] - points[j]) >= tol[k] for j in keep):
                keep.append(k)
        if not keep:
            return False
        keep = np.array(keep)
        first = self.first_added + len(self.added)
        self.added.extend(points[keep])
        self._place(cells[keep] - self.origin, np.arange(first, first + len(keep)))
        return True

    def _even_edges(self, points: np.ndarray, u: np.ndarray, v: np.ndarray, share: float) -> np.ndarray:
        """(K,) whether the four half-edges of corners at points (steps u, v) each show at least
        `share` of the strongest one's contrast on the log scale (ccdn.edges.half_edge_contrast): on a
        board's outline one runs into the margin."""
        contrast = half_edge_contrast(self._log_gray(), points, np.stack([u, -u, v, -v], 1))
        return contrast.min(1) >= share * contrast.max(1)  # NaN (off the image): not

    def _in_shade(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K,) whether the quads around points (canvas cells, steps u, v) look like the board's in
        shade: their contrast below SHADED_CONTRAST x the seed's on the grey scale, and a larger share
        of the board's on the log scale (SHADE_OFFSET; the median over up to 32 of its corners) than
        on the grey scale: shade multiplies grey levels, which cancels on the log scale, while a
        board's outline against a mid-grey background loses contrast on both."""
        sign = self._signs(cells)
        levels = quad_levels(self.sampler, points, u, v)[0]
        grey = _contrast(levels, sign) / self.contrast
        board = np.argwhere(self.idx >= 0)[:32]
        board_u, board_v = self._axes(board)
        stepped = np.isfinite(board_u[:, 0]) & np.isfinite(board_v[:, 0])  # NaN: no filled neighbour pair
        board = board[stepped]
        board_levels = quad_levels(self.sampler, self.pos[board[:, 0], board[:, 1]], board_u[stepped],
                                   board_v[stepped])[0]
        # the median over its corners, skipping those (NaN) without a quad pair on the image
        board_log = nanmedian_rows(_contrast(board_levels, self._signs(board), log=True)[None])[0]
        return (grey < SHADED_CONTRAST) & (_contrast(levels, sign, log=True) / board_log > grey)

    def _on_shadows_edge(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K,) whether predictions at points (canvas cells, steps u, v) that failed the strict image
        test lie on a shadow's edge across the board: the board holds the cell's neighbours on both
        sides along its row or its column (a gap in the board; beyond its outline, the margin's quads
        fail the test too: with two neighbours at a right angle allowed, a board's outline next to
        clutter took 2 false corners on 1500 renders) and its quads look like the board's in shade
        (_in_shade). There the shadow's edge makes a quad non-uniform, or a lit dark square lighter
        than a shaded light one, while the corner's four edges still show (_on_edge_lines judges them)."""
        filled = self.idx >= 0
        r, c = cells[:, 0], cells[:, 1]
        ok = (filled[r, c - 1] & filled[r, c + 1]) | (filled[r - 1, c] & filled[r + 1, c])
        if ok.any():
            ok[ok] = self._in_shade(cells[ok], points[ok], u[ok], v[ok])
        return ok

    def _on_edge_lines(self, preds: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corners in shade that no saddle fit finds (a shadow's edge across the corner curves the
        grey levels more than the quadric holds) or that fail the strict image test on a shadow's
        edge (_on_shadows_edge), at the crossing of their lattice lines fitted to the squares' edges
        on the log scale (ccdn.edges), from predictions preds (K, 2) with steps u, v: (K, 2) points
        and whether each is a corner there, its four half-edges each at least EVEN_EDGES of the
        strongest one's contrast (on a board's outline, one runs into the margin)."""
        points, moved = refine_on_edges(self._log_gray(), preds, np.stack([u, -u, v, -v], 1))
        return points, moved & self._even_edges(points, u, v, EVEN_EDGES)

    def _log_gray(self) -> np.ndarray:
        """The frame's grey levels on the log scale (_LOG_GREY), made at the first call."""
        if self.log_gray is None:
            self.log_gray = cv2.LUT(self.gray, _LOG_GREY)
        return self.log_gray

    def _support(self, cells: np.ndarray):
        """Predictions, tolerances (TOLERANCE x the shorter local step, or x SLIVER_REACH x the cell's
        lesser height where less) and steps u, v for cells."""
        u, v = self._axes(cells)
        tol = TOLERANCE * np.minimum(_shorter(u, v), SLIVER_REACH * altitude(u, v))
        preds = self._predict(cells)
        tol[~np.isfinite(preds).all(1)] = np.nan
        return preds, tol, u, v

    def grow(self) -> None:
        """Add corners round by round (all open positions of the frontier at once) until neither a
        neighbour, nor a position beyond a hole, nor (completing) a corner from the image is added."""
        self._grow_by_homography()
        while True:
            # the frontier's support serves all three steps: the canvas only changes when one adds
            cells = self._frontier()
            support = preds, tol, u, v = self._support(cells)
            fresh = ~self.stale[cells[:, 0], cells[:, 1]]
            known = fresh & np.isfinite(tol)
            filled = np.zeros(len(cells), bool)
            origin = self.origin.copy()
            filled[known] = self._take(cells[known], preds[known], tol[known], u[known], v[known])
            failed = cells[fresh & ~filled] + (self.origin - origin)  # the canvas may have grown
            self.stale[failed[:, 0], failed[:, 1]] = True
            if filled.any():
                continue
            beyond = self._beyond(cells, support)
            if self._jump_holes(*beyond):
                continue
            if self.gray is None or not (self._complete(cells, support) or self._complete(*self._checkered(*beyond))):
                return

    def vouch(self) -> None:
        """Completing, take the free corners the network vouches for at positions the pruned board holds
        on LOOSE_NEIGHBOURS sides or more: within VOUCH_REACH of the shorter local step of the grid's
        prediction, scored at least VOUCH_SCORE x the board's median, keeping lines straight and cells
        no flatter than a seed's, without the image test. Where an occluder or the other board covers
        part of a corner's quads, every image test fails while the network still finds the corner (module
        docstring). After prune, whose kept corners have two linked neighbours: a point that growth took
        beyond an outline and prune dropped cannot lend a position its second side."""
        if self.gray is None or self.score is None:
            return
        filled = self.idx >= 0
        cells = _held_on_two_sides(filled)
        own = self.idx[filled]
        own = own[own < len(self.xy)]  # the given corners: completion's have no score
        if len(cells) == 0 or len(own) == 0:
            return
        preds, tol, u, v = self._support(cells)
        ok = np.isfinite(tol) & _square_enough(u, v)
        cells, preds, tol = cells[ok], preds[ok], tol[ok]
        if len(cells) == 0 or (nearest := self._nearest_free(preds)) is None:
            return
        candidate, dist = nearest
        # tol / TOLERANCE: the shorter local step (or SLIVER_REACH x the cell's lesser height, where less)
        near = (dist < VOUCH_REACH * tol / TOLERANCE) & (self.score[candidate] >= VOUCH_SCORE * median(self.score[own]))
        near[near] = self._straight(cells[near], self.xy[candidate[near]])
        take = _nearest_cell_wins(np.nonzero(near)[0], dist, candidate)
        if len(take):
            self._place(cells[take] - self.origin, candidate[take])

    def _jump_holes(self, targets: np.ndarray, support: tuple[np.ndarray, ...]) -> bool:
        """Take free corners at the positions beyond the frontier (_beyond): across a one-corner hole."""
        preds, tols = support[:2]
        return len(targets) > 0 and bool(self._take(targets, preds, tols, *self._axes(targets)).any())

    def _beyond(self, cells: np.ndarray, support: tuple[np.ndarray, ...]):
        """Positions two steps beyond the frontier `cells` (with their _support) along a row or column,
        each once, and their support: (cells (K, 2), (predictions (K, 2), tolerances (K,), the
        frontier's steps u, v)). Growth jumps a one-corner hole to them; completion asks the image
        there where a line of a board's corners fails the image test, e.g. under a shadow's sharp
        edge, which darkens two of their quads (the line left between becomes holes)."""
        _, tol, u, v = support
        uv = np.concatenate([u, v], 1)
        targets, preds, tols, steps = [], [], [], []
        for dr, dc in _DIRECTIONS:
            p1 = self._gather(cells[:, 0] + dr, cells[:, 1] + dc)
            p2 = self._gather(cells[:, 0] + 2 * dr, cells[:, 1] + 2 * dc)
            target = cells - [dr, dc]
            t = self._gather(target[:, 0], target[:, 1])
            ok = np.isfinite(p1[:, 0]) & np.isfinite(p2[:, 0]) & np.isnan(t[:, 0]) & np.isfinite(tol)
            ok &= (target >= 0).all(1) & (target < self.idx.shape).all(1)
            targets.append(target[ok])
            preds.append((3 * p1 - 2 * p2)[ok])
            tols.append(tol[ok])
            steps.append(uv[ok])
        targets, preds, tols, steps = (np.concatenate(part) for part in (targets, preds, tols, steps))
        first = np.sort(_first_of_each_cell(targets, self.idx.shape[1]))
        return targets[first], (preds[first], tols[first], steps[first, :2], steps[first, 2:])

    def _checkered(self, cells: np.ndarray, support: tuple[np.ndarray, ...]):
        """The cells (and their support) whose four quad centres' box means alternate in the board's
        sign at the predictions: a look at one sample per quad (completion's strict test samples
        each quad 5 times, twice), for positions where a board rarely continues (_beyond)."""
        preds, _, u, v = support
        means = quad_means(self.sampler, preds, u, v)
        keep = (pair_differences(means) * self._signs(cells)[:, None] > MIN_CONTRAST).all(1)
        return cells[keep], tuple(part[keep] for part in support)

    def _signs(self, cells: np.ndarray) -> np.ndarray:
        """(K,) the board's sign at canvas cells: + where the corner's own-parity quads are light."""
        return np.where(((cells - self.origin).sum(1) % 2) == 0, self.sign, -self.sign)

    def unkink(self) -> None:
        """Drop corners until no row or column turns by more than MAX_TURN degrees between consecutive
        steps (_bends). Perspective keeps a board's lines straight and lens distortion bends them
        gently (1120 stress renders: 13 degrees at most, where the turn moves a step's end by KINK_PX);
        growth's tolerance lets a line bend a little at each step, and on a board's sliver, where
        the network scores the tips at which two squares of one colour nearly touch, growth wandered
        off the true lattice onto theirs (a stress render: 23 of a board's 57 corners such tips,
        its lines turning by up to 100 degrees). Growth takes no corner that would turn a line by
        more than GROWTH_TURN (_straight: looser, since the first corner taken is not always the
        right one); this settles what is left, what a homography's round took and what corners
        added in one round do together. Each round drops, of the corners in such turns, the one
        farthest from its prediction by the others (_predict), relative to the local lattice step."""
        limit = math.cos(math.radians(MAX_TURN))
        while True:
            bad = np.zeros(self.idx.shape, bool)
            for pos, mark in ((self.pos, bad), (self.pos.transpose(1, 0, 2), bad.T)):  # along rows, columns
                turn = _bends(pos[:, 1:-1] - pos[:, :-2], pos[:, 2:] - pos[:, 1:-1], limit)
                mark[:, :-2] |= turn
                mark[:, 1:-1] |= turn
                mark[:, 2:] |= turn
            suspects = np.argwhere(bad)
            if len(suspects) == 0:
                return
            off = vector_lengths(self.pos[suspects[:, 0], suspects[:, 1]] - self._predict(suspects))
            off = np.nan_to_num(off / _shorter(*self._axes(suspects)), nan=np.inf)  # unpredictable: first
            worst = suspects[off.argmax()]
            self.idx[worst[0], worst[1]] = -1
            self.pos[worst[0], worst[1]] = np.nan

    def prune(self) -> None:
        """Drop corners with fewer than 2 row/column neighbours: lone points on a board's outline.
        A corner with one neighbour stays where the frame cuts the board (a missing neighbour would
        lie off the frame) if it passes the strict image test (the seed's: even contrast, uniform
        quads): the last visible corner of a partial board; and, completing, where an occluder or
        another board hides its other neighbours (_hidden_around)."""
        kept = np.zeros(self.idx.shape, bool)
        while True:
            filled = self.idx >= 0
            neighbours = row_col_neighbours(filled)
            weak = filled & (neighbours < 2)
            single = np.argwhere(weak & (neighbours == 1))
            if len(single):
                u, v = self._axes(single)
                points = self.pos[single[:, 0], single[:, 1]]
                beyond = np.stack([points + u, points - u, points + v, points - v], 1).reshape(-1, 2)
                sure = ~self.sampler.contains(beyond).reshape(-1, 4).all(1)
                sure &= np.isfinite(u).all(1) & np.isfinite(v).all(1)
                sure[sure] = self._accepts(single[sure], points[sure], u[sure], v[sure], strict=True)
                if self.gray is not None and (rest := ~sure).any():  # completing: the image at hand
                    linked = filled & ((neighbours >= 2) | kept)
                    sure[rest] = self._hidden_around(single[rest], points[rest], u[rest], v[rest], linked)
                weak[single[sure, 0], single[sure, 1]] = False
                kept[single[sure, 0], single[sure, 1]] = True
            if not weak.any():
                return
            self.idx[weak] = -1
            self.pos[weak] = np.nan

    def _hidden_around(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray,
                       linked: np.ndarray) -> np.ndarray:
        """(K,) whether corners with one neighbour at points (canvas cells, steps u, v; linked: the
        canvas's cells filled with corners of two neighbours or more) are a board's corners whose
        other neighbours something in front of the board hides: their row and their column each
        hold a linked corner (a point beyond an outer row or column, on the outline, has its
        neighbour in one of them only, and at most other such points in the other) and
        each of their four half-edges shows at least HIDDEN_EDGES of the strongest one's contrast
        on the log scale (ccdn.edges.half_edge_contrast). Pruned before, an occluder cut a row's
        end off a board one corner at a time (its last corner has one neighbour, and then the one
        before it). Both tests count: without the row and column test, 5 false corners more on the
        outline of boards next to clutter; where an occluder's or the other board's edges cross a
        board's outline they make an X-junction whose half-edges reach 0.55 of the strongest."""
        ok = np.isfinite(u).all(1) & np.isfinite(v).all(1)
        ok &= linked[cells[:, 0]].any(1) & linked[:, cells[:, 1]].any(0)
        if ok.any():
            ok[ok] = self._even_edges(points[ok], u[ok], v[ok], HIDDEN_EDGES)
        return ok

    def trim_outline(self) -> None:
        """Drop an outermost row or column that is a stub of the line inside it (at most
        OUTLINE_STUB of its length) where the rest of it would lie inside the frame: beyond a
        board's edge, clutter that continues its pattern for a few squares lets the outline pass
        the image test there (on the stress renders, every false positive of the clean,
        motion-blur, defocus, low-contrast and two-boards subsets lay on such a stub). A line that
        the frame cuts keeps its corners."""
        filled = self.idx >= 0
        drop = np.zeros_like(filled)
        for grid, mask, pos in ((filled, drop, self.pos), (filled.T, drop.T, self.pos.transpose(1, 0, 2))):  # rows, columns
            lines = np.nonzero(grid.any(1))[0]
            if len(lines) < 3:
                continue
            for outer, step in ((lines[0], 1), (lines[-1], -1)):
                inner = outer + step
                if grid[outer].sum() > OUTLINE_STUB * grid[inner].sum():
                    continue
                missing = grid[inner] & ~grid[outer]
                beyond = 2 * pos[inner, missing] - pos[inner + step, missing]  # where the outer corners would be
                beyond = beyond[np.isfinite(beyond).all(1)]
                if len(beyond) and self.sampler.contains(beyond).all():
                    mask[outer] |= grid[outer]
        self.idx[drop] = -1
        self.pos[drop] = np.nan

    def split_at_bridge(self) -> None:
        """Cut the grid at a seam between two boards grown into one, keeping the larger side: an inner
        row or column holding at most BRIDGE of the corners of each line beside it (each of
        MIN_BRIDGED or more) where those three lines are not one lattice (a homography fitted to
        them misses one by more than SEAM_RESIDUAL of the step). Where one board lies in front of
        another, points on its outline alternate like corners where the one behind shows through,
        and growth walked over them onto the other's lattice (a fresh stress two-boards render: one
        wrongly indexed board of 108 corners, 2 between lines of 13 and 6). On one board such a line
        is one that a shadow's edge runs along (a stress shadow render: 1 between 6 and 6)."""
        while True:
            filled = self.idx >= 0
            for axis in (0, 1):
                counts = filled.sum(1 - axis)
                beside = np.minimum(counts[:-2], counts[2:])
                bridges = np.nonzero((counts[1:-1] > 0) & (beside >= MIN_BRIDGED)
                                     & (counts[1:-1] <= BRIDGE * beside))[0] + 1
                line = next((line for line in bridges.tolist() if self._two_lattices(axis, line)), None)
                if line is not None:
                    lines = np.arange(len(counts))
                    keep_before = counts[:line].sum() >= counts[line + 1:].sum()
                    drop = lines >= line if keep_before else lines <= line
                    cut = np.broadcast_to(drop[:, None] if axis == 0 else drop[None, :], filled.shape)
                    self.idx[cut] = -1
                    self.pos[cut] = np.nan
                    break
            else:
                return

    def _two_lattices(self, axis: int, line: int) -> bool:
        """Whether the corners of canvas row (axis 0) or column (axis 1) `line` and the lines beside
        it lie on no one lattice: a homography fitted to them misses one by over SEAM_RESIDUAL of
        the shorter step."""
        near = np.zeros(self.idx.shape, bool)
        if axis == 0:
            near[line - 1:line + 2] = True
        else:
            near[:, line - 1:line + 2] = True
        cells = np.argwhere(near & (self.idx >= 0))
        grid = (cells - self.origin)[:, ::-1].astype(np.float64)
        points = self.pos[cells[:, 0], cells[:, 1]]
        homography, _ = cv2.findHomography(grid, points, 0)
        if homography is None:
            return True
        fitted, u, v = _project_with_steps(homography, grid)
        return bool((vector_lengths(fitted - points) > SEAM_RESIDUAL * _shorter(u, v)).any())

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """The board so far: grid positions (M, 2) (row, col) and corner indices (M,)."""
        rc = np.argwhere(self.idx >= 0)
        return rc - self.origin, self.idx[rc[:, 0], rc[:, 1]]


def _project_with_steps(homography: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image positions (K, 2) of grid points (col, row) (K, 2) under a homography, and the steps
    to their +col and +row neighbours (u, v)."""
    moved = cv2.perspectiveTransform(np.concatenate([grid, grid + [1, 0], grid + [0, 1]])[None], homography)[0]
    points, right, down = moved.reshape(3, -1, 2)
    return points, right - points, down - points


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K, M) distances between points a (K, 2) and b (M, 2): np.linalg.norm(a[:, None] - b[None], axis=2)
    to the last bit, an order of magnitude faster (its sum over an axis of length 2 is slow)."""
    dx = a[:, :1] - b[:, 0]
    dy = a[:, 1:] - b[:, 1]
    dx *= dx
    dy *= dy
    dx += dy
    return np.sqrt(dx, out=dx)


def _nearest_cell_wins(ok: np.ndarray, dist: np.ndarray, corner: np.ndarray) -> np.ndarray:
    """The cells `ok` (indices) that keep their corner (corner (K,), at dist (K,)): one cell per
    corner, the nearest winning a contested one."""
    ok = ok[np.argsort(dist[ok], kind="stable")]
    return ok[np.unique(corner[ok], return_index=True)[1]]


def _first_of_each_cell(cells: np.ndarray, width: int) -> np.ndarray:
    """Indices of the first occurrence of each distinct canvas cell in cells (K, 2) (row, col < width),
    in (row, col) order: np.unique(axis=0, return_index=True) on one integer key per cell, without
    its slow row-wise path."""
    return np.unique(cells[:, 0] * width + cells[:, 1], return_index=True)[1]


@lru_cache(maxsize=4)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), cached: the index pairs (i < j) of n neighbours."""
    i, j = np.triu_indices(n, 1)
    i.setflags(write=False)
    j.setflags(write=False)
    return i, j


def _contrast(levels: np.ndarray, sign: np.ndarray, log: bool = False) -> np.ndarray:
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


def _shorter(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) the shorter of each pair of steps."""
    return np.minimum(np.hypot(u[:, 0], u[:, 1]), np.hypot(v[:, 0], v[:, 1]))


def _square_enough(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(...) whether the cells spanned by steps u, v (..., 2) are no flatter than a seed square may
    be: the sine of the steps' angle above MIN_SINE (seeds and every growth step)."""
    return _unsheared(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0], np.hypot(u[..., 0], u[..., 1]),
                      np.hypot(v[..., 0], v[..., 1]))


def _unsheared(cross: np.ndarray, lu: np.ndarray, lv: np.ndarray) -> np.ndarray:
    """_square_enough from the steps' cross product and lengths (np.hypot's), where these are at hand."""
    return np.abs(cross) > MIN_SINE * lu * lv


def _bends(a: np.ndarray, b: np.ndarray, cos_limit: float) -> np.ndarray:
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


def _held_on_two_sides(filled: np.ndarray) -> np.ndarray:
    """(K, 2) (row, col) of the empty cells of a grid (filled: (R, C) bool) with LOOSE_NEIGHBOURS or
    more filled row/column neighbours: inside a board or in a notch of its outline."""
    return np.argwhere((row_col_neighbours(filled) >= LOOSE_NEIGHBOURS) & ~filled)


def _seed_squares(xy: np.ndarray, sampler: Sampler, seeds: np.ndarray, neighbours: np.ndarray,
                  free: np.ndarray, uneven: tuple[int, ...] = (0,)) -> list[tuple[np.ndarray, ...]]:
    """A verified square at each seed corner, all seeds at once (neighbours (S, K): each seed's
    nearest corners, nearest first; only free ones count), for each count in `uneven` of a square's
    corners that may have non-uniform quads (0, 1 or BEHIND_UNEVEN, strictest first; find_boards):
    one sampling serves them all (a looser count's shortest passing square is among the squares
    sampled for the strictest, which samples further only for the seeds none of whose shortest passed).

    A square is p, p + u, p + v and a fourth corner near p + u + v, with u, v from the seed's
    SEED_NEIGHBOURS nearest free corners, whose four corners pass the image test; of the passing
    bases the shortest is taken (the colour test cannot tell (u, v) from (u, v + 2u)). Returns, per
    count: found (S,), corners (S, 4) ordered (0,0), (0,1), (1,0), (1,1) with u x v > 0 (+col, +row
    like image +x, +y), the board's sign (S,) (+: quads of even row + col are light) and contrast (S,).
    """
    if len(seeds) > SEED_CHUNK:  # bounds the (seeds x pairs x neighbours) arrays
        parts = [_seed_squares(xy, sampler, seeds[k : k + SEED_CHUNK], neighbours[k : k + SEED_CHUNK], free, uneven)
                 for k in range(0, len(seeds), SEED_CHUNK)]
        return [tuple(np.concatenate(arrays) for arrays in zip(*level)) for level in zip(*parts)]
    n_seeds = len(seeds)
    none = (np.zeros(n_seeds, bool), np.zeros((n_seeds, 4), np.int64), np.zeros(n_seeds), np.zeros(n_seeds))
    valid = free[neighbours]
    rows = np.arange(n_seeds)[:, None]
    free_first = np.argsort(~valid, axis=1, kind="stable")[:, :SEED_NEIGHBOURS]  # free neighbours first, nearest first
    nb, nb_valid = neighbours[rows, free_first], valid[rows, free_first]
    i, j = _pairs(nb.shape[1])
    around = xy[neighbours] - xy[seeds][:, None]  # (S, K, 2) candidates relative to their seed, in their given order
    steps = around[rows, free_first]  # (S, N, 2) the steps to the nearest free candidates
    # pairs (u, v) of steps to the nearest candidates (S, P), from each step's coordinates and length
    step_x, step_y = steps[..., 0], steps[..., 1]
    length = vector_lengths(steps)
    lu, lv = length[:, i], length[:, j]
    cross = step_x[:, i] * step_y[:, j] - step_y[:, i] * step_x[:, j]
    hypot = np.hypot(step_x, step_y)  # _square_enough's lengths (hypot's last bit, not the norm's)
    longer = np.maximum(lu, lv)
    ok = (nb_valid[:, i] & nb_valid[:, j] & _unsheared(cross, hypot[:, i], hypot[:, j]) & (lu < 5 * lv)
          & (lv < 5 * lu) & (np.abs(cross) >= MIN_SQUARE_PX * longer))
    si, pi = np.nonzero(ok)  # the fourth corner is sought for the plausible pairs only
    flip = cross[si, pi] < 0
    ia, ib = np.where(flip, j[pi], i[pi]), np.where(flip, i[pi], j[pi])  # u x v > 0
    a, b = nb[si, ia], nb[si, ib]
    uu, vv = steps[si, ia], steps[si, ib]
    size = longer[si, pi]  # the longer step
    # the fourth corner: the candidate nearest p + u + v, invalid ones far away (argmin's first of equals: the
    # same free candidate in the given order as with the free ones first)
    around[~valid] = np.inf
    target = uu + vv
    d2 = ((around[si, :, 0] - target[:, :1]) ** 2) + ((around[si, :, 1] - target[:, 1:]) ** 2)  # (G, K)
    nearest = d2.argmin(1)
    fourth = neighbours[si, nearest]
    tol = TOLERANCE * np.minimum(lu[si, pi], lv[si, pi])
    keep = ((d2[np.arange(len(si)), nearest] < tol**2) & (fourth != seeds[si]) & (fourth != a) & (fourth != b))
    si, a, b, fourth, uu, vv, size = si[keep], a[keep], b[keep], fourth[keep], uu[keep], vv[keep], size[keep]
    if len(si) == 0:
        return [none] * len(uneven)
    square = np.stack([seeds[si], a, b, fourth], 1)  # (G, 4)
    by_size = np.lexsort((size, si))  # each seed's squares, shortest first
    rank = np.empty(len(si), np.int64)
    rank[by_size] = np.arange(len(si)) - np.searchsorted(si[by_size], si[by_size])
    passed = np.zeros((len(uneven), len(si)), bool)
    g_sign, g_contrast = np.zeros(len(si)), np.zeros(len(si))
    first_round = rank < 3  # the image test is the costly part: the shortest squares first ...
    for second in (False, True):  # ... the rest only for the seeds whose shortest all failed
        if second:  # the squares of seeds none of whose squares passed yet (a lookup, not np.isin's sort)
            seed_passed = np.zeros(n_seeds, bool)
            seed_passed[si[passed[0]]] = True
            t = np.nonzero(~first_round & ~seed_passed[si])[0]
        else:
            t = np.nonzero(first_round)[0]
        if len(t) == 0:  # usually the second round: every seed passed with one of its shortest
            continue
        # many squares: the seed corner alone first (passing needs its 4 quad pairs to differ one way by MIN_CONTRAST)
        if len(t) > FEW_SQUARES:
            seed_diffs, seed_spread = quad_differences(sampler, xy[square[t, 0]], uu[t], vv[t], SEED_REACH_UNIFORM,
                                                       SEED_AXES)
            alternating = (seed_diffs.min(1) > MIN_CONTRAST) | (seed_diffs.max(1) < -MIN_CONTRAST)
            t, seed_diffs, seed_spread = t[alternating], seed_diffs[alternating], seed_spread[alternating]
            if len(t) == 0:
                continue
            diffs, spread = quad_differences(sampler, xy[square[t, 1:].ravel()], np.repeat(uu[t], 3, 0),
                                             np.repeat(vv[t], 3, 0), SEED_REACH_UNIFORM, SEED_AXES)
            diffs = np.concatenate([seed_diffs[:, None], diffs.reshape(-1, 3, 4)], 1)
            spread = np.concatenate([seed_spread[:, None], spread.reshape(-1, 3)], 1)
        else:  # all four corners in one call (a square that fails the seed corner's test fails `even` below)
            diffs, spread = quad_differences(sampler, xy[square[t].ravel()], np.repeat(uu[t], 4, 0),
                                             np.repeat(vv[t], 4, 0), SEED_REACH_UNIFORM, SEED_AXES)
            diffs, spread = diffs.reshape(-1, 4, 4), spread.reshape(-1, 4)
        # corners (0, 0), (0, 1), (1, 0), (1, 1): flip the odd ones to "even-parity quads minus odd"
        diffs = (diffs * np.array([1.0, -1.0, -1.0, 1.0])[None, :, None]).reshape(len(t), 16)
        # the square's spread for each count: that of its 4 - uneven most uniform corners
        spreads = np.sort(spread, 1)
        g_sign[t] = np.sign(median(diffs, axis=1))
        g_contrast[t] = median(diffs * g_sign[t][:, None], axis=1)
        with np.errstate(invalid="ignore"):
            even = (g_sign[t] != 0) & (np.min(diffs * g_sign[t][:, None], axis=1)
                                       > np.maximum(MIN_CONTRAST, 0.4 * g_contrast[t]))
            for level, count in enumerate(uneven):
                passed[level, t] = even & (spreads[:, 3 - count] < 0.5 * g_contrast[t])
    results = []
    for level_passed in passed:
        found, corners, sign, contrast = (part.copy() for part in none)
        best = by_size[level_passed[by_size]]  # passing squares by seed, shortest first
        owner = si[best]
        head = np.ones(len(best), bool)  # each seed's first (np.unique's first occurrences, without its sort)
        head[1:] = owner[1:] != owner[:-1]
        first = best[head]
        found[si[first]] = True
        corners[si[first]] = square[first]
        sign[si[first]], contrast[si[first]] = g_sign[first], g_contrast[first]
        results.append((found, corners, sign, contrast))
    return results


def _behind_squares(xy: np.ndarray, sampler: Sampler, seeds: np.ndarray, neighbours: np.ndarray, free: np.ndarray,
                    behind: list[tuple[np.ndarray, tuple[np.ndarray, ...]]]
                    ) -> tuple[tuple[np.ndarray, ...], dict[int, int]]:
    """The last round's squares (BEHIND_UNEVEN uneven corners) of the free `seeds` and each seed's row
    in them: those the earlier rounds sampled since the last board was grown (`behind`: (seeds, their
    squares)) as they are, the others sampled now."""
    fresh = list(behind)
    known = np.zeros(len(xy), bool)
    for ahead, _ in fresh:
        known[ahead] = True
    if not known[seeds].all():
        stale = seeds[~known[seeds]]
        fresh.append((stale, _seed_squares(xy, sampler, stale, neighbours[stale], free, (BEHIND_UNEVEN,))[0]))
    ahead = np.concatenate([a for a, _ in fresh])
    squares = tuple(np.concatenate(parts) for parts in zip(*(q for _, q in fresh)))
    return squares, dict(zip(ahead.tolist(), range(len(ahead))))  # a seed sampled twice: its last row


def _grow_board(xy: np.ndarray, free: np.ndarray, sampler: Sampler, gray: np.ndarray | None, added: list,
                square: list, gaps: np.ndarray, score: np.ndarray) -> _Grower | None:
    """The board grown from a verified seed square (_seed_squares' found, corners, sign, contrast) over
    the free corners (gray given: with completion; `added`: corners earlier boards completed; gaps: each
    corner's distance to its nearest; score: their network scores), pruned, vouched for and trimmed;
    None when it is smaller than MIN_CORNERS or MIN_EXTENT."""
    occupied = np.concatenate([xy[~free], np.reshape(added, (-1, 2))])
    grower = _Grower(xy, free, sampler, gaps, gray, len(xy) + len(added), occupied, score)
    grower.seed(square[1], float(square[2]), float(square[3]))
    grower.grow()
    grower.unkink()
    grower.prune()
    grower.vouch()
    grower.trim_outline()
    grower.split_at_bridge()
    grid, idx = grower.cells()
    if len(idx) < MIN_CORNERS or (grid.max(0) - grid.min(0) + 1).min() < MIN_EXTENT:
        return None
    return grower


def _orient(grid: np.ndarray, xy: np.ndarray, sign: float, board_size: tuple[int, int] | None,
            allow_partial: bool) -> np.ndarray | None:
    """(row, col) in the documented orientation, or None if the board does not fit board_size."""
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


def nearest_neighbours(xy: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point's min(k, N - 1) nearest other points, nearest first: indices (N, k) and squared
    distances (N, k). Distances come from one matrix product per block of 256 rows (|a|^2 + |b|^2 -
    2 a.b), so memory stays O(N) per block and time is a small fraction of the direct form's."""
    k = min(k, len(xy) - 1)
    index, dist2 = np.empty((len(xy), k), np.int64), np.empty((len(xy), k))
    norms = (xy**2).sum(1)
    for start in range(0, len(xy), 256):
        block = slice(start, start + 256)
        d2 = xy[block] @ xy.T  # in place from here: temporaries of this size cost more than the arithmetic
        d2 *= -2
        d2 += norms[None]
        d2 += norms[block, None]
        d2.ravel()[start :: len(xy) + 1] = np.inf  # each row's own point: its diagonal
        part = d2.argmin(1)[:, None] if k == 1 else np.argpartition(d2, k - 1, axis=1)[:, :k]
        d2 = np.take_along_axis(d2, part, 1)
        order = np.argsort(d2, axis=1, kind="stable")
        index[block] = np.take_along_axis(part, order, 1)
        dist2[block] = np.maximum(np.take_along_axis(d2, order, 1), 0)
    return index, dist2


def find_boards(gray: np.ndarray, xy: np.ndarray, score: np.ndarray, board_size: tuple[int, int] | None = None,
                *, allow_partial: bool = False, complete: bool = False, uneven_seeds: int = 0,
                shade_unfound: bool = False) -> tuple[Board, ...]:
    """Link corners into checkerboards: the boards found, largest first (ties: top, then left).

    gray: (H, W) uint8 image the corners come from. xy: (N, 2) corner positions (x, y), (0, 0) the
    centre of the top-left pixel; score: (N,) confidences (seeds are tried best first).
    board_size: (cols, rows) inner corners; if given, only boards of that size (either way round,
    re-indexed to cols x rows) are returned, or also smaller ones that fit it when allow_partial
    (their indices then start at 0 where the found part starts). See the module docstring for the
    orientation of the indices. complete: also take corners the image shows where the grid predicts
    one that xy lacks (module docstring); their corner_index is >= len(xy), their position in Board.xy.
    uneven_seeds: how many corners of a seed square may have non-uniform quads (0 or 1) before the last round
    (module docstring). shade_unfound (with complete): where no board is found, also search the
    levelled frame when the corner-like points lie in uneven light (module docstring, Shade).
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be a 2-D uint8 image, got shape {gray.shape} dtype {gray.dtype}")
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    score = np.asarray(score, np.float64).reshape(-1)
    if len(score) != len(xy):
        raise ValueError(f"xy has {len(xy)} rows but score has {len(score)}")
    n = len(xy)
    if n < MIN_CORNERS:
        return ()
    neighbours, dist2 = nearest_neighbours(xy, SEED_REACH)
    gaps = np.sqrt(dist2[:, 0])
    sampler = Sampler(gray)
    boards = _search(gray, sampler, xy, score, neighbours, gaps, board_size, allow_partial, complete, uneven_seeds)
    square = None
    if complete and boards:
        square = _shaded_square(gray, sampler, boards)
    elif complete and shade_unfound:
        square = _unlit_square(gray, xy, gaps)
    if square is not None:
        # a board under a shadow: the search again on the frame with its light levelled (ccdn.shade), kept
        # where it finds more corners
        flat = levelled(gray, square)
        again = _search(flat, Sampler(flat), xy, score, neighbours, gaps, board_size, allow_partial, complete,
                        uneven_seeds)
        if sum(map(len, again)) > sum(map(len, boards)):
            boards = again
    return boards


def _shaded_square(gray: np.ndarray, sampler: Sampler, boards: tuple[Board, ...]) -> float | None:
    """The median lattice step (px) of the first board lit more unevenly than SHADE_SPREAD
    (ccdn.shade.light_spread), None when none is."""
    for board in boards:
        steps = lattice_steps(board)
        if light_spread(light_levels(gray, board.xy.astype(np.float64), steps, sampler)) > SHADE_SPREAD:
            return median_step(steps)
    return None


def _unlit_square(gray: np.ndarray, xy: np.ndarray, gaps: np.ndarray) -> float | None:
    """The median gap (px) of the corner-like points (ccdn.checker.x_like) among corners xy with
    their `gaps`, where at least MIN_CORNERS of them are lit more unevenly than SHADE_SPREAD
    (ccdn.shade.points_light_spread); None otherwise."""
    corner_like = x_like(gray, xy, gaps)
    if corner_like.sum() < MIN_CORNERS:
        return None
    square = float(median(gaps[corner_like]))
    return square if points_light_spread(gray, xy[corner_like], square) > SHADE_SPREAD else None


def _search(gray: np.ndarray, sampler: Sampler, xy: np.ndarray, score: np.ndarray, neighbours: np.ndarray,
            gaps: np.ndarray, board_size: tuple[int, int] | None, allow_partial: bool, complete: bool,
            uneven_seeds: int) -> tuple[Board, ...]:
    """find_boards' search on `gray` (sampled by `sampler`) for corners xy with their nearest
    neighbours (nearest_neighbours) and gaps (distance to the nearest)."""
    n = len(xy)
    order = np.lexsort((xy[:, 0], xy[:, 1], -score))
    corner_like = x_like(gray, xy, gaps)[order]
    seeds = np.concatenate([order[corner_like], order[~corner_like][:MAX_PLAIN_SEEDS]])
    free = inside_margin(xy, gray.shape)  # corners at the frame's edge are in no board
    found, added = [], []
    # strict seed squares first; squares with uneven corners only among the seeds left when they are done
    # (tried first, they changed the boards the strict ones find: a fisheye board seeded elsewhere grew less);
    # squares with BEHIND_UNEVEN uneven corners last, once a board is found (module docstring)
    grown = False
    behind: list[tuple[np.ndarray, tuple[np.ndarray, ...]]] = []  # (seeds, their squares at BEHIND_UNEVEN)
    for uneven in [*range(uneven_seeds + 1), BEHIND_UNEVEN]:
        last = uneven == BEHIND_UNEVEN
        if last and not (grown and free[seeds].any()):
            break
        batch: dict[int, int] = {}  # seed -> its row in squares, checked in growing batches of the free seeds
        size = 1 if uneven == 0 else SEED_CHUNK
        if last:  # the earlier rounds sampled the last round's squares too: since the last board grew, they hold
            squares, batch = _behind_squares(xy, sampler, seeds[free[seeds]], neighbours, free, behind)
        for k, s in enumerate(seeds.tolist()):
            if not free[s]:
                continue
            if s not in batch:
                ahead = seeds[k:][free[seeds[k:]]][:size]
                size = min(4 * size, SEED_CHUNK)  # the first seed usually finds the board
                squares, *later = _seed_squares(xy, sampler, ahead, neighbours[ahead], free,
                                                (uneven,) if last else (uneven, BEHIND_UNEVEN))
                batch = dict(zip(ahead.tolist(), range(len(ahead))))
                behind.extend((ahead, part) for part in later)
            square = [part[batch[s]] for part in squares]
            if square[0] and not free[square[1]].all():  # a board took some of its corners: look again
                square = [part[0] for part in _seed_squares(xy, sampler, seeds[k : k + 1], neighbours[s][None], free,
                                                            (uneven,))[0]]
            grower = (_grow_board(xy, free, sampler, gray if complete else None, added, square, gaps, score)
                      if square[0] else None)
            if grower is None:
                continue
            grid, idx = grower.cells()
            grown = True
            behind.clear()  # sampled while the board's corners were free: `free` changes only here
            free[idx[idx < n]] = False  # a board of another size still owns its corners
            batch, size = {}, SEED_CHUNK  # the rest is mostly clutter: one batch, checked against what is free now
            added.extend(grower.added)
            oriented = _orient(grid, grower.points(idx), grower.sign, board_size, allow_partial)
            if oriented is not None:
                found.append((idx, oriented))
    points = np.concatenate([xy, np.reshape(added, (-1, 2))])
    return tuple(largest_first([indexed_board(idx, grid, points[idx]) for idx, grid in found]))
