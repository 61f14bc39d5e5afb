"""Grid recovery: unordered corners -> boards with (row, col) indices, without knowing the board size.

How: seeds are tried in order of score, first the corners whose surroundings look like a checker
corner (on a small ring around it the grey level alternates twice: the ring's second angular
harmonic beats its first, as it does not at an edge or a T-junction), then at most 200 others (a
cheap filter that keeps clutter from costing a seed attempt per point). A seed is a corner p with
two neighbours p + u, p + v whose sum p + u + v is also a corner (one square of the lattice) and
whose four corners pass the image test (ccdn.growth), with uniform grey inside each sampled quad, sampled
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
boards the shrunk passes find: extreme pose 18 -> 64 missed). Each such corner may have one quad
hidden, its three others alternating (ccdn.seeds.BEHIND_UNEVEN): the front board's light margin over
a dark quad of the one behind (stress two-boards render 7120536: a piece of 6 corners below the front
board found, indexed as it is; ~1780 cached frames of every other kind the same). The boards this
round finds are grown again once the earlier boards are bridged, and bridged in turn: seeded here, a
piece of a back board grew into a board of its own, where the back board, grown from elsewhere,
bridged to it before (fresh render 7122551: 81 corners -> 69 and 8).
The board then grows from the seed square (ccdn.growth: ring-at-once while it looks flat, then
position by position, each corner passing the image test; completing, also from the image:
ccdn.completion) and is cleaned up (ccdn.cleanup: sharp turns, lone points on its outline, stubs,
a seam between two boards grown into one). A grid of at least 2 x 3 positions and 8 corners is a
board (two rows or columns: the strip of a board that another hides; 3 x 3 before, which lost two
such strips of 9 and 18 corners in the four stress samples' 1440 renders and changed nothing else
there, on real-dev or its perturbed photos), or of MIN_PIECE (6) corners where the search also
finds a board of 8 (a piece of a board behind another: on its own too small to tell from clutter)
or where it is a close-up (_close_up: squares too large for clutter to pass for), and each of its
corners lies where the lattice of the others puts it (ccdn.lattice); its corners are removed and
the search repeats for further boards. Once no seed is left, each board takes its pieces beyond a
gap (another board or an occluder in front of it) among the corners no board holds (ccdn.bridging),
and only then are the pieces grown again from their seed squares, where these are still free (grown
during the search, a piece of the board behind another kept 6 corners that board, grown later,
would have reached and gone on from: a fresh two-boards render, 7122551, lost 6 corners).
Corners in no board are dropped, and no corner closer than EDGE_MARGIN to the frame's edge joins
one (where the frame cuts a board's outline, its one visible quad pair alternates like a corner's).

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

Markers (the detector's shrunk and full-frame passes): a ChArUco-style board holds a marker in each light
square, 0.6-0.8 of its side, whose bits make those quads anything but uniform, so no seed square
passes and the board is lost although the network finds its corners. Where the search (and the
levelled one) finds no board, it runs once more with the seed squares' quads sampled near their
corners (MARKER_QUADS), inside the markers' light border, where every quad is uniform again
(without the samples along the steps, which there fall on the corner's own edges),
and with the corner-like seeds only (the plain ones found no more on marked boards and cost a
boardless 2000x1500 frame 20 ms). Growth's own image test passes such corners as they are, but
for its crowded corners' uniform quads (ccdn.growth: every corner of a marked board is crowded, the
markers' own corners lying within its cells), which it then samples near them too (stress renders
with markers: 28.8 -> 11.6 % missed, held out 10.3 -> 2.1 % and 13.8 -> 6.2 %, a board falling
apart into pieces before; their mean error 0.03-0.06 -> 0.05-0.06 px; fisheye close-ups, which the
same search finds, 3-5 corners fewer missed; ~1800 other cached renders bit for bit the same). A
board so found is kept only where its light quads do hold markers (_marked: their samples range
much more than its dark quads', less where those are clean: MARKED_CLEAN, stress renders with
markers 11.6 -> 4.6 % missed, 4.5 -> 3.9 % held out, OpenCV's ChArUco images 44 -> 45 of 54 boards,
no plain board more); a plain board it finds (e.g. one whose seed squares an occluder spoils) took
outline points with it. Only frames where nothing else is found can change (stress
renders with markers, ccdn_training.synth's p_markers: 86 -> 29 % missed, held out 74-77 -> 10-12 %;
OpenCV's ChArUco images: 21 -> 34 of 54 boards at 640x480, 3 -> 9 of 9 at 2000x1500; every frame
with a board found before the same). Where markers leave a light border of a pixel or two (small
squares, or markers of 0.7-0.8 of the square), no quad sampled near a corner is uniform either: where
that search finds no board, it runs once more with seed squares judged by their dark quads
(MARKER_DARK, ccdn.seeds.dark_squares; stress renders with markers: held out 2.1 -> 1.7 % and 6.2 ->
4.5 % missed, no false positive; OpenCV's ChArUco images 34 -> 44 of 54 boards; ~2400 other cached
renders and frames bit for bit the same; boardless frames spend 4-6 % of their time on it). On the
full frame that search also takes the saddle fits that failed, retried from their peaks' diagonal
neighbours (find_boards' more; ccdn.refine.refine_from_neighbours): a corner between two pixels
whose peak lies on its light side, where the fit's window reaches a marker's border 2-3 px in
(OpenCV's markers of 0.8 on 25 px squares: every other corner of the board), converges from the
dark side (OpenCV's ChArUco images 45 -> 48 of 54 boards, stress renders with markers 4.6 / 1.7 /
3.9 -> 2.1 / 1.6 / 3.5 % missed; only this search takes them: in the plain one such retried fits,
most of them on clutter, took the place of corners completion fits right on steep boards). Where neither
finds a board, a last round seeks seed squares among the corner-like points alone (ccdn.checker.x_like),
from the seeds whose SEED_NEIGHBOURS nearest that changes: on a small marked board the network scores
its markers' own corners too, most of them not corner-like, and they outnumbered a corner's lattice
neighbours among its nearest points (stress render 7170287: 19 of 116 lattice neighbours not even among
the SEED_REACH nearest, the board lost whole; found whole now, 35 corners; 80 fresh renders with markers:
one board more, 13 of 21 corners, rightly indexed, nothing lost; ~1780 cached frames of every other kind
bit for bit the same). Failed fits that converge from no diagonal
neighbour are fitted once more from their peak with the narrowest window (ccdn.refine.NARROW_RADIUS):
markers of 0.8 of small squares leave a light border of a pixel or two, which the usual window
reaches (render 7170081: 16 of its 40 corners). These join growth alone, neither seeds nor a seed
square's corners: taken there too, they changed the seed squares found and lost boards whole (7170163,
7170287). Stress renders with markers, the four samples: 124 -> 86 of 5045 corners missed; 80 fresh
ones: 99 -> 71 of 5197; none lost, no false positive, none of 159 boards wrongly indexed; their hits
0.059 -> 0.062 px off the truth (mean), 69 -> 83 of them over 0.5 px; ~1780 cached frames of every
other kind bit for bit the same. A boardless frame, which runs these rounds, takes 6-8 % longer for them
(README, Latency). The same search finds
close-ups: a few squares filling the
frame, whose size perspective changes from one square to the next, so that the plain search's quads,
sampled widely with one square's steps, cross into other squares; a plain board it finds is kept
where its largest squares span over CLOSE_UP of the frame's shorter side (_close_up), where close_ups is
asked for (the detector's full-frame pass: on a shrunk pass, a piece of a fisheye close-up so found
stopped the full frame's pass, which found the whole board; stress close-up renders, squares of
100-200 px at 640x480: 12.4 -> 1.9 % missed, no false positive; every other render the same).

Close-ups linked (close_ups: the detector's full-frame pass): through a fisheye lens a close-up's
squares shrink from over 100 px at the centre to a few px at the rim within a few rows, faster than
growth's predictions follow, and such boards were found in pieces or not at all although the
network scores their corners. Where at least MIN_CORNERS corners are in no board (or any is, and a
board found is a close-up: growth found part of it), the corners are also linked along the board's
edges (ccdn.linked: no prediction, each pair of neighbours tested for an edge between them), and
each close-up so linked, judged by its longest step (_close_up: a fisheye close-up's many rim steps
can keep its longest tenth short), replaces the boards it shares corners with where it holds more
corners than they do together (stress fisheye close-up renders at 640x480, the first 40: 42.1 ->
7.6 % missed, 80 more: 44.1 -> 8.5 %, boards wrongly indexed 2 -> 0, false positives 0 -> 1;
close-ups, the first 40: 1.9 -> 1.7 %, 80 more: 2.22 -> 0.97 %; ~1800 cached frames of every other
kind bit for bit the same).

The boards' indices are oriented as ccdn.board says.

Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from .board import Board, checked_size, fitted_grid, indexed_board, largest_first, reoriented
from .checker import Sampler, quad_levels, x_like
from .edges import lattice_steps, median_step
from .growth import Grower
from .lattice import SEED_AXES, SEED_REACH_UNIFORM, distances, each_where_the_others_put_it, inside_margin
from .linked import edge_pairs, kept_edges, linked_components
from .seeds import BEHIND_UNEVEN, SEED_CHUNK, SEED_NEIGHBOURS, SEED_REACH, NearQuads, seed_squares
from .shade import LightEnvelope, levelled, light_envelope, light_levels, light_spread, points_light_spread
from .stats import median, quantile, vector_lengths

MIN_CORNERS = 8
MIN_PIECE = 6  # corners a board may hold beside one of MIN_CORNERS or as a close-up (module docstring)
MIN_EXTENT = 2  # rows and columns a board spans, at least: a strip of a board behind another (module docstring)
MAX_PLAIN_SEEDS = 200  # seeds tried among the corners that fail the ring test
SAME_CORNER_PX = 1.0  # a free corner this close to one a board completed from the image is that corner
MARKER_QUADS = NearQuads(3.0, 0.1, 0.15)  # where the search for a marked board samples seed squares' quads: ~3 px
# from the corner along each step, 0.1-0.15 of the steps (squares over 40 px: 0.15 reached the markers of 0.8 of the
# square on 145 px squares; under 40 px: nearer than 0.15 the squares' edges blur the samples)
MARKER_DARK = MARKER_QUADS._replace(dark=True)  # ... and, where that search finds no board, seed squares judged by
# their dark quads (ccdn.seeds.dark_squares), growth's crowded corners still near them
CLOSE_UP = 0.15  # of the frame's shorter side: a plain board the marker search finds is kept where the longest tenth
# of its lattice steps are longer (_close_up). Boards of 88-192 px squares at 640x480, 8-13 corners in view, their
# perspective changing the squares' size from one to the next (renders with squares of 100-200 px): the seed squares'
# wide samples crossed into other squares. The plain boards that search found in ~3000 stress renders: steps of 15-55
# px (median), 16-57 px (the longest tenth), and there (7141597) 2 false outline points. Through a fisheye lens the
# squares of a close-up thin towards the rim: the longest tenth of the steps, not the median, tells it (40 fisheye
# close-up renders of squares 100-200 px at the centre, seeds 9 000 000 on: 65.3 -> 47.2 % missed)
MARKED = 0.5  # a board found so holds markers where its light quads' samples range this much more than its dark ones'
# (of their contrast; _marked), ...
MARKED_CLEAN = 0.4  # ... or this much where its dark quads are clean: their samples range under CLEAN_DARK of it.
CLEAN_DARK = 0.05  # Of the 114 marked boards the marker search found in 140 renders with markers, the lowest at
# 0.46 and 0.50 (small squares, whose boxes average a marker's bits; a steep board of faint markers), every one's
# dark quads under 0.03; of the 362 plain boards it found (close-ups, fisheye close-ups, ~2000 stress renders), the
# highest 0.49, 0.43, 0.42 (their dark quads 0.70, 0.11, 0.50: samples across other squares), of those with clean
# dark quads 0.27
SAMPLED_REACH = 4.0  # x the corners' median gap: how far around them find_boards' Sampler integrates the image
# (ccdn.checker.Sampler; real-dev frames at 4000x3000: 12.3 -> 6.0 Mpx a frame; 2 and 3 grew the window more often)
SHADE_SPREAD = 2.0  # a board lit more unevenly (ccdn.shade.light_spread) is searched for again, levelled: 1.5 found
# the same corners on shadow renders; every board (0) 7 more of 6427, for a second search on every frame
LINK_BLUR = 0.8  # px: the Gaussian the image is smoothed with before corners are linked along its edges (ccdn.linked)
def _sampled_squares(xy: np.ndarray, sampler: Sampler, seeds: np.ndarray, neighbours: np.ndarray, free: np.ndarray,
                     sampled: dict[int, list[tuple[np.ndarray, tuple[np.ndarray, ...]]]], levels: tuple[int, ...],
                     near: NearQuads | None) -> tuple[tuple[np.ndarray, ...], dict[int, int]]:
    """A later round's squares (levels[0] uneven corners) of the free `seeds` and each seed's row in
    them: those the earlier rounds sampled since the last board was grown (sampled[levels[0]]:
    (seeds, their squares)) as they are, the others sampled now, at all the `levels` still to come
    (their squares at the further levels go to `sampled` too)."""
    fresh = list(sampled[levels[0]])
    known = np.zeros(len(xy), bool)
    for ahead, _ in fresh:
        known[ahead] = True
    if not known[seeds].all():
        stale = seeds[~known[seeds]]
        fresh.append((stale, _sample_ahead(xy, sampler, stale, neighbours, free, sampled, levels, near)))
    ahead = np.concatenate([a for a, _ in fresh])
    squares = tuple(np.concatenate(parts) for parts in zip(*(q for _, q in fresh)))
    return squares, dict(zip(ahead.tolist(), range(len(ahead))))  # a seed sampled twice: its last row


def _sample_ahead(xy: np.ndarray, sampler: Sampler, seeds: np.ndarray, neighbours: np.ndarray, free: np.ndarray,
                  sampled: dict[int, list[tuple[np.ndarray, tuple[np.ndarray, ...]]]], levels: tuple[int, ...],
                  near: NearQuads | None) -> tuple[np.ndarray, ...]:
    """The squares of `seeds` at levels[0] uneven corners (seed_squares, their quads sampled `near`
    their corners where given); their squares at the further `levels`, from the same sampling, go to
    `sampled` for the rounds to come."""
    now, *later = seed_squares(xy, sampler, seeds, neighbours[seeds], free, levels, near)
    for level, squares in zip(levels[1:], later):
        sampled[level].append((seeds, squares))
    return now


def _grow_board(xy: np.ndarray, free: np.ndarray, sampler: Sampler, gray: np.ndarray | None, added: list,
                square: list, gaps: np.ndarray, score: np.ndarray, near: NearQuads | None) -> Grower | None:
    """The board grown from a verified seed square (seed_squares' found, corners, sign, contrast) over
    the free corners (gray given: with completion; `added`: corners earlier boards completed; gaps: each
    corner's distance to its nearest; score: their network scores; near: how the seed squares' quads
    were sampled, and growth's crowded corners' too), pruned, vouched for and trimmed; None when it
    is smaller than MIN_PIECE or MIN_EXTENT, or is a piece (under MIN_CORNERS) with a corner off the
    lattice of the others (ccdn.lattice.each_where_the_others_put_it)."""
    occupied = np.concatenate([xy[~free], np.reshape(added, (-1, 2))])
    grower = Grower(xy, free, sampler, gaps, gray, len(xy) + len(added), occupied, score, near)
    grower.seed(square[1], float(square[2]), float(square[3]))
    grower.grow()
    grower.unkink()
    grower.prune()
    grower.vouch()
    grower.trim_outline()
    grower.split_at_bridge()
    grid, idx = grower.cells()
    if len(idx) < MIN_PIECE or (grid.max(0) - grid.min(0) + 1).min() < MIN_EXTENT:
        return None
    if len(idx) < MIN_CORNERS and not each_where_the_others_put_it(grid[:, ::-1].astype(np.float64),
                                                                    grower.points(idx)):
        return None
    return grower


def _take_board(grower: Grower, xy: np.ndarray, free: np.ndarray, added: list, growers: list[Grower]) -> None:
    """The grown board's corners taken from `free` (and the free ones at its completed corners:
    _cover_completed); the board joins `growers`, and its completed corners `added`, unless it is a
    grid of lines (ccdn.cleanup), which still owns its corners, as a board of another size does."""
    idx = grower.cells()[1]
    free[idx[idx < len(xy)]] = False
    _cover_completed(free, xy, grower.points(idx[idx >= len(xy)]))
    if not grower.line_grid():
        added.extend(grower.added)
        growers.append(grower)


def _cover_completed(free: np.ndarray, xy: np.ndarray, completed: np.ndarray) -> None:
    """Mark the free corners within SAME_CORNER_PX of a board's `completed` corners (its fits from the
    image) as taken: the same corners, which growth's test refused (on a marked board, the markers'
    own corners crowd them) and completion then fitted; left free, a later board took them twice."""
    if len(completed) and free.any():
        candidates = np.nonzero(free)[0]
        free[candidates[distances(xy[candidates], completed).min(1) < SAME_CORNER_PX]] = False


def _bridge_leftovers(growers: list[Grower], free: np.ndarray) -> None:
    """Once the search is done, each board in turn takes its pieces beyond a gap among the corners no
    board holds (ccdn.bridging); `free` follows. Done during the search, a board took 3 corners of a
    like-posed board beside it, on its lattice by chance, before that board was found; and growing
    on from the pieces it took, a board took a point on the outline of the board in front of it."""
    n = len(free)
    for grower in growers:
        grower.free = free.copy()
        if grower.bridge():
            idx = grower.cells()[1]
            free[idx[idx < n]] = False


def nearest_neighbours(xy: np.ndarray, k: int, among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each point's min(k, M - 1) nearest other points among the M points `among` marks ((N,) bool;
    default: all), nearest first: indices into xy (N, k) and squared distances (N, k). Distances come
    from one matrix product per block of 256 rows (|a|^2 + |b|^2 - 2 a.b), so memory stays O(N) per
    block and time is a small fraction of the direct form's."""
    own = (xy**2).sum(1)
    ids = None if among is None or among.all() else np.nonzero(among)[0]  # None: all points, no mapping
    others, norms = (xy, own) if ids is None else (xy[ids], own[ids])
    k = min(k, len(others) - 1)
    index, dist2 = np.empty((len(xy), k), np.int64), np.empty((len(xy), k))
    for start in range(0, len(xy), 256):
        block = slice(start, start + 256)
        d2 = xy[block] @ others.T  # in place from here: temporaries of this size cost more than the arithmetic
        d2 *= -2
        d2 += norms[None]
        d2 += own[block, None]
        if ids is None:
            d2.ravel()[start :: len(xy) + 1] = np.inf  # each row's own point: its diagonal
        else:
            d2[ids[None] == np.arange(len(xy))[block, None]] = np.inf
        part = d2.argmin(1)[:, None] if k == 1 else np.argpartition(d2, k - 1, axis=1)[:, :k]
        d2 = np.take_along_axis(d2, part, 1)
        order = np.argsort(d2, axis=1, kind="stable")
        nearest = np.take_along_axis(part, order, 1)
        index[block] = nearest if ids is None else ids[nearest]
        dist2[block] = np.maximum(np.take_along_axis(d2, order, 1), 0)
    return index, dist2


