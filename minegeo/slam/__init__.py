"""minegeo.slam: LiDAR SLAM building blocks (Ren et al. 2019).

* :mod:`minegeo.slam.odometry`: GICP odometry between frames and keyframes (Ren et al. 2019 Sec. 3.3);
* :mod:`minegeo.slam.loops`: rule-based loop closure verified by GICP (Sec. 3.4.1);
* :mod:`minegeo.slam.posegraph`: pose-graph optimisation (Levenberg–Marquardt on the Lie algebra,
  sparse normal equations) with the cost of ``slam_contract.md``; g2o files in :mod:`minegeo.io.g2o`;
* :mod:`minegeo.slam.mapping`: roadway noise removal of the map (Sec. 3.5);
* :mod:`minegeo.slam.evaluate`: ATE / RPE as evo computes them.
"""


def _warmup() -> None:
    """Compile the pose-graph kernels (SE(3) and SE(2) edge terms and residuals) on tiny graphs."""
    import numpy as np

    from minegeo.optim import between_residuals, between_terms

    for kind, d in (("SE3", 4), ("SE2", 3)):
        poses = np.tile(np.eye(d), (2, 1, 1))
        edges = np.array([[0, 1]], dtype=np.int64)
        Z = np.eye(d)[None].copy()
        between_terms(kind, poses, edges, Z)
        between_residuals(kind, poses, edges, Z)
    _warmup_solver()
    _warmup_planes_and_map()


def _warmup_solver() -> None:
    """Run the Levenberg–Marquardt solver on a tiny SE(3) and SE(2) loop (block Cholesky path)."""
    import numpy as np

    from minegeo.io.g2o import PoseGraph
    from minegeo.slam.posegraph import optimize_pose_graph

    for kind, d, m in (("SE3", 4, 6), ("SE2", 3, 3)):
        poses = np.tile(np.eye(d), (4, 1, 1))
        for k in range(4):
            poses[k, 0, d - 1] = float(k)
        edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]], dtype=np.int64)
        Z = np.stack([np.linalg.solve(poses[i], poses[j]) for i, j in edges])
        Z[:, 1, d - 1] += 0.01
        graph = PoseGraph(kind, np.arange(4, dtype=np.int64), poses, edges, Z, np.tile(np.eye(m), (4, 1, 1)))
        optimize_pose_graph(graph)


def _warmup_planes_and_map() -> None:
    """Compile the floor-plane, pose–plane and map noise-removal kernels on a tiny roadway."""
    import numpy as np

    from minegeo.slam.mapping import remove_roadway_noise
    from minegeo.slam.planes import extract_floor_plane, pose_plane_residuals, pose_plane_terms

    g = np.linspace(-2.0, 2.0, 9)
    x, y = np.meshgrid(np.linspace(0.0, 4.0, 9), g)
    floor = np.c_[x.ravel(), y.ravel(), np.full(x.size, -2.0)]
    walls = np.concatenate([np.c_[x.ravel(), np.full(x.size, s), (y.ravel() + 2.0) * 0.5 - 2.0] for s in (-2.0, 2.0)])
    roof = floor + [0.0, 0.0, 4.0]
    cloud = np.concatenate([floor, walls, roof])
    extract_floor_plane(cloud, np.array([2.0, 0.0, 0.0]), seed=0)
    poses = np.eye(4)[None].copy()
    planes = np.array([[0.0, 0.0, 1.0, 2.0]])
    edges = np.array([[0, 0]], dtype=np.int64)
    pose_plane_terms(poses, planes, edges, planes)
    pose_plane_residuals(poses, planes, edges, planes)
    remove_roadway_noise(cloud, np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.0]]))
