"""Vectorised parsing and formatting of numeric text tables (ASCII PLY/PCD bodies, XYZ, CSV).

Parsing uses an exact Numba fast path (decimal significands up to 2^53, exponents within
+-22: one correctly rounded IEEE operation, Clinger 1990) and otherwise NumPy's C tokenizer
(:func:`numpy.loadtxt`); never a Python loop over rows.
Only when parsing fails does a diagnostic pass walk the lines to name the first bad one
(line numbers are 1-based and count from the start of the file).
"""

from __future__ import annotations

import io

import numpy as np

from minegeo.errors import FileFormatError
from minegeo.io.limits import MAX_COLUMNS

__all__ = [
    "parse_table",
    "format_table",
    "line_offsets",
    "is_number",
    "data_line_locator",
    "unterminated_last_line",
    "note_unterminated_last_line",
]

#: rows formatted per ``%`` operation when writing text (bounds memory, no per-row loop)
_CHUNK_ROWS = 200_000


def is_number(token: str) -> bool:
    """True if ``token`` parses as a float (``nan``/``inf`` included)."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def line_offsets(data: bytes | memoryview, start: int, nlines: int) -> int:
    """Byte offset just after the ``nlines``-th newline at or after ``start`` (or ``len(data)``)."""
    if nlines <= 0:
        return start
    buf = np.frombuffer(data, dtype=np.uint8, offset=start)
    nl = np.flatnonzero(buf == 10)
    if nl.size < nlines:
        return len(data)
    return start + int(nl[nlines - 1]) + 1


def unterminated_last_line(data: bytes | str) -> tuple[int, str] | None:
    """``(line number, text)`` of a last data line that has no end-of-line, else None.

    A file cut short (copy interrupted, disk full) usually ends in the middle of a line. A
    line cut at a separator has fewer values than the others and :func:`parse_table` refuses
    it (naming the line); a line cut inside a number (``12.3`` for ``12.345``) cannot be told
    from a complete one, only the missing end-of-line shows it. Blank and ``#`` comment tails
    are ignored.
    """
    nl = "\n" if isinstance(data, str) else b"\n"
    if not data or data.endswith(nl):
        return None
    tail = data[data.rfind(nl) + 1 :]
    if isinstance(tail, bytes):
        tail = tail.decode("latin-1")
    tail = tail.strip()
    if not tail or tail.startswith("#") or tail.startswith("//"):
        return None
    return data.count(nl) + 1, tail


def note_unterminated_last_line(path, data: bytes | str, meta: dict) -> None:
    """Record a missing final end-of-line in ``meta`` (policy of the text readers).

    The points are read (many programs write no final newline) but
    ``meta["unterminated_last_line"]`` holds the line number and ``meta["warnings"]`` a
    sentence that :func:`~minegeo.io.read_point_cloud` logs once the file has been read
    completely, so the surveyor is told to check the last point.
    """
    found = unterminated_last_line(data)
    if found is None:
        return
    lineno, tail = found
    meta["unterminated_last_line"] = lineno
    meta.setdefault("warnings", []).append(
        f"the last line ({lineno}: {tail[:60]!r}) has no end-of-line: the file may have been cut short; "
        "check that its values are complete"
    )


def data_line_locator(text: str, first_line: int, comments: str | None = "#"):
    """Return ``f(row) -> line number`` of the ``row``-th data row of ``text`` (error path only).

    Blank lines and comment lines are skipped exactly as :func:`parse_table` skips them.
    """

    def locate(row: int) -> int | None:
        count = -1
        for i, line in enumerate(io.StringIO(text)):
            s = line.strip()
            if not s or (comments and s.startswith(comments)):
                continue
            count += 1
            if count == row:
                return first_line + i
        return None

    return locate


def _diagnose(path, text: str, ncols: int | None, delimiter: str | None, first_line: int) -> str | None:
    """Find the first malformed line (error path only); return a message or None."""
    for i, line in enumerate(text.splitlines()):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        toks = [t for t in (s.split(delimiter) if delimiter else s.split())]
        if delimiter:
            toks = [t.strip() for t in toks]
        if ncols is not None and len(toks) != ncols:
            return f"line {first_line + i}: expected {ncols} values, found {len(toks)}: {s[:80]!r}"
        for t in toks:
            if not is_number(t):
                return f"line {first_line + i}: {t[:40]!r} is not a number"
        if ncols is None:
            ncols = len(toks)
    return None


def parse_table(
    path,
    text: str,
    ncols: int | None,
    first_line: int,
    delimiter: str | None = None,
    expected_rows: int | None = None,
    max_rows: int | None = None,
    comments: str | None = "#",
) -> np.ndarray:
    """Parse a numeric table into a float64 ``(rows, ncols)`` array.

    Parameters
    ----------
    path : str
        File name used in error messages.
    text : str
        The table text (no header).
    ncols : int or None
        Required number of columns (None: take it from the first row).
    first_line : int
        1-based line number of the first line of ``text`` within the file.
    delimiter : str or None
        Column separator (None: any whitespace).
    expected_rows : int or None
        If given, the number of rows must match (header point count).
    max_rows : int or None
        Read at most this many rows (rest of ``text`` ignored).

    Raises
    ------
    FileFormatError
        Non-numeric value, varying number of columns (names the line), or a row count that
        differs from ``expected_rows``.
    """
    if ncols is not None and ncols > MAX_COLUMNS:
        raise FileFormatError(path, f"{ncols} values per line declared, more than the {MAX_COLUMNS} allowed (damaged header?)")
    if not text.strip():
        arr = np.empty((0, ncols or 0))
    elif (arr := _fast_parse(text, ncols, delimiter, comments, max_rows)) is not None:
        pass
    else:
        try:
            arr = np.loadtxt(
                io.StringIO(text),
                dtype=np.float64,
                delimiter=delimiter,
                comments=comments,
                ndmin=2,
                max_rows=max_rows,
                encoding=None,
            )
        except ValueError as exc:
            body = text if max_rows is None else "\n".join(text.splitlines()[: max_rows + 1000])
            msg = _diagnose(path, body, ncols, delimiter, first_line)
            raise FileFormatError(path, msg or f"unreadable numeric data ({exc})") from None
    if ncols is not None and arr.shape[0] > 0 and arr.shape[1] != ncols:
        msg = _diagnose(path, text, ncols, delimiter, first_line)
        raise FileFormatError(path, msg or f"expected {ncols} values per line, found {arr.shape[1]}")
    if expected_rows is not None and arr.shape[0] != expected_rows:
        what = "file truncated?" if arr.shape[0] < expected_rows else "header count too small?"
        raise FileFormatError(
            path, f"header declares {expected_rows} points but {arr.shape[0]} data lines were found ({what})"
        )
    return arr


def _fast_parse(text: str, ncols: int | None, delimiter: str | None, comments: str | None, max_rows: int | None):
    """Exact Numba fast path (see :func:`minegeo.io._kernels.parse_text_kernel`), or None."""
    if ncols is None or ncols < 1 or delimiter not in (None, ",", ";") or comments not in (None, "#"):
        return None
    from minegeo.io._kernels import POW10, parse_text_kernel

    buf = np.frombuffer(text.encode("latin-1"), dtype=np.uint8)
    nlines = int(np.count_nonzero(buf == 10)) + 1
    if max_rows is not None:
        nlines = min(nlines, max_rows)
    # a row of ncols values takes at least 2 * ncols bytes: never allocate more rows than fit
    # (blank and comment lines count in nlines; if the bound is hit the kernel falls back)
    nlines = min(nlines, buf.size // (2 * ncols) + 1)
    out = np.empty((nlines, ncols), dtype=np.float64)
    rows, status = parse_text_kernel(
        buf,
        ncols,
        0 if delimiter is None else ord(delimiter),
        -1 if comments is None else ord(comments),
        -1 if max_rows is None else int(max_rows),
        POW10,
        out,
    )
    if status != 0:
        return None
    return out[:rows] if rows == nlines else out[:rows].copy()


def format_table(columns: list[np.ndarray], formats: list[str], delimiter: str = " ") -> str:
    """Format columns as text rows, e.g. ``formats=["%.17g"] * 3`` (vectorised in chunks).

    Integer columns should use ``"%d"``; every column is passed through float64, which is
    exact for all integer types up to 32 bits and for float32.
    """
    n = columns[0].shape[0] if columns else 0
    if n == 0:
        return ""
    mat = np.column_stack([np.asarray(c, dtype=np.float64) for c in columns])
    row = delimiter.join(formats) + "\n"
    parts = []
    for s in range(0, n, _CHUNK_ROWS):
        block = mat[s : s + _CHUNK_ROWS]
        parts.append((row * block.shape[0]) % tuple(block.ravel().tolist()))
    return "".join(parts)
