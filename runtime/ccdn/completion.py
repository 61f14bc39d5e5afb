"""Completing a growing board from the image (ccdn.growth's Grower, mixed in).

Completion (ccdn.grid.find_boards' complete=True): where no given corner lies near a predicted
position, the image itself is asked: where the image test, made as strict as the seed's (its
evenness and uniformity on the log scale: ccdn.growth's image test), passes at the prediction, a
saddle point is fitted there (ccdn.refine, within the same tolerance) and taken if it passes the
ring test and the strict image test, with at least two of its quad pairs on the image (one pair
alone, at the frame's edge, is what a board's outline shows too). Where the strict test fails but
growth's plain one passes (one quad may be hidden: an occluder or the other board covers part of the
corner's surroundings) at a position the board holds on two sides or more (LOOSE_NEIGHBOURS), the
fit is taken if the plain test passes at it and its four half-edges each show LOOSE_EDGES of the
strongest one's contrast on the log scale (on a board's outline one runs into the margin): with the
prune change above, four stress samples' 1140 renders: 311 -> 292 corners missed, 17 -> 15 false
positives, the gains all in the occluded, two-boards and shadow subsets. This recovers the corners
the network scored too low (shadowed, blurred, or first found on a downscaled frame); such corners
get indices >= len(xy), in order of addition. A slope in the grey levels shifts a saddle fit's point
by slope / contrast, so under a soft shadow, whose light falls off across a corner faster than the
shaded squares differ, the fit found no saddle: where it fails at a prediction whose quads look like
the board's in shade (lower contrast than the seed's, yet a larger share of the board's on the log
scale than on the grey scale: shade multiplies grey levels, a board's outline against a mid-grey
background loses both alike), it is fitted again on the log scale of grey, where the shade's factor
is an offset and the squares keep the lit ones' contrast (stress shadow renders: 150 -> 109 of 3819
corners missed over 60 renders, those found 0.13 px off the truth (median); 1440 renders of the
other subsets: 3 occluded corners more, no false positive more; without the log-scale share, a
board's outline took a false corner). Where neither scale's fit finds a saddle (a shadow's blurred
edge through the corner curves the grey levels more than a quadric holds), the corner is the
crossing of its lattice lines fitted to its squares' edges on the log scale (ccdn.edges), taken
where each of its four half-edges shows at least EVEN_EDGES of the strongest one's contrast (on a
board's outline one runs into the margin: without this test a radial and a two-boards render took 2
false corners each): shadow renders 109 -> 92 missed, 1440 others unchanged; the ring test (x_like)
does not judge such a crossing: the shadow's edge across the corner puts the ring's first harmonic
above its second, on the log scale too (stress shadow renders, README sample: 21 -> 7 corners
missed; held-out 8 either way; no false positive more). A prediction that fails the strict test
itself, in a gap of the board (filled neighbours on both sides along its row or column) where its
quads look like the board's in shade (a shadow's edge across the corner leaves a quad half lit, or a
lit dark square lighter than a shaded light one), goes to the edge-line fit directly and is judged
by its half-edges instead (shadow renders 92 -> 81 missed, occluded renders 2 fewer, no false
positive more; also with two neighbours at a right angle: 12 fewer still, but a board's outline next
to clutter took 2 false corners). When that adds nothing, completion also asks the image two
positions beyond the frontier along rows and columns, where the four quads alternate in the board's
sign at their centres (one box each, a cheap look before the strict test): a shadow's sharp edge
along a line of corners darkens two quads of each, so that line fails the test, and the board past
it was lost (stress shadow renders: 15 of 165 missed corners over 60 renders found; 1440 renders of
the other subsets unchanged); the line left between stays holes unless completion then fills it."""

from __future__ import annotations

import cv2
import numpy as np

from .checker import altitude, quad_levels, x_like
from .edges import half_edge_contrast, refine_on_edges
from .lattice import (LOOSE_NEIGHBOURS, SHADE_OFFSET, TOLERANCE, distances, inside_margin, quad_contrast,
                      row_col_neighbours)
