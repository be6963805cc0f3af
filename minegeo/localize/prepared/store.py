"""The prepared map's file format: version constants, the integrity manifest and the checked reading of a stored ``.npz``.

A prepared map is stored as a NumPy ``.npz`` without pickles: the core arrays (:data:`CORE_ARRAYS`),
a JSON ``meta`` record (format, version, parameters, georeferencing) and optional search indexes
(members prefixed :data:`INDEX_PREFIX`). Every member is covered by an integrity manifest
(:data:`INTEGRITY_ALGORITHM` digests); the readers here check the format, the version, the digests
and the type and range of every stored number before any of it is used.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError
from minegeo.io.jsonio import load_json_text
from minegeo.io.npzstore import array_digest as _array_digest
from minegeo.io.npzstore import crc_failure, open_store
from minegeo.io.npzstore import json_digest as _json_digest
from minegeo.io.npzstore import member_header as _member_header

#: ``format`` tag stored in a prepared-map file.
PREPARED_FORMAT = "minegeo-prepared-map"
#: Current file format version (increase on any incompatible change).
PREPARED_VERSION = 1

#: Format of the search structures a prepared file may also hold (``meta["indexes"]``).
INDEX_VERSION = 1
INDEX_PREFIX = "index__"

#: Hash of the integrity record (``meta["integrity"]``) of a prepared-map file.
INTEGRITY_ALGORITHM = "sha256"
#: The map's own arrays: a damaged one makes the file unusable (the search structures are
#: optional: a damaged one is rebuilt).
CORE_ARRAYS = ("points", "normals", "features", "icp_points", "icp_normals", "work_origin")
#: FPFH descriptor length (Rusu 2009: 3 angles x 11 bins).
FPFH_DIM = 33
_REPREPARE = "prepare the map again with minegeo prepare-map"


# ----------------------------------------------------------------------------- file checks
def _manifest(meta: dict, digests: dict) -> str:
    """Hash of the meta (without ``integrity`` and the search structures' ``indexes``) and of the
    map arrays' hashes."""
    core = {k: v for k, v in meta.items() if k not in ("integrity", "indexes")}
    return _json_digest({"meta": core, "arrays": {k: digests.get(k) for k in CORE_ARRAYS}})


def _entry_digest(entry, name: str, digests: dict) -> str:
    """Hash of one search structure's meta record and of its arrays' hashes."""
    pre = f"{INDEX_PREFIX}{name}__"
    return _json_digest({"entry": entry, "arrays": {k: d for k, d in digests.items() if k.startswith(pre)}})


def _integrity_record(meta: dict, arrays: dict) -> dict:
    """``meta["integrity"]`` of a file holding ``arrays`` (every array but ``meta``)."""
    digests = {k: _array_digest(v) for k, v in sorted(arrays.items())}
    entries = (meta.get("indexes") or {}).get("entries", [])
    return {"algorithm": INTEGRITY_ALGORITHM, "arrays": digests, "manifest": _manifest(meta, digests),
            "indexes": {e["name"]: _entry_digest(e, e["name"], digests) for e in entries}}


def _read_prepared_file(p: Path):
    """``(meta, map arrays, index arrays, damaged members)`` of a prepared-map file.

    Nothing is read before the archive's members are checked: uncompressed, not overlapping,
    each holding exactly the bytes its header announces (so a member cannot make the reader
    allocate more than the file holds). A damaged member of a search structure is only
    reported (``{name: problem}``); one of the map is a :class:`FileFormatError`.
    """
    try:
        z = open_store(p, "minegeo prepared map")
        size = p.stat().st_size
        with z:
            infos = z.zip.infolist()
            names = [i.filename[:-4] if i.filename.endswith(".npy") else i.filename for i in infos]
            if len(set(names)) != len(names) or sum(i.compress_size for i in infos) > size:
                raise FileFormatError(p, "the archive's members overlap or repeat (not written by minegeo)")
            bad, headers = {}, {}
            for name, info in zip(names, infos, strict=True):
                problem, shape, dtype = _member_header(z.zip, info)
                if problem is not None:
                    bad[name] = problem
                headers[name] = (shape, dtype)
            if "meta" not in headers:
                raise FileFormatError(p, "not a minegeo prepared map (no 'meta' entry)")
            if "meta" in bad or headers["meta"][1].kind != "U" or headers["meta"][0] != ():
                raise FileFormatError(p, f"not a minegeo prepared map (bad 'meta' entry{': ' + bad.get('meta', '')})")
            meta = load_json_text(str(z["meta"]), p, allow_nonfinite=True)
            if not isinstance(meta, dict):
                raise FileFormatError(p, "not a minegeo prepared map (its meta is not a JSON object)")
            arrays = {}
            for k in CORE_ARRAYS:
                if k not in headers:
                    raise FileFormatError(p, f"prepared map has no array {k!r}: {_REPREPARE}")
                if k in bad:
                    raise FileFormatError(p, f"array {k!r} is damaged ({bad[k]}): {_REPREPARE}")
                if headers[k][1] != np.float64:
                    raise FileFormatError(p, f"array {k!r} has dtype {headers[k][1]}, not float64: the file was "
                                             f"edited or corrupted; {_REPREPARE}")
                arrays[k] = np.ascontiguousarray(z[k])
            index_arrays = {}
            for k in names:
                if k in arrays or k == "meta":
                    continue
                if not k.startswith(INDEX_PREFIX):
                    raise FileFormatError(p, f"unexpected array {k!r} (not part of a prepared map): the file was "
                                             f"edited; {_REPREPARE}")
                if k not in bad and "indexes" in meta:
                    index_arrays[k] = z[k]
    except FileFormatError:
        raise
    except (OSError, ValueError, KeyError, EOFError, RuntimeError, zipfile.BadZipFile) as exc:
        if (member := crc_failure(exc)) is not None:
            raise FileFormatError(p, f"was changed after it was written (archive checksum mismatch of {member}): "
                                     f"{_REPREPARE}") from None
        raise FileFormatError(p, f"cannot read prepared map ({exc})") from None
    return meta, arrays, index_arrays, {k: v for k, v in bad.items() if k.startswith(INDEX_PREFIX)}


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_meta(meta: dict, p: Path) -> None:
    """Format, version and the types of the meta fields (a :class:`FileFormatError` names the field)."""
    if meta.get("format") != PREPARED_FORMAT:
        raise FileFormatError(p, f"not a minegeo prepared map (format {str(meta.get('format'))[:80]!r})")
    v = meta.get("version")
    if not _is_int(v):
        raise FileFormatError(p, f"prepared-map format version {str(v)[:40]!r} is not an integer: {_REPREPARE}")
    if v != PREPARED_VERSION:
        raise FileFormatError(p, f"prepared-map format version {v} is not {PREPARED_VERSION}: prepare the map again")
    for key, types, what in (("params", dict, "an object"), ("params_hash", str, "a string"),
                             ("georef", (dict, type(None)), "an object or null"),
                             ("crs", (str, type(None)), "a string or null"),
                             ("source", (dict, type(None)), "an object"),
                             ("timings_s", (dict, type(None)), "an object")):
        if not isinstance(meta.get(key), types):
            raise FileFormatError(p, f"meta field {key!r} must be {what}, got {type(meta.get(key)).__name__}: "
                                     f"the file was edited or corrupted; {_REPREPARE}")
    if not all(t is None or _is_number(t) for t in (meta.get("timings_s") or {}).values()):
        raise FileFormatError(p, f"meta field 'timings_s' must hold numbers: {_REPREPARE}")


def _verify_integrity(meta: dict, arrays: dict, index_arrays: dict, bad: dict, p: Path) -> dict:
    """Compare every array and the meta with ``meta["integrity"]``.

    A map array or the meta that does not match is a :class:`FileFormatError`. Returns
    ``{name: problem}`` of the search structures that do not match (or hold a damaged member).
    """
    rec = meta.get("integrity")
    if rec is None:
        raise FileFormatError(p, "prepared map has no integrity hashes (written by an older minegeo): " + _REPREPARE)
    if (not isinstance(rec, dict) or rec.get("algorithm") != INTEGRITY_ALGORITHM
            or not isinstance(rec.get("arrays"), dict) or not isinstance(rec.get("manifest"), str)
            or not isinstance(rec.get("indexes", {}), dict)):
        raise FileFormatError(p, f"its integrity record is malformed: the file was edited or corrupted; {_REPREPARE}")
    recorded = rec["arrays"]
    digests = {}
    for k in CORE_ARRAYS:
        digests[k] = _array_digest(arrays[k])
        if digests[k] != recorded.get(k):
            raise FileFormatError(p, f"array {k!r} does not match its integrity hash: the file was edited or "
                                     f"corrupted; {_REPREPARE}")
    if _manifest(meta, digests) != rec["manifest"]:
        raise FileFormatError(p, f"the meta record does not match its integrity hash: the file was edited or "
                                 f"corrupted; {_REPREPARE}")
    skip: dict = {}
    record = meta.get("indexes")
    entries = record.get("entries") if isinstance(record, dict) else None
    for e in entries if isinstance(entries, list) else []:
        name = e.get("name") if isinstance(e, dict) else None
        if not isinstance(name, str):
            continue
        pre = f"{INDEX_PREFIX}{name}__"
        for k in sorted(bad):
            if k.startswith(pre):
                skip[name] = f"array {k!r} is damaged: {bad[k]}"
                break
        if name in skip:
            continue
        for k, a in index_arrays.items():
            if k.startswith(pre):
                digests[k] = _array_digest(a)
                if digests[k] != recorded.get(k):
                    skip[name] = f"array {k!r} does not match its integrity hash"
                    break
        if name not in skip and _entry_digest(e, name, digests) != rec.get("indexes", {}).get(name):
            skip[name] = "its record does not match its integrity hash"
    return skip


def _stored(a: dict, key: str, dtype, shape: tuple | None = None, ndim: int | None = None) -> np.ndarray:
    """Stored array ``a[key]`` of exactly ``dtype`` (and ``shape`` / ``ndim``), else ``ValueError``."""
    if key not in a:
        raise ValueError(f"array {key!r} is missing")
    x = a[key]
    if x.dtype != np.dtype(dtype):
        raise ValueError(f"array {key!r} has dtype {x.dtype}, expected {np.dtype(dtype)}")
    if (shape is not None and x.shape != tuple(shape)) or (ndim is not None and x.ndim != ndim):
        raise ValueError(f"array {key!r} has shape {x.shape}")
    return np.ascontiguousarray(x)


def _integer(e: dict, key: str, lo: int, hi: int) -> int:
    """Meta field ``e[key]``: an integer in ``[lo, hi]``, else ``ValueError``."""
    v = e[key]
    if not _is_int(v) or not lo <= v <= hi:
        raise ValueError(f"{key} must be an integer in [{lo}, {hi}], got {str(v)[:40]!r}")
    return v


def _number(e, key, positive: bool = False) -> float:
    """Meta field ``e[key]``: a finite number (``> 0`` with ``positive``), else ``ValueError``."""
    v = e[key]
    if not _is_number(v) or (positive and not v > 0):
        raise ValueError(f"{key} must be a finite{' positive' if positive else ''} number, got {str(v)[:40]!r}")
    return float(v)


def _flag(e: dict, key: str) -> bool:
    v = e[key]
    if not isinstance(v, bool):
        raise ValueError(f"{key} must be true or false, got {str(v)[:40]!r}")
    return v


def _in_range(x: np.ndarray, lo: int, hi: int, what: str) -> None:
    """``ValueError`` unless every value of ``x`` is in ``[lo, hi)``."""
    if x.size and (int(x.min()) < lo or int(x.max()) >= hi):
        raise ValueError(f"{what} out of range")
