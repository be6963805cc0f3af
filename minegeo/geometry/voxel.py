"""Voxel-grid downsampling with Open3D 0.20 ``VoxelDownSample`` centroid semantics.

With voxel edge ``v`` and the cloud's bounds ``[b_min, b_max]``:

1. grid origin ``o = b_min − v/2`` (every axis);
2. voxel key ``k_i = floor((p_i − o) / v)`` (integer, per axis);
3. each output point is the arithmetic mean of its voxel's points, summed in input order
   in float64 and divided by the count;
4. normals are summed skipping rows that contain a NaN, divided by the **total** count,
   and **not** renormalised (their length < 1 measures how much they disagree).

The only deliberate difference from Open3D is the output order: Open3D emits voxels in
its hash-map iteration order; minegeo emits them sorted lexicographically by voxel key
(kx, then ky, then kz), which is deterministic and independent of the input order.
See ``shared/specs/open3d_oracle.md`` §2.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError
from minegeo.geometry import _kernels as K

__all__ = ["VoxelResult", "voxel_downsample"]

_INT_MAX = 2**31 - 1


@dataclass(frozen=True)
class VoxelResult:
    """Output of :func:`voxel_downsample` (one row per occupied voxel, sorted by voxel key).

    Attributes
    ----------
    points : (m, 3) float64
        Voxel centroids (m, same frame as the input).
    normals : (m, 3) float64 or None
        Averaged input normals (not unit length), None when no normals were given.
    counts : (m,) int64
        Number of input points per voxel.
    voxel_keys : (m, 3) int64
        Integer voxel coordinates ``floor((p − origin)/voxel_size_m)``.
    point_voxel : (n,) int64
        Output row of every input point.
    attributes : dict
        Float attributes averaged like the points; integer/bool attributes take the
        value of the voxel's first point (lowest input index).
    origin : (3,) float64
        Grid origin ``min_bound − voxel_size_m/2``.
    voxel_size_m : float
    """

    points: np.ndarray
    normals: np.ndarray | None
    counts: np.ndarray
    voxel_keys: np.ndarray
    point_voxel: np.ndarray
    attributes: dict = field(default_factory=dict)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    voxel_size_m: float = 0.0


def voxel_downsample(points, voxel_size_m: float, normals=None, attributes=None) -> VoxelResult:
    """Replace the points of every occupied voxel by their centroid (Open3D semantics).

    Parameters
    ----------
    points : (n, 3) array_like of float
        Cloud in metres. Large projected coordinates work, but voxel centroids of points
        at 10^6 m keep only ~1e-10 m resolution (float64); work in a local frame when possible.
    voxel_size_m : float
        Voxel edge length in metres (> 0).
    normals : (n, 3) array_like, optional
        Per-point normals; rows containing NaN are skipped in the sums (not in the count).
    attributes : dict of name -> (n,) or (n, k) arrays, optional
        Extra per-point values (intensity, time, class ...).

    Returns
    -------
    VoxelResult

    Raises
    ------
    InputError
        Non-positive/non-finite voxel size, NaN/inf points, wrong shapes, or a voxel size
        so small that voxel indices would overflow 32-bit integers (Open3D's limit).
    TooFewPointsError
        Empty cloud.
    """
    pts = as_points(points, "points", min_points=1)
    v = check_positive(voxel_size_m, "voxel_size_m")
    n = pts.shape[0]
    bmin, bmax = K.bounds3(pts)
    if v * _INT_MAX < float(np.max(bmax - bmin)):
        raise InputError(
            f"voxel_size_m={v} is too small for a cloud extent of {float(np.max(bmax - bmin)):.3f} m "
            "(voxel indices would overflow 32-bit integers)"
        )
    nrm = None
    if normals is not None:
        nrm = np.ascontiguousarray(np.asarray(normals, dtype=np.float64))
        if nrm.shape != (n, 3):
            raise InputError(f"normals must have shape ({n}, 3), got {nrm.shape}")
        if np.isinf(nrm).any():
            raise InputError("normals contain inf values")
    origin = bmin - v * 0.5
    # the largest key per axis is the key of the max bound (floor is monotone)
    dims = [int(np.floor((bmax[a] - origin[a]) / v)) + 1 for a in range(3)]
    if dims[0] * dims[1] * dims[2] < 2**62:
        lin = np.empty(n, dtype=np.int64)
        K.voxel_linear_keys(pts, origin, v, dims[1], dims[2], lin)
        order = K.radix_argsort(lin)
        starts = K.group_starts(lin, order)
        first = order[starts[:-1]]
        kf = lin[first]
        out_keys = np.stack([kf // (dims[1] * dims[2]), (kf // dims[2]) % dims[1], kf % dims[2]], axis=1)
    else:  # pragma: no cover - needs > 2^62 cells
        keys = np.empty((n, 3), dtype=np.int64)
        K.voxel_keys(pts, origin, v, keys)
        order = np.ascontiguousarray(np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0])), dtype=np.int64)
        sk = keys[order]
        change = np.flatnonzero(np.any(sk[1:] != sk[:-1], axis=1)) + 1
        starts = np.concatenate(([0], change, [n])).astype(np.int64)
        first = order[starts[:-1]]
        out_keys = keys[first]
    m = starts.shape[0] - 1
    out_p = np.empty((m, 3))
    out_n = np.empty((m, 3)) if nrm is not None else np.empty((0, 3))
    K.voxel_reduce(pts, nrm if nrm is not None else np.empty((0, 3)), nrm is not None, order, starts,
                   out_p, out_n)
    counts = np.diff(starts)
    point_voxel = np.empty(n, dtype=np.int64)
    K.group_members(order, starts, point_voxel)
    out_attr = {}
    for name, val in (attributes or {}).items():
        a = np.asarray(val)
        if a.shape[0] != n or a.ndim not in (1, 2):
            raise InputError(f"attribute {name!r} must have {n} rows, got shape {a.shape}")
        if np.issubdtype(a.dtype, np.floating):
            cols = np.ascontiguousarray(a.reshape(n, -1), dtype=np.float64)
            red = np.empty((m, cols.shape[1]))
            K.voxel_reduce_columns(cols, order, starts, red)
            out_attr[name] = red.reshape((m,) + a.shape[1:])
        else:
            out_attr[name] = a[first]
    return VoxelResult(out_p, out_n if nrm is not None else None, counts, out_keys, point_voxel,
                       out_attr, origin, v)
