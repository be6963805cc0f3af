"""A continuous-time sensor motion: a smooth pose curve with analytic derivatives.

:class:`MotionCurve` is a uniform cubic B-spline (knot spacing ``dt_knot_s``) in six channels:
position ``x, y, z`` (m, world frame, z up) and the Euler angles ``yaw, pitch, roll`` (rad) of

    R(t) = Rz(yaw) Ry(pitch) Rx(roll),      T_world_sensor(t) = [R(t), p(t); 0, 1]

(sensor x forward, y left, z up). On segment ``i`` (``t0 + i dt <= t < t0 + (i+1) dt``, ``u`` the
fraction of the segment) a channel is ``c(t) = sum_k B_k(u) c_{i+k}`` with the uniform cubic basis

    B0 = (1-u)^3/6,  B1 = (3u^3 - 6u^2 + 4)/6,  B2 = (-3u^3 + 3u^2 + 3u + 1)/6,  B3 = u^3/6,

so position, velocity ``v = dp/dt`` and acceleration ``a = d2p/dt2`` are exact polynomials (``a``
continuous, piecewise linear) and the angular rate in the sensor frame is exact too. It is
evaluated as ``c_{i+1} + sum_k B_k (c_{i+k} - c_{i+1})``, so where four control points are equal
(a stop) the pose is bit-for-bit constant and the derivatives exactly zero:

    omega_sensor = [roll' - yaw' sin(pitch),
                    pitch' cos(roll) + yaw' sin(roll) cos(pitch),
                    -pitch' sin(roll) + yaw' cos(roll) cos(pitch)]      (rad/s)

(``R^T dR/dt = [omega]_x`` for the ZYX convention). :func:`curve_from_samples` builds a curve from
sampled channels (control points = the samples, optionally Gaussian-smoothed first). The curve is
the truth of every synthetic sensor stream (:mod:`minegeo.synth.stream`): each LiDAR beam is cast
from ``T_world_sensor(t)`` at its own firing time and the IMU reads ``omega_sensor(t)`` and
``R(t)^T (a(t) - g)`` from the same curve (:mod:`minegeo.synth.imu`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo.errors import InputError
from minegeo.io.types import Trajectory

__all__ = ["MotionCurve", "MotionState", "curve_from_samples", "rot_zyx", "gaussian_smooth"]


def rot_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)``, shape (n, 3, 3) from (n,) angles in rad."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.empty((len(yaw), 3, 3))
    R[:, 0] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], 1)
    R[:, 1] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], 1)
    R[:, 2] = np.stack([-sp, cp * sr, cp * cr], 1)
    return R


def gaussian_smooth(x: np.ndarray, sigma_samples: float) -> np.ndarray:
    """Gaussian moving average along axis 0 (kernel +-4 sigma, ends padded with the end values)."""
    if sigma_samples <= 0:
        return np.array(x, dtype=np.float64, copy=True)
    h = int(np.ceil(4.0 * sigma_samples))
    k = np.exp(-0.5 * (np.arange(-h, h + 1) / sigma_samples) ** 2)
    k /= k.sum()
    x = np.asarray(x, dtype=np.float64)
    xp = np.concatenate([np.repeat(x[:1], h, 0), x, np.repeat(x[-1:], h, 0)])
    if x.ndim == 1:
        return np.convolve(xp, k, mode="valid")
    return np.stack([np.convolve(xp[:, j], k, mode="valid") for j in range(x.shape[1])], 1)


@dataclass(frozen=True)
class MotionState:
    """The sensor's state at times ``t`` (n,): everything in SI units, float64.

    Attributes
    ----------
    t : (n,) s
    R : (n, 3, 3)
        Rotation sensor -> world.
    p, v, a : (n, 3)
        Position (m), velocity (m/s), acceleration (m/s^2) of the sensor origin, world frame.
    omega : (n, 3)
        Angular rate (rad/s) in the sensor frame (``R^T dR/dt = [omega]_x``).
    """

    t: np.ndarray
    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    omega: np.ndarray


@dataclass(frozen=True, eq=False)
class MotionCurve:
    """Uniform cubic B-spline pose curve (see the module docstring).

    Attributes
    ----------
    t0_s : float
        Time of the first knot (s).
    dt_knot_s : float
        Knot spacing (s).
    ctrl : ndarray (m, 6)
        Control points: x, y, z (m), yaw, pitch, roll (rad); m >= 4.
    """

    t0_s: float
    dt_knot_s: float
    ctrl: np.ndarray

    def __post_init__(self):
        c = np.ascontiguousarray(self.ctrl, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 6 or c.shape[0] < 4 or not np.all(np.isfinite(c)):
            raise InputError(f"MotionCurve: need finite control points of shape (m >= 4, 6), got {c.shape}")
        if not (np.isfinite(self.dt_knot_s) and self.dt_knot_s > 0 and np.isfinite(self.t0_s)):
            raise InputError(f"MotionCurve: knot spacing must be > 0, got {self.dt_knot_s}")
        object.__setattr__(self, "ctrl", c)

    @property
    def t_start(self) -> float:
        """First time the curve is defined (s)."""
        return float(self.t0_s)

    @property
    def t_end(self) -> float:
        """Last time the curve is defined (s)."""
        return float(self.t0_s + (self.ctrl.shape[0] - 3) * self.dt_knot_s)

    def channels(self, t, order: int = 2):
        """Channel values and their first ``order`` time derivatives at ``t``.

        Returns
        -------
        list of ndarray (n, 6)
            ``[c, dc/dt, d2c/dt2][:order + 1]``.

        Raises
        ------
        InputError
            A time outside ``[t_start, t_end]`` (1e-9 s tolerance).
        """
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if t.size and (t.min() < self.t_start - 1e-9 or t.max() > self.t_end + 1e-9 or not np.all(np.isfinite(t))):
            raise InputError(f"motion curve: times must lie in [{self.t_start:.6f}, {self.t_end:.6f}] s, "
                             f"got [{t.min():.6f}, {t.max():.6f}]")
        s = (t - self.t0_s) / self.dt_knot_s
        i = np.clip(np.floor(s).astype(np.int64), 0, self.ctrl.shape[0] - 4)
        u = s - i
        C = [self.ctrl[i + k] for k in range(4)]
        u2, u3 = u * u, u * u * u
        bases = [np.stack([(1 - u) ** 3, 3 * u3 - 6 * u2 + 4, -3 * u3 + 3 * u2 + 3 * u + 1, u3], 1) / 6.0]
        if order >= 1:
            bases.append(np.stack([-(1 - u) ** 2, 3 * u2 - 4 * u, -3 * u2 + 2 * u + 1, u2], 1)
                         / (2.0 * self.dt_knot_s))
        if order >= 2:
            bases.append(np.stack([1 - u, 3 * u - 2, 1 - 3 * u, u], 1) / self.dt_knot_s ** 2)
        # sum_k B_k (C_k - C_1) (+ C_1 for the value; the derivative bases sum to 0): where the four
        # control points are equal the differences are exactly 0, so a standing carrier's pose is
        # exactly constant and its velocity, acceleration and angular rate exactly 0
        D = [C[k] - C[1] for k in range(4)]
        out = [sum(B[:, k, None] * D[k] for k in range(4)) for B in bases]
        out[0] = out[0] + C[1]
        return out

    def rotation_position(self, t):
        """``(R (n, 3, 3), p (n, 3))`` of ``T_world_sensor`` at times ``t`` (s)."""
        (c,) = self.channels(t, order=0)
        return rot_zyx(c[:, 3], c[:, 4], c[:, 5]), c[:, :3]

    def state(self, t) -> MotionState:
        """Pose, velocity, acceleration and sensor-frame angular rate at times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        c, d, _dd = self.channels(t, order=2)
        yaw, pitch, roll = c[:, 3], c[:, 4], c[:, 5]
        dy, dp, dr = d[:, 3], d[:, 4], d[:, 5]
        sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
        omega = np.column_stack([dr - dy * sp, dp * cr + dy * sr * cp, -dp * sr + dy * cr * cp])
        return MotionState(t=t, R=rot_zyx(yaw, pitch, roll), p=c[:, :3], v=d[:, :3], a=_dd[:, :3], omega=omega)

    def poses(self, t) -> np.ndarray:
        """``T_world_sensor`` (n, 4, 4) at times ``t``."""
        R, p = self.rotation_position(t)
        T = np.tile(np.eye(4), (len(p), 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        return T

    def trajectory(self, t) -> Trajectory:
        """The curve sampled at times ``t`` as a :class:`~minegeo.io.types.Trajectory` (world <- sensor)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        return Trajectory(times_s=t, poses=self.poses(t), frame="world", body="sensor")


def curve_from_samples(t0_s: float, dt_s: float, xyz: np.ndarray, ypr: np.ndarray,
                       smooth_s: float = 0.0) -> MotionCurve:
    """A :class:`MotionCurve` whose control points are samples of the channels every ``dt_s``.

    Parameters
    ----------
    t0_s, dt_s : float
        Time of the first sample and the sample spacing (s).
    xyz : (m, 3) m
        Positions at ``t0_s + k dt_s``.
    ypr : (m, 3) rad
        Yaw, pitch, roll (unwrapped) at the same times.
    smooth_s : float
        Standard deviation (s) of a Gaussian smoothing applied to the samples first (0: none).

    Returns
    -------
    MotionCurve
        Knot spacing ``dt_s``; the control point ``k`` sits at the sample ``k``, the curve is
        defined on ``[t0_s + dt_s, t0_s + (m - 2) dt_s]`` (the cubic B-spline of uniform samples
        lags none: a sample row's curve value is ``(c_{k-1} + 4 c_k + c_{k+1}) / 6``).
    """
    C = np.column_stack([np.asarray(xyz, np.float64), np.asarray(ypr, np.float64)])
    if smooth_s > 0:
        C = gaussian_smooth(C, smooth_s / dt_s)
    return MotionCurve(t0_s=float(t0_s) + float(dt_s), dt_knot_s=float(dt_s), ctrl=C)
