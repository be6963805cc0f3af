"""Delimited survey tables (control points, stations): the shared line grammar.

A table file is UTF-8 text: blank lines and ``#`` comment lines are skipped, except a comment
``# crs: EPSG:5186`` (also ``# crs = ...``) which names the file's CRS; the first other line is the
header; every following line is a row with as many fields as the header. The delimiter is taken
from the header line: ``,`` if it has one, else ``;``, else a tab, else runs of white space.
Fields are read with :mod:`csv` (quotes allowed) and stripped.

Every error names the file and the line (:class:`~minegeo.errors.FileFormatError`). What the
columns mean, and the checks of the header and of each value, belong to the reader of the kind
of table (:func:`minegeo.io.gcp.read_gcps`, :func:`minegeo.io.stations.read_stations`), which
uses :func:`number` and :func:`sigma` for the checks they share.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from minegeo.errors import FileFormatError
from minegeo.io.limits import MIN_SIGMA_M

__all__ = ["Table", "read_table", "table_writer", "number", "check_sigma", "new_id", "split_fields", "delimiter"]


def delimiter(line: str) -> str | None:
    """The delimiter of a header line: ``,``, else ``;``, else tab, else None (white space)."""
    return "," if "," in line else (";" if ";" in line else ("\t" if "\t" in line else None))


def split_fields(path, lineno: int, line: str, delim: str | None) -> list[str]:
    """The stripped fields of one line (``delim`` None: split on runs of white space)."""
    if delim is None:
        return line.split()
    try:
        row = next(csv.reader([line], delimiter=delim, skipinitialspace=True), [])
    except csv.Error as exc:
        raise FileFormatError(path, f"line {lineno}: unreadable CSV ({exc})") from None
    return [t.strip() for t in row]


@dataclass(frozen=True)
class Table:
    """The header and rows of a table file, before any value is interpreted.

    Attributes
    ----------
    names : tuple of str
        Header fields as written.
    columns : tuple of str
        Header fields in their canonical spelling (the reader's ``canon``).
    rows : tuple of (int, dict)
        ``(line number, {canonical column: field text})`` per row, in file order.
    crs : str or None
        The value of the file's last ``# crs:`` comment.
    """

    names: tuple[str, ...]
    columns: tuple[str, ...]
    rows: tuple[tuple[int, dict[str, str]], ...]
    crs: str | None


def read_table(path, text: str, canon: Callable[[str], str],
               check_header: Callable[[int, list[str], list[str]], None]) -> Table | None:
    """Split ``text`` (the file's content) into a :class:`Table`; None when it has no header.

    ``canon(name)`` gives a header field's canonical column name; ``check_header(lineno, names,
    columns)`` raises the reader's own error for a header it does not accept.
    """
    p = Path(path)
    file_crs = None
    names: list[str] | None = None
    columns: list[str] = []
    delim = None
    rows: list[tuple[int, dict[str, str]]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line[1:].strip()
            if body.lower().startswith("crs"):
                value = body[3:].lstrip(" :=").strip()
                if not value:
                    raise FileFormatError(p, f"line {lineno}: '# crs:' line without a CRS")
                file_crs = value
            continue
        if names is None:
            delim = delimiter(line)
            names = split_fields(p, lineno, line, delim)
            columns = [canon(n) for n in names]
            check_header(lineno, names, columns)
            continue
        toks = split_fields(p, lineno, line, delim)
        if len(toks) != len(columns):
            raise FileFormatError(p, f"line {lineno}: expected {len(columns)} fields, found {len(toks)}")
        rows.append((lineno, dict(zip(columns, toks, strict=True))))
    if names is None:
        return None
    return Table(names=tuple(names), columns=tuple(columns), rows=tuple(rows), crs=file_crs)


def number(path, lineno: int, column: str, text: str, limit: float, what: str = "") -> float:
    """The finite float in field ``text`` of ``column``, at most ``limit`` in magnitude.

    ``what`` is added to the out-of-range message (e.g. ``": not a survey coordinate"``)."""
    try:
        v = float(text)
    except ValueError:
        raise FileFormatError(path, f"line {lineno}: {column} = {text!r} is not a number") from None
    if not math.isfinite(v):
        raise FileFormatError(path, f"line {lineno}: {column} is {text} (NaN/inf not allowed)")
    if abs(v) > limit:
        raise FileFormatError(path, f"line {lineno}: {column} = {v:g} is beyond +-{limit:.0e}{what} "
                                    "(damaged file or wrong units?)")
    return v


def check_sigma(path, lineno: int, column: str, text: str, v: float, meaning: str = "") -> float:
    """``v`` (a standard deviation in m read from field ``text``) checked: > 0 and not below
    :data:`~minegeo.io.limits.MIN_SIGMA_M`; ``meaning`` is added to the message of a value <= 0."""
    if v <= 0:
        raise FileFormatError(path, f"line {lineno}: {column} = {text} must be > 0{meaning}")
    if v < MIN_SIGMA_M:
        raise FileFormatError(path, f"line {lineno}: {column} = {v:g} m is below {MIN_SIGMA_M:g} m, finer than any "
                                    "survey (wrong units?)")
    return v


def new_id(path, lineno: int, text: str, ids: list[str], lines: list[int]) -> str:
    """``text`` as the id of the row on ``lineno``: not empty and not one of ``ids`` (read on ``lines``)."""
    if not text:
        raise FileFormatError(path, f"line {lineno}: empty id")
    if text in ids:
        raise FileFormatError(path, f"line {lineno}: duplicate id {text!r} (first on line {lines[ids.index(text)]})")
    return text


def table_writer(crs) -> tuple:
    """``(text buffer, csv.writer)`` of a table file as :func:`read_table` reads it: a
    ``# crs: <crs>`` line first when ``crs`` is set (white space folded to single spaces), rows
    comma-separated, LF line ends."""
    buf = io.StringIO()
    if crs:
        buf.write(f"# crs: {' '.join(str(crs).split())}\n")
    return buf, csv.writer(buf, lineterminator="\n")
