"""The one JSON loader of minegeo's readers: bounded size and depth, no duplicate keys, no NaN.

Python's :func:`json.loads` accepts things a surveyor's file must not contain:

* **duplicate keys** (``{"A": {...}, "A": {...}}``): the last value silently wins, so a
  point or parameter typed twice loses one of its values without a word;
* ``NaN``, ``Infinity``, ``-Infinity`` (not JSON, RFC 8259 Sec. 6) and numbers such as
  ``1e400`` that overflow float64 to ``inf``;
* arbitrarily deep nesting, which ends in a ``RecursionError`` traceback.

:func:`load_json_text` and :func:`load_json_file` refuse all of these with a
:class:`~minegeo.errors.FileFormatError` naming the file. The nesting depth is measured
before parsing by a vectorised scan of the brackets outside strings (:func:`json_depth`,
linear in the text size, no Python loop over characters).
"""

from __future__ import annotations

import json
import math

import numpy as np

from minegeo.errors import FileFormatError
from minegeo.io.limits import read_file_bytes

__all__ = ["MAX_JSON_DEPTH", "MAX_JSON_BYTES", "load_json_text", "load_json_file", "json_depth"]

#: deepest nesting of arrays/objects accepted (minegeo's own files nest at most ~6 levels)
MAX_JSON_DEPTH = 64
#: largest JSON text accepted (bytes, UTF-8): networks and sidecars are kilobytes
MAX_JSON_BYTES = 64 << 20
#: most digits of a JSON integer (beyond float64's range, 1.8e308, a number is not a measurement)
_MAX_INT_DIGITS = 309


class _Reject(Exception):
    """Internal: raised by the parser hooks, turned into a FileFormatError with the path."""


def json_depth(data: bytes) -> int:
    """Deepest nesting of ``[``/``{`` outside strings in JSON ``data`` (0 for a scalar).

    Quotes preceded by an odd run of backslashes are escaped; brackets between unescaped
    quote pairs are inside strings. Memory: one byte per input byte plus 8 bytes per quote,
    backslash and bracket. Invalid JSON gives some number (the parser reports the error).
    """
    a = np.frombuffer(data, dtype=np.uint8)
    q = np.flatnonzero(a == 34)
    if q.size:
        bs = np.flatnonzero(a == 92)
        if bs.size:
            idx = np.arange(bs.size)
            start = np.ones(bs.size, dtype=bool)
            start[1:] = np.diff(bs) != 1
            run_start = np.maximum.accumulate(np.where(start, idx, 0))  # first backslash of each run
            prev = np.searchsorted(bs, q) - 1  # last backslash before each quote
            safe = np.maximum(prev, 0)
            touching = (prev >= 0) & (bs[safe] == q - 1)
            run = np.where(touching, safe - run_start[safe] + 1, 0)
            q = q[run % 2 == 0]
    br = np.flatnonzero((a == 91) | (a == 93) | (a == 123) | (a == 125))
    if br.size == 0:
        return 0
    if q.size:
        br = br[np.searchsorted(q, br) % 2 == 0]  # an even number of quotes before: outside strings
        if br.size == 0:
            return 0
    c = a[br]
    steps = np.where((c == 91) | (c == 123), 1, -1).astype(np.int64)
    return int(max(np.cumsum(steps).max(), 0))


def _dict_no_duplicates(pairs: list) -> dict:
    d = dict(pairs)
    if len(d) != len(pairs):
        seen: set = set()
        for k, _ in pairs:
            if k in seen:
                keys = ", ".join(str(kk) for kk, _ in pairs[:8]) + (", ..." if len(pairs) > 8 else "")
                raise _Reject(
                    f"duplicate key {k!r} in one JSON object (keys: {keys}); a repeated key would silently "
                    "keep only its last value: remove or rename one"
                )
            seen.add(k)
    return d


def _reject_constant(name: str):
    raise _Reject(f"{name} is not a number JSON allows (write a finite number, or null where a value is unknown)")


def _float(s: str) -> float:
    v = float(s)
    if not math.isfinite(v):
        raise _Reject(f"the number {s[:40]} is too large for float64")
    return v


def _int(s: str) -> int:
    if len(s.lstrip("-")) > _MAX_INT_DIGITS:
        raise _Reject(f"an integer with {len(s)} digits is too large to be a measurement")
    return int(s)


def load_json_text(
    text: str | bytes,
    path,
    *,
    max_depth: int = MAX_JSON_DEPTH,
    max_bytes: int = MAX_JSON_BYTES,
    allow_nonfinite: bool = False,
):
    """Parse JSON text strictly (see the module docstring).

    Parameters
    ----------
    text : str or bytes
        The JSON document (bytes are decoded as UTF-8, a byte-order mark is skipped).
    path : str or Path
        File (or other source) named in error messages.
    max_depth : int
        Deepest nesting of arrays/objects accepted.
    max_bytes : int
        Largest document accepted (bytes, UTF-8).
    allow_nonfinite : bool
        Accept ``NaN``/``Infinity`` (only for formats minegeo itself writes with them).

    Returns
    -------
    object
        The parsed value (dicts, lists, str, int, float, bool, None).

    Raises
    ------
    FileFormatError
        Too large, nested too deep, not valid JSON (with line and column), a duplicate key,
        or a non-finite number.
    """
    if isinstance(text, str):
        data = text.encode("utf-8", "surrogatepass")
    else:
        data = bytes(text)
    if len(data) > max_bytes:
        raise FileFormatError(path, f"JSON text of {len(data)} bytes is larger than the {max_bytes} allowed (wrong file?)")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    depth = json_depth(data)
    if depth > max_depth:
        raise FileFormatError(
            path, f"JSON nested {depth} levels deep, more than the {max_depth} a minegeo file can have (damaged or not "
            "a minegeo file?)"
        )
    try:
        s = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(path, f"JSON is not UTF-8 text (byte {exc.start})") from None
    kw: dict = {"object_pairs_hook": _dict_no_duplicates, "parse_int": _int}
    if not allow_nonfinite:
        kw.update(parse_constant=_reject_constant, parse_float=_float)
    try:
        return json.loads(s, **kw)
    except json.JSONDecodeError as exc:
        raise FileFormatError(path, f"invalid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
    except _Reject as exc:
        raise FileFormatError(path, str(exc)) from None
    except RecursionError:  # the depth scan should have caught it; belt and braces
        raise FileFormatError(path, "JSON nested too deep to read (damaged or not a minegeo file?)") from None
    except ValueError as exc:  # e.g. Python's limit on integer digits
        raise FileFormatError(path, f"invalid JSON: {exc}") from None


def load_json_file(path, *, max_depth: int = MAX_JSON_DEPTH, max_bytes: int = MAX_JSON_BYTES,
                   allow_nonfinite: bool = False, what: str = "JSON file"):
    """Read a regular file (:func:`~minegeo.io.limits.read_file_bytes`) and :func:`load_json_text` it."""
    data = read_file_bytes(path, max_bytes=max_bytes, what=what)
    return load_json_text(data, path, max_depth=max_depth, max_bytes=max_bytes, allow_nonfinite=allow_nonfinite)
