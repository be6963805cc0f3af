"""Umeyama/Kabsch, evaluate_registration, pose_covariance and the reduction kernels."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from helpers import require_oracle
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from reference.naive_icp import (
    naive_evaluate,
    naive_kd_build,
    naive_point_to_plane_system,
    naive_point_to_point_information,
    naive_umeyama,
)

from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.geometry.se3 import invert, random_transform, transform_points
from minegeo.kernels import kdtree as KD
from minegeo.kernels import rigid
from minegeo.kernels.chunks import n_chunks
from minegeo.registration import _kernels as K
from minegeo.registration import evaluate_registration, kabsch, pose_covariance, umeyama

SETTINGS = settings(max_examples=25, deadline=None)


def _cloud(seed, n=40, spread=2.0):
    return np.random.default_rng(seed).normal(scale=spread, size=(n, 3))


# ---------------------------------------------------------------- Umeyama / Kabsch


def test_umeyama_matches_naive_twin_with_noise_weights_and_scale(rng):
    P = rng.normal(size=(60, 3))
    T = random_transform(rng, 3.0, 5.0)
    Q = 1.7 * transform_points(T, P) + rng.normal(scale=0.05, size=P.shape)
    w = rng.uniform(0.1, 2.0, size=60)
    for with_scale in (False, True):
        for weights in (None, w):
            Tm, c = umeyama(P, Q, with_scale=with_scale, weights=weights)
            Tn, cn = naive_umeyama(P, Q, with_scale, weights)
            np.testing.assert_allclose(Tm, Tn, atol=1e-12)
            assert c == pytest.approx(cn, rel=1e-12)


def test_umeyama_small_kernel_matches_public(rng):
    P = rng.normal(size=(4, 3))
    Q = transform_points(random_transform(rng), P) + rng.normal(scale=0.01, size=P.shape)
    Tk, ck = rigid.umeyama_small_kernel(P, Q, False)
    np.testing.assert_allclose(Tk, kabsch(P, Q), atol=1e-13)
    Tk, ck = rigid.umeyama_small_kernel(P, 2 * Q, True)
    Ts, cs = umeyama(P, 2 * Q, with_scale=True)
    np.testing.assert_allclose(Tk, Ts, atol=1e-12)
    assert ck == pytest.approx(cs, rel=1e-12)


def test_reflection_fix_planar_points_give_proper_rotation(rng):
    # planar source + heavy noise is the classic case where R = V U^T ([Baek2022 Eq. 12] alone) is a reflection
    P = np.c_[rng.normal(size=(5, 2)), np.zeros(5)]
    Q = P.copy()
    Q[:, 2] = rng.normal(scale=0.5, size=5)
    Q[:, :2] = Q[:, :2] * np.array([1.0, -1.0])  # mirrored in y: best orthogonal map is a reflection
    W = (P - P.mean(0)).T @ (Q - Q.mean(0))
    U, _, Vt = np.linalg.svd(W)
    assert np.linalg.det(Vt.T @ U.T) < 0  # the unfixed [Baek2022 Eq. 12] would be a reflection
    T = kabsch(P, Q)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 50))
def test_exact_correspondences_give_exact_transform(seed, n):
    rng = np.random.default_rng(seed)
    P = rng.normal(scale=3.0, size=(n, 3))
    T = random_transform(rng, np.pi, 10.0)
    Q = transform_points(T, P)
    # the cross-covariance of exact correspondences is R times the scatter of P: its singular values are
    # the scatter's eigenvalues; nearly collinear points (second one below 1e-9 of the first, a thousand
    # times kabsch's rank tolerance) are the degenerate case tested elsewhere, every other set must solve
    Pc = P - P.mean(axis=0)
    ev = np.linalg.eigvalsh(Pc.T @ Pc)
    assume(ev[1] > 1e-9 * ev[2])
    Te = kabsch(P, Q)
    # (arccos-based angles lose precision near 0, so compare the matrices: |dR| ~ angle)
    np.testing.assert_allclose(Te[:3, :3], T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(Te[:3, 3], T[:3, 3], atol=1e-8)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_umeyama_invariances(seed):
    rng = np.random.default_rng(seed)
    P = rng.normal(scale=2.0, size=(30, 3))
    Q = transform_points(random_transform(rng, 1.0, 3.0), P) + rng.normal(scale=0.1, size=P.shape)
    T = kabsch(P, Q)
    # swapped source/target -> inverse (the rigid objective is symmetric)
    np.testing.assert_allclose(kabsch(Q, P), invert(T), atol=1e-10)
    # permutation of the correspondences
    perm = rng.permutation(30)
    np.testing.assert_allclose(kabsch(P[perm], Q[perm]), T, atol=1e-12)
    # rigid motion G of the target composes: T' = G T
    G = random_transform(rng, np.pi, 5.0)
    np.testing.assert_allclose(kabsch(P, transform_points(G, Q)), G @ T, atol=1e-10)
    # rigid motion of the source: T' = T G^-1
    np.testing.assert_allclose(kabsch(transform_points(G, P), Q), T @ invert(G), atol=1e-10)
    # determinism (bit-identical)
    assert np.array_equal(kabsch(P, Q), T)


def test_umeyama_bad_inputs():
    P = _cloud(1, 10)
    with pytest.raises(TooFewPointsError):
        kabsch(P[:2], P[:2])
    with pytest.raises(InputError):
        kabsch(P, P[:9])
    Pn = P.copy()
    Pn[3, 1] = np.nan
    with pytest.raises(InputError, match="row 3"):
        kabsch(Pn, P)
    Pi = P.copy()
    Pi[0, 0] = np.inf
    with pytest.raises(InputError):
        kabsch(P, Pi)
    with pytest.raises(InputError):
        kabsch(P, P, weights=-np.ones(10))
    with pytest.raises(InputError):
        kabsch(P, P, weights=np.zeros(10))
    line = np.outer(np.linspace(0, 1, 8), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateGeometryError):
        kabsch(line, line + 1.0)
    with pytest.raises(DegenerateGeometryError):
        kabsch(np.ones((5, 3)), np.ones((5, 3)))
    # allowed on request (RANSAC minimal samples): a proper rotation, deterministic
    T = kabsch(line, line + 1.0, allow_degenerate=True)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    assert np.array_equal(T, kabsch(line, line + 1.0, allow_degenerate=True))


@pytest.mark.oracle
def test_umeyama_matches_open3d(rng):
    o3d = require_oracle("open3d")
    R = o3d.pipelines.registration
    P = rng.normal(size=(200, 3))
    Q = 1.3 * transform_points(random_transform(rng, 3.0, 4.0), P) + rng.normal(scale=0.05, size=P.shape)
    corr = o3d.utility.Vector2iVector(np.c_[np.arange(200), np.arange(200)].astype(np.int32))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(Q))
    for scale in (False, True):
        To = R.TransformationEstimationPointToPoint(scale).compute_transformation(src, tgt, corr)
        np.testing.assert_allclose(umeyama(P, Q, with_scale=scale)[0], To, atol=1e-12)


# ---------------------------------------------------------------- evaluate_registration


def test_evaluate_matches_naive_and_gate_is_strict(rng):
    P = rng.uniform(0, 1, size=(150, 3))
    Q = rng.uniform(0, 1, size=(120, 3))
    T = random_transform(rng, 0.2, 0.1)
    f, r, c = evaluate_registration(P, Q, T, 0.08)
    fn, rn, cn = naive_evaluate(P, Q, T, 0.08)
    assert f == fn and r == pytest.approx(rn, rel=1e-13) and np.array_equal(c, cn)
    # strict gate: a pair at exactly distance d is not an inlier
    P1 = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    Q1 = np.array([[0.5, 0.0, 0.0], [5.0, 0.25, 0.0]])
    f, r, c = evaluate_registration(P1, Q1, np.eye(4), 0.5)
    assert f == 0.5 and np.array_equal(c, [[1, 1]]) and r == pytest.approx(0.25)
    f, r, c = evaluate_registration(P1, Q1 + 100.0, np.eye(4), 0.5)
    assert (f, r, c.shape) == (0.0, 0.0, (0, 2))


def test_evaluate_bad_inputs():
    P = _cloud(2, 10)
    for d in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(InputError):
            evaluate_registration(P, P, np.eye(4), d)
    with pytest.raises(InputError):
        evaluate_registration(P, P, np.diag([1.0, 1.0, -1.0, 1.0]), 1.0)
    with pytest.raises(InputError):
        evaluate_registration(P[:, :2], P, np.eye(4), 1.0)


@pytest.mark.oracle
def test_evaluate_matches_open3d(rng):
    o3d = require_oracle("open3d")
    P = rng.normal(size=(500, 3))
    Q = transform_points(random_transform(rng, 0.3, 0.2), P) + rng.normal(scale=0.05, size=P.shape)
    T = kabsch(P, Q)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(Q))
    for d in (0.05, 0.1, 1.0):
        o = o3d.pipelines.registration.evaluate_registration(src, tgt, d, T)
        f, r, c = evaluate_registration(P, Q, T, d)
        assert f == o.fitness
        assert r == pytest.approx(o.inlier_rmse, rel=1e-13)
        assert np.array_equal(c, np.asarray(o.correspondence_set))


# ---------------------------------------------------------------- gated KD-tree vs brute force


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), d=st.sampled_from([0.05, 0.2, 1.0, 10.0]))
def test_gated_kdtree_matches_brute_force(seed, n, d):
    rng = np.random.default_rng(seed)
    kind = seed % 3
    if kind == 0:
        Q = rng.uniform(0, 2, size=(n, 3))
    elif kind == 1:  # clustered, duplicates and a plane: deep, uneven tree
        Q = np.round(rng.normal(scale=[1.0, 1.0, 1e-6], size=(n, 3)), 3)
        Q[: n // 3] = Q[0]
    else:  # grid points: many exact ties
        Q = rng.integers(0, 5, size=(n, 3)).astype(float) * 0.1
    P = np.vstack([Q[: min(n, 50)], rng.uniform(-1, 3, size=(80, 3)), Q[:5] + d])  # includes sq == d² cases
    idx, sq = KD.GatedKDTree(np.ascontiguousarray(Q)).query(np.ascontiguousarray(P), d * d)
    D = ((P[:, None, :] - Q[None, :, :]) ** 2).sum(-1)
    D[D >= d * d] = np.inf
    best = D.min(1)
    # lowest index among the (exact) minima, "no neighbour" = n
    ref = np.where(np.isfinite(best), np.argmax(D == best[:, None], axis=1), n)
    assert np.array_equal(idx, ref)
    np.testing.assert_array_equal(sq, np.where(np.isfinite(best), best, np.inf))


# ---------------------------------------------------------------- kernels vs naive, determinism


def test_kd_build_same_tree_as_two_pass_build(rng):
    """The one-pass build (boxes accumulated while partitioning) gives the naive build's tree exactly."""
    clouds = [
        rng.normal(size=(n, 3)) for n in (1, 2, 13, 300, 1500)
    ] + [
        np.round(rng.normal(size=(800, 3)) * 3) / 3,  # many duplicates
        np.zeros((40, 3)),  # no spread
        np.c_[np.linspace(0, 1, 200), np.zeros(200), np.full(200, 1e6)],  # collinear, large offset
        1e6 + rng.normal(size=(400, 3)) * 1e-9,  # spreads at rounding level
    ]
    for Q in clouds:
        for leaf in (1, 2, KD.KD_LEAF):
            got = KD.kd_build(np.ascontiguousarray(Q), leaf)
            ref = naive_kd_build(Q, leaf)
            for a, b in zip(got, ref, strict=True):
                assert np.array_equal(a, b), (Q.shape, leaf)


