"""Grid recovery (ccdn.grid.find_boards) on renders with exact labels and on labelled real photos.

The true corners (plus random false points) are fed in, so these tests do not depend on the model.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ccdn.board import Board, hole_cells
from ccdn.grid import find_boards
from conftest import REAL_DEV, index_map, nearest_distances, render, stress_scene, true_board, whole_boards

synth = pytest.importorskip("ccdn_training.synth")


def with_false_points(scene: synth.Scene, n: int, seed: int) -> np.ndarray:
    h, w = scene.image.shape
    return np.concatenate([scene.corners, np.random.default_rng(seed).random((n, 2)) * [w, h]]).astype(np.float32)


def largest_matching(boards: tuple[Board, ...], wanted: np.ndarray) -> Board:
    return max(boards, key=lambda b: np.isin(b.corner_index, wanted).sum())


@pytest.mark.parametrize("lens", [dict(), dict(p_radial=1.0, radial_k1=(0.3, 0.45)), dict(p_fisheye=1.0)],
                         ids=["pinhole", "strong-radial", "fisheye"])
def test_recovers_each_board_with_consistent_indices_and_drops_false_points(lens):
    found = total = 0
    for seed in range(4):
        scene = render(seed, **lens)
        xy = with_false_points(scene, 40, seed)
        boards = find_boards(scene.image, xy, np.ones(len(xy)))
        assert len(boards) == 1
        board = boards[0]
        assert (board.corner_index < len(scene.corners)).all(), "a random false point joined the board"
        assert index_map(board, scene.grid[board.corner_index]) is not None
        cols, rows = scene.boards[0]
        if len(board) == len(scene.corners) == cols * rows:  # all visible and all found: the board's extent
            assert sorted((board.cols, board.rows)) == sorted((cols, rows))
        found, total = found + len(board), total + len(scene.corners)
    assert found >= 0.97 * total


@pytest.mark.parametrize("invert", [0.0, 1.0], ids=["dark-top-left", "inverted"])
def test_asymmetric_board_origin_is_the_corner_whose_quad_is_light(invert):
    """The renderer's quad at (0, 0) is dark (light when inverted); ccdn's (0, 0) quad is light."""
    for scene in whole_boards(3, board_sizes=((9, 6),), p_invert=invert):
        (board,) = find_boards(scene.image, scene.corners, np.ones(len(scene.corners)), board_size=(9, 6))
        true = scene.grid[board.corner_index]
        expected = true if invert else np.column_stack([5 - true[:, 0], 8 - true[:, 1]])
        np.testing.assert_array_equal(board.grid, expected)


def test_several_boards_are_returned_each_with_its_own_indices():
    seen = 0
    for seed in range(6):
        scene = render(seed, p_two_boards=1.0, square_px=(15.0, 30.0), board_sizes=((7, 5), (6, 4), (5, 5)))
        xy = with_false_points(scene, 30, seed)
        boards = find_boards(scene.image, xy, np.ones(len(xy)))
        for b in range(len(scene.boards)):
            mine = np.nonzero(scene.board_index == b)[0]
            if len(mine) < 16:  # mostly hidden behind the other board
                continue
            board = largest_matching(boards, mine)
            assert np.isin(board.corner_index, mine).all(), "two boards were merged"
            assert index_map(board, scene.grid[board.corner_index]) is not None
            assert len(board) >= 0.9 * len(mine)
            seen += 1
    assert seen >= 8


@pytest.mark.parametrize("hole", ["one corner", "a whole column"])
def test_missing_corners_leave_holes_not_broken_boards(hole):
    (scene,) = whole_boards(1, board_sizes=((9, 6),), max_tilt_deg=25.0)
    gone = (scene.grid[:, 0] == 2) & (scene.grid[:, 1] == 4) if hole == "one corner" else scene.grid[:, 1] == 4
    keep = np.nonzero(~gone)[0]
    (board,) = find_boards(scene.image, scene.corners[keep], np.ones(len(keep)), board_size=(9, 6))
    assert len(board) == len(keep)
    assert index_map(board, scene.grid[keep][board.corner_index]) is not None


ROW_1 = [(1, 0), (1, 1), (1, 2), (1, 3)]


@pytest.mark.parametrize("missing, holes", [([(1, 1)], [(1, 1)]), ([(0, 0), (2, 3)], [(0, 0), (2, 3)]),
                                             ([(0, 0), (0, 1)], [(0, 1)]), (ROW_1, ROW_1)])
def test_hole_cells_are_the_missing_corners_the_board_holds_on_two_sides(missing, holes):
    """A missing corner with two of the board's next to it along its row and column is a hole
    (inside the board, or a notch of its outline such as a corner an occluder covers); one with a
    single neighbour, beyond a straight stretch of the outline, is not."""
    rows, cols = np.mgrid[0:3, 0:4]
    grid = np.stack([rows.ravel(), cols.ravel()], 1)
    grid = grid[[tuple(cell) not in missing for cell in grid.tolist()]].astype(np.int32)
    board = Board(np.arange(len(grid)), grid, grid[:, ::-1].astype(np.float32) * 20, 4, 3)
    assert hole_cells(board).tolist() == [list(cell) for cell in holes]


def test_points_off_any_checkerboard_form_no_board():
    scene = render(3, p_no_board=1.0)
    xy = np.random.default_rng(0).random((300, 2)) * [640, 480]
    assert find_boards(scene.image, xy, np.ones(len(xy))) == ()


def test_board_size_prior_keeps_that_size_transposes_it_and_rejects_others():
    (scene,) = whole_boards(1, board_sizes=((9, 6),))
    xy, score = scene.corners, np.ones(len(scene.corners))
    (board,) = find_boards(scene.image, xy, score, board_size=(9, 6))
    assert (board.cols, board.rows) == (9, 6) and board.grid[:, 1].max() == 8
    (transposed,) = find_boards(scene.image, xy, score, board_size=(6, 9))
    assert (transposed.cols, transposed.rows) == (6, 9)
    assert find_boards(scene.image, xy, score, board_size=(7, 5)) == ()
    assert find_boards(scene.image, xy, score, board_size=(10, 7)) == ()
    part = np.nonzero(scene.grid[:, 1] < 7)[0]  # a board cut to 7 x 6
    assert find_boards(scene.image, xy[part], score[part], board_size=(9, 6)) == ()
    (partial,) = find_boards(scene.image, xy[part], score[part], board_size=(9, 6), allow_partial=True)
    assert (partial.cols, partial.rows) == (7, 6)


def test_result_does_not_depend_on_input_order():
    scene = render(0)
    xy = with_false_points(scene, 30, 0)
    perm = np.random.default_rng(1).permutation(len(xy))
    (a,), (b,) = find_boards(scene.image, xy, np.ones(len(xy))), find_boards(scene.image, xy[perm], np.ones(len(xy)))
    np.testing.assert_array_equal(perm[b.corner_index], a.corner_index)
    np.testing.assert_array_equal(b.grid, a.grid)


def test_board_arrays_are_row_major_frozen_and_json_ready():
    scene = render(0)
    (board,) = find_boards(scene.image, scene.corners, np.ones(len(scene.corners)))
    assert board.corner_index.dtype == np.int64 and board.grid.dtype == np.int32 and board.xy.dtype == np.float32
    order = board.grid[:, 0] * 1000 + board.grid[:, 1]
    assert (np.diff(order) > 0).all()
    np.testing.assert_array_equal(board.xy, scene.corners[board.corner_index])
    with pytest.raises(ValueError):
        board.grid[0, 0] = 5
    d = json.loads(json.dumps(board.to_dict()))
    assert d["cols"] == board.cols and len(d["corners"]) == len(d["grid"]) == len(board)


def test_bad_input_is_refused_and_few_points_give_no_board():
    scene = render(0)
    with pytest.raises(ValueError, match="uint8"):
        find_boards(scene.image.astype(np.float32), scene.corners, np.ones(len(scene.corners)))
    with pytest.raises(ValueError, match="score"):
        find_boards(scene.image, scene.corners, np.ones(3))
    assert find_boards(scene.image, scene.corners[:5], np.ones(5)) == ()
    assert find_boards(scene.image, np.zeros((0, 2)), np.zeros(0)) == ()


def test_real_photos_labelled_corners_link_into_the_labelled_board():
    if not (REAL_DEV / "labels.json").is_file():
        pytest.skip("../shared/data/real-dev is absent")
    import cv2

    images = json.loads((REAL_DEV / "labels.json").read_text())["images"]
    recovered = same_origin = asymmetric = 0
    for meta in images:
        gray = cv2.imread(str(REAL_DEV / "images" / meta["file"]), cv2.IMREAD_GRAYSCALE)
        label = meta["boards"][0]
        cols, rows = label["cols"], label["rows"]
        xy = np.asarray(label["corners"], np.float32).reshape(-1, 2)
        free = find_boards(gray, xy, np.ones(len(xy)))
        boards = find_boards(gray, xy, np.ones(len(xy)), board_size=(cols, rows))
        free_size = sorted((free[0].cols, free[0].rows)) if free else None
        if len(boards) == 1 and len(boards[0]) == cols * rows and free_size == sorted((cols, rows)):
            recovered += 1
            labelled = np.column_stack(np.divmod(boards[0].corner_index, cols))  # labels are row-major
            if (cols + rows) % 2:
                asymmetric += 1
                same_origin += np.array_equal(labelled, boards[0].grid)
    assert recovered >= len(images) - 1
    # the labels come from cv2.findChessboardCornersSB, whose (0, 0) quad is light as well
    assert same_origin >= 0.9 * asymmetric


def test_detector_returns_the_board_with_indices_into_its_corners(detector, examples):
    ex = examples["board"]
    result = detector.detect(ex["path"], boards=True, board_size=(9, 6))
    (board,) = result.boards
    assert (board.cols, board.rows) == (9, 6)
    np.testing.assert_array_equal(board.xy, result.xy[board.corner_index])
    near = np.linalg.norm(board.xy[:, None] - ex["corners"][None], axis=2).min(1) < 2.0
    assert near.all() and len(board) >= 0.9 * 54
    assert json.loads(result.to_json())["boards"][0]["cols"] == 9


@pytest.mark.parametrize("seed, detected", [(7_160_030, 60), (7_160_031, 72)])
def test_a_board_half_in_deep_shadow_is_one_board(seed, detected):
    """A shadow taking 80-95 % of the light (the stress set's shadow renders) leaves the shaded part
    of a board a fifth to a twentieth of the lit part's contrast, and across its edge two of a
    corner's quads darken: judged on the grey scale against the seed's contrast, the shaded corners
    failed the image test, and these two boards, given their true corners, came out as two boards
    each (31 + 27 and 53 + 24 corners, indexed apart). On the log scale (ccdn.lattice.SHADE_OFFSET) each is one
    board of every corner, indexed as it is. The detector, from its own peaks, finds one board of
    all 60 and of 73 of the 77 (4 on the shadow's edge are missed); before, boards of 28 + 21 and
    28 + 24 + 13 corners."""
    import ccdn
    scene = stress_scene("shadow", seed)
    (board,) = find_boards(scene.image, scene.corners, np.ones(len(scene.corners)), complete=True)
    assert len(board) == len(scene.corners)
    assert index_map(board, scene.grid[board.corner_index]) is not None
    found = ccdn.Detector(threads=2).detect(scene.image)
    assert len(found.boards) == 1 and len(found.boards[0]) >= detected


def test_a_board_under_a_soft_shadow_is_searched_for_again_on_the_levelled_frame(monkeypatch):
    """Given its true corners, the shadow render 7160406's board (a soft shadow across most of it)
    grows to 39 of its 54 corners on the frame itself (32 before prune kept the corners whose other
    neighbours the shadow hides): the corners in the penumbra fail the image tests on the grey and
    the log scale. That part is lit unevenly (ccdn.shade.light_spread 7.4 > ccdn.grid.SHADE_SPREAD),
    so the search runs again on the levelled frame: 53, indexed as they are. (The image tests alone:
    the given corners all score 1, and the network would vouch for every one the board holds on two
    sides: Grower.vouch.)"""
    monkeypatch.setattr("ccdn.growth.VOUCH_SCORE", np.inf)
    scene = stress_scene("shadow", 7_160_406)
    (board,) = find_boards(scene.image, scene.corners, np.ones(len(scene.corners)), complete=True)
    assert len(board) == 53 and (board.corner_index < len(scene.corners)).all()
    assert index_map(board, scene.grid[board.corner_index]) is not None
    monkeypatch.setattr("ccdn.grid.SHADE_SPREAD", np.inf)
    (board,) = find_boards(scene.image, scene.corners, np.ones(len(scene.corners)), complete=True)
    assert len(board) <= 39


@pytest.mark.parametrize("seed, strip", [(7_120_597, (2, 9, 18)), (7_120_704, (2, 5, 9))])
def test_the_strip_of_a_board_another_hides_is_a_board(seed, strip, monkeypatch):
    """Where one board hides most of another, what shows of the back one can be a strip two corners
    wide (the stress set's two-boards renders 7120597 and 7120704): a board of 2 x 9 and of 2 x 5
    positions, indexed as they are, next to the front board. With boards needing 3 x 3 positions
    (ccdn.grid.MIN_EXTENT 3 before), they were lost. (Bridging off: 7120597's strip also takes a
    column beyond the front board, tests/test_bridging.py.)"""
    import ccdn
    scene = stress_scene("two-boards", seed)
    monkeypatch.setattr("ccdn.bridging.Bridging.bridge", lambda self: False)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert len(boards) == 2
    back = boards[1]
    cols, rows, count = strip
    assert (back.cols, back.rows, len(back)) == (cols, rows, count)
    label = np.linalg.norm(back.xy[:, None] - scene.corners[None], axis=2).argmin(1)
    assert len(set(scene.board_index[label])) == 1 and index_map(back, scene.grid[label]) is not None
    assert nearest_distances(scene.corners, back.xy).max() < 0.1
    monkeypatch.setattr("ccdn.grid.MIN_EXTENT", 3)
    assert len(ccdn.Detector(threads=2).detect(scene.image).boards) == 1


def test_a_piece_of_a_board_behind_another_is_a_board_beside_it(monkeypatch):
    """In the two-boards render 7121839 (a fresh seed) what shows of the back board is a piece of 2 x 3
    corners beside the front board's edge: with boards of 8 corners at least it was lost. A board of
    ccdn.grid.MIN_PIECE corners where the search also finds one of 8: indexed as it is, each corner
    within 0.1 px of its label."""
    import ccdn
    scene = stress_scene("two-boards", 7_121_839)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [27, 6]
    assert (boards[1].rows, boards[1].cols) == (2, 3) and true_board(boards[1], scene, 0.1)
    monkeypatch.setattr("ccdn.grid.MIN_PIECE", 8)
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [27]


def test_a_piece_holds_no_point_off_the_lattice_of_its_others(monkeypatch):
    """In the two-boards render 7120386 a piece of 2 x 3 corners of the back board took a point where
    the front board's outline crosses a hidden corner's squares, 2.3 px off it (ccdn.lattice.
    each_where_the_others_put_it: 0.11 of a step from where the piece's 5 other corners put it, a
    true piece's corners 0.002): no such piece, and no point of any board over 0.3 px off its label."""
    import ccdn
    scene = stress_scene("two-boards", 7_120_386)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [54]
    assert nearest_distances(scene.corners, result.xy).max() < 0.3  # each corner found, to its label
    monkeypatch.setattr("ccdn.grid.each_where_the_others_put_it", lambda grid, points: True)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [54, 6] and not true_board(boards[1], scene, 1.0)


def test_a_piece_is_grown_once_the_boards_are_found(monkeypatch):
    """In the two-boards render 7122551 (a fresh seed) a seed square of the back board, ranked first,
    grows into a piece of 6 corners that the front board cuts off; taken during the search, it kept
    corners the back board, grown later, reaches them through: that board lost 12. Grown once the
    boards are found (and bridged), its corners are the back board's: 81 of them."""
    import ccdn
    scene = stress_scene("two-boards", 7_122_551)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert sorted(len(board) for board in result.boards) == [77, 81]
    monkeypatch.setattr("ccdn.grid.MIN_CORNERS", 6)  # a piece is a board: taken during the search
    assert sorted(len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards) == [6, 69, 77]


def test_a_piece_alone_is_no_board(monkeypatch):
    """On the extreme-pose render 7100021 the full frame's search finds a piece of 6 corners of the
    board and no board of 8; kept, it took the place of the look at the steep board's clusters
    (ccdn.magnify), whose board holds all 55 corners, with a magnified look at itself that found 54."""
    import ccdn
    scene = stress_scene("extreme-pose", 7_100_021)
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [55]
    monkeypatch.setattr("ccdn.grid.MIN_CORNERS", 6)  # a board of 6 counts as one of 8: a piece alone is kept
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [54]


def test_a_board_behind_another_seeds_where_two_corners_of_each_square_are_covered(monkeypatch):
    """What shows of the back board in the stress set's two-boards render 7120041 is an L: the front
    board's outline crosses the quads of two corners of every square of it left, and seed squares
    allowed one such corner at most, so it was lost (18 of its corners, every one with a network
    peak). Once a board is found, a last round of seeds allows two (ccdn.grid.BEHIND_UNEVEN): 11 of
    them, in a second board of one true board, indexed as it is (12 when found, 13 while the network
    vouched for one next to the front board, Grower.vouch, and before two crowded by the front
    board's outline points, whose wide-sampled quads it covers, lost their second chance); with the
    row of it beyond the front board, bridged (ccdn.bridging), 17."""
    import ccdn
    scene = stress_scene("two-boards", 7_120_041)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [49, 17]
    assert true_board(boards[1], scene, 1.5)
    monkeypatch.setattr("ccdn.grid.BEHIND_UNEVEN", 1)  # the last round as lenient as the full frame's second
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [49]


def test_a_piece_behind_another_board_seeds_where_its_outline_hides_a_quad_of_two_corners(monkeypatch):
    """In the stress set's two-boards render 7120536 a piece of 2 x 3 corners of the back board
    shows below the front one, whose light margin covers one quad of each corner along its edge: those
    quads are light where a dark one belongs, so the seed squares' quads did not alternate at two of
    their corners and the piece was lost. In the last round (ccdn.seeds.BEHIND_UNEVEN) such a
    corner's three other quads alternating suffice: the piece is found, 6 corners, indexed as it is."""
    import ccdn
    scene = stress_scene("two-boards", 7_120_536)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [100, 6]
    assert all(true_board(board, scene, 0.5) for board in boards)
    monkeypatch.setattr("ccdn.seeds.BEHIND_UNEVEN", 3)  # every corner of a seed square all four quads again
    assert [len(board) for board in ccdn.Detector(threads=2).detect(scene.image).boards] == [100]


def test_a_corner_the_board_behind_took_from_the_one_in_front_goes_to_the_front_boards_hole(monkeypatch):
    """In the stress set's two-boards render 7122387 (fresh renders, seeds from the 200th on) a board
    of small squares lies in front of one of large squares, and growth let the one behind take a
    corner of the front one's outer column where its own corner lies hidden beneath: a board of 18
    corners indexed wrongly, and the front board lacked one. That corner lies 0.01 px from the front
    board's prediction at its hole, where the board behind, without it, predicts none
    (ccdn.holes.settled): it moves, and both boards hold one true board each, indexed as it is.
    (Growth's guard against ambiguous predictions, ccdn.growth.AMBIGUOUS, refuses that corner too:
    left out for the case without settled.)"""
    import ccdn
    scene = stress_scene("two-boards", 7_122_387)
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [77, 17]
    assert all(true_board(board, scene, 0.1) for board in boards)
    monkeypatch.setattr("ccdn.detector.settled", lambda boards, shape: boards)
    monkeypatch.setattr("ccdn.growth.AMBIGUOUS", (np.inf, 1.5))
    boards = ccdn.Detector(threads=2).detect(scene.image).boards
    assert [len(board) for board in boards] == [76, 18]
    assert true_board(boards[0], scene, 0.1) and not true_board(boards[1], scene, 0.1)


def test_where_the_frame_cuts_a_board_its_outline_gives_no_corner():
    """Where the frame's edge cuts a board's outline, the one quad pair left on the image alternates
    like a corner's: the stress set's partial render 7130009 had a board corner 0.2 px from the edge
    and 49 px from any true corner (and real-dev photos rotated by 90 degrees, a board one column too
    wide). Corners closer than ccdn.lattice.EDGE_MARGIN to the frame's edge join no board (the renders'
    labels leave them out too): every corner found is a true one."""
    import ccdn
    from ccdn.lattice import EDGE_MARGIN
    scene = stress_scene("partial", 7_130_009)
    h, w = scene.image.shape
    found = ccdn.Detector(threads=2).detect(scene.image).xy
    assert len(found) >= 20
    assert (found >= EDGE_MARGIN).all() and (found <= np.array([w - 1, h - 1]) - EDGE_MARGIN).all()
    assert (np.linalg.norm(found[:, None] - scene.corners[None], axis=2).min(1) < 1.0).all()
