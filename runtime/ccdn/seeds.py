"""Seed squares for ccdn.grid's search: one verified square of the lattice at each seed corner, all
seeds at once (ccdn.grid's module docstring says how seeds are chosen and tried).

A seed square's quads must be uniform: each quad's samples range under half the square's contrast.
On a noisy frame (ccdn.checker.image_noise at least NOISY_SIGMA) they may range NOISE_RANGE x the
noise over the sampled boxes' side more: a small board's boxes are single pixels, whose noise alone
ranged over half the contrast of a low-contrast board (renders of the training distribution, seeds
5200000+ and 5300000+, 150 each: 12.53 -> 10.21 % and 11.99 -> 11.32 % of the corners missed, false
positives 14 -> 13 and 23 -> 22; on every frame, without the NOISY_SIGMA gate, a grid of thick lines
on a quiet frame passed as a board: 27 false positives; 3 x the noise: 88).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .checker import (MIN_CONTRAST, NOISY_SIGMA, PAIRS_WITHOUT, Sampler, altitude, box_radius, quad_differences,
                      quad_levels)
from .lattice import SEED_AXES, SEED_REACH_UNIFORM, TOLERANCE, unsheared
from .stats import median, vector_lengths

SEED_NEIGHBOURS = 12  # a seed's square is sought among these nearest corners ...
SEED_REACH = 24  # ... and its fourth corner among these
SEED_CHUNK = 256  # seeds checked at once
FEW_SQUARES = 3  # seed squares up to this many (one seed's first round) are sampled at all 4 corners in one call:
# a call costs as much as 20-50 corners, while the seed corner alone fails ~4 in 5 of many seeds' squares (clutter)
BEHIND_UNEVEN = 2  # corners of a seed square with non-uniform quads in ccdn.grid's last round (its module
# docstring), each of which may have one quad hidden: its three others alternate
MIN_SQUARE_PX = 3.5  # the seed square's smaller height: below it quad centres cannot be sampled
NOISE_RANGE = 1.5  # x the image noise over the sampled boxes' side: how much more a noisy frame's seed quads' samples
# may range (module docstring)
DARK_CONTRAST = 8.0  # grey levels, at least: dark_squares' contrast (light quads' lightest samples - dark medians)
DARK_SPREAD = 0.25  # x that contrast: dark_squares' dark quads' samples range less (uniform), ...
DARK_GAP = 0.4  # ... each light quad holds a sample lighter than every dark quad's lightest by this x it, ...
MARKED_SPREAD = 0.5  # ... and the light quads' samples range more than this x it (median): markers in them


class NearQuads(NamedTuple):
    """Seed squares' quads sampled near their corners (ccdn.grid, Markers): about `inset` px from the
    corner along each step, i.e. 2 inset / the square's height of the steps, kept within low..high.
    dark: the seed squares are judged by their dark quads instead (dark_squares), sampled widely: a
    marked board whose markers leave too thin a light border to sample near its corners."""

    inset: float
    low: float
    high: float
    dark: bool = False

    def steps(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lattice steps u, v (K, 2) scaled so that quads sampled with them lie near their corners."""
        share = np.clip(2 * self.inset / altitude(u, v), self.low, self.high)[:, None]  # heights >= MIN_SQUARE_PX
        return share * u, share * v


