"""Point-cloud file entry points: :func:`read_point_cloud`, :func:`write_point_cloud`, :func:`cloud_info`.

Formats (chosen from the file suffix unless ``format`` is given):

=========  =========================  ==========================================
format     suffixes                   module
=========  =========================  ==========================================
ply        .ply                       :mod:`minegeo.io.ply`
pcd        .pcd                       :mod:`minegeo.io.pcd`
las / laz  .las / .laz                :mod:`minegeo.io.las` (optional laspy)
xyz        .xyz .txt                  :mod:`minegeo.io.xyz`
csv        .csv                       :mod:`minegeo.io.xyz`
pts        .pts                       :mod:`minegeo.io.xyz` (Leica PTS)
3d         .3d                        :mod:`minegeo.io.xyz` (3DTK scans, centimetres)
e57        .e57                       :mod:`minegeo.io.e57` (optional pye57; scans merged by their poses)
=========  =========================  ==========================================

A ``.zip`` holding exactly one point-cloud file (e.g. ``scan.pcd.zip``) is read directly.
Files are read whole into memory and parsed with vectorised NumPy (structured dtypes for
binary data, NumPy's C tokenizer for text): no Python loop runs over points. Every read is
bounded (:mod:`minegeo.io.limits`): only regular files, whose size is known before
allocating; header point counts checked against the bytes present; zip members checked
against their declared size and compression ratio before inflating.
"""

from __future__ import annotations

import logging
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes, sha256_file
from minegeo.errors import FileFormatError, InputError
from minegeo.io._common import assemble
from minegeo.io.limits import _ZIP_RATIO_FREE_BYTES, MAX_ZIP_MEMBER_BYTES, MAX_ZIP_RATIO, read_file_bytes
from minegeo.io.types import PointCloud

log = logging.getLogger(__name__)

__all__ = ["read_point_cloud", "read_points", "write_point_cloud", "cloud_info", "detect_format", "POINT_CLOUD_FORMATS"]

_SUFFIX = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".las": "las",
    ".laz": "laz",
    ".xyz": "xyz",
    ".txt": "xyz",
    ".csv": "csv",
    ".pts": "pts",
    ".3d": "3d",
    ".e57": "e57",
    ".zip": "zip",
}
POINT_CLOUD_FORMATS = ("ply", "pcd", "las", "laz", "xyz", "csv", "pts", "3d", "e57")


def detect_format(path, format: str | None = None) -> str:
    """Format name from ``format`` or the file suffix; raise :class:`FileFormatError` if unknown."""
    if format is not None:
        f = str(format).lower().lstrip(".")
        f = {"txt": "xyz"}.get(f, f)
        if f not in POINT_CLOUD_FORMATS and f != "zip":
            raise InputError(f"unknown point-cloud format {format!r}; choose one of {', '.join(POINT_CLOUD_FORMATS)}")
        return f
    suffix = Path(str(path)).suffix.lower()
    if suffix not in _SUFFIX:
        raise FileFormatError(
            path,
            f"unknown point-cloud file extension {suffix or '(none)'!r}; known: "
            f"{' '.join(sorted(_SUFFIX))} (or pass format=...)",
        )
    return _SUFFIX[suffix]


def _read_raw(name: str, data: bytes, fmt: str, columns=None):
    if fmt == "ply":
        from minegeo.io.ply import read_ply_bytes

        return read_ply_bytes(name, data)
    if fmt == "pcd":
        from minegeo.io.pcd import read_pcd_bytes

        return read_pcd_bytes(name, data)
    if fmt in ("las", "laz"):
        from minegeo.io.las import read_las_bytes

        return read_las_bytes(name, data)
    if fmt == "e57":  # libE57 reads from a path: an E57 inside a zip goes through a temporary file
        import tempfile

        from minegeo.io.e57 import read_e57_raw

        with tempfile.TemporaryDirectory(prefix="minegeo-e57-") as td:
            tmp = Path(td) / "member.e57"
            tmp.write_bytes(data)
            try:
                return read_e57_raw(tmp)
            except FileFormatError as exc:
                raise FileFormatError(name, exc.problem) from None
    from minegeo.io.xyz import read_text_bytes

    return read_text_bytes(name, data, fmt, columns=columns)


