"""Correlative 4-DOF search (minegeo.localize.correlative): kernels against a naive twin,
recovery of a known placement, determinism, parameter checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference.naive_correlative import dilated_cells, nearest_grid, score_placements

from minegeo.errors import InputError
from minegeo.localize import _kernels as K
from minegeo.localize.correlative import (
    CorrelativeParams,
    correlative_candidates,
    map_occupancy,
    placement_grid,
)
from minegeo.localize.params import CorrelativeStageParams


def _blocked(cells, radius, log2=10):
    keys, bits, nb = K.build_blocked_occupancy(cells, radius, log2)
    assert nb <= (1 << log2) // 2
    return keys, bits, log2


def test_blocked_occupancy_equals_naive_set():
    rng = np.random.default_rng(1)
    P = rng.uniform(-3.0, 3.0, (300, 3))
    cells = K.unique_cells(P, 0.5)
    assert {tuple(c) for c in cells} == {tuple(int(math.floor(v / 0.5)) for v in p) for p in P}
    dil, occ = dilated_cells(P, 0.5, 1), dilated_cells(P, 0.5, 0)
    keys, bits, log2 = _blocked(cells, 1)
    # every cell of a box that covers the dilated set with a margin, negative indices included
    # (blocks of 8 cells: floor division and modulo of negative indices)
    got = {}
    for ix in range(-10, 10):
        for iy in range(-10, 10):
            for iz in range(-10, 10):
                got[(ix, iy, iz)] = K.occupancy_state(keys, bits, log2, ix, iy, iz)
    assert {c for c, v in got.items() if v >= 1} == dil
    assert {c for c, v in got.items() if v == 2} == occ
    # the population of the bit masks is the size of the sets (nothing outside the box)
    pop = [sum(bin(int(w)).count("1") for w in bits[keys >= 0, lo:lo + 8].ravel()) for lo in (0, 8)]
    assert pop == [len(dil), len(occ)]


def test_blocked_occupancy_grows_when_the_table_is_full():
    cells = K.unique_cells(np.random.default_rng(5).uniform(-40.0, 40.0, (3000, 3)), 0.5)
    _, _, nb = K.build_blocked_occupancy(cells, 1, 4)
    assert nb > 8  # stopped: the caller must retry with a larger table
    occ = map_occupancy(cells * 0.5 + 0.25, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), CorrelativeParams())
    assert occ.n_blocks <= (1 << occ.log2_blocks) // 2 and occ.n_cells == cells.shape[0]


def test_score_placements_equals_naive_twin():
    rng = np.random.default_rng(2)
    Q = rng.uniform(-4.0, 4.0, (400, 3))
    cells = K.unique_cells(Q, 0.5)
    keys, bits, log2 = _blocked(cells, 1)
    S = rng.uniform(-3.0, 3.0, (40, 3))
    anchors = rng.uniform(-1.0, 1.0, (7, 3))
    yaws = np.deg2rad(np.arange(0.0, 360.0, 30.0))
    m = S.shape[0]
    grid = placement_grid(S, yaws, anchors, 0.5)
    ref = np.array(score_placements(dilated_cells(Q, 0.5, 1), 0.5, S, anchors, yaws))
    ref_t = np.array(score_placements(dilated_cells(Q, 0.5, 0), 0.5, S, anchors, yaws))
    table, lo = K.dense_block_table(keys, 1 << 20)
    assert table.size > 0
    no_table = (np.zeros((0, 0, 0), dtype=np.int32), np.zeros(3, dtype=np.int64))
    # the same counts through the dense block directory and through the hash table
    for tab in ((table, lo), no_table):
        got, got_t = K.score_placements(keys, bits, log2, *tab, *grid, m, 1.0, float(m))
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(got_t, ref_t)
        # early stopping only ever lowers a count, and never one that stayed above the bar
        early, _ = K.score_placements(keys, bits, log2, *tab, *grid, 12, 0.3, 4.0)
        assert np.all(early <= ref)
        full = ref >= m - 12
        assert np.all(early[full & (early >= m - 12)] == ref[full & (early >= m - 12)])


def test_dense_block_table_points_at_every_stored_block_and_nowhere_else():
    rng = np.random.default_rng(8)
    cells = K.unique_cells(rng.uniform(-14.0, 9.0, (150, 3)), 0.5)
    keys, bits, log2 = _blocked(cells, 1)
    table, lo = K.dense_block_table(keys, 1 << 20)
    stored = {int(s) for s in np.flatnonzero(keys >= 0)}
    seen = set()
    for idx in np.ndindex(*table.shape):
        s = int(table[idx])
        b = np.asarray(idx) + lo
        if s in stored:
            assert keys[s] == K.cell_key(*b) and s not in seen
            seen.add(s)
        else:  # a block that is not stored points at an empty slot (all bits zero)
            assert keys[s] == -1 and not bits[s].any()
    assert seen == stored
    # too large a bounding box: no directory (the scoring probes the hash table)
    assert K.dense_block_table(keys, 3)[0].size == 0


def test_first_of_each_bin_matches_numpy_unique():
    from minegeo.localize.correlative import _first_of_each_bin

    rng = np.random.default_rng(4)
    bins = rng.integers(-5, 5, (5000, 4))
    np.testing.assert_array_equal(np.sort(_first_of_each_bin(bins)), np.sort(np.unique(bins, axis=0, return_index=True)[1]))
    huge = np.array([[0, 0, 0, 0], [2**40, 2**40, 2**40, 3], [0, 0, 0, 0]])  # ranges too wide to pack
    np.testing.assert_array_equal(np.sort(_first_of_each_bin(huge)), [0, 1])
    assert _first_of_each_bin(np.zeros((0, 4), dtype=np.int64)).size == 0


def _box_corner(step):
    """Three 6 m faces of a box corner sampled every ``step`` m, their normals, 300 of the points
    as the scan sample, and a placement 0.3/-0.25/0.1 m and 2 deg off the truth (identity)."""
    g = np.arange(0.0, 6.0, step)
    A, B = np.meshgrid(g, g, indexing="ij")
    a, b = A.ravel(), B.ravel()
    Q = np.vstack([np.column_stack([a, b, 0 * a]), np.column_stack([a, 0 * a, b]), np.column_stack([0 * a, a, b])])
    Nq = np.vstack([np.tile(n, (a.size, 1)) for n in ([0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0])])
    S = Q[np.random.default_rng(0).choice(Q.shape[0], 300, replace=False)]
    psi = np.deg2rad(2.0)
    T0 = np.eye(4)
    T0[:3, :3] = [[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]]
    T0[:3, 3] = [0.3, -0.25, 0.1]
    return Q, Nq, S, T0


def test_refine_kernel_recovers_an_offset_placement():
    """The 4-DOF Gauss-Newton kernel pulls a placement 0.4 m / 2 deg off back onto a box corner."""
    from minegeo.registration import build_target_index

    Q, Nq, S, T0 = _box_corner(0.1)
    index = build_target_index(Q)
    out_T = np.empty((1, 4, 4))
    cnt = np.zeros(1, dtype=np.int64)
    K.refine_placements_4dof(S, T0[None], Q, Nq, index.packed, np.linspace(1.5, 0.5, 8) ** 2, 0.05, 0.25, out_T, cnt)
    np.testing.assert_allclose(out_T[0], np.eye(4), atol=1e-6)
    assert cnt[0] == S.shape[0]


def test_nearest_grid_equals_naive_twin():
    rng = np.random.default_rng(6)
    Q = rng.uniform(-2.0, 2.0, (120, 3))
    keys, nearest, nb = K.build_nearest_grid(Q, 0.5, 2, 10)
    assert nb <= 512
    ref = nearest_grid(Q, 0.5, 2)
    got = {}
    for s in np.flatnonzero(keys >= 0):
        k = int(keys[s])
        bx, by, bz = (((k >> (2 * 21)) & ((1 << 21) - 1)) - (1 << 20), ((k >> 21) & ((1 << 21) - 1)) - (1 << 20),
                      (k & ((1 << 21) - 1)) - (1 << 20))
        assert K.block_slot(keys, k, 10) == s  # the table has 2^10 slots
        for loc in np.flatnonzero(nearest[s] >= 0):
            got[(8 * bx + (loc >> 6), 8 * by + ((loc >> 3) & 7), 8 * bz + (loc & 7))] = int(nearest[s, loc])
    assert got == ref
    # the lookup: the stored point when within the gate, else "none" (= len(Q))
    X = rng.uniform(-3.0, 3.0, (500, 3))
    out = np.empty(500, dtype=np.int64)
    K._grid_nn_rows(X, keys, nearest, 10, 0.5, Q, 0.6**2, out)
    for x, j in zip(X, out, strict=True):
        c = tuple(int(math.floor(v / 0.5)) for v in x)
        k = ref.get(c)
        want = k if k is not None and np.sum((x - Q[k]) ** 2) <= 0.36 else Q.shape[0]
        assert j == want


def test_grid_refine_kernel_brings_an_offset_placement_into_the_exact_basin():
    """The lookup-grid variant of the 4-DOF kernel (approximate neighbours) reduces a 0.4 m /
    2 deg offset on a box corner, and the exact KD-tree stage then lands on the truth; with no
    step the exact kernel only counts (the pose passes through unchanged)."""
    from minegeo.registration import build_target_index

    Q, Nq, S, T0 = _box_corner(0.25)
    keys, nearest, nb = K.build_nearest_grid(Q, 0.5, 3, 12)
    assert nb <= 2048
    Tg = np.empty((1, 4, 4))
    cnt = np.zeros(1, dtype=np.int64)
    K.steps_4dof_grid(S, T0[None], Q, Nq, keys, nearest, 12, 0.5, np.array([1.5, 1.0, 0.7]) ** 2, Tg)
    err0 = np.max(np.linalg.norm(S @ T0[:3, :3].T + T0[:3, 3] - S, axis=1))
    err1 = np.max(np.linalg.norm(S @ Tg[0, :3, :3].T + Tg[0, :3, 3] - S, axis=1))
    assert err1 < 0.5 * err0
    index = build_target_index(Q)
    same = np.empty((1, 4, 4))
    K.refine_placements_4dof(S, Tg, Q, Nq, index.packed, np.zeros(0), 0.05, 0.25, same, cnt)
    np.testing.assert_array_equal(same, Tg)
    out_T = np.empty((1, 4, 4))
    K.refine_placements_4dof(S, Tg, Q, Nq, index.packed, np.linspace(1.0, 0.5, 4) ** 2, 0.05, 0.25, out_T, cnt)
    np.testing.assert_allclose(out_T[0], np.eye(4), atol=1e-6)
    assert cnt[0] == S.shape[0]


# ----------------------------------------------------------------------------- a small asymmetric mine
def _box_drift(a, b, width, height, step, rng):
    """Surface points (floor, walls, roof) of a straight rectangular drift from a to b (xy, z=0)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    L = float(np.linalg.norm(b - a))
    u = (b - a) / L
    v = np.array([-u[1], u[0]])
    s = np.arange(0.0, L, step)
    w = np.arange(-width / 2, width / 2 + 1e-9, step)
    h = np.arange(0.0, height + 1e-9, step)
    S1, W1 = np.meshgrid(s, w, indexing="ij")
    floor = np.column_stack([(a + np.outer(S1.ravel(), u) + np.outer(W1.ravel(), v)), np.zeros(S1.size)])
    roof = floor.copy()
    roof[:, 2] = height + 0.3 * np.sin(S1.ravel() / 3.0)  # an irregular roof
    S2, H2 = np.meshgrid(s, h, indexing="ij")
    walls = []
    for side in (-1.0, 1.0):
        xy = a + np.outer(S2.ravel(), u) + side * width / 2 * v
        walls.append(np.column_stack([xy, H2.ravel()]))
    P = np.vstack([floor, roof, *walls])
    return P + rng.normal(0.0, 0.01, P.shape)


