"""Exact neighbour search: k nearest, radius and hybrid (radius + max count).

Semantics follow Open3D 0.20's ``KDTreeFlann`` (``docs/registration_geometry.md``,
``shared/specs/open3d_oracle.md`` §1):

* **radius(r)** – every point with squared distance ``sq < r**2`` (strict);
* **hybrid(r, max_nn)** – the ``<= max_nn`` nearest points strictly inside ``r``;
* **knn(k)** – the ``k`` nearest points (all of them if the cloud has fewer).

Every row is sorted by ascending squared distance; the query point itself is included
when it belongs to the cloud (distance 0). Unlike Open3D, ties are broken by the lowest
point index, so results are fully deterministic.

All searches use a uniform hash grid written in Numba. The cell edge is the search radius,
or for kNN about the median k-th neighbour distance, unless ``cell_size_m`` is given.
Points are sorted by their cell key (a Morton code, for memory locality); an
open-addressing table maps occupied cell keys to point ranges; every query scans only
the cells whose box lies closer than ``r`` (and, once ``max_nn`` candidates are held,
closer than the current worst), keeping candidates sorted by (distance, index). Queries
are visited in grid order. kNN repeats the hybrid search with a doubling radius until k
points lie strictly inside it, which makes it exact.

Memory: a result holds ``n_queries * kmax * 16`` bytes (int64 indices + float64 squared
distances), e.g. 4.8 GB for 10^7 queries with kmax = 30. Use :meth:`NeighborIndex.iter_hybrid`
to stream, or :func:`minegeo.geometry.estimate_normals`, which never materialises the
neighbourhoods. The index itself costs about 48 bytes per
point (sorted copy of the points, permutation, cell keys) plus the hash table.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError
from minegeo.geometry import _kernels as K
from minegeo.kernels import hashgrid as HG

__all__ = ["Neighborhoods", "NeighborIndex"]

log = logging.getLogger(__name__)

#: Largest number of grid cells (nx*ny*nz) a linear int64 cell key can address.
_MAX_CELLS = 2**62


@dataclass(frozen=True)
class Neighborhoods:
    """Padded neighbour lists of a batch of queries.

    Attributes
    ----------
    indices : (n, kmax) int64
        Point indices into the indexed cloud, ascending by squared distance (ties: lowest
        index first), padded with -1.
    sq_distances : (n, kmax) float64
        Squared Euclidean distances in m², padded with ``inf``.
    counts : (n,) int64
        Number of valid entries per row.
    kind : str
        ``"knn"``, ``"radius"`` or ``"hybrid"``.
    radius_m : float or None
        Search radius (strict: ``sq < radius_m**2``), None for kNN.
    max_nn : int or None
        Neighbour cap (k for kNN), None for a pure radius search.
    """

    indices: np.ndarray
    sq_distances: np.ndarray
    counts: np.ndarray
    kind: str
    radius_m: float | None = None
    max_nn: int | None = None

    @property
    def kmax(self) -> int:
        """Number of columns of the padded arrays."""
        return int(self.indices.shape[1])

    @property
    def nbytes(self) -> int:
        """Memory held by the padded arrays, in bytes."""
        return int(self.indices.nbytes + self.sq_distances.nbytes + self.counts.nbytes)

    def row(self, i: int) -> np.ndarray:
        """Valid neighbour indices of query ``i`` (ascending by distance)."""
        return self.indices[i, : self.counts[i]]

    def __len__(self) -> int:
        return int(self.counts.shape[0])


@dataclass(frozen=True)
class _Grid:
    cell: float
    origin: np.ndarray
    nx: int
    ny: int
    nz: int
    morton: bool  # cell keys are Morton codes (else linear keys)
    pts: np.ndarray  # points sorted by cell key
    order: np.ndarray  # pts[j] = points[order[j]]
    cell_start: np.ndarray  # (ncells + 1,)
    bits: int
    table_keys: np.ndarray
    table_vals: np.ndarray

    def args(self):
        """Positional kernel arguments after ``pts``/``order`` (see ``_kernels.hybrid_one``)."""
        return (self.cell_start, self.origin, self.cell, 1.0 / self.cell, self.nx, self.ny, self.nz,
                self.morton, self.bits, self.table_keys, self.table_vals)

    def query_order(self, queries: np.ndarray, is_self: bool) -> np.ndarray:
        """Visiting order of the queries: sorted by grid cell (cache locality), stable."""
        if is_self:
            return self.order
        keys = np.empty(queries.shape[0], dtype=np.int64)
        K.grid_cell_keys(queries, self.origin, 1.0 / self.cell, self.nx, self.ny, self.nz, self.morton, keys)
        return K.radix_argsort(keys)


def _build_grid(points: np.ndarray, cell: float) -> _Grid:
    origin = points.min(axis=0)
    inv = 1.0 / cell
    top = np.floor((points.max(axis=0) - origin) * inv)
    nx, ny, nz = (int(t) + 1 for t in top)
    if nx * ny * nz >= _MAX_CELLS:
        raise InputError(
            f"the neighbour-search grid would need {nx}x{ny}x{nz} cells of {cell} m: the cloud "
            "extent is too large for this radius; use a larger radius or split the cloud"
        )
    morton = max(nx, ny, nz) <= 1 << 21
    n = points.shape[0]
    keys = np.empty(n, dtype=np.int64)
    K.grid_cell_keys(points, origin, inv, nx, ny, nz, morton, keys)
    order = K.radix_argsort(keys)
    sk = keys[order]
    change = np.flatnonzero(sk[1:] != sk[:-1]) + 1
    cell_start = np.concatenate(([0], change, [n])).astype(np.int64)
    cell_keys = np.ascontiguousarray(sk[cell_start[:-1]])
    ncells = cell_keys.shape[0]
    bits = HG.table_bits(ncells)
    table_keys, table_vals = HG.new_table(cell_keys, bits)
    pts = np.ascontiguousarray(points[order])
    return _Grid(cell, origin, nx, ny, nz, morton, pts, order, cell_start, bits, table_keys, table_vals)


def _check_int(value, name: str, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


class NeighborIndex:
    """Exact neighbour-search index over a fixed point cloud.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Cloud to index, in metres, any frame (coordinates up to ~10^7 m are fine: all
        distances are formed from coordinate differences in float64).
    cell_size_m : float, optional
        Edge of the hash-grid cells used by radius/hybrid searches. Default: the search
        radius of each call (one grid per distinct radius is built lazily and cached).

    Examples
    --------
    >>> idx = NeighborIndex(points)                       # doctest: +SKIP
    >>> nb = idx.hybrid(points, radius_m=0.2, max_nn=30)  # doctest: +SKIP
    >>> nb.row(0)                                        # doctest: +SKIP
    """

    def __init__(self, points, cell_size_m: float | None = None):
        self.points = as_points(points, "points", min_points=1)
        self.cell_size_m = None if cell_size_m is None else check_positive(cell_size_m, "cell_size_m")
        self._grids: dict[float, _Grid] = {}
        self._knn_cells: dict[int, tuple[float, float]] = {}

    def __len__(self) -> int:
        return int(self.points.shape[0])

    # -- internals -----------------------------------------------------------------------
    def _grid(self, radius_m: float) -> _Grid:
        """Grid for a radius search (cell = ``cell_size_m`` or the radius)."""
        return self._grid_cell(self.cell_size_m if self.cell_size_m is not None else radius_m)

    def _grid_cell(self, cell: float) -> _Grid:
        g = self._grids.get(cell)
        if g is None:
            if len(self._grids) >= 2:  # keep memory bounded: at most two cached grids
                self._grids.pop(next(iter(self._grids)))
            g = _build_grid(self.points, cell)
            self._grids[cell] = g
        return g

    def _knn_cell(self, k: int) -> tuple[float, float]:
        """(grid cell, initial kNN radius) ≈ (median, 90th percentile) of the k-th neighbour distance.

        Estimated deterministically from up to 512 evenly spaced sample points searched
        exactly on a provisional grid of cell ``max_extent / n^(1/3)``. Only speed depends
        on this choice; kNN results are exact for any cell.
        """
        h = self._knn_cells.get(k)
        if h is not None:
            return h
        n = self.points.shape[0]
        ext = float(np.max(self.points.max(axis=0) - self.points.min(axis=0)))
        h0 = ext / max(n, 1) ** (1.0 / 3.0) if ext > 0 else 1.0
        g0 = _build_grid(self.points, h0)
        sample = np.ascontiguousarray(self.points[np.unique(np.linspace(0, n - 1, min(n, 512)).astype(np.int64))])
        kk = min(k, n)
        m = sample.shape[0]
        idx = np.empty((m, kk), dtype=np.int64)
        sq = np.empty((m, kk), dtype=np.float64)
        cnt = np.empty(m, dtype=np.int64)
        K.grid_hybrid(sample, g0.query_order(sample, False), True, h0, np.inf, kk, g0.pts, g0.order, *g0.args(),
                      idx, sq, cnt)
        dk = np.sqrt(sq[:, kk - 1])
        med, p90 = float(np.median(dk)), float(np.quantile(dk, 0.9))
        cell = med if med > 0 and np.isfinite(med) else h0
        if self.cell_size_m is not None:
            cell = self.cell_size_m
        r0 = max(p90 * 1.01, cell) if np.isfinite(p90) else cell
        h = (cell, r0)
        self._knn_cells[k] = h
        return h

    def _queries(self, queries) -> np.ndarray:
        if queries is None:
            return self.points
        return as_points(queries, "queries", min_points=0)

    # -- public API ------------------------------------------------------------------------
    def hybrid(self, queries, radius_m: float, max_nn: int) -> Neighborhoods:
        """The ``<= max_nn`` nearest points with ``sq < radius_m**2`` (Open3D ``KDTreeSearchParamHybrid``).

        Parameters
        ----------
        queries : (m, 3) array_like or None
            Query positions in the cloud's frame (m); None means the indexed points.
        radius_m : float
            Search radius in metres (strict inequality).
        max_nn : int
            Maximum number of neighbours per query (>= 1).

        Returns
        -------
        Neighborhoods
            ``indices``/``sq_distances`` of shape (m, max_nn), padded with -1/inf.
        """
        q = self._queries(queries)
        r = check_positive(radius_m, "radius_m")
        cap = _check_int(max_nn, "max_nn")
        return self._hybrid(q, r, cap, "hybrid")

    def _hybrid_plan(self, r: float, cap: int) -> tuple[bool, float, _Grid]:
        """How to run a hybrid search of radius ``r`` and cap ``cap``: (knn flag, start radius, grid).

        When the cap is reached well inside ``r`` (dense cloud, large radius: the estimated
        90th-percentile ``cap``-th neighbour distance is below r), search as a kNN bounded
        by ``r`` on a grid sized for ``cap`` neighbours (:func:`_kernels.search_one`): same
        neighbours, same order, but only the points near the ``cap``-th distance are visited
        instead of every point within ``r`` (e.g. 5 m FPFH balls of an unreduced 20 m scan).
        Otherwise: one search of radius ``r`` on a grid of cell ``r``.
        """
        n = self.points.shape[0]
        if self.cell_size_m is None and cap < n:
            cell, r0 = self._knn_cell(cap)
            if r0 < r:
                return True, r0, self._grid_cell(cell)
        return False, r, self._grid(r)

    def _hybrid(self, q: np.ndarray, r: float, cap: int, kind: str) -> Neighborhoods:
        knn, r0, g = self._hybrid_plan(r, cap) if kind == "hybrid" else (False, r, self._grid(r))
        m = q.shape[0]
        idx = np.empty((m, cap), dtype=np.int64)
        sq = np.empty((m, cap), dtype=np.float64)
        cnt = np.empty(m, dtype=np.int64)
        qorder = g.query_order(q, q is self.points)
        K.grid_hybrid(q, qorder, knn, r0, r, cap, g.pts, g.order, *g.args(), idx, sq, cnt)
        return Neighborhoods(idx, sq, cnt, kind, r, cap if kind == "hybrid" else None)

    def iter_hybrid(self, queries, radius_m: float, max_nn: int, chunk_size: int = 1 << 18
                    ) -> Iterator[tuple[int, Neighborhoods]]:
        """Yield ``(first_query_row, Neighborhoods)`` for consecutive chunks of queries.

        Use this for 10^7-point clouds: memory per chunk is ``chunk_size * max_nn * 16`` bytes.
        """
        q = self._queries(queries)
        r = check_positive(radius_m, "radius_m")
        cap = _check_int(max_nn, "max_nn")
        cs = _check_int(chunk_size, "chunk_size")
        for s in range(0, q.shape[0], cs):
            yield s, self._hybrid(np.ascontiguousarray(q[s : s + cs]), r, cap, "hybrid")

    def radius_counts(self, queries, radius_m: float) -> np.ndarray:
        """Number of points with ``sq < radius_m**2`` around each query, (m,) int64."""
        q = self._queries(queries)
        r = check_positive(radius_m, "radius_m")
        g = self._grid(r)
        cnt = np.empty(q.shape[0], dtype=np.int64)
        K.grid_radius_count(q, g.query_order(q, q is self.points), r, g.pts, *g.args(), cnt)
        return cnt

    def radius(self, queries, radius_m: float, max_nn: int | None = None) -> Neighborhoods:
        """Every point with ``sq < radius_m**2`` (Open3D ``KDTreeSearchParamRadius``).

        With ``max_nn`` this is :meth:`hybrid`. Without it, a counting pass sizes the
        output: ``kmax`` = the largest neighbourhood, so one crowded query makes the
        padded arrays wide (memory ``m * kmax * 16`` bytes).
        """
        if max_nn is not None:
            return self.hybrid(queries, radius_m, max_nn)
        q = self._queries(queries)
        r = check_positive(radius_m, "radius_m")
        cnt = self.radius_counts(q, r)
        kmax = int(cnt.max()) if cnt.size else 0
        if kmax == 0:
            return Neighborhoods(np.full((q.shape[0], 0), -1, np.int64), np.full((q.shape[0], 0), np.inf),
                                 cnt, "radius", r, None)
        return self._hybrid(q, r, kmax, "radius")

    def knn(self, queries, k: int) -> Neighborhoods:
        """The ``k`` nearest points of each query (all points when the cloud has fewer than k).

        Exact, on the same hash grid: hybrid searches with a radius doubling from the
        median k-th neighbour distance until k points lie strictly inside it. Rows are
        sorted by (squared distance, index), so ties — including at the k-th place — go
        to the lowest index (Open3D keeps its traversal order there).
        """
        q = self._queries(queries)
        k = _check_int(k, "k")
        kk = min(k, self.points.shape[0])
        cell, r0 = self._knn_cell(kk)
        g = self._grid_cell(cell)
        m = q.shape[0]
        idx = np.empty((m, kk), dtype=np.int64)
        sq = np.empty((m, kk), dtype=np.float64)
        cnt = np.empty(m, dtype=np.int64)
        K.grid_hybrid(q, g.query_order(q, q is self.points), True, r0, np.inf, kk, g.pts, g.order, *g.args(),
                      idx, sq, cnt)
        return Neighborhoods(idx, sq, cnt, "knn", None, k)
