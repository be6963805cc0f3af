"""A synthetic IMU (gyroscope + accelerometer) read from a :class:`~minegeo.synth.motion.MotionCurve`.

Model (continuous time, the Kalibr / Allan-variance parameterisation; Furgale et al. 2013, the
Kalibr wiki "IMU Noise Model"), sensor axes = the LiDAR's (the IMU sits at the sensor origin):

    gyro(t)  = omega(t) + b_g(t) + n_g(t),              b_g' = w_bg
    accel(t) = R(t)^T (a(t) - g) + b_a(t) + n_a(t),     b_a' = w_ba,      g = (0, 0, -9.80665) m/s^2

``omega`` the sensor-frame angular rate and ``a`` the world-frame acceleration of the curve, so a
unit at rest reads +9.80665 m/s^2 on its up axis (specific force). ``n`` is white noise of density
``gyroscope_noise_density`` (rad/s/sqrt(Hz)) / ``accelerometer_noise_density`` (m/s^2/sqrt(Hz));
``w`` drives a bias random walk of density ``gyroscope_random_walk`` (rad/s^2/sqrt(Hz)) /
``accelerometer_random_walk`` (m/s^3/sqrt(Hz)). Discretised at the sample spacing ``dt``:

    n_d ~ N(0, sigma_n^2 / dt)          (white noise: sigma_d = sigma_c / sqrt(dt))
    b[k+1] = b[k] + sqrt(dt) sigma_b N(0, 1)   (random walk: sigma_d = sigma_c sqrt(dt))

The initial biases are drawn from ``N(0, gyroscope_bias_init^2)`` / ``N(0, accelerometer_bias_init^2)``
per axis. Defaults are those of the ADIS16448 of the EuRoC MAV data set (its Kalibr ``imu.yaml``).
The white noise and the bias walk draw from their own generators (:mod:`minegeo.synth.stream` spawns
them from one ``SeedSequence``), so changing one does not change the other.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from minegeo.errors import InputError

__all__ = ["GRAVITY_MPS2", "ImuParams", "ImuData", "simulate_imu", "imu_csv_text", "imu_truth_csv_text"]

#: standard gravity (m/s^2), along -z of the world (slam_contract.md, "Sensor streams")
GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class ImuParams:
    """IMU rate and noise (Kalibr names and units).

    Attributes
    ----------
    rate_hz : float
        Sample rate (Hz), 100-400 for the presets.
    gyroscope_noise_density : float
        rad/s/sqrt(Hz).
    gyroscope_random_walk : float
        rad/s^2/sqrt(Hz).
    accelerometer_noise_density : float
        m/s^2/sqrt(Hz).
    accelerometer_random_walk : float
        m/s^3/sqrt(Hz).
    gyroscope_bias_init, accelerometer_bias_init : float
        Standard deviation of the initial bias per axis (rad/s, m/s^2).
    """

    rate_hz: float = 200.0
    gyroscope_noise_density: float = 1.6968e-4
    gyroscope_random_walk: float = 1.9393e-5
    accelerometer_noise_density: float = 2.0e-3
    accelerometer_random_walk: float = 3.0e-3
    gyroscope_bias_init: float = 1.0e-3
    accelerometer_bias_init: float = 2.0e-2

    def __post_init__(self):
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InputError(f"IMU rate must be > 0 Hz, got {self.rate_hz}")
        for k, v in asdict(self).items():
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"IMU {k} must be finite and >= 0, got {v}")


@dataclass(frozen=True, eq=False)
class ImuData:
    """Simulated IMU samples (float64, sensor frame).

    Attributes
    ----------
    t : (n,) s
    gyro, accel : (n, 3)
        Measurements: rad/s, m/s^2 (specific force, gravity included), with bias and noise.
    gyro_true, accel_true : (n, 3)
        The same without bias and noise (``omega`` and ``R^T (a - g)`` of the curve).
    bias_gyro, bias_accel : (n, 3)
        The true biases at each sample.
    velocity : (n, 3)
        True world-frame velocity (m/s) of the sensor.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_true: np.ndarray
    accel_true: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    velocity: np.ndarray


def _bias_walk(rng: np.random.Generator, n: int, sigma_init: float, sigma_rw: float, dt: float) -> np.ndarray:
    """Biases (n, 3): ``b[0] ~ N(0, sigma_init^2)``, ``b[k+1] = b[k] + sigma_rw sqrt(dt) N(0, 1)``."""
    steps = rng.standard_normal((n, 3))
    steps[0] *= sigma_init
    steps[1:] *= sigma_rw * np.sqrt(dt)
    return np.cumsum(steps, axis=0)


def simulate_imu(curve, params: ImuParams, t_start: float, t_end: float, noise_rng: np.random.Generator,
                 bias_rng: np.random.Generator) -> ImuData:
    """IMU samples at ``t_start + k / rate_hz`` up to ``t_end`` from ``curve`` (see the module docstring).

    Parameters
    ----------
    curve : MotionCurve
    params : ImuParams
    t_start, t_end : float
        Time span (s); must lie inside the curve's.
    noise_rng, bias_rng : numpy.random.Generator
        White noise (gyro then accelerometer, one (n, 3) draw each) and bias walk (gyro then
        accelerometer).
    """
    dt = 1.0 / params.rate_hz
    n = int(np.floor((t_end - t_start) * params.rate_hz + 1e-9)) + 1
    if n < 2:
        raise InputError(f"IMU span {t_end - t_start:.3f} s holds fewer than 2 samples at {params.rate_hz} Hz")
    t = t_start + np.arange(n) * dt
    s = curve.state(t)
    g = np.array([0.0, 0.0, -GRAVITY_MPS2])
    gyro_true = s.omega
    accel_true = np.einsum("nji,nj->ni", s.R, s.a - g)              # R^T (a - g)
    bg = _bias_walk(bias_rng, n, params.gyroscope_bias_init, params.gyroscope_random_walk, dt)
    ba = _bias_walk(bias_rng, n, params.accelerometer_bias_init, params.accelerometer_random_walk, dt)
    ng = noise_rng.standard_normal((n, 3)) * (params.gyroscope_noise_density / np.sqrt(dt))
    na = noise_rng.standard_normal((n, 3)) * (params.accelerometer_noise_density / np.sqrt(dt))
    return ImuData(t=t, gyro=gyro_true + bg + ng, accel=accel_true + ba + na, gyro_true=gyro_true,
                   accel_true=accel_true, bias_gyro=bg, bias_accel=ba, velocity=s.v)


def _csv(header: str, cols: list) -> str:
    M = np.column_stack(cols)
    return header + "\n" + "\n".join(",".join(f"{x:.17g}" for x in row) for row in M) + "\n"


def imu_csv_text(imu: ImuData) -> str:
    """The measurements as the contract's IMU CSV: ``t,gx,gy,gz,ax,ay,az`` (s, rad/s, m/s^2)."""
    return _csv("t,gx,gy,gz,ax,ay,az", [imu.t, imu.gyro, imu.accel])


def imu_truth_csv_text(imu: ImuData) -> str:
    """Noise- and bias-free readings, the true biases and velocity:
    ``t,gx,gy,gz,ax,ay,az,bgx,bgy,bgz,bax,bay,baz,vx,vy,vz``."""
    return _csv("t,gx,gy,gz,ax,ay,az,bgx,bgy,bgz,bax,bay,baz,vx,vy,vz",
                [imu.t, imu.gyro_true, imu.accel_true, imu.bias_gyro, imu.bias_accel, imu.velocity])
