"""IMU preintegration and the IMU factor [Forster2017]: GTSAM 4.3 as the oracle (its Manifold
preintegration is Forster's), a closed form for constant rates, finite differences for the
Jacobians, and a small solve that recovers velocity and biases."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_oracle
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo.errors import InputError
from minegeo.geometry.se3 import exp_so3, hat, se3_exp
from minegeo.optim import FactorProblem, LMParams, PriorFactors, Values, levenberg_marquardt
from minegeo.optim.imu import (
    GRAVITY_M_S2,
    BiasRandomWalkFactors,
    ImuFactors,
    ImuNoise,
    Preintegrated,
    gravity_vector,
    imu_factor_terms,
    preintegrate,
)

NOISE = ImuNoise(1e-3, 2e-2, 1e-4, 1e-3, 0.0)
#: minegeo's (rotation, velocity, position) rows from GTSAM's (rotation, position, velocity)
PERM = [0, 1, 2, 6, 7, 8, 3, 4, 5]


def _samples(rng, n=200):
    gyro = rng.normal(size=(n, 3)) * 0.5 + [0.3, -0.2, 0.8]
    acc = rng.normal(size=(n, 3)) * 1.0 + [0.5, 0.2, 9.8]
    return gyro, acc, np.array([0.05, -0.03, 0.02, 0.01, -0.02, 0.015])


def _gtsam_pim(gtsam, cls, gyro, acc, h, bias, noise=NOISE):
    P = gtsam.PreintegrationParams.MakeSharedU(GRAVITY_M_S2)
    P.setGyroscopeCovariance(np.eye(3) * noise.gyroscope_noise_density ** 2)
    P.setAccelerometerCovariance(np.eye(3) * noise.accelerometer_noise_density ** 2)
    P.setIntegrationCovariance(np.eye(3) * noise.integration_sigma ** 2)
    P.setImuFactorErrorMode(gtsam.ImuFactorErrorMode.Legacy)
    G = getattr(gtsam, cls)(P, gtsam.imuBias.ConstantBias(bias[:3], bias[3:]))
    for k in range(gyro.shape[0]):
        G.integrateMeasurement(acc[k], gyro[k], h)
    return G


def test_preintegration_matches_gtsam_manifold_preintegration(rng):
    """ΔR, Δv, Δp, the covariance and the bias-corrected prediction against GTSAM's
    ``PreintegratedImuMeasurementsManifold`` (same noise, gravity 9.80665 along −z, biases).

    GTSAM 4.3 keeps the covariance of (δφ, δp, δv) with ``p = p̂ + ΔR δp``, ``v = v̂ + ΔR δv``;
    minegeo (and [Forster2017 Sec. VI-B]) with ``p = p̂ + δp``: the two are related by
    ``diag(I, ΔRᵀ, ΔRᵀ)``."""
    gtsam = require_oracle("gtsam")
    gyro, acc, bias = _samples(rng)
    noise = ImuNoise(1e-3, 2e-2, 1e-4, 1e-3, 1e-4)
    pim = preintegrate(gyro, acc, 0.005, bias, noise)
    G = _gtsam_pim(gtsam, "PreintegratedImuMeasurementsManifold", gyro, acc, 0.005, bias, noise)
    assert pim.dt == pytest.approx(G.deltaTij(), abs=1e-12)
    np.testing.assert_allclose(pim.delta_R, G.deltaRij().matrix(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(pim.delta_v, G.deltaVij(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(pim.delta_p, G.deltaPij(), rtol=0, atol=1e-12)
    T = np.eye(9)
    T[3:6, 3:6] = T[6:9, 6:9] = pim.delta_R.T
    C = G.preintMeasCov()
    np.testing.assert_allclose(T @ pim.covariance[np.ix_(PERM, PERM)] @ T.T, C, rtol=0, atol=1e-12 * np.abs(C).max())
    for _ in range(3):  # the first-order bias correction through the bias Jacobians
        Ti, vi, bi = se3_exp(rng.normal(size=6)), rng.normal(size=3), bias + rng.normal(size=6) * 0.02
        ns = G.predict(gtsam.NavState(gtsam.Pose3(Ti), vi), gtsam.imuBias.ConstantBias(bi[:3], bi[3:]))
        Tj, vj = pim.predict(Ti, vi, bi)
        np.testing.assert_allclose(Tj, ns.pose().matrix(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(vj, ns.velocity(), rtol=0, atol=1e-12)


def test_imu_factor_error_matches_gtsam_imu_factor(rng):
    """The residual against GTSAM's ``ImuFactor`` (Legacy error mode) at states around the
    prediction. GTSAM's factor takes its default (tangent) preintegration, whose deltas differ from
    Forster's by O(Δt²): minegeo's factor is given GTSAM's deltas. GTSAM's error is the predicted
    state seen from state j, ``e = −(r_R, R_jᵀR_i r_p, R_jᵀR_i r_v)``: the same residual in another chart."""
    gtsam = require_oracle("gtsam")
    gyro, acc, bias = _samples(rng)
    G = _gtsam_pim(gtsam, "PreintegratedImuMeasurements", gyro, acc, 0.005, bias)
    own = preintegrate(gyro, acc, 0.005, bias, NOISE)
    pim = Preintegrated(G.deltaTij(), G.deltaRij().matrix(), G.deltaVij(), G.deltaPij(), own.jacobians,
                        own.covariance, bias)
    factor = gtsam.ImuFactor(1, 2, 3, 4, 5, G)
    for _ in range(5):
        Ti, vi = se3_exp(rng.normal(size=6)), rng.normal(size=3)
        Tj, vj = pim.predict(Ti, vi)
        Tj, vj = Tj @ se3_exp(rng.normal(size=6) * 0.05), vj + rng.normal(size=3) * 0.1
        values = gtsam.Values()
        for key, val in ((1, gtsam.Pose3(Ti)), (2, vi), (3, gtsam.Pose3(Tj)), (4, vj),
                         (5, gtsam.imuBias.ConstantBias(bias[:3], bias[3:]))):
            values.insert(key, val)
        r = imu_factor_terms(Ti, vi, bias, Tj, vj, bias, pim)[0]
        Q = Tj[:3, :3].T @ Ti[:3, :3]
        np.testing.assert_allclose(factor.unwhitenedError(values), -np.r_[r[:3], Q @ r[6:9], Q @ r[3:6]],
                                   rtol=0, atol=1e-12)
        assert np.abs(r).max() > 1e-3  # away from the prediction: a real comparison


def _zoh_truth(T0, v0, gyro, acc_world_fn, h):
    """States of a rigid body driven by piecewise-constant body rates ``gyro`` and world accelerations
    (exact solution of the zero-order hold, a naive world-frame twin of the preintegration)."""
    R, p, v = T0[:3, :3].copy(), T0[:3, 3].copy(), v0.copy()
    states, acc = [], []
    for k in range(gyro.shape[0]):
        a_w = acc_world_fn(k)
        acc.append(R.T @ (a_w - gravity_vector()))
        states.append((R.copy(), p.copy(), v.copy()))
        p = p + v * h + 0.5 * a_w * h * h
        v = v + a_w * h
        R = R @ exp_so3(gyro[k] * h)
    states.append((R, p, v))
    return states, np.asarray(acc)


def _pose(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


@settings(max_examples=25, deadline=None)
@given(w=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
       a=st.lists(st.floats(-15.0, 15.0), min_size=3, max_size=3),
       n=st.integers(1, 60), h=st.floats(1e-3, 2e-2))
def test_constant_rate_and_specific_force_give_the_closed_form(w, a, n, h):
    """Constant body rate ω and specific force a: ``ΔR = Exp(ω nΔt)`` and, with θ = |ω|Δt and the
    rotation axis K = [ω/|ω|]×, ``Δv = Δt (n I + S_s K + (n − S_c) K²) a`` where
    ``S_s = Σ_{k<n} sin kθ``, ``S_c = Σ_{k<n} cos kθ`` in closed form (Dirichlet sums); ``Δp`` within
    ``½|ω|Δt T²|a|`` of the continuous ``T² Γ₂(ωT) a`` (the zero-order hold's bound)."""
    w, a = np.asarray(w), np.asarray(a)
    assume(np.linalg.norm(w) > 1e-3)
    pim = preintegrate(np.tile(w, (n, 1)), np.tile(a, (n, 1)), h)
    T = n * h
    np.testing.assert_allclose(pim.delta_R, exp_so3(w * T), rtol=0, atol=1e-12)
    th = np.linalg.norm(w) * h
    K = hat(w / np.linalg.norm(w))
    s_s = np.sin(n * th / 2) * np.sin((n - 1) * th / 2) / np.sin(th / 2)
    s_c = np.sin(n * th / 2) * np.cos((n - 1) * th / 2) / np.sin(th / 2)
    dv = h * (n * np.eye(3) + s_s * K + (n - s_c) * K @ K) @ a
    np.testing.assert_allclose(pim.delta_v, dv, rtol=0, atol=1e-11 * (1 + np.abs(dv).max()))
    phi = np.linalg.norm(w) * T
    Kw = hat(w * T)
    gamma2 = 0.5 * np.eye(3) + (phi - np.sin(phi)) / phi**3 * Kw + (phi**2 / 2 + np.cos(phi) - 1) / phi**4 * Kw @ Kw
    bound = 0.5 * np.linalg.norm(w) * h * T * T * np.linalg.norm(a) + 1e-12
    assert np.linalg.norm(pim.delta_p - T * T * gamma2 @ a) <= bound


def _states(rng, n=2):
    poses = np.stack([se3_exp(rng.normal(size=6)) for _ in range(n)])
    vec = rng.normal(size=(n, 9)) * np.r_[np.ones(3), np.full(6, 0.05)]
    return Values(np.ascontiguousarray(poses), np.ascontiguousarray(vec))


def _fd_jacobian(group, values, var, h=1e-6):
    """Central differences of ``group.residuals`` along the 15 tangent directions of variable ``var``."""
    cols = []
    col = np.full(values.n, -1, dtype=np.int64)
    col[var] = 0
    for k in range(15):
        d = np.zeros(15)
        d[k] = h
        cols.append((group.residuals(values.retract(col, d)) - group.residuals(values.retract(col, -d)))[0] / (2 * h))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_imu_and_bias_factor_jacobians_against_finite_differences(seed):
    rng = np.random.default_rng(seed)
    gyro, acc, bias = _samples(rng, 50)
    pim = preintegrate(gyro, acc, 0.01, bias, NOISE)
    values = _states(rng)
    values = Values(values.poses, values.vectors + np.r_[np.zeros(3), bias])  # δb ≠ 0 but small
    for group in (ImuFactors([(0, 1, pim)]), BiasRandomWalkFactors([[0, 1]], 0.5, NOISE)):
        r, (Ji, Jj) = group.linearize(values)
        for var, J in ((0, Ji[0]), (1, Jj[0])):
            fd = _fd_jacobian(group, values, var)
            np.testing.assert_allclose(J, fd, rtol=0, atol=1e-6 * max(1.0, np.abs(fd).max()))
        assert np.abs(Ji[0][:, 12:15]).max() > 0 or isinstance(group, BiasRandomWalkFactors)


def test_bad_imu_input_is_refused():
    with pytest.raises(InputError):
        preintegrate(np.zeros((3, 3)), np.zeros((2, 3)), 0.01)
    with pytest.raises(InputError):
        preintegrate(np.zeros((3, 3)), np.zeros((3, 3)), [0.01, 0.0, 0.01])
    with pytest.raises(InputError):
        ImuNoise(gyroscope_noise_density=0.0)


def test_a_short_trajectory_with_imu_factors_and_pose_priors_recovers_velocity_and_bias():
    """7 states 0.25 s apart, IMU at 200 Hz from a curving, accelerating motion (exact zero-order
    hold), biases b = (0.08, −0.05, 0.1 m/s², 0.02, −0.01, 0.015 rad/s) added to the samples.
    Priors on 4 of the poses; the solve starts from zero velocity and zero bias."""
    rng = np.random.default_rng(3)
    h, per, n_states = 0.005, 50, 7
    n = per * (n_states - 1)
    t = np.arange(n) * h
    gyro = np.c_[0.3 * np.sin(2 * t), 0.2 * np.cos(3 * t), 0.5 + 0.3 * np.sin(t)]
    states, acc = _zoh_truth(np.eye(4), np.array([1.0, 0.2, 0.0]), gyro,
                             lambda k: np.array([np.cos(2 * t[k]), np.sin(1.5 * t[k]), 0.5 * np.cos(t[k])]), h)
    b_true = np.array([0.08, -0.05, 0.1, 0.02, -0.01, 0.015])
    gyro_m, acc_m = gyro + b_true[3:], acc + b_true[:3]
    truth = [states[k * per] for k in range(n_states)]
    pims = [preintegrate(gyro_m[k * per:(k + 1) * per], acc_m[k * per:(k + 1) * per], h, np.zeros(6), NOISE)
            for k in range(n_states - 1)]
    T_true = np.stack([_pose(R, p) for R, p, _ in truth])
    prior_at = [0, 2, 4, 6]
    groups = [PriorFactors(prior_at, T_true[prior_at], np.tile(np.diag([1e6] * 3 + [1e6] * 3), (4, 1, 1))),
              ImuFactors([(k, k + 1, pims[k]) for k in range(n_states - 1)]),
              BiasRandomWalkFactors([(k, k + 1) for k in range(n_states - 1)], per * h, NOISE)]
    start = Values(np.ascontiguousarray(np.stack([T @ se3_exp(rng.normal(size=6) * 0.02) for T in T_true])),
                   np.zeros((n_states, 9)))
    out = levenberg_marquardt(FactorProblem(n_states, 15, groups, (), LMParams()), start, LMParams())
    assert out.status == "converged", out.reason
    v_true = np.stack([v for _, _, v in truth])
    np.testing.assert_allclose(out.values.vectors[:, :3], v_true, rtol=0, atol=2e-3)
    np.testing.assert_allclose(out.values.vectors[:, 3:], np.tile(b_true, (n_states, 1)), rtol=0, atol=2e-3)
    np.testing.assert_allclose(out.values.poses, T_true, rtol=0, atol=2e-3)
