"""Boards linked along their edges: grid recovery that needs no prediction of where the next corner lies.

Growth (ccdn.growth) predicts each next corner from the lattice around it; through a fisheye lens
a close-up's squares shrink from over 100 px at the centre to a few px at the rim within a few
rows, faster than any such prediction follows, and no plain seed square may pass there. Here the
board's own edges link its corners instead:

1. Each corner is paired with its LINK_REACH nearest. A pair is an edge where, between 0.3 and 0.7
   of the segment joining them, the image on one side of it is darker than on the other at every
   sample, the weakest difference at least EDGE_EVEN of the strongest and the median at least
   EDGE_CONTRAST of the strongest edges' (the 90th percentile), and the same side darker near its
   ends (END_SAMPLES, closer to the segment): a diagonal of a square has the same grey on both
   sides, a segment over two squares changes side half-way (over two of a fisheye rim's, whose
   sizes differ, near an end). The samples lie EDGE_OFFSETS of its length off the segment, a pair
   passing at either: far enough off to clear a curved edge's bulge, or close enough to stay inside
   the thin rows of a fisheye's rim.
2. Around a checker corner the quadrants alternate, so the edges along one lattice line have the
   same sign (which side is darker, looking away from the corner) and the perpendicular ones the
   other. Each corner keeps, per sign, its shortest edge and the shortest pointing away from it
   (OPPOSITE); an edge stays where both its corners keep it.
3. A breadth-first walk gives every corner its (row, col): from a corner reached along lattice step
   v, the edge back has -v, the other edge of the same sign +v, and the edges of the other sign
   the perpendicular steps, told apart by the side they leave on (a view never mirrors the board).
   A corner on an edge that disagrees with the walk's indices, or sharing its position with
   another, is dropped and the walk repeats, at most MAX_DROPS times. So are both ends of a step
   over MAX_STEP_RATIO times longer or shorter than the one before it on its line (_steady_steps:
   a link across the frame made a small board a "close-up"), and a corner held by one edge only,
   as long as any is (_confirmed), but where the frame cuts its line: at a fisheye's rim such a
   step may span corners the network missed (a wrongly indexed board), where an occluder's
   outline crosses the board's edges it may end on that outline (a false corner; fisheye
   close-ups, 80 renders: kept where shorter than the step continuing their line, 2 boards
   wrongly indexed and 7 false corners; dropped but where the frame cuts their line, none and 1).
   A component whose rows and columns turn by more than MAX_MEDIAN_TURN at the median corner is
   no board (_smooth): a lens bends a board's lines gradually, links through clutter zigzag.

The sign of an edge tells the colour of the squares beside it, so the board's light squares come
with it, which ccdn.grid orients its indices by.
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from .lattice import first_of_each_cell
from .stats import median, quantile, vector_lengths

LINK_REACH = 8  # nearest corners each is paired with: its 4 edge neighbours and 4 diagonal ones on a square lattice
EDGE_SAMPLES = np.array([0.3, 0.4, 0.5, 0.6, 0.7])  # where along a pair's segment the two sides are sampled
EDGE_OFFSETS = (0.12, 0.04)  # of the segment's length: how far off it each side is sampled there, an edge at either
# (a curved long edge bulges past the second, a fisheye rim's rows are thinner than the first; 0.25 too: nothing) ...
END_SAMPLES = np.array([0.1, 0.9])  # ... and where, near its ends, only which side is darker counts ...
END_OFFSET = 0.02  # ... sampled this far off it (0.04: the same corners on 40 fisheye close-ups) ...
MIN_OFFSET = 1.5  # px: ... each at least
EDGE_EVEN = 0.4  # an edge's weakest difference across it, of its strongest
EDGE_CONTRAST = 0.25  # an edge's median difference across it, of the strongest edges' (90th percentile)
OPPOSITE = -0.3  # cosine: a corner's second edge of a sign points away from its first
MAX_MEDIAN_TURN = 15.0  # degrees: a component's rows and columns turn less at the median corner (_smooth). Fisheye
# close-ups: 3-10; clutter linked beside a motion-blurred board (fresh render 7030523): 25-51
MAX_STEP_RATIO = 8.0  # a step this many times longer or shorter than the one before it on its line drops its
# corners (_steady_steps; fisheye close-ups: up to ~3.3)
MAX_DROPS = 10  # corners dropped for disagreeing with a walk before the component is given up


def edge_pairs(image: np.ndarray, xy: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (E, 2) of corners xy among each one's `neighbours` (N, >= LINK_REACH) that are edges
    of a checkerboard in `image` (float32, smoothed; module docstring, 1), with their signs (E,): +1
    where the side to the left of the step from the first to the second (x right, y down: its
    +90-degree normal) is the lighter."""
    near = neighbours[:, :LINK_REACH]
    pairs = np.sort(np.stack([np.repeat(np.arange(len(xy)), near.shape[1]), near.ravel()], 1), axis=1)
    pairs = pairs[first_of_each_cell(pairs)]  # each once, smaller first, in (first, second) order
    pairs = pairs[(xy[pairs[:, 0]] != xy[pairs[:, 1]]).any(1)]  # two points at one place have no segment
    if not len(pairs):
        return pairs, np.zeros(0)
    a = xy[pairs[:, 0]]
    step = xy[pairs[:, 1]] - a
    t = np.concatenate([EDGE_SAMPLES, END_SAMPLES])
    steady, sign, strength = np.zeros(len(pairs), bool), np.zeros(len(pairs)), np.zeros(len(pairs))
    for edge_offset in EDGE_OFFSETS:  # an edge at any of them (curved long ones far off, slivers' close to);
        todo = np.flatnonzero(~steady)  # each tried on the pairs the ones before did not pass
        if not len(todo):
            break
        offset = np.where(np.arange(len(t)) < len(EDGE_SAMPLES), edge_offset, END_OFFSET)
        difference = _across(image, a[todo], step[todo], t, offset)
        side = np.sign(difference[:, len(EDGE_SAMPLES) // 2])
        magnitude = np.abs(difference[:, : len(EDGE_SAMPLES)])
        ok = (np.sign(difference) == side[:, None]).all(1) & (magnitude.min(1) >= EDGE_EVEN * magnitude.max(1))
        ok &= np.isfinite(difference).all(1) & (side != 0)
        passed = todo[ok]
        sign[passed], strength[passed] = side[ok], np.sort(magnitude[ok], 1)[:, len(EDGE_SAMPLES) // 2]
        steady[passed] = True
    if steady.any():
        steady &= strength >= EDGE_CONTRAST * quantile(strength[steady], 0.9)
    return pairs[steady], sign[steady]


def _across(image: np.ndarray, start: np.ndarray, step: np.ndarray, t: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(P, T) grey level left minus right of each segment start + t step (P starts and steps (P, 2)),
    sampled `offset` (T,) of its length off it, at least MIN_OFFSET px; NaN off the image."""
    length = vector_lengths(step)[:, None]
    unit_normal = np.stack([-step[:, 1], step[:, 0]], 1) / length
    normal = unit_normal[:, None] * np.maximum(offset * length, MIN_OFFSET)[..., None]
    along = start[:, None] + step[:, None] * t[None, :, None]
    points = np.concatenate([along + normal, along - normal], 1).astype(np.float32)
    values = cv2.remap(image, points[..., 0], points[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=np.nan)
    return values[:, : len(t)] - values[:, len(t) :]


def kept_edges(xy: np.ndarray, pairs: np.ndarray, sign: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges both of whose corners keep them (module docstring, 2)."""
    if not len(pairs):
        return pairs, sign
    e = len(pairs)
    start = np.concatenate([pairs[:, 0], pairs[:, 1]])
    end = np.concatenate([pairs[:, 1], pairs[:, 0]])
    seen_sign = np.concatenate([sign, -sign])  # seen from the other end, left and right swap
    step = xy[end] - xy[start]
    unit = step / vector_lengths(step)[:, None]
    group = 2 * start + (seen_sign > 0)
    order = np.lexsort((vector_lengths(step), group))
    group, unit = group[order], unit[order]
    first = np.r_[True, group[1:] != group[:-1]]
    head = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))  # each row's group's first row
    away = ~first & ((unit * unit[head]).sum(1) < OPPOSITE)
    # the first row pointing away in each group: away rows ranked within their group
    rank = np.cumsum(away)
    rank_at_head = np.maximum.accumulate(np.where(first, rank - away, 0))
    second = away & (rank - rank_at_head == 1)
    keep = np.zeros(2 * e, bool)
    keep[order[first | second]] = True
    both = keep[:e] & keep[e:]
    return pairs[both], sign[both]


def linked_components(shape: tuple[int, ...], xy: np.ndarray, pairs: np.ndarray, sign: np.ndarray, min_corners: int
                      ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Corners indexed by walks along the kept edges (module docstring, 3): per component of at least
    min_corners, largest first, (corner indices (M,), (row, col) (M, 2) from 0, sign: + where the
    squares of even row + col, between (row, col) and (row + 1, col + 1), are light). shape: the
    image's (H, W, ...), where a line the frame cuts may end in a corner held by one edge."""
    adjacent: list[dict[int, int]] = [{} for _ in range(len(xy))]
    for (a, b), s in zip(pairs.tolist(), sign.tolist()):
        adjacent[a][b], adjacent[b][a] = int(s), -int(s)
    done = np.zeros(len(xy), bool)
    found = []
    for start in np.argsort([-len(a) for a in adjacent], kind="stable").tolist():
        if done[start] or len(adjacent[start]) < 2:
            continue
        for _ in range(MAX_DROPS + 1):
            cells, steps = _walk(xy, adjacent, start)
            wrong = _disagreeing(cells, steps)
            if not wrong:
                break
            for corner in wrong:  # out of the graph for good
                for other in adjacent[corner]:
                    del adjacent[other][corner]
                adjacent[corner] = {}
            if not adjacent[start]:
                break
        done[list(cells)] = True
        if wrong or len(cells) < min_corners:  # the checks below only drop corners
            continue
        cells = _confirmed(xy, shape, _steady_steps(xy, cells, steps), steps)
        if len(cells) < min_corners or not _smooth(xy, cells, steps):
            continue
        idx = np.fromiter(cells, np.int64, len(cells))
        colrow = np.array([cells[i] for i in idx.tolist()], np.int64)
        grid = colrow[:, ::-1] - colrow[:, ::-1].min(0)
        found.append((idx, grid, _light_parity(cells, steps, adjacent)))
    return sorted(found, key=lambda c: -len(c[0]))


def _walk(xy: np.ndarray, adjacent: list[dict[int, int]], start: int
          ) -> tuple[dict[int, tuple[int, int]], dict[tuple[int, int], tuple[int, int]]]:
    """A breadth-first walk from `start`: each corner's (col, row) and each edge's lattice step
    (d col, d row), its first edge taken for +col."""
    cells = {start: (0, 0)}
    steps: dict[tuple[int, int], tuple[int, int]] = {}
    queue = deque([(start, next(iter(adjacent[start])), (1, 0))])
    while queue:
        a, known, v = queue.popleft()  # a reached from `known`: the step from a to it is v
        reference, base = adjacent[a][known], xy[known] - xy[a]
        for b, s in adjacent[a].items():
            if (a, b) in steps:
                continue
            if b == known:  # the start's first edge
                w = v
            elif s == reference:
                w = (-v[0], -v[1])
            else:
                e = xy[b] - xy[a]
                w = (-v[1], v[0]) if base[0] * e[1] - base[1] * e[0] > 0 else (v[1], -v[0])
            steps[(a, b)], steps[(b, a)] = w, (-w[0], -w[1])
            if b not in cells:
                cells[b] = (cells[a][0] + w[0], cells[a][1] + w[1])
                queue.append((b, a, (-w[0], -w[1])))
    return cells, steps


def _steady_steps(xy: np.ndarray, cells: dict[int, tuple[int, int]], steps: dict[tuple[int, int], tuple[int, int]]
                  ) -> dict[int, tuple[int, int]]:
    """The corners less those of each two consecutive steps along a line where one is over
    MAX_STEP_RATIO times the other: a lens changes the squares' size by ~3x from one to the next at
    most, while a corner beside a board's outline may link to a point across the frame."""
    before, here, after = _line_triples(cells, steps)
    ratio = vector_lengths(xy[after] - xy[here]) / vector_lengths(xy[here] - xy[before])
    jump = ~((ratio >= 1 / MAX_STEP_RATIO) & (ratio <= MAX_STEP_RATIO))
    dropped = set(np.concatenate([before[jump], here[jump], after[jump]]).tolist())
    return {corner: cell for corner, cell in cells.items() if corner not in dropped}


def _line_triples(cells: dict[int, tuple[int, int]], steps: dict[tuple[int, int], tuple[int, int]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each corner with edges to its neighbours on both sides along a row or column: (before, here,
    after) corner indices (K,) each, before at (col - 1) or (row - 1)."""
    owner = {cell: corner for corner, cell in cells.items()}
    triples = []
    for corner, (col, row) in cells.items():
        for dc, dr in ((1, 0), (0, 1)):
            a, b = owner.get((col - dc, row - dr)), owner.get((col + dc, row + dr))
            if a is not None and b is not None and (a, corner) in steps and (corner, b) in steps:
                triples.append((a, corner, b))
    before, here, after = np.array(triples, np.int64).reshape(-1, 3).T
    return before, here, after


def _confirmed(xy: np.ndarray, shape: tuple[int, ...], cells: dict[int, tuple[int, int]],
               steps: dict[tuple[int, int], tuple[int, int]]) -> dict[int, tuple[int, int]]:
    """The corners held by two edges or more, dropped repeatedly as corners go: a corner hanging on
    one edge has a step nothing else confirms (at a fisheye's rim it may span corners the network
    missed, at an occluder end on its outline), unless the frame cuts its line (_cut_by_frame)."""
    next_along = {(a, step): b for (a, b), step in steps.items()}  # (corner, lattice step) -> the corner there
    kept = dict(cells)
    while True:
        edges: dict[int, list[int]] = {corner: [] for corner in kept}
        for a, b in steps:
            if a in kept and b in kept:
                edges[a].append(b)
        loose = []
        for corner, ends in edges.items():
            if len(ends) == 1:
                dc, dr = steps[(ends[0], corner)]
                if _cut_by_frame(xy, shape, corner, ends[0], next_along.get((ends[0], (-dc, -dr)))):
                    continue
            if len(ends) < 2:
                loose.append(corner)
        if not loose:
            return kept
        for corner in loose:
            del kept[corner]


def _cut_by_frame(xy: np.ndarray, shape: tuple[int, ...], corner: int, anchor: int, beyond: int | None) -> bool:
    """Whether a corner hanging on one edge, from `anchor`, ends its line at the frame: half its step
    past it lies off the image, and the step is shorter than the one from the anchor to `beyond`,
    its next corner the other way along the line (the squares shrink towards the corner, as towards
    a fisheye's rim; a longer step may span a corner)."""
    x, y = 1.5 * xy[corner] - 0.5 * xy[anchor]
    if 0 <= x <= shape[1] - 1 and 0 <= y <= shape[0] - 1:
        return False
    return beyond is not None and bool(vector_lengths(xy[corner] - xy[anchor])
                                       < vector_lengths(xy[beyond] - xy[anchor]))


def _smooth(xy: np.ndarray, cells: dict[int, tuple[int, int]], steps: dict[tuple[int, int], tuple[int, int]]
            ) -> bool:
    """Whether the component's rows and columns run smoothly: the median turn between consecutive
    edges along them at most MAX_MEDIAN_TURN degrees (a lens bends them gradually; clutter's links
    zigzag)."""
    before, here, after = _line_triples(cells, steps)
    if not len(here):
        return False
    u, v = xy[here] - xy[before], xy[after] - xy[here]
    cosine = (u * v).sum(1) / (vector_lengths(u) * vector_lengths(v))
    return bool(median(cosine) >= np.cos(np.radians(MAX_MEDIAN_TURN)))


def _disagreeing(cells: dict[int, tuple[int, int]], steps: dict[tuple[int, int], tuple[int, int]]) -> set[int]:
    """Corners on an edge whose step differs from their cells' difference, or sharing a cell."""
    wrong = set()
    for (a, b), (dc, dr) in steps.items():
        if (cells[b][0] - cells[a][0], cells[b][1] - cells[a][1]) != (dc, dr):
            wrong.update((a, b))
    owner: dict[tuple[int, int], int] = {}
    for corner, cell in cells.items():
        if cell in owner:
            wrong.update((corner, owner[cell]))
        owner[cell] = corner
    return wrong


def _light_parity(cells: dict[int, tuple[int, int]], steps: dict[tuple[int, int], tuple[int, int]],
                  adjacent: list[dict[int, int]]) -> float:
    """+1 where the squares of even row + col are light (the vote of the edges along +col: the square
    to their left, +row, is (row, col)'s)."""
    vote = 0
    for (a, b), (dc, dr) in steps.items():
        if (dc, dr) == (1, 0) and a in cells and b in adjacent[a]:
            col, row = cells[a]
            vote += adjacent[a][b] * (1 if (row + col) % 2 == 0 else -1)
    return 1.0 if vote >= 0 else -1.0
