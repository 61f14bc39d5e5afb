"""Seed squares (ccdn.seeds): what seeds a board and what must not, through ccdn.grid.find_boards.

True corners (plus false points) or the detector on renders with exact labels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ccdn.checker import Sampler
from ccdn.grid import BEHIND_UNEVEN, find_boards, nearest_neighbours
from ccdn.seeds import SEED_REACH, seed_squares
from conftest import index_map, stress_scene, true_board, whole_boards

pytest.importorskip("ccdn_training.synth")


def sheared_board(u: tuple[float, float], v: tuple[float, float], squares: tuple[int, int] = (8, 7)):
    """A board whose square steps in the image are u and v (an affine view), drawn 4x supersampled
    on a light background; returns the image and its inner corners (row-major) with (row, col)."""
    origin, ss = np.array([30.0, 20.0]), 4
    to_board = np.linalg.inv(np.column_stack([u, v]))
    yy, xx = (np.mgrid[0 : 240 * ss, 0 : 320 * ss] + 0.5) / ss - 0.5
    c, r = np.einsum("ij,jhw->ihw", to_board, np.stack([xx, yy]) - origin[:, None, None])
    inside = (c >= 0) & (c < squares[0]) & (r >= 0) & (r < squares[1])
    dark = inside & ((np.floor(c) + np.floor(r)) % 2 == 0)
    big = np.where(dark, 40.0, 210.0).astype(np.float32)
    image = cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA).astype(np.uint8)
    grid = np.array([(r, c) for r in range(1, squares[1]) for c in range(1, squares[0])])
    corners = origin + grid[:, 1:2] * np.array(u) + grid[:, 0:1] * np.array(v)
    return image, corners.astype(np.float32), grid


def test_points_on_a_plain_grid_of_lines_form_no_board():
    """Crossings of a line grid are regularly spaced but their quads do not alternate dark/light."""
    image = np.full((240, 320), 200, np.uint8)
    image[20:220:20, :] = 30
    image[:, 20:300:20] = 30
    yy, xx = np.mgrid[20:220:20, 20:300:20]
    xy = np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float32)
    assert find_boards(image, xy, np.ones(len(xy))) == ()


@pytest.mark.parametrize("u, v, whole", [((14.0, 0.0), (24.0, 9.0), True), ((14.0, 2.0), (25.0, 11.0), False)])
def test_a_strongly_sheared_board_never_gets_a_shorter_lattice(u, v, whole):
    """Steep views shear a board so that v - 2u is shorter than v, and the basis (u, v - 2u) passes
    the colour test like (u, v) (its quad centres are square centres too): the seed's wider
    uniformity samples must reject it, or every row's indices shift by 2 columns. In the second
    view v is not among a corner's 12 nearest, so no seed can form the true square: no board is
    then the right answer, never a wrongly indexed one."""
    image, corners, grid = sheared_board(u, v)
    boards = find_boards(image, corners, np.ones(len(corners)))
    assert all(index_map(board, grid[board.corner_index]) is not None for board in boards)
    if whole:
        assert len(boards) == 1 and len(boards[0]) == len(corners)
        assert sorted((boards[0].cols, boards[0].rows)) == [6, 7]


def test_midpoints_of_a_thin_line_mesh_form_no_board():
    """The midpoints of a mesh's line segments are saddles on a diagonal lattice whose 'quads' are a
    light cell and a dark crossing; sampled along the lines' directions the crossing looks like a
    dark square, so the seed also samples along the lattice steps, which leave the thin lines."""
    image = np.full((240, 320), 200, np.uint8)
    image[20:220:8, 20:300] = 40
    image[20:220, 20:300:8] = 40
    image = cv2.GaussianBlur(image, (0, 0), 0.6)
    yy, xx = np.mgrid[20:212:8, 20:292:8]
    mid = np.concatenate([np.column_stack([xx.ravel() + 4, yy.ravel()]), np.column_stack([xx.ravel(), yy.ravel() + 4])])
    assert find_boards(image, mid.astype(np.float32), np.ones(len(mid))) == ()


@pytest.mark.parametrize("dotted", ["corner squares", "every square"])
def test_a_board_with_marks_in_its_corner_squares_still_seeds(dotted):
    """Boards often carry marks (dots, a logo) in some squares. A dot in each corner square of a
    3 x 3-corner board breaks the uniform-quad test at one corner of every possible seed square,
    which may have one such corner with uneven_seeds=1 (the detector's full-frame pass): the board is
    found. Dots in every square break it at all four
    corners: no seed, no board."""
    rows, cols = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    squares = np.stack([rows.ravel(), cols.ravel()], 1)  # (row, col) of the 4 x 4 squares
    if dotted == "corner squares":
        squares = squares[np.isin(squares, (0, 3)).all(1)]
    for scene in whole_boards(3, board_sizes=((3, 3),), square_px=(30.0, 40.0), max_tilt_deg=15.0):
        # square (r, c) spans inner corners (r - 1, c - 1) .. (r, c): its centre from an affine fit to them
        fit, *_ = np.linalg.lstsq(np.c_[scene.grid, np.ones(len(scene.grid))], scene.corners, rcond=None)
        centres = np.c_[squares - 0.5, np.ones(len(squares))] @ fit
        if ((centres > 20) & (centres < np.array(scene.image.shape[::-1]) - 20)).all():  # whole board in frame
            break
    else:
        pytest.fail("no render with the whole board in frame")
    image = scene.image.copy()
    for centre in centres:
        light = cv2.getRectSubPix(image, (1, 1), tuple(map(float, centre)))[0, 0] > 127
        cv2.circle(image, tuple(int(round(c)) for c in centre), 4, 0 if light else 255, -1)
    boards = find_boards(image, scene.corners, np.ones(len(scene.corners)), uneven_seeds=1)
    if dotted == "corner squares":
        (board,) = boards
        assert len(board) == 9 and index_map(board, scene.grid[board.corner_index]) is not None
        assert find_boards(image, scene.corners, np.ones(len(scene.corners))) == ()  # strict seeds only
    else:
        assert boards == ()


def test_one_sampling_serves_every_count_of_uneven_corners():
    """seed_squares asked for several counts at once (ccdn.grid's search samples a later round's
    squares with an earlier round's) gives each count what asking for it alone gives: on a two-boards
    stress render's corners, with clutter points among them so that many seeds' shortest squares
    fail and are sampled further, every seed, at 1 and BEHIND_UNEVEN uneven corners."""
    scene = stress_scene("two-boards", 7_120_937)
    rng = np.random.default_rng(0)
    h, w = scene.image.shape
    clutter = rng.uniform((0, 0), (w - 1, h - 1), (150, 2))
    xy = np.concatenate([scene.corners, clutter]).astype(np.float64)
    neighbours = nearest_neighbours(xy, SEED_REACH)[0]
    sampler, free, seeds = Sampler(scene.image), np.ones(len(xy), bool), np.arange(len(xy))
    together = seed_squares(xy, sampler, seeds, neighbours, free, (0, 1, BEHIND_UNEVEN))
    assert together[1][0].sum() > together[0][0].sum() > 0  # the looser count passes more seeds
    for level, alone in ((1, (1, BEHIND_UNEVEN)), (2, (BEHIND_UNEVEN,))):
        for part, same in zip(together[level], seed_squares(xy, sampler, seeds, neighbours, free, alone)[0]):
            np.testing.assert_array_equal(part, same)


def test_a_noisy_frames_seed_quads_may_range_with_its_noise(monkeypatch):
    """On the training-distribution render 5200034 (noise of ~7.7 grey levels, a low-contrast board of
    small squares, whose quads are sampled in single pixels) the noise alone made every seed square's
    quads range over half its contrast, and the board was lost whole. Allowed ccdn.seeds.NOISE_RANGE x
    the noise, 38 of its 39 corners form one board, indexed as they are."""
    import ccdn
    from ccdn_training.synth import SceneConfig, render_scene

    scene = render_scene(np.random.default_rng(5_200_034), SceneConfig(p_no_board=0.0))
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [38] and true_board(boards[0], scene, 1.0)
    monkeypatch.setattr("ccdn.seeds.NOISE_RANGE", 0.0)
    assert ccdn.Detector(threads=2).detect(scene.image).boards == ()
