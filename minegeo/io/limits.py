"""Bounded reading of input files: every reader knows how much it may allocate before it does.

A user can name anything on the command line: a character device (``/dev/zero``,
``/dev/urandom``), a FIFO whose writer never stops, a socket, a file whose header announces
more points than it holds, a header that never ends, a zip bomb. The readers of
:mod:`minegeo.io`, :mod:`minegeo.mast` and :mod:`minegeo.survey` therefore

* read only **regular files**, whose size is known (``fstat``) before a byte is allocated
  (:func:`read_file_bytes`); special files are refused with a :class:`FileFormatError`
  without being opened (opening a FIFO would block until a writer appears);
* read Python-parsed tables (control points, beacons, 2D scans, survey networks) only up to
  :data:`MAX_TABLE_FILE_BYTES`;
* look for the end of a header only within :data:`MAX_HEADER_BYTES`;
* check a header's point count against the bytes that follow it before allocating for it;
* refuse coordinates beyond :data:`MAX_ABS_COORDINATE` (file units), so that no later sum,
  difference or square overflows float64 (:func:`check_coordinate_range`).

Running out of memory while reading a (regular, large) file is reported as a
:class:`FileFormatError` naming the file and its size instead of a ``MemoryError`` traceback.
"""

from __future__ import annotations

import os
import stat

import numpy as np

from minegeo.errors import FileFormatError

__all__ = [
    "MAX_HEADER_BYTES",
    "MAX_HEADER_LINE_BYTES",
    "MAX_TABLE_FILE_BYTES",
    "MAX_COLUMNS",
    "MAX_ABS_COORDINATE",
    "MAX_ABS_TIME",
    "MIN_SIGMA_M",
    "MAX_ZIP_MEMBER_BYTES",
    "MAX_ZIP_RATIO",
    "read_file_bytes",
    "read_file_text",
    "check_coordinate_range",
    "file_kind",
]

#: bytes within which a PLY/PCD header must end (``end_header`` / ``DATA``): real headers are
#: a few hundred bytes, a CloudCompare or PCL header with many comments a few kilobytes
MAX_HEADER_BYTES = 1 << 20
#: longest header / preamble line of a text cloud (bytes): the column-name line of a file with
#: thousands of columns is still far below this
MAX_HEADER_LINE_BYTES = 1 << 16
#: largest control-point, beacon, 2D-scan, survey-network, ``.adj`` or 4x4-matrix file (bytes).
#: These are parsed line by line in Python; real ones are kilobytes (a MAST scan of a million
#: returns is ~20 MB)
MAX_TABLE_FILE_BYTES = 64 << 20
#: most values on one line / in one point record (a PCD ``COUNT`` sum, a PLY property list, text
#: columns): descriptors have tens to hundreds; a larger header count is damage
MAX_COLUMNS = 1 << 16
#: largest absolute coordinate (or range) accepted from a file, in the file's units: 10^12 m is
#: beyond the solar system, 10^12 mm is 10^9 m; with this bound ``x - y``, ``x + y`` and
#: ``x * x`` of any two coordinates are finite in float64
MAX_ABS_COORDINATE = 1e12
#: largest absolute time stamp accepted from a trajectory file (its units: seconds, or the
#: nanoseconds of ROS stamps, ~1.7e18 today); differences of two stamps stay finite
MAX_ABS_TIME = 1e20
#: smallest a-priori standard deviation accepted from a file (m): its weight ``1/sigma^2`` stays
#: far inside float64 (a nanometre is beyond any survey instrument)
MIN_SIGMA_M = 1e-9
#: largest uncompressed member of a ``.zip`` point cloud (bytes, as declared in the archive)
MAX_ZIP_MEMBER_BYTES = 1 << 34
#: largest compression ratio (uncompressed / compressed bytes) of a ``.zip`` member larger
#: than :data:`_ZIP_RATIO_FREE_BYTES`; point clouds deflate 1.5-10x, a zip bomb ~1000x
MAX_ZIP_RATIO = 200
#: members up to this size (bytes) are read whatever their compression ratio
_ZIP_RATIO_FREE_BYTES = 64 << 20


