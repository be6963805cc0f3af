"""The one registration loop (minegeo.registration.loop): each factor against its naive twin, a
finite-difference check of every factor's gradient (which a deliberately broken Jacobian fails),
the pieces of the loop (search, solve, termination) and the loop against the naive ICP loop."""

from __future__ import annotations

import numpy as np
import pytest
from reference.naive_gicp import naive_gicp_system, naive_plane_covariances
from reference.naive_icp import naive_evaluate, naive_icp, naive_point_to_plane_system, naive_umeyama
from reference.naive_mast import naive_point_to_line_system

from minegeo._provenance import StageTimer
from minegeo.errors import DegenerateGeometryError, TooFewPointsError
from minegeo.geometry.se3 import random_transform
from minegeo.kernels import kdtree as KD
from minegeo.mast.icp import NearestSegment2D
from minegeo.registration import _kernels as K
from minegeo.registration import loop as L


def _surface(rng, n, noise=0.0):
    """Points on a wavy surface z = f(x, y) with its unit normals (m)."""
    xy = rng.uniform(-2, 2, size=(n, 2))
    z = 0.3 * np.sin(1.3 * xy[:, 0]) + 0.2 * np.cos(1.7 * xy[:, 1])
    grad = np.c_[0.39 * np.cos(1.3 * xy[:, 0]), -0.34 * np.sin(1.7 * xy[:, 1])]
    N = np.c_[-grad, np.ones(n)]
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return np.ascontiguousarray(np.c_[xy, z] + noise * rng.normal(size=(n, 3))), np.ascontiguousarray(N)


def _pairs(rng, k=200):
    Q, N = _surface(rng, 600)
    P = np.ascontiguousarray(Q[:k] + 0.02 * rng.normal(size=(k, 3)))
    corr = np.c_[np.arange(k), np.arange(k)].astype(np.int64)
    return P, Q, N, L.Matches(1.0, 0.0, corr)


def test_point_to_plane_factor_matches_naive_twin():
    P, Q, N, m = _pairs(np.random.default_rng(1))
    H, g, cost = L.PointToPlaneFactor(Q, N).linearize(P, np.eye(4), m)
    Hn, gn, cn = naive_point_to_plane_system(P, Q[:200], N[:200])
    np.testing.assert_allclose(H, Hn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, gn, rtol=1e-12, atol=1e-14)
    assert cost == pytest.approx(cn, rel=1e-12)


def test_gicp_factor_matches_naive_twin():
    rng = np.random.default_rng(2)
    P, Q, _, m = _pairs(rng)
    Cs = naive_plane_covariances(P, k=10)
    Ct = naive_plane_covariances(Q, k=10)
    R = random_transform(rng, 0.3, 0.0)[:3, :3]
    H, g, cost = L.GICPFactor(Q, Cs, Ct).linearize(P, np.r_[np.c_[R, np.zeros(3)], [[0, 0, 0, 1]]], m)
    Hn, gn, cn = naive_gicp_system(P, Q, Cs, Ct, R, *m.pairs())
    np.testing.assert_allclose(H, Hn, rtol=1e-9, atol=1e-9 * np.abs(Hn).max())
    np.testing.assert_allclose(g, gn, rtol=1e-9, atol=1e-9 * np.abs(gn).max())
    assert cost == pytest.approx(cn, rel=1e-9)


def test_point_to_point_factor_matches_naive_umeyama():
    rng = np.random.default_rng(3)
    P, Q, _, m = _pairs(rng)
    Qm = Q[:200] @ random_transform(rng, 0.2, 0.5)[:3, :3].T
    Qm = np.ascontiguousarray(np.r_[Qm, Q[200:]])
    dT, singular, _ = L.PointToPointFactor(Qm).step(P, np.eye(4), m)
    np.testing.assert_allclose(dT, naive_umeyama(P, Qm[:200])[0], atol=1e-12)
    assert not singular
    line = np.ascontiguousarray(np.outer(np.linspace(0, 1, 200), [1.0, 2.0, 3.0]))  # collinear pairs
    assert L.PointToPointFactor(line).step(line, np.eye(4), m)[1]