def find_boards(gray: np.ndarray, xy: np.ndarray, score: np.ndarray, board_size: tuple[int, int] | None = None,
                *, allow_partial: bool = False, complete: bool = False, uneven_seeds: int = 0,
                shade_unfound: bool = False, markers: bool = False, close_ups: bool = False,
                more: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None) -> tuple[Board, ...]:
    """Link corners into checkerboards: the boards found, largest first (ties: top, then left).

    gray: (H, W) uint8 image the corners come from. xy: (N, 2) corner positions (x, y), (0, 0) the
    centre of the top-left pixel; score: (N,) confidences (seeds are tried best first).
    board_size: (cols, rows) inner corners; if given, only boards of that size (either way round,
    re-indexed to cols x rows; one line too wide where clutter along the outline continues the
    pattern: cut to it, ccdn.board.fitted_grid) are returned, or also smaller ones that fit it when
    allow_partial (their indices then start at 0 where the found part starts); anything but two whole
    numbers of at least 2 is a ValueError. The indices' orientation: ccdn.board's module docstring.
    complete: also take corners the image shows where the grid predicts one that xy lacks
    (ccdn.completion); their corner_index is >= len(xy), their position in Board.xy.
    uneven_seeds: how many corners of a seed square may have non-uniform quads (0 or 1) before the last round
    (module docstring). shade_unfound (with complete): where no board is found, also search the
    levelled frame when the corner-like points lie in uneven light (module docstring, Shade).
    markers: where no board is found, search again for a board with markers in its light squares
    (module docstring, Markers); close_ups (with markers): keep the plain boards of close-ups that
    search finds too, and link corners along their edges for the close-ups growth missed (module
    docstring, Close-ups linked). more (with markers): corners (xy, score, unseeded) that search may use
    besides xy, asked for only when it runs (the detector's failed saddle fits retried: module
    docstring, Markers), those `unseeded` marks ((K,) bool) for growth alone, neither seeds nor a seed
    square's corners; the boards' corner_index past len(xy) then names these too, their positions in
    Board.xy.
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be a 2-D uint8 image, got shape {gray.shape} dtype {gray.dtype}")
    board_size = checked_size(board_size)
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    score = np.asarray(score, np.float64).reshape(-1)
    if len(score) != len(xy):
        raise ValueError(f"xy has {len(xy)} rows but score has {len(score)}")
    n = len(xy)
    if n < MIN_PIECE:
        return ()
    neighbours, dist2 = nearest_neighbours(xy, SEED_REACH)
    gaps = np.sqrt(dist2[:, 0])
    sampler = Sampler(gray, (xy, SAMPLED_REACH * median(gaps)))
    boards = _search(gray, sampler, xy, score, neighbours, gaps, board_size, allow_partial, complete, uneven_seeds)
    square = envelope = None
    if complete and boards:
        square = _shaded_square(gray, sampler, boards)
    elif complete and shade_unfound and (unlit := _unlit_square(gray, xy, gaps)) is not None:
        square, envelope = unlit
    if square is not None:
        # a board under a shadow: the search again on the frame with its light levelled (ccdn.shade), kept
        # where it finds more corners
        flat = levelled(gray, square, envelope)
        again = _search(flat, Sampler(flat), xy, score, neighbours, gaps, board_size, allow_partial, complete,
                        uneven_seeds)
        if sum(map(len, again)) > sum(map(len, boards)):
            boards = again
    if markers and not boards:  # a ChArUco-style board or a close-up (module docstring, Markers)
        marker_xy, marker_score, marker_neighbours, marker_gaps = xy, score, neighbours, gaps
        seedable = np.ones(len(xy), bool)
        if more is not None and len((extra := more())[0]):  # this search's corners besides xy (more)
            marker_xy, marker_score = np.concatenate([xy, extra[0]]), np.concatenate([score, extra[1]])
            seedable = np.concatenate([seedable, ~extra[2]])
            marker_neighbours, dist2 = nearest_neighbours(marker_xy, SEED_REACH, seedable)
            marker_gaps = np.sqrt(dist2[:, 0])
        corner_like = x_like(gray, marker_xy, marker_gaps) & seedable  # every round's seeds (plain_seeds=0)
        for quads in (MARKER_QUADS, MARKER_DARK):  # the dark squares' seeds where the others find no board
            found = _search(gray, sampler, marker_xy, marker_score, marker_neighbours, marker_gaps, board_size,
                            allow_partial, complete, uneven_seeds, quads, plain_seeds=0, corner_like=corner_like)
            if found:
                break
        else:  # seed squares among the corner-like points alone (module docstring, Markers)
            like, crowded = _corner_like_neighbours(marker_xy, corner_like, marker_neighbours)
            if crowded.any():
                found = _search(gray, sampler, marker_xy, marker_score, like, marker_gaps, board_size, allow_partial,
                                complete, uneven_seeds, MARKER_QUADS, plain_seeds=0, corner_like=crowded)
        boards = tuple(board for board in found
                       if _marked(sampler, board) or (close_ups and _close_up(board, gray.shape)))
    if close_ups:
        boards = _with_linked_close_ups(gray, xy, neighbours, boards, board_size)
    return boards


def _with_linked_close_ups(gray: np.ndarray, xy: np.ndarray, neighbours: np.ndarray, boards: tuple[Board, ...],
                           board_size: tuple[int, int] | None) -> tuple[Board, ...]:
    """The boards with each close-up (_close_up) that linking corners along their edges finds
    (ccdn.linked) in place of the boards it shares corners with, where it holds more corners than
    they do together (module docstring, Close-ups linked). Only where MIN_CORNERS corners are in no
    board, or any is and a board is a close-up."""
    taken = np.zeros(len(xy), bool)
    for board in boards:
        taken[board.corner_index[board.corner_index < len(xy)]] = True
    left = int((~taken).sum())
    if left < MIN_CORNERS and not (left and any(_close_up(board, gray.shape) for board in boards)):
        return boards
    image = cv2.GaussianBlur(gray, (0, 0), LINK_BLUR).astype(np.float32)
    pairs, sign = edge_pairs(image, xy, neighbours)
    inside = inside_margin(xy, gray.shape)[pairs].all(1)  # a corner at the frame's edge is in no board
    pairs, sign = kept_edges(xy, pairs[inside], sign[inside])
    kept, changed = list(boards), False
    for idx, grid, light in linked_components(gray.shape, xy, pairs, sign, MIN_CORNERS):
        board = reoriented(indexed_board(idx, grid, xy[idx]), light, board_size)
        if board is None or min(board.cols, board.rows) < MIN_EXTENT or not _close_up(board, gray.shape, 1.0):
            continue
        mine = np.zeros(len(xy) + 1, bool)  # a board's completed corners (index >= len(xy)) fall on the last slot
        mine[idx] = True
        overlapping = [b for b in kept if mine[np.minimum(b.corner_index, len(xy))].any()]
        if len(board) > sum(map(len, overlapping)):
            kept, changed = [b for b in kept if not any(b is o for o in overlapping)] + [board], True
    return tuple(largest_first(kept)) if changed else boards


def _close_up(board: Board, shape: tuple[int, ...], largest: float = 0.9) -> bool:
    """Whether a board's largest squares (the `largest` quantile of its lattice steps' lengths) span
    more than CLOSE_UP of the frame's shorter side: a close-up view (module docstring, Markers)."""
    lengths = vector_lengths(lattice_steps(board))
    return quantile(lengths[np.isfinite(lengths)], largest) > CLOSE_UP * min(shape[:2])  # np.quantile imports numpy.ma


