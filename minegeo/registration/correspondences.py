"""Putative point correspondences from descriptor nearest neighbours.

Baek et al. (2022), Sec. 2.3.2 step 1: each source point is paired with the target
point whose FPFH is nearest in 33-D Euclidean distance (Open3D's
``correspondences_from_features``, spec ``open3d_oracle.md`` Sec. 5).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import InputError, TooFewPointsError
from minegeo.registration import _kernels_ransac as K

__all__ = ["FeatureIndex", "FeatureMatches", "RowTree", "build_feature_index", "feature_correspondences", "nearest_rows",
           "row_tree_from_partition", "row_tree_is_brute", "FEATURE_LEAF", "FEATURE_ROT"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeatureMatches:
    """Putative correspondences between two clouds.

    Attributes
    ----------
    pairs : ndarray, shape (k, 2), int64
        ``(source index, target index)`` rows in ascending source index.
    feature_sq_distances : ndarray, shape (k,)
        Squared 33-D descriptor distance of each pair.
    mutual_requested, mutual_applied : bool
        Whether the mutual (cross-check) filter was asked for, and whether its
        result was used (it is not when fewer than ``mutual_min_ratio`` of the
        matchable source points survive; the unfiltered set is then returned, as
        Open3D does, and ``reason`` says so).
    n_source_matchable, n_target_matchable : int
        Points whose descriptor is not all-zero (isolated points are excluded).
    reason : str
        Empty, or why the mutual filter was not applied.
    """

    pairs: np.ndarray
    feature_sq_distances: np.ndarray
    mutual_requested: bool
    mutual_applied: bool
    n_source_matchable: int
    n_target_matchable: int
    reason: str = ""


#: Below this many rows of ``B`` (in leaves) the tree does not pay off: brute force.
_TREE_MIN_LEAVES = 8
#: Rows per leaf of the descriptor tree (:class:`RowTree`).
FEATURE_LEAF = K.FEATURE_LEAF
#: Most leading principal directions the descriptor tree rotates onto (:class:`RowTree` ``V`` columns).
FEATURE_ROT = K.FEATURE_ROT


def nearest_rows(A: np.ndarray, B: np.ndarray, tree: RowTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact Euclidean nearest row of ``B`` for every row of ``A`` (any dimension).

    Parameters
    ----------
    A, B : ndarray (na, dim), (nb, dim), float64, finite
    tree : RowTree, optional
        The search structure of ``B`` from :func:`_row_tree` (``B`` must be the array it
        was built from), to search the same ``B`` many times without rebuilding it.

    Returns
    -------
    index : ndarray (na,) int64
        Row of ``B`` nearest to each row of ``A``; ties go to the lowest index.
    sq_distance : ndarray (na,)
        ``sum_c (A[i, c] - B[index, c])^2`` evaluated directly, c in order (not from an
        expansion such as ``|a|^2 + |b|^2 - 2 a.b``).

    Notes
    -----
    Descriptors such as FPFH are concentrated near a low-dimensional subspace, so the
    search runs on a kd partition of ``B`` in its principal axes: ``B`` and ``A`` are
    projected on the ``FEATURE_ROT`` leading eigenvectors ``V`` of the scatter matrix of
    ``B`` (``Q = (A - mu) V``), ``B`` is split into balanced leaves of ``FEATURE_LEAF``
    rows on the projected coordinate of largest spread, and each query scans its nearest
    leaf by box distance first, then only the leaves whose box lower bound can still hold
    a point at the best distance or closer; inside a leaf, a point whose distance over the
    first ``FEATURE_LEAD`` projected coordinates already exceeds the best is skipped. Both
    bounds are partial sums of an orthonormal rotation, corrected for its rounding, so
    they never rule out a point at the best distance. Every point not ruled out gets the
    direct distance above: the projection only decides which points are looked at, never
    which one wins, so the answer is the exact nearest row (lowest index on ties),
    bit-identical to the brute force and independent of the thread count. Small ``B``
    uses the brute force.
    """
    A = np.ascontiguousarray(A, dtype=np.float64)
    if tree is None:
        tree = _row_tree(B)
    elif tree.B is not B:
        raise InputError("the descriptor search tree was built for other rows than B")
    if tree.brute:
        idx, d2 = K.feature_nn_brute(A, tree.B)
    else:
        Q = K.feature_rotate(A, tree.mu, tree.V)
        # rounding of (x - mu) V in distance units: ~ (dim + 2) u |x - mu| per row; 1e-9 is generous
        ra = float(np.sqrt(np.max(np.einsum("ij,ij->i", A - tree.mu, A - tree.mu)))) if A.shape[0] else 0.0
        delta = 1e-9 * (1.0 + tree.B.shape[1]) * (ra + tree.rb)
        idx, d2 = K.feature_tree_nn(A, Q, tree.perm, tree.lstart, tree.lead, tree.Bp, tree.loT, tree.hiT, delta)
    if idx.size and int(idx.min()) < 0:
        raise InputError("descriptor values are too large to compare (squared distances overflow)")
    return idx, d2


