"""Argument types of the command line: every number an option takes is checked before any work.

A count is a positive (or non-negative) finite integer, a length, a time or a tolerance a finite
float in its range. Each function here is an ``argparse`` ``type=``: a value outside its range
raises :class:`argparse.ArgumentTypeError`, which the parser turns into the one line
``minegeo <verb>: error: argument --name: ...`` and exit status 2, before any file is read.

Example::

    parser.add_argument("--delta", type=positive_float, default=1.0)
    parser.add_argument("--max-iterations", type=positive_int, default=100)
    parser.add_argument("--confidence", type=open_unit_interval, default=0.95)
"""

from __future__ import annotations

import argparse
import math

__all__ = ["positive_int", "nonnegative_int", "positive_float", "nonnegative_float", "finite_float",
           "open_unit_interval", "int_in_range", "float_in_range"]

#: largest count an option accepts (a count above this is a typo, and keeps int64 arithmetic safe)
MAX_COUNT = 10**9


def _parse_float(text: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def _parse_int(text: str) -> int:
    try:
        return int(str(text).strip(), 10)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def finite_float(text: str) -> float:
    """A finite float (no NaN, no inf)."""
    return _parse_float(text)


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = _parse_float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be greater than 0")
    return value


def nonnegative_float(text: str) -> float:
    """A finite float >= 0."""
    value = _parse_float(text)
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r} must be 0 or more")
    return value


def open_unit_interval(text: str) -> float:
    """A probability or confidence strictly between 0 and 1."""
    value = _parse_float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} must lie strictly between 0 and 1")
    return value


def positive_int(text: str) -> int:
    """A whole number from 1 to :data:`MAX_COUNT`."""
    value = _parse_int(text)
    if not 1 <= value <= MAX_COUNT:
        raise argparse.ArgumentTypeError(f"{text!r} must be a whole number from 1 to {MAX_COUNT}")
    return value


def nonnegative_int(text: str) -> int:
    """A whole number from 0 to :data:`MAX_COUNT`."""
    value = _parse_int(text)
    if not 0 <= value <= MAX_COUNT:
        raise argparse.ArgumentTypeError(f"{text!r} must be a whole number from 0 to {MAX_COUNT}")
    return value


def int_in_range(lo: int, hi: int):
    """An argparse type: a whole number in ``[lo, hi]``."""

    def parse(text: str) -> int:
        value = _parse_int(text)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text!r} must be a whole number from {lo} to {hi}")
        return value

    parse.__name__ = f"int_in_range({lo}, {hi})"
    return parse


def float_in_range(lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False):
    """An argparse type: a finite float in the interval from ``lo`` to ``hi`` (ends open or closed)."""

    def parse(text: str) -> float:
        value = _parse_float(text)
        ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
        if not ok:
            left, right = "(" if lo_open else "[", ")" if hi_open else "]"
            raise argparse.ArgumentTypeError(f"{text!r} must lie in {left}{lo:g}, {hi:g}{right}")
        return value

    parse.__name__ = f"float_in_range({lo}, {hi})"
    return parse
