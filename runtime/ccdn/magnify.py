"""A second look, magnified, at boards seen so steeply that their far squares are slivers.

On a steep view the far end of a board thins to squares a few pixels across, which the network,
trained at 1:1, barely scores and the saddle fit cannot resolve (stress renders: 79 % of corners
with squares under 4 px across missed, 19 % at 4-6 px, 0.4 % above). When the full-frame pass finds
a board whose thinnest squares are under THIN_ALTITUDE px across, the detector runs once more on the
board's surroundings scaled up MAGNIFICATION times (bicubic) and keeps a board found there in place
of the ones it covers when it has more corners. Frames with no board found pay nothing: a
magnified look at every boardless frame's dense responses, which would also find wholly missed
slivers, measured 150-250 ms more per cluttered frame (CHANGES.md).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .checker import altitude
from .edges import lattice_steps
from .grid import Board, largest_first

MAGNIFICATION = 2
THIN_ALTITUDE = 5.0  # px: a board whose thinnest fifth of corners have squares narrower than this is magnified
THIN_SHARE = 0.2  # that fifth
PAD = (0.25, 8.0)  # the region magnified: the thin boards' corners' bounding box grown by this share of its
# size and these px each way, where the steep end the pass lost continues
MAX_SHARE = 0.5  # of the frame's area at most (the magnified pass costs MAGNIFICATION^2 times its pixels)
SAME_CORNER = 2.0  # px: a magnified board's corner this close to one of a board found before: the same board


def thin_region(boards: tuple[Board, ...], shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1): the part of a frame of `shape` (h, w) around the boards whose squares thin
    below THIN_ALTITUDE, to be magnified; None when no board is thin or the region is too large."""
    thin = [board.xy for board in boards if _thinnest(board) < THIN_ALTITUDE]
    if not thin:
        return None
    xy = np.concatenate(thin).astype(np.float64)
    low, high = xy.min(0), xy.max(0)
    pad = PAD[0] * (high - low) + PAD[1]
    h, w = shape
    x0, y0 = np.maximum(np.floor(low - pad), 0).astype(np.int64).tolist()
    x1, y1 = np.minimum(np.ceil(high + pad) + 1, (w, h)).astype(np.int64).tolist()
    if (x1 - x0) * (y1 - y0) > MAX_SHARE * h * w:
        return None
    return x0, y0, x1, y1


def magnified(gray: np.ndarray, region: tuple[int, int, int, int]) -> np.ndarray:
    """The region (x0, y0, x1, y1) of gray scaled up MAGNIFICATION times (bicubic, uint8)."""
    x0, y0, x1, y1 = region
    return cv2.resize(gray[y0:y1, x0:x1], None, fx=MAGNIFICATION, fy=MAGNIFICATION, interpolation=cv2.INTER_CUBIC)


def to_frame(xy: np.ndarray, region: tuple[int, int, int, int]) -> np.ndarray:
    """Positions (N, 2) on the magnified region -> frame pixels (pixel centres map onto pixel centres)."""
    return ((xy + 0.5) / MAGNIFICATION - 0.5 + np.array(region[:2])).astype(np.float32)


def merge(xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...], more_xy: np.ndarray,
          more_values: np.ndarray, more_boards: tuple[Board, ...]):
    """The corners (xy, values) and boards of the full-frame pass and of the magnified one (already
    in frame pixels), with each magnified board that has more corners than the boards it shares
    corners with (SAME_CORNER) in their place, and a magnified board that shares none added. Returns
    xy and values of both passes, one after the other, and the boards kept (largest first, ties:
    top, then left), their corner_index into that xy."""
    kept = list(boards)
    for board in more_boards:
        shares = [_shares_corners(board.xy, old.xy) for old in kept]
        if len(board) > sum(len(old) for old, shared in zip(kept, shares) if shared):
            kept = [old for old, shared in zip(kept, shares) if not shared]
            kept.append(dataclasses.replace(board, corner_index=board.corner_index + len(xy)))
    return np.concatenate([xy, more_xy]), np.concatenate([values, more_values]), tuple(largest_first(kept))


def _thinnest(board: Board) -> float:
    """The median width across (checker.altitude) of the squares at the board's thinnest THIN_SHARE
    of corners, px (inf for a board too small to tell)."""
    steps = lattice_steps(board)
    widths = altitude(steps[:, 0], steps[:, 2])
    widths = np.sort(widths[np.isfinite(widths)])
    if len(widths) == 0:
        return float("inf")
    return float(np.median(widths[: max(3, int(THIN_SHARE * len(widths)))]))


def _shares_corners(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether any corner of a (N, 2) lies within SAME_CORNER px of one of b (M, 2)."""
    d2 = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1)
    return bool((d2 <= SAME_CORNER**2).any())
