"""PCD (Point Cloud Library) point clouds: ``DATA ascii``, ``binary`` and ``binary_compressed``.

Header keys: ``VERSION FIELDS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA``
(``COUNT`` defaults to 1, ``POINTS`` to ``WIDTH*HEIGHT``; lines starting with ``#`` are
comments). Data layouts (PCL ``pcd_io.cpp``):

* ``ascii``: one point per line, fields in order, ``COUNT`` values per field.
* ``binary``: packed little-endian records (array of structures), no padding.
* ``binary_compressed``: ``uint32 compressed_size, uint32 uncompressed_size``, then one
  LZF stream of the *structure of arrays* layout (all values of field 1, then field 2...).

Conventions: normals ``normal_x normal_y normal_z``; colour either PCL's packed ``rgb``
/``rgba`` (4 bytes ``0xAARRGGBB``, stored as float or uint) or separate ``red green blue``
fields (16-bit values, as in LAS-derived files, are divided by 256) -> ``attributes["rgb"]``;
fields with ``COUNT > 1`` (e.g. descriptors) become ``(n, COUNT)`` attributes; PCL padding
fields named ``_`` are dropped. Organized clouds (``HEIGHT > 1``) are read row by row and
the grid is recorded in ``metadata`` (``width``, ``height``).
"""

from __future__ import annotations

import numpy as np

from minegeo import __version__
from minegeo.errors import FileFormatError, InputError
from minegeo.io._common import (
    RawCloud,
    check_unique_names,
    find_xyz,
    minegeo_comments,
    minegeo_header_lines,
    recorded_origin,
    rgb_of,
    writable_attributes,
    writer_values,
)
from minegeo.io._lzf import lzf_compress, lzf_decompress
from minegeo.io.limits import MAX_COLUMNS, MAX_HEADER_BYTES
from minegeo.io.text import data_line_locator, format_table, note_unterminated_last_line, parse_table
from minegeo.io.types import PointCloud

__all__ = ["read_pcd_bytes", "write_pcd_bytes", "PCD_ENCODINGS"]

PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")
_KEYS = ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_VALID = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}
_MAX_HEADER_LINES = 64
#: largest LZF expansion: a 3-byte back reference copies at most 264 bytes (liblzf ``lzf_d.c``)
_LZF_MAX_RATIO = 88


def _np_code(t: str, s: int) -> str:
    return {"F": "f", "I": "i", "U": "u"}[t] + str(s)


def _parse_header(path, data: bytes):
    pos = 0
    hdr: dict[str, list[str]] = {}
    comments: list[str] = []
    lineno = 0
    while True:
        lineno += 1
        if lineno > _MAX_HEADER_LINES:
            raise FileFormatError(path, "PCD header has no DATA line in its first 64 lines (not a PCD file?)")
        nl = data.find(b"\n", pos, MAX_HEADER_BYTES)  # a header line that never ends is found quickly
        if nl < 0:
            if len(data) > MAX_HEADER_BYTES:
                raise FileFormatError(
                    path, f"PCD header has no DATA line in its first {MAX_HEADER_BYTES} bytes (damaged or not PCD)"
                )
            if not data[pos:].strip():
                what = "empty file" if not data.strip() else "PCD header ends before its DATA line"
                raise FileFormatError(path, f"{what} (truncated?)")
            nl = len(data)
        line = data[pos:nl].decode("latin-1").strip()
        pos = nl + 1
        if not line:
            continue
        if line.startswith("#"):
            comments.append(line[1:].strip())
            continue
        tok = line.split()
        key = tok[0].upper()
        if key not in _KEYS:
            raise FileFormatError(path, f"line {lineno}: unknown PCD header keyword {tok[0]!r} (not a PCD file?)")
        hdr["FIELDS" if key == "COLUMNS" else key] = tok[1:]
        if key == "DATA":
            return hdr, comments, min(pos, len(data)), lineno


def _int(path, hdr, key, default=None) -> int:
    if key not in hdr:
        if default is None:
            raise FileFormatError(path, f"PCD header has no {key} line")
        return default
    v = hdr[key]
    if len(v) != 1 or not v[0].isdigit():
        raise FileFormatError(path, f"PCD {key} must be one non-negative integer, got {' '.join(v)!r}")
    return int(v[0])