@pytest.fixture(scope="module")
def small_mine():
    from minegeo.localize import PrepareParams, prepare_map

    rng = np.random.default_rng(5)
    parts = [_box_drift((0, 0), (40, 0), 5.0, 4.0, 0.2, rng), _box_drift((40, -2.5), (40, 30), 4.0, 4.0, 0.2, rng),
             _box_drift((18, 0), (18, -14), 4.0, 3.5, 0.2, rng)]
    P = np.vstack(parts) + np.array([512_000.0, 4_100_000.0, 350.0])
    pm = prepare_map(P, PrepareParams.fast())
    return P, pm


def _scan_of(P, centre_xy, radius, yaw, t):
    sel = np.sum((P[:, :2] - centre_xy) ** 2, axis=1) < radius**2
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    X = (P[sel] - t) @ T[:3, :3]  # scan = T^-1 map
    return X, T


def test_correlative_search_recovers_a_levelled_placement(small_mine):
    from minegeo.localize import LocalizeParams
    from minegeo.localize.prepared import prepare_cloud_features

    P, pm = small_mine
    lp = LocalizeParams.fast()
    t = np.array([512_030.0, 4_100_002.0, 351.0])
    X, T_true = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(37.0), t)
    D, N, _ = prepare_cloud_features(X, lp.scan_voxel_size_m, None, lp.features)
    cp = CorrelativeParams()
    occ = map_occupancy(pm.icp_points, pm.points, pm.normals, cp)
    assert occ.anchors.shape[0] > 50
    r1 = correlative_candidates(occ, D, N, cp, seed=3, refine_target=(pm.target_index(), pm.icp_points, pm.icp_normals))
    assert r1.candidates, r1.reason
    T0 = r1.candidates[0][0].copy()
    T0[:3, 3] += pm.work_origin
    Xm = X @ T0[:3, :3].T + T0[:3, 3]
    Xt = X @ T_true[:3, :3].T + T_true[:3, 3]
    assert np.max(np.linalg.norm(Xm - Xt, axis=1)) < 0.3
    # deterministic: same inputs and seed, identical candidates
    r2 = correlative_candidates(occ, D, N, cp, seed=3, refine_target=(pm.target_index(), pm.icp_points, pm.icp_normals))
    assert len(r1.candidates) == len(r2.candidates)
    for (Ta, fa), (Tb, fb) in zip(r1.candidates, r2.candidates, strict=True):
        np.testing.assert_array_equal(Ta, Tb)
        assert fa == fb
    # unrefined grid placements are returned when no refinement target is given
    r3 = correlative_candidates(occ, D, N, cp, seed=3)
    assert 0 < len(r3.candidates) <= cp.n_candidates


