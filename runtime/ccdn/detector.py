"""The Detector: image -> network -> peaks -> refinement, built once and called many times."""

from __future__ import annotations

import os
import time

import numpy as np

from .grid import find_boards
from .image import DEFAULT_MAX_PIXELS, read_gray, to_gray
from .peaks import find_peaks, kmeans_outliers, suppress
from .refine import refine
from .result import Detection
from .session import ScoreSession

ImageInput = str | os.PathLike | np.ndarray


class Detector:
    """Checkerboard inner-corner detector around one onnxruntime CPU session.

    model: a bundled model's name (default "paper") or a path to an .onnx file.
    threads: intra-op threads (default: available CPUs, capped at 4). spinning: False keeps idle
    threads from busy-waiting, for apps that share the CPU.
    relative, floor: keep score peaks >= max(relative * max score, floor) (paper: relative 0.5).
    cluster: apply the paper's k-means++ outlier removal. refinement: "saddle", "cornersubpix", "none".
    detect() is thread-safe: one Detector may serve several threads.
    """

    def __init__(self, model: str | os.PathLike | None = None, threads: int | None = None, *, spinning: bool = True,
                 relative: float = 0.5, floor: float = 0.3, cluster: bool = True, refinement: str = "saddle",
                 max_pixels: int = DEFAULT_MAX_PIXELS) -> None:
        self._session = ScoreSession(model, threads, spinning)
        self.model = self._session.info
        self.threads = self._session.threads
        self.relative, self.floor, self.cluster = relative, floor, cluster
        self.refinement = refinement
        self.max_pixels = max_pixels

    def load(self, image: ImageInput) -> np.ndarray:
        """A path or an array -> validated HxW uint8 gray (raises ccdn.ImageError)."""
        if isinstance(image, np.ndarray):
            return to_gray(image, self.max_pixels)
        return read_gray(image, self.max_pixels)

    def detect(self, image: ImageInput, *, boards: bool = False, board_size: tuple[int, int] | None = None) -> Detection:
        """Inner corners of the checkerboard(s) in `image` (path, or HxW / HxWx3 BGR array).

        boards=True also links the corners into boards (ccdn.grid.find_boards; board_size=(cols, rows)
        keeps only boards of that size); otherwise Detection.boards is empty and costs nothing.
        """
        t0 = time.perf_counter()
        gray = self.load(image)
        t1 = time.perf_counter()
        score = self._session.scores(gray)
        t2 = time.perf_counter()
        xy, values = find_peaks(score, self.relative, self.floor)
        if self.cluster and len(xy):
            keep = kmeans_outliers(xy)
            xy, values = xy[keep], values[keep]
        refined, ok = refine(gray, xy, self.refinement)
        refined, values = refined[ok], values[ok]
        distinct = suppress(refined, radius=1.0)  # refinement can move two peaks onto one corner
        refined, values = refined[distinct], values[distinct]
        found = find_boards(gray, refined, values, board_size) if boards else ()
        t3 = time.perf_counter()
        timings = {"load": (t1 - t0) * 1e3, "network": (t2 - t1) * 1e3, "postprocess": (t3 - t2) * 1e3}
        return Detection(refined, np.clip(values, 0, 1), (gray.shape[1], gray.shape[0]),
                         f"{self.model.name} {self.model.version}", found, timings)

    def scores(self, image: ImageInput) -> np.ndarray:
        """The network's raw (H, W) float32 score map, for inspection."""
        return self._session.scores(self.load(image))


_default: Detector | None = None


def detect(image: ImageInput) -> Detection:
    """Detect with a cached default Detector (the "paper" model, default settings)."""
    global _default
    if _default is None:
        _default = Detector()
    return _default.detect(image)