def _field_layout(path, hdr):
    """Field names (padding renamed ``__padJ``), numpy codes and counts, point count and DATA mode."""
    names = hdr.get("FIELDS")
    if not names:
        raise FileFormatError(path, "PCD header has no FIELDS")
    k = len(names)
    sizes = hdr.get("SIZE", [])
    types = [t.upper() for t in hdr.get("TYPE", [])]
    counts = hdr.get("COUNT", ["1"] * k)
    if not (len(sizes) == len(types) == len(counts) == k):
        raise FileFormatError(
            path,
            f"PCD header lists {k} FIELDS but {len(sizes)} SIZE, {len(types)} TYPE, {len(counts)} COUNT entries",
        )
    try:
        sizes_i = [int(s) for s in sizes]
        counts_i = [int(c) for c in counts]
    except ValueError:
        raise FileFormatError(path, "PCD SIZE/COUNT entries must be integers") from None
    for nm, t, s, c in zip(names, types, sizes_i, counts_i, strict=True):
        if (t, s) not in _VALID or c < 1:
            raise FileFormatError(path, f"PCD field {nm!r}: unsupported TYPE {t} SIZE {s} COUNT {c}")
    if sum(counts_i) > MAX_COLUMNS:
        raise FileFormatError(
            path, f"PCD COUNT entries add up to {sum(counts_i)} values per point, more than {MAX_COLUMNS} (damaged header?)"
        )
    width = _int(path, hdr, "WIDTH")
    height = _int(path, hdr, "HEIGHT", 1)
    n = _int(path, hdr, "POINTS", width * height)
    if n != width * height:
        raise FileFormatError(path, f"PCD POINTS ({n}) differs from WIDTH*HEIGHT ({width}*{height})")
    mode = (hdr.get("DATA") or [""])[0].lower()
    if mode not in PCD_ENCODINGS:
        raise FileFormatError(path, f"unknown PCD DATA type {mode!r} (expected ascii, binary or binary_compressed)")
    # unique names for padding fields
    uniq = []
    for j, nm in enumerate(names):
        uniq.append(f"__pad{j}" if nm == "_" or nm in uniq else nm)
    codes = [_np_code(t, s) for t, s in zip(types, sizes_i, strict=True)]
    return uniq, codes, counts_i, width, height, n, mode


def _read_ascii(path, data: bytes, body: int, header_lines: int, uniq, codes, counts_i, n):
    """Columns of an ascii body and the row -> line locator."""
    cols: dict[str, np.ndarray] = {}
    ncols = sum(counts_i)
    text = data[body:].decode("latin-1")
    table = parse_table(
        path,
        text,
        ncols=ncols,
        first_line=header_lines + 1,
        expected_rows=n,
        comments="#",
    )
    j = 0
    for nm, code, c in zip(uniq, codes, counts_i, strict=True):
        block = table[:, j : j + c]
        j += c
        if code[0] != "f":
            if np.any(block != np.round(block)):
                raise FileFormatError(path, f"PCD integer field {nm!r} holds non-integer values")
        elif nm.lower() in ("rgb", "rgba"):
            block = block.astype(np.float32)  # packed colour: the float's bits matter
        cols[nm] = block[:, 0].astype(code) if c == 1 else block.astype(code)
    return cols, data_line_locator(text, header_lines + 1)


def _read_binary(path, data: bytes, body: int, dt: np.dtype, uniq, xyz, n):
    """Columns of a ``binary`` (array of structures) body; x, y, z stay views into ``data``."""
    cols: dict[str, np.ndarray] = {}
    need = n * dt.itemsize
    have = len(data) - body
    if have < need:
        raise FileFormatError(
            path, f"file truncated: header declares {n} points ({need} bytes) but {have} bytes follow"
        )
    if have > need and data[body + need :].strip(b" \t\r\n\0"):
        raise FileFormatError(path, f"{have - need} bytes after the last point: header POINTS ({n}) is wrong")
    arr = np.frombuffer(data, dtype=dt, count=n, offset=body)
    for j, nm in enumerate(uniq):
        # x, y, z stay views into the buffer (converted once below)
        cols[nm] = arr[nm] if j in xyz else arr[nm].astype(arr.dtype[nm].base.newbyteorder("="))
    return cols


