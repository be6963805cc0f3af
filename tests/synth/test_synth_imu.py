"""The synthetic IMU against independent references (minegeo.synth.imu, minegeo.synth.motion).

* the curve's velocity, acceleration and angular rate equal finite differences of its poses;
* integrating the noise-free IMU with a naive trapezoid strapdown twin written here reproduces the
  curve's orientation, velocity and position over 4 s of the most dynamic preset (drone);
* the white noise's sample std at rate f is density * sqrt(f) (Allan: sigma(tau) = N / sqrt(tau)),
  the bias increments have std random_walk * sqrt(dt).
"""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.synth.imu import ImuParams, simulate_imu
from minegeo.synth.stream import stream_motion, stream_network

G = np.array([0.0, 0.0, -9.80665])
QUIET = ImuParams(rate_hz=400.0, gyroscope_noise_density=0.0, gyroscope_random_walk=0.0,
                  accelerometer_noise_density=0.0, accelerometer_random_walk=0.0, gyroscope_bias_init=0.0,
                  accelerometer_bias_init=0.0)


@pytest.fixture(scope="module")
def drone_curve():
    net = stream_network("loop", None, 0.0, 0)
    return stream_motion(net, "drone", 12.0, np.random.default_rng(3))


def _expm_so3(w):
    """Rodrigues' formula, written here as the twin's own rotation update."""
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def _log_so3(R):
    c = np.clip((np.trace(R) - 1) / 2, -1, 1)
    th = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v / 2 if th < 1e-9 else th / (2 * np.sin(th)) * v


def test_curve_derivatives_match_finite_differences(drone_curve):
    c = drone_curve
    t = np.linspace(2.0, 10.0, 37)
    h = 1e-4
    s = c.state(t)
    Rm, pm = c.rotation_position(t - h)
    Rp, pp = c.rotation_position(t + h)
    _, p0 = c.rotation_position(t)
    v_fd = (pp - pm) / (2 * h)
    a_fd = (pp - 2 * p0 + pm) / h**2
    w_fd = np.array([_log_so3(Rm[i].T @ Rp[i]) / (2 * h) for i in range(len(t))])
    assert np.abs(s.v - v_fd).max() < 1e-6
    assert np.abs(s.a - a_fd).max() < 1e-3            # h^2 rounding of the second difference
    assert np.abs(s.omega - w_fd).max() < 1e-6
    assert np.linalg.norm(s.v, axis=1).max() > 2.0 and np.degrees(np.linalg.norm(s.omega, axis=1)).max() > 10.0


def test_noise_free_imu_integrates_to_the_curve(drone_curve):
    """Strapdown twin: R' = R [w]x, v' = R f + g, p' = v (trapezoid at 400 Hz), from the curve's pose
    at 3 s and a finite-difference velocity; after 4 s it must sit on the curve."""
    c = drone_curve
    t0, t1 = 3.0, 7.0
    imu = simulate_imu(c, QUIET, t0, t1, np.random.default_rng(0), np.random.default_rng(1))
    assert np.array_equal(imu.gyro, imu.gyro_true) and np.array_equal(imu.accel, imu.accel_true)
    R0, p0 = c.rotation_position([t0])
    _, pa = c.rotation_position([t0 - 1e-5])
    _, pb = c.rotation_position([t0 + 1e-5])
    R, p, v = R0[0].copy(), p0[0].copy(), (pb[0] - pa[0]) / 2e-5
    dt = 1.0 / QUIET.rate_hz
    for k in range(len(imu.t) - 1):
        R1 = R @ _expm_so3(0.5 * (imu.gyro[k] + imu.gyro[k + 1]) * dt)
        v1 = v + 0.5 * (R @ imu.accel[k] + R1 @ imu.accel[k + 1]) * dt + G * dt
        p = p + 0.5 * (v + v1) * dt
        R, v = R1, v1
    Rt, pt = c.rotation_position([imu.t[-1]])
    st = c.state([imu.t[-1]])
    travelled = np.linalg.norm(pt[0] - p0[0])
    rot_err = np.degrees(np.linalg.norm(_log_so3(Rt[0].T @ R)))
    assert travelled > 8.0                                # a real flight segment, not a hover
    # measured: 4.5e-6 deg, 3.4e-7 m/s, 1.4e-6 m at 400 Hz (x16 at 100 Hz: the twin's O(dt^2) error)
    assert rot_err < 5e-5, rot_err
    assert np.linalg.norm(v - st.v[0]) < 5e-6, np.linalg.norm(v - st.v[0])
    assert np.linalg.norm(p - pt[0]) < 2e-5, np.linalg.norm(p - pt[0])


def test_at_rest_reads_gravity_on_the_up_axis():
    from minegeo.synth.motion import curve_from_samples

    n = 50
    c = curve_from_samples(0.0, 0.01, np.zeros((n, 3)), np.zeros((n, 3)))
    imu = simulate_imu(c, QUIET, c.t_start, c.t_end, np.random.default_rng(0), np.random.default_rng(1))
    assert np.allclose(imu.accel, [0.0, 0.0, 9.80665], atol=1e-12) and np.allclose(imu.gyro, 0.0, atol=1e-12)


@pytest.mark.parametrize("rate_hz", [100.0, 400.0])
def test_white_noise_std_is_density_sqrt_rate(drone_curve, rate_hz):
    p = ImuParams(rate_hz=rate_hz)
    imu = simulate_imu(drone_curve, p, 0.5, 11.5, np.random.default_rng([7, int(rate_hz)]),
                       np.random.default_rng([8, int(rate_hz)]))
    ng = imu.gyro - imu.gyro_true - imu.bias_gyro
    na = imu.accel - imu.accel_true - imu.bias_accel
    n = ng.size                                              # 3 axes x (11 s x rate) samples
    tol = 4.0 / np.sqrt(2 * n)                               # 4 sigma of a sample std's relative error
    assert abs(ng.std() / (p.gyroscope_noise_density * np.sqrt(rate_hz)) - 1) < tol
    assert abs(na.std() / (p.accelerometer_noise_density * np.sqrt(rate_hz)) - 1) < tol
    dbg, dba = np.diff(imu.bias_gyro, axis=0), np.diff(imu.bias_accel, axis=0)
    assert abs(dbg.std() / (p.gyroscope_random_walk / np.sqrt(rate_hz)) - 1) < tol
    assert abs(dba.std() / (p.accelerometer_random_walk / np.sqrt(rate_hz)) - 1) < tol
    # Allan deviation of the measured accelerometer (truth removed, bias kept) at tau = 0.05 s:
    # N / sqrt(tau) (white noise); the bias walk adds K sqrt(tau / 3), 0.01 % of it here
    m = int(round(0.05 * rate_hz))
    y = (imu.accel - imu.accel_true)[: (len(imu.t) // m) * m].reshape(-1, m, 3).mean(1)
    adev = np.sqrt(0.5 * np.mean(np.diff(y, axis=0) ** 2))
    n_clusters = 3 * (len(y) - 1)
    assert abs(adev / (p.accelerometer_noise_density / np.sqrt(0.05)) - 1) < 4.0 / np.sqrt(2 * n_clusters)
