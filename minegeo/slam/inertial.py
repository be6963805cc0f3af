"""LiDAR-inertial SLAM: the IMU's gyro in the odometry, its preintegration in the keyframe graph.

Conventions (the SLAM contract, "Sensor streams"; :mod:`minegeo.io.imu`; :mod:`minegeo.optim.imu`):

* The IMU samples are :class:`~minegeo.io.imu.ImuSamples` (an IMU CSV or a bag's ``sensor_msgs/Imu``
  topic: every entry point of this module takes the samples, not a file): times on the frames'
  clock, gyro ω̃ (rad/s) and specific force ã (m/s², gravity included) on the IMU axes, which are
  the LiDAR's unless ``T_lidar_imu = E`` is given (``p_lidar = R_E p_imu + t_E``).
* A sample is the rate at its instant: an interval between two sample times carries the two samples'
  mean (the midpoint rule, :meth:`GyroAid.samples`).

Front end (:class:`GyroAid`, used by :func:`minegeo.slam.odometry.run_odometry`):

* **Rotation prior of each registration**: the rotation of the LiDAR between two frame times from
  the integrated gyro, ``ΔR_L = R_E ΔR_I R_Eᵀ`` with ``ΔR_I = Π Exp((ω̃_k − b̂_g) Δt_k)``
  [Forster2017 Sec. VI-A] (the bias ``b̂_g`` estimated so far); the translation from the constant
  velocity of the odometry.
* **IMU deskew**: a point measured ``τ`` after the frame time in the sensor frame of that instant is
  moved to the frame time by ``q = ΔR_L(τ) p + τ v``, ``ΔR_L(τ)`` the gyro-integrated rotation
  from the frame time to ``t + τ`` (each point at its own time) and ``v`` the velocity of the
  odometry's constant-velocity twist (m/s, sensor frame at the frame time).
* **IMU gate** (no silent runaway): a registration whose rotation since the last registered frame
  differs from the gyro's over the same interval by more than a bound from the gyro's noise and a
  registration tolerance (:meth:`GyroAid.disagreement`) is rejected; the frame is then held by the
  IMU (rotation from the gyro, translation from the constant velocity: the front end has no
  velocity or gravity state to integrate the accelerometer with, so the translation is checked by the
  odometry's motion-prior bounds only) and flagged as a held stretch
  (:meth:`minegeo.slam.odometry.OdometryResult.held_stretches`, ``held_by``).
* **Gyro bias**: each registered motion ``ΔR_reg`` over ``[t_a, t_b]`` measures the bias through
  ``Log(ΔR_I(b̂)ᵀ ΔR_reg) ≈ J_g (b_g − b̂)`` (``J_g = ∂ΔR/∂b_g``, [Forster2017 Eq. 44]); the
  estimate is the linear least-squares solution over the registered frames so far with a prior
  ``σ_bg,prior`` about zero.

Back end (:func:`optimize_inertial_graph`): the keyframe pose graph of the LiDAR (odometry, extra
and loop edges) with, per keyframe, a navigation state ``(T_world_imu, v, b_a, b_g)`` and between
consecutive keyframes an IMU factor [Forster2017 Sec. VI-D] and a bias random-walk factor, solved by
the one optimiser (:func:`minegeo.optim.lm.levenberg_marquardt`). The world frame is the first
keyframe's LiDAR frame turned so that gravity is ``(0, 0, −9.80665)``: the first keyframe's up axis
from the specific force over ``gravity_window_s``, each sample rotated into its axes by the gyro,
less the LiDAR trajectory's velocity change (:func:`_initial_states`); a prior fixes its position
and heading (yaw about the world z) and holds its roll and pitch to ``roll_pitch_sigma_deg``. The
roll and pitch of every later keyframe then follow from gravity in the IMU factors' velocity and
position residuals (the first keyframe's own tilt is told from an accelerometer bias only by the
yaw changes of the run, weakly: hence the prior). The LiDAR edges ``Z`` of the LiDAR frame become
``E⁻¹ Z E`` with information ``Ad(E)ᵀ Ω Ad(E)`` on the IMU poses. The result is returned in the
first keyframe's LiDAR frame (the contract's map frame).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from minegeo._params import bounded, group, validate
from minegeo.errors import InputError
from minegeo.geometry.se3 import compose, invert, project
from minegeo.io.imu import ImuSamples
from minegeo.kernels.lie import se3_adjoint, so3_exp, so3_log
from minegeo.optim import (
    BetweenFactors,
    FactorGroup,
    FactorProblem,
    LMParams,
    LMStatus,
    PriorFactors,
    Values,
    levenberg_marquardt,
)
from minegeo.optim.imu import BiasRandomWalkFactors, ImuFactors, ImuNoise, preintegrate
from minegeo.slam._kernels_inertial import gyro_deskew_kernel
from minegeo.slam.odometry import start_velocity

__all__ = ["GyroAid", "InertialParams", "InertialResult", "check_imu_for_frames", "optimize_inertial_graph"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InertialParams:
    """Parameters of the LiDAR-inertial SLAM.

    Attributes
    ----------
    noise : ImuNoise
        The IMU's Kalibr noise densities and random walks (:class:`minegeo.optim.imu.ImuNoise`).
    max_gap_s : float
        Longest time between two IMU samples within the frames' time span (s).
    gravity_window_s : float
        The first keyframe's up axis is from the specific force over this time from its frame time (s;
        :func:`_initial_states`).
    roll_pitch_sigma_deg : float
        Prior standard deviation of the first keyframe's roll and pitch about that up axis (deg). The
        IMU factors observe the tilt only through the yaw changes that separate a tilted gravity from
        an accelerometer bias: on the 20 s handheld stream, with the LiDAR edges exact, holding gravity
        at the truth instead of 0.5° off raised the cost by 0.43 only.
    gyro_bias_sigma : float
        Prior standard deviation of the gyro bias about zero (rad/s), front end and graph.
    accel_bias_sigma : float
        Prior standard deviation of the accelerometer bias about zero (m/s²), graph.
    rotation_sigma_deg : float
        Standard deviation of a registered rotation in the front end's bias estimate (deg).
    edge_sigma_deg, edge_sigma_m : float
        Noise added to every LiDAR edge's covariance in the inertial graph (deg, m per axis):
        ``Ω' = (Ω⁻¹ + diag(σ_r² I, σ_t² I))⁻¹``. GICP's own information (σ below 1 mm and 0.01°
        on the simulated streams) holds the registration's scatter only, not its bias (ring
        pattern, deskewing), and against the IMU such an edge pulls gravity and the accelerometer
        bias away (measured: 32° of tilt on a 3 s handheld stream without the floor). Too much
        noise lets the IMU's tilt, which an accelerometer bias mimics on a level straight, override
        the LiDAR's: 0.05° and 5 mm gave a lower unaligned ATE than 0.2° and 2 cm on each of the
        eleven 20 s streams of ``benchmarks/bench_inertial_edge_noise.py`` (docs/slam.md
        "LiDAR-inertial"), 0.02° and 2 mm a higher one on some.
    gate_tolerance_deg, gate_sigmas : float
        The IMU gate of each registration (:meth:`GyroAid.disagreement`): a registered rotation more
        than ``gate_tolerance_deg + gate_sigmas · σ_θ`` from the gyro's over the same interval is
        rejected (deg; dimensionless). The tolerance is the registration's own rotation error: on
        the simulated 10 Hz streams (3 s from t = 13 s, seed 1) GICP's registered rotations were within
        0.25° (handheld), 0.45° (vehicle) and 1.4° (drone, fast turns, sparse rings) of the truth; ``σ_θ``
        the gyro's (white noise, bias estimate, bias random walk over the interval).

    Each field declares its rule in its metadata (:mod:`minegeo._params`): the same rule checks the
    dataclass, the ``--imu-max-gap`` option of ``minegeo slam`` and ``minegeo track`` and its key in a
    ``--config`` file; ``noise`` is an :class:`~minegeo.optim.imu.ImuNoise` (which checks itself).
    """

    noise: ImuNoise = group(ImuNoise)
    max_gap_s: float = bounded(0.05, gt=0.0)
    gravity_window_s: float = bounded(1.0, gt=0.0)
    roll_pitch_sigma_deg: float = bounded(0.3, gt=0.0)
    gyro_bias_sigma: float = bounded(0.05, gt=0.0)
    accel_bias_sigma: float = bounded(0.5, gt=0.0)
    rotation_sigma_deg: float = bounded(0.05, gt=0.0)
    edge_sigma_deg: float = bounded(0.05, gt=0.0)
    edge_sigma_m: float = bounded(0.005, gt=0.0)
    gate_tolerance_deg: float = bounded(2.0, gt=0.0)
    gate_sigmas: float = bounded(4.0, gt=0.0)

    def __post_init__(self):
        validate(self)


def check_imu_for_frames(imu: ImuSamples, t_first: float, t_last: float, max_gap_s: float, what: str) -> None:
    """The IMU as the LiDAR-inertial run needs it, checked before any work.

    Its samples must cover the frames' time span ``[t_first, t_last]`` (s) and leave no gap longer
    than ``max_gap_s`` within it (the order of the rows is checked by the reader,
    :func:`minegeo.io.imu.imu_samples`).

    Raises
    ------
    InputError
        Naming ``what`` (the file or topic), the span and the first gap.
    """
    t = imu.t_s
    if t.size < 2:
        raise InputError(f"{what}: {t.size} IMU sample(s); the IMU must cover the frames' time span "
                         f"{t_first:.6f} to {t_last:.6f} s")
    if t[0] > t_first or t[-1] < t_last:
        raise InputError(f"{what}: the IMU samples span {t[0]:.6f} to {t[-1]:.6f} s and do not cover the frames' "
                         f"time span {t_first:.6f} to {t_last:.6f} s (same clock, seconds)")
    lo = max(int(np.searchsorted(t, t_first, side="right")) - 1, 0)
    hi = min(int(np.searchsorted(t, t_last, side="left")), t.size - 1)
    gaps = np.diff(t[lo:hi + 1])
    if gaps.size and gaps.max() > max_gap_s:
        k = lo + int(np.argmax(gaps))
        raise InputError(f"{what}: no IMU sample for {gaps.max():.6g} s (from {t[k]:.6f} to {t[k + 1]:.6f} s), "
                         f"longer than the {max_gap_s:g} s allowed (--imu-max-gap)")


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """``Exp(φ)`` of each row of ``phi`` (n, 3) → (n, 3, 3), Rodrigues' formula (Solà 2018, App. B; series below 1e-8 rad²)."""
    th2 = np.einsum("ij,ij->i", phi, phi)
    th = np.sqrt(th2)
    small = th2 < 1e-8
    safe = np.where(small, 1.0, th)
    s = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    c = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = np.zeros((phi.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    return np.eye(3)[None] + s[:, None, None] * K + c[:, None, None] * (K @ K)


class GyroAid:
    """The gyro in the odometry: rotation prior, per-point deskew and a running gyro-bias estimate
    (module docstring).

    Parameters
    ----------
    imu : ImuSamples
    params : InertialParams, optional
    """

    def __init__(self, imu: ImuSamples, params: InertialParams | None = None):
        self.params = params or InertialParams()
        self.imu = imu
        E = imu.T_lidar_imu if imu.T_lidar_imu is not None else np.eye(4)
        self.R_E = np.ascontiguousarray(E[:3, :3])
        self.t = imu.t_s
        self.gyro = imu.gyro_rad_s
        p = self.params
        self._A = np.eye(3) / p.gyro_bias_sigma ** 2  # normal equations of the bias (IMU axes)
        self._b = np.zeros(3)
        self._A_gate = np.eye(3) / p.gyro_bias_sigma ** 2  # the same with the gate's tolerance (bias_sigma)
        self.bias_g = np.zeros(3)
        self.n_updates = 0

    def samples(self, t0: float, t1: float):
        """``(gyro, accel, Δt)`` over ``[t0, t1]`` (IMU axes; rad/s, m/s², s): the interval cut at the
        sample times, each piece of length ``Δt_k > 0`` carrying the mean of the two samples of the
        sample interval it lies in (the midpoint rule; the first or last sample outside the samples'
        span).

        The samples are the rates at their instants: holding each over the next interval (zero-order
        hold) lags the motion by half a sample, which on the simulated handheld walk (sway of 0.3 rad/s,
        200 Hz) turned gravity by 0.04° in the body axes and left 10-20 mm/s of velocity residual per
        1.7 s keyframe interval at the true states; the midpoint rule is second order."""
        t = self.t
        knots = np.r_[t0, t[(t > t0) & (t < t1)], t1]
        h = np.diff(knots)
        keep = h > 0
        k = np.searchsorted(t, (0.5 * (knots[:-1] + knots[1:]))[keep], side="right") - 1
        k0, k1 = np.clip(k, 0, t.size - 1), np.clip(k + 1, 0, t.size - 1)
        g = 0.5 * (self.gyro[k0] + self.gyro[k1])
        a = 0.5 * (self.imu.accel_m_s2[k0] + self.imu.accel_m_s2[k1])
        return g.reshape(-1, 3), a.reshape(-1, 3), h[keep]

    def _delta_R_imu(self, t0: float, t1: float, bias_g: np.ndarray) -> np.ndarray:
        """``ΔR_I = Π Exp((ω̃_k − b_g) Δt_k)`` over ``[t0, t1]`` [Forster2017 Sec. VI-A] (IMU axes)."""
        g, _, h = self.samples(t0, t1)
        R = np.eye(3)
        for w, dt in zip(g, h, strict=True):
            R = R @ so3_exp(np.ascontiguousarray((w - bias_g) * dt))
        return R

    def rotation(self, t0: float, t1: float) -> np.ndarray:
        """The LiDAR's rotation from ``t0`` to ``t1`` (``R_L(t0)ᵀ R_L(t1)``) from the gyro, bias removed."""
        return self.R_E @ self._delta_R_imu(t0, t1, self.bias_g) @ self.R_E.T

    def guess(self, motion_cv: np.ndarray, t0: float, t1: float) -> np.ndarray:
        """The motion ``T(t0)⁻¹ T(t1)``: rotation from the gyro, translation ``motion_cv``'s (the constant
        velocity's over the same time)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation(t0, t1)
        out[:3, 3] = motion_cv[:3, 3]
        return project(out)

    def mean_rate(self, t0: float, t1: float) -> np.ndarray:
        """Mean angular rate of the LiDAR over ``[t0, t1]`` (rad/s, LiDAR axes, bias removed)."""
        g, _, h = self.samples(t0, t1)
        if h.size == 0:
            return self.R_E @ (np.array([np.interp(t0, self.t, self.gyro[:, i]) for i in range(3)]) - self.bias_g)
        return self.R_E @ (((g - self.bias_g) * h[:, None]).sum(axis=0) / h.sum())

    def deskew(self, points: np.ndarray, offsets_s: np.ndarray, t: float, v: np.ndarray) -> np.ndarray:
        """Points moved to the sensor frame at frame time ``t``: ``q_i = ΔR_L(τ_i) p_i + τ_i v``, the rotation
        from the gyro at each point's own time, ``v`` the velocity (m/s, sensor frame at ``t``)."""
        P = np.asarray(points, dtype=np.float64)
        tau = np.asarray(offsets_s, dtype=np.float64).reshape(-1)
        if P.shape[0] == 0:
            return P.copy()
        lo, hi = min(t, t + float(tau.min())), max(t, t + float(tau.max()))
        g, _, h = self.samples(lo, hi)
        if h.size == 0:  # every point at the frame time
            return P + tau[:, None] * np.asarray(v, dtype=np.float64)[None, :]
        w = (g - self.bias_g) @ self.R_E.T  # LiDAR axes
        steps = _rodrigues(w * h[:, None])
        knots_R = np.empty((h.size + 1, 3, 3))  # rotation from `lo` to each knot
        knots_R[0] = np.eye(3)
        for j in range(h.size):
            knots_R[j + 1] = knots_R[j] @ steps[j]
        knots_t = lo + np.r_[0.0, np.cumsum(h)]
        jf = min(max(int(np.searchsorted(knots_t, t, side="right")) - 1, 0), h.size - 1)
        R_t = knots_R[jf] @ _rodrigues((w[jf] * (t - knots_t[jf]))[None])[0]
        M = np.ascontiguousarray(np.einsum("ji,njk->nik", R_t, knots_R[:-1]))  # R(t)ᵀ R(t_j)
        P = np.ascontiguousarray(P) if P.flags.writeable else P.copy()  # the kernel takes writable arrays
        return gyro_deskew_kernel(P, np.ascontiguousarray(t + tau), np.ascontiguousarray(knots_t),
                                  M, np.ascontiguousarray(w), np.r_[np.asarray(v, dtype=np.float64), t])

    def bias_sigma(self) -> float:
        """Standard deviation of the running gyro-bias estimate along its worst axis (rad/s), as the gate
        sees it: ``√λ_max(A_g⁻¹)``, ``A_g = I/σ_bg,prior² + Σ J_gᵀ J_g / θ_tol²`` over the registered
        motions, each registered rotation taken as good as the gate's tolerance ``θ_tol``
        (``gate_tolerance_deg``), not ``rotation_sigma_deg``: on a simulated drone stream one
        registration 0.9° off over 0.1 s moved the estimate by 0.16 rad/s where the estimate's own
        normal matrix claimed 0.009 rad/s, and the gate then rejected every later registration."""
        return math.sqrt(1.0 / float(np.linalg.eigvalsh(self._A_gate)[0]))

    def disagreement(self, t0: float, t1: float, R_reg: np.ndarray) -> tuple[float, float]:
        """``(θ, θ_max)`` (rad): how far a registered LiDAR rotation ``R_reg = R_L(t0)ᵀ R_L(t1)`` is from
        the gyro's over the same interval, and the bound beyond which the registration is rejected.

        ``θ = |Log(ΔR_Lᵀ R_reg)|`` with ``ΔR_L`` from :meth:`rotation` (bias ``b̂_g`` removed). Over
        ``Δt = t1 − t0`` the gyro's rotation error per axis has the variance
        ``σ_θ² = σ_g² Δt + σ_b² Δt² + σ_bg² Δt³ / 3``: the white noise ``σ_g`` (rad/s/√Hz) integrated, the
        bias estimate's error ``σ_b`` (:meth:`bias_sigma`) held over the interval and the bias random
        walk ``σ_bg`` (rad/s²/√Hz) integrated twice. The bound is
        ``θ_max = θ_tol + n_σ √3 σ_θ`` (``θ_tol = gate_tolerance_deg``, the registration's own error;
        ``n_σ = gate_sigmas``; ``√3 σ_θ`` the RMS norm of the 3-axis error).
        """
        dt = max(float(t1 - t0), 0.0)
        R_gyro = self.rotation(t0, t1)
        theta = float(np.linalg.norm(so3_log(np.ascontiguousarray(R_gyro.T @ R_reg))))
        n = self.params.noise
        var = (n.gyroscope_noise_density ** 2 * dt + self.bias_sigma() ** 2 * dt ** 2
               + n.gyroscope_random_walk ** 2 * dt ** 3 / 3.0)
        bound = math.radians(self.params.gate_tolerance_deg) + self.params.gate_sigmas * math.sqrt(3.0 * var)
        return theta, bound

    def update(self, t0: float, t1: float, R_reg: np.ndarray) -> None:
        """Add a registered LiDAR rotation ``R_reg = R_L(t0)ᵀ R_L(t1)`` to the gyro-bias estimate:
        ``Log(ΔR_I(b̂)ᵀ ΔR_reg,I) ≈ J_g (b_g − b̂)`` [Forster2017 Eq. 44], least squares over the
        registered motions with the prior (rotation noise ``rotation_sigma_deg``)."""
        g, a, h = self.samples(t0, t1)
        if h.size == 0:
            return
        pim = preintegrate(g, a, h, np.r_[0.0, 0.0, 0.0, self.bias_g], self.params.noise)
        R_imu = self.R_E.T @ R_reg @ self.R_E
        e = so3_log(np.ascontiguousarray(pim.delta_R.T @ R_imu))
        J = pim.jacobians[0]
        w = 1.0 / math.radians(self.params.rotation_sigma_deg) ** 2
        self._A += w * J.T @ J
        self._A_gate += J.T @ J / math.radians(self.params.gate_tolerance_deg) ** 2
        self._b += w * J.T @ (e + J @ self.bias_g)
        self.bias_g = np.linalg.solve(self._A, self._b)
        self.n_updates += 1


class _BiasPrior(FactorGroup):
    """``r = (b_a, b_g) − b_prior`` on the vector part of variables ``index`` (a unary factor)."""

    def __init__(self, index, prior, information):
        self.variables = np.asarray(index, dtype=np.int64).reshape(-1, 1)
        self.prior = np.asarray(prior, dtype=np.float64).reshape(-1, 6)
        self.information = np.ascontiguousarray(information, dtype=np.float64).reshape(-1, 6, 6)

    def residuals(self, values: Values) -> np.ndarray:
        return values.vectors[self.variables[:, 0], 3:9] - self.prior

    def linearize(self, values: Values) -> tuple:
        J = np.zeros((self.variables.shape[0], 6, 15))
        J[:, :, 9:15] = np.eye(6)
        return self.residuals(values), (J,)


@dataclass(frozen=True)
class InertialResult:
    """Outcome of :func:`optimize_inertial_graph`.

    Attributes
    ----------
    keyframe_poses : (k, 4, 4)
        ``T_map_lidar`` of the keyframes (map = the first keyframe's LiDAR frame).
    velocities : (k, 3)
        IMU velocity at each keyframe (m/s, map frame).
    bias_accel, bias_gyro : (k, 3)
        Accelerometer (m/s²) and gyro (rad/s) bias at each keyframe, IMU axes.
    gravity_map : (3,)
        Gravity in the map frame (m/s²).
    status, reason, iterations, cost_initial, cost_final
        The optimiser's outcome (:class:`minegeo.optim.lm.LMOutcome`); with ``"failed"`` the poses
        are the LiDAR graph's.
    front_end_bias_gyro : (3,)
        The odometry's gyro-bias estimate (rad/s, IMU axes).
    """

    keyframe_poses: np.ndarray
    velocities: np.ndarray
    bias_accel: np.ndarray
    bias_gyro: np.ndarray
    gravity_map: np.ndarray
    status: LMStatus
    reason: str
    iterations: int
    cost_initial: float
    cost_final: float
    front_end_bias_gyro: np.ndarray

    def summary(self, times_s: np.ndarray) -> dict:
        return {"status": self.status, "reason": self.reason, "iterations": int(self.iterations),
                "cost_initial": float(self.cost_initial), "cost_final": float(self.cost_final),
                "gravity_map_m_s2": [float(x) for x in self.gravity_map],
                "front_end_bias_gyro_rad_s": [float(x) for x in self.front_end_bias_gyro],
                "keyframes": [{"time_s": float(t), "velocity_m_s": [float(x) for x in v],
                               "bias_accel_m_s2": [float(x) for x in ba], "bias_gyro_rad_s": [float(x) for x in bg]}
                              for t, v, ba, bg in zip(times_s, self.velocities, self.bias_accel, self.bias_gyro,
                                                      strict=True)],
                "convention": "velocities in the map frame (the first keyframe's LiDAR frame); biases on the IMU "
                              "axes; gyro = omega + b_g, accel = R^T (a - g) + b_a"}


def _up_rotation(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``up`` to ``(0, 0, 1)``."""
    u = up / np.linalg.norm(up)
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(axis), float(u[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(np.ascontiguousarray(axis / s * math.atan2(s, c)))


def _lidar_edges_on_imu(edges, Z, info_rt, E):
    """LiDAR between edges on IMU poses: with ``T_L = T_I E⁻¹``,
    ``T_Li⁻¹ T_Lj = E T_Ii⁻¹ T_Ij E⁻¹``, so ``Z_I = E⁻¹ Z E`` and ``r_L = Ad(E) r_I``,
    ``Ω_I = Ad(E)ᵀ Ω_L Ad(E)`` (``E Exp(ξ) E⁻¹ = Exp(Ad(E) ξ)``)."""
    Ei = invert(E)
    ZI = np.stack([compose(Ei, z, E) for z in Z]) if len(Z) else np.zeros((0, 4, 4))
    A = se3_adjoint(np.ascontiguousarray(E))
    OI = np.einsum("ji,njk,kl->nil", A, np.asarray(info_rt).reshape(-1, 6, 6), A)
    return np.asarray(edges, dtype=np.int64).reshape(-1, 2), ZI, np.ascontiguousarray(0.5 * (OI + OI.transpose(0, 2, 1)))


def _with_floor(info_rt, params: InertialParams) -> np.ndarray:
    """``Ω' = (Ω⁻¹ + Σ_floor)⁻¹`` of each LiDAR edge (rotation first), ``Σ_floor = diag(σ_r² I, σ_t² I)``;
    a singular ``Ω`` through ``Ω (I + Σ_floor Ω)⁻¹`` (the same matrix, no inverse of ``Ω``)."""
    S = np.diag(np.r_[np.full(3, math.radians(params.edge_sigma_deg) ** 2), np.full(3, params.edge_sigma_m ** 2)])
    out = []
    for Om in np.asarray(info_rt, dtype=np.float64).reshape(-1, 6, 6):
        M = Om @ np.linalg.inv(np.eye(6) + S @ Om)
        out.append(0.5 * (M + M.T))
    return np.asarray(out).reshape(-1, 6, 6)


def _velocity(times, positions, t: float, half_s: float = 0.25):
    """Velocity at ``t`` (m/s): the slope of the least-squares line through the positions within
    ``± half_s`` (:func:`minegeo.slam.odometry.start_velocity`; None with fewer than two)."""
    sel = np.abs(times - t) <= half_s
    if sel.sum() < 2:
        return None
    return start_velocity(times[sel], positions[sel])


def _initial_states(aid: GyroAid, kf_times, kf_poses, params: InertialParams, trajectory=None):
    """World rotation ``R_WL0`` from the first keyframe's up axis, the IMU poses in that world,
    velocities by finite differences and biases (0, the front end's gyro bias).

    Over the window ``W = gravity_window_s`` from the first keyframe's time ``t0``, in its axes,
    ``∫ R(t) ã dt = ∫ (a − g) dt = Δv − g W`` (bias neglected), so the up axis is
    ``u ∝ Σ h_k ΔR_0k ã_k − Δv``: each sample rotated into the first keyframe's axes by the gyro (a
    handheld's sway moved the plain mean 2° from the true up) and the velocity change ``Δv`` of the
    LiDAR trajectory (``trajectory = (times, T_map_lidar)``, each velocity a straight-line fit over
    ±0.25 s; the vehicle stream accelerates in its first second: 1° of tilt without it)."""
    imu = aid.imu
    E = imu.T_lidar_imu if imu.T_lidar_imu is not None else np.eye(4)
    t0 = kf_times[0]
    g, a, h = aid.samples(t0, t0 + params.gravity_window_s)
    R = np.eye(3)  # the IMU's rotation from t0 to each sample (the gyro): a sway is taken out of the mean
    up_I = np.zeros(3)
    for w, f, dt in zip(g, a, h, strict=True):
        up_I += dt * (R @ f)
        R = R @ so3_exp(np.ascontiguousarray((w - aid.bias_g) * dt))
    up_L = aid.R_E @ up_I
    if trajectory is not None:
        times, P = np.asarray(trajectory[0], dtype=np.float64), np.asarray(trajectory[1], dtype=np.float64)
        p0 = np.einsum("ij,nj->ni", kf_poses[0][:3, :3].T, P[:, :3, 3] - kf_poses[0][:3, 3])  # first keyframe's axes
        va, vb = _velocity(times, p0, t0), _velocity(times, p0, t0 + float(h.sum()))
        if va is not None and vb is not None:
            up_L = up_L - (vb - va)
    T_WL0 = np.eye(4)
    T_WL0[:3, :3] = _up_rotation(up_L)
    poses = np.stack([compose(T_WL0, T, E) for T in kf_poses])
    p = poses[:, :3, 3]
    v = np.gradient(p, kf_times, axis=0) if len(kf_times) > 1 else np.zeros((1, 3))
    vec = np.zeros((len(kf_times), 9))
    vec[:, :3] = v
    vec[:, 6:9] = aid.bias_g
    return T_WL0, E, np.ascontiguousarray(poses), vec


def _first_prior(T0: np.ndarray, params: InertialParams):
    """Prior on the first IMU pose: position and heading (yaw about world z) fixed (1e10), roll and
    pitch to ``roll_pitch_sigma_deg``; residual ``Log(T_prior⁻¹ T)`` (rotation first, body axes)."""
    n = T0[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # world z in the body axes
    s2 = math.radians(params.roll_pitch_sigma_deg) ** 2
    info = np.zeros((6, 6))
    info[:3, :3] = 1e10 * np.outer(n, n) + (np.eye(3) - np.outer(n, n)) / s2
    info[3:, 3:] = 1e10 * np.eye(3)
    return PriorFactors([0], T0[None], info[None])


def _solve(aid, kf_times, poses, vec, lidar, T_prior, params: InertialParams, lm: LMParams):
    """Preintegrate at the biases of ``vec`` and solve the inertial graph once (the first pose's prior at
    ``T_prior``): the optimiser's outcome."""
    noise = params.noise
    k = len(kf_times)
    pims = []
    for a in range(k - 1):
        g, acc, h = aid.samples(kf_times[a], kf_times[a + 1])
        pims.append((a, a + 1, preintegrate(g, acc, h, vec[a, 3:9], noise)))
    bias_info = np.diag(np.r_[np.full(3, params.accel_bias_sigma ** -2), np.full(3, params.gyro_bias_sigma ** -2)])
    groups = [BetweenFactors(*lidar), ImuFactors(pims),
              BiasRandomWalkFactors([(a, a + 1) for a in range(k - 1)], np.diff(kf_times), noise),
              _first_prior(T_prior, params), _BiasPrior([0], np.zeros((1, 6)), bias_info[None])]
    problem = FactorProblem(k, 15, groups, (), lm, labels=lambda v: (f"keyframe {v}", int(v)),
                            hint="(a keyframe without LiDAR edges and IMU samples?)")
    return levenberg_marquardt(problem, Values(poses, vec), lm)


def optimize_inertial_graph(aid: GyroAid, kf_times, kf_poses, edges, Z, info_rt, params: InertialParams | None = None,
                            lm: LMParams | None = None, trajectory=None) -> InertialResult:
    """The keyframe graph with IMU preintegration factors (module docstring), solved twice (the second
    time preintegrated at the first solution's biases).

    Parameters
    ----------
    aid : GyroAid
        The IMU samples and the front end's gyro bias.
    kf_times : (k,) float
        Keyframe times (s, increasing).
    kf_poses : (k, 4, 4)
        ``T_map_lidar`` of the keyframes (initial values; map = first keyframe's LiDAR frame).
    edges, Z, info_rt : (m, 2) int, (m, 4, 4), (m, 6, 6)
        LiDAR between edges ``Z ≈ T_i⁻¹ T_j`` (LiDAR frame) and their information (rotation first).
    params : InertialParams, optional
    lm : LMParams, optional
    trajectory : (times, (n, 4, 4) T_map_lidar), optional
        Every frame's pose (the odometry), for the velocity change in the first keyframe's gravity
        estimate (:func:`_initial_states`).

    Returns
    -------
    InertialResult
        With ``status == "failed"`` the keyframe poses are ``kf_poses`` unchanged.
    """
    params = params or aid.params
    lm = lm or LMParams()
    kf_times = np.asarray(kf_times, dtype=np.float64)
    T_WL0, E, poses, vec = _initial_states(aid, kf_times, kf_poses, params, trajectory)
    lidar = _lidar_edges_on_imu(edges, Z, _with_floor(info_rt, params), E)
    out = _solve(aid, kf_times, poses, vec, lidar, poses[0], params, lm)
    if out.status != "failed":
        out2 = _solve(aid, kf_times, out.values.poses, out.values.vectors, lidar, poses[0], params, lm)
        out = out2 if out2.status != "failed" else out
    g_map = T_WL0[:3, :3].T @ np.array([0.0, 0.0, -9.80665])
    if out.status == "failed":
        log.warning("LiDAR-inertial graph not solved (%s); the LiDAR graph's poses are kept", out.reason)
        return InertialResult(np.asarray(kf_poses).copy(), vec[:, :3], vec[:, 3:6], vec[:, 6:9], g_map, out.status,
                              out.reason, out.iterations, out.cost_initial, out.cost_initial, aid.bias_g.copy())
    Ei = invert(E)
    T_WL = np.stack([compose(T, Ei) for T in out.values.poses])
    T_map_W = invert(T_WL[0])  # the first keyframe's LiDAR frame stays the map frame
    kf_out = np.stack([compose(T_map_W, T) for T in T_WL])
    v_map = out.values.vectors[:, :3] @ T_map_W[:3, :3].T
    g_map = T_map_W[:3, :3] @ np.array([0.0, 0.0, -9.80665])
    return InertialResult(kf_out, v_map, out.values.vectors[:, 3:6].copy(), out.values.vectors[:, 6:9].copy(), g_map,
                          out.status, out.reason, out.iterations, out.cost_initial, out.cost_final, aid.bias_g.copy())

