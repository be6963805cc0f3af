"""Map preparation for global localization: downsample, normals, FPFH, saved once (Baek et al. 2022, Sec. 2.2-2.3).

A *prepared map* holds everything of the prior map that the localization of a scan needs
and that does not depend on the scan: the downsampled map points (Sec. 2.2), their surface
normals (Eq. 2) and FPFH descriptors (Eqs. 3-6), in the **map frame** relative to a recorded
working origin, plus the georeferencing of the map (if any). It is computed once
(:func:`prepare_map`, ``minegeo prepare-map``) and stored as a NumPy ``.npz`` file without
pickles (:meth:`PreparedMap.save` / :meth:`PreparedMap.load`), carrying a format version and
a hash of the parameters; loading with other parameters is an error, so a scan is never
matched against features computed with different settings.

Frames
------
``map``   the frame of the map *before* georeferencing (the ``map`` of ``T_crs_map``); for a
          map without georeferencing sidecar, the file's own coordinates.
``work``  ``map`` minus ``work_origin`` (a rounded point near the map's centre): all
          arrays of a :class:`PreparedMap` are in this frame (float64 precision for any map).
``geo``   CRS minus the georeferencing origin (see :mod:`minegeo.localize.georef`).

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
from minegeo._validate import as_points, check_positive, is_permutation
from minegeo.errors import FileFormatError, InputError, TooFewPointsError
from minegeo.io.types import PointCloud

__all__ = [
    "FeatureParams",
    "PrepareParams",
    "PreparedMap",
    "prepare_map",
    "prepare_cloud_features",
    "orient_normals_void",
    "params_hash",
    "cache_path",
    "PREPARED_FORMAT",
    "PREPARED_VERSION",
    "FAST_FEATURES",
]

log = logging.getLogger(__name__)

#: ``format`` tag stored in a prepared-map file.
PREPARED_FORMAT = "minegeo-prepared-map"
#: Current file format version (increase on any incompatible change).
PREPARED_VERSION = 1

#: Format of the search structures a prepared file may also hold (``meta["indexes"]``).
INDEX_VERSION = 1
INDEX_PREFIX = "index__"
_ORIENTATIONS = ("void", "none", "centroid")
#: Nearest neighbours of the PCA normals of the ICP target.
ICP_NORMAL_NN = 20


@dataclass(frozen=True)
class FeatureParams:
    """Normal and FPFH settings shared by the map and the scan (defaults: Baek et al. 2022, Table 3).

    Attributes
    ----------
    normal_radius_m : float
        Sphere radius of the PCA normal neighbourhood (Eq. 2), m. Table 3: 1 m.
    normal_max_nn : int
        At most this many neighbours for a normal. Table 3: 1000.
    fpfh_radius_m : float
        FPFH sphere radius r (Eqs. 3-6), m. Table 3: 2.5 m.
    fpfh_max_nn : int
        At most this many FPFH neighbours. Table 3: 1000.
    fpfh_weight : {"inverse_distance", "open3d"}
        Neighbour weight of Eq. 6 (``1/ω`` as the paper, or ``1/ω²`` as Open3D).
    orientation : {"void", "none", "centroid"}
        Normal sign rule (module docstring). Not in the paper (Open3D leaves signs to the
        solver); "void" makes the descriptors independent of the scan's orientation.
    orientation_radius_m : float
        Half-edge of the cube whose centroid the "void" rule points to, m (about a drift width).
    """

    normal_radius_m: float = 1.0
    normal_max_nn: int = 1000
    fpfh_radius_m: float = 2.5
    fpfh_max_nn: int = 1000
    fpfh_weight: str = "inverse_distance"
    orientation: str = "void"
    orientation_radius_m: float = 5.0

    def __post_init__(self):
        check_positive(self.normal_radius_m, "FeatureParams.normal_radius_m")
        check_positive(self.fpfh_radius_m, "FeatureParams.fpfh_radius_m")
        check_positive(self.orientation_radius_m, "FeatureParams.orientation_radius_m")
        for name in ("normal_max_nn", "fpfh_max_nn"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 3:
                raise InputError(f"FeatureParams.{name} must be an integer >= 3, got {v!r}")
        if self.orientation not in _ORIENTATIONS:
            raise InputError(f"FeatureParams.orientation must be one of {_ORIENTATIONS}, got {self.orientation!r}")


#: Feature settings of the fast profile (Table 3 ratios at a 1 m voxel).
FAST_FEATURES = FeatureParams(normal_radius_m=2.0, fpfh_radius_m=5.0)


@dataclass(frozen=True)
class PrepareParams:
    """How the map is prepared (defaults: Baek et al. 2022, Table 3).

    Attributes
    ----------
    voxel_size_m : float or None
        Voxel-centroid downsampling edge, m (Table 3: 0.5 m). Ignored when ``octree_level``
        is given.
    octree_level : int or None
        Octree subsampling level instead (Sec. 2.2: the point nearest to each occupied cell
        centre; the paper used level 10 for its map). The cell edge is the map's bounding
        cube edge / 2^level.
    features : FeatureParams
        Normals and FPFH settings; a scan must be localized with the same ones.
    icp_voxel_size_m : float or None
        The ICP target: the paper aligns against the full-resolution global cloud
        ``Q_init`` (Sec. 2.4); minegeo keeps a voxel-centroid copy at this edge (m, default
        0.1 m, about the survey's noise level) so that the prepared file stays bounded.
        None keeps every map point. The coarse (``voxel_size_m``) cloud quantises nearest-
        neighbour distances to ~0.2 m and cannot tell a correct placement from a near miss.
    """

    voxel_size_m: float | None = 0.5
    octree_level: int | None = None
    features: FeatureParams = field(default_factory=FeatureParams)
    icp_voxel_size_m: float | None = 0.1

    def __post_init__(self):
        if self.octree_level is None:
            if self.voxel_size_m is None:
                raise InputError("give voxel_size_m or octree_level")
            check_positive(self.voxel_size_m, "PrepareParams.voxel_size_m")
        else:
            lv = self.octree_level
            if isinstance(lv, bool) or int(lv) != lv or not 1 <= lv <= 21:
                raise InputError(f"octree_level must be an integer in 1..21, got {lv!r}")
        if not isinstance(self.features, FeatureParams):
            raise InputError("PrepareParams.features must be a FeatureParams")
        if self.icp_voxel_size_m is not None:
            check_positive(self.icp_voxel_size_m, "PrepareParams.icp_voxel_size_m")

    @classmethod
    def fast(cls, **overrides) -> PrepareParams:
        """The map side of :meth:`LocalizeParams.fast` (voxel 1 m, normals 2 m, FPFH 5 m)."""
        kw = {"voxel_size_m": 1.0, "features": FAST_FEATURES}
        kw.update(overrides)
        return cls(**kw)

    def describe(self) -> str:
        """One line: the downsampling used."""
        if self.octree_level is not None:
            return f"octree level {self.octree_level}"
        return f"voxel {self.voxel_size_m:g} m"


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
    """Downsample (Sec. 2.2), estimate normals (Eq. 2) and FPFH (Eqs. 3-6) of one cloud.

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
    from minegeo.features import FPFHParams, compute_fpfh
    from minegeo.geometry import NormalParams, estimate_normals

    t = {} if timings is None else timings
    P = as_points(points, "points", min_points=1)
    t0 = time.perf_counter()
    D = _downsample(P, voxel_size_m, octree_level)
    t["downsample"] = time.perf_counter() - t0
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
    return D, np.ascontiguousarray(N), np.ascontiguousarray(F)


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
            self._occ_cache[key] = map_occupancy(self.icp_points, self.points, self.normals, params)
        return self._occ_cache[key]

    def build_indexes(self, params=None) -> dict:
        """Build every per-process search structure that :func:`localize_scan` with ``params``
        (:class:`LocalizeParams`, default the defaults) will use, so the first scan does not pay
        for them: the KD-trees of the ICP cloud, the descriptor tree, and for levelled scans
        with the correlative search its occupancy bitmap and thinned screening cloud (GICP:
        the target covariances). Returns the seconds spent per structure (0 when cached)."""
        from minegeo.localize.pipeline import LocalizeParams

        p = LocalizeParams() if params is None else params
        out = {}

        def _t(name, fn):
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
        from minegeo.localize.correlative import SCREEN_GATES_M

        key = ("screen_grid", float(voxel_size_m))
        if key not in self._gicp_cache:
            _, Qs, _ = self.screen_target(voxel_size_m)
            c = float(voxel_size_m)
            band = int(math.ceil(max(SCREEN_GATES_M) / c))
            n_cells = Qs.shape[0] * (2 * band + 1) ** 3
            log2 = max(10, int(math.ceil(math.log2(max(1, n_cells) / 512 / 8))) + 1)
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
        (plane covariances ``I − (1 − ε) n nᵀ``, Ren 2019 Eqs. 2-3)."""
        from minegeo.registration import estimate_gicp_covariances

        key = (float(params.epsilon), int(params.covariance_neighbours), str(params.covariance_mode))
        if key not in self._gicp_cache:
            self._gicp_cache[key] = estimate_gicp_covariances(self.icp_points, params, normals=self.icp_normals)
        return self._gicp_cache[key], self.target_index()

    @property
    def georef_result(self):
        """The :class:`~minegeo.localize.georef.GeorefResult` or None."""
        if self.georef is None:
            return None
        if self._georef_obj is None:
            from minegeo.localize.georef import GeorefResult

            self._georef_obj = GeorefResult.from_dict(self.georef)
        return self._georef_obj

    def points_map(self) -> np.ndarray:
        """Downsampled points in the ``map`` frame (m)."""
        return self.points + self.work_origin

    def check_params(self, params: PrepareParams | FeatureParams) -> None:
        """Raise :class:`InputError` if ``params`` differ from those the map was prepared with."""
        mine = self.params.features if isinstance(params, FeatureParams) else self.params
        if params != mine:
            a, b = to_jsonable(asdict(mine)), to_jsonable(asdict(params))
            diff = _diff(a, b)
            raise InputError(
                "the prepared map was made with other parameters than requested ("
                + "; ".join(f"{k}: map {va!r}, requested {vb!r}" for k, va, vb in diff)
                + "): prepare the map again with 'minegeo prepare-map' and these parameters"
            )

    # -- files --------------------------------------------------------------------------
    def save(self, path, *, indexes: bool = True) -> Path:
        """Write the prepared map to ``path`` (``.npz``, no pickles), atomically.

        The file holds the arrays plus a JSON ``meta`` string with ``format``, ``version``,
        ``params``, ``params_hash``, ``georef``, ``crs`` and ``source``. With ``indexes`` it also
        holds every search structure built so far (:meth:`build_indexes`: the Numba KD-trees of
        the ICP cloud and of the thinned screening cloud, the descriptor tree, the occupancy
        bitmap, the lookup grid; ``meta["indexes"]``), which :meth:`load` restores instead of
        rebuilding them (~5 s for the 6.5 km paper map). Only pykdtree's tree is rebuilt.
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
        extra: dict = {}
        if indexes:
            extra, meta["indexes"] = self._index_payload()
        buf = io.BytesIO()
        np.savez(buf, points=self.points, normals=self.normals, features=self.features, icp_points=self.icp_points,
                 icp_normals=self.icp_normals,
                 work_origin=self.work_origin, meta=np.array(json.dumps(meta, sort_keys=True)), **extra)
        return atomic_write_bytes(path, buf.getvalue())

    def _index_payload(self) -> tuple[dict, dict]:
        """Arrays (``index__*`` keys) and meta record of the search structures built so far."""
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
        for i, (key, occ) in enumerate(self._occ_cache.items()):
            name = f"occupancy{i}"
            used = occ.block_keys != -1  # only the rows of used slots (the others are zero)
            put(name, {"block_keys": occ.block_keys, "bits": occ.bits[used], "anchors": occ.anchors})
            entries.append({"kind": "occupancy", "name": name, "key": list(key), "log2_blocks": occ.log2_blocks,
                            "n_cells": occ.n_cells, "n_blocks": occ.n_blocks, "build_s": occ.build_s})
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
                put(name, {"keys": keys, "nearest": nearest[keys != -1]})  # used slots' rows (the others are -1)
                entries.append({"kind": "screen_grid", "name": name, "voxel_size_m": key[1], "log2_blocks": log2,
                                "cell_m": c})
        return arrays, {"version": INDEX_VERSION, "entries": entries}

    def _restore_indexes(self, z: dict, record: dict, path) -> list[str]:
        """Put the stored search structures (``z``: the file's ``index__*`` arrays) back in the caches.

        A structure whose arrays fail the checks is skipped with a warning (it is rebuilt when
        needed): the map itself is intact. Returns the kinds restored.
        """
        from minegeo.localize.correlative import MapOccupancy
        from minegeo.registration._kernels import GatedKDTree
        from minegeo.registration.correspondences import FeatureIndex, _RowTree

        restored: list[str] = []
        if not isinstance(record, dict) or record.get("version") != INDEX_VERSION:
            log.warning("%s: stored search structures of another format version: rebuilding them", path)
            return restored
        for e in record.get("entries", []):
            name = f"{INDEX_PREFIX}{e.get('name')}__"
            try:
                a = {k[len(name):]: v_ for k, v_ in z.items() if k.startswith(name)}
                kind = e["kind"]
                if kind == "target_kdtree":
                    self._gicp_cache["index"] = GatedKDTree.from_arrays(self.icp_points, a)
                elif kind == "feature_index":
                    rows = np.ascontiguousarray(a["rows"], dtype=np.int64)
                    m = self.features.shape[0]
                    if rows.ndim != 1 or rows.size == 0 or rows.min() < 0 or rows.max() >= m:
                        raise ValueError("descriptor rows out of range")
                    B = np.ascontiguousarray(self.features[rows])
                    if e["brute"]:
                        tree = _RowTree(B=B, brute=True)
                    else:
                        tree = _restore_row_tree(B, a, float(e["rb"]))
                    self._feature_index = FeatureIndex(features=self.features,
                                                       drop_zero_features=bool(e["drop_zero_features"]), rows=rows,
                                                       tree=tree)
                elif kind == "occupancy":
                    occ = _restore_occupancy(MapOccupancy, a, e)
                    cell, dil, tilt = e["key"]
                    self._occ_cache[(float(cell), int(dil), float(tilt))] = occ
                elif kind == "screen_target":
                    v = float(e["voxel_size_m"])
                    if e["full"]:
                        self._gicp_cache[("screen", v)] = (self.target_index(), self.icp_points, self.icp_normals)
                    else:
                        pts = as_points(a["points"], "screening points")
                        nrm = as_points(a["normals"], "screening normals")
                        if nrm.shape != pts.shape:
                            raise ValueError("screening points and normals differ in length")
                        tree = GatedKDTree.from_arrays(pts, {k[5:]: x for k, x in a.items() if k.startswith("tree_")})
                        self._gicp_cache[("screen", v)] = (tree, pts, nrm)
                elif kind == "screen_grid":
                    v = float(e["voxel_size_m"])
                    key_s = ("screen", v)
                    if key_s not in self._gicp_cache:
                        raise ValueError("lookup grid stored without its screening cloud")
                    n_s = self._gicp_cache[key_s][1].shape[0]
                    keys = np.ascontiguousarray(a["keys"])
                    rows = a["nearest"]
                    log2 = int(e["log2_blocks"])
                    used = keys != -1
                    if (keys.dtype != np.int64 or rows.dtype != np.int32 or keys.shape != (1 << log2,)
                            or rows.shape != (int(used.sum()), 512)
                            or (rows.size and (rows.min() < -1 or rows.max() >= n_s))
                            or np.count_nonzero(~used) == 0):
                        raise ValueError("lookup grid arrays out of range")
                    nearest = np.full((keys.shape[0], 512), -1, dtype=np.int32)
                    nearest[used] = rows
                    self._gicp_cache[("screen_grid", v)] = (keys, nearest, log2, float(e["cell_m"]))
                else:
                    raise ValueError(f"unknown kind {kind!r}")
                restored.append(kind)
            except (KeyError, ValueError, TypeError, IndexError, InputError) as exc:
                log.warning("%s: stored search structure %r not usable (%s): it will be rebuilt", path,
                            e.get("name"), exc)
        return restored

    @classmethod
    def load(cls, path, params: PrepareParams | None = None) -> PreparedMap:
        """Read a file written by :meth:`save`.

        Parameters
        ----------
        path : str or Path
        params : PrepareParams, optional
            If given, the file's parameters must equal these (else :class:`InputError`).

        Raises
        ------
        FileFormatError
            Not a prepared map, a newer format version, corrupted arrays or a parameter hash
            that does not match the stored parameters.
        InputError
            ``params`` given and different from the file's.
        """
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as z:
                if "meta" not in z.files:
                    raise FileFormatError(p, "not a minegeo prepared map (no 'meta' entry)")
                meta = json.loads(str(z["meta"]))
                arrays = {k: np.array(z[k], dtype=np.float64) for k in ("points", "normals", "features", "icp_points", "icp_normals",
                                                                     "work_origin")}
                index_arrays = {k: z[k] for k in z.files if k.startswith(INDEX_PREFIX)} if "indexes" in meta else {}
        except FileFormatError:
            raise
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
            raise FileFormatError(p, f"cannot read prepared map ({exc})") from None
        if meta.get("format") != PREPARED_FORMAT:
            raise FileFormatError(p, f"not a minegeo prepared map (format {meta.get('format')!r})")
        if int(meta.get("version", 0)) != PREPARED_VERSION:
            raise FileFormatError(
                p, f"prepared-map format version {meta.get('version')} is not {PREPARED_VERSION}: prepare the map again"
            )
        try:
            stored = _params_from_dict(meta["params"])
        except (KeyError, TypeError, InputError) as exc:
            raise FileFormatError(p, f"bad parameter record ({exc})") from None
        if params_hash(stored) != meta.get("params_hash"):
            raise FileFormatError(p, "parameter hash does not match the stored parameters (file edited or corrupted)")
        m = arrays["points"].shape[0]
        if (arrays["points"].shape != (m, 3) or arrays["normals"].shape != (m, 3) or arrays["features"].shape[0] != m
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
        if params is not None:
            pm.check_params(params)
        if "indexes" in meta:
            pm._restore_indexes(index_arrays, meta["indexes"], p)
        return pm


def _restore_row_tree(B: np.ndarray, a: dict, rb: float):
    """The descriptor tree over ``B`` from its stored rotation and leaf partition (the leaf
    storage is packed again from ``B``, so it cannot disagree with the map's descriptors)."""
    from minegeo.registration import _kernels_ransac as KR
    from minegeo.registration.correspondences import _RowTree

    n, dim = B.shape
    mu = np.ascontiguousarray(a["mu"], dtype=np.float64)
    V = np.ascontiguousarray(a["V"], dtype=np.float64)
    perm = np.ascontiguousarray(a["perm"], dtype=np.int64)
    lstart = np.ascontiguousarray(a["lstart"], dtype=np.int64)
    if (mu.shape != (dim,) or V.ndim != 2 or V.shape[0] != dim or not 1 <= V.shape[1] <= KR.FEATURE_ROT
            or not (np.isfinite(mu).all() and np.isfinite(V).all())):
        raise ValueError("descriptor tree rotation has the wrong shape")
    if not is_permutation(perm, n):
        raise ValueError("descriptor tree order is not a permutation of the rows")
    sizes = np.diff(lstart)
    if lstart.ndim != 1 or lstart.size < 2 or lstart[0] != 0 or lstart[-1] != n or sizes.min() < 0 \
            or sizes.max() > KR.FEATURE_LEAF:
        raise ValueError("descriptor tree leaves out of range")
    P = KR.feature_rotate(B, mu, V)
    lead, Bp, loT, hiT = KR.feature_tree_pack(B, P, perm, lstart)
    return _RowTree(B=B, brute=False, mu=mu, V=V, perm=perm, lstart=lstart, lead=lead, Bp=Bp, loT=loT, hiT=hiT,
                    rb=float(rb))


def _restore_occupancy(cls, a: dict, e: dict):
    """A stored :class:`~minegeo.localize.correlative.MapOccupancy` (its dense directory is
    rebuilt from the block keys)."""
    from minegeo.localize import _kernels as LK
    from minegeo.localize.correlative import MAX_DENSE_BLOCKS

    log2 = int(e["log2_blocks"])
    keys = np.ascontiguousarray(a["block_keys"])
    rows = a["bits"]
    anchors = as_points(a["anchors"], "floor anchors", min_points=0)
    used = keys != -1
    if (keys.dtype != np.int64 or rows.dtype != np.uint64 or keys.shape != (1 << log2,)
            or rows.shape != (int(used.sum()), 16) or np.count_nonzero(~used) == 0):
        raise ValueError("occupancy arrays have the wrong shapes")
    bits = np.zeros((keys.shape[0], 16), dtype=np.uint64)  # an empty slot's bits must be zero
    bits[used] = rows
    cell, dil, _ = e["key"]
    table, table_lo = LK.dense_block_table(keys, MAX_DENSE_BLOCKS)
    return cls(block_keys=keys, bits=bits, log2_blocks=log2, table=table, table_lo=table_lo,
               n_cells=int(e["n_cells"]), n_blocks=int(e["n_blocks"]), anchors=np.ascontiguousarray(anchors),
               cell_size_m=float(cell), dilation_cells=int(dil), build_s=float(e.get("build_s", 0.0)))


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
                work_origin=None) -> PreparedMap:
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
    timings: dict = {}
    D, N, F = prepare_cloud_features(P, params.voxel_size_m, params.octree_level, params.features, timings)
    if D.shape[0] < 10:
        raise TooFewPointsError(f"the map has only {D.shape[0]} points after downsampling ({params.describe()})")
    t0 = time.perf_counter()
    if params.icp_voxel_size_m is None:
        icp_pts = np.ascontiguousarray(P)
    else:
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
    log.info("prepared map: %d -> %d points (%s) in %.2f s", P.shape[0], D.shape[0], params.describe(), timings["total"])
    src = dict(source or {})
    src.setdefault("n_points", int(P.shape[0]))
    return PreparedMap(points=D, normals=N, features=F, icp_points=icp_pts, icp_normals=icp_nrm,
                       work_origin=np.asarray(work_origin, dtype=np.float64),
                       params=params, params_hash=params_hash(params), georef=gdict, crs=crs, source=src,
                       timings_s=timings, _georef_obj=georef)


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
    through :func:`~minegeo.localize.georef.load_georeferenced_map` and taken back to the map
    frame with :func:`~minegeo.localize.georef.crs_to_map` (exact inverse of the similarity),
    so registration is rigid in the frame the map was surveyed in, even when the
    georeferencing has a scale. A plain cloud is used as is.
    """
    from minegeo.io import read_point_cloud
    from minegeo.localize.georef import crs_to_map, load_georeferenced_map, sidecar_path

    p = Path(path)
    if not p.exists():
        raise InputError(f"map file {p} does not exist")
    if sidecar_path(p).exists() or p.name.endswith(".georef.json"):
        cloud, g = load_georeferenced_map(p)
        pts_map = crs_to_map(cloud.points, g)
        return PointCloud(points=pts_map, crs=g.crs, frame="map", metadata={"georeferenced": True}), g
    cloud = read_point_cloud(p)
    return cloud, None


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
    cloud, g = load_map_cloud(p)
    pm = prepare_map(cloud, params, georef=g, source={"path": str(p), "sha256": sha, "n_points": len(cloud.points),
                                                      "georeferenced": g is not None})
    if write_cache:
        try:
            pm.save(cp)
        except OSError as exc:
            log.warning("could not write prepared-map cache %s: %s", cp, exc)
    return pm, "computed"