def _marked(sampler: Sampler, board: Board) -> bool:
    """Whether a board's light squares hold markers: over its corners (median), the range of the
    samples inside its light quads, less that inside its dark quads, exceeds MARKED of the contrast
    between them, MARKED_CLEAN where the dark quads' samples range under CLEAN_DARK of it (a seed's
    samples: ccdn.checker.quad_levels; the light quads are those whose lightest samples are
    lighter). A plain board's quads are all uniform: ~0."""
    steps = lattice_steps(board)[:, [0, 2]]  # +col, +row
    stepped = np.isfinite(steps).all((1, 2))  # NaN: no neighbour along a row or a column
    _, low, high = quad_levels(sampler, board.xy[stepped].astype(np.float64), steps[stepped, 0], steps[stepped, 1],
                               SEED_REACH_UNIFORM, SEED_AXES)
    spread = high - low  # (4 quads, K): own-parity quads 0 and 3, the others 1 and 2
    own, other = high[[0, 3]].mean(0), high[[1, 2]].mean(0)
    own_spread, other_spread = spread[[0, 3]].mean(0), spread[[1, 2]].mean(0)
    light = own > other
    light_spread, dark_spread = np.where(light, own_spread, other_spread), np.where(light, other_spread, own_spread)
    known = np.isfinite(light_spread - dark_spread)
    if not known.any():
        return False
    excess, contrast = median((light_spread - dark_spread)[known]), median(np.abs(own - other)[known])
    return bool(excess > (MARKED_CLEAN if median(dark_spread[known]) < CLEAN_DARK * contrast else MARKED) * contrast)


