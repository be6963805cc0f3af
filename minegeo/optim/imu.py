"""IMU preintegration and the IMU factors [Forster2017] ("On-Manifold Preintegration for Real-Time
Visual-Inertial Odometry", IEEE T-RO 33(1), 2017).

Conventions
-----------
* World frame z up; gravity ``g = (0, 0, −9.80665)`` m/s² (:data:`GRAVITY_M_S2` along −z), GTSAM's
  ``PreintegrationParams.MakeSharedU(9.80665)``.
* The IMU measures in its own frame: the gyroscope ``ω̃ = ω + b_g + η_g`` (rad/s), the
  accelerometer the specific force ``ã = Rᵀ(a − g) + b_a + η_a`` (m/s²: at rest, level, it reads
  ``+9.80665`` on its up axis), ``R`` the rotation of ``T_world_imu``; white noise ``η`` and biases
  ``b`` that follow random walks. Noise parameters are Kalibr's (:class:`ImuNoise`).
* A bias is ``b = (b_a, b_g)`` (GTSAM's ``imuBias::ConstantBias`` vector order).
* A navigation state is ``T_world_imu`` (4×4), the velocity ``v`` of the IMU in the world frame
  (m/s) and the bias: in :class:`minegeo.optim.factors.Values`, ``poses`` and
  ``vectors = (v, b_a, b_g)`` (9); its tangent vector (15) is ``(φ, ρ, δv, δb_a, δb_g)``.
* Samples are held over their interval (zero-order hold): sample ``k`` at time ``t_k`` acts on
  ``[t_k, t_k + Δt_k)``, as GTSAM's ``integrateMeasurement(acc, omega, dt)``.

Preintegration (:func:`preintegrate`, [Forster2017 Sec. VI-A]) gives ``ΔR_ij``, ``Δv_ij``,
``Δp_ij`` from samples corrected by a bias estimate ``b̂``, their covariance (order rotation,
velocity, position; [Forster2017 Sec. VI-B]) and their Jacobians with respect to the bias
and the first-order bias correction [Forster2017 Sec. VI-C]. The IMU factor
(:class:`ImuFactors`, [Forster2017 Sec. VI-D]) ties states i and j:

.. math::

    r_R = \\operatorname{Log}(\\Delta\\bar R^\\top R_i^\\top R_j), \\quad
    r_v = R_i^\\top(v_j - v_i - g\\Delta t) - \\Delta\\bar v, \\quad
    r_p = R_i^\\top(t_j - t_i - v_i\\Delta t - \\tfrac12 g\\Delta t^2) - \\Delta\\bar p

(the component-wise error of GTSAM's ``ImuFactor`` in its ``Legacy`` error mode, reordered), with
information the inverse of the preintegration covariance; :class:`BiasRandomWalkFactors` ties
``b_j − b_i`` with covariance ``diag(σ_ba², σ_bg²) Δt``. Section numbers are those of the T-RO paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo._params import bounded, validate
from minegeo.errors import InputError
from minegeo.kernels.lie import so3_exp
from minegeo.optim import _kernels_imu as KI
from minegeo.optim.factors import FactorGroup, Values

__all__ = ["GRAVITY_M_S2", "BiasRandomWalkFactors", "ImuFactors", "ImuNoise", "Preintegrated", "gravity_vector",
           "imu_factor_terms", "preintegrate"]

#: standard gravity (m/s²), along −z of the world frame
GRAVITY_M_S2 = 9.80665


def gravity_vector() -> np.ndarray:
    """``g = (0, 0, −9.80665)`` m/s², world frame (z up)."""
    return np.array([0.0, 0.0, -GRAVITY_M_S2])


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise as Kalibr's ``imu.yaml`` names it (continuous-time densities).

    Attributes
    ----------
    gyroscope_noise_density : float
        σ_g, rad/s/√Hz (white noise of the gyroscope).
    accelerometer_noise_density : float
        σ_a, m/s²/√Hz.
    gyroscope_random_walk : float
        σ_bg, rad/s²/√Hz (random walk of the gyroscope bias).
    accelerometer_random_walk : float
        σ_ba, m/s³/√Hz.
    integration_sigma : float
        σ_int, m/√s: a white position noise that models the error of the zero-order hold
        (GTSAM's ``integrationCovariance`` = σ_int² I); 0 by default.

    Each field declares its rule in its metadata (:mod:`minegeo._params`): the four densities and
    random walks finite and > 0, ``integration_sigma`` finite and >= 0; the same rules check the
    values of a Kalibr ``imu.yaml`` (:func:`minegeo.io.imu.read_imu_noise`, ``--imu-noise``).
    """

    gyroscope_noise_density: float = bounded(1.7e-4, gt=0.0)
    accelerometer_noise_density: float = bounded(2.0e-3, gt=0.0)
    gyroscope_random_walk: float = bounded(1.9e-5, gt=0.0)
    accelerometer_random_walk: float = bounded(3.0e-3, gt=0.0)
    integration_sigma: float = bounded(0.0, ge=0.0)

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class Preintegrated:
    """Preintegrated IMU measurements between two states [Forster2017 Sec. VI-A].

    Attributes
    ----------
    dt : float
        ``Δt_ij`` (s).
    delta_R : ndarray (3, 3)
        ``ΔR_ij``, the rotation of the IMU frame at j in the IMU frame at i.
    delta_v, delta_p : ndarray (3,)
        ``Δv_ij``, ``Δp_ij`` (m/s, m; IMU frame at i, gravity not included).
    jacobians : ndarray (5, 3, 3)
        ``∂ΔR/∂b_g`` (as a right perturbation), ``∂Δv/∂b_a``, ``∂Δv/∂b_g``, ``∂Δp/∂b_a``, ``∂Δp/∂b_g``.
    covariance : ndarray (9, 9)
        Of ``(δφ, δv, δp)`` (rad², (m/s)², m²).
    bias : ndarray (6,)
        ``b̂ = (b_a, b_g)`` the samples were corrected with.
    """

    dt: float
    delta_R: np.ndarray
    delta_v: np.ndarray
    delta_p: np.ndarray
    jacobians: np.ndarray
    covariance: np.ndarray
    bias: np.ndarray

    def corrected(self, bias) -> tuple:
        """``(ΔR̄, Δv̄, Δp̄)`` for another bias by the first-order correction [Forster2017 Sec. VI-C]."""
        b = _vector(bias, 6, "bias")
        dba, dbg = b[:3] - self.bias[:3], b[3:] - self.bias[3:]
        J = self.jacobians
        return (self.delta_R @ so3_exp(J[0] @ dbg), self.delta_v + J[1] @ dba + J[2] @ dbg,
                self.delta_p + J[3] @ dba + J[4] @ dbg)

    def predict(self, T_world_imu_i, v_i, bias=None):
        """State j predicted from state i: ``R_j = R_i ΔR̄``, ``v_j = v_i + g Δt + R_i Δv̄``,
        ``t_j = t_i + v_i Δt + ½ g Δt² + R_i Δp̄``. Returns ``(T_world_imu_j, v_j)``."""
        T = np.asarray(T_world_imu_i, dtype=np.float64)
        v = _vector(v_i, 3, "v_i")
        dR, dv, dp = self.corrected(self.bias if bias is None else bias)
        g, h, R = gravity_vector(), self.dt, T[:3, :3]
        out = np.eye(4)
        out[:3, :3] = R @ dR
        out[:3, 3] = T[:3, 3] + v * h + 0.5 * g * h * h + R @ dp
        return out, v + g * h + R @ dv


