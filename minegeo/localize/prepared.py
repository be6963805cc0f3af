"""Map preparation for global localization: downsample, normals, FPFH, saved once (Baek et al. 2022, Sec. 2.2-2.3).

A *prepared map* holds everything of the prior map that the localization of a scan needs
and that does not depend on the scan: the downsampled map points (Sec. 2.2), their surface
normals ([Baek2022 Eq. 2]) and FPFH descriptors ([Baek2022 Eqs. 3-6]), in the **map frame** relative to a recorded
working origin, plus the georeferencing of the map (if any). It is computed once
(:func:`prepare_map`, ``minegeo prepare-map``) and stored as a NumPy ``.npz`` file without
pickles (:meth:`PreparedMap.save` / :meth:`PreparedMap.load`), carrying a format version and
a hash of the parameters; loading with other parameters is an error, so a scan is never
matched against features computed with different settings. Map *files* are prepared by
:func:`prepare_map_file`, which reads them in chunks (two passes, memory bounded by the
downsampled map plus one chunk) and gives the same arrays as :func:`prepare_map`, bit for bit.

Frames
------
``map``   the frame of the map *before* georeferencing (the ``map`` of ``T_crs_map``); for a
          map without georeferencing sidecar, the file's own coordinates.
``work``  ``map`` minus ``work_origin`` (a rounded point near the map's centre): all
          arrays of a :class:`PreparedMap` are in this frame (float64 precision for any map).
``geo``   CRS minus the georeferencing origin (see :mod:`minegeo.georef`).

Normal orientation
------------------
FPFH depends on the signs of the normals, so the map and the scan must be oriented by the
same rotation-invariant rule. Default ``"void"``: each normal is flipped to point towards
the centroid of the points within a cube of half-edge ``orientation_radius_m`` around it
(for a drift wider than a few metres this is the drift's interior, the air side where the
scanner was). ``"none"`` keeps the PCA solver's sign (Open3D's behaviour, not rotation
invariant); ``"centroid"`` orients towards the whole cloud's centroid.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes, sha256_file, to_jsonable
from minegeo._validate import as_points, is_permutation
from minegeo.errors import FileFormatError, InputError, TooFewPointsError
from minegeo.io.jsonio import load_json_text
from minegeo.io.npzstore import array_digest as _array_digest
from minegeo.io.npzstore import crc_failure, open_store
from minegeo.io.npzstore import json_digest as _json_digest
from minegeo.io.npzstore import member_header as _member_header
from minegeo.io.types import PointCloud
from minegeo.localize._progress import FEATURE_STEPS, StepTimings, announce
from minegeo.localize.params import FAST_FEATURES, FeatureParams, LocalizeParams, PrepareParams

__all__ = [
    "FeatureParams",
    "PrepareParams",
    "PreparedMap",
    "prepare_map",
    "prepare_map_file",
    "MemoryLimitError",
    "prepare_cloud_features",
    "orient_normals_void",
    "params_hash",
    "cache_path",
    "PREPARED_FORMAT",
    "PREPARED_VERSION",
    "FAST_FEATURES",
    "profile_name",
    "is_georeferenced",
]

log = logging.getLogger(__name__)

#: ``format`` tag stored in a prepared-map file.
PREPARED_FORMAT = "minegeo-prepared-map"
#: Current file format version (increase on any incompatible change).
PREPARED_VERSION = 1

#: Format of the search structures a prepared file may also hold (``meta["indexes"]``).
INDEX_VERSION = 1
INDEX_PREFIX = "index__"
#: Nearest neighbours of the PCA normals of the ICP target.
ICP_NORMAL_NN = 20

#: Hash of the integrity record (``meta["integrity"]``) of a prepared-map file.
INTEGRITY_ALGORITHM = "sha256"
#: The map's own arrays: a damaged one makes the file unusable (the search structures are
#: optional: a damaged one is rebuilt).
CORE_ARRAYS = ("points", "normals", "features", "icp_points", "icp_normals", "work_origin")
#: FPFH descriptor length (Rusu 2009: 3 angles x 11 bins).
FPFH_DIM = 33
#: Largest hash table (log2 of its slots) a stored search structure may announce.
_MAX_LOG2_SLOTS = 40
_REPREPARE = "prepare the map again with minegeo prepare-map"


def params_hash(params: PrepareParams) -> str:
    """SHA-256 (hex) of the canonical JSON of ``params`` plus the file format version."""
    blob = json.dumps({"v": PREPARED_VERSION, "params": to_jsonable(asdict(params))}, sort_keys=True)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def _params_from_dict(d: dict) -> PrepareParams:
    f = dict(d["features"])
    return PrepareParams(voxel_size_m=d.get("voxel_size_m"), octree_level=d.get("octree_level"),
                         features=FeatureParams(**f), icp_voxel_size_m=d.get("icp_voxel_size_m"))


# ----------------------------------------------------------------------------- features
def orient_normals_void(points: np.ndarray, normals: np.ndarray, radius_m: float) -> np.ndarray:
    """Flip normals to point towards the local centroid (the drift's air side).

    For every point ``p_i`` the centroid ``c_i`` of all points in the cube of half-edge
    ``radius_m`` around the grid cell of ``p_i`` (cells of edge ``radius_m``, 3x3x3 block) is
    computed; ``n_i`` is flipped when ``n_i · (c_i − p_i) < 0``. Rotation invariant up to the
    cube's shape; O(n log n).

    Returns a new (n, 3) array.
    """
    P = points
    N = np.array(normals, dtype=np.float64, copy=True)
    if P.shape[0] == 0:
        return N
    cell = float(radius_m)
    key3 = np.floor((P - P.min(axis=0)) / cell).astype(np.int64) + 1
    dims = key3.max(axis=0) + 2
    key = (key3[:, 2] * dims[1] + key3[:, 1]) * dims[0] + key3[:, 0]
    uk, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    sums = np.zeros((uk.size, 3))
    np.add.at(sums, inv, P)
    cnt = np.bincount(inv, minlength=uk.size).astype(np.float64)
    bs = np.zeros((uk.size, 3))
    bc = np.zeros(uk.size)
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                nk = uk + (dz * dims[1] + dy) * dims[0] + dx
                j = np.searchsorted(uk, nk)
                j = np.minimum(j, uk.size - 1)
                hit = uk[j] == nk
                bs[hit] += sums[j[hit]]
                bc[hit] += cnt[j[hit]]
    c = bs[inv] / bc[inv, None]
    flip = np.einsum("ij,ij->i", N, c - P) < 0.0
    N[flip] *= -1.0
    return N


def _downsample(points: np.ndarray, voxel_size_m, octree_level) -> np.ndarray:
    from minegeo.geometry import octree_downsample, voxel_downsample

    if octree_level is not None:
        return np.ascontiguousarray(octree_downsample(points, int(octree_level)).points)
    return np.ascontiguousarray(voxel_downsample(points, float(voxel_size_m)).points)


def prepare_cloud_features(points, voxel_size_m, octree_level, features: FeatureParams, timings: dict | None = None):
    """Downsample (Sec. 2.2), estimate normals ([Baek2022 Eq. 2]) and FPFH ([Baek2022 Eqs. 3-6]) of one cloud.

    Parameters
    ----------
    points : (n, 3) array_like
        Cloud (m), any frame with moderate coordinates.
    voxel_size_m, octree_level
        Downsampling (octree level wins when given).
    features : FeatureParams
    timings : dict, optional
        Receives ``downsample``, ``normals``, ``fpfh`` seconds.

    Returns
    -------
    (points_down (m, 3), normals (m, 3), fpfh (m, 33))
    """
    t = {} if timings is None else timings
    P = as_points(points, "points", min_points=1)
    t0 = time.perf_counter()
    D = _downsample(P, voxel_size_m, octree_level)
    t["downsample"] = time.perf_counter() - t0
    N, F = _normals_fpfh(D, features, t)
    return D, N, F


def _normals_fpfh(D: np.ndarray, features: FeatureParams, t: dict):
    """Normals ([Baek2022 Eq. 2]) and FPFH ([Baek2022 Eqs. 3-6]) of a downsampled cloud (timings into ``t``)."""
    from minegeo.features import FPFHParams, compute_fpfh
    from minegeo.geometry import NormalParams, estimate_normals

    t0 = time.perf_counter()
    fp = features
    orient = None if fp.orientation == "centroid" else "none"
    nr = estimate_normals(D, NormalParams(radius_m=fp.normal_radius_m, max_nn=int(fp.normal_max_nn)),
                          orient_towards=orient)
    N = nr.normals
    if fp.orientation == "void":
        N = orient_normals_void(D, N, fp.orientation_radius_m)
    t["normals"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if D.shape[0] >= 2:
        F = compute_fpfh(D, N, FPFHParams(radius_m=fp.fpfh_radius_m, max_nn=int(fp.fpfh_max_nn),
                                          weight=fp.fpfh_weight)).features
    else:
        F = np.zeros((D.shape[0], 33))
    t["fpfh"] = time.perf_counter() - t0
    return np.ascontiguousarray(N), np.ascontiguousarray(F)


# ----------------------------------------------------------------------------- the prepared map
@dataclass
class PreparedMap:
    """A map ready for :func:`minegeo.localize.localize_scan`.

    Attributes
    ----------
    points : (m, 3) float64
        Downsampled map points in the ``work`` frame (map frame minus ``work_origin``), m.
    normals : (m, 3) float64
        Unit normals (oriented by ``params.features.orientation``).
    features : (m, 33) float64
        FPFH descriptors.
    icp_points : (k, 3) float64
        The ICP target (``params.icp_voxel_size_m`` voxel centroids, or every map point), work frame.
    icp_normals : (k, 3) float64
        PCA normals of ``icp_points`` (20 nearest neighbours), for point-to-plane ICP and the
        pose covariance.
    work_origin : (3,) float64
        Map-frame coordinates of the ``work`` frame's origin, m.
    params : PrepareParams
    params_hash : str
        :func:`params_hash` of ``params``.
    georef : dict or None
        The map's georeferencing record (``GeorefResult`` as a dict, from the sidecar) or
        None for a map without one; then ``crs`` is the cloud's own CRS, if any.
    crs : str or None
    source : dict
        ``{"path", "sha256", "n_points", "kind"}`` of the map file it was prepared from.
    timings_s : dict
        Seconds per preparation stage.
    """

    points: np.ndarray
    normals: np.ndarray
    features: np.ndarray
    icp_points: np.ndarray
    icp_normals: np.ndarray
    work_origin: np.ndarray
    params: PrepareParams
    params_hash: str
    georef: dict | None = None
    crs: str | None = None
    source: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    _kdtree: object = field(default=None, repr=False, compare=False)
    _georef_obj: object = field(default=None, repr=False, compare=False)
    _gicp_cache: dict = field(default_factory=dict, repr=False, compare=False)
    _occ_cache: dict = field(default_factory=dict, repr=False, compare=False)
    _feature_index: object = field(default=None, repr=False, compare=False)
    # search structures read from a file and checked, expanded on first use (``_restore_indexes``)
    _packed: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        # validated once here, so localization can search the map without re-scanning it
        # (``check_target=False``); the arrays must not be modified afterwards
        self.points = as_points(self.points, "prepared map points", min_points=1)
        m = self.points.shape[0]
        self.normals = as_points(self.normals, "prepared map normals", min_points=1)
        f = np.asarray(self.features)
        if f.ndim != 2:
            raise InputError(f"prepared map features must have shape (m, dim), got {f.shape}")
        self.features = as_points(f, "prepared map features", dim=f.shape[1], min_points=1)
        self.icp_points = as_points(self.icp_points, "prepared map ICP points", min_points=1)
        self.icp_normals = as_points(self.icp_normals, "prepared map ICP normals", min_points=1)
        self.work_origin = np.asarray(self.work_origin, dtype=np.float64)
        if (self.normals.shape[0] != m or self.features.shape[0] != m
                or self.icp_normals.shape[0] != self.icp_points.shape[0]):
            raise InputError("prepared map arrays disagree in length (points, normals, features; ICP points, normals)")
        if self.work_origin.shape != (3,) or not np.isfinite(self.work_origin).all():
            raise InputError(f"prepared map work_origin must be a finite 3-vector, got {self.work_origin!r}")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def kdtree(self):
        """pykdtree KD-tree over ``icp_points`` (built once per process, then reused)."""
        if self._kdtree is None:
            from pykdtree.kdtree import KDTree

            self._kdtree = KDTree(self.icp_points)
        return self._kdtree

    @property
    def feature_index(self):
        """Descriptor search tree over ``features`` (:func:`minegeo.registration.correspondences.build_feature_index`),
        built once per process and reused by every scan's RANSAC."""
        if self._feature_index is None:
            from minegeo.registration.correspondences import build_feature_index

            self._feature_index = build_feature_index(self.features)
        return self._feature_index

    def occupancy(self, params):
        """Occupancy table and floor anchors for the correlative search
        (:func:`minegeo.localize.correlative.map_occupancy`), built once per process and per
        cell setting."""
        from minegeo.localize.correlative import map_occupancy

        key = (float(params.cell_size_m), int(params.dilation_cells), float(params.anchor_max_tilt_deg))
        if key not in self._occ_cache:
            packed = self._packed.pop(("occupancy", key), None)
            if packed is not None:  # stored in the file: only its empty slots are added back
                self._occ_cache[key] = _expand_occupancy(packed)
            else:
                self._occ_cache[key] = map_occupancy(self.icp_points, self.points, self.normals, params)
        return self._occ_cache[key]

    def build_indexes(self, params=None, progress=None) -> dict:
        """Build every per-process search structure that :func:`localize_scan` with ``params``
        (:class:`LocalizeParams`, default the defaults) will use, so the first scan does not pay
        for them: the KD-trees of the ICP cloud, the descriptor tree, and for levelled scans
        with the correlative search its occupancy bitmap and thinned screening cloud (GICP:
        the target covariances). Returns the seconds spent per structure (0 when cached).
        ``progress(name)`` (optional) is called as each structure starts."""
        p = LocalizeParams() if params is None else params
        out = {}

        def _t(name, fn):
            announce(progress, name)
            t0 = time.perf_counter()
            fn()
            out[name] = time.perf_counter() - t0

        _t("kdtree", lambda: self.kdtree)
        _t("target_index", self.target_index)
        _t("feature_index", lambda: self.feature_index)
        if p.ransac.model == "levelled" and p.correlative != "off":
            _t("occupancy", lambda: self.occupancy(p.correlative_params))
            cp = p.correlative_params
            _t("screen_target", lambda: self.screen_target(cp.screen_voxel_size_m))
            if cp.screen_grid and cp.screen_voxel_size_m is not None:
                _t("screen_grid", lambda: self.screen_grid(cp.screen_voxel_size_m))
        if p.icp_method == "gicp":
            from minegeo.registration import GICPParams

            gp = GICPParams(max_correspondence_distance_m=float(p.icp_max_correspondence_m),
                            max_iterations=int(p.icp_max_iterations))
            _t("gicp_target", lambda: self.gicp_target(gp))
        return out

    def screen_target(self, voxel_size_m):
        """``(GatedKDTree, points, normals)`` of the ICP cloud thinned to one point per voxel of
        edge ``voxel_size_m`` (centroid, and mean normal renormalised; voxels whose normals
        disagree, mean length < 0.5, e.g. both faces of a thin railing, are left out), for the
        correlative search's screening stage. Built once per process and voxel size;
        ``None`` gives the full ICP cloud."""
        if voxel_size_m is None:
            return self.target_index(), self.icp_points, self.icp_normals
        key = ("screen", float(voxel_size_m))
        if key not in self._gicp_cache:
            from minegeo.geometry import voxel_downsample
            from minegeo.registration import build_target_index

            v = voxel_downsample(self.icp_points, float(voxel_size_m), normals=self.icp_normals)
            length = np.linalg.norm(v.normals, axis=1)
            ok = length >= 0.5
            if not ok.any():  # nothing coherent (degenerate map): screen on the full cloud
                self._gicp_cache[key] = (self.target_index(), self.icp_points, self.icp_normals)
            else:
                pts = np.ascontiguousarray(v.points[ok])
                nrm = np.ascontiguousarray(v.normals[ok] / length[ok, None])
                self._gicp_cache[key] = (build_target_index(pts), pts, nrm)
        return self._gicp_cache[key]

    def screen_grid(self, voxel_size_m):
        """Nearest-point lookup grid over :meth:`screen_target`'s points, cells of edge
        ``voxel_size_m``, reaching the screening stage's widest gate
        (:func:`minegeo.localize._kernels.build_nearest_grid`): ``(block_keys, nearest,
        log2_blocks, cell_m)``, built once per process and voxel size (~1 s and ~70 MB for the
        paper map at 0.5 m)."""
        from minegeo.localize import _kernels as LK

        key = ("screen_grid", float(voxel_size_m))
        if key not in self._gicp_cache and key in self._packed:  # stored: add back the empty slots
            keys, rows, log2, c = self._packed.pop(key)
            nearest = np.full((keys.shape[0], 512), -1, dtype=np.int32)
            nearest[keys != -1] = rows
            self._gicp_cache[key] = (keys, nearest, log2, c)
        if key not in self._gicp_cache:
            _, Qs, _ = self.screen_target(voxel_size_m)
            c = float(voxel_size_m)
            band, log2 = _grid_log2_start(Qs.shape[0], c)
            while True:
                keys, nearest, nb = LK.build_nearest_grid(np.ascontiguousarray(Qs), c, band, log2)
                if nb <= (1 << log2) // 2:
                    break
                log2 += 1
            self._gicp_cache[key] = (keys, nearest, log2, c)
        return self._gicp_cache[key]

    def target_index(self):
        """Numba gated KD-tree over ``icp_points`` (:func:`minegeo.registration.build_target_index`),
        built once per process (shared with :meth:`gicp_target`)."""
        if "index" not in self._gicp_cache:
            from minegeo.registration import build_target_index

            self._gicp_cache["index"] = build_target_index(self.icp_points)
        return self._gicp_cache["index"]

    def gicp_target(self, params):
        """``(covariances (k, 3, 3), KD-tree)`` of ``icp_points`` for GICP, computed once per
        process and per (ε, neighbours, covariance mode) from the stored ICP normals
        (plane covariances ``I − (1 − ε) n nᵀ``, [Ren2019 Eqs. 2-3])."""
        from minegeo.registration import estimate_gicp_covariances

        key = (float(params.epsilon), int(params.covariance_neighbours), str(params.covariance_mode))
        if key not in self._gicp_cache:
            self._gicp_cache[key] = estimate_gicp_covariances(self.icp_points, params, normals=self.icp_normals)
        return self._gicp_cache[key], self.target_index()

    @property
    def georef_result(self):
        """The :class:`~minegeo.georef.GeorefResult` or None."""
        if self.georef is None:
            return None
        if self._georef_obj is None:
            from minegeo.georef import GeorefResult

            self._georef_obj = GeorefResult.from_dict(self.georef)
        return self._georef_obj

    def points_map(self) -> np.ndarray:
        """Downsampled points in the ``map`` frame (m)."""
        return self.points + self.work_origin

    def check_params(self, params: PrepareParams | FeatureParams) -> None:
        """Raise :class:`InputError` if ``params`` differ from those the map was prepared with.

        The message names the ``--profile`` the map was prepared with and the one asked (or says
        that either is not a profile's values, e.g. after ``--voxel``), the differing values, and
        the two ways out: the map's profile for this run, or the map prepared again."""
        mine = self.params.features if isinstance(params, FeatureParams) else self.params
        if params != mine:
            a, b = to_jsonable(asdict(mine)), to_jsonable(asdict(params))
            diff = "; ".join(f"{k}: map {va!r}, this run {vb!r}" for k, va, vb in _diff(a, b))
            have, want = profile_name(mine), profile_name(params)
            other = "values of no profile (e.g. --voxel or --octree-level)"
            have_t = f"the values of --profile {have}" if have else other
            want_t = f"the values of --profile {want}" if want else other
            if have and want:
                todo = (f"run again with --profile {have}, or prepare the map again with "
                        f"'minegeo prepare-map --profile {want}'")
            elif have:
                todo = (f"run again with --profile {have} and without --voxel / --octree-level, or prepare the map "
                        "again with 'minegeo prepare-map' and this run's --profile / --voxel")
            else:
                todo = ("run again with the --profile / --voxel the map was prepared with (see its .json record), "
                        "or prepare the map again with 'minegeo prepare-map' and this run's --profile / --voxel")
            raise InputError(f"the prepared map was prepared with {have_t} and this run asks for {want_t} ({diff}): "
                             f"{todo}")

    # -- files --------------------------------------------------------------------------
    def save(self, path, *, indexes: bool = True) -> Path:
        """Write the prepared map to ``path`` (``.npz``, uncompressed, no pickles), atomically.

        The file holds the arrays plus a JSON ``meta`` string with ``format``, ``version``,
        ``params``, ``params_hash``, ``georef``, ``crs``, ``source`` and ``integrity``. With
        ``indexes`` it also holds every search structure built so far (:meth:`build_indexes`: the
        Numba KD-trees of the ICP cloud and of the thinned screening cloud, the descriptor tree,
        the occupancy bitmap, the lookup grid; ``meta["indexes"]``), which :meth:`load` restores
        instead of rebuilding them (~5 s for the 6.5 km paper map). Only pykdtree's tree is rebuilt.

        ``meta["integrity"]`` holds the SHA-256 of every stored array (of its dtype, shape and
        bytes, :func:`_array_digest`), a ``manifest`` hash of the meta (without the search
        structures' records) together with the six map arrays' hashes, and per search
        structure a hash of its meta record together with its arrays' hashes.
        """
        import io

        meta = {
            "format": PREPARED_FORMAT,
            "version": PREPARED_VERSION,
            "params": to_jsonable(asdict(self.params)),
            "params_hash": self.params_hash,
            "georef": to_jsonable(self.georef),
            "crs": self.crs,
            "source": to_jsonable(self.source),
            "timings_s": to_jsonable(self.timings_s),
        }
        arrays = {"points": self.points, "normals": self.normals, "features": self.features,
                  "icp_points": self.icp_points, "icp_normals": self.icp_normals, "work_origin": self.work_origin}
        if indexes:
            extra, meta["indexes"] = self._index_payload()
            arrays.update(extra)
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        meta = json.loads(json.dumps(meta, sort_keys=True))  # hash exactly what load reads back
        meta["integrity"] = _integrity_record(meta, arrays)
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
        return atomic_write_bytes(path, buf.getvalue())

    def _index_payload(self) -> tuple[dict, dict]:
        """Arrays (``index__*`` keys) and meta record of the search structures built so far
        (and of those read from a file and not used yet, as they were stored)."""
        arrays: dict = {}
        entries: list = []

        def put(name, d):
            for k, v in d.items():
                arrays[f"{INDEX_PREFIX}{name}__{k}"] = np.asarray(v)

        if "index" in self._gicp_cache:
            put("target", self._gicp_cache["index"].arrays())
            entries.append({"kind": "target_kdtree", "name": "target"})
        if self._feature_index is not None:
            fi = self._feature_index
            t = fi.tree
            d = {"rows": fi.rows}
            if not t.brute:  # the leaf storage is packed again on loading
                d.update(mu=t.mu, V=t.V, perm=t.perm, lstart=t.lstart)
            put("feature", d)
            entries.append({"kind": "feature_index", "name": "feature", "drop_zero_features": fi.drop_zero_features,
                            "brute": bool(t.brute), "rb": float(t.rb)})
        occs = [(key, occ.block_keys, occ.bits[occ.block_keys != -1], occ.anchors, occ.log2_blocks, occ.n_cells,
                 occ.n_blocks, occ.build_s) for key, occ in self._occ_cache.items()]
        occs += [(key[1], pk["keys"], pk["rows"], pk["anchors"], pk["log2"], pk["n_cells"], pk["n_blocks"],
                  pk["build_s"]) for key, pk in self._packed.items() if key[0] == "occupancy"]
        for i, (key, keys, rows, anchors, log2, n_cells, n_blocks, build_s) in enumerate(occs):
            name = f"occupancy{i}"
            put(name, {"block_keys": keys, "bits": rows, "anchors": anchors})  # used slots' rows only (others: 0)
            entries.append({"kind": "occupancy", "name": name, "key": list(key), "log2_blocks": log2,
                            "n_cells": n_cells, "n_blocks": n_blocks, "build_s": build_s})
        grids = []
        for i, (key, val) in enumerate(self._gicp_cache.items()):
            if not isinstance(key, tuple) or key[0] not in ("screen", "screen_grid"):
                continue
            name = f"{key[0]}{i}"
            if key[0] == "screen":
                index, pts, nrm = val
                full = pts is self.icp_points
                put(name, {} if full else {"points": pts, "normals": nrm, **{f"tree_{k}": v for k, v in index.arrays().items()}})
                entries.append({"kind": "screen_target", "name": name, "voxel_size_m": key[1], "full": full})
            else:
                keys, nearest, log2, c = val
                grids.append((name, key[1], keys, nearest[keys != -1], log2, c))  # used slots' rows (others: -1)
        n = len(self._gicp_cache)
        grids += [(f"screen_grid{n + j}", key[1], *pk) for j, (key, pk) in
                  enumerate((k, v) for k, v in self._packed.items() if k[0] == "screen_grid")]
        for name, v, keys, rows, log2, c in grids:  # after every screening cloud (load needs it first)
            put(name, {"keys": keys, "nearest": rows})
            entries.append({"kind": "screen_grid", "name": name, "voxel_size_m": v, "log2_blocks": log2, "cell_m": c})
        return arrays, {"version": INDEX_VERSION, "entries": entries}

    def _restore_indexes(self, z: dict, record, path, skip: dict | None = None) -> list[str]:
        """Check the stored search structures (``z``: the file's ``index__*`` arrays) and put them
        back in the caches.

        Every stored integer used as an index (KD-tree order, node ranges and children, descriptor
        rows, order and leaves, hash-table slots and keys, lookup-grid rows) is range-checked,
        every size announced in the meta (``log2_blocks``, ``n_cells``, ``n_blocks``) must be the
        one the builder would have chosen for the stored arrays and the map's point counts, and
        every dtype and shape must be the builder's, *before* anything is allocated from them:
        the Numba kernels do not bounds-check. The occupancy bitmap and the lookup grid are
        stored without their empty slots; they are expanded on first use (:meth:`occupancy`,
        :meth:`screen_grid`), i.e. only for the settings a localization asks for, so the
        expansion is never larger than building them would be.

        A structure that fails (or is named in ``skip``: it failed its integrity hash) is
        skipped with a warning and rebuilt when needed: the map itself is intact. Returns the
        kinds restored.
        """
        from minegeo.registration.correspondences import FeatureIndex, RowTree, row_tree_is_brute

        skip = skip or {}
        restored: list[str] = []
        if not isinstance(record, dict) or record.get("version") != INDEX_VERSION \
                or not isinstance(record.get("entries"), list):
            log.warning("%s: stored search structures of another format version: rebuilding them", path)
            return restored
        k = self.icp_points.shape[0]
        for e in record["entries"]:
            name = e.get("name") if isinstance(e, dict) else None
            if not isinstance(name, str):
                log.warning("%s: malformed search-structure record %.80r: it will be rebuilt", path, e)
                continue
            if name in skip:
                log.warning("%s: stored search structure %r not usable (%s): it will be rebuilt", path, name,
                            skip[name])
                continue
            pre = f"{INDEX_PREFIX}{name}__"
            try:
                a = {key[len(pre):]: v_ for key, v_ in z.items() if key.startswith(pre)}
                kind = e["kind"]
                if kind == "target_kdtree":
                    self._gicp_cache["index"] = _restore_kdtree(self.icp_points, a)
                elif kind == "feature_index":
                    dz, brute = _flag(e, "drop_zero_features"), _flag(e, "brute")
                    rows = _expected_feature_rows(self.features, dz)
                    if rows.size == 0:
                        raise ValueError("no descriptor row to search")
                    if not np.array_equal(_stored(a, "rows", np.int64, rows.shape), rows):
                        raise ValueError("descriptor rows are not the map's searchable rows")
                    B = np.ascontiguousarray(self.features[rows])
                    if brute != row_tree_is_brute(B.shape[0]):
                        raise ValueError("descriptor tree kind does not match the number of rows")
                    tree = RowTree(B=B, brute=True) if brute else _restore_row_tree(B, a, e.get("rb"))
                    self._feature_index = FeatureIndex(features=self.features, drop_zero_features=dz, rows=rows,
                                                       tree=tree)
                elif kind == "occupancy":
                    key, packed = _check_occupancy(a, e, k, self.points, self.normals)
                    self._packed[("occupancy", key)] = packed
                elif kind == "screen_target":
                    v = _number(e, "voxel_size_m", positive=True)
                    if _flag(e, "full"):
                        self._gicp_cache[("screen", v)] = (self.target_index(), self.icp_points, self.icp_normals)
                    else:
                        pts = _stored(a, "points", np.float64, ndim=2)
                        if not 1 <= pts.shape[0] <= k:
                            raise ValueError(f"{pts.shape[0]} screening points for a map of {k} ICP points")
                        pts = as_points(pts, "screening points")
                        nrm = as_points(_stored(a, "normals", np.float64, pts.shape), "screening normals")
                        tree = _restore_kdtree(pts, a, "tree_")
                        self._gicp_cache[("screen", v)] = (tree, pts, nrm)
                elif kind == "screen_grid":
                    v = _number(e, "voxel_size_m", positive=True)
                    if _number(e, "cell_m", positive=True) != v:
                        raise ValueError("lookup grid cell differs from its voxel size")
                    if ("screen", v) not in self._gicp_cache:
                        raise ValueError("lookup grid stored without its screening cloud")
                    n_s = self._gicp_cache[("screen", v)][1].shape[0]
                    log2 = _integer(e, "log2_blocks", 10, _MAX_LOG2_SLOTS)
                    keys = _stored(a, "keys", np.int64, (1 << log2,))
                    nb = int(np.count_nonzero(keys != -1))
                    rows = _stored(a, "nearest", np.int32, (nb, 512))
                    if rows.size and (rows.min() < -1 or rows.max() >= n_s):
                        raise ValueError("lookup grid rows out of range")
                    if log2 != _table_log2(_grid_log2_start(n_s, v)[1], nb):
                        raise ValueError(f"lookup grid size 2^{log2} is not the one built for {nb} blocks")
                    _check_hash_table(keys, log2, "lookup grid")
                    self._packed[("screen_grid", v)] = (keys, rows, log2, v)
                else:
                    raise ValueError(f"unknown kind {kind!r}")
                restored.append(kind)
            except (KeyError, ValueError, TypeError, IndexError, OverflowError, InputError) as exc:
                log.warning("%s: stored search structure %r not usable (%s): it will be rebuilt", path, name, exc)
        return restored

    @classmethod
    def load(cls, path, params: PrepareParams | None = None) -> PreparedMap:
        """Read a file written by :meth:`save`, checking all of it.

        The map's own arrays must be float64 of consistent shapes and finite, the meta fields of
        the right types, and every array and the meta must match the integrity record written
        by :meth:`save` (SHA-256 of each array's dtype, shape and bytes; of the meta). A damaged
        map array or meta is a :class:`FileFormatError`; a damaged search structure (hash or
        range checks, :meth:`_restore_indexes`) is skipped with a warning and rebuilt when
        needed. The archive itself must be an uncompressed ``.npz`` whose members hold exactly
        the bytes their headers announce, so nothing larger than the file is allocated on
        reading it.

        A file written before the integrity record existed (format version 1 without
        ``meta["integrity"]``) is refused with a request to prepare the map again: the
        record is an addition that older readers ignore, so the format version stays 1.

        Parameters
        ----------
        path : str or Path
        params : PrepareParams, optional
            If given, the file's parameters must equal these (else :class:`InputError`).

        Raises
        ------
        FileFormatError
            Not a prepared map, a newer format version, no integrity record, map arrays or meta
            that are malformed, non-finite or do not match their integrity hashes, or a
            parameter hash that does not match the stored parameters.
        InputError
            ``params`` given and different from the file's.
        """
        p = Path(path)
        meta, arrays, index_arrays, bad = _read_prepared_file(p)
        _check_meta(meta, p)
        try:
            stored = _params_from_dict(meta["params"])
        except (KeyError, TypeError, ValueError, AttributeError, InputError) as exc:
            raise FileFormatError(p, f"bad parameter record ({exc})") from None
        if params_hash(stored) != meta.get("params_hash"):
            raise FileFormatError(p, "parameter hash does not match the stored parameters (file edited or corrupted)")
        m = arrays["points"].shape[0]
        if (arrays["points"].shape != (m, 3) or arrays["normals"].shape != (m, 3)
                or arrays["features"].shape != (m, FPFH_DIM)
                or arrays["work_origin"].shape != (3,) or arrays["icp_points"].ndim != 2
                or arrays["icp_points"].shape[1] != 3 or arrays["icp_normals"].shape != arrays["icp_points"].shape):
            raise FileFormatError(p, "array shapes are inconsistent")
        try:
            pm = cls(points=arrays["points"], normals=arrays["normals"], features=arrays["features"],
                     icp_points=arrays["icp_points"], icp_normals=arrays["icp_normals"],
                     work_origin=arrays["work_origin"], params=stored, params_hash=meta["params_hash"],
                     georef=meta.get("georef"), crs=meta.get("crs"), source=meta.get("source") or {},
                     timings_s=meta.get("timings_s") or {})
        except InputError as exc:  # NaN/inf or inconsistent arrays in the file
            raise FileFormatError(p, f"corrupted arrays ({exc})") from None
        skip = _verify_integrity(meta, arrays, index_arrays, bad, p)
        if pm.georef is not None:
            try:
                pm.georef_result  # noqa: B018 - parsed now, so a bad record is a file error, not a late traceback
            except InputError as exc:
                raise FileFormatError(p, f"bad georeferencing record ({exc})") from None
        if params is not None:
            pm.check_params(params)
        if "indexes" in meta:
            pm._restore_indexes(index_arrays, meta["indexes"], p, skip)
        return pm


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


def _restore_kdtree(Q: np.ndarray, a: dict, prefix: str = ""):
    """A stored :class:`~minegeo.kernels.kdtree.GatedKDTree` over ``Q`` (``k`` points):
    dtypes and shapes of the builder's, at most ``2 k`` nodes, point order within ``[0, k)``
    (checked before :func:`~minegeo._validate.is_permutation` counts it), then
    ``GatedKDTree.from_arrays`` (permutation, node ranges, children, depth)."""
    from minegeo.kernels.kdtree import GatedKDTree

    k = Q.shape[0]
    idx = _stored(a, prefix + "idx", np.int64, (k,))
    start = _stored(a, prefix + "start", np.int64, ndim=1)
    n = start.shape[0]
    if not 1 <= n <= 2 * k:
        raise ValueError(f"KD-tree of {n} nodes over {k} points")
    nodes = {name: _stored(a, prefix + name, dt, (n,)) for name, dt in
             (("end", np.int64), ("dim", np.int64), ("split", np.float64), ("left", np.int64), ("right", np.int64))}
    depth = _stored(a, prefix + "depth", np.int64, (1,))
    _in_range(idx, 0, k, "KD-tree point order")
    _in_range(depth, 0, n, "KD-tree depth")
    if not np.isfinite(nodes["split"]).all():
        raise ValueError("KD-tree split values are not finite")
    return GatedKDTree.from_arrays(Q, {"idx": idx, "start": start, "depth": depth, **nodes})


def _expected_feature_rows(F: np.ndarray, drop_zero_features: bool) -> np.ndarray:
    """The rows :func:`~minegeo.registration.correspondences.build_feature_index` searches."""
    return np.flatnonzero(np.any(F != 0.0, axis=1)) if drop_zero_features else np.arange(F.shape[0])


def _restore_row_tree(B: np.ndarray, a: dict, rb):
    """The descriptor tree over ``B`` from its stored rotation and leaf partition (the leaf
    storage is packed again from ``B``, so it cannot disagree with the map's descriptors):
    rotation of the builder's shape and finite, order a permutation (range-checked first),
    exactly ``ceil(n / FEATURE_LEAF)`` leaves of at most ``FEATURE_LEAF`` rows, and the search
    radius bound ``rb`` the one of ``B`` and the stored mean."""
    from minegeo.registration.correspondences import FEATURE_LEAF, FEATURE_ROT, row_tree_from_partition

    n, dim = B.shape
    L = FEATURE_LEAF
    mu = _stored(a, "mu", np.float64, (dim,))
    V = _stored(a, "V", np.float64, (dim, min(dim, FEATURE_ROT)))
    perm = _stored(a, "perm", np.int64, (n,))
    lstart = _stored(a, "lstart", np.int64, ((n + L - 1) // L + 1,))
    if not (np.isfinite(mu).all() and np.isfinite(V).all()):
        raise ValueError("descriptor tree rotation is not finite")
    _in_range(perm, 0, n, "descriptor tree order")
    if not is_permutation(perm, n):
        raise ValueError("descriptor tree order is not a permutation of the rows")
    sizes = np.diff(lstart)
    if lstart[0] != 0 or lstart[-1] != n or sizes.min() < 0 or sizes.max() > L:
        raise ValueError("descriptor tree leaves out of range")
    if not _is_number(rb) or float(rb) != float(np.sqrt(np.max(np.einsum("ij,ij->i", B - mu, B - mu)))):
        raise ValueError("descriptor tree radius bound is not the one of the map's descriptors")
    return row_tree_from_partition(B, mu, V, perm, lstart, float(rb))


def _table_log2(log2_start: int, n_blocks: int) -> int:
    """Table size (log2 of its slots) the builders end with: the first from ``log2_start`` that
    keeps ``n_blocks`` at most half full."""
    log2 = log2_start
    while n_blocks > (1 << log2) // 2:
        log2 += 1
    return log2


def _grid_log2_start(n_points: int, cell_m: float) -> tuple[int, int]:
    """``(band, first log2)`` of :meth:`PreparedMap.screen_grid` over ``n_points`` points."""
    from minegeo.localize.correlative import SCREEN_GATES_M

    band = int(math.ceil(max(SCREEN_GATES_M) / cell_m))
    n_cells = n_points * (2 * band + 1) ** 3
    return band, max(10, int(math.ceil(math.log2(max(1, n_cells) / 512 / 8))) + 1)


def _occupancy_log2_start(n_cells: int, dilation: int) -> int:
    """First log2 of :func:`minegeo.localize.correlative.map_occupancy` (same formula)."""
    return max(10, int(math.ceil(math.log2(max(1, n_cells) * (1 + 2 * dilation) / 32))) + 1)


def _hash_home(keys: np.ndarray, log2: int) -> np.ndarray:
    """Home slots of ``keys`` in a table of ``2^log2`` slots: :func:`minegeo.kernels.hashgrid.hash_slot`
    vectorised (top ``log2`` bits of ``key * HASH_MULT`` modulo 2^64)."""
    from minegeo.kernels.hashgrid import HASH_MULT

    with np.errstate(over="ignore"):
        return ((keys.astype(np.uint64) * HASH_MULT) >> np.uint64(64 - log2)).astype(np.int64)


def _check_hash_table(keys: np.ndarray, log2: int, what: str) -> None:
    """``ValueError`` unless ``keys`` (``2^log2`` int64, -1 = empty) is a table the kernels'
    linear probing (:func:`minegeo.localize._kernels.block_slot`) can use: an empty slot exists
    (a probe ends), used keys are valid block keys (non-negative), distinct, and each is
    reached from its hash slot through used slots only."""
    cap = keys.shape[0]
    mask = cap - 1
    used = keys != -1
    free = np.flatnonzero(~used)
    if free.size == 0:
        raise ValueError(f"{what} hash table has no empty slot")
    slots = np.flatnonzero(used)
    k = keys[slots]
    if k.size == 0:
        return
    if int(k.min()) < 0 or np.unique(k).size != k.size:
        raise ValueError(f"{what} hash table holds invalid or repeated keys")
    home = _hash_home(k, log2)
    pos = np.arange(cap)
    r = np.roll(used, -free[0])  # rotated so that slot 0 is empty
    run = pos - np.maximum.accumulate(np.where(r, 0, pos)) - 1  # used slots before each in its run
    if np.any(((slots - home) & mask) > run[(slots - free[0]) & mask]):
        raise ValueError(f"{what} hash table: a key is not where its probe finds it")


def _check_occupancy(a: dict, e: dict, k: int, points: np.ndarray, normals: np.ndarray):
    """Checks of a stored :class:`~minegeo.localize.correlative.MapOccupancy` (``k`` ICP points):
    ``((cell, dilation, tilt), packed)`` with the used slots' rows, expanded on first use."""
    key = e["key"]
    if not isinstance(key, list) or len(key) != 3:
        raise ValueError("occupancy key must be [cell, dilation, tilt]")
    kd = dict(zip(("cell", "dilation", "tilt"), key, strict=True))
    cell, dil, tilt = _number(kd, "cell", positive=True), _integer(kd, "dilation", 0, 1 << 20), _number(kd, "tilt")
    log2 = _integer(e, "log2_blocks", 10, _MAX_LOG2_SLOTS)
    n_cells = _integer(e, "n_cells", 1, k)
    nb = _integer(e, "n_blocks", 1, 1 << (log2 - 1))
    keys = _stored(a, "block_keys", np.int64, (1 << log2,))
    if int(np.count_nonzero(keys != -1)) != nb:
        raise ValueError("occupancy block count does not match its table")
    rows = _stored(a, "bits", np.uint64, (nb, 16))
    if log2 != _table_log2(_occupancy_log2_start(n_cells, dil), nb):
        raise ValueError(f"occupancy table size 2^{log2} is not the one built for {n_cells} cells")
    _check_hash_table(keys, log2, "occupancy")
    anchors = _stored(a, "anchors", np.float64, ndim=2)
    if not np.array_equal(anchors, points[normals[:, 2] >= math.cos(math.radians(tilt))]):
        raise ValueError("floor anchors are not the map's")
    build_s = _number(e, "build_s") if "build_s" in e else 0.0
    return (cell, dil, tilt), {"key": (cell, dil, tilt), "keys": keys, "rows": rows, "anchors": anchors, "log2": log2, "n_cells": n_cells,
                               "n_blocks": nb, "build_s": build_s}


def _expand_occupancy(pk: dict):
    """The :class:`~minegeo.localize.correlative.MapOccupancy` of a checked stored one (empty
    slots added back with zero bits, dense directory rebuilt from the block keys)."""
    from minegeo.localize import _kernels as LK
    from minegeo.localize.correlative import MAX_DENSE_BLOCKS, MapOccupancy

    cell, dil, _ = pk["key"]
    keys = pk["keys"]
    bits = np.zeros((keys.shape[0], 16), dtype=np.uint64)  # an empty slot's bits must be zero
    bits[keys != -1] = pk["rows"]
    table, table_lo = LK.dense_block_table(keys, MAX_DENSE_BLOCKS)
    return MapOccupancy(block_keys=keys, bits=bits, log2_blocks=pk["log2"], table=table, table_lo=table_lo,
                        n_cells=pk["n_cells"], n_blocks=pk["n_blocks"], anchors=pk["anchors"], cell_size_m=float(cell),
                        dilation_cells=int(dil), build_s=pk["build_s"])


def profile_name(params: PrepareParams | FeatureParams) -> str | None:
    """The CLI ``--profile`` whose values ``params`` are exactly (``fast``, ``table3``), else None."""
    for name, ref in (("fast", PrepareParams.fast()), ("table3", PrepareParams())):
        if params == (ref.features if isinstance(params, FeatureParams) else ref):
            return name
    return None


def _diff(a: dict, b: dict, prefix: str = "") -> list:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _diff(va, vb, prefix + k + ".")
        elif va != vb:
            out.append((prefix + k, va, vb))
    return out


def prepare_map(map_cloud, params: PrepareParams | None = None, *, georef=None, source: dict | None = None,
                work_origin=None, progress=None) -> PreparedMap:
    """Prepare a prior map for localization (downsample, normals, FPFH), once.

    Parameters
    ----------
    map_cloud : PointCloud or (n, 3) array_like
        The map in its ``map`` frame (``points + origin``), m. For a georeferenced map pass
        the cloud in the map frame and its ``georef`` (see :func:`load_map_for_localization`).
    params : PrepareParams, optional
        Defaults to Baek et al. (2022) Table 3 (voxel 0.5 m, normals r = 1 m, FPFH r = 2.5 m).
    georef : GeorefResult, optional
        Georeferencing of the map (kept in the prepared map to put results in the CRS).
    source : dict, optional
        Provenance of the map file (``path``, ``sha256``...).
    work_origin : (3,) array_like, optional
        Working origin (map frame); default: the centre of the bounding box rounded to 1 m.
    progress : callable, optional
        ``progress(step)`` when each step starts (``"downsample"``, ``"normals"``, ``"FPFH"``,
        ``"ICP target"``; :mod:`minegeo.localize._progress`). Nothing is printed.

    Returns
    -------
    PreparedMap

    Raises
    ------
    TooFewPointsError
        Fewer than 10 points after downsampling.
    """
    params = PrepareParams() if params is None else params
    if not isinstance(params, PrepareParams):
        raise InputError(f"params must be a PrepareParams, got {type(params).__name__}")
    t_all = time.perf_counter()
    if isinstance(map_cloud, PointCloud):
        pts, org, crs = map_cloud.points, np.asarray(map_cloud.origin, dtype=np.float64), map_cloud.crs
    else:
        pts, org, crs = map_cloud, np.zeros(3), None
    P = as_points(pts, "map points", min_points=1)
    if work_origin is None:
        lo, hi = P.min(axis=0), P.max(axis=0)
        wo_rel = np.round((lo + hi) / 2.0)
        work_origin = org + wo_rel
    else:
        work_origin = np.asarray(work_origin, dtype=np.float64).reshape(3)
        wo_rel = work_origin - org
    P = P - wo_rel
    timings: dict = StepTimings(progress, FEATURE_STEPS)  # announces normals / FPFH as they start
    announce(progress, "downsample")
    t0 = time.perf_counter()
    D = _downsample(P, params.voxel_size_m, params.octree_level)
    timings["downsample"] = time.perf_counter() - t0
    icp_pts = None
    if params.icp_voxel_size_m is None:
        icp_pts = np.ascontiguousarray(P)
    return _finish(D, icp_pts, P, P.shape[0], work_origin, params, georef, crs, source, timings, t_all, progress)


def _finish(D, icp_pts, P, n_points: int, work_origin, params: PrepareParams, georef, crs, source, timings, t_all,
            progress) -> PreparedMap:
    """Normals, FPFH and the ICP target of the downsampled map ``D``, and the :class:`PreparedMap`
    (shared by :func:`prepare_map` and :func:`prepare_map_file`). ``icp_pts`` None: the
    ``icp_voxel_size_m`` centroids of ``P`` are computed here."""
    if D.shape[0] < 10:
        raise TooFewPointsError(f"the map has only {D.shape[0]} points after downsampling ({params.describe()})")
    N, F = _normals_fpfh(D, params.features, timings)
    announce(progress, "ICP target")
    t0 = time.perf_counter()
    if icp_pts is None:
        from minegeo.geometry import voxel_downsample

        icp_pts = np.ascontiguousarray(voxel_downsample(P, float(params.icp_voxel_size_m)).points)
    from minegeo.geometry import NormalParams, estimate_normals

    icp_nrm = np.ascontiguousarray(estimate_normals(icp_pts, NormalParams(max_nn=ICP_NORMAL_NN)).normals)
    timings["icp_target"] = time.perf_counter() - t0
    gdict = None
    if georef is not None:
        gdict = to_jsonable(_georef_dict(georef))
        crs = georef.crs
    timings["total"] = time.perf_counter() - t_all
    log.info("prepared map: %d -> %d points (%s) in %.2f s", n_points, D.shape[0], params.describe(), timings["total"])
    src = dict(source or {})
    src.setdefault("n_points", int(n_points))
    return PreparedMap(points=D, normals=N, features=F, icp_points=icp_pts, icp_normals=icp_nrm,
                       work_origin=np.asarray(work_origin, dtype=np.float64),
                       params=params, params_hash=params_hash(params), georef=gdict, crs=crs, source=src,
                       timings_s=dict(timings), _georef_obj=georef)


def _georef_dict(georef) -> dict:
    """A GeorefResult as the dict its ``from_dict`` reads."""
    return {k: v for k, v in georef.as_dict().items() if k != "timings_s"}


# ----------------------------------------------------------------------------- map files
def cache_path(map_path, params: PrepareParams) -> Path:
    """Cache file of a prepared map next to its source: ``<map>.prepared-<hash12>.npz``."""
    p = Path(map_path)
    return p.with_name(f"{p.name}.prepared-{params_hash(params)[:12]}.npz")


def load_map_cloud(path):
    """Read a map file in its ``map`` frame: ``(PointCloud, GeorefResult or None)``.

    A georeferenced map (``minegeo georef`` output with its ``.georef.json`` sidecar) is read
    through :func:`~minegeo.georef.load_georeferenced_map` and taken back to the map
    frame with :func:`~minegeo.georef.crs_to_map` (exact inverse of the similarity),
    so registration is rigid in the frame the map was surveyed in, even when the
    georeferencing has a scale. A plain cloud is used as is.
    """
    from minegeo.georef import crs_to_map, load_georeferenced_map, sidecar_path
    from minegeo.io import read_point_cloud

    p = Path(path)
    if not p.exists():
        raise InputError(f"map file {p} does not exist")
    if sidecar_path(p).exists() or p.name.endswith(".georef.json"):
        cloud, g = load_georeferenced_map(p)
        pts_map = crs_to_map(cloud.points, g)
        return PointCloud(points=pts_map, crs=g.crs, frame="map", metadata={"georeferenced": True}), g
    cloud = read_point_cloud(p)
    return cloud, None


class MemoryLimitError(InputError):
    """The preparation would exceed ``--max-memory-gb`` (:func:`prepare_map_file`)."""


#: Estimated bytes per point of one chunk in memory (reader records, float64 copies, frame shifts).
CHUNK_BYTES_PER_POINT = 160
#: Estimated bytes per downsampled map point for normals, FPFH and their neighbour searches.
FEATURE_BYTES_PER_POINT = 2500
#: Estimated bytes per ICP target point for its normals (20 neighbours).
ICP_BYTES_PER_POINT = 600
#: Smallest chunk the memory ceiling may shrink ``chunk_points`` to.
MIN_CHUNK_POINTS = 4096


def _rss_bytes() -> int:
    """Resident set size of this process (Linux ``/proc``; 0 elsewhere)."""
    import os

    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


class _MemoryBudget:
    """Estimate of the preparation's peak memory against an optional ceiling (bytes)."""

    def __init__(self, max_memory_gb):
        self.base = _rss_bytes()  # interpreter, NumPy, Numba, SciPy: not ours to shrink
        self.limit = None if max_memory_gb is None else float(max_memory_gb) * 1e9
        if self.limit is not None and not (math.isfinite(self.limit) and self.limit > 0):
            raise InputError(f"max_memory_gb must be a positive number, got {max_memory_gb!r}")
        self.peak = self.base

    def fit_chunk(self, chunk_points: int) -> int:
        """``chunk_points``, reduced so that one chunk takes at most a quarter of the room left."""
        if self.limit is None:
            return chunk_points
        room = self.limit - self.base
        fit = int(room / 4 / CHUNK_BYTES_PER_POINT)
        k = min(chunk_points, fit)
        if fit < min(chunk_points, MIN_CHUNK_POINTS):
            raise MemoryLimitError(f"--max-memory-gb {self.limit / 1e9:g} leaves no room for reading: the process "
                                   f"already uses {self.base / 1e9:.2f} GB before the map is read")
        if k < chunk_points:
            log.info("chunk of %d points reduced to %d to stay under %.2f GB", chunk_points, k, self.limit / 1e9)
        return k

    def check(self, what: str, nbytes: float) -> None:
        est = self.base + nbytes
        self.peak = max(self.peak, est)
        if self.limit is not None and est > self.limit:
            raise MemoryLimitError(
                f"preparing this map needs about {est / 1e9:.2f} GB ({what}), more than --max-memory-gb "
                f"{self.limit / 1e9:g}: raise the ceiling, or use a larger voxel (--voxel, --icp-voxel)")


def _open_map(path, chunk_points: int):
    """``(PointChunks, GeorefResult or None, transform or None)`` of a map file (see :func:`load_map_cloud`)."""
    from minegeo.georef import crs_to_map, read_georef_sidecar, same_crs, sidecar_path
    from minegeo.io.chunked import open_point_chunks

    p = Path(path)
    if not p.exists():
        raise InputError(f"map file {p} does not exist")
    if sidecar_path(p).exists() or p.name.endswith(".georef.json"):
        cloud_p, _, g = read_georef_sidecar(p)
        chunks = open_point_chunks(cloud_p, chunk_points, origin=g.origin)
        if chunks.crs and not same_crs(str(chunks.crs), g.crs):
            raise FileFormatError(cloud_p, f"the file says CRS {chunks.crs} but its sidecar says {g.crs}")
        return chunks, g, lambda q: crs_to_map(q, g)
    return open_point_chunks(p, chunk_points), None, None


def prepare_map_file(path, params: PrepareParams | None = None, *, chunk_points: int | None = None,
                     max_memory_gb: float | None = None, source: dict | None = None, progress=None,
                     read_progress=None) -> PreparedMap:
    """Prepare a map file read in chunks: the same :class:`PreparedMap` as :func:`prepare_map` of
    :func:`load_map_cloud`, bit for bit, with memory bounded by the downsampled map plus one chunk.

    Two passes over the file (:mod:`minegeo.io.chunked`): (1) the exact bounds, which give the
    work origin (bounding-box centre rounded to 1 m), the voxel grid origin and the octree
    cube; (2) every chunk, taken to the map frame (``crs_to_map`` for a georeferenced map) and
    the work frame, is added to the map's voxel (or octree) accumulator and to the ICP target's
    voxel accumulator (:mod:`minegeo.geometry.stream`). Normals, FPFH and the ICP normals are
    then computed on the downsampled clouds as in :func:`prepare_map`.

    Parameters
    ----------
    path : str or Path
        Map file (PLY, PCD, LAS/LAZ, E57 chunked; text formats read whole), or a georeferenced
        map with its ``.georef.json`` sidecar.
    params : PrepareParams, optional
        ``icp_voxel_size_m=None`` (every point as ICP target) keeps the whole map in memory.
    chunk_points : int, optional
        Points per chunk (default :data:`minegeo.io.chunked.DEFAULT_CHUNK_POINTS`).
    max_memory_gb : float, optional
        Ceiling (GB = 10^9 bytes) on the estimated peak memory of the process: the chunk is
        reduced to a quarter of the room left, and :class:`MemoryLimitError` is raised as soon
        as the estimate (process memory at the start + cell tables x 3 during growth + one
        chunk + the feature stage of the cells so far) exceeds it.
    source : dict, optional
        Provenance (``path``, ``sha256``...); ``streaming`` (chunking record) is added.
    progress : callable, optional
        ``progress(step)`` as in :func:`prepare_map`.
    read_progress : callable, optional
        ``read_progress(pass_number, bytes_read, size_bytes)`` after each chunk.

    Raises
    ------
    MemoryLimitError
        The estimate exceeds ``max_memory_gb``; ``icp_voxel_size_m=None`` with a ceiling.
    FileFormatError, TooFewPointsError
    """
    from minegeo.geometry.stream import OctreeAccumulator, VoxelAccumulator
    from minegeo.io.chunked import DEFAULT_CHUNK_POINTS, scan_bounds

    params = PrepareParams() if params is None else params
    if not isinstance(params, PrepareParams):
        raise InputError(f"params must be a PrepareParams, got {type(params).__name__}")
    t_all = time.perf_counter()
    budget = _MemoryBudget(max_memory_gb)
    k = budget.fit_chunk(DEFAULT_CHUNK_POINTS if chunk_points is None else chunk_points)
    chunks, g, transform = _open_map(path, k)
    announce(progress, "read map (pass 1: bounds)")
    rp = (lambda b, s: read_progress(1, b, s)) if read_progress is not None else None
    t0 = time.perf_counter()
    n, lo, hi = scan_bounds(chunks, transform, rp)
    t_bounds = time.perf_counter() - t0
    wo_rel = np.round((lo + hi) / 2.0)
    work_origin = np.zeros(3) + wo_rel
    # fl(x - w) is monotone in x: the bounds of the shifted cloud are the shifted bounds, exactly
    blo, bhi = lo - wo_rel, hi - wo_rel
    if params.octree_level is not None:
        acc = OctreeAccumulator(blo, bhi, int(params.octree_level))
    else:
        acc = VoxelAccumulator(blo, bhi, float(params.voxel_size_m))
    icp = None if params.icp_voxel_size_m is None else VoxelAccumulator(blo, bhi, float(params.icp_voxel_size_m))
    if icp is None:
        budget.check("every map point kept as the ICP target (icp_voxel_size_m=None cannot stream)", n * 24.0 * 2)
    timings: dict = StepTimings(progress, FEATURE_STEPS)
    announce(progress, "read map (pass 2: downsample)")
    t0 = time.perf_counter()
    keep, n_chunks = [], 0
    for c in chunks:
        q = (c if transform is None else transform(c)) - wo_rel
        acc.add(q)
        if icp is None:
            keep.append(q)
        else:
            icp.add(q)
        n_chunks += 1
        m_icp = 0 if icp is None else icp.n_used
        budget.check("cell tables, one chunk and the feature stage",
                     3.0 * (acc.nbytes + (0 if icp is None else icp.nbytes)) + chunks.chunk_points * CHUNK_BYTES_PER_POINT
                     + acc.n_used * FEATURE_BYTES_PER_POINT + m_icp * ICP_BYTES_PER_POINT)
        if read_progress is not None:
            read_progress(2, chunks.bytes_read, chunks.size_bytes)
    D = acc.result()[0]
    icp_pts = np.concatenate(keep) if icp is None else icp.result()[0]
    del acc, icp, keep
    timings["downsample"] = time.perf_counter() - t0
    src = dict(source or {})
    src.setdefault("n_points", int(n))
    src["streaming"] = {"chunk_points": int(chunks.chunk_points), "n_chunks": n_chunks, "passes": 2,
                        "format": chunks.format, "encoding": chunks.encoding, "read_whole": not chunks.chunked,
                        "max_memory_gb": max_memory_gb, "memory_estimate_peak_bytes": int(budget.peak),
                        "bounds_pass_s": t_bounds}
    crs = None if g is not None else chunks.crs
    return _finish(D, np.ascontiguousarray(icp_pts), None, n, work_origin, params, g, crs, src, timings, t_all,
                   progress)


def is_georeferenced(p: Path) -> bool:
    """True when the map file ``p`` has a ``.georef.json`` sidecar or is itself one."""
    from minegeo.georef import sidecar_path

    return sidecar_path(p).exists() or p.name.endswith(".georef.json")


def is_prepared_file(path) -> bool:
    """True if ``path`` looks like a prepared-map ``.npz``."""
    return str(path).lower().endswith(".npz")


def load_or_prepare(path, params: PrepareParams, *, use_cache: bool = True, write_cache: bool = True):
    """A :class:`PreparedMap` from a prepared ``.npz`` or a map file (prepared, cached next to it).

    Returns ``(prepared, how)`` with ``how`` in ``{"prepared_file", "cache", "computed"}``.
    The cache (``<map>.prepared-<hash12>.npz``, see :func:`cache_path`) is used only if its
    recorded source SHA-256 equals the map file's; otherwise the map is prepared again.
    """
    p = Path(path)
    if is_prepared_file(p):
        if not p.exists():
            raise InputError(f"prepared map {p} does not exist")
        pm = PreparedMap.load(p)
        pm.check_params(params.features)  # the scan's descriptors must be computed the same way
        return pm, "prepared_file"
    if not p.exists():
        raise InputError(f"map file {p} does not exist")
    sha = sha256_file(p)
    cp = cache_path(p, params)
    if use_cache and cp.exists():
        try:
            pm = PreparedMap.load(cp, params)
            if pm.source.get("sha256") == sha:
                return pm, "cache"
        except (FileFormatError, InputError) as exc:
            log.warning("ignoring prepared-map cache %s: %s", cp, exc)
    georeferenced = is_georeferenced(p)
    pm = prepare_map_file(p, params, source={"path": str(p), "sha256": sha, "georeferenced": georeferenced})
    if write_cache:
        try:
            pm.save(cp)
        except OSError as exc:
            log.warning("could not write prepared-map cache %s: %s", cp, exc)
    return pm, "computed"
