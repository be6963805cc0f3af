"""Intersection semantic knowledge base built from a prior map (Liang et al. 2024, Sec. 3.2, Fig. 8).

For every junction of the map's drift skeleton (:mod:`minegeo.semantic.skeleton`) the knowledge
base holds its geometric invariant point ``C^i`` (map frame), its dense point cloud ``P^i`` (the map
points within ``cloud_radius_m`` horizontally), its PWCV ``V_d^i`` and its CWC ``M_d^i``
(:mod:`minegeo.semantic.descriptors`). A map without junctions gives ``status="no_intersections"``
with a reason, not an exception. Stored as ``.npz`` (arrays + JSON metadata, no pickles).
See ``docs/intersections.md`` ("Knowledge base").
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from dataclasses import asdict, dataclass, field, fields
from enum import StrEnum
from pathlib import Path

import numpy as np

from minegeo._params import bounded, group, validate
from minegeo._provenance import atomic_write_bytes, to_jsonable
from minegeo._validate import as_points
from minegeo.errors import FileFormatError, InputError
from minegeo.io.jsonio import load_json_text
from minegeo.io.npzstore import array_digest, crc_failure, json_digest, member_header, open_store
from minegeo.semantic.descriptors import DescriptorParams, cwc, pwcv, similarity
from minegeo.semantic.skeleton import SkeletonParams, drift_skeleton, mine_levels

__all__ = ["KBParams", "IntersectionKB", "KBStatus", "build_knowledge_base", "similarity_matrix", "KB_FORMAT", "KB_VERSION"]

KB_FORMAT = "minegeo-intersection-kb"
#: format version of the file; 2: every stored record, meta included, under the integrity hash
KB_VERSION = 2
_ARRAYS = ("ids", "degree", "invariant_points", "clearance_m", "cloud_offsets", "cloud_points", "pwcv", "cwc")


@dataclass(frozen=True)
class KBParams:
    """Parameters of :func:`build_knowledge_base`.

    Attributes
    ----------
    skeleton : SkeletonParams
    descriptor : DescriptorParams
    cloud_radius_m : float
        Horizontal radius (m) of the dense intersection cloud kept per junction, at least the descriptor
        radius ``descriptor.radius_m`` (a check across the fields refuses less) so the online side can
        verify by ICP against it.

    Each field declares its rule in its metadata (:mod:`minegeo._params`): the same rule checks the
    dataclass, ``minegeo intersections build --cloud-radius`` and its ``--config`` key; the nested
    groups check themselves.
    """

    skeleton: SkeletonParams = group(SkeletonParams)
    descriptor: DescriptorParams = group(DescriptorParams)
    cloud_radius_m: float = bounded(15.0, gt=0.0)

    def __post_init__(self):
        validate(self)
        if self.cloud_radius_m < self.descriptor.radius_m:
            raise InputError(f"KBParams.cloud_radius_m ({self.cloud_radius_m:g} m) must be at least the descriptor "
                             f"radius ({self.descriptor.radius_m:g} m): the online side verifies a recognition by ICP "
                             "against the dense cloud of what the descriptor saw")


class KBStatus(StrEnum):
    """Status of a knowledge base (:attr:`IntersectionKB.status`); each member is its string value."""

    #: at least one intersection
    OK = "ok"
    #: the map's drift skeleton has no junction: an empty base
    NO_INTERSECTIONS = "no_intersections"


@dataclass(frozen=True, eq=False)
class IntersectionKB:
    """Intersection semantic knowledge base (all coordinates in the map frame, m, z up).

    Attributes
    ----------
    status : KBStatus
        ``ok`` or ``no_intersections`` (a string is stored as its member; another value is
        refused with ``ValueError``).
    reason : str
        Why the status is not ``ok`` (empty for ``ok``).
    ids : ndarray (k,) int
        Intersection ids 0..k-1 (sorted by invariant point x, then y).
    degree : ndarray (k,) int
        Number of drifts meeting at each intersection.
    invariant_points : ndarray (k, 3)
        Geometric invariant points ``C^i``: x, y = centre of the largest empty circle among the wall
        points, z = floor height there.
    clearance_m : ndarray (k,)
        Radius of that circle (m).
    cloud_offsets : ndarray (k + 1,) int
        Intersection i's dense cloud is ``cloud_points[cloud_offsets[i]:cloud_offsets[i + 1]]``.
    cloud_points : ndarray (N, 3)
    pwcv : ndarray (k, N_s)
    cwc : ndarray (k, N_b, N_s)
    params : KBParams
    provenance : dict
        Number and SHA-256 of the input points, number of skeleton branches, format version.
    georef : dict
        Georeferencing of the map the base was built from (empty when none): ``crs`` (e.g.
        ``"EPSG:5186"``, or None) and ``origin_m`` (3,), the CRS coordinates of the base's frame
        origin (a georeferenced map's points are relative to it), so ``p_crs = p + origin_m``.
    """

    status: KBStatus
    reason: str
    ids: np.ndarray
    degree: np.ndarray
    invariant_points: np.ndarray
    clearance_m: np.ndarray
    cloud_offsets: np.ndarray
    cloud_points: np.ndarray
    pwcv: np.ndarray
    cwc: np.ndarray
    params: KBParams
    provenance: dict
    georef: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "status", KBStatus(self.status))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def cloud(self, i: int) -> np.ndarray:
        """Dense point cloud ``P^i`` (m, map frame) of intersection ``i``."""
        return self.cloud_points[self.cloud_offsets[i]:self.cloud_offsets[i + 1]]

    def save(self, path) -> Path:
        """Write the knowledge base to ``path`` (``.npz``, uncompressed, no pickles), atomically.

        The archive holds the arrays of :data:`_ARRAYS` and a JSON ``meta`` string: ``format``,
        ``version``, ``status``, ``reason``, ``params``, ``provenance``, ``georef`` and ``integrity``.
        ``meta["integrity"]`` holds the SHA-256 of every array (of its dtype, shape and bytes,
        :func:`minegeo.io.npzstore.array_digest`) and a ``manifest``: the SHA-256 of the canonical JSON of
        the rest of the meta together with the arrays' hashes, so that no stored record (array,
        parameter, provenance, georeferencing, status) can change without :meth:`load` noticing.
        """
        arrays = {k: np.ascontiguousarray(getattr(self, k)) for k in _ARRAYS}
        meta = {"format": KB_FORMAT, "version": KB_VERSION, "status": self.status, "reason": self.reason,
                "params": to_jsonable(asdict(self.params)), "provenance": to_jsonable(self.provenance),
                "georef": to_jsonable(self.georef)}
        meta = json.loads(json.dumps(meta, sort_keys=True, allow_nan=False))  # hash exactly what load reads back
        meta["integrity"] = _integrity_record(meta, arrays)
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta, sort_keys=True, allow_nan=False)), **arrays)
        return atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path) -> IntersectionKB:
        """Read a knowledge base written by :meth:`save`, checking all of it.

        In this order: the file is an uncompressed ``.npz`` archive of exactly the members
        :meth:`save` writes, each holding the bytes its header announces; its ``meta`` is JSON of
        this format and version; every array and the meta match the integrity record (a mismatch
        means the file was changed after it was written); the stored values are valid: the
        parameters within the rules of :class:`KBParams` and its groups (the field is named), the status,
        reason, provenance and georeferencing of the right types, the arrays of the right dtypes,
        finite, of consistent shapes. The arrays are returned as stored (bit for bit).

        Raises
        ------
        FileNotFoundError
            No such file.
        FileFormatError
            Not such an archive, written by another format version (rebuild it with
            ``minegeo intersections build``), changed after it was written (integrity hash
            mismatch), or holding a value out of range.
        """
        p = Path(path)
        meta, arrays = _read_kb_file(p)
        _check_format(meta, p)
        _verify_integrity(meta, arrays, p)
        params = _params_from_meta(meta.get("params"), p)
        status, reason, provenance, georef = _check_records(meta, p)
        kb = cls(status, reason, params=params, provenance=provenance, georef=georef, **arrays)
        _check_arrays(kb, p)
        return kb


#: what a file that is not a base is called in the messages
_WHAT = "minegeo intersection base"
_REBUILD = "rebuild it with minegeo intersections build"
_INT_ARRAYS = ("ids", "degree", "cloud_offsets")
_INTEGRITY_ALGORITHM = "sha256"


class _Bad(Exception):
    """A stored value out of range (turned into a :class:`FileFormatError` naming the field)."""


def _manifest(meta: dict, digests: dict) -> str:
    """SHA-256 of the meta (without ``integrity``) together with the arrays' hashes."""
    core = {k: v for k, v in meta.items() if k != "integrity"}
    return json_digest({"meta": core, "arrays": {k: digests.get(k) for k in _ARRAYS}})


