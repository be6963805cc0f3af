"""The odometry's keyframe edges carry a calibrated covariance: a small Monte Carlo against the simulator's truth.

Reference: the simulator's pose curve (``minegeo.synth.stream``) at the keyframes' frame times, never the
odometry's output. For each keyframe edge ``Z = T_i⁻¹ T_j`` with information ``Ω`` (right perturbation,
(ω, ρ) order, as the pose graph uses it), ``e = Log(Z*⁻¹ Z)`` against the true ``Z* = T*_i⁻¹ T*_j``; a
calibrated ``Ω`` gives ``E[eᵀ Ω e] = 6`` (χ²(6)). GICP's own Hessian (the floors of
:class:`~minegeo.slam.odometry.OdometryParams` at 0) gives a mean of several hundred on these streams
(``benchmarks/results/edge_covariance_2026-11-29.json``). The streams here (seeds 31, 32: not among the
fit seeds 1-8 of the benchmark) are short pieces of a vehicle and a handheld drive without stops, 5 Hz,
0.4° azimuth step.
"""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.kernels.lie import se3_log
from minegeo.slam.odometry import OdometryParams, edge_covariance_floor, floored_information, run_odometry
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

#: the accepted interval of the mean NEES (χ²(6) has mean 6): a factor 2.5 either side, for ~15 edges
#: with heavy-tailed errors (the uncalibrated mean is > 100)
NEES_INTERVAL = (6.0 / 2.5, 6.0 * 2.5)


def _edges(preset: str, seed: int, first: int, n: int):
    st = simulate_stream(StreamParams(preset=preset, duration_s=(first + n) / 5.0 + 0.5, lidar_hz=5.0,
                                      azimuth_step_deg=0.4, seed=seed))
    ft = st.frame_times[first:first + n]
    sweeps = [(t, P, tau) for t, P, tau, _r in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                            st.lidar_seed)]
    truth = st.curve.poses(ft)
    odo = run_odometry(iter(sweeps), OdometryParams(edge_covariance_floor=True))
    out = []
    for a in range(len(odo.keyframes) - 1):
        i, j = odo.keyframes[a], odo.keyframes[a + 1]
        Zt = np.linalg.inv(truth[i]) @ truth[j]
        e = se3_log(np.ascontiguousarray(np.linalg.inv(Zt) @ odo.keyframe_edges[a]))
        out.append((e, odo.keyframe_information[a]))
    return out


@pytest.fixture(scope="module")
def edges():
    return _edges("vehicle", 31, 15, 45) + _edges("handheld", 32, 15, 45)


def test_keyframe_edge_nees_is_near_six(edges):
    nees = np.array([e @ info @ e for e, info in edges])
    # measured (floors of OdometryParams' defaults): see the comment of NEES_INTERVAL
    assert len(nees) >= 8
    assert NEES_INTERVAL[0] <= nees.mean() <= NEES_INTERVAL[1], (nees.mean(), np.round(nees, 1))


def test_floored_information_is_the_inverse_of_the_summed_covariance():
    # reference: the explicit inverse of Ω⁻¹ + F on a well-conditioned Ω
    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 6))
    omega = A @ A.T + 6 * np.eye(6)
    p = OdometryParams(edge_sigma_tilt_deg_per_sqrt_m=0.2, edge_sigma_tilt_deg_per_deg=0.1,
                       edge_sigma_yaw_deg_per_sqrt_m=0.05, edge_sigma_trans_xy_m_per_sqrt_m=0.004,
                       edge_sigma_trans_z_m_per_sqrt_m=0.01, edge_sigma_trans_z_m_per_deg=0.002)
    F = edge_covariance_floor(2.0, 5.0, p)  # 2 m and 5 deg, by hand (deg² → rad² for the rotation):
    tilt, yaw = 0.2**2 * 2 + (0.1 * 5) ** 2, 0.05**2 * 2  # 0.33, 0.005 deg²
    np.testing.assert_allclose(np.diag(F), np.r_[np.radians(1.0) ** 2 * np.array([tilt, tilt, yaw]),
                                                 0.004**2 * 2, 0.004**2 * 2, 0.01**2 * 2 + (0.002 * 5) ** 2])
    np.testing.assert_allclose(floored_information(omega, F), np.linalg.inv(np.linalg.inv(omega) + F), rtol=1e-10)
    # a direction GICP does not observe (Ω singular) stays unobserved, the others are floored
    omega0 = np.diag([1e6, 1e6, 1e6, 1e6, 1e6, 0.0])
    got = floored_information(omega0, F)
    assert got[5, 5] == 0.0 and np.all(np.diag(got)[:5] < 1 / np.diag(F)[:5])
