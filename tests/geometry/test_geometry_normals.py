"""PCA normals: naive twin, eigen-solvers, degenerate neighbourhoods, orientation, invariances."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_geometry import naive_neighbors, naive_normals, synthetic_tunnel

from minegeo.errors import InputError, TooFewPointsError
from minegeo.geometry import (
    STATUS_COINCIDENT,
    STATUS_COLLINEAR,
    STATUS_OK,
    STATUS_TOO_FEW,
    NeighborIndex,
    NormalParams,
    estimate_normals,
)
from minegeo.geometry.se3 import random_transform
from minegeo.kernels import eig3


def _angle_up_to_sign(a, b):
    """Angle (rad) between unit vectors, ignoring sign; stable for tiny angles."""
    c = np.abs(np.sum(a * b, axis=1))
    s = np.linalg.norm(np.cross(a, b), axis=1)
    return np.arctan2(s, c)


@pytest.fixture(scope="module")
def tunnel():
    return synthetic_tunnel(n=3000, seed=3)


def test_accurate_mode_matches_naive_eigh(tunnel):
    pts, _ = tunnel
    res = estimate_normals(pts, NormalParams(radius_m=0.5, max_nn=25))
    naive_nb = naive_neighbors(pts, pts, 0.5, 25)
    nrm, ev = naive_normals(pts, [i for i, _ in naive_nb])
    ok = res.status == STATUS_OK
    assert ok.mean() > 0.95
    np.testing.assert_array_equal(res.counts, [i.size for i, _ in naive_nb])
    assert _angle_up_to_sign(res.normals[ok], nrm[ok]).max() < 1e-9
    np.testing.assert_allclose(res.eigenvalues[ok], ev[ok], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(res.curvature[ok], ev[ok, 0] / ev[ok].sum(axis=1), rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-14)


def test_crowded_neighbourhoods_take_the_fallback_path_correctly():
    """More than max(4·max_nn, 128) points inside r: the unsorted collector overflows and the
    sorted search takes over; the neighbour sets must still be the max_nn nearest."""
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(400, 3)) * [1.0, 1.0, 0.05]
    for p in (NormalParams(radius_m=10.0, max_nn=6), NormalParams(radius_m=0.3, max_nn=6), NormalParams(max_nn=6)):
        res = estimate_normals(pts, p)
        naive_nb = naive_neighbors(pts, pts, p.radius_m, 6)
        nrm, _ = naive_normals(pts, [i for i, _ in naive_nb])
        ok = res.status == STATUS_OK
        assert ok.sum() > 300
        np.testing.assert_array_equal(res.counts, [i.size for i, _ in naive_nb])
        assert _angle_up_to_sign(res.normals[ok], nrm[ok]).max() < 1e-8


def test_radius_far_beyond_cap_uses_bounded_knn_with_the_same_neighbours(tunnel):
    """Dense cloud, radius >> max_nn-th neighbour (unreduced scan, 2 m normals): the fused
    search runs as a kNN bounded by the radius; neighbour sets equal the brute force."""
    pts, _ = tunnel
    idx = NeighborIndex(pts)
    assert idx._hybrid_plan(3.0, 60)[0]
    naive_nb = naive_neighbors(pts, pts, 3.0, 60)
    nrm, ev = naive_normals(pts, [i for i, _ in naive_nb])
    for mode in ("accurate", "open3d"):
        res = estimate_normals(pts, NormalParams(radius_m=3.0, max_nn=60, mode=mode), index=idx)
        ok = res.status == STATUS_OK
        assert ok.mean() > 0.95
        np.testing.assert_array_equal(res.counts, [i.size for i, _ in naive_nb])
        assert _angle_up_to_sign(res.normals[ok], nrm[ok]).max() < 1e-8
        np.testing.assert_allclose(res.eigenvalues[ok], ev[ok], rtol=1e-8, atol=1e-15)


def test_knn_mode_and_given_neighborhoods_agree(tunnel):
    pts, _ = tunnel
    for mode in ("accurate", "open3d"):
        nb = NeighborIndex(pts).knn(pts, 15)
        a = estimate_normals(pts, NormalParams(max_nn=15, mode=mode))
        b = estimate_normals(pts, NormalParams(max_nn=15, mode=mode), neighborhoods=nb)
        nbh = NeighborIndex(pts).hybrid(pts, 0.4, 20)
        c = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=20, mode=mode))
        d = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=20, mode=mode), neighborhoods=nbh)
        np.testing.assert_array_equal(a.counts, b.counts)
        np.testing.assert_array_equal(c.counts, d.counts)
        if mode == "open3d":  # both sum in (distance, index) order: bit-identical
            assert a.normals.tobytes() == b.normals.tobytes()
            assert c.normals.tobytes() == d.normals.tobytes()
        else:  # the fused path sums the same neighbours in collection order
            np.testing.assert_allclose(a.normals, b.normals, atol=1e-12)
            np.testing.assert_allclose(c.normals, d.normals, atol=1e-12)
            np.testing.assert_allclose(c.eigenvalues, d.eigenvalues, rtol=1e-10, atol=1e-18)


def _fast(C):
    out = np.empty(6)
    eig3.fast_eigen3x3(C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2], out)
    return out


def _jacobi(C):
    A = np.array(C, dtype=np.float64)
    V = np.empty((3, 3))
    w = np.empty(3)
    eig3.jacobi_eigh3(A, V, w)
    return w, V


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), kind=st.sampled_from(["random", "plane", "line", "repeated", "diag"]))
def test_eigen_solvers_match_numpy(seed, kind):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lam = {"random": rng.uniform(0.1, 2.0, 3), "plane": [0.0, 1.0, 2.0], "line": [0.0, 0.0, 1.0],
           "repeated": [0.5, 0.5, 2.0], "diag": rng.uniform(0.1, 2.0, 3)}[kind]
    C = np.diag(lam) if kind == "diag" else Q @ np.diag(lam) @ Q.T
    C = (C + C.T) / 2
    wn, Vn = np.linalg.eigh(C)
    w, V = _jacobi(C)
    np.testing.assert_allclose(w, wn, atol=1e-14)
    np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(C @ V, V * w, atol=1e-13)
    f = _fast(C)
    # the trigonometric closed form loses ~sqrt(eps) on (near-)repeated eigenvalues:
    # one reason the default "accurate" mode uses Jacobi instead
    np.testing.assert_allclose(f[3:], wn, atol=1e-7 * wn[2])
    if wn[1] - wn[0] > 1e-6:  # smallest eigenvector is well defined
        assert _angle_up_to_sign(f[None, :3], Vn[None, :, 0])[0] < 1e-7
        assert _angle_up_to_sign(V[None, :, 0], Vn[None, :, 0])[0] < 1e-12


def test_fast_eigen_special_cases():
    assert np.all(_fast(np.zeros((3, 3)))[:3] == 0.0)  # zero matrix -> zero vector
    assert np.array_equal(_fast(np.eye(3))[:3], [0.0, 0.0, 1.0])  # identity -> e_z (Open3D's <3 rule)
    assert np.array_equal(_fast(np.diag([1.0, 0.5, 2.0]))[:3], [0.0, 1.0, 0.0])


def test_perfect_plane_and_degenerate_neighbourhoods():
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2) * 0.1
    plane = np.c_[g, np.full(g.shape[0], 7.0)]
    for mode in ("accurate", "open3d"):
        r = estimate_normals(plane, NormalParams(radius_m=0.25, max_nn=30, mode=mode))
        assert np.all(r.status == STATUS_OK)
        np.testing.assert_allclose(np.abs(r.normals[:, 2]), 1.0, atol=1e-12)
        np.testing.assert_allclose(r.curvature, 0.0, atol=1e-12)
        ev = r.eigenvalues
        np.testing.assert_allclose(r.planarity, (ev[:, 1] - ev[:, 0]) / ev[:, 2])
        # interior points have a symmetric (isotropic in-plane) neighbourhood: planarity 1
        interior = r.counts == r.counts.max()
        np.testing.assert_allclose(r.planarity[interior], 1.0, atol=1e-12)
    # a line: normal undetermined -> flagged, still a unit vector perpendicular to the line
    line = np.c_[np.arange(20.0) * 0.1, np.zeros(20), np.zeros(20)]
    r = estimate_normals(line, NormalParams(radius_m=0.25, max_nn=10))
    assert np.all(r.status == STATUS_COLLINEAR)
    np.testing.assert_allclose(r.normals[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(r.normals, axis=1), 1.0)
    np.testing.assert_allclose(r.linearity, 1.0, atol=1e-12)
    # isolated points: fewer than 3 neighbours -> (0, 0, 1), NaN curvature
    iso = np.array([[0.0, 0, 0], [10.0, 0, 0], [10.05, 0, 0]])
    r = estimate_normals(iso, NormalParams(radius_m=0.5))
    assert np.all(r.status == STATUS_TOO_FEW)
    np.testing.assert_array_equal(r.normals, np.tile([0.0, 0.0, 1.0], (3, 1)))
    assert np.all(np.isnan(r.curvature))
    # coincident points
    r = estimate_normals(np.ones((5, 3)), NormalParams(radius_m=0.5))
    assert np.all(r.status == STATUS_COINCIDENT)
    np.testing.assert_array_equal(r.normals, np.tile([0.0, 0.0, 1.0], (5, 1)))
    assert r.n_flagged["coincident"] == 5


def test_orientation_towards_sensor_and_trajectory(tunnel):
    pts, axis = tunnel
    r = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30), orient_towards=axis)
    assert r.orientation == "trajectory"
    # tunnel normals point into the void: towards the drift axis
    to_axis = np.c_[-pts[:, 0], np.zeros(len(pts)), -pts[:, 2]]
    assert np.mean(np.sum(r.normals * to_axis, axis=1) > 0) > 0.99
    from minegeo.io import Trajectory

    poses = np.tile(np.eye(4), (axis.shape[0], 1, 1))
    poses[:, :3, 3] = axis
    rt = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30),
                          orient_towards=Trajectory(np.arange(axis.shape[0], dtype=float), poses))
    assert rt.orientation == "trajectory" and rt.normals.tobytes() == r.normals.tobytes()
    s = np.array([0.3, 4.0, -0.2])
    r = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30), orient_towards=s)
    assert r.orientation == "point"
    oriented = (r.status == STATUS_OK) | (r.status == STATUS_COLLINEAR)  # fallback normals are not flipped
    assert oriented.mean() > 0.9
    assert np.all(np.sum(r.normals * (s - pts), axis=1)[oriented] >= 0)
    r = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30, mode="open3d"))
    assert r.orientation == "solver"
    r = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30))
    assert r.orientation == "centroid"
    c = pts.mean(axis=0)
    assert np.all(np.sum(r.normals * (c - pts), axis=1)[oriented] >= 0)


def test_large_offset_accurate_mode_is_unaffected(tunnel):
    pts, _ = tunnel
    off = np.array([4.5e6, 6.8e6, 1.2e3])
    p = NormalParams(radius_m=0.4, max_nn=30)
    a = estimate_normals(pts, p)
    b = estimate_normals(pts + off, p)
    # adding the offset already rounds the input to ulp(6.8e6 m) ~ 1e-9 m; on 0.4 m
    # neighbourhoods with few points that moves the normal by ~1e-8 rad at most
    ang = _angle_up_to_sign(a.normals, b.normals)
    assert ang.max() < 1e-7
    assert np.median(ang) < 1e-9
    assert np.array_equal(a.status, b.status)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_rigid_motion_invariance(seed):
    rng = np.random.default_rng(seed)
    pts, _ = synthetic_tunnel(n=600, seed=seed % 1000)
    T = random_transform(rng, np.pi, 50.0)
    R, t = T[:3, :3], T[:3, 3]
    p = NormalParams(radius_m=0.8, max_nn=20)
    a = estimate_normals(pts, p)
    b = estimate_normals(pts @ R.T + t, p)
    ok = (a.status == STATUS_OK) & (b.status == STATUS_OK)
    # neighbourhoods may differ only for points at exactly the radius (measure zero): compare where equal
    same = ok & (a.counts == b.counts)
    assert same.mean() > 0.95
    an = a.normals[same] @ R.T
    assert _angle_up_to_sign(an, b.normals[same]).max() < 1e-8
    # centroid orientation is equivariant: signs agree away from grazing lines of sight
    c = pts.mean(axis=0)
    clear = np.abs(np.sum(a.normals[same] * (c - pts[same]), axis=1)) > 1e-6
    assert np.all(np.sum(an[clear] * b.normals[same][clear], axis=1) > 0)
    np.testing.assert_allclose(a.curvature[same], b.curvature[same], rtol=1e-6, atol=1e-12)


def test_deterministic_bitwise(tunnel):
    pts, axis = tunnel
    for mode in ("accurate", "open3d"):
        p = NormalParams(radius_m=0.4, max_nn=30, mode=mode)
        a = estimate_normals(pts, p, orient_towards=axis)
        b = estimate_normals(pts, p, orient_towards=axis)
        assert a.normals.tobytes() == b.normals.tobytes()
        assert a.eigenvalues.tobytes() == b.eigenvalues.tobytes()


def test_bad_input():
    pts = np.random.default_rng(0).random((10, 3))
    bad = pts.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError, match="row 4"):
        estimate_normals(bad)
    with pytest.raises(TooFewPointsError):
        estimate_normals(np.zeros((0, 3)))
    with pytest.raises(InputError):
        NormalParams(radius_m=0.0)
    with pytest.raises(InputError):
        NormalParams(max_nn=0)
    with pytest.raises(InputError):
        NormalParams(mode="fast")
    with pytest.raises(InputError):
        estimate_normals(pts, orient_towards="sky")
    with pytest.raises(InputError):
        estimate_normals(pts, orient_towards=np.array([0.0, np.inf, 0.0]))
    with pytest.raises(InputError):
        estimate_normals(pts, neighborhoods=NeighborIndex(pts[:5]).knn(pts[:5], 3))
    # fewer points than max_nn is fine: all points are used
    r = estimate_normals(pts[:4], NormalParams(max_nn=30))
    assert np.all(r.counts == 4)


def test_thread_count_does_not_change_bits(tunnel):
    import numba

    pts, axis = tunnel
    p = NormalParams(radius_m=0.4, max_nn=30)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        a = estimate_normals(pts, p, orient_towards=axis)
        na = NeighborIndex(pts).hybrid(None, 0.4, 30)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        b = estimate_normals(pts, p, orient_towards=axis)
        nb = NeighborIndex(pts).hybrid(None, 0.4, 30)
    finally:
        numba.set_num_threads(before)
    assert a.normals.tobytes() == b.normals.tobytes()
    assert a.eigenvalues.tobytes() == b.eigenvalues.tobytes()
    assert na.indices.tobytes() == nb.indices.tobytes()
