"""Pose-graph optimisation: Levenberg–Marquardt on the Lie algebra, sparse normal equations.

The back end of Ren et al. 2019 (Sec. 3.4, "solved by Gauss-Newton or Levenberg-Marquardt"), written
out so that an auditor can check it, and the cost fixed by the SLAM contract (``slam_contract.md``;
the same as GTSAM's ``BetweenFactorPose3`` / ``BetweenFactorPose2`` on a file read by ``readG2o``):

.. math::

    F(T) = \\tfrac12 \\sum_{(i,j)} r_{ij}^\\top \\Omega_{ij} r_{ij}, \\qquad
    r_{ij} = \\operatorname{Log}(Z_{ij}^{-1} T_i^{-1} T_j)

with ``r`` ordered rotation first, (ω, ρ) for SE(3) and (θ, x, y) for SE(2) (the file's (t, r) and
(x, y, θ) information matrices are permuted to match; the cost is unchanged by the ordering). One iteration linearises every edge (:mod:`minegeo.slam._kernels`:
analytic Jacobians ``J_i``, ``J_j``), assembles the sparse normal equations

.. math::

    (H + \\lambda\\, \\mathrm{diag}(H))\\, \\delta = -g, \\quad
    H = \\sum J^\\top W \\Omega J, \\quad g = \\sum J^\\top W \\Omega r

by hand into a ``scipy.sparse`` matrix (blocks ``(i,i), (i,j), (j,i), (j,j)`` per edge), removes
the fixed poses (gauge: the ``FIX`` vertices, else the first one), solves with a sparse LU
factorisation, and retracts ``T ← T · Exp(δ)``. A step is accepted when it lowers the cost (λ ÷ 10),
else rejected (λ × 10) [Nocedal2006 Sec. 10.3]. Robust kernels reweight each edge by its whitened
residual ``s = sqrt(rᵀΩr)`` (IRLS): Huber ``w = min(1, k/s)``, Cauchy ``w = 1/(1 + (s/k)²)``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from minegeo.errors import InputError
from minegeo.io.g2o import PoseGraph, non_psd_edges
from minegeo.kernels.lie import se2_exp, se3_exp
from minegeo.slam import _kernels as K

__all__ = ["PoseGraphParams", "PoseGraphResult", "optimize_pose_graph", "pose_graph_cost"]

log = logging.getLogger(__name__)

ROBUST = ("none", "huber", "cauchy")


@dataclass(frozen=True)
class PoseGraphParams:
    """Parameters of :func:`optimize_pose_graph`.

    Attributes
    ----------
    max_iterations : int
        Largest number of linearisations.
    lambda_init : float
        Initial LM damping (relative to ``diag(H)``).
    relative_cost_tolerance : float
        Stop when an accepted step lowers the cost by less than this fraction.
    step_tolerance : float
        Stop when the largest step component (rad or m) is below this.
    robust : {"none", "huber", "cauchy"}
        Robust kernel on the whitened residual norm.
    robust_scale : float
        Kernel width ``k`` in whitened units (1 = one standard deviation).
    """

    max_iterations: int = 100
    lambda_init: float = 1e-5
    relative_cost_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    robust: str = "none"
    robust_scale: float = 1.0

    def __post_init__(self):
        if self.robust not in ROBUST:
            raise InputError(f"robust must be one of {ROBUST}, got {self.robust!r}")
        if not (self.max_iterations >= 1 and self.lambda_init > 0 and self.robust_scale > 0):
            raise InputError("max_iterations >= 1, lambda_init > 0 and robust_scale > 0 are required")


@dataclass
class PoseGraphResult:
    """Outcome of :func:`optimize_pose_graph`.

    Attributes
    ----------
    graph : PoseGraph
        The input graph with the optimised poses (edges unchanged).
    status : {"converged", "max_iterations", "failed"}
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
        Edges whose information matrix is not positive semi-definite (kept as read).
    """

    graph: PoseGraph
    status: str
    reason: str
    cost_initial: float
    cost_final: float
    iterations: int
    history: list = field(default_factory=list)
    fixed_ids: tuple = ()
    non_psd_edges: int = 0
    params: PoseGraphParams = field(default_factory=PoseGraphParams)
    timings_s: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"status": self.status, "reason": self.reason, "cost_initial": self.cost_initial,
                "cost_final": self.cost_final, "iterations": self.iterations, "fixed_ids": list(self.fixed_ids),
                "non_psd_edges": self.non_psd_edges, "params": asdict(self.params)}


def _dof(kind: str) -> int:
    return 6 if kind == "SE3" else 3


def _information_rt(graph: PoseGraph) -> np.ndarray:
    """Information matrices in residual order, rotation first: SE3 (t, r) → (r, t); SE2 (x, y, θ) → (θ, x, y)."""
    p = [3, 4, 5, 0, 1, 2] if graph.kind == "SE3" else [2, 0, 1]
    info = np.asarray(graph.information, dtype=np.float64)
    return np.ascontiguousarray(info[:, p][:, :, p])


def _residuals(kind, poses, edges, Z):
    r = np.empty((edges.shape[0], _dof(kind)))
    (K.se3_residuals if kind == "SE3" else K.se2_residuals)(poses, edges, Z, r)
    return r


def _cost(r, info) -> float:
    return 0.5 * float(np.einsum("ei,eij,ej->", r, info, r))


def pose_graph_cost(graph: PoseGraph) -> float:
    """The contract cost ``F = ½ Σ rᵀΩr`` of the graph at its current poses."""
    poses, edges, Z = _arrays(graph)
    return _cost(_residuals(graph.kind, poses, edges, Z), _information_rt(graph))


def _arrays(graph: PoseGraph):
    return (np.ascontiguousarray(graph.poses, dtype=np.float64), np.ascontiguousarray(graph.edges, dtype=np.int64),
            np.ascontiguousarray(graph.measurements, dtype=np.float64))


def _robust_weights(r, info, params: PoseGraphParams) -> np.ndarray:
    if params.robust == "none":
        return np.ones(r.shape[0])
    s = np.sqrt(np.maximum(np.einsum("ei,eij,ej->e", r, info, r), 0.0))
    k = params.robust_scale
    if params.robust == "huber":
        return np.where(s <= k, 1.0, k / np.maximum(s, k))
    return 1.0 / (1.0 + (s / k) ** 2)


def _robust_cost(r, info, params: PoseGraphParams) -> float:
    if params.robust == "none":
        return _cost(r, info)
    s2 = np.maximum(np.einsum("ei,eij,ej->e", r, info, r), 0.0)
    k = params.robust_scale
    if params.robust == "huber":
        s = np.sqrt(s2)
        rho = np.where(s <= k, s2, 2.0 * k * s - k * k)
    else:
        rho = k * k * np.log1p(s2 / (k * k))
    return 0.5 * float(rho.sum())


def _normal_equations(kind, poses, edges, Z, info, w, free_col):
    """Sparse ``H`` and dense ``g`` over the free poses (``free_col[v]`` = first column of v, or -1)."""
    d = _dof(kind)
    m = edges.shape[0]
    r = np.empty((m, d))
    Ji = np.empty((m, d, d))
    Jj = np.empty((m, d, d))
    (K.se3_edge_terms if kind == "SE3" else K.se2_edge_terms)(poses, edges, Z, r, Ji, Jj)
    WO = info * w[:, None, None]
    J = (Ji, Jj)
    cols = (free_col[edges[:, 0]], free_col[edges[:, 1]])
    n = int(free_col.max()) + d if np.any(free_col >= 0) else 0
    g = np.zeros(n)
    rows_all, cols_all, vals_all = [], [], []
    ar = np.arange(d)
    for a in (0, 1):
        keep_a = cols[a] >= 0
        JtW = np.einsum("eji,ejk->eik", J[a], WO)  # J_aᵀ W Ω
        np.add.at(g, (cols[a][keep_a, None] + ar[None, :]), np.einsum("eik,ek->ei", JtW, r)[keep_a])
        for b in (0, 1):
            keep = keep_a & (cols[b] >= 0)
            blk = np.einsum("eik,ekj->eij", JtW[keep], J[b][keep])
            rows_all.append(np.broadcast_to((cols[a][keep][:, None] + ar)[:, :, None], blk.shape).ravel())
            cols_all.append(np.broadcast_to((cols[b][keep][:, None] + ar)[:, None, :], blk.shape).ravel())
            vals_all.append(blk.ravel())
    H = sp.coo_matrix((np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
                      shape=(n, n)).tocsc()
    return H, g, r


def _unanchored(n: int, edges: np.ndarray, fixed_idx) -> np.ndarray:
    """Vertices in a connected component without a fixed vertex (their gauge is free: H is singular)."""
    from scipy.sparse.csgraph import connected_components

    adj = sp.coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    anchored = np.isin(label, label[list(fixed_idx)])
    return np.flatnonzero(~anchored)


def _retract(kind, poses, free_ids, free_col, delta):
    out = poses.copy()
    d = _dof(kind)
    exp = se3_exp if kind == "SE3" else se2_exp
    for v in free_ids:
        c = free_col[v]
        out[v] = poses[v] @ exp(np.ascontiguousarray(delta[c:c + d]))
    return out


def optimize_pose_graph(graph: PoseGraph, params: PoseGraphParams | None = None) -> PoseGraphResult:
    """Minimise the contract cost of a pose graph by Levenberg–Marquardt on the Lie algebra.

    Parameters
    ----------
    graph : PoseGraph
        Poses ``T_world_vertex`` (initial values) and between-edges ``Z_ij ≈ T_i⁻¹ T_j`` with
        information matrices, e.g. from :func:`minegeo.io.g2o.read_g2o`.
    params : PoseGraphParams, optional

    Returns
    -------
    PoseGraphResult
        The optimised graph, costs before/after (``F = ½ Σ rᵀΩr``), iterations and status.
        ``status`` is ``"failed"`` (with the reason) when the normal equations are singular
        (a vertex no edge constrains) or the cost is not finite; the poses are then the input ones.
    """
    params = params or PoseGraphParams()
    t0 = time.perf_counter()
    if graph.n_edges == 0:
        raise InputError("the pose graph has no edges: nothing to optimise")
    if graph.kind not in ("SE3", "SE2"):
        raise InputError(f"pose graph kind must be SE3 or SE2, got {graph.kind!r}")
    poses, edges, Z = _arrays(graph)
    info = _information_rt(graph)
    d = _dof(graph.kind)
    n = graph.n_vertices
    fixed_idx = [int(np.flatnonzero(graph.ids == f)[0]) for f in graph.fixed] or [0]
    fixed_ids = tuple(int(graph.ids[k]) for k in fixed_idx)
    free = np.ones(n, dtype=bool)
    free[fixed_idx] = False
    free_col = np.full(n, -1, dtype=np.int64)
    free_col[free] = np.arange(int(free.sum())) * d
    free_ids = np.flatnonzero(free)
    unanchored = _unanchored(n, edges, fixed_idx)
    if unanchored.size:
        return PoseGraphResult(graph, "failed", f"{unanchored.size} vertex(es) not constrained by any edge path to a fixed "
                               f"vertex (first: id {int(graph.ids[unanchored[0]])}); disconnected graph?", float("nan"),
                               float("nan"), 0, [], fixed_ids, 0, params, {"total": time.perf_counter() - t0})
    n_bad = int(non_psd_edges(graph).size)
    if n_bad:
        log.warning("%d edge(s) have an information matrix that is not positive semi-definite (kept as read)", n_bad)

    r = _residuals(graph.kind, poses, edges, Z)
    cost0 = _cost(r, info)
    cost = _robust_cost(r, info, params)
    lam = params.lambda_init
    history: list[dict] = []
    status, reason, it = "max_iterations", f"stopped after {params.max_iterations} iterations", 0
    if not np.isfinite(cost0):
        return PoseGraphResult(graph, "failed", "the initial cost is not finite", cost0, cost0, 0, [], fixed_ids, n_bad,
                               params, {"total": time.perf_counter() - t0})
    for it in range(1, params.max_iterations + 1):
        w = _robust_weights(r, info, params)
        H, g, _ = _normal_equations(graph.kind, poses, edges, Z, info, w, free_col)
        diag = H.diagonal()
        accepted = False
        while lam < 1e12:
            A = (H + sp.diags(lam * np.maximum(diag, 1e-12))).tocsc()
            try:
                delta = spla.splu(A).solve(-g)
            except RuntimeError:  # exactly singular: a vertex no edge reaches
                return PoseGraphResult(graph, "failed", "singular normal equations: a vertex is not constrained by any "
                                       "edge (disconnected graph?)", cost0, cost0, it, history, fixed_ids, n_bad, params,
                                       {"total": time.perf_counter() - t0})
            trial = _retract(graph.kind, poses, free_ids, free_col, delta)
            r_trial = _residuals(graph.kind, trial, edges, Z)
            cost_trial = _robust_cost(r_trial, info, params)
            step = float(np.abs(delta).max()) if delta.size else 0.0
            if np.isfinite(cost_trial) and cost_trial <= cost:
                history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": True, "step": step})
                rel = (cost - cost_trial) / max(cost, 1e-300)
                poses, r, cost, accepted = trial, r_trial, cost_trial, True
                lam = max(lam / 10.0, 1e-12)
                break
            history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": False, "step": step})
            lam *= 10.0
        if not accepted:
            status, reason = "converged", "no step lowers the cost (damping exhausted): at a minimum"
            break
        if rel < params.relative_cost_tolerance or step < params.step_tolerance:
            status, reason = "converged", f"relative cost decrease {rel:.2e}, largest step {step:.2e}"
            break
    out = graph.with_poses(poses)
    return PoseGraphResult(out, status, reason, cost0, _cost(r, info), it, history, fixed_ids, n_bad, params,
                           {"total": time.perf_counter() - t0})