def test_correlative_without_floor_says_so(small_mine):
    _, pm = small_mine
    cp = CorrelativeParams()
    occ = map_occupancy(pm.icp_points, pm.points, pm.normals, cp)
    X = np.random.default_rng(0).uniform(0, 5, (100, 3))
    N = np.tile([1.0, 0.0, 0.0], (100, 1))
    r = correlative_candidates(occ, X, N, cp)
    assert not r.candidates and "floor" in r.reason


def test_localize_fallback_and_always(small_mine):
    from dataclasses import replace

    from minegeo.localize import LocalizeParams, localize_scan
    from minegeo.localize.pipeline import error_vs_truth

    P, pm = small_mine
    t = np.array([512_030.0, 4_100_002.0, 351.0])
    X, T_true = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(-58.0), t)
    base = LocalizeParams.fast()
    crippled = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=1,
                       min_iterations=0)
    off = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative=None), seed=0)
    assert off.status != "ok" and off.correlative is None
    fb = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative=replace(base.correlative, mode="fallback")), seed=0)
    assert fb.status == "ok", fb.reason
    assert fb.correlative is not None and fb.correlative["n_candidates"] > 0
    assert fb.hypotheses[0]["source"].startswith("correlative")
    assert error_vs_truth(fb.T_map_scan, T_true, X)["max_point_error_m"] < 0.05
    # bit-identical on a second run (same inputs and seed), correlative path included
    fb2 = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative=replace(base.correlative, mode="fallback")), seed=0)
    np.testing.assert_array_equal(fb.T_map_scan, fb2.T_map_scan)
    np.testing.assert_array_equal(fb.covariance_6x6, fb2.covariance_6x6)
    assert [h["plane_fitness"] for h in fb.hypotheses] == [h["plane_fitness"] for h in fb2.hypotheses]
    assert fb.correlative["hit_fractions"] == fb2.correlative["hit_fractions"]
    al = localize_scan(pm, X, None, replace(base, ransac=replace(crippled, max_iterations=100_000),
                                            correlative=replace(base.correlative, mode="always")), seed=0)
    assert al.status == "ok" and al.correlative is not None
    assert error_vs_truth(al.T_map_scan, T_true, X)["max_point_error_m"] < 0.05
    # a small scan's `ok` is confirmed against the whole map (fallback mode), a large one's is not
    lev = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=100_000)
    big = localize_scan(pm, X, None, replace(base, ransac=lev, ambiguity=replace(base.ambiguity, small_scan_below_points=0)), seed=0)
    assert big.status == "ok" and big.correlative is None
    small = localize_scan(pm, X, None, replace(base, ransac=lev, ambiguity=replace(
        base.ambiguity, small_scan_below_points=big.n_scan_down + 1)), seed=0)
    assert small.status == "ok" and small.correlative is not None
    np.testing.assert_allclose(small.T_map_scan, big.T_map_scan, atol=1e-6)
    # a 6-DOF (not levelled) search never runs the correlative search
    six = localize_scan(pm, X, None, replace(base, ransac=replace(base.ransac, max_iterations=2000,
                                                                   min_iterations=0)), seed=0)
    assert six.correlative is None


