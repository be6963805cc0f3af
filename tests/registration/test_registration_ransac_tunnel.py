"""Global localization of tunnel sections in their map: FPFH + RANSAC + ICP, 20 seeds.

Issue 4 item 5 acceptance: random rigid motions (any rotation, up to 20 m) of local
sections of a synthetic rough T-junction are recovered inside the map. The pipeline is
minegeo end to end: voxel downsampling, PCA normals (map normals oriented towards the
drift axes, scan normals towards the scanner), FPFH (paper weight), RANSAC with the
Table 3 defaults except the distance threshold (1.5 voxels), point-to-plane ICP.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from tunnel_fixture_ransac import centerline, local_section, tunnel_map

from minegeo.features import FPFHParams, compute_fpfh
from minegeo.geometry import NormalParams, estimate_normals, voxel_downsample
from minegeo.geometry.se3 import invert, random_transform, rotation_angle, transform_points
from minegeo.registration import ICPParams, register_icp
from minegeo.registration.ransac import RansacParams, register_ransac

VOXEL = 0.5


@pytest.fixture(scope="module")
def tunnel():
    dense = tunnel_map(0, half_length=25.0, cross_length=20.0)
    M = voxel_downsample(dense, VOXEL).points
    nm = estimate_normals(M, NormalParams(radius_m=2 * VOXEL, max_nn=30),
                          orient_towards=centerline(25.0, 20.0)).normals
    fm = compute_fpfh(M, nm, FPFHParams(5 * VOXEL, 100)).features
    return dense, M, nm, fm


@pytest.mark.parametrize("seed", range(20))
def test_section_is_localized_in_its_map(tunnel, seed):
    dense, M, nm, fm = tunnel
    rng = np.random.default_rng(seed)
    c = np.array([rng.uniform(-18, 18), 0.0, 0.0]) if seed % 2 else np.array([0.0, rng.uniform(0.0, 15.0), 0.0])
    G = random_transform(rng, math.pi, 20.0)  # section frame -> scan frame (unknown to the method)
    scan = voxel_downsample(transform_points(G, local_section(dense, c, 10.0, rng)), VOXEL).points
    ns = estimate_normals(scan, NormalParams(radius_m=2 * VOXEL, max_nn=30),
                          orient_towards=transform_points(G, c[None])[0]).normals
    fs = compute_fpfh(scan, ns, FPFHParams(5 * VOXEL, 100)).features
    r = register_ransac(scan, M, fs, fm, RansacParams(distance_threshold_m=1.5 * VOXEL), seed=seed)
    assert r.status in ("converged", "max_validations") and r.fitness > 0.8
    icp = register_icp(scan, M, r.T_target_source,
                       ICPParams(max_correspondence_distance_m=VOXEL, method="point_to_plane"), target_normals=nm)
    T_true = invert(G)
    T = icp.T_target_source
    assert math.degrees(rotation_angle(T[:3, :3].T @ T_true[:3, :3])) < 1.0
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.15
    # RANSAC alone already lands within the ICP basin
    assert np.linalg.norm(transform_points(r.T_target_source, scan) - transform_points(T_true, scan), axis=1).max() < 2.0


def test_fpfh_weight_modes_match_about_equally_well(tunnel):
    """FPFH weight 1/d ([Baek2022 Eq. 6], default) vs Open3D's 1/d^2: fraction of putative matches that
    land within 2 voxels of the true position, on the same sections. Over 30 sections at three voxel
    sizes the paper weight won 23 times (docs/registration_features.md), but per section the two are
    within a few per cent; this test pins that the choice changes the descriptors, not the quality."""
    from minegeo.registration.correspondences import feature_correspondences

    dense, M, nm, _ = tunnel
    frac = {"inverse_distance": [], "open3d": []}
    fm = {w: compute_fpfh(M, nm, FPFHParams(5 * VOXEL, 100, w)).features for w in frac}
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        c = np.array([rng.uniform(-18, 18), 0.0, 0.0])
        G = random_transform(rng, math.pi, 20.0)
        scan = voxel_downsample(transform_points(G, local_section(dense, c, 10.0, rng)), VOXEL).points
        ns = estimate_normals(scan, NormalParams(radius_m=2 * VOXEL, max_nn=30),
                              orient_towards=transform_points(G, c[None])[0]).normals
        truth = transform_points(invert(G), scan)
        for w in frac:
            fs = compute_fpfh(scan, ns, FPFHParams(5 * VOXEL, 100, w)).features
            pairs = feature_correspondences(fs, fm[w]).pairs
            frac[w].append(np.mean(np.linalg.norm(truth[pairs[:, 0]] - M[pairs[:, 1]], axis=1) < 2 * VOXEL))
    assert frac["inverse_distance"] != frac["open3d"]
    assert abs(np.mean(frac["inverse_distance"]) - np.mean(frac["open3d"])) < 0.02, frac
    assert min(frac["inverse_distance"]) > 0.3 and min(frac["open3d"]) > 0.3, frac
