"""Numba kernels of IMU preintegration and the IMU factor [Forster2017].

Contiguous float64 arrays in, no checks (:mod:`minegeo.optim.imu` validates). Conventions:

* Gravity ``g`` is a world-frame vector (``(0, 0, −9.80665)`` m/s²: z up); the accelerometer
  measures the specific force ``ã = Rᵀ(a − g) + b_a + η_a`` in the IMU frame, the gyroscope
  ``ω̃ = ω + b_g + η_g`` (rad/s).
* A bias is ``b = (b_a, b_g)`` (m/s², rad/s), GTSAM's ``imuBias::ConstantBias`` order.
* A navigation state is a pose ``T_world_imu`` (``R``, ``t``), a velocity ``v`` (world, m/s) and a
  bias; its tangent vector (15) is ``(φ, ρ, δv, δb_a, δb_g)`` applied as ``T ← T Exp((φ, ρ))``,
  ``v ← v + δv``, ``b ← b + δb`` (to first order ``R ← R Exp(φ)``, ``t ← t + R ρ``).
* A sample ``k`` (ω̃_k, ã_k) is held over its interval ``Δt_k`` (zero-order hold).
* The preintegration covariance and the factor residual are ordered (rotation, velocity,
  position), ``(δφ, δv, δp)`` with ``ΔR = ΔR̂ Exp(δφ)``, ``Δv = Δv̂ + δv``, ``Δp = Δp̂ + δp``.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit
from minegeo.kernels.lie import hat, so3_exp, so3_log, so3_right_jacobian, so3_right_jacobian_inv


@njit
def preintegrate(dt, acc, gyro, bias, cov_a, cov_g, cov_int, dR, dv, dp, J, cov):
    """Preintegrate samples ``k = 0..N−1`` [Forster2017 Secs. VI-A to VI-C].

    With ``a_k = ã_k − b_a``, ``w_k = ω̃_k − b_g`` and ``δR_k = Exp(w_k Δt_k)``:

    * ``ΔR ← ΔR δR_k``, ``Δv ← Δv + ΔR a_k Δt``, ``Δp ← Δp + Δv Δt + ½ ΔR a_k Δt²`` (old ΔR, Δv);
    * bias Jacobians ``J[0] = ∂ΔR/∂b_g ← δR_kᵀ J[0] − J_r(w_k Δt) Δt``,
      ``J[1] = ∂Δv/∂b_a ← J[1] − ΔR Δt``, ``J[2] = ∂Δv/∂b_g ← J[2] − ΔR [a_k]× J[0] Δt``,
      ``J[3] = ∂Δp/∂b_a ← J[3] + J[1] Δt − ½ ΔR Δt²``,
      ``J[4] = ∂Δp/∂b_g ← J[4] + J[2] Δt − ½ ΔR [a_k]× J[0] Δt²`` (right-hand sides at the old values);
    * covariance ``Σ ← A Σ Aᵀ + B_g (Σ_g/Δt) B_gᵀ + B_a (Σ_a/Δt) B_aᵀ`` (+ ``Σ_int Δt`` on the
      position block), ``A = [[δR_kᵀ, 0, 0], [−ΔR [a_k]× Δt, I, 0], [−½ ΔR [a_k]× Δt², I Δt, I]]``,
      ``B_g = [J_r(w_k Δt) Δt; 0; 0]``, ``B_a = [0; ΔR Δt; ½ ΔR Δt²]`` (``Σ_g``, ``Σ_a``,
      ``Σ_int``: continuous-time densities, (rad/s)²/Hz, (m/s²)²/Hz, m²/s).

    Outputs (overwritten): ``dR`` (3, 3), ``dv``, ``dp`` (3,), ``J`` (5, 3, 3), ``cov`` (9, 9).
    """
    R = np.eye(3)
    v = np.zeros(3)
    p = np.zeros(3)
    Jw = np.zeros((5, 3, 3))
    S = np.zeros((9, 9))
    A = np.zeros((9, 9))
    Bg = np.zeros((9, 3))
    Ba = np.zeros((9, 3))
    for k in range(dt.shape[0]):
        h = dt[k]
        a = acc[k] - bias[:3]
        w = (gyro[k] - bias[3:]) * h
        dRk = so3_exp(w)
        Jr = so3_right_jacobian(w)
        Ra = R @ a
        RaX = R @ hat(a)
        # covariance propagation (old R)
        A[:] = 0.0
        A[0:3, 0:3] = dRk.T
        A[3:6, 0:3] = -RaX * h
        A[6:9, 0:3] = -0.5 * RaX * h * h
        for q in range(3):
            A[3 + q, 3 + q] = 1.0
            A[6 + q, 6 + q] = 1.0
            A[6 + q, 3 + q] = h
        Bg[:] = 0.0
        Bg[0:3, :] = Jr * h
        Ba[:] = 0.0
        Ba[3:6, :] = R * h
        Ba[6:9, :] = 0.5 * R * h * h
        S = A @ S @ A.T + Bg @ (cov_g / h) @ Bg.T + Ba @ (cov_a / h) @ Ba.T
        S[6:9, 6:9] += cov_int * h
        # bias Jacobians (right-hand sides at the old values)
        J0 = Jw[0].copy()
        Jw[3] = Jw[3] + Jw[1] * h - 0.5 * R * h * h
        Jw[4] = Jw[4] + Jw[2] * h - 0.5 * (RaX @ J0) * h * h
        Jw[1] = Jw[1] - R * h
        Jw[2] = Jw[2] - (RaX @ J0) * h
        Jw[0] = dRk.T @ J0 - Jr * h
        # the deltas
        p = p + v * h + 0.5 * Ra * h * h
        v = v + Ra * h
        R = R @ dRk
    dR[:] = R
    dv[:] = v
    dp[:] = p
    J[:] = Jw
    cov[:] = 0.5 * (S + S.T)


@njit
def imu_factor_terms(poses, vec, pairs, dR, dv, dp, J, bias_hat, dT, g, r, Ji, Jj):
    """Residuals ``r`` (m, 9) and Jacobians ``Ji``, ``Jj`` (m, 9, 15) of IMU factors [Forster2017 Sec. VI-D].

    State ``i`` = (``poses[i]``, ``vec[i] = (v, b_a, b_g)``); ``δb = b_i − b̂`` (``bias_hat[e]``, the
    bias the factor was preintegrated with); first-order bias correction
    ``ΔR̄ = ΔR Exp(J_R^g δb_g)``, ``Δv̄ = Δv + J_v^a δb_a + J_v^g δb_g``, ``Δp̄ = Δp + J_p^a δb_a + J_p^g δb_g``:

    * ``r_R = Log(ΔR̄ᵀ R_iᵀ R_j)``,
    * ``r_v = R_iᵀ (v_j − v_i − g Δt) − Δv̄``,
    * ``r_p = R_iᵀ (t_j − t_i − v_i Δt − ½ g Δt²) − Δp̄``.

    Jacobians (columns ``φ, ρ, v, b_a, b_g`` of state i, then j): ``∂r_R/∂φ_i = −J_r⁻¹(r_R) R_jᵀR_i``,
    ``∂r_R/∂φ_j = J_r⁻¹(r_R)``, ``∂r_R/∂b_g = −J_r⁻¹(r_R) Exp(r_R)ᵀ J_r(J_R^g δb_g) J_R^g``;
    ``∂r_v/∂φ_i = [R_iᵀ(v_j − v_i − gΔt)]×``, ``∂r_v/∂v_i = −R_iᵀ``, ``∂r_v/∂v_j = R_iᵀ``,
    ``∂r_v/∂b = −(J_v^a, J_v^g)``; ``∂r_p/∂φ_i = [R_iᵀ(t_j − t_i − v_iΔt − ½gΔt²)]×``,
    ``∂r_p/∂ρ_i = −I``, ``∂r_p/∂ρ_j = R_iᵀR_j``, ``∂r_p/∂v_i = −R_iᵀ Δt``, ``∂r_p/∂b = −(J_p^a, J_p^g)``.
    """
    for e in range(pairs.shape[0]):
        i, j = pairs[e, 0], pairs[e, 1]
        Ri = np.ascontiguousarray(poses[i, :3, :3])
        Rj = np.ascontiguousarray(poses[j, :3, :3])
        ti, tj = poses[i, :3, 3], poses[j, :3, 3]
        vi, vj = vec[i, 0:3], vec[j, 0:3]
        dba = vec[i, 3:6] - bias_hat[e, 0:3]
        dbg = vec[i, 6:9] - bias_hat[e, 3:6]
        h = dT[e]
        JRg = np.ascontiguousarray(J[e, 0])
        phi_b = JRg @ dbg
        E = (dR[e] @ so3_exp(phi_b)).T @ Ri.T @ Rj
        rR = so3_log(E)
        Jrinv = so3_right_jacobian_inv(rR)
        dvw = vj - vi - g * h
        dpw = tj - ti - vi * h - 0.5 * g * h * h
        rv = Ri.T @ dvw - (dv[e] + J[e, 1] @ dba + J[e, 2] @ dbg)
        rp = Ri.T @ dpw - (dp[e] + J[e, 3] @ dba + J[e, 4] @ dbg)
        r[e, 0:3] = rR
        r[e, 3:6] = rv
        r[e, 6:9] = rp
        Ji[e] = 0.0
        Jj[e] = 0.0
        Ji[e, 0:3, 0:3] = -Jrinv @ Rj.T @ Ri
        Jj[e, 0:3, 0:3] = Jrinv
        Ji[e, 0:3, 12:15] = -Jrinv @ E.T @ so3_right_jacobian(phi_b) @ JRg
        Ji[e, 3:6, 0:3] = hat(Ri.T @ dvw)
        Ji[e, 3:6, 6:9] = -Ri.T
        Jj[e, 3:6, 6:9] = Ri.T
        Ji[e, 3:6, 9:12] = -J[e, 1]
        Ji[e, 3:6, 12:15] = -J[e, 2]
        Ji[e, 6:9, 0:3] = hat(Ri.T @ dpw)
        for q in range(3):
            Ji[e, 6 + q, 3 + q] = -1.0
        Jj[e, 6:9, 3:6] = Ri.T @ Rj
        Ji[e, 6:9, 6:9] = -Ri.T * h
        Ji[e, 6:9, 9:12] = -J[e, 3]
        Ji[e, 6:9, 12:15] = -J[e, 4]
