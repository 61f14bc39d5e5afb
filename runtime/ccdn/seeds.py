"""Seed squares for ccdn.grid's search: one verified square of the lattice at each seed corner, all
seeds at once (ccdn.grid's module docstring says how seeds are chosen and tried).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .checker import MIN_CONTRAST, Sampler, altitude, quad_differences
from .lattice import SEED_AXES, SEED_REACH_UNIFORM, TOLERANCE, unsheared
from .stats import median, vector_lengths

SEED_NEIGHBOURS = 12  # a seed's square is sought among these nearest corners ...
SEED_REACH = 24  # ... and its fourth corner among these
SEED_CHUNK = 256  # seeds checked at once
FEW_SQUARES = 3  # seed squares up to this many (one seed's first round) are sampled at all 4 corners in one call:
# a call costs as much as 20-50 corners, while the seed corner alone fails ~4 in 5 of many seeds' squares (clutter)
MIN_SQUARE_PX = 3.5  # the seed square's smaller height: below it quad centres cannot be sampled


class NearQuads(NamedTuple):
    """Seed squares' quads sampled near their corners (ccdn.grid, Markers): about `inset` px from the
    corner along each step, i.e. 2 inset / the square's height of the steps, kept within low..high."""

    inset: float
    low: float
    high: float

    def steps(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lattice steps u, v (K, 2) scaled so that quads sampled with them lie near their corners."""
        share = np.clip(2 * self.inset / altitude(u, v), self.low, self.high)[:, None]  # heights >= MIN_SQUARE_PX
        return share * u, share * v


@lru_cache(maxsize=4)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), cached: the index pairs (i < j) of n neighbours."""
    i, j = np.triu_indices(n, 1)
    i.setflags(write=False)
    j.setflags(write=False)
    return i, j


def seed_squares(xy: np.ndarray, sampler: Sampler, seeds: np.ndarray, neighbours: np.ndarray,
                  free: np.ndarray, uneven: tuple[int, ...] = (0,), near: NearQuads | None = None
                  ) -> list[tuple[np.ndarray, ...]]:
    """A verified square at each seed corner, all seeds at once (neighbours (S, K): each seed's
    nearest corners, nearest first; only free ones count), for each count in `uneven` of a square's
    corners that may have non-uniform quads (0, 1 or BEHIND_UNEVEN, strictest first; find_boards):
    one sampling serves them all (a looser count's shortest passing square is among the squares
    sampled for the strictest, which samples further only for the seeds none of whose shortest passed).
    near: the corners' quads sampled near them (NearQuads; ccdn.grid.MARKER_QUADS: inside a marked
    square's light border), and without the samples along the steps (SEED_AXES), which there fall
    on the corner's own edges.

    A square is p, p + u, p + v and a fourth corner near p + u + v, with u, v from the seed's
    SEED_NEIGHBOURS nearest free corners, whose four corners pass the image test; of the passing
    bases the shortest is taken (the colour test cannot tell (u, v) from (u, v + 2u)). Returns, per
    count: found (S,), corners (S, 4) ordered (0,0), (0,1), (1,0), (1,1) with u x v > 0 (+col, +row
    like image +x, +y), the board's sign (S,) (+: quads of even row + col are light) and contrast (S,).
    """
    if len(seeds) > SEED_CHUNK:  # bounds the (seeds x pairs x neighbours) arrays
        parts = [seed_squares(xy, sampler, seeds[k : k + SEED_CHUNK], neighbours[k : k + SEED_CHUNK], free, uneven,
                              near)
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
    hypot = np.hypot(step_x, step_y)  # square_enough's lengths (hypot's last bit, not the norm's)
    longer = np.maximum(lu, lv)
    ok = (nb_valid[:, i] & nb_valid[:, j] & unsheared(cross, hypot[:, i], hypot[:, j]) & (lu < 5 * lv)
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
    axes = SEED_AXES if near is None else 0.0  # near a corner, samples along the steps fall on its own edges
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
        su, sv = uu[t], vv[t]  # the steps the quads are sampled with
        if near is not None:
            su, sv = near.steps(su, sv)
        # many squares: the seed corner alone first (passing needs its 4 quad pairs to differ one way by MIN_CONTRAST)
        if len(t) > FEW_SQUARES:
            seed_diffs, seed_spread = quad_differences(sampler, xy[square[t, 0]], su, sv, SEED_REACH_UNIFORM, axes)
            alternating = (seed_diffs.min(1) > MIN_CONTRAST) | (seed_diffs.max(1) < -MIN_CONTRAST)
            t, seed_diffs, seed_spread = t[alternating], seed_diffs[alternating], seed_spread[alternating]
            if len(t) == 0:
                continue
            su, sv = su[alternating], sv[alternating]
            diffs, spread = quad_differences(sampler, xy[square[t, 1:].ravel()], np.repeat(su, 3, 0),
                                             np.repeat(sv, 3, 0), SEED_REACH_UNIFORM, axes)
            diffs = np.concatenate([seed_diffs[:, None], diffs.reshape(-1, 3, 4)], 1)
            spread = np.concatenate([seed_spread[:, None], spread.reshape(-1, 3)], 1)
        else:  # all four corners in one call (a square that fails the seed corner's test fails `even` below)
            diffs, spread = quad_differences(sampler, xy[square[t].ravel()], np.repeat(su, 4, 0),
                                             np.repeat(sv, 4, 0), SEED_REACH_UNIFORM, axes)
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
