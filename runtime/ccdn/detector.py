"""The Detector: image -> network -> peaks -> outlier filter -> refinement -> boards, built once.

Refinement is the saddle fit (ccdn.refine); the corners of the boards found are then moved onto
their edge lines (ccdn.edges), which use many more pixels: on noisy frames (ccdn.checker.image_noise
>= NOISY_SIGMA grey levels) every corner, elsewhere those on straight lattice lines
(ccdn.edges.on_straight_lines: no lens distortion, squares not thin). On a board under a shadow,
the corners its edge runs across are first fitted again on the frame divided by its light level
(ccdn.shade), where the light's slope no longer pulls them.

Frames go coarse-to-fine: the network first runs on the frame shrunk by the largest power of two
that leaves its shorter side >= COARSE_MIN_SIDE (640x480: halved; 2000x1500: 8x, 4x, then 2x).
When the score peaks there lie at least COARSE_MIN_SQUARE px apart and the pass finds boards whose
squares are that big on the shrunk frame (DEEP_MIN_SQUARE on frames shrunk 4x or more; on the
halved frame none of them thinner than THIN_SQUARE, as a fisheye board's rim can be), their
corners are refined on the full-resolution image and the finer passes are skipped (the holes such a
pass leaves in a board, where an occluder's or a shadow's edge hid corners from the shrunk frame,
are looked at with the full-resolution network: ccdn.holes; not with fast_check); otherwise the
next finer pass runs, down to the full frame, which is scored only inside boxes around what the
finest shrunk pass responded to (ccdn.regions: a frame with nothing there costs no full-resolution
network). Small squares and frames without a board therefore pay for the shrunk passes, and a
board too small to be seen shrunk is lost when another board in the same frame has squares big
enough (measured in benchmarks/; README). A board the
full-frame pass finds with sliver squares (a steep view's far end) gets one more look, its
surroundings magnified (ccdn.magnify), and each sliver-shaped cluster of the full-frame pass's
score peaks that no board covers gets a look stretched across its long axis (a board seen so
steeply that no pass links it); exhaustive detection (for offline calibration) looks at every
such cluster, whatever its shape (ccdn.magnify).

The default detector is a cascade: the shrunk passes run the cheap `fast` model (`fast-int8` on
CPUs with VNNI: ccdn.models.default_coarse_model), whose one weakness, corners closer than ~5 px (its
4x4-pixel output cells), cannot matter there, since a shrunk pass is kept only when its squares are
>= COARSE_MIN_SQUARE px; the full-frame pass, which small squares reach, runs the paper net. A model
named explicitly runs every pass itself.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time

import cv2
import numpy as np

from .checker import NOISY_SIGMA, image_noise
from .edges import lattice_steps, on_straight_lines, refine_on_edges
from .board import Board, checked_size, fitted_grid, with_corners
from .grid import SHADE_SPREAD, find_boards, nearest_neighbours
from .holes import filled_holes, hole_boxes, predicted_holes, settled
from .image import DEFAULT_MAX_PIXELS, read_gray, to_gray
from .magnify import from_view, loose_clusters, magnified, magnified_to_frame, merge, stretched, thin_region, thinnest
from .models import default_coarse_model
from .outliers import off_lattice
from .peaks import best_near, find_peaks, kmeans_outliers, suppress
from .regions import look_boxes
from .refine import (NARROW_RADIUS, refine, refine_from_neighbours, refine_from_shrunk, refine_saddle_points,
                     window_for_spacing)
from .result import Detection
from .session import ScoreSession
from .shade import across_shadows_edge, light_levels, light_spread, refined_across_shadows_edge
from .shaded import grown_into_shade
from .sizing import fitted_board
from .stats import median, nanmedian_rows, quantile, vector_lengths

ImageInput = str | os.PathLike | np.ndarray
FILTERS = ("grid", "kmeans", "none")
COARSE_MIN_SIDE = 160  # px: the shorter side of a frame shrunk for a coarse pass, at least. Measured: 120
# also quartered 640x480 frames, which found 5 of the 12 latency frames' boards on 160x120 but cost the others a
# pass, so the median went up (real-dev frames 20.9 -> 22.7 ms, stress renders 27.7 -> 29.2 ms), and the fast
# model lost whole second boards there (stress two-boards 1.7 -> 8.0 % missed); 240 left 2000x1500 frames at 4x
# (network 27 vs 7 ms); 90 adds a 16x pass at 2000x1500 that never finds the board there
COARSE_MIN_SQUARE = 7.0  # px on the shrunk frame: smaller squares go to the next finer pass (chosen on the
# stress renders: at 7 their figures stay those of the full-resolution pass)
DEEP_MIN_SQUARE = 5.0  # px: the same for the boards a pass on a frame shrunk 4x or more found, whose squares are
# >= 20 px at full size (2000x1500 real-dev frames found at 8x with 5-7 px squares there ran the 4x pass too, for
# the same corners: 31-40 against 14-18 ms); 5 at 2x lost corners of steep boards (stress renders, 640x480)
THIN_SQUARE = 5.0  # px on the shrunk frame: a board whose thinnest squares (ccdn.magnify.thinnest) are narrower goes
# to the next finer pass too: `fast` cannot follow a fisheye board's rim or a steep board's far end there, and its
# cleaner score maps no longer sent such frames on by their stray peaks (stress renders, fast 1.1.0: fisheye 58 -> 38
# corners missed of 5909, the training-distribution renders 985 -> 902 of 4456); on the halved frame only: on frames
# shrunk 4x or more it sent real-dev's GoPro fisheye boards (2000x1500) on to the finer passes for the same corners
# (23 -> 70-79 ms)
COARSE_MAX_SHIFT = 3.0  # shrunk px a corner may lie from its peak on a shrunk frame: `fast`'s peaks there can be
# ~2 px off (its 4x4-pixel output cells; 2.0 lost such a corner: stress partial 0.22 -> 0.11 % missed, the rest as it was)
FULL_FRAME_UNEVEN_SEEDS = 1  # on the full frame a seed square may have a corner whose quads an occluder's edge
# crosses (ccdn.grid); not on shrunk passes, where finding a hard board would stop the finer passes
GRID_THRESHOLD = (0.4, 0.25)  # (relative, floor) with the grid filter: the recall of (0.3, 0.2) at half its cost (measured)
PAPER_THRESHOLD = (0.5, 0.3)  # the paper's half of the maximum (and a floor), for the other filters
NARROW_SHIFT = 1.5  # px a failed fit retried with the narrowest window may move from its peak (_retried_fits)
MIN_BOARD_SQUARE = 5.0  # px: a board of the full frame's pass or its looks (a shrunk pass finds none so small) whose
# squares' longer side (median over its corners) is shorter is dropped (_without_tiny_boards): smaller than any
# square the networks were trained on (6 px) or the benchmarks hold, and where lines cross, clutter holds such
# lattices (a double-lined grid: a false board of 14 corners, ~4 px steps, in a fresh extreme-pose render); the
# smallest true board on ~1800 cached frames measured 5.7 px


class Detector:
    """Checkerboard inner-corner detector around its onnxruntime CPU sessions (one per model it runs).

    model: a bundled model's name (default: ccdn.models.default_model(): "paper-int8" on CPUs with
    VNNI, "paper" elsewhere) or a path to an .onnx file: the model of the full-frame pass.
    coarse_model: the model of the shrunk passes of coarse-to-fine: by default
    ccdn.models.default_coarse_model() ("fast-int8" on CPUs with VNNI, "fast" elsewhere) when `model`
    is not named (the default cascade, module docstring), else `model` itself.
    threads: intra-op threads (default: available CPUs, capped at 4). The workers never busy-wait
    between network runs (ccdn.session); spinning=False keeps them from it within a run too, for
    apps that share the CPU.
    relative, floor: keep score peaks >= max(relative * max score, floor). Default: 0.4 and 0.25 with
    the grid filter, which rejects the clutter a lower threshold lets in (measured on the stress
    renders: missed 2.5 -> 1.7 %, motion blur 10 -> 1 %, for 10-17 % more time), the paper's 0.5
    and 0.3 otherwise.
    filter: how false corners are removed: "grid" keeps corners that form a checkerboard (ccdn.grid,
    the default), "kmeans" is the paper's k-means++ clustering, "none" keeps every peak.
    refinement: "saddle" (default), "cornersubpix" or "none" (integer peaks, as in the paper).
    coarse_to_fine: try passes on the frame shrunk first (see the module docstring); only with the
    grid filter, whose boards tell whether a shrunk pass saw enough, and a sub-pixel refinement
    (the attribute says whether it applies).
    fast_check: for live previews, like OpenCV's CALIB_CB_FAST_CHECK: never run the full-resolution
    pass. A frame whose shrunk passes find no board returns no corners at once (boardless 640x480
    stress renders: ~4 ms against ~80), and the finest shrunk pass keeps the boards it finds
    whatever their squares' size, having no finer pass to defer to. The price is the boards that
    pass cannot see: squares too small for the shrunk frame, steep, glaring or strongly distorted
    views (README; benchmarks/stress.py --fast-check). Frames too small to shrink (shorter side
    under 2 x COARSE_MIN_SIDE) and detectors without coarse-to-fine run the full frame as usual.
    exhaustive: for offline calibration, where a view is worth more than its time, like OpenCV's
    CALIB_CB_EXHAUSTIVE: where the full-frame pass runs, every cluster of its score peaks that no
    board covers gets a look stretched across its long axis, not only the sliver-shaped ones
    (ccdn.magnify.loose_clusters, stretched). Costs: README. Not with fast_check, its opposite.
    detect() is thread-safe: one Detector may serve several threads.
    """

    def __init__(self, model: str | os.PathLike | None = None, threads: int | None = None, *,
                 coarse_model: str | os.PathLike | None = None, spinning: bool = True, relative: float | None = None,
                 floor: float | None = None, filter: str = "grid", refinement: str = "saddle",
                 coarse_to_fine: bool = True, fast_check: bool = False, exhaustive: bool = False,
                 max_pixels: int = DEFAULT_MAX_PIXELS) -> None:
        if filter not in FILTERS:
            raise ValueError(f"unknown filter {filter!r}; choose from {FILTERS}")
        if fast_check and exhaustive:
            raise ValueError("fast_check and exhaustive exclude each other")
        self._session = ScoreSession(model, threads, spinning)
        self.model = self._session.info
        self.threads = self._session.threads
        default_relative, default_floor = GRID_THRESHOLD if filter == "grid" else PAPER_THRESHOLD
        self.relative = default_relative if relative is None else relative
        self.floor = default_floor if floor is None else floor
        self.filter = filter
        self.refinement = refinement
        self.coarse_to_fine = coarse_to_fine and filter == "grid" and refinement != "none"
        if coarse_model is None and model is None:
            coarse_model = default_coarse_model()
        self._coarse_session = (ScoreSession(coarse_model, threads, spinning) if self.coarse_to_fine and coarse_model
                                is not None else self._session)
        self.coarse_model = self._coarse_session.info
        self.fast_check = fast_check
        # boards the grid filter completed, corners the saddle fit refined: what the looks again
        # (magnified, stretched) and the edge lines build on
        self._saddle_boards = filter == "grid" and refinement == "saddle"
        self.exhaustive = exhaustive and self._saddle_boards
        self.max_pixels = max_pixels

    @property
    def models(self) -> str:
        """The models it runs, by name: "fast+paper" for a cascade (shrunk passes + full frame)."""
        names = (self.coarse_model.name, self.model.name)
        return names[1] if self.coarse_model is self.model else "+".join(names)

    def load(self, image: ImageInput) -> np.ndarray:
        """A path or an array -> validated HxW uint8 gray (raises ccdn.ImageError)."""
        if isinstance(image, np.ndarray):
            return to_gray(image, self.max_pixels)
        return read_gray(image, self.max_pixels)

    def detect(self, image: ImageInput, *, boards: bool = False, board_size: tuple[int, int] | None = None) -> Detection:
        """Inner corners of the checkerboard(s) in `image` (path, or HxW / HxWx3 BGR array).

        Detection.boards holds the boards the corners form (ccdn.grid.find_boards) whenever they
        were found: always with the default grid filter, and with boards=True under the others.
        board_size=(cols, rows) keeps only boards, and their corners, of that size (found as without
        it, then fitted to it: ccdn.sizing); anything but two whole numbers of at least 2 raises
        ValueError.
        Coordinates: (x, y), (0, 0) is the centre of the top-left pixel.
        """
        clock = _Clock()
        board_size = checked_size(board_size)
        boards = boards or board_size is not None  # non-grid filters find boards for the size too
        gray = self.load(image)
        clock.lap("load")
        xy = values = found = shrunk = None
        model = self.coarse_model
        scales = _coarse_scales(gray.shape) if self.coarse_to_fine else []
        for scale, small in zip(scales, _halvings(gray, len(scales))[::-1]):
            any_squares = self.fast_check and scale == scales[-1]  # the finest shrunk pass: none finer to defer to
            xy, values, found, score = self._coarse(gray, small, scale, boards, board_size, clock, any_squares)
            if xy is not None:
                break
            shrunk = score, scale  # the finest shrunk pass's, in the end
        if xy is None and self.fast_check and shrunk is not None:
            xy, values, found = np.zeros((0, 2), np.float32), np.zeros(0, np.float32), ()
        elif xy is None:
            model = self.model
            boxes = None if shrunk is None else look_boxes(*shrunk, gray.shape, self._session.halo)
            xy, values, found, peaks = self._full_frame(gray, boxes, boards, clock)
            if self._saddle_boards:
                xy, values, found = self._loose_looks(gray, xy, values, found, peaks, boards, clock)
                xy, values, found = _without_tiny_boards(xy, values, found)
        lights = None
        if self._saddle_boards and not self.fast_check:
            xy, values, found, lights = self._grown_into_shade(gray, xy, values, found, clock)
        xy, values, found = self._on_edges(gray, xy, values, found, clock, lights)
        if board_size is not None:  # the boards every pass and look made, fitted (ccdn.sizing)
            fitted = (fitted_board(gray, board, board_size) for board in found)
            xy, values, found = _keep_board_corners(xy, values, tuple(board for board in fitted if board is not None))
        return Detection(xy, np.clip(values, 0, 1), (gray.shape[1], gray.shape[0]), f"{model.name} {model.version}",
                         found, clock.laps)

    def scores(self, image: ImageInput) -> np.ndarray:
        """The network's raw (H, W) float32 score map, for inspection."""
        return self._session.scores(self.load(image))

    def _coarse(self, gray: np.ndarray, small: np.ndarray, scale: int, boards: bool, board_size, clock: _Clock,
                any_squares: bool = False):
        """The pass on `small`, gray shrunk `scale` times (_halvings): (xy, values, boards, its score
        map), xy, values and boards None when the squares are too small to trust there (judged first
        on the peaks, before any refinement, then on the corners found, their gaps and, on the halved
        frame, their boards' thinnest squares, before their edge-line refinement, which a pass left to
        a finer one would waste: with any_squares, only on the peaks) or no board is found. The holes
        a kept pass leaves in its boards are filled from the full-resolution network (_filled_holes).
        With a board_size, a pass none of whose boards fits it (ccdn.board.fitted_grid) is not kept."""
        score, xy, values, gaps = self._peaks(self._coarse_session, small, clock)
        # the peaks' upper quartile: clutter's peaks lie closer together than a board's corners and,
        # more numerous with the fast model, pull the median below the board's squares
        if len(xy) < 9 or quantile(gaps, 0.75) < COARSE_MIN_SQUARE:
            return None, None, None, score
        xy, values, found = self._corners(gray, small, scale, score, xy, values, gaps, boards, clock, markers=True)
        fits = board_size is None or any(fitted_grid(b.grid, b.xy, 0.0, board_size, False) is not None for b in found)
        if len(xy) < 9 or not fits or (not any_squares and _too_small(xy, found, scale)):
            return None, None, None, score
        if not self.fast_check and self._saddle_boards:
            xy, values, found = self._filled_holes(gray, xy, values, found, clock)
        return xy, values, found, score

    def _peaks(self, session: ScoreSession, frame: np.ndarray, clock: _Clock,
               boxes: list[tuple[int, int, int, int]] | None = None):
        """The score map of `session`'s network on `frame` (only inside `boxes` when given: ccdn.regions),
        its peaks (xy, values) after the filter and their gaps (_gaps)."""
        score = session.scores(frame) if boxes is None else session.scores_in(frame, boxes)
        clock.lap("network")
        xy, values = find_peaks(score, self.relative, self.floor)
        if self.filter == "kmeans" and len(xy):
            keep = kmeans_outliers(xy)
            xy, values = xy[keep], values[keep]
        gaps = _gaps(xy)
        clock.lap("peaks")
        return score, xy, values, gaps

    def _corners(self, gray: np.ndarray, frame: np.ndarray, scale: int, score: np.ndarray, xy: np.ndarray,
                 values: np.ndarray, gaps: np.ndarray, boards: bool, clock: _Clock,
                 full_frame: bool = False, markers: bool = False):
        """Peaks xy of `score` (the network on `frame`: gray shrunk by `scale`; `gaps`: theirs, in
        frame pixels) refined on gray, then the boards they form (full_frame: the full frame's pass,
        which asks ccdn.grid.find_boards for shade_unfound and close_ups: where it finds no board, no
        finer pass follows, while a shrunk pass keeping a close-up's piece would stop the full frame's,
        whose uneven seeds may find all of it; markers: find_boards', which the shrunk and the full
        frame's passes ask for, the looks not)."""
        start = (xy + 0.5) * scale - 0.5  # pixel centres of the shrunk frame in full-size pixels
        radius = window_for_spacing(median(gaps) * scale)
        if scale > 1 and self.refinement == "saddle":  # rough starts: a first pass on the shrunk frame
            refined, ok = refine_from_shrunk(gray, frame, xy, scale, radius, COARSE_MAX_SHIFT * scale)
        else:
            refined, ok = refine(gray, start, self.refinement, 2.0 * scale, radius)
        peak_values = values
        refined, values = refined[ok], values[ok]
        distinct = suppress(refined, radius=1.0)  # refinement can move two peaks onto one corner
        refined, values = refined[distinct], values[distinct]
        clock.lap("refine")
        more = None  # the failed fits retried, for the marker search alone (ccdn.grid, Markers)
        if markers and scale == 1 and self.refinement == "saddle" and not ok.all():
            more = functools.partial(_retried_fits, gray, start[~ok], peak_values[~ok], radius, refined)
        found: tuple[Board, ...] = ()
        if self.filter == "grid" or boards:
            complete = self.filter == "grid"
            found = settled(find_boards(gray, refined, values, complete=complete,
                                        uneven_seeds=FULL_FRAME_UNEVEN_SEEDS if scale == 1 else 0,
                                        shade_unfound=full_frame, markers=markers, close_ups=full_frame, more=more),
                            gray.shape)
            if complete:
                refined, values = _with_completed(refined, values, found, score, scale)
            if complete:
                refined, values, found = _keep_board_corners(refined, values, found)
            clock.lap("boards")
        return refined, values, found

    def _filled_holes(self, gray: np.ndarray, xy: np.ndarray, values: np.ndarray, found: tuple[Board, ...],
                      clock: _Clock):
        """xy, values and boards with the holes a shrunk pass left in its boards (ccdn.board.hole_cells)
        filled from the full-resolution network's peaks, scored only around them (ccdn.holes)."""
        holes = [predicted_holes(board, gray.shape) for board in found]
        boxes = [box for _, preds, steps in holes for box in hole_boxes(preds, steps, gray.shape)]
        if not boxes:
            return xy, values, found
        score = self._session.scores_in(gray, boxes)
        clock.lap("network")
        boards = []
        for board, (cells, preds, steps) in zip(found, holes):
            if len(cells):
                cells, points, scores = filled_holes(gray, board, cells, preds, steps, score, xy)
                board = with_corners(board, cells, points, len(xy))
                xy, values = np.concatenate([xy, points]), np.concatenate([values, scores])
            boards.append(board)
        xy, values, found = _keep_board_corners(xy, values, tuple(boards))
        clock.lap("boards")
        return xy, values, found

    def _grown_into_shade(self, gray: np.ndarray, xy: np.ndarray, values: np.ndarray, found: tuple[Board, ...],
                          clock: _Clock):
        """xy, values and boards with each board's part in deep shade grown from it (ccdn.shaded): the
        network on the frame levelled around a board across whose corners a shadow's edge runs. Also
        each board's lattice steps and light levels (_light) where it did not grow, for the edge stage."""
        boards, lights, before = [], [], len(xy)
        for board in found:
            light = _light(gray, board)
            board, points, scores = grown_into_shade(gray, board, *light, self._session, xy)
            xy, values = np.concatenate([xy, points]), np.concatenate([values, scores])
            boards.append(board)
            lights.append(None if len(points) else light)
        if len(xy) > before:
            xy, values, found = _keep_board_corners(xy, values, tuple(boards))
        clock.lap("boards")
        return xy, values, found, lights

    def _full_frame(self, gray: np.ndarray, boxes: list[tuple[int, int, int, int]] | None, boards: bool,
                    clock: _Clock):
        """The full-frame pass (the network only inside `boxes` when given: ccdn.regions), with the
        magnified look at its thin boards: (xy, values, boards, its score peaks)."""
        score, peaks, values, gaps = self._peaks(self._session, gray, clock, boxes)
        xy, values, found = self._corners(gray, gray, 1, score, peaks, values, gaps, boards, clock,
                                          full_frame=True, markers=True)
        if self._saddle_boards:
            xy, values, found = self._magnified(gray, thin_region(found, gray.shape), xy, values, found, boards,
                                                clock)
        return xy, values, found, peaks

    def _loose_looks(self, gray: np.ndarray, xy: np.ndarray, values: np.ndarray, found: tuple[Board, ...],
                     peaks: np.ndarray, boards: bool, clock: _Clock):
        """xy, values and boards with the looks at the clusters of score peaks that no board covers
        (sliver-shaped ones; exhaustive: all), each stretched across its long axis (ccdn.magnify.stretched),
        one after the other."""
        for cluster in loose_clusters(peaks, found, gray.shape, any_shape=self.exhaustive):
            view = stretched(gray, cluster)
            if view is not None:
                xy, values, found = self._look(*view, xy, values, found, boards, clock)
        return xy, values, found

    def _magnified(self, gray: np.ndarray, region: tuple[int, int, int, int] | None, xy: np.ndarray,
                   values: np.ndarray, found: tuple[Board, ...], boards: bool, clock: _Clock):
        """The corners and boards with the look at `region` magnified (ccdn.magnify; None: as they are)."""
        if region is None:
            return xy, values, found
        return self._look(magnified(gray, region), magnified_to_frame(region), xy, values, found, boards, clock)

    def _look(self, view: np.ndarray, to_frame: np.ndarray, xy: np.ndarray, values: np.ndarray,
              found: tuple[Board, ...], boards: bool, clock: _Clock):
        """The corners and boards, with the boards found on `view`, a resampled part of the frame (its
        affine (2, 3) `to_frame` maps it back), in place of those they cover where they have more
        corners (ccdn.magnify.merge). The look runs the shrunk passes' model: corners lie farther
        apart there."""
        more_xy, more_values, more_found = self._corners(view, view, 1, *self._peaks(self._coarse_session, view, clock),
                                                         boards, clock)
        more_found = tuple(dataclasses.replace(b, xy=_read_only(from_view(b.xy, to_frame))) for b in more_found)
        return _keep_board_corners(*merge(xy, values, found, from_view(more_xy, to_frame), more_values, more_found))

    def _on_edges(self, gray: np.ndarray, xy: np.ndarray, values: np.ndarray, found: tuple[Board, ...],
                  clock: _Clock, lights=None):
        """xy, values and boards, the boards' corners refined on their edge lines where the grid filter
        completed them and the saddle fit refined them (_refined_on_edges; lights: each board's _light,
        where known), then their lattice outliers fitted again or dropped (_without_off_lattice)."""
        if self._saddle_boards and found:
            xy, found, steps = _refined_on_edges(gray, xy, found, image_noise(gray) >= NOISY_SIGMA, lights)
            xy, values, found = _without_off_lattice(gray, xy, values, found, steps)
            clock.lap("edges")
        return xy, values, found


