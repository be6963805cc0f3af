"""Registration quality: nearest-neighbour correspondences, fitness and inlier RMSE.

References
----------
Baek et al. (2022), Sensors 22, 2873, [Baek2022 Eq. 19] (inlier RMSE).
Open3D ``evaluate_registration`` semantics: ``../shared/specs/open3d_oracle.md`` §8.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from minegeo._validate import as_points, as_transform, check_positive
from minegeo.errors import InputError
from minegeo.kernels.kdtree import GatedKDTree
from minegeo.registration import _kernels as K

__all__ = ["evaluate_registration", "build_target_index", "nearest_within", "is_identity"]

#: Eigen's ``isIdentity`` precision used by Open3D to skip transforming the source.
IDENTITY_TOL = 1e-12


def is_identity(T, tol: float = IDENTITY_TOL) -> bool:
    """True when every entry of ``T`` is within ``tol`` of the 4x4 identity (Eigen ``isIdentity``)."""
    return bool(np.all(np.abs(np.asarray(T) - np.eye(4)) <= tol))


#: Queries with at least this many points use ``numba.get_num_threads()`` search workers.
PARALLEL_QUERY_MIN = 1024


def _kdtree(Q: np.ndarray):
    """Gated nearest-neighbour KD-tree over the target (:class:`minegeo.kernels.kdtree.GatedKDTree`)."""
    return GatedKDTree(Q)


def build_target_index(target_points):
    """Search structure over the target points, reusable across calls.

    A sliding-midpoint KD-tree written in Numba (:class:`minegeo.kernels.kdtree.GatedKDTree`) whose queries are
    bounded by the correspondence gate, so each query visits only a few leaves.

    Parameters
    ----------
    target_points : (m, 3) array_like
        Target points (metres). They must be the same array later passed as ``target``.
    """
    Q = as_points(target_points, "target")
    return _kdtree(Q)


def _query_nn(index, P: np.ndarray, d: float, m: int) -> np.ndarray:
    """Nearest target index per row of P (``m`` = no neighbour within ~d)."""
    # slightly inflated bound: the strict gate is applied afterwards on recomputed distances
    bound = d * (1.0 + 1e-9) + 1e-300
    if isinstance(index, cKDTree):
        workers = 1
        if P.shape[0] >= PARALLEL_QUERY_MIN:
            import numba

            workers = int(numba.get_num_threads())
        _, idx = index.query(P, k=1, distance_upper_bound=bound, workers=workers)
        return np.ascontiguousarray(np.asarray(idx, dtype=np.int64).reshape(-1))
    if hasattr(index, "query"):  # pykdtree.KDTree (same conventions)
        _, idx = index.query(P, k=1, distance_upper_bound=bound)
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        return np.ascontiguousarray(idx)
    if hasattr(index, "knn"):  # minegeo.geometry.NeighborIndex
        nb = index.knn(P, 1)
        idx = np.asarray(nb.indices, dtype=np.int64)[:, 0].copy()
        idx[idx < 0] = m
        return np.ascontiguousarray(idx)
    raise InputError(
        "target_index must come from build_target_index (or be a SciPy cKDTree, a pykdtree KDTree "
        "or a minegeo.geometry.NeighborIndex)"
    )


def nearest_within(P: np.ndarray, Q: np.ndarray, index, d: float):
    """Strictly gated nearest neighbours: ``(src_idx, tgt_idx, sq)`` with ``sq < d²``, ascending ``src_idx``.

    ``P`` and ``Q`` must already be validated contiguous float64 arrays (internal helper).
    """
    if isinstance(index, GatedKDTree):
        idx, sq = index.query(P, d * d)
        src = np.flatnonzero(idx < Q.shape[0])
        return src, idx[src], np.ascontiguousarray(sq[src])
    idx = _query_nn(index, P, d, Q.shape[0])
    sq, valid = K.gate_nearest_kernel(P, Q, idx, d * d)
    src = np.flatnonzero(valid)
    return src, idx[src], np.ascontiguousarray(sq[src])


def evaluate_registration(source, target, T, max_correspondence_distance_m: float, target_index=None):
    """Fitness and inlier RMSE of ``T_target_source`` (Open3D ``evaluate_registration``).

    Parameters
    ----------
    source : (n, 3) array_like
        Source points (metres, source frame).
    target : (m, 3) array_like
        Target points (metres, target frame).
    T : (4, 4) array_like
        ``T_target_source``; the source is mapped into the target frame with it, unless it is
        within 1e-12 of the identity (then it is used as is, like Open3D).
    max_correspondence_distance_m : float
        Gate ``d`` (metres, > 0): a source point is an inlier when its nearest target point is
        at squared distance ``< d²`` (strict).
    target_index : optional
        A reusable search structure over ``target`` from :func:`build_target_index`
        (a SciPy ``cKDTree``, a pykdtree ``KDTree`` or a ``minegeo.geometry.NeighborIndex`` also
        work); built on the fly when omitted.

    Returns
    -------
    fitness : float
        ``|C| / n``: fraction of source points with a target neighbour within ``d``.
    inlier_rmse_m : float
        ``sqrt(Σ_{(p,q)∈C} |T p - q|² / |C|)`` ([Baek2022 Eq. 19]), Euclidean; 0 when ``C`` is empty.
    correspondences : (|C|, 2) int64 ndarray
        ``(source index, target index)`` pairs in ascending source index.

    Raises
    ------
    InputError
        Bad shapes, NaN/inf, non-rigid ``T``, ``d`` not > 0 (Open3D silently returns fitness 0
        for ``d <= 0``; minegeo refuses it).
    """
    P = as_points(source, "source")
    Q = as_points(target, "target")
    T = as_transform(T, "T")
    d = check_positive(max_correspondence_distance_m, "max_correspondence_distance_m")
    if target_index is None:
        target_index = _kdtree(Q)
    if not is_identity(T):
        P = K.transform_points_kernel(P, T)
    return _evaluate_transformed(P, Q, target_index, d)


def _evaluate_transformed(P: np.ndarray, Q: np.ndarray, index, d: float):
    """Evaluate already-transformed source points: ``(fitness, rmse, corr (k,2))``."""
    src, tgt, sq = nearest_within(P, Q, index, d)
    corr = np.empty((src.size, 2), dtype=np.int64)
    corr[:, 0] = src
    corr[:, 1] = tgt
    if src.size == 0:
        return 0.0, 0.0, corr
    fitness = src.size / P.shape[0]
    rmse = float(np.sqrt(K.sum_kernel(sq) / src.size))
    return float(fitness), rmse, corr