def _segments_scene():
    th = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    wall = np.c_[10 * np.cos(th), 6 * np.sin(th)]
    segs = np.ascontiguousarray(np.c_[wall, np.roll(wall, -1, axis=0)])
    e = segs[:, 2:] - segs[:, :2]
    u = e / np.linalg.norm(e, axis=1)[:, None]
    return wall, segs, np.column_stack([-u[:, 1], u[:, 0]])


def test_point_to_line_factor_matches_naive_twin():
    wall, segs, nrm = _segments_scene()
    rng = np.random.default_rng(4)
    mid = 0.5 * (wall + np.roll(wall, -1, axis=0)) + 0.01 * rng.normal(size=wall.shape)
    q = np.ascontiguousarray(mid)
    m = NearestSegment2D(segs, 0.0, 0.2)(q, None)
    se2 = L.SE2Points(q)
    H, g, (n_in, b) = L.PointToLine2DFactor(se2, nrm, 0.2, 3).linearize(q, (np.eye(2), np.zeros(2)), m)
    Hn, gn, cn = naive_point_to_line_system(q[m.corr[:, 0]], nrm[m.corr[:, 1]], m.extra)
    assert n_in == m.corr.shape[0] == len(q)
    np.testing.assert_allclose(H, Hn, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, gn, rtol=1e-12, atol=1e-15)
    assert float(b @ b) == pytest.approx(cn, rel=1e-12)


# ----------------------------------------------------------------------------- gradient check


class _BrokenPointToPlane(L.PointToPlaneFactor):
    """A deliberately wrong Jacobian: the sign of the rotation part flipped (J = [n × p, n])."""

    def linearize(self, P, pose, matches):
        H, g, cost = super().linearize(P, pose, matches)
        S = np.diag([-1.0, -1, -1, 1, 1, 1])
        return S @ H @ S, S @ g, cost


def _gradient_error(factor, P, pose, matches, h=1e-6):
    """max |∇cost - 2 g| / max |2 g|, the cost Σ r² (or Σ dᵀ M⁻¹ d at fixed M) as the factor's aux,
    differentiated numerically along each increment direction x of the factor's manifold."""
    _, g, _ = factor.linearize(P, pose, matches)
    num = np.zeros(6)
    for i in range(6):
        c = []
        for s in (h, -h):
            x = np.zeros(6)
            x[i] = s
            Pm = K.transform_points_kernel(P, L.euler6_to_transform(x))
            c.append(factor.linearize(Pm, pose, matches)[2])
        num[i] = (c[0] - c[1]) / (2 * h)
    return float(np.abs(num - 2 * g).max() / np.abs(2 * g).max())


@pytest.mark.parametrize("kind", ["point_to_plane", "gicp"])
def test_factor_gradient_matches_finite_differences(kind):
    rng = np.random.default_rng(5)
    P, Q, N, m = _pairs(rng)
    if kind == "point_to_plane":
        f = L.PointToPlaneFactor(Q, N)
    else:
        f = L.GICPFactor(Q, naive_plane_covariances(P, k=10), naive_plane_covariances(Q, k=10))
    assert _gradient_error(f, P, np.eye(4), m) < 1e-6


def test_broken_jacobian_is_caught():
    P, Q, N, m = _pairs(np.random.default_rng(6))
    assert _gradient_error(_BrokenPointToPlane(Q, N), P, np.eye(4), m) > 0.1
    # and the loop with it does not reach the answer the true factor reaches
    rng = np.random.default_rng(7)
    T0 = random_transform(rng, 0.05, 0.05)
    Q, N = _surface(rng, 3000)
    P0 = np.ascontiguousarray(Q[::3])
    stop = L.Termination(relative_fitness=1e-9, relative_rmse=1e-9)
    search = L.NearestInGate(Q, 0.3, tree=KD.kd_build(Q, KD.KD_LEAF))
    P = K.transform_points_kernel(P0, T0)
    good = L.run_loop(P, T0, search, L.PointToPlaneFactor(Q, N), stop, 30, StageTimer())
    bad = L.run_loop(P, T0, search, _BrokenPointToPlane(Q, N), stop, 30, StageTimer())
    assert np.abs(good.pose - np.eye(4)).max() < 1e-6
    assert np.abs(bad.pose - np.eye(4)).max() > 1e-4


