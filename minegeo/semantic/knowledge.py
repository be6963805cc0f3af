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
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes, to_jsonable
from minegeo._validate import as_points, check_positive
from minegeo.errors import FileFormatError, InputError
from minegeo.semantic.descriptors import DescriptorParams, cwc, pwcv, similarity
from minegeo.semantic.skeleton import SkeletonParams, drift_skeleton

__all__ = ["KBParams", "IntersectionKB", "build_knowledge_base", "similarity_matrix", "KB_FORMAT", "KB_VERSION"]

KB_FORMAT = "minegeo-intersection-kb"
KB_VERSION = 1
_ARRAYS = ("ids", "degree", "invariant_points", "clearance_m", "cloud_offsets", "cloud_points", "pwcv", "cwc")


@dataclass(frozen=True)
class KBParams:
    """Parameters of :func:`build_knowledge_base`.

    Attributes
    ----------
    skeleton : SkeletonParams
    descriptor : DescriptorParams
    cloud_radius_m : float
        Horizontal radius (m) of the dense intersection cloud kept per junction (>= the descriptor radius
        so the online side can verify by ICP against it).
    """

    skeleton: SkeletonParams = field(default_factory=SkeletonParams)
    descriptor: DescriptorParams = field(default_factory=DescriptorParams)
    cloud_radius_m: float = 15.0

    def check(self) -> None:
        """Raise :class:`InputError` for a value out of range."""
        self.skeleton.check()
        self.descriptor.check()
        check_positive(self.cloud_radius_m, "cloud_radius_m")


