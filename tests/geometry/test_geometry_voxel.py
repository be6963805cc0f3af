"""Voxel downsampling against the naive dict twin (Open3D centroid semantics)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_geometry import naive_voxel

from minegeo.errors import InputError, TooFewPointsError
from minegeo.geometry import voxel_downsample


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(11)
    pts = rng.normal(size=(3000, 3)) * [2.0, 1.0, 0.5]
    nrm = rng.normal(size=(3000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm[[5, 17, 400]] = np.nan
    return pts, nrm


@pytest.mark.parametrize("v", [0.05, 0.25, 1.0, 10.0])
def test_matches_naive_exactly(cloud, v):
    pts, nrm = cloud
    res = voxel_downsample(pts, v, normals=nrm)
    ref = naive_voxel(pts, v, nrm)
    assert res.points.shape[0] == len(ref)
    for k in range(res.points.shape[0]):
        p, n, c = ref[tuple(res.voxel_keys[k].tolist())]
        assert res.counts[k] == c
        assert np.array_equal(res.points[k], p)  # same sums in input order: bit-identical
        assert np.array_equal(res.normals[k], n)
    # output sorted by voxel key, bookkeeping consistent
    keys = res.voxel_keys
    assert np.all(np.lexsort(keys.T[::-1]) == np.arange(keys.shape[0]))
    assert res.counts.sum() == pts.shape[0]
    np.testing.assert_array_equal(np.bincount(res.point_voxel), res.counts)
    np.testing.assert_allclose(res.origin, pts.min(axis=0) - v / 2)


def test_normals_not_renormalised_and_attributes(cloud):
    pts = np.array([[0.0, 0, 0], [0.01, 0, 0], [5.0, 5, 5]])
    nrm = np.array([[1.0, 0, 0], [0.0, 1, 0], [np.nan, 0, 0]])
    res = voxel_downsample(pts, 1.0, normals=nrm,
                           attributes={"intensity": np.array([1.0, 2.0, 7.0]), "cls": np.array([3, 4, 5]),
                                       "rgb": np.array([[0.0, 2, 4], [2, 2, 2], [1, 1, 1]])})
    np.testing.assert_allclose(res.normals[0], [0.5, 0.5, 0.0])  # length 0.707, not renormalised
    np.testing.assert_array_equal(res.normals[1], [0.0, 0.0, 0.0])  # NaN normal skipped, divided by count 1
    np.testing.assert_allclose(res.attributes["intensity"], [1.5, 7.0])
    np.testing.assert_array_equal(res.attributes["cls"], [3, 5])  # integer attribute: first point's value
    np.testing.assert_allclose(res.attributes["rgb"], [[1.0, 2, 3], [1, 1, 1]])
    assert res.normals is not None and voxel_downsample(pts, 1.0).normals is None


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), v=st.floats(0.05, 2.0))
def test_permutation_invariant_as_sets(seed, v):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-3, 3, (400, 3))
    perm = rng.permutation(400)
    a = voxel_downsample(pts, v)
    b = voxel_downsample(pts[perm], v)
    np.testing.assert_array_equal(a.voxel_keys, b.voxel_keys)  # same voxels, same (sorted) order
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-12)  # only summation order differs


def test_deterministic_bitwise(cloud):
    pts, nrm = cloud
    a = voxel_downsample(pts, 0.2, normals=nrm)
    b = voxel_downsample(pts, 0.2, normals=nrm)
    assert a.points.tobytes() == b.points.tobytes() and a.normals.tobytes() == b.normals.tobytes()


def test_bad_input(cloud):
    pts, _ = cloud
    for v in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(InputError):
            voxel_downsample(pts, v)
    bad = pts.copy()
    bad[7] = [np.inf, 0, 0]
    with pytest.raises(InputError, match="row 7"):
        voxel_downsample(bad, 0.1)
    with pytest.raises(TooFewPointsError):
        voxel_downsample(np.zeros((0, 3)), 0.1)
    with pytest.raises(InputError):
        voxel_downsample(pts, 0.1, normals=np.zeros((3, 3)))
    with pytest.raises(InputError):
        voxel_downsample(np.array([[0.0, 0, 0], [1e6, 0, 0]]), 1e-4)  # index overflow (Open3D limit)
    with pytest.raises(InputError):
        voxel_downsample(pts, 0.1, attributes={"i": np.zeros(5)})
    one = voxel_downsample(np.array([[1.0, 2.0, 3.0]]), 0.5)
    np.testing.assert_array_equal(one.points, [[1.0, 2.0, 3.0]])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), bits=st.integers(1, 62), n=st.integers(0, 3000))
def test_radix_argsort_equals_numpy_stable(seed, bits, n):
    from minegeo.geometry._kernels import radix_argsort

    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 2**bits, n, dtype=np.int64)
    keys[: n // 3] = keys[0] if n else 0  # plenty of ties
    np.testing.assert_array_equal(radix_argsort(keys), np.argsort(keys, kind="stable"))