def uniform_sampling(near: NearQuads | None, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """How a seed square's quads are sampled for their uniformity at corners with lattice steps u, v
    (K, 2): the steps to sample with and the samples along them (quad_levels' axes). Near the corners
    (near given: NearQuads.steps) without the samples along the steps, which there fall on the
    corner's own edges; else widely, with them (SEED_AXES)."""
    if near is None:
        return u, v, SEED_AXES
    return (*near.steps(u, v), 0.0)


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
    on the corner's own edges; with near.dark, the squares judged by dark_squares instead.

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
    si, square, uu, vv, size = _candidate_squares(xy, seeds, neighbours, free)
    if len(si) == 0:
        return [none] * len(uneven)
    by_size = np.lexsort((size, si))  # each seed's squares, shortest first
    rank = np.empty(len(si), np.int64)
    rank[by_size] = np.arange(len(si)) - np.searchsorted(si[by_size], si[by_size])
    if near is not None and near.dark:
        return [dark_squares(sampler, xy, n_seeds, si, square, uu, vv, by_size, rank)] * len(uneven)
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
        su, sv, axes = uniform_sampling(near, uu[t], vv[t])  # the steps the quads are sampled with
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
            floor = np.maximum(MIN_CONTRAST, 0.4 * g_contrast[t])[:, None, None]
            alike = (diffs * g_sign[t][:, None]).reshape(-1, 4, 4) > floor  # (square, corner, pair)
            even = {count: (g_sign[t] != 0) & _even(alike, spread, count) for count in set(uneven)}
            if (even[max(uneven)] & ~(spreads[:, 3 - uneven[0]] < 0.5 * g_contrast[t])).any():  # only these can change
                spreads = np.maximum(spreads - _noise_allowance(sampler, su, sv)[:, None], 0)
            for level, count in enumerate(uneven):
                passed[level, t] = even[count] & (spreads[:, 3 - count] < 0.5 * g_contrast[t])
    return [_shortest_passing(n_seeds, si, square, by_size, level_passed, g_sign, g_contrast)
            for level_passed in passed]


def _even(alike: np.ndarray, spread: np.ndarray, uneven: int) -> np.ndarray:
    """(G,) whether the quads of squares' 4 corners alternate evenly (alike: (G, corner, pair), each
    quad pair differing in the square's sign by 0.4 of its contrast), with `uneven` corners allowed
    non-uniform quads (spread: (G, 4), the least uniform are those): every pair of every corner, but
    at BEHIND_UNEVEN, where the uneven corners may have one quad hidden."""
    if uneven < BEHIND_UNEVEN:
        return alike.all((1, 2))
    rows = np.arange(len(spread))[:, None]
    hidden = np.zeros(spread.shape, bool)
    hidden[rows, np.argsort(spread, 1, kind="stable")[:, 4 - uneven :]] = True  # the uneven corners
    three = alike[:, :, PAIRS_WITHOUT].all(3).any(2)  # (G, 4): the pairs without one quad alike
    return (alike.all(2) | (hidden & three)).all(1)


def _noise_allowance(sampler: Sampler, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(K,) grey levels by which the samples of a noisy frame's quads (steps u, v (K, 2)) may range more:
    NOISE_RANGE x the image noise over the side of the boxes they average (ccdn.checker.box_radius),
    on frames whose noise is at least NOISY_SIGMA, else 0."""
    sigma = sampler.noise()
    if sigma < NOISY_SIGMA:
        return np.zeros(len(u))
    return NOISE_RANGE * sigma / (2 * box_radius(u, v) + 1)


def _shortest_passing(n_seeds: int, si: np.ndarray, square: np.ndarray, by_size: np.ndarray, passed: np.ndarray,
                      sign: np.ndarray, contrast: np.ndarray) -> tuple[np.ndarray, ...]:
    """seed_squares' result for one count: each seed's shortest passing square (squares (G, 4) of seeds
    si (G,), by_size: their order by seed, then length; passed, sign, contrast: (G,) each)."""
    found, corners = np.zeros(n_seeds, bool), np.zeros((n_seeds, 4), np.int64)
    seed_sign, seed_contrast = np.zeros(n_seeds), np.zeros(n_seeds)
    best = by_size[passed[by_size]]  # passing squares by seed, shortest first
    owner = si[best]
    head = np.ones(len(best), bool)  # each seed's first (np.unique's first occurrences, without its sort)
    head[1:] = owner[1:] != owner[:-1]
    first = best[head]
    found[si[first]] = True
    corners[si[first]] = square[first]
    seed_sign[si[first]], seed_contrast[si[first]] = sign[first], contrast[first]
    return found, corners, seed_sign, seed_contrast


def _candidate_squares(xy: np.ndarray, seeds: np.ndarray, neighbours: np.ndarray, free: np.ndarray
                       ) -> tuple[np.ndarray, ...]:
    """seed_squares' candidates, before any image test: each plausible square p, p + u, p + v, p + u + v
    of a seed p (its steps u, v to two of its SEED_NEIGHBOURS nearest free corners, its fourth corner the
    free one nearest p + u + v): the seed's row (G,), the square's corners (G, 4) ordered (0,0), (0,1),
    (1,0), (1,1), u and v (G, 2) with u x v > 0, and the longer step's length (G,)."""
    valid = free[neighbours]
    rows = np.arange(len(seeds))[:, None]
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
    square = np.stack([seeds[si], a, b, fourth], 1)
    return si[keep], square[keep], uu[keep], vv[keep], size[keep]


_EVEN_QUADS = np.array([[1, 0, 0, 1], [0, 1, 1, 0], [0, 1, 1, 0], [1, 0, 0, 1]], bool)  # [corner, quad] of a seed
# square: whether the quad (quad_levels' order) is one of even row + col, at corners (0,0), (0,1), (1,0), (1,1)
_EVEN_QUADS.setflags(write=False)


def dark_squares(sampler: Sampler, xy: np.ndarray, n_seeds: int, si: np.ndarray, square: np.ndarray,
                 uu: np.ndarray, vv: np.ndarray, by_size: np.ndarray, rank: np.ndarray) -> tuple[np.ndarray, ...]:
    """seed_squares' result for a marked board whose markers leave too thin a light border to sample
    near the corners (NearQuads.dark; ccdn.grid, Markers), from the candidates of _candidate_squares
    (each seed's 3 shortest: rank; by_size their order): quads sampled widely, a square passes where
    its 8 dark quads (those of one parity: the darker by their medians) are uniform (every sample
    range under DARK_SPREAD of the contrast), its 8 light quads each hold a sample lighter than every
    dark quad's lightest by DARK_GAP of it, and those quads' samples range over MARKED_SPREAD of it
    (markers; the contrast: the light quads' lightest samples over the dark quads' medians, both
    their median, at least DARK_CONTRAST). The seed corner is judged alone first (its light quads'
    lightest samples above its dark ones')."""
    t = np.nonzero(rank < 3)[0]
    seed_levels = quad_levels(sampler, xy[square[t, 0]], uu[t], vv[t], SEED_REACH_UNIFORM, SEED_AXES)
    lightest = seed_levels[2]
    own_max, own_min = np.fmax(lightest[0], lightest[3]), np.fmin(lightest[0], lightest[3])  # the seed's parity
    other_max, other_min = np.fmax(lightest[1], lightest[2]), np.fmin(lightest[1], lightest[2])
    with np.errstate(invalid="ignore"):  # NaN: a quad off the image
        alternating = (own_max < other_min) | (other_max < own_min)  # one parity's lightest under the other's
    t = t[alternating]
    passed, sign, contrast = np.zeros(len(si), bool), np.zeros(len(si)), np.zeros(len(si))
    if len(t):
        others = quad_levels(sampler, xy[square[t, 1:].ravel()], np.repeat(uu[t], 3, 0), np.repeat(vv[t], 3, 0),
                             SEED_REACH_UNIFORM, SEED_AXES)
        middle, low, high = (np.concatenate([seed[:, alternating, None], rest.reshape(4, len(t), 3)], 2)
                             .transpose(1, 2, 0)  # (squares, corner, quad)
                             for seed, rest in zip(seed_levels, others))
        even = np.broadcast_to(_EVEN_QUADS, middle.shape)
        even_darker = (median(middle[even].reshape(len(t), 8), axis=1)
                       < median(middle[~even].reshape(len(t), 8), axis=1))
        dark = np.where(even_darker[:, None, None], even, ~even)
        dark_middle, dark_low, dark_high = (part[dark].reshape(len(t), 8) for part in (middle, low, high))
        light_low, light_high = (part[~dark].reshape(len(t), 8) for part in (low, high))
        gap = median(light_high, axis=1) - median(dark_middle, axis=1)
        with np.errstate(invalid="ignore"):
            passed[t] = ((gap > DARK_CONTRAST) & ((dark_high - dark_low).max(1) < DARK_SPREAD * gap)
                         & (light_high.min(1) > dark_high.max(1) + DARK_GAP * gap)
                         & (median(light_high - light_low, axis=1) > MARKED_SPREAD * gap))
        sign[t], contrast[t] = np.where(even_darker, -1.0, 1.0), gap
    return _shortest_passing(n_seeds, si, square, by_size, passed, sign, contrast)