@dataclass(frozen=True, eq=False)
class IntersectionKB:
    """Intersection semantic knowledge base (all coordinates in the map frame, m, z up).

    Attributes
    ----------
    status : str
        ``"ok"`` or ``"no_intersections"``.
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

    status: str
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

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def cloud(self, i: int) -> np.ndarray:
        """Dense point cloud ``P^i`` (m, map frame) of intersection ``i``."""
        return self.cloud_points[self.cloud_offsets[i]:self.cloud_offsets[i + 1]]

    def save(self, path) -> Path:
        """Write the knowledge base to ``path`` (``.npz``, uncompressed, no pickles), atomically.

        The archive holds the arrays of :data:`_ARRAYS` and a JSON ``meta`` string (format, version,
        status, reason, params, provenance, SHA-256 of every array).
        """
        arrays = {k: np.ascontiguousarray(getattr(self, k)) for k in _ARRAYS}
        meta = {"format": KB_FORMAT, "version": KB_VERSION, "status": self.status, "reason": self.reason,
                "params": to_jsonable(asdict(self.params)), "provenance": to_jsonable(self.provenance),
                "georef": to_jsonable(self.georef),
                "sha256": {k: _digest(v) for k, v in arrays.items()}}
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
        return atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path) -> IntersectionKB:
        """Read a knowledge base written by :meth:`save`.

        Raises
        ------
        FileFormatError
            Not such an archive, another format version, a missing or altered array, or
            inconsistent shapes.
        """
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                arrays = {k: np.array(z[k]) for k in _ARRAYS}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
            raise FileFormatError(p, f"not a minegeo intersection knowledge base ({exc})") from None
        if meta.get("format") != KB_FORMAT or meta.get("version") != KB_VERSION:
            raise FileFormatError(p, f"format {meta.get('format')!r} version {meta.get('version')!r}, expected "
                                     f"{KB_FORMAT!r} version {KB_VERSION}")
        for k, v in arrays.items():
            if meta.get("sha256", {}).get(k) != _digest(v):
                raise FileFormatError(p, f"array {k!r} does not match its recorded SHA-256")
        try:
            pr = meta["params"]
            params = KBParams(SkeletonParams(**{k: tuple(v) if isinstance(v, list) else v
                                                for k, v in pr["skeleton"].items()}),
                              DescriptorParams(**{k: tuple(v) if isinstance(v, list) else v
                                                  for k, v in pr["descriptor"].items()}),
                              float(pr["cloud_radius_m"]))
        except (KeyError, TypeError) as exc:
            raise FileFormatError(p, f"parameters unreadable ({exc})") from None
        kb = cls(str(meta["status"]), str(meta["reason"]), params=params, provenance=dict(meta["provenance"]),
                 georef=dict(meta.get("georef") or {}), **arrays)
        _check_shapes(kb, p)
        return kb


def _digest(a: np.ndarray) -> str:
    h = hashlib.sha256(f"{a.dtype.str}|{list(a.shape)}|".encode("ascii"))
    h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _check_shapes(kb: IntersectionKB, p: Path) -> None:
    k = kb.ids.shape[0]
    d = kb.params.descriptor
    ok = (kb.degree.shape == (k,) and kb.invariant_points.shape == (k, 3) and kb.clearance_m.shape == (k,)
          and kb.cloud_offsets.shape == (k + 1,) and kb.cloud_points.ndim == 2 and kb.cloud_points.shape[1] == 3
          and kb.pwcv.shape == (k, d.n_sectors) and kb.cwc.shape == (k, d.n_bands, d.n_sectors)
          and int(kb.cloud_offsets[0]) == 0 and int(kb.cloud_offsets[-1]) == kb.cloud_points.shape[0]
          and bool(np.all(np.diff(kb.cloud_offsets) >= 0)) and kb.status in ("ok", "no_intersections"))
    if not ok:
        raise FileFormatError(p, "inconsistent array shapes in the knowledge base")


def _points_of(map_cloud) -> np.ndarray:
    pts = getattr(map_cloud, "points", map_cloud)
    return as_points(pts, "map_cloud", min_points=100)


def build_knowledge_base(map_cloud, params: KBParams | None = None) -> IntersectionKB:
    """Build the intersection knowledge base of a prior map.

    Parameters
    ----------
    map_cloud : PointCloud or array_like (n, 3)
        The map (m, map frame, z up; a :class:`~minegeo.io.types.PointCloud`'s ``points`` are used
        as they are, relative to its origin), one mine level.
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
    params.check()
    P = _points_of(map_cloud)
    sk = drift_skeleton(P, params.skeleton)
    k = sk.junction_xy.shape[0]
    z = sk.floor.height(sk.junction_xy) if k else np.zeros(0)
    C = np.c_[sk.junction_xy, z].reshape(-1, 3)
    d = params.descriptor
    from scipy.spatial import cKDTree

    clear = cKDTree(sk.wall_xy).query(sk.junction_xy)[0] if k else np.zeros(0)
    dxy = P[:, :2]
    clouds = [P[np.einsum("ij,ij->i", dxy - c[:2], dxy - c[:2]) <= params.cloud_radius_m ** 2] for c in C]
    offsets = np.r_[0, np.cumsum([len(c) for c in clouds])].astype(np.int64)
    V = np.array([pwcv(c, ci, d) for c, ci in zip(clouds, C, strict=True)]).reshape(k, d.n_sectors)
    M = np.array([cwc(c, ci, d) for c, ci in zip(clouds, C, strict=True)]).reshape(k, d.n_bands, d.n_sectors)
    h = hashlib.sha256(P.tobytes()).hexdigest()
    prov = {"n_points": int(P.shape[0]), "points_sha256": h, "n_branches": int(sk.n_branches),
            "format": KB_FORMAT, "version": KB_VERSION}
    status, reason = "ok", ""
    if k == 0:
        status = "no_intersections"
        reason = (f"the drift skeleton has {sk.n_branches} branch(es) and no junction of degree >= 3 "
                  f"(merge radius {params.skeleton.merge_radius_m} m, spurs < {params.skeleton.min_branch_m} m "
                  "ignored)")
    return IntersectionKB(status, reason, np.arange(k, dtype=np.int64), sk.junction_degree.astype(np.int64), C,
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
