"""Where the full-frame pass of coarse-to-fine must look: boxes around the shrunk pass's responses.

The full-frame pass runs only when no shrunk pass found a board with big enough squares: small
squares, boards seen too steeply, or no board at all. The network of the finest shrunk pass has
then already scored the whole frame, and a board's corners score there even when they lie too
close together to be told apart (measured on the stress renders that reach the full frame: the
shrunk score within 2 px of nearly every true corner is >= 0.2). So the full-resolution network
runs only on the boxes around the shrunk pixels scoring >= LOOK_SCORE, grown by LOOK_MARGIN
shrunk pixels (a board's neighbouring corners the shrunk pass scored lower), and the rest of the
score map is 0; a frame without any such response costs no full-resolution pass at all. Many
scattered boxes (more than MAX_BOXES) are judged by their cost with their halos and network calls,
which then add up; where the boxes would cost more than WHOLE_FRAME_SHARE of the frame, the whole
frame runs.
"""

from __future__ import annotations

import cv2
import numpy as np

LOOK_SCORE = 0.1  # shrunk score at or above which the full frame is looked at (the peaks' floor is 0.25)
LOOK_MARGIN = 4  # shrunk px around those pixels
MAX_BOXES = 64  # up to this many boxes (the stress renders have at most 30) their area alone decides; beyond it
# their halos and calls count too (scattered specks: a 2000x1500 boardless frame's 144 boxes cost 210 ms where the
# whole frame costs 615)
MOST_BOXES = 1024  # more than this: the whole frame, which also bounds the pairwise nesting test
CALL_PIXELS = 400  # a network call's own cost in pixels' worth (paper-int8: ~0.05 ms a call, ~140 ns a pixel)
WHOLE_FRAME_SHARE = 0.6  # boxes costing more than this share of the frame: run the whole frame instead (a box
# costs more per pixel than the whole frame: its halo, one more network call)


def look_boxes(score: np.ndarray, scale: int, shape: tuple[int, int], halo: int) -> list[tuple[int, int, int, int]] | None:
    """Boxes (top, bottom, left, right) in full-frame pixels of a frame of `shape` where the
    full-resolution network (whose boxes run with `halo` px around them: ccdn.session) must run,
    from the `score` map of a pass on it shrunk `scale` times; [] when nothing responded, None when
    the whole frame is cheaper (most of it covered, or too many boxes)."""
    h, w = shape
    look = (score >= LOOK_SCORE).astype(np.uint8)
    if not look.any():
        return []
    look = cv2.dilate(look, np.ones((2 * LOOK_MARGIN + 1, 2 * LOOK_MARGIN + 1), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(look, connectivity=8)
    if count - 1 > MOST_BOXES:
        return None
    x, y, bw, bh = (stats[1:, i].astype(np.int64) for i in range(4))
    small_h, small_w = score.shape
    # a box at the shrunk frame's far edge reaches the full frame's (a shrunk frame drops h % scale rows)
    bottom = np.where(y + bh >= small_h, h, (y + bh) * scale)
    right = np.where(x + bw >= small_w, w, (x + bw) * scale)
    boxes = np.stack([y * scale, bottom, x * scale, right], 1)
    boxes = boxes[~_nested(boxes)]
    heights, widths = boxes[:, 1] - boxes[:, 0], boxes[:, 3] - boxes[:, 2]
    cost = heights * widths
    if len(boxes) > MAX_BOXES:
        cost = (heights + 2 * halo) * (widths + 2 * halo) + CALL_PIXELS
    if cost.sum() > WHOLE_FRAME_SHARE * h * w:
        return None
    return [tuple(int(v) for v in box) for box in boxes]


def _nested(boxes: np.ndarray) -> np.ndarray:
    """True for boxes inside another (a component in another's hole), which that one's pass scores
    already; of two equal boxes the first is kept."""
    top, bottom, left, right = (boxes[:, i] for i in range(4))
    within = ((top[None] <= top[:, None]) & (bottom[:, None] <= bottom[None]) & (left[None] <= left[:, None])
              & (right[:, None] <= right[None]))  # [i, j]: box i inside box j
    equal = within & within.T
    first = np.arange(len(boxes))[:, None] > np.arange(len(boxes))[None]  # [i, j]: j comes before i
    return ((within & ~equal) | (equal & first)).any(1)
