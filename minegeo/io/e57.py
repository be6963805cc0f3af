"""ASTM E57 point clouds (terrestrial scanner exports) through the optional ``pye57`` package.

``pip install 'minegeo[e57]'`` installs pye57 (Python bindings of libE57Format); without it
every function here raises :class:`~minegeo.errors.OptionalDependencyError`.

An E57 file (ASTM E2807-11) holds any number of scans under ``/data3D``. Each scan stores its
points in its own frame and, optionally, a ``pose`` (a unit quaternion ``rotation`` ``w x y z``
and a ``translation``, ASTM E2807 Sec. 8.3.8 "RigidBody") that maps the scan frame into the
file's common frame::

    p_file = R(q) p_scan + t        (T_file_scan = [[R(q), t], [0, 1]])

minegeo reads every scan (or the ``scans`` asked for), transforms its points with its pose
into the file frame in float64 and concatenates them in file order: scan 0 first, each scan
in its stored record order. ``attributes["scan_index"]`` (int32) says which scan each point
came from; ``metadata["e57_scans"]`` holds each scan's name, guid, point count and
``T_file_scan``. A scan without a pose has the identity pose.

Coordinates: ``cartesianX/Y/Z`` (float or scaled-integer nodes; read as float64 after
libE57's scaling), else ``sphericalRange/Azimuth/Elevation`` converted by the E57 convention
(ASTM E2807 Sec. 8.4.11; libE57 "best coordinates")::

    x = r cos(el) cos(az),  y = r cos(el) sin(az),  z = r sin(el)

Points flagged invalid (``cartesianInvalidState`` / ``sphericalInvalidState`` != 0: direction
only, or no return) are dropped and counted in ``metadata["e57_invalid_dropped"]``.
``intensity`` (float) and ``colorRed/Green/Blue`` (as ``rgb`` uint8 when 0..255) are kept when
every scan read has them.

Large (projected) coordinates: the pose is applied in float64 (``R p + t``, spacing ~2e-9 m at
10^7 m) and no file offset is recorded (E57 has none): ``origin="auto"`` of
:func:`~minegeo.io.read_point_cloud` then subtracts a whole-metre local origin, as for every
format. pye57 itself writes ``cartesianX/Y/Z`` as **single** precision floats (E57_SINGLE),
so a file it wrote keeps the float32 values of the scan-frame coordinates; the pose is double.

Memory: :func:`iter_e57_chunks` reads each scan through libE57's compressed-vector reader in
blocks of ``chunk_points`` records (libE57 reads sub-ranges), so its peak memory is one block
(plus libE57's own page cache), not one scan. :func:`read_e57` reads the same blocks into one
preallocated array.

Damaged files: the 48-byte file header is checked in Python first (signature ``ASTM-E57``,
physical length against the file size, page size), then every libE57 failure (checksum
mismatch, bad XML, bad compressed-vector packet) becomes a :class:`FileFormatError` with the
first line of libE57's message; a file without scans, or a scan without cartesian or spherical
coordinates, is a :class:`FileFormatError` too.

Poses are checked against the text of the file's XML section as written (:func:`_xml_pose_texts`):
libE57 turns a float element it cannot parse (``<w>nan</w>``, ``<x>inf</x>``, ``<y>abc</y>``) into 0
without a word, which can make a damaged quaternion look like another rotation and a damaged
translation look like the origin. A pose element that is not a finite number, a quaternion of zero
length or far from unit length is a :class:`FileFormatError` naming the scan and the values as
written, e.g. ``scan 0 ('station 1'): pose rotation quaternion (w=nan, x=0, y=0, z=0) ...``.
"""

from __future__ import annotations

import logging
import math
import os
import stat
import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError, OptionalDependencyError
from minegeo.io._common import RawCloud, assemble
from minegeo.io.limits import file_kind
from minegeo.io.types import PointCloud

log = logging.getLogger(__name__)

__all__ = ["read_e57", "e57_scan_poses", "iter_e57_chunks", "read_e57_raw", "e57_header_check"]