def _read_compressed(path, data: bytes, body: int, dt: np.dtype, uniq, codes, counts_i, n):
    """Columns of a ``binary_compressed`` body (size header, then one LZF stream of the structure of arrays)."""
    cols: dict[str, np.ndarray] = {}
    need = n * dt.itemsize
    if len(data) - body < 8:
        raise FileFormatError(path, "file truncated: binary_compressed PCD has no size header")
    csize, usize = (int(v) for v in np.frombuffer(data, dtype="<u4", count=2, offset=body))
    if usize != need:
        raise FileFormatError(
            path,
            f"binary_compressed PCD: uncompressed size {usize} bytes does not match "
            f"{n} points x {dt.itemsize} bytes (wrong POINTS or fields)",
        )
    if len(data) - body - 8 < csize:
        raise FileFormatError(
            path, f"file truncated: {csize} compressed bytes declared, {len(data) - body - 8} present"
        )
    if usize > _LZF_MAX_RATIO * csize:  # checked before allocating the output
        raise FileFormatError(
            path, f"binary_compressed PCD: {csize} compressed bytes cannot hold {usize} bytes "
            f"(LZF expands at most {_LZF_MAX_RATIO}x; wrong POINTS or damaged size header)"
        )
    try:
        raw = lzf_decompress(memoryview(data)[body + 8 : body + 8 + csize], usize) if usize else b""
    except InputError as exc:
        raise FileFormatError(path, f"binary_compressed PCD: {exc}") from None
    off = 0
    for nm, code, c in zip(uniq, codes, counts_i, strict=True):
        nbytes = n * c * int(code[1:])
        a = np.frombuffer(raw, dtype="<" + code, count=n * c, offset=off).astype(code)
        off += nbytes
        cols[nm] = a if c == 1 else a.reshape(n, c)
    return cols


def _unpack_rgb(cols: dict) -> None:
    """Replaces PCL's packed ``rgb``/``rgba`` field (4 bytes ``0xAARRGGBB``) by ``red green blue (alpha)``."""
    low = {nm.lower(): nm for nm in cols}
    for key in ("rgb", "rgba"):
        if key in low and cols[low[key]].ndim == 1 and cols[low[key]].dtype.itemsize == 4:
            packed = np.ascontiguousarray(cols.pop(low[key])).view(np.uint32)
            cols["red"] = ((packed >> 16) & 0xFF).astype(np.uint8)
            cols["green"] = ((packed >> 8) & 0xFF).astype(np.uint8)
            cols["blue"] = (packed & 0xFF).astype(np.uint8)
            if key == "rgba":
                cols["alpha"] = ((packed >> 24) & 0xFF).astype(np.uint8)
            break


def read_pcd_bytes(path, data: bytes) -> RawCloud:
    """Parse PCD bytes (``path`` only names the file in errors); see the module docstring."""
    hdr, comments, body, header_lines = _parse_header(path, data)
    uniq, codes, counts_i, width, height, n, mode = _field_layout(path, hdr)
    ix, iy, iz = find_xyz(path, uniq)
    line_of_row = None
    if mode == "ascii":
        cols, line_of_row = _read_ascii(path, data, body, header_lines, uniq, codes, counts_i, n)
    else:
        dt = np.dtype(
            [(nm, "<" + code, (c,)) if c > 1 else (nm, "<" + code) for nm, code, c in zip(uniq, codes, counts_i, strict=True)]
        )
        if mode == "binary":
            cols = _read_binary(path, data, body, dt, uniq, (ix, iy, iz), n)
        else:
            cols = _read_compressed(path, data, body, dt, uniq, codes, counts_i, n)
    for nm in [u for u in uniq if u.startswith("__pad")]:
        cols.pop(nm)
    _unpack_rgb(cols)
    values = np.empty((n, 3), dtype=np.float64)
    for j, k in enumerate((uniq[ix], uniq[iy], uniq[iz])):
        col = cols.pop(k)
        if col.ndim != 1:
            raise FileFormatError(path, f"PCD coordinate field {k!r} has COUNT > 1")
        values[:, j] = col
    meta = {
        "format": "pcd",
        "encoding": mode,
        "width": width,
        "height": height,
        "dtype": str(np.result_type(*(np.dtype(codes[i]) for i in (ix, iy, iz)))),
    }
    if mode == "ascii":
        note_unterminated_last_line(path, data, meta)
    if "VIEWPOINT" in hdr:
        meta["viewpoint"] = hdr["VIEWPOINT"]
    if "VERSION" in hdr:
        meta["version"] = " ".join(hdr["VERSION"])
    mg = minegeo_comments(comments)
    file_origin = recorded_origin(path, mg, "#")
    return RawCloud(values, cols, file_origin, mg.get("crs"), mg.get("frame"), meta, line_of_row)