def _integrity_record(meta: dict, arrays: dict) -> dict:
    digests = {k: array_digest(arrays[k]) for k in _ARRAYS}
    return {"algorithm": _INTEGRITY_ALGORITHM, "arrays": digests, "manifest": _manifest(meta, digests)}


def _read_kb_file(p: Path) -> tuple[dict, dict]:
    """``(meta, arrays)`` of a base file; nothing is read before its members are checked."""
    try:
        z = open_store(p, _WHAT)
        size = p.stat().st_size
        with z:
            infos = z.zip.infolist()
            names = [i.filename[:-4] if i.filename.endswith(".npy") else i.filename for i in infos]
            if len(set(names)) != len(names) or sum(i.compress_size for i in infos) > size:
                raise FileFormatError(p, f"not a {_WHAT} (the archive's members overlap or repeat)")
            extra = sorted(set(names) - {"meta", *_ARRAYS})
            if "meta" not in names or extra:
                why = "no 'meta' entry" if "meta" not in names else f"unexpected entry {extra[0][:60]!r}"
                raise FileFormatError(p, f"not a {_WHAT} ({why})")
            headers = {}
            for name, info in zip(names, infos, strict=True):
                problem, shape, dtype = member_header(z.zip, info)
                if problem is not None:
                    raise FileFormatError(p, f"{_WHAT} entry {name!r} is damaged ({problem}): {_REBUILD}")
                headers[name] = (shape, dtype)
            if headers["meta"][1].kind != "U" or headers["meta"][0] != ():
                raise FileFormatError(p, f"not a {_WHAT} (its 'meta' entry is not a text record)")
            meta = load_json_text(str(z["meta"]), p)
            if not isinstance(meta, dict):
                raise FileFormatError(p, f"not a {_WHAT} (its meta is not a JSON object)")
            if meta.get("format") != KB_FORMAT:
                raise FileFormatError(p, f"not a {_WHAT} (format {str(meta.get('format'))[:80]!r})")
            arrays = {}
            for k in _ARRAYS:
                if k not in headers:
                    raise FileFormatError(p, f"{_WHAT} has no array {k!r}: {_REBUILD}")
                want = np.int64 if k in _INT_ARRAYS else np.float64
                if headers[k][1] != want:
                    raise FileFormatError(p, f"array {k!r} has dtype {headers[k][1]}, not {np.dtype(want)}: the "
                                             f"file was edited or corrupted; {_REBUILD}")
                arrays[k] = np.ascontiguousarray(z[k])
    except (FileFormatError, FileNotFoundError):
        raise
    except zipfile.BadZipFile as exc:
        if (member := crc_failure(exc)) is not None:
            raise FileFormatError(p, f"was changed after it was written (archive checksum mismatch of {member}); "
                                     f"{_REBUILD}") from None
        raise FileFormatError(p, f"not a {_WHAT} (damaged archive: {str(exc)[:200]})") from None
    except (OSError, ValueError, KeyError, EOFError, RuntimeError) as exc:
        raise FileFormatError(p, f"not a {_WHAT} (unreadable archive: {str(exc)[:200]})") from None
    return meta, arrays


