"""Text point clouds: XYZ/TXT, CSV, Leica PTS and 3DTK ``.3d`` scans.

One point per line, numbers separated by whitespace (``,`` or ``;`` are detected; CSV
always uses ``,``). Column names come from, in this order:

1. the ``columns`` argument;
2. a header line whose tokens are all non-numeric and match the number of columns, bare
   (``x,y,z,intensity``) or as a comment (``# x y z``, CloudCompare's ``//X Y Z``);
3. the format's convention for files without a header:

   ========  ==========================================================================
   format    columns
   ========  ==========================================================================
   xyz/csv   ``x y z`` then ``col4 col5 ...`` (1-based column numbers; no guessing)
   pts       first line = point count; 3: xyz, 4: + intensity, 6: + red green blue,
             7: + intensity red green blue (Leica PTS)
   3d        3DTK: optional first line ``W x H`` (scan grid), then ``x y z [reflectance]``;
             **units are centimetres** and the frame is 3DTK's left-handed scanner frame
             (x right, y up, z forward). ``metadata["units"] = "cm"``; pass ``scale=0.01``
             to :func:`~minegeo.io.read_point_cloud` to get metres.
   ========  ==========================================================================

Normals are ``nx ny nz`` (or ``normal_x ..``), colour ``red green blue`` (0..255) ->
``attributes["rgb"]``. Text has no dtypes: other attributes are read back as float64.
minegeo writes its CRS/frame/local origin as ``# minegeo <key> <value>`` lines.

Damaged files: every data line must have as many values as the first one (a line cut
short at a separator is an error naming its line). A last line without an end-of-line,
the usual mark of a file cut short inside a number, is read, logged as a warning and
recorded in ``metadata["unterminated_last_line"]`` (its line number) and
``metadata["warnings"]``. Preamble lines longer than
:data:`~minegeo.io.limits.MAX_HEADER_LINE_BYTES` (binary data) and coordinates beyond
:data:`~minegeo.io.limits.MAX_ABS_COORDINATE` are errors.
"""

from __future__ import annotations

import logging
import re

import numpy as np

from minegeo import __version__
from minegeo.errors import FileFormatError, InputError
from minegeo.io._common import (
    RawCloud,
    check_unique_names,
    find_xyz,
    minegeo_header_lines,
    recorded_origin,
    rgb_of,
    writable_attributes,
    writer_values,
)
from minegeo.io.limits import MAX_HEADER_LINE_BYTES
from minegeo.io.text import (
    data_line_locator,
    format_table,
    is_number,
    note_unterminated_last_line,
    parse_table,
)
from minegeo.io.types import PointCloud

log = logging.getLogger(__name__)

__all__ = ["read_text_bytes", "write_text_bytes", "TEXT_FORMATS"]

TEXT_FORMATS = ("xyz", "csv", "pts", "3d")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_GRID = re.compile(r"^\s*(\d+)\s*x\s*(\d+)\s*$")
_MAX_PREAMBLE = 200


def _split(line: str, delim: str | None) -> list[str]:
    return [t.strip() for t in line.split(delim)] if delim else line.split()


def _default_names(fmt: str, k: int) -> list[str]:
    if fmt == "pts":
        table = {3: [], 4: ["intensity"], 6: ["red", "green", "blue"], 7: ["intensity", "red", "green", "blue"]}
        extra = table.get(k, [f"col{j + 1}" for j in range(3, k)])
    elif fmt == "3d":
        extra = ["reflectance"] + [f"col{j + 1}" for j in range(4, k)] if k >= 4 else []
    else:
        extra = [f"col{j + 1}" for j in range(3, k)]
    return ["x", "y", "z"] + extra


