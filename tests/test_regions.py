"""ccdn.regions: the boxes the full-resolution pass of coarse-to-fine looks at, from a shrunk pass's scores."""

from __future__ import annotations

import cv2
import numpy as np

import ccdn
from ccdn.regions import LOOK_SCORE, MAX_BOXES, _nested, look_boxes

HALO = 12  # px: the paper net's receptive halo (ccdn.session)


def _inside(xy: np.ndarray, boxes) -> np.ndarray:
    """For each (x, y), whether some box (top, bottom, left, right) holds its pixel."""
    col, row = np.rint(xy).astype(int).T
    return np.any([(top <= row) & (row < bottom) & (left <= col) & (col < right) for top, bottom, left, right in boxes], 0)


def test_boxes_hold_every_corner_of_a_board_too_small_for_the_halved_frame(small_board):
    frame, corners = small_board["frame"], small_board["corners"]
    halved = cv2.resize(frame, (320, 240), interpolation=cv2.INTER_AREA)
    score = ccdn.Detector("fast", threads=2)._session.scores(halved)
    boxes = look_boxes(score, 2, frame.shape, HALO)
    assert boxes and _inside(corners, boxes).all()
    assert sum((b - t) * (r - l) for t, b, l, r in boxes) < 0.3 * frame.size


def test_a_quiet_score_map_needs_no_box_and_a_busy_one_the_whole_frame():
    assert look_boxes(np.full((240, 320), LOOK_SCORE / 2, np.float32), 2, (480, 640), HALO) == []
    busy = np.zeros((240, 320), np.float32)
    busy[::8, ::8] = 1.0  # responses everywhere: boxes would cover the frame
    assert look_boxes(busy, 2, (480, 640), HALO) is None


def test_a_box_at_the_shrunk_frame_edge_reaches_the_full_frame_edge():
    score = np.zeros((93, 125), np.float32)  # a 187x251 frame shrunk 2x drops its last row and column
    score[90, 120] = 1.0
    (top, bottom, left, right), = look_boxes(score, 2, (187, 251), HALO)
    assert bottom == 187 and right == 251 and top <= 180 and left <= 240


def test_a_box_inside_another_is_dropped_and_of_equal_ones_one_is_kept():
    score = np.zeros((120, 160), np.float32)
    score[20, 20:61] = score[60, 20:61] = score[20:61, 20] = score[20:61, 60] = 1.0  # a ring...
    score[40, 40] = 1.0  # ...with a response in its hole: one component inside the other's box
    (top, bottom, left, right), = look_boxes(score, 2, (240, 320), HALO)
    assert (top, bottom, left, right) == (32, 130, 32, 130)
    twins = np.array([[0, 10, 0, 10], [0, 10, 0, 10], [2, 8, 2, 8]])
    assert _nested(twins).tolist() == [False, True, True]


def test_scattered_specks_run_in_boxes_unless_their_halos_and_calls_cost_more_than_the_frame():
    score = np.zeros((480, 640), np.float32)
    score[::20, ::20] = 1.0  # 24 x 32 isolated specks: small boxes, but their halos cost more than the frame
    assert 24 * 32 > MAX_BOXES and look_boxes(score, 2, (960, 1280), HALO) is None
    assert len(look_boxes(score[:60, :80], 2, (960, 1280), HALO)) == 12  # a few specks: one box each
    sparse = np.zeros((750, 1000), np.float32)
    sparse[::75, ::100] = 1.0  # 10 x 10 specks on a 2000x1500 frame: more than MAX_BOXES, yet cheap
    boxes = look_boxes(sparse, 2, (1500, 2000), HALO)
    assert len(boxes) == 100 > MAX_BOXES
    assert all(bottom - top <= 18 and right - left <= 18 for top, bottom, left, right in boxes)
