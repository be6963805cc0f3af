"""minegeo.kernels.hashgrid and minegeo.kernels.kdtree against their naive twins."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_kernels import naive_gated_nn, naive_knn, naive_radius_count, naive_table

from minegeo.kernels import hashgrid as HG
from minegeo.kernels import kdtree as KD


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 2**62), min_size=1, max_size=300, unique=True), st.integers(0, 3))
def test_hash_table_answers_like_a_dict(keys, extra_bits):
    keys = np.array(keys, dtype=np.int64)
    bits = HG.table_bits(keys.size) + extra_bits
    tk, tv = HG.new_table(keys, bits)
    ref = naive_table(keys)
    assert HG.table_bits_of(tk) == bits
    for k in keys:
        assert HG.lookup(k, bits, tk, tv) == ref[int(k)]
        assert tk[HG.find_slot(tk, k, bits)] == k
    missing = int(keys.max()) + 1
    assert HG.lookup(missing, bits, tk, tv) == -1
    assert tk[HG.find_slot(tk, missing, bits)] == HG.EMPTY


def _cloud(seed, n, dup=False):
    rng = np.random.default_rng(seed)
    Q = rng.uniform(-2, 2, (n, 3))
    if dup:  # coincident points and exact ties
        Q[n // 2:] = Q[: n - n // 2]
        Q = np.round(Q, 1)
    return np.ascontiguousarray(Q), np.ascontiguousarray(rng.uniform(-2.5, 2.5, (60, 3)))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 400), st.booleans(), st.integers(1, 12))
def test_kdtree_knn_gated_radius_match_brute_force(seed, n, dup, k):
    Q, P = _cloud(seed, n, dup)
    tree = KD.GatedKDTree(Q)
    idx, sq = KD.kd_knn(P, tree.packed, k)
    ridx, rsq = naive_knn(Q, P, k)
    np.testing.assert_array_equal(idx, ridx)
    np.testing.assert_array_equal(sq, rsq)
    for d2 in (0.01, 0.3, np.inf):
        gi, gs = tree.query(P, d2)
        ri, rs = naive_gated_nn(Q, P, d2)
        np.testing.assert_array_equal(gi, ri)
        np.testing.assert_array_equal(gs, rs)
    for r in (0.0, 0.3, 1.5):
        np.testing.assert_array_equal(KD.kd_radius_count(P, tree.packed, r), naive_radius_count(Q, P, r))


def test_kdtree_answers_do_not_depend_on_point_order():
    Q, P = _cloud(3, 500)
    perm = np.random.default_rng(1).permutation(len(Q))
    i1, s1 = KD.GatedKDTree(Q).query(P, 0.5)
    i2, s2 = KD.GatedKDTree(np.ascontiguousarray(Q[perm])).query(P, 0.5)
    ok = i1 < len(Q)
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(i1[ok], perm[i2[ok]])


def test_stored_tree_round_trips_and_bad_arrays_are_refused():
    Q, P = _cloud(4, 300)
    t = KD.GatedKDTree(Q)
    t2 = KD.GatedKDTree.from_arrays(Q, t.arrays())
    np.testing.assert_array_equal(t.query(P, 1.0)[0], t2.query(P, 1.0)[0])
    a = t.arrays()
    a["idx"] = a["idx"].copy()
    a["idx"][0] = a["idx"][1]
    try:
        KD.GatedKDTree.from_arrays(Q, a)
    except ValueError:
        pass
    else:
        raise AssertionError("a non-permutation was accepted")
