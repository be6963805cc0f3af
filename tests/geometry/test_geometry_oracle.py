"""Open3D 0.20 as oracle for voxel downsampling, neighbour search, normals and the octree."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_open3d, shared_data
from reference.naive_geometry import synthetic_tunnel

from minegeo.geometry import NeighborIndex, NormalParams, Octree, estimate_normals, voxel_downsample

pytestmark = pytest.mark.oracle


def _o3d_cloud(o3d, pts, normals=None):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd


def _angle(a, b, signed=False):
    c = np.sum(a * b, axis=1)
    if not signed:
        c = np.abs(c)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), c)


@pytest.fixture(scope="module")
def bunny():
    from minegeo.io import read_point_cloud

    return read_point_cloud(shared_data("pcl_bunny_icp", "bun0.pcd")).points


@pytest.fixture(scope="module")
def tunnel():
    return synthetic_tunnel(n=4000, seed=21)


def test_voxel_downsample_equals_open3d_as_sets(tunnel):
    o3d = require_open3d()
    pts, _ = tunnel
    rng = np.random.default_rng(0)
    nrm = rng.normal(size=pts.shape)
    nrm[::97] = np.nan
    for v in (0.05, 0.2, 0.7):
        d = _o3d_cloud(o3d, pts, nrm).voxel_down_sample(v)
        A, An = np.asarray(d.points), np.asarray(d.normals)
        res = voxel_downsample(pts, v, normals=nrm)
        ia, ib = np.lexsort(A.T[::-1]), np.lexsort(res.points.T[::-1])
        assert A.shape == res.points.shape
        np.testing.assert_array_equal(A[ia], res.points[ib])
        np.testing.assert_array_equal(An[ia], res.normals[ib])


@pytest.mark.parametrize("which", ["bunny", "tunnel"])
def test_radius_and_hybrid_equal_kdtreeflann(which, bunny, tunnel):
    o3d = require_open3d()
    pts = bunny if which == "bunny" else tunnel[0]
    r = 0.01 if which == "bunny" else 0.3
    tree = o3d.geometry.KDTreeFlann(_o3d_cloud(o3d, pts))
    idx = NeighborIndex(pts)
    q = pts[:: max(1, pts.shape[0] // 300)]
    rad = idx.radius(q, r)
    hyb = idx.hybrid(q, r, 12)
    for i, qq in enumerate(q):
        _, ii, dd = tree.search_radius_vector_3d(qq, r)
        assert set(np.asarray(ii).tolist()) == set(rad.row(i).tolist())
        np.testing.assert_allclose(np.sort(np.asarray(dd)), rad.sq_distances[i, : rad.counts[i]], rtol=1e-12, atol=0)
        _, ii, dd = tree.search_hybrid_vector_3d(qq, r, 12)
        dd = np.asarray(dd)
        ours = hyb.sq_distances[i, : hyb.counts[i]]
        np.testing.assert_allclose(dd, ours, rtol=1e-12, atol=0)  # same distances, same order
        # sets are equal unless points tie at the cut-off distance (Open3D keeps traversal order there)
        if ours.size:
            row_all = rad.sq_distances[i, : rad.counts[i]]
            if np.count_nonzero(row_all == ours[-1]) == np.count_nonzero(ours == ours[-1]):
                assert set(np.asarray(ii).tolist()) == set(hyb.row(i).tolist())


def test_knn_equals_kdtreeflann(bunny):
    o3d = require_open3d()
    tree = o3d.geometry.KDTreeFlann(_o3d_cloud(o3d, bunny))
    nb = NeighborIndex(bunny).knn(None, 10)
    for i in range(bunny.shape[0]):
        _, ii, dd = tree.search_knn_vector_3d(bunny[i], 10)
        np.testing.assert_allclose(np.asarray(dd), nb.sq_distances[i], rtol=1e-12, atol=0)
        if np.count_nonzero(np.asarray(dd) == dd[-1]) == 1:  # untied cut-off: same set
            assert set(np.asarray(ii).tolist()) == set(nb.row(i).tolist())


@pytest.mark.parametrize("which", ["bunny", "tunnel"])
@pytest.mark.parametrize("search", ["hybrid", "knn"])
def test_normals_equal_open3d(which, search, bunny, tunnel):
    o3d = require_open3d()
    pts = bunny if which == "bunny" else tunnel[0]
    r = 0.02 if which == "bunny" else 0.4
    if search == "hybrid":
        sp, radius = o3d.geometry.KDTreeSearchParamHybrid(r, 30), r
    else:
        sp, radius = o3d.geometry.KDTreeSearchParamKNN(30), None
    pcd = _o3d_cloud(o3d, pts)  # fresh cloud: no stored normals/covariances to be reused
    pcd.estimate_normals(sp)
    ref = np.asarray(pcd.normals)
    exact = estimate_normals(pts, NormalParams(radius_m=radius, max_nn=30, mode="open3d"))
    assert _angle(exact.normals, ref, signed=True).max() < 1e-6  # signs equal too
    acc = estimate_normals(pts, NormalParams(radius_m=radius, max_nn=30))
    ok = acc.status == 0
    assert _angle(acc.normals[ok], ref[ok]).max() < 1e-6  # equal up to sign


def test_large_offset_default_mode_beats_open3d(tunnel):
    """At 10^6 m offsets Open3D's raw-moment covariance cancels; minegeo's centred one does not."""
    o3d = require_open3d()
    pts, _ = tunnel
    off = np.array([5.0e6, 4.5e6, 1.0e3])
    far = pts + off
    base = estimate_normals(pts, NormalParams(radius_m=0.4, max_nn=30)).normals
    ours = estimate_normals(far, NormalParams(radius_m=0.4, max_nn=30))
    pcd = _o3d_cloud(o3d, far)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(0.4, 30))
    theirs = np.asarray(pcd.normals)
    ok = ours.status == 0
    e_ours = _angle(ours.normals[ok], base[ok])
    e_o3d = _angle(theirs[ok], base[ok])
    assert np.median(e_ours) < 1e-9 and e_ours.max() < 1e-6
    assert np.median(e_o3d) > 1e3 * np.median(e_ours)
    assert e_ours.max() < e_o3d.max()
    # our open3d mode reproduces Open3D's degraded normals at the offset too
    mine_o3d = estimate_normals(far, NormalParams(radius_m=0.4, max_nn=30, mode="open3d")).normals
    assert np.median(_angle(mine_o3d[ok], theirs[ok])) < 1e-6


@pytest.mark.parametrize("level", [2, 5])
def test_octree_leaves_equal_open3d(tunnel, level):
    o3d = require_open3d()
    pts, _ = tunnel
    oc = o3d.geometry.Octree(max_depth=level)
    oc.convert_from_point_cloud(_o3d_cloud(o3d, pts), size_expand=0.01)
    leaves = []

    def collect(node, info):
        if isinstance(node, o3d.geometry.OctreeLeafNode):
            leaves.append(sorted(node.indices))
        return False

    oc.traverse(collect)
    tree = Octree(pts, level)
    np.testing.assert_array_equal(np.asarray(oc.origin), tree.origin)
    assert oc.size == tree.size
    mine = [tree.leaf_points(k).tolist() for k in range(tree.n_leaves)]
    assert sorted(leaves) == sorted(mine)
