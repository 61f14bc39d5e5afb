"""Cleaning up a grown board (ccdn.growth's Grower, mixed in): sharp turns, lone points, stubs, seams.

Once grown, corners are dropped until no line turns by more than MAX_TURN (Cleanup.unkink):
perspective keeps lines straight, lens distortion bends them gently, and tips scored like corners
let growth wander off the true lattice one tolerated step at a time (ccdn.growth). Corners left with
fewer than two row/column neighbours are then dropped (lone points on the outline), except,
completing, one whose other neighbours something in front of the board hides: its row and its column
each hold a corner of two neighbours or more, and its four half-edges are even
(Cleanup._hidden_around; the four stress samples' 1440 renders: 323 -> 281 corners missed, occluded
110 -> 76, two-boards 101 -> 95, 20 false positives either way; 280 fresh renders of 7 subsets:
occluded 59 -> 29, two-boards 42 -> 39, the others unchanged); a corner so kept counts as such a
corner in prune's later rounds (before, where its neighbour lost its other neighbour, the next round
dropped both, each one's line holding only the other: the 300 occluded, two-boards and shadow
renders of four stress samples, 6 corners more in 3, nothing else changed). An outermost row or
column that is a stub of the line inside it (at most 0.3 of its length) is dropped too, unless the
frame cuts it (clutter continuing the pattern beyond an edge). An inner row or column that holds at
most BRIDGE of the corners of each line beside it, where those three lines are no one lattice, joins
two boards: where one board lies in front of another, points on its outline alternate like corners
where the one behind shows through, and growth walked over them onto the other's lattice (a wrongly
indexed board); the grid is cut there and the larger side kept (Cleanup.split_at_bridge). A board
whose quads are dark along their diagonals and light along the lattice's steps is a grid of thick
lines, not a checkerboard (Cleanup.line_grid): ccdn.grid drops it and keeps its corners from other
boards."""

from __future__ import annotations

import math

import cv2
import numpy as np

from .checker import axis_pull
from .edges import wide_squares
from .lattice import bends, project_with_steps, row_col_neighbours, shorter_length
from .stats import nanmedian_rows, vector_lengths

MAX_TURN = 15.0  # degrees between consecutive steps along a row or column: a sharper turn is a wrong corner
# where it also moves the shorter step's end ccdn.lattice.KINK_PX (bends)
HIDDEN_EDGES = 0.6  # prune keeps a corner whose neighbours are hidden if its half-edges are this even (_hidden_around)
OUTLINE_STUB = 0.3  # an outermost line this short against the line inside it is an outline artefact ...
OUTLINE_SHORT = 0.6  # ... and one this short whose corners' half-edges are uneven (OUTLINE_EVEN; trim_outline)
TRIM_INSIDE = 0.25  # of a step: an outermost line's missing corners, extrapolated from the two lines inside,
# count as inside the frame only this far inside it; nearer its edge the frame may cut them off (perspective widens
# a close-up's squares from one line to the next, so the extrapolation falls short: trim_outline)
OUTLINE_EVEN = 0.5  # of the strongest half-edge's log-scale contrast, each of a corner's four at least
BRIDGE = 0.4  # an inner line this short against both lines beside it joins two boards (Cleanup.split_at_bridge) ...
MIN_BRIDGED = 4  # ... where each of those holds this many corners ...
SEAM_RESIDUAL = 0.1  # ... and a homography fitted to the three lines misses one by this x the shorter step
LINE_GRID = 0.5  # a board's median axis pull (ccdn.checker.axis_pull) above this is a grid of lines (line_grid) ...
LINE_GRID_CORNERS = 16  # ... over this many of its corners at most


