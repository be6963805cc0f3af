"""PLY (Stanford polygon format) point clouds: ascii, binary_little_endian, binary_big_endian.

Only the ``vertex`` element is read (faces and other elements are skipped). Property
names follow the common conventions: ``x y z``, normals ``nx ny nz`` (or ``normal_x ..``),
colour ``red green blue`` (uchar) -> ``attributes["rgb"]``, ``intensity`` (CloudCompare's
``scalar_intensity`` is renamed to ``intensity``); every other scalar property becomes an
attribute with its stored dtype.

minegeo writes its CRS, frame name and (for ``coordinates="local"``) local origin as header
comments (``comment minegeo crs EPSG:5186``, ``comment minegeo origin x y z``) and reads
them back; other programs ignore comments.
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
from minegeo.io.limits import MAX_HEADER_BYTES
from minegeo.io.text import data_line_locator, format_table, note_unterminated_last_line, parse_table
from minegeo.io.types import PointCloud

__all__ = ["read_ply_bytes", "write_ply_bytes", "PLY_ENCODINGS"]

PLY_ENCODINGS = ("ascii", "binary_little_endian", "binary_big_endian")

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
          "f4": "float", "f8": "double"}  # fmt: skip


def _parse_header(path, data: bytes):
    if not data.startswith(b"ply"):
        raise FileFormatError(path, "not a PLY file (does not start with 'ply')")
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)  # a header that never ends is found quickly
    if end < 0:
        if len(data) > MAX_HEADER_BYTES:
            raise FileFormatError(
                path, f"PLY header has no 'end_header' line in its first {MAX_HEADER_BYTES} bytes (damaged or not PLY)"
            )
        raise FileFormatError(path, "PLY header has no 'end_header' line (truncated or not PLY)")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise FileFormatError(path, "PLY file ends right after 'end_header' (no data)")
    header = data[:end].decode("latin-1").splitlines()
    body_start = nl + 1
    fmt = None
    elements: list[dict] = []
    comments: list[str] = []
    for lineno, line in enumerate(header, start=1):
        tok = line.split()
        if not tok or tok[0] == "ply":
            continue
        key = tok[0]
        if key == "format":
            if len(tok) < 2 or tok[1] not in PLY_ENCODINGS:
                raise FileFormatError(path, f"line {lineno}: unknown PLY format {line.strip()!r}")
            fmt = tok[1]
        elif key in ("comment", "obj_info"):
            comments.append(line.split(None, 1)[1] if len(tok) > 1 else "")
        elif key == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise FileFormatError(path, f"line {lineno}: malformed element line {line.strip()!r}")
            elements.append({"name": tok[1], "count": int(tok[2]), "props": [], "has_list": False})
        elif key == "property":
            if not elements:
                raise FileFormatError(path, f"line {lineno}: property before any element")
            if len(tok) >= 2 and tok[1] == "list":
                if len(tok) != 5 or tok[2] not in _TYPES or tok[3] not in _TYPES:
                    raise FileFormatError(path, f"line {lineno}: malformed list property {line.strip()!r}")
                elements[-1]["has_list"] = True
                elements[-1]["props"].append((tok[4], None, (_TYPES[tok[2]], _TYPES[tok[3]])))
            else:
                if len(tok) != 3 or tok[1] not in _TYPES:
                    raise FileFormatError(path, f"line {lineno}: unknown property type in {line.strip()!r}")
                elements[-1]["props"].append((tok[2], _TYPES[tok[1]], None))
        else:
            raise FileFormatError(path, f"line {lineno}: unknown PLY header keyword {key!r}")
    if fmt is None:
        raise FileFormatError(path, "PLY header has no 'format' line")
    return fmt, elements, comments, body_start, len(header) + 1


def _vertex_element(path, elements: list) -> tuple:
    """The point cloud of a parsed PLY header (:func:`_parse_header`'s ``elements``):
    ``(index of the vertex element, the element, its property names, the columns of x, y, z,
    the vertex count)``; :class:`FileFormatError` when there is no vertex element, it has a list
    property, a property name repeats, or x, y, z are missing."""
    names = [e["name"] for e in elements]
    if "vertex" not in names:
        raise FileFormatError(path, "PLY header has no 'vertex' element")
    vi = names.index("vertex")
    vert = elements[vi]
    if vert["has_list"]:
        raise FileFormatError(path, "PLY vertex element has a list property (not a point cloud)")
    pnames = [p[0] for p in vert["props"]]
    if len(set(pnames)) != len(pnames):
        raise FileFormatError(path, f"PLY vertex element repeats a property name: {' '.join(pnames)}")
    return vi, vert, pnames, find_xyz(path, pnames), vert["count"]


def _binary_vertices(path, fmt: str, elements: list, vi: int, body_start: int) -> tuple:
    """``(byte offset of the first vertex, the vertex record dtype)`` of a binary PLY body starting
    at ``body_start``: the fixed-size elements before the vertex element ``vi`` skipped;
    :class:`FileFormatError` when one of them has a list property (its size is not known)."""
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    for e in elements[:vi]:
        if e["has_list"]:
            raise FileFormatError(path, f"binary PLY with list element {e['name']!r} before the vertices")
        offset += e["count"] * sum(np.dtype(p[1]).itemsize for p in e["props"])
    return offset, np.dtype([(p[0], endian + p[1]) for p in elements[vi]["props"]])


def read_ply_bytes(path, data: bytes) -> RawCloud:
    """Parse PLY bytes (``path`` only names the file in errors); see the module docstring."""
    fmt, elements, comments, body_start, header_lines = _parse_header(path, data)
    vi, vert, pnames, (ix, iy, iz), n = _vertex_element(path, elements)
    meta = {"format": "ply", "encoding": fmt}
    if fmt == "ascii":
        text_lines = sum(e["count"] for e in elements[:vi])
        text = data[body_start:].decode("latin-1")
        if text_lines:
            lines = text.split("\n", text_lines)
            text = lines[-1] if len(lines) > text_lines else ""
        tail_elements = vi < len(elements) - 1
        table = parse_table(
            path,
            text,
            ncols=len(pnames),
            first_line=header_lines + 1 + text_lines,
            expected_rows=None if tail_elements else n,
            max_rows=n if tail_elements else None,
            comments=None,
        )
        if table.shape[0] != n:
            raise FileFormatError(
                path, f"header declares {n} vertices but {table.shape[0]} data lines were found (file truncated?)"
            )
        cols = {p[0]: table[:, j].astype(p[1]) for j, p in enumerate(vert["props"])}
        line_of_row = data_line_locator(text, header_lines + 1 + text_lines, comments=None)
        if not tail_elements:
            note_unterminated_last_line(path, data, meta)
    else:
        offset, dt = _binary_vertices(path, fmt, elements, vi, body_start)
        need = n * dt.itemsize
        have = len(data) - offset
        if have < need:
            raise FileFormatError(
                path,
                f"file truncated: header declares {n} vertices ({need} bytes) but only {max(have, 0)} bytes follow",
            )
        if vi == len(elements) - 1 and have > need:
            extra = data[offset + need :]
            if extra.strip(b" \t\r\n\0"):
                raise FileFormatError(
                    path, f"{have - need} bytes after the last vertex: header vertex count ({n}) is wrong"
                )
        arr = np.frombuffer(data, dtype=dt, count=n, offset=offset)
        xyz_set = {pnames[ix], pnames[iy], pnames[iz]}
        # x, y, z stay views into the buffer (converted once below); other fields to native order
        cols = {
            p[0]: arr[p[0]] if p[0] in xyz_set else arr[p[0]].astype(np.dtype(p[1]).newbyteorder("="))
            for p in vert["props"]
        }
        line_of_row = None
    values = np.empty((n, 3), dtype=np.float64)
    for j, k in enumerate((pnames[ix], pnames[iy], pnames[iz])):
        values[:, j] = cols.pop(k)
    mg = minegeo_comments(comments)
    file_origin = recorded_origin(path, mg, "comment")
    meta["dtype"] = str(np.result_type(*(np.dtype(vert["props"][i][1]) for i in (ix, iy, iz))))
    if len(elements) > 1:
        meta["skipped_elements"] = [f"{e['name']}({e['count']})" for e in elements if e is not vert]
    return RawCloud(
        values=values,
        fields=cols,
        file_origin=file_origin,
        crs=mg.get("crs"),
        frame=mg.get("frame"),
        metadata=meta,
        line_of_row=line_of_row,
    )


def write_ply_bytes(
    cloud: PointCloud,
    encoding: str = "binary_little_endian",
    dtype: str = "float64",
    coordinates: str = "global",
) -> bytes:
    """Serialise ``cloud`` as PLY.

    Parameters
    ----------
    encoding : {"ascii", "binary_little_endian", "binary_big_endian"}
    dtype : {"float64", "float32"}
        Coordinate (and normal) type. float32 is refused when it would move points by more
        than 1 mm (large projected coordinates): write ``coordinates="local"`` instead.
    coordinates : {"global", "local"}
        ``"global"`` writes ``points + origin``; ``"local"`` writes ``points`` and records
        ``origin`` in a header comment that :func:`read_ply_bytes` restores.
    """
    if encoding not in PLY_ENCODINGS:
        raise InputError(f"PLY encoding must be one of {PLY_ENCODINGS}, got {encoding!r}")
    values, rec_origin = writer_values(cloud, coordinates, dtype)
    ftype = "f8" if dtype == "float64" else "f4"
    cols: list[tuple[str, str, np.ndarray]] = [
        ("x", ftype, values[:, 0]),
        ("y", ftype, values[:, 1]),
        ("z", ftype, values[:, 2]),
    ]
    if cloud.normals is not None:
        cols += [(nm, ftype, cloud.normals[:, j]) for j, nm in enumerate(("nx", "ny", "nz"))]
    rgb = rgb_of(cloud)
    if rgb is not None:
        cols += [(nm, "u1", rgb[:, j]) for j, nm in enumerate(("red", "green", "blue"))]
    for name, v in writable_attributes(cloud):
        code = v.dtype.newbyteorder("=").str[1:]
        if code not in _NAMES:
            if np.issubdtype(v.dtype, np.integer):
                if v.size and (v.min() < -(2**31) or v.max() > 2**32 - 1):
                    raise InputError(f"attribute {name!r} has integers beyond 32 bits; PLY cannot store them")
                code = "i4" if (v.size == 0 or v.min() < 0) else "u4"
            else:
                code = "f8"
        cols.append((name, code, v))
    check_unique_names([nm for nm, _, _ in cols])
    header = ["ply", f"format {encoding} 1.0", f"comment minegeo {__version__}"]
    header += minegeo_header_lines(cloud, coordinates, rec_origin, "comment")
    header.append(f"element vertex {len(cloud)}")
    header += [f"property {_NAMES[c]} {nm}" for nm, c, _ in cols]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    if encoding == "ascii":
        fmts = ["%.17g" if c == "f8" else "%.9g" if c == "f4" else "%d" for _, c, _ in cols]
        return head + format_table([v for _, _, v in cols], fmts).encode("ascii")
    endian = "<" if encoding == "binary_little_endian" else ">"
    dt = np.dtype([(nm, endian + c) for nm, c, _ in cols])
    arr = np.empty(len(cloud), dtype=dt)
    for nm, _, v in cols:
        arr[nm] = v
    return head + arr.tobytes()