def _unzip(path: Path, data: bytes) -> tuple[str, bytes, str]:
    import io

    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError) as exc:
        raise FileFormatError(path, f"not a readable zip archive ({exc})") from None
    members = [
        m
        for m in zf.infolist()
        if not m.is_dir() and not m.filename.startswith("__MACOSX/") and Path(m.filename).suffix.lower() in _SUFFIX
    ]
    members = [m for m in members if _SUFFIX[Path(m.filename).suffix.lower()] != "zip"]
    if len(members) != 1:
        names = ", ".join(m.filename for m in zf.infolist()) or "(nothing)"
        raise FileFormatError(path, f"zip must hold exactly one point-cloud file, it holds: {names}")
    m = members[0]
    # the declared size bounds what zipfile will inflate: check it before inflating (zip bombs)
    if m.file_size > MAX_ZIP_MEMBER_BYTES:
        raise FileFormatError(
            path, f"zip member {m.filename!r} declares {m.file_size} bytes uncompressed, more than the "
            f"{MAX_ZIP_MEMBER_BYTES} allowed (unzip it and read the file itself)"
        )
    if m.file_size > _ZIP_RATIO_FREE_BYTES and m.file_size > MAX_ZIP_RATIO * max(m.compress_size, 1):
        raise FileFormatError(
            path, f"zip member {m.filename!r} would inflate {m.compress_size} bytes to {m.file_size} "
            f"(ratio above {MAX_ZIP_RATIO}): not a point cloud (zip bomb?)"
        )
    try:
        inner = zf.read(m)
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, NotImplementedError, RuntimeError) as exc:
        raise FileFormatError(path, f"zip member {m.filename!r} is damaged or unsupported ({exc})") from None
    if len(inner) != m.file_size:
        raise FileFormatError(path, f"zip member {m.filename!r} is damaged ({len(inner)} bytes, {m.file_size} declared)")
    return f"{path}!{m.filename}", inner, _SUFFIX[Path(m.filename).suffix.lower()]


def read_point_cloud(
    path,
    format: str | None = None,
    origin=None,
    *,
    drop_nonfinite: bool = False,
    scale: float | None = None,
    columns=None,
) -> PointCloud:
    """Read a point cloud file into a float64 :class:`~minegeo.io.types.PointCloud`.

    Parameters
    ----------
    path : str or Path
        The file (opened read-only, never modified). A ``.zip`` with one point-cloud file
        inside is read directly.
    format : str, optional
        ``ply pcd las laz xyz csv pts 3d e57`` (default: from the suffix).
    origin : None, "auto", "file" or (3,) array_like, optional
        Local origin (m) to subtract so that large projected coordinates keep their
        precision: ``points = global - origin`` and ``cloud.origin = origin``.
        ``None``: no subtraction (origin 0). ``"auto"``: 0 if all coordinates lie within
        +-10 km, else the bounding-box centre rounded to whole metres. ``"file"``: the
        offset stored in the file (LAS header offset, or the ``minegeo origin`` comment of a
        file written with ``coordinates="local"``). For LAS the points are computed as
        ``X * scale + (offset - origin)`` with ``X`` the stored integers.
    drop_nonfinite : bool
        Points with NaN/inf coordinates are an error by default (the message names the
        first one and its line); ``True`` drops them, logs how many, and records the
        count in ``metadata["dropped_nonfinite"]`` (organised PCD clouds mark missing
        returns with NaN).
    scale : float, optional
        Multiply coordinates by this unit factor after reading (e.g. ``0.01`` for 3DTK
        scans in centimetres -> metres); ``metadata["units"]`` is updated. Applied before
        ``origin`` is subtracted, so ``origin`` is in the scaled unit.
    columns : list of str, optional
        Column names for text formats without a header (e.g. ``["x","y","z","intensity"]``).

    Returns
    -------
    PointCloud
        ``points`` float64 (n, 3) relative to ``origin``; ``normals``; ``attributes``
        (``rgb`` (n, 3) uint8, ``intensity`` and other fields with their stored dtypes);
        ``crs``; ``metadata`` (``format``, ``encoding``, ``source``, ``units``, LAS
        ``las_scale``/``las_offset``...).

    Raises
    ------
    FileFormatError
        Unknown extension, wrong or unknown header, truncated data, point count that differs
        from the header, non-numeric values, NaN coordinates, coordinates beyond
        :data:`~minegeo.io.limits.MAX_ABS_COORDINATE`, empty file; not a regular file
        (``/dev/zero``, a FIFO: refused without being opened), a header that does not end
        within :data:`~minegeo.io.limits.MAX_HEADER_BYTES`, a zip member that would inflate
        beyond :data:`~minegeo.io.limits.MAX_ZIP_RATIO` times its size, or not enough memory
        for the file; the message names the file and the problem (and the line for text data).
    OptionalDependencyError
        LAS/LAZ without laspy installed; E57 without pye57.
    FileNotFoundError
        The file does not exist.
    """
    p = Path(path)
    is_zip = p.suffix.lower() == ".zip" or (format is not None and str(format).lower() == "zip")
    fmt = "zip" if is_zip else detect_format(p, format)
    if fmt == "e57":  # libE57 reads the file itself, block by block (minegeo.io.e57)
        return _read_e57_cloud(p, origin, drop_nonfinite, scale)
    data = read_file_bytes(p, what="point-cloud file")  # regular files only: size known before allocating
    name = str(p)
    size = len(data)
    try:
        if is_zip:
            if data[:4] != b"PK\x03\x04":
                raise FileFormatError(p, "not a zip archive (bad signature)")
            name, data, fmt = _unzip(p, data)
            if format is not None and str(format).lower() != "zip":
                fmt = detect_format(name, format)
        if len(data) == 0:
            raise FileFormatError(name, "empty file")
        size = len(data)
        raw = _read_raw(name, data, fmt, columns=columns)
        del data
        cloud = assemble(name, raw, origin=origin, drop_nonfinite=drop_nonfinite, scale=scale)
    except MemoryError:
        raise FileFormatError(name, f"not enough memory to read this {size}-byte point cloud") from None
    cloud.metadata["source"] = name
    if "unterminated_last_line" in cloud.metadata:  # told only once the whole file has been read
        log.warning("%s: %s", name, cloud.metadata["warnings"][-1])
    log.debug("read %d points from %s (%s)", len(cloud), name, fmt)
    return cloud


