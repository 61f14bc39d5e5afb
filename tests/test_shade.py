"""ccdn.shade: how unevenly a board is lit, and the frame with its light levelled."""

from __future__ import annotations

import numpy as np
import pytest

from ccdn.edges import lattice_steps
from ccdn.board import Board
from ccdn.grid import SHADE_SPREAD
from ccdn.shade import across_shadows_edge, levelled, light_envelope, light_levels, light_spread, points_light_spread
from conftest import stress_scene

pytest.importorskip("ccdn_training.synth")


def true_board(scene) -> tuple[np.ndarray, np.ndarray]:
    """A render's one board from its labels: corners (M, 2) float64 and lattice steps (M, 4, 2)."""
    grid = scene.grid.astype(np.int32)
    board = Board(np.arange(len(grid)), grid, scene.corners.astype(np.float32), int(grid[:, 1].max() + 1),
                  int(grid[:, 0].max() + 1))
    return scene.corners.astype(np.float64), lattice_steps(board)


@pytest.mark.parametrize("subset, seed, low, high", [("clean", 7_000_000, 1.0, 1.2), ("glare", 7_070_000, 1.0, 1.5),
                                                     ("shadow", 7_160_393, 10.0, 16.0)])
def test_light_spread_tells_a_board_under_a_shadow_from_one_under_one_light(subset, seed, low, high):
    """The lightest quads of a board under one light, glare included, differ by well under
    SHADE_SPREAD across it (measured 1.07 and 1.30 on these renders); under the shadow render
    7160393's, which takes 80-95 % of the light, by 12.7x."""
    scene = stress_scene(subset, seed)
    xy, steps = true_board(scene)
    spread = light_spread(light_levels(scene.image, xy, steps))
    assert low <= spread <= high
    assert (spread > SHADE_SPREAD) == (subset == "shadow")


@pytest.mark.parametrize("subset, seed, low, high", [("clean", 7_000_000, 1.0, 1.2), ("glare", 7_070_000, 1.0, 1.6),
                                                     ("shadow", 7_160_393, 10.0, 16.0)])
def test_points_light_spread_reads_loose_corners_as_light_spread_reads_their_board(subset, seed, low, high):
    """From the points alone (the light level under each, for squares of their nearest-neighbour
    gap) the same renders' corners read as their boards do: 1.06, 1.41 and 13.3x."""
    scene = stress_scene(subset, seed)
    gaps = np.linalg.norm(scene.corners[:, None] - scene.corners[None], axis=2)
    np.fill_diagonal(gaps, np.inf)
    envelope = light_envelope(scene.image, float(np.median(gaps.min(1))))
    spread = points_light_spread(envelope, scene.corners.astype(np.float64))
    assert low <= spread <= high
    assert (spread > SHADE_SPREAD) == (subset == "shadow")


def test_levelling_evens_out_a_shadow_and_keeps_the_squares_contrast():
    """On the levelled frame the shadowed board's lightest quads differ by under 10 % across it
    (12.7x on the frame itself), and at every corner its dark quads stay well below its light ones."""
    scene = stress_scene("shadow", 7_160_393)
    xy, steps = true_board(scene)
    square = float(np.nanmedian(np.linalg.norm(steps, axis=2)))
    flat = levelled(scene.image, square)
    assert flat.dtype == np.uint8 and flat.shape == scene.image.shape
    assert light_spread(light_levels(flat, xy, steps)) < 1.1
    quads = light_levels(flat, xy, steps)  # (4, M)
    assert (quads.min(0) < 0.6 * quads.max(0)).all()


def test_levelling_leaves_a_black_frame_black_and_lifts_an_even_one_to_white():
    """The light level is floored at ccdn.shade.MIN_LIGHT, so a black frame is not noise blown up
    (and divides by nothing); an evenly lit frame is its own light level."""
    assert levelled(np.zeros((48, 64), np.uint8), 10.0).max() == 0
    assert (levelled(np.full((48, 64), 200, np.uint8), 10.0) == 255).all()


def test_corners_across_a_shadows_edge_are_told_by_their_two_light_quads():
    """A shadow's edge across a corner leaves its two light quads in different light: 16 of the 44
    corners of the shadow render 7160393, none of a clean render's 74; glare's bright spot does it
    to 5 of 69 (the detector only asks on a board lit as unevenly as a shadow leaves it)."""
    counts = {}
    for subset, seed in (("clean", 7_000_000), ("glare", 7_070_000), ("shadow", 7_160_393)):
        scene = stress_scene(subset, seed)
        xy, steps = true_board(scene)
        counts[subset] = int(across_shadows_edge(light_levels(scene.image, xy, steps)).sum())
    assert counts["clean"] == 0 and counts["glare"] <= 8 and counts["shadow"] >= 12
