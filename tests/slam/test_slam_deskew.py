"""Deskewing a sweep by a constant body twist (minegeo.slam.deskew).

Reference: the sensor motion over the sweep made with SciPy's matrix exponential of the twist
matrix ``[[ω]×, v; 0, 0]`` (an independent implementation of exp on SE(3)), not minegeo's kernels.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from minegeo.errors import InputError
from minegeo.slam.deskew import deskew_points, twist_from_motion


def _twist_matrix(xi):
    w, v = xi[:3], xi[3:]
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    X[:3, 3] = v
    return X


def _smeared_sweep(xi, n=400, period=0.1, seed=0):
    """Points X fixed in the sensor frame at the frame time; each measured at its offset τ from the
    sensor pose G(τ) = expm(τ ξ^) (relative to the frame-time pose): p = G(τ)⁻¹ X."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-30, 30, (n, 3))
    tau = np.sort(rng.uniform(0.0, period, n))
    P = np.empty_like(X)
    for i in range(n):
        G = expm(tau[i] * _twist_matrix(xi))
        P[i] = np.linalg.solve(G[:3, :3], X[i] - G[:3, 3])
    return X, P, tau


@pytest.mark.parametrize("xi", [
    np.array([0.0, 0.0, 0.0, 3.0, 0.0, 0.0]),          # vehicle at 3 m/s
    np.array([0.05, -0.1, 0.9, 2.5, 0.3, -0.2]),      # turning at 52 deg/s
    np.array([0.6, -0.4, 1.0, 1.2, -0.5, 0.4]),       # handheld / drone, 75 deg/s
])
def test_deskew_recovers_the_rigid_sweep(xi):
    X, P, tau = _smeared_sweep(xi)
    raw_err = np.linalg.norm(P - X, axis=1).max()
    assert raw_err > 0.1  # the sweep is really smeared (at 10 Hz, ~0.3 m at 3 m/s)
    Q = deskew_points(P, tau, xi)
    assert np.abs(Q - X).max() < 1e-9


def test_deskew_validates():
    P = np.zeros((3, 3))
    with pytest.raises(InputError):
        deskew_points(P, np.zeros(2), np.zeros(6))
    with pytest.raises(InputError):
        deskew_points(P, np.zeros(3), np.zeros(5))
    with pytest.raises(InputError):
        deskew_points(P, np.array([0.0, np.nan, 0.0]), np.zeros(6))
    with pytest.raises(InputError):
        deskew_points(np.zeros((3, 2)), np.zeros(3), np.zeros(6))
    with pytest.raises(InputError):
        twist_from_motion(np.eye(4), 0.0)


_f = st.floats(-3.0, 3.0, allow_nan=False)
_twists = st.lists(_f, min_size=6, max_size=6).map(np.array)
_taus = st.lists(st.floats(-0.01, 0.2, allow_nan=False), min_size=1, max_size=40).map(np.array)


def _points(n, seed):
    return np.random.default_rng(seed).uniform(-50, 50, (n, 3))


@settings(max_examples=60, deadline=None)
@given(_taus, st.integers(0, 2**31 - 1))
def test_zero_twist_is_the_identity(tau, seed):
    P = _points(tau.size, seed)
    assert np.array_equal(deskew_points(P, tau, np.zeros(6)), P)


@settings(max_examples=60, deadline=None)
@given(_twists, _taus, st.integers(0, 2**31 - 1))
def test_twist_then_its_negative_is_the_identity(xi, tau, seed):
    # exp(τ(-ξ)) exp(τξ) = I: a one-parameter subgroup
    assume(np.linalg.norm(xi) > 1e-6)
    P = _points(tau.size, seed)
    back = deskew_points(deskew_points(P, tau, xi), tau, -xi)
    assert np.abs(back - P).max() < 1e-9 * (1 + np.abs(P).max())


_tau_pairs = st.lists(st.tuples(st.floats(-0.01, 0.2, allow_nan=False), st.floats(-0.01, 0.2, allow_nan=False)),
                      min_size=1, max_size=40).map(np.array)


@settings(max_examples=60, deadline=None)
@given(_twists, _tau_pairs, st.integers(0, 2**31 - 1))
def test_offsets_add(xi, pairs, seed):
    # exp(τ₂ξ) exp(τ₁ξ) = exp((τ₁ + τ₂)ξ)
    t1, t2 = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    assume(np.linalg.norm(xi) > 1e-6)
    P = _points(t1.size, seed)
    two = deskew_points(deskew_points(P, t1, xi), t2, xi)
    one = deskew_points(P, t1 + t2, xi)
    assert np.abs(two - one).max() < 1e-9 * (1 + np.abs(P).max())


@settings(max_examples=60, deadline=None)
@given(_twists, st.floats(0.01, 2.0))
def test_twist_from_motion_inverts_the_exponential(xi, dt):
    # Log is unique for rotation angles below π
    assume(np.linalg.norm(xi[:3]) * dt < np.pi - 0.1)
    D = expm(dt * _twist_matrix(xi))
    assert np.abs(twist_from_motion(D, dt) - xi).max() < 1e-8 * (1 + np.abs(xi).max())


_runs = st.lists(st.tuples(st.sampled_from([0.0, -0.0, 1e-5, 0.05, 0.0999, -0.005]), st.integers(1, 17)),
                 min_size=1, max_size=12)


@settings(max_examples=60, deadline=None)
@given(_twists, _runs, st.integers(0, 2**31 - 1), st.booleans())
def test_points_fired_together_are_deskewed_as_each_alone(xi, runs, seed, read_only):
    # a spinning LiDAR fires its rings together: runs of equal times (the kernel reuses a time's
    # coefficients along a run, ±0 told apart); each point must get the bits it gets alone, from
    # writable and read-only (file) arrays alike, and match the expm reference
    tau = np.concatenate([np.full(n, t) for t, n in runs])
    P = _points(tau.size, seed)
    if read_only:
        P.flags.writeable = tau.flags.writeable = False
    Q = deskew_points(P, tau, xi)
    alone = np.vstack([deskew_points(P[i:i + 1], tau[i:i + 1], xi) for i in range(tau.size)])
    assert np.array_equal(Q, alone)
    G = {t: expm(t * _twist_matrix(xi)) for t, _ in runs}  # one per time (±0 give the same matrix)
    ref = np.array([G[t][:3, :3] @ p + G[t][:3, 3] for t, p in zip(tau, P, strict=True)])
    assert np.abs(Q - ref).max() < 1e-9 * (1 + np.abs(P).max())


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6), st.integers(2, 12), st.floats(-1e3, 1e3),
       st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3))
def test_start_velocity_is_the_slope_and_ignores_a_common_shift(c, n, t0, shift):
    """Positions on a line ``x_0 + v τ`` at 10 Hz: :func:`start_velocity` returns ``v`` (the slope by hand);
    every position shifted alike (the error an anchor's deskewing gives the frames registered to it)
    leaves it unchanged, and so does a time origin anywhere."""
    from minegeo.slam.odometry import start_velocity

    x0, v = np.array(c[:3]), np.array(c[3:])
    tau = 0.1 * np.arange(1, n + 1)
    P = x0 + tau[:, None] * v
    got = start_velocity(t0 + tau, P)
    assert np.allclose(got, v, atol=1e-9 * (1 + abs(t0))), (got, v)
    assert np.allclose(start_velocity(t0 + tau, P + np.array(shift)), got, atol=1e-9 * (1 + abs(t0)))