def test_kernels_match_naive_twins(rng):
    P = rng.normal(size=(2500, 3))  # > CHUNK so several chunks are summed
    Q = P + rng.normal(scale=0.01, size=P.shape)
    N = rng.normal(size=P.shape)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    H, g, rr = K.point_to_plane_system_kernel(P, Q, N)
    Hn, gn, rrn = naive_point_to_plane_system(P, Q, N)
    np.testing.assert_allclose(H, Hn, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(g, gn, rtol=1e-10, atol=1e-12)
    assert rr == pytest.approx(rrn, rel=1e-12)
    np.testing.assert_allclose(
        K.point_to_point_information_kernel(Q[:300]), naive_point_to_point_information(Q[:300]), rtol=1e-12, atol=1e-9
    )
    assert K.sum_kernel(P[:, 0].copy()) == pytest.approx(P[:, 0].sum(), abs=1e-11)
    # indexed variants (used by ICP) are bit-identical to gathering first
    si = rng.integers(0, 2500, size=1800)
    ti = rng.integers(0, 2500, size=1800)
    a = K.point_to_plane_system_idx(P, Q, N, si, ti)
    b = K.point_to_plane_system_kernel(P[si], Q[ti], N[ti])
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    a = K.weighted_moments_idx(P, Q, si, ti)
    b = K.weighted_moments_kernel(P[si], Q[ti], np.ones(si.size))
    assert all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(a, b, strict=True))


