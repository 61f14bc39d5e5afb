"""Grid recovery: unordered corners -> boards with (row, col) indices, without knowing the board size.

How: seeds are tried in order of score, first the corners whose surroundings look like a checker
corner (on a small ring around it the grey level alternates twice: the ring's second angular
harmonic beats its first, as it does not at an edge or a T-junction), then at most 200 others (a
cheap filter that keeps clutter from costing a seed attempt per point). A seed is a corner p with
two neighbours p + u, p + v whose sum p + u + v is also a corner (one square of the lattice) and
whose four corners pass the image test below, with uniform grey inside each sampled quad (a wrong
lattice samples edges); of the passing bases the shortest is taken. The board then grows position
by position: each empty neighbour of the grid is predicted from the grid (along a row or column
from the previous two or three corners, e.g. 2 p1 - p2, also across a hole, and from parallelograms
with diagonal neighbours; the median of the predictions), and the nearest free corner within 0.3 of
the shorter local lattice step is taken if it passes the image test. When nothing more can be
added, growth may jump over one missing position along a row or column (a hole, not the end of the
board). Corners left with fewer than two row/column neighbours are then dropped (lone points on the
outline). A grid of at least 3 x 3 positions and 8 corners is a board; its corners are removed and
the search repeats for further boards. Corners in no board are dropped. Local predictions make this
tolerant of perspective and strong radial/fisheye distortion.

Completion (complete=True): where no given corner lies near a predicted position, the image itself
is asked: a saddle point is fitted there (ccdn.refine, within the same tolerance) and taken if it
passes the same image test. This recovers the corners the network scored too low (shadowed, blurred,
or first found on a downscaled frame); such corners get indices >= len(xy), in order of addition.

Image test: at a checker corner the four squares around it alternate dark/light. The mean grey
level is sampled at the four quad centres p +- u/2 +- v/2 (u, v: the local lattice steps; halfway
to a centre that is off the image) and all four edge-adjacent quad pairs must differ with the
board's sign (fixed at its seed: quads with even row + col are all dark or all light), their median
by at least a fifth of the seed's contrast and the weakest by 0.15 of the strongest. This rejects
false corners and points on the board's outline (where two outside quads are alike).

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

import numpy as np

from .checker import MIN_CONTRAST, Sampler, quad_differences, x_like
from .refine import refine_saddle_points, window_for_spacing

MIN_CORNERS = 8
MIN_EXTENT = 3
SEED_NEIGHBOURS = 12  # a seed's square is sought among these nearest corners ...
SEED_REACH = 24  # ... and its fourth corner among these
MAX_PLAIN_SEEDS = 200  # seeds tried among the corners that fail the ring test
TOLERANCE = 0.3  # of the shorter local lattice step
MIN_SQUARE_PX = 3.5  # the seed square's smaller height: below it quad centres cannot be sampled
RELATIVE_CONTRAST = 0.2  # of the seed's median contrast
PAIR_RATIO = 0.15  # weakest over strongest quad pair at a corner (a board outline has a ~0 pair)
_DIRECTIONS = ((0, -1), (0, 1), (-1, 0), (1, 0))
_DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
_NEARBY = sorted(((i, j) for i in range(-3, 4) for j in range(-3, 4)), key=lambda q: (abs(q[0]) + abs(q[1]), q))
_REACH = 4  # a position's prediction and axes use filled positions up to this many steps away


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


class _Grower:
    """Grows one board from a seed square over the free corners."""

    def __init__(self, xy: np.ndarray, free: np.ndarray, sampler: Sampler, gray: np.ndarray | None = None,
                 first_added: int = 0) -> None:
        self.xy, self.free, self.sampler = xy, free.copy(), sampler
        self.gray = gray  # given: complete the grid from the image (module docstring)
        self.first_added = first_added  # index of this grower's first added corner
        self.added: list[np.ndarray] = []
        self.tried: set[tuple[int, int]] = set()  # positions completion has asked the image about
        self.at: dict[tuple[int, int], int] = {}
        self.stale: set[tuple[int, int]] = set()  # failed, and nothing near them changed since
        self.sign = 1.0
        self.threshold = MIN_CONTRAST

    def seed(self, s: int, neighbours: np.ndarray) -> bool:
        """Find a verified square at corner s (neighbours: its nearest corners, nearest first); on
        success the grid holds the square's 4 corners."""
        candidates = neighbours[self.free[neighbours]]
        nb = candidates[:SEED_NEIGHBOURS]
        if len(nb) < 3:
            return False
        p = self.xy[s]
        i, j = np.triu_indices(len(nb), 1)
        u, v = self.xy[nb[i]] - p, self.xy[nb[j]] - p
        lu, lv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
        cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
        ok = ((np.abs(cross) > 0.3 * lu * lv) & (lu < 5 * lv) & (lv < 5 * lu)
              & (np.abs(cross) >= MIN_SQUARE_PX * np.maximum(lu, lv)))
        if not ok.any():
            return False
        flip = cross < 0  # order each pair so that u x v > 0: +col, +row like image +x, +y
        a, b = np.where(flip, nb[j], nb[i])[ok], np.where(flip, nb[i], nb[j])[ok]
        u, v = self.xy[a] - p, self.xy[b] - p
        d = np.linalg.norm(self.xy[candidates][None] - (p + u + v)[:, None], axis=2)
        nearest = d.argmin(1)
        tol = TOLERANCE * np.minimum(np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1))
        good = np.nonzero(d[np.arange(len(d)), nearest] < tol)[0]
        fourth = candidates[nearest[good]]
        good = good[(fourth != s) & (fourth != a[good]) & (fourth != b[good])]
        if len(good) == 0:
            return False
        corners = np.stack([np.full(len(good), s), a[good], b[good], candidates[nearest[good]]], 1)  # (G, 4)
        diffs, spread = quad_differences(self.sampler, self.xy[corners.ravel()], np.repeat(u[good], 4, 0),
                                          np.repeat(v[good], 4, 0))
        # corners (0, 0), (0, 1), (1, 0), (1, 1): flip the odd ones to "even-parity quads minus odd"
        diffs = (diffs.reshape(-1, 4, 4) * np.array([1.0, -1.0, -1.0, 1.0])[None, :, None]).reshape(len(good), 16)
        spread = spread.reshape(-1, 4).max(1)
        sign = np.sign(np.median(diffs, axis=1))
        contrast = np.median(diffs * sign[:, None], axis=1)
        with np.errstate(invalid="ignore"):
            passed = ((sign != 0) & (np.min(diffs * sign[:, None], axis=1) > np.maximum(MIN_CONTRAST, 0.4 * contrast))
                      & (spread < 0.5 * contrast))
        if not passed.any():
            return False
        # the colour test cannot tell (u, v) from (u, v + 2u) and the like: take the shortest basis
        size = np.maximum(np.linalg.norm(u[good], axis=1), np.linalg.norm(v[good], axis=1))
        k = int(np.argmin(np.where(passed, size, np.inf)))
        self.sign = float(sign[k])  # + : quads of even row + col are light
        self.threshold = max(MIN_CONTRAST, RELATIVE_CONTRAST * float(contrast[k]))
        for rc, idx in zip(((0, 0), (0, 1), (1, 0), (1, 1)), corners[k]):
            self._add(rc, int(idx))
        return True

    def _add(self, rc: tuple[int, int], idx: int) -> None:
        self.at[rc] = idx
        if idx < len(self.free):
            self.free[idx] = False
        r, c = rc
        self.stale -= {(r + i, c + j) for i in range(-_REACH, _REACH + 1) for j in range(-_REACH, _REACH + 1)}

    def point(self, idx: int) -> np.ndarray:
        """Position of corner idx: a given one, or one this grower added."""
        return self.xy[idx] if idx < len(self.xy) else self.added[idx - self.first_added]

    def _p(self, r: int, c: int) -> np.ndarray | None:
        idx = self.at.get((r, c))
        return None if idx is None else self.point(idx)

    def _axis(self, r: int, c: int, dr: int, dc: int) -> np.ndarray | None:
        """The lattice step along (dr, dc) nearest to position (r, c), from filled pairs (or across a hole)."""
        for step in (1, 2):
            for i, j in _NEARBY:
                a, b = self._p(r + i, c + j), self._p(r + i + step * dr, c + j + step * dc)
                if a is not None and b is not None:
                    return (b - a) / step
        return None

    def _accepts(self, rc: tuple[int, int], point: np.ndarray) -> bool:
        """The image test at `point` for grid position rc (quads off the image are not counted)."""
        u, v = self._axis(*rc, 0, 1), self._axis(*rc, 1, 0)
        if u is None or v is None:
            return False
        parity = 1.0 if (rc[0] + rc[1]) % 2 == 0 else -1.0
        diffs = quad_differences(self.sampler, point, u, v)[0][0] * parity * self.sign
        diffs = diffs[np.isfinite(diffs)]
        return bool(len(diffs) >= 2 and np.median(diffs) > self.threshold
                    and diffs.min() > max(MIN_CONTRAST, PAIR_RATIO * diffs.max()))

    def _prediction(self, r: int, c: int) -> tuple[np.ndarray, float] | None:
        """Predicted position of (r, c) and the tolerance, or None without enough support."""
        preds = []
        for dr, dc in _DIRECTIONS:
            p1, p2, p3 = (self._p(r + k * dr, c + k * dc) for k in (1, 2, 3))
            if p1 is not None and p2 is not None:
                preds.append(3 * p1 - 3 * p2 + p3 if p3 is not None else 2 * p1 - p2)
            elif p1 is not None and p3 is not None:  # across a hole
                preds.append(1.5 * p1 - 0.5 * p3)
        for dr, dc in _DIAGONALS:
            a, b, m = self._p(r + dr, c), self._p(r, c + dc), self._p(r + dr, c + dc)
            if a is not None and b is not None and m is not None:
                preds.append(a + b - m)
        tol = self._tolerance(r, c)
        if not preds or tol is None:
            return None
        return (preds[0] if len(preds) == 1 else np.median(preds, axis=0)), tol

    def _tolerance(self, r: int, c: int) -> float | None:
        """TOLERANCE times the shorter lattice step near (r, c)."""
        u, v = self._axis(r, c, 0, 1), self._axis(r, c, 1, 0)
        return None if u is None or v is None else TOLERANCE * min(math.hypot(*u), math.hypot(*v))

    def _take(self, rc: tuple[int, int], pred: np.ndarray, tol: float) -> bool:
        """Fill position rc with the free corner nearest its prediction if it passes the image test."""
        free = np.nonzero(self.free)[0]
        if len(free) == 0:
            return False
        d = np.linalg.norm(self.xy[free] - pred, axis=1)
        k = int(d.argmin())
        if d[k] >= tol or not self._accepts(rc, self.xy[free[k]]):
            return False
        self._add(rc, int(free[k]))
        return True

    def _complete(self) -> bool:
        """One round of completion over the whole frontier: the image's saddle points near the
        predictions (one vectorised fit), each added if it passes the image test; True if any was."""
        h, w = self.gray.shape
        asked = []
        for rc in self._frontier():
            found = self._prediction(*rc) if rc not in self.tried else None
            self.tried.add(rc)
            if found is not None and 0 <= found[0][0] <= w - 1 and 0 <= found[0][1] <= h - 1:
                asked.append((rc, *found))
        if not asked:
            return False
        tol = np.array([t for _, _, t in asked])
        radius = window_for_spacing(float(np.median(tol)) / TOLERANCE)
        points, ok = refine_saddle_points(self.gray, np.array([p for _, p, _ in asked]), radius, 0.4 * radius,
                                          max_shift=float(tol.max()), wide=int(np.clip(np.median(tol), radius + 2, 8)))
        added = False
        for (rc, pred, t), point, good in zip(asked, points.astype(np.float64), ok):
            if not good or np.hypot(*(point - pred)) > t or not self._accepts(rc, point):
                continue
            taken = np.array([self._p(*q) for q in self.at])
            if (np.linalg.norm(taken - point, axis=1) < t).any():
                continue
            self.added.append(point)
            self._add(rc, self.first_added + len(self.added) - 1)
            added = True
        return added

    def _frontier(self) -> list[tuple[int, int]]:
        empty = {(r + dr, c + dc) for r, c in self.at for dr, dc in _DIRECTIONS} - self.at.keys()
        support = {q: sum((q[0] + i, q[1] + j) in self.at for i in (-1, 0, 1) for j in (-1, 0, 1)) for q in empty}
        return sorted(empty, key=lambda q: (-support[q], q))

    def grow(self) -> None:
        """Add corners until neither a neighbour, nor a position beyond a hole, nor (completing) a
        corner from the image can be added."""
        while True:
            added = False
            for rc in self._frontier():
                if rc in self.stale:
                    continue
                found = self._prediction(*rc)
                if found is not None and self._take(rc, *found):
                    added = True
                else:
                    self.stale.add(rc)
            if added:
                continue
            for r, c in self._frontier():  # jump over a hole: two steps along a row or column
                for dr, dc in _DIRECTIONS:
                    p1, p2 = self._p(r + dr, c + dc), self._p(r + 2 * dr, c + 2 * dc)
                    target = (r - dr, c - dc)
                    if p1 is None or p2 is None or target in self.at:
                        continue
                    tol = self._tolerance(r, c)
                    if tol is not None:
                        added |= self._take(target, 3 * p1 - 2 * p2, tol)
            if not added and not (self.gray is not None and self._complete()):
                return

    def prune(self) -> None:
        """Drop corners with fewer than 2 row/column neighbours: lone points on a board's outline."""
        while True:
            weak = [(r, c) for r, c in self.at if sum((r + dr, c + dc) in self.at for dr, dc in _DIRECTIONS) < 2]
            if not weak:
                return
            for rc in weak:
                del self.at[rc]


