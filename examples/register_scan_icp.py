"""Point-to-plane ICP: refine a scan's pose in the mine map from a rough start.

What a surveyor learns: how ``minegeo.registration.register_icp`` (Baek et al. 2022 Sec. 2.4,
point-to-plane as in Low 2004) pulls a local scan onto the prior map when the start is off by
~3 deg and ~0.8 m (e.g. a tape-and-compass setup), how close it gets to the true pose
``T_map_scan``, and which quality numbers to read: fitness (share of scan points with a map
partner within the gate), inlier RMSE, iterations, and the degeneracy check of the 6x6
information matrix (a straight, featureless drift would be flagged). Synthetic small mine; its
quick map is sparse (3 deg sensor azimuth step), so expect a few mm and a few arc-minutes, not better.
Usage: ``python examples/register_scan_icp.py``.
"""

import numpy as np

from minegeo.geometry import NormalParams, estimate_normals, voxel_downsample
from minegeo.geometry.se3 import invert, random_transform, rotation_angle
from minegeo.registration import ICPParams, register_icp
from minegeo.synth import Velodyne16, build_map, build_world, local_scan

world = build_world("small", 1)
mine_map = voxel_downsample(build_map(world, seed=1).points, 0.1).points
scan, _, T_true = local_scan(world, "curve", 20.0, Velodyne16(), seed=2, max_rays=15_000)
src = voxel_downsample(scan.points, 0.1).points
normals = estimate_normals(mine_map, NormalParams(radius_m=0.5, max_nn=30)).normals

T_start = random_transform(np.random.default_rng(4), np.radians(3.0), 0.8) @ T_true
for gate_m in (1.0, 0.3, 0.15):  # coarse-to-fine gate, metres
    res = register_icp(src, mine_map, T_start, ICPParams(gate_m, max_iterations=50, method="point_to_plane"),
                       target_normals=normals)
    T_start = res.T_target_source
    print(f"gate {gate_m} m: fitness {res.fitness:.3f}, inlier RMSE {res.inlier_rmse_m * 1000:.1f} mm, "
          f"{res.iterations} iterations, converged {res.converged}, degenerate {res.degenerate}")
E = invert(T_true) @ res.T_target_source
print(f"scan points {len(src)}, map points {len(mine_map)}")
print(f"error vs truth: {np.linalg.norm(E[:3, 3]) * 1000:.1f} mm, {np.degrees(rotation_angle(E[:3, :3])) * 3600:.0f} arcsec")
print(f"constraint eigenvalues (normalised) {np.array2string(res.constraint_eigenvalues, precision=3)}, "
      f"weakest/strongest {res.degeneracy_ratio:.4f} (flagged below {res.params.degeneracy_ratio_threshold})")
