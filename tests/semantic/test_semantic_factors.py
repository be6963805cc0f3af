"""The intersection factor graph of Liang et al. 2024 (Sec. 3): Jacobians against central finite
differences, covariances against their definitions and a Monte Carlo registration, exact data,
incremental warm starts, gauge and bad input, and GTSAM 4.3 as the oracle of the whole graph."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo.errors import DegenerateGeometryError, InputError
from minegeo.geometry.se3 import exp_so3, hat, invert, se3_exp, se3_log
from minegeo.kernels.rigid import umeyama_rigid
from minegeo.semantic.factors import (
    FactorGraph,
    PoseGraphParams,
    descriptor_completeness,
    intersection_covariance,
    intersection_jacobians_paper,
    intersection_terms,
    relative_jacobians_left,
    relative_pose_covariance,
    relative_pose_information,
    relative_terms,
)

H = 1e-6  # finite-difference step (rad, m)


def _random_pose(rng, angle=np.pi * 0.9, trans=20.0):
    axis = rng.normal(size=3)
    return se3_exp(np.r_[axis / np.linalg.norm(axis) * rng.uniform(0, angle), rng.uniform(-trans, trans, 3)])


def _central(f, x0_apply, dim=6):
    """Columns ``(f(apply(+h e_k)) − f(apply(−h e_k))) / 2h``."""
    cols = []
    for k in range(dim):
        d = np.zeros(dim)
        d[k] = H
        cols.append((f(x0_apply(d)) - f(x0_apply(-d))) / (2 * H))
    return np.stack(cols, axis=1)


# ------------------------------------------------------------------ Jacobians


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_relative_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    Ti, Tj = _random_pose(rng), _random_pose(rng)
    Z = invert(Ti) @ Tj @ _random_pose(rng, angle=0.6, trans=1.0)
    res = lambda Ta, Tb: se3_log(invert(Z) @ invert(Ta) @ Tb)  # noqa: E731
    assume(np.linalg.norm(res(Ti, Tj)[:3]) <= 2.8)  # away from the ±π cut of Log
    r, Ji, Jj = relative_terms(Ti, Tj, Z)
    assert np.allclose(r, res(Ti, Tj), atol=1e-12)
    # right perturbation T ← T Exp(δ) (the solver's and GTSAM's)
    assert np.allclose(Ji, _central(lambda T: res(T, Tj), lambda d: Ti @ se3_exp(d)), atol=1e-6)
    assert np.allclose(Jj, _central(lambda T: res(Ti, T), lambda d: Tj @ se3_exp(d)), atol=1e-6)
    # the paper's left perturbation T ← Exp(δ) T [Liang2024 Eqs. 12-14]
    Li, Lj = relative_jacobians_left(Ti, Tj, Z)
    assert np.allclose(Li, _central(lambda T: res(T, Tj), lambda d: se3_exp(d) @ Ti), atol=1e-6)
    assert np.allclose(Lj, _central(lambda T: res(Ti, T), lambda d: se3_exp(d) @ Tj), atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_intersection_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    T = _random_pose(rng, angle=np.pi * 0.99, trans=500.0)
    z, C = rng.uniform(-15, 15, 3), rng.uniform(-500, 500, 3)
    e, J = intersection_terms(T, z, C)
    res = lambda T_: C - T_[:3, 3] - T_[:3, :3] @ z  # noqa: E731  [Liang2024 Eq. 22]
    assert np.allclose(e, res(T), atol=1e-12)
    assert np.allclose(J, _central(res, lambda d: T @ se3_exp(d)), atol=1e-5)
    # the paper's parametrisation: R ← Exp(φ) R, t ← t + δt, z ← z + δz [Liang2024 Eqs. 26-28]
    d_phi, d_t, d_z = intersection_jacobians_paper(T, z)
    R, t = T[:3, :3], T[:3, 3]
    assert np.allclose(d_phi, _central(lambda Rr: C - t - Rr @ z, lambda d: exp_so3(d) @ R, 3), atol=1e-5)
    assert np.allclose(d_t, _central(lambda tt: C - tt - R @ z, lambda d: t + d, 3), atol=1e-6)
    assert np.allclose(d_z, _central(lambda zz: C - t - R @ zz, lambda d: z + d, 3), atol=1e-6)


# ------------------------------------------------------------------ covariances


def test_relative_information_is_the_papers_sum_for_isotropic_noise():
    """``Σ Hᵀ Λ⁻¹ H`` with ``Λ = diag(2σ²)`` [Liang2024 Eqs. 16-18] for isotropic σ (any rotation),
    and for anisotropic σ when ``R = I``."""
    rng = np.random.default_rng(4)
    Pj = rng.uniform(-10, 10, (25, 3))
    for Z, sig in ((_random_pose(rng, trans=3.0), 0.02), (se3_exp(np.r_[0, 0, 0, 1.0, 2.0, 0.5]), [0.01, 0.02, 0.05])):
        Pi = (Z[:3, :3] @ Pj.T).T + Z[:3, 3]
        s = np.broadcast_to(np.asarray(sig, float), (3,))
        lam_inv = np.diag(1.0 / (2 * s**2))
        R = Z[:3, :3]
        want = np.zeros((6, 6))
        for p in Pj:
            Hm = np.hstack([-R @ hat(p), R])
            want += Hm.T @ lam_inv @ Hm
        assert np.allclose(relative_pose_information(Pi, Pj, Z, sig), want, rtol=1e-12)


def test_relative_covariance_matches_monte_carlo_registration():
    """The covariance is that of the least-squares registration: simulate noisy pairs, fit by
    Umeyama, and compare the sample covariance of ``Log(Z_true⁻¹ Ẑ)``."""
    rng = np.random.default_rng(7)
    Z = _random_pose(rng, trans=5.0)
    Pj = rng.uniform(-8, 8, (40, 3)) * [1.0, 0.4, 0.2]
    Pi = (Z[:3, :3] @ Pj.T).T + Z[:3, 3]
    sigma = 0.02
    cov = relative_pose_covariance(Pi, Pj, Z, sigma)
    samples = []
    for _ in range(3000):
        R, t, ok = umeyama_rigid(Pj + rng.normal(scale=sigma, size=Pj.shape),
                                 Pi + rng.normal(scale=sigma, size=Pi.shape), 1e-9)
        samples.append(se3_log(invert(Z) @ np.block([[R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])))
    emp = np.cov(np.asarray(samples).T)
    sd = np.sqrt(np.diag(cov))
    assert np.allclose(np.sqrt(np.diag(emp)) / sd, 1.0, atol=0.06)
    assert np.abs(emp / np.outer(sd, sd) - cov / np.outer(sd, sd)).max() < 0.06  # correlations too
    with pytest.raises(DegenerateGeometryError):
        relative_pose_covariance(Pi[:2], Pj[:2], Z, sigma)


def test_intersection_covariance_scales_with_completeness():
    assert descriptor_completeness(6, 8) == 0.75
    for bad in ((0, 8), (6, 0), (2.5, 8), ("a", 8), (None, 8)):
        with pytest.raises(InputError):
            descriptor_completeness(*bad)
    c = descriptor_completeness(3, 12)
    assert np.allclose(intersection_covariance(c, 0.5), 0.25 * 0.25 * np.eye(3))  # [Liang2024 Eq. 32]
    assert np.allclose(intersection_covariance(c, 0.5, scaling="inverse"), 0.25 * 4.0 * np.eye(3))
    # with matched points: J Ω⁻¹ Jᵀ, Ω = Σ Qᵀ Λ_I⁻¹ Q [Liang2024 Eqs. 30-31], linear in Λ_I
    rng = np.random.default_rng(2)
    T = _random_pose(rng, trans=100.0)
    Pk = rng.uniform(-10, 10, (30, 3))
    Pw = (T[:3, :3] @ Pk.T).T + T[:3, 3]
    z = np.array([3.0, -1.0, 0.5])
    a = intersection_covariance(1.0, 0.1, points_keyframe=Pk, points_map=Pw, T_world_keyframe=T, z=z)
    b = intersection_covariance(0.5, 0.1, points_keyframe=Pk, points_map=Pw, T_world_keyframe=T, z=z)
    assert np.allclose(b, 0.5 * a, rtol=1e-10) and np.all(np.linalg.eigvalsh(a) > 0)
    # a point at the registered points' centroid is known to σ²/N per axis (rotation does not move it)
    z0 = Pk.mean(axis=0)
    c0 = intersection_covariance(1.0, 0.1, points_keyframe=Pk, points_map=Pw, T_world_keyframe=T, z=z0)
    assert np.allclose(c0, 0.01 / 30 * np.eye(3), rtol=1e-9, atol=1e-15)
    for bad in ((0.0, 0.1), (1.0, -1.0), (np.nan, 0.1)):
        with pytest.raises(InputError):
            intersection_covariance(*bad)


# ------------------------------------------------------------------ synthetic graphs


def _drift_graph(rng, n=60, n_int=4, sigma_rel=(0.002, 0.02), sigma_int=0.1, noise=True, start_noise=0.0):
    """A drift trajectory (1 m steps with gentle turns and grade), odometry factors between
    consecutive keyframes, a few loop-like factors, and ``n_int`` intersections next to the track
    each seen from every keyframe within 6 m. Start: the noisy odometry chained (drifting)."""
    truth = [np.eye(4)]
    for _ in range(n - 1):
        truth.append(truth[-1] @ se3_exp(np.r_[rng.normal(scale=0.01, size=2), rng.normal(scale=0.06), 1.0,
                                               rng.normal(scale=0.02, size=2)]))
    truth = np.stack(truth)
    s_rot, s_tr = sigma_rel
    info_rel = np.diag(np.r_[np.full(3, 1 / s_rot**2), np.full(3, 1 / s_tr**2)])
    g = FactorGraph()
    Zs = []
    for k in range(n - 1):
        Z = invert(truth[k]) @ truth[k + 1]
        if noise:
            Z = Z @ se3_exp(np.r_[rng.normal(scale=s_rot, size=3), rng.normal(scale=s_tr, size=3)])
        Zs.append(Z)
    start = [truth[0] @ se3_exp(rng.normal(scale=start_noise, size=6)) if start_noise else truth[0]]
    for Z in Zs:
        start.append(start[-1] @ Z)
    for T in start:
        g.add_keyframe(T)
    for k, Z in enumerate(Zs):
        g.add_relative(k, k + 1, Z, info_rel)
    idx = np.linspace(n // (2 * n_int), n - 1 - n // (2 * n_int), n_int).astype(int)
    for c, k0 in enumerate(idx):
        C = truth[k0][:3, :3] @ np.array([0.0, 3.0 * (-1) ** c, 1.0]) + truth[k0][:3, 3]
        for k in range(n):
            if np.linalg.norm(truth[k][:3, 3] - C) < 6.0:
                Tinv = invert(truth[k])
                z = Tinv[:3, :3] @ C + Tinv[:3, 3] + (rng.normal(scale=sigma_int, size=3) if noise else 0.0)
                g.add_intersection(k, z, C, np.eye(3) / sigma_int**2, intersection_id=100 + c)
    return g, truth


def test_exact_data_recovers_the_exact_poses():
    rng = np.random.default_rng(1)
    g, truth = _drift_graph(rng, n=40, n_int=3, noise=False, start_noise=0.3)
    assert g.cost(truth) < 1e-20
    assert g.gauge() == ()  # three non-collinear intersections anchor the whole graph
    res = g.optimize()
    assert res.status == "converged", res.reason
    assert res.cost_initial > 1.0 and res.cost_final < 1e-18
    assert np.abs(res.poses - truth).max() < 1e-9
    assert np.array_equal(g.poses, res.poses)


def test_incremental_warm_start_reaches_the_batch_optimum():
    rng = np.random.default_rng(3)
    full, _ = _drift_graph(rng, n=50, n_int=3)
    batch = full.optimize(warm_start=False)
    inc = FactorGraph()
    rel = {(i, j): (Z, W) for i, j, Z, W in full.relative_factors()}
    ints = full.intersection_factors()
    for k in range(full.n_keyframes):
        inc.add_keyframe(np.eye(4) if k == 0 else inc.predict(k - 1, rel[(k - 1, k)][0]))
        if k:
            inc.add_relative(k - 1, k, *rel[(k - 1, k)])
        for i, z, C, W, cid in ints:
            if i == k:
                inc.add_intersection(i, z, C, W, cid)
        if k % 10 == 9 or k == full.n_keyframes - 1:
            res = inc.optimize()  # early on: first keyframe held (fewer than three intersections)
            assert res.status == "converged", res.reason
    assert res.held == ()
    assert res.cost_final == pytest.approx(batch.cost_final, rel=1e-9)
    assert np.abs(res.poses - batch.poses).max() < 1e-7


def test_priors_and_held_keyframes_and_robust_kernel():
    rng = np.random.default_rng(5)
    g, truth = _drift_graph(rng, n=20, n_int=1, noise=False, start_noise=0.0)
    assert g.gauge() == (0,)  # one intersection leaves the rotation free: first keyframe held
    with pytest.raises(DegenerateGeometryError, match="keyframes 0"):
        g.gauge("error")
    g.add_prior(5, truth[5], np.eye(6) * 1e6)
    assert g.gauge("error") == ()
    moved = g.poses.copy()
    moved[1:] = moved[1:] @ se3_exp(np.r_[0.02, -0.01, 0.03, 0.3, -0.2, 0.1])
    g.set_estimate(moved)
    res = g.optimize(PoseGraphParams(robust="huber", robust_scale=3.0))
    assert res.status == "converged" and np.abs(res.poses - truth).max() < 1e-8
    h = FactorGraph()
    a, b = h.add_keyframe(truth[0], fixed=True), h.add_keyframe(truth[1] @ se3_exp(np.full(6, 0.1)))
    h.add_relative(a, b, invert(truth[0]) @ truth[1], np.eye(6))
    res = h.optimize()
    assert res.held == (0,) and np.array_equal(res.poses[0], truth[0]) and np.abs(res.poses[1] - truth[1]).max() < 1e-9


def test_disconnected_component_without_anchor():
    """Two chains, intersections (three, non-collinear) only on the first: the second is held at its
    first keyframe with gauge="hold_first" and named by gauge="error"."""
    rng = np.random.default_rng(9)
    g, truth = _drift_graph(rng, n=30, n_int=3, noise=False, start_noise=0.0)
    c = g.add_keyframe(truth[0] @ se3_exp(np.r_[0, 0, 0, 100.0, 0, 0]))
    d = g.add_keyframe(g.poses[c] @ se3_exp(np.r_[0, 0, 0.1, 1.0, 0, 0]))
    g.add_relative(c, d, se3_exp(np.r_[0, 0, 0.1, 1.0, 0, 0]), np.eye(6))
    with pytest.raises(DegenerateGeometryError, match=f"keyframes {c}"):
        g.optimize(gauge="error")
    res = g.optimize()
    assert res.held == (c,) and res.status == "converged" and res.cost_final < 1e-18


def test_bad_input_is_a_typed_error():
    g = FactorGraph()
    a = g.add_keyframe(np.eye(4))
    with pytest.raises(InputError, match="nothing to optimise"):
        g.optimize()
    b = g.add_keyframe(se3_exp(np.r_[0, 0, 0, 1.0, 0, 0]))
    spd = np.eye(6)
    for args in ((a, 2, np.eye(4), spd), (a, a, np.eye(4), spd), (a, b, np.eye(4), -spd),
                 (a, b, np.eye(4), np.diag([1, 1, 1, 1, 1, 0.0])), (a, b, np.full((4, 4), np.nan), spd),
                 (a, b, np.eye(4), np.triu(np.ones((6, 6)))), (a, b, np.eye(4) * 2, spd), (a, b, np.eye(4), np.eye(5))):
        with pytest.raises(InputError):
            g.add_relative(*args)
    for args in ((5, np.zeros(3), np.zeros(3), np.eye(3)), (a, np.r_[np.nan, 0, 0], np.zeros(3), np.eye(3)),
                 (a, np.zeros(3), np.zeros(3), -np.eye(3)), (a, np.zeros(2), np.zeros(3), np.eye(3))):
        with pytest.raises(InputError):
            g.add_intersection(*args)
    with pytest.raises(InputError):
        g.add_keyframe(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InputError):
        g.add_prior(-1, np.eye(4), spd)
    with pytest.raises(InputError):
        g.optimize(gauge="none")
    assert g.n_factors == {"relative": 0, "intersection": 0, "prior": 0}


# ------------------------------------------------------------------ GTSAM, the oracle


def _gtsam_intersection_error(gtsam, z, C, this, values, jacobians):
    """``e = C − T z`` [Liang2024 Eq. 22]; the Jacobian is GTSAM's own ``Pose3.transformFrom`` one
    (right perturbation, (ω, v) order), negated: not minegeo's."""
    T = values.atPose3(this.keys()[0])
    Hp, Hz = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
    p = T.transformFrom(z, Hp, Hz)
    if jacobians is not None:
        jacobians[0] = -Hp
    return C - p


