"""Shared fixtures: the bundled examples with exact labels, real-dev photos when ../shared is present."""

from __future__ import annotations

import json
from functools import lru_cache
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from ccdn.board import Board

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
REAL_DEV = ROOT.parent / "shared" / "data" / "real-dev"


@pytest.fixture(scope="session")
def examples() -> dict[str, dict]:
    """name -> {"path", "corners" (N, 2), "boards"} for the bundled rendered examples."""
    meta = json.loads((EXAMPLES / "labels.json").read_text())["images"]
    return {Path(m["file"]).stem: {"path": EXAMPLES / m["file"], "corners": np.asarray(m["corners"], np.float64).reshape(-1, 2),
                                   "boards": m["boards"]} for m in meta}


@pytest.fixture(scope="session")
def small_board(examples) -> dict:
    """The bundled board shrunk to 256x192 px (squares ~10 px: too small for a halved 640x480 frame)
    on a plain 640x480 frame: {"frame", "corners" (N, 2)}."""
    import cv2

    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    frame = np.full_like(gray, int(np.median(gray)))
    frame[150:342, 200:456] = cv2.resize(gray, (256, 192), interpolation=cv2.INTER_AREA)
    frame.setflags(write=False)
    return {"frame": frame, "corners": (examples["board"]["corners"] + 0.5) * 0.4 - 0.5 + [200, 150]}


@pytest.fixture(scope="session")
def real_dev() -> list[dict]:
    if not (REAL_DEV / "labels.json").is_file():
        pytest.skip("../shared/data/real-dev is absent")
    meta = json.loads((REAL_DEV / "labels.json").read_text())["images"]
    return [{"path": REAL_DEV / "images" / m["file"], "source": m["source"],
             "corners": np.concatenate([np.asarray(b["corners"], np.float64).reshape(-1, 2) for b in m["boards"]])}
            for m in meta]


@pytest.fixture(scope="session")
def detector():
    import ccdn

    return ccdn.Detector(threads=2)


def nearest_distances(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """For each true point, the distance to the nearest found point (inf if none)."""
    if len(found) == 0:
        return np.full(len(truth), np.inf)
    return np.linalg.norm(truth[:, None] - found[None].astype(np.float64), axis=2).min(1)


ROTATIONS = [np.array(m) for m in ([[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]])]


def index_map(board, true_grid: np.ndarray) -> np.ndarray | None:
    """The proper rotation R with found = R @ true + offset for every corner of a ccdn.board.Board
    (true_grid: its corners' true (row, col)), or None if there is none."""
    for rot in ROTATIONS:
        offset = board.grid - true_grid @ rot.T
        if (offset == offset[0]).all():
            return rot
    return None


def calm_scene(seed: int, **changes):
    """A render of one board without lens, blur, noise or lighting effects (ccdn_training.synth),
    with `changes` to its SceneConfig."""
    from ccdn_training.synth import SceneConfig, render_scene

    calm = dict(p_no_board=0, p_two_boards=0, p_occluder=0, p_blur=0, p_motion=0, p_defocus=0, p_noise=0, p_jpeg=0,
                p_glare=0, p_shadow=0, p_dark=0, p_low_contrast=0, p_radial=0, p_fisheye=0, p_invert=0)
    return render_scene(np.random.default_rng(seed), SceneConfig(**{**calm, **changes}))


def no_holes(board, shape):
    """ccdn.holes.predicted_holes finding none (monkeypatch ccdn.detector.predicted_holes with it): a
    shrunk pass's boards kept as it found them, to judge another mechanism alone."""
    return np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 4, 2))


def as_fitted(gray, board, steps):
    """ccdn.outliers.off_lattice leaving every corner as it is (monkeypatch ccdn.detector.off_lattice with
    it): each corner where the fits before it put it, to judge another mechanism alone."""
    return board.xy, np.ones(len(board), bool)


def no_growth_into_shade(gray, board, *rest):
    """ccdn.shaded.grown_into_shade growing nothing (monkeypatch ccdn.detector.grown_into_shade with
    it): a board kept without its part in deep shade, to judge another mechanism alone."""
    return board, np.zeros((0, 2), np.float32), np.zeros(0, np.float32)


def stress_scene(subset: str, seed: int):
    """Render `seed` of benchmarks/stress.py's `subset` as the benchmark does (its calm scene with the
    subset's condition), so that a test and the benchmark's table speak of the same image."""
    import sys

    from ccdn_training.synth import SceneConfig, render_scene

    if str(ROOT / "benchmarks") not in sys.path:
        sys.path.insert(0, str(ROOT / "benchmarks"))
    from stress import CALM, SUBSETS

    return render_scene(np.random.default_rng(seed), SceneConfig(**{**CALM, **SUBSETS[subset]}))


# a clean frame for render(): one board, no lens, blur, noise or lighting effects, squares 18-45 px
CLEAN = dict(p_no_board=0.0, p_two_boards=0.0, p_occluder=0.0, p_blur=0.0, p_motion=0.0, p_defocus=0.0,
             noise_sigma=(0.0, 0.01), p_jpeg=0.0, p_low_contrast=0.0, p_dark=0.0, p_glare=0.0, p_shadow=0.0,
             square_px=(18.0, 45.0), max_tilt_deg=45.0, p_radial=0.0, p_fisheye=0.0)


@lru_cache(maxsize=None)
def render(seed: int, **changes):
    """A render (ccdn_training.synth) of one board on a clean frame (CLEAN: no lens, blur, noise or
    lighting effects, squares 18-45 px), with `changes` to its SceneConfig; cached by seed."""
    from ccdn_training.synth import SceneConfig, render_scene

    return render_scene(np.random.default_rng(seed), SceneConfig(**{**CLEAN, **changes}))


def whole_boards(n: int, **changes) -> list:
    """The first n renders (by seed) whose single board is entirely visible."""
    scenes = (render(seed, **{"square_px": (14.0, 22.0), **changes}) for seed in range(50))
    found = list(islice((s for s in scenes if len(s.corners) == s.boards[0][0] * s.boards[0][1]), n))
    assert len(found) == n
    return found


def true_part(board: Board, scene) -> tuple[Board, np.ndarray]:
    """The board's corners within 1 px of a true corner, as a Board, and those true corners' indices."""
    distance = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    true = distance.min(1) < 1.0
    kept = Board(board.corner_index[true], board.grid[true], board.xy[true], board.cols, board.rows)
    return kept, distance[true].argmin(1)


def true_board(board, scene, within: float) -> bool:
    """Whether a found board's corners lie on one true board of the render, indexed as it is (one
    rotation and offset), each within `within` px of its label (the nearest one)."""
    distance = np.linalg.norm(board.xy[:, None] - scene.corners[None], axis=2)
    label = distance.argmin(1)
    return (len(set(scene.board_index[label])) == 1 and index_map(board, scene.grid[label]) is not None
            and distance.min(1).max() < within)
