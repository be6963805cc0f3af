"""Control/check-station statistics (minegeo.survey.control_stats) against hand calculations,
scipy.stats critical values and Monte Carlo sampling distributions under H0."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy import stats

from minegeo.survey.control_stats import (
    check_errors,
    class_test,
    control_statistics,
    misclosure_ratio,
    sp1_allowed_mm,
)


def _translation_adjustment(obs, cov_blocks):
    """Textbook GLS: every station observes the same translation t (3,); v = B t̂ − l, Qvv = Qll − B Qxx Bᵀ."""
    n = len(obs)
    B = np.tile(np.eye(3), (n, 1))
    Q = np.zeros((3 * n, 3 * n))
    for k in range(n):
        Q[3 * k:3 * k + 3, 3 * k:3 * k + 3] = cov_blocks[k]
    P = np.linalg.inv(Q)
    Qxx = np.linalg.inv(B.T @ P @ B)
    t = Qxx @ B.T @ P @ obs.reshape(-1)
    v = (B @ t - obs.reshape(-1)).reshape(n, 3)
    return v, Q - B @ Qxx @ B.T


def test_hand_example_three_stations():
    # three stations observe one shift, sigma 1 cm each: t̂ = mean; v_E = (0.01, 0, -0.01), v_H = (-0.02, 0.01, 0.01)
    obs = np.array([[0.00, 0.0, 0.03], [0.01, 0.0, 0.00], [0.02, 0.0, 0.00]])
    v, Qvv = _translation_adjustment(obs, [np.eye(3) * 1e-4] * 3)
    np.testing.assert_allclose(v[:, 0], [0.01, 0.0, -0.01], atol=1e-15)
    np.testing.assert_allclose(v[:, 2], [-0.02, 0.01, 0.01], atol=1e-15)
    s = control_statistics(v, np.full((3, 3), 0.01), qvv=Qvv, ids=["A", "B", "C"])
    assert s.dof == 6 and s.qvv_source == "adjustment"
    # vᵀPv = (1 + 1 + 4 + 1 + 1) cm² / 1 cm² = 8;  σ̂0² = 8 / 6
    assert s.vtpv == pytest.approx(8.0, rel=1e-12)
    assert s.sigma0_sq == pytest.approx(8.0 / 6.0, rel=1e-12)
    assert s.chi2.lower == pytest.approx(stats.chi2.ppf(0.025, 6)) and s.chi2.upper == pytest.approx(
        stats.chi2.ppf(0.975, 6))
    assert s.chi2.passed is True
    # qvv_ii = σ² (1 − 1/3): w = v / (σ √(2/3)); redundancy numbers 2/3
    np.testing.assert_allclose(s.w, v / (0.01 * np.sqrt(2.0 / 3.0)), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s.redundancy_numbers, 2.0 / 3.0, rtol=1e-12)
    assert s.w_critical == pytest.approx(3.2905, abs=1e-4) and s.flagged == ()
    # r only: uniform redundancy r/3n = 2/3 is exact here, so the same w
    s2 = control_statistics(v, np.full((3, 3), 0.01), dof=6)
    np.testing.assert_allclose(s2.w, s.w, rtol=1e-12)
    assert s2.qvv_source.startswith("uniform")


def test_blunder_flagged_and_named():
    rng = np.random.default_rng(11)
    obs = rng.normal(0, 0.01, (6, 3))
    obs[3, 2] += 0.12
    v, Qvv = _translation_adjustment(obs, [np.diag([1e-4, 1e-4, 1e-4])] * 6)
    s = control_statistics(v, np.full((6, 3), 0.01), qvv=Qvv, ids=[f"S{i}" for i in range(6)])
    assert s.flagged_ids[0] == "S3" and s.flagged[0][1] == "H"
    assert s.chi2.passed is False


def test_monte_carlo_under_h0():
    """Under H0: each w ~ N(0, 1), vᵀPv ~ χ²(r); the χ² test rejects at rate α. 2000 seeded draws;
    tolerances 4.5 standard errors of the sampled statistic."""
    rng = np.random.default_rng(20261129)
    n, draws = 5, 2000
    blocks = []
    for _ in range(n):
        A = rng.normal(0, 0.01, (3, 3))
        blocks.append(A @ A.T + np.eye(3) * 2e-5)              # correlated E N H per station
    chol = [np.linalg.cholesky(b) for b in blocks]
    W, T, rej = [], [], 0
    for _ in range(draws):
        obs = np.array([chol[k] @ rng.standard_normal(3) for k in range(n)]) + [0.3, -0.2, 0.1]
        v, Qvv = _translation_adjustment(obs, blocks)
        s = control_statistics(v, np.array(blocks), qvv=Qvv)
        W.append(s.w.reshape(-1))
        T.append(s.vtpv)
        rej += s.chi2.passed is False
    W, T = np.array(W), np.array(T)
    r = 3 * (n - 1)
    se = 4.5 / np.sqrt(draws)
    assert np.all(np.abs(W.mean(axis=0)) < se)
    assert np.all(np.abs(W.var(axis=0) - 1.0) < 4.5 * np.sqrt(2.0 / draws))
    assert abs(T.mean() / r - 1.0) < 4.5 * np.sqrt(2.0 / r / draws)
    assert stats.kstest(T, stats.chi2(r).cdf).pvalue > 1e-3
    assert abs(rej / draws - 0.05) < 4.5 * np.sqrt(0.05 * 0.95 / draws)


def test_check_errors_hand():
    est = np.array([[10.003, 20.004, 5.012], [0.0, 0.0, 0.0]])
    sur = np.array([[10.0, 20.0, 5.0], [0.0, 0.0, 0.0]])
    e = check_errors(est, sur, ids=["C1", "C2"])
    np.testing.assert_allclose(e.horizontal, [0.005, 0.0], atol=1e-12)
    np.testing.assert_allclose(e.d3, [0.013, 0.0], atol=1e-12)
    assert e.rmse_horizontal == pytest.approx(np.sqrt(0.005**2 / 2), rel=1e-9)
    assert e.rmse_vertical == pytest.approx(np.sqrt(0.012**2 / 2), rel=1e-9)
    assert e.rmse_3d == pytest.approx(np.sqrt(0.013**2 / 2), rel=1e-9)


def test_sp1_class_and_ratio_hand():
    # Class D, d = 500 m = 0.5 km: r = 50 (0.5 + 0.2) = 35 mm
    assert sp1_allowed_mm(500.0) == pytest.approx(35.0)
    assert sp1_allowed_mm(0.0, c=30.0) == pytest.approx(6.0)
    control = np.array([[0.0, 0.0, 0.0], [2000.0, 0.0, 0.0]])
    control_d = np.array([[0.0, 0.005, 0.0], [0.0, 0.0, 0.0]])
    check = np.array([[0.0, 500.0, 0.0], [1700.0, 0.0, 0.0]])
    check_d = np.array([[0.03, 0.005, 0.0], [0.0, 0.034, 0.0]])
    t = class_test(check, check_d, control, control_d, check_ids=["K1", "K2"], control_ids=["C1", "C2"])
    assert t.nearest_control == ("C1", "C2")
    np.testing.assert_allclose(t.distance_m, [500.0, 300.0])
    np.testing.assert_allclose(t.allowed_mm, [35.0, 25.0])
    np.testing.assert_allclose(t.relative_error_mm, [30.0, 34.0], atol=1e-9)
    assert t.passed.tolist() == [True, False]
    # 95 % relative ellipse: semi-major 2.4477 σ_max = 24.477 mm for σ = 10 mm (passes 35, fails nothing more)
    t2 = class_test(check[:1], check_d[:1], control, control_d, relative_cov_h=[np.diag([1e-4, 0.25e-4])])
    assert t2.ellipse_semi_major_mm[0] == pytest.approx(10.0 * np.sqrt(stats.chi2.ppf(0.95, 2)), rel=1e-9)
    assert misclosure_ratio(1000.0, 0.2) == pytest.approx(5000.0)
    assert np.isinf(misclosure_ratio(100.0, 0.0))


def _rzyx(yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


@given(st.integers(3, 7), st.integers(0, 2**31 - 1), st.booleans())
@settings(max_examples=60, deadline=None)
def test_fit_residual_cofactors_are_the_projection_of_a_finite_difference_jacobian(n, seed, scale):
    """(CS7) against a naive twin: the model ``x = s Rz(ψ)Ry(θ)Rx(φ) p + t`` differentiated numerically in
    its own parameters (Euler angles, not the rotation vector of the function): ``Qll − A (AᵀPA)⁻¹ Aᵀ``
    depends only on the space A spans, so both give the same ``Qvv``; ``tr(Qvv P) = 3n − 6 (− 1)``."""
    from minegeo.survey.control_stats import fit_residual_cofactors

    rng = np.random.default_rng(seed)
    p = rng.uniform(-300.0, 300.0, (n, 3)) * np.array([1.0, 1.0, 0.1])
    assume(np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[1] > 20.0)  # not on one line
    ang, t, s = rng.uniform(-np.pi, np.pi, 3) * np.array([1.0, 0.1, 0.1]), rng.uniform(-1e3, 1e3, 3), 1.0 + 1e-4 * rng.normal()
    sig = rng.uniform(0.003, 0.03, (n, 3))
    Q = np.zeros((3 * n, 3 * n))
    Q[np.diag_indices(3 * n)] = sig.reshape(-1) ** 2

    def model(x):  # (t, ψ θ φ, s) -> stacked fitted points
        return ((x[6] if scale else s) * (_rzyx(*x[3:6]) @ p.T).T + x[:3]).reshape(-1)

    x0 = np.r_[t, ang, s] if scale else np.r_[t, ang]
    h = 1e-6 * np.maximum(1.0, np.abs(x0))
    A = np.column_stack([(model(x0 + h[j] * np.eye(x0.size)[j]) - model(x0 - h[j] * np.eye(x0.size)[j])) / (2 * h[j])
                         for j in range(x0.size)])
    P = np.linalg.inv(Q)
    ref = Q - A @ np.linalg.solve(A.T @ P @ A, A.T)
    got = fit_residual_cofactors(s * (_rzyx(*ang) @ p.T).T, sig, scale=scale)
    assert np.allclose(got, ref, rtol=0, atol=1e-6 * sig.min() ** 2), np.abs(got - ref).max()
    assert np.trace(got @ P) == pytest.approx(3 * n - (7 if scale else 6), abs=1e-6)
