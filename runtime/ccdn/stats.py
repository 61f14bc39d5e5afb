"""Medians, quantiles and vector lengths for the detect path, without numpy's own.

np.median and np.percentile import numpy.ma on their first call (35-40 ms of a cold start here,
which parses signatures as it loads) and check for masked arrays on every call; np.linalg.norm's
argument handling costs more than its work on a few (x, y) vectors. These work on the small plain
arrays the detector has (gaps between peaks, tolerances, a few values per row, lattice steps) and
give np.median's, np.percentile's and np.linalg.norm's values to the bit (median: the mean of the
two middle values; quantile: numpy's default linear interpolation).
"""

from __future__ import annotations

import numpy as np


def median(a: np.ndarray, axis: int | None = None) -> np.ndarray | np.floating:
    """np.median(a, axis): NaN where a NaN is present (NaNs sort last)."""
    if axis is None:
        a, axis = np.ravel(a), 0
    ordered = np.sort(a, axis=axis)
    n = ordered.shape[axis]
    middle = (ordered.take((n - 1) // 2, axis) + ordered.take(n // 2, axis)) / 2
    return np.where(np.isnan(ordered.take(n - 1, axis)), np.nan, middle)[()]


def quantile(a: np.ndarray, q: float) -> float:
    """np.percentile(a, 100 q) of a 1-d float64 array without NaN (linear interpolation, numpy's form of it)."""
    ordered = np.sort(a)
    position = q * (len(ordered) - 1)
    low = int(np.floor(position))
    high = min(low + 1, len(ordered) - 1)
    t = position - low
    below, above = float(ordered[low]), float(ordered[high])
    step = above - below  # numpy interpolates from the nearer end
    return above - step * (1 - t) if t >= 0.5 else below + step * t


def nanmedian_rows(a: np.ndarray) -> np.ndarray:
    """Median along axis 1 ignoring NaN (NaN where a row has none): np.nanmedian without its slow
    masked-array path, for the few values per row used here."""
    ordered = np.sort(a, axis=1)  # NaNs sort last
    finite = np.isfinite(ordered)
    n = (finite if a.ndim == 2 else finite[..., 0]).sum(1)
    rows = np.arange(len(a))
    # the middle finite values (where there are none, index -1 and 0: any, overwritten below)
    median = (ordered[rows, (n - 1) // 2] + ordered[rows, n // 2]) / 2
    median[n == 0] = np.nan
    return median


def vector_lengths(vectors: np.ndarray, axis: int = -1) -> np.ndarray:
    """The lengths of vectors whose (x, y) run along `axis`: np.linalg.norm(vectors, axis=axis), to the bit."""
    return np.sqrt((vectors * vectors).sum(axis))
