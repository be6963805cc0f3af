"""Drift skeleton of a mine point cloud and its junctions (knowledge base, step 1).

Pipeline (every step is defined exactly in ``docs/intersections.md``, "Knowledge base"):

1. **Floor map**: the low quantile of z per ``floor_cell_m`` cell, holes filled from the nearest
   filled cell; the height of a point is ``h = z - floor(x, y)``.
2. **Wall points**: ``wall_band_m[0] <= h <= wall_band_m[1]`` (floor and roof excluded by height; the
   band must stay under the lowest roof).
3. **Occupancy grid** (``cell_m``): wall cells hold a wall point; the *footprint* is the cells that
   hold any point, closed by a disc of radius ``fill_radius_m`` (a LiDAR map leaves floor and roof
   unsampled between its rings and under each scan position: no sample is not rock); free cells are
   footprint cells not within one cell of a wall cell; holes in the free space smaller than
   ``max_hole_m2`` are filled, free components smaller than ``min_component_m2`` dropped.
4. **Medial axis** by Zhang-Suen thinning of the free space (``_kernels_skeleton.zhang_suen``); the
   one-pixel rings it can leave at symmetric crossings are filled and thinned again.
5. **Graph**: skeleton pixels with >= 3 branches crossing the square ring of radius 3 pixels around
   them are junction pixels; those within
   ``merge_radius_m`` form one junction zone; the skeleton minus the zones falls into branches; a
   branch that ends free (a pixel with one neighbour) and is shorter than ``min_branch_m`` is a spur
   and dropped; the degree of a zone is the number of remaining branches touching it. Junctions =
   zones of degree >= 3.
6. **Geometric invariant point**: centre of the largest empty circle among the wall points, searched
   within ``refine_radius_m`` of the zone's centroid (:func:`invariant_point`).

Frames: every coordinate is the input's (m, z up), the map frame for a map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from minegeo._params import bounded, validate
from minegeo._validate import as_points
from minegeo.errors import InputError
from minegeo.semantic import _kernels_skeleton as K

__all__ = ["SkeletonParams", "FloorMap", "Skeleton", "floor_map", "wall_mask", "drift_skeleton", "invariant_point",
           "point_floor", "mine_levels"]

_EIGHT = np.ones((3, 3), bool)


@dataclass(frozen=True)
class SkeletonParams:
    """Parameters of :func:`drift_skeleton` (lengths in m, areas in m^2).

    Each numeric field declares its bounds in its metadata (:mod:`minegeo._params`): the same rule
    checks the dataclass, ``minegeo intersections build --floor-cell`` and its ``--config`` key;
    ``wall_band_m`` (an increasing pair of heights above the floor) is checked here.
    """

    cell_m: float = bounded(0.25, gt=0.0)
    floor_cell_m: float = bounded(2.0, gt=0.0)
    floor_quantile: float = bounded(0.02, ge=0.0, lt=1.0)
    wall_band_m: tuple = (0.4, 2.2)
    max_hole_m2: float = bounded(4.0, ge=0.0)
    min_component_m2: float = bounded(20.0, ge=0.0)
    min_branch_m: float = bounded(4.0, gt=0.0)
    merge_radius_m: float = bounded(3.0, gt=0.0)
    refine_radius_m: float = bounded(3.0, gt=0.0)
    fill_radius_m: float = bounded(1.5, ge=0.0)
    level_gap_m: float = bounded(6.0, gt=0.0)

    def __post_init__(self):
        validate(self)
        check_height_band(self.wall_band_m, "SkeletonParams.wall_band_m")


def check_height_band(band, where: str) -> None:
    """``band`` must be an increasing ``(lo, hi)`` pair of finite heights (m); else :class:`InputError`."""
    try:
        lo, hi = (float(v) for v in band)
    except (TypeError, ValueError):
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise InputError(f"{where} must be an increasing (lo, hi) pair of finite heights, got {band!r}")


@dataclass(frozen=True, eq=False)
class FloorMap:
    """Floor height (m) on a horizontal grid: ``z[i, j]`` at cell ``origin + (i, j) * cell``."""

    origin: np.ndarray
    cell: float
    z: np.ndarray

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Floor z (m) under each horizontal position ``xy`` (k, 2) (nearest cell, clamped to the grid)."""
        ij = np.floor((np.asarray(xy, np.float64) - self.origin) / self.cell).astype(np.int64)
        i = np.clip(ij[:, 0], 0, self.z.shape[0] - 1)
        j = np.clip(ij[:, 1], 0, self.z.shape[1] - 1)
        return self.z[i, j]


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Result of :func:`drift_skeleton`.

    Attributes
    ----------
    origin : ndarray (2,)
        Map-frame x/y (m) of the corner of grid cell (0, 0); cell (i, j) covers
        ``origin + [i, i + 1) x [j, j + 1) * cell_m``.
    cell_m : float
    free, wall, skeleton : ndarray (h, w) bool
        Free-space, wall and medial-axis cells.
    junction_xy : ndarray (k, 2)
        Invariant points (m, map frame) of the junctions, sorted by x then y.
    junction_guess_xy : ndarray (k, 2)
        Centroids of the junction zones (before refinement).
    junction_degree : ndarray (k,) int
        Number of branches leaving each junction.
    n_branches : int
        Branches kept after spur pruning.
    floor : FloorMap
    wall_xy : ndarray (w, 2)
        Horizontal positions of the wall points (m).
    """

    origin: np.ndarray
    cell_m: float
    free: np.ndarray
    wall: np.ndarray
    skeleton: np.ndarray
    junction_xy: np.ndarray
    junction_guess_xy: np.ndarray
    junction_degree: np.ndarray
    n_branches: int
    floor: FloorMap
    wall_xy: np.ndarray


def floor_map(points: np.ndarray, cell_m: float = 2.0, quantile: float = 0.02) -> FloorMap:
    """Floor height map: per ``cell_m`` cell the ``quantile`` of the z of its points; empty cells take
    the value of the nearest non-empty cell (Euclidean, ``scipy.ndimage.distance_transform_edt``)."""
    P = np.asarray(points, np.float64)
    origin = P[:, :2].min(0)
    ij = np.floor((P[:, :2] - origin) / cell_m).astype(np.int64)
    shape = tuple(ij.max(0) + 1)
    key = ij[:, 0] * shape[1] + ij[:, 1]
    order = np.lexsort((P[:, 2], key))
    ks, zs = key[order], P[order, 2]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[starts, len(ks)])
    pick = starts + np.floor(quantile * (counts - 1)).astype(np.int64)
    z = np.full(shape[0] * shape[1], np.nan)
    z[ks[starts]] = zs[pick]
    z = z.reshape(shape)
    empty = np.isnan(z)
    if empty.any():
        _, (ii, jj) = ndimage.distance_transform_edt(empty, return_indices=True)
        z = z[ii, jj]
    return FloorMap(origin, float(cell_m), z)


def point_floor(points: np.ndarray, cell_m: float = 2.0, quantile: float = 0.02, gap_m: float = 6.0) -> np.ndarray:
    """Floor height (m) under each point, level by level.

    The points of a ``cell_m`` cell are sorted by z and split where two consecutive heights differ by
    more than ``gap_m`` (the rock between two levels; a drift's own floor-to-roof gap is smaller); a
    point's floor is the ``quantile`` of the z of its own group.
    """
    P = np.asarray(points, np.float64)
    ij = np.floor((P[:, :2] - P[:, :2].min(0)) / cell_m).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((P[:, 2], key))
    ks, zs = key[order], P[order, 2]
    new = np.r_[True, (ks[1:] != ks[:-1]) | (np.diff(zs) > gap_m)]
    group = np.cumsum(new) - 1
    starts = np.flatnonzero(new)
    counts = np.diff(np.r_[starts, len(ks)])
    fz = zs[starts + np.floor(quantile * (counts - 1)).astype(np.int64)]
    out = np.empty(len(P))
    out[order] = fz[group]
    return out


def mine_levels(points, params: SkeletonParams | None = None, min_share: float = 0.05) -> list[np.ndarray]:
    """Split a map into mine levels: index arrays of the points of each level, lowest first.

    The drift skeleton is 2-D; two levels in one projection merge their drifts (and the low quantile
    of a floor cell picks the lower level, so the upper level has no wall points). Level floors are
    the peaks of the histogram (1 m bins) of :func:`point_floor` that hold at least ``min_share`` of
    the points and are the largest within ``level_gap_m``; level ``k`` is the slab between the
    mid-heights to the floors below and above it (a ramp between two levels is cut half-way, as far
    as possible from both floors, and appears in each level as a drift leaving it). One peak: one
    level, every point.
    """
    params = params or SkeletonParams()
    P = as_points(points, "points", min_points=1)
    f = point_floor(P, params.floor_cell_m, params.floor_quantile, params.level_gap_m)
    lo = np.floor(f.min())
    counts = np.bincount(np.floor(f - lo).astype(np.int64))
    w = int(np.ceil(params.level_gap_m))
    padded = np.r_[np.zeros(w, np.int64), counts, np.zeros(w, np.int64)]
    local_max = np.array([counts[i] >= padded[i:i + 2 * w + 1].max() for i in range(counts.size)], bool)
    peaks = np.flatnonzero(local_max & (counts >= min_share * len(P)))
    if peaks.size <= 1:
        return [np.arange(len(P))]
    floors = lo + peaks + 0.5
    edges = np.r_[-np.inf, 0.5 * (floors[:-1] + floors[1:]), np.inf]
    k = np.searchsorted(edges, P[:, 2], side="right") - 1
    return [np.flatnonzero(k == i) for i in range(floors.size)]


def wall_mask(points: np.ndarray, floor: FloorMap, band_m=(0.4, 2.2)) -> np.ndarray:
    """True for the points whose height above the floor map lies in ``band_m`` (m): the wall points."""
    h = points[:, 2] - floor.height(points[:, :2])
    return (h >= band_m[0]) & (h <= band_m[1])


def invariant_point(wall_xy: np.ndarray, guess_xy, radius_m: float = 3.0, inside=None) -> tuple[np.ndarray, float]:
    """Geometric invariant point of a junction: centre of the largest empty circle among the walls.

    Maximises the clearance ``c(p) = min_i |p - w_i|`` (horizontal distance to the nearest wall point)
    over the disc-bounding square of half-side ``radius_m`` around ``guess_xy``, by three nested grid
    searches (0.1 m over the square, then 0.01 m and 0.001 m over +-2 steps of the previous grid).
    Candidates outside the drifts are excluded by ``inside`` (a function of (q, 2) positions returning
    a bool mask; :func:`drift_skeleton` passes its free-space grid): in the rock beside a narrow drift
    the distance to the nearest wall point can exceed the junction's clearance. The result depends
    only on the wall points and the free space (not on the grid of the map or the heading of the
    scanner), which is what makes it repeatable from a map or from stacked keyframes.

    Returns
    -------
    (ndarray (2,), float)
        The point (m, frame of ``wall_xy``) and its clearance (m).
    """
    from scipy.spatial import cKDTree

    W = as_points(wall_xy, "wall_xy", dim=2, min_points=3)
    tree = cKDTree(W)
    c = np.asarray(guess_xy, np.float64).reshape(2)
    half, step = float(radius_m), 0.1
    best = 0.0
    for _ in range(3):
        g = np.arange(-half, half + 0.5 * step, step)
        Q = c + np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
        d, _ = tree.query(Q)
        if inside is not None:
            d = np.where(inside(Q), d, -1.0)
        k = int(np.argmax(d))
        c, best = Q[k], float(d[k])
        half, step = 2.0 * step, step / 10.0
    return c, best


def _occupancy(P: np.ndarray, is_wall: np.ndarray, params: SkeletonParams):
    """Free and wall grids (bool) and the grid origin.

    The footprint (cells holding any point) is closed by a disc of ``fill_radius_m``: a LiDAR map samples
    floor and roof along rings, with gaps of up to a few metres under each scan position, and an
    unsampled cell inside a drift is not rock. Rock is bounded by wall cells, which are removed (with
    their 8 neighbours) after the closing.
    """
    cell = params.cell_m
    r = int(np.ceil(params.fill_radius_m / cell - 1e-9))
    origin = P[:, :2].min(0) - (2.0 + r) * cell
    ij = np.floor((P[:, :2] - origin) / cell).astype(np.int64)
    shape = tuple(ij.max(0) + 3 + 2 * r)
    wall = np.zeros(shape, bool)
    wall[ij[is_wall, 0], ij[is_wall, 1]] = True
    foot = np.zeros(shape, bool)
    foot[ij[:, 0], ij[:, 1]] = True
    if r > 0:
        di, dj = np.mgrid[-r:r + 1, -r:r + 1]
        foot = ndimage.binary_closing(foot, (di * di + dj * dj) <= r * r)
    free = foot & ~ndimage.binary_dilation(wall, _EIGHT)
    lab, n = ndimage.label(~free)
    if n:
        area = ndimage.sum_labels(np.ones(shape), lab, np.arange(1, n + 1)) * cell * cell
        border = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
        small = np.flatnonzero(area <= params.max_hole_m2) + 1
        small = small[~np.isin(small, border)]
        free |= np.isin(lab, small)
    lab, n = ndimage.label(free, _EIGHT)
    if n:
        area = ndimage.sum_labels(np.ones(shape), lab, np.arange(1, n + 1)) * cell * cell
        free &= np.isin(lab, np.flatnonzero(area >= params.min_component_m2) + 1)
    free[0], free[-1], free[:, 0], free[:, -1] = False, False, False, False
    return free, wall, origin


def _thin(free: np.ndarray) -> np.ndarray:
    """Zhang-Suen skeleton of ``free``; rings it leaves around holes of <= 4 pixels (at symmetric
    crossings) are filled and the result thinned again."""
    sk = K.zhang_suen(free.astype(np.uint8)).astype(bool)
    lab, n = ndimage.label(~sk)
    if n > 1:
        size = ndimage.sum_labels(np.ones(sk.shape), lab, np.arange(1, n + 1))
        small = np.flatnonzero(size <= 4) + 1
        if small.size:
            sk = K.zhang_suen((sk | np.isin(lab, small)).astype(np.uint8)).astype(bool)
    return sk


def _crossing_number(sk: np.ndarray, rad: int = 1) -> np.ndarray:
    """Number of 0->1 transitions along the square ring of Chebyshev radius ``rad`` around each
    skeleton pixel (0 off the skeleton): the number of skeleton branches crossing that ring. With
    ``rad = 1`` (the 8 neighbours) 1 marks a line end; with ``rad = 3`` >= 3 marks a branch point
    even where Zhang-Suen leaves two lines touching diagonally at a crossing."""
    a = np.pad(sk.astype(np.int8), rad)
    h, w = sk.shape
    ring = ([(-rad, dj) for dj in range(-rad, rad)] + [(di, rad) for di in range(-rad, rad)]
            + [(rad, dj) for dj in range(rad, -rad, -1)] + [(di, -rad) for di in range(rad, -rad, -1)])
    vals = [a[rad + di:rad + di + h, rad + dj:rad + dj + w] for di, dj in ring]
    cn = np.zeros(sk.shape, np.int64)
    for k in range(len(vals)):
        cn += (vals[k] == 0) & (vals[(k + 1) % len(vals)] == 1)
    return np.where(sk, cn, 0)


def _junction_zones(sk: np.ndarray, params: SkeletonParams):
    """Junction zones (label image, count), their degrees and the number of kept branches."""
    nb = _crossing_number(sk, 1)
    jpix = sk & (_crossing_number(sk, 3) >= 3)
    it = max(int(round(params.merge_radius_m / params.cell_m)), 1)
    zones, nz = ndimage.label(ndimage.binary_dilation(jpix, _EIGHT, iterations=it) if jpix.any() else jpix, _EIGHT)
    branches, nbr = ndimage.label(sk & (zones == 0), _EIGHT)
    if nz == 0 or nbr == 0:
        return zones, nz, np.zeros(nz, np.int64), jpix, nbr
    touch = ndimage.grey_dilation(zones, footprint=_EIGHT)
    sel = (branches > 0) & (touch > 0)
    pairs = np.unique(np.c_[branches[sel], touch[sel]], axis=0)
    idx = np.arange(1, nbr + 1)
    length = ndimage.sum_labels(np.ones(sk.shape), branches, idx) * params.cell_m
    free_end = ndimage.maximum(sk & (nb == 1), branches, idx).astype(bool)
    n_zones_touched = np.bincount(pairs[:, 0], minlength=nbr + 1)[1:]
    spur = free_end & (length < params.min_branch_m) & (n_zones_touched <= 1)
    keep = ~spur[pairs[:, 0] - 1]
    degree = np.bincount(pairs[keep, 1], minlength=nz + 1)[1:]
    return zones, nz, degree, jpix, int((~spur).sum())


def drift_skeleton(points, params: SkeletonParams | None = None, *, complete_walls: bool = True) -> Skeleton:
    """Skeleton and junctions of the drifts of a point cloud (map or stacked keyframes).

    Parameters
    ----------
    points : array_like (n, 3)
        Points (m), z up; one mine level (the 2-D projection merges levels).
    params : SkeletonParams, optional
    complete_walls : bool
        True for a map (every wall around a junction is in the cloud): the search for a junction's
        invariant point starts at the junction pixel of its zone farthest from the walls (a zone can
        chain junction pixels over metres, e.g. along a wall structure, and its centroid then misses
        the crossing). False for stacked keyframes (walls partial; the clearance grows toward what
        the sensor did not see): it starts at the zone's centroid.

    Returns
    -------
    Skeleton
        Grids, junction invariant points and degrees (an empty junction list is not an error).

    Raises
    ------
    InputError
        Wrong shape, NaN/inf, fewer than 100 points, no wall points in the band, or a grid larger
        than 10^8 cells.
    """
    params = params or SkeletonParams()
    P = as_points(points, "points", min_points=100)
    floor = floor_map(P, params.floor_cell_m, params.floor_quantile)
    is_wall = wall_mask(P, floor, params.wall_band_m)
    if is_wall.sum() < 3:
        raise InputError(f"no wall points between {params.wall_band_m} m above the floor: is z up?")
    extent = np.ptp(P[:, :2], axis=0) / params.cell_m
    if float(np.prod(extent + 5.0)) > 1e8:
        raise InputError(f"the cloud spans {np.ptp(P[:, :2], axis=0)} m: over 1e8 cells of {params.cell_m} m")
    free, wall, origin = _occupancy(P, is_wall, params)
    sk = _thin(free)
    zones, nz, degree, jpix, nbr = _junction_zones(sk, params)
    wall_xy = np.ascontiguousarray(P[is_wall, :2])
    free_d = ndimage.binary_dilation(free, _EIGHT)

    def inside(Q):
        ij = np.floor((Q - origin) / params.cell_m).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < free.shape[0]) & (ij[:, 1] < free.shape[1])
        out = np.zeros(len(Q), bool)
        out[ok] = free_d[ij[ok, 0], ij[ok, 1]]
        return out

    guess, pts, deg = [], [], []
    from scipy.spatial import cKDTree

    wall_tree = cKDTree(wall_xy)
    for z in np.flatnonzero(degree >= 3) + 1:
        ij = np.argwhere(jpix & (zones == z))
        # the search starts at the zone's junction pixel farthest from the walls, or its centroid
        q = origin + (ij + 0.5) * params.cell_m
        g = q[int(np.argmax(wall_tree.query(q)[0]))] if complete_walls else q.mean(0)
        c, _ = invariant_point(wall_xy, g, params.refine_radius_m, inside)
        s = g
        for _ in range(3):  # the maximum on the edge of the search square: the zone's centroid was off
            if np.max(np.abs(c - s)) < params.refine_radius_m - 0.2:
                break
            s = c
            c, _ = invariant_point(wall_xy, s, params.refine_radius_m, inside)
        guess.append(g)
        pts.append(c)
        deg.append(int(degree[z - 1]))
    pts_a, guess_a, deg_a = _merge(np.array(pts).reshape(-1, 2), np.array(guess).reshape(-1, 2),
                                   np.array(deg, np.int64), params.merge_radius_m)
    order = np.lexsort((pts_a[:, 1], pts_a[:, 0]))
    return Skeleton(origin, params.cell_m, free, wall, sk, pts_a[order], guess_a[order], deg_a[order], nbr, floor,
                    wall_xy)


def _merge(pts: np.ndarray, guess: np.ndarray, deg: np.ndarray, radius: float):
    """Merge junctions whose invariant points are within ``radius`` (keep the first, max degree)."""
    keep = np.ones(len(pts), bool)
    deg = deg.copy()
    for i in range(len(pts)):
        if not keep[i]:
            continue
        for j in range(i + 1, len(pts)):
            if keep[j] and np.hypot(*(pts[i] - pts[j])) < radius:
                keep[j] = False
                deg[i] = max(deg[i], deg[j])
    return pts[keep], guess[keep], deg[keep]
