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

    (H + \\lambda D)\\, \\delta = -g, \\quad
    H = \\sum J^\\top W \\Omega J, \\quad g = \\sum J^\\top W \\Omega r

with ``D = I`` (GTSAM's default damping) or ``D = diag(H)`` (Marquardt's, ``damping="diagonal"``),
over the free poses (gauge: the ``FIX`` vertices, else the first one), and retracts
``T ← T · Exp(δ)``. A step is accepted when it lowers the cost (λ ÷ 10), else rejected (λ × 10)
[Nocedal2006 Sec. 10.3]. The linear algebra is by d×d blocks (d = 6 or 3): the free poses are put
in a fill-reducing order once (minimum degree on the pose graph), the pattern of the Cholesky factor
is computed once (elimination tree), every edge's blocks are accumulated by a serial Numba kernel
straight into that pattern, and each damping trial is a left-looking block Cholesky and two block
triangular solves (:mod:`minegeo.slam._kernels`); a trial whose damped matrix is not positive
definite is rejected like a step that raises the cost. Graphs with an indefinite information
matrix (the real ``cubicle.g2o``) or with plane landmarks use the general path instead: the same
normal equations as a ``scipy.sparse`` matrix (blocks ``(i,i), (i,j), (j,i), (j,j)`` per edge)
solved by a sparse LU factorisation, which does not need ``H + λD`` to be positive definite. Robust kernels reweight each edge by its whitened
residual ``s = sqrt(rᵀΩr)`` (IRLS): Huber ``w = min(1, k/s)``, Cauchy ``w = 1/(1 + (s/k)²)``.

Optional plane landmarks (:class:`PlaneSet`, Ren et al. 2019 Sec. 3.4.2-3.4.3): world planes
``π_l = (n, d)`` as extra nodes and pose–plane edges with the error of [Ren2019 Eq. 11]
(:func:`minegeo.slam._kernels_planes.pose_plane_edge_terms`), added to the same cost,
``F = ½ Σ rᵀΩr + ½ Σ e_tᵀ Ω_t e_t``. The free poses keep their columns ``6·k``; plane ``l`` takes
the columns ``n_pose_cols + 3·l`` (all planes free), updated on S² × R by
:func:`~minegeo.slam._kernels_planes.plane_retract`. A plane constrains only height, roll and pitch
of a pose, so every pose still needs a between-edge path to a fixed pose. Without planes the
solver runs exactly as before (bit-identical).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from minegeo.errors import InputError
from minegeo.io.g2o import PoseGraph, edge_label, gtsam_information, non_psd_edges
from minegeo.kernels.lie import se2_exp, se3_exp
from minegeo.slam import _kernels as K
from minegeo.slam import _kernels_planes as KP

__all__ = ["PlaneSet", "PoseGraphParams", "PoseGraphResult", "optimize_pose_graph", "pose_graph_cost"]

log = logging.getLogger(__name__)

ROBUST = ("none", "huber", "cauchy")
INDEFINITE = ("gtsam", "refuse")
#: a pivot of the undamped ``H`` below this fraction of its diagonal entry: ``H`` is singular there
SINGULAR_PIVOT = 1e-12
#: rotations of the result orthonormal to this (max |RRᵀ − I|, |det R − 1|)
ROTATION_TOL = 1e-9


