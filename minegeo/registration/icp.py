"""Iterative Closest Point: point-to-point (SVD/Umeyama) and point-to-plane (linearised).

Frames: ``source_points`` are in the source (scan) frame, ``target_points`` in the target
(map) frame. The result ``T_target_source`` maps the scan into the map:
``p_map = R p_scan + t``.

The loop, the correspondence gate and the convergence test are those of Open3D 0.20's
``registration_icp`` (oracle spec ``../shared/specs/open3d_oracle.md`` §7, §8, §10), so
minegeo and Open3D agree to ~1e-12 from the same start and parameters; see
``docs/registration_icp.md`` for the equations and for how to read the degeneracy report.

References
----------
Baek et al. (2022), Sensors 22, 2873, Sec. 2.4, [Baek2022 Eqs. 10-16, 19], Table 3.
Besl, P. J., McKay, N. D. (1992). A method for registration of 3-D shapes. IEEE TPAMI 14(2).
Low, K.-L. (2004). Linear least-squares optimization for point-to-plane ICP surface
registration. Technical Report TR04-004, UNC Chapel Hill.
Gelfand, N., Ikemoto, L., Rusinkiewicz, S., Levoy, M. (2003). Geometrically stable sampling
for the ICP algorithm. 3DIM (the eigen-analysis of the 6x6 constraint matrix).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from enum import StrEnum

import numba
import numpy as np
from scipy.spatial import cKDTree

from minegeo._provenance import StageTimer
from minegeo._validate import as_points, as_transform, as_trusted_points, internal_transform
from minegeo.errors import InputError
from minegeo.kernels.kdtree import KD_LEAF, GatedKDTree, kd_build
from minegeo.registration import _kernels as K
from minegeo.registration.evaluation import is_identity
from minegeo.registration.loop import (
    NearestInGate,
    PointToPlaneFactor,
    PointToPointFactor,
    Termination,
    run_loop,
)

__all__ = ["ICPParams", "ICPResult", "ICPStatus", "register_icp", "constraint_analysis", "METHODS"]

log = logging.getLogger(__name__)

#: Supported ICP variants.
METHODS = ("point_to_point", "point_to_plane")
#: Minimum number of points (and of correspondences for a full-rank step) per method.
MIN_POINTS = {"point_to_point": 3, "point_to_plane": 6}
#: Neighbours used to estimate target normals for the degeneracy analysis of point-to-point ICP.
PCA_NEIGHBOURS = 10
#: Coordinates larger than this (m) suggest projected coordinates without a local origin.
LARGE_COORDINATE_M = 1e5


@dataclass(frozen=True)
class ICPParams:
    """Parameters of :func:`register_icp` (defaults = Open3D's ``ICPConvergenceCriteria``).

    Attributes
    ----------
    max_correspondence_distance_m : float
        Gate ``d`` (metres, > 0): pairs with squared distance ``>= d²`` are ignored.
        Baek 2022 Table 3 uses 0.5 m.
    max_iterations : int
        Maximum number of updates (>= 0). Table 3: 30.
    relative_fitness : float
        Stop when ``|fitness_k - fitness_{k-1}| < relative_fitness`` **and** the RMSE test holds.
        (Open3D's name; it is an absolute difference of fractions.)
    relative_rmse : float
        Stop threshold on ``|rmse_k - rmse_{k-1}|`` in metres (absolute difference). Table 3: 1e-6.
    method : str
        ``"point_to_point"`` (SVD/Umeyama step) or ``"point_to_plane"`` (needs target normals).
    degeneracy_ratio_threshold : float
        Flag the result as degenerate when the smallest/largest eigenvalue of the normalised
        constraint matrix (see :func:`constraint_analysis`) is below this (dimensionless, > 0).
    step_translation_m, step_rotation_rad : float
        Also stop when the last update ``ΔT`` translated by less than ``step_translation_m``
        **and** rotated by less than ``step_rotation_rad`` (the test of
        :class:`~minegeo.registration.GICPParams`). 0 (default) switches it off: Open3D's test
        alone. Open3D's fitness test holds only once no source point enters or leaves the
        gate (the fitness moves in steps of ``1/n``), so on tens of thousands of points it can
        run to ``max_iterations`` while the pose no longer moves.
    """

    max_correspondence_distance_m: float
    max_iterations: int = 30
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    method: str = "point_to_point"
    degeneracy_ratio_threshold: float = 1e-2
    step_translation_m: float = 0.0
    step_rotation_rad: float = 0.0

    def __post_init__(self):
        d = self.max_correspondence_distance_m
        if not isinstance(d, int | float | np.floating | np.integer) or not np.isfinite(d) or d <= 0:
            raise InputError(
                f"max_correspondence_distance_m must be a finite distance > 0 m, got {d!r}"
            )
        it = self.max_iterations
        if isinstance(it, bool) or not isinstance(it, int | np.integer) or it < 0:
            raise InputError(f"max_iterations must be an integer >= 0, got {it!r}")
        for name in ("relative_fitness", "relative_rmse", "step_translation_m", "step_rotation_rad"):
            v = getattr(self, name)
            if not isinstance(v, int | float | np.floating | np.integer) or not np.isfinite(v) or v < 0:
                raise InputError(f"{name} must be finite and >= 0, got {v!r}")
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        r = self.degeneracy_ratio_threshold
        if not isinstance(r, int | float | np.floating) or not np.isfinite(r) or not 0 < r < 1:
            raise InputError(f"degeneracy_ratio_threshold must be in (0, 1), got {r!r}")


class ICPStatus(StrEnum):
    """Status of an ICP or GICP run (:attr:`ICPResult.status`); each member is its string value."""

    #: the convergence test held before ``max_iterations`` and the result is not degenerate
    CONVERGED = "converged"
    #: ``max_iterations`` reached before the convergence test held (not degenerate)
    MAX_ITERATIONS = "max_iterations"
    #: no source point within the gate of the target at the final pose
    NO_CORRESPONDENCES = "no_correspondences"
    #: the matched geometry does not constrain all six pose directions (see ``degeneracy_reason``)
    DEGENERATE = "degenerate"


@dataclass(frozen=True)
class ICPResult:
    """Outcome of :func:`register_icp`.

    Attributes
    ----------
    T_target_source : (4, 4) ndarray
        Final transform, ``p_target = R p_source + t``.
    fitness : float
        Fraction of source points with a target neighbour closer than ``d`` at the solution.
    inlier_rmse_m : float
        Euclidean RMSE of those pairs ([Baek2022 Eq. 19]), metres.
    iterations : int
        Number of updates performed.
    converged : bool
        The fitness and RMSE change tests both held before ``max_iterations`` was reached.
    information_6x6 : (6, 6) ndarray
        ``Σ J_iᵀ J_i`` at the solution; parameters ``(ω_x, ω_y, ω_z, t_x, t_y, t_z)`` =
        rotation (rad) first, then translation (m), as a left perturbation in the target frame
        about its origin. Point-to-plane: ``J_i = [(p_i × n_i)ᵀ, n_iᵀ]``; point-to-point:
        Open3D's ``GetInformationMatrixFromPointClouds`` (three rows ``[-[q_i]×, I]`` per pair).
    information_eigenvalues : (6,) ndarray
        Ascending eigenvalues of ``information_6x6`` (mixed units; see the normalised ones).
    degenerate : bool
        True when the geometry does not constrain all six pose directions (or nothing matched).
    degeneracy_reason : str
        Empty when not degenerate; otherwise what is unconstrained, in words.
    params : ICPParams
        Parameters used.
    timings_s : dict
        Seconds per stage (``search``, ``estimate``, ``information``, ``total``).
    correspondences : (k, 2) int64 ndarray
        ``(source index, target index)`` inlier pairs at the solution.
    constraint_eigenvalues : (6,) ndarray
        Ascending eigenvalues of the normalised, centred point-to-plane constraint matrix
        (dimensionless; see :func:`constraint_analysis`).
    constraint_eigenvectors : (6, 6) ndarray
        Matching eigenvectors (columns) in the centred, length-scaled parameters.
    degeneracy_ratio : float
        ``constraint_eigenvalues[0] / constraint_eigenvalues[-1]``.
    history : tuple
        ``(fitness, inlier_rmse_m)`` after the initial evaluation and after each update.
    status : ICPStatus
        ``converged``, ``max_iterations``, ``no_correspondences`` or ``degenerate``.
    """

    T_target_source: np.ndarray
    fitness: float
    inlier_rmse_m: float
    iterations: int
    converged: bool
    information_6x6: np.ndarray
    information_eigenvalues: np.ndarray
    degenerate: bool
    degeneracy_reason: str
    params: ICPParams
    timings_s: dict = field(default_factory=dict)
    correspondences: np.ndarray = field(default_factory=lambda: np.empty((0, 2), dtype=np.int64))
    constraint_eigenvalues: np.ndarray = field(default_factory=lambda: np.zeros(6))
    constraint_eigenvectors: np.ndarray = field(default_factory=lambda: np.eye(6))
    degeneracy_ratio: float = 0.0
    history: tuple = ()
    status: ICPStatus = field(kw_only=True)


_AXIS_NAMES = ("rotation about x", "rotation about y", "rotation about z",
               "translation along x", "translation along y", "translation along z")


def constraint_analysis(points, normals, threshold: float = 1e-2, pairs=None):
    """Eigen-analysis of the point-to-plane constraint matrix (Gelfand et al. 2003).

    Parameters
    ----------
    points : (k, 3) ndarray
        Matched source points at the solution, in the target frame (metres).
    normals : (k, 3) ndarray
        Target normals at the matched target points (unit length).
    threshold : float
        Degeneracy threshold on ``λ_min / λ_max``.
    pairs : (source indices, target indices), optional
        Analyse ``points[si]`` with ``normals[ti]`` (``k = len(si)`` pairs) without gathering them
        (the registrations pass their whole clouds and the pairs); default: row ``i`` with row ``i``.

    Returns
    -------
    eigenvalues : (6,) ndarray
        Ascending eigenvalues of ``C = S Mᵀ H M S / k`` (dimensionless).
    eigenvectors : (6, 6) ndarray
        Columns; parameters ``(L ω, t_c)``.
    ratio : float
        ``λ_min / λ_max`` (0 when ``λ_max = 0``).
    reason : str
        Empty if ``ratio >= threshold``; else a description of the weakest direction.

    Notes
    -----
    ``H = Σ J_iᵀ J_i`` with ``J_i = [(p_i × n_i)ᵀ, n_iᵀ]`` is re-expressed about the centroid
    ``c`` of the points (``t = t_c + [c]× ω``, i.e. ``M = [[I, 0], [[c]×, I]]``) so that the
    answer does not depend on where the frame origin is, and the rotation is scaled by the RMS
    radius ``L`` of the points about ``c`` (``S = diag(1/L, 1/L, 1/L, 1, 1, 1)``) so that all
    six parameters are in metres of surface displacement. Dividing by ``k`` makes the
    translation block the mean of ``n nᵀ`` (trace 1). An eigenvalue near 0 is a direction
    in which the surfaces can slide without changing any residual: translation along a
    straight, featureless tunnel, or in-plane motion on a single plane.
    """
    P = np.ascontiguousarray(points, dtype=np.float64)
    N = np.ascontiguousarray(normals, dtype=np.float64)
    if pairs is None:
        si = ti = np.arange(P.shape[0], dtype=np.int64)
    else:
        si, ti = (np.ascontiguousarray(a, dtype=np.int64) for a in pairs)
    k = si.shape[0]
    if k == 0:
        return np.zeros(6), np.eye(6), 0.0, "no correspondences"
    # H computed directly at the centred points is M^T H M (an exact identity)
    H, L = K.constraint_system_idx(P, si, N, ti)
    s = np.array([1.0 / L if L > 0 else 0.0] * 3 + [1.0] * 3)
    C = (H * s[:, None] * s[None, :]) / k
    ev, V = np.linalg.eigh(C)
    ev = np.maximum(ev, 0.0)
    ratio = float(ev[0] / ev[-1]) if ev[-1] > 0 else 0.0
    reason = ""
    if ratio < threshold:
        weak = [i for i in range(6) if ev[i] < threshold * ev[-1]]
        parts = []
        for i in weak:
            v = V[:, i]
            rot, tra = np.linalg.norm(v[:3]), np.linalg.norm(v[3:])
            if tra >= rot:
                axis = v[3:] / tra
                parts.append(f"translation along ({axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f})")
            else:
                axis = v[:3] / rot
                parts.append(f"rotation about ({axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f})")
        reason = (
            f"{len(weak)} pose direction(s) weakly constrained by the geometry "
            f"(eigenvalue ratio {ratio:.2e} < {threshold:g}): " + "; ".join(parts)
        )
    return ev, V, ratio, reason


def _pca_normals(Q: np.ndarray, index, idx: np.ndarray, k: int = PCA_NEIGHBOURS) -> np.ndarray:
    """Unit normals at target points ``Q[idx]`` from the PCA of their ``k`` nearest target points.

    Only used for the degeneracy analysis, where the normal's sign does not matter.
    """
    kk = min(k, Q.shape[0])
    uniq, inv = np.unique(idx, return_inverse=True)
    if not hasattr(index, "query") or isinstance(index, GatedKDTree):
        index = cKDTree(Q)  # the gated 1-NN tree cannot answer k-NN queries
    workers = 1 if uniq.size < 2048 else int(numba.get_num_threads())
    if hasattr(index, "n"):  # scipy cKDTree
        _, nb = index.query(Q[uniq], k=kk, workers=workers)
    else:
        _, nb = index.query(Q[uniq], k=kk)
    nb = np.ascontiguousarray(np.asarray(nb, dtype=np.int64).reshape(uniq.size, kk))
    return np.ascontiguousarray(K.pca_normals_kernel(Q, nb)[inv.reshape(-1)])


def _points(arr, name: str, min_points: int) -> tuple[np.ndarray, float]:
    """:func:`minegeo._validate.as_points` with one fused pass for the finiteness test and the
    largest coordinate magnitude; anything unusual goes through ``as_points`` for its typed error."""
    a = np.asarray(arr) if isinstance(arr, np.ndarray) else None
    if (a is not None and a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3
            and a.shape[0] >= min_points and a.flags.c_contiguous):
        m = float(K.finite_max_abs(a))
        if np.isfinite(m):
            return a, m
    a = as_points(arr, name, min_points=min_points)
    return a, float(K.finite_max_abs(a))


def final_diagnosis(k: int, need: int, gate_m: float, method: str, singular_step: bool, singular_text: str,
                    constraint_reason: str, converged: bool) -> tuple[list[str], bool, ICPStatus]:
    """Degeneracy reasons and status of a finished ICP/GICP run (shared by both).

    Returns ``(reasons, degenerate, status)``: reasons for no or too few pairs at the solution
    (< ``need``), a rank-deficient update step (``singular_text``) and the constraint analysis
    (``constraint_reason``); status ``no_correspondences`` / ``degenerate`` / ``converged`` /
    ``max_iterations``.
    """
    reasons = []
    if k == 0:
        reasons.append(
            f"no source point is within {gate_m} m of the target at the final pose: "
            "the initial pose is too far off or the clouds do not overlap"
        )
    elif k < need:
        reasons.append(f"only {k} correspondence(s) at the solution; {method} needs at least {need}")
    if singular_step:
        reasons.append(singular_text)
    if k > 0 and constraint_reason:
        reasons.append(constraint_reason)
    degenerate = bool(reasons)
    if k == 0:
        status = ICPStatus.NO_CORRESPONDENCES
    elif degenerate:
        status = ICPStatus.DEGENERATE
    elif converged:
        status = ICPStatus.CONVERGED
    else:
        status = ICPStatus.MAX_ITERATIONS
    return reasons, degenerate, status


def result_fields(out, analysis: tuple, need: int, gate_m: float, method: str, singular_text: str, params,
                  timer: StageTimer, t_start: float, label: str, logger: logging.Logger) -> dict:
    """The :class:`ICPResult` fields of a finished ICP/GICP run (shared by both).

    ``out`` is the loop's :class:`~minegeo.registration.loop.LoopOutcome`, ``analysis`` the
    ``(information, its eigenvalues, constraint eigenvalues, eigenvectors, degeneracy ratio,
    constraint reason)`` at the solution; status and reasons by :func:`final_diagnosis` (a
    degenerate result is logged at DEBUG on ``logger`` as ``"<label> result is degenerate: ..."``; the result
    carries the flag and the reason, the caller decides what to tell); ``timings_s["total"]``
    is the wall time since ``t_start`` (s).
    """
    info, info_ev, c_ev, c_vec, ratio, reason = analysis
    corr = out.matches.corr
    reasons, degenerate, status = final_diagnosis(corr.shape[0], need, gate_m, method, out.singular_step,
                                                  singular_text, reason, out.converged)
    if degenerate:
        logger.debug("%s result is degenerate: %s", label, "; ".join(reasons))
    timings = timer.as_dict()
    timings["total"] = time.perf_counter() - t_start
    return dict(
        T_target_source=out.pose, fitness=float(out.matches.fitness), inlier_rmse_m=float(out.matches.rmse),
        iterations=out.iterations, converged=out.converged, information_6x6=info, information_eigenvalues=info_ev,
        degenerate=degenerate, degeneracy_reason="; ".join(reasons), params=params, timings_s=timings,
        correspondences=corr, constraint_eigenvalues=c_ev, constraint_eigenvectors=c_vec,
        degeneracy_ratio=float(ratio), history=tuple(out.history), status=status,
    )


def register_icp(source_points, target_points, T_init, params: ICPParams, target_normals=None,
                 target_index=None, *, check_target: bool = True, trusted_init: bool = False) -> ICPResult:
    """Refine ``T_target_source`` by ICP (Baek 2022 Sec. 2.4; Open3D ``registration_icp``).

    Parameters
    ----------
    source_points : (n, 3) array_like
        Scan points (metres, source frame), e.g. the RANSAC-aligned local cloud.
    target_points : (m, 3) array_like
        Map points (metres, target frame). Use coordinates relative to a recorded local
        origin, not raw projected coordinates (10⁶ m magnitudes lose precision in ``p × n``).
    T_init : (4, 4) array_like
        Initial ``T_target_source`` (e.g. from RANSAC), a proper rigid transform.
    params : ICPParams
        Gate, iteration limit, convergence thresholds and method.
    target_normals : (m, 3) array_like, optional
        Target unit normals; required for ``point_to_plane``. For ``point_to_point`` they are
        only used for the degeneracy analysis (estimated by local PCA when omitted).
    target_index : optional
        A KD-tree over ``target_points`` to reuse, from
        :func:`minegeo.registration.build_target_index` (built when omitted).
    check_target : bool
        True (default) scans ``target_points`` and ``target_normals`` for NaN/inf. False only
        checks their layout (C-contiguous float64 (m, 3)): for a map validated once and
        registered against many times (as ``scipy.linalg``'s ``check_finite=False``); the
        large-coordinate warning then looks at the source alone.
    trusted_init : bool
        As in :func:`minegeo.registration.register_gicp`: False validates ``T_init`` as user input
        (:class:`~minegeo.errors.InputError`), True checks it as a transform the caller composed and
        re-projected itself (:class:`~minegeo.errors.InternalError` when it is not rigid: a bug).

    Returns
    -------
    ICPResult
        Transform, fitness, inlier RMSE, iterations, convergence flag, the 6x6 information matrix
        and its eigenvalues, the degeneracy flag with its reason, and timings.

    Raises
    ------
    InputError
        Bad shapes, NaN/inf rows, non-rigid ``T_init``, missing target normals for point-to-plane.
    TooFewPointsError
        Fewer points than the method needs (3 for point-to-point, 6 for point-to-plane).

    Notes
    -----
    Loop (Open3D §10): evaluate the correspondences at ``T_init``; then for ``k = 1..max_iterations``
    estimate an increment ``ΔT`` from the current pairs, set ``T ← ΔT T`` and ``p ← ΔT p``,
    re-evaluate, and stop when ``|Δfitness| < relative_fitness`` **and**
    ``|Δrmse| < relative_rmse`` (both strict), or (when set) when the step ``ΔT`` was below
    ``step_translation_m`` and ``step_rotation_rad``. The last evaluation is returned (no
    best-so-far).

    *Correspondences* (Baek Sec. 2.4 step 1, Open3D §8): the nearest target point of every
    source point, kept when its squared distance is ``< d²``.

    *Point-to-point step* ([Baek2022 Eqs. 10-13]): ``ΔT`` = Umeyama/Kabsch on the pairs, with the
    reflection fix ``R = V diag(1, 1, det(V Uᵀ)) Uᵀ``; the error minimised is
    ``Σ |q_i - (R p_i + t)|²`` (the squared form of [Baek2022 Eq. 15]).

    *Point-to-plane step* (Low 2004, Open3D §7): ``r_i = (p_i - q_i)·n_i``,
    ``J_i = [p_i × n_i, n_i]``, ``H = Σ J_iᵀ J_i``, ``g = Σ J_iᵀ r_i``, ``H x = -g``;
    ``x = (α, β, γ, t)`` gives ``ΔR = R_z(γ) R_y(β) R_x(α)`` exactly (no small-angle matrix).
    A singular ``H`` (single plane) uses the minimum-norm step and is reported as degenerate.

    *Degeneracy*: :func:`constraint_analysis` at the solution; ``degenerate`` is True when the
    eigenvalue ratio is below ``params.degeneracy_ratio_threshold``, when there are fewer
    matched pairs than the method needs, or when a point-to-point step had a rank-deficient
    cross-covariance (collinear pairs).
    """
    t_start = time.perf_counter()
    P0, Q, Nt, T = _icp_inputs(source_points, target_points, T_init, params, target_normals, check_target,
                               trusted_init)
    timer = StageTimer()
    if target_index is None:
        with timer("search"):
            tree = kd_build(Q, KD_LEAF)
    else:
        tree = target_index.packed if isinstance(target_index, GatedKDTree) else None
    search = NearestInGate(Q, params.max_correspondence_distance_m, tree=tree, index=target_index)
    factor = PointToPointFactor(Q) if params.method == "point_to_point" else PointToPlaneFactor(Q, Nt)
    stop = Termination(relative_fitness=params.relative_fitness, relative_rmse=params.relative_rmse,
                       step_translation=params.step_translation_m, step_rotation=params.step_rotation_rad)
    P = P0 if is_identity(T) else K.transform_points_kernel(P0, T)
    out = run_loop(P, T, search, factor, stop, params.max_iterations, timer)
    with timer("information"):
        analysis = _icp_information(out.points, Q, Nt, out.matches.corr, target_index, params)
    return ICPResult(**result_fields(
        out, analysis, MIN_POINTS[params.method], float(params.max_correspondence_distance_m), params.method,
        "an update step was rank deficient (collinear correspondences or a single plane): "
        "the motion along the free direction is arbitrary", params, timer, t_start, "ICP", log))


def _icp_inputs(source_points, target_points, T_init, params, target_normals, check_target: bool,
                trusted_init: bool = False):
    """Validated ``(P0, Q, target normals or None, T_init copy)`` of :func:`register_icp`
    (logs a warning for coordinates beyond ``LARGE_COORDINATE_M``)."""
    if not isinstance(params, ICPParams):
        raise InputError(f"params must be an ICPParams, got {type(params).__name__}")
    need = MIN_POINTS[params.method]
    P0, p_max = _points(source_points, "source_points", need)
    if check_target:
        Q, q_max = _points(target_points, "target_points", need)
    else:
        Q, q_max = as_trusted_points(target_points, "target_points", min_points=need), 0.0
    # user input at the user's tolerance; a transform the caller composed is an internal invariant
    T = internal_transform(T_init, "T_init") if trusted_init else as_transform(T_init, "T_init").copy()
    Nt = None
    if target_normals is not None:
        Nt = (_points(target_normals, "target_normals", 1)[0] if check_target
              else as_trusted_points(target_normals, "target_normals"))
        if Nt.shape[0] != Q.shape[0]:
            raise InputError(
                f"target_normals has {Nt.shape[0]} rows but target_points has {Q.shape[0]}"
            )
    if params.method == "point_to_plane" and Nt is None:
        raise InputError("point_to_plane ICP needs target_normals (estimate them on the map first)")
    if max(p_max, q_max) > LARGE_COORDINATE_M:
        log.warning(
            "ICP input coordinates exceed %.0e m: subtract a local origin first for full precision",
            LARGE_COORDINATE_M,
        )
    return P0, Q, Nt, T


def _icp_information(P, Q, Nt, corr, target_index, params: ICPParams):
    """``(information_6x6, its eigenvalues, constraint eigenvalues, eigenvectors, ratio, reason)``
    at the solution (moved source ``P``, pairs ``corr``); see :class:`ICPResult`."""
    k = corr.shape[0]
    Ps = np.ascontiguousarray(P[corr[:, 0]])
    Qs = np.ascontiguousarray(Q[corr[:, 1]])
    if Nt is not None:
        Ns = np.ascontiguousarray(Nt[corr[:, 1]])
    elif k > 0:
        Ns = _pca_normals(Q, target_index, corr[:, 1])
    else:
        Ns = np.empty((0, 3))
    if params.method == "point_to_plane":
        info, _, _ = K.point_to_plane_system_kernel(Ps, Qs, Ns)
    else:
        info = K.point_to_point_information_kernel(Qs)
    info_ev = np.linalg.eigvalsh(info)
    return (info, info_ev, *constraint_analysis(Ps, Ns, params.degeneracy_ratio_threshold))
