"""Second looks, magnified or stretched, at boards seen so steeply that their squares are slivers.

On a steep view the far end of a board thins to squares a few pixels across, which the network,
trained at 1:1, barely scores and the saddle fit cannot resolve (stress renders: 79 % of corners
with squares under 4 px across missed, 19 % at 4-6 px, 0.4 % above). When the full-frame pass finds
a board whose thinnest squares are under THIN_ALTITUDE px across, the detector runs once more on the
board's surroundings scaled up MAGNIFICATION times (bicubic) and keeps a board found there in place
of the ones it covers when it has more corners.

When the full-frame pass runs, the detector also looks at the clusters of score peaks that no
board covers and that are shaped like a sliver (SLIVER_PEAKS peaks or more, SLIVER_ELONGATION times
longer than wide; peaks linked within LOOSE_LINK px, and again within TIGHT_LINK, where clutter
beside a sliver would otherwise merge with it), each resampled along its long axis and stretched
STRETCH times across it: a board seen so steeply that no pass finds it is a sliver whose cells are
sheared flatter than a lattice is grown over (ccdn.lattice.MIN_SINE), which magnifying keeps
(angles do not change), and stretching across opens up. Exhaustive detection (Detector(exhaustive=True)) looks at every
cluster of LOOSE_PEAKS or more, whatever its shape: on a cluttered frame ~30 ms more at 640x480
and 90-190 ms at 2000x1500 (examples/no-board.jpg), where the sliver-shaped ones cost a few ms (README).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .checker import altitude
from .edges import lattice_steps
from .board import Board, largest_first
from .stats import median

MAGNIFICATION = 2
THIN_ALTITUDE = 5.0  # px: a board whose thinnest fifth of corners have squares narrower than this is magnified
THIN_SHARE = 0.2  # that fifth
PAD = (0.25, 8.0)  # the region magnified: the thin boards' corners' bounding box grown by this share of its
# size and these px each way, where the steep end the pass lost continues
MAX_SHARE = 0.5  # of the frame's area at most (the magnified pass costs MAGNIFICATION^2 times its pixels)
SAME_CORNER = 2.0  # px: a magnified board's corner this close to one of a board found before: the same board
LOOSE_PEAKS = 9  # a cluster of at least this many score peaks that no board covers ...
LOOSE_LINK = 12.0  # ... each within this many px of another, is looked at stretched (loose_clusters, stretched) ...
TIGHT_LINK = 8.0  # px: sliver-shaped clusters are also sought among peaks linked this closely, where a looser link
# merges a sliver with clutter beside it (thin grid lines crossing), whose spread then hides the sliver's shape
# and turns its look away from the board's axis
MAX_LOOKS = 8  # ... the largest this many clusters of a frame; by default only sliver-shaped clusters:
SLIVER_PEAKS = 30  # at least this many peaks, ...
SLIVER_ELONGATION = 4.5  # ... their spread (standard deviation) along the long axis this many times that across ...
SLIVER_WIDTH = 2.0  # ... which is at least this many px (not one line of peaks, such as an edge's). Measured on
# 1280 stress renders: the 9 looks that found boards had 50-342 peaks, elongations 5.3-24 and widths 2.9-15 px;
# of the 1159 looks at clusters of any shape, 95 are sliver-shaped, which cost 1.5 of the 17.0 s. 4.0 (tried with
# TIGHT_LINK on 80 fresh extreme-pose renders) found nothing more there for the default and sent clusters of noise
# peaks (4.0-4.5) to looks of 100-330 ms
STRETCH = 3.0  # x across a cluster's long axis (measured on 90 extreme-pose renders: 2x magnified
# isotropically found 8 of the 127 corners of four missed slivers, 3x across alone 109)
MAX_STRETCHED = 2.0  # x the frame's pixels at most per stretched view
COVERED = 3.0  # px: a peak this close to a board's corner, or inside its outline, is that board's


def _link_disk(link: float) -> np.ndarray:
    """The disk of radius half `link` that _linked grows each peak by: overlapping disks link."""
    r = int(link / 2)
    disk = cv2.circle(np.zeros((2 * r + 1,) * 2, np.uint8), (r, r), r, 1, -1)
    disk.setflags(write=False)
    return disk


_LINK_DISKS = {link: _link_disk(link) for link in (LOOSE_LINK, TIGHT_LINK)}


def thin_region(boards: tuple[Board, ...], shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1): the part of a frame of `shape` (h, w) around the boards whose squares thin
    below THIN_ALTITUDE, to be magnified; None when no board is thin or the region is too large."""
    thin = [board.xy for board in boards if thinnest(board) < THIN_ALTITUDE]
    if not thin:
        return None
    xy = np.concatenate(thin).astype(np.float64)
    low, high = xy.min(0), xy.max(0)  # their bounding box, grown by PAD, at most MAX_SHARE of the frame
    pad = PAD[0] * (high - low) + PAD[1]
    h, w = shape
    x0, y0 = np.maximum(np.floor(low - pad), 0).astype(np.int64).tolist()
    x1, y1 = np.minimum(np.ceil(high + pad) + 1, (w, h)).astype(np.int64).tolist()
    if (x1 - x0) * (y1 - y0) > MAX_SHARE * h * w:
        return None
    return x0, y0, x1, y1


