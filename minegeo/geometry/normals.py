"""Surface normals by PCA of local neighbourhoods (Baek et al. 2022, Sec. 2.3.1, [Baek2022 Eq. 2]).

For every point p_i with neighbourhood N_i (hybrid search: the ``<= max_nn`` nearest
points strictly inside ``radius_m``, p_i included; or the ``max_nn`` nearest when
``radius_m`` is None), the covariance

.. math:: C_i = \\frac{1}{|N_i|} \\sum_{j \\in N_i} (p_j - \\bar p)(p_j - \\bar p)^T

is eigen-decomposed, ``λ0 <= λ1 <= λ2``, and the normal is the eigenvector of the smallest
eigenvalue, ``n_i = V_0`` ([Baek2022 Eq. 2]). Shape descriptors returned alongside:

* curvature (surface variation) ``λ0 / (λ0 + λ1 + λ2)`` (0 on a plane, 1/3 for isotropic);
* planarity ``(λ1 - λ0) / λ2`` (≈1 on a plane, ≈0 on a line);
* linearity ``(λ2 - λ1) / λ2`` (≈1 when the neighbourhood is a line: normal undetermined).

Two modes (see ``docs/registration_geometry.md``):

``"accurate"`` (default)
    Two-pass covariance: differences to the query point, then to their mean, so the
    result does not degrade at projected coordinates of 10^6–10^7 m. Cyclic Jacobi
    eigen-solver (high relative accuracy, orthonormal vectors). Normals are oriented
    (see ``orient_towards``).
``"open3d"``
    Open3D 0.20 bit-for-bit: one-pass raw-moment covariance in absolute coordinates
    ``C = (1/N) Σ p pᵀ − m mᵀ`` and Eberly's closed-form ``FastEigen3x3`` with its exact
    sign behaviour; no orientation unless ``orient_towards`` is given. Use it for oracle
    comparisons only: at 10^6 m offsets cancellation in the raw moments destroys the normals.

Neighbourhoods with fewer than 3 points get the normal (0, 0, 1) (as Open3D) and
``status = STATUS_TOO_FEW``; all-coincident neighbourhoods ``STATUS_COINCIDENT``;
collinear ones (``λ1 <= degenerate_ratio · λ2``) keep the solver's vector (some unit
vector perpendicular to the line, deterministic) but are flagged ``STATUS_COLLINEAR``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError
from minegeo.geometry import _kernels as K
from minegeo.geometry.neighbors import Neighborhoods, NeighborIndex
from minegeo.kernels import eig3 as E3

__all__ = [
    "NormalParams",
    "NormalsResult",
    "estimate_normals",
    "STATUS_OK",
    "STATUS_TOO_FEW",
    "STATUS_COLLINEAR",
    "STATUS_COINCIDENT",
]

log = logging.getLogger(__name__)

STATUS_OK = E3.STATUS_OK
STATUS_TOO_FEW = E3.STATUS_TOO_FEW
STATUS_COLLINEAR = E3.STATUS_COLLINEAR
STATUS_COINCIDENT = E3.STATUS_COINCIDENT

_MODES = ("accurate", "open3d")


@dataclass(frozen=True)
class NormalParams:
    """Parameters of :func:`estimate_normals`.

    Attributes
    ----------
    radius_m : float or None
        Hybrid search radius in metres (strict, Open3D ``KDTreeSearchParamHybrid``).
        None: plain kNN with k = ``max_nn`` (Open3D's default ``KNN(30)``).
    max_nn : int
        Neighbour cap (hybrid) or k (kNN). The point itself counts.
    mode : {"accurate", "open3d"}
        Covariance and eigen-solver variant (see module docstring).
    degenerate_ratio : float
        A neighbourhood is flagged collinear when ``λ1 <= degenerate_ratio · λ2``.
    """

    radius_m: float | None = None
    max_nn: int = 30
    mode: str = "accurate"
    degenerate_ratio: float = 1e-8

    def __post_init__(self):
        if self.radius_m is not None:
            check_positive(self.radius_m, "radius_m")
        if isinstance(self.max_nn, bool) or not isinstance(self.max_nn, (int, np.integer)) or self.max_nn < 1:
            raise InputError(f"max_nn must be an integer >= 1, got {self.max_nn!r}")
        if self.mode not in _MODES:
            raise InputError(f"mode must be one of {_MODES}, got {self.mode!r}")
        check_positive(self.degenerate_ratio, "degenerate_ratio", allow_zero=True)


@dataclass(frozen=True)
class NormalsResult:
    """Normals and local shape descriptors, one row per input point.

    Attributes
    ----------
    normals : (n, 3) float64
        Unit normals (frame of the input points).
    curvature : (n,) float64
        ``λ0/(λ0+λ1+λ2)``; NaN where ``status`` is TOO_FEW or COINCIDENT.
    planarity, linearity : (n,) float64
        ``(λ1-λ0)/λ2`` and ``(λ2-λ1)/λ2``; NaN where undefined.
    eigenvalues : (n, 3) float64
        ``λ0 <= λ1 <= λ2`` of the neighbourhood covariance (m²).
    counts : (n,) int64
        Neighbourhood sizes (point itself included).
    status : (n,) int8
        ``STATUS_OK`` (0), ``STATUS_TOO_FEW`` (1, < 3 neighbours), ``STATUS_COLLINEAR`` (2),
        ``STATUS_COINCIDENT`` (3).
    params : NormalParams
    orientation : str
        How signs were chosen: ``"solver"``, ``"centroid"``, ``"point"`` or ``"trajectory"``.
    timings_s : dict
        Wall-clock seconds per stage.
    """

    normals: np.ndarray
    curvature: np.ndarray
    planarity: np.ndarray
    linearity: np.ndarray
    eigenvalues: np.ndarray
    counts: np.ndarray
    status: np.ndarray
    params: NormalParams
    orientation: str
    timings_s: dict = field(default_factory=dict)

    @property
    def n_flagged(self) -> dict:
        """Number of points per non-OK status."""
        return {
            "too_few": int(np.count_nonzero(self.status == STATUS_TOO_FEW)),
            "collinear": int(np.count_nonzero(self.status == STATUS_COLLINEAR)),
            "coincident": int(np.count_nonzero(self.status == STATUS_COINCIDENT)),
        }


def _targets(orient_towards, points: np.ndarray, mode: str):
    """(targets (m,3), index (n,), label) or None for no orientation."""
    n = points.shape[0]
    if orient_towards is None:
        if mode == "open3d":
            return None
        c = points.mean(axis=0).reshape(1, 3)
        return c, np.zeros(n, dtype=np.int64), "centroid"
    if isinstance(orient_towards, str):
        if orient_towards == "none":
            return None
        if orient_towards == "centroid":
            return points.mean(axis=0).reshape(1, 3), np.zeros(n, dtype=np.int64), "centroid"
        raise InputError(f"orient_towards must be None, 'none', 'centroid', a point or positions, got {orient_towards!r}")
    if hasattr(orient_towards, "poses"):
        orient_towards = np.asarray(orient_towards.poses, dtype=np.float64)[:, :3, 3]
    t = np.asarray(orient_towards, dtype=np.float64)
    if t.shape == (3,):
        t = as_points(t.reshape(1, 3), "orient_towards")
        return t, np.zeros(n, dtype=np.int64), "point"
    t = as_points(t, "orient_towards (trajectory positions)", min_points=1)
    if t.shape[0] == 1:
        return t, np.zeros(n, dtype=np.int64), "point"
    from pykdtree.kdtree import KDTree

    _, nearest = KDTree(t).query(points, k=1)
    return t, np.ascontiguousarray(np.asarray(nearest, dtype=np.int64).reshape(n)), "trajectory"


def estimate_normals(points, params: NormalParams | None = None, orient_towards=None,
                     neighborhoods: Neighborhoods | None = None,
                     index: NeighborIndex | None = None) -> NormalsResult:
    """Estimate unit normals by PCA of each point's neighbourhood ([Baek2022 Eq. 2]).

    Parameters
    ----------
    points : (n, 3) array_like of float
        Point cloud in metres (any frame; large projected coordinates are fine in the
        default mode).
    params : NormalParams, optional
        Search and solver settings; default ``NormalParams()`` (kNN 30, accurate).
    orient_towards : None, "none", "centroid", (3,) point, (m, 3) positions or Trajectory
        Sign rule: flip ``n_i`` when ``n_i · (s - p_i) < 0``, with ``s`` the given sensor
        position or the nearest trajectory position (normals then point into the drift
        void, towards where the scanner was). ``None``: mode "accurate" orients towards
        the cloud centroid (for a drift section the centroid lies in the void); mode
        "open3d" keeps the solver's sign like Open3D. When ``n_i · (s - p_i) == 0`` the
        largest-magnitude component is made positive. Positions must be in the same frame
        and relative to the same local origin as ``points``.
    neighborhoods : Neighborhoods, optional
        Precomputed neighbourhoods of ``points`` in ``points`` (row i = point i); the
        search parameters of ``params`` are then ignored.
    index : NeighborIndex, optional
        Reuse an index built on the same ``points``.

    Returns
    -------
    NormalsResult

    Raises
    ------
    InputError
        NaN/inf rows, wrong shapes, bad parameters or neighbourhoods of the wrong shape.
    TooFewPointsError
        Empty cloud.

    Notes
    -----
    The fused radius kernel searches and decomposes per point in one parallel pass, so
    no (n, max_nn) arrays are stored. Fallback normals (TOO_FEW, COINCIDENT) are not
    oriented.
    """
    params = NormalParams() if params is None else params
    if not isinstance(params, NormalParams):
        raise InputError(f"params must be a NormalParams, got {type(params).__name__}")
    pts = as_points(points, "points", min_points=1)
    n = pts.shape[0]
    mode_o3d = params.mode == "open3d"
    ratio = float(params.degenerate_ratio)
    normals = np.empty((n, 3))
    evals = np.empty((n, 3))
    status = np.empty(n, dtype=np.int8)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if neighborhoods is not None:
        if not isinstance(neighborhoods, Neighborhoods) or neighborhoods.indices.shape[0] != n:
            raise InputError("neighborhoods must be a Neighborhoods with one row per point")
        idx = np.ascontiguousarray(neighborhoods.indices, dtype=np.int64)
        if idx.size and (idx.max() >= n):
            raise InputError("neighborhoods refer to point indices outside this cloud")
        counts = np.ascontiguousarray(neighborhoods.counts, dtype=np.int64)
        K.normals_from_neighborhoods(pts, 0, idx, counts, mode_o3d, ratio, normals, evals, status)
    else:
        if index is None:
            index = NeighborIndex(pts)
        elif index.points is not pts and not np.array_equal(index.points, pts):
            raise InputError("index was built on a different cloud than points")
        counts = np.empty(n, dtype=np.int64)
        if params.radius_m is not None:
            rmax, cap = float(params.radius_m), int(params.max_nn)
            knn, r, g = index._hybrid_plan(rmax, cap)
        else:
            knn, cap, rmax = True, min(int(params.max_nn), n), np.inf
            cell, r = index._knn_cell(cap)
            g = index._grid_cell(cell)
        K.normals_hybrid_fused(knn, r, rmax, cap, mode_o3d, ratio, g.pts, g.order, *g.args(),
                               normals, evals, status, counts)
    timings["search_and_pca"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    tg = _targets(orient_towards, pts, params.mode)
    orientation = "solver"
    if tg is not None:
        targets, tindex, orientation = tg
        skip = (status == STATUS_TOO_FEW) | (status == STATUS_COINCIDENT)
        K.orient_normals(pts, normals, np.ascontiguousarray(targets), tindex, skip)
    timings["orientation"] = time.perf_counter() - t1

    with np.errstate(invalid="ignore", divide="ignore"):
        l0, l1, l2 = evals[:, 0], evals[:, 1], evals[:, 2]
        bad = (status == STATUS_TOO_FEW) | (status == STATUS_COINCIDENT)
        tot = l0 + l1 + l2
        curvature = np.where(bad, np.nan, l0 / tot)
        planarity = np.where(bad, np.nan, (l1 - l0) / l2)
        linearity = np.where(bad, np.nan, (l2 - l1) / l2)
    nflag = int(np.count_nonzero(status))
    if nflag:
        log.debug("estimate_normals: %d of %d points flagged degenerate", nflag, n)
    return NormalsResult(normals, curvature, planarity, linearity, evals, counts, status, params,
                         orientation, timings)