def test_point_to_line_gradient_matches_finite_differences():
    wall, segs, nrm = _segments_scene()
    q0 = np.ascontiguousarray(0.5 * (wall + np.roll(wall, -1, axis=0)) * 1.003)
    pose = (np.eye(2), np.zeros(2))
    se2 = L.SE2Points(q0)
    f = L.PointToLine2DFactor(se2, nrm, 0.5, 3)
    search = NearestSegment2D(segs, 0.0, 0.5)
    _, g, _ = f.linearize(q0, pose, search(q0, None))
    num = np.zeros(3)
    h = 1e-7
    for i in range(3):
        c = []
        for s in (h, -h):
            x = np.zeros(3)
            x[i] = s
            q = L.SE2Points(q0).move(None, L.SE2Points.compose(x, pose), x)
            c.append(float(np.sum(search(q, None).extra ** 2)))
        num[i] = (c[0] - c[1]) / (2 * h)
    np.testing.assert_allclose(num, 2 * g, rtol=1e-5, atol=1e-8)


# ----------------------------------------------------------------------------- pieces


def test_nearest_in_gate_warm_equals_cold_and_brute_force():
    rng = np.random.default_rng(8)
    Q, _ = _surface(rng, 4000, noise=0.01)
    P = np.ascontiguousarray(Q[rng.choice(4000, 700)] + 0.05 * rng.normal(size=(700, 3)))
    search = L.NearestInGate(Q, 0.08, tree=KD.kd_build(Q, KD.KD_LEAF))
    cold = search(P, None)
    f, r, corr = naive_evaluate(P, Q, np.eye(4), 0.08)
    np.testing.assert_array_equal(cold.corr, corr)
    assert cold.fitness == f and cold.rmse == pytest.approx(r, rel=1e-12)
    P2 = np.ascontiguousarray(P + 0.01)
    warm = search(P2, cold)
    again = search(P2, None)
    np.testing.assert_array_equal(warm.corr, again.corr)
    assert (warm.fitness, warm.rmse) == (again.fitness, again.rmse)
    serial = L.NearestInGate(Q, 0.08, tree=search.tree, parallel_rows=10**9)(P2, cold)
    parallel = L.NearestInGate(Q, 0.08, tree=search.tree, parallel_rows=1)(P2, cold)
    np.testing.assert_array_equal(serial.corr, parallel.corr)
    assert serial.rmse == parallel.rmse


def test_solve_normal_equations_full_rank_and_singular():
    rng = np.random.default_rng(9)
    A = rng.normal(size=(20, 6))
    H, g = A.T @ A, rng.normal(size=6)
    x, singular = L.solve_normal_equations(H, g)
    assert not singular
    np.testing.assert_allclose(H @ x, -g, atol=1e-10)
    A[:, 5] = 0.0  # one free direction: minimum-norm step, flagged
    H = A.T @ A
    x, singular = L.solve_normal_equations(H, g)
    assert singular
    np.testing.assert_allclose(x, -np.linalg.pinv(H, rcond=1e-12) @ g, atol=1e-10)
    assert L.solve_normal_equations(np.zeros((6, 6)), g)[1]


def test_point_to_line_solve_refuses_parallel_lines():
    with pytest.raises(DegenerateGeometryError):
        L.PointToLine2DFactor.solve(np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), np.ones(3))
    f = L.PointToLine2DFactor(L.SE2Points(np.zeros((5, 2))), np.zeros((1, 2)), 0.1, 3)
    with pytest.raises(TooFewPointsError):
        f.step(np.zeros((5, 2)), (np.eye(2), np.zeros(2)), L.Matches(0.0, 0.0, np.zeros((2, 2), np.int64),
                                                                      extra=np.zeros(2)))