from .refine import refine_saddle_points, window_for_spacing
from .stats import median, nanmedian_rows, vector_lengths

NARROW_ALTITUDE = 2.0  # squares narrower than this many fit windows get the narrow window's second fit (refine):
# 1.5 left completion unable to fit the 4.5-6 px wide squares of steep views (stress extreme-pose renders: 820 ->
# 681 missed of 5449 corners over 80 renders, together with SLIVER_REACH; 2.5 the same as 2.0)
COMPLETION_MIN_PAIRS = 2  # quad pairs on the image a completed corner needs: one pair alone, at the frame's edge,
# is an edge (a board's outline there took indices: held-out stress renders 3 false positives fewer, 2 corners
# 1.5-2 px from the frame's edge fewer; the benchmark's renders 2 such corners fewer)
LOOSE_EDGES = 0.6  # completion's fits where only growth's plain test passes: half-edges this even (0.75 found
# 10 instead of 16 corners on the 300 occluded, two-boards and shadow renders of four stress samples, the same
# false positives), at positions held on ccdn.lattice.LOOSE_NEIGHBOURS sides or more
EVEN_EDGES = 0.5  # completion's edge-line fit in shade: each half-edge's log-scale contrast >= this x the strongest's
SHADED_CONTRAST = 0.85  # completion's strict test also passes on the quads sampled NEAR_QUADS of the way where
# their grey-level contrast is below this x the seed's (or above 1 / this): a corner in other light than the seed's
_LOG_GREY = (255 * np.log1p(np.arange(256) / SHADE_OFFSET) / np.log1p(255 / SHADE_OFFSET)).astype(np.float32)
_LOG_GREY.setflags(write=False)  # grey level -> log(grey + SHADE_OFFSET), stretched back onto 0..255 so that
# the saddle fit's min_saddle (grey levels / px^2) keeps its meaning: completion's fit in shade (module docstring)


class Completion:
    """Grower's completion steps: a mixin that uses its canvas (idx, pos, origin, tried, occupied,
    added), image (gray, sampler, contrast) and its image tests (_accepts, _straight, _axes, _signs,
    _place)."""

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
            good &= distances(points, taken).min(1) >= tol
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
        contrast = self._half_edges(points, u, v)
        return contrast.min(1) >= share * contrast.max(1)  # NaN (off the image): not

    def _half_edges(self, points: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K, 4): the log-scale contrast across the four half-edges of corners at points (steps u, v;
        ccdn.edges.half_edge_contrast), NaN where one runs off the image."""
        return half_edge_contrast(self._log_gray(), points, np.stack([u, -u, v, -v], 1))

    def _in_shade(self, cells: np.ndarray, points: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(K,) whether the quads around points (canvas cells, steps u, v) look like the board's in
        shade: their contrast below SHADED_CONTRAST x the seed's on the grey scale, and a larger share
        of the board's on the log scale (SHADE_OFFSET; the median over up to 32 of its corners) than
        on the grey scale: shade multiplies grey levels, which cancels on the log scale, while a
        board's outline against a mid-grey background loses contrast on both."""
        sign = self._signs(cells)
        levels = quad_levels(self.sampler, points, u, v)[0]
        grey = quad_contrast(levels, sign) / self.contrast
        board = np.argwhere(self.idx >= 0)[:32]
        board_u, board_v = self._axes(board)
        stepped = np.isfinite(board_u[:, 0]) & np.isfinite(board_v[:, 0])  # NaN: no filled neighbour pair
        board = board[stepped]
        board_levels = quad_levels(self.sampler, self.pos[board[:, 0], board[:, 1]], board_u[stepped],
                                   board_v[stepped])[0]
        # the median over its corners, skipping those (NaN) without a quad pair on the image
        board_log = nanmedian_rows(quad_contrast(board_levels, self._signs(board), log=True)[None])[0]
        return (grey < SHADED_CONTRAST) & (quad_contrast(levels, sign, log=True) / board_log > grey)

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