def _with_completed(xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...], score: np.ndarray, scale: int):
    """xy and values extended by the corners grid completion added (indices >= len(xy)); their score
    is the network's best response within one pixel of them (usually below the threshold)."""
    total = max([len(xy)] + [int(b.corner_index.max()) + 1 for b in boards])
    if total == len(xy):
        return xy, values
    extra = np.zeros((total - len(xy), 2), np.float32)
    for board in boards:
        new = board.corner_index >= len(xy)
        extra[board.corner_index[new] - len(xy)] = board.xy[new]
    near = best_near(score, (extra + 0.5) / scale - 0.5)  # the 3x3 pixels of the pass's map around each
    return np.concatenate([xy, extra]), np.concatenate([values, near]).astype(np.float32)


def _retried_fits(gray: np.ndarray, failed: np.ndarray, failed_values: np.ndarray, radius: int, refined: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners (xy, values, narrow) of the full frame's failed saddle fits (peaks `failed`, their
    scores) that converge from their peak's diagonal neighbours (ccdn.refine.refine_from_neighbours)
    or else, `narrow` marks them, from the peak with the narrowest window (ccdn.refine.NARROW_RADIUS:
    a marker's light border of a pixel or two inside the usual window), but those within 1 px of a
    refined corner or of one another: corners the marker search alone may use, the narrow ones for
    growth only (ccdn.grid, Markers; a marker's border reaches the window of a corner whose peak lies
    on its light side; elsewhere such retried fits land on clutter, markers' bits and, on steep
    boards, 1-1.7 px off corners that completion fits right: 4 corners of 7100590 lost so, when the
    plain search used them too)."""
    points, converged = refine_from_neighbours(gray, failed, radius, 1.0)
    narrow = np.zeros(len(points), bool)
    if radius > NARROW_RADIUS and (again := ~converged).any():
        points[again], converged[again] = refine_saddle_points(gray, failed[again], NARROW_RADIUS,
                                                               0.4 * NARROW_RADIUS, max_shift=NARROW_SHIFT)
        narrow[again] = True
    points, values, narrow = points[converged], failed_values[converged], narrow[converged]
    distinct = suppress(np.concatenate([refined, points]), radius=1.0)[len(refined):]
    return points[distinct], values[distinct], narrow[distinct]


def _light(gray: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """A board's lattice steps (ccdn.edges.lattice_steps) and the light levels of its corners' quads
    (ccdn.shade.light_levels), which the shade and the edge stages both judge it by."""
    steps = lattice_steps(board)
    return steps, light_levels(gray, board.xy.astype(np.float64), steps)


def _refined_on_edges(gray: np.ndarray, xy: np.ndarray, boards: tuple[Board, ...], noisy: bool, lights=None):
    """xy and boards with the boards' corners refined on their edge lines (ccdn.edges): all of them
    on a noisy frame, else those on straight lines; on a board under a shadow (ccdn.shade.light_spread
    above ccdn.grid.SHADE_SPREAD) the corners a shadow's edge runs across first get the saddle fit
    again on the levelled frame (ccdn.shade.refined_across_shadows_edge), where its slope no longer
    pulls them (100 shadow renders: ~850 such corners, 0.31 -> 0.15 px off the truth on average).
    Also each board's lattice steps, as measured before (the lattice outliers' stage takes them)."""
    xy = xy.copy()
    refined, measured = [], []
    for board, light in zip(boards, lights or [None] * len(boards)):
        steps, levels = light or _light(gray, board)
        measured.append(steps)
        chosen = np.ones(len(board), bool) if noisy else on_straight_lines(board, steps)
        board_xy, moved = board.xy.copy(), np.zeros(len(board), bool)  # unmoved corners keep their place
        board_xy[chosen], moved[chosen] = refine_on_edges(gray, board.xy[chosen], steps[chosen])
        if light_spread(levels) > SHADE_SPREAD and (edge := across_shadows_edge(levels)).any():
            board_xy[edge], moved_too = refined_across_shadows_edge(gray, board.xy[edge].astype(np.float64),
                                                                    steps[edge])
            moved[edge] |= moved_too
        xy[board.corner_index[moved]] = board_xy[moved]
        board_xy.setflags(write=False)
        refined.append(dataclasses.replace(board, xy=board_xy))
    return xy, tuple(refined), measured


def _without_off_lattice(gray: np.ndarray, xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...],
                         steps: list[np.ndarray]):
    """xy, values and boards with each flat board's lattice outliers fitted again, or dropped where
    no fit confirms them (ccdn.outliers; steps: each board's lattice steps)."""
    xy, kept, dropped = xy.copy(), [], False
    for board, board_steps in zip(boards, steps):
        board_xy, keep = off_lattice(gray, board, board_steps)
        if board_xy is not board.xy or not keep.all():  # the board keeps its extent (off_lattice)
            xy[board.corner_index] = board_xy
            board = dataclasses.replace(board, corner_index=_read_only(board.corner_index[keep]),
                                        grid=_read_only(board.grid[keep]), xy=_read_only(board_xy[keep]))
            dropped |= not keep.all()
        kept.append(board)
    return _keep_board_corners(xy, values, tuple(kept)) if dropped else (xy, values, tuple(kept))


def _read_only(a: np.ndarray) -> np.ndarray:
    """a, made read-only in place, as ccdn.grid leaves a Board's arrays."""
    a.setflags(write=False)
    return a


def _keep_board_corners(xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...]):
    """Only the corners that belong to a board, by descending score (ties by y, x), boards re-indexed."""
    member = np.zeros(len(xy), bool)
    for board in boards:
        member[board.corner_index] = True
    keep = np.nonzero(member)[0]
    keep = keep[np.lexsort((xy[keep, 0], xy[keep, 1], -values[keep]))]
    new_index = np.empty(len(xy), np.int64)
    new_index[keep] = np.arange(len(keep))
    boards = tuple(dataclasses.replace(b, corner_index=new_index[b.corner_index]) for b in boards)
    return xy[keep], values[keep], boards