def test_screening_caps_only_rank(small_mine):
    """The screening ICP (capped points and iterations) only picks which hypotheses get the
    full-resolution ICP: the chosen placement and its numbers come from that ICP alone."""
    from dataclasses import replace

    from minegeo.localize import LocalizeParams, localize_scan

    P, pm = small_mine
    X, _ = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(-58.0),
                    np.array([512_030.0, 4_100_002.0, 351.0]))
    base = LocalizeParams.fast()
    lev = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=100_000)
    runs = [localize_scan(pm, X, None, replace(base, ransac=lev, correlative=replace(base.correlative, mode="always"),
                                               icp=replace(base.icp, screen_max_points=n, screen_max_iterations=it)),
                          seed=0)
            for n, it in ((10**6, 30), (1000, 10), (120, 5))]
    assert runs[0].n_scan_down > 120  # the last run really screens on a subset
    for r in runs:
        assert r.status == runs[0].status == "ok"
        assert r.hypotheses[0]["source"] == runs[0].hypotheses[0]["source"]
        np.testing.assert_array_equal(r.T_map_scan, runs[0].T_map_scan)
        assert r.hypotheses[0]["plane_fitness"] == runs[0].hypotheses[0]["plane_fitness"]
        assert r.params.icp.screen_max_points in (10**6, 1000, 120)


