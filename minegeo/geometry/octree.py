"""Linear octree and octree subsampling (Baek et al. 2022, Sec. 2.2).

Bounding cube (Open3D 0.20 ``Octree.convert_from_point_cloud(pcd, size_expand)`` rule,
``shared/specs/open3d_oracle.md`` §2): with the bounding-box centre ``c`` and the largest
half-extent ``h``,

* origin ``o = min(b_min, c − h)`` per axis (equal to ``c − h`` up to rounding),
* edge ``s = 2h(1 + size_expand)``, or ``s = size_expand`` when ``h = 0``;

the expansion is added on the max side only, so every point satisfies ``o <= p < o + s``.
A node at level ``l`` has edge ``s / 2^l``; level 0 is the root cube.

Points are assigned to leaves by descending from the root exactly as Open3D does: at each
level the child index is ``ix + 2·iy + 4·iz`` with ``i = 1`` when the coordinate is >= the
cell midpoint. The concatenated child indices form the leaf's Morton code; sorting the
points by code gives a *linear octree*: every node at every level is a contiguous range of
the sorted points, stored per level as (codes, point ranges, child ranges).

Octree subsampling keeps, in every occupied leaf, the point closest to the leaf centre
(Sec. 2.2: "only points closest to the center of the octree voxels are sampled"); ties go
to the lowest input index. Output rows are in Morton (depth-first) order of the leaves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_matrix, as_points, check_positive
from minegeo.errors import InputError
from minegeo.geometry import _kernels as K

__all__ = ["Octree", "OctreeDownsampleResult", "octree_downsample", "MAX_OCTREE_DEPTH"]

#: Deepest level supported: 3 bits per level in a signed 64-bit Morton code.
MAX_OCTREE_DEPTH = 21


def _check_level(level, name: str = "max_depth") -> int:
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 0 <= level <= MAX_OCTREE_DEPTH:
        raise InputError(f"{name} must be an integer in [0, {MAX_OCTREE_DEPTH}], got {level!r}")
    return int(level)


def _morton_decode(codes: np.ndarray, level: int) -> np.ndarray:
    """Integer cell coordinates (k, 3) of node codes at ``level`` (child index = ix + 2 iy + 4 iz)."""
    ijk = np.zeros((codes.shape[0], 3), dtype=np.int64)
    for b in range(level):
        c = (codes >> (3 * b)) & 7
        ijk[:, 0] |= (c & 1) << b
        ijk[:, 1] |= ((c >> 1) & 1) << b
        ijk[:, 2] |= ((c >> 2) & 1) << b
    return ijk


class Octree:
    """Linear (Morton-ordered) octree built to ``max_depth`` over the cloud's bounding cube.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Cloud in metres (kept by reference after conversion to float64).
    max_depth : int
        Leaf level L (0..21); leaves have edge ``size / 2^L``.
    size_expand : float
        Relative enlargement of the cube (Open3D default 0.01), see module docstring.

    Attributes
    ----------
    origin : (3,) float64
        Minimum corner of the root cube (m).
    size : float
        Root cube edge (m).
    order : (n,) int64
        Point indices sorted by leaf Morton code (stable: ascending index within a leaf).
    """

    def __init__(self, points, max_depth: int, size_expand: float = 0.01):
        self.points = as_points(points, "points", min_points=1)
        self.max_depth = _check_level(max_depth)
        self.size_expand = check_positive(size_expand, "size_expand")
        bmin = self.points.min(axis=0)
        bmax = self.points.max(axis=0)
        c = (bmin + bmax) / 2.0
        h = float(np.max(c - bmin))
        self.origin = np.minimum(bmin, c - h)
        self.size = self.size_expand if h == 0.0 else h * 2.0 * (1.0 + self.size_expand)
        n = self.points.shape[0]
        codes = np.empty(n, dtype=np.int64)
        inside = np.empty(n, dtype=np.bool_)
        K.octree_codes(self.points, self.origin, self.size, self.max_depth, codes, inside)
        if not inside.all():  # pragma: no cover - the cube contains the cloud by construction
            raise InputError("internal octree error: a point fell outside the bounding cube")
        self.order = K.radix_argsort(codes)
        sc = codes[self.order]
        L = self.max_depth
        codes_l, pstart_l, pend_l = [], [], []
        for lvl in range(L + 1):
            c_l = sc >> (3 * (L - lvl))
            change = np.flatnonzero(c_l[1:] != c_l[:-1]) + 1
            st = np.concatenate(([0], change)).astype(np.int64)
            codes_l.append(c_l[st])
            pstart_l.append(st)
            pend_l.append(np.concatenate((st[1:], [n])).astype(np.int64))
        off = np.zeros(L + 2, dtype=np.int64)
        off[1:] = np.cumsum([c.shape[0] for c in codes_l])
        cstart = np.zeros(off[-1], dtype=np.int64)
        cend = np.zeros(off[-1], dtype=np.int64)
        for lvl in range(L):
            child = codes_l[lvl + 1]
            parent = codes_l[lvl]
            cstart[off[lvl] : off[lvl + 1]] = off[lvl + 1] + np.searchsorted(child, parent << 3, side="left")
            cend[off[lvl] : off[lvl + 1]] = off[lvl + 1] + np.searchsorted(child, (parent << 3) + 7, side="right")
        self._level_off = off
        self._codes = np.concatenate(codes_l)
        self._pstart = np.concatenate(pstart_l)
        self._pend = np.concatenate(pend_l)
        self._cstart = cstart
        self._cend = cend

    # -- structure -----------------------------------------------------------------------
    def cell_size(self, level: int) -> float:
        """Edge length (m) of a node at ``level``."""
        return self.size / float(1 << _check_level(level, "level"))

    def node_codes(self, level: int) -> np.ndarray:
        """Morton codes of the occupied nodes at ``level``, ascending."""
        lvl = _check_level(level, "level")
        if lvl > self.max_depth:
            raise InputError(f"level {lvl} is deeper than the octree (max_depth={self.max_depth})")
        return self._codes[self._level_off[lvl] : self._level_off[lvl + 1]].copy()

    def node_counts(self, level: int) -> np.ndarray:
        """Number of points in each occupied node at ``level`` (same order as :meth:`node_codes`)."""
        lvl = _check_level(level, "level")
        if lvl > self.max_depth:
            raise InputError(f"level {lvl} is deeper than the octree (max_depth={self.max_depth})")
        a, b = self._level_off[lvl], self._level_off[lvl + 1]
        return self._pend[a:b] - self._pstart[a:b]

    def occupied_per_level(self) -> np.ndarray:
        """Number of occupied nodes at levels 0..max_depth, (L+1,) int64."""
        return np.diff(self._level_off)

    def node_bounds(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Minimum corners (k, 3) and edge (m) of the occupied nodes at ``level``."""
        codes = self.node_codes(level)
        ijk = _morton_decode(codes, level).astype(np.float64)
        cs = self.cell_size(level)
        return self.origin + ijk * cs, cs

    @property
    def n_leaves(self) -> int:
        """Number of occupied leaves."""
        return int(self._level_off[-1] - self._level_off[-2])

    @property
    def leaf_codes(self) -> np.ndarray:
        """Morton codes of the occupied leaves, ascending."""
        return self.node_codes(self.max_depth)

    def leaf_centres(self) -> np.ndarray:
        """Centres (k, 3) of the occupied leaves, in leaf order."""
        lo, cs = self.node_bounds(self.max_depth)
        return lo + 0.5 * cs

    # -- queries -------------------------------------------------------------------------
    def leaf_of(self, query_points) -> np.ndarray:
        """Leaf number (0..n_leaves-1) containing each query point, -1 if outside the cube or
        in an empty leaf. Uses the same midpoint descent as the build."""
        q = as_points(query_points, "query_points", min_points=0)
        codes = np.empty(q.shape[0], dtype=np.int64)
        inside = np.empty(q.shape[0], dtype=np.bool_)
        K.octree_codes(q, self.origin, self.size, self.max_depth, codes, inside)
        leaves = self.leaf_codes
        pos = np.searchsorted(leaves, codes)
        pos_c = np.minimum(pos, leaves.shape[0] - 1)
        found = inside & (leaves[pos_c] == codes)
        return np.where(found, pos_c, -1).astype(np.int64)

    def leaf_points(self, leaf: int) -> np.ndarray:
        """Indices of the points in leaf number ``leaf`` (ascending)."""
        if not 0 <= int(leaf) < self.n_leaves:
            raise InputError(f"leaf must be in [0, {self.n_leaves}), got {leaf!r}")
        g = self._level_off[self.max_depth] + int(leaf)
        return self.order[self._pstart[g] : self._pend[g]].copy()

    def _region(self, is_sphere, centre, r2, lo, hi) -> np.ndarray:
        out = np.empty(self.points.shape[0], dtype=np.int64)
        cnt = K.octree_region_query(self.points, self.order, self._codes, self._pstart, self._pend,
                                    self._cstart, self._cend, self._level_off, self.max_depth,
                                    self.origin, self.size, is_sphere, centre[0], centre[1],
                                    centre[2], r2, lo, hi, out)
        return np.sort(out[:cnt])

    def radius(self, centre, radius_m: float) -> np.ndarray:
        """Indices (ascending) of points with squared distance < radius_m² to ``centre``."""
        c = as_matrix(centre, (3,), "centre")
        r = check_positive(radius_m, "radius_m")
        return self._region(True, c, r * r, np.zeros(3), np.zeros(3))

    def box(self, lo, hi) -> np.ndarray:
        """Indices (ascending) of points with ``lo <= p <= hi`` on every axis."""
        lo = as_matrix(lo, (3,), "lo")
        hi = as_matrix(hi, (3,), "hi")
        if np.any(lo > hi):
            raise InputError(f"box lower corner {lo.tolist()} exceeds upper corner {hi.tolist()}")
        return self._region(False, np.zeros(3), 0.0, lo, hi)

    def downsample(self, level: int | None = None) -> OctreeDownsampleResult:
        """Closest-to-centre point of every occupied node at ``level`` (default: leaves)."""
        lvl = self.max_depth if level is None else _check_level(level, "level")
        if lvl > self.max_depth:
            raise InputError(f"level {lvl} is deeper than the octree (max_depth={self.max_depth})")
        a, b = self._level_off[lvl], self._level_off[lvl + 1]
        starts = np.concatenate((self._pstart[a:b], [self.points.shape[0]])).astype(np.int64)
        codes = np.ascontiguousarray(self._codes[a:b])
        idx = np.empty(b - a, dtype=np.int64)
        K.octree_nearest_to_centre(self.points, self.order, starts, codes, lvl, self.origin, self.size, idx)
        return OctreeDownsampleResult(idx, self.points[idx], codes, starts[1:] - starts[:-1], lvl,
                                      self.origin.copy(), self.size, self.cell_size(lvl))


