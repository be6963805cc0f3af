"""Roadway floor planes (Ren et al. 2019, Sec. 3.4.2): RANSAC floor extraction, the plane in the
sensor frame [Ren2019 Eq. 9] [Ren2019 Eq. 10], and the pose–plane factor [Ren2019 Eq. 11]
against the naive twin (tests/reference/naive_planes.py) and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import naive_planes as NPL
from reference import naive_posegraph as NP

from minegeo.errors import InputError
from minegeo.slam import _kernels_planes as KP
from minegeo.slam.planes import (
    FloorPlaneParams,
    extract_floor_plane,
    plane_in_sensor_frame,
    plane_in_world_frame,
    plane_q_paper,
    pose_plane_residuals,
    pose_plane_terms,
    retract_plane,
)


def _rot(rng, angle=np.pi * 0.95):
    axis = rng.normal(size=3)
    return NP.exp(np.r_[axis / np.linalg.norm(axis) * rng.uniform(0, angle), np.zeros(3)])[:3, :3]


def _pose(rng, angle=np.pi * 0.95, trans=20.0):
    T = np.eye(4)
    T[:3, :3] = _rot(rng, angle)
    T[:3, 3] = rng.uniform(-trans, trans, 3)
    return T


def _unit(v):
    return v / np.linalg.norm(v)


def _roadway(rng, floor_plane=(0.0, 0.0, 1.0, 0.0), n_floor=3000, noise=0.0, clutter=400):
    """A 6 m wide roadway along x: floor points on ``floor_plane`` (+ noise), two walls and a roof
    starting 0.3 m above the floor, and clutter boxes (people, machines) 0.3-1.8 m above it."""
    n = np.asarray(floor_plane[:3], float)
    d = float(floor_plane[3])
    xy = rng.uniform([-12, -3], [12, 3], size=(n_floor, 2))
    z = -(d + n[0] * xy[:, 0] + n[1] * xy[:, 1]) / n[2]  # on the plane
    floor = np.c_[xy, z] + (rng.normal(scale=noise, size=(n_floor, 3)) if noise else 0.0)
    m = 1500
    wall_x = rng.uniform(-12, 12, m)
    walls = [np.c_[wall_x, np.full(m, s * 3.0), rng.uniform(0.3, 4.0, m)] for s in (-1, 1)]
    roof = np.c_[rng.uniform([-12, -3], [12, 3], size=(m, 2)), np.full(m, 4.0)]
    box = np.c_[rng.uniform(-1, 1, (clutter, 2)) + [4.0, 1.0], rng.uniform(0.3, 1.8, clutter)]
    rest = np.r_[walls[0], walls[1], roof, box]
    # lift the non-floor geometry onto the (possibly sloped) floor
    rest[:, 2] += -(d + n[0] * rest[:, 0] + n[1] * rest[:, 1]) / n[2]
    return np.r_[floor, rest], n_floor


# ---------------------------------------------------------------- floor extraction (RANSAC)


@pytest.mark.parametrize("plane", [(0.0, 0.0, 1.0, 0.0), (0.05, -0.08, 1.0, 1.7), (-0.2, 0.1, 1.0, -3.0)])
def test_exact_floor_is_found_exactly(rng, plane):
    n = _unit(np.asarray(plane[:3]))
    truth = np.r_[n, plane[3] / np.linalg.norm(plane[:3])]
    P, n_floor = _roadway(rng, truth)
    center = np.array([0.5, 0.2, 0.0])
    center[2] = -(truth[3] + n[0] * center[0] + n[1] * center[1]) / n[2] + 2.0  # 2 m above the floor
    res = extract_floor_plane(P, center, FloorPlaneParams(radius_m=15.0), seed=3)
    assert res.status == "ok", res.reason
    np.testing.assert_allclose(res.plane, truth, atol=1e-12)
    rel = P[:n_floor] - center  # the floor points of the sub-map (a slope can rise above the sensor)
    band = (np.einsum("ij,ij->i", rel, rel) <= 15.0 ** 2) & (rel[:, 2] <= -0.3) & (rel[:, 2] >= -5.0)
    np.testing.assert_array_equal(res.inliers, np.flatnonzero(band))
    assert res.rms_m < 1e-12
    assert res.sensor_height_m == pytest.approx(2.0 * n[2], abs=1e-9)


def test_noisy_floor_with_clutter(rng):
    P, n_floor = _roadway(rng, noise=0.01)
    res = extract_floor_plane(P, [0, 0, 2.0], FloorPlaneParams(radius_m=15.0), seed=11)
    assert res.status == "ok", res.reason
    assert np.degrees(np.arccos(res.normal @ [0, 0, 1])) < 0.1
    assert abs(res.d) < 2e-3
    assert 0.006 < res.rms_m < 0.012
    assert res.n_inliers > 0.99 * n_floor


def test_same_seed_same_result_and_kernel_matches_naive(rng):
    P, _ = _roadway(rng, noise=0.01, n_floor=400, clutter=50)
    p = FloorPlaneParams(radius_m=15.0, iterations=40)
    a, b = extract_floor_plane(P, [0, 0, 2.0], p, seed=5), extract_floor_plane(P, [0, 0, 2.0], p, seed=5)
    assert a.plane.tobytes() == b.plane.tobytes() and np.array_equal(a.inliers, b.inliers)
    # the counts of every hypothesis, kernel against the loop twin (same draws)
    rel = P - [0, 0, 2.0]
    cand = np.flatnonzero((np.einsum("ij,ij->i", rel, rel) <= 15.0 ** 2) & (rel[:, 2] <= -0.3) & (rel[:, 2] >= -5))
    Pc = np.ascontiguousarray(P[cand])
    samples = np.random.default_rng(5).integers(0, cand.size, size=(40, 3))
    samples[0] = [1, 1, 2]  # a degenerate sample
    counts, hyp = np.empty(40, dtype=np.int64), np.empty((40, 4))
    cos_t = np.cos(np.deg2rad(20.0))
    KP.ransac_plane_counts(Pc, samples, np.array([0, 0, 1.0]), cos_t, 0.05, counts, hyp)
    np.testing.assert_array_equal(counts, NPL.ransac_counts(Pc, samples, np.array([0, 0, 1.0]), cos_t, 0.05))
    assert counts[0] == -1 and np.any(counts == -2) and counts.max() > 300


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_extraction_is_rigid_motion_invariant(s):
    rng = np.random.default_rng(s)
    P, _ = _roadway(rng, noise=0.01, n_floor=800, clutter=100)
    T = _pose(rng)
    R, t = T[:3, :3], T[:3, 3]
    p = FloorPlaneParams(radius_m=15.0, iterations=200)
    a = extract_floor_plane(P, [0.3, -0.2, 2.0], p, seed=s)
    b = extract_floor_plane(P @ R.T + t, R @ [0.3, -0.2, 2.0] + t, p, seed=s, up=R[:, 2])
    assert a.status == b.status and a.n_inliers == b.n_inliers  # "ok" in almost every case
    for pa, pb in ((a.ransac_plane, b.ransac_plane), (a.plane, b.plane)):
        n = R @ pa[:3]
        np.testing.assert_allclose(pb, np.r_[n, pa[3] - n @ t], atol=1e-9)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert b.rms_m == pytest.approx(a.rms_m, rel=1e-9)


def test_status_without_a_floor(rng):
    P, n_floor = _roadway(rng)
    walls_only = P[n_floor:]
    walls_only = walls_only[walls_only[:, 2] < 3.9]  # no roof either
    res = extract_floor_plane(walls_only, [0, 0, 2.0], FloorPlaneParams(radius_m=15.0), seed=1)
    assert res.status == "no plane" and np.all(np.isnan(res.plane))
    # a 30 degree ramp is too steep for the 20 degree default
    ramp = np.r_[np.sin(np.radians(30)), 0.0, np.cos(np.radians(30)), 0.0]
    P2, _ = _roadway(rng, ramp, clutter=0)
    res2 = extract_floor_plane(P2[:3000], [0, 0, 2.0], FloorPlaneParams(radius_m=15.0), seed=1)
    assert res2.status == "no plane" and "steeper" in res2.reason
    assert extract_floor_plane(P2[:3000], [0, 0, 2.0], FloorPlaneParams(radius_m=15.0, max_tilt_deg=35),
                               seed=1).status == "ok"
    # too few points: empty cloud, or everything above the sensor
    assert extract_floor_plane(np.empty((0, 3)), [0, 0, 0], seed=0).status == "too few points"
    assert extract_floor_plane(P, [0, 0, -5.0], seed=0).status == "too few points"
    with pytest.raises(InputError):
        FloorPlaneParams(max_tilt_deg=95)


# ---------------------------------------------------------------- plane transformation


def test_plane_in_sensor_frame_round_trip_and_twin(rng):
    for _ in range(20):
        T = _pose(rng)
        pw = np.r_[_unit(rng.normal(size=3)), rng.uniform(-10, 10)]
        ps = plane_in_sensor_frame(pw, T)
        np.testing.assert_allclose(ps, NPL.plane_to_sensor(pw, T), atol=1e-12)
        np.testing.assert_allclose(plane_in_world_frame(ps, T), pw, atol=1e-12)
        # a point of the plane, seen from the sensor, is on the transformed plane
        p_w = -pw[3] * pw[:3] + np.cross(pw[:3], rng.normal(size=3))
        p_s = T[:3, :3].T @ (p_w - T[:3, 3])
        assert abs(ps[:3] @ p_s + ps[3]) < 1e-10
        # the paper's form with [R_t, t_t] = T⁻¹ (world to sensor) gives the same plane
        Rt, tt = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
        n_p = Rt @ pw[:3]
        np.testing.assert_allclose(ps, np.r_[n_p, pw[3] - tt @ n_p], atol=1e-12)
        # R instead of Rᵀ (the paper's R_t read as T_world_sensor's rotation) is wrong
        assert np.linalg.norm(T[:3, :3] @ pw[:3] - ps[:3]) > 1e-6


# ---------------------------------------------------------------- pose–plane factor


def _edges(rng, m=12, tilt_deg=15.0, consistent=False):
    """Random poses and world planes (floors and walls), measurements near the prediction."""
    poses = np.stack([_pose(rng) for _ in range(4)])
    planes = np.stack([np.r_[_unit(rng.normal(size=3)), rng.uniform(-5, 5)] for _ in range(2)]
                      + [np.array([0.0, 0.0, 1.0, 1.5]), np.array([0.0, 0.0, -1.0, 4.0])])
    edges = np.c_[rng.integers(0, 4, m), rng.integers(0, 4, m)]
    meas = []
    for i, k in edges:
        ps = NPL.plane_to_sensor(planes[k], poses[i])
        if not consistent:
            n = ps[:3] @ _rot(rng, np.radians(tilt_deg)).T
            ps = np.r_[n / np.linalg.norm(n), ps[3] + rng.normal(scale=0.2)]
        meas.append(ps)
    return poses, planes, edges, np.stack(meas)


def test_residual_is_zero_for_consistent_pose_and_plane(rng):
    poses, planes, edges, meas = _edges(rng, consistent=True)
    # a levelled sensor above a floor: the paper's q() is at its singularity here, the chart is not
    poses[0] = np.eye(4)
    poses[0][:3, 3] = [3.0, -1.0, 0.5]
    edges[0] = [0, 2]
    meas[0] = plane_in_sensor_frame(planes[2], poses[0])
    np.testing.assert_allclose(meas[0][:3], [0, 0, 1], atol=1e-15)
    r = pose_plane_residuals(poses, planes, edges, meas)
    np.testing.assert_allclose(r, 0.0, atol=1e-10)


def test_residual_and_jacobians_against_twin_and_finite_differences(rng):
    poses, planes, edges, meas = _edges(rng, m=30)
    r, Jp, Jl = pose_plane_terms(poses, planes, edges, meas)
    for e, (i, k) in enumerate(edges):
        np.testing.assert_allclose(r[e], NPL.residual(poses[i], planes[k], meas[e]), atol=1e-12)
        Jp_n, Jl_n = NPL.numeric_jacobians(poses[i], planes[k], meas[e])
        np.testing.assert_allclose(Jp[e], Jp_n, atol=1e-6)
        np.testing.assert_allclose(Jl[e], Jl_n, atol=1e-6)


def test_finite_difference_check_catches_a_broken_jacobian(rng):
    # the same check as above applied to a deliberately broken pose Jacobian (a sign error in the
    # rotation block, the typical left/right-perturbation mistake) must fail
    poses, planes, edges, meas = _edges(rng, m=8)
    _, Jp, _ = pose_plane_terms(poses, planes, edges, meas)
    broken = Jp.copy()
    broken[:, :2, :3] *= -1.0
    ok_good = ok_broken = True
    for e, (i, k) in enumerate(edges):
        Jp_n, _ = NPL.numeric_jacobians(poses[i], planes[k], meas[e])
        ok_good &= np.allclose(Jp[e], Jp_n, atol=1e-6)
        ok_broken &= np.allclose(broken[e], Jp_n, atol=1e-6)
    assert ok_good and not ok_broken


def test_plane_retraction_and_basis(rng):
    for n in [np.array([0, 0, 1.0]), np.array([0, 0, -1.0]), _unit(rng.normal(size=3)), _unit(rng.normal(size=3))]:
        B = KP.plane_tangent_basis(n)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-14)
        np.testing.assert_allclose(B.T @ n, 0.0, atol=1e-14)
        pl = np.r_[n, 2.0]
        np.testing.assert_allclose(retract_plane(pl, np.zeros(3)), pl, atol=1e-15)
        delta = np.array([0.01, -0.02, 0.3])
        out = retract_plane(pl, delta)
        np.testing.assert_allclose(out, NPL.retract_plane(pl, delta), atol=1e-15)
        assert np.linalg.norm(out[:3]) == pytest.approx(1.0) and out[3] == pytest.approx(2.3)


def test_paper_q_is_singular_for_a_floor():
    # why the factor uses a chart: at a vertical normal the paper's azimuth jumps by π between
    # opposite 1 mrad tilts and its elevation cannot tell them apart (π/2 − |tilt|, a kink)
    q0 = plane_q_paper([0, 0, 1.0, 1.0])
    q1 = plane_q_paper(np.r_[_unit(np.array([1e-3, 0, 1.0])), 1.0])
    q2 = plane_q_paper(np.r_[_unit(np.array([-1e-3, 0, 1.0])), 1.0])
    assert q0[1] == pytest.approx(np.pi / 2) and q1[1] == pytest.approx(q2[1], abs=1e-15)
    assert abs(q1[0] - q2[0]) == pytest.approx(np.pi)
    tilted = np.r_[_unit(np.array([1e-3, 0, 1.0])), 1.0]
    r = pose_plane_residuals(np.eye(4)[None], tilted[None], [[0, 0]], [[0, 0, 1.0, 1.0]])
    assert np.linalg.norm(r[0, :2]) == pytest.approx(1e-3, rel=1e-6)


def test_factor_removes_height_drift_in_a_small_gauss_newton(rng):
    # three keyframes on a level floor, the poses drifted in height and roll; the floor landmark
    # (seen from each) with the first pose held fixed pull the others back onto it
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    truth = [np.eye(4) for _ in range(3)]
    for k, T in enumerate(truth):
        T[:3, 3] = [5.0 * k, 0.0, 1.2]
    meas = np.stack([plane_in_sensor_frame(floor, T) for T in truth])
    poses = [truth[0]] + [T @ NP.exp(np.r_[0.03, -0.02, 0.0, 0.0, 0.0, 0.15]) for T in truth[1:]]
    plane = floor.copy()
    edges = np.array([[0, 0], [1, 0], [2, 0]])
    for _ in range(10):  # pose 0 fixed (gauge); unknowns: poses 1, 2 (6 each) and the plane (3)
        r, Jp, Jl = pose_plane_terms(np.stack(poses), plane[None], edges, meas)
        J = np.zeros((9, 15))
        for e in range(3):
            if e:
                J[3 * e:3 * e + 3, 6 * (e - 1):6 * e] = Jp[e]
            J[3 * e:3 * e + 3, 12:] = Jl[e]
        delta = -np.linalg.lstsq(J, r.ravel(), rcond=None)[0]  # minimum-norm: yaw/x/y are unobservable
        poses = [poses[0]] + [poses[k] @ NP.exp(delta[6 * (k - 1):6 * k]) for k in (1, 2)]
        plane = retract_plane(plane, delta[12:])
    r = pose_plane_residuals(np.stack(poses), plane[None], edges, meas)
    assert np.abs(r).max() < 1e-10
    for T, Tt in zip(poses, truth, strict=True):
        assert T[2, 3] == pytest.approx(Tt[2, 3], abs=1e-9)
        np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-9)  # roll and pitch restored