def _check_format(meta: dict, p: Path) -> None:
    v = meta.get("version")
    if not (isinstance(v, int) and not isinstance(v, bool)):
        raise FileFormatError(p, f"{_WHAT} format version {str(v)[:40]!r} is not an integer: {_REBUILD}")
    if v < KB_VERSION:
        raise FileFormatError(p, f"written by an older minegeo ({_WHAT} format version {v}, without integrity "
                                 f"hashes; this minegeo reads version {KB_VERSION}): {_REBUILD}")
    if v > KB_VERSION:
        raise FileFormatError(p, f"{_WHAT} format version {v} is newer than this minegeo reads ({KB_VERSION}): "
                                 f"update minegeo or {_REBUILD}")


def _verify_integrity(meta: dict, arrays: dict, p: Path) -> None:
    rec = meta.get("integrity")
    if (not isinstance(rec, dict) or rec.get("algorithm") != _INTEGRITY_ALGORITHM
            or not isinstance(rec.get("arrays"), dict) or not isinstance(rec.get("manifest"), str)):
        raise FileFormatError(p, f"was changed after it was written (its integrity record is missing or malformed); "
                                 f"{_REBUILD}")
    digests = {k: array_digest(arrays[k]) for k in _ARRAYS}
    for k in _ARRAYS:
        if digests[k] != rec["arrays"].get(k):
            raise FileFormatError(p, f"was changed after it was written (integrity hash mismatch: array {k!r}); "
                                     f"{_REBUILD}")
    if _manifest(meta, digests) != rec["manifest"]:
        raise FileFormatError(p, f"was changed after it was written (integrity hash mismatch: its meta record of "
                                 f"status, parameters, provenance and georeferencing); {_REBUILD}")


