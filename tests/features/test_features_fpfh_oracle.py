"""FPFH against Open3D 0.20 ``compute_fpfh_feature`` (issue 4 item 4 acceptance).

Both libraries get the same points and the same (Open3D-estimated) normals; the
neighbourhoods are each library's own hybrid search, which agree except for the order
of exact distance ties. Agreement: relative L1 difference per point <= 1e-6.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_open3d, shared_data

from minegeo.features import FPFHParams, compute_fpfh


def _tunnel_section(seed=0, n=6000):
    """Drift section with an irregular arched wall and a floor (m), seeded."""
    rng = np.random.default_rng(seed)
    th = rng.uniform(-0.7, np.pi + 0.7, n)
    y = rng.uniform(0, 12.0, n)
    r = 2.5 + 0.15 * np.sin(3 * th + 1.0) * np.cos(0.9 * y) + 0.1 * np.sin(7 * th) * np.sin(2.1 * y)
    wall = np.stack([r * np.cos(th), y, r * np.sin(th)], axis=1)
    wall = wall[wall[:, 2] > -1.6]
    m = n // 4
    floor = np.stack([rng.uniform(-1.9, 1.9, m), rng.uniform(0, 12.0, m), -1.6 + 0.01 * rng.standard_normal(m)], 1)
    return np.vstack([wall, floor])


def _compare(o3d, pts, normal_radius, radius, max_nn):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    nrm = np.asarray(pcd.normals).copy()
    ref = np.asarray(
        o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius, max_nn)).data
    ).T
    got = compute_fpfh(pts, nrm, FPFHParams(radius, max_nn, "open3d")).features
    rel = np.abs(got - ref).sum(axis=1) / np.maximum(np.abs(ref).sum(axis=1), 1e-300)
    return rel, got, ref


@pytest.mark.oracle
def test_fpfh_matches_open3d_on_bunny():
    o3d = require_open3d()
    pts = np.asarray(o3d.io.read_point_cloud(str(shared_data("pcl_bunny_icp", "bun0.pcd"))).points, dtype=np.float64)
    for radius, max_nn in ((0.025, 100), (0.012, 30)):
        rel, got, ref = _compare(o3d, pts, 0.01, radius, max_nn)
        assert rel.max() <= 1e-6, (radius, max_nn, rel.max())
        assert np.array_equal(got.sum(axis=1) > 0, ref.sum(axis=1) > 0)


@pytest.mark.oracle
def test_fpfh_matches_open3d_on_tunnel_section():
    o3d = require_open3d()
    pts = _tunnel_section()
    rel, got, ref = _compare(o3d, pts, 0.5, 1.25, 100)
    assert rel.max() <= 1e-6, rel.max()
    assert np.array_equal(got.sum(axis=1) > 0, ref.sum(axis=1) > 0)
