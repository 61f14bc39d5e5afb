"""ccdn and its peer detectors behind one call, for side-by-side benchmarks.

Every adapter answers `detect(gray, board_size) -> (N, 2) float64 (x, y)` in one pixel convention:
(0, 0) is the centre of the top-left pixel. All four libraries already use it: on nine clean and
inverted stress renders with exact labels, each one's mean offset is under 0.015 px in x and in y,
so there is no 0.5 px shift to correct.
Only OpenCV uses `board_size` (cols, rows of inner corners); the others find corners without it.
Each peer is optional: an adapter whose library is not installed is skipped with a note.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import version

import numpy as np

BoardSize = tuple[int, int]


@dataclass(frozen=True)
class Adapter:
    """A named detector: `detect(gray HxW uint8, board_size)` -> (N, 2) float64 (x, y); `note` says how it runs.
    `boards` (detectors that index their corners): the last detect's boards as (grid (M, 2) row, col;
    xy (M, 2)) pairs."""

    name: str
    detect: Callable[[np.ndarray, BoardSize], np.ndarray]
    note: str
    boards: Callable[[], list[tuple[np.ndarray, np.ndarray]]] | None = None


def ccdn_adapter(model: str | os.PathLike | None, threads: int | None, fast_check: bool = False,
                 exhaustive: bool = False, coarse_model: str | os.PathLike | None = None) -> Adapter:
    """ccdn.Detector with its default settings (and its fast check, exhaustive search or shrunk
    passes' model when asked)."""
    import ccdn

    detector = ccdn.Detector(model, threads, coarse_model=coarse_model, fast_check=fast_check, exhaustive=exhaustive)
    last: list = [None]

    def detect(gray: np.ndarray, size: BoardSize) -> np.ndarray:
        last[0] = detector.detect(gray)
        return last[0].xy.astype(np.float64)

    check = ", fast check" if fast_check else ", exhaustive" if exhaustive else ""
    return Adapter("ccdn", detect, f"model {detector.models} {detector.model.version}, {detector.threads} threads{check}",
                   lambda: [(b.grid, b.xy.astype(np.float64)) for b in last[0].boards])


def opencv_adapter(threads: int | None) -> Adapter:
    """cv2.findChessboardCornersSB given the board size, as it requires; all corners of one board or none."""
    import cv2

    if threads:
        cv2.setNumThreads(threads)
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY

    def detect(gray: np.ndarray, size: BoardSize) -> np.ndarray:
        found, corners = cv2.findChessboardCornersSB(gray, size, flags=flags)
        return corners.reshape(-1, 2).astype(np.float64) if found else np.zeros((0, 2))

    return Adapter("opencv", detect, f"OpenCV {cv2.__version__} findChessboardCornersSB(EXHAUSTIVE | ACCURACY), "
                                     f"{cv2.getNumThreads()} threads; needs the board size; finds one board at most")


def chess_corners_adapter() -> Adapter:
    """chess_corners.Detector with the library's default config; orientation off (unused, positions unchanged)."""
    import chess_corners

    detector = chess_corners.Detector(chess_corners.DetectorConfig().without_orientation())

    def detect(gray: np.ndarray, size: BoardSize) -> np.ndarray:
        return detector.detect(np.ascontiguousarray(gray)).xy.astype(np.float64)

    return Adapter("chess-corners", detect, f"chess-corners {version('chess_corners')}: ChESS, default DetectorConfig "
                                            "without orientation; the library's own threading")


def libcbdetect_adapter() -> Adapter:
    """libCBDetect's corner stage (Geiger et al.'s corners, scored and non-maximum suppressed).

    Its board stage is left out: through these bindings (1.0.5) it seeds its search from the clock, so
    results change run to run; it returns one board only (the last found); it kills the process
    (SIGFPE) on an image without corners; and, by its source, it reads missing corners (index -1)
    out of bounds.
    """
    from libCBDetect import Checkerboard

    finder = Checkerboard()
    finder.show_processing = False  # it prints progress to stdout otherwise

    def detect(gray: np.ndarray, size: BoardSize) -> np.ndarray:
        h, w = gray.shape
        finder.array_to_image(gray.astype(np.float64).ravel(), h, w)  # copied back into an 8-bit image
        finder.find_corners()
        u, v = np.zeros(finder.number_of_corners), np.zeros(finder.number_of_corners)
        finder.get_corners(u, v)
        return np.stack([u, v], 1)

    return Adapter("libcbdetect", detect, f"libCBDetect {version('libcbdetect')}: corner stage (find_corners), "
                                          "default parameters, no board stage")


DETECTORS = ["ccdn", "opencv", "chess-corners", "libcbdetect"]


def load_adapters(names: list[str], model: str | None, threads: int | None, fast_check: bool = False,
                  exhaustive: bool = False, coarse_model: str | None = None) -> tuple[list[Adapter], dict[str, str]]:
    """The adapters named, in order, and a note for each one skipped because its library is missing."""
    factories: dict[str, Callable[[], Adapter]] = {
        "ccdn": lambda: ccdn_adapter(model, threads, fast_check, exhaustive, coarse_model),
        "opencv": lambda: opencv_adapter(threads),
        "chess-corners": chess_corners_adapter,
        "libcbdetect": libcbdetect_adapter,
    }
    adapters, skipped = [], {}
    for name in names:
        try:
            adapters.append(factories[name]())
        except ImportError as exc:
            skipped[name] = f"skipped: {exc}"
    return adapters, skipped