def test_small_scans_keep_the_full_screening(small_mine, monkeypatch):
    """The screening ICP's caps (iterations, points) apply to ordinary scans only: a small
    scan's rivals are judged on the narrower small-scan margin, so its screening gets the full
    budget."""
    from dataclasses import replace

    import minegeo.localize.verification as PL
    from minegeo.localize import LocalizeParams, localize_scan

    P, pm = small_mine
    X, _ = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(-58.0),
                    np.array([512_030.0, 4_100_002.0, 351.0]))
    base = LocalizeParams.fast()
    lev = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=100_000)
    seen: list = []
    real = PL.register_icp

    def spy(P_src, Q, T, prm, **kw):
        seen.append((P_src.shape[0], prm.max_iterations, prm.step_translation_m, prm.max_correspondence_distance_m))
        return real(P_src, Q, T, prm, **kw)

    monkeypatch.setattr(PL, "register_icp", spy)
    caps = {}
    for name, below in (("ordinary", 0), ("small", 10**6)):
        seen.clear()
        r = localize_scan(pm, X, None, replace(base, ransac=lev, correlative=replace(base.correlative, mode="always"),
                                                icp=replace(base.icp, screen_max_iterations=4, screen_max_points=60),
                                                ambiguity=replace(base.ambiguity, small_scan_below_points=below)),
                          seed=0)
        # screening calls: the decision's 0.5 m gate with the stage step test (the full-resolution
        # ICP has no step test, the coarse pull-in a 1.5 m gate)
        screen = [(n, it) for n, it, step, g in seen if g == 0.5 and step > 0]
        assert screen, name
        caps[name] = set(screen)
    n = r.n_scan_down
    assert n > 60
    # ordinary: capped iterations on at most icp.screen_max_points points; small: neither cap
    assert caps["ordinary"] == {(60, 4)}
    assert caps["small"] == {(n, base.icp.max_iterations)}


