"""Real data: the DARPA SubT Urban (Satsop) below-grade survey scan is split into two disjoint
random halves; the map is prepared from one half only, and scans are cropped from the other half
and moved by known random rigid motions. No scan point is a map point, so the pipeline must place
independent samples of the same real surfaces, as with a new scan of a surveyed mine.

Tolerance (derived, not observed): ``TOL_M`` = 0.05 m on the largest error over *every* scan
point, i.e. half the 0.1 m ICP voxel on both sides (``PrepareParams.icp_voxel_size_m``,
``LocalizeParams.scan_icp_voxel_size_m``). Point-to-plane ICP pairs voxel centroids of the scan
with voxel centroids of the map: on a plane a centroid lies on the surface, at an edge or corner it
sits up to about half a voxel inside it, and the two halves' grids differ (the scan is moved), so
that offset is a systematic error ICP cannot remove. The random part is far below it: the
surface noise is ~0.04 m (the pipeline's own ``scan_noise_m``), averaged over ~10^4 ICP pairs,
sigma/sqrt(N) ~ 0.5 mm, or a few mm with spatially correlated residuals. A wrong ICP fixed point
is at least a map voxel (0.1 m) away. The rotation bound follows from the same 0.05 m at the scan
point farthest from the scan centroid, and the error must also lie within twice the reported
95 % displacement bound (the pose covariance must cover the actual error).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import shared_data

from minegeo.geometry.se3 import random_transform
from minegeo.io.types import PointCloud
from minegeo.localize import LocalizeParams, PrepareParams, localize_scan, prepare_map
from minegeo.localize.pipeline import error_vs_truth

TOL_M = 0.05  # half the 0.1 m ICP voxel (module docstring)
SPLIT_SEED = 20


@pytest.fixture(scope="module")
def satsop():
    from minegeo.io import read_point_cloud

    cloud = read_point_cloud(shared_data("subt_urban_satsop_scan", "Urban_Circuit_LowRes_Scan_alpha_LowerFloor.pcd.zip"))
    P = cloud.points
    in_map = np.random.default_rng(SPLIT_SEED).random(P.shape[0]) < 0.5
    assert 0.45 < in_map.mean() < 0.55
    pm = prepare_map(PointCloud(points=P[in_map], origin=cloud.origin), PrepareParams.fast())
    return cloud, P[in_map], P[~in_map], pm


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_satsop_scan_from_other_half_localized(satsop, seed):
    from scipy.spatial import cKDTree

    cloud, map_pts, rest, pm = satsop
    rng = np.random.default_rng(seed)
    centre = rest[rng.integers(rest.shape[0])]
    piece = rest[np.all(np.abs(rest[:, :2] - centre[:2]) < 10.0, axis=1)]  # ~20 m x 20 m of the other half
    assert piece.shape[0] > 5000
    # independent of the map's samples: no scan point coincides with a map point
    assert cKDTree(map_pts).query(piece)[0].min() > 0.0
    T = random_transform(rng, np.pi, 100.0)  # any rotation, up to 100 m away
    scan = piece @ T[:3, :3].T + T[:3, 3]
    T_true = np.linalg.inv(T)
    T_true[:3, 3] += cloud.origin  # map frame = points + origin
    r = localize_scan(pm, scan, None, LocalizeParams.fast(), seed=seed)
    assert r.status == "ok", r.reason
    e = error_vs_truth(r.T_map_scan, T_true, scan)
    r_max = float(np.linalg.norm(scan - scan.mean(axis=0), axis=1).max())
    assert e["max_point_error_m"] <= TOL_M, e
    assert e["rotation_deg"] <= math.degrees(TOL_M / r_max), (e, r_max)
    assert e["max_point_error_m"] <= 2.0 * r.displacement_95_m, (e, r.displacement_95_m)