def _number(v, where: str, integer: bool) -> float | int:
    if isinstance(v, bool) or not isinstance(v, int | float) or (integer and not isinstance(v, int)):
        raise _Bad(f"{where} must be {'a whole number' if integer else 'a number'}, got {str(v)[:40]!r}")
    if not math.isfinite(v):
        raise _Bad(f"{where} must be finite, got {v!r}")
    return v


def _dataclass_from(cls, d, where: str):
    """An instance of the parameter dataclass ``cls`` from its stored JSON object ``d``: exactly its
    fields, each of the type of the field's default (whole number, number, pair of numbers)."""
    if not isinstance(d, dict):
        raise _Bad(f"{where} must be an object, got {type(d).__name__}")
    names = [f.name for f in fields(cls)]
    unknown, missing = sorted(set(d) - set(names)), [n for n in names if n not in d]
    if unknown or missing:
        raise _Bad(f"{where}: " + (f"unknown field {where}.{unknown[0][:40]}" if unknown
                                   else f"missing field {where}.{missing[0]}"))
    default = cls()
    out = {}
    for n in names:
        ref, v, w = getattr(default, n), d[n], f"{where}.{n}"
        if isinstance(ref, tuple):
            if not isinstance(v, list) or len(v) != len(ref):
                raise _Bad(f"{w} must be a list of {len(ref)} numbers, got {str(v)[:40]!r}")
            out[n] = tuple(_number(x, w, False) for x in v)
        else:
            out[n] = _number(v, w, isinstance(ref, int))
    return _checked(where, lambda: cls(**out))


def _params_from_meta(d, p: Path) -> KBParams:
    """The stored :class:`KBParams`, checked against the bounds the parameters have when building."""
    try:
        if not isinstance(d, dict) or sorted(d) != ["cloud_radius_m", "descriptor", "skeleton"]:
            raise _Bad("params must be an object with the fields cloud_radius_m, descriptor, skeleton")
        sk = _dataclass_from(SkeletonParams, d["skeleton"], "params.skeleton")
        de = _dataclass_from(DescriptorParams, d["descriptor"], "params.descriptor")
        radius = float(_number(d["cloud_radius_m"], "params.cloud_radius_m", False))
        params = _checked("params", lambda: KBParams(sk, de, radius))
    except _Bad as exc:
        raise FileFormatError(p, f"stored value out of range: {exc}; {_REBUILD}") from None
    return params


