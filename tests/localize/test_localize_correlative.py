"""Correlative 4-DOF search (minegeo.localize.correlative): kernels against a naive twin,
recovery of a known placement, determinism, parameter checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference.naive_correlative import dilated_cells, score_placements

from minegeo.errors import InputError
from minegeo.localize import _kernels as K
from minegeo.localize.correlative import CorrelativeParams, correlative_candidates, map_occupancy


def _keys(cells):
    return {int(K.cell_key(np.int64(a), np.int64(b), np.int64(c))) for a, b, c in cells}


def test_dilated_table_equals_naive_set():
    rng = np.random.default_rng(1)
    P = rng.uniform(-3.0, 3.0, (300, 3))
    cells = K.unique_cells(P, 0.5)
    assert {tuple(c) for c in cells} == {tuple(int(math.floor(v / 0.5)) for v in p) for p in P}
    table, n = K.build_dilated_table(cells, 1, 16)
    naive = dilated_cells(P, 0.5, 1)
    assert n == len(naive)
    members = {int(k) for k in table if k >= 0}
    assert members == _keys(naive)
    mask, shift = np.int64((1 << 16) - 1), np.int64(64 - 16)
    probe = rng.integers(-12, 12, (2000, 3))
    for c in probe:
        key = K.cell_key(np.int64(c[0]), np.int64(c[1]), np.int64(c[2]))
        assert K.hash_contains(table, key, shift, mask) == (tuple(int(v) for v in c) in naive)


def test_score_placements_equals_naive_twin():
    rng = np.random.default_rng(2)
    Q = rng.uniform(-4.0, 4.0, (400, 3))
    cells = K.unique_cells(Q, 0.5)
    table, _ = K.build_dilated_table(cells, 1, 16)
    S = rng.uniform(-3.0, 3.0, (40, 3))
    anchors = rng.uniform(-1.0, 1.0, (7, 3))
    yaws = np.deg2rad(np.arange(0.0, 360.0, 30.0))
    m = S.shape[0]
    tight, _ = K.build_dilated_table(cells, 0, 15)
    got, got_t = K.score_placements(table, 16, tight, 15, 0.5, S, anchors, np.cos(yaws), np.sin(yaws), m, 1.0,
                                    float(m))
    ref = np.array(score_placements(dilated_cells(Q, 0.5, 1), 0.5, S, anchors, yaws))
    ref_t = np.array(score_placements(dilated_cells(Q, 0.5, 0), 0.5, S, anchors, yaws))
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(got_t, ref_t)
    # early stopping only ever lowers a count, and never one that stayed above the bar
    early, _ = K.score_placements(table, 16, tight, 15, 0.5, S, anchors, np.cos(yaws), np.sin(yaws), 12, 0.3, 4.0)
    assert np.all(early <= ref)
    full = ref >= m - 12
    assert np.all(early[full & (early >= m - 12)] == ref[full & (early >= m - 12)])


def test_refine_kernel_recovers_an_offset_placement():
    """The 4-DOF Gauss-Newton kernel pulls a placement 0.4 m / 2 deg off back onto a box corner."""
    from minegeo.registration import build_target_index

    g = np.arange(0.0, 6.0, 0.1)
    A, B = np.meshgrid(g, g, indexing="ij")
    a, b = A.ravel(), B.ravel()
    Q = np.vstack([np.column_stack([a, b, 0 * a]), np.column_stack([a, 0 * a, b]), np.column_stack([0 * a, a, b])])
    Nq = np.vstack([np.tile(n, (a.size, 1)) for n in ([0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0])])
    S = Q[np.random.default_rng(0).choice(Q.shape[0], 300, replace=False)]
    psi = np.deg2rad(2.0)
    T0 = np.eye(4)
    T0[:3, :3] = [[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]]
    T0[:3, 3] = [0.3, -0.25, 0.1]
    index = build_target_index(Q)
    out_T = np.empty((1, 4, 4))
    cnt = np.zeros(1, dtype=np.int64)
    K.refine_placements_4dof(S, T0[None], Q, Nq, *index._tree, np.linspace(1.5, 0.5, 8) ** 2, 0.05, 0.25, out_T, cnt)
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
    off = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative="off"), seed=0)
    assert off.status != "ok" and off.correlative is None
    fb = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative="fallback"), seed=0)
    assert fb.status == "ok", fb.reason
    assert fb.correlative is not None and fb.correlative["n_candidates"] > 0
    assert fb.hypotheses[0]["source"].startswith("correlative")
    assert error_vs_truth(fb.T_map_scan, T_true, X)["max_point_error_m"] < 0.05
    # bit-identical on a second run (same inputs and seed), correlative path included
    fb2 = localize_scan(pm, X, None, replace(base, ransac=crippled, correlative="fallback"), seed=0)
    np.testing.assert_array_equal(fb.T_map_scan, fb2.T_map_scan)
    np.testing.assert_array_equal(fb.covariance_6x6, fb2.covariance_6x6)
    assert [h["plane_fitness"] for h in fb.hypotheses] == [h["plane_fitness"] for h in fb2.hypotheses]
    assert fb.correlative["hit_fractions"] == fb2.correlative["hit_fractions"]
    al = localize_scan(pm, X, None, replace(base, ransac=replace(crippled, max_iterations=100_000),
                                            correlative="always"), seed=0)
    assert al.status == "ok" and al.correlative is not None
    assert error_vs_truth(al.T_map_scan, T_true, X)["max_point_error_m"] < 0.05
    # a small scan's `ok` is confirmed against the whole map (fallback mode), a large one's is not
    lev = replace(base.ransac, model="levelled", ransac_n=2, max_tilt_deg=3.0, max_iterations=100_000)
    big = localize_scan(pm, X, None, replace(base, ransac=lev, correlative_confirm_below_points=0), seed=0)
    assert big.status == "ok" and big.correlative is None
    small = localize_scan(pm, X, None, replace(base, ransac=lev, correlative_confirm_below_points=big.n_scan_down + 1),
                          seed=0)
    assert small.status == "ok" and small.correlative is not None
    np.testing.assert_allclose(small.T_map_scan, big.T_map_scan, atol=1e-6)
    # a 6-DOF (not levelled) search never runs the correlative search
    six = localize_scan(pm, X, None, replace(base, ransac=replace(base.ransac, max_iterations=2000,
                                                                   min_iterations=0)), seed=0)
    assert six.correlative is None


@pytest.mark.parametrize("kw", [{"cell_size_m": 0.0}, {"yaw_step_deg": -1.0}, {"min_hit_fraction": 0.0},
                                {"min_hit_fraction": 1.5}, {"n_candidates": 0}, {"dilation_cells": -1},
                                {"anchor_max_tilt_deg": 90.0}, {"max_scan_points": 2.5}])
def test_params_validation(kw):
    with pytest.raises(InputError):
        CorrelativeParams(**kw)


def test_localize_params_reject_unknown_mode():
    from minegeo.localize import LocalizeParams

    with pytest.raises(InputError):
        LocalizeParams(correlative="sometimes")
    with pytest.raises(InputError):
        LocalizeParams(correlative_confirm_below_points=-1)


def test_cli_correlative_option_reaches_the_params():
    import argparse

    from minegeo.localize import _cli_localize as C

    ap = argparse.ArgumentParser()
    C.add_arguments(ap)
    args = ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o", "--levelled", "3",
                          "--correlative", "always"])
    _, lp = C.params_from_args(args)
    assert lp.correlative == "always" and lp.ransac.model == "levelled"
    _, lp = C.params_from_args(ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o"]))
    assert lp.correlative == "fallback" and lp.ransac.model != "levelled"
    with pytest.raises(SystemExit):
        ap.parse_args(["--map", "m.ply", "--scan", "s.ply", "--out", "o", "--correlative", "maybe"])


def test_cli_polish_option_reaches_the_params():
    import argparse

    from minegeo.localize import _cli_localize as C

    ap = argparse.ArgumentParser()
    C.add_arguments(ap)
    base = ["--map", "m.ply", "--scan", "s.ply", "--out", "o"]
    assert C.params_from_args(ap.parse_args(base))[1].icp_polish_correspondence_m == 0.25
    assert C.params_from_args(ap.parse_args([*base, "--polish", "0.3"]))[1].icp_polish_correspondence_m == 0.3
    assert C.params_from_args(ap.parse_args([*base, "--polish", "0"]))[1].icp_polish_correspondence_m is None
    with pytest.raises(InputError, match="--polish"):
        C.params_from_args(ap.parse_args([*base, "--polish", "-1"]))
