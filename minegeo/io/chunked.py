"""Chunked reading of point-cloud files: bounded memory for maps of any size.

:func:`open_point_chunks` opens a file and returns a :class:`PointChunks`, iterable any number
of times (each iteration reads the file again from the start), yielding float64 ``(k, 3)``
arrays of at most ``chunk_points`` points in file order. Concatenated, the chunks are
**bit-identical** to ``read_point_cloud(path, origin=origin).points``: the same parsers and
the same float conversions are applied to each slice of the file (tests in
``tests/io/test_io_chunked.py``). The file's metadata (``crs``, recorded ``file_origin``,
``n_points``, format, encoding) is read once from the header, before any point.

==========================  =====================================================================
format                      how it is chunked
==========================  =====================================================================
PLY binary (both endians)   ``numpy.fromfile`` of ``chunk_points`` records at a time
PLY ascii                   blocks of whole lines parsed by :func:`minegeo.io.text.parse_table`
                            (a vertex element preceded by other elements: read whole)
PCD binary / ascii          as PLY
PCD binary_compressed       read whole (one LZF stream cannot be split), then sliced
LAS / LAZ                   ``laspy.open(...).chunk_iterator`` (LAZ decoded chunk by chunk)
E57                         :func:`minegeo.io.e57.iter_e57_chunks` (the ``e57`` extra)
XYZ / CSV / PTS / 3D / zip  read whole with :func:`~minegeo.io.read_point_cloud`, then sliced
==========================  =====================================================================

"Read whole" formats still work but their memory is the whole cloud (logged once at INFO).
Errors are typed as in the whole-file readers: a truncated binary file is a
:class:`~minegeo.errors.FileFormatError` before the first point is read (the header's point
count is checked against the file size), a truncated text or LAZ file when the short chunk
is reached; NaN/inf and out-of-range coordinates name the global point index.
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io.limits import MAX_ABS_COORDINATE, MAX_HEADER_BYTES, check_coordinate_range, file_kind

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_CHUNK_POINTS", "PointChunks", "open_point_chunks", "iter_point_chunks", "scan_bounds"]

#: Default points per chunk (about 24 MB of float64 coordinates, ~100 MB of reader temporaries).
DEFAULT_CHUNK_POINTS = 1 << 21
#: Text blocks: bytes read per block for every point of ``chunk_points`` (then split on lines).
_TEXT_BYTES_PER_POINT = 48


@dataclass
class PointChunks:
    """A point-cloud file opened for chunked reading (see the module docstring).

    Attributes
    ----------
    path : Path
    format : str
        ``ply pcd las laz e57 xyz ...``.
    encoding : str or None
        PLY/PCD data encoding.
    n_points : int or None
        Points declared by the header (None when the format does not say before reading).
    file_origin : (3,) float64
        Offset recorded in the file (LAS offset, ``minegeo origin`` comment), m.
    crs : str or None
        CRS recorded in the file.
    size_bytes : int
        File size (the progress total).
    chunked : bool
        False for the formats that are read whole and sliced.
    chunk_points : int
        Points per yielded chunk (the last one may be shorter).
    origin : (3,) float64
        Subtracted from global coordinates: chunks hold ``global - origin``.
    metadata : dict
        ``xyz_only`` (PLY/PCD: the records hold x, y, z and nothing else), ``read_whole``, LAS
        ``las_scale``/``las_offset``.
    bytes_read : int
        File position reached by the current iteration (for progress bars).
    """

    path: Path
    format: str
    encoding: str | None
    n_points: int | None
    file_origin: np.ndarray
    crs: str | None
    size_bytes: int
    chunked: bool
    chunk_points: int
    origin: np.ndarray
    metadata: dict = field(default_factory=dict)
    bytes_read: int = 0
    _values: Callable | None = field(default=None, repr=False)

    def __iter__(self) -> Iterator[np.ndarray]:
        shift = self.file_origin - self.origin
        add = bool(np.any(shift != 0))
        done = 0
        self.bytes_read = 0
        for values, pos in self._values(self):
            _check_values(self.path, values, done)
            done += values.shape[0]
            self.bytes_read = pos
            # the whole-file reader's ``values + shift`` (io._common.assemble), row by row
            yield values + shift if add else values
        if self.n_points is not None and done != self.n_points:
            raise FileFormatError(self.path, f"header declares {self.n_points} points but {done} were read (file truncated?)")
        self.bytes_read = self.size_bytes


def _check_values(path, values: np.ndarray, first: int) -> None:
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0]) + first
        raise FileFormatError(path, f"point {bad} has NaN or inf coordinates (a map must hold finite points only)")
    check_coordinate_range(path, values, "coordinate", lambda i: f"point {first + i}")


def _regular_size(p: Path) -> int:
    st = os.stat(p)  # never open() first: opening a FIFO blocks until a writer comes
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(p, f"is {file_kind(st.st_mode)}, not a point-cloud file: minegeo reads regular files only")
    return int(st.st_size)


def _head(p: Path, size: int) -> bytes:
    with open(p, "rb") as fh:
        return fh.read(min(size, MAX_HEADER_BYTES + 1))


def _check_chunk_points(chunk_points) -> int:
    if isinstance(chunk_points, bool) or not isinstance(chunk_points, (int, np.integer)) or int(chunk_points) < 1:
        raise InputError(f"chunk_points must be a positive integer, got {chunk_points!r}")
    return int(chunk_points)


def open_point_chunks(path, chunk_points: int = DEFAULT_CHUNK_POINTS, origin=None) -> PointChunks:
    """Open a point-cloud file for chunked reading (header read and checked now).

    Parameters
    ----------
    path : str or Path
        The file (regular file; ``.ply .pcd .las .laz .e57`` chunked, others read whole).
    chunk_points : int
        Points per chunk (>= 1).
    origin : None, "file" or (3,) array_like
        As in :func:`~minegeo.io.read_point_cloud` (``"auto"`` needs the bounds: not here).

    Returns
    -------
    PointChunks

    Raises
    ------
    FileFormatError
        Unreadable header, or a binary body shorter than the header's point count.
    InputError
        Bad ``chunk_points``/``origin``. An E57 file without the ``e57`` extra raises
        :class:`~minegeo.errors.OptionalDependencyError`.
    """
    k = _check_chunk_points(chunk_points)
    p = Path(path)
    if not p.exists():
        raise InputError(f"point-cloud file {p} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".e57":
        src = _open_e57(p)
    else:
        size = _regular_size(p)
        from minegeo.io.pointcloud import detect_format

        fmt = detect_format(p)
        opener = {"ply": _open_ply, "pcd": _open_pcd, "las": _open_las, "laz": _open_las}.get(fmt)
        src = opener(p, size) if opener is not None else None
        if src is None:
            src = _open_whole(p, size, fmt)
    src.chunk_points = k
    src.origin = _resolve_origin(p, origin, src.file_origin)
    return src


def iter_point_chunks(path, chunk_points: int = DEFAULT_CHUNK_POINTS, origin=None) -> Iterator[np.ndarray]:
    """Iterate over float64 ``(k, 3)`` chunks of a point-cloud file (see :func:`open_point_chunks`)."""
    return iter(open_point_chunks(path, chunk_points, origin))


def scan_bounds(chunks: PointChunks, transform: Callable | None = None, progress: Callable | None = None):
    """Pass 1 of a chunked computation: point count and exact bounds.

    Parameters
    ----------
    chunks : PointChunks
    transform : callable, optional
        ``(k, 3) -> (k, 3)`` applied to each chunk first (e.g. CRS -> map frame).
    progress : callable, optional
        ``progress(bytes_read, size_bytes)`` after each chunk.

    Returns
    -------
    (n, lo (3,), hi (3,))
        ``lo``/``hi`` equal ``min``/``max`` of the whole (transformed) cloud exactly.

    Raises
    ------
    TooFewPointsError
        The file holds no point.
    """
    from minegeo.errors import TooFewPointsError

    n = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for c in chunks:
        q = c if transform is None else transform(c)
        if q.shape[0]:
            lo = np.minimum(lo, q.min(axis=0))
            hi = np.maximum(hi, q.max(axis=0))
        n += q.shape[0]
        if progress is not None:
            progress(chunks.bytes_read, chunks.size_bytes)
    if n == 0:
        raise TooFewPointsError(f"{chunks.path} holds no points")
    return n, lo, hi


def _resolve_origin(p, origin, file_origin) -> np.ndarray:
    if origin is None:
        return np.zeros(3)
    if isinstance(origin, str):
        if origin == "file":
            return np.array(file_origin, dtype=np.float64)
        raise InputError(f"chunked reading takes origin None, 'file' or 3 numbers, got {origin!r}")
    o = np.asarray(origin, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.isfinite(o).all() or np.abs(o).max() > MAX_ABS_COORDINATE:
        raise InputError(f"origin must be 3 finite numbers within +-{MAX_ABS_COORDINATE:.0e} (m), got {origin!r}")
    return o


def _make(p, fmt, enc, n, file_origin, crs, size, chunked, values, meta=None) -> PointChunks:
    return PointChunks(path=p, format=fmt, encoding=enc, n_points=n, file_origin=np.asarray(file_origin, dtype=np.float64),
                       crs=crs, size_bytes=size, chunked=chunked, chunk_points=DEFAULT_CHUNK_POINTS,
                       origin=np.zeros(3), metadata=dict(meta or {}), _values=values)


# ----------------------------------------------------------------------------- whole-read fallback
def _open_whole(p: Path, size: int, fmt: str, why: str = "") -> PointChunks:
    held: list = []  # the cloud, read once and kept for the next pass (it is whole anyway)

    def values(src: PointChunks):
        from minegeo.io import read_point_cloud

        if not held:
            log.info("%s: no chunked reader for %s%s: the file is read whole (memory ~ the whole cloud)", p, fmt, why)
            held.append(read_point_cloud(p, origin="file").points)  # values relative to the recorded origin
        P = held[0]
        for i in range(0, P.shape[0], src.chunk_points):
            yield P[i : i + src.chunk_points], size
    # the header is parsed on reading; origin/crs are those read_point_cloud finds
    from minegeo.io import read_point_cloud

    if fmt in ("ply", "pcd"):  # header only (cheap) to know the recorded origin and CRS
        info = _text_header_info(p, size, fmt)
    else:
        c = read_point_cloud(p, origin="file")
        info = (len(c), np.asarray(c.metadata.get("recorded_origin", np.zeros(3)), dtype=np.float64), c.crs,
                c.metadata.get("encoding"))
        held.append(c.points)
    n, fo, crs, enc = info
    return _make(p, fmt, enc, n, fo, crs, size, False, values, {"read_whole": True})


def _text_header_info(p, size, fmt):
    from minegeo.io._common import minegeo_comments, recorded_origin

    head = _head(p, size)
    if fmt == "ply":
        from minegeo.io.ply import _parse_header

        enc, elements, comments, _, _ = _parse_header(p, head)
        n = next((e["count"] for e in elements if e["name"] == "vertex"), None)
        marker = "comment"
    else:
        from minegeo.io.pcd import _field_layout, _parse_header

        hdr, comments, _, _ = _parse_header(p, head)
        _, _, _, _, _, n, enc = _field_layout(p, hdr)
        marker = "#"
    mg = minegeo_comments(comments)
    return n, recorded_origin(p, mg, marker), mg.get("crs"), enc


# ----------------------------------------------------------------------------- binary records
def _binary_values(p: Path, offset: int, dt: np.dtype, names: tuple, n: int):
    """Reader of ``n`` packed records of ``dt`` from byte ``offset``: x, y, z fields -> float64."""

    def values(src: PointChunks):
        with open(p, "rb") as fh:
            fh.seek(offset)
            left = n
            while left > 0:
                k = min(src.chunk_points, left)
                arr = np.fromfile(fh, dtype=dt, count=k)
                if arr.shape[0] != k:
                    raise FileFormatError(p, f"file truncated: {n - left + arr.shape[0]} of {n} points present")
                out = np.empty((k, 3), dtype=np.float64)
                for j, nm in enumerate(names):
                    out[:, j] = arr[nm]
                left -= k
                yield out, fh.tell()

    return values


def _check_binary_size(p, size: int, offset: int, dt: np.dtype, n: int, last: bool, what: str) -> None:
    need = n * dt.itemsize
    have = size - offset
    if have < need:
        raise FileFormatError(p, f"file truncated: header declares {n} {what} ({need} bytes) but only {max(have, 0)} bytes follow")
    if last and have > need:
        with open(p, "rb") as fh:
            fh.seek(offset + need)
            while block := fh.read(1 << 20):
                if block.strip(b" \t\r\n\0"):
                    raise FileFormatError(p, f"{have - need} bytes after the last point: header point count ({n}) is wrong")


# ----------------------------------------------------------------------------- text blocks
def _text_values(p: Path, body: int, first_line: int, ncols: int, n: int, tail_ok: bool, comments, convert):
    """Reader of ``n`` rows of ``ncols`` numbers from byte ``body``, in blocks of whole lines.

    ``convert(table) -> (k, 3) float64`` applies the whole-file reader's per-column dtype
    round trip. With ``tail_ok`` lines after the ``n``-th row are ignored (other elements),
    otherwise they are an error (header count too small), as in the whole-file readers."""
    from minegeo.io.text import parse_table

    def values(src: PointChunks):
        block = max(1 << 16, src.chunk_points * _TEXT_BYTES_PER_POINT)
        done = 0
        line = first_line
        carry = b""
        with open(p, "rb") as fh:
            fh.seek(body)
            while True:
                data = fh.read(block)
                eof = not data
                buf = carry + data
                if not eof:
                    cut = buf.rfind(b"\n") + 1
                    if cut == 0:
                        carry = buf
                        continue
                    buf, carry = buf[:cut], buf[cut:]
                else:
                    carry = b""
                if buf.strip():
                    text = buf.decode("latin-1")
                    left = n - done
                    table = parse_table(p, text, ncols=ncols, first_line=line, max_rows=left + (0 if tail_ok else 1),
                                        comments=comments)
                    if table.shape[0] > left:
                        raise FileFormatError(p, f"header declares {n} points but more data lines follow (header count too small?)")
                    for i in range(0, table.shape[0], src.chunk_points):
                        yield convert(table[i : i + src.chunk_points]), fh.tell()
                    done += table.shape[0]
                    line += buf.count(b"\n")
                    if done == n and tail_ok:
                        return
                if eof:
                    if done != n:
                        raise FileFormatError(p, f"header declares {n} points but {done} data lines were found (file truncated?)")
                    return

    return values


# ----------------------------------------------------------------------------- PLY
def _open_ply(p: Path, size: int) -> PointChunks | None:
    from minegeo.io._common import minegeo_comments, recorded_origin
    from minegeo.io.ply import _binary_vertices, _parse_header, _vertex_element

    fmt, elements, comments, body, header_lines = _parse_header(p, _head(p, size))
    vi, vert, pnames, (ix, iy, iz), n = _vertex_element(p, elements)
    mg = minegeo_comments(comments)
    fo, crs = recorded_origin(p, mg, "comment"), mg.get("crs")
    last = vi == len(elements) - 1
    if fmt == "ascii":
        if vi > 0:
            return _open_whole(p, size, "ply", " (ascii PLY with elements before the vertices)")
        codes = [vert["props"][i][1] for i in (ix, iy, iz)]

        def convert(table):
            out = np.empty((table.shape[0], 3))
            for j, (col, code) in enumerate(zip((ix, iy, iz), codes, strict=True)):
                out[:, j] = table[:, col].astype(code)
            return out

        vals = _text_values(p, body, header_lines + 1, len(pnames), n, not last, None, convert)
        return _make(p, "ply", fmt, n, fo, crs, size, True, vals, {"xyz_only": len(pnames) == 3})
    offset, dt = _binary_vertices(p, fmt, elements, vi, body)
    _check_binary_size(p, size, offset, dt, n, last, "vertices")
    vals = _binary_values(p, offset, dt, (pnames[ix], pnames[iy], pnames[iz]), n)
    return _make(p, "ply", fmt, n, fo, crs, size, True, vals, {"xyz_only": len(pnames) == 3})


# ----------------------------------------------------------------------------- PCD
def _open_pcd(p: Path, size: int) -> PointChunks | None:
    from minegeo.io._common import find_xyz, minegeo_comments, recorded_origin
    from minegeo.io.pcd import _field_layout, _parse_header

    hdr, comments, body, header_lines = _parse_header(p, _head(p, size))
    uniq, codes, counts_i, _, _, n, mode = _field_layout(p, hdr)
    ix, iy, iz = find_xyz(p, uniq)
    for i in (ix, iy, iz):
        if counts_i[i] != 1:
            raise FileFormatError(p, f"PCD coordinate field {uniq[i]!r} has COUNT > 1")
    mg = minegeo_comments(comments)
    fo, crs = recorded_origin(p, mg, "#"), mg.get("crs")
    if mode == "binary_compressed":
        return _open_whole(p, size, "pcd", " (binary_compressed PCD is one LZF stream)")
    if mode == "ascii":
        cols = [int(sum(counts_i[:i])) for i in (ix, iy, iz)]
        xcodes = [codes[i] for i in (ix, iy, iz)]

        def convert(table):
            out = np.empty((table.shape[0], 3))
            for j, (col, code) in enumerate(zip(cols, xcodes, strict=True)):
                block = table[:, col]
                if code[0] != "f" and np.any(block != np.round(block)):
                    raise FileFormatError(p, f"PCD integer field {uniq[(ix, iy, iz)[j]]!r} holds non-integer values")
                out[:, j] = block.astype(code)
            return out

        vals = _text_values(p, body, header_lines + 1, int(sum(counts_i)), n, False, "#", convert)
        return _make(p, "pcd", mode, n, fo, crs, size, True, vals, {"xyz_only": len(uniq) == 3})
    dt = np.dtype([(nm, "<" + code, (c,)) if c > 1 else (nm, "<" + code) for nm, code, c in zip(uniq, codes, counts_i, strict=True)])
    _check_binary_size(p, size, body, dt, n, True, "points")
    vals = _binary_values(p, body, dt, (uniq[ix], uniq[iy], uniq[iz]), n)
    return _make(p, "pcd", mode, n, fo, crs, size, True, vals, {"xyz_only": len(uniq) == 3})


# ----------------------------------------------------------------------------- LAS / LAZ
def _open_las(p: Path, size: int) -> PointChunks:
    import mmap

    from minegeo.io.las import (
        _check_laszip_vlr,
        _check_laz_chunk_table,
        _check_record_counts,
        _laspy,
        crs_to_string,
    )

    laspy = _laspy()
    with open(p, "rb") as fh:
        sig = fh.read(4)
        if sig != b"LASF":
            raise FileFormatError(p, "not a LAS/LAZ file (no 'LASF' signature)")
        # the whole-file reader's checks of the record counts (a corrupt VLR count would make laspy
        # loop for hours), on a read-only map of the file: only the pages looked at are read
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            _check_record_counts(p, mm)
    try:
        with laspy.open(p) as rd:
            hdr = rd.header
    except Exception as exc:  # laspy raises several types
        raise FileFormatError(p, f"unreadable LAS header: truncated or corrupt ({type(exc).__name__}: {exc})") from None
    n, rec = int(hdr.point_count), int(hdr.point_format.size)
    if not hdr.are_points_compressed:
        need = int(hdr.offset_to_point_data) + n * rec
        if size < need:
            raise FileFormatError(p, f"file truncated: header declares {n} points ({need} bytes with the header) but the file has {size} bytes")
    else:
        _check_laszip_vlr(p, hdr, rec)
        with open(p, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            _check_laz_chunk_table(p, mm, int(hdr.offset_to_point_data), n)  # before the decoder sizes buffers
    scale = np.asarray(hdr.scales, dtype=np.float64)
    offset = np.asarray(hdr.offsets, dtype=np.float64)
    if not (np.isfinite(scale).all() and (scale != 0).all() and np.isfinite(offset).all()):
        raise FileFormatError(p, f"the header's scale {scale.tolist()} / offset {offset.tolist()} is not usable (damaged header?)")
    try:
        parsed = hdr.parse_crs()
    except Exception as exc:
        raise FileFormatError(p, f"the CRS record cannot be parsed ({exc})") from None
    crs = crs_to_string(parsed) if parsed is not None else None

    def values(src: PointChunks):
        done = 0
        try:
            with laspy.open(p) as rd:
                for pts in rd.chunk_iterator(src.chunk_points):
                    X = np.column_stack([np.asarray(pts.X), np.asarray(pts.Y), np.asarray(pts.Z)]).astype(np.float64)
                    with np.errstate(over="ignore", invalid="ignore"):
                        v = X * scale  # read_las_bytes: values = X * scale, the offset added as the origin
                    done += v.shape[0]
                    yield v, int(size * done / max(n, 1))
        except FileFormatError:
            raise
        except (KeyboardInterrupt, SystemExit, MemoryError, GeneratorExit):
            raise
        except BaseException as exc:  # laspy raises several types; lazrs panics derive from BaseException
            raise FileFormatError(p, f"unreadable LAS/LAZ: truncated or corrupt ({type(exc).__name__}: {exc})") from None

    fmt = "laz" if hdr.are_points_compressed else "las"
    return _make(p, fmt, None, n, offset, crs, size, True, values,
                 {"las_scale": scale.tolist(), "las_offset": offset.tolist()})


# ----------------------------------------------------------------------------- E57
def _open_e57(p: Path) -> PointChunks:
    """E57 maps through :func:`minegeo.io.e57.iter_e57_chunks` (the ``e57`` extra: without pye57,
    :class:`~minegeo.errors.OptionalDependencyError` names the extra to install)."""
    from minegeo.io import e57 as _e57

    _e57._pye57()  # the extra is installed, or the one-line error that says how to install it
    fn = _e57.iter_e57_chunks
    size = _regular_size(p)
    f, _, _, _ = _e57._open_scans(p, None)  # the CRS the whole-file reader finds, without reading points
    with f:
        crs = _e57._crs_of(p, f.coordinate_metadata())

    def values(src: PointChunks):
        for c in fn(p, src.chunk_points):
            a = c[0] if isinstance(c, tuple) else c
            yield np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3)), size

    return _make(p, "e57", None, None, np.zeros(3), crs, size, True, values)