def _checked(where: str, build):
    """``build()`` (a parameter group, checked as it is made), its refusal a :class:`_Bad` naming ``where``."""
    try:
        return build()
    except (InputError, TypeError, ValueError) as exc:
        raise _Bad(f"{where}: {exc}") from None


def _check_records(meta: dict, p: Path) -> tuple[str, str, dict, dict]:
    """Status, reason, provenance and georeferencing of the meta, of the right types and values."""
    status, reason, prov, geo = (meta.get(k) for k in ("status", "reason", "provenance", "georef"))
    try:
        if status not in ("ok", "no_intersections"):
            raise _Bad(f"status must be 'ok' or 'no_intersections', got {str(status)[:40]!r}")
        if not isinstance(reason, str):
            raise _Bad("reason must be a text")
        if not isinstance(prov, dict):
            raise _Bad("provenance must be an object")
        if not isinstance(geo, dict) or set(geo) - {"crs", "origin_m"}:
            raise _Bad("georef must be an object with the fields crs and origin_m")
        if geo:
            if not (geo.get("crs") is None or isinstance(geo.get("crs"), str)):
                raise _Bad("georef.crs must be a text or null")
            o = geo.get("origin_m")
            if o is not None and not (isinstance(o, list) and len(o) == 3):
                raise _Bad("georef.origin_m must be a list of 3 numbers")
            for x in o or []:
                _number(x, "georef.origin_m", False)
    except _Bad as exc:
        raise FileFormatError(p, f"stored value out of range: {exc}; {_REBUILD}") from None
    return status, reason, dict(prov), dict(geo)


def _check_arrays(kb: IntersectionKB, p: Path) -> None:
    """Shapes consistent with each other and with the descriptor parameters; values in range."""
    k = kb.ids.shape[0]
    d = kb.params.descriptor
    ok = (kb.ids.ndim == 1 and kb.degree.shape == (k,) and kb.invariant_points.shape == (k, 3)
          and kb.clearance_m.shape == (k,) and kb.cloud_offsets.shape == (k + 1,) and kb.cloud_points.ndim == 2
          and kb.cloud_points.shape[1] == 3 and kb.pwcv.shape == (k, d.n_sectors)
          and kb.cwc.shape == (k, d.n_bands, d.n_sectors))
    if not ok:
        raise FileFormatError(p, f"inconsistent array shapes in the {_WHAT}: {_REBUILD}")
    if (kb.status == "ok") != (k > 0):
        raise FileFormatError(p, f"status {str(kb.status)!r} with {k} intersection(s): {_REBUILD}")
    problems = [
        ("ids", not np.array_equal(kb.ids, np.arange(k))),
        ("degree", bool(np.any(kb.degree < 3))),
        ("cloud_offsets", not (int(kb.cloud_offsets[0]) == 0 and int(kb.cloud_offsets[-1]) == kb.cloud_points.shape[0]
                               and bool(np.all(np.diff(kb.cloud_offsets) >= 0)))),
        *((name, not bool(np.isfinite(getattr(kb, name)).all()))
          for name in ("invariant_points", "clearance_m", "cloud_points", "pwcv", "cwc")),
        ("clearance_m", bool(np.any(kb.clearance_m < 0))),
    ]
    bad = next((name for name, b in problems if b), None)
    if bad is not None:
        raise FileFormatError(p, f"array {bad!r} holds values out of range: {_REBUILD}")


def _points_of(map_cloud) -> np.ndarray:
    pts = getattr(map_cloud, "points", map_cloud)
    return as_points(pts, "map_cloud", min_points=100)


