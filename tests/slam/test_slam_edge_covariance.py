"""The pose graph's edges carry a calibrated covariance: a small Monte Carlo against the simulator's truth.

Reference: the simulator's pose curve (``minegeo.synth.stream``) at the keyframes' frame times, never the
odometry's output. For each edge ``Z = T_i⁻¹ T_j`` with information ``Ω`` (right perturbation, (ω, ρ)
order, as the pose graph uses it), ``e = Log(Z*⁻¹ Z)`` against the true ``Z* = T*_i⁻¹ T*_j``; its
covariance is ``Ω⁻¹`` plus the two keyframes' own pose noise (``Q_j + Ad(Z*⁻¹) Q_i Ad(Z*⁻¹)ᵀ``,
:func:`~minegeo.slam.odometry.keyframe_pose_noise`), and calibrated gives ``E[eᵀ Σ⁻¹ e] = 6`` (χ²(6)). GICP's own Hessian (the floors of
:class:`~minegeo.slam.odometry.OdometryParams` at 0) gives a mean of several hundred to thousands on
these streams (``benchmarks/results/edge_covariance_2026-11-30.json``). The streams here (seeds 31, 32:
not among the fit seeds of the benchmark) are short pieces of a vehicle and a handheld drive without
stops, 10 Hz, 0.2° azimuth step, odometry to the local map, as ``minegeo slam --control`` runs a
sensor stream. The loop floor is checked on direct registrations of keyframes two apart (the
registration a loop closure makes, at a few metres: a revisit of the same place needs a longer drive).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from minegeo.kernels.lie import se3_adjoint, se3_log
from minegeo.registration import build_target_index
from minegeo.slam.loops import LoopCandidate
from minegeo.slam.odometry import (
    EDGE_FLOOR_FIELDS,
    OdometryParams,
    OdometryResult,
    PreparedFrame,
    edge_covariance_floor,
    floored_information,
    keyframe_pose_noise,
    keyframe_rates_deg_s,
    register_frames,
    run_odometry,
)
from minegeo.slam.pipeline import keyframe_graph
from minegeo.synth.flight import NetworkWorld
from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

#: the accepted interval of the mean NEES (χ²(6) has mean 6): a factor 3 either side, for ~15 edges
#: with heavy-tailed errors from two short pieces of stream (GICP's information alone gives > 100).
#: Measured with the defaults: odometry edges 2.2 (vehicle 2.6, handheld 1.2), loop-like edges 4.5;
#: the constants are fitted jointly on 200 s streams, where single edges give 4.1-5.0 (vehicle) and
#: 6.3-11.8 (handheld) and chains of 10-60 edges 5-7 (vehicle): these short straight pieces err less
#: than the streams' turns and stops (benchmarks/results/edge_covariance_2026-11-30b.json)
NEES_INTERVAL = (6.0 / 3.0, 6.0 * 3.0)
P = [3, 4, 5, 0, 1, 2]  # the graph's (t, r) information order → (ω, ρ)


def _edges(preset: str, seed: int, first: int, n: int):
    """``(odometry edges, loop-like edges)``: each ``(e, covariance)`` with the floor of
    :class:`OdometryParams`' defaults (the odometry's from :func:`keyframe_graph`) and the two
    keyframes' own pose noise."""
    st = simulate_stream(StreamParams(preset=preset, duration_s=(first + n) / 10.0 + 0.5, seed=seed))
    ft = st.frame_times[first:first + n]
    sweeps = [(t, P_, tau) for t, P_, tau, _r in iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft,
                                                             st.lidar_seed)]
    truth = st.curve.poses(ft)
    params = OdometryParams(edge_covariance_floor=True, frame_target="submap")
    odo = run_odometry(iter(sweeps), params)
    kf = odo.keyframes
    g = keyframe_graph(odo.poses[kf], odo, [], params)
    rates = keyframe_rates_deg_s(odo.times_s, odo.poses, kf)

    Q = keyframe_pose_noise(rates, params)

    def err(i, j, Z, info):
        """The error and its covariance: the floored edge's plus the keyframes' own noise,
        ``Q_j + Ad(Z*⁻¹) Q_i Ad(Z*⁻¹)ᵀ`` (:func:`keyframe_pose_noise`)."""
        Zt = np.linalg.inv(truth[kf[i]]) @ truth[kf[j]]
        A = se3_adjoint(np.ascontiguousarray(np.linalg.inv(Zt)))
        return se3_log(np.ascontiguousarray(np.linalg.inv(Zt) @ Z)), np.linalg.inv(info) + Q[j] + A @ Q[i] @ A.T

    keep = [m for m in range(len(g.edges)) if np.trace(g.information[m]) > 1e-3]
    chain = [err(*g.edges[m], g.measurements[m], g.information[m][P][:, P]) for m in keep]
    # the chain's errors jointly: Σ = blockdiag(Ω⁻¹) + A Q Aᵀ, A the +I (at j) and −Ad(Z*⁻¹) (at i) blocks
    A = np.zeros((6 * len(keep), 6 * len(kf)))
    S = np.zeros((6 * len(keep), 6 * len(keep)))
    for r, m in enumerate(keep):
        i, j = g.edges[m]
        Zt = np.linalg.inv(truth[kf[i]]) @ truth[kf[j]]
        A[6 * r:6 * r + 6, 6 * j:6 * j + 6] = np.eye(6)
        A[6 * r:6 * r + 6, 6 * i:6 * i + 6] = -se3_adjoint(np.ascontiguousarray(np.linalg.inv(Zt)))
        S[6 * r:6 * r + 6, 6 * r:6 * r + 6] = np.linalg.inv(g.information[m][P][:, P])
    Qd = np.zeros((6 * len(kf), 6 * len(kf)))
    for k in range(len(kf)):
        Qd[6 * k:6 * k + 6, 6 * k:6 * k + 6] = Q[k]
    joint = (np.concatenate([e for e, _ in chain]), S + A @ Qd @ A.T)
    frames = []
    for k in range(len(kf)):
        index = build_target_index(odo.keyframe_clouds[k])
        frames.append(PreparedFrame(float(odo.times_s[kf[k]]), index.data, odo.keyframe_covariances[k], index))
    loops = []
    for i in range(len(kf) - 2):
        j = i + 2
        guess = np.linalg.solve(odo.poses[kf[i]], odo.poses[kf[j]])
        reg = register_frames(frames[j], frames[i], guess, params, trusted_init=True)
        if not reg.ok:
            continue
        cand = LoopCandidate(i, j, 0.0, reg.fitness, reg.rmse_m, True, "", reg.T, reg.information)
        info = keyframe_graph(odo.poses[kf], odo, [cand], params).information[-1][P][:, P]
        F = edge_covariance_floor(0.0, 0.0, params, rates_deg_s=(rates[i], rates[j]), loop=True)
        np.testing.assert_allclose(info, floored_information(0.5 * (reg.information + reg.information.T), F),
                                   rtol=1e-9, atol=1e-9)
        loops.append(err(i, j, reg.T, info))
    return chain, loops, joint