def _orient(grid: np.ndarray, xy: np.ndarray, sign: float, board_size: tuple[int, int] | None,
            allow_partial: bool) -> np.ndarray | None:
    """(row, col) in the documented orientation, or None if the board does not fit board_size."""
    index = {(int(r), int(c)): k for k, (r, c) in enumerate(grid)}

    def mean_step(dr: int, dc: int) -> np.ndarray:
        pairs = [(k, index[(r + dr, c + dc)]) for (r, c), k in index.items() if (r + dr, c + dc) in index]
        steps = np.array([xy[b] - xy[a] for a, b in pairs])
        return (steps / np.linalg.norm(steps, axis=1, keepdims=True)).mean(0)

    col_dir, row_dir = mean_step(0, 1), mean_step(1, 0)
    # the 4 proper rotations (new_r, new_c) of (r, c), with the image directions of +col and +row
    rotations = [(lambda r, c: (r, c), col_dir, row_dir), (lambda r, c: (-c, r), row_dir, -col_dir),
                 (lambda r, c: (-r, -c), -col_dir, -row_dir), (lambda r, c: (c, -r), -row_dir, col_dir)]
    ref_light = sign > 0  # the quad between internal corners (0, 0) and (1, 1) has even parity
    best, best_key = None, None
    for rotate, new_col, new_row in rotations:
        r, c = rotate(grid[:, 0], grid[:, 1])
        r0, c0 = r.min(), c.min()
        cols, rows = int(c.max() - c0 + 1), int(r.max() - r0 + 1)
        if board_size is not None:
            bc, br = board_size
            fits = (cols, rows) == (bc, br) or (allow_partial and cols <= bc and rows <= br)
            if not fits:
                continue
        qr, qc = rotate(np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]))
        origin_light = ((qr.min() - r0 + qc.min() - c0) % 2 == 0) == ref_light
        horizontal = abs(new_col[0]) / np.linalg.norm(new_col) >= abs(new_row[0]) / np.linalg.norm(new_row)
        axis_rank = 0 if (board_size is not None and board_size[0] != board_size[1]) or horizontal else 1
        key = (axis_rank, not origin_light, new_col[0] <= 0)
        if best_key is None or key < best_key:
            best, best_key = np.stack([r - r0, c - c0], 1), key
    return best


