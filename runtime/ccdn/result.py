"""The detection result: frozen, (x, y) float32 arrays, deterministic order, JSON-ready."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .board import Board


def _frozen(a: np.ndarray, dtype, shape_tail: tuple[int, ...]) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=dtype).reshape((-1, *shape_tail))
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Detection:
    """Corners found in one image.

    xy: (N, 2) float32, (x, y) sub-pixel positions; (0, 0) is the centre of the top-left pixel.
    score: (N,) float32 confidence in [0, 1]: the network's response at the corner, clipped. Corners
    the network found score at least the detector's threshold (max(relative x the image's best,
    floor)); corners grid completion took from the image (see ccdn.grid) carry the network's lower
    response there, so `score >= t` keeps only corners the network itself is that sure of.
    Corners are sorted by descending score, ties by (y, x); no corners gives arrays of length 0.
    image_size: (width, height) of the input; model: name and version of the model used.
    boards: the checkerboards the corners form (ccdn.board.Board, indices into xy), largest first;
    empty unless asked for (Detector.detect(..., boards=True)).
    """

    xy: np.ndarray
    score: np.ndarray
    image_size: tuple[int, int]
    model: str = ""
    boards: tuple[Board, ...] = ()
    timings_ms: dict[str, float] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "xy", _frozen(self.xy, np.float32, (2,)))
        object.__setattr__(self, "score", _frozen(self.score, np.float32, ()))
        if len(self.xy) != len(self.score):
            raise ValueError(f"xy has {len(self.xy)} rows but score has {len(self.score)}")

    def __len__(self) -> int:
        return len(self.xy)

    def to_dict(self) -> dict:
        return {
            "image_size": list(self.image_size),
            "model": self.model,
            "corners": [[round(float(x), 3), round(float(y), 3)] for x, y in self.xy],
            "score": [round(float(s), 4) for s in self.score],
            "boards": [b.to_dict() for b in self.boards],
        }

    def to_json(self) -> str:
        import json  # here, not at the top: ~3 ms of every start that never writes JSON

        return json.dumps(self.to_dict())