_SIGNATURE = b"ASTM-E57"
_HEADER = struct.Struct("<8sIIQQQQ")  # signature, major, minor, physical length, xml offset, xml length, page size
_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_COLOUR = ("colorRed", "colorGreen", "colorBlue")
#: records read per libE57 call by :func:`read_e57` (its own buffers: 3 doubles + extras per record)
_READ_BLOCK = 1 << 20
#: largest XML section whose pose texts are checked as written (larger: libE57's values only)
_MAX_XML_BYTES = 64 << 20
#: a pose quaternion's length may differ from 1 by this much (rounding of a written unit quaternion)
_UNIT_TOLERANCE = 1e-2


def _pye57():
    try:
        import pye57
        from pye57 import libe57
    except ImportError:
        raise OptionalDependencyError("pye57", "e57") from None
    return pye57, libe57


def _libe57_problem(exc: BaseException) -> str:
    """The first line of a libE57 message (the rest is its debug dump)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def e57_header_check(path) -> dict:
    """Check the 48-byte E57 file header before libE57 opens the file (ASTM E2807 Sec. 8.2.1).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    dict
        ``version`` ("major.minor"), ``physical_length``, ``page_size``.

    Raises
    ------
    FileFormatError
        Not a regular file, empty, not an E57 file (no ``ASTM-E57`` signature), truncated (the
        header's physical length differs from the file size) or an implausible header.
    FileNotFoundError
        The file does not exist.
    """
    st = os.stat(path)  # never open() first: a FIFO would block
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(path, f"is {file_kind(st.st_mode)}, not an E57 file: minegeo reads regular files only")
    if st.st_size == 0:
        raise FileFormatError(path, "empty file")
    with open(path, "rb") as fh:
        head = fh.read(_HEADER.size)
    if head[:8] != _SIGNATURE:
        raise FileFormatError(path, "not an E57 file (no 'ASTM-E57' signature at the start)")
    if len(head) < _HEADER.size:
        raise FileFormatError(path, f"file truncated: {st.st_size} bytes, an E57 header has {_HEADER.size}")
    _, major, minor, phys, xml_off, xml_len, page = _HEADER.unpack(head)
    if phys != st.st_size:
        what = "truncated" if phys > st.st_size else "longer than its header says (appended data?)"
        raise FileFormatError(path, f"file {what}: the E57 header declares {phys} bytes, the file has {st.st_size} "
                                    "(an interrupted copy or download?)")
    if page == 0 or page > (1 << 20) or phys % page != 0 or xml_off + xml_len > phys:
        raise FileFormatError(path, f"corrupt E57 header (page size {page}, XML section at {xml_off}+{xml_len}, "
                                    f"file {phys} bytes)")
    return {"version": f"{major}.{minor}", "physical_length": int(phys), "page_size": int(page),
            "xml_offset": int(xml_off), "xml_length": int(xml_len)}


def _xml_section(path, header: dict) -> bytes | None:
    """The XML section of an E57 file (logical bytes: each page's trailing 4-byte checksum removed,
    ASTM E2807 Sec. 8.2.2), or None when it is larger than :data:`_MAX_XML_BYTES`."""
    page, off, n = header["page_size"], header["xml_offset"], header["xml_length"]
    if n > _MAX_XML_BYTES or page <= 4 or off % page >= page - 4:
        return None
    data = page - 4
    out = bytearray()
    with open(path, "rb") as fh:
        fh.seek(off - off % page)
        skip = off % page
        while len(out) < n:
            block = fh.read(page)
            if len(block) < page:
                return None
            out += block[skip:data]
            skip = 0
    return bytes(out[:n])


def _xml_pose_texts(path, header: dict) -> list[dict] | None:
    """Per scan of ``/data3D`` (file order), the text of each pose element as written in the XML:
    ``{"rotation": {"w": "nan", "x": "0", ...}, "translation": {...}}`` (an empty element is "0", the
    E57 default; a missing one is absent). None when the section cannot be read here (too large, or
    XML this parser refuses): the poses are then checked on libE57's values only."""
    try:
        raw = _xml_section(path, header)
        if raw is None:
            return None
        root = ET.fromstring(raw)
    except (OSError, ET.ParseError, ValueError) as exc:
        log.debug("%s: XML section not read for the pose check (%s)", path, exc)
        return None

    def local(el) -> str:
        return el.tag.rsplit("}", 1)[-1]

    def child(el, name):
        return next((c for c in el if local(c) == name), None) if el is not None else None

    scans = []
    for vc in child(root, "data3D") if child(root, "data3D") is not None else []:
        pose = child(vc, "pose")
        rec = {}
        for part, keys in (("rotation", "wxyz"), ("translation", "xyz")):
            node = child(pose, part)
            if node is not None:
                rec[part] = {k: ((child(node, k).text or "").strip() or "0") for k in keys if child(node, k) is not None}
        scans.append(rec)
    return scans


def _pose_values(texts: dict | None, read: np.ndarray, keys: str):
    """``(values as written, shown text)`` of one pose element group: the written texts parsed as
    floats (NaN for a text that is not a number) when known, else libE57's values."""
    if not texts or set(texts) != set(keys):
        return read, ", ".join(f"{k}={v:g}" for k, v in zip(keys, read.tolist(), strict=True))
    vals = []
    for k in keys:
        try:
            vals.append(float(texts[k]))
        except ValueError:
            vals.append(math.nan)
    shown = ", ".join(f"{k}={texts[k][:24]}" for k in keys)
    return np.array(vals, dtype=np.float64), shown


class _E57File:
    """An E57 file opened read-only by libE57, with every libE57 error turned into :class:`FileFormatError`."""

    def __init__(self, path):
        self.path = Path(path)
        self.header = e57_header_check(self.path)
        self.pye57, self.lib = _pye57()
        try:
            # libe57.ImageFile directly (not pye57.E57): it never creates or removes a file
            self.imf = self.lib.ImageFile(str(self.path), "r")
        except self.lib.E57Exception as exc:
            raise FileFormatError(self.path, f"unreadable E57 file: {_libe57_problem(exc)}") from None
        except (RuntimeError, ValueError, OSError) as exc:
            raise FileFormatError(self.path, f"unreadable E57 file ({type(exc).__name__}: {exc})") from None

    def __enter__(self) -> _E57File:
        return self

    def pose_texts(self) -> list[dict] | None:
        """:func:`_xml_pose_texts` of this file (read once)."""
        if not hasattr(self, "_pose_texts"):
            self._pose_texts = _xml_pose_texts(self.path, self.header)
        return self._pose_texts

    def __exit__(self, *exc) -> None:
        try:
            self.imf.close()
        except Exception:  # noqa: BLE001 - closing a read-only file cannot lose data
            pass

    def _fail(self, what: str, exc: BaseException):
        if isinstance(exc, self.lib.E57Exception):
            return FileFormatError(self.path, f"{what}: {_libe57_problem(exc)} (damaged E57 file?)")
        return FileFormatError(self.path, f"{what} ({type(exc).__name__}: {exc}) (damaged E57 file?)")

    def scan_headers(self) -> list:
        try:
            root = self.imf.root()
            if not root.isDefined("data3D"):
                raise FileFormatError(self.path, "no /data3D section: the file holds no 3D scans")
            data3d = root["data3D"]
            n = int(data3d.childCount())
            heads = [self.pye57.ScanHeader(data3d[i]) for i in range(n)]
        except FileFormatError:
            raise
        except Exception as exc:  # noqa: BLE001 - libE57 and pye57 raise several types
            raise self._fail("cannot read the scan list", exc) from None
        if not heads:
            raise FileFormatError(self.path, "the E57 file holds no 3D scans (data3D is empty; images only?)")
        return heads

    def coordinate_metadata(self) -> str:
        try:
            root = self.imf.root()
            return str(root["coordinateMetadata"].value()) if root.isDefined("coordinateMetadata") else ""
        except Exception:  # noqa: BLE001 - optional element
            return ""


def _string(node, name: str) -> str | None:
    try:
        return str(node[name].value()) if node.isDefined(name) else None
    except Exception:  # noqa: BLE001 - a non-string element of that name
        return None


def _same(written: np.ndarray, read: np.ndarray) -> bool:
    """Whether libE57 read the values written (to single-precision rounding: a pose element may be
    stored as a single-precision float)."""
    return bool(np.all(np.abs(written - read) <= 1e-6 * np.maximum(1.0, np.abs(written))))


def _pose(f: _E57File, h, index: int) -> np.ndarray:
    """``T_file_scan`` (4x4 float64) of one scan header (identity without a pose).

    Each pose element is checked as written in the XML (:func:`_xml_pose_texts`): a value that is not
    a finite number, a quaternion of zero length or whose length differs from 1 by more than
    :data:`_UNIT_TOLERANCE`, is a :class:`FileFormatError` naming the scan and the values as written.
    A value written differently from what libE57 read (libE57 reads an unparsable float as 0) is
    refused the same way."""
    T = np.eye(4)
    node = h.node
    name = _string(node, "name")
    scan = f"scan {index}" + (f" ({name[:60]!r})" if name else "")
    texts = f.pose_texts()
    written = texts[index] if texts is not None and index < len(texts) else None
    try:
        if not node.isDefined("pose"):
            return T
        pose = node["pose"]
        if pose.isDefined("rotation"):
            r = pose["rotation"]
            read = np.array([float(r[k].value()) for k in ("w", "x", "y", "z")], dtype=np.float64)
            q, shown = _pose_values((written or {}).get("rotation"), read, "wxyz")
            nq = float(np.linalg.norm(q)) if np.isfinite(q).all() else math.nan
            problem = ("holds a value that is not a finite number" if not math.isfinite(nq)
                       else "has zero length" if nq == 0.0
                       else f"has length {nq:.6g}, not 1" if abs(nq - 1.0) > _UNIT_TOLERANCE
                       else "was read by libE57 as other values" if not _same(q, read) else "")
            if problem:
                raise FileFormatError(f.path, f"{scan}: pose rotation quaternion ({shown}) {problem}: not a "
                                              "rotation (damaged file?)")
            w, x, y, z = read / float(np.linalg.norm(read))
            T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
        if pose.isDefined("translation"):
            tr = pose["translation"]
            read = np.array([float(tr[k].value()) for k in ("x", "y", "z")], dtype=np.float64)
            t, shown = _pose_values((written or {}).get("translation"), read, "xyz")
            if not np.isfinite(t).all() or not _same(t, read):
                raise FileFormatError(f.path, f"{scan}: pose translation ({shown}) holds a value that is not a "
                                              "finite number (damaged file?)")
            T[:3, 3] = read
    except FileFormatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise f._fail(f"{scan}: unreadable pose", exc) from None
    return T


def _scan_record(f: _E57File, h, index: int) -> dict:
    try:
        n = int(h.point_count)
        fields = list(h.point_fields)
    except Exception as exc:  # noqa: BLE001
        raise f._fail(f"scan {index}: unreadable point header", exc) from None
    if all(c in fields for c in _CARTESIAN):
        coords = "cartesian"
    elif all(c in fields for c in _SPHERICAL):
        coords = "spherical"
    else:
        raise FileFormatError(f.path, f"scan {index} has neither cartesianX/Y/Z nor sphericalRange/Azimuth/Elevation "
                                      f"coordinates (its fields: {' '.join(fields) or 'none'})")
    return {"index": index, "name": _string(h.node, "name") or f"scan {index}", "guid": _string(h.node, "guid"),
            "points": n, "coordinates": coords, "fields": fields, "T_file_scan": _pose(f, h, index)}


def _select(path, records: list[dict], scans) -> list[dict]:
    if scans is None:
        return records
    if isinstance(scans, (int, np.integer, str)):
        scans = [scans]
    out = []
    for s in scans:
        if isinstance(s, str):
            hit = [r for r in records if r["name"] == s or r["guid"] == s]
            if not hit:
                raise InputError(f"{path}: no scan named {s!r}; scans: {', '.join(r['name'] for r in records)}")
            out.append(hit[0])
        else:
            i = int(s)
            if not 0 <= i < len(records):
                raise InputError(f"{path}: scan index {i} out of range (the file has {len(records)} scans)")
            out.append(records[i])
    if not out:
        raise InputError(f"{path}: no scans selected")
    return out


def _read_blocks(f: _E57File, h, rec: dict, block: int, extras: tuple) -> Iterator[tuple[np.ndarray, dict, int]]:
    """Yield ``(xyz in the file frame (k, 3) float64, {extra field: (k,) array}, invalid dropped)`` per block."""
    lib = f.lib
    coords = _CARTESIAN if rec["coordinates"] == "cartesian" else _SPHERICAL
    state = "cartesianInvalidState" if rec["coordinates"] == "cartesian" else "sphericalInvalidState"
    names = list(coords) + [e for e in extras] + ([state] if state in rec["fields"] else [])
    dtypes = {"intensity": np.float64, "colorRed": np.uint16, "colorGreen": np.uint16, "colorBlue": np.uint16,
              state: np.int8}  # pye57 binds 8-, 16-bit and "q" integers safely
    cap = max(1, min(int(block), max(rec["points"], 1)))
    arrays = {}
    try:
        bufs = lib.VectorSourceDestBuffer()
        for nm in names:
            a = np.empty(cap, dtype=dtypes.get(nm, np.float64))
            arrays[nm] = a
            bufs.append(lib.SourceDestBuffer(f.imf, nm, a, cap, True, True))
        reader = h.points.reader(bufs)
    except Exception as exc:  # noqa: BLE001
        raise f._fail(f"scan {rec['index']}: cannot set up the point reader", exc) from None
    R, t = rec["T_file_scan"][:3, :3], rec["T_file_scan"][:3, 3]
    got = 0
    try:
        while True:
            try:
                k = int(reader.read())
            except Exception as exc:  # noqa: BLE001
                raise f._fail(f"scan {rec['index']}: points unreadable after {got} records", exc) from None
            if k == 0:
                break
            got += k
            if got > rec["points"]:
                raise FileFormatError(f.path, f"scan {rec['index']}: more records than the {rec['points']} declared")
            a, b, c = (arrays[nm][:k].copy() for nm in coords)
            if rec["coordinates"] == "spherical":  # ASTM E2807 Sec. 8.4.11
                rc = a * np.cos(c)
                a, b, c = rc * np.cos(b), rc * np.sin(b), a * np.sin(c)
            xyz = np.column_stack([a, b, c])
            keep = None
            if state in arrays:
                keep = arrays[state][:k] == 0
                if keep.all():
                    keep = None
                else:
                    xyz = xyz[keep]
            xyz = xyz @ R.T + t  # p_file = R p_scan + t
            ext = {nm: (arrays[nm][:k] if keep is None else arrays[nm][:k][keep]).copy() for nm in extras}
            yield xyz, ext, (0 if keep is None else int(k - keep.sum()))
    finally:
        try:
            reader.close()
        except Exception:  # noqa: BLE001
            pass
    if got != rec["points"]:
        raise FileFormatError(f.path, f"scan {rec['index']}: {got} records read, {rec['points']} declared (truncated?)")


def _open_scans(path, scans):
    f = _E57File(path)
    try:
        heads = f.scan_headers()
        records = [_scan_record(f, h, i) for i, h in enumerate(heads)]
        chosen = _select(path, records, scans)
    except BaseException:
        f.__exit__(None, None, None)
        raise
    return f, heads, records, chosen


def e57_scan_poses(path) -> list[dict]:
    """The scans of an E57 file and their poses, without reading points.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    list of dict
        One per scan, in file order: ``index``, ``name``, ``guid``, ``points`` (declared record
        count, invalid returns included), ``coordinates`` (``"cartesian"`` / ``"spherical"``),
        ``fields`` (stored point fields) and ``T_file_scan`` ((4, 4) float64: scan frame -> file frame).

    Raises
    ------
    FileFormatError
        Not an E57 file, truncated, corrupt, no scans, a scan without coordinates, a bad pose.
    OptionalDependencyError
        pye57 is not installed.
    """
    f, _, records, _ = _open_scans(path, None)
    with f:
        return records


def iter_e57_chunks(path, chunk_points: int) -> Iterator[np.ndarray]:
    """Stream the points of every scan in the file frame, ``chunk_points`` records at a time.

    Same frame, order and values as ``read_e57(path).global_points`` (scan 0 first, records in
    stored order, invalid returns dropped): concatenating the chunks gives exactly that array.
    Chunks never span two scans; a chunk may be shorter than ``chunk_points`` (end of a scan, or
    invalid returns dropped). Peak memory: one chunk (libE57 reads sub-ranges of a scan).

    Parameters
    ----------
    path : str or Path
    chunk_points : int
        Records read per block (>= 1).

    Yields
    ------
    ndarray (k, 3) float64
        File-frame coordinates (m), ``k >= 1``.
    """
    if int(chunk_points) < 1:
        raise InputError(f"chunk_points must be >= 1, got {chunk_points}")
    f, heads, _, chosen = _open_scans(path, None)
    with f:
        for rec in chosen:
            for xyz, _, _ in _read_blocks(f, heads[rec["index"]], rec, int(chunk_points), ()):
                if len(xyz):
                    yield xyz


def _crs_of(path, text: str) -> str | None:
    text = (text or "").strip()
    if not text:
        return None
    try:
        import pyproj

        from minegeo.io.las import crs_to_string

        return crs_to_string(pyproj.CRS.from_user_input(text))
    except Exception:  # noqa: BLE001 - free text is allowed by the standard
        log.warning("%s: coordinateMetadata %r is not a CRS pyproj knows; kept in metadata only", path, text[:80])
        return None


def read_e57_raw(path, scans=None, *, block: int = _READ_BLOCK) -> RawCloud:
    """Read the points of an E57 file as a :class:`~minegeo.io._common.RawCloud` (see the module docstring)."""
    f, heads, records, chosen = _open_scans(path, scans)
    with f:
        extras = []
        if all("intensity" in r["fields"] for r in chosen):
            extras.append("intensity")
        if all(all(c in r["fields"] for c in _COLOUR) for r in chosen):
            extras.extend(_COLOUR)
        total = sum(r["points"] for r in chosen)
        try:
            xyz = np.empty((total, 3), dtype=np.float64)
            ext = {nm: np.empty(total, dtype=np.float64 if nm == "intensity" else np.uint16) for nm in extras}
            sidx = np.empty(total, dtype=np.int32)
        except MemoryError:
            raise FileFormatError(path, f"not enough memory for the {total} points of this E57 file") from None
        n = 0
        dropped = 0
        for rec in chosen:
            for blk, e, nd in _read_blocks(f, heads[rec["index"]], rec, block, tuple(extras)):
                k = len(blk)
                xyz[n:n + k] = blk
                for nm in extras:
                    ext[nm][n:n + k] = e[nm]
                sidx[n:n + k] = rec["index"]
                n += k
                dropped += nd
        crs_text = f.coordinate_metadata()
    fields: dict = {"scan_index": sidx[:n]}
    if "intensity" in ext:
        fields["intensity"] = ext["intensity"][:n]
    if "colorRed" in ext:
        rgb = [ext[c][:n] for c in _COLOUR]
        if n and max(int(c.max()) for c in rgb) > 255:
            rgb = [(c >> 8) for c in rgb]
        fields.update(red=rgb[0].astype(np.uint8), green=rgb[1].astype(np.uint8), blue=rgb[2].astype(np.uint8))
    meta = {
        "format": "e57",
        "encoding": f"E57 {f.header['version']}",
        "units": "m",
        "dtype": "float64 (scan coordinates transformed by each scan's pose)",
        "e57_scans": [{k: v for k, v in r.items() if k != "fields"} for r in records],
        "e57_scans_read": [r["index"] for r in chosen],
        "e57_invalid_dropped": int(dropped),
        "e57_coordinate_metadata": crs_text,
    }
    return RawCloud(values=xyz[:n], fields=fields, crs=_crs_of(path, crs_text), frame="e57_file", metadata=meta)


def read_e57(path, scans=None, *, origin=None, drop_nonfinite: bool = False) -> PointCloud:
    """Read an E57 file: every scan (or ``scans``) in the file's common frame, merged.

    Parameters
    ----------
    path : str or Path
        The ``.e57`` file (opened read-only).
    scans : None, int, str or list of them, optional
        Scans to read: indices in file order, names or guids (default: all).
    origin : None, "auto", "file" or (3,) array_like, optional
        Local origin to subtract, as in :func:`~minegeo.io.read_point_cloud` (E57 records none,
        so ``"file"`` is zero).
    drop_nonfinite : bool
        Drop points with NaN/inf coordinates instead of refusing the file.

    Returns
    -------
    PointCloud
        ``points`` float64 (n, 3) in the file frame (``frame="e57_file"``) minus ``origin``;
        ``attributes["scan_index"]`` (int32) per point, ``intensity``, ``rgb`` when every scan
        has them; ``metadata["e57_scans"]`` (name, guid, points, ``T_file_scan``, ...).

    Raises
    ------
    FileFormatError
        Not an E57 file, truncated or corrupt (the message names the problem), no scans, a
        scan without cartesian or spherical coordinates, an unusable pose.
    InputError
        ``scans`` names a scan the file does not hold.
    OptionalDependencyError
        pye57 is not installed (``pip install 'minegeo[e57]'``).
    """
    raw = read_e57_raw(path, scans)
    cloud = assemble(str(path), raw, origin=origin, drop_nonfinite=drop_nonfinite)
    cloud.metadata["source"] = str(path)
    return cloud
