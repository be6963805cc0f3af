"""FPFH (minegeo.features): naive twin, invariances, edge cases, weight modes, errors."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_fpfh import naive_fpfh, naive_neighborhoods, naive_pair_features

from minegeo.errors import InputError, TooFewPointsError
from minegeo.features import FPFHParams, compute_fpfh
from minegeo.features._kernels import pair_features
from minegeo.geometry.se3 import random_transform


def _surface(rng, n=160, noise=0.01):
    """Points on a wavy surface z = f(x, y) in a 2 m square with analytic unit normals."""
    x, y = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    z = 0.3 * np.sin(2 * x) * np.cos(3 * y) + noise * rng.standard_normal(n)
    gx, gy = 0.6 * np.cos(2 * x) * np.cos(3 * y), -0.9 * np.sin(2 * x) * np.sin(3 * y)
    nrm = np.stack([-gx, -gy, np.ones(n)], axis=1)
    return np.stack([x, y, z], axis=1), nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def _tuple(nbs, n):
    kmax = max(len(i) for i, _ in nbs)
    idx = np.full((n, kmax), -1, dtype=np.int64)
    sq = np.full((n, kmax), np.inf)
    cnt = np.zeros(n, dtype=np.int64)
    for r, (i, d) in enumerate(nbs):
        idx[r, : len(i)], sq[r, : len(i)], cnt[r] = i, d, len(i)
    return idx, sq, cnt


@pytest.mark.parametrize("weight", ["open3d", "inverse_distance"])
def test_matches_naive_twin(rng, weight):
    pts, nrm = _surface(rng)
    nbs = naive_neighborhoods(pts, 0.5, 40)
    ref, _ = naive_fpfh(pts, nrm, nbs, weight)
    got = compute_fpfh(pts, nrm, FPFHParams(0.5, 40, weight), neighborhoods=_tuple(nbs, len(pts))).features
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-10)
    # the built-in search (minegeo.geometry, ties by lowest index) gives the same neighbourhoods
    auto = compute_fpfh(pts, nrm, FPFHParams(0.5, 40, weight)).features
    np.testing.assert_allclose(auto, ref, rtol=1e-12, atol=1e-10)


def test_pair_features_match_naive(rng):
    for _ in range(200):
        p1, p2 = rng.normal(size=3), rng.normal(size=3)
        n1, n2 = rng.normal(size=3), rng.normal(size=3)
        n1, n2 = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
        np.testing.assert_allclose(pair_features(p1, n1, p2, n2), naive_pair_features(p1, n1, p2, n2), atol=1e-14)
    # degenerate pairs: coincident points, connecting line parallel to the normal
    z = np.array([0.0, 0.0, 1.0])
    assert pair_features(np.zeros(3), z, np.zeros(3), z) == (0.0, 0.0, 0.0, 0.0)
    assert pair_features(np.zeros(3), z, np.array([0, 0, 2.0]), z) == (0.0, 0.0, 0.0, 0.0)


def test_block_sums_and_edge_cases():
    # a normal point: 200 per block; duplicates only: 100 per block; isolated: 0
    rng = np.random.default_rng(3)
    pts, nrm = _surface(rng, 60)
    far = np.array([[50.0, 50, 50], [80.0, 80, 80], [80.0, 80, 80]])
    pts = np.vstack([pts, far])
    nrm = np.vstack([nrm, [[0, 0, 1.0]] * 3])
    res = compute_fpfh(pts, nrm, FPFHParams(0.6, 30))
    f = res.features
    blocks = f.reshape(len(pts), 3, 11).sum(axis=2)
    np.testing.assert_allclose(blocks[:60], 200.0, rtol=1e-12)
    np.testing.assert_array_equal(f[60], 0.0)
    np.testing.assert_allclose(blocks[61:], 100.0, rtol=1e-12)
    # the coincident pair is degenerate: it lands in the middle bins 5, 16, 27
    assert f[61, 5] == f[61, 16] == f[61, 27] == 100.0
    assert res.n_isolated == 1
    assert f.dtype == np.float64 and f.shape == (63, 33)


def test_weight_modes_differ_by_one_power_of_distance():
    """[Baek2022 Eq. 6] (paper, 1/d) vs Open3D (1/d^2): with neighbours at 1 m and 2 m the neighbour
    SPFHs are blended 2:1 (paper) or 4:1 (Open3D) before the block normalisation."""
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0], [0.3, 0.9, 0.0]])
    nrm = np.array([[0, 0, 1.0], [0, 0.6, 0.8], [0.6, 0, 0.8], [0.0, 0.0, 1.0]])
    nbs = naive_neighborhoods(pts, 3.0, 4)
    out = {}
    for w in ("inverse_distance", "open3d"):
        out[w] = compute_fpfh(pts, nrm, FPFHParams(3.0, 4, w), neighborhoods=_tuple(nbs, 4)).features
        ref, spfh = naive_fpfh(pts, nrm, nbs, w)
        np.testing.assert_allclose(out[w], ref, rtol=1e-12)
    assert not np.allclose(out["inverse_distance"], out["open3d"])
    # point 0: neighbours 3 (d=0.949), 1 (d=1), 2 (d=2); check the un-normalised blend directly
    idx, d2 = nbs[0]
    for w, power in (("inverse_distance", 0.5), ("open3d", 1.0)):
        acc = sum(spfh[j] / s**power for j, s in zip(idx[1:], d2[1:], strict=True))
        acc = acc.reshape(3, 11) * (100.0 / acc.reshape(3, 11).sum(axis=1, keepdims=True))
        np.testing.assert_allclose(out[w][0], acc.ravel() + spfh[0], rtol=1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_rigid_motion_and_permutation_invariance(seed):
    rng = np.random.default_rng(seed)
    pts, nrm = _surface(rng, 120)
    prm = FPFHParams(0.45, 30)
    f0 = compute_fpfh(pts, nrm, prm).features
    T = random_transform(rng, math.pi, 100.0)
    f1 = compute_fpfh(pts @ T[:3, :3].T + T[:3, 3], nrm @ T[:3, :3].T, prm).features
    # rounding may move a value across a bin edge only with probability ~1e-12
    np.testing.assert_allclose(f1, f0, atol=1e-8)
    perm = rng.permutation(len(pts))
    f2 = compute_fpfh(pts[perm], nrm[perm], prm).features
    np.testing.assert_allclose(f2, f0[perm], atol=1e-8)


def test_deterministic_and_thread_independent(rng):
    pts, nrm = _surface(rng, 300)
    prm = FPFHParams(0.4, 50)
    a = compute_fpfh(pts, nrm, prm).features
    b = compute_fpfh(pts, nrm, prm).features
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = compute_fpfh(pts, nrm, prm).features
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a, b) and np.array_equal(a, c)


def test_bad_input_raises_typed_errors(rng):
    pts, nrm = _surface(rng, 20)
    bad = pts.copy()
    bad[4] = np.nan
    with pytest.raises(InputError, match="row 4"):
        compute_fpfh(bad, nrm, FPFHParams(0.5, 10))
    bad = nrm.copy()
    bad[2] = np.inf
    with pytest.raises(InputError):
        compute_fpfh(pts, bad, FPFHParams(0.5, 10))
    with pytest.raises(TooFewPointsError):
        compute_fpfh(pts[:1], nrm[:1], FPFHParams(0.5, 10))
    with pytest.raises(InputError, match="zero-length"):
        compute_fpfh(pts, np.zeros_like(nrm), FPFHParams(0.5, 10))
    with pytest.raises(InputError):
        compute_fpfh(pts, nrm[:5], FPFHParams(0.5, 10))
    with pytest.raises(InputError):
        compute_fpfh(pts[:, :2], nrm, FPFHParams(0.5, 10))
    with pytest.raises(InputError):
        compute_fpfh(pts, nrm, FPFHParams(0.5, 10), neighborhoods=(np.zeros((3, 2), np.int64),) * 3)
    for kwargs in ({"radius_m": 0.0}, {"radius_m": -1.0}, {"max_nn": 1}, {"weight": "1/d^3"}, {"radius_m": np.nan}):
        with pytest.raises(InputError):
            FPFHParams(**{"radius_m": 0.5, "max_nn": 10, **kwargs})
    # coplanar / collinear clouds are valid FPFH input (all pairs land in fixed bins), not an error
    line = np.stack([np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)], axis=1)
    f = compute_fpfh(line, np.tile([0, 0, 1.0], (10, 1)), FPFHParams(0.3, 10)).features
    assert np.isfinite(f).all()


def test_chunked_search_gives_identical_features(rng, monkeypatch):
    """Large clouds are processed in chunks (two searches); the result must not change."""
    from minegeo.features import fpfh as mod

    pts, nrm = _surface(rng, 2500)
    for w in ("inverse_distance", "open3d"):
        full = compute_fpfh(pts, nrm, FPFHParams(0.2, 40, w)).features
        monkeypatch.setattr(mod, "_CHUNK_ENTRIES", 40 * 1000)  # 1024-point chunks
        chunked = compute_fpfh(pts, nrm, FPFHParams(0.2, 40, w)).features
        monkeypatch.undo()
        assert np.array_equal(full, chunked)