@dataclass(frozen=True)
class OctreeDownsampleResult:
    """Output of :func:`octree_downsample`.

    Attributes
    ----------
    indices : (m,) int64
        Kept input indices, one per occupied node, in Morton order of the nodes.
    points : (m, 3) float64
        ``points[indices]`` (original coordinates, not cell centres).
    node_codes : (m,) int64
        Morton codes of the occupied nodes.
    counts : (m,) int64
        Input points per node.
    level : int
    origin : (3,) float64
        Root cube corner (m).
    size : float
        Root cube edge (m).
    cell_size_m : float
        Node edge at ``level`` (m).
    """

    indices: np.ndarray
    points: np.ndarray
    node_codes: np.ndarray
    counts: np.ndarray
    level: int
    origin: np.ndarray
    size: float
    cell_size_m: float


def octree_downsample(points, level: int, size_expand: float = 0.01) -> OctreeDownsampleResult:
    """Octree subsampling (Baek et al. 2022, Sec. 2.2): one point per occupied level-``level`` cell.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Cloud in metres.
    level : int
        Octree level (0..21). The cell edge is ``size / 2^level`` with ``size`` the
        bounding-cube edge (≈ the largest bounding-box extent × 1.01); e.g. the paper's
        level 10 on a 1 km map gives ≈1 m cells.
    size_expand : float
        Cube enlargement (Open3D's default 0.01).

    Returns
    -------
    OctreeDownsampleResult
        The point nearest to each occupied cell's centre (ties: lowest index).
    """
    return Octree(points, level, size_expand).downsample()
