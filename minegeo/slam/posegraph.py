"""Pose-graph optimisation: Levenberg–Marquardt on the Lie algebra, sparse normal equations.

The back end of Ren et al. 2019 (Sec. 3.4, "solved by Gauss-Newton or Levenberg-Marquardt"), written
out so that an auditor can check it, and the cost fixed by the SLAM contract (``slam_contract.md``;
the same as GTSAM's ``BetweenFactorPose3`` / ``BetweenFactorPose2`` on a file read by ``readG2o``):

.. math::

    F(T) = \\tfrac12 \\sum_{(i,j)} r_{ij}^\\top \\Omega_{ij} r_{ij}, \\qquad
    r_{ij} = \\operatorname{Log}(Z_{ij}^{-1} T_i^{-1} T_j)

with ``r`` ordered rotation first, (ω, ρ) for SE(3) and (θ, x, y) for SE(2) (the file's (t, r) and
(x, y, θ) information matrices are permuted to match; the cost is unchanged by the ordering). The solver is the one optimiser of :mod:`minegeo.optim`: the edges are
:class:`minegeo.optim.factors.BetweenFactors` (analytic Jacobians ``J_i``, ``J_j``), the normal
equations ``(H + λD) δ = −g`` over the free poses (gauge: the ``FIX`` vertices, else the first one)
are solved by blocks (:class:`minegeo.optim.blocks.BlockSystem`, block Cholesky in a fill-reducing
order), poses are retracted ``T ← T · Exp(δ)``, and the damping, step acceptance, stopping rule and
result check are those of :func:`minegeo.optim.lm.levenberg_marquardt`. Robust kernels
(:mod:`minegeo.optim.robust`) reweight each edge by its whitened residual ``s = sqrt(rᵀΩr)``.
Graphs with plane landmarks use the general path: the same normal equations as a ``scipy.sparse``
matrix solved by sparse LU (:class:`minegeo.optim.blocks.SparseSystem`).

Optional plane landmarks (:class:`PlaneSet`, Ren et al. 2019 Sec. 3.4.2-3.4.3): world planes
``π_l = (n, d)`` as extra nodes and pose–plane edges with the error of [Ren2019 Eq. 11]
(:func:`minegeo.slam._kernels_planes.pose_plane_edge_terms`), added to the same cost,
``F = ½ Σ rᵀΩr + ½ Σ e_tᵀ Ω_t e_t``. The free poses keep their columns ``6·k``; plane ``l`` takes
the columns ``n_pose_cols + 3·l`` (all planes free), updated on S² × R by
:func:`~minegeo.slam._kernels_planes.plane_retract`. A plane constrains only height, roll and pitch
of a pose, so every pose still needs a between-edge path to a fixed pose.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from minegeo._params import one_of
from minegeo.errors import InputError
from minegeo.io.g2o import PoseGraph, edge_label, gtsam_information, non_psd_edges
from minegeo.kernels.lie import se2_exp, se3_exp
from minegeo.optim import (
    BetweenFactors,
    FactorProblem,
    LMParams,
    LMStatus,
    SparseSystem,
    Values,
    between_residuals,
    between_terms,
    check_result,
    levenberg_marquardt,
    quadratic_cost,
    robust_cost,
    robust_weights,
)
from minegeo.slam import _kernels_planes as KP

__all__ = ["PlaneSet", "PoseGraphParams", "PoseGraphResult", "optimize_pose_graph", "pose_graph_cost"]

log = logging.getLogger(__name__)

INDEFINITE = ("gtsam", "refuse")


@dataclass(frozen=True)
class PoseGraphParams(LMParams):
    """Parameters of :func:`optimize_pose_graph`.

    Attributes
    ----------
    max_iterations : int
        Largest number of linearisations (500: torus3D, where Gauss–Newton converges linearly,
        needs about 200 for :attr:`remaining_cost_tolerance`; GTSAM's LM needs 290 for its
        relative tolerance 1e-12).
    lambda_init : float
        Initial LM damping λ (see ``damping``).
    relative_cost_tolerance : float
        Stop when an accepted step lowers the cost by less than this fraction ``ε_k = (F_{k-1} − F_k)/F_{k-1}``.
    remaining_cost_tolerance : float
        Stop after an accepted step when both estimates of the decrease still to come are below this
        fraction of the cost: the Gauss–Newton model's decrease of the iteration,
        ``m_k = −½ gᵀδ / F`` (``(H + λD)δ = −g``; ``½ gᵀH⁻¹g / F``, the Newton decrement, as λ → 0),
        which measures the quadratic phase, and the rest of the geometric series of the last two
        accepted decreases, ``ε_k ρ / (1 − ρ)`` with ``ρ = ε_k / ε_{k−1} < 1`` (Aitken's estimate,
        exact for linear convergence at rate ρ), which measures the linear phase. GTSAM stops on
        ``ε_k`` alone (``relativeErrorTol`` 1e-5 by default), which under linear convergence leaves
        ``ε_k ρ/(1 − ρ)`` (1.3e-4 on torus3D) undone. The default 1e-8 ends torus3D 1e-8 above
        its optimum (measured), the other standard files at it.
    step_tolerance : float
        Stop when the largest step component (rad or m) is below this.
    robust : {"none", "huber", "cauchy"}
        Robust kernel on the whitened residual norm.
    robust_scale : float
        Kernel width ``k`` in whitened units (1 = one standard deviation).
    damping : {"diagonal", "identity"}
        LM damping matrix ``D`` in ``(H + λD) δ = -g``: ``diag(H)`` (Marquardt, unit-free) or
        ``I`` (GTSAM's default; fewer iterations on graphs with very large information values).
    indefinite_information : {"gtsam", "refuse"}
        What to do with an edge whose information matrix is not positive semi-definite (such a
        matrix makes the cost unbounded below): ``"gtsam"`` replaces it by the matrix GTSAM's
        ``readG2o`` uses, ``RᵀR`` (:func:`minegeo.io.g2o.gtsam_information`), and reports how many
        were replaced; ``"refuse"`` raises :class:`~minegeo.errors.InputError` naming the first one.

    Each field declares its rule in its metadata (:mod:`minegeo._params`; the LM fields' in
    :class:`~minegeo.optim.LMParams`), checked by :func:`~minegeo._params.validate` from
    ``LMParams.__post_init__``.
    """

    indefinite_information: str = one_of("gtsam", INDEFINITE)

    # __post_init__: LMParams' validate(self) checks every field's rule, this class's as well


@dataclass(frozen=True)
class PlaneSet:
    """Plane landmarks and pose–plane edges for :func:`optimize_pose_graph` (Ren et al. 2019 Sec. 3.4.2).

    Attributes
    ----------
    planes : ndarray (L, 4)
        Initial world planes ``(n, d)``, ``n·p + d = 0``, unit ``n`` (d in m).
    edges : ndarray (mp, 2) of int
        ``(pose index, plane index)``: the pose is a row of ``graph.poses`` (not a vertex id).
    measurements : ndarray (mp, 4)
        The plane observed from that pose, in its sensor frame (unit normal, d in m).
    information : ndarray (mp, 3, 3)
        Information of the residual ``(azimuth, elevation, d)`` (1/rad², 1/m²) of
        :func:`minegeo.slam.planes.pose_plane_terms`.
    """

    planes: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray

    def __post_init__(self):
        pl = np.ascontiguousarray(np.asarray(self.planes, dtype=np.float64).reshape(-1, 4))
        e = np.ascontiguousarray(np.asarray(self.edges, dtype=np.int64).reshape(-1, 2))
        m = np.ascontiguousarray(np.asarray(self.measurements, dtype=np.float64).reshape(-1, 4))
        info = np.ascontiguousarray(np.asarray(self.information, dtype=np.float64).reshape(-1, 3, 3))
        if not (e.shape[0] == m.shape[0] == info.shape[0]):
            raise InputError(f"PlaneSet: {e.shape[0]} edges, {m.shape[0]} measurements and {info.shape[0]} "
                             "information matrices: the counts must agree")
        if e.size and (e[:, 1].min() < 0 or e[:, 1].max() >= pl.shape[0] or e[:, 0].min() < 0):
            raise InputError("PlaneSet: an edge indexes a plane that does not exist (or a negative pose)")
        for name, a in (("planes", pl), ("measurements", m)):
            if not np.all(np.isfinite(a)) or (a.size and not np.allclose(np.linalg.norm(a[:, :3], axis=1), 1.0,
                                                                         atol=1e-6)):
                raise InputError(f"PlaneSet: {name} must be finite with unit normals")
        if not np.all(np.isfinite(info)):
            raise InputError("PlaneSet: information matrices must be finite")
        for k, v in (("planes", pl), ("edges", e), ("measurements", m), ("information", info)):
            object.__setattr__(self, k, v)

    @property
    def n_planes(self) -> int:
        return int(self.planes.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    def with_planes(self, planes: np.ndarray) -> PlaneSet:
        """The same edges with other plane values."""
        return PlaneSet(planes, self.edges, self.measurements, self.information)


@dataclass(frozen=True)
class PoseGraphResult:
    """Outcome of :func:`optimize_pose_graph`.

    Attributes
    ----------
    graph : PoseGraph
        The input graph with the optimised poses (edges unchanged).
    status : LMStatus
        ``converged``, ``max_iterations`` or ``failed`` (the optimiser's status; ``failed`` also for a
        graph that cannot be solved).
    reason : str
    cost_initial, cost_final : float
        ``F`` (contract cost, no robust kernel) before and after.
    iterations : int
        Linearisations performed.
    history : list of dict
        Per iteration: cost, lambda, accepted, step norm.
    fixed_ids : tuple of int
        The vertices held fixed (gauge).
    non_psd_edges : int
        Edges whose information matrix, as given, is not positive semi-definite.
    information_changed : int
        Of those, the edges whose matrix was replaced by GTSAM's ``RᵀR``
        (``indefinite_information="gtsam"``); the cost and optimisation use the replaced matrices.
    convergence : dict
        ``relative_decrease`` of the last accepted step and ``predicted_relative_decrease``, the
        Gauss–Newton model's decrease ``½ gᵀH⁻¹g / F`` at the final poses (how far from a
        stationary point the result is; None with plane landmarks).
    user_error : bool
        The failure comes from the input graph (a vertex or plane nothing constrains), not from the
        optimisation: the CLI reports it as a user error.
    planes : PlaneSet or None
        With plane landmarks: the optimised planes (edges unchanged); else None.
    """

    graph: PoseGraph
    status: LMStatus
    reason: str
    cost_initial: float
    cost_final: float
    iterations: int
    history: list = field(default_factory=list)
    fixed_ids: tuple = ()
    non_psd_edges: int = 0
    params: PoseGraphParams = field(default_factory=PoseGraphParams)
    timings_s: dict = field(default_factory=dict)
    planes: PlaneSet | None = None
    information_changed: int = 0
    convergence: dict = field(default_factory=dict)
    user_error: bool = False

    def summary(self) -> dict:
        out = {"status": self.status, "reason": self.reason, "cost_initial": self.cost_initial,
               "cost_final": self.cost_final, "iterations": self.iterations, "fixed_ids": list(self.fixed_ids),
               "non_psd_edges": self.non_psd_edges, "information_changed": self.information_changed,
               "information_rule": (f"GTSAM readG2o RᵀR for the {self.information_changed} non-PSD edge(s)"
                                    if self.information_changed else "as given"),
               "convergence": self.convergence, "params": asdict(self.params)}
        if self.planes is not None:
            out["planes"] = {"nodes": self.planes.n_planes, "edges": self.planes.n_edges}
        return out


def _dof(kind: str) -> int:
    return 6 if kind == "SE3" else 3


def _information_rt(graph: PoseGraph) -> np.ndarray:
    """Information matrices in residual order, rotation first: SE3 (t, r) → (r, t); SE2 (x, y, θ) → (θ, x, y)."""
    p = [3, 4, 5, 0, 1, 2] if graph.kind == "SE3" else [2, 0, 1]
    info = np.asarray(graph.information, dtype=np.float64)
    return np.ascontiguousarray(info[:, p][:, :, p])


def _residuals(kind, poses, edges, Z):
    return between_residuals(kind, poses, edges, Z)


def _cost(r, info) -> float:
    return quadratic_cost(r, info)


def _plane_residuals(poses, planes: np.ndarray, ps: PlaneSet) -> np.ndarray:
    """Pose–plane residuals (mp, 3) [Ren2019 Eq. 11] at the given poses and plane values."""
    r = np.empty((ps.n_edges, 3))
    KP.pose_plane_residuals(poses, planes, ps.edges, ps.measurements, r)
    return r


def pose_graph_cost(graph: PoseGraph, planes: PlaneSet | None = None) -> float:
    """The contract cost ``F = ½ Σ rᵀΩr`` of the graph at its current poses (plus ``½ Σ eᵀΩe`` of
    the pose–plane edges [Ren2019 Eq. 11] at the current plane values, if ``planes`` is given)."""
    poses, edges, Z = _arrays(graph)
    cost = _cost(_residuals(graph.kind, poses, edges, Z), _information_rt(graph))
    if planes is not None:
        cost += _cost(_plane_residuals(poses, planes.planes, planes), planes.information)
    return cost


def _arrays(graph: PoseGraph):
    return (np.ascontiguousarray(graph.poses, dtype=np.float64), np.ascontiguousarray(graph.edges, dtype=np.int64),
            np.ascontiguousarray(graph.measurements, dtype=np.float64))


def _normal_equations(kind, poses, edges, Z, info, w, free_col, plane_part=None):
    """Sparse ``H``, dense ``g`` and the edge residuals over the free poses (``free_col[v]`` = first
    column of v, or -1) and, with ``plane_part = (planes, PlaneSet, weights)``, the plane landmarks
    after them (:class:`minegeo.optim.blocks.SparseSystem`)."""
    d = _dof(kind)
    n = n_pose_cols = int(free_col.max()) + d if np.any(free_col >= 0) else 0
    if plane_part is not None:
        n += 3 * plane_part[1].n_planes
    system = SparseSystem(n, "singular normal equations: a vertex is not constrained by any edge (disconnected graph?)")
    r = _linearize_into(system, kind, poses, edges, Z, info, w, free_col, plane_part, n_pose_cols)
    return system.matrix(), system.g, r


def _linearize_into(system, kind, poses, edges, Z, info, w, free_col, plane_part, n_pose_cols):
    """Add the between edges and (``plane_part = (planes, PlaneSet, weights)``) the pose–plane edges
    [Ren2019 Eq. 11] to ``system``; returns the edge residuals."""
    r, Ji, Jj = between_terms(kind, poses, edges, Z)
    system.add(r, info * w[:, None, None], ((free_col[edges[:, 0]], Ji), (free_col[edges[:, 1]], Jj)))
    if plane_part is not None:
        pl, ps, wp = plane_part
        m = ps.n_edges
        rp, Jp, Jl = np.empty((m, 3)), np.empty((m, 3, 6)), np.empty((m, 3, 3))
        KP.pose_plane_edge_terms(poses, pl, ps.edges, ps.measurements, rp, Jp, Jl)
        system.add(rp, ps.information * wp[:, None, None],
                   ((free_col[ps.edges[:, 0]], Jp), (n_pose_cols + 3 * ps.edges[:, 1], Jl)))
    return r


@dataclass(frozen=True)
class _PosesPlanes:
    """The variables of a pose graph with plane landmarks."""

    poses: np.ndarray
    planes: np.ndarray


class _PlaneProblem:
    """Poses and plane landmarks for :func:`minegeo.optim.lm.levenberg_marquardt`: between edges and
    pose–plane edges [Ren2019 Eq. 11], general sparse normal equations (poses 6 columns, planes 3)."""

    hint = ""

    def __init__(self, graph: PoseGraph, info, ps: PlaneSet, held, free_col, free_ids, n_pose_cols,
                 params: PoseGraphParams):
        self.kind, self.held, self.params, self.ps, self.info = graph.kind, tuple(held), params, ps, info
        self.poses, self.edges, self.Z = _arrays(graph)
        self.free_col, self.free_ids, self.n_pose_cols = free_col, free_ids, n_pose_cols
        self.system = SparseSystem(n_pose_cols + 3 * ps.n_planes, "singular normal equations: a vertex is not "
                                   "constrained by any edge (disconnected graph?)")

    def evaluate(self, v: _PosesPlanes):
        return _residuals(self.kind, v.poses, self.edges, self.Z), _plane_residuals(v.poses, v.planes, self.ps)

    def cost(self, res) -> float:
        return _cost(res[0], self.info) + _cost(res[1], self.ps.information)

    def robust_cost(self, res) -> float:
        k, s = self.params.robust, self.params.robust_scale
        return robust_cost(res[0], self.info, k, s) + robust_cost(res[1], self.ps.information, k, s)

    def linearize(self, v: _PosesPlanes, res):
        k, s = self.params.robust, self.params.robust_scale
        self.system.reset()
        _linearize_into(self.system, self.kind, v.poses, self.edges, self.Z, self.info,
                        robust_weights(res[0], self.info, k, s), self.free_col,
                        (v.planes, self.ps, robust_weights(res[1], self.ps.information, k, s)), self.n_pose_cols)
        return self.system

    def gauss_newton_decrease(self, v, res):
        return None, -1  # not computed by the LU path

    def retract(self, v: _PosesPlanes, delta) -> _PosesPlanes:
        return _PosesPlanes(_retract(self.kind, v.poses, self.free_ids, self.free_col, delta),
                            _retract_planes(v.planes, delta, self.n_pose_cols))

    def singular(self, v: int):
        return "singular normal equations", -1

    def check(self, v0: _PosesPlanes, v1: _PosesPlanes, cost_final: float, cost_initial: float) -> str:
        return check_result(v0.poses, v1.poses, self.held, cost_final, cost_initial)


def _unanchored(n: int, edges: np.ndarray, fixed_idx) -> np.ndarray:
    """Vertices in a connected component without a fixed vertex (their gauge is free: H is singular)."""
    from scipy.sparse.csgraph import connected_components

    adj = sp.coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    anchored = np.isin(label, label[list(fixed_idx)])
    return np.flatnonzero(~anchored)


def _unobserved_planes(ps: PlaneSet) -> np.ndarray:
    """Plane landmarks no pose–plane edge reaches (their 3 columns of H are zero)."""
    seen = np.zeros(ps.n_planes, dtype=bool)
    seen[ps.edges[:, 1]] = True
    return np.flatnonzero(~seen)


def _retract(kind, poses, free_ids, free_col, delta):
    out = poses.copy()
    d = _dof(kind)
    exp = se3_exp if kind == "SE3" else se2_exp
    for v in free_ids:
        c = free_col[v]
        out[v] = poses[v] @ exp(np.ascontiguousarray(delta[c:c + d]))
    return out


def _retract_planes(planes, delta, n_pose_cols: int) -> np.ndarray:
    """Every plane ``l`` ← ``plane_retract(π_l, δ[c:c+3])``, ``c = n_pose_cols + 3 l`` (S² × R update)."""
    out = np.empty_like(planes)
    for k in range(planes.shape[0]):
        c = n_pose_cols + 3 * k
        out[k] = KP.plane_retract(planes[k], np.ascontiguousarray(delta[c:c + 3]))
    return out


def _check_planes(graph: PoseGraph, ps: PlaneSet | None) -> str:
    """Why the plane set cannot be used with this graph ("" if it can)."""
    if ps is None:
        return ""
    if graph.kind != "SE3":
        raise InputError("plane landmarks need an SE3 pose graph")
    if ps.n_edges and ps.edges[:, 0].max() >= graph.n_vertices:
        raise InputError(f"a pose–plane edge indexes pose {int(ps.edges[:, 0].max())} of {graph.n_vertices}")
    lost = _unobserved_planes(ps)
    return f"{lost.size} plane(s) observed by no pose (first: plane {int(lost[0])})" if lost.size else ""


def _gauge(graph: PoseGraph):
    """The fixed vertices (``FIX`` records, else the first) and the column layout of the free ones:
    ``(fixed indices, fixed ids, free mask, first column per vertex (-1 fixed), free indices, pose columns)``."""
    d = _dof(graph.kind)
    n = graph.n_vertices
    fixed_idx = [int(np.flatnonzero(graph.ids == f)[0]) for f in graph.fixed] or [0]
    fixed_ids = tuple(int(graph.ids[k]) for k in fixed_idx)
    free = np.ones(n, dtype=bool)
    free[fixed_idx] = False
    free_col = np.full(n, -1, dtype=np.int64)
    free_col[free] = np.arange(int(free.sum())) * d
    return fixed_idx, fixed_ids, free, free_col, np.flatnonzero(free), int(free.sum()) * d


def _used_information(graph: PoseGraph, params: PoseGraphParams):
    """``(information in the file's order as optimised, number of non-PSD edges, number replaced)``."""
    bad = non_psd_edges(graph)
    info = np.asarray(graph.information, dtype=np.float64)
    if not bad.size:
        return info, 0, 0
    ev = float(np.linalg.eigvalsh(info[bad[0]])[0])
    if params.indefinite_information == "refuse":
        raise InputError(f"{edge_label(graph, int(bad[0]))}: the information matrix is not positive semi-definite "
                         f"(smallest eigenvalue {ev:.6g}); {bad.size} edge(s) are (indefinite_information='gtsam', "
                         "--indefinite-information gtsam, uses GTSAM's readG2o matrix for them)")
    info = info.copy()
    info[bad] = gtsam_information(info[bad], graph.kind)
    log.warning("%d edge(s) have an information matrix that is not positive semi-definite (first: %s, smallest "
                "eigenvalue %.6g): each replaced by the matrix GTSAM's readG2o uses, RᵀR with R from Eigen's LLT "
                "stopped at its first non-positive pivot (positive semi-definite)", bad.size,
                edge_label(graph, int(bad[0])), ev)
    return info, int(bad.size), int(bad.size)


def _check_graph(graph: PoseGraph, fixed_idx) -> None:
    """Input errors no optimisation can mend: no edges, a self-loop, every vertex held."""
    if graph.n_edges == 0:
        raise InputError("the pose graph has no edges: nothing to optimise")
    if graph.kind not in ("SE3", "SE2"):
        raise InputError(f"pose graph kind must be SE3 or SE2, got {graph.kind!r}")
    loops = np.flatnonzero(graph.edges[:, 0] == graph.edges[:, 1])
    if loops.size:
        raise InputError(f"{edge_label(graph, int(loops[0]))}: an edge from a vertex to itself constrains nothing")
    if len(set(fixed_idx)) >= graph.n_vertices:
        raise InputError(f"every vertex ({graph.n_vertices}) is held fixed (FIX records): nothing to optimise")


def optimize_pose_graph(graph: PoseGraph, params: PoseGraphParams | None = None,
                        planes: PlaneSet | None = None) -> PoseGraphResult:
    """Minimise the contract cost of a pose graph by Levenberg–Marquardt on the Lie algebra.

    Parameters
    ----------
    graph : PoseGraph
        Poses ``T_world_vertex`` (initial values) and between-edges ``Z_ij ≈ T_i⁻¹ T_j`` with
        information matrices, e.g. from :func:`minegeo.io.g2o.read_g2o`. A matrix that is not
        positive semi-definite is replaced by GTSAM's ``RᵀR`` or refused
        (``params.indefinite_information``).
    params : PoseGraphParams, optional
    planes : PlaneSet, optional
        Plane landmarks (initial values) and pose–plane edges [Ren2019 Eq. 11] (SE3 only); their
        cost is added to ``F`` and the planes are optimised with the poses.

    Returns
    -------
    PoseGraphResult
        The optimised graph (and planes), costs before/after (``F = ½ Σ rᵀΩr`` with the matrices
        optimised, plus the plane edges' ``½ Σ eᵀΩe``), iterations and status. ``"converged"``
        only when the stopping test held **and** the result passed
        :func:`minegeo.optim.lm.check_result` and the undamped normal equations at the result are
        positive definite (block path). ``"max_iterations"``: stopped
        at the cap, the reason says how far from converged (last relative decrease, Gauss–Newton
        predicted decrease). ``"failed"`` (with the reason) when the normal equations are singular
        (a vertex no edge with non-zero information constrains, a pose without a between-edge path
        to a fixed pose, a plane no pose observes), the cost is not finite or the result fails its
        check; the poses are then the input ones.

    Raises
    ------
    InputError
        No edges, a self-loop edge, every vertex fixed, or (``indefinite_information="refuse"``)
        an information matrix that is not positive semi-definite.
    """
    params = params or PoseGraphParams()
    t0 = time.perf_counter()
    fixed_idx, fixed_ids, free, free_col, _, n_pose_cols = _gauge(graph)
    _check_graph(graph, fixed_idx)
    plane_problem = _check_planes(graph, planes)
    info_file, n_bad, n_changed = _used_information(graph, params)
    used = PoseGraph(graph.kind, graph.ids, graph.poses, graph.edges, graph.measurements, info_file, graph.fixed)

    def result(status, reason, cost_i, cost_f, iters, hist, pl=None, g=graph, conv=None, user=False):
        return PoseGraphResult(g, status, reason, cost_i, cost_f, iters, hist, fixed_ids, n_bad, params,
                               {"total": time.perf_counter() - t0}, pl if pl is not None else planes, n_changed,
                               conv or {}, user)

    live = np.any(info_file != 0.0, axis=(1, 2))  # an all-zero information ties nothing
    unanchored = _unanchored(graph.n_vertices, graph.edges[live], fixed_idx)  # planes fix only z, roll, pitch
    if unanchored.size:
        return result(LMStatus.FAILED, f"{unanchored.size} vertex(es) not constrained by any edge path (edges with non-zero "
                      f"information) to a fixed vertex (first: id {int(graph.ids[unanchored[0]])}); disconnected "
                      "graph?", float("nan"), float("nan"), 0, [], user=True)
    if plane_problem:
        return result(LMStatus.FAILED, plane_problem, float("nan"), float("nan"), 0, [], user=True)
    outcome = _solve(used, params, planes, fixed_idx, free_col, np.flatnonzero(free), n_pose_cols)
    status, reason, cost0, it, history, conv = (outcome.status, outcome.reason, outcome.cost_initial,
                                                outcome.iterations, outcome.history, outcome.convergence)
    if status == LMStatus.FAILED:
        return result(status, reason, cost0, cost0, it, history, conv=conv, user=conv.get("singular_vertex") is not None)
    v = outcome.values
    pl = planes.with_planes(v.planes) if planes is not None and hasattr(v, "planes") else None
    return result(status, reason, cost0, outcome.cost_final, it, history, pl, graph.with_poses(v.poses), conv)


def _solve(graph: PoseGraph, params: PoseGraphParams, planes, fixed_idx, free_col, free_ids, n_pose_cols):
    """Levenberg–Marquardt (:func:`minegeo.optim.lm.levenberg_marquardt`) on ``graph`` (its information
    as optimised): block Cholesky on the poses, or sparse LU with plane landmarks."""
    poses, edges, Z = _arrays(graph)
    info = _information_rt(graph)
    if planes is None or (planes.n_planes == 0 and planes.n_edges == 0):
        ids = graph.ids
        problem = FactorProblem(graph.n_vertices, _dof(graph.kind), [BetweenFactors(edges, Z, info)], fixed_idx,
                                params, labels=lambda v: (f"vertex id {int(ids[v])}", int(ids[v])))
        return levenberg_marquardt(problem, Values(poses), params)
    problem = _PlaneProblem(graph, info, planes, fixed_idx, free_col, free_ids, n_pose_cols, params)
    return levenberg_marquardt(problem, _PosesPlanes(poses, planes.planes.copy()), params)
