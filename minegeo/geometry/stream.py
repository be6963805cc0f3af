"""Chunk-by-chunk voxel and octree downsampling, bit-identical to the in-memory functions.

Both downsamplers need one global quantity before the first point: the voxel grid origin
``b_min − v/2`` (:func:`~minegeo.geometry.voxel_downsample`) and the octree's bounding cube
(:class:`~minegeo.geometry.Octree`), computed from the cloud's exact bounds (a first pass over
the file, :func:`minegeo.io.chunked.scan_bounds`). The accumulators then take the cloud in
chunks, **in input order**, and keep only one record per occupied cell:

* :class:`VoxelAccumulator` — float64 sums and a count per voxel. The sums are formed point
  by point in input order starting from 0.0, exactly the additions of the in-memory kernel
  (which visits each voxel's points in ascending index order), so ``sum / count`` is the same
  float; rows are sorted by voxel key as :func:`voxel_downsample` does.
* :class:`OctreeAccumulator` — per leaf the closest point to the leaf centre so far, its
  squared distance and global index; a later point replaces it only when strictly closer, so
  ties keep the lowest index as in :meth:`Octree.downsample`. Rows in Morton order.

Memory: one hash-table slot per occupied cell at load factor <= 1/2 (voxel: 40 B per slot,
octree: 56 B per slot), i.e. bounded by the downsampled cloud, not by the input size.
"""

from __future__ import annotations

import numpy as np

from minegeo._validate import check_positive
from minegeo.errors import InputError
from minegeo.geometry import _kernels_stream as KS
from minegeo.geometry.octree import _check_level

__all__ = ["VoxelAccumulator", "OctreeAccumulator", "octree_cube"]

_INT_MAX = 2**31 - 1
_MIN_BITS = 10


def octree_cube(bmin, bmax, size_expand: float = 0.01) -> tuple[np.ndarray, float]:
    """Origin (3,) and edge (m) of :class:`~minegeo.geometry.Octree`'s bounding cube from the bounds."""
    bmin = np.asarray(bmin, dtype=np.float64)
    bmax = np.asarray(bmax, dtype=np.float64)
    c = (bmin + bmax) / 2.0
    h = float(np.max(c - bmin))
    origin = np.minimum(bmin, c - h)
    size = size_expand if h == 0.0 else h * 2.0 * (1.0 + size_expand)
    return origin, float(size)


class _Table:
    """Growable open-addressing table (``2^bits`` slots, at most half used)."""

    def __init__(self, bits: int):
        self._alloc(bits)
        self.n_used = 0

    def _alloc(self, bits: int) -> None:
        self.bits = bits
        self.keys = np.full(1 << bits, -1, dtype=np.int64)

    @property
    def max_used(self) -> int:
        return (1 << self.bits) // 2

    def add(self, points: np.ndarray) -> None:
        P = np.ascontiguousarray(points, dtype=np.float64)
        i = 0
        while i < P.shape[0]:
            self.n_used, j = self._kernel(P[i:], i)
            if j < 0:
                raise InputError(f"point {self.n_seen + i - 1 - j} lies outside the bounds given to the accumulator")
            i += j
            if i < P.shape[0]:
                self._grow()
        self.n_seen += P.shape[0]

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self._arrays()))


