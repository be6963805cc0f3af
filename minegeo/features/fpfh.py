"""Fast Point Feature Histograms (FPFH), 33-D surface descriptors.

References
----------
Rusu, R. B., Blodow, N., Beetz, M. (2009). Fast Point Feature Histograms (FPFH)
for 3D registration. ICRA 2009.

Baek, J., Park, J., Cho, S., Lee, C. (2022). 3D global localization in the
underground mine environment using mobile LiDAR mapping and point cloud
registration. Sensors 22, 2873. Sec. 2.3.1, [Baek2022 Eqs. 3-6], Table 3.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError
from minegeo.features import _kernels as K
from minegeo.geometry import NeighborIndex

__all__ = ["FPFHParams", "FPFHResult", "compute_fpfh", "hybrid_neighborhoods"]

log = logging.getLogger(__name__)

_WEIGHTS = {"inverse_distance": K.WEIGHT_INVERSE_DISTANCE, "open3d": K.WEIGHT_OPEN3D}
#: Neighbour-table entries (points x max_nn) above which the search runs in chunks, twice
#: (once for SPFH, once for FPFH), so memory stays near 16 bytes x this number.
_CHUNK_ENTRIES = 1 << 24


@dataclass(frozen=True)
class FPFHParams:
    """Parameters of :func:`compute_fpfh`.

    Parameters
    ----------
    radius_m : float
        Neighbourhood sphere radius r (m); neighbours satisfy ``|p_j - p_i| < r``
        (strict, as Open3D's hybrid search). Baek et al. (2022) Table 3: 2.5 m at
        a 0.5 m voxel size (5 voxels, as Open3D's tutorial).
    max_nn : int
        At most this many nearest neighbours inside the sphere, the point itself
        included (Table 3: 1000).
    weight : {"inverse_distance", "open3d"}
        Neighbour weight in [Baek2022 Eq. 6]. ``"inverse_distance"`` is the paper's
        ``1/omega_j`` with ``omega_j`` the Euclidean distance; ``"open3d"`` is
        ``1/omega_j^2`` (squared distance) as Open3D and PCL implement it. Both
        then scale each 11-bin block of the weighted neighbour sum to 100 before
        adding the point's own SPFH (which makes the paper's ``1/k`` immaterial).
    """

    radius_m: float = 2.5
    max_nn: int = 1000
    weight: str = "inverse_distance"

    def __post_init__(self):
        check_positive(self.radius_m, "FPFHParams.radius_m")
        if int(self.max_nn) != self.max_nn or self.max_nn < 2:
            raise InputError(f"FPFHParams.max_nn must be an integer >= 2, got {self.max_nn!r}")
        if self.weight not in _WEIGHTS:
            raise InputError(f"FPFHParams.weight must be one of {sorted(_WEIGHTS)}, got {self.weight!r}")


@dataclass(frozen=True)
class FPFHResult:
    """Output of :func:`compute_fpfh`.

    Attributes
    ----------
    features : ndarray, shape (n, 33)
        FPFH per point (float64). Blocks 0-10 (theta), 11-21 (alpha), 22-32 (phi)
        each sum to 200 for a point with neighbours at non-zero distance, 100
        when every neighbour coincides with it, and 0 for an isolated point.
    params : FPFHParams
        Parameters used.
    neighbor_counts : ndarray, shape (n,)
        Size of each neighbourhood, the point itself included.
    n_isolated : int
        Points without any neighbour other than themselves (all-zero feature;
        they cannot be matched and should be dropped before correspondence search).
    timings_s : dict
        Wall-clock seconds per stage (``neighbors``, ``spfh``, ``fpfh``).
    """

    features: np.ndarray
    params: FPFHParams
    neighbor_counts: np.ndarray
    n_isolated: int
    timings_s: dict = field(default_factory=dict)


def hybrid_neighborhoods(points: np.ndarray, radius_m: float, max_nn: int):
    """Hybrid (radius + max_nn) neighbourhoods with Open3D semantics.

    Returns ``(indices (n, kmax) int64 padded -1, sq_distances (n, kmax) padded inf,
    counts (n,) int64)``, sorted by ascending distance (ties: lowest index), the query
    point included, neighbours strictly closer than ``radius_m``
    (``minegeo.geometry.NeighborIndex.hybrid``).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    nb = NeighborIndex(points).hybrid(points, radius_m, max_nn)
    return _unpack_neighborhoods(nb, points.shape[0])


def _unpack_neighborhoods(nb, n: int, n_points: int | None = None):
    """Accept a ``Neighborhoods`` object or an ``(indices, sq_distances, counts)`` tuple.

    ``n`` rows are expected; indices must refer to ``n_points`` points (default ``n``).
    """
    n_points = n if n_points is None else n_points
    if isinstance(nb, tuple | list):
        idx, d2, counts = nb
    else:
        idx, d2, counts = nb.indices, nb.sq_distances, nb.counts
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    d2 = np.ascontiguousarray(d2, dtype=np.float64)
    counts = np.ascontiguousarray(counts, dtype=np.int64)
    if idx.ndim == 2 and idx.shape[1] == 0:
        idx = np.full((n, 1), -1, dtype=np.int64)
        d2 = np.full((n, 1), np.inf)
    if idx.ndim != 2 or idx.shape[0] != n or d2.shape != idx.shape or counts.shape != (n,):
        raise InputError(
            f"neighborhoods do not match the {n} points: indices {idx.shape}, "
            f"sq_distances {d2.shape}, counts {counts.shape}"
        )
    if n and (counts.min() < 0 or counts.max() > idx.shape[1]):
        raise InputError("neighborhoods.counts out of range of the index table")
    if n:
        used = idx[np.arange(idx.shape[1])[None, :] < counts[:, None]]
        if used.size and (used.min() < 0 or used.max() >= n_points):
            raise InputError("neighborhoods.indices refer to points that do not exist")
    return idx, d2, counts


def compute_fpfh(points, normals, params: FPFHParams | None = None, neighborhoods=None) -> FPFHResult:
    """Fast Point Feature Histogram of every point (33-D, float64).

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Point coordinates (m), any frame; use a local origin for projected
        coordinates. Must be finite.
    normals : array_like, shape (n, 3)
        Surface normals (unit length expected; used as given, as Open3D does).
        The descriptor depends on their signs.
    params : FPFHParams, optional
        Radius, max_nn and neighbour weight; defaults to Baek et al. (2022) Table 3.
    neighborhoods : Neighborhoods or tuple, optional
        Precomputed hybrid neighbourhoods ``(indices, sq_distances, counts)``
        (self at position 0, ascending). If omitted they are searched with
        ``params.radius_m`` and ``params.max_nn``.

    Returns
    -------
    FPFHResult

    Raises
    ------
    InputError
        Wrong shapes, NaN/inf, zero-length normals, inconsistent neighbourhoods.
    TooFewPointsError
        Fewer than 2 points.

    Notes
    -----
    For each point ``p_i`` and neighbour ``p_j`` the Darboux frame is
    ``u = n_i``, ``v = (p_j - p_i) x u / |.|``, ``w = u x v`` (Baek 2022 Sec. 2.3.1;
    the frame sits at whichever of the two points has the smaller angle between
    its normal and the connecting line, Rusu 2009), and

    .. math::
        \\alpha = v \\cdot n_j \\;(3), \\quad
        \\phi = u \\cdot \\frac{p_j - p_i}{\\|p_j - p_i\\|} \\;(4), \\quad
        \\theta = \\operatorname{atan2}(w \\cdot n_j, u \\cdot n_j) \\;(5).

    Each is binned into 11 equal bins over its range ([-pi, pi] or [-1, 1]);
    SPFH_i adds ``100/(k_i - 1)`` per neighbour, so each block sums to 100.
    [Baek2022 Eq. 6], ``FPFH_i = SPFH_i + (1/k) sum_j SPFH_j / omega_j``, is evaluated as in
    Open3D: the weighted neighbour sum (``omega_j = d_j`` or ``d_j^2``, see
    :class:`FPFHParams`) is scaled so each block sums to 100, then ``SPFH_i`` is
    added. With ``weight="open3d"`` and the same neighbourhoods and normals the
    result matches Open3D's ``compute_fpfh_feature`` to rounding.
    """
    params = FPFHParams() if params is None else params
    t = {}
    t0 = time.perf_counter()
    pts = as_points(points, "points", min_points=2)
    nrm = as_points(normals, "normals", min_points=2)
    if nrm.shape[0] != pts.shape[0]:
        raise InputError(f"normals has {nrm.shape[0]} rows but points has {pts.shape[0]}")
    zero = ~(np.abs(nrm) > 0).any(axis=1)
    if zero.any():
        raise InputError(
            f"normals contain {int(zero.sum())} zero-length vector(s) (first at row {int(np.flatnonzero(zero)[0])}); "
            "estimate normals before computing FPFH"
        )
    n = pts.shape[0]
    w = _WEIGHTS[params.weight]
    max_nn = int(params.max_nn)
    if neighborhoods is None and n * max_nn > _CHUNK_ENTRIES:
        # large cloud: search in chunks, once for the SPFH pass and again for the FPFH pass
        index = NeighborIndex(pts)
        chunk = max(1024, _CHUNK_ENTRIES // max_nn)
        spfh = np.empty((n, K.N_FEATURES))
        counts = np.empty(n, dtype=np.int64)
        t["neighbors"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for row0, nb in index.iter_hybrid(pts, params.radius_m, max_nn, chunk_size=chunk):
            idx, _, cnt = _unpack_neighborhoods(nb, len(nb), n)
            spfh[row0 : row0 + len(nb)] = K.spfh_kernel(pts, nrm, idx, cnt, row0)
            counts[row0 : row0 + len(nb)] = cnt
        t["spfh"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        feats = np.empty((n, K.N_FEATURES))
        for row0, nb in index.iter_hybrid(pts, params.radius_m, max_nn, chunk_size=chunk):
            idx, d2, cnt = _unpack_neighborhoods(nb, len(nb), n)
            feats[row0 : row0 + len(nb)] = K.fpfh_kernel(spfh, idx, d2, cnt, w, row0)
        t["fpfh"] = time.perf_counter() - t0
    else:
        if neighborhoods is None:
            idx, d2, counts = hybrid_neighborhoods(pts, params.radius_m, max_nn)
        else:
            idx, d2, counts = _unpack_neighborhoods(neighborhoods, n)
        t["neighbors"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        spfh = K.spfh_kernel(pts, nrm, idx, counts, 0)
        t["spfh"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        feats = K.fpfh_kernel(spfh, idx, d2, counts, w, 0)
        t["fpfh"] = time.perf_counter() - t0
    n_iso = int((counts <= 1).sum())
    if n_iso:
        log.info("FPFH: %d of %d points have no neighbour within %.3f m (zero descriptor)", n_iso, n, params.radius_m)
    return FPFHResult(features=feats, params=params, neighbor_counts=counts, n_isolated=n_iso, timings_s=t)
