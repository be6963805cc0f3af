"""Numba kernels of the roadway-plane constraints (Ren et al. 2019, Sec. 3.4.2).

Contiguous float64 arrays in, no checks (the public functions in :mod:`minegeo.slam.planes`
validate). Conventions:

* A plane is the 4-vector ``π = (n_a, n_b, n_c, d)`` with ``n·p + d = 0`` and ``|n| = 1``
  (n unitless, d in m); ``-d`` is the signed distance of the frame origin from the plane.
* Poses are ``T_world_sensor`` (4x4, ``p_world = R p_sensor + t``), perturbed on the right,
  ``T ← T · Exp(δ)`` with ``δ = (ω, ρ)`` rotation first (rad, m), as in
  :mod:`minegeo.slam._kernels`.
* A plane landmark (world frame) is updated on its manifold S² × R by
  ``n ← normalize(n + B(n) δ_n)``, ``d ← d + δ_d``, ``δ = (δ_n1, δ_n2, δ_d)`` (rad, rad, m),
  where ``B(n)`` (3x2) is the orthonormal tangent basis of :func:`plane_tangent_basis`
  (recomputed from the current ``n`` at every linearisation, and the same in the retraction).

The pose–plane residual ([Ren2019 Eq. 11]) is the paper's ``q(π) = [atan(n_a/n_b),
atan(n_c/|n|), d]`` evaluated in a chart attached to the measured plane (see
:func:`pose_plane_edge_terms`): the paper's q() is singular for a vertical normal, which is
exactly where a floor normal lies in a levelled sensor frame.

The per-edge kernels (:func:`pose_plane_edge_terms`, :func:`pose_plane_residuals`) are serial
(``prange`` runs as ``range``): a SLAM run has hundreds of pose–plane edges, and their ``parallel``
variants cost 2.3 s more one-time compilation (CPU, docs/first_use.md) to save about 12 ms per call at
5,000 edges on two threads. Each edge writes only its own rows, so serial and parallel give the same
bits. :func:`ransac_plane_counts` (hypotheses × points) stays ``parallel``.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange

#: Smallest horizontal norm of the chart coordinates before the azimuth is clamped (the
#: predicted normal is then 90 degrees off the measured one: a gross outlier).
_H_MIN = 1e-12


@njit
def plane_tangent_basis(n):
    """Orthonormal tangent basis ``B`` (3, 2) of the unit vector ``n``: ``Bᵀn = 0``, ``BᵀB = I``.

    Frisvad's construction as revised by Duff et al. 2017 (JCGT 6(1), "Building an orthonormal
    basis, revisited"), branch on the sign of ``n_c``: smooth on each hemisphere, exact for
    ``n = (0, 0, ±1)`` (a floor normal gives ``B ≈ [e_x, e_y]``).
    """
    s = 1.0 if n[2] >= 0.0 else -1.0
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    B = np.empty((3, 2))
    B[0, 0] = 1.0 + s * n[0] * n[0] * a
    B[1, 0] = s * b
    B[2, 0] = -s * n[0]
    B[0, 1] = b
    B[1, 1] = s + n[1] * n[1] * a
    B[2, 1] = -n[1]
    return B


@njit
def plane_retract(plane, delta):
    """``π ⊕ δ``: ``(normalize(n + B(n) δ[:2]), d + δ[2])`` for ``δ`` = (rad, rad, m)."""
    n = np.ascontiguousarray(plane[:3])
    B = plane_tangent_basis(n)
    m = n + B @ np.ascontiguousarray(delta[:2])
    m = m / np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
    out = np.empty(4)
    out[:3] = m
    out[3] = plane[3] + delta[2]
    return out


@njit
def plane_world_to_sensor(T, plane):
    """The world plane ``π`` in the sensor frame of ``T = T_world_sensor`` [Ren2019 Eqs. 9-10].

    ``n·(R p_s + t) + d = 0`` gives ``n_s = Rᵀ n`` [Ren2019 Eq. 9] and ``d_s = d + n·t``
    [Ren2019 Eq. 10]. The paper's ``[R_t, t_t]`` is the world-to-sensor transform
    ``T⁻¹ = [Rᵀ, −Rᵀt]``: ``n' = R_t n = Rᵀn`` and ``d' = d − t_t·n' = d + tᵀR Rᵀn = d + n·t``.
    """
    out = np.empty(4)
    for i in range(3):
        out[i] = T[0, i] * plane[0] + T[1, i] * plane[1] + T[2, i] * plane[2]  # (Rᵀ n)_i
    out[3] = plane[3] + plane[0] * T[0, 3] + plane[1] * T[1, 3] + plane[2] * T[2, 3]
    return out


@njit
def measurement_chart(n_meas):
    """Rows ``(n_meas, b1, b2)`` (3, 3): the frame in which the measured normal is ``(1, 0, 0)``."""
    B = plane_tangent_basis(n_meas)
    M = np.empty((3, 3))
    for j in range(3):
        M[0, j] = n_meas[j]
        M[1, j] = B[j, 0]
        M[2, j] = B[j, 1]
    return M


@njit
def _chart_angles(M, ns):
    """``u = M n_s``, azimuth ``atan2(u1, u0)``, elevation ``atan2(u2, hypot(u0, u1))`` and ∂(angles)/∂n_s (2, 3)."""
    u = M @ ns
    h2 = u[0] * u[0] + u[1] * u[1]
    h = np.sqrt(h2)
    if h < _H_MIN:
        h = _H_MIN
        h2 = h * h
    r2 = h2 + u[2] * u[2]
    Dq = np.zeros((2, 3))
    Dq[0, 0] = -u[1] / h2
    Dq[0, 1] = u[0] / h2
    Dq[1, 0] = -u[2] * u[0] / (h * r2)
    Dq[1, 1] = -u[2] * u[1] / (h * r2)
    Dq[1, 2] = h / r2
    return np.arctan2(u[1], u[0]), np.arctan2(u[2], h), Dq @ M


@njit
def _residual(T, plane, meas):
    ps = plane_world_to_sensor(T, plane)
    M = measurement_chart(np.ascontiguousarray(meas[:3]))
    az, el, A = _chart_angles(M, np.ascontiguousarray(ps[:3]))
    return az, el, ps[3] - meas[3], ps, A


@njit
def pose_plane_edge_terms(poses, planes, edges, meas, r, J_pose, J_plane):
    """Fill ``r`` (m, 3), ``J_pose`` (m, 3, 6), ``J_plane`` (m, 3, 3) of pose–plane edges.

    Edge ``e`` joins pose ``T = poses[edges[e, 0]]`` (``T_world_sensor``) and the world plane
    landmark ``π = planes[edges[e, 1]]``; ``meas[e] = (n_t, d_t)`` is the plane observed in
    that sensor frame (unit ``n_t``). With ``π' = (n_s, d_s)`` the landmark in the sensor
    frame [Ren2019 Eqs. 9-10] the residual is [Ren2019 Eq. 11]
    ``e = q_t(π') − q_t(π_t)`` with ``q_t(π) = [atan2(u_1, u_0), atan2(u_2, hypot(u_0, u_1)), d]``,
    ``u = M_t n``, ``M_t`` the rows ``(n_t, b1, b2)`` of :func:`measurement_chart`. So ``q_t`` is the
    paper's ``q()`` (azimuth ``atan(n_a/n_b)`` with ``n_b ↔ u_0``, ``n_a ↔ u_1``; elevation
    with ``n_c ↔ u_2``) in a frame where the measured normal is on the equator at azimuth 0:
    ``q_t(π_t) = (0, 0, d_t)``, and the residual is smooth as long as the predicted normal is
    less than 90 degrees from the measured one. The rows are (rad, rad, m).

    Jacobians (right perturbations): ``n_s(δ) = Exp(−ω) Rᵀ n ≈ n_s + [n_s]x ω`` and
    ``d_s(δ) ≈ d_s + n_s·ρ``; the landmark update gives ``∂n/∂δ_n = B(n)``, so
    ``∂n_s/∂δ_n = Rᵀ B``, ``∂d_s/∂δ_n = tᵀ B``, ``∂d_s/∂δ_d = 1``. With ``A = ∂(angles)/∂n_s``:
    ``J_pose = [[A [n_s]x, 0], [0, n_sᵀ]]``, ``J_plane = [[A Rᵀ B, 0], [tᵀ B, 1]]``.
    """
    for e in prange(edges.shape[0]):
        T = poses[edges[e, 0]]
        plane = planes[edges[e, 1]]
        az, el, dd, ps, A = _residual(T, plane, meas[e])
        r[e, 0] = az
        r[e, 1] = el
        r[e, 2] = dd
        n0, n1, n2 = ps[0], ps[1], ps[2]
        for k in range(2):
            # A @ hat(n_s), hat(n_s) = [[0, -n2, n1], [n2, 0, -n0], [-n1, n0, 0]]
            J_pose[e, k, 0] = A[k, 1] * n2 - A[k, 2] * n1
            J_pose[e, k, 1] = -A[k, 0] * n2 + A[k, 2] * n0
            J_pose[e, k, 2] = A[k, 0] * n1 - A[k, 1] * n0
            J_pose[e, k, 3] = 0.0
            J_pose[e, k, 4] = 0.0
            J_pose[e, k, 5] = 0.0
        for j in range(3):
            J_pose[e, 2, j] = 0.0
            J_pose[e, 2, 3 + j] = ps[j]
        R = np.ascontiguousarray(T[:3, :3])
        t = np.ascontiguousarray(T[:3, 3])
        B = plane_tangent_basis(np.ascontiguousarray(plane[:3]))
        AB = A @ (R.T @ B)
        tB = t @ B
        for k in range(2):
            J_plane[e, k, 0] = AB[k, 0]
            J_plane[e, k, 1] = AB[k, 1]
            J_plane[e, k, 2] = 0.0
        J_plane[e, 2, 0] = tB[0]
        J_plane[e, 2, 1] = tB[1]
        J_plane[e, 2, 2] = 1.0


@njit
def pose_plane_residuals(poses, planes, edges, meas, r):
    """Residuals only (cost evaluation of a trial step), as :func:`pose_plane_edge_terms`."""
    for e in prange(edges.shape[0]):
        az, el, dd, _, _ = _residual(poses[edges[e, 0]], planes[edges[e, 1]], meas[e])
        r[e, 0] = az
        r[e, 1] = el
        r[e, 2] = dd


@njit_parallel
def ransac_plane_counts(P, samples, up, cos_max_tilt, threshold, counts, planes):
    """Score RANSAC plane hypotheses from 3-point samples (indices drawn by the caller).

    For each row ``k`` of ``samples`` (s, 3): the plane through the three points, normal
    oriented so that ``n·up ≥ 0``, and ``counts[k]`` = number of points with
    ``|n·p + d| ≤ threshold`` (m); ``counts[k] = -1`` for a degenerate (collinear or repeated)
    sample, ``-2`` for a plane tilted more than ``arccos(cos_max_tilt)`` from ``up``.
    """
    N = P.shape[0]
    for k in prange(samples.shape[0]):
        i, j, m = samples[k, 0], samples[k, 1], samples[k, 2]
        a = P[j] - P[i]
        b = P[m] - P[i]
        c = np.empty(3)
        c[0] = a[1] * b[2] - a[2] * b[1]
        c[1] = a[2] * b[0] - a[0] * b[2]
        c[2] = a[0] * b[1] - a[1] * b[0]
        cn = np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
        scale = np.sqrt((a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) * (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]))
        if cn <= 1e-9 * scale or cn == 0.0:
            counts[k] = -1
            planes[k, :] = 0.0
            continue
        c /= cn
        if c[0] * up[0] + c[1] * up[1] + c[2] * up[2] < 0.0:
            c = -c
        d = -(c[0] * P[i, 0] + c[1] * P[i, 1] + c[2] * P[i, 2])
        planes[k, :3] = c
        planes[k, 3] = d
        if c[0] * up[0] + c[1] * up[1] + c[2] * up[2] < cos_max_tilt:
            counts[k] = -2
            continue
        cnt = 0
        for q in range(N):
            if abs(c[0] * P[q, 0] + c[1] * P[q, 1] + c[2] * P[q, 2] + d) <= threshold:
                cnt += 1
        counts[k] = cnt