def _vector(x, n: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape != (n,) or not np.all(np.isfinite(x)):
        raise InputError(f"{name} must be a finite {n}-vector, got shape {x.shape}")
    return np.ascontiguousarray(x)


def preintegrate(gyro, acc, dt, bias=None, noise: ImuNoise | None = None) -> Preintegrated:
    """Preintegrate IMU samples between two states [Forster2017 Secs. VI-A to VI-C].

    Parameters
    ----------
    gyro : ndarray (N, 3)
        Angular rate ω̃ (rad/s, IMU frame).
    acc : ndarray (N, 3)
        Specific force ã (m/s², IMU frame, gravity included).
    dt : ndarray (N,) or float
        Interval of each sample (s, > 0): sample k is held over ``dt[k]``.
    bias : ndarray (6,), optional
        ``b̂ = (b_a, b_g)`` removed from the samples (m/s², rad/s); zero by default.
    noise : ImuNoise, optional

    Returns
    -------
    Preintegrated
    """
    noise = noise or ImuNoise()
    w = np.ascontiguousarray(np.asarray(gyro, dtype=np.float64))
    a = np.ascontiguousarray(np.asarray(acc, dtype=np.float64))
    if w.ndim != 2 or w.shape[1] != 3 or a.shape != w.shape or w.shape[0] == 0:
        raise InputError(f"gyro and acc must both be (N, 3) arrays with N >= 1, got {w.shape} and {a.shape}")
    h = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=np.float64), (w.shape[0],)))
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(a)) and np.all(np.isfinite(h)) and np.all(h > 0)):
        raise InputError("IMU samples must be finite and every interval dt positive")
    b = np.zeros(6) if bias is None else _vector(bias, 6, "bias")
    I3 = np.eye(3)
    dR, dv, dp, J, cov = np.empty((3, 3)), np.empty(3), np.empty(3), np.empty((5, 3, 3)), np.empty((9, 9))
    KI.preintegrate(h, a, w, b, I3 * noise.accelerometer_noise_density ** 2, I3 * noise.gyroscope_noise_density ** 2,
                    I3 * noise.integration_sigma ** 2, dR, dv, dp, J, cov)
    return Preintegrated(float(h.sum()), dR, dv, dp, J, cov, b.copy())