@pytest.fixture(scope="module")
def edges():
    v, h = _edges("vehicle", 31, 30, 90), _edges("handheld", 32, 30, 90)
    return v[0] + h[0], v[1] + h[1], (v[2], h[2])


def test_odometry_edge_nees_is_near_six(edges):
    nees = np.array([e @ np.linalg.solve(C, e) for e, C in edges[0]])
    # measured (floors of OdometryParams' defaults): see the comment of NEES_INTERVAL
    assert len(nees) >= 8
    assert NEES_INTERVAL[0] <= nees.mean() <= NEES_INTERVAL[1], (nees.mean(), np.round(nees, 1))


def test_loop_edge_nees_is_near_six(edges):
    nees = np.array([e @ np.linalg.solve(C, e) for e, C in edges[1]])
    assert len(nees) >= 8
    assert NEES_INTERVAL[0] <= nees.mean() <= NEES_INTERVAL[1], (nees.mean(), np.round(nees, 1))


def test_turn_and_loop_terms_by_hand():
    p = OdometryParams(edge_sigma_tilt_deg_per_sqrt_m=0.2, edge_sigma_tilt_deg_per_deg=0.1,
                       edge_sigma_yaw_deg_per_sqrt_m=0.05, edge_sigma_trans_xy_m_per_sqrt_m=0.004,
                       edge_sigma_trans_z_m_per_sqrt_m=0.01, edge_sigma_trans_z_m_per_deg=0.002,
                       edge_sigma_tilt_deg_per_deg_s=0.01, edge_sigma_yaw_deg_per_deg_s=0.02,
                       edge_sigma_trans_xy_m_per_deg_s=0.001, edge_sigma_trans_z_m_per_deg_s=0.0005,
                       loop_sigma_tilt_deg=0.3, loop_sigma_yaw_deg=0.1, loop_sigma_trans_xy_m=0.02,
                       loop_sigma_trans_z_m=0.03)
    d2r = math.radians(1.0) ** 2
    W = 30.0**2 + 40.0**2  # rates 30 and 40 deg/s at the two keyframes: W = 2500 (deg/s)²
    F = edge_covariance_floor(2.0, 5.0, p, rates_deg_s=(30.0, 40.0))
    tilt = 0.2**2 * 2 + (0.1 * 5) ** 2 + 0.01**2 * W  # 0.08 + 0.25 + 0.25 deg²
    yaw = 0.05**2 * 2 + 0.02**2 * W  # 0.005 + 1.0 deg²
    xy = 0.004**2 * 2 + 0.001**2 * W
    z = 0.01**2 * 2 + (0.002 * 5) ** 2 + 0.0005**2 * W
    np.testing.assert_allclose(np.diag(F), [d2r * tilt, d2r * tilt, d2r * yaw, xy, xy, z], rtol=1e-12)
    # a loop: length and angle play no part (a loop at 180 deg is as good as one at 0 deg)
    G = edge_covariance_floor(0.5, 180.0, p, rates_deg_s=(30.0, 40.0), loop=True)
    np.testing.assert_allclose(np.diag(G), [d2r * (0.09 + 0.25), d2r * (0.09 + 0.25), d2r * (0.01 + 1.0),
                                            0.0004 + 0.0025, 0.0004 + 0.0025, 0.0009 + 0.000625], rtol=1e-12)
    assert np.array_equal(G, edge_covariance_floor(0.0, 0.0, p, rates_deg_s=(30.0, 40.0), loop=True))
    assert np.count_nonzero(G - np.diag(np.diag(G))) == 0


