"""GICP covariances of a frame's points from its own points and those of the frames before it.

A spinning LiDAR's sweep samples the floor and the roof along its laser rings, metres apart, so the
``k`` nearest neighbours of a point of one sweep (after voxel downsampling) mostly lie along its own
ring, and their PCA plane (the GICP plane model of the source point, [Ren2019 Eqs. 2-3]) follows the
ring line and the rock's relief along it rather than the surface. On the paper world's ramp (issue
29: a half turn on a 7° grade, where each keyframe's rotation has a roll part of about 0.6°), frames
deskewed with the truth and registered from their true pose to a local map built from the true poses
(the last five keyframes, 2 m apart) came out with a mean roll error of −0.076° (± 0.019°, 39
keyframes of the turn): 2.2° of world tilt summed over the ramp, about 0.7° of pitch error after the
local map's averaging, the front end's error with a perfect deskew. With each point's covariance taken
from the voxelised union of its sweep and the eight sweeps before it (0.8 s, moved into its frame by the
odometry's poses: the rings of nine places interleave) the same registrations err by −0.008°
(± 0.014°); with the four before, −0.012°. The points registered stay the frame's own.
"""

from __future__ import annotations

import numpy as np

from minegeo.geometry import NormalParams, voxel_downsample
from minegeo.kernels.kdtree import KD_LEAF, kd_build, kd_knn
from minegeo.registration import GICPParams, estimate_gicp_covariances
from minegeo.slam._kernels_covariance import plane_normals_from_lists

__all__ = ["covariances_with_history"]

#: a neighbourhood is collinear (isotropic covariance) when its middle eigenvalue is at most this
#: fraction of its largest (the default of :class:`minegeo.geometry.NormalParams`, the rule of
#: :func:`minegeo.registration.estimate_gicp_covariances`)
COLLINEAR_RATIO = NormalParams().degenerate_ratio


def covariances_with_history(points: np.ndarray, history: np.ndarray, params: GICPParams,
                             voxel_m: float | None = None) -> np.ndarray:
    """Plane-like GICP covariances ``C = I − (1 − ε) n nᵀ`` (n, 3, 3) of ``points`` (n, 3, sensor frame,
    m) from the PCA of each point's ``params.covariance_neighbours`` nearest points among ``points``
    and ``history`` (m, 3): the points of earlier frames moved into the same frame. The covariance
    is centred on the neighbourhood's mean; a collinear or coincident neighbourhood gets ``I``
    (:func:`minegeo.registration.estimate_gicp_covariances` given these normals: its formula and
    ``params.covariance_mode``)."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    Q = np.ascontiguousarray(np.concatenate([P, np.asarray(history, dtype=np.float64).reshape(-1, 3)]))
    if voxel_m is not None:  # one density over the frames: the frame's own ring no longer fills the neighbourhood
        Q = np.ascontiguousarray(voxel_downsample(Q, voxel_m).points)
    k = min(int(params.covariance_neighbours), Q.shape[0])
    idx, _ = kd_knn(P, kd_build(Q, KD_LEAF), k)
    normals = plane_normals_from_lists(Q, np.ascontiguousarray(idx), float(COLLINEAR_RATIO))
    return estimate_gicp_covariances(P, params, normals=normals)