def _without_tiny_boards(xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...]):
    """xy, values and boards without the boards whose squares are under MIN_BOARD_SQUARE px along both
    axes (the median over the corners of the longer of their two lattice steps), nor their corners."""
    kept = tuple(board for board in boards if not _longer_step(board) < MIN_BOARD_SQUARE)
    return (xy, values, boards) if len(kept) == len(boards) else _keep_board_corners(xy, values, kept)


def _longer_step(board: Board) -> float:
    """The median over a board's corners of the longer of their two lattice steps, px (NaN steps left
    out; ccdn.stats, not np.nanmedian, which imports numpy.ma: 35-40 ms of a cold start)."""
    longer = np.fmax.reduce(vector_lengths(lattice_steps(board)[:, [0, 2]]), 1)
    return float(nanmedian_rows(longer[None])[0])


def _too_small(xy: np.ndarray, boards: tuple[Board, ...], scale: int) -> bool:
    """Whether a shrunk pass's corners xy (full-size px; on gray shrunk `scale` times) are too close
    together to trust: their median gap under COARSE_MIN_SQUARE shrunk px (DEEP_MIN_SQUARE on frames
    shrunk 4x or more) or, on the halved frame, a board's thinnest squares under THIN_SQUARE."""
    if median(_gaps(xy)) / scale < (COARSE_MIN_SQUARE if scale <= 2 else DEEP_MIN_SQUARE):
        return True
    return scale <= 2 and min(map(thinnest, boards), default=np.inf) / scale < THIN_SQUARE


