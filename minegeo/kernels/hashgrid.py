"""Open-addressing hash table of non-negative int64 keys (the one hash grid of minegeo).

Layout: two arrays of ``2**bits`` slots, ``table_keys`` (``EMPTY`` = -1 marks a free slot) and
``table_vals``; a key's home slot is the top ``bits`` bits of ``key * 0x9E3779B97F4A7C15``
modulo 2^64 (Fibonacci hashing, Knuth TAOCP Vol. 3, Sec. 6.4), collisions probe linearly
(``s + 1`` modulo the table size). The table must keep at least one free slot (callers size it
to at least twice the number of keys), so every probe ends.

Users: the neighbour grid of :mod:`minegeo.geometry` (cell key -> cell number), the radius-NN
grid of RANSAC (:mod:`minegeo.registration._kernels_ransac`: cell key -> unique-cell row) and the
blocked occupancy bitmaps of :mod:`minegeo.localize._kernels` (block key -> slot of its bit rows,
:func:`find_slot`). Lookups return the same value whatever the slot layout, so results never
depend on the hash function; :mod:`minegeo.localize._kernels` also walks the slots, in slot order,
only to build a dense directory of them (which again maps keys to their own slots).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit

__all__ = ["HASH_MULT", "EMPTY", "table_bits", "table_bits_of", "hash_slot", "build_table", "new_table", "lookup", "find_slot"]

#: 2**64 / golden ratio (Fibonacci hashing multiplier), 0x9E3779B97F4A7C15.
HASH_MULT = np.uint64(11400714819323198485)
#: Key of a free slot.
EMPTY = -1


def table_bits(n_keys: int, min_bits: int = 4) -> int:
    """Smallest ``bits >= min_bits`` with ``2**bits >= 2 n_keys + 1`` (load factor <= 1/2)."""
    bits = int(min_bits)
    while (1 << bits) < 2 * int(n_keys) + 1:
        bits += 1
    return bits


@njit
def table_bits_of(table_keys):
    """``bits`` of a table of ``2**bits`` slots (its ``table_keys`` array). O(1): the size is a
    power of two, so its float64 log2 is exact (hot loops call this once per lookup)."""
    return np.int64(np.log2(np.float64(table_keys.shape[0])))


@njit
def hash_slot(key, bits):
    """Home slot of ``key`` in a table of ``2**bits`` slots (top ``bits`` bits of ``key * HASH_MULT``)."""
    h = np.uint64(key) * HASH_MULT
    return np.int64(h >> np.uint64(64 - bits))


@njit
def build_table(keys, bits, table_keys, table_vals):
    """Insert ``keys[c] -> c`` for every row ``c`` (keys distinct) into the empty table
    ``table_keys`` / ``table_vals`` (``2**bits`` slots, ``table_keys`` all ``EMPTY``)."""
    mask = (np.int64(1) << bits) - 1
    for c in range(keys.shape[0]):
        key = keys[c]
        s = hash_slot(key, bits)
        while table_keys[s] != EMPTY:
            s = (s + 1) & mask
        table_keys[s] = key
        table_vals[s] = c


@njit
def new_table(keys, bits):
    """``(table_keys, table_vals)`` of a new ``2**bits``-slot table holding ``keys[c] -> c``."""
    size = np.int64(1) << np.int64(bits)
    table_keys = np.full(size, EMPTY, dtype=np.int64)
    table_vals = np.full(size, EMPTY, dtype=np.int64)
    build_table(keys, bits, table_keys, table_vals)
    return table_keys, table_vals


@njit
def lookup(key, bits, table_keys, table_vals):
    """Value stored for ``key``, or -1 when the key is not in the table."""
    mask = (np.int64(1) << bits) - 1
    s = hash_slot(key, bits)
    while True:
        k = table_keys[s]
        if k == key:
            return table_vals[s]
        if k == EMPTY:
            return np.int64(-1)
        s = (s + 1) & mask


@njit
def find_slot(table_keys, key, bits):
    """Slot holding ``key``, or the free slot where it would be inserted (keys-only tables)."""
    mask = (np.int64(1) << bits) - 1
    s = hash_slot(key, bits)
    while True:
        v = table_keys[s]
        if v == key or v == EMPTY:
            return s
        s = (s + 1) & mask