def test_keyframe_rates_of_a_constant_turn():
    """Reference: a pose curve turning at 25 deg/s about z (and 5 deg/s about x) by construction."""
    t = np.arange(12) * 0.1
    poses = np.tile(np.eye(4), (12, 1, 1))
    for k, tk in enumerate(t):
        a, b = math.radians(25.0 * tk), math.radians(5.0 * tk)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        Rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        poses[k, :3, :3] = Rz @ Rx
        poses[k, :3, 3] = [2.0 * tk, 0.0, 0.0]
    r = keyframe_rates_deg_s(t, poses, np.array([0, 5, 11]))
    # the angle of R(t)ᵀ R(t + 0.2) of a rotation Rz(ωz t) Rx(ωx t), over 0.2 s, by scipy's rotation vector
    from scipy.spatial.transform import Rotation

    def ref(f0, f1):
        R = poses[f0, :3, :3].T @ poses[f1, :3, :3]
        return np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())) / (t[f1] - t[f0])

    np.testing.assert_allclose(r, [ref(0, 1), ref(4, 6), ref(10, 11)], rtol=1e-9)
    assert 24.0 < r[1] < 26.0
    assert np.array_equal(keyframe_rates_deg_s(t[:1], poses[:1], np.array([0])), [0.0])


def test_keyframe_graph_floors_every_edge_only_when_asked():
    """The graph's information: GICP's as given without the flag; with it, each odometry edge floored
    by its own translation and rotation, a loop edge by the loop floor, both with the keyframes' rates."""
    rng = np.random.default_rng(3)
    t = np.arange(4) * 0.1
    poses = np.tile(np.eye(4), (4, 1, 1))
    for k in range(4):
        a = math.radians(20.0 * t[k])
        poses[k, :2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
        poses[k, :3, 3] = [1.5 * k, 0.1 * k, 0.0]
    kf = np.array([0, 2, 3])
    Z = np.stack([np.linalg.solve(poses[kf[a]], poses[kf[a + 1]]) for a in range(2)])
    infos = []
    for _ in range(3):
        A = rng.standard_normal((6, 6))
        infos.append(A @ A.T * 1e4 + 1e3 * np.eye(6))
    odo = OdometryResult(t, poses, np.ones(4, bool), [""] * 4, [""] * 4, np.ones(4), kf, Z, np.stack(infos[:2]))
    loop = LoopCandidate(0, 2, 0.1, 0.9, 0.02, True, "", np.linalg.solve(poses[0], poses[3]), infos[2])
    rejected = replace(loop, accepted=False, j=1)
    p = OdometryParams(edge_covariance_floor=True)
    g = keyframe_graph(poses[kf], odo, [rejected, loop], p)
    assert g.edges.tolist() == [[0, 1], [1, 2], [0, 2]]
    rates = keyframe_rates_deg_s(t, poses, kf)
    for m, (Zm, I) in enumerate(zip([Z[0], Z[1], loop.T_i_j], infos, strict=True)):
        i, j = g.edges[m]
        ang = np.degrees(np.linalg.norm(se3_log(np.ascontiguousarray(Zm))[:3]))
        F = edge_covariance_floor(np.linalg.norm(Zm[:3, 3]), ang, p, rates_deg_s=(rates[i], rates[j]), loop=m == 2)
        np.testing.assert_allclose(g.information[m][P][:, P], np.linalg.inv(np.linalg.inv(I) + F), rtol=1e-8)
    raw = keyframe_graph(poses[kf], odo, [loop], replace(p, edge_covariance_floor=False))
    for m, I in enumerate(infos):
        assert np.array_equal(raw.information[m][P][:, P], I)
    zero = keyframe_graph(poses[kf], odo, [loop], replace(p, **dict.fromkeys(EDGE_FLOOR_FIELDS, 0.0)))
    for m, I in enumerate(infos):
        np.testing.assert_allclose(zero.information[m][P][:, P], I, rtol=1e-12)


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
