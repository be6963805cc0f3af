"""The IMU of a drone flight (minegeo.synth.flight.flight_imu) against the flight's own poses.

The reference is the flight's 10 Hz clock poses from ``make_flight`` (the poses the frames are simulated
at), not the IMU's curve: the gyro integrated from one clock pose must reach the rotation of a later one,
and the accelerometer, turned into the world by that integrated rotation and with gravity added back,
double-integrated over a symmetric window must give the clock positions' second difference
``p(t0 + T) - 2 p(t0) + p(t0 - T) = int_0^T (T - s) (a(t0 + s) + a(t0 - s)) ds`` (no velocity needed).
The true biases are removed (``ImuData.bias_*``); the white noise stays.
"""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.synth.flight import CLOCK_HZ, FlightParams, flight_imu, make_flight, write_flight_imu
from minegeo.synth.imu import GRAVITY_MPS2
from minegeo.synth.network import DriftNetwork


def _so3_exp(w):
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


@pytest.fixture(scope="module")
def flight():
    # an L-shaped drift pair: straight flight, a cut corner at (30, 0), straight again
    net = DriftNetwork(np.array([(0, 0), (30, 0), (30, 30)], float), np.array([(0, 1), (1, 2)]),
                       np.full(2, 4.0), np.full(3, 3.6), ("", "", ""), {"kind": "L"})
    return make_flight(net, FlightParams(length_m=60.0, seed=3), route=[0, 1, 2])


def test_flight_imu_integrates_to_the_flight_poses(flight):
    imu = flight_imu(flight)
    t, P = flight.clock.times_s, flight.clock.poses
    dt = imu.t[1] - imu.t[0]
    assert dt == pytest.approx(1 / 200.0)
    gyro = imu.gyro - imu.bias_gyro
    acc = imu.accel - imu.bias_accel
    yaw = np.unwrap(np.arctan2(P[:, 1, 0], P[:, 0, 0]))
    rate = np.abs(np.gradient(yaw, t))
    T_s = 1.0
    h = int(round(T_s * CLOCK_HZ))
    # windows centred where the yaw turns fastest (the corner: 0.6 m of second difference) and on the
    # straight 6 s before it; measured 0.012 / 0.029 deg and 2.1 / 1.2 mm
    corner = int(np.argmax(rate))
    for c, min_turn in ((corner, 0.3), (corner - 60, 0.0)):
        k0, k1 = c - h, c + h
        i0 = int(round((t[k0] - imu.t[0]) / dt))
        i1 = int(round((t[k1] - imu.t[0]) / dt))
        assert abs(imu.t[i0] - t[k0]) < 1e-9 and abs(imu.t[i1] - t[k1]) < 1e-9
        R = [P[k0, :3, :3]]
        for i in range(i0, i1):                            # midpoint rule on the gyro
            R.append(R[-1] @ _so3_exp(0.5 * (gyro[i] + gyro[i + 1]) * dt))
        R = np.array(R)
        dR = R[-1].T @ P[k1, :3, :3]
        ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert ang < 0.06, f"gyro integrated over {2 * T_s} s is {ang:.3f} deg off the flight's rotation"
        a = np.einsum("nij,nj->ni", R, acc[i0:i1 + 1]) + np.array([0.0, 0.0, -GRAVITY_MPS2])
        s = imu.t[i0:i1 + 1] - t[c]
        w = (T_s - np.abs(s))[:, None] * a                   # kernel (T - |s|) over [-T, T]
        second = dt * (w.sum(0) - 0.5 * (w[0] + w[-1]))      # trapezoid rule
        ref = P[k1, :3, 3] - 2 * P[c, :3, 3] + P[k0, :3, 3]
        err = np.linalg.norm(second - ref)
        assert err < 0.01, f"accelerometer double-integrated: second difference {err * 100:.2f} cm off"
        assert np.linalg.norm(ref) >= min_turn                # the corner window does accelerate


def test_flight_imu_is_deterministic_and_written_in_the_contract_form(flight, tmp_path):
    from minegeo.io.imu import read_imu_csv

    a, b = flight_imu(flight), flight_imu(flight)
    assert np.array_equal(a.gyro, b.gyro) and np.array_equal(a.accel, b.accel)
    assert not np.array_equal(flight_imu(flight, seed=5).gyro, a.gyro)
    path = write_flight_imu(tmp_path, flight)
    assert path.read_text().splitlines()[0] == "t,gx,gy,gz,ax,ay,az"
    s = read_imu_csv(path)
    assert np.array_equal(s.t_s, a.t) and np.array_equal(s.gyro_rad_s, a.gyro)
    assert s.t_s[0] <= flight.truth.times_s[0] and s.t_s[-1] >= flight.truth.times_s[-1]
