"""Restoring and checking the search indexes stored with a prepared map.

A saved index (the map's k-d tree, the feature index's row tree, the occupancy hash tables of the
correlative screen) is used only after its stored arrays are shown consistent with the map they
index: shapes, ranges, the hash-table slot counts they were built with and, for the hash tables, that
every key sits where the probe sequence finds it. An index that fails a check is rebuilt, never used.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._validate import is_permutation
from minegeo.localize.prepared.store import _in_range, _integer, _is_number, _number, _stored

#: Largest hash table (log2 of its slots) a stored search structure may announce.
_MAX_LOG2_SLOTS = 40


def _restore_kdtree(Q: np.ndarray, a: dict, prefix: str = ""):
    """A stored :class:`~minegeo.kernels.kdtree.GatedKDTree` over ``Q`` (``k`` points):
    dtypes and shapes of the builder's, at most ``2 k`` nodes, point order within ``[0, k)``
    (checked before :func:`~minegeo._validate.is_permutation` counts it), then
    ``GatedKDTree.from_arrays`` (permutation, node ranges, children, depth)."""
    from minegeo.kernels.kdtree import GatedKDTree

    k = Q.shape[0]
    idx = _stored(a, prefix + "idx", np.int64, (k,))
    start = _stored(a, prefix + "start", np.int64, ndim=1)
    n = start.shape[0]
    if not 1 <= n <= 2 * k:
        raise ValueError(f"KD-tree of {n} nodes over {k} points")
    nodes = {name: _stored(a, prefix + name, dt, (n,)) for name, dt in
             (("end", np.int64), ("dim", np.int64), ("split", np.float64), ("left", np.int64), ("right", np.int64))}
    depth = _stored(a, prefix + "depth", np.int64, (1,))
    _in_range(idx, 0, k, "KD-tree point order")
    _in_range(depth, 0, n, "KD-tree depth")
    if not np.isfinite(nodes["split"]).all():
        raise ValueError("KD-tree split values are not finite")
    return GatedKDTree.from_arrays(Q, {"idx": idx, "start": start, "depth": depth, **nodes})


def _expected_feature_rows(F: np.ndarray, drop_zero_features: bool) -> np.ndarray:
    """The rows :func:`~minegeo.registration.correspondences.build_feature_index` searches."""
    return np.flatnonzero(np.any(F != 0.0, axis=1)) if drop_zero_features else np.arange(F.shape[0])


def _restore_row_tree(B: np.ndarray, a: dict, rb):
    """The descriptor tree over ``B`` from its stored rotation and leaf partition (the leaf
    storage is packed again from ``B``, so it cannot disagree with the map's descriptors):
    rotation of the builder's shape and finite, order a permutation (range-checked first),
    exactly ``ceil(n / FEATURE_LEAF)`` leaves of at most ``FEATURE_LEAF`` rows, and the search
    radius bound ``rb`` the one of ``B`` and the stored mean."""
    from minegeo.registration.correspondences import FEATURE_LEAF, FEATURE_ROT, row_tree_from_partition

    n, dim = B.shape
    L = FEATURE_LEAF
    mu = _stored(a, "mu", np.float64, (dim,))
    V = _stored(a, "V", np.float64, (dim, min(dim, FEATURE_ROT)))
    perm = _stored(a, "perm", np.int64, (n,))
    lstart = _stored(a, "lstart", np.int64, ((n + L - 1) // L + 1,))
    if not (np.isfinite(mu).all() and np.isfinite(V).all()):
        raise ValueError("descriptor tree rotation is not finite")
    _in_range(perm, 0, n, "descriptor tree order")
    if not is_permutation(perm, n):
        raise ValueError("descriptor tree order is not a permutation of the rows")
    sizes = np.diff(lstart)
    if lstart[0] != 0 or lstart[-1] != n or sizes.min() < 0 or sizes.max() > L:
        raise ValueError("descriptor tree leaves out of range")
    if not _is_number(rb) or float(rb) != float(np.sqrt(np.max(np.einsum("ij,ij->i", B - mu, B - mu)))):
        raise ValueError("descriptor tree radius bound is not the one of the map's descriptors")
    return row_tree_from_partition(B, mu, V, perm, lstart, float(rb))


def _table_log2(log2_start: int, n_blocks: int) -> int:
    """Table size (log2 of its slots) the builders end with: the first from ``log2_start`` that
    keeps ``n_blocks`` at most half full."""
    log2 = log2_start
    while n_blocks > (1 << log2) // 2:
        log2 += 1
    return log2


def _grid_log2_start(n_points: int, cell_m: float) -> tuple[int, int]:
    """``(band, first log2)`` of :meth:`PreparedMap.screen_grid` over ``n_points`` points."""
    from minegeo.localize.correlative import SCREEN_GATES_M

    band = int(math.ceil(max(SCREEN_GATES_M) / cell_m))
    n_cells = n_points * (2 * band + 1) ** 3
    return band, max(10, int(math.ceil(math.log2(max(1, n_cells) / 512 / 8))) + 1)


def _occupancy_log2_start(n_cells: int, dilation: int) -> int:
    """First log2 of :func:`minegeo.localize.correlative.map_occupancy` (same formula)."""
    return max(10, int(math.ceil(math.log2(max(1, n_cells) * (1 + 2 * dilation) / 32))) + 1)


def _hash_home(keys: np.ndarray, log2: int) -> np.ndarray:
    """Home slots of ``keys`` in a table of ``2^log2`` slots: :func:`minegeo.kernels.hashgrid.hash_slot`
    vectorised (top ``log2`` bits of ``key * HASH_MULT`` modulo 2^64)."""
    from minegeo.kernels.hashgrid import HASH_MULT

    with np.errstate(over="ignore"):
        return ((keys.astype(np.uint64) * HASH_MULT) >> np.uint64(64 - log2)).astype(np.int64)


def _check_hash_table(keys: np.ndarray, log2: int, what: str) -> None:
    """``ValueError`` unless ``keys`` (``2^log2`` int64, -1 = empty) is a table the kernels'
    linear probing (:func:`minegeo.localize._kernels.block_slot`) can use: an empty slot exists
    (a probe ends), used keys are valid block keys (non-negative), distinct, and each is
    reached from its hash slot through used slots only."""
    cap = keys.shape[0]
    mask = cap - 1
    used = keys != -1
    free = np.flatnonzero(~used)
    if free.size == 0:
        raise ValueError(f"{what} hash table has no empty slot")
    slots = np.flatnonzero(used)
    k = keys[slots]
    if k.size == 0:
        return
    if int(k.min()) < 0 or np.unique(k).size != k.size:
        raise ValueError(f"{what} hash table holds invalid or repeated keys")
    home = _hash_home(k, log2)
    pos = np.arange(cap)
    r = np.roll(used, -free[0])  # rotated so that slot 0 is empty
    run = pos - np.maximum.accumulate(np.where(r, 0, pos)) - 1  # used slots before each in its run
    if np.any(((slots - home) & mask) > run[(slots - free[0]) & mask]):
        raise ValueError(f"{what} hash table: a key is not where its probe finds it")


def _check_occupancy(a: dict, e: dict, k: int, points: np.ndarray, normals: np.ndarray):
    """Checks of a stored :class:`~minegeo.localize.correlative.MapOccupancy` (``k`` ICP points):
    ``((cell, dilation, tilt), packed)`` with the used slots' rows, expanded on first use."""
    key = e["key"]
    if not isinstance(key, list) or len(key) != 3:
        raise ValueError("occupancy key must be [cell, dilation, tilt]")
    kd = dict(zip(("cell", "dilation", "tilt"), key, strict=True))
    cell, dil, tilt = _number(kd, "cell", positive=True), _integer(kd, "dilation", 0, 1 << 20), _number(kd, "tilt")
    log2 = _integer(e, "log2_blocks", 10, _MAX_LOG2_SLOTS)
    n_cells = _integer(e, "n_cells", 1, k)
    nb = _integer(e, "n_blocks", 1, 1 << (log2 - 1))
    keys = _stored(a, "block_keys", np.int64, (1 << log2,))
    if int(np.count_nonzero(keys != -1)) != nb:
        raise ValueError("occupancy block count does not match its table")
    rows = _stored(a, "bits", np.uint64, (nb, 16))
    if log2 != _table_log2(_occupancy_log2_start(n_cells, dil), nb):
        raise ValueError(f"occupancy table size 2^{log2} is not the one built for {n_cells} cells")
    _check_hash_table(keys, log2, "occupancy")
    anchors = _stored(a, "anchors", np.float64, ndim=2)
    if not np.array_equal(anchors, points[normals[:, 2] >= math.cos(math.radians(tilt))]):
        raise ValueError("floor anchors are not the map's")
    build_s = _number(e, "build_s") if "build_s" in e else 0.0
    return (cell, dil, tilt), {"key": (cell, dil, tilt), "keys": keys, "rows": rows, "anchors": anchors, "log2": log2, "n_cells": n_cells,
                               "n_blocks": nb, "build_s": build_s}


def _expand_occupancy(pk: dict):
    """The :class:`~minegeo.localize.correlative.MapOccupancy` of a checked stored one (empty
    slots added back with zero bits, dense directory rebuilt from the block keys)."""
    from minegeo.localize import _kernels as LK
    from minegeo.localize.correlative import MAX_DENSE_BLOCKS, MapOccupancy

    cell, dil, _ = pk["key"]
    keys = pk["keys"]
    bits = np.zeros((keys.shape[0], 16), dtype=np.uint64)  # an empty slot's bits must be zero
    bits[keys != -1] = pk["rows"]
    table, table_lo = LK.dense_block_table(keys, MAX_DENSE_BLOCKS)
    return MapOccupancy(block_keys=keys, bits=bits, log2_blocks=pk["log2"], table=table, table_lo=table_lo,
                        n_cells=pk["n_cells"], n_blocks=pk["n_blocks"], anchors=pk["anchors"], cell_size_m=float(cell),
                        dilation_cells=int(dil), build_s=pk["build_s"])