def test_reductions_independent_of_thread_count_and_driver(rng):
    n = K.PARALLEL_MIN_ROWS + 3000  # above the threshold: the parallel driver runs
    P = rng.normal(size=(n, 3))
    Q = P + rng.normal(scale=0.01, size=P.shape)
    N = np.ascontiguousarray(np.tile([0.0, 0.6, 0.8], (n, 1)))
    w = np.ones(n)
    old = numba.get_num_threads()
    try:
        out = []
        for nt in sorted({1, old}):
            numba.set_num_threads(nt)
            out.append((K.point_to_plane_system_kernel(P, Q, N), K.weighted_moments_kernel(P, Q, w)))
    finally:
        numba.set_num_threads(old)
    (a1, b1), (a2, b2) = out[0], out[-1]
    for x, y in zip(list(a1) + list(b1), list(a2) + list(b2), strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    # serial and parallel drivers share chunk bodies and summation order: bit-identical
    ps, pp = np.zeros((n_chunks(n), 28)), np.zeros((n_chunks(n), 28))
    K._p2l_serial(P, Q, N, ps)
    K._p2l_parallel(P, Q, N, pp)
    assert np.array_equal(ps, pp)
    s1, s2 = np.zeros((n_chunks(n), 7)), np.zeros((n_chunks(n), 7))
    t1, t2 = np.zeros((n_chunks(n), 10)), np.zeros((n_chunks(n), 10))
    K._moments_serial(P, Q, w, s1, t1)
    K._moments_parallel(P, Q, w, s2, t2)
    assert np.array_equal(s1, s2) and np.array_equal(t1, t2)


def test_pca_normals_kernel_matches_numpy(rng):
    Q = rng.normal(size=(400, 3)) * [3.0, 2.0, 0.1]
    nb = np.ascontiguousarray(rng.integers(0, 400, size=(300, 10)))
    n = K.pca_normals_kernel(Q, nb)
    X = Q[nb] - Q[nb].mean(axis=1, keepdims=True)
    ref = np.linalg.eigh(np.einsum("mki,mkj->mij", X, X))[1][:, :, 0]
    np.testing.assert_allclose(np.abs((n * ref).sum(1)), 1.0, atol=1e-9)


# ---------------------------------------------------------------- pose covariance


def test_pose_covariance(rng):
    J = rng.normal(size=(100, 6))
    H = J.T @ J
    C = pose_covariance(H, 0.02)
    np.testing.assert_allclose(C, 0.0004 * np.linalg.inv(H), rtol=1e-12)
    H0 = H.copy()
    H0[:, 0] = 0
    H0[0, :] = 0
    with pytest.raises(DegenerateGeometryError):
        pose_covariance(H0, 0.02)
    with pytest.raises(InputError):
        pose_covariance(H, 0.0)
    with pytest.raises(InputError):
        pose_covariance(np.triu(H), 0.1)
