"""Sub-pixel corner refinement, vectorised over all corners of an image.

`saddle`: fit f(x, y) = a x^2 + b xy + c y^2 + d x + e y + g by least squares to a Gaussian-smoothed
patch around each corner (one matrix product for all corners: the fit's pseudo-inverse depends
only on the patch grid), step to the quadric's stationary point, re-centre and repeat. A checker
corner is a clear saddle (sqrt(b^2 - 4ac) >= `min_saddle` gray levels / px^2); a corner whose fit is
no saddle (flat, an edge, a blob), or that walks away from its peak, is flagged as not converged.
The fit is biased when it starts more than about a pixel off (measured on renders: a third of the
corners started 2 px off end up 0.3-1.3 px away), so starts known to be rough first go through a
rough pass, then the fine pass: peaks from a downscaled frame are fitted on that frame itself
(`refine_from_shrunk`: a quarter of the pixels at half size), positions predicted by the grid with
a `wide` pass (the same fit with a larger window on a more smoothed image, whose basin is wider).

`cornersubpix`: OpenCV's gradient-orthogonality refinement (one C call for all corners).
Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

METHODS = ("saddle", "cornersubpix", "none")
SUBPIXEL_ITERATIONS = 2


def window_for_spacing(spacing: float) -> int:
    """The saddle fit's window radius for corners `spacing` px apart: a tenth of the square, 3..4 px.
    Measured on renders of the training distribution (blur, defocus, motion, noise, JPEG, perspective;
    the corners started up to 0.7 px off): mean error at radius 3 / 4 / 5 / 6 px was 0.078 / 0.081 /
    0.092 / 0.114 px for 35-80 px squares at 640x480 and 0.041 / 0.040 / 0.042 / 0.045 px for 40-110
    px squares at 2000x1500: the blur, not the square, sets the useful window (an upscaled board,
    blurred with it, is the exception: 0.18 px at radius 3, 0.06 at 6)."""
    return int(np.clip(round(spacing / 10), 3, 4))


@dataclass(frozen=True)
class _Quadric:
    """The least-squares quadric fit on a (2r+1)^2 patch: its radius r, offsets, design matrix,
    squared weights and, for patches wholly inside the image, the fit's pseudo-inverse (read-only arrays)."""

    radius: int
    ox: np.ndarray
    oy: np.ndarray
    design: np.ndarray
    weight2: np.ndarray
    pinv: np.ndarray


@lru_cache(maxsize=16)
def _quadric(radius: int) -> _Quadric:
    """The fit for a window radius (cached: it depends on the radius only)."""
    oy, ox = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    ox, oy = ox.ravel().astype(np.float64), oy.ravel().astype(np.float64)
    sigma = radius  # weight the centre more: the quadric only models the corner's neighbourhood
    w = np.exp(-(ox**2 + oy**2) / (2 * sigma**2))
    design = np.stack([ox * ox, ox * oy, oy * oy, ox, oy, np.ones_like(ox)], 1)
    pinv = np.linalg.pinv(design * w[:, None]) * w[None, :]
    fit = _Quadric(radius, ox.astype(np.int64), oy.astype(np.int64), design, w * w, pinv)
    for a in (fit.ox, fit.oy, fit.design, fit.weight2, fit.pinv):
        a.setflags(write=False)
    return fit