def _pcd_code(v: np.ndarray) -> tuple[str, int]:
    dt = v.dtype
    if dt == np.bool_:
        return "U", 1
    kind = {"f": "F", "i": "I", "u": "U"}.get(dt.kind)
    if kind is None:
        raise InputError(f"dtype {dt} cannot be written to PCD")
    return kind, dt.itemsize


def write_pcd_bytes(
    cloud: PointCloud,
    encoding: str = "binary",
    dtype: str = "float64",
    coordinates: str = "global",
) -> bytes:
    """Serialise ``cloud`` as PCD v0.7.

    Parameters
    ----------
    encoding : {"ascii", "binary", "binary_compressed"}
    dtype : {"float64", "float32"}
        Coordinate and normal type (float32 refused if it would move points by > 1 mm).
    coordinates : {"global", "local"}
        As for PLY: ``"local"`` records the origin in a ``# minegeo origin`` header comment.

    Notes
    -----
    Colour is written as PCL's packed ``rgb`` field (``F 4`` in binary modes, ``U 4`` in
    ascii so the text is exact). 2-D attributes keep their column count (``COUNT``).
    """
    if encoding not in PCD_ENCODINGS:
        raise InputError(f"PCD encoding must be one of {PCD_ENCODINGS}, got {encoding!r}")
    n = len(cloud)
    values, rec_origin = writer_values(cloud, coordinates, dtype)
    fs = 8 if dtype == "float64" else 4
    fields: list[tuple[str, str, int, int, np.ndarray]] = [
        (nm, "F", fs, 1, values[:, j]) for j, nm in enumerate("xyz")
    ]
    if cloud.normals is not None:
        fields += [(nm, "F", fs, 1, cloud.normals[:, j]) for j, nm in enumerate(("normal_x", "normal_y", "normal_z"))]
    rgb = rgb_of(cloud)
    if rgb is not None:
        packed = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
        if encoding == "ascii":
            fields.append(("rgb", "U", 4, 1, packed))
        else:
            fields.append(("rgb", "F", 4, 1, packed.view(np.float32)))
    for name, v in cloud.attributes.items():
        if name == "rgb":
            continue
        v = np.asarray(v)
        writable_attributes(PointCloud(np.zeros((n, 3)), attributes={name: v}))  # validates name/dtype
        t, s = _pcd_code(v)
        if v.dtype == np.bool_:
            v = v.astype(np.uint8)
        if v.ndim == 1:
            fields.append((name, t, s, 1, v))
        else:
            fields.append((name, t, s, v.shape[1], v))
    check_unique_names([f[0] for f in fields])
    header = [f"# .PCD v0.7 - Point Cloud Data file format (minegeo {__version__})"]
    header += minegeo_header_lines(cloud, coordinates, rec_origin, "#")
    header += [
        "VERSION 0.7",
        "FIELDS " + " ".join(f[0] for f in fields),
        "SIZE " + " ".join(str(f[2]) for f in fields),
        "TYPE " + " ".join(f[1] for f in fields),
        "COUNT " + " ".join(str(f[3]) for f in fields),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n}",
        f"DATA {encoding}",
    ]
    head = ("\n".join(header) + "\n").encode("ascii")
    if encoding == "ascii":
        cols, fmts = [], []
        for _, t, s, c, v in fields:
            fmt = "%d" if t != "F" else ("%.17g" if s == 8 else "%.9g")
            if t in ("I", "U") and s == 8 and v.size and np.abs(v).max() > 2**53:
                raise InputError("64-bit integers above 2^53 cannot be written exactly as PCD ascii")
            if c == 1:
                cols.append(v)
                fmts.append(fmt)
            else:
                cols += [v[:, j] for j in range(c)]
                fmts += [fmt] * c
        return head + format_table(cols, fmts).encode("ascii")
    dt = np.dtype(
        [(f"f{j}", "<" + _np_code(t, s), (c,)) if c > 1 else (f"f{j}", "<" + _np_code(t, s)) for j, (_, t, s, c, _) in enumerate(fields)]
    )
    if encoding == "binary":
        arr = np.empty(n, dtype=dt)
        for j, f in enumerate(fields):
            arr[f"f{j}"] = f[4]
        return head + arr.tobytes()
    soa = b"".join(np.ascontiguousarray(np.asarray(f[4]).astype("<" + _np_code(f[1], f[2]))).tobytes() for f in fields)
    comp = lzf_compress(soa) if soa else b""
    sizes = np.array([len(comp), len(soa)], dtype="<u4").tobytes()
    return head + sizes + comp
