"""Bridging (ccdn.bridging): a board's pieces beyond something in front of it join the board, on
the stress benchmark's renders (benchmarks/stress.py), and nothing else does."""

import numpy as np
from conftest import nearest_distances, stress_scene, true_board


def _no_bridging(monkeypatch):
    monkeypatch.setattr("ccdn.bridging.Bridging.bridge", lambda self: False)


def test_a_column_beyond_the_board_in_front_joins_its_board(monkeypatch):
    """In the two-boards render 7120597 what shows of the back board is a strip 2 x 9 corners on one
    side of the front board and a column of 9 on the other, 9 columns on: without bridging the
    column was lost (a strip one corner wide is no board); bridged, one board of 27 corners,
    indexed as the true board is, every corner within 0.1 px of its label."""
    import ccdn
    scene = stress_scene("two-boards", 7_120_597)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    back = next(board for board in boards if len(board) != 56)
    assert len(back) == 27 and back.cols == 13 and back.rows == 9
    assert true_board(back, scene, 0.1)
    _no_bridging(monkeypatch)
    assert sorted(map(len, ccdn.Detector(threads=2).detect(scene.image).boards)) == [18, 56]


def test_a_row_beyond_an_occluder_joins_its_board(monkeypatch):
    """In the occluded render 7140236 an occluder hides a row of the board: the 4 corners beyond it
    join the board, indexed as they are."""
    import ccdn
    scene = stress_scene("occluded", 7_140_236)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [22] and true_board(result.boards[0], scene, 0.2)
    assert nearest_distances(result.xy, scene.corners).max() < 0.2
    _no_bridging(monkeypatch)
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [18]


def test_a_like_posed_board_beside_keeps_its_corners():
    """In the two-boards render 7121269 (a fresh seed) two boards lie side by side in nearly one pose,
    and a column of 3 corners of one lies on the other's lattice within ccdn.bridging.BRIDGE_REACH:
    bridged while the search still ran, the other board took them before that one was found. Each
    board holds its own corners, indexed as it is."""
    import ccdn
    scene = stress_scene("two-boards", 7_121_269)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [77, 45]
    assert all(true_board(board, scene, 0.2) for board in boards)


def test_the_outline_beside_a_board_is_not_bridged():
    """In the low-contrast render 7060025 three points on the board's outline, a row beyond its last
    one, lie on its lattice and pass the image test that growth and cleanup refused them: bridging
    takes pieces beyond a gap only, so none of the corners is off the true ones."""
    import ccdn
    scene = stress_scene("low-contrast", 7_060_025)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert len(result.xy) == len(scene.corners)
    assert nearest_distances(scene.corners, result.xy).max() < 0.2
    assert np.linalg.norm(result.xy[:, None] - scene.corners[None], axis=2).min(1).max() < 0.2
