"""minegeo.kernels.eig3 and minegeo.kernels.rigid against their naive twins."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_kernels import naive_eigh3, naive_pca, naive_similarity, naive_so3_exp, naive_yaw_fit

from minegeo.kernels import eig3 as E3
from minegeo.kernels import rigid as RG


def _sym(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    w = np.sort(rng.uniform(0.0, 2.0, 3) ** 3)
    Qm, _ = np.linalg.qr(A)
    return Qm @ np.diag(w) @ Qm.T


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000))
def test_jacobi_and_closed_form_match_lapack(seed):
    C = _sym(seed)
    w_ref, V_ref = naive_eigh3(C)
    A = C.copy()
    V = np.empty((3, 3))
    w = np.empty(3)
    E3.jacobi_eigh3(A, V, w)
    scale = max(1.0, abs(w_ref).max())
    np.testing.assert_allclose(w, w_ref, atol=1e-12 * scale)
    np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(C @ V, V * w, atol=1e-11 * scale)
    out = np.empty(6)
    E3.fast_eigen3x3(C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2], out)
    np.testing.assert_allclose(out[3:], w_ref, atol=1e-9 * scale)
    if w_ref[1] - w_ref[0] > 1e-3 * scale:  # smallest eigenvector defined
        assert abs(abs(out[:3] @ V_ref[:, 0]) - 1.0) < 1e-6


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 100_000), st.booleans())
def test_pca_normal_is_rigid_motion_and_permutation_invariant(seed, open3d):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(40, 3)) * [3.0, 1.0, 0.05]
    n_ref, w_ref = naive_pca(X)
    R = naive_so3_exp(rng.normal(size=3))
    out_n = np.empty((2, 3))
    out_e = np.empty((2, 3))
    st_ = np.empty(2, np.int8)
    args = (np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(6), out_n, out_e, st_)
    nbr = np.arange(40, dtype=np.int64)
    E3.pca_normal(np.ascontiguousarray(X), nbr, 40, 0, 0, open3d, 1e-8, *args)
    Y = np.ascontiguousarray((X @ R.T + rng.normal(size=3) * 10)[rng.permutation(40)])
    E3.pca_normal(Y, nbr, 40, 0, 1, open3d, 1e-8, *args)
    np.testing.assert_allclose(out_e[0], w_ref, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out_e[1], w_ref, rtol=1e-6, atol=1e-7)
    assert abs(abs(out_n[0] @ n_ref) - 1) < 1e-8
    assert abs(abs(out_n[1] @ (R @ n_ref)) - 1) < 1e-6


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000), st.booleans(), st.integers(3, 50))
def test_umeyama_recovers_exact_parameters(seed, with_scale, n):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 3)) * 5
    R = naive_so3_exp(rng.normal(size=3))
    c = rng.uniform(0.5, 2.0) if with_scale else 1.0
    t = rng.normal(size=3) * 100
    Q = np.ascontiguousarray(c * P @ R.T + t)
    T, cs = RG.umeyama_small_kernel(np.ascontiguousarray(P), Q, with_scale)
    np.testing.assert_allclose(T[:3, :3], c * R, atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], t, atol=1e-7)
    assert abs(cs - c) < 1e-9
    Rr, tr, ok = RG.umeyama_rigid(np.ascontiguousarray(P), np.ascontiguousarray(P @ R.T + t), 1e-9)
    assert ok
    np.testing.assert_allclose(Rr, R, atol=1e-9)
    np.testing.assert_allclose(tr, t, atol=1e-7)
    Rc, cc = RG.umeyama_centred(P - P.mean(0), Q - Q.mean(0), with_scale)
    np.testing.assert_allclose(Rc, R, atol=1e-9)
    assert abs(cc - c) < 1e-9


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 100_000), st.booleans())
def test_umeyama_matches_textbook_svd_on_noisy_data(seed, with_scale):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(20, 3))
    Q = P @ naive_so3_exp(rng.normal(size=3)).T + rng.normal(size=(20, 3)) * 0.3
    T_ref, c_ref = naive_similarity(P, Q, with_scale)
    T, c = RG.umeyama_small_kernel(np.ascontiguousarray(P), np.ascontiguousarray(Q), with_scale)
    np.testing.assert_allclose(T, T_ref, atol=1e-9)
    assert abs(c - c_ref) < 1e-9
    mu_p, mu_q, W, var_p = RG.unit_moments(np.ascontiguousarray(P), np.ascontiguousarray(Q))
    np.testing.assert_allclose(W, (P - P.mean(0)).T @ (Q - Q.mean(0)) / 20, atol=1e-12)


def test_rigid_fits_flag_collinear_samples():
    P = np.ascontiguousarray(np.outer(np.arange(4.0), [1.0, 2.0, 0.5]))
    _, _, ok = RG.umeyama_rigid(P, P.copy(), 1e-9)
    assert not ok


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 100_000))
def test_yaw_fit_matches_brute_force_search(seed):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(15, 3)) * 4
    th = rng.uniform(-3, 3)
    c, s = np.cos(th), np.sin(th)
    Q = P @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T + rng.normal(size=3) + rng.normal(size=(15, 3)) * 0.2
    T, spread = RG.yaw_fit(np.ascontiguousarray(P), np.ascontiguousarray(Q))
    th_ref, t_ref = naive_yaw_fit(P, Q)
    assert abs(np.angle(np.exp(1j * (np.arctan2(T[1, 0], T[0, 0]) - th_ref)))) < 1e-6
    np.testing.assert_allclose(T[:3, 3], t_ref, atol=1e-5)
    assert spread > 0