def test_screen_target_thins_the_icp_cloud(small_mine):
    """One point per 0.5 m voxel (centroid), unit normals, voxels with opposing normals left
    out; cached per voxel size; None is the full ICP cloud."""
    from minegeo.geometry import voxel_downsample
    from minegeo.localize import PrepareParams, prepare_map

    _, pm = small_mine
    idx, Qs, Ns = pm.screen_target(0.5)
    assert pm.screen_target(0.5)[1] is Qs
    v = voxel_downsample(pm.icp_points, 0.5, normals=pm.icp_normals)
    assert 0.5 * v.points.shape[0] < Qs.shape[0] <= v.points.shape[0] < pm.icp_points.shape[0]
    np.testing.assert_allclose(np.linalg.norm(Ns, axis=1), 1.0, atol=1e-12)
    assert idx.packed.idx.shape[0] == Qs.shape[0]
    full = pm.screen_target(None)
    assert full[1] is pm.icp_points and full[2] is pm.icp_normals
    # a thin wall seen from both sides: its voxels' normals cancel and are left out; the floor stays
    g = np.arange(0.0, 4.0, 0.05)
    A, B = np.meshgrid(g, g, indexing="ij")
    a, b = A.ravel(), B.ravel()
    wall = np.column_stack([a, np.full(a.size, 10.1), b + 0.1])
    floor = np.column_stack([a, b, np.zeros(a.size)])
    pts = np.ascontiguousarray(np.vstack([floor, wall, wall + [0.0, 0.02, 0.0]]))
    nrm = np.ascontiguousarray(np.vstack([np.tile([0.0, 0.0, 1.0], (a.size, 1)), np.tile([0.0, -1.0, 0.0], (a.size, 1)),
                                          np.tile([0.0, 1.0, 0.0], (a.size, 1))]))
    pm2 = prepare_map(pts, PrepareParams.fast())
    pm2.icp_points, pm2.icp_normals = pts, nrm  # (used as a container of these arrays only)
    _, Q2, N2 = pm2.screen_target(0.5)
    assert Q2.shape[0] >= 64 and np.all(N2[:, 2] == 1.0) and np.all(Q2[:, 2] < 0.01)  # floor voxels only
    # nothing coherent at all: the full cloud
    pm3 = prepare_map(pts, PrepareParams.fast())
    pm3.icp_points, pm3.icp_normals = pts[floor.shape[0]:], nrm[floor.shape[0]:]
    assert pm3.screen_target(0.5)[1] is pm3.icp_points


def test_build_indexes_builds_what_localization_uses(small_mine):
    from dataclasses import replace

    from minegeo.localize import LocalizeParams, PrepareParams, prepare_map

    P, _ = small_mine
    pm = prepare_map(P, PrepareParams.fast())
    base = LocalizeParams.fast()
    lev = replace(base, ransac=replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0))
    t = pm.build_indexes(lev)
    assert set(t) == {"kdtree", "target_index", "feature_index", "occupancy", "screen_target", "screen_grid"}
    assert all(v >= 0.0 for v in t.values())
    cp = lev.correlative.search
    occ = pm.occupancy(cp)
    assert pm.build_indexes(lev)["occupancy"] < t["occupancy"] + 1.0 and pm.occupancy(cp) is occ
    assert set(pm.build_indexes(base)) == {"kdtree", "target_index", "feature_index"}  # 6-DOF: no correlative
    assert "gicp_target" in pm.build_indexes(replace(base, icp=replace(base.icp, method="gicp")))