def read_points(path, *, with_times: bool = False, format: str | None = None, drop_nonfinite: bool = False):
    """Coordinates of a point-cloud file, and on request its per-point times.

    Parameters
    ----------
    path : str or Path
        Any file :func:`read_point_cloud` reads.
    with_times : bool
        ``False`` (default): return the (n, 3) float64 coordinates only. ``True``: return a
        :class:`~minegeo.io.times.TimedPoints` with the per-point times
        (:mod:`minegeo.io.times`: PLY/PCD/text fields ``time``, ``t``, ``timestamp``,
        ``offset_time``, the first found; float = seconds after the frame time, unsigned integer =
        nanoseconds, converted; LAS/LAZ ``gps_time`` as absolute seconds).
    format, drop_nonfinite
        As for :func:`read_point_cloud` (a dropped point's time is dropped with it).

    Returns
    -------
    ndarray (n, 3) float64 or TimedPoints
        Global coordinates (the file's own offset added; no local origin subtracted), metres.

    Raises
    ------
    FileFormatError
        As :func:`read_point_cloud`; with ``with_times``, also a time field stored as a signed
        integer, or offsets outside [-0.01 s, 1 s] or NaN (the file is named).
    """
    cloud = read_point_cloud(path, format=format, drop_nonfinite=drop_nonfinite)
    xyz = cloud.points + cloud.origin if np.any(cloud.origin != 0) else cloud.points
    if not with_times:
        return xyz
    from minegeo.io.times import timed_points

    return timed_points(xyz, cloud.attributes, cloud.metadata.get("source", str(path)), cloud.metadata.get("format"))


def _read_e57_cloud(p: Path, origin, drop_nonfinite: bool, scale) -> PointCloud:
    from minegeo.io.e57 import read_e57_raw

    try:
        raw = read_e57_raw(p)
        cloud = assemble(str(p), raw, origin=origin, drop_nonfinite=drop_nonfinite, scale=scale)
    except MemoryError:
        raise FileFormatError(p, f"not enough memory to read this {p.stat().st_size}-byte E57 file") from None
    cloud.metadata["source"] = str(p)
    log.debug("read %d points from %s (e57, %d scans)", len(cloud), p, len(raw.metadata["e57_scans_read"]))
    return cloud


