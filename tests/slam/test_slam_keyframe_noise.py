"""A keyframe's own pose noise (minegeo.slam.odometry.keyframe_pose_noise) in the control adjustment:
the formula by hand, the noise carried to a station point, and a Monte Carlo of graphs whose keyframes
err by a noise of their own (``x_k = y_k Exp(n_k)``) besides the edges' error."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from _control_common import CHI2_2_95, CRS, OFFSET, stations, truth

from minegeo.kernels.lie import se3_exp, se3_inverse
from minegeo.slam.control import (
    ControlParams,
    apply_control,
    graph_pose_noise,
    slam_pose_noise,
    station_point_noise,
)
from minegeo.slam.odometry import KEYFRAME_NOISE_FIELDS, OdometryParams, keyframe_pose_noise
from minegeo.slam.pipeline import SlamParams


def test_keyframe_pose_noise_by_hand():
    p = replace(OdometryParams(), keyframe_sigma_tilt_deg=0.02, keyframe_sigma_yaw_deg=0.01, keyframe_sigma_trans_xy_m=0.003,
                keyframe_sigma_trans_z_m=0.004, keyframe_sigma_tilt_deg_per_deg_s=0.002,
                keyframe_sigma_yaw_deg_per_deg_s=0.001, keyframe_sigma_trans_xy_m_per_deg_s=0.0005,
                keyframe_sigma_trans_z_m_per_deg_s=0.0002)
    Q = keyframe_pose_noise([0.0, 30.0], p)
    r = math.pi / 180.0
    np.testing.assert_allclose(np.diag(Q[0]), [(0.02 * r) ** 2] * 2 + [(0.01 * r) ** 2, 0.003**2, 0.003**2, 0.004**2],
                               rtol=1e-14)
    tilt, yaw = (0.02**2 + (0.002 * 30) ** 2) * r * r, (0.01**2 + (0.001 * 30) ** 2) * r * r
    np.testing.assert_allclose(np.diag(Q[1]), [tilt, tilt, yaw, 0.003**2 + 0.015**2, 0.003**2 + 0.015**2,
                                               0.004**2 + 0.006**2], rtol=1e-14)
    assert np.count_nonzero(Q - np.stack([np.diag(np.diag(q)) for q in Q])) == 0


def test_station_point_noise_is_the_covariance_of_the_lever_arm_point():
    """``J Q Jᵀ`` against the sample covariance of ``p = T Exp(n) · offset`` for n ~ N(0, Q)."""
    rng = np.random.default_rng(5)
    T = se3_exp(np.array([0.3, -0.2, 1.1, 5.0, 2.0, 1.0]))
    Q = np.diag([4e-4, 9e-4, 1e-4, 1e-4, 4e-4, 9e-4])
    n = rng.multivariate_normal(np.zeros(6), Q, size=200_000)
    pts = np.stack([(T @ se3_exp(d))[:3, :3] @ OFFSET + (T @ se3_exp(d))[:3, 3] for d in n[:20_000]])
    C = station_point_noise(T[None], OFFSET, Q[None])[0]
    np.testing.assert_allclose(np.cov(pts.T), C, rtol=0.05, atol=2e-6)


def test_graph_pose_noise_on_keyframes_and_between():
    t = np.array([0.0, 1.0, 2.0])
    Q = np.stack([np.diag(np.full(6, v)) for v in (1.0, 3.0, 2.0)])
    G = graph_pose_noise(t, Q, np.array([0.0, 0.5, 1.0, 1.7, 2.0]))
    np.testing.assert_array_equal(np.diagonal(G, axis1=1, axis2=2)[:, 0], [1.0, 3.0, 3.0, 3.0, 2.0])


def test_slam_pose_noise_only_with_the_floor():
    times = np.arange(5) * 0.1
    poses = np.stack([se3_exp(np.array([0.0, 0.0, 0.1 * k, k, 0.0, 0.0])) for k in range(5)])
    on = replace(OdometryParams(edge_covariance_floor=True), **{**dict.fromkeys(KEYFRAME_NOISE_FIELDS, 0.0),
                 "keyframe_sigma_trans_xy_m": 0.004, "keyframe_sigma_yaw_deg_per_deg_s": 0.01})
    res = SimpleNamespace(times_s=times, poses=poses, params=SlamParams(odometry=on))
    Q = slam_pose_noise(res, np.array([0.2]))
    rate = math.degrees(0.2) / 0.2  # 0.1 rad per frame, frames on either side
    np.testing.assert_allclose(Q[0, 3, 3], 0.004**2, rtol=1e-12)
    np.testing.assert_allclose(Q[0, 2, 2], math.radians(0.01 * rate) ** 2, rtol=1e-9)
    assert slam_pose_noise(SimpleNamespace(times_s=times, poses=poses, params=SlamParams()), np.array([0.2])) is None


SIG_W = np.r_[np.full(3, 1e-4), np.full(3, 0.002)]  # the edges' accumulating error (rad, m)
SIG_N = np.r_[np.full(2, 1.5e-3), 2e-4, np.full(2, 0.02), 0.015]  # each keyframe's own error (rad, m)


def _graph_with_keyframe_noise(T, rng):
    """Keyframe poses ``x_k = y_k Exp(n_k)`` (``y`` the truth), chain edges ``Z = x_k⁻¹ x_{k+1} Exp(w)``
    with the information of ``w`` alone; the poses chained from the first."""
    k = T.shape[0]
    x = np.stack([T[a] @ se3_exp(rng.standard_normal(6) * SIG_N) for a in range(k)])
    Z = np.stack([se3_inverse(x[a]) @ x[a + 1] @ se3_exp(rng.standard_normal(6) * SIG_W) for a in range(k - 1)])
    P = np.tile(np.eye(4), (k, 1, 1))
    for e in range(k - 1):
        P[e + 1] = P[e] @ Z[e]
    return np.c_[np.arange(k - 1), np.arange(1, k)], Z, np.tile(np.diag(SIG_W**-2.0), (k - 1, 1, 1)), P


def test_keyframe_noise_calibrates_check_ellipses_and_sigma0():
    """60 graphs whose keyframes err by their own noise (2 cm, 0.09° tilt) far beyond the edges' (2 mm):
    with ``pose_noise`` the check stations' 95 % ellipses cover 95 % (240 cases, within 3.5 binomial sd)
    and the pooled σ̂0 is 1 (within 3.5 sd of its χ² spread); without it the control factors are
    too tight (σ̂0 far above 1) and the ellipses cover a minority."""
    t, T = truth(n=61)
    times = np.array([0.0, 8.0, 16.0, 30.0, 38.0, 46.0, 60.0])  # on keyframes
    roles = ["control", "check", "check", "control", "check", "check", "control"]
    Q = np.tile(np.diag(SIG_N**2), (t.size, 1, 1))
    out = {}
    for name, noise in (("with", Q), ("without", None)):
        inside = total = 0
        stat = dof = 0.0
        for r in range(60):
            rng = np.random.default_rng([11, r])
            edges, Z, info, P = _graph_with_keyframe_noise(T, rng)
            st, true = stations(t, T, times, roles, rng, OFFSET)
            res = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(mode="graph", snooping=False),
                                noise)
            chk = st.is_check
            e = (res.station_enh_local - true)[chk][:, :2]
            C = res.station_cov_enh[chk][:, :2, :2]
            inside += int((np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e) <= CHI2_2_95).sum())
            total += e.shape[0]
            stat += res.global_chi2.statistic
            dof += res.global_chi2.dof
        out[name] = (inside / total, total, stat, dof)
    cov, total, stat, dof = out["with"]
    assert abs(cov - 0.95) <= 3.5 * np.sqrt(0.95 * 0.05 / total), f"coverage {cov:.3f} of {total}"
    assert abs(stat / dof - 1.0) <= 3.5 * np.sqrt(2.0 / dof), f"sigma0² {stat / dof:.3f} on {dof:.0f}"
    assert out["without"][0] < 0.7, out["without"]
    assert out["without"][2] / out["without"][3] > 2.5, out["without"]


SIG_LOOP = np.r_[np.full(3, 3e-4), np.full(3, 0.003)]  # a loop edge's own error (rad, m)


def _graph_with_loops(T, rng, loops):
    """Chain and loop edges of keyframes ``x_k = y_k Exp(n_k)``: ``y`` the chain drifting by the edges'
    accumulating error ``w`` (``y_{k+1} = y_k T_k⁻¹ T_{k+1} Exp(w_k)``), so a chain edge is ``x_k⁻¹ x_{k+1}``;
    a loop ``(i, j)`` measures the truth with the two keyframes' own noise and an error of its own,
    ``Exp(−n_i) T_i⁻¹ T_j Exp(n_j) Exp(w_ij)`` (information of ``w`` alone); the poses chained from the first."""
    k = T.shape[0]
    y = [T[0]]
    for e in range(k - 1):
        y.append(y[-1] @ se3_inverse(T[e]) @ T[e + 1] @ se3_exp(rng.standard_normal(6) * SIG_W))
    En = [se3_exp(rng.standard_normal(6) * SIG_N) for _ in range(k)]
    x = np.stack([y[a] @ En[a] for a in range(k)])
    Zc = np.stack([se3_inverse(x[a]) @ x[a + 1] for a in range(k - 1)])
    Zl = np.stack([se3_inverse(En[i]) @ se3_inverse(T[i]) @ T[j] @ En[j] @ se3_exp(rng.standard_normal(6) * SIG_LOOP)
                   for i, j in loops])
    P = np.tile(np.eye(4), (k, 1, 1))
    for e in range(k - 1):
        P[e + 1] = P[e] @ Zc[e]
    edges = np.r_[np.c_[np.arange(k - 1), np.arange(1, k)], np.asarray(loops)]
    info = np.r_[np.tile(np.diag(SIG_W**-2.0), (k - 1, 1, 1)), np.tile(np.diag(SIG_LOOP**-2.0), (len(loops), 1, 1))]
    return edges, np.r_[Zc, Zl], info, P


def test_keyframe_noise_calibrates_check_ellipses_in_a_graph_with_loops():
    """As above with loop edges between keyframes 20 apart (each measures the truth of its two keyframes
    with their own noise and a loop error of its own, the model ``minegeo slam`` fits): the loops hold
    the chain's drift, so the check errors are mostly the keyframes' own and the control survey's.
    With ``pose_noise`` the 95 % ellipses cover 95 % (240 cases, within 3.5 binomial sd); without it
    far fewer."""
    t, T = truth(n=61)
    times = np.array([0.0, 8.0, 16.0, 30.0, 38.0, 46.0, 60.0])
    roles = ["control", "check", "check", "control", "check", "check", "control"]
    loops = [(a, a + 20) for a in range(0, 41, 2)]
    Q = np.tile(np.diag(SIG_N**2), (t.size, 1, 1))
    out = {}
    for name, noise in (("with", Q), ("without", None)):
        inside = total = 0
        for r in range(60):
            rng = np.random.default_rng([12, r])
            edges, Z, info, P = _graph_with_loops(T, rng, loops)
            st, true = stations(t, T, times, roles, rng, OFFSET)
            res = apply_control(t, P, edges, Z, info, st, OFFSET, CRS, ControlParams(mode="graph", snooping=False),
                                noise)
            e = (res.station_enh_local - true)[st.is_check][:, :2]
            C = res.station_cov_enh[st.is_check][:, :2, :2]
            inside += int((np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e) <= CHI2_2_95).sum())
            total += e.shape[0]
        out[name] = (inside / total, total)
    cov, total = out["with"]
    assert abs(cov - 0.95) <= 3.5 * np.sqrt(0.95 * 0.05 / total), f"coverage {cov:.3f} of {total}"
    assert out["without"][0] < 0.7, out["without"]