def build_knowledge_base(map_cloud, params: KBParams | None = None) -> IntersectionKB:
    """Build the intersection knowledge base of a prior map.

    Parameters
    ----------
    map_cloud : PointCloud or array_like (n, 3)
        The map (m, map frame, z up; a :class:`~minegeo.io.types.PointCloud`'s ``points`` are used
        as they are, relative to its origin). Several mine levels are split by
        :func:`~minegeo.semantic.skeleton.mine_levels` and each level's skeleton is built on its own.
    params : KBParams, optional

    Returns
    -------
    IntersectionKB
        ``status="ok"`` with k >= 1 intersections, or ``status="no_intersections"`` (k = 0) with the
        reason (e.g. a single drift).

    Raises
    ------
    InputError
        Empty map, wrong shape, NaN/inf coordinates, no wall points (see :func:`drift_skeleton`).
    """
    params = params or KBParams()
    P = _points_of(map_cloud)
    from scipy.spatial import cKDTree

    C_all, deg_all, clear_all, clouds, n_branches = [], [], [], [], 0
    for idx in mine_levels(P, params.skeleton):  # the skeleton is 2-D: one level at a time
        L = P[idx]
        if L.shape[0] < 100:
            continue
        sk = drift_skeleton(L, params.skeleton)
        n_branches += int(sk.n_branches)
        if sk.junction_xy.shape[0] == 0:
            continue
        C_all.append(np.c_[sk.junction_xy, sk.floor.height(sk.junction_xy)])
        deg_all.append(sk.junction_degree)
        clear_all.append(cKDTree(sk.wall_xy).query(sk.junction_xy)[0])
        dxy = L[:, :2]
        clouds += [L[np.einsum("ij,ij->i", dxy - c[:2], dxy - c[:2]) <= params.cloud_radius_m ** 2]
                   for c in C_all[-1]]
    C = np.concatenate(C_all).reshape(-1, 3) if C_all else np.zeros((0, 3))
    k = C.shape[0]
    degree = np.concatenate(deg_all).astype(np.int64) if deg_all else np.zeros(0, np.int64)
    clear = np.concatenate(clear_all) if clear_all else np.zeros(0)
    d = params.descriptor
    offsets = np.r_[0, np.cumsum([len(c) for c in clouds])].astype(np.int64)
    V = np.array([pwcv(c, ci, d) for c, ci in zip(clouds, C, strict=True)]).reshape(k, d.n_sectors)
    M = np.array([cwc(c, ci, d) for c, ci in zip(clouds, C, strict=True)]).reshape(k, d.n_bands, d.n_sectors)
    h = hashlib.sha256(P.tobytes()).hexdigest()
    prov = {"n_points": int(P.shape[0]), "points_sha256": h, "n_branches": int(n_branches),
            "format": KB_FORMAT, "version": KB_VERSION}
    status, reason = KBStatus.OK, ""
    if k == 0:
        status = KBStatus.NO_INTERSECTIONS
        reason = (f"the drift skeleton has {n_branches} branch(es) and no junction of degree >= 3 "
                  f"(merge radius {params.skeleton.merge_radius_m} m, spurs < {params.skeleton.min_branch_m} m "
                  "ignored)")
    return IntersectionKB(status, reason, np.arange(k, dtype=np.int64), degree, C,
                          np.asarray(clear, np.float64), offsets,
                          np.ascontiguousarray(np.concatenate(clouds) if k else np.zeros((0, 3))),
                          np.ascontiguousarray(V), np.ascontiguousarray(M), params, prov)


def similarity_matrix(kb: IntersectionKB, kind: str = "pwcv") -> np.ndarray:
    """Symmetric (k, k) matrix of heading-invariant similarities between the knowledge base's
    intersections, from their PWCV (``kind="pwcv"``) or CWC (``"cwc"``) descriptors, without the
    occlusion rule (both are complete map descriptors); the diagonal is 1 (Liang2024 Fig. 16)."""
    if kind not in ("pwcv", "cwc"):
        raise InputError(f"kind must be 'pwcv' or 'cwc', got {kind!r}")
    D = kb.pwcv if kind == "pwcv" else kb.cwc
    k = len(kb)
    S = np.eye(k)
    for i in range(k):
        for j in range(i + 1, k):
            S[i, j] = S[j, i] = similarity(D[i], D[j], occlusion=False).score
    return S