@dataclass(frozen=True)
class PoseGraphParams:
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
    """

    max_iterations: int = 500
    lambda_init: float = 1e-5
    relative_cost_tolerance: float = 1e-10
    remaining_cost_tolerance: float = 1e-8
    step_tolerance: float = 1e-10
    robust: str = "none"
    robust_scale: float = 1.0
    damping: str = "identity"
    indefinite_information: str = "gtsam"

    def __post_init__(self):
        if self.damping not in ("diagonal", "identity"):
            raise InputError(f"damping must be 'diagonal' or 'identity', got {self.damping!r}")
        if self.robust not in ROBUST:
            raise InputError(f"robust must be one of {ROBUST}, got {self.robust!r}")
        if self.indefinite_information not in INDEFINITE:
            raise InputError(f"indefinite_information must be one of {INDEFINITE}, got {self.indefinite_information!r}")
        if not (self.max_iterations >= 1 and self.lambda_init > 0 and self.robust_scale > 0):
            raise InputError("max_iterations >= 1, lambda_init > 0 and robust_scale > 0 are required")
        if not (np.isfinite(self.lambda_init) and np.isfinite(self.robust_scale)
                and self.relative_cost_tolerance >= 0 and self.step_tolerance >= 0
                and self.remaining_cost_tolerance >= 0):
            raise InputError("lambda_init and robust_scale must be finite, the tolerances >= 0")


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
    r = np.empty((edges.shape[0], _dof(kind)))
    (K.se3_residuals if kind == "SE3" else K.se2_residuals)(poses, edges, Z, r)
    return r


def _cost(r, info) -> float:
    return 0.5 * float(np.einsum("ei,eij,ej->", r, info, r))


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


def _plane_blocks(poses, planes, ps: PlaneSet, wp, free_col, n_pose_cols, g, rows_all, cols_all, vals_all):
    """Add the pose–plane edges [Ren2019 Eq. 11] to ``g`` and the block lists of ``H``.

    Per edge ``(pose p, plane l)``: ``(p,p) = JpᵀWΩJp``, ``(p,l) = JpᵀWΩJl`` and its transpose,
    ``(l,l) = JlᵀWΩJl``, ``g_p += JpᵀWΩe``, ``g_l += JlᵀWΩe``; pose blocks skipped for fixed poses.
    """
    m = ps.n_edges
    r, Jp, Jl = np.empty((m, 3)), np.empty((m, 3, 6)), np.empty((m, 3, 3))
    KP.pose_plane_edge_terms(poses, planes, ps.edges, ps.measurements, r, Jp, Jl)
    WO = ps.information * wp[:, None, None]
    J = (Jp, Jl)
    cols = (free_col[ps.edges[:, 0]], n_pose_cols + 3 * ps.edges[:, 1])
    ar = (np.arange(6), np.arange(3))
    for a in (0, 1):
        keep_a = cols[a] >= 0
        JtW = np.einsum("eji,ejk->eik", J[a], WO)
        np.add.at(g, (cols[a][keep_a, None] + ar[a][None, :]), np.einsum("eik,ek->ei", JtW, r)[keep_a])
        for b in (0, 1):
            keep = keep_a & (cols[b] >= 0)
            blk = np.einsum("eik,ekj->eij", JtW[keep], J[b][keep])
            rows_all.append(np.broadcast_to((cols[a][keep][:, None] + ar[a])[:, :, None], blk.shape).ravel())
            cols_all.append(np.broadcast_to((cols[b][keep][:, None] + ar[b])[:, None, :], blk.shape).ravel())
            vals_all.append(blk.ravel())
    return r


def _normal_equations(kind, poses, edges, Z, info, w, free_col, plane_part=None):
    """Sparse ``H`` and dense ``g`` over the free poses (``free_col[v]`` = first column of v, or -1)
    and, with ``plane_part = (planes, PlaneSet, weights)``, the plane landmarks after them."""
    d = _dof(kind)
    m = edges.shape[0]
    r = np.empty((m, d))
    Ji = np.empty((m, d, d))
    Jj = np.empty((m, d, d))
    (K.se3_edge_terms if kind == "SE3" else K.se2_edge_terms)(poses, edges, Z, r, Ji, Jj)
    WO = info * w[:, None, None]
    J = (Ji, Jj)
    cols = (free_col[edges[:, 0]], free_col[edges[:, 1]])
    n = n_pose_cols = int(free_col.max()) + d if np.any(free_col >= 0) else 0
    if plane_part is not None:
        n += 3 * plane_part[1].n_planes
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
    if plane_part is not None:
        _plane_blocks(poses, *plane_part, free_col, n_pose_cols, g, rows_all, cols_all, vals_all)
    H = sp.coo_matrix((np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
                      shape=(n, n)).tocsc()
    return H, g, r


def _elimination_order(nf: int, pairs: np.ndarray) -> np.ndarray:
    """A fill-reducing elimination order of the free poses (minimum degree on ``AᵀA + A``).

    The order comes from SuperLU's multiple-minimum-degree ordering (``MMD_AT_PLUS_A``) applied to
    the pose-level pattern of ``H`` (one scalar per d×d block, made diagonally dominant so that
    SuperLU keeps the diagonal pivots); ``order[k]`` is the free pose eliminated k-th. The same
    order serves every iteration (the pattern of ``H`` does not change).
    """
    if nf <= 1 or pairs.shape[0] == 0:
        return np.arange(nf, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    deg = np.bincount(np.r_[a, b], minlength=nf).astype(np.float64)
    P = sp.coo_matrix((np.r_[np.full(a.size, -1.0), np.full(a.size, -1.0), deg + 1.0],
                       (np.r_[a, b, np.arange(nf)], np.r_[b, a, np.arange(nf)])), shape=(nf, nf)).tocsc()
    lu = spla.splu(P, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.argsort(lu.perm_c).astype(np.int64)


def _symbolic_cholesky(nb: int, lower: np.ndarray):
    """Column patterns of the block Cholesky factor: ``(Lp, Li)`` from the lower block pattern of ``H``.

    ``lower`` holds ``(row, col)`` block pairs with ``row > col``. The pattern of column j is its own
    rows in ``H`` united with the patterns of its children in the elimination tree (the columns whose
    first sub-diagonal row is j) [Davis2006 Thm. 4.2]; the diagonal block comes first.
    """
    by_col = [[] for _ in range(nb)]
    for r_, c_ in lower.tolist():
        by_col[c_].append(r_)
    children = [[] for _ in range(nb)]
    cols = []
    for j in range(nb):
        parts = [np.asarray(by_col[j], dtype=np.int64)] + [cols[c][cols[c] > j] for c in children[j]]
        rows = np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)
        rows = rows[rows > j]
        cols.append(rows)
        if rows.size:
            children[int(rows[0])].append(j)
    Lp = np.zeros(nb + 1, dtype=np.int64)
    Lp[1:] = np.cumsum([c.size + 1 for c in cols])
    Li = np.concatenate([np.r_[j, c] for j, c in enumerate(cols)]).astype(np.int64) if nb else np.zeros(0, np.int64)
    return Lp, Li


class _BlockSystem:
    """The pose-only normal equations as d×d blocks in the pattern of their Cholesky factor.

    Built once per optimisation (ordering and symbolic factorisation); each iteration accumulates
    ``H``, ``g`` (:func:`minegeo.slam._kernels.accumulate_normal_equations`), and each damping trial
    factorises ``H + λD`` (:func:`~minegeo.slam._kernels.block_cholesky`) and solves. Vertex
    ``v``'s step is ``δ[col[v] : col[v] + d]`` (``col = -1`` for a fixed pose)."""

    def __init__(self, kind: str, n: int, edges: np.ndarray, free: np.ndarray):
        d = self.d = _dof(kind)
        self.kind = kind
        nf = int(free.sum())
        fidx = np.full(n, -1, dtype=np.int64)
        fidx[free] = np.arange(nf)
        fe = fidx[edges]
        both = (fe >= 0).all(axis=1) & (fe[:, 0] != fe[:, 1])
        order = _elimination_order(nf, fe[both])
        rank = np.empty(nf, dtype=np.int64)
        rank[order] = np.arange(nf)
        blk = np.where(fidx >= 0, rank[np.maximum(fidx, 0)], -1)  # block index of each vertex, -1 fixed
        self.bcol = np.ascontiguousarray(blk[edges])
        bi, bj = self.bcol[:, 0], self.bcol[:, 1]
        lo_r, lo_c = np.maximum(bi, bj), np.minimum(bi, bj)
        self.Lp, self.Li = _symbolic_cholesky(nf, np.c_[lo_r, lo_c][both])
        key = np.repeat(np.arange(nf, dtype=np.int64), np.diff(self.Lp)) * max(nf, 1) + self.Li
        self.slot_ii = np.where(bi >= 0, self.Lp[np.maximum(bi, 0)], -1)
        self.slot_jj = np.where(bj >= 0, self.Lp[np.maximum(bj, 0)], -1)
        self.slot_ij = np.where(both, np.searchsorted(key, lo_c * max(nf, 1) + lo_r), -1)
        self.ij_lower = (bi > bj).astype(np.int64)
        self.col = np.ascontiguousarray(np.where(blk >= 0, blk * d, -1))
        self.block_vertex = np.empty(nf, dtype=np.int64)  # vertex index of each block column
        self.block_vertex[blk[blk >= 0]] = np.flatnonzero(blk >= 0)
        self.n_cols = nf * d
        self.Hx = self.g = None
        self.failed_block = -1

    def assemble(self, poses, edges, Z, info, w):
        """Linearise every edge at ``poses`` and accumulate ``H`` (blocks) and ``g``."""
        d, m = self.d, edges.shape[0]
        r, Ji, Jj = np.empty((m, d)), np.empty((m, d, d)), np.empty((m, d, d))
        (K.se3_edge_terms if self.kind == "SE3" else K.se2_edge_terms)(poses, edges, Z, r, Ji, Jj)
        self.Hx = np.zeros((self.Li.size, d, d))
        self.g = np.zeros(self.n_cols)
        WO = np.ascontiguousarray(info * w[:, None, None])
        K.accumulate_normal_equations(r, Ji, Jj, WO, self.bcol, self.slot_ii, self.slot_jj, self.slot_ij,
                                      self.ij_lower, self.Hx, self.g)

    def solve(self, lam: float, relative: bool, tiny: float = 0.0):
        """``δ`` with ``(H + λ D) δ = -g`` (elimination order), or None if not positive definite
        (a pivot ``≤ tiny ·`` its diagonal entry; :attr:`failed_block` is then the block column);
        ``D = diag(H)`` when ``relative``, else ``I``."""
        Lx = np.empty_like(self.Hx)
        self.failed_block = int(K.block_cholesky(self.Lp, self.Li, self.Hx, lam, relative, Lx, tiny))
        if self.failed_block >= 0:
            return None
        return K.block_cholesky_solve(self.Lp, self.Li, Lx, -self.g)

    def gauss_newton_decrease(self):
        """``(½ gᵀH⁻¹g, -1)`` of the undamped normal equations last assembled (the decrease of the
        cost the Gauss–Newton model predicts), or ``(nan, v)`` when ``H`` is singular
        (:data:`SINGULAR_PIVOT`) at the pose of vertex index ``v``."""
        delta = self.solve(0.0, False, SINGULAR_PIVOT)
        if delta is None:
            return float("nan"), int(self.block_vertex[self.failed_block])
        return -0.5 * float(self.g @ delta), -1

    def retract(self, poses, delta):
        """``T_v ← T_v · Exp(δ_v)`` for every free pose."""
        out = np.empty_like(poses)
        (K.se3_retract_all if self.kind == "SE3" else K.se2_retract_all)(poses, self.col, delta, out)
        return out


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


