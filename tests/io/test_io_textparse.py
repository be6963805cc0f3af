"""The exact Numba text parser agrees bit for bit with NumPy's (strtod-based) parser."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.io.text import _fast_parse, parse_table

FMTS = ["%.3f", "%.6g", "%.9g", "%.15g", "%.17g", "%e", "%.2E", "%d", "%.0f", "%+.4f"]


@settings(max_examples=60, deadline=None)
@given(
    vals=st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=3, max_size=60),
    fmt=st.sampled_from(FMTS),
    delim=st.sampled_from([None, ","]),
)
def test_fast_parser_matches_numpy(vals, fmt, delim):
    k = 3
    n = len(vals) // k
    a = np.array(vals[: n * k]).reshape(n, k)
    if fmt == "%d":
        a = np.trunc(np.clip(a, -1e15, 1e15))
    sep = " " if delim is None else ", "
    text = "".join(sep.join(fmt % v for v in row) + "\n" for row in a)
    ref = np.loadtxt(io.StringIO(text), delimiter=delim, ndmin=2)
    fast = _fast_parse(text, k, delim, "#", None)
    if fast is not None:  # the fast path either declines or is exact
        assert fast.shape == ref.shape
        np.testing.assert_array_equal(fast.view(np.int64), ref.view(np.int64))
    got = parse_table("t", text, ncols=k, first_line=1, delimiter=delim)
    np.testing.assert_array_equal(got.view(np.int64), ref.view(np.int64))


@pytest.mark.parametrize(
    "text,expected",
    [
        ("1. .5 -.5\n+3 1e5 1E-05\n00012 0.000 -0\n", [[1, 0.5, -0.5], [3, 1e5, 1e-5], [12, 0, -0.0]]),
        ("# comment\n\n  1 2 3  \r\n\t4\t5\t6\n", [[1, 2, 3], [4, 5, 6]]),
        ("0.1 0.2 0.3\n", [[0.1, 0.2, 0.3]]),
        ("512345.123 4123456.789 350.001\n", [[512345.123, 4123456.789, 350.001]]),
    ],
)
def test_fast_parser_tokens(text, expected):
    got = _fast_parse(text, 3, None, "#", None)
    assert got is not None
    np.testing.assert_array_equal(got, expected)
    assert np.signbit(got).tolist() == np.signbit(np.array(expected, dtype=float)).tolist()


@pytest.mark.parametrize(
    "text",
    ["nan 1 2\n", "1 2\n", "1 2 3 4\n", "1.5.2 1 2\n", "0x10 1 2\n", "1e 2 3\n", "- 1 2\n", "1,2,3\n",
     "1 2 123456789012345678901\n", "1e-300 1 2\n"],
)
def test_fast_parser_declines(text):
    assert _fast_parse(text, 3, None, "#", None) is None


def test_fast_parser_max_rows_and_trailing_delimiter():
    got = _fast_parse("1 2 3\n4 5 6\n7 8\n", 3, None, None, 2)
    np.testing.assert_array_equal(got, [[1, 2, 3], [4, 5, 6]])
    assert _fast_parse("1,2,3,\n", 3, ",", "#", None) is None
