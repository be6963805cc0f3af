"""LAS / LAZ point clouds through the optional ``laspy`` package (``pip install 'minegeo[las]'``).

LAS stores coordinates as 32-bit integers ``X`` with a per-axis ``scale`` and ``offset``:
``x = X * scale + offset`` (ASPRS LAS 1.4 R15, Sec. 2.4, "X, Y, and Z scale factors /
offsets"). minegeo reads the integers and forms ``X * scale`` (small numbers, exact to
float64 rounding) and adds ``offset - origin`` as one float64 vector, so projected
coordinates of 10^6-10^7 m lose nothing when a local origin is subtracted.

Reading: colour ``red green blue`` -> ``attributes["rgb"]`` (16-bit values divided by 256
when any exceeds 255), every other standard dimension that is not all zero (``intensity``
uint16, ``gps_time``, ``classification``, ``return_number``...; LAS stores every standard
field, so all zeros means "not recorded"), and every extra-bytes dimension (``nx ny nz``
become normals). The CRS (WKT or GeoTIFF keys) is
read with pyproj and reported as ``"EPSG:<code>"`` when it has one, else as WKT.

Writing: LAS 1.4, point format 6 (7 with colour), a WKT CRS VLR, the scale/offset that the
cloud was read with (``metadata["las_scale"]``/``["las_offset"]``) unless given, else
scale 0.001 m and a whole-metre offset near the data. ``uint8`` colour ``c`` is stored as
``c * 257`` (so 255 -> 65535 and reading gives ``c`` back).
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from minegeo.errors import CRSError, FileFormatError, InputError, OptionalDependencyError
from minegeo.io._common import RawCloud, rgb_of, writable_attributes
from minegeo.io.types import PointCloud

log = logging.getLogger(__name__)

__all__ = ["read_las_bytes", "write_las_bytes", "rewrite_las_xyz"]

#: largest plausible LAZ compression ratio (uncompressed / compressed bytes) before a header
#: point count is treated as corrupt; real LiDAR compresses 5-15x
_MAX_LAZ_RATIO = 200


def _laspy():
    try:
        import laspy
    except ImportError:
        raise OptionalDependencyError("laspy", "las") from None
    return laspy


def crs_to_string(crs) -> str:
    """``"EPSG:<code>"`` if pyproj can identify one, else the WKT (one line)."""
    code = crs.to_epsg()
    if code is not None:
        return f"EPSG:{code}"
    auth = crs.to_authority()
    if auth is not None:
        return f"{auth[0]}:{auth[1]}"
    return crs.to_wkt()


def _check_record_counts(path, data: bytes) -> None:
    """Bound the header's VLR/EVLR counts by the file size (ASPRS LAS 1.4 R15, Table 3).

    laspy loops over the declared number of VLRs, so a corrupt count (up to 2^32) would
    hang; a VLR header is 54 bytes and must fit between the header and the point data,
    an EVLR header is 60 bytes and must fit in the file.
    """
    if len(data) < 227:
        raise FileFormatError(path, f"file truncated: {len(data)} bytes, a LAS header has at least 227")
    header_size = int.from_bytes(data[94:96], "little")
    offset_points = int.from_bytes(data[96:100], "little")
    n_vlr = int.from_bytes(data[100:104], "little")
    if header_size < 227 or header_size > offset_points or offset_points > len(data):
        raise FileFormatError(
            path,
            f"corrupt or truncated LAS header (header size {header_size}, point data at byte {offset_points}, "
            f"file {len(data)} bytes)",
        )
    if n_vlr * 54 > offset_points - header_size:
        raise FileFormatError(
            path, f"corrupt LAS header: {n_vlr} VLRs cannot fit in the {offset_points - header_size} bytes before the points"
        )
    if data[25] >= 4 and header_size >= 247:  # LAS 1.4: extended VLRs after the points
        start = int.from_bytes(data[235:243], "little")
        n_evlr = int.from_bytes(data[243:247], "little")
        if n_evlr and start + n_evlr * 60 > len(data):
            raise FileFormatError(
                path, f"corrupt or truncated LAS file: {n_evlr} extended VLRs declared at byte {start} beyond the end"
            )


def _check_laszip_vlr(path, hdr, rec: int) -> None:
    """Check the LASzip VLR (user id ``laszip encoded``, record 22204) before decoding.

    Layout (LASzip specification): ``u16 compressor, u16 coder, u8 u8 u16 version, u32 options,
    u32 chunk_size, i64, i64, u16 num_items`` then ``num_items x (u16 type, u16 size, u16
    version)``. The item sizes must add up to the point record length, and the chunk size must
    be "variable" (``0xFFFFFFFF``) or small enough that one chunk fits in memory.
    """
    vlr = next((v for v in hdr.vlrs if getattr(v, "record_id", None) == 22204), None)
    if vlr is None:
        raise FileFormatError(path, "LAZ file without its LASzip VLR (corrupt header)")
    try:
        raw = bytes(vlr.record_data_bytes())
    except Exception as exc:
        raise FileFormatError(path, f"unreadable LASzip VLR ({exc})") from None
    if len(raw) < 34:
        raise FileFormatError(path, "LASzip VLR truncated")
    chunk = int.from_bytes(raw[12:16], "little")
    n_items = int.from_bytes(raw[32:34], "little")
    if len(raw) < 34 + 6 * n_items:
        raise FileFormatError(path, f"LASzip VLR declares {n_items} items but is {len(raw)} bytes long")
    sizes = [int.from_bytes(raw[34 + 6 * i + 2 : 34 + 6 * i + 4], "little") for i in range(n_items)]
    if sum(sizes) != rec:
        raise FileFormatError(path, f"LASzip items total {sum(sizes)} bytes but a point record has {rec} (corrupt)")
    if chunk != 0xFFFFFFFF and (chunk == 0 or chunk * rec > (1 << 31)):
        raise FileFormatError(path, f"implausible LAZ chunk size {chunk} (corrupt LASzip VLR)")


def _check_laz_chunk_table(path, data: bytes, offset_points: int, n_points: int) -> None:
    """Sanity-check the LAZ chunk table before the decoder sizes its buffers from it.

    LASzip stores, at the start of the point data, an int64 pointer to the chunk table
    (``-1`` if absent); the table starts with ``uint32 version = 0, uint32 n_chunks``.
    A corrupt pointer or count would make the Rust decoder try to allocate many GB and
    abort the process, so it is rejected here as a :class:`FileFormatError`.
    """
    if offset_points + 8 > len(data):
        raise FileFormatError(path, "file truncated: LAZ point data missing")
    ptr = int.from_bytes(data[offset_points : offset_points + 8], "little", signed=True)
    if ptr == -1:
        return
    if not (offset_points + 8 <= ptr <= len(data) - 8):
        raise FileFormatError(path, f"corrupt or truncated LAZ: chunk table pointer {ptr} outside the file")
    version = int.from_bytes(data[ptr : ptr + 4], "little")
    n_chunks = int.from_bytes(data[ptr + 4 : ptr + 8], "little")
    if version != 0 or n_chunks > max(n_points, 1) or n_chunks > len(data):
        raise FileFormatError(
            path, f"corrupt LAZ chunk table (version {version}, {n_chunks} chunks for {n_points} points)"
        )


def read_las_bytes(path, data: bytes) -> RawCloud:
    """Read LAS or LAZ bytes; see the module docstring."""
    laspy = _laspy()
    if len(data) == 0:
        raise FileFormatError(path, "empty file")
    if not data.startswith(b"LASF"):
        raise FileFormatError(path, "not a LAS/LAZ file (no 'LASF' signature)")
    _check_record_counts(path, data)
    # check the declared point count against the file size before laspy allocates for it
    # (a corrupt header must not make us allocate gigabytes)
    try:
        hdr0 = laspy.LasHeader.read_from(io.BytesIO(data))
    except Exception as exc:  # laspy raises several types
        raise FileFormatError(path, f"unreadable LAS header: truncated or corrupt ({type(exc).__name__}: {exc})") from None
    n0, rec = int(hdr0.point_count), int(hdr0.point_format.size)
    if not hdr0.are_points_compressed:
        need = int(hdr0.offset_to_point_data) + n0 * rec
        if len(data) < need:
            raise FileFormatError(
                path,
                f"file truncated: header declares {n0} points ({need} bytes with the header) but the file has {len(data)} bytes",
            )
    elif n0 * rec > _MAX_LAZ_RATIO * len(data):
        raise FileFormatError(
            path, f"header declares {n0} points, impossible for a {len(data)}-byte LAZ file (corrupt header)"
        )
    else:
        _check_laszip_vlr(path, hdr0, rec)
        _check_laz_chunk_table(path, data, int(hdr0.offset_to_point_data), n0)
    try:
        las = laspy.read(io.BytesIO(data))
    except (KeyboardInterrupt, SystemExit, MemoryError):
        raise
    except BaseException as exc:  # laspy raises several types; lazrs panics derive from BaseException
        raise FileFormatError(path, f"unreadable LAS/LAZ: truncated or corrupt ({type(exc).__name__}: {exc})") from None
    hdr = las.header
    n = len(las.points)
    if hdr.point_count != n:
        raise FileFormatError(path, f"header declares {hdr.point_count} points, {n} were read (truncated?)")
    scale = np.asarray(hdr.scales, dtype=np.float64)
    offset = np.asarray(hdr.offsets, dtype=np.float64)
    if not (np.isfinite(scale).all() and (scale != 0).all() and np.isfinite(offset).all()):
        raise FileFormatError(path, f"the header's scale {scale.tolist()} / offset {offset.tolist()} is not usable "
                                    "(damaged header?)")
    X = np.column_stack([np.asarray(las.X), np.asarray(las.Y), np.asarray(las.Z)]).astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        values = X * scale
    if not np.isfinite(values).all() or (values.size and not np.isfinite(np.abs(values).max(axis=0) + np.abs(offset)).all()):
        raise FileFormatError(path, f"coordinates overflow with the header's scale {scale.tolist()} and offset "
                                    f"{offset.tolist()} (damaged header?)")
    fields: dict[str, np.ndarray] = {}
    extra = list(las.point_format.extra_dimension_names)
    for dim in las.point_format.standard_dimension_names:
        if dim in ("X", "Y", "Z"):
            continue
        arr = np.asarray(las[dim])
        # colour whenever the point format has it; other dimensions only when they carry data
        # (LAS always stores every standard field: all zeros means "not recorded")
        if dim in ("red", "green", "blue") or (arr.size and np.any(arr != 0)):
            fields[dim] = arr.copy()
    for dim in extra:
        fields[dim] = np.asarray(las[dim]).copy()
    warnings = []
    if n:
        lo = X.min(axis=0) * scale + offset
        hi = X.max(axis=0) * scale + offset
        hmin = np.asarray(hdr.mins, dtype=np.float64)
        hmax = np.asarray(hdr.maxs, dtype=np.float64)
        tol = scale + 1e-9 * np.maximum(np.abs(hmin), np.abs(hmax))
        if np.any(hmin != 0) or np.any(hmax != 0):  # all zero: bounds not filled in by the writer
            if np.any(lo < hmin - tol) or np.any(hi > hmax + tol):
                msg = (
                    f"points extend beyond the header bounding box (data {lo.tolist()}..{hi.tolist()}, "
                    f"header {hmin.tolist()}..{hmax.tolist()}): corrupt data or a stale header"
                )
                log.warning("%s: %s", path, msg)
                warnings.append(msg)
    crs = None
    try:
        parsed = hdr.parse_crs()
    except Exception as exc:  # malformed CRS VLR: report, do not guess
        raise FileFormatError(path, f"the CRS record cannot be parsed ({exc})") from None
    if parsed is not None:
        crs = crs_to_string(parsed)
    meta = {
        "format": "laz" if hdr.are_points_compressed else "las",
        "las_version": str(hdr.version),
        "las_point_format": int(hdr.point_format.id),
        "las_scale": scale.tolist(),
        "las_offset": offset.tolist(),
        "las_header_min": list(map(float, hdr.mins)),
        "las_header_max": list(map(float, hdr.maxs)),
        "dtype": "int32*scale+offset",
    }
    if warnings:
        meta["warnings"] = warnings
    return RawCloud(values=values, fields=fields, file_origin=offset, crs=crs, frame=None, metadata=meta)


def write_las_bytes(
    cloud: PointCloud,
    compress: bool = False,
    las_scale=None,
    las_offset=None,
) -> bytes:
    """Serialise ``cloud`` as LAS 1.4 (LAZ if ``compress``); see the module docstring.

    Parameters
    ----------
    las_scale : float or (3,) floats, optional
        Coordinate resolution in metres (default: the scale the cloud was read with, else 0.001).
    las_offset : (3,) floats, optional
        Integer-coordinate offset in metres (default: as read, else the whole-metre floor
        of the cloud's minimum, in global coordinates).

    Raises
    ------
    InputError
        Coordinates that do not fit 32-bit integers with this scale/offset; attributes that
        do not fit the LAS standard field they are named after (e.g. non-integer intensity).
    CRSError
        ``cloud.crs`` is not understood by pyproj.
    """
    laspy = _laspy()
    n = len(cloud)
    meta = cloud.metadata or {}
    scale = np.broadcast_to(
        np.asarray(las_scale if las_scale is not None else meta.get("las_scale", 0.001), dtype=np.float64), (3,)
    ).copy()
    if not (np.isfinite(scale).all() and (scale > 0).all()):
        raise InputError(f"las_scale must be positive, got {scale.tolist()}")
    if las_offset is not None:
        offset = np.asarray(las_offset, dtype=np.float64).reshape(3)
    elif "las_offset" in meta:
        offset = np.asarray(meta["las_offset"], dtype=np.float64).reshape(3)
    elif n:
        offset = np.floor(cloud.points.min(axis=0) + cloud.origin)
    else:
        offset = np.zeros(3)
    # X = round((p_local + (origin - offset)) / scale): combine the big numbers first
    Xf = np.round((cloud.points + (cloud.origin - offset)) / scale)
    lim = 2.0**31 - 1
    if n and (np.abs(Xf).max() > lim):
        raise InputError(
            f"coordinates do not fit LAS 32-bit integers with scale {scale.tolist()} and offset "
            f"{offset.tolist()}; choose a larger las_scale or an offset nearer the data"
        )
    rgb = rgb_of(cloud)
    fmt = 7 if rgb is not None else 6
    hdr = laspy.LasHeader(point_format=fmt, version="1.4")
    hdr.scales = scale
    hdr.offsets = offset
    las = laspy.LasData(hdr)
    las.X = Xf[:, 0].astype(np.int32)
    las.Y = Xf[:, 1].astype(np.int32)
    las.Z = Xf[:, 2].astype(np.int32)
    if rgb is not None:
        for j, nm in enumerate(("red", "green", "blue")):
            las[nm] = rgb[:, j].astype(np.uint16) * 257
    std = set(las.point_format.standard_dimension_names)
    cols = writable_attributes(cloud)
    if cloud.normals is not None:
        cols += [(nm, cloud.normals[:, j]) for j, nm in enumerate(("nx", "ny", "nz"))]
    for name, v in cols:
        if name in std:
            target = np.asarray(las[name]).dtype
            if np.issubdtype(target, np.integer):
                info = np.iinfo(target)
                ok = v.size == 0 or (
                    np.all(np.isfinite(v)) and np.all(v == np.round(v)) and v.min() >= info.min and v.max() <= info.max
                )
                if not ok:
                    raise InputError(
                        f"attribute {name!r} does not fit the LAS field {name} ({target}); "
                        "rescale it or rename the attribute to store it as an extra dimension"
                    )
            las[name] = np.asarray(v).astype(target)
        else:
            dt = np.asarray(v).dtype
            if dt.kind not in "iuf":
                raise InputError(f"attribute {name!r} of dtype {dt} cannot be written to LAS")
            las.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dt.newbyteorder("=")))
            las[name] = v
    if cloud.crs:
        try:
            import pyproj

            crs = pyproj.CRS.from_user_input(cloud.crs)
        except Exception as exc:
            raise CRSError(f"cannot write CRS {cloud.crs!r} to LAS: {exc}") from None
        las.header.add_crs(crs)
    buf = io.BytesIO()
    las.write(buf, do_compress=compress)
    return buf.getvalue()


#: LAS VLRs that carry a CRS (GeoTIFF keys 34735-34737, OGC WKT 2111/2112): replaced by :func:`rewrite_las_xyz`
_CRS_VLR_IDS = frozenset({(b"LASF_Projection", 2111), (b"LASF_Projection", 2112), (b"LASF_Projection", 34735),
                          (b"LASF_Projection", 34736), (b"LASF_Projection", 34737)})


def rewrite_las_xyz(src, dst, xyz, *, offsets, crs, chunk_points: int) -> None:
    """Copy the LAS/LAZ file ``src`` to ``dst`` record by record, with new integer coordinates.

    Every record keeps **all its fields** (intensity, return numbers, classification, GPS time,
    colour, extra bytes) in the source's point format, LAS version and ``scale``; only the integers
    ``X, Y, Z`` change (``x = X·scale + offset``, ASPRS LAS 1.4 R15 Sec. 2.4). The header offset
    becomes ``offsets``, the CRS records (GeoTIFF keys, WKT) are replaced by ``crs`` and the other
    VLRs are kept. ``dst`` is compressed (LAZ) when its suffix is ``.laz``. Memory: one chunk.

    Parameters
    ----------
    src, dst : str or Path
        The LAS/LAZ file read, and the file written (in place: pass a staged path).
    xyz : callable
        ``xyz(n, scales) -> ndarray (n, 3)``, called once per chunk of ``n`` records of ``src``
        in file order with the per-axis ``scales`` (m): the chunk's new integer coordinates as
        float64 values, rounded and within the int32 range (the caller checks the range, in the
        words of what the coordinates are).
    offsets : (3,) floats
        The LAS offset of ``dst`` (m).
    crs : str or None
        The CRS written to ``dst`` (pyproj user input, e.g. ``"EPSG:5186"``); none when empty.
    chunk_points : int
        Records per chunk.

    Raises
    ------
    FileFormatError
        ``src`` is truncated or corrupt (any error of laspy/lazrs while reading or writing).
        A :class:`~minegeo.errors.FileFormatError` or :class:`~minegeo.errors.InputError` raised
        by ``xyz`` passes through unchanged.
    OptionalDependencyError
        ``laspy`` is not installed (the ``las`` extra).
    """
    laspy = _laspy()
    src, dst = Path(src), Path(dst)
    try:
        with laspy.open(src) as rd:
            ih = rd.header
            hdr = laspy.LasHeader(point_format=ih.point_format, version=ih.version)
            hdr.scales = np.asarray(ih.scales, dtype=np.float64)
            hdr.offsets = np.array(offsets, dtype=np.float64).reshape(3)

            def _keep(v):
                uid = v.user_id.encode() if isinstance(v.user_id, str) else bytes(v.user_id)
                return (uid.rstrip(b"\0"), int(v.record_id)) not in _CRS_VLR_IDS and type(v).__name__ != "ExtraBytesVlr"

            hdr.vlrs.extend(v for v in ih.vlrs if _keep(v))
            if crs:
                import pyproj

                hdr.add_crs(pyproj.CRS.from_user_input(crs))
            with laspy.open(dst, mode="w", header=hdr, do_compress=dst.suffix.lower() == ".laz") as wr:
                for pts in rd.chunk_iterator(chunk_points):
                    Xf = xyz(len(pts), hdr.scales)
                    rec = laspy.ScaleAwarePointRecord(pts.array.copy(), pts.point_format, scales=hdr.scales,
                                                      offsets=hdr.offsets)
                    rec.X = Xf[:, 0].astype(np.int32)
                    rec.Y = Xf[:, 1].astype(np.int32)
                    rec.Z = Xf[:, 2].astype(np.int32)
                    wr.write_points(rec)
    except (FileFormatError, InputError):
        raise
    except (KeyboardInterrupt, SystemExit, MemoryError):
        raise
    except BaseException as exc:  # laspy/lazrs raise several types
        raise FileFormatError(src, f"unreadable LAS/LAZ: truncated or corrupt ({type(exc).__name__}: {exc})") from None
