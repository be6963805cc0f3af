"""minegeo.registration: correspondences, closed-form estimation, evaluation and ICP.

Public API
----------
umeyama, kabsch            closed-form rigid / similarity fit (Baek 2022 Eqs. 10-13)
pose_covariance            σ² I⁻¹ from a 6x6 information matrix
evaluate_registration      fitness and inlier RMSE (Baek 2022 Eq. 19, Open3D semantics)
build_target_index         reusable KD-tree over a target cloud
ICPParams, register_icp    point-to-point / point-to-plane ICP with information matrix
ICPResult, constraint_analysis
"""

from __future__ import annotations

import numpy as np

from minegeo.registration.estimation import kabsch, pose_covariance, umeyama
from minegeo.registration.evaluation import build_target_index, evaluate_registration
from minegeo.registration.icp import ICPParams, ICPResult, constraint_analysis, register_icp

__all__ = [
    "umeyama",
    "kabsch",
    "pose_covariance",
    "evaluate_registration",
    "build_target_index",
    "ICPParams",
    "ICPResult",
    "register_icp",
    "constraint_analysis",
]


def _warmup() -> None:
    """Compile every Numba kernel of :mod:`minegeo.registration` on tiny inputs."""
    from minegeo.registration import _kernels as K

    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    Q = P + 0.1
    N = np.tile(np.array([0.0, 0.0, 1.0]), (4, 1))
    T = np.eye(4)
    K.transform_points_kernel(P, T)
    K.rotate_vectors_kernel(N, T[:3, :3].copy())
    K.gate_nearest_kernel(P, Q, np.arange(4, dtype=np.int64), 1.0)
    K.sum_kernel(P[:, 0].copy())
    sw, mp, mq, W, vp = K.weighted_moments_kernel(P, Q, np.ones(4))
    K.umeyama_from_moments(mp, mq, W, vp, False)
    K.umeyama_small_kernel(P, Q, False)
    K.point_to_plane_system_kernel(P, Q, N)
    K.point_to_point_information_kernel(Q)
