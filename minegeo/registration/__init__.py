"""minegeo.registration: correspondences, closed-form estimation, evaluation and ICP.

Public API
----------
umeyama, kabsch            closed-form rigid / similarity fit ([Baek2022 Eqs. 10-13])
pose_covariance            σ² I⁻¹ from a 6x6 information matrix
evaluate_registration      fitness and inlier RMSE ([Baek2022 Eq. 19], Open3D semantics)
build_target_index         reusable KD-tree over a target cloud
ICPParams, register_icp    point-to-point / point-to-plane ICP with information matrix
ICPResult, constraint_analysis
GICPParams, register_gicp  Generalized-ICP (Segal 2009; [Ren2019 Eqs. 1-6]), Open3D-compatible mode
GICPResult, estimate_gicp_covariances
warmup_scan_matching       compile the kernels a scan's localization reaches (another package's warm-up)
RansacParams, RansacResult, register_ransac
                           global registration by RANSAC on FPFH matches (Baek 2022 Sec. 2.3.2)
feature_correspondences, FeatureMatches
                           exact descriptor nearest neighbours (optionally mutual)

Internals
---------
loop                       the one registration loop (``run_loop``: search -> factor -> reduction ->
                           Gauss-Newton step on SE(3)/SE(2) -> termination) under ``register_icp``,
                           ``register_gicp`` and MAST's ``icp_point_to_line``; new factors plug in here
"""

from __future__ import annotations

import numpy as np

from minegeo.registration.correspondences import FeatureMatches, feature_correspondences
from minegeo.registration.estimation import kabsch, pose_covariance, umeyama
from minegeo.registration.evaluation import build_target_index, evaluate_registration
from minegeo.registration.gicp import GICPParams, GICPResult, estimate_gicp_covariances, register_gicp
from minegeo.registration.icp import ICPParams, ICPResult, ICPStatus, constraint_analysis, register_icp
from minegeo.registration.ransac import RansacParams, RansacResult, RansacStatus, register_ransac

__all__ = [
    "umeyama",
    "kabsch",
    "pose_covariance",
    "evaluate_registration",
    "build_target_index",
    "ICPParams",
    "ICPResult",
    "ICPStatus",
    "register_icp",
    "constraint_analysis",
    "GICPParams",
    "GICPResult",
    "register_gicp",
    "estimate_gicp_covariances",
    "RansacParams",
    "RansacResult",
    "RansacStatus",
    "register_ransac",
    "feature_correspondences",
    "FeatureMatches",
    "warmup_scan_matching",
]


def warmup_scan_matching() -> None:
    """Compile on tiny inputs the serial RANSAC/grid drivers and the indexed point-to-plane sums that a scan's
    localization reaches (a caller's warm-up that does not need the whole of :func:`_warmup`)."""
    from minegeo.registration import _kernels as K
    from minegeo.registration.ransac import _warmup as _ransac_warmup

    _ransac_warmup()
    P = np.zeros((4, 3))
    idx = np.arange(4, dtype=np.int64)
    K.point_to_plane_system_idx(P.copy(), P.copy(), np.tile([0.0, 0.0, 1.0], (4, 1)), idx, idx)


def _warmup() -> None:
    """Compile every Numba kernel of :mod:`minegeo.registration` on tiny inputs (serial and parallel drivers)."""
    from minegeo.kernels import kdtree as KD
    from minegeo.kernels import rigid
    from minegeo.registration import _kernels as K

    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    Q = P + 0.1
    N = np.tile(np.array([0.0, 0.0, 1.0]), (4, 1))
    T = np.eye(4)
    w = np.ones(4)
    out = np.empty((4, 3))
    K._transform_serial(P, T, out)
    K._transform_parallel(P, T, out)
    idx = np.arange(4, dtype=np.int64)
    sq = np.empty(4)
    valid = np.empty(4, dtype=np.bool_)
    K._gate_serial(P, Q, idx, 1.0, sq, valid)
    K._gate_parallel(P, Q, idx, 1.0, sq, valid)
    part = np.zeros(1)
    K._sum_serial(sq, part)
    K._sum_parallel(sq, part)
    K._moments_serial(P, Q, w, np.zeros((1, 7)), np.zeros((1, 10)))
    K._moments_parallel(P, Q, w, np.zeros((1, 7)), np.zeros((1, 10)))
    K._p2l_serial(P, Q, N, np.zeros((1, 28)))
    K._p2l_parallel(P, Q, N, np.zeros((1, 28)))
    K._moments_q_serial(Q, np.zeros((1, 9)))
    nb = np.array([[0, 1, 2, 3]] * 4, dtype=np.int64)
    K._pca_serial(P, nb, out)
    K._pca_parallel(P, nb, out)
    sw, mp, mq, W, vp = K.weighted_moments_kernel(P, Q, w)
    rigid.umeyama_from_moments(mp, mq, W, vp, False)
    rigid.umeyama_small_kernel(P, Q, False)
    K.point_to_plane_system_idx(P, Q, N, idx, idx)
    K.weighted_moments_idx(P, Q, idx, idx)
    tree = KD.kd_build(np.vstack([P, Q, P + 2.0, Q + 3.0]), 2)
    i_out = np.empty(4, dtype=np.int64)
    KD.kd_nn_serial(P, tree, 1.0, i_out, sq)
    KD.kd_nn_parallel(P, tree, 1.0, i_out, sq)
    from minegeo.registration import _kernels_gicp, _kernels_loop

    _kernels_gicp._warmup()
    _kernels_loop._warmup()
    from minegeo.registration import gicp

    gicp._warmup()
    # the RANSAC kernels of this package live in ransac.py (features engineer's module)
    import importlib

    try:
        ransac = importlib.import_module("minegeo.registration.ransac")
    except ImportError:
        ransac = None
    if ransac is not None and hasattr(ransac, "_warmup"):
        ransac._warmup()