def gtsam_graph(gtsam, g: FactorGraph, start: np.ndarray):
    """The same factors in GTSAM: ``BetweenFactorPose3`` (relative), ``PriorFactorPose3`` (priors),
    a ``CustomFactor`` for each intersection; every noise model ``Gaussian.Information(Ω)``."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, T in enumerate(start):
        values.insert(k, gtsam.Pose3(T))
    for i, j, Z, W in g.relative_factors():
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(Z), gtsam.noiseModel.Gaussian.Information(W)))
    for i, T, W in g.prior_factors():
        graph.add(gtsam.PriorFactorPose3(i, gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Information(W)))
    for i, z, C, W, _ in g.intersection_factors():
        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Gaussian.Information(W), [i],
                                     partial(_gtsam_intersection_error, gtsam, z.copy(), C.copy())))
    return graph, values


def gtsam_optimize(gtsam, graph, values, max_iterations=200):
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(max_iterations)
    p.setRelativeErrorTol(1e-12)
    p.setAbsoluteErrorTol(1e-14)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, p).optimize()


@pytest.mark.oracle
@pytest.mark.parametrize("seed,n", [(11, 120), (12, 200)])
def test_same_optimum_as_gtsam(seed, n):
    """Acceptance (issue #18): the same graph of relative-pose and intersection factors, solved by
    GTSAM 4.3 LM from the same (drifting odometry) start, reaches the same optimum: cost to 1e-6
    relative, poses to 1e-6 m / rad; the start cost equals GTSAM's ``graph.error`` to 1e-12."""
    from helpers import require_oracle

    gtsam = require_oracle("gtsam")
    rng = np.random.default_rng(seed)
    g, truth = _drift_graph(rng, n=n, n_int=5)
    g.add_prior(0, truth[0], np.eye(6) * 1e2)  # a weak prior too, so PriorFactorPose3 is compared
    start = g.poses.copy()
    graph, values = gtsam_graph(gtsam, g, start)
    assert g.cost() == pytest.approx(graph.error(values), rel=1e-12)
    out = gtsam_optimize(gtsam, graph, values)
    ref = np.stack([out.atPose3(k).matrix() for k in range(n)])
    res = g.optimize(PoseGraphParams(max_iterations=200))
    assert res.status == "converged", res.reason
    assert res.cost_final == pytest.approx(graph.error(out), rel=1e-6)
    assert g.cost(ref) == pytest.approx(graph.error(out), rel=1e-12)
    assert np.abs(res.poses - ref).max() < 1e-6
    assert res.cost_initial > 10 * res.cost_final  # the start drifts: a real optimisation


@pytest.mark.oracle
def test_marginal_covariance_equals_gtsam_marginals():
    """The keyframes' marginal covariances (the tracker's recognition gate) equal GTSAM's
    ``Marginals.marginalCovariance`` of the same factors at the same optimum (right perturbation,
    (ω, v) order, as minegeo's (φ, ρ)), to 1e-6 relative; with keyframe 0 held instead of a prior its
    covariance is zero and the chain's last keyframe equals GTSAM's with a near-rigid prior (1e12)."""
    from helpers import require_oracle

    gtsam = require_oracle("gtsam")
    rng = np.random.default_rng(21)
    g, truth = _drift_graph(rng, n=40, n_int=3)
    g.add_prior(0, truth[0], np.eye(6) * 1e2)
    assert g.optimize(PoseGraphParams(max_iterations=200)).status == "converged"
    graph, values = gtsam_graph(gtsam, g, g.poses)
    M = gtsam.Marginals(graph, values)
    for k in (0, 17, 39):
        ref = M.marginalCovariance(k)
        assert np.allclose(g.marginal_covariance(k), ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max()), k
    h = FactorGraph()                      # keyframe 0 held: a chain of four
    h.add_keyframe(truth[0], fixed=True)
    for k in range(1, 4):
        Z = np.linalg.solve(truth[k - 1], truth[k])
        h.add_keyframe(h.predict(k - 1, Z))
        h.add_relative(k - 1, k, Z, np.diag([1e4] * 3 + [1e2] * 3))
    assert np.all(h.marginal_covariance(0) == 0.0)
    graph, values = gtsam_graph(gtsam, h, h.poses)
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(truth[0]), gtsam.noiseModel.Gaussian.Information(np.eye(6) * 1e12)))
    ref = gtsam.Marginals(graph, values).marginalCovariance(3)
    assert np.allclose(h.marginal_covariance(3), ref, rtol=1e-6, atol=1e-9)