def loose_clusters(peaks: np.ndarray, boards: tuple[Board, ...], shape: tuple[int, int],
                   any_shape: bool = False) -> list[np.ndarray]:
    """The clusters (each (K, 2)) of score peaks (N, 2) on a frame of `shape` (h, w) that no board
    covers (COVERED), largest first, at most MAX_LOOKS: a cluster links peaks within LOOSE_LINK px
    of each other and needs LOOSE_PEAKS of them; unless any_shape, only sliver-shaped ones
    (_sliver_shaped), among those and, inside the others, among the clusters of peaks linked within
    TIGHT_LINK px. On a board seen so steeply that its squares are slivers the network still
    scores many corners that no pass links."""
    h, w = shape
    loose = np.asarray(peaks, np.float64).reshape(-1, 2)
    col, row = np.clip(np.rint(loose), 0, (w - 1, h - 1)).astype(np.int64).T  # each peak's pixel
    if boards and len(loose):
        outline = np.zeros(shape, np.uint8)
        for board in boards:
            cv2.fillConvexPoly(outline, cv2.convexHull(np.rint(board.xy).astype(np.int32)), 1)
        corners = np.concatenate([board.xy for board in boards]).astype(np.float64)
        near = ((loose[:, None] - corners[None]) ** 2).sum(-1).min(1) <= COVERED**2
        keep = ~near & (outline[row, col] == 0)
        loose, col, row = loose[keep], col[keep], row[keep]
    if len(loose) < LOOSE_PEAKS:
        return []
    if any_shape:
        return [loose[members] for members in _linked(row, col, shape, LOOSE_LINK, LOOSE_PEAKS)][:MAX_LOOKS]
    least = max(LOOSE_PEAKS, SLIVER_PEAKS)
    clusters, others = [], np.zeros(len(loose), bool)
    for members in _linked(row, col, shape, LOOSE_LINK, least):
        if _sliver_shaped(loose[members]):
            clusters.append(loose[members])
        else:
            others |= members
    if others.any():  # the tighter link splits the others (its clusters nest in the looser link's)
        inside = np.nonzero(others)[0]
        for members in _linked(row[inside], col[inside], shape, TIGHT_LINK, least):
            if _sliver_shaped(loose[inside[members]]):
                clusters.append(loose[inside[members]])
    return sorted(clusters, key=len, reverse=True)[:MAX_LOOKS]  # stable: ties keep the looser link's first


def _linked(row: np.ndarray, col: np.ndarray, shape: tuple[int, int], link: float, least: int) -> list[np.ndarray]:
    """The clusters of the peaks at pixels (row, col) of a frame of `shape` (each a (N,) bool mask
    over them) linking peaks within `link` px of each other, those of at least `least` peaks, largest
    first. Drawn on the peaks' bounding box grown by the disk's radius (within the frame), which
    holds every link: the clusters drawing the whole frame would give, for less."""
    disk = _LINK_DISKS[link]
    r = len(disk) // 2
    top, left = max(row.min() - r, 0), max(col.min() - r, 0)
    bottom, right = min(row.max() + r + 1, shape[0]), min(col.max() + r + 1, shape[1])
    links = np.zeros((bottom - top, right - left), np.uint8)  # each peak's disk of half the link: overlapping
    links[row - top, col - left] = 1  # disks link
    _, labels = cv2.connectedComponents(cv2.dilate(links, disk), connectivity=8)
    label = labels[row - top, col - left]
    counts = np.bincount(label)
    return [label == k for k in np.argsort(-counts, kind="stable") if k and counts[k] >= least]


def _sliver_shaped(cluster: np.ndarray) -> bool:
    """Whether a cluster of peaks (K, 2) could be a steep view's sliver of board: spread
    SLIVER_ELONGATION times farther along its long axis than across, and across by at least
    SLIVER_WIDTH px (a lattice's rows, not one line)."""
    (across, along), _ = _principal_axes(cluster)
    return bool(across >= SLIVER_WIDTH and along >= SLIVER_ELONGATION * across)