@dataclass(frozen=True, eq=False)
class RowTree:
    """Search structure over the rows of ``B`` used by :func:`nearest_rows` (see its Notes)."""

    B: np.ndarray
    brute: bool
    mu: np.ndarray | None = None
    V: np.ndarray | None = None
    perm: np.ndarray | None = None
    lstart: np.ndarray | None = None
    lead: np.ndarray | None = None
    Bp: np.ndarray | None = None
    loT: np.ndarray | None = None
    hiT: np.ndarray | None = None
    rb: float = 0.0


def row_tree_is_brute(n: int) -> bool:
    """True when a descriptor set of ``n`` rows is searched by brute force, not by a :class:`RowTree` partition."""
    return n < _TREE_MIN_LEAVES * K.FEATURE_LEAF


def row_tree_from_partition(B: np.ndarray, mu: np.ndarray, V: np.ndarray, perm: np.ndarray, lstart: np.ndarray,
                            rb: float) -> RowTree:
    """The :class:`RowTree` over ``B`` from a stored rotation ``(mu, V)``, leaf order ``perm``, leaf starts
    ``lstart`` and radius bound ``rb`` (the leaf storage packed again from ``B``); the caller has checked them."""
    P = K.feature_rotate(B, mu, V)
    lead, Bp, loT, hiT = K.feature_tree_pack(B, P, perm, lstart)
    return RowTree(B=B, brute=False, mu=mu, V=V, perm=perm, lstart=lstart, lead=lead, Bp=Bp, loT=loT, hiT=hiT, rb=rb)


def _row_tree(B: np.ndarray) -> RowTree:
    """Build the kd partition of :func:`nearest_rows` over ``B`` (brute force when small)."""
    B = np.ascontiguousarray(B, dtype=np.float64)
    nb, dim = B.shape
    if row_tree_is_brute(nb):
        return RowTree(B=B, brute=True)
    mu, C = K.feature_mean_cov(B)
    _, V = np.linalg.eigh(C)
    V = np.ascontiguousarray(V[:, ::-1][:, : min(dim, K.FEATURE_ROT)])  # largest variance first
    P = K.feature_rotate(B, mu, V)
    perm, lstart = K.feature_tree_build(P)
    lead, Bp, loT, hiT = K.feature_tree_pack(B, P, perm, lstart)
    rb = float(np.sqrt(np.max(np.einsum("ij,ij->i", B - mu, B - mu))))
    return RowTree(B=B, brute=False, mu=mu, V=V, perm=perm, lstart=lstart, lead=lead, Bp=Bp, loT=loT, hiT=hiT, rb=rb)


@dataclass(frozen=True, eq=False)
class FeatureIndex:
    """Descriptor search structure over a target's features, built once and reused.

    Build it with :func:`build_feature_index` and pass it to :func:`feature_correspondences`
    (or :func:`minegeo.registration.register_ransac`) with the **same** feature array: the
    answers are bit-identical to searching without it, only the build is skipped.

    Attributes
    ----------
    features : (m, dim) float64
        The validated target descriptors the index was built from.
    drop_zero_features : bool
        Whether all-zero descriptors were left out (as in :func:`feature_correspondences`).
    rows : (k,) int64
        Target rows that take part in the search.
    """

    features: np.ndarray
    drop_zero_features: bool
    rows: np.ndarray
    tree: RowTree


def build_feature_index(target_features, drop_zero_features: bool = True) -> FeatureIndex:
    """Search structure over ``target_features`` (m, dim) for repeated :func:`feature_correspondences`.

    Raises
    ------
    InputError
        Not a finite 2-D array.
    TooFewPointsError
        No row (or, with ``drop_zero_features``, no non-zero row).
    """
    ft = _features(target_features, "target_features")
    t_ok = np.flatnonzero(np.any(ft != 0.0, axis=1)) if drop_zero_features else np.arange(ft.shape[0])
    if t_ok.size == 0:
        raise TooFewPointsError("no point has a non-zero descriptor in the target cloud: the FPFH radius is "
                                "smaller than the point spacing")
    return FeatureIndex(features=ft, drop_zero_features=bool(drop_zero_features), rows=t_ok,
                        tree=_row_tree(np.ascontiguousarray(ft[t_ok])))