def accept_step(cost_trial: float, cost: float) -> bool:
    """Whether an LM trial step is accepted: its cost is finite, not negative and not above ``cost``.

    A cost ``½ Σ rᵀΩr`` with positive semi-definite ``Ω`` (and every robust kernel here) cannot be
    negative; a negative trial cost means the problem is not the one stated, and is never accepted.
    """
    return bool(np.isfinite(cost_trial) and 0.0 <= cost_trial <= cost)


def remaining_decrease(rel: float, rel_prev: float) -> float:
    """Aitken's estimate of the relative cost decrease still to come, ``ε ρ / (1 − ρ)``, ``ρ = ε / ε_prev``
    (``inf`` when the decreases do not shrink or there is no previous one)."""
    if not (rel_prev > 0.0 and np.isfinite(rel_prev)) or not rel >= 0.0:
        return float("inf")
    rho = rel / rel_prev
    return rel * rho / (1.0 - rho) if rho < 1.0 else float("inf")


def check_result(poses_in: np.ndarray, poses_out: np.ndarray, held, cost_final: float, cost_initial: float) -> str:
    """Why an optimised result may not be reported as converged ("" when it may).

    Checks: the cost is finite and not negative (rounding allowance ``1e-12 · F₀``); every held
    pose (rows ``held``) is bit-identical to its input; every pose is a proper rigid transform
    (rotation orthonormal, ``det R = +1`` and last row ``(0, …, 0, 1)`` to :data:`ROTATION_TOL`).
    """
    if not np.isfinite(cost_final) or cost_final < -1e-12 * max(abs(cost_initial), 1e-300):
        return f"the final cost {cost_final!r} is not a finite non-negative number"
    held = list(held)
    if held and not np.array_equal(poses_out[held], poses_in[held]):
        return "a held (fixed) pose moved: the gauge was not kept"
    d = poses_out.shape[-1] - 1
    R = poses_out[:, :d, :d]
    ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(d)).max(axis=(1, 2))
    det = np.linalg.det(R)
    last = np.abs(poses_out[:, d, :] - np.eye(d + 1)[d]).max(axis=1)
    bad = np.flatnonzero(~((ortho <= ROTATION_TOL) & (np.abs(det - 1.0) <= ROTATION_TOL) & (last <= ROTATION_TOL)))
    if bad.size:
        return f"{bad.size} optimised pose(s) are not rigid transforms (first: row {int(bad[0])})"
    return ""


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
        only when the stopping test held **and** the result passed :func:`check_result` and the
        undamped normal equations at the result are positive definite. ``"max_iterations"``: stopped
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
    fixed_idx, fixed_ids, free, free_col, free_ids, n_pose_cols = _gauge(graph)
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
        return result("failed", f"{unanchored.size} vertex(es) not constrained by any edge path (edges with non-zero "
                      f"information) to a fixed vertex (first: id {int(graph.ids[unanchored[0]])}); disconnected "
                      "graph?", float("nan"), float("nan"), 0, [], user=True)
    if plane_problem:
        return result("failed", plane_problem, float("nan"), float("nan"), 0, [], user=True)
    out = _levenberg_marquardt(used, params, planes, free, free_col, free_ids, n_pose_cols)
    status, reason, cost0, cost_f, it, history, poses, pl, conv = out
    if status == "failed":
        return result(status, reason, cost0, cost0, it, history, conv=conv, user=conv.get("singular_vertex") is not None)
    problem = check_result(graph.poses, poses, fixed_idx, cost_f, cost0)
    if problem:
        return result("failed", f"the result failed its check: {problem}", cost0, cost0, it, history, conv=conv)
    return result(status, reason, cost0, cost_f, it, history, planes.with_planes(pl) if planes is not None else None,
                  graph.with_poses(poses), conv)


