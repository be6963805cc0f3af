"""Numba kernels of the pose-graph solver: per-edge residuals and analytic Jacobians.

Contiguous float64 arrays in, no checks (the public functions in :mod:`minegeo.slam.posegraph`
validate). Tangent vectors are ordered (rotation, translation) for SE(3), ``ξ = (ω, ρ)``, and
(θ, x, y) for SE(2) (the g2o/GTSAM (x, y, θ) information is permuted to match);
perturbations are on the right,
``T ← T · Exp(δ)``.

For an edge ``(i, j)`` with measurement ``Z`` the residual is ``r = Log(Z⁻¹ T_i⁻¹ T_j)``
(the between-factor of slam_contract.md, GTSAM's ``BetweenFactorPose3``), and with ``A = T_i⁻¹ T_j``

* ``∂r/∂δ_j = J_r⁻¹(r)``,
* ``∂r/∂δ_i = −J_r⁻¹(r) · Ad(A⁻¹)``,

because ``Z⁻¹ Exp(−δ) A = Z⁻¹ A · Exp(−Ad(A⁻¹) δ)`` (the adjoint, Solà et al. 2018 Sec. 2.6) and
``Log(E · Exp(δ)) ≈ Log(E) + J_r⁻¹(Log E) δ`` (the right Jacobian of Log, ibid. Sec. 4).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels.lie import (
    se2_adjoint,
    se2_log,
    se2_right_jacobian_inv,
    se3_adjoint,
    se3_log,
    se3_right_jacobian_inv,
)


@njit
def _rel(Ti, Tj, Z, d):
    """``E = Z⁻¹ T_i⁻¹ T_j`` and ``A⁻¹ = T_j⁻¹ T_i`` for homogeneous d×d rigid matrices."""
    k = d - 1
    Ri, ti = np.ascontiguousarray(Ti[:k, :k]), np.ascontiguousarray(Ti[:k, k])
    Rj, tj = np.ascontiguousarray(Tj[:k, :k]), np.ascontiguousarray(Tj[:k, k])
    A = np.eye(d)
    RiT = np.ascontiguousarray(Ri.T)
    A[:k, :k] = RiT @ Rj
    A[:k, k] = RiT @ (tj - ti)
    Rz, tz = np.ascontiguousarray(Z[:k, :k]), np.ascontiguousarray(Z[:k, k])
    E = np.eye(d)
    RzT = np.ascontiguousarray(Rz.T)
    E[:k, :k] = RzT @ np.ascontiguousarray(A[:k, :k])
    E[:k, k] = RzT @ (np.ascontiguousarray(A[:k, k]) - tz)
    Ainv = np.eye(d)
    RaT = np.ascontiguousarray(A[:k, :k].T)
    Ainv[:k, :k] = RaT
    Ainv[:k, k] = -(RaT @ np.ascontiguousarray(A[:k, k]))
    return E, Ainv


@njit_parallel
def se3_edge_terms(poses, edges, Z, r, Ji, Jj):
    """Fill ``r`` (m, 6), ``Ji``, ``Jj`` (m, 6, 6) for SE(3) between-edges (ω, ρ order)."""
    for e in prange(edges.shape[0]):
        E, Ainv = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 4)
        xi = se3_log(E)
        Jinv = se3_right_jacobian_inv(xi)
        r[e] = xi
        Jj[e] = Jinv
        Ji[e] = -(Jinv @ se3_adjoint(Ainv))


@njit_parallel
def se2_edge_terms(poses, edges, Z, r, Ji, Jj):
    """Fill ``r`` (m, 3), ``Ji``, ``Jj`` (m, 3, 3) for SE(2) between-edges (θ, x, y order)."""
    for e in prange(edges.shape[0]):
        E, Ainv = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 3)
        xi = se2_log(E)
        Jinv = se2_right_jacobian_inv(xi)
        r[e] = xi
        Jj[e] = Jinv
        Ji[e] = -(Jinv @ se2_adjoint(Ainv))


@njit_parallel
def se3_residuals(poses, edges, Z, r):
    """Residuals only (cost evaluation of a trial step)."""
    for e in prange(edges.shape[0]):
        E, _ = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 4)
        r[e] = se3_log(E)


@njit_parallel
def se2_residuals(poses, edges, Z, r):
    for e in prange(edges.shape[0]):
        E, _ = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 3)
        r[e] = se2_log(E)
