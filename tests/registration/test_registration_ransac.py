"""Feature RANSAC (minegeo.registration.ransac): naive twin, properties, runner-up, errors."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_ransac import naive_hypothesis, naive_umeyama

from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.geometry.se3 import invert, random_transform, rotation_angle, transform_points
from minegeo.registration import _kernels_ransac as K
from minegeo.registration.correspondences import feature_correspondences, nearest_rows
from minegeo.registration.ransac import (
    RansacParams,
    _Grid,
    hypothesis_distance,
    register_ransac,
    required_iterations,
)


def _blob(rng, n=150, scale=3.0):
    """A non-planar cloud: points on three random bumpy patches (m)."""
    return rng.uniform(-scale, scale, (n, 3)) * np.array([1.0, 0.8, 0.6])


def _params(**kw):
    base = {"distance_threshold_m": 0.05, "ransac_n": 3, "max_iterations": 5000, "max_validations": None}
    return RansacParams(**{**base, **kw})


def _features_for(n, rng, dim=33):
    return rng.uniform(0, 100, (n, dim))


def _pose_err(T, T_ref):
    return math.degrees(rotation_angle(T[:3, :3].T @ T_ref[:3, :3])), float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3]))


# ----------------------------------------------------------------------------- kernels vs twins


def test_kernels_match_naive_twin(rng):
    src = _blob(rng, 60)
    G = random_transform(rng, 1.0, 2.0)
    tgt = np.vstack([transform_points(G, src[:40]) + 0.003 * rng.standard_normal((40, 3)), _blob(rng, 30)])
    corr = np.stack([np.arange(60), np.r_[np.arange(40), rng.integers(0, 70, 20)]], axis=1)
    csrc, ctgt = np.ascontiguousarray(src[corr[:, 0]]), np.ascontiguousarray(tgt[corr[:, 1]])
    samples = rng.integers(0, 60, (300, 3))
    samples[:100] = rng.integers(0, 40, (100, 3))  # many all-inlier samples
    d = 0.05
    grid = _Grid(tgt, d)
    z = np.zeros((1, 3))
    status, Ts = K.ransac_check_kernel(csrc, ctgt, z, z, samples, 0.9, True, d, False, -2.0, 1e-9, False)
    ok = np.flatnonzero(status == K.ST_EVALUATED)
    cnt, sse, pruned = K.ransac_score_serial(src, np.arange(60), np.ascontiguousarray(Ts[ok]), np.int64(0), d,
                                             *grid.args())
    cnt_p, sse_p, _ = K.ransac_score_kernel(src, np.arange(60), np.ascontiguousarray(Ts[ok]), np.int64(0), d,
                                            *grid.args())
    assert np.array_equal(cnt, cnt_p) and np.array_equal(sse, sse_p) and not pruned.any()
    score = dict(zip(ok.tolist(), zip(cnt.tolist(), sse.tolist(), strict=True), strict=True))
    n_eval = 0
    for h in range(len(samples)):
        st_ref, c_ref, s_ref, T_ref = naive_hypothesis(src, tgt, csrc, ctgt, samples[h], 0.9, d)
        assert status[h] == st_ref, h
        if T_ref is not None and st_ref != K.ST_DEGENERATE:  # degenerate: rotation arbitrary
            np.testing.assert_allclose(Ts[h], T_ref, atol=1e-9)
        if st_ref == K.ST_EVALUATED:
            n_eval += 1
            assert score[h][0] == c_ref
            np.testing.assert_allclose(score[h][1], s_ref, rtol=1e-9, atol=1e-15)
    assert n_eval > 20


def test_umeyama_kernel_matches_naive(rng):
    for _ in range(20):
        P = rng.normal(size=(6, 3))
        T = random_transform(rng, math.pi, 5.0)
        Q = transform_points(T, P) + 0.01 * rng.normal(size=(6, 3))
        R, t, ok = K.umeyama_rigid(P, Q, 1e-9)
        R2, t2, _ = naive_umeyama(P, Q)
        assert ok
        np.testing.assert_allclose(R, R2, atol=1e-12)
        np.testing.assert_allclose(t, t2, atol=1e-12)
        assert np.linalg.det(R) > 0
    # collinear sample: flagged
    P = np.outer(np.arange(4.0), [1.0, 2.0, 0.5])
    assert not K.umeyama_rigid(P, P + 1.0, 1e-9)[2]


def test_grid_nearest_exact_dense_and_hashed(rng, monkeypatch):
    from minegeo.registration import ransac as mod

    tgt = rng.uniform(-5, 5, (400, 3))
    q = rng.uniform(-6, 6, (300, 3))
    d = 0.7
    d2 = ((q[:, None, :] - tgt[None]) ** 2).sum(-1)
    ref = np.where(d2.min(1) < d * d, d2.argmin(1), -1)
    for dense_max in (8_000_000, 0):
        monkeypatch.setattr(mod, "_DENSE_MAX_CELLS", dense_max)
        g = mod._Grid(tgt, d)
        assert (g.dstart.size > 1) == (dense_max > 0)
        j, s = g.nearest(q, np.eye(4), d)
        assert np.array_equal(j, ref)
        np.testing.assert_allclose(s[j >= 0], d2.min(1)[j >= 0], rtol=1e-12)


def test_feature_nearest_rows_exact_with_ties(rng):
    A = rng.uniform(0, 200, (120, 33))
    B = rng.uniform(0, 200, (150, 33))
    B[7] = B[3]  # duplicate target descriptor: tie -> lowest index
    A[0] = B[3]
    idx, d2 = nearest_rows(A, B)
    D = ((A[:, None, :] - B[None]) ** 2).sum(-1)
    assert np.array_equal(idx, D.argmin(1))  # argmin returns the first (lowest) index on ties
    assert idx[0] == 3 and d2[0] == 0.0
    np.testing.assert_allclose(d2, D.min(1), rtol=1e-12)


def test_feature_nearest_rows_tree_equals_brute_force(rng):
    """The descriptor tree (B >= 8 leaves) returns the brute-force answer bit for bit, ties included."""
    n_tree = 8 * K.FEATURE_LEAF
    for dim in (1, 3, 10, 33):
        # low-rank, quantised descriptors (like FPFH): many exact ties and duplicate rows
        basis = rng.normal(size=(min(dim, 4), dim))
        B = np.round(rng.normal(size=(n_tree + 57, basis.shape[0])) @ basis * 4.0) / 4.0
        B[::7] = B[3]
        A = np.vstack([B[::5] + 0.125, B[:40], np.round(rng.normal(size=(30, dim)) * 8.0) / 4.0])
        idx, d2 = nearest_rows(A, B)
        ref_i, ref_d = K.feature_nn_brute(np.ascontiguousarray(A), np.ascontiguousarray(B))
        assert np.array_equal(idx, ref_i) and np.array_equal(d2, ref_d), dim
        D = ((A[:, None, :] - B[None]) ** 2).sum(-1)
        assert np.array_equal(D[np.arange(len(A)), idx], D.min(1))  # exact on these dyadic values
        assert np.array_equal(idx, D.argmin(1))  # lowest index on ties
    # all target rows identical (scatter matrix zero): still exact, lowest index
    B = np.tile(rng.random((1, 33)), (n_tree, 1))
    idx, d2 = nearest_rows(rng.random((5, 33)), B)
    assert np.all(idx == 0)


def test_feature_nearest_rows_thread_independent(rng):
    A = rng.uniform(0, 200, (300, 33))
    B = rng.uniform(0, 200, (700, 33))
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        i1, d1 = nearest_rows(A, B)
    finally:
        numba.set_num_threads(old)
    i2, d2 = nearest_rows(A, B)
    assert np.array_equal(i1, i2) and np.array_equal(d1, d2)


def test_mutual_filter_and_fallback(rng):
    fs = _features_for(50, rng)
    ft = np.vstack([fs[::-1], _features_for(20, rng)])
    m = feature_correspondences(fs, ft, mutual_filter=True)
    assert m.mutual_applied and len(m.pairs) == 50
    assert np.array_equal(m.pairs[:, 1], 49 - np.arange(50))
    # all source features identical except one -> mutual keeps 1 pair < 10 %: fall back to all
    fs2 = np.tile(fs[:1], (50, 1))
    fs2[10] += 1.0
    m2 = feature_correspondences(fs2, ft, mutual_filter=True)
    assert not m2.mutual_applied and len(m2.pairs) == 50 and "unfiltered" in m2.reason
    # isolated points (all-zero FPFH) are not matched
    fs3 = fs.copy()
    fs3[5] = 0.0
    m3 = feature_correspondences(fs3, ft)
    assert 5 not in m3.pairs[:, 0] and m3.n_source_matchable == 49


# ----------------------------------------------------------------------------- properties


def _exact_problem(rng, n=120, outlier_frac=0.3):
    src = _blob(rng, n)
    G = random_transform(rng, math.pi, 10.0)
    perm = rng.permutation(n)
    tgt = transform_points(G, src)[perm]
    fs = _features_for(n, rng)
    ft = fs[perm].copy()
    bad = rng.random(n) < outlier_frac  # corrupt some target descriptors -> wrong matches
    ft[bad] = _features_for(int(bad.sum()), rng)
    return src, tgt, fs, ft, G


def test_exact_correspondences_give_exact_transform(rng):
    src, tgt, fs, ft, G = _exact_problem(rng)
    r = register_ransac(src, tgt, fs, ft, _params(), seed=1)
    np.testing.assert_allclose(r.T_target_source, G, atol=1e-9)
    assert r.fitness == 1.0 and r.n_inliers == len(src) and r.inlier_rmse_m < 1e-9
    assert r.status == "converged" and r.converged and r.iterations < 5000
    assert r.inlier_pairs.shape == (len(src), 2)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_rigid_motion_swap_permutation(seed):
    rng = np.random.default_rng(seed)
    src, tgt, fs, ft, G = _exact_problem(rng, n=80)
    p = _params()
    r = register_ransac(src, tgt, fs, ft, p, seed=seed)
    np.testing.assert_allclose(r.T_target_source, G, atol=1e-8)
    # moving the target by H composes: T' = H T (same draws, same hypotheses)
    H = random_transform(rng, math.pi, 50.0)
    r2 = register_ransac(src, transform_points(H, tgt), fs, ft, p, seed=seed)
    np.testing.assert_allclose(r2.T_target_source, H @ r.T_target_source, atol=1e-8)
    # swapped roles give the inverse
    r3 = register_ransac(tgt, src, ft, fs, p, seed=seed)
    np.testing.assert_allclose(r3.T_target_source, invert(r.T_target_source), atol=1e-8)
    # permuting the source points (with their descriptors) does not change the answer
    perm = rng.permutation(len(src))
    r4 = register_ransac(src[perm], tgt, fs[perm], ft, p, seed=seed)
    np.testing.assert_allclose(r4.T_target_source, r.T_target_source, atol=1e-8)
    assert r4.n_inliers == r.n_inliers


def test_noisy_recovery_and_refit_improves(rng):
    src, tgt, fs, ft, G = _exact_problem(rng, n=200, outlier_frac=0.5)
    tgt = tgt + 0.01 * rng.standard_normal(tgt.shape)
    p = _params(distance_threshold_m=0.05)
    r = register_ransac(src, tgt, fs, ft, p, seed=3)
    r0 = register_ransac(src, tgt, fs, ft, _params(distance_threshold_m=0.05, refit_iterations=0), seed=3)
    a, t = _pose_err(r.T_target_source, G)
    assert a < 0.5 and t < 0.02
    assert (r.n_inliers, -r.inlier_rmse_m) >= (r0.n_inliers, -r0.inlier_rmse_m)
    # the Open3D-compatible mode also recovers the pose (minimal-sample estimate, no refit)
    ro = register_ransac(src, tgt, fs, ft, RansacParams.open3d_compatible(0.05, max_iterations=5000), seed=3)
    assert ro.params.mode == "open3d" and _pose_err(ro.T_target_source, G)[0] < 2.0


def test_deterministic_and_thread_independent(rng):
    src, tgt, fs, ft, _ = _exact_problem(rng, n=150, outlier_frac=0.6)
    tgt = tgt + 0.01 * rng.standard_normal(tgt.shape)
    p = _params(distance_threshold_m=0.04, batch_size=64)
    a = register_ransac(src, tgt, fs, ft, p, seed=11)
    b = register_ransac(src, tgt, fs, ft, p, seed=11)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = register_ransac(src, tgt, fs, ft, p, seed=11)
    finally:
        numba.set_num_threads(old)
    for r in (b, c):
        assert np.array_equal(r.T_target_source, a.T_target_source)
        assert (r.fitness, r.inlier_rmse_m, r.iterations, r.n_validations, r.status) == (
            a.fitness, a.inlier_rmse_m, a.iterations, a.n_validations, a.status)
        assert np.array_equal(r.inlier_pairs, a.inlier_pairs)
        assert r.second_best_n_inliers == a.second_best_n_inliers


def test_required_iterations_eq8():
    assert required_iterations(0.0, 3, 0.999) == math.inf
    assert required_iterations(1.0, 3, 0.999) == 0.0
    assert required_iterations(0.5, 3, 1.0) == math.inf
    assert required_iterations(0.5, 3, 0.99) == pytest.approx(math.log(0.01) / math.log(1 - 0.125))
    assert required_iterations(0.5, 4, 0.99) > required_iterations(0.5, 3, 0.99)


def test_runner_up_flags_a_repeated_structure(rng):
    """Two identical copies of the scanned object in the map: the runner-up is the other copy."""
    obj = _blob(rng, 100, scale=1.0)
    shift = np.array([10.0, 0.0, 0.0])
    tgt = np.vstack([obj, obj + shift, _blob(rng, 50, scale=8.0) + [5, 0, 8]])
    G = random_transform(rng, math.pi, 4.0)
    src = transform_points(invert(G), obj)
    # both copies carry the same descriptors; a source point matches one of them at random
    fs = _features_for(100, rng)
    ft = np.vstack([fs, fs, _features_for(50, rng)])
    ft[100:200] += 1e-3 * rng.random((100, 33))
    coin = rng.random(100) < 0.5
    corr = np.stack([np.arange(100), np.where(coin, np.arange(100), np.arange(100) + 100)], axis=1)
    r = register_ransac(src, tgt, params=_params(distance_threshold_m=0.02), seed=5, correspondences=corr)
    assert r.fitness == 1.0
    assert r.ambiguity_ratio == 1.0 and r.second_best_fitness == 1.0 == r.second_best_score
    assert r.second_best_distance_m == pytest.approx(10.0, abs=1e-6)
    placements = sorted([r.T_target_source[0, 3] - G[0, 3], r.second_best_T_target_source[0, 3] - G[0, 3]])
    np.testing.assert_allclose(placements, [0.0, 10.0], atol=1e-6)
    d, ang = hypothesis_distance(r.T_target_source, r.second_best_T_target_source, src.mean(axis=0))
    assert d == pytest.approx(r.second_best_distance_m) and ang < 1e-6
    # unique structure: the runner-up explains much less
    r1 = register_ransac(src, tgt[:100], params=_params(distance_threshold_m=0.02), seed=5,
                         correspondences=np.stack([np.arange(100)] * 2, axis=1))
    assert r1.ambiguity_ratio < 0.5


def test_max_validations_and_failure_status(rng):
    src, tgt, fs, ft, _ = _exact_problem(rng, n=100, outlier_frac=0.5)
    r = register_ransac(src, tgt, fs, ft, _params(max_validations=3, confidence=1.0), seed=0)
    assert r.status == "max_validations" and r.n_validations == 3 and not r.converged
    r = register_ransac(src, tgt, fs, ft, _params(max_iterations=7, confidence=1.0), seed=0)
    assert r.iterations == 7 and r.status in ("max_iterations", "failed")
    # no overlap at all: honest failure, identity transform
    far = tgt + 1000.0
    corr = np.stack([np.arange(3), np.arange(3)], axis=1)
    r = register_ransac(src, far * [1, 2, 3], params=_params(max_iterations=50), seed=0, correspondences=corr)
    assert r.status == "failed" and not r.converged and np.array_equal(r.T_target_source, np.eye(4))
    assert r.fitness == 0.0 and "no hypothesis" in r.reason


def test_normal_check(rng):
    src, tgt, fs, ft, G = _exact_problem(rng, n=100, outlier_frac=0.0)
    ns = rng.normal(size=src.shape)
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    # target normals in the target's order: rotate the source normals and apply the same permutation
    d2 = ((tgt[:, None, :] - transform_points(G, src)[None]) ** 2).sum(-1)
    nt = (ns @ G[:3, :3].T)[d2.argmin(1)]
    p = _params(normal_angle_threshold_rad=math.radians(20))
    r = register_ransac(src, tgt, fs, ft, p, seed=0, source_normals=ns, target_normals=nt)
    np.testing.assert_allclose(r.T_target_source, G, atol=1e-9)
    r = register_ransac(src, tgt, fs, ft, p, seed=0, source_normals=ns, target_normals=-nt)
    assert r.status == "failed"
    with pytest.raises(InputError, match="normal"):
        register_ransac(src, tgt, fs, ft, p, seed=0)


def test_bad_input_raises_typed_errors(rng):
    src, tgt, fs, ft, _ = _exact_problem(rng, n=40)
    p = _params()
    bad = src.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="row 3"):
        register_ransac(bad, tgt, fs, ft, p)
    bad = tgt.copy()
    bad[0] = np.inf
    with pytest.raises(InputError):
        register_ransac(src, bad, fs, ft, p)
    with pytest.raises(TooFewPointsError):
        register_ransac(src[:2], tgt, fs[:2], ft, p)
    with pytest.raises(TooFewPointsError):
        register_ransac(src, tgt, params=p, correspondences=np.array([[0, 0], [1, 1]]))
    with pytest.raises(InputError):
        register_ransac(src, tgt, fs[:10], ft, p)
    with pytest.raises(InputError):
        register_ransac(src, tgt, fs, ft[:, :20], p)
    with pytest.raises(InputError):
        register_ransac(src, tgt, params=p, correspondences=np.array([[0, 0], [1, 99], [2, 2]]))
    with pytest.raises(InputError):
        register_ransac(src, tgt, params=p)
    plane = src.copy()
    plane[:, 2] = 0.0
    with pytest.raises(DegenerateGeometryError, match="plane"):
        register_ransac(plane, tgt, fs, ft, p)
    line = np.outer(np.linspace(0, 1, 40), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateGeometryError, match="line"):
        register_ransac(src, line, fs, ft, p)
    with pytest.raises(DegenerateGeometryError, match="coincide"):
        register_ransac(np.ones((40, 3)), tgt, fs, ft, p)
    for kw in ({"distance_threshold_m": 0}, {"ransac_n": 2}, {"edge_length_similarity": 1.5},
               {"edge_pairs": "star"}, {"normal_angle_threshold_rad": 4.0}, {"max_iterations": 0},
               {"max_validations": 0}, {"confidence": 1.2}, {"mode": "pcl"}, {"refit_iterations": -1},
               {"batch_size": 0}, {"distinct_angle_deg": 0}):
        with pytest.raises(InputError):
            _params(**kw)


def test_repeated_correspondence_rejected_in_minegeo_mode(rng):
    src = _blob(rng, 10)
    csrc = np.ascontiguousarray(src)
    z = np.zeros((1, 3))
    samples = np.array([[0, 1, 2], [3, 3, 4], [5, 6, 5]])
    st_distinct, _ = K.ransac_check_kernel(csrc, csrc, z, z, samples, 0.9, True, 0.1, False, -2.0, 1e-9, True)
    st_replace, _ = K.ransac_check_kernel(csrc, csrc, z, z, samples, 0.9, True, 0.1, False, -2.0, 1e-9, False)
    assert st_distinct.tolist() == [K.ST_EVALUATED, K.ST_DEGENERATE, K.ST_DEGENERATE]
    # with replacement (Open3D mode) the repeated pair is kept; two distinct points leave the
    # rotation about their line undetermined, so the SVD model flags the sample as degenerate
    assert st_replace[0] == K.ST_EVALUATED and st_replace[1] == K.ST_DEGENERATE


def test_mutual_filter_equals_full_cross_check():
    """The back-search runs only from the chosen target rows; the result must equal the
    textbook cross-check that searches back from every target row (ties included)."""
    from minegeo.registration.correspondences import nearest_rows

    r = np.random.default_rng(11)
    ft = np.round(r.uniform(0, 3, (4000, 33)))  # coarse values: many exact ties
    fs = np.vstack([ft[r.choice(4000, 300)] + r.normal(0, 0.3, (300, 33)), np.round(r.uniform(0, 3, (200, 33)))])
    m = feature_correspondences(fs, ft, mutual_filter=True, mutual_min_ratio=0.0)
    j, _ = nearest_rows(fs, ft)
    i_back, _ = nearest_rows(ft, fs)
    keep = i_back[j] == np.arange(fs.shape[0])
    expected = np.stack([np.arange(fs.shape[0]), j], axis=1)[keep]
    np.testing.assert_array_equal(m.pairs, expected)
    assert 0 < len(m.pairs) < fs.shape[0]


def test_feature_index_reuse_gives_identical_matches(rng):
    """A prebuilt FeatureIndex (tree path and brute path) gives the same matches bit for bit;
    it is refused for another array or another drop_zero_features setting."""
    from minegeo.registration.correspondences import build_feature_index

    for n_t in (40, 8 * K.FEATURE_LEAF + 31):
        ft = np.round(_features_for(n_t, rng) / 7.0)
        ft[3] = 0.0  # an isolated target point
        fs = np.vstack([ft[::3] + 0.25, _features_for(25, rng)])
        fs[1] = 0.0
        idx = build_feature_index(ft)
        assert idx.tree.brute == (n_t < 8 * K.FEATURE_LEAF) and 3 not in idx.rows
        for mutual in (False, True):
            a = feature_correspondences(fs, ft, mutual_filter=mutual)
            b = feature_correspondences(fs, ft, mutual_filter=mutual, target_index=idx)
            assert np.array_equal(a.pairs, b.pairs) and np.array_equal(a.feature_sq_distances, b.feature_sq_distances)
            assert (a.mutual_applied, a.n_target_matchable) == (b.mutual_applied, b.n_target_matchable)
        with pytest.raises(InputError, match="build_feature_index"):
            feature_correspondences(fs, ft.copy(), target_index=idx)
        with pytest.raises(InputError, match="drop_zero_features"):
            feature_correspondences(fs, ft, drop_zero_features=False, target_index=idx)
    with pytest.raises(TooFewPointsError):
        build_feature_index(np.zeros((5, 33)))
    with pytest.raises(InputError):
        build_feature_index(np.full((5, 33), np.nan))


def test_ransac_with_feature_index_and_unchecked_target_is_identical(rng):
    """register_ransac with a reused FeatureIndex and check_target=False returns the same result;
    the unchecked path still refuses a target of the wrong layout."""
    from minegeo.registration.correspondences import build_feature_index

    tgt = _blob(rng, 200)
    T = random_transform(rng, 2.0)
    src = transform_points(invert(T), tgt[:150])
    ft = _features_for(200, rng)
    fs = ft[:150] + rng.normal(0, 0.5, (150, 33))
    p = _params(max_iterations=3000)
    a = register_ransac(src, tgt, fs, ft, p, seed=4)
    b = register_ransac(src, tgt, fs, ft, p, seed=4, target_feature_index=build_feature_index(ft), check_target=False)
    assert np.array_equal(a.T_target_source, b.T_target_source) and a.fitness == b.fitness
    with pytest.raises(InputError, match="C-contiguous float64"):
        register_ransac(src, np.asfortranarray(tgt), fs, ft, p, seed=4, check_target=False)
