"""Shared plumbing of the point-cloud readers and writers.

Every reader returns a :class:`RawCloud`: the stored coordinate values, the file's own
coordinate offset (``global = values + file_origin``; the LAS offset, or a local origin
that minegeo recorded in a PLY/PCD/XYZ header), and named per-point fields as stored.
:func:`assemble` maps field names onto :class:`~minegeo.io.types.PointCloud` (normals,
``rgb``, attributes), rejects (or drops) non-finite points, and applies the local origin.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io.limits import MAX_ABS_COORDINATE, check_coordinate_range
from minegeo.io.types import PointCloud

log = logging.getLogger(__name__)

NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
RGB_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
#: field-name aliases applied when reading (CloudCompare prefixes scalar fields)
ALIASES = {"scalar_intensity": "intensity"}


@dataclass
class RawCloud:
    """What a format reader found, before origin handling (internal)."""

    values: np.ndarray  # (n, 3) float64 coordinate values as stored (times scale for LAS)
    fields: dict  # name -> (n,) or (n, k) arrays, as stored (x, y, z excluded)
    file_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    crs: str | None = None
    frame: str | None = None
    metadata: dict = field(default_factory=dict)
    line_of_row: object = None  # text formats: callable row -> 1-based line number (error messages)


def find_xyz(path, names: list[str]) -> tuple[int, int, int]:
    """Indices of the x, y, z columns in ``names`` (case-insensitive; ``//X`` accepted)."""
    low = [n.lower().lstrip("/") for n in names]
    try:
        return low.index("x"), low.index("y"), low.index("z")
    except ValueError:
        raise FileFormatError(path, f"no x, y, z fields in the header (fields: {' '.join(names)})") from None


def minegeo_comments(comments: list[str]) -> dict:
    """``key -> value`` of the ``minegeo <key> <value>`` header comments (PLY, PCD); the last of a key wins."""
    out = {}
    for c in comments:
        tok = c.split(None, 2)
        if len(tok) == 3 and tok[0] == "minegeo":
            out[tok[1]] = tok[2].strip()
    return out


def recorded_origin(path, mg: dict, marker: str) -> np.ndarray:
    """The local origin minegeo recorded in the header (``<marker> minegeo origin x y z``; zeros if none).

    ``mg`` is the header's ``minegeo`` comments (see :func:`minegeo_comments`); ``marker`` is
    the format's comment prefix, named in the error message.
    """
    if "origin" not in mg:
        return np.zeros(3)
    try:
        return np.array([float(t) for t in mg["origin"].split()], dtype=np.float64).reshape(3)
    except ValueError:
        raise FileFormatError(path, f"malformed '{marker} minegeo origin {mg['origin']}'") from None


def writer_values(cloud: PointCloud, coordinates: str, dtype: str) -> tuple[np.ndarray, np.ndarray]:
    """The coordinates a writer stores and the origin it records (:func:`global_values`).

    Refuses a ``dtype`` other than ``"float64"`` or ``"float32"``, and ``"float32"`` when it
    would move a point by more than 1 mm (:func:`check_float32_precision`).
    """
    if dtype not in ("float64", "float32"):
        raise InputError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
    values, rec_origin = global_values(cloud, coordinates)
    if dtype == "float32":
        check_float32_precision(values)
    return values, rec_origin


def minegeo_header_lines(cloud: PointCloud, coordinates: str, rec_origin: np.ndarray, marker: str) -> list[str]:
    """The ``<marker> minegeo crs|frame|origin`` header comments a writer records (read back by
    :func:`minegeo_comments` and :func:`recorded_origin`); the origin only for ``"local"`` coordinates."""
    lines = []
    if cloud.crs:
        lines.append(f"{marker} minegeo crs {one_line_crs(cloud.crs)}")
    lines.append(f"{marker} minegeo frame {cloud.frame}")
    if coordinates == "local" and np.any(rec_origin != 0):
        lines.append(f"{marker} minegeo origin " + " ".join(repr(float(v)) for v in rec_origin))
    return lines


def _rgb_to_uint8(path, r, g, b, meta: dict) -> np.ndarray:
    rgb = np.column_stack([np.asarray(r), np.asarray(g), np.asarray(b)])
    if rgb.size == 0:
        return rgb.astype(np.uint8)
    if np.issubdtype(rgb.dtype, np.floating):
        if not np.isfinite(rgb).all():
            raise FileFormatError(path, "colour fields contain NaN or inf")
        # float colours are conventionally 0..1 (PLY "float red"); integral floats > 1 are 0..255/65535
        if rgb.min() >= 0.0 and rgb.max() <= 1.0 and not (meta.get("dtype") == "text"):
            meta["rgb_source"] = "float 0..1 scaled to 0..255"
            return np.round(rgb * 255.0).astype(np.uint8)
        if np.any(rgb != np.round(rgb)):
            if rgb.min() >= 0.0 and rgb.max() <= 1.0:
                meta["rgb_source"] = "float 0..1 scaled to 0..255"
                return np.round(rgb * 255.0).astype(np.uint8)
            raise FileFormatError(path, "colour fields are neither integers nor in 0..1")
    lo, hi = rgb.min(), rgb.max()
    if lo < 0 or hi > 65535:
        raise FileFormatError(path, f"colour values out of range ({lo}..{hi})")
    if hi > 255:
        meta["rgb_source"] = "16-bit colour, divided by 256"
        return (rgb.astype(np.uint32) >> 8).astype(np.uint8)
    return rgb.astype(np.uint8)


def map_fields(path, fields: dict, meta: dict) -> tuple[np.ndarray | None, dict]:
    """Split stored fields into (normals, attributes) using the naming conventions above."""
    fields = {ALIASES.get(k, k): v for k, v in fields.items()}
    low = {k.lower(): k for k in fields}
    normals = None
    for trio in NORMAL_NAMES:
        if all(t in low for t in trio):
            keys = [low[t] for t in trio]
            normals = np.column_stack([np.asarray(fields.pop(k), dtype=np.float64) for k in keys])
            break
    attrs: dict = {}
    for trio in RGB_NAMES:
        if all(t in low for t in trio):
            keys = [low[t] for t in trio]
            attrs["rgb"] = _rgb_to_uint8(path, *(fields.pop(k) for k in keys), meta)
            break
    attrs.update(fields)
    return normals, attrs


def resolve_origin(path, origin, raw: RawCloud) -> np.ndarray:
    """The local origin to subtract: None -> zeros, "file" -> recorded, "auto", or a 3-vector.

    ``"auto"``: zeros if every global coordinate is within +-10 km, else the centre of the
    bounding box rounded to whole metres (so the subtraction of a whole-metre origin is
    exact in float64 for coordinates below 2^52 mm).
    """
    if origin is None:
        return np.zeros(3)
    if isinstance(origin, str):
        if origin == "file":
            return raw.file_origin.copy()
        if origin == "auto":
            v = raw.values
            if v.shape[0] == 0:
                return np.zeros(3)
            lo = v.min(axis=0) + raw.file_origin
            hi = v.max(axis=0) + raw.file_origin
            if max(np.abs(lo).max(), np.abs(hi).max()) <= 1e4:
                return np.zeros(3)
            return np.round(0.5 * (lo + hi))
        raise InputError(f"origin must be None, 'auto', 'file' or 3 numbers, got {origin!r}")
    try:
        o = np.asarray(origin, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"origin must be None, 'auto', 'file' or 3 numbers, got {origin!r}") from None
    if o.shape != (3,) or not np.isfinite(o).all() or np.abs(o).max() > MAX_ABS_COORDINATE:
        raise InputError(f"origin must be 3 finite numbers within +-{MAX_ABS_COORDINATE:.0e} (m), got {origin!r}")
    return o


def _kept_row(keep, i: int) -> int:
    """Row of the file of the ``i``-th kept point (``keep``: mask of kept rows, or None)."""
    return i if keep is None else int(np.flatnonzero(keep)[i])


def _row_label(raw: RawCloud, i: int) -> str:
    line = raw.line_of_row(i) if callable(raw.line_of_row) else None
    return f"point {i} (line {line})" if line else f"point {i}"


def assemble(
    path,
    raw: RawCloud,
    origin=None,
    drop_nonfinite: bool = False,
    scale: float | None = None,
) -> PointCloud:
    """Turn a :class:`RawCloud` into a :class:`PointCloud` (see module docstring).

    ``points = values * scale + (file_origin * scale - origin)``: the file offset and the
    requested origin are combined first so that large LAS/projected coordinates keep
    their precision (the bulk values are small when the file stores an offset).
    """
    values = raw.values
    meta = dict(raw.metadata)
    s = None
    if scale is not None:
        s = float(scale)
        if not np.isfinite(s) or s <= 0:
            raise InputError(f"scale must be a positive number, got {scale!r}")
    keep = None
    if not np.isfinite(values).all():  # one flat pass; rows only when something is bad
        finite = np.isfinite(values).all(axis=1)
        bad = np.flatnonzero(~finite)
        if not drop_nonfinite:
            raise FileFormatError(
                path,
                f"{bad.size} point(s) have NaN or inf coordinates (first: {_row_label(raw, int(bad[0]))}); "
                "pass drop_nonfinite=True to drop them",
            )
        log.warning("%s: dropped %d point(s) with NaN/inf coordinates", path, bad.size)
        meta["dropped_nonfinite"] = int(bad.size)
        keep = finite
        values = values[keep]
    # huge finite values (1e308 in a text file, a garbage float32 in binary data) would overflow
    # in every later difference or square: refuse them here, where the file can be named
    check_coordinate_range(path, values, "coordinate", lambda i: _row_label(raw, _kept_row(keep, i)))
    if not np.isfinite(raw.file_origin).all():
        raise FileFormatError(path, f"the origin recorded in the header is not finite: {raw.file_origin.tolist()}")
    check_coordinate_range(path, raw.file_origin.reshape(1, 3), "recorded origin coordinate", lambda i: "the header")
    if s is not None:
        lim = MAX_ABS_COORDINATE / s
        if s > 1.0 and values.size and max(float(values.max()), -float(values.min()), *np.abs(raw.file_origin)) > lim:
            raise InputError(f"scale {s:g} makes coordinates larger than +-{MAX_ABS_COORDINATE:.0e}; check the scale")
        values = values * s
        raw = RawCloud(values, raw.fields, raw.file_origin * s, raw.crs, raw.frame, meta, raw.line_of_row)
        units = meta.get("units")
        conv = {("cm", 0.01): "m", ("mm", 0.001): "m", ("m", 1.0): "m"}
        meta["scale_applied"] = s
        meta["units"] = conv.get((units, s), f"{units or 'file units'} x {s:g}")
    o = resolve_origin(path, origin, RawCloud(values, {}, raw.file_origin))
    shift = raw.file_origin - o
    # ``values`` is a fresh array owned by this call: no copy needed when there is no shift
    points = values + shift if np.any(shift != 0) else np.asarray(values, dtype=np.float64)
    fields = {k: (v[keep] if keep is not None else v) for k, v in raw.fields.items()}
    normals, attrs = map_fields(path, fields, meta)
    if np.any(raw.file_origin != 0):
        meta["recorded_origin"] = raw.file_origin.tolist()
    return PointCloud(
        points=points,
        normals=normals,
        attributes=attrs,
        origin=o,
        crs=raw.crs,
        frame=raw.frame or "local",
        metadata=meta,
    )


def global_values(cloud: PointCloud, coordinates: str) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates to write and the origin to record: ``("global"|"local")``."""
    if coordinates == "global":
        if np.any(cloud.origin != 0):
            return cloud.points + cloud.origin, np.zeros(3)
        return cloud.points, np.zeros(3)
    if coordinates == "local":
        return cloud.points, cloud.origin.copy()
    raise InputError(f"coordinates must be 'global' or 'local', got {coordinates!r}")


def check_float32_precision(values: np.ndarray, tol_m: float = 1e-3) -> None:
    """Refuse float32 output when rounding would move points by more than ``tol_m``."""
    if values.shape[0] == 0:
        return
    m = float(np.abs(values).max())
    # float32 has a 24-bit significand: rounding error <= m * 2^-24
    if m * 2.0**-24 > tol_m:
        raise InputError(
            f"coordinates up to {m:.0f} m cannot be stored as float32 within {tol_m * 1000:g} mm "
            f"(rounding up to {m * 2.0**-24 * 1000:.1f} mm); use dtype='float64' or "
            "coordinates='local' with a local origin"
        )


def writable_attributes(cloud: PointCloud) -> list[tuple[str, np.ndarray]]:
    """Attributes as ``(name, column)`` pairs: (n, k) arrays become ``name_0 .. name_{k-1}``.

    ``rgb`` is excluded (formats write it themselves).
    """
    out = []
    for name, v in cloud.attributes.items():
        if name == "rgb":
            continue
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise InputError(f"attribute name {name!r} cannot be written (use letters, digits, _)")
        v = np.asarray(v)
        if v.dtype == np.bool_:
            v = v.astype(np.uint8)
        if not (np.issubdtype(v.dtype, np.integer) or np.issubdtype(v.dtype, np.floating)):
            raise InputError(f"attribute {name!r} has dtype {v.dtype}; only numbers can be written")
        if v.ndim == 1:
            out.append((name, v))
        elif v.ndim == 2:
            out.extend((f"{name}_{j}", v[:, j]) for j in range(v.shape[1]))
        else:
            raise InputError(f"attribute {name!r} has {v.ndim} dimensions; at most 2 can be written")
    return out


def check_unique_names(names: list[str]) -> None:
    """Refuse to write two columns with the same (case-insensitive) name, e.g. an attribute ``nx``
    next to the normals, which would make the file ambiguous to read back."""
    seen: dict[str, str] = {}
    for nm in names:
        key = nm.lower()
        if key in seen:
            raise InputError(
                f"attribute {nm!r} clashes with the column {seen[key]!r} (coordinates, normals or colour); rename it"
            )
        seen[key] = nm


def rgb_of(cloud: PointCloud) -> np.ndarray | None:
    """The ``rgb`` attribute as (n, 3) uint8, or None."""
    rgb = cloud.attributes.get("rgb")
    if rgb is None:
        return None
    rgb = np.asarray(rgb)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise InputError(f"attribute 'rgb' must have shape (n, 3), got {rgb.shape}")
    if rgb.dtype != np.uint8:
        if rgb.size and (rgb.min() < 0 or rgb.max() > 255 or np.any(rgb != np.round(rgb))):
            raise InputError("attribute 'rgb' must hold integers 0..255 (uint8)")
        rgb = rgb.astype(np.uint8)
    return rgb


def one_line_crs(crs: str | None) -> str | None:
    """CRS text on one line (WKT may contain newlines) for header comments."""
    if crs is None:
        return None
    return " ".join(str(crs).split())
