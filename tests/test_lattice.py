"""Lattice geometry (ccdn.lattice) on a render's exact labels: projections, distances, the frame's
margin and which empty cells a board holds on two sides."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ccdn.lattice import (EDGE_MARGIN, distances, held_on_two_sides, inside_margin, project_with_steps,
                          square_enough)
from conftest import calm_scene

pytest.importorskip("ccdn_training.synth")


def test_a_flat_boards_homography_projects_its_grid_onto_its_labels_with_the_steps_between_them():
    """A flat board under a pinhole lens is a homography of its grid: projecting the (col, row) grid
    gives the labelled corners, and u, v are the steps to the +col and +row neighbours' projections."""
    scene = calm_scene(3)
    grid = scene.grid[:, ::-1].astype(np.float64)  # (col, row), like (x, y)
    homography, _ = cv2.findHomography(grid, scene.corners.astype(np.float64), 0)
    points, u, v = project_with_steps(homography, grid)
    assert np.abs(points - scene.corners).max() < 0.05
    right, _, _ = project_with_steps(homography, grid + [1, 0])
    down, _, _ = project_with_steps(homography, grid + [0, 1])
    assert np.allclose(points + u, right) and np.allclose(points + v, down)
    assert square_enough(u, v).all()  # a calm view's cells are far from flat
    assert not square_enough(u, u + 0.1 * v).any()  # a basis this close to parallel is (MIN_SINE)


def test_distances_match_the_direct_norm_and_the_margin_keeps_corners_off_the_frames_edge():
    scene = calm_scene(5)
    a, b = scene.corners[:7].astype(np.float64), scene.corners.astype(np.float64)
    assert np.array_equal(distances(a, b), np.linalg.norm(a[:, None] - b[None], axis=2))
    h, w = scene.image.shape
    xy = np.array([[EDGE_MARGIN, EDGE_MARGIN], [EDGE_MARGIN - 0.01, 100.0], [w - 1 - EDGE_MARGIN, h - 1 - EDGE_MARGIN],
                   [100.0, h - 1 - EDGE_MARGIN + 0.01]])
    assert inside_margin(xy, scene.image.shape).tolist() == [True, False, True, False]


def test_an_empty_cell_is_held_on_two_sides_inside_the_board_or_in_a_notch_not_beyond_its_outline():
    filled = np.zeros((6, 7), bool)
    filled[1:5, 1:6] = True  # a 4 x 5 board on a canvas with a margin
    filled[2, 3] = False  # a hole inside it
    filled[1, 1] = False  # its outline's corner cut off: a notch
    held = {tuple(cell) for cell in held_on_two_sides(filled)}
    assert held == {(2, 3), (1, 1)}  # nothing beyond the outline, where a cell has one neighbour at most
