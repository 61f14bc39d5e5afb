"""Edge-line refinement, which noisy frames (ccdn.checker.image_noise) switch on, on renders with exact labels."""

from __future__ import annotations

import cv2
import numpy as np

from conftest import calm_scene, stress_scene
from ccdn.checker import NOISY_SIGMA, image_noise
from ccdn.edges import lattice_steps, on_straight_lines, refine_on_edges


def _calm_scene(seed: int, noise: float):
    return calm_scene(seed, p_noise=1.0 if noise else 0.0, noise_sigma=(noise, noise), square_px=(18, 30),
                      max_tilt_deg=30)


def _errors(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(found[:, None].astype(np.float64) - truth[None], axis=2).min(1)


def _saddle_only(monkeypatch) -> None:
    """Switch the edge-line refinement off: no frame counts as noisy, no board as straight."""
    monkeypatch.setattr("ccdn.detector.NOISY_SIGMA", np.inf)
    monkeypatch.setattr("ccdn.edges.FLAT_BOARD", 0.0)


def _compare(detector, monkeypatch, scenes) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the labelled corners found with the edge stage and without it (_saddle_only)."""
    with_edges = [detector.detect(scene.image) for scene in scenes]
    assert all("edges" in found.timings_ms for found in with_edges)
    with monkeypatch.context() as patch:
        _saddle_only(patch)
        without = [detector.detect(scene.image) for scene in scenes]
    on = np.concatenate([_errors(found.xy, scene.corners) for found, scene in zip(with_edges, scenes)])
    off = np.concatenate([_errors(found.xy, scene.corners) for found, scene in zip(without, scenes)])
    assert len(on) == len(off) > 100
    hits = (on < 1.5) & (off < 1.5)  # detections of labelled corners (not ones the renderer ignores)
    assert hits.mean() > 0.95
    return on[hits], off[hits]


def test_edge_lines_beat_the_saddle_fit_in_heavy_noise(detector, monkeypatch):
    """On noisy renders (18 grey levels) the detector moves board corners to their edge lines, which
    land closer to the exact corners than the saddle fit it returns with the edge stage off."""
    scenes = [_calm_scene(seed, 0.07) for seed in (3, 4, 5)]
    assert all(image_noise(scene.image) >= NOISY_SIGMA for scene in scenes)
    on, off = _compare(detector, monkeypatch, scenes)
    assert on.mean() < 0.8 * off.mean()


def test_edge_lines_beat_the_saddle_fit_on_straight_clean_boards(detector, monkeypatch):
    """Without noise too, where a board's lines are straight (a pinhole lens): about half the error."""
    scenes = [_calm_scene(seed, 0.0) for seed in (3, 4, 5)]
    assert all(image_noise(scene.image) < NOISY_SIGMA for scene in scenes)
    on, off = _compare(detector, monkeypatch, scenes)
    assert on.mean() < 0.7 * off.mean()
    assert on.mean() < 0.03


def test_the_number_of_edge_line_fits_is_the_best_one(detector, monkeypatch):
    """Each fit resamples the profiles around the corner the last one moved; later fits drift
    instead of converging (measured on 88878 stress-render corners: the comment at ITERATIONS). On
    motion-blurred renders, where the drift is largest, one fit fewer and one more both land
    farther from the exact corners than ITERATIONS fits."""
    import ccdn.edges

    scenes = [stress_scene("motion-blur", seed) for seed in (7030011, 7030032, 7030044, 7030061)]

    def mean_error(fits: int) -> float:
        monkeypatch.setattr(ccdn.edges, "ITERATIONS", fits)
        found = [detector.detect(scene.image) for scene in scenes]
        errors = np.concatenate([_errors(f.xy, scene.corners) for f, scene in zip(found, scenes)])
        assert len(errors) > 200 and (errors < 1.0).mean() > 0.95
        return float(errors[errors < 1.0].mean())

    best = ccdn.edges.ITERATIONS
    assert mean_error(best) < mean_error(best + 1)
    if best > 1:
        assert mean_error(best) < mean_error(best - 1)


def test_curved_and_thin_boards_keep_the_saddle_fit(detector):
    """A fisheye lens bends the lattice lines, which the edge lines would fit straight, and squares a
    few pixels thin leave no room for edge profiles: on_straight_lines leaves those corners alone."""
    def straight(scene) -> np.ndarray:
        board = detector.detect(scene.image).boards[0]
        assert len(board) >= 40
        return on_straight_lines(board, lattice_steps(board))

    assert straight(stress_scene("clean", 7000004)).all()
    assert not straight(stress_scene("fisheye", 7010004)).any()
    steep = straight(stress_scene("extreme-pose", 7100013))  # tilted 60-75 degrees: its far squares are slivers
    assert 0 < steep.sum() < 0.5 * len(steep)


def test_lattice_steps_mirror_missing_neighbours():
    from ccdn.board import Board

    grid = np.array([(r, c) for r in range(2) for c in range(3)], np.int32)
    xy = (grid[:, ::-1] * [10.0, 12.0] + [5, 7]).astype(np.float32)
    board = Board(np.arange(6), grid, xy, 3, 2)
    steps = lattice_steps(board)
    np.testing.assert_allclose(steps[:, 0], [[10, 0]] * 6)  # +col, mirrored at the last column
    np.testing.assert_allclose(steps[:, 1], [[-10, 0]] * 6)
    np.testing.assert_allclose(steps[:, 2], [[0, 12]] * 6)  # +row, mirrored on the last row
    np.testing.assert_allclose(steps[:, 3], [[0, -12]] * 6)


def test_profiles_without_contrast_raise_no_warnings(detector):
    """A noisy render where some edge profiles are flat (contrast 0): they are unusable, and the
    detection emits no numpy warning (an inf - inf sum did, in the app's log)."""
    import warnings

    from ccdn_training.synth import SceneConfig, render_scene

    image = render_scene(np.random.default_rng(7021), SceneConfig()).image
    assert image_noise(image) >= NOISY_SIGMA
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = detector.detect(image)
    assert "edges" in found.timings_ms and len(found.boards) > 0


def test_refining_no_corners_returns_empty_arrays(examples):
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    xy, moved = refine_on_edges(gray, np.zeros((0, 2), np.float32), np.zeros((0, 4, 2)))
    assert xy.shape == (0, 2) and moved.shape == (0,)