def _levenberg_marquardt(graph: PoseGraph, params: PoseGraphParams, planes, free, free_col, free_ids, n_pose_cols):
    """The LM iterations of :func:`optimize_pose_graph` on ``graph`` (its information as optimised).

    Returns ``(status, reason, cost0, cost_final, iterations, history, poses, planes, convergence)``.
    """
    poses, edges, Z = _arrays(graph)
    info = _information_rt(graph)
    pl = planes.planes.copy() if planes is not None else None
    r = _residuals(graph.kind, poses, edges, Z)
    cost0 = _cost(r, info)
    cost = _robust_cost(r, info, params)
    rp = None
    if planes is not None:
        rp = _plane_residuals(poses, pl, planes)
        cost0 += _cost(rp, planes.information)
        cost += _robust_cost(rp, planes.information, params)
    lam, history, rel, rel_prev, rest = params.lambda_init, [], float("nan"), float("nan"), float("inf")
    model = float("inf")  # the Gauss-Newton model's relative decrease of the current iteration
    status, reason, it = "max_iterations", "", 0
    if not np.isfinite(cost0):
        return "failed", "the initial cost is not finite", cost0, cost0, 0, [], poses, pl, {}
    # block Cholesky unless planes are present (the general sparse LU path)
    no_planes = planes is None or (planes.n_planes == 0 and planes.n_edges == 0)
    blocks = _BlockSystem(graph.kind, graph.n_vertices, edges, free) if no_planes else None
    for it in range(1, params.max_iterations + 1):
        w = _robust_weights(r, info, params)
        if blocks is not None:
            blocks.assemble(poses, edges, Z, info, w)
        else:
            part = None if planes is None else (pl, planes, _robust_weights(rp, planes.information, params))
            H, g, _ = _normal_equations(graph.kind, poses, edges, Z, info, w, free_col, part)
            diag = H.diagonal()
        accepted, factorised = False, False
        while lam < 1e12:
            if blocks is not None:
                delta = blocks.solve(lam, params.damping == "diagonal")
                if delta is None:  # H + λD not positive definite: more damping
                    history.append({"iteration": it, "cost": cost, "lambda": lam, "accepted": False, "step": 0.0,
                                    "factorised": False})
                    lam *= 10.0
                    continue
                trial = blocks.retract(poses, delta)
                g = blocks.g
            else:
                D = np.maximum(diag, 1e-12) if params.damping == "diagonal" else np.ones(diag.size)
                try:
                    delta = spla.splu((H + sp.diags(lam * D)).tocsc()).solve(-g)
                except RuntimeError:  # exactly singular: a vertex no edge reaches
                    return ("failed", "singular normal equations: a vertex is not constrained by any edge "
                            "(disconnected graph?)", cost0, cost0, it, history, poses, pl, {"singular_vertex": -1})
                trial = _retract(graph.kind, poses, free_ids, free_col, delta)
            if not factorised:
                model = -0.5 * float(g @ delta) / max(cost, 1e-300)
            factorised = True
            r_trial = _residuals(graph.kind, trial, edges, Z)
            cost_trial = _robust_cost(r_trial, info, params)
            if planes is not None:
                pl_trial = _retract_planes(pl, delta, n_pose_cols)
                rp_trial = _plane_residuals(trial, pl_trial, planes)
                cost_trial += _robust_cost(rp_trial, planes.information, params)
            step = float(np.abs(delta).max()) if delta.size else 0.0
            if accept_step(cost_trial, cost):
                history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": True, "step": step})
                rel_prev, rel = rel, (cost - cost_trial) / max(cost, 1e-300)
                rest = remaining_decrease(rel, rel_prev)
                poses, r, cost, accepted = trial, r_trial, cost_trial, True
                if planes is not None:
                    pl, rp = pl_trial, rp_trial
                lam = max(lam / 10.0, 1e-12)
                break
            history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": False, "step": step})
            lam *= 10.0
        if not accepted and not factorised:
            return ("failed", "the damped normal equations are not positive definite at any damping",
                    cost0, cost0, it, history, graph.poses, pl, {})
        if not accepted:
            status, reason = "converged", "no step lowers the cost (damping exhausted): at a minimum"
            break
        if (rel < params.relative_cost_tolerance or max(rest, model) < params.remaining_cost_tolerance
                or step < params.step_tolerance):
            status, reason = "converged", (f"relative cost decrease {rel:.2e}, estimated decrease to come "
                                           f"{max(rest, model):.2e}, largest step {step:.2e}")
            break
    cost_final = _cost(r, info) + (_cost(rp, planes.information) if planes is not None else 0.0)
    conv = {"relative_decrease": rel, "geometric_remaining_relative_decrease": rest,
            "model_relative_decrease": model, "predicted_relative_decrease": None}
    if blocks is not None:  # the undamped normal equations at the result: singular? how far from stationary?
        blocks.assemble(poses, edges, Z, info, _robust_weights(r, info, params))
        pred, v = blocks.gauss_newton_decrease()
        if v >= 0:
            conv["singular_vertex"] = int(graph.ids[v])
            return ("failed", f"the normal equations are singular at vertex id {int(graph.ids[v])}: the information "
                    "of its edges leaves a direction of its pose unconstrained", cost0, cost0, it, history,
                    graph.poses, pl, conv)
        conv["predicted_relative_decrease"] = pred / max(cost, 1e-300)
    if status == "max_iterations":
        pred = conv["predicted_relative_decrease"]
        reason = (f"stopped after {params.max_iterations} iterations short of convergence: last relative decrease "
                  f"{rel:.2e}, estimated decrease to come {max(rest, model):.2e} of the cost"
                  + (f", Gauss-Newton predicted decrease {pred:.2e}" if pred is not None else ""))
    return status, reason, cost0, cost_final, it, history, poses, pl, conv
