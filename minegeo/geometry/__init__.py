"""minegeo.geometry: SE(3) helpers, downsampling (voxel, octree), neighbour search, normals.

Public API
----------
NeighborIndex, Neighborhoods          exact kNN / radius / hybrid search (Open3D semantics)
estimate_normals, NormalParams, NormalsResult
                                      PCA normals ([Baek2022 Eq. 2]), curvature, planarity
voxel_downsample, VoxelResult         Open3D-compatible voxel-centroid downsampling
Octree, octree_downsample, OctreeDownsampleResult
                                      linear octree; closest-to-centre subsampling (Baek et al. 2022, Sec. 2.2)
"""

from __future__ import annotations

import numpy as np

from minegeo.geometry.neighbors import Neighborhoods, NeighborIndex
from minegeo.geometry.normals import (
    STATUS_COINCIDENT,
    STATUS_COLLINEAR,
    STATUS_OK,
    STATUS_TOO_FEW,
    NormalParams,
    NormalsResult,
    estimate_normals,
)
from minegeo.geometry.octree import MAX_OCTREE_DEPTH, Octree, OctreeDownsampleResult, octree_downsample
from minegeo.geometry.voxel import VoxelResult, voxel_downsample

__all__ = [
    "NeighborIndex",
    "Neighborhoods",
    "NormalParams",
    "NormalsResult",
    "estimate_normals",
    "STATUS_OK",
    "STATUS_TOO_FEW",
    "STATUS_COLLINEAR",
    "STATUS_COINCIDENT",
    "voxel_downsample",
    "VoxelResult",
    "Octree",
    "OctreeDownsampleResult",
    "octree_downsample",
    "MAX_OCTREE_DEPTH",
]


def _warmup() -> None:
    """Compile (or load from cache) every Numba kernel of the package on tiny inputs."""
    rng = np.random.default_rng(0)
    pts = rng.random((40, 3))
    idx = NeighborIndex(pts)
    idx.hybrid(pts, 0.5, 8)
    idx.radius(pts, 0.3)
    idx.knn(pts, 4)
    for mode in ("accurate", "open3d"):
        estimate_normals(pts, NormalParams(radius_m=0.5, max_nn=8, mode=mode), orient_towards=np.zeros(3))
        estimate_normals(pts, NormalParams(max_nn=5, mode=mode))
    vr = voxel_downsample(pts, 0.3, normals=pts, attributes={"i": pts[:, 0]})
    assert vr.points.shape[0] > 0
    tree = Octree(pts, 3)
    tree.downsample()
    tree.radius(pts[0], 0.3)
    tree.box(pts[0] - 0.2, pts[0] + 0.2)
    tree.leaf_of(pts[:3])