def file_kind(mode: int) -> str:
    """Human name of a non-regular file type from ``st_mode`` (for error messages)."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _human(n: int) -> str:
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} bytes"


def read_file_bytes(path, *, max_bytes: int | None = None, what: str = "file") -> bytes:
    """Read a regular file whole, knowing its size before allocating.

    Parameters
    ----------
    path : str or Path
        The file; opened read-only. Symbolic links are followed.
    max_bytes : int, optional
        Refuse larger files (``None``: no limit other than memory).
    what : str
        What the file should be, for error messages (``"point-cloud file"``).

    Returns
    -------
    bytes
        The file's contents.

    Raises
    ------
    FileFormatError
        ``path`` is a directory, character/block device, FIFO or socket (refused without
        opening it), larger than ``max_bytes``, changed size while being read, or does not
        fit in memory.
    FileNotFoundError, PermissionError
        As raised by the operating system.
    """
    st = os.stat(path)  # never open() first: opening a FIFO blocks until a writer comes
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(
            path, f"is {file_kind(st.st_mode)}, not a {what}: minegeo reads regular files only (copy the data to a file)"
        )
    _check_size(path, st.st_size, max_bytes, what)
    try:
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())  # the file that was opened (it may have been replaced)
            if not stat.S_ISREG(st.st_mode):
                raise FileFormatError(path, f"is {file_kind(st.st_mode)}, not a {what}")
            size = _check_size(path, st.st_size, max_bytes, what)
            data = fh.read(size)
            if len(data) != size or fh.read(1):
                raise FileFormatError(
                    path, f"the file changed size while it was read ({_human(size)} expected); is another program writing it?"
                )
    except MemoryError:
        raise FileFormatError(path, f"not enough memory to read this {_human(st.st_size)} {what}") from None
    return data


def _check_size(path, size: int, max_bytes: int | None, what: str) -> int:
    if max_bytes is not None and size > max_bytes:
        raise FileFormatError(
            path, f"is {_human(size)}, larger than the {_human(max_bytes)} a {what} may have (wrong file?)"
        )
    return int(size)


def read_file_text(path, *, encoding: str = "utf-8", max_bytes: int | None = MAX_TABLE_FILE_BYTES,
                   what: str = "text file") -> str:
    """:func:`read_file_bytes` then decode; undecodable text is a :class:`FileFormatError`.

    ``encoding="utf-8-sig"`` tolerates a byte-order mark.
    """
    data = read_file_bytes(path, max_bytes=max_bytes, what=what)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise FileFormatError(
            path, f"line {line}: byte {data[exc.start]:#04x} is not {encoding.replace('-sig', '').upper()} text: save "
            f"the {what} as UTF-8 (or is it a binary file?)"
        ) from None


def check_coordinate_range(path, values: np.ndarray, what: str = "coordinate", locate=None,
                           limit: float = MAX_ABS_COORDINATE, row_noun: str = "point") -> None:
    """Refuse values beyond ``+-limit`` (NaN/inf are left to the caller's own check).

    Two reductions without temporaries (``max`` and ``min``); rows are located only on the
    error path.

    Parameters
    ----------
    path : str or Path
        File named in the message.
    values : ndarray
        Finite values (a NaN makes ``max`` NaN and is ignored here).
    what : str
        What the values are (``"coordinate"``, ``"range"``), for the message.
    locate : callable, optional
        ``row -> text`` naming a row (e.g. ``"point 7 (line 12)"``) for the message.
    limit : float
        Largest accepted absolute value (default :data:`MAX_ABS_COORDINATE`).
    row_noun : str
        What a row is (``"point"``, ``"pose"``), for the message.

    Raises
    ------
    FileFormatError
        A value beyond ``+-limit``; the message counts the rows and names the first.
    """
    v = np.asarray(values)
    if v.size == 0 or not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        return
    hi, lo = v.max(), v.min()
    if not (hi > limit or lo < -limit):
        return
    with np.errstate(invalid="ignore"):
        bad = np.abs(v) > limit
    rows = np.flatnonzero(bad.reshape(v.shape[0], -1).any(axis=1)) if v.ndim > 1 else np.flatnonzero(bad)
    i = int(rows[0])
    val = float(v[i][np.argmax(bad[i])]) if v.ndim > 1 else float(v[i])
    where = locate(i) if callable(locate) else f"{row_noun} {i}"
    raise FileFormatError(
        path,
        f"{rows.size} {row_noun}(s) with a {what} beyond +-{limit:.0e} (first: {where}: {val:.6g}); not a survey "
        f"{what}: the file is damaged or in the wrong units",
    )