class Cleanup:
    """Grower's steps after growth: a mixin that uses its canvas (idx, pos, origin), sampler and its
    tests (_predict, _axes, _accepts, _even_edges, _half_edges)."""

    def unkink(self) -> None:
        """Drop corners until no row or column turns by more than MAX_TURN degrees between consecutive
        steps (bends). Perspective keeps a board's lines straight and lens distortion bends them
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
                turn = bends(pos[:, 1:-1] - pos[:, :-2], pos[:, 2:] - pos[:, 1:-1], limit)
                mark[:, :-2] |= turn
                mark[:, 1:-1] |= turn
                mark[:, 2:] |= turn
            suspects = np.argwhere(bad)
            if len(suspects) == 0:
                return
            off = vector_lengths(self.pos[suspects[:, 0], suspects[:, 1]] - self._predict(suspects))
            off = np.nan_to_num(off / shorter_length(*self._axes(suspects)), nan=np.inf)  # unpredictable: first
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
        OUTLINE_STUB of its length, or OUTLINE_SHORT where most of its corners' half-edges are
        uneven: _uneven_line) where the rest of it would lie inside the frame: beyond a board's
        edge, clutter that continues its pattern for a few squares lets the outline pass the image
        test there (on the stress renders, every false positive of the clean, motion-blur, defocus,
        low-contrast and two-boards subsets lay on such a stub). A line that the frame cuts keeps
        its corners: one whose missing corners, extrapolated, lie off the frame or within TRIM_INSIDE
        of a step of its edge (80 fresh close-ups: 2 corners more, whose line's next squares
        perspective widened past the frame's edge)."""
        filled = self.idx >= 0
        drop = np.zeros_like(filled)
        frame_end = np.array([self.sampler.width - 1, self.sampler.height - 1])
        for columns, grid, mask, pos in ((False, filled, drop, self.pos),
                                         (True, filled.T, drop.T, self.pos.transpose(1, 0, 2))):
            lines = np.nonzero(grid.any(1))[0]
            if len(lines) < 3:
                continue
            for outer, step in ((lines[0], 1), (lines[-1], -1)):
                inner = outer + step
                count, inside = grid[outer].sum(), grid[inner].sum()
                stub = count <= OUTLINE_STUB * inside or (
                    count <= OUTLINE_SHORT * inside and self._uneven_line(np.nonzero(grid[outer])[0], outer, columns))
                if not stub:
                    continue
                missing = grid[inner] & ~grid[outer]
                last = pos[inner, missing] - pos[inner + step, missing]
                beyond = pos[inner, missing] + last  # where the outer corners would be
                known = np.isfinite(beyond).all(1)
                margin = TRIM_INSIDE * vector_lengths(last[known])[:, None]
                if known.any() and ((beyond[known] >= margin) & (beyond[known] <= frame_end - margin)).all():
                    mask[outer] |= grid[outer]
        self.idx[drop] = -1
        self.pos[drop] = np.nan

    def _uneven_line(self, positions: np.ndarray, line: int, columns: bool) -> bool:
        """Whether most corners of canvas row `line` (columns: column) at `positions` along it have a
        half-edge under OUTLINE_EVEN of their strongest on the log scale (as _even_edges judges):
        where a board's outline runs along clutter that continues its pattern, the points beyond
        its last line have one running into the margin. False for a single corner, when not
        completing (no image at hand) or when fewer than half of them can be judged: squares
        thinner than ccdn.edges.MIN_ASPECT (steep views: their half-edge profiles are no judge), a
        half-edge off the frame (a board the frame cuts)."""
        if self.gray is None or len(positions) < 2:  # a lone corner: the last visible one where the frame cuts
            return False
        cells = np.stack([np.full(len(positions), line), positions], 1)  # (row, col)
        if columns:
            cells = cells[:, ::-1]
        u, v = self._axes(cells)
        wide = wide_squares(u, v)
        if 2 * int(wide.sum()) < len(cells):  # squares too thin for half-edge profiles (steep views): kept
            return False
        contrast = self._half_edges(self.pos[cells[wide, 0], cells[wide, 1]], u[wide], v[wide])
        judged = np.isfinite(contrast).all(1)  # a half-edge off the frame (a board the frame cuts): not judged
        if 2 * int(judged.sum()) < len(cells):
            return False
        uneven = contrast[judged].min(1) < OUTLINE_EVEN * contrast[judged].max(1)
        return 2 * int(uneven.sum()) > len(cells)

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

    def line_grid(self) -> bool:
        """Whether the board is a grid of thick lines, not a checkerboard: the median axis pull
        (ccdn.checker.axis_pull) of up to LINE_GRID_CORNERS of its corners that have neighbours on
        their +col and +row sides, evenly spread, above LINE_GRID. On the lattice of its crossings
        and cells turned 45 degrees such a grid passes every test a corner gets (a fresh boardless
        stress render: one board of 2059 false corners, its lines 3 px wide every 10 px): its median
        pull 1.14, against at most 0.26 on the 2379 boards grown on ~2100 cached frames (the stress
        samples, fresh renders, real-dev at three sizes)."""
        filled = self.idx >= 0  # corners with a neighbour on their +col and +row sides: their steps at hand
        cells = np.argwhere(filled[:-1, :-1] & filled[:-1, 1:] & filled[1:, :-1])
        if len(cells) == 0:
            return False
        r, c = cells[:: -(-len(cells) // LINE_GRID_CORNERS)].T
        p = self.pos[r, c]
        pull = axis_pull(self.sampler, p, self.pos[r, c + 1] - p, self.pos[r + 1, c] - p)
        return bool(nanmedian_rows(pull[None])[0] > LINE_GRID)  # NaN (every quad off the image): False

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
        fitted, u, v = project_with_steps(homography, grid)
        return bool((vector_lengths(fitted - points) > SEAM_RESIDUAL * shorter_length(u, v)).any())
