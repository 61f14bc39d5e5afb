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

Where a fit fails, refine_from_neighbours fits again from the peak's 4 diagonal neighbours (ccdn.grid's
marker search takes those fits: a corner between two pixels whose peak lies on the side where the
window reaches a marker's border converges from the other side).

`cornersubpix`: OpenCV's gradient-orthogonality refinement (one C call for all corners).
Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

METHODS = ("saddle", "cornersubpix", "none")
SUBPIXEL_ITERATIONS = 2
NARROW_RADIUS = 2
REFIT_FAILED_RADIUS = 4  # windows from this radius whose fit, cut by the frame's edge, failed are fitted again smaller


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
    weights, the fit's weighted pseudo-inverse for patches wholly inside the image, transposed (P, 6),
    and `shifted`: that pseudo-inverse placed at each of the 4 corners of a (2r+2)^2 patch, transposed
    ((2r+2)^2, 24), so that a fit at a sub-pixel centre is the bilinear blend of the 4 integer fits
    around it (the fit is linear in the pixels, and so is bilinear sampling), read from one integer
    patch. Read-only arrays; the transposes are contiguous, for patches (N, P) @ them (measured: a
    transposed view multiplies 1.5x slower)."""

    radius: int
    ox: np.ndarray
    oy: np.ndarray
    design: np.ndarray
    weight: np.ndarray
    pinv: np.ndarray
    shifted: np.ndarray


@lru_cache(maxsize=16)
def _quadric(radius: int) -> _Quadric:
    """The fit for a window radius (cached: it depends on the radius only)."""
    oy, ox = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    ox, oy = ox.ravel().astype(np.float64), oy.ravel().astype(np.float64)
    sigma = radius  # weight the centre more: the quadric only models the corner's neighbourhood
    weight = np.exp(-(ox**2 + oy**2) / (2 * sigma**2))
    design = np.stack([ox * ox, ox * oy, oy * oy, ox, oy, np.ones_like(ox)], 1)
    pinv = _weighted_pinv(design, weight)
    side = 2 * radius + 1
    shifted = np.zeros((4, 6, side + 1, side + 1))
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):  # the bilinear weights' order in _fit
        shifted[k, :, dy : dy + side, dx : dx + side] = pinv.reshape(6, side, side)
    fit = _Quadric(radius, ox.astype(np.int64), oy.astype(np.int64), design, weight, np.ascontiguousarray(pinv.T),
                   np.ascontiguousarray(shifted.reshape(24, (side + 1) ** 2).T))
    for a in (fit.ox, fit.oy, fit.design, fit.weight, fit.pinv, fit.shifted):
        a.setflags(write=False)
    return fit


class _FitsInside:
    """The quadric fits (6, P) over only the part of a window the frame's edge leaves, one per
    rectangle of offsets met (first..last per axis; the other pixels get weight 0), kept in one
    array so that a call's K cut windows gather theirs in one step (a frame's share a few). On frames
    larger than the window an edge cuts each axis on one side at most: at most (4r + 3)^2 rectangles
    (r = 8: 1225, 17 MB)."""

    def __init__(self, radius: int) -> None:
        self.radius = radius
        self._row: dict[int, int] = {}
        self._table = np.zeros((0, 6, (2 * radius + 1) ** 2))
        self._lock = threading.Lock()

    def __call__(self, first: np.ndarray, last: np.ndarray) -> np.ndarray:
        """(K, 6, P) for first, last: (K, 2) int offsets (x, y) in -radius..radius."""
        r, side = self.radius, 2 * self.radius + 1
        keys = (((first + r) * side + last + r) @ np.array([side * side, 1])).tolist()
        with self._lock:
            missing = [key for key in dict.fromkeys(keys) if key not in self._row]
            if missing:
                self._table = np.concatenate([self._table, np.stack([self._fit(key) for key in missing])])
                self._row.update((key, len(self._row)) for key in missing)
            table, row = self._table, self._row
        return table[[row[key] for key in keys]]

    def _fit(self, key: int) -> np.ndarray:
        """The fit for one key (as __call__ encodes it)."""
        r, side = self.radius, 2 * self.radius + 1
        x, y = divmod(key, side * side)
        (first_x, last_x), (first_y, last_y) = divmod(x, side), divmod(y, side)
        fit = _quadric(r)
        inside = (fit.ox >= first_x - r) & (fit.ox <= last_x - r) & (fit.oy >= first_y - r) & (fit.oy <= last_y - r)
        return _weighted_pinv(fit.design, fit.weight * inside)


@lru_cache(maxsize=16)
def _fits_inside(radius: int) -> _FitsInside:
    """The _FitsInside of a window radius (one per radius, shared by all detectors and threads)."""
    return _FitsInside(radius)


def _weighted_pinv(design: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(6, P): the weighted least-squares fit of design's columns (P, 6) to P pixel values."""
    return np.linalg.pinv(design * weight[:, None]) * weight[None, :]