def _features(arr, name):
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim != 2:
        raise InputError(f"{name} must be a 2-D array (n, dim), got shape {a.shape}")
    return as_points(a, name, dim=a.shape[1], min_points=1)


def feature_correspondences(
    source_features,
    target_features,
    mutual_filter: bool = False,
    mutual_min_ratio: float = 0.1,
    drop_zero_features: bool = True,
    target_index: FeatureIndex | None = None,
) -> FeatureMatches:
    """Nearest-neighbour matches in descriptor space (optionally mutual).

    Parameters
    ----------
    source_features, target_features : array_like, shape (n, dim), (m, dim)
        Descriptors (e.g. FPFH, dim = 33) of the source and target points.
    mutual_filter : bool
        Keep ``(i, j)`` only if ``i`` is also the nearest source descriptor of
        ``j`` (cross-check).
    mutual_min_ratio : float
        If fewer than ``floor(mutual_min_ratio * n)`` pairs survive the mutual
        filter, the unfiltered matches are returned (Open3D's rule, ratio 0.1).
    drop_zero_features : bool
        Ignore points whose descriptor is all zeros (isolated points: no
        neighbour within the FPFH radius). Open3D keeps them; their matches are
        arbitrary ties.
    target_index : FeatureIndex, optional
        From :func:`build_feature_index` on this very ``target_features`` array (same object)
        and the same ``drop_zero_features``: skips the target's validation and tree build.

    Returns
    -------
    FeatureMatches

    Notes
    -----
    The search is exact (see :func:`nearest_rows`); ties go to the lowest
    target index, so the result is deterministic.
    """
    fs = _features(source_features, "source_features")
    if target_index is not None:
        if not isinstance(target_index, FeatureIndex) or target_index.features is not target_features:
            raise InputError("target_index must come from build_feature_index on this target_features array")
        if target_index.drop_zero_features != bool(drop_zero_features):
            raise InputError("target_index was built with another drop_zero_features setting")
        ft = target_index.features
    else:
        ft = _features(target_features, "target_features")
    if fs.shape[1] != ft.shape[1]:
        raise InputError(
            f"source and target descriptors differ in length ({fs.shape[1]} vs {ft.shape[1]})"
        )
    if not 0.0 <= float(mutual_min_ratio) <= 1.0:
        raise InputError(f"mutual_min_ratio must be in [0, 1], got {mutual_min_ratio!r}")
    s_ok = np.flatnonzero(np.any(fs != 0.0, axis=1)) if drop_zero_features else np.arange(fs.shape[0])
    if target_index is not None:
        t_ok, tree = target_index.rows, target_index.tree
    else:
        t_ok = np.flatnonzero(np.any(ft != 0.0, axis=1)) if drop_zero_features else np.arange(ft.shape[0])
        tree = None
    if s_ok.size == 0 or t_ok.size == 0:
        raise TooFewPointsError(
            "no point has a non-zero descriptor in the "
            + ("source" if s_ok.size == 0 else "target")
            + " cloud: the FPFH radius is smaller than the point spacing"
        )
    A = np.ascontiguousarray(fs[s_ok])
    B = tree.B if tree is not None else np.ascontiguousarray(ft[t_ok])
    j_loc, d2 = nearest_rows(A, B, tree)
    pairs = np.stack([s_ok, t_ok[j_loc]], axis=1).astype(np.int64)
    applied = False
    reason = ""
    if mutual_filter:
        # only the target rows that some source row chose can be mutual: search back from
        # those alone (exact search, same tie rule, so the same answer as searching from all)
        uj, inv = np.unique(j_loc, return_inverse=True)
        i_back, _ = nearest_rows(np.ascontiguousarray(B[uj]), A)
        keep = i_back[inv.reshape(-1)] == np.arange(A.shape[0])
        need = int(np.float32(mutual_min_ratio) * A.shape[0])
        if int(keep.sum()) < need:
            reason = (
                f"mutual filter kept {int(keep.sum())} of {A.shape[0]} matches (< {need}); "
                "using the unfiltered matches"
            )
            log.warning(reason)
        else:
            pairs = pairs[keep]
            d2 = d2[keep]
            applied = True
    return FeatureMatches(
        pairs=np.ascontiguousarray(pairs),
        feature_sq_distances=np.ascontiguousarray(d2),
        mutual_requested=bool(mutual_filter),
        mutual_applied=applied,
        n_source_matchable=int(s_ok.size),
        n_target_matchable=int(t_ok.size),
        reason=reason,
    )
