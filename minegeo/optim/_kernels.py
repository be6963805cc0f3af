"""Numba kernels of the optimiser: the between factor on SE(3)/SE(2), block normal equations,
block Cholesky and the retraction of poses.

Contiguous float64 arrays in, no checks (:mod:`minegeo.optim.factors`, :mod:`minegeo.optim.blocks`
and the callers validate). Tangent vectors are ordered (rotation, translation) for SE(3),
``ξ = (ω, ρ)``, and (θ, x, y) for SE(2) (the g2o/GTSAM (x, y, θ) information is permuted to
match); perturbations are on the right, ``T ← T · Exp(δ)``.

For a between factor ``(i, j)`` with measurement ``Z`` the residual is ``r = Log(Z⁻¹ T_i⁻¹ T_j)``
(the between-factor of slam_contract.md, GTSAM's ``BetweenFactorPose3``), and with ``A = T_i⁻¹ T_j``

* ``∂r/∂δ_j = J_r⁻¹(r)``,
* ``∂r/∂δ_i = −J_r⁻¹(r) · Ad(A⁻¹)``,

because ``Z⁻¹ Exp(−δ) A = Z⁻¹ A · Exp(−Ad(A⁻¹) δ)`` (the adjoint, Solà et al. 2018 Sec. 2.6) and
``Log(E · Exp(δ)) ≈ Log(E) + J_r⁻¹(Log E) δ`` (the right Jacobian of Log, ibid. Sec. 4)
[Sola2018 Sec. 4].
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit
from minegeo.kernels.lie import (
    se2_adjoint,
    se2_exp,
    se2_log,
    se2_right_jacobian_inv,
    se3_adjoint,
    se3_exp,
    se3_log,
    se3_right_jacobian_inv,
)


@njit
def _rel(Ti, Tj, Z, d):
    """``E = Z⁻¹ T_i⁻¹ T_j`` and ``A⁻¹ = T_j⁻¹ T_i`` for homogeneous d×d rigid matrices.

    With ``A = T_i⁻¹ T_j``: ``R_A = R_iᵀ R_j``, ``t_A = R_iᵀ (t_j − t_i)``; ``R_E = R_zᵀ R_A``,
    ``t_E = R_zᵀ (t_A − t_z)``; ``A⁻¹ = [R_Aᵀ, −R_Aᵀ t_A]`` (scalar loops: no temporaries).
    """
    k = d - 1
    A = np.zeros((d, d))
    E = np.zeros((d, d))
    Ainv = np.zeros((d, d))
    for a in range(k):
        for c in range(k):
            s = 0.0
            for t in range(k):
                s += Ti[t, a] * Tj[t, c]
            A[a, c] = s
        s = 0.0
        for t in range(k):
            s += Ti[t, a] * (Tj[t, k] - Ti[t, k])
        A[a, k] = s
    for a in range(k):
        for c in range(k):
            s = 0.0
            for t in range(k):
                s += Z[t, a] * A[t, c]
            E[a, c] = s
            Ainv[a, c] = A[c, a]
        s = 0.0
        u = 0.0
        for t in range(k):
            s += Z[t, a] * (A[t, k] - Z[t, k])
            u += A[t, a] * A[t, k]
        E[a, k] = s
        Ainv[a, k] = -u
    E[k, k] = 1.0
    Ainv[k, k] = 1.0
    return E, Ainv


@njit
def _neg_product(A, B, out):
    """``out = −A B`` for small square matrices (a loop: no BLAS call per edge)."""
    n = A.shape[0]
    for a in range(n):
        for c in range(n):
            s = 0.0
            for t in range(n):
                s += A[a, t] * B[t, c]
            out[a, c] = -s


@njit
def se3_edge_terms(poses, edges, Z, r, Ji, Jj):
    """Fill ``r`` (m, 6), ``Ji``, ``Jj`` (m, 6, 6) for SE(3) between-edges (ω, ρ order)."""
    for e in range(edges.shape[0]):
        E, Ainv = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 4)
        xi = se3_log(E)
        Jinv = se3_right_jacobian_inv(xi)
        r[e] = xi
        Jj[e] = Jinv
        _neg_product(Jinv, se3_adjoint(Ainv), Ji[e])


@njit
def se2_edge_terms(poses, edges, Z, r, Ji, Jj):
    """Fill ``r`` (m, 3), ``Ji``, ``Jj`` (m, 3, 3) for SE(2) between-edges (θ, x, y order)."""
    for e in range(edges.shape[0]):
        E, Ainv = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 3)
        xi = se2_log(E)
        Jinv = se2_right_jacobian_inv(xi)
        r[e] = xi
        Jj[e] = Jinv
        _neg_product(Jinv, se2_adjoint(Ainv), Ji[e])


@njit
def se3_residuals(poses, edges, Z, r):
    """Residuals only (cost evaluation of a trial step)."""
    for e in range(edges.shape[0]):
        E, _ = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 4)
        r[e] = se3_log(E)


@njit
def se2_residuals(poses, edges, Z, r):
    for e in range(edges.shape[0]):
        E, _ = _rel(poses[edges[e, 0]], poses[edges[e, 1]], Z[e], 3)
        r[e] = se2_log(E)


# ------------------------------------------------------------------ sparse normal equations, block form
#
# The normal equations are kept as d×d blocks (d = 6 for SE(3), 3 for SE(2)) in the pattern of their
# Cholesky factor L (block columns in elimination order, each column's block rows sorted, the diagonal
# block first): ``Lp`` (nb + 1) column pointers, ``Li`` block rows, ``Lx`` (nnz, d, d) values. The
# lower blocks of H are accumulated straight into that pattern (fill-in blocks start at zero) and
# factorised in place by a left-looking block Cholesky (Davis 2006, "Direct Methods for Sparse Linear
# Systems", Sec. 4.8, by blocks), so one pattern serves every iteration and every damping trial.


@njit(inline="always")
def _jt_wo(J, WO, e, A):
    """``A = J[e]ᵀ WO[e]`` (d, k) for factor ``e`` (``J`` (m, k, d), ``WO`` (m, k, k)), each entry summed
    over the residual index in order."""
    kr = WO.shape[1]
    for a in range(J.shape[2]):
        for c in range(kr):
            s = 0.0
            for k in range(kr):
                s += J[e, k, a] * WO[e, k, c]
            A[a, c] = s


@njit(inline="always")
def _add_diagonal(A, J, r, e, b, slot, Hx, g):
    """Add factor ``e``'s diagonal block ``A J[e]`` (``A = J[e]ᵀWΩ``) to ``Hx[slot]`` and ``A r[e]`` to the
    gradient rows of block ``b``."""
    d = J.shape[2]
    kr = r.shape[1]
    for a in range(d):
        ga = 0.0
        for k in range(kr):
            ga += A[a, k] * r[e, k]
        g[b * d + a] += ga
        for c in range(d):
            h = 0.0
            for k in range(kr):
                h += A[a, k] * J[e, k, c]
            Hx[slot, a, c] += h


@njit
def accumulate_normal_equations(r, Ji, Jj, WO, bcol, slot_ii, slot_jj, slot_ij, ij_lower, Hx, g):
    """Add every binary factor's ``JᵀWΩJ`` blocks to ``Hx`` and ``JᵀWΩr`` to ``g`` (serial: bit-reproducible).

    ``r`` (m, k), ``Ji``, ``Jj`` (m, k, d), ``WO`` (m, k, k): the residual dimension ``k`` may differ
    from the block dimension ``d``. Per factor (i, j): ``H_ii += J_iᵀWΩJ_i``, ``H_jj += J_jᵀWΩJ_j``,
    the lower off-diagonal block ``H_ij = J_iᵀWΩJ_j`` (stored transposed when ``ij_lower`` is 0,
    i.e. when j's block row is below i's), ``g_i += J_iᵀWΩr``, ``g_j += J_jᵀWΩr``. ``bcol[e, 0/1]``
    is the block index of i / j in the elimination order, -1 for a held variable (its blocks are
    skipped); ``slot_*`` index ``Hx``.
    """
    m, kr = r.shape
    d = Ji.shape[2]
    A = np.empty((d, kr))
    B = np.empty((d, kr))
    for e in range(m):
        bi, bj = bcol[e, 0], bcol[e, 1]
        _jt_wo(Ji, WO, e, A)  # A = J_iᵀ WΩ
        _jt_wo(Jj, WO, e, B)  # B = J_jᵀ WΩ
        if bi >= 0:
            _add_diagonal(A, Ji, r, e, bi, slot_ii[e], Hx, g)
        if bj >= 0:
            _add_diagonal(B, Jj, r, e, bj, slot_jj[e], Hx, g)
        if slot_ij[e] >= 0:  # both variables free and distinct
            s = slot_ij[e]
            for a in range(d):
                for c in range(d):
                    h = 0.0
                    for k in range(kr):
                        h += A[a, k] * Jj[e, k, c]
                    if ij_lower[e]:
                        Hx[s, a, c] += h
                    else:
                        Hx[s, c, a] += h


@njit
def accumulate_unary(r, J, WO, bcol, Lp, Hx, g):
    """Add unary factors to the block normal equations (serial: bit-reproducible).

    Per factor ``e`` on a free variable of block ``b = bcol[e] ≥ 0`` (−1: a held variable, skipped):
    ``H_bb += Jᵀ WΩ J`` (stored at ``Hx[Lp[b]]``, the diagonal block of the Cholesky pattern) and
    ``g_b += Jᵀ WΩ r``. ``J`` is (m, k, d), ``r`` (m, k), ``WO`` (m, k, k): the robust weight times
    the information matrix. A unary factor adds no fill-in.
    """
    m, k = r.shape
    d = J.shape[2]
    A = np.empty((d, k))
    for e in range(m):
        b = bcol[e]
        if b < 0:
            continue
        _jt_wo(J, WO, e, A)
        _add_diagonal(A, J, r, e, b, Lp[b], Hx, g)


@njit
def block_cholesky(Lp, Li, Hx, lam, relative, Lx, tiny=0.0):
    """Left-looking block Cholesky ``L Lᵀ = H + λ·D`` in the pattern of ``L``.

    ``D = diag(max(diag H, 1e-12))`` when ``relative`` (Marquardt's scaling), else ``D = I``
    (GTSAM's default ``diagonalDamping = false``).

    ``Hx`` holds the lower blocks of ``H`` in that pattern (not modified); ``Lx`` receives ``L``.
    Returns -1, or the block column whose pivot block is not positive definite (a scalar pivot
    ``s ≤ tiny · max_a H_aa``, the largest undamped diagonal entry of that block: the damped matrix
    is indefinite or (numerically) singular; the caller raises the damping, or names that column's
    pose).
    """
    nb = Lp.shape[0] - 1
    d = Hx.shape[1]
    W = np.zeros((nb, d, d))
    head = np.full(nb, -1, dtype=np.int64)  # head[j]: first column k < j whose next row is j
    link = np.full(nb, -1, dtype=np.int64)
    ptr = np.empty(nb, dtype=np.int64)  # ptr[k]: position in column k of its next row to be used
    C = np.empty((d, d))
    Ljk = np.empty((d, d))
    for j in range(nb):
        p0, p1 = Lp[j], Lp[j + 1]
        for p in range(p0, p1):
            W[Li[p]] = Hx[p]
        for a in range(d):
            W[j, a, a] += lam * max(Hx[p0, a, a], 1e-12) if relative else lam
        k = head[j]
        while k != -1:
            nxt = link[k]
            p = ptr[k]  # Li[p] == j
            for c in range(d):
                for t in range(d):
                    Ljk[t, c] = Lx[p, c, t]
            if d == 6:  # the same loop with a compile-time size (unrolled and vectorised by LLVM)
                for q in range(p, Lp[k + 1]):  # W_i -= L_ik L_jkᵀ
                    i = Li[q]
                    for a in range(6):
                        for t in range(6):
                            x = Lx[q, a, t]
                            for c in range(6):
                                W[i, a, c] -= x * Ljk[t, c]
            else:
                for q in range(p, Lp[k + 1]):
                    i = Li[q]
                    for a in range(d):
                        for t in range(d):
                            x = Lx[q, a, t]
                            for c in range(d):
                                W[i, a, c] -= x * Ljk[t, c]
            ptr[k] = p + 1
            if p + 1 < Lp[k + 1]:
                rnext = Li[p + 1]
                link[k] = head[rnext]
                head[rnext] = k
            k = nxt
        # dense Cholesky of the pivot block: C Cᵀ = W[j]
        floor = 0.0
        for a in range(d):
            floor = max(floor, tiny * Hx[p0, a, a])
        for a in range(d):
            for c in range(a + 1):
                s = W[j, a, c]
                for t in range(c):
                    s -= C[a, t] * C[c, t]
                if a == c:
                    if not (s > 0.0 and s > floor):
                        return j
                    C[a, a] = np.sqrt(s)
                else:
                    C[a, c] = s / C[c, c]
            for c in range(a + 1, d):
                C[a, c] = 0.0
        Lx[p0] = C
        # sub-diagonal blocks: L_ij = W_i C⁻ᵀ (row by row, forward substitution)
        for q in range(p0 + 1, p1):
            i = Li[q]
            for a in range(d):
                for c in range(d):
                    s = W[i, a, c]
                    for t in range(c):
                        s -= Lx[q, a, t] * C[c, t]
                    Lx[q, a, c] = s / C[c, c]
        ptr[j] = p0 + 1
        if p0 + 1 < p1:
            rnext = Li[p0 + 1]
            link[j] = head[rnext]
            head[rnext] = j
    return -1


@njit
def block_cholesky_solve(Lp, Li, Lx, b):
    """``x`` with ``L Lᵀ x = b`` (forward, then backward substitution by blocks)."""
    nb = Lp.shape[0] - 1
    d = Lx.shape[1]
    x = b.copy()
    for j in range(nb):  # L y = b
        p0 = Lp[j]
        for a in range(d):
            s = x[j * d + a]
            for t in range(a):
                s -= Lx[p0, a, t] * x[j * d + t]
            x[j * d + a] = s / Lx[p0, a, a]
        for q in range(p0 + 1, Lp[j + 1]):
            i = Li[q]
            for a in range(d):
                s = 0.0
                for t in range(d):
                    s += Lx[q, a, t] * x[j * d + t]
                x[i * d + a] -= s
    for j in range(nb - 1, -1, -1):  # Lᵀ x = y
        p0 = Lp[j]
        for q in range(p0 + 1, Lp[j + 1]):
            i = Li[q]
            for t in range(d):
                s = 0.0
                for a in range(d):
                    s += Lx[q, a, t] * x[i * d + a]
                x[j * d + t] -= s
        for a in range(d - 1, -1, -1):
            s = x[j * d + a]
            for t in range(a + 1, d):
                s -= Lx[p0, t, a] * x[j * d + t]
            x[j * d + a] = s / Lx[p0, a, a]
    return x


@njit
def se3_retract_all(poses, col, delta, out):
    """``out[v] = poses[v] · Exp(δ[col[v]:col[v]+6])`` for every pose with ``col[v] >= 0``, else a copy
    (the pose occupies the first 6 columns of its block)."""
    for v in range(poses.shape[0]):
        c = col[v]
        if c < 0:
            out[v] = poses[v]
        else:
            out[v] = poses[v] @ se3_exp(np.ascontiguousarray(delta[c:c + 6]))


@njit
def se2_retract_all(poses, col, delta, out):
    """``out[v] = poses[v] · Exp(δ[col[v]:col[v]+3])`` for every vertex with ``col[v] >= 0``, else a copy."""
    for v in range(poses.shape[0]):
        c = col[v]
        if c < 0:
            out[v] = poses[v]
        else:
            out[v] = poses[v] @ se2_exp(np.ascontiguousarray(delta[c:c + 3]))
