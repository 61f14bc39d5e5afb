"""Corners linked along a board's edges (ccdn.linked): fisheye close-ups, whose squares change size
faster than growth's predictions follow, found with their indices right."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import ccdn
import ccdn.grid
import ccdn.linked
from ccdn.grid import LINK_BLUR, nearest_neighbours
from ccdn.linked import edge_pairs
from conftest import index_map, nearest_distances, stress_scene


def _true_pairs(scene) -> dict[str, set[tuple[int, int]]]:
    """Pairs of a render's labelled corners (indices into scene.corners, smaller first) by kind: "edge"
    (row or column neighbours), "diagonal" and "two apart" (two steps along a row or column)."""
    cell = {(int(b), int(r), int(c)): k for k, (b, (r, c)) in enumerate(zip(scene.board_index, scene.grid))}
    kinds = {"edge": ((0, 1), (1, 0)), "diagonal": ((1, 1), (1, -1)), "two apart": ((0, 2), (2, 0))}
    pairs = {kind: set() for kind in kinds}
    for (b, r, c), k in cell.items():
        for kind, offsets in kinds.items():
            for dr, dc in offsets:
                other = cell.get((b, r + dr, c + dc))
                if other is not None:
                    pairs[kind].add((min(k, other), max(k, other)))
    return pairs


def test_edges_join_row_and_column_neighbours_not_diagonals_nor_corners_two_apart():
    """On a fisheye close-up's true corners, the edge test passes most pairs of row or column
    neighbours and no diagonal (the same grey on both sides) nor pair two squares apart (the side
    changes half-way)."""
    scene = stress_scene("fisheye-close-up", 7_190_029)
    xy = scene.corners.astype(np.float64)
    neighbours, _ = nearest_neighbours(xy, 24)
    image = cv2.GaussianBlur(scene.image, (0, 0), LINK_BLUR).astype(np.float32)
    pairs, sign = edge_pairs(image, xy, neighbours)
    found = set(map(tuple, pairs.tolist()))
    truth = _true_pairs(scene)
    reachable = {p for p in truth["edge"] if p[1] in neighbours[p[0], :8] or p[0] in neighbours[p[1], :8]}
    assert len(found & reachable) >= 0.9 * len(reachable)
    assert not found & truth["diagonal"]
    assert not found & truth["two apart"]
    assert set(np.unique(sign).tolist()) == {-1.0, 1.0}


@pytest.mark.parametrize("seed", [7_190_029, 7_190_007])
def test_a_fisheye_close_up_growth_misses_is_linked_along_its_edges(seed):
    """Fisheye close-ups where growth found no board (7190029: 51 corners, 7190007: 42; squares of
    ~150 px at the centre, a few px at the rim): linked along their edges, over half their corners are
    found, all true ones, indexed as the render's board."""
    scene = stress_scene("fisheye-close-up", seed)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert len(result.boards) == 1
    board = result.boards[0]
    assert len(board) >= 0.5 * len(scene.corners)
    apart = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    assert (apart.min(1) < 0.5).all()
    assert index_map(board, scene.grid[apart.argmin(1)]) is not None


def test_a_corner_hanging_on_one_edge_is_dropped(monkeypatch):
    """A corner linked by one edge only has a step nothing else confirms: where a fisheye close-up's
    outer squares meet the background (7190014: (522, 14) px) its outline links like a corner; at a
    rim such a step may span corners the network missed. They are dropped but where the frame cuts
    their line (ccdn.linked._cut_by_frame): every corner the detector returns there is a true one,
    on a board indexed as the render's; keeping every such corner, one is over 20 px from any."""
    scene = stress_scene("fisheye-close-up", 7_190_014)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert len(result.xy) >= 0.9 * len(scene.corners)
    assert (nearest_distances(scene.corners, result.xy) < 1.0).all()
    for board in result.boards:
        apart = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
        assert index_map(board, scene.grid[apart.argmin(1)]) is not None
    monkeypatch.setattr(ccdn.linked, "_cut_by_frame", lambda *args: True)
    kept = ccdn.Detector(threads=2).detect(scene.image)
    assert (nearest_distances(scene.corners, kept.xy) > 20).any()


def test_clutter_linked_into_a_zigzag_is_no_board():
    """Beside a motion-blurred board (the stress set's render 7030523: 24 corners), links through
    the clutter formed a "close-up" of 10 corners whose lines turned 37 degrees at the median
    corner; a component turning over ccdn.linked.MAX_MEDIAN_TURN is no board: the board alone is found."""
    scene = stress_scene("motion-blur", 7_030_523)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [len(scene.corners)]
    assert (nearest_distances(scene.corners, result.xy) < 1.0).all()



def test_edges_along_a_fisheye_rims_thin_rows_link_at_the_near_offset(monkeypatch):
    """At a fisheye close-up's rim the rows thin to a few px, thinner than 0.12 of the edges along
    them; an edge also passes on samples 0.04 of its length off it (ccdn.linked.EDGE_OFFSETS): the
    stress set's render 7190027 loses 1 of its 90 corners, 13 with the far samples alone."""
    scene = stress_scene("fisheye-close-up", 7_190_027)

    def found(result) -> int:
        return int((nearest_distances(result.xy, scene.corners) < 1.0).sum())

    assert found(ccdn.Detector(threads=2).detect(scene.image)) >= len(scene.corners) - 2
    monkeypatch.setattr(ccdn.linked, "EDGE_OFFSETS", ccdn.linked.EDGE_OFFSETS[:1])
    assert found(ccdn.Detector(threads=2).detect(scene.image)) <= len(scene.corners) - 10


def test_a_fisheye_close_up_mostly_rim_is_told_by_its_largest_square(monkeypatch):
    """A fisheye close-up whose few central squares span ~150 px and whose many rim squares a few
    (the stress set's render 7190050: 103 corners): the longest tenth of its steps is short, so a
    linked board is judged a close-up by its longest step (ccdn.grid._close_up with largest=1.0).
    Nearly all its corners are found; judged by the longest tenth, none."""
    scene = stress_scene("fisheye-close-up", 7_190_050)

    def found() -> int:
        return int((nearest_distances(ccdn.Detector(threads=2).detect(scene.image).xy, scene.corners) < 1.0).sum())

    assert found() >= len(scene.corners) - 5
    tenth = ccdn.grid._close_up
    monkeypatch.setattr(ccdn.grid, "_close_up", lambda board, shape, largest=0.9: tenth(board, shape, 0.9))
    assert found() == 0


def test_a_step_far_longer_than_the_one_before_it_is_no_edge_of_the_board(monkeypatch):
    """Beside a board of ~10 px squares (the stress set's render 7090160: 49 corners) a corner
    linked to a point 344 px across the frame, and that one step made the board a "close-up" that
    took 4 false corners. A step over ccdn.linked.MAX_STEP_RATIO times the one before it on its line
    (or under its inverse) drops its corners (a lens changes squares' size ~3x at most): the board
    alone is found."""
    scene = stress_scene("small-squares", 7_090_160)
    result = ccdn.Detector(threads=2).detect(scene.image)
    assert [len(board) for board in result.boards] == [len(scene.corners)]
    assert (nearest_distances(scene.corners, result.xy) < 1.0).all()
    monkeypatch.setattr(ccdn.linked, "_steady_steps", lambda xy, cells, steps: cells)
    unchecked = ccdn.Detector(threads=2).detect(scene.image)
    assert (nearest_distances(scene.corners, unchecked.xy) > 20).any()
