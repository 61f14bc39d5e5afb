"""Growth (ccdn.growth): ring-at-once and position-by-position rounds, the image test, vouching.

True corners (plus false points) or the detector on renders with exact labels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ccdn.checker import Sampler
from ccdn.board import Board
from ccdn.grid import find_boards, nearest_neighbours
from ccdn.growth import AMBIGUOUS, Grower
from conftest import as_fitted, index_map, nearest_distances, no_holes, stress_scene, true_board, true_part, whole_boards

pytest.importorskip("ccdn_training.synth")


@pytest.mark.parametrize("radius, kept", [(0.3, True), (0.6, False)], ids=["quad centre", "most of the quad"])
def test_corners_stay_when_an_occluder_covers_the_middle_of_their_square_not_its_corners(radius, kept):
    """An occluder over the middle of a square fails the quad-centre test at its four corners; each
    still shows its four quads close by, and they stay in the board. Covering that square up to near
    its corners (the corners themselves still visible) drops them."""
    (scene,) = whole_boards(1, board_sizes=((9, 6),), max_tilt_deg=25.0)
    at = {(int(r), int(c)): p for (r, c), p in zip(scene.grid, scene.corners)}
    corner = at[(2, 4)]
    quad = (corner + at[(2, 5)] + at[(3, 4)] + at[(3, 5)]) / 4  # the middle of the square it shares with (3, 5)
    step = min(np.linalg.norm(at[(2, 5)] - corner), np.linalg.norm(at[(3, 4)] - corner))
    image = scene.image.copy()
    light = cv2.getRectSubPix(image, (1, 1), tuple(map(float, quad)))[0, 0] > 127
    cv2.circle(image, tuple(int(round(c)) for c in quad), int(radius * step), 0 if light else 255, -1)
    (board,) = find_boards(image, scene.corners, np.ones(len(scene.corners)), board_size=(9, 6))
    square = np.nonzero(np.isin(scene.grid[:, 0], (2, 3)) & np.isin(scene.grid[:, 1], (4, 5)))[0]
    assert np.isin(square, board.corner_index).all() if kept else not np.isin(square, board.corner_index).any()
    assert len(board) == (54 if kept else 50)


def test_a_flat_board_grows_ring_at_once_from_its_seed_square():
    """Before any local round, the homography growth alone fills a flat board (the speed-up)."""
    for scene in whole_boards(2, board_sizes=((9, 6),), max_tilt_deg=35.0):
        xy = scene.corners.astype(np.float64)
        grower = Grower(xy, np.ones(len(xy), bool), Sampler(scene.image), np.sqrt(nearest_neighbours(xy, 1)[1][:, 0]))
        at = {(int(r), int(c)): k for k, (r, c) in enumerate(scene.grid)}
        square = [at[(2, 3)], at[(2, 4)], at[(3, 3)], at[(3, 4)]]
        (ux, uy), (vx, vy) = xy[square[1]] - xy[square[0]], xy[square[2]] - xy[square[0]]
        if ux * vy - uy * vx < 0:  # the grower's (u, v) are right-handed like image (x, y)
            square = [square[0], square[2], square[1], square[3]]
        grower.seed(square, sign=1.0, contrast=100.0)
        grower._grow_by_homography()
        grid, idx = grower.cells()
        assert len(idx) == 54
        assert index_map(Board(idx, grid, xy[idx], 9, 6), scene.grid[idx]) is not None


def test_ring_at_once_growth_does_not_jump_a_gap_to_another_board_on_the_same_lattice():
    """Two boards cut from one pattern by a blank band two squares wide: their corners line up on
    one lattice with matching colours, but no row or column of corners joins them."""
    step, squares_x, squares_y = 24, 13, 7
    image = np.full((squares_y * step + 48, squares_x * step + 48), 230, np.uint8)
    for r in range(squares_y):
        for c in range(squares_x):
            if (r + c) % 2 == 0 and c not in (6, 7):
                image[24 + r * step : 24 + (r + 1) * step, 24 + c * step : 24 + (c + 1) * step] = 25
    image[:, 24 + 6 * step : 24 + 8 * step] = 230
    image = cv2.GaussianBlur(image, (5, 5), 1.0)
    cols = [c for c in range(1, squares_x) if c not in (6, 7, 8)]  # inner corners: not on the band's edges
    xy = np.array([(23.5 + c * step, 23.5 + r * step) for r in range(1, squares_y) for c in cols], np.float32)
    boards = find_boards(image, xy, np.ones(len(xy)))
    assert sorted((b.cols, b.rows) for b in boards) == [(4, 6), (5, 6)]


@pytest.mark.parametrize("seed", [7_120_744, 7_120_467])
def test_a_board_does_not_take_corners_of_the_board_beside_it(seed):
    """Quad centres of a sublattice of a board (steps (2, 1) and (-1, 2) of its squares) are square
    centres too, so the plain image test passed there: in the stress set's two-boards render
    7120744 a board of 45 px squares grew onto 16 corners of its 21 px-square neighbour, and in
    7120467 one board took the other's outermost corner where its own is hidden. Growth also wants
    quads uniform where a seed's are sampled (ccdn.growth.WIDE_SPREAD): every board holds corners of
    one true board only, indexed as they are."""
    import ccdn
    scene = stress_scene("two-boards", seed)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert len(boards) == 2
    for board in boards:
        kept, label = true_part(board, scene)
        assert len(kept) == len(board) and len(set(scene.board_index[label])) == 1
        assert index_map(kept, scene.grid[label]) is not None


def test_the_network_vouches_for_a_corner_whose_quads_an_occluder_covers(monkeypatch):
    """In the stress set's occluded render 7141116 (fresh renders, seeds from the 60th on) an occluder
    covers part of the quads of one of the board's corners: every image test fails there, so the
    board held 67 of its 68 corners, though the network's peak lies on the corner. The pruned board
    holds that position on two sides, and the peak lies within 0.05 of a step of the grid's
    prediction, scored like the board's corners (ccdn.growth.VOUCH_REACH, VOUCH_SCORE): every corner
    now, in one board, indexed as it is, each within 0.11 px of its label."""
    import ccdn
    scene = stress_scene("occluded", 7_141_116)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert len(scene.corners) == 68 and [len(board) for board in boards] == [68]
    assert true_board(boards[0], scene, 0.11)
    monkeypatch.setattr("ccdn.growth.VOUCH_SCORE", np.inf)
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)  # (ccdn.holes' look takes it too)
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [67]


def test_a_crowded_corner_whose_wide_quads_are_mixed_gets_no_second_chance(monkeypatch):
    """Growth's image test gives a point whose far quads fail a second chance on quads closer to it
    (one quad may be hidden). A corner of a denser lattice passes that around itself: in the stress
    set's two-boards renders 7120620 (third sample) and 7121496 (fresh renders) a smaller board lies
    on a larger one, and the larger board took one of its corners near its own hidden ones (a wrongly
    indexed board); in 7120896 a board's outline next to a grid of thin lines took 2 false corners.
    A point with another within CROWDED of the shorter step must have quads uniform where a seed's
    are sampled to pass at all (ccdn.growth.WIDE_SPREAD): both boards of each render on one true board,
    indexed as they are, and no false corner; without the crowded test (CROWDED 0) as before."""
    import ccdn
    # a corner the front board half covers, unlabelled, joins a board by ccdn.holes' look: left out here;
    # ccdn.holes.settled moves a corner such as those two to the smaller board too: left out as well
    monkeypatch.setattr("ccdn.detector.predicted_holes", no_holes)
    monkeypatch.setattr("ccdn.detector.settled", lambda boards, shape: boards)
    monkeypatch.setattr("ccdn.detector.off_lattice", as_fitted)  # ccdn.outliers drops such a corner too: left out
    for seed in (7_120_620, 7_121_496):
        scene = stress_scene("two-boards", seed)
        for crowded, right in ((0.75, True), (0.0, False)):
            monkeypatch.setattr("ccdn.growth.CROWDED", crowded)
            # growth's guard against ambiguous predictions refuses such a corner too: off for the case without
            monkeypatch.setattr("ccdn.growth.AMBIGUOUS", (np.inf, 1.5) if crowded == 0 else AMBIGUOUS)
            boards = ccdn.Detector(threads=2).detect(scene.image).boards
            assert len(boards) == 2 and all(true_board(board, scene, 1.5) for board in boards) == right
    scene = stress_scene("two-boards", 7_120_896)
    labelled = np.concatenate([scene.corners, scene.ignore])
    monkeypatch.setattr("ccdn.cleanup.OUTLINE_SHORT", 0.0)  # the trim of uneven outline stubs drops them too
    for crowded, false in ((0.75, 0), (0.0, 2)):
        monkeypatch.setattr("ccdn.growth.CROWDED", crowded)
        found = ccdn.Detector(threads=2).detect(scene.image)
        assert (nearest_distances(labelled, found.xy) > 2.5).sum() == false
