"""Building a prepared map: downsampling, oriented normals and FPFH of a cloud (:func:`prepare_map`) or of a
map file read in chunks under a memory budget (:func:`prepare_map_file`), and the on-disk cache
(:func:`load_or_prepare`).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

from minegeo._provenance import sha256_file, to_jsonable
from minegeo._validate import as_points
from minegeo.errors import FileFormatError, InputError, TooFewPointsError
from minegeo.io.types import PointCloud
from minegeo.localize._progress import FEATURE_STEPS, StepTimings, announce
from minegeo.localize.params import FeatureParams, PrepareParams
from minegeo.localize.prepared.model import PreparedMap, params_hash

#: the prepared map's one logger for all its modules (the CLI filters its summary line by this name)
log = logging.getLogger("minegeo.localize.prepared")


#: Nearest neighbours of the PCA normals of the ICP target.
ICP_NORMAL_NN = 20


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