def read_text_bytes(path, data: bytes, fmt: str = "xyz", columns=None) -> RawCloud:
    """Parse a text point cloud (see the module docstring); ``fmt`` in ``TEXT_FORMATS``."""
    if fmt not in TEXT_FORMATS:
        raise InputError(f"text format must be one of {TEXT_FORMATS}, got {fmt!r}")
    text = data.decode("latin-1")
    if not text.strip():
        raise FileFormatError(path, "empty file (no points)")
    meta: dict = {"format": fmt, "encoding": "ascii"}
    if fmt == "3d":
        meta["units"] = "cm"
        meta["frame_note"] = "3DTK left-handed scanner frame: x right, y up, z forward"
    mg: dict = {}
    candidates: list[tuple[int, str, bool]] = []  # (line, text, is_comment): possible headers
    expected = None
    pos = 0
    lineno = 0
    first_data = None
    delim = "," if fmt == "csv" else None
    while lineno < _MAX_PREAMBLE and pos < len(text):
        nl = text.find("\n", pos, pos + MAX_HEADER_LINE_BYTES + 1)
        if nl < 0 and len(text) - pos > MAX_HEADER_LINE_BYTES:
            raise FileFormatError(
                path, f"line {lineno + 1} is longer than {MAX_HEADER_LINE_BYTES} bytes: not a text point cloud (binary data?)"
            )
        end = len(text) if nl < 0 else nl
        line = text[pos:end].strip()
        line_start = pos
        lineno += 1
        pos = end + 1
        if not line:
            continue
        if line.startswith("#") or line.startswith("//"):
            body = line.lstrip("#/").strip()
            tok = body.split(None, 2)
            if len(tok) == 3 and tok[0] == "minegeo":
                mg[tok[1]] = tok[2]
            elif body:
                candidates.append((lineno, body, True))
            continue
        if delim is None and fmt != "3d":
            delim = "," if "," in line else (";" if ";" in line else None)
        toks = _split(line, delim)
        if all(is_number(t) for t in toks):
            if fmt == "pts" and expected is None and len(toks) == 1 and toks[0].isdigit():
                expected = int(toks[0])
                meta["declared_points"] = expected
                continue
            first_data = (lineno, line_start, len(toks))
            break
        if fmt == "3d" and lineno == 1 and _GRID.match(line):
            meta["grid"] = line
            continue
        candidates.append((lineno, line, False))
    if first_data is None:
        if expected == 0:
            return RawCloud(np.empty((0, 3)), {}, metadata=meta)
        raise FileFormatError(path, "no numeric data lines found (empty file or unreadable header)")
    lineno, start, k = first_data
    if k < 3 and columns is None:
        raise FileFormatError(path, f"line {lineno}: {k} value(s); a point needs at least x y z")
    names = None
    if columns is not None:
        names = [str(c) for c in columns]
        if len(names) != k:
            raise InputError(f"{path}: {len(names)} column names given but the data have {k} columns")
    else:
        for cl, body, _ in reversed(candidates):
            toks = _split(body, delim) if (delim and delim in body) else body.split()
            if len(toks) == k and all(_NAME.match(t.lstrip("/")) for t in toks):
                names = [t.lstrip("/") for t in toks]
                meta["header_line"] = cl
                break
        if names is None:
            bare = [c for c in candidates if not c[2]]
            if bare:
                cl, body, _ = bare[-1]
                raise FileFormatError(
                    path, f"line {cl}: {body[:80]!r} is neither numbers nor a header of {k} column names"
                )
            names = _default_names(fmt, k)
    if len(set(n.lower() for n in names)) != len(names):
        raise FileFormatError(path, f"repeated column names: {' '.join(names)}")
    ix, iy, iz = find_xyz(path, names)
    table = parse_table(path, text[start:], ncols=k, first_line=lineno, delimiter=delim, expected_rows=expected)
    values = table[:, [ix, iy, iz]]
    fields = {nm: np.ascontiguousarray(table[:, j]) for j, nm in enumerate(names) if j not in (ix, iy, iz)}
    del table
    file_origin = recorded_origin(path, mg, "#")
    if "units" in mg:
        meta["units"] = mg["units"]
    meta["dtype"] = "text"
    meta["columns"] = names
    locate = data_line_locator(text[start:], lineno)
    note_unterminated_last_line(path, text, meta)
    return RawCloud(values, fields, file_origin, mg.get("crs"), mg.get("frame"), meta, locate)


