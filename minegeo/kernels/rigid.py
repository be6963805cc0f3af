"""Closed-form rigid and similarity fits of paired 3-D points (Umeyama / Kabsch, 4-DOF yaw).

All solve ``min Σ w_i |q_i - (c R p_i + t)|²`` by the SVD of the cross-covariance
([Umeyama1991 Eqs. 40-42], [Baek2022 Eqs. 10-13]) with the reflection fix ``diag(1, 1, d)``.
Frames: ``P`` rows are source points, ``Q`` rows the corresponding target points (metres); the
result maps source into target coordinates, ``q ≈ c R p + t``.

Three variants of the same formula are kept because each caller's bits depend on its own
rounding (a merge would change published outputs):

* :func:`umeyama_from_moments` -- SVD of ``W = Σ w (p-p̄)(q-q̄)ᵀ / Σw``, ``R = V D Uᵀ`` (Eigen's
  ``umeyama``, Open3D's point-to-point estimation); fed by the chunked weighted moments of
  ICP / :func:`minegeo.registration.umeyama`, or by :func:`unit_moments` in
  :func:`umeyama_small_kernel`.
* :func:`umeyama_rigid` -- SVD of ``Wᵀ`` (Umeyama's own orientation), with a rank test; the
  RANSAC minimal-sample fit.
* :func:`umeyama_centred` -- NumPy/BLAS products (survey Helmert start values).

:func:`yaw_fit` is the 4-DOF (yaw + translation) fit of levelled frames. Contiguous arrays in,
no checks.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit

__all__ = ["unit_moments", "umeyama_from_moments", "umeyama_small_kernel", "umeyama_rigid", "umeyama_centred",
           "yaw_fit"]


@njit
def unit_moments(P, Q):
    """Means and centred second moments of paired rows with unit weights.

    Returns ``(mu_p, mu_q, W, var_p)``: ``W[r, k] = Σ_i (p_ir - mu_p_r)(q_ik - mu_q_k) / m``
    ([Baek2022 Eq. 10] centred) and ``var_p = Σ_i |p_i - mu_p|² / m``, sums in row order.
    ``m >= 1``.
    """
    m = P.shape[0]
    mu_p = np.zeros(3)
    mu_q = np.zeros(3)
    for i in range(m):
        for k in range(3):
            mu_p[k] += P[i, k]
            mu_q[k] += Q[i, k]
    for k in range(3):
        mu_p[k] /= m
        mu_q[k] /= m
    W = np.zeros((3, 3))
    var_p = 0.0
    for i in range(m):
        for r in range(3):
            a = P[i, r] - mu_p[r]
            var_p += a * a
            for k in range(3):
                W[r, k] += a * (Q[i, k] - mu_q[k])
    for r in range(3):
        for k in range(3):
            W[r, k] /= m
    var_p /= m
    return mu_p, mu_q, W, var_p


@njit
def umeyama_from_moments(mu_p, mu_q, W, var_p, with_scale):
    """Closed-form similarity from the moments ([Baek2022 Eqs. 11-13], [Umeyama1991 Eqs. 40-42]).

    ``W = U S V^T`` ([Baek2022 Eq. 11]), ``R = V diag(1, 1, d) U^T`` with ``d = sign det(V U^T)``
    ([Baek2022 Eq. 12] with the reflection fix), ``c = tr(S diag(1,1,d)) / var_p`` if scaling, and
    ``t = mu_q - c R mu_p`` ([Baek2022 Eq. 13]). Returns ``(T 4x4, c, singular values S)``.
    """
    U, S, Vt = np.linalg.svd(W)
    V = Vt.T
    d = 1.0
    if np.linalg.det(V) * np.linalg.det(U) < 0.0:
        d = -1.0
    D = np.eye(3)
    D[2, 2] = d
    R = V @ D @ U.T
    c = 1.0
    if with_scale:
        if var_p > 0.0:
            c = (S[0] + S[1] + d * S[2]) / var_p
        else:
            c = 1.0
    T = np.eye(4)
    for r in range(3):
        for k in range(3):
            T[r, k] = c * R[r, k]
        T[r, 3] = mu_q[r] - c * (R[r, 0] * mu_p[0] + R[r, 1] * mu_p[1] + R[r, 2] * mu_p[2])
    return T, c, S


@njit
def umeyama_small_kernel(P, Q, with_scale):
    """Serial, allocation-light Umeyama for tiny samples (RANSAC minimal sets), unit weights.

    :func:`unit_moments` + :func:`umeyama_from_moments` (the same numbers as the chunked
    weighted moments for up to one chunk of rows), callable from other njit code. Returns
    ``(T 4x4, scale)``; identity for 0 rows (Open3D semantics).
    """
    m = P.shape[0]
    if m == 0:
        return np.eye(4), 1.0
    mu_p, mu_q, W, var_p = unit_moments(P, Q)
    T, c, _ = umeyama_from_moments(mu_p, mu_q, W, var_p, with_scale)
    return T, c


@njit
def umeyama_rigid(P, Q, rel_tol):
    """Least-squares rigid motion ``Q ~ R P + t`` from paired rows ([Baek2022 Eqs. 10-13], [Umeyama1991 Eqs. 40-42]).

    ``Sigma = (1/n) sum (q_i - q_bar)(p_i - p_bar)^T = U D V^T`` (the transpose of
    :func:`unit_moments`' ``W``, exactly), ``R = U diag(1, 1, s) V^T`` with
    ``s = sign(det U det V)`` (reflection fix), ``t = q_bar - R p_bar``. Returns ``(R, t, ok)``;
    ``ok`` is False when the second singular value is below ``rel_tol`` times the first
    (collinear or coincident points: rotation undetermined). ``n >= 1`` rows.
    """
    pm, qm, W, _ = unit_moments(P, Q)
    S = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            S[a, b] = W[b, a]
    U, D, Vt = np.linalg.svd(S)
    ok = D[0] > 0.0 and D[1] > rel_tol * D[0]
    s = 1.0
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        s = -1.0
    R = np.zeros((3, 3))
    for a in range(3):
        for b in range(3):
            R[a, b] = U[a, 0] * Vt[0, b] + U[a, 1] * Vt[1, b] + s * U[a, 2] * Vt[2, b]
    t = np.zeros(3)
    for a in range(3):
        t[a] = qm[a] - (R[a, 0] * pm[0] + R[a, 1] * pm[1] + R[a, 2] * pm[2])
    return R, t, ok


def umeyama_centred(src_c: np.ndarray, dst_c: np.ndarray, with_scale: bool):
    """Closed-form similarity of centred point sets ([Umeyama1991 Eqs. 40-42]), NumPy/BLAS.

    ``S = dst_cᵀ src_c / n = U D Vᵀ``, ``R = U E Vᵀ`` with ``E = diag(1, 1, sign(det U det V))``,
    scale ``c = tr(D E) / σ_p²`` (``σ_p² = Σ|src_c|² / n``) or 1. Returns ``(R (3, 3), c)``.
    Plain NumPy (not njit): the survey adjustment's start value, whose numbers come from BLAS
    matrix products (a loop order would change the last bits of the adjusted parameters).
    """
    n = src_c.shape[0]
    S = dst_c.T @ src_c / n
    U, D, Vt = np.linalg.svd(S)
    E = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1.0
    R = U @ E @ Vt
    if with_scale:
        var = float(np.sum(src_c**2) / n)
        s = float(np.trace(np.diag(D) @ E) / var)
    else:
        s = 1.0
    return R, s


@njit
def yaw_fit(P, Q):
    """Least-squares yaw + translation ``q ≈ Rz(θ) p + t`` of paired rows (n >= 2).

    With horizontally centred coordinates ``p' = p − p̄``, ``q' = q − q̄``:
    ``θ = atan2(Σ (p'_x q'_y − p'_y q'_x), Σ (p'_x q'_x + p'_y q'_y))`` (the 2-D Procrustes /
    Kabsch solution), ``t = q̄ − Rz(θ) p̄`` (z: mean height difference). Returns
    ``(T (4, 4), horizontal spread Σ |p'_xy|²)``.
    """
    n = P.shape[0]
    pbx = pby = pbz = qbx = qby = qbz = 0.0
    for i in range(n):
        pbx += P[i, 0]
        pby += P[i, 1]
        pbz += P[i, 2]
        qbx += Q[i, 0]
        qby += Q[i, 1]
        qbz += Q[i, 2]
    pbx /= n
    pby /= n
    pbz /= n
    qbx /= n
    qby /= n
    qbz /= n
    s = c = spread = 0.0
    for i in range(n):
        px = P[i, 0] - pbx
        py = P[i, 1] - pby
        qx = Q[i, 0] - qbx
        qy = Q[i, 1] - qby
        s += px * qy - py * qx
        c += px * qx + py * qy
        spread += px * px + py * py
    th = math.atan2(s, c)
    ct = math.cos(th)
    st = math.sin(th)
    T = np.zeros((4, 4))
    T[0, 0] = ct
    T[0, 1] = -st
    T[1, 0] = st
    T[1, 1] = ct
    T[2, 2] = 1.0
    T[3, 3] = 1.0
    T[0, 3] = qbx - (ct * pbx - st * pby)
    T[1, 3] = qby - (st * pbx + ct * pby)
    T[2, 3] = qbz - pbz
    return T, spread