def refine_saddle_points(gray: np.ndarray, xy: np.ndarray, radius: int = 3, sigma: float = 1.2,
                         iterations: int = 3, max_shift: float = 2.0, min_saddle: float = 0.5,
                         wide: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Refine integer peaks xy (N, 2) to sub-pixel saddle points of the smoothed image; `wide` >
    radius: a first pass with that window radius (module docstring).

    Returns refined xy (N, 2) float32 and a converged mask (N,) bool.
    """
    if wide > radius and len(xy):
        rough, ok = refine_saddle_points(gray, xy, wide, 0.4 * wide, 5, max_shift, min_saddle)
        fine, ok_fine = refine_saddle_points(gray, np.where(ok[:, None], rough, xy), radius, sigma, iterations,
                                             max_shift, min_saddle)
        ok = ok_fine & (np.hypot(*(fine - xy).T) <= max_shift)
        return np.where(ok[:, None], fine, xy).astype(np.float32), ok
    n = len(xy)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    smoothed = _smoothed_around(gray, xy, sigma, radius * (iterations + 1))
    h, w = gray.shape
    quadric = _quadric(radius)
    start = xy.astype(np.float64)
    centre = np.rint(start).astype(np.int64)
    offset = np.zeros((n, 2))
    ok = np.ones(n, bool)
    for _ in range(iterations):  # whole-pixel steps to the saddle's pixel
        offset, ok = _fit(smoothed, centre, quadric, min_saddle)
        step = np.rint(np.clip(np.where(ok[:, None], offset, 0), -radius, radius)).astype(np.int64)
        if not step.any():
            break
        centre = centre + step
    refined = centre + offset
    for _ in range(SUBPIXEL_ITERATIONS):  # re-fit centred on the estimate: the fit is least biased there
        again, ok_again = _fit(smoothed, refined, quadric, min_saddle)
        move = ok & ok_again & np.all(np.abs(again) <= 0.5, 1)
        refined = np.where(move[:, None], refined + again, refined)
        offset = np.where(move[:, None], refined - centre, offset)
    ok &= np.all(np.abs(offset) <= 0.75, 1) & (np.hypot(*(refined - start).T) <= max_shift)
    ok &= (refined[:, 0] >= 0) & (refined[:, 0] <= w - 1) & (refined[:, 1] >= 0) & (refined[:, 1] <= h - 1)
    # a window cut by the frame's edge is lopsided, which biases the fit (measured: 0.7-1.4 px at
    # 1-3 px from the edge): such corners are fitted again with the largest window that fits (>= 2)
    refined = np.where(ok[:, None], refined, start)
    edge = np.floor(np.minimum(np.minimum(refined[:, 0], w - 1 - refined[:, 0]),
                               np.minimum(refined[:, 1], h - 1 - refined[:, 1]))).astype(np.int64)
    for small in range(2, radius):  # one call per window (_smoothed_around smooths only near the corners)
        group = np.clip(edge, 2, radius) == small
        if group.any():
            refined[group], ok[group] = refine_saddle_points(gray, refined[group], small, 0.4 * small, iterations,
                                                             max_shift, min_saddle)
    ok &= np.hypot(*(refined - start).T) <= max_shift
    return np.where(ok[:, None], refined, start).astype(np.float32), ok


def _fit(smoothed: _Smoothed, centre: np.ndarray, quadric: _Quadric, min_saddle: float) -> tuple[np.ndarray, np.ndarray]:
    """One quadric fit around each centre (N, 2) (frame pixels; sub-pixel centres are sampled
    bilinearly): the offsets (N, 2) to the stationary points and whether each is a saddle.
    Patches reaching off the frame are fitted on their pixels inside it, so corners at the frame's
    edge refine too."""
    h, w = smoothed.frame_shape
    r = quadric.radius
    cx, cy = centre[:, 0:1] - smoothed.shift[:, 0:1], centre[:, 1:2] - smoothed.shift[:, 1:2]  # in the smoothed image
    sx, sy = cx + quadric.ox[None], cy + quadric.oy[None]
    lo, hi = smoothed.low, smoothed.high
    if not ((cx[:, 0] - r >= lo[:, 0]) & (cx[:, 0] + r <= hi[:, 0]) & (cy[:, 0] - r >= lo[:, 1])
            & (cy[:, 0] + r <= hi[:, 1])).all():  # clamped: never into another patch (a no-op otherwise)
        sx = np.minimum(np.maximum(sx, lo[:, 0:1]), hi[:, 0:1])
        sy = np.minimum(np.maximum(sy, lo[:, 1:2]), hi[:, 1:2])
    if centre.dtype.kind == "i":
        values = np.ravel(smoothed.image).take(sy * smoothed.image.shape[1] + sx)
    else:
        values = cv2.remap(smoothed.image, sx.astype(np.float32), sy.astype(np.float32), cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    values = values.astype(np.float64)
    coef = values @ quadric.pinv.T  # (N, 6): a, b, c, d, e, g
    x, y = centre[:, 0], centre[:, 1]
    cut = np.nonzero((x - r < 0) | (x + r > w - 1) | (y - r < 0) | (y + r > h - 1))[0]  # windows off the frame
    if len(cut):
        mx, my = centre[cut, 0:1] + quadric.ox[None], centre[cut, 1:2] + quadric.oy[None]
        inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        # weighted normal equations over the pixels inside, one 6x6 system per corner
        weighted = (quadric.weight2[None] * inside)[:, None, :] * quadric.design.T[None]  # (K, 6, P)
        normal = weighted @ quadric.design
        rhs = (weighted @ values[cut][..., None])[..., 0]
        # the pixels inside form a rectangle: a quadric needs at least 3 of its columns and 3 rows
        box = inside.reshape(len(cut), 2 * r + 1, 2 * r + 1)
        solvable = (box.any(1).sum(1) >= 3) & (box.any(2).sum(1) >= 3)
        coef[cut] = np.nan
        coef[cut[solvable]] = np.linalg.solve(normal[solvable], rhs[solvable][..., None])[..., 0]
    a, b, c, d, e = coef[:, 0], coef[:, 1], coef[:, 2], coef[:, 3], coef[:, 4]
    det = 4 * a * c - b * b
    safe = np.where(np.abs(det) < 1e-12, 1e-12, det)
    offset = np.stack([(b * e - 2 * c * d) / safe, (b * d - 2 * a * e) / safe], 1)
    return offset, (det < -min_saddle * min_saddle) & np.all(np.isfinite(offset), 1)


@dataclass(frozen=True)
class _Smoothed:
    """The Gaussian-smoothed (float32) pixels the fits read: corner k's frame pixel (x, y) is
    image[y - shift[k, 1], x - shift[k, 0]], within low[k]..high[k] (x, y, inclusive)."""

    image: np.ndarray
    shift: np.ndarray
    low: np.ndarray
    high: np.ndarray
    frame_shape: tuple[int, int]


def _smoothed_around(gray: np.ndarray, xy: np.ndarray, sigma: float, reach: int) -> _Smoothed:
    """gray smoothed wherever a fit may read, `reach` px around the points: the region they span, or,
    when that is larger (corners spread over a big frame), a square patch per point (their
    pixels only: on a 2000x1500 frame the region cost most of the refinement)."""
    h, w = gray.shape
    margin = int(np.ceil(4 * sigma)) + 1  # beyond the blur's reach the crop edge cannot matter
    x0, y0 = (max(int(np.floor(xy[:, k].min())) - reach - margin, 0) for k in (0, 1))
    x1 = min(int(np.ceil(xy[:, 0].max())) + reach + margin + 1, w)
    y1 = min(int(np.ceil(xy[:, 1].max())) + reach + margin + 1, h)
    side = 2 * (reach + margin) + 2  # a patch: the reach each way around the rounded point, one pixel for rounding
    n = len(xy)
    if 2 * n * side * side >= (x1 - x0) * (y1 - y0):  # a patch pixel, gathered, costs about two of a slice (measured)
        part = gray[y0:y1, x0:x1].astype(np.float32)
        part = _blur_inside(part, sigma) if sigma > 0 else part
        return _Smoothed(part, np.broadcast_to(np.array([x0, y0]), (n, 2)), np.zeros((n, 2), np.int64),
                         np.broadcast_to(np.array([x1 - x0 - 1, y1 - y0 - 1]), (n, 2)), (h, w))
    corner = np.floor(xy).astype(np.int64) - reach - margin  # each patch's top-left (x, y) in the frame
    offsets = np.arange(side)
    cols, rows = corner[:, 0:1] + offsets, corner[:, 1:2] + offsets  # (N, side) each
    patches = gray[np.clip(rows, 0, h - 1)[:, :, None], np.clip(cols, 0, w - 1)[:, None, :]].astype(np.float32)
    col_in, row_in = (cols >= 0) & (cols < w), (rows >= 0) & (rows < h)
    cut = ~(col_in.all(1) & row_in.all(1))
    patches[cut] *= (row_in[cut, :, None] & col_in[cut, None, :])
    stacked = patches.reshape(n * side, side)  # one blur for all: a patch's margin absorbs its neighbours'
    if sigma > 0:
        stacked = cv2.GaussianBlur(stacked, (_kernel_size(sigma),) * 2, sigma, borderType=cv2.BORDER_CONSTANT)
        if cut.any():  # normalised convolution where the frame's edge cuts a patch (_blur_inside)
            row_mass, col_mass = (_mass_inside(inside[cut], sigma) for inside in (row_in, col_in))
            blurred = stacked.reshape(n, side, side)
            blurred[cut] /= np.maximum(row_mass[:, :, None] * col_mass[:, None, :], 1e-12)
    shift = corner - np.stack([np.zeros(n, np.int64), np.arange(n) * side], 1)
    low = np.stack([np.zeros(n, np.int64), np.arange(n) * side], 1)
    return _Smoothed(stacked, shift, low, low + side - 1, (h, w))


def _kernel_size(sigma: float) -> int:
    """cv2.GaussianBlur's kernel size for sigma: odd, covering +-4 sigma."""
    return int(round(8 * sigma + 1)) | 1


def _blur_inside(part: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur that averages only pixels inside `part` (normalised convolution): mirroring
    or repeating the edge, as usual borders do, would pull a corner near the frame's edge towards
    its mirror image (measured: 1-1.7 px off at 2 px from the edge). The normaliser is separable
    and differs from 1 only within the kernel's reach of an edge, so only those bands are divided."""
    blurred = cv2.GaussianBlur(part, (_kernel_size(sigma),) * 2, sigma, borderType=cv2.BORDER_CONSTANT)
    rows, cols = (_mass_inside(np.ones((1, n), bool), sigma)[0] for n in part.shape)
    top, left = np.nonzero(np.abs(rows - 1) > 1e-6)[0], np.nonzero(np.abs(cols - 1) > 1e-6)[0]
    blurred[top] /= rows[top, None]
    blurred[:, left] /= cols[None, left]
    return blurred


def _mass_inside(inside: np.ndarray, sigma: float) -> np.ndarray:
    """(K, n) float32: along each of K lines of n pixels (inside: (K, n) bool), the share of the
    blur's 1-D kernel that falls on inside pixels at each position: the separable normaliser of a
    blur that averages only pixels inside (a region's edges, or the frame's edge across a patch)."""
    kernel = cv2.getGaussianKernel(_kernel_size(sigma), sigma, cv2.CV_64F).reshape(1, -1)
    return cv2.filter2D(inside.astype(np.float64), -1, kernel, borderType=cv2.BORDER_CONSTANT).astype(np.float32)


def refine_from_shrunk(gray: np.ndarray, shrunk: np.ndarray, xy: np.ndarray, scale: int, radius: int,
                       max_shift: float) -> tuple[np.ndarray, np.ndarray]:
    """Saddle points of gray for peaks xy (N, 2) found on `shrunk` (gray reduced `scale` times): the
    rough pass on the shrunk frame itself (a 1/scale^2 of the pixels to smooth and fit), then the
    fine pass on gray, from the rough position where the rough pass converged and from the peak
    where it did not (e.g. an occluder's edge next to the corner spoils the shrunk frame's fit);
    corners may move max_shift px (gray's) from the peaks. Returns refined xy (N, 2) float32 in
    gray's pixels (the peaks' own where not converged) and a converged mask (N,) bool."""
    start = (xy + 0.5) * scale - 0.5  # pixel centres of the shrunk frame in gray's pixels
    if len(xy) == 0:
        return start.astype(np.float32), np.zeros(0, bool)
    small = max(3, -(-radius // scale) + 1)  # the fine window on the shrunk frame, and a pixel for the peaks' rounding
    rough, ok = refine_saddle_points(shrunk, xy, small, 0.4 * small, 3, max_shift / scale)
    begin = np.where(ok[:, None], (rough.astype(np.float64) + 0.5) * scale - 0.5, start)
    fine, ok = refine_saddle_points(gray, begin, radius, 0.4 * radius, max_shift=max_shift)
    ok &= np.hypot(*(fine - start).T) <= max_shift
    return np.where(ok[:, None], fine, start).astype(np.float32), ok


def refine_cornersubpix(gray: np.ndarray, xy: np.ndarray, radius: int = 4, max_shift: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV cornerSubPix on all corners at once; same outputs as refine_saddle_points."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    pts = xy.astype(np.float32).reshape(-1, 1, 2).copy()
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    cv2.cornerSubPix(gray, pts, (radius, radius), (-1, -1), criteria)
    refined = pts.reshape(-1, 2)
    h, w = gray.shape
    ok = np.hypot(*(refined - xy).T) <= max_shift
    ok &= (refined[:, 0] >= 0) & (refined[:, 0] <= w - 1) & (refined[:, 1] >= 0) & (refined[:, 1] <= h - 1)
    return np.where(ok[:, None], refined, xy).astype(np.float32), ok


def refine(gray: np.ndarray, xy: np.ndarray, method: str = "saddle", max_shift: float = 2.0,
           radius: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Dispatch to a refinement method by name (see METHODS); corners may move up to max_shift px;
    radius: the window (saddle: sigma 0.4 radius)."""
    if method == "saddle":
        return refine_saddle_points(gray, xy, radius, 0.4 * radius, max_shift=max_shift)
    if method == "cornersubpix":
        return refine_cornersubpix(gray, xy, radius + 1, max_shift=max_shift)
    if method == "none":
        return xy.astype(np.float32), np.ones(len(xy), bool)
    raise ValueError(f"unknown refinement {method!r}; choose from {METHODS}")