def test_correlative_precheck_keeps_the_best_and_records_all(small_mine):
    """The pre-check scores every whole-map candidate; ratio 1 lets only the best reach ICP,
    ratio 0 all; the answer is the same right placement."""
    from dataclasses import replace

    from minegeo.localize import LocalizeParams, localize_scan
    from minegeo.localize.pipeline import error_vs_truth

    P, pm = small_mine
    t = np.array([512_030.0, 4_100_002.0, 351.0])
    X, T_true = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(-58.0), t)
    base = LocalizeParams.fast()
    crippled = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=1, min_iterations=0)
    res = {}
    for ratio in (0.0, 1.0):
        r = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative=replace(
            base.correlative, mode="fallback", precheck_ratio=ratio)), seed=0)
        pre = r.correlative["precheck_plane_fitness"]
        assert len(pre) == r.correlative["n_candidates"] and r.correlative["precheck_ratio"] == ratio
        # "correlative #k (...)": the k-th candidate reached ICP; only those at or above the bar may
        ks = [int(h["source"].split("#")[1].split()[0]) for h in r.hypotheses if h["source"].startswith("correlative")]
        assert ks and all(pre[k - 1] >= ratio * max(pre) for k in ks), (ratio, ks, pre)
        if ratio == 1.0:
            assert all(pre[k - 1] == max(pre) for k in ks)
        assert error_vs_truth(r.T_map_scan, T_true, X)["max_point_error_m"] < 0.05
        res[ratio] = (r, len(ks))
    assert res[1.0][1] < res[0.0][1]  # the pre-check did drop candidates
    assert res[1.0][0].status == "ok"
    with pytest.raises(InputError):
        CorrelativeStageParams(precheck_ratio=1.5)


@pytest.mark.parametrize("kw", [{"cell_size_m": 0.0}, {"yaw_step_deg": -1.0}, {"min_hit_fraction": 0.0},
                                {"min_hit_fraction": 1.5}, {"n_candidates": 0}, {"dilation_cells": -1},
                                {"anchor_max_tilt_deg": 90.0}, {"max_scan_points": 2.5},
                                {"screen_voxel_size_m": 0.0}, {"screen_voxel_size_m": -0.5}, {"screen_grid": "yes"}])
def test_params_validation(kw):
    with pytest.raises(InputError):
        CorrelativeParams(**kw)


def test_localize_params_reject_unknown_mode():
    from minegeo.localize import LocalizeParams
    from minegeo.localize.params import AmbiguityParams, IcpParams

    with pytest.raises(InputError):
        CorrelativeStageParams(mode="sometimes")
    with pytest.raises(InputError):
        LocalizeParams(correlative="fallback")
    with pytest.raises(InputError):
        AmbiguityParams(small_scan_below_points=-1)
    for name in ("screen_max_iterations", "screen_max_points"):
        for bad in (0, -3, 2.5, True):
            with pytest.raises(InputError):
                IcpParams(**{name: bad})