def _principal_axes(cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The spreads (standard deviations, px) of points (K, 2) across and along their long axis, and
    those axes as the columns of a (2, 2) array, the long one last."""
    variances, axes = np.linalg.eigh(np.cov(cluster.T))
    return np.sqrt(np.maximum(variances, 0)), axes


def stretched(gray: np.ndarray, cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """gray around a cluster of peaks (K, 2) (loose_clusters), resampled (bicubic) with the cluster's
    long axis along x and stretched STRETCH times across it, and the affine (2, 3) that maps its
    pixels back onto the frame's; None when that image would exceed MAX_STRETCHED x the frame's
    pixels. A board seen very steeply is a sliver along its long axis whose cells are sheared
    flatter than a lattice is grown over (ccdn.lattice.MIN_SINE: stress renders' missed slivers, sines
    0.18-0.31): stretched across, its cells open up (sine 0.25 -> ~0.6 at 3x) and its squares widen."""
    centre = cluster.mean(0)
    along = _principal_axes(cluster)[1][:, 1]
    to_image = np.stack([along, STRETCH * np.array([-along[1], along[0]])])  # (2, 2): frame offsets -> image
    projected = (cluster - centre) @ to_image.T
    low, high = projected.min(0), projected.max(0)
    pad = PAD[0] * (high - low) + PAD[1] * np.array([1.0, STRETCH])
    low, high = low - pad, high + pad
    width, height = (np.ceil(high - low).astype(np.int64) + 1).tolist()
    if width * height > MAX_STRETCHED * gray.size:
        return None
    forward = np.concatenate([to_image, (-to_image @ centre - low)[:, None]], 1)
    image = cv2.warpAffine(gray, forward, (width, height), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return image, cv2.invertAffineTransform(forward)


def from_view(xy: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Positions (N, 2) on a resampled view -> frame pixels, by the view's affine (2, 3) back."""
    return (xy.astype(np.float64) @ affine[:, :2].T + affine[:, 2]).astype(np.float32)


def magnified(gray: np.ndarray, region: tuple[int, int, int, int]) -> np.ndarray:
    """The region (x0, y0, x1, y1) of gray scaled up MAGNIFICATION times (bicubic, uint8)."""
    x0, y0, x1, y1 = region
    return cv2.resize(gray[y0:y1, x0:x1], None, fx=MAGNIFICATION, fy=MAGNIFICATION, interpolation=cv2.INTER_CUBIC)


def magnified_to_frame(region: tuple[int, int, int, int]) -> np.ndarray:
    """The affine (2, 3) from the magnified region's pixels back to the frame's (for from_view):
    pixel centres map onto pixel centres."""
    shift = 0.5 / MAGNIFICATION - 0.5
    return np.array([[1 / MAGNIFICATION, 0, region[0] + shift], [0, 1 / MAGNIFICATION, region[1] + shift]])


def merge(xy: np.ndarray, values: np.ndarray, boards: tuple[Board, ...], more_xy: np.ndarray,
          more_values: np.ndarray, more_boards: tuple[Board, ...]):
    """The corners (xy, values) and boards of the full-frame pass and of a look at a resampled part of
    it (magnified or stretched; already in frame pixels), with each board of the look that has more
    corners than the boards it shares corners with (SAME_CORNER) in their place, and one that shares
    none added. Returns
    xy and values of both passes, one after the other, and the boards kept (largest first, ties:
    top, then left), their corner_index into that xy."""
    kept = list(boards)
    for board in more_boards:
        shares = [_shares_corners(board.xy, old.xy) for old in kept]
        if len(board) > sum(len(old) for old, shared in zip(kept, shares) if shared):
            kept = [old for old, shared in zip(kept, shares) if not shared]
            kept.append(dataclasses.replace(board, corner_index=board.corner_index + len(xy)))
    return np.concatenate([xy, more_xy]), np.concatenate([values, more_values]), tuple(largest_first(kept))


def thinnest(board: Board) -> float:
    """The median width across (checker.altitude) of the squares at the board's thinnest THIN_SHARE
    of corners, px (inf for a board too small to tell)."""
    steps = lattice_steps(board)
    widths = altitude(steps[:, 0], steps[:, 2])
    widths = np.sort(widths[np.isfinite(widths)])
    if len(widths) == 0:
        return float("inf")
    return float(median(widths[: max(3, int(THIN_SHARE * len(widths)))]))


def _shares_corners(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether any corner of a (N, 2) lies within SAME_CORNER px of one of b (M, 2)."""
    d2 = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1)
    return bool((d2 <= SAME_CORNER**2).any())