class VoxelAccumulator(_Table):
    """Voxel centroids accumulated chunk by chunk (see the module docstring).

    Parameters
    ----------
    bmin, bmax : (3,) array_like
        Exact bounds of the whole cloud (m), as ``K.bounds3`` / ``min``/``max`` give them.
    voxel_size_m : float
        Voxel edge (m, > 0).
    """

    def __init__(self, bmin, bmax, voxel_size_m: float):
        v = check_positive(voxel_size_m, "voxel_size_m")
        bmin = np.asarray(bmin, dtype=np.float64).reshape(3)
        bmax = np.asarray(bmax, dtype=np.float64).reshape(3)
        if v * _INT_MAX < float(np.max(bmax - bmin)):
            raise InputError(f"voxel_size_m={v} is too small for a cloud extent of {float(np.max(bmax - bmin)):.3f} m "
                             "(voxel indices would overflow 32-bit integers)")
        self.voxel_size_m = v
        self.origin = bmin - v * 0.5
        dims = [int(np.floor((bmax[a] - self.origin[a]) / v)) + 1 for a in range(3)]
        if dims[0] * dims[1] * dims[2] >= 2**62:
            raise InputError(f"voxel grid of {dims} cells is too large for the chunked downsampling (>= 2^62 cells)")
        self.dims = dims
        self.n_seen = 0
        super().__init__(_MIN_BITS)

    def _alloc(self, bits: int) -> None:
        super()._alloc(bits)
        self.sums = np.zeros((1 << bits, 3))
        self.counts = np.zeros(1 << bits, dtype=np.int64)

    def _arrays(self):
        return self.keys, self.sums, self.counts

    def _kernel(self, P, i0):
        return KS.voxel_accumulate(P, self.origin, self.voxel_size_m, self.dims[1], self.dims[2], self.keys, self.bits,
                                   self.sums, self.counts, self.n_used, self.max_used)

    def _grow(self) -> None:
        old = self._arrays()
        self._alloc(self.bits + 1)
        KS.voxel_rehash(*old, self.keys, self.bits, self.sums, self.counts)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(points (m, 3), counts (m,), voxel_keys (m, 3))`` sorted by voxel key, as
        :func:`~minegeo.geometry.voxel_downsample` returns them."""
        used = np.flatnonzero(self.keys != -1)
        order = used[np.argsort(self.keys[used], kind="stable")]
        k = self.keys[order]
        cnt = self.counts[order]
        pts = self.sums[order] / cnt.astype(np.float64)[:, None]
        d1, d2 = self.dims[1], self.dims[2]
        keys3 = np.stack([k // (d1 * d2), (k // d2) % d1, k % d2], axis=1)
        return np.ascontiguousarray(pts), cnt, keys3


class OctreeAccumulator(_Table):
    """Octree subsampling (closest point to each occupied leaf centre) chunk by chunk.

    Parameters
    ----------
    bmin, bmax : (3,) array_like
        Exact bounds of the whole cloud (m).
    level : int
        Leaf level (0..21), as :func:`~minegeo.geometry.octree_downsample`.
    size_expand : float
        Cube enlargement (Open3D's default 0.01).
    """

    def __init__(self, bmin, bmax, level: int, size_expand: float = 0.01):
        self.level = _check_level(level, "level")
        self.origin, self.size = octree_cube(bmin, bmax, check_positive(size_expand, "size_expand"))
        self.n_seen = 0
        super().__init__(_MIN_BITS)

    def _alloc(self, bits: int) -> None:
        super()._alloc(bits)
        self.best_sq = np.full(1 << bits, np.inf)
        self.best_idx = np.full(1 << bits, -1, dtype=np.int64)
        self.best_pts = np.zeros((1 << bits, 3))
        self.counts = np.zeros(1 << bits, dtype=np.int64)

    def _arrays(self):
        return self.keys, self.best_sq, self.best_idx, self.best_pts, self.counts

    def _kernel(self, P, i0):
        return KS.octree_accumulate(P, self.n_seen + i0, self.origin, self.size, self.level, self.keys, self.bits,
                                    self.best_sq, self.best_idx, self.best_pts, self.counts, self.n_used, self.max_used)

    def _grow(self) -> None:
        old = self._arrays()
        self._alloc(self.bits + 1)
        KS.octree_rehash(*old, self.keys, self.bits, self.best_sq, self.best_idx, self.best_pts, self.counts)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(points (m, 3), indices (m,), node_codes (m,), counts (m,))`` in Morton order, as
        :func:`~minegeo.geometry.octree_downsample` returns them."""
        used = np.flatnonzero(self.keys != -1)
        order = used[np.argsort(self.keys[used], kind="stable")]
        return (np.ascontiguousarray(self.best_pts[order]), self.best_idx[order], self.keys[order], self.counts[order])