def refine_saddle_points(gray: np.ndarray, xy: np.ndarray, radius: int = 3, sigma: float = 1.2,
                         iterations: int = 3, max_shift: float = 2.0, min_saddle: float = 0.5,
                         wide: int = 0, rough: bool = False, narrow: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Refine integer peaks xy (N, 2) to sub-pixel saddle points of the smoothed image; `wide` >
    radius: a first pass with that window radius (module docstring); `rough`: a pass whose result
    only starts a finer one, which refits anyway: no sub-pixel re-fits after the whole-pixel steps
    and no re-fits of corners near the frame's edge with smaller windows. `narrow`: (N,) mask of
    corners that, where this fit fails, are fitted again from their start with the narrowest window
    (NARROW_RADIUS): a steep view's squares can be narrower than the window, which then spans the
    neighbouring corners' edges and finds no saddle. gray: uint8, or float32 grey levels on another
    scale (ccdn.grid fits corners in shade on the log scale), min_saddle then in its units.

    Returns refined xy (N, 2) float32 and a converged mask (N,) bool.
    """
    if wide > radius and len(xy):
        widely, ok = refine_saddle_points(gray, xy, wide, 0.4 * wide, 5, max_shift, min_saddle)
        fine, ok_fine = refine_saddle_points(gray, np.where(ok[:, None], widely, xy), radius, sigma, iterations,
                                             max_shift, min_saddle, narrow=narrow)
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
        step = np.rint(np.minimum(np.maximum(np.where(ok[:, None], offset, 0), -radius), radius)).astype(np.int64)
        if not step.any():
            break
        centre = centre + step
    refined = centre + np.where(ok[:, None], offset, 0)  # where not converged: left where it was
    for _ in range(0 if rough else SUBPIXEL_ITERATIONS):  # re-fit centred on the estimate: least biased there
        again, ok_again = _fit(smoothed, refined, quadric, min_saddle)
        move = ok & ok_again & (np.abs(again) <= 0.5).all(1)
        refined = np.where(move[:, None], refined + again, refined)
        offset = np.where(move[:, None], refined - centre, offset)
    ok &= (np.abs(offset) <= 0.75).all(1) & (np.hypot(*(refined - start).T) <= max_shift)
    frame_end = np.array([w - 1, h - 1])  # the last pixel's (x, y)
    ok &= ((refined >= 0) & (refined <= frame_end)).all(1)
    # a window cut by the frame's edge is lopsided, which biases the fit (measured: 0.7-1.4 px at
    # 1-3 px from the edge): such corners are fitted again with the largest window that fits (>= 2),
    # except by a rough pass, whose result only starts a fine pass that does this itself; a failed
    # fit only from REFIT_FAILED_RADIUS: most failed fits of radius 3 are score peaks on the frame's
    # outermost pixels (0.7 ms per 640x480 real photo), while its cut window fails on few corners
    # (measured on renders: 2 of 181 at 1.5 px from the edge, none farther in; radius 4: 13, 5: 111)
    refined = np.where(ok[:, None], refined, start)
    if not rough:
        edge = np.floor(np.minimum(refined, frame_end - refined).min(1)).astype(np.int64)
        window, refit = np.maximum(edge, 2), ok | (radius >= REFIT_FAILED_RADIUS)
        for small in range(2, radius):  # one call per window (_smoothed_around smooths only near the corners)
            group = (window == small) & refit
            if group.any():
                refined[group], ok[group] = refine_saddle_points(gray, refined[group], small, 0.4 * small, iterations,
                                                                 max_shift, min_saddle)
    ok &= np.hypot(*(refined - start).T) <= max_shift
    if narrow is not None and radius > NARROW_RADIUS and (again := ~ok & narrow).any():
        refined[again], ok[again] = refine_saddle_points(gray, start[again], NARROW_RADIUS, 0.4 * NARROW_RADIUS,
                                                         iterations, max_shift, min_saddle)
    return np.where(ok[:, None], refined, start).astype(np.float32), ok


def _fit(smoothed: _Smoothed, centre: np.ndarray, quadric: _Quadric, min_saddle: float) -> tuple[np.ndarray, np.ndarray]:
    """One quadric fit around each centre (N, 2) (frame pixels; at sub-pixel centres the patch is
    sampled bilinearly, exactly: _Quadric.shifted): the offsets (N, 2) to the stationary points and
    whether each is a saddle. Patches reaching off the frame are fitted on their pixels inside it,
    so corners at the frame's edge refine too."""
    h, w = smoothed.frame_shape
    r = quadric.radius
    whole = centre.dtype.kind == "i"
    floor = centre if whole else np.floor(centre)
    span = 2 * r + 1 if whole else 2 * r + 2  # the integer patch read: one more row and column to blend
    patch = _gather(smoothed, floor.astype(np.int64, copy=False) - smoothed.shift - r, span)  # (N, span^2) float64
    if whole:
        coef = patch @ quadric.pinv  # (N, 6): a, b, c, d, e, g
    else:
        frac = centre - floor
        along = np.concatenate([1 - frac, frac], 1).reshape(-1, 2, 2)  # (N, 2 weights, x / y)
        blend = (along[:, :, None, 1] * along[:, None, :, 0]).reshape(-1, 1, 4)  # (y, x) as in _Quadric.shifted
        coef = (blend @ (patch @ quadric.shifted).reshape(-1, 4, 6))[:, 0]
    frame_end = np.array([w - 1, h - 1])  # the last pixel's (x, y)
    cut = np.nonzero(((centre < r) | (centre > frame_end - r)).any(1))[0]  # windows off the frame
    if len(cut):
        if whole:
            values = patch[cut]
        else:  # the bilinear samples themselves
            p = patch[cut].reshape(-1, span, span)
            k = blend[cut, 0, :, None, None]
            values = (k[:, 0] * p[:, :-1, :-1] + k[:, 1] * p[:, :-1, 1:] + k[:, 2] * p[:, 1:, :-1]
                      + k[:, 3] * p[:, 1:, 1:]).reshape(len(cut), -1)
        # the pixels inside form a rectangle of offsets, first..last per axis: a quadric needs at least 3 of
        # its columns and 3 rows; each rectangle's fit is computed once (_FitsInside)
        first = np.ceil(np.maximum(-centre[cut], -r)).astype(np.int64)
        last = np.floor(np.minimum(frame_end - centre[cut], r)).astype(np.int64)
        solvable = (last - first >= 2).all(1)
        coef[cut] = np.nan
        if solvable.any():
            coef[cut[solvable]] = (_fits_inside(r)(first[solvable], last[solvable]) @ values[solvable][..., None])[..., 0]
    # b e - 2 c d, b d - 2 a e, 4 a c - b^2: the stationary point's numerators and the Hessian's determinant
    terms = (coef[:, _PAIRS[0]] * coef[:, _PAIRS[1]]) @ _STATIONARY
    det = terms[:, 2]
    saddle = det < -min_saddle * min_saddle  # False where the fit failed (NaN)
    return terms[:, :2] / np.where(saddle, det, -1.0)[:, None], saddle  # offsets of non-saddles mean nothing


# the terms above from the coefficients (a, b, c, d, e, g): the pairs multiplied (b e, c d, b d, a e, a c,
# b b), and the factors that sum their products to each term (6, 3)
_PAIRS = np.array([[1, 2, 1, 0, 0, 1], [4, 3, 3, 4, 2, 1]])
_STATIONARY = np.array([[1, 0, 0], [-2, 0, 0], [0, 1, 0], [0, -2, 0], [0, 0, 4], [0, 0, -1]], np.float64)
_PAIRS.setflags(write=False)
_STATIONARY.setflags(write=False)


def _gather(smoothed: _Smoothed, top_left: np.ndarray, span: int) -> np.ndarray:
    """(N, span^2) float64: the span x span pixels of smoothed.image from each top_left (N, 2) (x, y,
    in the image), clamped to each point's own region (low..high: never into another patch)."""
    stride = smoothed.image.shape[1]
    lo, hi = smoothed.low, smoothed.high
    if ((top_left >= lo) & (top_left + span - 1 <= hi)).all():  # the usual case: one add per pixel
        index = (top_left[:, 1] * stride + top_left[:, 0])[:, None] + _patch_offsets(span, stride)
    else:
        steps = np.arange(span)
        rows = np.minimum(np.maximum(top_left[:, 1:2] + steps, lo[:, 1:2]), hi[:, 1:2])
        cols = np.minimum(np.maximum(top_left[:, 0:1] + steps, lo[:, 0:1]), hi[:, 0:1])
        index = (rows[:, :, None] * stride + cols[:, None, :]).reshape(len(top_left), -1)
    return smoothed.image.ravel().take(index).astype(np.float64)


@lru_cache(maxsize=64)
def _patch_offsets(span: int, stride: int) -> np.ndarray:
    """(1, span^2): the flat offsets of a span x span patch's pixels from its top-left, in an image
    `stride` pixels wide (cached: a few (span, stride) pairs recur for every frame)."""
    steps = np.arange(span)
    offsets = (steps[:, None] * stride + steps[None, :]).reshape(1, -1)
    offsets.setflags(write=False)
    return offsets


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
    x0, y0 = np.maximum(np.floor(xy.min(0)).astype(np.int64) - reach - margin, 0).tolist()
    x1, y1 = np.minimum(np.ceil(xy.max(0)).astype(np.int64) + reach + margin + 1, (w, h)).tolist()
    side = 2 * (reach + margin) + 2  # a patch: the reach each way around the rounded point, one pixel for rounding
    n = len(xy)
    if 2 * n * side * side >= (x1 - x0) * (y1 - y0):  # a patch pixel, gathered, costs about two of a slice (measured)
        part = gray[y0:y1, x0:x1].astype(np.float32)
        part = _blur_inside(part, sigma) if sigma > 0 else part
        return _Smoothed(part, np.full((n, 2), (x0, y0)), np.zeros((n, 2), np.int64),
                         np.full((n, 2), (x1 - x0 - 1, y1 - y0 - 1)), (h, w))
    corner = np.floor(xy).astype(np.int64) - reach - margin  # each patch's top-left (x, y) in the frame
    offsets = np.arange(side)
    cols, rows = corner[:, 0:1] + offsets, corner[:, 1:2] + offsets  # (N, side) each
    col_in, row_in = (cols >= 0) & (cols < w), (rows >= 0) & (rows < h)
    cut = ~(col_in.all(1) & row_in.all(1))
    # side by side in one wide image, (row, patch, column): a wide image blurs faster than a tall one (~2x)
    patches = np.empty((side, n, side), np.float32)
    if not cut.all():  # a whole patch is a window of the frame: copied from a strided view, no index array
        # (measured: 0.09 against 2.3 ms for 90 patches of 50 x 50 px; a take over int64 indices before)
        whole = ~cut
        windows = sliding_window_view(gray, (side, side))[corner[whole, 1], corner[whole, 0]]  # (K, side, side)
        patches[:, whole] = windows.transpose(1, 0, 2)
    if cut.any():  # patches the frame's edge cuts: read clamped (broadcast indices: no index array), then zeroed
        rows_in, cols_in = np.minimum(np.maximum(rows[cut], 0), h - 1), np.minimum(np.maximum(cols[cut], 0), w - 1)
        patches[:, cut] = gray[rows_in.T[:, :, None], cols_in[None]]
        patches[:, cut] *= row_in[cut].T[:, :, None] & col_in[cut][None]
    wide = patches.reshape(side, n * side)  # one blur for all: a patch's margin absorbs its neighbours'
    if sigma > 0:
        wide = cv2.GaussianBlur(wide, (kernel_size(sigma),) * 2, sigma, borderType=cv2.BORDER_CONSTANT)
        if cut.any():  # normalised convolution where the frame's edge cuts a patch (_blur_inside)
            row_mass, col_mass = (_mass_inside(inside[cut], sigma) for inside in (row_in, col_in))
            blurred = wide.reshape(side, n, side)
            blurred[:, cut] /= np.maximum(row_mass.T[:, :, None] * col_mass[None], 1e-12)
    low = np.zeros((n, 2), np.int64)
    low[:, 0] = np.arange(0, n * side, side)
    return _Smoothed(wide, corner - low, low, low + side - 1, (h, w))


def kernel_size(sigma: float) -> int:
    """cv2.GaussianBlur's kernel size for sigma on float images (what it picks for ksize (0, 0)): odd,
    covering +-4 sigma."""
    return int(round(8 * sigma + 1)) | 1


def _blur_inside(part: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur that averages only pixels inside `part` (normalised convolution): mirroring
    or repeating the edge, as usual borders do, would pull a corner near the frame's edge towards
    its mirror image (measured: 1-1.7 px off at 2 px from the edge). The normaliser is separable
    and differs from 1 only within the kernel's reach of an edge, so only those bands are divided."""
    size = kernel_size(sigma)
    blurred = cv2.GaussianBlur(part, (size, size), sigma, borderType=cv2.BORDER_CONSTANT)
    for lines in (blurred, blurred.T):  # rows, then columns
        n = len(lines)
        if n >= size:  # the kernel reaches past one end at a time: the ends' normaliser, the same for every n
            end = _end_mass(sigma)
            lines[: len(end)] /= end[:, None]
            lines[n - len(end) :] /= end[::-1, None]
        else:
            mass = _mass_inside(np.ones((1, n), bool), sigma)[0]
            band = np.abs(mass - 1) > 1e-6
            lines[band] /= mass[band, None]
    return blurred


@lru_cache(maxsize=16)
def _end_mass(sigma: float) -> np.ndarray:
    """(k,) float32: _blur_inside's normaliser at the first k pixels of a line at least a kernel long,
    those where it differs from 1 by more than 1e-6; the last k pixels hold it reversed, those between
    exactly 1. Cached: it depends on sigma only (measured: the same bits as _mass_inside on the whole
    line, for lines from a kernel to 3000 pixels long, sigma 0.8 to 4)."""
    size = kernel_size(sigma)
    mass = _mass_inside(np.ones((1, size), bool), sigma)[0, : size // 2]
    end = mass[np.abs(mass - 1) > 1e-6]
    end.setflags(write=False)
    return end


def _mass_inside(inside: np.ndarray, sigma: float) -> np.ndarray:
    """(K, n) float32: along each of K lines of n pixels (inside: (K, n) bool), the share of the
    blur's 1-D kernel that falls on inside pixels at each position: the separable normaliser of a
    blur that averages only pixels inside (a region's edges, or the frame's edge across a patch)."""
    kernel = cv2.getGaussianKernel(kernel_size(sigma), sigma, cv2.CV_64F).reshape(1, -1)
    return cv2.filter2D(inside.astype(np.float64), -1, kernel, borderType=cv2.BORDER_CONSTANT).astype(np.float32)


def refine_from_shrunk(gray: np.ndarray, shrunk: np.ndarray, xy: np.ndarray, scale: int, radius: int,
                       max_shift: float) -> tuple[np.ndarray, np.ndarray]:
    """Saddle points of gray for peaks xy (N, 2) found on `shrunk` (gray reduced `scale` times): the
    rough pass on the shrunk frame itself (a 1/scale^2 of the pixels to smooth and fit; without
    sub-pixel re-fits, which the fine pass would redo: measured, 2 ms less per 640x480 frame and the
    same corners to 0.01 px but one real-dev corner, which moved 1.4 px onto its label; nor re-fits
    near the frame's edge: 1.4 ms less, the same corners on 156 frames), then the
    fine pass on gray, from the rough position where the rough pass converged and from the peak
    where it did not (e.g. an occluder's edge next to the corner spoils the shrunk frame's fit);
    corners may move max_shift px (gray's) from the peaks. Returns refined xy (N, 2) float32 in
    gray's pixels (the peaks' own where not converged) and a converged mask (N,) bool."""
    start = (xy + 0.5) * scale - 0.5  # pixel centres of the shrunk frame in gray's pixels
    if len(xy) == 0:
        return start.astype(np.float32), np.zeros(0, bool)
    small = max(3, -(-radius // scale) + 1)  # the fine window on the shrunk frame, and a pixel for the peaks' rounding
    rough, ok = refine_saddle_points(shrunk, xy, small, 0.4 * small, 3, max_shift / scale, rough=True)
    begin = np.where(ok[:, None], (rough.astype(np.float64) + 0.5) * scale - 0.5, start)
    fine, ok = refine_saddle_points(gray, begin, radius, 0.4 * radius, max_shift=max_shift)
    ok &= np.hypot(*(fine - start).T) <= max_shift
    return np.where(ok[:, None], fine, start).astype(np.float32), ok


def refine_from_neighbours(gray: np.ndarray, starts: np.ndarray, radius: int, max_shift: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Saddle fits (refine_saddle_points, window `radius`) from the 4 diagonal neighbours of each start
    (K, 2) whose own fit failed: a corner between two pixels whose score peak lies on its light side,
    where the window reaches a marker's border a few px in (a ChArUco-style board: ccdn.grid, Markers),
    converges from the dark side. Each start takes the converged fit nearest it, within max_shift of
    it (a corner between two pixels lies 0.71 px from its peak pixel). Returns xy (K, 2) float32 (the
    starts' own where none converged) and a converged mask (K,) bool."""
    start = starts.astype(np.float64)
    k = len(start)
    # one call for all 4 neighbours (one smoothing of the frame's region); from a neighbour the fit may move
    # the step back to the start and max_shift beyond it
    fitted, ok = refine_saddle_points(gray, (start[None] + _DIAGONALS[:, None]).reshape(-1, 2), radius, 0.4 * radius,
                                      max_shift=max_shift + np.sqrt(2))
    fitted = fitted.reshape(4, k, 2)
    distance = np.where(ok.reshape(4, k), np.hypot(*(fitted - start[None]).transpose(2, 0, 1)), np.inf)
    nearest = distance.argmin(0)
    converged = distance[nearest, np.arange(k)] <= max_shift
    return np.where(converged[:, None], fitted[nearest, np.arange(k)], start).astype(np.float32), converged


_DIAGONALS = np.array([[1.0, 1.0], [-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0]])
_DIAGONALS.setflags(write=False)


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