def write_point_cloud(
    path,
    cloud: PointCloud,
    format: str | None = None,
    binary: bool = True,
    dtype: str = "float64",
    *,
    encoding: str | None = None,
    coordinates: str = "global",
    las_scale=None,
    las_offset=None,
    header: bool = True,
) -> Path:
    """Write ``cloud`` atomically (temporary file + rename); inputs are never touched.

    Parameters
    ----------
    path : str or Path
        Output file; its suffix selects the format unless ``format`` is given.
    cloud : PointCloud
    format : str, optional
        ``ply pcd las laz xyz csv pts 3d``.
    binary : bool
        PLY: ``binary_little_endian`` (True) or ``ascii``; PCD: ``binary`` or ``ascii``.
    dtype : {"float64", "float32"}
        Coordinate/normal storage type for PLY, PCD and text. float32 is refused if it would
        move any point by more than 1 mm (write ``coordinates="local"`` instead).
    encoding : str, optional
        Overrides ``binary``: PLY ``ascii | binary_little_endian | binary_big_endian``;
        PCD ``ascii | binary | binary_compressed`` (LZF).
    coordinates : {"global", "local"}
        ``"global"`` (default) writes ``points + origin``; ``"local"`` writes ``points`` and
        records ``origin`` in the header (PLY/PCD/XYZ/CSV), restored by
        ``read_point_cloud(..., origin="file")``. LAS always stores global coordinates.
    las_scale, las_offset
        LAS/LAZ integer resolution and offset (m); default: as read, else 0.001 and a
        whole-metre offset below the data.
    header : bool
        XYZ/CSV: write the ``# minegeo`` lines and column names.

    Returns
    -------
    Path
        The written file.
    """
    if not isinstance(cloud, PointCloud):
        raise InputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
    p = Path(path)
    fmt = detect_format(p, format)
    if fmt == "zip":
        raise InputError("writing .zip archives is not supported; write the point-cloud file itself")
    if fmt == "e57":
        raise InputError("writing E57 is not supported; write PLY, LAS or PCD")
    if fmt == "ply":
        from minegeo.io.ply import write_ply_bytes

        enc = encoding or ("binary_little_endian" if binary else "ascii")
        data = write_ply_bytes(cloud, encoding=enc, dtype=dtype, coordinates=coordinates)
    elif fmt == "pcd":
        from minegeo.io.pcd import write_pcd_bytes

        enc = encoding or ("binary" if binary else "ascii")
        data = write_pcd_bytes(cloud, encoding=enc, dtype=dtype, coordinates=coordinates)
    elif fmt in ("las", "laz"):
        from minegeo.io.las import write_las_bytes

        if coordinates != "global":
            raise InputError("LAS/LAZ always store global coordinates (integer * scale + offset)")
        data = write_las_bytes(cloud, compress=(fmt == "laz"), las_scale=las_scale, las_offset=las_offset)
    else:
        from minegeo.io.xyz import write_text_bytes

        data = write_text_bytes(cloud, fmt=fmt, dtype=dtype, coordinates=coordinates, header=header)
    if p.exists() and _same_file(p, cloud.metadata.get("source")):
        raise InputError(f"refusing to overwrite the input file {p}; write to a new path")
    atomic_write_bytes(p, data)
    log.debug("wrote %d points to %s (%s)", len(cloud), p, fmt)
    return p


def _same_file(p: Path, source) -> bool:
    if not source:
        return False
    src = str(source).split("!", 1)[0]
    try:
        return os.path.samefile(p, src)
    except OSError:
        return False


def cloud_info(path, format: str | None = None) -> dict:
    """Summary of a point-cloud file for ``minegeo info`` and result JSONs.

    Returns
    -------
    dict
        ``path``, ``format``, ``encoding``, ``points``, ``bounds_min``/``bounds_max``
        (global coordinates, m or file units), ``extent``, ``attributes`` (name -> dtype
        and shape), ``normals``, ``crs``, ``recorded_origin``, ``units``, ``size_bytes``,
        ``sha256``, the reader's ``metadata`` and ``point_times``
        (:func:`minegeo.io.times.times_summary`: time field, encoding, span; None without times).
    """
    p = Path(path)
    cloud = read_point_cloud(p, format=format)
    n = len(cloud)
    g = cloud.global_points
    attrs = {"normals": {"dtype": "float64", "shape": [n, 3]}} if cloud.normals is not None else {}
    for k, v in cloud.attributes.items():
        attrs[k] = {"dtype": str(v.dtype), "shape": list(v.shape)}
        if v.size and np.issubdtype(v.dtype, np.number):
            attrs[k]["min"] = float(np.nanmin(v)) if np.isfinite(v).any() else None
            attrs[k]["max"] = float(np.nanmax(v)) if np.isfinite(v).any() else None
    meta = dict(cloud.metadata)
    info = {
        "path": str(p),
        "format": meta.get("format"),
        "encoding": meta.get("encoding"),
        "points": n,
        "bounds_min": g.min(axis=0).tolist() if n else None,
        "bounds_max": g.max(axis=0).tolist() if n else None,
        "extent": (g.max(axis=0) - g.min(axis=0)).tolist() if n else None,
        "normals": cloud.normals is not None,
        "attributes": attrs,
        "crs": cloud.crs,
        "frame": cloud.frame,
        "recorded_origin": meta.get("recorded_origin", [0.0, 0.0, 0.0]),
        "units": meta.get("units", "m (assumed)"),
        "size_bytes": p.stat().st_size,
        "sha256": sha256_file(p),
        "metadata": meta,
    }
    from minegeo.io.times import times_summary

    info["point_times"] = times_summary(cloud.attributes, meta.get("format"))
    return info