def write_text_bytes(
    cloud: PointCloud,
    fmt: str = "xyz",
    dtype: str = "float64",
    coordinates: str = "global",
    header: bool = True,
) -> bytes:
    """Serialise ``cloud`` as text.

    Parameters
    ----------
    fmt : {"xyz", "csv", "pts", "3d"}
        ``xyz``/``csv`` keep normals, colour and all attributes (with a header line).
        ``pts`` keeps ``intensity`` and colour, ``3d`` keeps ``reflectance``; other fields
        are dropped with a logged warning (the formats have no place for them).
    dtype : {"float64", "float32"}
        ``float64`` prints 17 significant digits (exact round trip), ``float32`` 9.
    header : bool
        Write the ``# minegeo`` comment lines and the column-name line (xyz/csv only).
    """
    if fmt not in TEXT_FORMATS:
        raise InputError(f"text format must be one of {TEXT_FORMATS}, got {fmt!r}")
    values, rec_origin = writer_values(cloud, coordinates, dtype)
    ffmt = "%.17g" if dtype == "float64" else "%.9g"
    if dtype == "float32":
        values = values.astype(np.float32)
    cols: list[tuple[str, np.ndarray, str]] = [(nm, values[:, j], ffmt) for j, nm in enumerate("xyz")]
    rgb = rgb_of(cloud)
    attrs = writable_attributes(cloud)
    dropped: list[str] = []

    def afmt(v):
        # text has no dtype: print floats with 17 digits so float32 values come back exactly as float64
        return "%d" if np.issubdtype(v.dtype, np.integer) else "%.17g"

    if fmt in ("xyz", "csv"):
        if cloud.normals is not None:
            nrm = cloud.normals.astype(np.float32) if dtype == "float32" else cloud.normals
            cols += [(nm, nrm[:, j], ffmt) for j, nm in enumerate(("nx", "ny", "nz"))]
        if rgb is not None:
            cols += [(nm, rgb[:, j], "%d") for j, nm in enumerate(("red", "green", "blue"))]
        cols += [(nm, v, afmt(v)) for nm, v in attrs]
    elif fmt == "pts":
        amap = dict(attrs)
        if "intensity" in amap:
            cols.append(("intensity", amap.pop("intensity"), afmt(cloud.attributes["intensity"])))
        if rgb is not None:
            cols += [(nm, rgb[:, j], "%d") for j, nm in enumerate(("red", "green", "blue"))]
            if "intensity" not in [c[0] for c in cols]:
                cols.insert(3, ("intensity", np.zeros(len(cloud), dtype=np.int32), "%d"))
                log.warning("PTS with colour needs an intensity column: writing 0")
        dropped = list(amap) + (["normals"] if cloud.normals is not None else [])
    else:  # 3d
        amap = dict(attrs)
        if "reflectance" in amap:
            v = amap.pop("reflectance")
            cols.append(("reflectance", v, afmt(v)))
        dropped = list(amap) + (["rgb"] if rgb is not None else []) + (["normals"] if cloud.normals is not None else [])
    if dropped:
        log.warning("%s format cannot store %s: not written", fmt, ", ".join(dropped))
    check_unique_names([c[0] for c in cols])
    delim = "," if fmt == "csv" else " "
    lines: list[str] = []
    if fmt == "pts":
        lines.append(str(len(cloud)))
    elif header:
        lines.append(f"# minegeo {__version__}")
        lines += minegeo_header_lines(cloud, coordinates, rec_origin, "#")
        if cloud.metadata.get("units") and fmt != "3d":
            lines.append(f"# minegeo units {cloud.metadata['units']}")
        if fmt == "csv":
            lines.append(",".join(c[0] for c in cols))
        elif fmt == "xyz":
            lines.append("# " + " ".join(c[0] for c in cols))
    head = "".join(line + "\n" for line in lines)
    body = format_table([c[1] for c in cols], [c[2] for c in cols], delimiter=delim)
    return (head + body).encode("ascii")