def _coarse_scales(shape: tuple[int, ...]) -> list[int]:
    """The shrink factors of the coarse passes for a frame, coarsest first: powers of two that leave
    its shorter side at least COARSE_MIN_SIDE (640x480: [2]; 2000x1500: [8, 4, 2])."""
    scales, scale = [], 2
    while min(shape) // scale >= COARSE_MIN_SIDE:
        scales.append(scale)
        scale *= 2
    return scales[::-1]


def _halvings(gray: np.ndarray, count: int) -> list[np.ndarray]:
    """gray shrunk 2, 4, ... 2^count times, each level the previous one (cropped to even sides)
    halved by 2x2 pixel means: level k covers gray's first floor(h / 2^k) 2^k rows and as many
    columns, so its pixels map exactly onto gray's. OpenCV halves with a fast path that other
    factors lack (measured at 2000x1500: 0.06 ms for 2x, 0.75 ms for 8x at once, 0.08 ms for all
    three halvings); a level differs from a direct 2^k-fold mean by rounding, a grey level or two."""
    levels = [gray]
    for _ in range(count):
        h, w = levels[-1].shape
        levels.append(cv2.resize(levels[-1][: h - h % 2, : w - w % 2], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return levels[1:]


def _gaps(xy: np.ndarray) -> np.ndarray:
    """Distances from each of the (first 512) points to its nearest neighbour (about one square
    side on a board); [0.0] with fewer than two points."""
    if len(xy) < 2:
        return np.zeros(1)
    return np.sqrt(nearest_neighbours(xy[:512].astype(np.float64), 1)[1][:, 0])


class _Clock:
    """Per-stage wall times in ms (stages met twice, e.g. two network passes, add up)."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.laps[stage] = self.laps.get(stage, 0.0) + (now - self._last) * 1e3
        self._last = now


_default: Detector | None = None


def detect(image: ImageInput) -> Detection:
    """Detect with a cached default Detector (the default model and settings)."""
    global _default
    if _default is None:
        _default = Detector()
    return _default.detect(image)