def imu_factor_terms(T_i, v_i, bias_i, T_j, v_j, bias_j, pim: Preintegrated):
    """Residual (9: rotation, velocity, position) and Jacobians (9 × 15 for state i and for state j,
    columns ``(φ, ρ, v, b_a, b_g)``) of one IMU factor [Forster2017 Sec. VI-D] (:class:`ImuFactors`)."""
    poses = np.ascontiguousarray(np.stack([np.asarray(T_i, float), np.asarray(T_j, float)]))
    vec = np.ascontiguousarray(np.stack([np.r_[_vector(v_i, 3, "v_i"), _vector(bias_i, 6, "bias_i")],
                                         np.r_[_vector(v_j, 3, "v_j"), _vector(bias_j, 6, "bias_j")]]))
    f = ImuFactors([(0, 1, pim)])
    r, (Ji, Jj) = f.linearize(Values(poses, vec))
    return r[0], Ji[0], Jj[0]


class ImuFactors(FactorGroup):
    """IMU factors [Forster2017 Sec. VI-D] between navigation states (:mod:`minegeo.optim.imu` conventions).

    Parameters
    ----------
    factors : sequence of (i, j, Preintegrated)
        States i and j (variable indices) and the measurements preintegrated between them.
    """

    def __init__(self, factors):
        factors = list(factors)
        m = len(factors)
        self.variables = np.asarray([(i, j) for i, j, _ in factors], dtype=np.int64).reshape(m, 2)
        P = [f[2] for f in factors]
        self.dR = np.ascontiguousarray(np.asarray([p.delta_R for p in P], dtype=np.float64).reshape(m, 3, 3))
        self.dv = np.ascontiguousarray(np.asarray([p.delta_v for p in P], dtype=np.float64).reshape(m, 3))
        self.dp = np.ascontiguousarray(np.asarray([p.delta_p for p in P], dtype=np.float64).reshape(m, 3))
        self.J = np.ascontiguousarray(np.asarray([p.jacobians for p in P], dtype=np.float64).reshape(m, 5, 3, 3))
        self.bias_hat = np.ascontiguousarray(np.asarray([p.bias for p in P], dtype=np.float64).reshape(m, 6))
        self.dT = np.asarray([p.dt for p in P], dtype=np.float64)
        cov = np.asarray([p.covariance for p in P], dtype=np.float64).reshape(m, 9, 9)
        if m and np.min(np.linalg.eigvalsh(cov)[:, 0]) <= 0:
            raise InputError("an IMU factor's preintegration covariance is not positive definite (zero noise?)")
        info = np.linalg.inv(cov) if m else np.zeros((0, 9, 9))
        self.information = np.ascontiguousarray(0.5 * (info + np.swapaxes(info, 1, 2)))
        self.g = gravity_vector()

    def _terms(self, values: Values):
        m = self.variables.shape[0]
        r, Ji, Jj = np.empty((m, 9)), np.empty((m, 9, 15)), np.empty((m, 9, 15))
        KI.imu_factor_terms(np.ascontiguousarray(values.poses), np.ascontiguousarray(values.vectors),
                            self.variables, self.dR, self.dv, self.dp, self.J, self.bias_hat, self.dT, self.g,
                            r, Ji, Jj)
        return r, Ji, Jj

    def residuals(self, values: Values) -> np.ndarray:
        return self._terms(values)[0]

    def linearize(self, values: Values) -> tuple:
        r, Ji, Jj = self._terms(values)
        return r, (Ji, Jj)


class BiasRandomWalkFactors(FactorGroup):
    """``r = b_j − b_i`` (6: accelerometer, gyroscope) with covariance ``diag(σ_ba² I, σ_bg² I) Δt_ij``
    (the biases' random walks of :class:`ImuNoise`).

    Parameters
    ----------
    pairs : ndarray (m, 2) of int
        States i and j.
    dt : ndarray (m,)
        ``Δt_ij`` (s, > 0).
    noise : ImuNoise
    """

    def __init__(self, pairs, dt, noise: ImuNoise):
        self.variables = np.ascontiguousarray(np.asarray(pairs, dtype=np.int64).reshape(-1, 2))
        h = np.broadcast_to(np.asarray(dt, dtype=np.float64), (self.variables.shape[0],))
        if not (np.all(np.isfinite(h)) and np.all(h > 0)):
            raise InputError("bias random-walk intervals must be positive and finite")
        d = np.r_[np.full(3, noise.accelerometer_random_walk ** 2), np.full(3, noise.gyroscope_random_walk ** 2)]
        self.information = np.ascontiguousarray(np.einsum("m,ij->mij", 1.0 / h, np.diag(1.0 / d)))

    def residuals(self, values: Values) -> np.ndarray:
        b = values.vectors[:, 3:9]
        return b[self.variables[:, 1]] - b[self.variables[:, 0]]

    def linearize(self, values: Values) -> tuple:
        m = self.variables.shape[0]
        Ji, Jj = np.zeros((m, 6, 15)), np.zeros((m, 6, 15))
        Ji[:, :, 9:15] = -np.eye(6)
        Jj[:, :, 9:15] = np.eye(6)
        return self.residuals(values), (Ji, Jj)
