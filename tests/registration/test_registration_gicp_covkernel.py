"""The GICP covariance kernel (kNN + PCA normals, :mod:`minegeo.registration._kernels_gicp`) against its
references, bit for bit: the leaf-batched kNN against ``kd_knn`` (sorted by ``(sq, index)``), the
scalar (and two-at-a-time) Jacobi PCA against :func:`minegeo.kernels.eig3.pca_normal`, on tie-heavy,
degenerate and far-from-origin clouds, every driver."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.kernels.eig3 import pca_normal
from minegeo.kernels.kdtree import KD_LEAF, kd_build, kd_knn
from minegeo.registration import _kernels_gicp as KG


def _clouds():
    rng = np.random.default_rng(21)
    lat = np.round(rng.uniform(-1, 1, size=(500, 3)), 1)
    thin = rng.normal(size=(1500, 3)) * [1.0, 1.0, 1e-4]
    return {
        "lattice_dup": (np.vstack([lat, lat[:30]]), 20),
        "grid": (rng.integers(0, 5, size=(300, 3)).astype(float), 7),
        "coincident_runs": (rng.integers(0, 2, size=(300, 3)).astype(float), 20),  # leaves of ~37 equal points
        "line": (np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], 10),
        "thin_far": (thin + [1e6, 2e6, 300.0], 20),
        "tilted_plane": ((rng.uniform(size=(800, 3)) * [10, 10, 1e-3]) @ np.linalg.qr(rng.normal(size=(3, 3)))[0], 20),
        "all_equal": (np.zeros((30, 3)), 5),
        "fewer_than_k": (rng.normal(size=(7, 3)), 20),
        "two_points": (rng.normal(size=(2, 3)), 20),
        "noise": (rng.normal(size=(700, 3)), 20),
    }


def _reference(Q, tree, k, mode_open3d):
    """kd_knn (exact, sorted by (sq, index)) then pca_normal per point."""
    m = Q.shape[0]
    nb, sq = kd_knn(Q, tree, k)
    n, e, s = np.empty((m, 3)), np.empty((m, 3)), np.empty(m, np.int8)
    A, V, w, tmp = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(6)
    for i in range(m):
        pca_normal(Q, nb[i], k, i, i, mode_open3d, KG.DEGENERATE_RATIO, A, V, w, tmp, n, e, s)
    rk = np.full(m, np.inf) if k == m else np.sqrt(sq[:, k - 1])
    return n, e, s, nb, rk


@pytest.mark.parametrize("name", list(_clouds()))
@pytest.mark.parametrize("leaf", [KD_LEAF, 2, 5, 40])
@pytest.mark.parametrize("mode_open3d", [False, True])
def test_covariance_kernel_equals_knn_then_pca_normal(name, leaf, mode_open3d):
    Q, k = _clouds()[name]
    Q = np.ascontiguousarray(Q, dtype=float)
    m = Q.shape[0]
    kk = min(k, m)
    tree = kd_build(Q, leaf)
    ref = _reference(Q, tree, kk, mode_open3d)
    outs = []
    for fn in (KG.knn_normals_lists_serial, KG.knn_normals_tasks):
        o = (np.empty((m, 3)), np.empty((m, 3)), np.empty(m, np.int8), np.empty((m, kk), np.int64), np.empty(m))
        fn(Q, tree, kk, mode_open3d, KG.DEGENERATE_RATIO, *o)
        outs.append(o)
    for fn in (KG._knn_normals_serial, KG._knn_normals_parallel):
        o = (np.empty((m, 3)), np.empty((m, 3)), np.empty(m, np.int8))
        fn(Q, tree, kk, mode_open3d, KG.DEGENERATE_RATIO, *o)
        outs.append(o)
    for o in outs:
        for a, b in zip(o, ref, strict=False):
            assert np.array_equal(a, b, equal_nan=True)


def test_scalar_jacobi_pca_equals_pca_normal_on_random_neighbourhoods():
    """_pca_normal_minegeo and the interleaved pair version give pca_normal's bits (mode "minegeo")
    on neighbourhoods of every shape, including exact zeros off the diagonal and repeated points."""
    rng = np.random.default_rng(5)
    pts = []
    for scale in ([1, 1, 1], [1, 1, 1e-6], [1, 1e-7, 1e-7], [0, 0, 0], [1, 0, 0], [1, 1, 0]):
        for off in (0.0, 1e6):
            pts.append(rng.normal(size=(20, 3)) * scale + off)
    pts.append(np.round(rng.normal(size=(20, 3)), 0))
    P = np.ascontiguousarray(np.vstack(pts))
    g = P.shape[0] // 20
    nb = np.arange(P.shape[0], dtype=np.int64).reshape(g, 20)
    rows = nb[:, 0]  # the query of group i is its first point; every output goes to the query's row
    A, V, w, tmp = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(6)
    for cnt in (2, 3, 7, 20):
        ref, one, two = ((np.zeros((P.shape[0], 3)), np.zeros((P.shape[0], 3)), np.zeros(P.shape[0], np.int8))
                         for _ in range(3))
        for i in range(g):
            pca_normal(P, nb[i], cnt, rows[i], rows[i], False, KG.DEGENERATE_RATIO, A, V, w, tmp, *ref)
            KG._pca_normal_minegeo(P, nb[i], cnt, rows[i], KG.DEGENERATE_RATIO, *one)
        for i in range(0, g - 1, 2):
            KG._pca_normal_minegeo_x2(P, nb[i], cnt, rows[i], nb[i + 1], cnt, rows[i + 1], KG.DEGENERATE_RATIO, *two)
        KG._pca_normal_minegeo_x2(P, nb[0], 2, rows[0], nb[g - 1], cnt, rows[g - 1], KG.DEGENERATE_RATIO, *two)
        KG._pca_normal_minegeo(P, nb[0], cnt, rows[0], KG.DEGENERATE_RATIO, *two)
        for a, b in zip(one, ref, strict=True):
            assert np.array_equal(a[rows], b[rows], equal_nan=True)
        for a, b in zip(two, ref, strict=True):
            assert np.array_equal(a[rows], b[rows], equal_nan=True)
