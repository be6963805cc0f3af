"""Factors of the control-station graph (:mod:`minegeo.slam.control`): the station position factor (C2), the
drift-carrying between factors and the drift random walk (C4), and the marginal covariances from the
selected inverse of the optimiser's block Cholesky factor (C3). The C-numbers are the sections of
:mod:`minegeo.slam.control`'s module docstring."""

from __future__ import annotations

import numpy as np

from minegeo.kernels.lie import se3_exp
from minegeo.optim import (
    SINGULAR_PIVOT,
    FactorGroup,
    FactorProblem,
    Values,
)


def _hat(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def station_points(poses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``R a + t`` (k, 3) of poses (k, 4, 4) and the offset ``a`` (3,) (C1)."""
    return poses[:, :3, :3] @ np.asarray(offset, dtype=np.float64) + poses[:, :3, 3]


def station_jacobian(poses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``∂p/∂ξ = [−R·hat(a), R]`` (k, 3, 6) of the station point ``p = R a + t`` under the pose's right
    perturbation ``T Exp(ξ)``, ``ξ = (ω, ρ)`` (C2)."""
    R = np.asarray(poses, dtype=np.float64)[:, :3, :3]
    J = np.empty((R.shape[0], 3, 6))
    J[:, :, :3] = -R @ _hat(np.asarray(offset, dtype=np.float64).reshape(3))
    J[:, :, 3:] = R
    return J


class PositionFactors(FactorGroup):
    """Unary position factors (C2): ``r = R a + t − p̄`` on poses ``index`` (m,).

    Parameters
    ----------
    index : (m,) int
        Pose variable of each factor.
    target : (m, 3)
        ``p̄`` (m, the frame of the poses).
    offset : (3,)
        ``a`` in the sensor frame (m).
    information : (m, 3, 3)
        ``Ω`` (m⁻²).
    """

    def __init__(self, index, target, offset, information):
        self.variables = np.ascontiguousarray(index, dtype=np.int64).reshape(-1, 1)
        self.target = np.ascontiguousarray(target, dtype=np.float64).reshape(-1, 3)
        self.offset = np.asarray(offset, dtype=np.float64).reshape(3)
        self.information = np.ascontiguousarray(information, dtype=np.float64).reshape(-1, 3, 3)

    def residuals(self, values: Values) -> np.ndarray:
        return station_points(values.poses[self.variables[:, 0]], self.offset) - self.target

    def linearize(self, values: Values) -> tuple:
        return self.residuals(values), (station_jacobian(values.poses[self.variables[:, 0]], self.offset),)


class DriftBetweenFactors(FactorGroup):
    """Between factors whose odometry carries a slowly varying systematic drift (C4).

    Every variable has the vector part ``β_i = (s, p, y)``: scale error of the odometry's translation
    (dimensionless), pitch and yaw rates (rad per metre travelled, about the sensor's y and z axes).
    The measurement of edge ``(i, j)`` with translation ``t_Z`` (``d = |t_Z|``) is taken as
    ``Z = Z_true Exp(ε)``, ``ε = (0, p d, y d, s t_Z)``, so the factor is::

        r = Log(Exp(ε(β_i)) Z⁻¹ T_i⁻¹ T_j)                                                (C4)
        ∂r/∂β_i ≈ J_l⁻¹(r) Ad(Exp ε) J_r(ε) ∂ε/∂β_i

    (pose Jacobians those of :class:`~minegeo.optim.BetweenFactors` with ``Z Exp(−ε)``).

    ``unit`` (3,): the variables' vector part holds ``β / unit`` (default 1: ``β`` itself), so that
    the states' information is of the order of the poses' in one 9 × 9 block (see
    :data:`DRIFT_UNIT`); ``∂r/∂(β/unit) = ∂r/∂β · diag(unit)``.
    """

    def __init__(self, edges, Z, information, unit=(1.0, 1.0, 1.0)):
        self.variables = np.ascontiguousarray(edges, dtype=np.int64).reshape(-1, 2)
        self.Z = np.ascontiguousarray(Z, dtype=np.float64)
        self.information = np.ascontiguousarray(information, dtype=np.float64)
        self.tz = self.Z[:, :3, 3].copy()
        self.d = np.linalg.norm(self.tz, axis=1)
        self.unit = np.asarray(unit, dtype=np.float64).reshape(3)

    def _eps(self, values: Values) -> np.ndarray:
        b = values.vectors[self.variables[:, 0]] * self.unit
        eps = np.zeros((self.variables.shape[0], 6))
        eps[:, 1] = b[:, 1] * self.d
        eps[:, 2] = b[:, 2] * self.d
        eps[:, 3:] = b[:, :1] * self.tz
        return eps

    def _corrected(self, values: Values):
        eps = self._eps(values)
        Zc = np.ascontiguousarray(np.stack([Z @ se3_exp(-e) for Z, e in zip(self.Z, eps, strict=True)]))
        return eps, Zc

    def residuals(self, values: Values) -> np.ndarray:
        from minegeo.optim import between_residuals

        return between_residuals("SE3", values.poses, self.variables, self._corrected(values)[1])

    def linearize(self, values: Values) -> tuple:
        from minegeo.kernels.lie import se3_adjoint, se3_left_jacobian_inv, se3_right_jacobian
        from minegeo.optim import between_terms

        eps, Zc = self._corrected(values)
        r, Ji, Jj = between_terms("SE3", values.poses, self.variables, Zc)
        m = r.shape[0]
        Jb = np.zeros((m, 6, 3))
        for e in range(m):
            A = se3_left_jacobian_inv(r[e]) @ se3_adjoint(se3_exp(eps[e])) @ se3_right_jacobian(eps[e])
            Jb[e, :, 0] = A[:, 3:] @ self.tz[e] * self.unit[0]
            Jb[e, :, 1] = A[:, 1] * self.d[e] * self.unit[1]
            Jb[e, :, 2] = A[:, 2] * self.d[e] * self.unit[2]
        Ji9 = np.concatenate([Ji, Jb], axis=2)
        return r, (Ji9, Jj)


class DriftWalkFactors(FactorGroup):
    """``r = β_j − β_i`` on consecutive variables (a random walk of the drift states, C4), or a prior
    ``r = β_i`` (arity 1)."""

    def __init__(self, variables, information):
        self.variables = np.ascontiguousarray(variables, dtype=np.int64)
        self.information = np.ascontiguousarray(information, dtype=np.float64)

    def residuals(self, values: Values) -> np.ndarray:
        b = values.vectors
        if self.arity == 1:
            return b[self.variables[:, 0]].copy()
        return b[self.variables[:, 1]] - b[self.variables[:, 0]]

    def linearize(self, values: Values) -> tuple:
        m = self.variables.shape[0]
        J = np.zeros((m, 3, 9))
        J[:, :, 6:] = np.eye(3)
        if self.arity == 1:
            return self.residuals(values), (J,)
        return self.residuals(values), (-J, J)


def selected_inverse(Lp: np.ndarray, Li: np.ndarray, Lx: np.ndarray) -> np.ndarray:
    """Blocks of ``H⁻¹`` in the pattern of its block Cholesky factor ``H = L Lᵀ`` (C3).

    ``Lx[p]`` is the block ``L[Li[p], j]`` for ``Lp[j] ≤ p < Lp[j+1]``, the diagonal block first
    (lower triangular). Returns ``S`` with ``S[p] = (H⁻¹)[Li[p], j]`` in the same slots: the
    diagonal blocks are the marginal covariances. Cost: one pass over the columns from the last,
    each touching only blocks of the factor's pattern (closed under the recursion: the rows of a
    column form a clique of the filled graph).
    """
    nb = Lp.size - 1
    d = Lx.shape[1]
    slot = {}
    for j in range(nb):
        for p in range(Lp[j], Lp[j + 1]):
            slot[(int(Li[p]), j)] = p
    S = np.zeros_like(Lx)

    def get(i, k):
        return S[slot[(i, k)]] if i >= k else S[slot[(k, i)]].T

    eye = np.eye(d)
    for j in range(nb - 1, -1, -1):
        p0, p1 = Lp[j], Lp[j + 1]
        Ljj_inv = np.linalg.solve(Lx[p0], eye)
        rows = [int(r) for r in Li[p0 + 1:p1]]
        LS = [Lx[p] @ Ljj_inv for p in range(p0 + 1, p1)]  # L_sj L_jj⁻¹
        for q, i in enumerate(rows):
            acc = np.zeros((d, d))
            for s, Ls in zip(rows, LS, strict=True):
                acc -= get(i, s) @ Ls
            S[p0 + 1 + q] = acc
        acc = Ljj_inv.T @ Ljj_inv
        for q, Ls in enumerate(LS):
            acc -= S[p0 + 1 + q].T @ Ls
        S[p0] = 0.5 * (acc + acc.T)
    return S


def marginal_covariances(problem: FactorProblem, values: Values, pairs=None):
    """Marginal covariances (n, d, d) of every free variable at ``values`` (held ones: zero),
    ``H⁻¹`` diagonal blocks by :func:`selected_inverse` on the optimiser's block Cholesky factor
    (undamped, the fill-reducing order of :class:`minegeo.optim.BlockSystem`; tangent order
    rotation first).

    With ``pairs`` (m, 2) (pairs of free variables joined by a binary factor, so in the factor's
    pattern) also their cross covariances ``Σ_ij`` (m, d, d): returns ``(marginals, cross)``."""
    system = problem.linearize(values, problem.evaluate(values))
    Lx = system.cholesky(0.0, False, SINGULAR_PIVOT)
    if Lx is None:
        raise ArithmeticError("the information matrix is singular at variable "
                              f"{int(system.block_vertex[system.failed_block])}")
    S = selected_inverse(system.Lp, system.Li, Lx)
    n = system.blk.size
    out = np.zeros((n, system.d, system.d))
    free = system.blk >= 0
    out[free] = S[system.Lp[system.blk[free]]]
    if pairs is None:
        return out
    _, _, _, slot_ij, ij_lower = system.binary_slots(pairs)
    # the slot holds H⁻¹[max block, min block]: Σ_ij when i's block is the larger, else its transpose
    cross = np.where(ij_lower[:, None, None] == 1, S[slot_ij], np.swapaxes(S[slot_ij], 1, 2))
    return out, cross