def _nearest(xy: np.ndarray, k: int) -> np.ndarray:
    """(N, min(k, N - 1)) indices of each point's nearest other points, nearest first (in row blocks,
    so that memory stays O(N) per block)."""
    k = min(k, len(xy) - 1)
    out = np.empty((len(xy), k), np.int64)
    for start in range(0, len(xy), 256):
        d = np.linalg.norm(xy[start : start + 256, None] - xy[None], axis=2)
        d[np.arange(len(d)), np.arange(start, start + len(d))] = np.inf
        part = np.argpartition(d, k - 1, axis=1)[:, :k]
        order = np.argsort(np.take_along_axis(d, part, 1), axis=1, kind="stable")
        out[start : start + len(d)] = np.take_along_axis(part, order, 1)
    return out


def find_boards(gray: np.ndarray, xy: np.ndarray, score: np.ndarray, board_size: tuple[int, int] | None = None,
                *, allow_partial: bool = False, complete: bool = False) -> tuple[Board, ...]:
    """Link corners into checkerboards: the boards found, largest first (ties: top, then left).

    gray: (H, W) uint8 image the corners come from. xy: (N, 2) corner positions (x, y), (0, 0) the
    centre of the top-left pixel; score: (N,) confidences (seeds are tried best first).
    board_size: (cols, rows) inner corners; if given, only boards of that size (either way round,
    re-indexed to cols x rows) are returned, or also smaller ones that fit it when allow_partial
    (their indices then start at 0 where the found part starts). See the module docstring for the
    orientation of the indices. complete: also take corners the image shows where the grid predicts
    one that xy lacks (module docstring); their corner_index is >= len(xy), their position in Board.xy.
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
    sampler = Sampler(gray)
    neighbours = _nearest(xy, SEED_REACH)
    order = np.lexsort((xy[:, 0], xy[:, 1], -score))
    corner_like = x_like(gray, xy, neighbours[:, 0])[order]
    seeds = np.concatenate([order[corner_like], order[~corner_like][:MAX_PLAIN_SEEDS]])
    free = np.ones(n, bool)
    found, added = [], []
    for s in seeds:
        if not free[s]:
            continue
        grower = _Grower(xy, free, sampler, gray if complete else None, n + len(added))
        if not grower.seed(int(s), neighbours[s]):
            continue
        grower.grow()
        grower.prune()
        if len(grower.at) < MIN_CORNERS:
            continue
        idx = np.array(list(grower.at.values()), np.int64)
        grid = np.array(list(grower.at.keys()), np.int64)
        extent = grid.max(0) - grid.min(0) + 1
        if extent.min() < MIN_EXTENT:
            continue
        free[idx[idx < n]] = False  # a board of another size still owns its corners
        added.extend(grower.added)
        oriented = _orient(grid, np.array([grower.point(i) for i in idx]), grower.sign, board_size, allow_partial)
        if oriented is not None:
            found.append((idx, oriented))
    points = np.concatenate([xy, np.reshape(added, (-1, 2))])
    boards = []
    for idx, grid in found:
        order = np.lexsort((grid[:, 1], grid[:, 0]))
        idx, grid = idx[order], grid[order].astype(np.int32)
        boards.append(Board(idx, grid, points[idx].astype(np.float32), int(grid[:, 1].max() + 1),
                            int(grid[:, 0].max() + 1)))
    boards.sort(key=lambda b: (-len(b), float(b.xy[:, 1].mean()), float(b.xy[:, 0].mean())))
    for b in boards:
        for a in (b.corner_index, b.grid, b.xy):
            a.setflags(write=False)
    return tuple(boards)