def _corner_like_neighbours(xy: np.ndarray, corner_like: np.ndarray, neighbours: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Each corner's SEED_REACH nearest among the corner-like ones (corner_like: (N,) bool, the seeds),
    and the seeds whose SEED_NEIGHBOURS nearest that changes (a search with the `neighbours` given has
    tried the others): a marked board's corners crowded by its markers' own (module docstring,
    Markers)."""
    if corner_like.sum() < 4:  # no seed square
        return neighbours, np.zeros(len(xy), bool)
    like = nearest_neighbours(xy, SEED_REACH, corner_like)[0]
    n = min(SEED_NEIGHBOURS, neighbours.shape[1])
    if like.shape[1] < n:  # fewer corner-like corners than that: every seed's change
        return like, corner_like
    return like, corner_like & (like[:, :n] != neighbours[:, :n]).any(1)


def _shaded_square(gray: np.ndarray, sampler: Sampler, boards: tuple[Board, ...]) -> float | None:
    """The median lattice step (px) of the first board lit more unevenly than SHADE_SPREAD
    (ccdn.shade.light_spread), None when none is."""
    for board in boards:
        steps = lattice_steps(board)
        if light_spread(light_levels(gray, board.xy.astype(np.float64), steps, sampler)) > SHADE_SPREAD:
            return median_step(steps)
    return None


def _unlit_square(gray: np.ndarray, xy: np.ndarray, gaps: np.ndarray) -> tuple[float, LightEnvelope] | None:
    """The median gap (px) of the corner-like points (ccdn.checker.x_like) among corners xy with
    their `gaps`, and gray's light level for squares that size (ccdn.shade.light_envelope, which
    levelling the frame takes up), where at least MIN_CORNERS of them are lit more unevenly than
    SHADE_SPREAD (ccdn.shade.points_light_spread); None otherwise."""
    corner_like = x_like(gray, xy, gaps)
    if corner_like.sum() < MIN_CORNERS:
        return None
    square = float(median(gaps[corner_like]))
    envelope = light_envelope(gray, square)
    return (square, envelope) if points_light_spread(envelope, xy[corner_like]) > SHADE_SPREAD else None


def _search(gray: np.ndarray, sampler: Sampler, xy: np.ndarray, score: np.ndarray, neighbours: np.ndarray,
            gaps: np.ndarray, board_size: tuple[int, int] | None, allow_partial: bool, complete: bool,
            uneven_seeds: int, near: NearQuads | None = None, plain_seeds: int = MAX_PLAIN_SEEDS,
            corner_like: np.ndarray | None = None) -> tuple[Board, ...]:
    """find_boards' search on `gray` (sampled by `sampler`) for corners xy with their nearest
    neighbours (nearest_neighbours) and gaps (distance to the nearest); near: seed squares' quads
    sampled near their corners (seed_squares); plain_seeds: how many seeds to try among the corners
    that fail the ring test (module docstring); corner_like: (N,) bool, the seeds that pass it
    where the caller knows them (e.g. some of them only; default: checker.x_like on xy)."""
    order = np.lexsort((xy[:, 0], xy[:, 1], -score))
    corner_like = (x_like(gray, xy, gaps) if corner_like is None else corner_like)[order]
    seeds = np.concatenate([order[corner_like], order[~corner_like][:plain_seeds]])
    free = inside_margin(xy, gray.shape)  # corners at the frame's edge are in no board
    growers: list[Grower] = []
    added: list[np.ndarray] = []
    pieces: list[list] = []  # the seed squares of boards under MIN_CORNERS ...
    behind: list[list] = []  # ... and of the last round's boards: both grown again once the boards are bridged
    claimed = np.zeros(len(xy), bool)  # the corners of the last round's boards (their seeds are not tried again)

    def grow(square: list) -> Grower | None:
        """The board grown from a seed square over the corners free now (_grow_board)."""
        return _grow_board(xy, free, sampler, gray if complete else None, added, square, gaps, score, near)

    # strict seed squares first; squares with uneven corners only among the seeds left when they are done
    # (tried first, they changed the boards the strict ones find: a fisheye board seeded elsewhere grew less);
    # squares with BEHIND_UNEVEN uneven corners last, once a board is found (module docstring)
    grown = False
    levels = (*range(uneven_seeds + 1), BEHIND_UNEVEN)
    # each later round's squares, sampled ahead with an earlier round's (one sampling serves every count:
    # seed_squares) since the last board grew: (seeds, their squares) per count
    sampled: dict[int, list[tuple[np.ndarray, tuple[np.ndarray, ...]]]] = {level: [] for level in levels[1:]}
    for round_index, uneven in enumerate(levels):
        last = uneven == BEHIND_UNEVEN
        if last and not (grown and free[seeds].any()):
            break
        batch: dict[int, int] = {}  # seed -> its row in squares, checked in growing batches of the free seeds
        size = 1 if uneven == 0 else SEED_CHUNK
        if uneven != 0 and free[seeds].any():  # the earlier rounds sampled this round's squares too, since the
            # last board grew
            squares, batch = _sampled_squares(xy, sampler, seeds[free[seeds]], neighbours, free, sampled,
                                              levels[round_index:], near)
        for k, s in enumerate(seeds.tolist()):
            if not free[s] or claimed[s]:
                continue
            if s not in batch:
                ahead = seeds[k:][free[seeds[k:]] & ~claimed[seeds[k:]]][:size]
                size = min(4 * size, SEED_CHUNK)  # the first seed usually finds the board
                squares = _sample_ahead(xy, sampler, ahead, neighbours, free, sampled, levels[round_index:], near)
                batch = dict(zip(ahead.tolist(), range(len(ahead))))
            square = [part[batch[s]] for part in squares]
            if square[0] and not free[square[1]].all():  # a board took some of its corners: look again
                square = [part[0] for part in seed_squares(xy, sampler, seeds[k : k + 1], neighbours[s][None], free,
                                                            (uneven,), near)[0]]
            grower = grow(square) if square[0] else None
            if grower is None:
                continue
            idx = grower.cells()[1]
            if len(idx) < MIN_CORNERS:  # a piece (module docstring)
                pieces.append(square)
                continue
            if last:  # a board behind another (module docstring)
                behind.append(square)
                claimed[idx[idx < len(xy)]] = True
                continue
            grown = True
            for parts in sampled.values():  # sampled while the board's corners were free: `free` changes only here
                parts.clear()
            _take_board(grower, xy, free, added, growers)
            batch, size = {}, SEED_CHUNK  # the rest is mostly clutter: one batch, checked against what is free now
    _bridge_leftovers(growers, free)
    # the boards behind others, bridged in turn, then the pieces: grown first, one kept corners a board grows
    # through (module docstring)
    for squares, bridged in ((behind, True), (pieces, False)):
        late: list[Grower] = []
        for square in squares:
            if free[square[1]].all() and (grower := grow(square)) is not None:
                _take_board(grower, xy, free, added, late)
        if bridged:
            _bridge_leftovers(late, free)
        growers += late
    points = np.concatenate([xy, np.reshape(added, (-1, 2))])
    found = []
    for grower in growers:
        grid, idx = grower.cells()
        fitted = fitted_grid(grid, grower.points(idx), grower.sign, board_size, allow_partial)
        if fitted is not None:
            keep, oriented = fitted
            found.append(indexed_board(idx[keep], oriented, points[idx[keep]]))
    if not any(len(board) >= MIN_CORNERS for board in found):  # pieces beside a board or close-ups (module docstring)
        found = [board for board in found if _close_up(board, gray.shape)]
    return tuple(largest_first(found))
