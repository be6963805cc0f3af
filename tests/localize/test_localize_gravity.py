"""Tests of minegeo.localize.gravity.estimate_up (issue 15: gravity from the scan's geometry).

The synthetic drifts are exact horseshoe sections (flat floor, vertical walls, half-circle
roof) sampled on regular grids, like the study worlds' drifts (minegeo.synth.world) without
rock roughness; up is known exactly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import InputError, TooFewPointsError
from minegeo.localize.gravity import (
    GravityParams,
    UpEstimate,
    estimate_up,
    hotelling_r2_95,
    levelling_rotation,
)

Z = np.array([0.0, 0.0, 1.0])


def horseshoe(length=14.0, width=4.5, wall_h=2.25, step=0.12, slope_deg=0.0, noise=0.0, seed=0, roof="arch"):
    """Points of a straight drift along x (floor z = x tan(slope), vertical walls, arched or flat roof)."""
    R = width / 2.0
    xs = np.arange(0.0, length + 1e-9, step)
    t = math.tan(math.radians(slope_deg))
    parts = []
    ys = np.arange(-R, R + 1e-9, step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    parts.append(np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)])  # floor
    zs = np.arange(step, wall_h + 1e-9, step)
    for side in (-R, R):  # walls
        X, Zw = np.meshgrid(xs, zs, indexing="ij")
        parts.append(np.c_[X.ravel(), np.full(X.size, side), Zw.ravel()])
    if roof == "arch":
        phis = np.arange(step / R, math.pi - step / R / 2, step / R)
        X, F = np.meshgrid(xs, phis, indexing="ij")
        parts.append(np.c_[X.ravel(), R * np.cos(F.ravel()), wall_h + R * np.sin(F.ravel())])
    else:  # flat roof at wall_h + R (a box section)
        zs2 = np.arange(wall_h + step, wall_h + R - 1e-9, step)
        for side in (-R, R):
            X, Zw = np.meshgrid(xs, zs2, indexing="ij")
            parts.append(np.c_[X.ravel(), np.full(X.size, side), Zw.ravel()])
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        parts.append(np.c_[X.ravel(), Y.ravel(), np.full(X.size, wall_h + R)])
    P = np.vstack(parts)
    P[:, 2] += P[:, 0] * t  # a ramp: every section moves up with x, walls stay vertical
    if noise > 0:
        P = P + np.random.default_rng(seed).normal(scale=noise, size=P.shape)
    return P


def rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def angle(a, b) -> float:
    return math.acos(min(1.0, max(-1.0, float(a @ b) / np.linalg.norm(a) / np.linalg.norm(b))))


@pytest.fixture(scope="module")
def drift():
    return horseshoe()


@pytest.mark.parametrize("rseed", [0, 1, 2])
def test_exact_drift_up_recovered(drift, rseed):
    R = rotation(np.random.default_rng(rseed))
    res = estimate_up(drift @ R.T)
    assert isinstance(res, UpEstimate)
    assert res.status == "ok", res.reason
    assert angle(res.up, R @ Z) < 1e-6
    assert res.sigma_deg < 1e-3  # noise-free: the jackknife has nothing to spread
    # the residual-tilt search is about the drift's cross axis, which is horizontal
    assert abs(float(res.tilt_axis @ (R @ Z))) < 1e-6
    assert abs(abs(float(res.tilt_axis @ (R @ np.array([0.0, 1.0, 0.0])))) - 1.0) < 1e-6
    lev = res.levelling_rotation()
    assert np.allclose(lev @ res.up, Z, atol=1e-12) and np.allclose(lev @ lev.T, np.eye(3), atol=1e-12)


def test_ramp_truth_inside_search_range():
    slope = 12.0
    P = horseshoe(length=20.0, slope_deg=slope)
    R = rotation(np.random.default_rng(7))
    res = estimate_up(P @ R.T)
    assert res.status == "ok", res.reason
    floor = [c for c in res.candidates if c.source == "floor"][0]
    # the floor hypothesis is off by the slope, about the cross axis
    assert abs(math.degrees(angle(floor.up, R @ Z)) - slope) < 1e-3
    a = res.assess(R @ Z)
    assert abs(abs(a["tilt_deg"]) - slope) < 1e-3 and abs(a["cross_deg"]) < 1e-3
    assert a["in_search"]
    lo, hi = res.tilt_range_deg
    assert lo <= -res.params.max_slope_deg and hi >= res.params.max_slope_deg
    # and the search's candidates contain an up within a step of the truth
    ups = res.tilt_candidates(step_deg=1.0)
    assert min(angle(u, R @ Z) for u in ups) < math.radians(0.5 + 1e-6)


@settings(max_examples=6, deadline=None)
@given(st.integers(min_value=0, max_value=2**31 - 1))
def test_rotation_equivariance(seed):
    P = horseshoe(length=10.0, step=0.15, noise=0.02, seed=3)
    R = rotation(np.random.default_rng(seed))
    a = estimate_up(P)
    b = estimate_up(P @ R.T)
    assert a.status == b.status == "ok"
    assert angle(b.up, R @ a.up) < 1e-6
    # the jackknife blocks are cut along the drift axis; float noise may move a boundary point
    assert abs(b.sigma_deg - a.sigma_deg) < 0.05 * a.sigma_deg + 1e-9


def test_permutation_invariance():
    P = horseshoe(length=10.0, step=0.15, noise=0.02, seed=4)
    perm = np.random.default_rng(5).permutation(len(P))
    p = GravityParams(max_points=5000)  # the area-uniform subsample is drawn too
    a = estimate_up(P, params=p)
    b = estimate_up(P[perm], params=p)
    assert np.array_equal(a.up, b.up)
    assert np.array_equal(a.covariance_rad2, b.covariance_rad2)


def test_deterministic():
    P = horseshoe(length=10.0, step=0.15, noise=0.03, seed=6)
    p = GravityParams(max_points=6000, seed=3)
    a, b = estimate_up(P, params=p), estimate_up(P, params=p)
    assert np.array_equal(a.up, b.up) and a.to_dict() == {**b.to_dict(), "timings_s": a.to_dict()["timings_s"]}


def test_noisy_drift_covered_by_cone():
    P = horseshoe(length=14.0, step=0.12, noise=0.03, seed=8)
    R = rotation(np.random.default_rng(9))
    res = estimate_up(P @ R.T)
    assert res.ok
    a = res.assess(R @ Z)
    assert a["angle_deg"] < 0.5 and a["angle_deg"] <= res.cone95_deg


def test_flat_roof_is_not_ok():
    # a box section: floor and roof alike, so the sign of up is not identifiable from shape
    res = estimate_up(horseshoe(roof="flat"))
    assert res.status in ("ambiguous", "failed")
    assert res.reason


def test_single_plane_fails():
    g = np.arange(0.0, 10.0, 0.1)
    X, Y = np.meshgrid(g, g)
    P = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    res = estimate_up(P)
    assert res.status == "failed" and res.up is None
    assert "plane" in res.reason
    with pytest.raises(InputError):
        res.levelling_rotation()


def test_vertical_shaft_fails():
    # a 4 x 4 m square shaft, 20 m deep, no floor in view
    s = 0.12
    a = np.arange(-2.0, 2.0 + 1e-9, s)
    z = np.arange(0.0, 20.0, s)
    parts = []
    for c in (-2.0, 2.0):
        A, Zz = np.meshgrid(a, z)
        parts.append(np.c_[np.full(A.size, c), A.ravel(), Zz.ravel()])
        parts.append(np.c_[A.ravel(), np.full(A.size, c), Zz.ravel()])
    res = estimate_up(np.vstack(parts))
    assert res.status == "failed"
    assert "floor" in res.reason or "plane" in res.reason


def test_bad_inputs():
    P = horseshoe(length=6.0, step=0.2)
    Pn = P.copy()
    Pn[10, 1] = np.nan
    with pytest.raises(InputError):
        estimate_up(Pn)
    with pytest.raises(TooFewPointsError):
        estimate_up(P[:50])
    with pytest.raises(InputError):
        estimate_up(P, normals=np.ones((3, 3)))
    with pytest.raises(InputError):
        estimate_up(P, normals=np.zeros_like(P))
    with pytest.raises(InputError):
        estimate_up(P[:, :2])
    with pytest.raises(InputError):
        GravityParams(n_blocks=2)
    with pytest.raises(InputError):
        GravityParams(max_slope_deg=95.0)


def test_given_normals_are_used(drift):
    # exact normals (floor z, walls y, roof radial) give the same answer as PCA normals
    N = np.zeros_like(drift)
    floor = drift[:, 2] == 0.0
    wall = (~floor) & (drift[:, 2] <= 2.25 + 1e-9)
    roof = ~(floor | wall)
    N[floor] = Z
    N[wall, 1] = 1.0
    N[roof, 1] = drift[roof, 1]
    N[roof, 2] = drift[roof, 2] - 2.25
    N[roof] /= np.linalg.norm(N[roof], axis=1)[:, None]
    res = estimate_up(drift, normals=N)
    assert res.ok and angle(res.up, Z) < 1e-9


def test_helpers():
    assert hotelling_r2_95(8) == pytest.approx(12.0, rel=1e-3)
    assert hotelling_r2_95(1000) == pytest.approx(5.99, rel=0.01)
    for u in (Z, -Z, np.array([1.0, 2.0, 3.0])):
        R = levelling_rotation(u)
        assert np.allclose(R @ (u / np.linalg.norm(u)), Z, atol=1e-12)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
