"""ccdn.stats: np.median's and np.percentile's values, to the bit, without numpy.ma."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ccdn.stats import median, nanmedian_rows, quantile

finite = st.floats(-1e6, 1e6, allow_nan=False, width=32)


@given(arrays(st.sampled_from([np.float32, np.float64]), st.tuples(st.integers(1, 5), st.integers(1, 20)),
              elements=st.floats(-1e6, 1e6, width=32) | st.just(np.nan)))
def test_median_is_numpys_with_nan_where_a_nan_is(a):
    assert np.array_equal(median(a, axis=1), np.median(a, axis=1), equal_nan=True)
    assert np.array_equal(median(a), np.median(a), equal_nan=True)


@given(arrays(np.float64, st.integers(1, 40), elements=finite), st.sampled_from([0.1, 0.25, 0.5, 0.75, 0.9]))
def test_quantile_is_numpys_percentile(a, q):
    assert quantile(a, q) == np.percentile(a, 100 * q)


def test_nanmedian_rows_ignores_nan_and_gives_nan_for_a_row_without_values():
    a = np.array([[1.0, np.nan, 3.0, 2.0], [np.nan] * 4, [4.0, 1.0, np.nan, np.nan]])
    assert np.array_equal(nanmedian_rows(a), [2.0, np.nan, 2.5], equal_nan=True)


def test_detecting_imports_no_masked_arrays(examples):
    """numpy.ma costs 35-40 ms of a cold start; np.median, np.percentile and np.unique import it."""
    code = ("import sys, numpy as np, ccdn; d = ccdn.Detector(threads=1); "
            f"[d.detect(str(p)) for p in {sorted(str(e['path']) for e in examples.values())!r}]; "
            "d.detect(np.zeros((480, 640), np.uint8)); assert 'numpy.ma' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
