"""minegeo.kernels.lie against dense matrix exponentials and finite differences."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_kernels import (
    naive_hat,
    naive_left_jacobian,
    naive_se2_exp,
    naive_se3_exp,
    naive_se3_log,
    naive_so3_exp,
)

from minegeo.geometry import se3
from minegeo.kernels import lie

ANGLES = st.sampled_from([0.0, 1e-9, 1e-5, 3e-4, 0.1, 1.0, 2.5, 3.1])


def _vec(seed, n, scale):
    v = np.random.default_rng(seed).normal(size=n)
    return v / np.linalg.norm(v[:3]) * scale if scale > 0 else v * 0.0


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 100_000), ANGLES)
def test_so3_exp_log_and_jacobians(seed, angle):
    w = _vec(seed, 3, angle)
    R = lie.so3_exp(w)
    np.testing.assert_allclose(R, naive_so3_exp(w), atol=1e-14)
    np.testing.assert_allclose(lie.so3_log(R), w, atol=1e-9)
    np.testing.assert_allclose(lie.hat(w) @ [1.0, 2.0, 3.0], np.cross(w, [1.0, 2.0, 3.0]), atol=1e-15)
    np.testing.assert_allclose(lie.vee(lie.hat(w)), w, atol=0)
    if angle < 3.0:  # finite differences of log stay smooth away from π
        so3_log = lambda R_: lie.so3_log(np.ascontiguousarray(R_))  # noqa: E731
        Jl = naive_left_jacobian(naive_so3_exp, so3_log, w)
        np.testing.assert_allclose(lie.so3_left_jacobian(w), Jl, atol=1e-7)
        np.testing.assert_allclose(lie.so3_right_jacobian(w), lie.so3_left_jacobian(-w), atol=0)
        np.testing.assert_allclose(lie.so3_left_jacobian_inv(w) @ lie.so3_left_jacobian(w), np.eye(3), atol=1e-12)
        np.testing.assert_allclose(lie.so3_right_jacobian_inv(w) @ lie.so3_right_jacobian(w), np.eye(3), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000), ANGLES)
def test_se3_exp_log_adjoint_and_jacobians(seed, angle):
    xi = _vec(seed, 6, angle)
    xi[3:] = np.random.default_rng(seed + 1).normal(size=3) * 2
    T = lie.se3_exp(xi)
    np.testing.assert_allclose(T, naive_se3_exp(xi), atol=1e-12)
    np.testing.assert_allclose(lie.se3_log(T), xi, atol=1e-9)
    np.testing.assert_allclose(lie.se3_exp(lie.se3_log(T)), T, atol=1e-12)
    if 0.0 < angle < 3.0:
        np.testing.assert_allclose(lie.se3_log(T), naive_se3_log(T), atol=1e-8)
    np.testing.assert_allclose(lie.se3_inverse(T) @ T, np.eye(4), atol=1e-12)
    # adjoint: T exp(η) T⁻¹ = exp(Ad η)
    eta = np.random.default_rng(seed + 2).normal(size=6) * 0.3
    np.testing.assert_allclose(T @ naive_se3_exp(eta) @ np.linalg.inv(T), naive_se3_exp(lie.se3_adjoint(T) @ eta),
                               atol=1e-10)
    if angle < 3.0:
        se3_log = lambda T_: lie.se3_log(np.ascontiguousarray(T_))  # noqa: E731
        Jl = naive_left_jacobian(naive_se3_exp, se3_log, xi)
        np.testing.assert_allclose(lie.se3_left_jacobian(xi), Jl, atol=1e-6)
        np.testing.assert_allclose(lie.se3_left_jacobian_inv(xi) @ lie.se3_left_jacobian(xi), np.eye(6), atol=1e-10)
        np.testing.assert_allclose(lie.se3_right_jacobian(xi), lie.se3_left_jacobian(-xi), atol=0)
        np.testing.assert_allclose(lie.se3_right_jacobian_inv(xi) @ lie.se3_right_jacobian(xi), np.eye(6),
                                   atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000), ANGLES)
def test_se2_exp_log(seed, angle):
    xi = np.random.default_rng(seed).normal(size=3)
    xi[0] = angle * np.sign(xi[0] or 1.0)
    T = lie.se2_exp(xi)
    np.testing.assert_allclose(T, naive_se2_exp(xi), atol=1e-13)
    np.testing.assert_allclose(lie.se2_log(T), xi, atol=1e-12)


def test_public_face_runs_the_kernel_source_under_numpy():
    rng = np.random.default_rng(0)
    for _ in range(200):
        w = rng.normal(size=3) * rng.uniform(0, 3)
        R = se3.exp_so3(w)
        np.testing.assert_array_equal(R, lie.so3_exp.py_func(w))
        np.testing.assert_allclose(R, lie.so3_exp(w), atol=1e-15)
        np.testing.assert_array_equal(se3.log_so3(R), lie.so3_log.py_func(R))
        np.testing.assert_array_equal(se3.hat(w), naive_hat(w))
    xi = rng.normal(size=6)
    np.testing.assert_array_equal(se3.se3_exp(xi), lie.se3_exp(xi))
    np.testing.assert_allclose(se3.se2_log(se3.se2_exp(xi[:3] * 0.5)), xi[:3] * 0.5, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000), ANGLES)
def test_se2_adjoint_and_right_jacobian_inverse(seed, angle):
    """``T exp(η) T⁻¹ = exp(Ad η)``; ``J_r⁻¹`` inverts the finite-difference right Jacobian
    ``δ ↦ log(exp(ξ)⁻¹ exp(ξ + δ))`` (a twin built from SciPy's expm/logm)."""
    from scipy.linalg import logm

    rng = np.random.default_rng(seed)
    xi = rng.normal(size=3)
    xi[0] = angle * np.sign(xi[0] or 1.0)
    T = naive_se2_exp(rng.normal(size=3))
    eta = rng.normal(size=3) * 0.3
    np.testing.assert_allclose(T @ naive_se2_exp(eta) @ np.linalg.inv(T), naive_se2_exp(lie.se2_adjoint(T) @ eta),
                               atol=1e-10)
    if angle < 3.0:
        def log(M):
            L = np.real(logm(M))
            return np.array([L[1, 0], L[0, 2], L[1, 2]])

        E0inv = np.linalg.inv(naive_se2_exp(xi))
        Jr = np.empty((3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-6
            Jr[:, j] = (log(E0inv @ naive_se2_exp(xi + e)) - log(E0inv @ naive_se2_exp(xi - e))) / 2e-6
        np.testing.assert_allclose(lie.se2_right_jacobian_inv(xi) @ Jr, np.eye(3), atol=1e-6)
