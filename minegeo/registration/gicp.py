"""Generalized-ICP (GICP, plane-to-plane ICP) with an Open3D-compatible mode.

Frames: ``source_points`` are in the source (scan) frame, ``target_points`` in the target
(map) frame. The result ``T_target_source`` maps the scan into the map:
``p_map = R p_scan + t``.

Model (Segal, Haehnel & Thrun 2009; Ren et al. 2019, Sec. 3.2, [Ren2019 Eqs. 1-6]). Every point carries
a covariance ``C`` describing the local surface; for a pair ``(b_i, m_i)`` (source point, its
nearest target point) the residual ``d_i = m_i - T b_i`` ([Ren2019 Eq. 4]) is modelled as
``N(0, C_i^M + R C_i^B Rᵀ)`` ([Ren2019 Eq. 5]), and the pose maximises the likelihood ([Ren2019 Eq. 6]; the paper
writes *arg max* in front of the quadratic form, it is the minimum of)

.. math:: T^* = \\arg\\min_T \\sum_i d_i^T (C_i^M + R C_i^B R^T)^{-1} d_i .

The covariance of a point is plane-like: from the PCA of its ``k`` nearest neighbours
([Ren2019 Eq. 2]), the eigenvalues are replaced by ``(ε, 1, 1)`` ([Ren2019 Eq. 3]), i.e.
``C = U diag(ε, 1, 1) Uᵀ = I - (1 - ε) n nᵀ`` with ``n`` the surface normal: a pair is
penalised ``1/ε`` times more across the surfaces than along them.

Correspondences and loop are those of :func:`minegeo.registration.register_icp` (Open3D
``registration_icp``; oracle spec §10, §11): Euclidean nearest neighbour with the strict gate
``|Tp - q|² < d²``, one Gauss-Newton step per iteration. By default the loop stops when a step
moves the source by less than 1e-5 m and 1e-6 rad, or on a 2-cycle of correspondence sets;
:meth:`GICPParams.open3d` restores Open3D's test (fitness and Euclidean inlier-RMSE changes below
1e-6) and covariances, and then reproduces Open3D's transform to ~1e-15; what differs in that mode is
in :mod:`minegeo.registration.open3d_compat`. See ``docs/registration_gicp.md``.

References
----------
Segal, A., Haehnel, D., Thrun, S. (2009). Generalized-ICP. Robotics: Science and Systems V.
Ren, Z., Wang, L., Bi, L. (2019). Robust GICP-based 3D LiDAR SLAM for underground mining
environment. Sensors 19, 2915. Sec. 3.2, [Ren2019 Eqs. 1-6].
Open3D 0.20 ``registration_generalized_icp`` (``../shared/specs/open3d_oracle.md`` §11).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numba
import numpy as np

from minegeo._provenance import StageTimer
from minegeo._validate import as_points, as_transform, as_trusted_points, internal_transform
from minegeo.errors import InputError
from minegeo.geometry.normals import STATUS_OK
from minegeo.kernels.kdtree import KD_LEAF, GatedKDTree, kd_build
from minegeo.registration import _kernels as K
from minegeo.registration import _kernels_gicp as KG
from minegeo.registration._kernels_loop import compact_matches
from minegeo.registration.evaluation import is_identity
from minegeo.registration.icp import ICPResult, constraint_analysis, result_fields
from minegeo.registration.loop import (
    GICPFactor,
    GICPNearestInGate,
    GICPSystem,
    LoopOutcome,
    Matches,
    Termination,
    rotation_angle,
    run_loop,
)
from minegeo.registration.open3d_compat import GICP_OPEN3D_FIELDS, convergence_tests, covariance_convention

__all__ = [
    "GICPParams",
    "GICPResult",
    "register_gicp",
    "estimate_gicp_covariances",
    "gicp_covariances_on_tree",
    "COVARIANCE_MODES",
    "CONVERGENCE_TESTS",
]

log = logging.getLogger(__name__)

#: Covariance conventions: minegeo's default and Open3D 0.20's.
COVARIANCE_MODES = ("minegeo", "open3d")
#: Convergence tests: minegeo's step test and Open3D's fitness/RMSE-change test.
CONVERGENCE_TESTS = ("step", "open3d")
#: Minimum number of points in each cloud (and of pairs for a full-rank step).
MIN_POINTS = 3
#: Coordinates larger than this (m) suggest projected coordinates without a local origin.
LARGE_COORDINATE_M = 1e5
#: Relative tolerance of the symmetry check on user covariances.
SYMMETRY_RTOL = 1e-9
#: Clouds and searches of at least this many points run the per-point kernels (kNN covariances,
#: the fused search + GICP sums) as ``prange`` tasks; fewer run serially. The bits are the same
#: either way (per-point results; sums over fixed chunks of ``GICP_ROWS`` rows, added in order).
#: Measured on the shared 2-core machine (load average ~9, benchmarks/results/gicp_2026-11-25.md):
#: on the 5,004-point small_gicp pair a ``prange`` region per iteration made a registration 4-8x
#: slower (each region waits for a descheduled worker thread), so on a busy machine small clouds
#: stay serial ...
PARALLEL_MIN_ROWS = 1 << 16
PARALLEL_SEARCH_ROWS = 1 << 16
#: ... while with two or more Numba threads (:func:`_parallel_rows`; never chosen from the machine's
#: load) clouds from this size run in ``prange`` already: on the same pair at
#: load 0.3 the fused search went from 11.2 to 7.0 ms per registration on 2 threads
#: (benchmarks/results/gicp_2026-11-25_parallel.md). Speed only: the same bits either way.
IDLE_PARALLEL_ROWS = 2048
#: With two or more Numba threads, the source and target covariances of at least this many points
#: each are estimated in one ``prange`` region over both clouds' tasks
#: (:func:`~minegeo.registration._kernels_gicp.knn_normals_pair_tasks`; no barrier per iteration).
#: The bits are those of the sequential estimate.
CONCURRENT_MIN_POINTS = 1024
#: The registration loops: ``"kernel"`` runs the default loop (``convergence="step"``) as one kernel
#: (:func:`~minegeo.registration._kernels_gicp.gicp_step_loop`, no return to Python per iteration;
#: on the small_gicp pair 0.4-0.8 ms less per registration of 7-10 iterations); ``"python"`` runs
#: :func:`~minegeo.registration.loop.run_loop`, the reference the kernel is tested against, and the
#: loop of ``convergence="open3d"``. When the target's covariances are estimated in the call, its
#: kNN lists are kept and a source point whose previous partner ``j`` is nearer than half the
#: distance of ``j``'s last neighbour takes its new partner from that list instead of the tree (the
#: same answer, bit for bit: :func:`~minegeo.registration._kernels_gicp._list_nearest`).
ENGINES = ("kernel", "python")

def _is_number(v) -> bool:
    return isinstance(v, int | float | np.floating | np.integer) and not isinstance(v, bool)


@dataclass(frozen=True)
class GICPParams:
    """Parameters of :func:`register_gicp`.

    The model parameters (ε, k) are those of Ren 2019, Segal 2009, Open3D and small_gicp. The
    defaults differ from Open3D in the convergence test and in the covariance details (see
    ``convergence``, ``stop_on_cycle`` and ``covariance_mode``); :meth:`GICPParams.open3d`
    gives Open3D 0.20's behaviour exactly.

    Attributes
    ----------
    max_correspondence_distance_m : float
        Gate ``d`` (metres, > 0): pairs with squared distance ``>= d²`` are ignored.
    max_iterations : int
        Maximum number of Gauss-Newton updates (>= 0). Open3D default 30.
    convergence : {"step", "open3d"}
        ``"step"`` (default): converged when the last update moved the source by less than
        ``step_translation_m`` **and** rotated it by less than ``step_rotation_rad``.
        ``"open3d"``: Open3D's test, ``|fitness_k - fitness_{k-1}| < relative_fitness`` **and**
        ``|rmse_k - rmse_{k-1}| < relative_rmse``. The Euclidean inlier RMSE is flat near the
        optimum and is not what GICP minimises, so Open3D's test can stop while the pose is
        still moving (measured: after a 11.5 mm step on a synthetic surface, 1 mm from the
        converged answer).
    step_translation_m : float
        Translation threshold of the step test (metres, >= 0).
    step_rotation_rad : float
        Rotation-angle threshold of the step test (radians, >= 0).
    relative_fitness : float
        Open3D's fitness-change threshold (an absolute difference of fractions); only used
        with ``convergence="open3d"``.
    relative_rmse : float
        Open3D's threshold on ``|rmse_k - rmse_{k-1}|`` (metres, Euclidean inlier RMSE); only
        used with ``convergence="open3d"``.
    epsilon : float
        ``ε`` of [Ren2019 Eq. 3]: variance across the surface relative to along it
        (dimensionless, 0 < ε <= 1). 1e-3 in Ren 2019, Segal 2009, Open3D and small_gicp.
    covariance_neighbours : int
        ``k`` of the kNN neighbourhood (point itself included) whose PCA gives the normal of
        each point without a given covariance or normal ([Ren2019 Eq. 2]). 20 as Open3D and Segal 2009.
    covariance_mode : {"minegeo", "open3d"}
        ``"minegeo"`` (default): two-pass centred neighbourhood covariance and a Jacobi
        eigen-solver (exact at projected 10⁶ m coordinates), ``C = I - (1-ε) n nᵀ`` exactly,
        and ``C = I`` (isotropic, no surface assumed) for points whose neighbourhood is
        collinear, coincident or has fewer than 3 points. ``"open3d"``: Open3D 0.20 bit for
        bit — raw-moment covariance and ``FastEigen3x3`` normals, the Rodrigues rotation
        e_x -> n which is replaced by the identity when ``n_x < -0.99`` (so such points get
        ``diag(ε, 1, 1)``, up to 8.1° off their surface), degenerate neighbourhoods get the
        normal (0, 0, 1).
    degeneracy_ratio_threshold : float
        Flag the result as degenerate when the smallest/largest eigenvalue of the normalised
        point-to-plane constraint matrix (:func:`minegeo.registration.constraint_analysis`,
        target normals at the matched points) is below this (dimensionless, in (0, 1)).
    stop_on_cycle : bool
        Also stop (converged) when the correspondence set equals the one of two iterations
        before while the last step changed it: the Gauss-Newton fixed points of two pair sets
        alternate and Open3D's fitness/RMSE test would never hold (measured on the small_gicp
        pair: a 2-cycle of 0.24 mm / 1.9e-5 rad that ran to ``max_iterations``). Of the two
        alternating states the one with the lower mean Mahalanobis cost is returned, so the
        answer does not depend on the phase the iteration stopped in (nor on the frame). The
        cycle amplitude is reported. False reproduces Open3D.

    Use :meth:`GICPParams.open3d` for the Open3D-compatible parameter set.
    """

    max_correspondence_distance_m: float
    max_iterations: int = 30
    convergence: str = "step"
    step_translation_m: float = 1e-5
    step_rotation_rad: float = 1e-6
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    epsilon: float = 1e-3
    covariance_neighbours: int = 20
    covariance_mode: str = "minegeo"
    degeneracy_ratio_threshold: float = 1e-2
    stop_on_cycle: bool = True

    @classmethod
    def open3d(cls, max_correspondence_distance_m: float, **overrides) -> GICPParams:
        """Open3D 0.20 ``registration_generalized_icp`` semantics: ``covariance_mode="open3d"``,
        ``convergence="open3d"`` and no cycle stop (other fields as given, defaults = Open3D's
        ``ICPConvergenceCriteria(1e-6, 1e-6, 30)`` and ``epsilon=1e-3``)."""
        kw = {**GICP_OPEN3D_FIELDS, **overrides}
        return cls(max_correspondence_distance_m, **kw)

    def __post_init__(self):
        d = self.max_correspondence_distance_m
        if not _is_number(d) or not np.isfinite(d) or d <= 0:
            raise InputError(
                f"max_correspondence_distance_m must be a finite distance > 0 m, got {d!r}"
            )
        it = self.max_iterations
        if isinstance(it, bool) or not isinstance(it, int | np.integer) or it < 0:
            raise InputError(f"max_iterations must be an integer >= 0, got {it!r}")
        if self.convergence not in CONVERGENCE_TESTS:
            raise InputError(f"convergence must be one of {CONVERGENCE_TESTS}, got {self.convergence!r}")
        for name in ("relative_fitness", "relative_rmse", "step_translation_m", "step_rotation_rad"):
            v = getattr(self, name)
            if not _is_number(v) or not np.isfinite(v) or v < 0:
                raise InputError(f"{name} must be finite and >= 0, got {v!r}")
        e = self.epsilon
        if not _is_number(e) or not np.isfinite(e) or not 0 < e <= 1:
            raise InputError(f"epsilon must be in (0, 1] (dimensionless), got {e!r}")
        k = self.covariance_neighbours
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 3:
            raise InputError(f"covariance_neighbours must be an integer >= 3, got {k!r}")
        if self.covariance_mode not in COVARIANCE_MODES:
            raise InputError(
                f"covariance_mode must be one of {COVARIANCE_MODES}, got {self.covariance_mode!r}"
            )
        r = self.degeneracy_ratio_threshold
        if not _is_number(r) or not np.isfinite(r) or not 0 < r < 1:
            raise InputError(f"degeneracy_ratio_threshold must be in (0, 1), got {r!r}")
        if not isinstance(self.stop_on_cycle, bool | np.bool_):
            raise InputError(f"stop_on_cycle must be True or False, got {self.stop_on_cycle!r}")


@dataclass(frozen=True)
class GICPResult(ICPResult):
    """Outcome of :func:`register_gicp`: every field of :class:`ICPResult`, plus the GICP cost.

    Differences in meaning from ICP
    -------------------------------
    information_6x6 : (6, 6) ndarray
        GICP Gauss-Newton matrix at the solution, ``H = Σ J_iᵀ M_i⁻¹ J_i`` with
        ``J_i = [-[p_i]×, I3]`` and ``M_i = C_i^M + R C_i^B Rᵀ``; parameters
        ``(ω_x, ω_y, ω_z, t_x, t_y, t_z)`` (rad, then m), left perturbation in the target
        frame about its origin. The covariances are dimensionless shape matrices, so the pose
        covariance is ``sigma_m² H⁻¹`` (``pose_covariance(information_6x6, sigma_m)``).
    params : GICPParams

    Attributes
    ----------
    mahalanobis_cost : float
        ``Σ d_iᵀ M_i⁻¹ d_i`` over the final pairs (m², [Ren2019 Eq. 6]).
    sigma_m : float
        ``sqrt(cost / (3k - 6))`` with ``k`` pairs: a posteriori scale of the covariances
        (metres). Neighbouring residuals are correlated, so ``sigma_m² H⁻¹`` is optimistic.
    source_covariances_from, target_covariances_from : str
        ``"given"`` (used unchanged), ``"normals"`` (plane model from given normals) or
        ``"estimated"`` (kNN PCA, then the plane model).
    convergence_reason : str
        ``"step"`` (the step test held), ``"fitness_rmse"`` (Open3D's test held),
        ``"cycle"`` (2-cycle of correspondence sets,
        see ``GICPParams.stop_on_cycle``) or ``""`` (not converged).
    cycle_amplitude_m, cycle_amplitude_rad : float
        Size of the last step when stopped on a cycle (translation m, rotation rad): how far
        apart the two alternating solutions are; 0 otherwise.
    """

    mahalanobis_cost: float = 0.0
    sigma_m: float = 0.0
    source_covariances_from: str = ""
    target_covariances_from: str = ""
    convergence_reason: str = ""
    cycle_amplitude_m: float = 0.0
    cycle_amplitude_rad: float = 0.0


def _parallel_rows(busy_rows: int) -> int:
    """The ``prange`` threshold (rows): :data:`IDLE_PARALLEL_ROWS` when this thread has two or more
    Numba threads (the thread count the user set), else ``busy_rows``. Chosen from the problem size
    and the thread count only, never from the machine's load. Speed only: serial and ``prange``
    drivers give the same bits."""
    if numba.get_num_threads() < 2:
        return busy_rows
    return min(busy_rows, IDLE_PARALLEL_ROWS)


def _knn_normals(points: np.ndarray, tree, k: int, mode_open3d: bool, parallel: bool = True, lists=None):
    """``(normals, status, eigenvalues)`` of :func:`~minegeo.registration._kernels_gicp.knn_normals_kernel`,
    with the points cut into ``prange`` tasks from :func:`_parallel_rows` points when ``parallel``
    (the same bits). ``lists`` = ``(nb (m, k), rk (m,))`` also receives the neighbour lists."""
    m = points.shape[0]
    out_n = np.empty((m, 3))
    out_eval = np.empty((m, 3))
    out_status = np.empty(m, dtype=np.int8)
    kk = min(int(k), m)
    args = (points, tree, kk, bool(mode_open3d), float(KG.DEGENERATE_RATIO), out_n, out_eval,
            out_status)
    if lists is None:
        lists = (np.empty((0, kk), np.int64), np.empty(0))
    if parallel and m >= _parallel_rows(PARALLEL_MIN_ROWS):
        KG.knn_normals_tasks(*args, *lists)
    else:
        KG.knn_normals_lists_serial(*args, *lists)
    return out_n, out_status, out_eval


def _covariances_of_pair(P0: np.ndarray, Q: np.ndarray, tree_q, params: GICPParams, lists):
    """``(Cs, Ct, Nt)`` of :func:`_covariances_and_normals` for both clouds, their kNN PCA in one
    ``prange`` region (:func:`~minegeo.registration._kernels_gicp.knn_normals_pair_tasks`; the same
    bits); ``lists`` receives the target's kNN lists."""
    conv = covariance_convention(params)
    k = int(params.covariance_neighbours)
    tree_p = kd_build(P0, KD_LEAF)
    n, m = P0.shape[0], Q.shape[0]
    out = [(np.empty((c, 3)), np.empty((c, 3)), np.empty(c, dtype=np.int8)) for c in (n, m)]
    KG.knn_normals_pair_tasks(P0, tree_p, min(k, n), Q, tree_q, min(k, m), conv.pca_open3d,
                              float(KG.DEGENERATE_RATIO), *out[0], np.empty((0, min(k, n)), np.int64), np.empty(0),
                              *out[1], *lists)
    Cs, Ct = (_plane_covariances(N, conv.isotropic(st != STATUS_OK), params) for N, _, st in out)
    return Cs, Ct, out[1][0]


def _plane_covariances(normals: np.ndarray, isotropic: np.ndarray, params: GICPParams) -> np.ndarray:
    return KG.plane_covariances_kernel(
        np.ascontiguousarray(normals), np.ascontiguousarray(isotropic, dtype=np.bool_),
        float(params.epsilon), covariance_convention(params).rodrigues,
    )


def _covariances_and_normals(points: np.ndarray, params: GICPParams, normals=None, name: str = "points",
                             tree=None, parallel: bool = True, lists=None):
    """``(C (n,3,3), N (n,3), source)`` for validated ``points``; see :func:`estimate_gicp_covariances`.
    ``lists`` (see :func:`_knn_normals`) receives the kNN lists when the PCA runs."""
    n = points.shape[0]
    conv = covariance_convention(params)
    if normals is not None:
        N = as_points(normals, f"{name} normals")
        if N.shape[0] != n:
            raise InputError(f"{name} normals have {N.shape[0]} rows but there are {n} points")
        return _plane_covariances(N, conv.isotropic(~(np.linalg.norm(N, axis=1) > 0)), params), N, "normals"
    tree = kd_build(points, KD_LEAF) if tree is None else tree
    N, status, _ = _knn_normals(points, tree, int(params.covariance_neighbours), conv.pca_open3d, parallel, lists)
    return _plane_covariances(N, conv.isotropic(status != STATUS_OK), params), N, "estimated"


def estimate_gicp_covariances(points, params: GICPParams | None = None, normals=None) -> np.ndarray:
    """Per-point plane-like GICP covariances ([Ren2019 Eqs. 2-3]; Segal 2009 Sec. III-B).

    Cache the result for a map that is registered against many times and pass it to
    :func:`register_gicp` as ``target_covariances``.

    Parameters
    ----------
    points : (n, 3) array_like
        Cloud in metres (any frame; the covariances are expressed in that frame).
    params : GICPParams, optional
        Uses ``epsilon``, ``covariance_neighbours`` and ``covariance_mode`` (default
        ``GICPParams(1.0)``, i.e. ε = 1e-3, k = 20, mode "minegeo").
    normals : (n, 3) array_like, optional
        Surface normals to use instead of a kNN PCA (sign irrelevant). In mode "minegeo" a
        zero normal gives the isotropic covariance ``I``.

    Returns
    -------
    (n, 3, 3) ndarray
        ``C_i = I - (1 - ε) n_i n_iᵀ`` (mode "minegeo"; ``I`` for degenerate neighbourhoods),
        or Open3D's ``R_i diag(ε, 1, 1) R_iᵀ`` (mode "open3d"). Dimensionless.

    Raises
    ------
    InputError
        NaN/inf rows, wrong shapes, bad parameters.
    TooFewPointsError
        Empty cloud.
    """
    params = GICPParams(1.0) if params is None else params
    if not isinstance(params, GICPParams):
        raise InputError(f"params must be a GICPParams, got {type(params).__name__}")
    P = as_points(points, "points", min_points=1)
    return _covariances_and_normals(P, params, normals)[0]


def gicp_covariances_on_tree(points: np.ndarray, params: GICPParams, index: GatedKDTree,
                             with_surface: bool = False):
    """:func:`estimate_gicp_covariances` of ``points`` from the kNN of an existing search tree.

    Parameters
    ----------
    points : (n, 3) ndarray
        C-contiguous float64 cloud (m), already validated (e.g. by
        :func:`minegeo.registration.build_target_index`).
    params : GICPParams
        Uses ``epsilon``, ``covariance_neighbours`` and ``covariance_mode``.
    index : GatedKDTree
        The tree of :func:`minegeo.registration.build_target_index` over these very points.

    with_surface : bool
        Also return the kNN PCA behind the covariances.

    Returns
    -------
    (n, 3, 3) ndarray
        The covariances of :func:`estimate_gicp_covariances` (the same bits: the kNN is exact).
        With ``with_surface``: ``(covariances, normals (n, 3), eigenvalues (n, 3) of the
        neighbourhood covariance (m², any order), status (n,) int8 of
        :mod:`minegeo.geometry.normals`)``.

    Raises
    ------
    InputError
        ``index`` is not a KD-tree over ``points``.
    """
    if not isinstance(index, GatedKDTree) or not (index.data is points or np.array_equal(index.data, points)):
        raise InputError("index must be the KD-tree of build_target_index over these points")
    if not with_surface:
        return _covariances_and_normals(index.data, params, tree=index.packed)[0]
    conv = covariance_convention(params)
    N, status, ev = _knn_normals(index.data, index.packed, int(params.covariance_neighbours), conv.pca_open3d)
    return _plane_covariances(N, conv.isotropic(status != STATUS_OK), params), N, ev, status


def _as_covariances(C, n: int, name: str) -> np.ndarray:
    """Validate user covariances: (n, 3, 3), finite, symmetric, positive definite (Sylvester)."""
    try:
        a = np.asarray(C, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from None
    if a.shape != (n, 3, 3):
        raise InputError(f"{name} must have shape ({n}, 3, 3) (one 3x3 matrix per point), got {a.shape}")
    f = a.reshape(n, 9)
    if KG.covariances_valid(np.ascontiguousarray(f), SYMMETRY_RTOL):  # the checks below in one pass
        return np.ascontiguousarray(a)
    if not np.isfinite(f).all():
        bad = np.flatnonzero(~np.isfinite(f).all(axis=1))
        raise InputError(f"{name} has {bad.size} matrix(es) with NaN or inf (first at row {int(bad[0])})")
    scale = np.abs(f).max(axis=1)
    asym = np.maximum(np.maximum(np.abs(f[:, 1] - f[:, 3]), np.abs(f[:, 2] - f[:, 6])), np.abs(f[:, 5] - f[:, 7]))
    bad = asym > SYMMETRY_RTOL * np.maximum(scale, 1e-300)
    if bad.any():
        raise InputError(f"{name} has {int(bad.sum())} non-symmetric matrix(es) (first at row "
                         f"{int(np.flatnonzero(bad)[0])})")
    # Sylvester's criterion: the three leading principal minors are positive
    a00, a01, a02, a11, a12, a22 = f[:, 0], f[:, 1], f[:, 2], f[:, 4], f[:, 5], f[:, 8]
    m2 = a00 * a11 - a01 * a01
    m3 = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    pd = (a00 > 0) & (m2 > 0) & (m3 > 0)
    if not pd.all():
        raise InputError(
            f"{name} has {int((~pd).sum())} matrix(es) that are not positive definite (first at row "
            f"{int(np.flatnonzero(~pd)[0])}); GICP needs invertible covariances"
        )
    return np.ascontiguousarray(a)


def register_gicp(source_points, target_points, T_init, params: GICPParams, source_covariances=None,
                  target_covariances=None, source_normals=None, target_normals=None,
                  target_index=None, *, check_target: bool = True, trusted_init: bool = False,
                  engine: str = "kernel") -> GICPResult:
    """Refine ``T_target_source`` by Generalized-ICP (Segal 2009; Ren 2019 Sec. 3.2, [Ren2019 Eqs. 1-6]).

    Parameters
    ----------
    source_points : (n, 3) array_like
        Scan points (metres, source frame), e.g. voxel-downsampled.
    target_points : (m, 3) array_like
        Map points (metres, target frame). Use coordinates relative to a recorded local
        origin, not raw projected coordinates.
    T_init : (4, 4) array_like
        Initial ``T_target_source`` (e.g. from RANSAC or the previous odometry pose).
    params : GICPParams
        Gate, iteration limit, convergence thresholds, ε, neighbourhood size and mode.
    source_covariances, target_covariances : (n, 3, 3) / (m, 3, 3) array_like, optional
        Per-point covariances in the cloud's own frame, used unchanged (no ε applied, as
        Open3D). Must be symmetric positive definite. Pass the cached
        :func:`estimate_gicp_covariances` of a prepared map as ``target_covariances``.
    source_normals, target_normals : array_like, optional
        Used for the plane model when the covariances are not given (Open3D does the same);
        otherwise the normals come from a kNN PCA with ``params.covariance_neighbours``.
    target_index : optional
        A KD-tree over ``target_points`` from :func:`minegeo.registration.build_target_index`
        to reuse (built when omitted or of another kind).
    check_target : bool
        True (default) validates the target fully. False checks only the layout of
        ``target_points`` (C-contiguous float64 (m, 3)) and the shape of
        ``target_covariances``, and requires ``target_index`` (if given) to hold the very same
        array: for a map validated once (e.g. a prepared map's cached covariances).
    trusted_init : bool
        False: ``T_init`` is user input (rigid within 1e-6, else InputError). True: the caller's own
        transform (``se3.compose``), checked within 1e-9 (else InternalError, a bug), re-projected.
    engine : {"kernel", "python"}
        The loop of ``convergence="step"`` (:data:`ENGINES`): one compiled kernel (default) or the
        Python loop it is tested against (the same steps; the last bits of the solve may differ).
        ``convergence="open3d"`` always runs the Python loop.

    Returns
    -------
    GICPResult
        Transform, fitness, Euclidean inlier RMSE, iterations, convergence flag, the GICP
        information matrix ``H`` and its eigenvalues, degeneracy flag with reason, Mahalanobis
        cost, ``sigma_m``, history and timings.

    Raises
    ------
    InputError
        Bad shapes, NaN/inf rows, non-rigid ``T_init``, covariances of the wrong shape or not
        symmetric positive definite, bad parameters.
    TooFewPointsError
        Fewer than 3 points in either cloud.

    Notes
    -----
    *Covariances* are prepared once per cloud, in its own frame ([Ren2019 Eqs. 2-3], see
    :func:`estimate_gicp_covariances`).

    *Loop* (Open3D oracle §10): evaluate the correspondences at ``T_init``; then for
    ``k = 1..max_iterations``: one Gauss-Newton step ``ΔT``, ``T ← ΔT T``, ``p ← ΔT p``,
    re-evaluate, and stop when the step was smaller than ``step_translation_m`` and
    ``step_rotation_rad`` (default) — or, with ``convergence="open3d"``, when
    ``|Δfitness| < relative_fitness`` **and** ``|Δrmse| < relative_rmse`` (strict) — or
    (``params.stop_on_cycle``, default) when the correspondence set repeats the one of two
    iterations before (a 2-cycle, reported with its amplitude). The last evaluation is
    returned; ``converged`` is False when ``max_iterations`` ran out first.

    *Correspondences*: nearest target point of every moved source point with
    ``|T b_i - m_i|² < d²`` (Euclidean, as in Ren 2019 Sec. 3.2: "the standard Euclidean
    distance is used ... to calculate the correspondence"), ties to the lowest target index.
    The exact KD-tree search starts its bound at the distance to the previous partner, which
    prunes most of the tree without changing the answer; a point whose partner provably stays
    its nearest (the next point was farther than the partner by more than twice the distance the
    point has moved since) skips the tree altogether, a point within half the neighbour radius of
    its previous partner takes the answer from that partner's kNN list when the target's
    covariances were estimated here (exact by the triangle inequality), and the normal equations
    below are summed in the same pass (:class:`minegeo.registration.loop.GICPNearestInGate`).

    *Step* ([Ren2019 Eq. 6] linearised about the current pose): with ``p_i = T b_i``,
    ``d_i = p_i - m_i``, ``M_i = C_i^M + R C_i^B Rᵀ`` ([Ren2019 Eq. 5]) and the left perturbation
    ``ΔT p ≈ p + ω × p + τ`` the residual Jacobian is ``J_i = [-[p_i]×, I3]``;
    ``H = Σ J_iᵀ M_i⁻¹ J_i``, ``g = Σ J_iᵀ M_i⁻¹ d_i``, ``H x = -g``, and
    ``x = (α, β, γ, τ)`` gives ``ΔR = R_z(γ) R_y(β) R_x(α)`` exactly (Open3D §7, §11).
    Open3D whitens with ``W = M^{-1/2}`` (``r = W d``, ``J_W = W J``); with the L2 loss
    ``J_Wᵀ J_W = Jᵀ M⁻¹ J`` and ``J_Wᵀ r = Jᵀ M⁻¹ d``, which is what is summed here (the two
    differ by rounding only). A singular ``H`` uses the minimum-norm step and is reported as
    degenerate.

    *Degeneracy*: :func:`minegeo.registration.constraint_analysis` on the matched source
    points and the target normals (eigenvector of the smallest eigenvalue of the target
    covariance), the same criterion as :func:`minegeo.registration.register_icp`.
    """
    t_start = time.perf_counter()
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {ENGINES}, got {engine!r}")
    timer = StageTimer()
    P0, Q, T, tree, Cs, Ct, Nt, src_from, tgt_from, lists = _gicp_inputs(
        source_points, target_points, T_init, params, source_covariances, target_covariances, source_normals,
        target_normals, target_index, check_target, timer, trusted_init)
    d = float(params.max_correspondence_distance_m)
    factor = GICPFactor(Q, Cs, Ct, T)
    P = P0 if is_identity(T) else K.transform_points_kernel(P0, T)
    out = _gicp_loop(P, T, tree, factor, d, params, timer, lists, engine)
    cyc_m = cyc_rad = 0.0
    if out.reason == "cycle":
        cyc_m = float(np.linalg.norm(out.cycle_delta[:3, 3]))
        cyc_rad = rotation_angle(out.cycle_delta[:3, :3])
        log.info("GICP stopped on a 2-cycle of correspondence sets (step %.2e m, %.2e rad)", cyc_m, cyc_rad)
    k = out.matches.corr.shape[0]
    with timer("information"):
        info, info_ev, cost, c_ev, c_vec, ratio, reason = _gicp_information(factor, out, Nt, params)
    return GICPResult(
        **result_fields(out, (info, info_ev, c_ev, c_vec, ratio, reason), MIN_POINTS, d, "GICP",
                        "an update step was rank deficient (the matched surfaces do not constrain all six "
                        "pose directions): the motion along the free direction is arbitrary", params, timer,
                        t_start, "GICP", log),
        mahalanobis_cost=float(cost), sigma_m=float(np.sqrt(cost / (3 * k - 6))) if 3 * k > 6 else 0.0,
        source_covariances_from=src_from, target_covariances_from=tgt_from, convergence_reason=out.reason,
        cycle_amplitude_m=cyc_m, cycle_amplitude_rad=cyc_rad,
    )


def _gicp_loop(P: np.ndarray, T: np.ndarray, tree, factor: GICPFactor, d: float, params: GICPParams, timer,
               lists, engine: str = "kernel") -> LoopOutcome:
    """The registration loop: the one-kernel loop for ``convergence="step"`` with ``engine="kernel"``,
    :func:`~minegeo.registration.loop.run_loop` otherwise."""
    if params.convergence == "step" and engine == "kernel":
        return _step_loop(P, T, tree, factor, d, params, timer, lists)
    search = GICPNearestInGate(factor.Q, d, tree, factor, parallel_rows=_parallel_rows(PARALLEL_SEARCH_ROWS),
                               lists=lists)
    return run_loop(P, T, search, factor, _termination(params), params.max_iterations, timer)


def _step_loop(P: np.ndarray, T: np.ndarray, tree, factor: GICPFactor, d: float, params: GICPParams,
               timer, lists=None) -> LoopOutcome:
    """:func:`~minegeo.registration.loop.run_loop` with :class:`GICPNearestInGate`, the step test and
    the 2-cycle test, as one kernel (:func:`~minegeo.registration._kernels_gicp.gicp_step_loop`; no
    return to Python per iteration). Its ``timings_s["search"]`` is the whole kernel (searches and
    steps), ``"estimate"`` the assembly of the outcome."""
    n, m = P.shape[0], factor.Q.shape[0]
    hist = np.empty((int(params.max_iterations) + 2, 2))
    with timer("search"):
        T_out, P_out, idx, sq, H, g, cost, iters, code, singular, cyc, nh = KG.gicp_step_loop(
            P, factor.Q, tree, d * d, factor.Cs, factor.Ct, np.ascontiguousarray(T), int(params.max_iterations),
            float(params.step_translation_m), float(params.step_rotation_rad), bool(params.stop_on_cycle),
            n >= _parallel_rows(PARALLEL_SEARCH_ROWS), n >= K.PARALLEL_MIN_ROWS, hist,
            *(KG.NO_LISTS if lists is None else lists))
    with timer("estimate"):
        corr, total = compact_matches(idx, sq, m)
        k = corr.shape[0]
        system = GICPSystem(np.ascontiguousarray(T_out[:3, :3]), H, g, float(cost))
        matches = Matches(float(k / n), float(np.sqrt(total / k)), corr, idx, system) if k else Matches(
            0.0, 0.0, corr, idx, system)
        out = LoopOutcome(T_out, P_out, matches, [(float(a), float(b)) for a, b in hist[:nh]], iterations=int(iters),
                          reason={KG.LOOP_STEP: "step", KG.LOOP_CYCLE: "cycle"}.get(int(code), ""),
                          singular_step=bool(singular))
        if code == KG.LOOP_CYCLE:
            out.cycle_delta = cyc
    return out


def _termination(params: GICPParams) -> Termination:
    """The convergence test of ``params`` (:func:`~minegeo.registration.open3d_compat.convergence_tests`)
    and the 2-cycle test."""
    return Termination(**convergence_tests(params), stop_on_cycle=bool(params.stop_on_cycle),
                       cycle_keeps_lower_cost=True)


def _gicp_information(factor: GICPFactor, out, Nt, params: GICPParams):
    """``(H, its eigenvalues, Mahalanobis cost, constraint eigenvalues, eigenvectors, ratio,
    reason)`` at the loop's solution; the constraint analysis uses the target normals (given, or
    the eigenvector of the smallest eigenvalue of the target covariance)."""
    info, _, cost = factor.linearize(out.points, out.pose, out.matches)
    info_ev = np.linalg.eigvalsh(info)
    if out.matches.corr.shape[0] == 0:
        return info, info_ev, cost, np.zeros(6), np.eye(6), 0.0, "no correspondences"
    si, ti = out.matches.pairs()
    if Nt is not None:  # the pairs index the clouds directly (nothing gathered)
        return (info, info_ev, cost, *constraint_analysis(out.points, Nt, params.degeneracy_ratio_threshold,
                                                           pairs=(si, ti)))
    Ns = KG.min_eigvec_kernel(factor.Ct, ti)
    return (info, info_ev, cost, *constraint_analysis(out.points, Ns, params.degeneracy_ratio_threshold,
                                                       pairs=(si, np.arange(ti.shape[0], dtype=np.int64))))


def _gicp_inputs(source_points, target_points, T_init, params, source_covariances, target_covariances,
                 source_normals, target_normals, target_index, check_target: bool, timer, trusted_init: bool = False):
    """Validated inputs of :func:`register_gicp`: ``(P0, Q, T_init copy, KD-tree of Q, Cs, Ct,
    target normals or None, source_covariances_from, target_covariances_from, the target's kNN
    lists (nb, rk) or None)``."""
    if not isinstance(params, GICPParams):
        raise InputError(f"params must be a GICPParams, got {type(params).__name__}")
    P0 = as_points(source_points, "source_points", min_points=MIN_POINTS)
    if check_target:
        Q = as_points(target_points, "target_points", min_points=MIN_POINTS)
        q_max = float(np.abs(Q).max())
    else:
        Q, q_max = as_trusted_points(target_points, "target_points", min_points=MIN_POINTS), 0.0
    # user input at the user's tolerance; a transform the caller composed is an internal invariant
    T = internal_transform(T_init, "T_init") if trusted_init else as_transform(T_init, "T_init").copy()
    if max(float(np.abs(P0).max()), q_max) > LARGE_COORDINATE_M:
        log.warning(
            "GICP input coordinates exceed %.0e m: subtract a local origin first for full precision",
            LARGE_COORDINATE_M,
        )
    with timer("search"):
        if isinstance(target_index, GatedKDTree):
            same = target_index.data is Q or (check_target and np.array_equal(target_index.data, Q))
            if target_index.m != Q.shape[0] or not same:
                raise InputError("target_index was built on a different cloud than target_points")
            tree = target_index.packed
        else:  # None or another kind of index: build the KD-tree this search needs
            tree = kd_build(Q, KD_LEAF)
    with timer("covariances"):
        Nt = None
        lists = None  # the target's kNN lists, when its covariances are estimated here
        if source_covariances is not None:
            Cs = _as_covariances(source_covariances, P0.shape[0], "source_covariances")
            src_from = "given"
        elif (target_covariances is None and source_normals is None and target_normals is None
              and min(P0.shape[0], Q.shape[0]) >= CONCURRENT_MIN_POINTS and numba.get_num_threads() > 1):
            # both clouds' kNN PCA in one prange region
            kk = min(int(params.covariance_neighbours), Q.shape[0])
            lists = (np.empty((Q.shape[0], kk), np.int64), np.empty(Q.shape[0]))
            Cs, Ct, Nt = _covariances_of_pair(P0, Q, tree, params, lists)
            return P0, Q, T, tree, Cs, Ct, Nt, "estimated", "estimated", lists
        else:
            Cs, _, src_from = _covariances_and_normals(P0, params, source_normals, "source")
        if target_covariances is not None and not check_target:
            Ct = target_covariances
            if not (isinstance(Ct, np.ndarray) and Ct.dtype == np.float64 and Ct.shape == (Q.shape[0], 3, 3)
                    and Ct.flags.c_contiguous):
                raise InputError(f"target_covariances: without checks it must be a C-contiguous float64 "
                                 f"({Q.shape[0]}, 3, 3) array")
            tgt_from = "given"
        elif target_covariances is not None:
            Ct = _as_covariances(target_covariances, Q.shape[0], "target_covariances")
            tgt_from = "given"
        else:
            # the kNN lists are kept for the correspondence search (gicp_fused_search's shortcut)
            if target_normals is None:
                kk = min(int(params.covariance_neighbours), Q.shape[0])
                lists = (np.empty((Q.shape[0], kk), np.int64), np.empty(Q.shape[0]))
            Ct, Nt, tgt_from = _covariances_and_normals(Q, params, target_normals, "target", tree=tree,
                                                        lists=lists)
    return P0, Q, T, tree, Cs, Ct, Nt, src_from, tgt_from, lists


def _warmup() -> None:
    """Compile the GICP kernels (fused search + sums and pair sums of
    :mod:`minegeo.registration._kernels_gicp`, serial and ``prange``, with and without neighbour
    lists; the loop kernel :func:`~minegeo.registration._kernels_gicp.gicp_step_loop`;
    :func:`~minegeo.registration._kernels_gicp.knn_normals_tasks`, ``knn_normals_pair_tasks``) on tiny
    inputs (called by ``minegeo.registration._warmup``)."""
    from minegeo.registration import _kernels_gicp as L

    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    Q = np.vstack([P, P + 2.0, P + 4.0])
    tree = kd_build(Q, 2)
    C = np.tile(np.eye(3), (Q.shape[0], 1, 1))
    R = np.eye(3)
    warm = np.full(4, Q.shape[0], dtype=np.int64)
    for parallel in (False, True):
        state = (np.empty((0, 3)), np.empty(4), np.empty(4), np.zeros(4))
        idx = L.gicp_fused_search(P, Q, tree, 1.0, warm, C[:4], C, R, parallel, state)[0]
        L.gicp_fused_search(P, Q, tree, 1.0, idx, C[:4], C, R, parallel, (P.copy(), *state[1:]))
    si = np.arange(4, dtype=np.int64)
    L.gicp_pairs_system(P, Q, C[:4], C, R, si, si)
    L._gicp_pairs_parallel(P, Q, C[:4], C, R, si, si, np.zeros((1, L.GICP_ACC)))
    hist = np.empty((4, 2))
    for parallel in (False, True):  # the loop kernel (one compilation; both drivers inside)
        KG.gicp_step_loop(P, Q, tree, 1.0, C[:4], C, np.eye(4), 2, 1e-5, 1e-6, True, parallel, parallel, hist,
                          *KG.NO_LISTS)
        lists = (np.empty((Q.shape[0], 3), np.int64), np.empty(Q.shape[0]))
        _knn_normals(Q, tree, 3, False, parallel, lists)
        KG.gicp_step_loop(P, Q, tree, 1.0, C[:4], C, np.eye(4), 2, 1e-5, 1e-6, True, parallel, parallel, hist,
                          *lists)
    m = Q.shape[0]
    for mode in (False, True):
        KG.knn_normals_pair_tasks(P, kd_build(P, 2), 3, Q, tree, 3, mode, KG.DEGENERATE_RATIO, np.empty((4, 3)),
                                  np.empty((4, 3)), np.empty(4, dtype=np.int8), np.empty((0, 3), np.int64), np.empty(0),
                                  np.empty((m, 3)), np.empty((m, 3)), np.empty(m, dtype=np.int8),
                                  np.empty((m, 3), np.int64), np.empty(m))
        KG.knn_normals_tasks(Q, tree, 3, mode, KG.DEGENERATE_RATIO, np.empty((m, 3)), np.empty((m, 3)),
                             np.empty(m, dtype=np.int8), np.empty((0, 3), np.int64), np.empty(0))
        KG.knn_normals_lists_serial(Q, tree, 3, mode, KG.DEGENERATE_RATIO, np.empty((m, 3)), np.empty((m, 3)),
                                    np.empty(m, dtype=np.int8), np.empty((0, 3), np.int64), np.empty(0))