def test_cli_correlative_option_reaches_the_params():
    import argparse

    from minegeo.cli import localize as C

    ap = argparse.ArgumentParser()
    C.add_arguments(ap)
    args = ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o", "--levelled", "3",
                          "--correlative", "always"])
    _, lp = C.params_from_args(args)
    assert lp.correlative.mode == "always" and lp.ransac.model == "levelled"
    _, lp = C.params_from_args(ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o"]))
    assert lp.correlative.mode == "fallback" and lp.ransac.model != "levelled"
    args = ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o", "--levelled", "3", "--correlative", "off"])
    assert C.params_from_args(args)[1].correlative is None
    with pytest.raises(SystemExit):
        ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o", "--correlative", "maybe"])


def test_cli_polish_option_reaches_the_params():
    import argparse

    from minegeo.cli import localize as C

    ap = argparse.ArgumentParser()
    C.add_arguments(ap)
    base = ["--map", "m.ply", "--scan", "s.ply", "--out", "o"]
    assert C.params_from_args(ap.parse_args(base))[1].icp.polish_correspondence_m == 0.25
    assert C.params_from_args(ap.parse_args([*base, "--polish", "0.3"]))[1].icp.polish_correspondence_m == 0.3
    assert C.params_from_args(ap.parse_args([*base, "--polish", "0"]))[1].icp.polish_correspondence_m is None
    with pytest.raises(SystemExit) as exc:  # refused by the option's type, before any work
        ap.parse_args([*base, "--polish", "-1"])
    assert exc.value.code == 2


def test_stored_search_structures_give_identical_results(small_mine, tmp_path, monkeypatch, caplog):
    """prepare-map stores the search structures; a localization on the loaded file builds none
    of them and gives bit-identical results; a damaged one is rebuilt, with a warning."""
    import json
    import logging
    from dataclasses import replace

    from minegeo.localize import LocalizeParams, PreparedMap, PrepareParams, localize_scan

    P, pm = small_mine
    base = LocalizeParams.fast()
    lp = replace(base, ransac=replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0,
                                      max_iterations=100_000), correlative=replace(base.correlative, mode="always"))
    pm.build_indexes(lp)
    X, _ = _scan_of(P, np.array([512_038.0, 4_100_004.0]), 11.0, math.radians(-58.0),
                    np.array([512_030.0, 4_100_002.0, 351.0]))
    ref = localize_scan(pm, X, None, lp, seed=0)
    f = tmp_path / "m.npz"
    pm.save(f)
    with np.load(f, allow_pickle=False) as z:
        kinds = [e["kind"] for e in json.loads(str(z["meta"]))["indexes"]["entries"]]
        arrays = {k: z[k] for k in z.files}
    assert {"target_kdtree", "feature_index", "occupancy", "screen_target", "screen_grid"} <= set(kinds)
    q = PreparedMap.load(f, PrepareParams.fast())

    def _no_build(*a, **k):
        raise AssertionError("a stored search structure was rebuilt")

    import minegeo.localize.correlative as C
    import minegeo.registration as R
    import minegeo.registration.correspondences as CO

    with monkeypatch.context() as mp:
        mp.setattr(R, "build_target_index", _no_build)
        mp.setattr(C, "map_occupancy", _no_build)
        mp.setattr(CO, "build_feature_index", _no_build)
        got = localize_scan(q, X, None, lp, seed=0)
    for r in (got,):
        assert r.status == ref.status
        np.testing.assert_array_equal(r.T_map_scan, ref.T_map_scan)
        np.testing.assert_array_equal(r.covariance_6x6, ref.covariance_6x6)
        assert [h["plane_fitness"] for h in r.hypotheses] == [h["plane_fitness"] for h in ref.hypotheses]
        assert r.correlative["hit_fractions"] == ref.correlative["hit_fractions"]
    # a file without them, and one whose stored structures are damaged: rebuilt, same answer
    plain = tmp_path / "plain.npz"
    pm.save(plain, indexes=False)
    with np.load(plain, allow_pickle=False) as z:
        assert not any(k.startswith("index__") for k in z.files)
    bad = dict(arrays)
    for k in list(bad):
        if k.endswith("__perm") or k.endswith("target__idx"):
            bad[k] = bad[k].copy()
            bad[k][0] = bad[k][1]  # no longer a permutation
        if k.endswith("__bits"):
            bad[k] = bad[k][:-1]  # a row short
        if k.endswith("__nearest"):
            bad[k] = bad[k].copy()
            bad[k][0, 0] = 10**9  # points nowhere
    damaged = tmp_path / "damaged.npz"
    np.savez(damaged, **bad)
    for path, n_warn in ((plain, 0), (damaged, 4)):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="minegeo.localize.prepared"):
            qq = PreparedMap.load(path, PrepareParams.fast())
        assert sum("will be rebuilt" in m for m in caplog.messages) == n_warn, caplog.messages
        r = localize_scan(qq, X, None, lp, seed=0)
        np.testing.assert_array_equal(r.T_map_scan, ref.T_map_scan)
        assert [h["plane_fitness"] for h in r.hypotheses] == [h["plane_fitness"] for h in ref.hypotheses]


def test_kdtree_from_arrays_checks_what_queries_rely_on():
    from minegeo.kernels.kdtree import GatedKDTree

    Q = np.random.default_rng(3).uniform(0, 10, (500, 3))
    t = GatedKDTree(Q)
    a = t.arrays()
    u = GatedKDTree.from_arrays(Q, a)
    P = np.random.default_rng(4).uniform(0, 10, (50, 3))
    for x, y in zip(t.query(P, 1.0), u.query(P, 1.0), strict=True):
        np.testing.assert_array_equal(x, y)
    for key, edit in (("idx", lambda v: np.r_[v[1:], v[0:1] * 0 + v[1]]), ("left", lambda v: v + 10**6),
                      ("depth", lambda v: v + 1), ("start", lambda v: v - 1), ("idx", lambda v: v[:-1])):
        b = dict(a)
        b[key] = edit(a[key].copy())
        with pytest.raises(ValueError):
            GatedKDTree.from_arrays(Q, b)