class _Alternating:
    """A search whose correspondence set alternates A, B, A, ... (a 2-cycle) after the first call."""

    def __init__(self):
        self.calls = 0

    def __call__(self, P, prev):
        self.calls += 1
        corr = np.array([[0, self.calls % 2]], dtype=np.int64)
        return L.Matches(1.0, 0.1 * (self.calls % 2), corr)


class _Fixed:
    manifold = L.SE3Euler

    def __init__(self, t):
        self.t = t

    def step(self, P, pose, matches):
        dT = np.eye(4)
        dT[0, 3] = self.t
        return dT, False, None


def test_termination_cycle_and_budget():
    P = np.zeros((1, 3))
    s = _Alternating()
    out = L.run_loop(P, np.eye(4), s, _Fixed(1.0), L.Termination(stop_on_cycle=True), 10, StageTimer())
    assert out.reason == "cycle" and out.iterations == 2 and s.calls == 3
    s = _Alternating()
    out = L.run_loop(P, np.eye(4), s, _Fixed(1.0), L.Termination(), 4, StageTimer())
    assert out.reason == "" and not out.converged and out.iterations == 4 and s.calls == 5
    assert out.pose[0, 3] == 4.0 and len(out.history) == 5
    # MAST semantics: the step test right after the step, no search after the budget's last step
    s = _Alternating()
    out = L.run_loop(P, np.eye(4), s, _Fixed(1.0), L.Termination(evaluate_after_last_step=False), 3, StageTimer())
    assert out.iterations == 3 and s.calls == 3
    s = _Alternating()
    stop = L.Termination(step_translation=1e-3, step_rotation=1e-3, evaluate_after_last_step=False)
    out = L.run_loop(P, np.eye(4), s, _Fixed(1e-4), stop, 3, StageTimer())
    assert out.reason == "step" and out.iterations == 1 and s.calls == 1


def test_loop_point_to_plane_matches_naive_icp():
    rng = np.random.default_rng(10)
    Q, N = _surface(rng, 3000, noise=0.002)
    P0 = np.ascontiguousarray(Q[::4] + 0.001 * rng.normal(size=Q[::4].shape))
    T0 = random_transform(rng, 0.05, 0.1)
    search = L.NearestInGate(Q, 0.3, tree=KD.kd_build(Q, KD.KD_LEAF))
    stop = L.Termination(relative_fitness=1e-6, relative_rmse=1e-6)
    out = L.run_loop(K.transform_points_kernel(P0, T0), T0, search, L.PointToPlaneFactor(Q, N), stop, 30,
                     StageTimer())
    Tn, f, r, it = naive_icp(P0, Q, T0, 0.3, normals=N)
    np.testing.assert_allclose(out.pose, Tn, atol=1e-9)
    assert out.iterations == it and out.matches.fitness == pytest.approx(f) and out.converged


@pytest.mark.parametrize("case", ["surface", "normal", "rounded", "coincident", "one", "signed_zeros"])
@pytest.mark.parametrize("leaf", [1, 2, 12])
def test_kd_build_is_the_reference_tree_byte_for_byte(case, leaf):
    """The kernel's tree (children's boxes kept in registers) is the plain rule's, byte for byte."""
    from reference.naive_kernels import naive_kd_build

    from minegeo.kernels.kdtree import kd_build

    rng = np.random.default_rng(11)
    Q = {"surface": lambda: _surface(rng, 5000)[0], "normal": lambda: rng.normal(size=(4000, 3)),
         "rounded": lambda: np.round(rng.normal(size=(3000, 3)), 1), "coincident": lambda: np.zeros((50, 3)),
         "one": lambda: rng.normal(size=(1, 3)),
         "signed_zeros": lambda: np.r_[np.zeros((20, 3)), -np.zeros((20, 3)), np.ones((5, 3))]}[case]()
    Q = np.ascontiguousarray(Q)
    for a, b in zip(naive_kd_build(Q, leaf), kd_build(Q, leaf), strict=True):
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        else:
            assert a == b
