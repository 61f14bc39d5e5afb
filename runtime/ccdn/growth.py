"""Growing one board over the free corners (ccdn.grid's search, from a seed square of ccdn.seeds).

The board grows from its seed square (ccdn.seeds), first ring-at-once while it looks flat: a
homography fitted to the grid so far predicts every cell up to the grid's own extent beyond it, and
the free corners within 0.3 of the shorter lattice step of a prediction that pass the image test
join where they connect to the grid along rows and columns (a 9 x 9 board fills in ~3 such rounds; a
fit off by more than 5 % of a step anywhere, as under lens distortion, stops this). Then position by
position: each empty neighbour of the grid is predicted from the grid (along a row or column from
the previous two or three corners, e.g. 2 p1 - p2, also across a hole, and from parallelograms with
diagonal neighbours; the median of the predictions), and the nearest free corner within 0.3 of the
shorter local lattice step (or of 1.5 x the cell's lesser height, where that is less: SLIVER_REACH)
is taken if it passes the image test, and unless, lying over half that tolerance off, another free
corner fits the prediction about as well (AMBIGUOUS; in the ring-at-once rounds too). No corner is
taken where the local steps are flatter than a seed's may be (the sine of their angle at most
MIN_SINE, in every growth step): on the slivers of boards tilted 60-75 degrees the tips where two
squares of one colour nearly touch score like corners, and a lattice of such tips passed the image
test (a stress render: 16 of a board's 25 corners 2-4 px off). Nor do these rounds or completion take one that turns a row or column sharply
at it or its neighbours (GROWTH_TURN; ccdn.cleanup settles what is left). When nothing more can be
added, growth may jump over one missing position along a row or column (a hole, not the end of the
board). Local predictions make this tolerant of perspective and strong radial/fisheye distortion;
with completion (ccdn.completion) the image itself is asked where no corner lies near a prediction.
Once the board is pruned (ccdn.cleanup), the network vouches for corners at the positions the pruned
board holds on two sides or more (Grower.vouch): a free corner within VOUCH_REACH (0.05) of the
shorter step of the grid's prediction, scored at least VOUCH_SCORE (0.5) x the board's median, joins
without the image test. Where an occluder or the other board covers part of a corner's quads every
image test fails, while the network, trained on renders with occluders, still finds it (1300 cached
renders: three samples of 340 and 280 fresh occluded, two-boards, shadow and partial ones: 25
corners more, no false positive more, each 0.01-0.34 px off the truth but one, 1.4 px, in a
penumbra. Within 0.15 of a step: 5 more on the 1140 looked at first, but 8 of those it took lay
1-3.7 px off, pulled by an occluder's edge 1-3 px away; before prune, an outline point growth took
lent a position its second side: 7 false positives).

Image test: at a checker corner the four squares around it alternate dark/light. The mean grey
level is sampled at the four quad centres p +- u/2 +- v/2 (u, v: the local lattice steps, or in
the position-by-position rounds those measured from the candidate to its filled neighbours where
they differ by over STEP_CHANGE: across a fisheye close-up, whose squares grow or shrink 1.5-2 x from
one to the next, the filled squares' steps sampled quads outside the candidate's; halfway to a
centre that is off the image) and all four edge-adjacent quad pairs must differ with the
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
board's corners. On a board seeded from quads sampled near their corners (Grower.near: ccdn.grid's
marker search), so are these: a marked board's corners are all crowded by the markers' own, whose
bits make its light quads anything but uniform where a plain seed's are sampled. An occluder
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
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .checker import (MIN_CONTRAST, PAIRS_WITHOUT, Sampler, altitude, pair_differences, quad_differences,
                      quad_levels, quad_means, quad_spread)
from .bridging import Bridging
from .cleanup import Cleanup
from .completion import SHADED_CONTRAST, Completion
from .lattice import (SEED_REACH_UNIFORM, SHADE_OFFSET, TOLERANCE, bends, distances, first_of_each_cell,
                      held_on_two_sides, looks_flat, project_with_steps, quad_contrast, row_col_neighbours,
                      shorter_length, square_enough)
from .seeds import NearQuads, uniform_sampling
from .stats import median, nanmedian_rows

SLIVER_REACH = 1.5  # growth's tolerance is TOLERANCE (ccdn.lattice) of the shorter local step, or of this x the
# cell's lesser height (altitude), where less: on a sheared sliver
# (steps 12-16 px, 4-5 px across) a tip where two squares of one colour nearly touch lies within 0.3 of the
# step of a true corner, and position-by-position growth took tips the network scored as corners, one
# after another (extreme-pose stress render 7100011 once its narrow squares completed: a wrongly indexed board
# and 38 false corners; 1.0 lost corners elsewhere, 2.0 still took the tips)
GROWTH_TURN = 20.0  # growth's own limit, looser: a wrong corner taken first must not keep out the true one
RELATIVE_CONTRAST = 0.05  # of the seed's median contrast: a board's part in deep shade keeps a fifth to a
# twentieth of its lit part's (stress shadow renders, 0.2 before: 12.2 -> 10.5 % missed; every other render the same)
PAIR_RATIO = 0.15  # weakest over strongest quad pair at a corner, on the log scale (a board outline has a ~0 pair)
WIDE_SPREAD = 1.5  # growth's image test: quads sampled as widely as a seed's vary by at most this x their contrast ...
CROWDED = 0.75  # ... at a corner with another this close (x the shorter lattice step): other corners in its cells
NEAR_QUADS = 0.36  # share of the way to the quad centres where the image test's second chance samples
STEP_CHANGE = 1.3  # growth's image test takes the steps measured at a candidate where they differ from the grid's
# by more than this factor either way (Grower._steps_at); on the steep slivers of an extreme pose, the measured
# steps of cells barely square enough turned the sheared-cell guard (MIN_SINE) either way: a board of 55 lost 17
AMBIGUOUS = (0.5, 1.5)  # a free corner farther from its prediction than this share of the tolerance is not taken
# where the next nearest free corner lies within this factor of its distance: between fast-growing squares a
# prediction fell between two corners (fisheye close-up 7190032: 26 and 29 px off, a tolerance of 27), and the
# nearer, a knight's move from the right one, made a wrongly indexed board
VOUCH_REACH = 0.05  # a free corner this close (x the shorter local step) to the prediction at a position held on
# LOOSE_NEIGHBOURS sides or more joins the pruned board without the image test where its network score is ...
VOUCH_SCORE = 0.5  # ... at least this x the board's median (Grower.vouch)
CANVAS_START = 16  # a new canvas holds this many cells each way from its seed (padding it costs more than its size)
CANVAS_MARGIN = 8  # empty grid cells kept around a growing board: lookups from the frontier (or a
# position beyond a hole, 2 cells out) reach 3 + 2 cells further, and must stay on the canvas
_DIRECTIONS = ((0, -1), (0, 1), (-1, 0), (1, 0))
_DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
_NEARBY = sorted(((i, j) for i in range(-3, 4) for j in range(-3, 4)), key=lambda q: (abs(q[0]) + abs(q[1]), q))
_REACH = 4  # a position's prediction and axes use filled positions up to this many steps away
_AXES_SHIFTS = ((0, 0), (0, 1), (0, 2), (1, 0), (2, 0))  # _axes reads the _NEARBY cells, then them shifted 1
# and 2 steps along +col and along +row, in one gather
_AXES_R = np.array([[dr + q[0] for dr, _ in _AXES_SHIFTS for q in _NEARBY]])
_AXES_C = np.array([[dc + q[1] for _, dc in _AXES_SHIFTS for q in _NEARBY]])
_AROUND_R = np.array([[0] * 5 + [-2, -1, 0, 1, 2]])  # a cell's row, then its column, 2 cells each way
_AROUND_C = np.array([[-2, -1, 0, 1, 2] + [0] * 5])
_PRED_R = np.array([[k * dr for k in (1, 2, 3) for dr, _ in _DIRECTIONS]
                    + [dr for dr, _ in _DIAGONALS] + [0] * 4 + [dr for dr, _ in _DIAGONALS]])
_PRED_C = np.array([[k * dc for k in (1, 2, 3) for _, dc in _DIRECTIONS]
                    + [0] * 4 + [dc for _, dc in _DIAGONALS] + [dc for _, dc in _DIAGONALS]])


class Grower(Completion, Cleanup, Bridging):
    """Grows one board from a seed square over the free corners (completing it from the image:
    Completion; cleaning it up after: Cleanup; reaching across a gap: Bridging)."""

    def __init__(self, xy: np.ndarray, free: np.ndarray, sampler: Sampler, gaps: np.ndarray,
                 gray: np.ndarray | None = None, first_added: int = 0, occupied: np.ndarray | None = None,
                 score: np.ndarray | None = None, near: NearQuads | None = None) -> None:
        self.xy, self.free, self.sampler = xy, free.copy(), sampler
        self.near = near  # the seed squares' quads were sampled near their corners (ccdn.seeds): so is the
        # crowded corners' uniformity (_accepts)
        self.score = score  # the corners' network scores (find_boards' score): vouch() needs them
        self.gaps = gaps  # each corner's distance to the nearest other one (find_boards' nearest_neighbours)
        self.gray = gray  # given: complete the grid from the image (ccdn.completion)
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
        """Start the grid from a verified square (seed_squares): corners (0,0), (0,1), (1,0), (1,1)."""
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
        square = square_enough(u, v)
        if strict:  # the strict test (completion's corners, prune's lone ones) gets no second chance
            levels = quad_levels(self.sampler, points, u, v)
            on_image = np.isfinite(pair_differences(levels[0])).sum(1) >= min_pairs
            ok = self._alternate(levels, sign, strict)
            if near and (again := ~ok & on_image & square).any():
                levels = quad_levels(self.sampler, points[again], NEAR_QUADS * u[again], NEAR_QUADS * v[again])
                contrast = quad_contrast(levels[0], sign[again]) / self.contrast
                shaded = (contrast < SHADED_CONTRAST) | (contrast > 1 / SHADED_CONTRAST)
                ok[again] = self._alternate(levels, sign[again], strict) & shaded
            return ok & on_image & square
        k = len(points)
        far = quad_levels(self.sampler, points, u, v)
        plain = self._alternate(far, sign, False)
        # crowded points: quads uniform where a seed's are sampled (a NaN contrast does not refuse), or no pass
        # and no second chance either: the second chance passes a corner of a denser lattice around itself
        mixed = np.zeros(k, bool)
        if crowded is not None and crowded.any():
            wide_u, wide_v, axes = uniform_sampling(self.near, u[crowded], v[crowded])  # as the seed squares were
            wide_diffs, wide_spread = quad_differences(self.sampler, points[crowded], wide_u, wide_v,
                                                       SEED_REACH_UNIFORM, axes)
            mixed[crowded] = wide_spread > WIDE_SPREAD * np.abs(nanmedian_rows(wide_diffs))
            plain &= ~mixed
        far_diffs = pair_differences(far[0]) * sign[:, None]
        three = (np.fmin.reduce(far_diffs[:, PAIRS_WITHOUT], 2) > max(MIN_CONTRAST, self.threshold)).any(1)
        retry = ~plain & ~mixed & three
        if retry.any():  # the second chance (module docstring), for the points with three quads that failed
            # the plain test: one quad may be hidden, the corner's surroundings may not
            near = quad_levels(self.sampler, points[retry], NEAR_QUADS * u[retry], NEAR_QUADS * v[retry])
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
        row or column turning by more than GROWTH_TURN at them or at their neighbours (bends)."""
        near = self._gather(cells[:, 0:1] + _AROUND_R, cells[:, 1:2] + _AROUND_C)  # (K, 2 x 5, 2)
        near[:, [2, 7]] = points[:, None]
        steps = np.diff(near.reshape(-1, 5, 2), axis=1)  # the corner's row, then its column, it at 2
        turns = bends(steps[:, :-1], steps[:, 1:], math.cos(math.radians(GROWTH_TURN)))
        return ~turns.reshape(len(cells), 6).any(1)

    def _frontier(self) -> np.ndarray:
        """Empty canvas cells next to a filled one along a row or column, (K, 2)."""
        filled = self.idx >= 0
        return np.argwhere((row_col_neighbours(filled) > 0) & ~filled)

    def _match(self, cells: np.ndarray, preds: np.ndarray, tol: np.ndarray, u: np.ndarray,
               v: np.ndarray, local: bool = True, nearest: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """For cells, the free corners nearest their predictions that pass the image test with
        lattice steps u, v (one corner per cell, the nearest cell wins a contested corner) and, for
        local predictions (not a homography's), keep the grid's lines straight: which cells (indices
        into cells) and their corners. nearest: the predictions' _nearest_free, where known."""
        none = np.zeros(0, np.int64)
        if len(cells) == 0 or (nearest := self._nearest_free(preds) if nearest is None else nearest) is None:
            return none, none
        candidate, dist = nearest
        ok = np.nonzero((dist < tol) & np.isfinite(u).all(1) & np.isfinite(v).all(1))[0]  # the test needs both steps
        ok = ok[~self._ambiguous(ok, preds, dist, tol)]
        if len(ok) == 0:
            return none, none
        points = self.xy[candidate[ok]]
        u, v = self._steps_at(cells[ok], points, u[ok], v[ok]) if local else (u[ok], v[ok])
        ok = ok[self._accepts(cells[ok], points, u, v, crowded=self._crowded(candidate[ok], u, v))]
        if local:
            ok = ok[self._straight(cells[ok], self.xy[candidate[ok]])]
        ok = _nearest_cell_wins(ok, dist, candidate)
        return ok, candidate[ok]

    def _ambiguous(self, ok: np.ndarray, preds: np.ndarray, dist: np.ndarray, tol: np.ndarray) -> np.ndarray:
        """(len(ok),) whether the cells `ok` (indices) have their nearest free corner over AMBIGUOUS[0]
        of the tolerance from their prediction and the next nearest within AMBIGUOUS[1] x its
        distance: a prediction two corners fit about as well (AMBIGUOUS)."""
        ambiguous = dist[ok] > AMBIGUOUS[0] * tol[ok]
        if not ambiguous.any():
            return ambiguous
        free = np.nonzero(self.free)[0]
        if len(free) < 2:
            return np.zeros(len(ok), bool)
        nearest_two = np.sort(distances(preds[ok[ambiguous]], self.xy[free]), 1)[:, :2]
        ambiguous[ambiguous] = nearest_two[:, 1] < AMBIGUOUS[1] * nearest_two[:, 0]
        return ambiguous

    def _steps_at(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The lattice steps (K, 2) for the image test of candidate points (K, 2) at canvas cells,
        given the grid's steps u, v there: where the step from the point to its filled neighbour
        along the row (u) or the column (v) differs in length from the grid's by over STEP_CHANGE
        either way, the measured steps (the other one, where it has no such neighbour, scaled
        alike); the grid's elsewhere. Across a fisheye close-up the squares grow or shrink 1.5-2 x
        from one to the next, and the grid's steps, taken from the filled squares beside, sampled
        quads outside the candidate's own (module docstring)."""
        measured = []
        for along_row, grid_step in ((True, u), (False, v)):
            step = np.full_like(grid_step, np.nan)
            for side in (-1, 1):
                neighbour = (self._gather(cells[:, 0], cells[:, 1] + side) if along_row
                             else self._gather(cells[:, 0] + side, cells[:, 1]))
                step = np.where(np.isnan(step[:, :1]), side * (neighbour - points), step)
            measured.append(step)
        mu, mv = measured
        has_u, has_v = np.isfinite(mu[:, 0]), np.isfinite(mv[:, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio_u = np.hypot(mu[:, 0], mu[:, 1]) / np.hypot(u[:, 0], u[:, 1])
            ratio_v = np.hypot(mv[:, 0], mv[:, 1]) / np.hypot(v[:, 0], v[:, 1])
            changed = (np.abs(np.log(np.where(has_u, ratio_u, ratio_v))) > np.log(STEP_CHANGE))[:, None]
        new_u = np.where(has_u[:, None], mu, u * np.where(has_v, ratio_v, 1.0)[:, None])
        new_v = np.where(has_v[:, None], mv, v * np.where(has_u, ratio_u, 1.0)[:, None])
        return np.where(changed, new_u, u), np.where(changed, new_v, v)

    def _crowded(self, corners: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K,) whether corners (K,) have another within CROWDED of the shorter of their steps u, v: inside
        their cells (_accepts)."""
        return self.gaps[corners] < CROWDED * shorter_length(u, v)

    def _nearest_free(self, preds: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Each prediction's (K, 2) nearest free corner and its distance: (corners (K,), distances
        (K,)); None when no corner is free."""
        free = np.nonzero(self.free)[0]
        if len(free) == 0:
            return None
        d = distances(preds, self.xy[free])
        nearest = d.argmin(1)
        return free[nearest], d[np.arange(len(preds)), nearest]

    def _take(self, cells: np.ndarray, preds: np.ndarray, tol: np.ndarray, u: np.ndarray,
              v: np.ndarray, nearest: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Fill cells with their matching free corners (_match; nearest: as there); (K,) which were filled."""
        ok, corners = self._match(cells, preds, tol, u, v, nearest=nearest)
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
        exceeds FLAT_RESIDUAL (ccdn.lattice) of the shorter step (lens distortion: the local rounds of grow()
        take over). A 9 x 9 board fills in 3 rounds instead of ~12 local ones."""
        while True:
            free = np.nonzero(self.free)[0]
            if len(free) == 0:
                return
            taken = self.idx >= 0
            filled, grid, points = self._filled()
            homography, _ = cv2.findHomography(grid, points, 0)
            if homography is None or abs(np.linalg.det(homography)) < 1e-12 or not looks_flat(homography, grid, points):
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
            preds, u, v = project_with_steps(homography, (cells - self.origin)[:, ::-1].astype(np.float64))
            ok, corners = self._match(cells, preds, TOLERANCE * shorter_length(u, v), u, v, False)
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

    def _support(self, cells: np.ndarray):
        """Predictions, tolerances (TOLERANCE x the shorter local step, or x SLIVER_REACH x the cell's
        lesser height where less) and steps u, v for cells."""
        u, v = self._axes(cells)
        tol = TOLERANCE * np.minimum(shorter_length(u, v), SLIVER_REACH * altitude(u, v))
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
        cells = held_on_two_sides(filled)
        own = self.idx[filled]
        own = own[own < len(self.xy)]  # the given corners: completion's have no score
        if len(cells) == 0 or len(own) == 0:
            return
        preds, tol, u, v = self._support(cells)
        ok = np.isfinite(tol) & square_enough(u, v)
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
        if len(targets) == 0 or (nearest := self._nearest_free(preds)) is None:
            return False
        near = nearest[1] < tols  # only these can take a corner (_match): the steps are wanted for them alone
        return bool(near.any()) and bool(self._take(targets[near], preds[near], tols[near], *self._axes(targets[near]),
                                                    (nearest[0][near], nearest[1][near])).any())

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
        first = np.sort(first_of_each_cell(targets))
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

    def _filled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The filled canvas cells (K, 2) (row, col), their lattice coordinates from the seed (K, 2)
        float (col, row), like (x, y): what a homography maps, and their positions (K, 2)."""
        filled = np.argwhere(self.idx >= 0)
        return filled, (filled - self.origin)[:, ::-1].astype(np.float64), self.pos[filled[:, 0], filled[:, 1]]

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """The board so far: grid positions (M, 2) (row, col) and corner indices (M,)."""
        rc = np.argwhere(self.idx >= 0)
        return rc - self.origin, self.idx[rc[:, 0], rc[:, 1]]


def _nearest_cell_wins(ok: np.ndarray, dist: np.ndarray, corner: np.ndarray) -> np.ndarray:
    """The cells `ok` (indices) that keep their corner (corner (K,), at dist (K,)): one cell per
    corner, the nearest winning a contested one."""
    ok = ok[np.argsort(dist[ok], kind="stable")]
    return ok[np.unique(corner[ok], return_index=True)[1]]

