"""Sub-pixel corner refinement, vectorised over all corners of an image.

`saddle`: fit f(x, y) = a x^2 + b xy + c y^2 + d x + e y + g by least squares to a Gaussian-smoothed
patch around each corner (one matrix product for all corners: the fit's pseudo-inverse depends
only on the patch grid), step to the quadric's stationary point, re-centre and repeat. A checker
corner is a clear saddle (sqrt(b^2 - 4ac) >= `min_saddle` gray levels / px^2); a corner whose fit is
no saddle (flat, an edge, a blob), or that walks away from its peak, is flagged as not converged.

`cornersubpix`: OpenCV's gradient-orthogonality refinement (one C call for all corners).
Pixel convention: (0, 0) is the centre of the top-left pixel; xy is (x, y).
"""

from __future__ import annotations

import cv2
import numpy as np

METHODS = ("saddle", "cornersubpix", "none")


def _fit_matrix(radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets of a (2r+1)^2 patch and the pseudo-inverse of its quadric design matrix."""
    oy, ox = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    ox, oy = ox.ravel().astype(np.float64), oy.ravel().astype(np.float64)
    sigma = radius  # weight the centre more: the quadric only models the corner's neighbourhood
    w = np.exp(-(ox**2 + oy**2) / (2 * sigma**2))
    design = np.stack([ox * ox, ox * oy, oy * oy, ox, oy, np.ones_like(ox)], 1)
    pinv = np.linalg.pinv(design * w[:, None]) * w[None, :]
    return ox.astype(np.int64), oy.astype(np.int64), pinv


def refine_saddle_points(gray: np.ndarray, xy: np.ndarray, radius: int = 3, sigma: float = 1.2,
                         iterations: int = 3, max_shift: float = 2.0, min_saddle: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Refine integer peaks xy (N, 2) to sub-pixel saddle points of the smoothed image.

    Returns refined xy (N, 2) float32 and a converged mask (N,) bool.
    """
    n = len(xy)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    smooth = cv2.GaussianBlur(gray, (0, 0), sigma) if sigma > 0 else gray
    smooth = smooth.astype(np.float32)
    h, w = smooth.shape
    ox, oy, pinv = _fit_matrix(radius)
    start = xy.astype(np.float64)
    centre = np.rint(start).astype(np.int64)
    offset = np.zeros((n, 2))
    ok = np.ones(n, bool)
    for _ in range(iterations):
        px = np.clip(centre[:, 0:1] + ox[None], 0, w - 1)
        py = np.clip(centre[:, 1:2] + oy[None], 0, h - 1)
        coef = smooth[py, px].astype(np.float64) @ pinv.T  # (N, 6): a, b, c, d, e, g
        a, b, c, d, e = coef[:, 0], coef[:, 1], coef[:, 2], coef[:, 3], coef[:, 4]
        det = 4 * a * c - b * b
        safe = np.where(np.abs(det) < 1e-12, 1e-12, det)
        offset = np.stack([(b * e - 2 * c * d) / safe, (b * d - 2 * a * e) / safe], 1)
        ok = (det < -min_saddle * min_saddle) & np.all(np.isfinite(offset), 1)
        step = np.rint(np.clip(np.where(ok[:, None], offset, 0), -radius, radius)).astype(np.int64)
        if not step.any():
            break
        centre = centre + step
    refined = centre + offset
    ok &= np.all(np.abs(offset) <= 0.75, 1) & (np.hypot(*(refined - start).T) <= max_shift)
    ok &= (refined[:, 0] >= 0) & (refined[:, 0] <= w - 1) & (refined[:, 1] >= 0) & (refined[:, 1] <= h - 1)
    return np.where(ok[:, None], refined, start).astype(np.float32), ok


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


def refine(gray: np.ndarray, xy: np.ndarray, method: str = "saddle", max_shift: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Dispatch to a refinement method by name (see METHODS); corners may move up to max_shift px."""
    if method == "saddle":
        return refine_saddle_points(gray, xy, max_shift=max_shift)
    if method == "cornersubpix":
        return refine_cornersubpix(gray, xy, max_shift=max_shift)
    if method == "none":
        return xy.astype(np.float32), np.ones(len(xy), bool)
    raise ValueError(f"unknown refinement {method!r}; choose from {METHODS}")
