"""Pose graph with plane landmarks (Ren et al. 2019 Sec. 3.4.2-3.4.3): exact data, the normal
equations against a dense finite-difference twin, a drifting chain pulled back by a shared floor,
the gauge rules, and the between-only path unchanged."""

from __future__ import annotations

import numpy as np
import pytest
from reference import naive_planes as NPL
from reference import naive_posegraph as NP
from reference import naive_posegraph_planes as NPP

from minegeo.errors import InputError
from minegeo.io.g2o import PoseGraph
from minegeo.slam import posegraph as PG
from minegeo.slam.planes import plane_in_sensor_frame
from minegeo.slam.posegraph import PlaneSet, PoseGraphParams, optimize_pose_graph, pose_graph_cost

TR = [3, 4, 5, 0, 1, 2]  # (ω, ρ) → the file's (t, r) order


def _unit(v):
    return v / np.linalg.norm(v)


def _scene(rng, n=6, n_planes=3, extra=3, noise=0.0):
    """Poses (moderate rotations), world planes, between-edges and pose–plane edges (2 planes per pose)."""
    truth = [np.eye(4)]
    for _ in range(1, n):
        truth.append(NP.exp(np.r_[rng.normal(scale=0.3, size=3), rng.uniform(-5, 5, 3)]))
    truth = np.stack(truth)
    planes = np.stack([np.r_[_unit(rng.normal(size=3) + [0, 0, 2.0]), rng.uniform(-3, 3)] for _ in range(n_planes)])
    pairs = [(k, k + 1) for k in range(n - 1)]
    while len(pairs) < n - 1 + extra:
        i, j = sorted(rng.choice(n, 2, replace=False).tolist())
        if (i, j) not in pairs:
            pairs.append((i, j))
    Z = np.stack([np.linalg.inv(truth[i]) @ truth[j] @ NP.exp(rng.normal(scale=noise, size=6)) for i, j in pairs])
    A = rng.normal(size=(len(pairs), 6, 6))
    info_rt = np.einsum("eij,ekj->eik", A, A) + 6 * np.eye(6)
    graph = PoseGraph("SE3", np.arange(n), truth.copy(), np.asarray(pairs), Z, info_rt[:, TR][:, :, TR])
    pedges = np.array([(v, (v + s) % n_planes) for v in range(n) for s in (0, 1)])
    meas = []
    for v, l in pedges:
        m = plane_in_sensor_frame(planes[l], truth[v])
        if noise:
            m = np.r_[_unit(m[:3] + rng.normal(scale=noise, size=3)), m[3] + rng.normal(scale=noise)]
        meas.append(m)
    B = rng.normal(size=(len(pedges), 3, 3))
    pinfo = np.einsum("eij,ekj->eik", B, B) + 3 * np.eye(3)
    return graph, truth, PlaneSet(planes.copy(), pedges, np.stack(meas), pinfo), info_rt


def _perturb(graph, ps, rng, scale, fixed=(0,)):
    p = graph.poses.copy()
    for k in range(graph.n_vertices):
        if k not in fixed:
            p[k] = p[k] @ NP.exp(rng.normal(scale=scale, size=6))
    pl = np.stack([NPL.retract_plane(q, rng.normal(scale=scale, size=3)) for q in ps.planes])
    return graph.with_poses(p), ps.with_planes(pl)


def test_exact_poses_and_planes_are_recovered_from_a_perturbed_start(rng):
    graph, truth, ps, _ = _scene(rng)
    g0, ps0 = _perturb(graph, ps, rng, 0.1)
    assert pose_graph_cost(g0, ps0) > 1.0
    res = optimize_pose_graph(g0, PoseGraphParams(), ps0)
    assert res.status == "converged" and res.cost_final < 1e-16
    np.testing.assert_allclose(res.graph.poses, truth, atol=1e-9)
    np.testing.assert_allclose(res.planes.planes, ps.planes, atol=1e-9)
    np.testing.assert_array_equal(res.planes.edges, ps.edges)
    assert res.summary()["planes"] == {"nodes": 3, "edges": 12}


def test_cost_gradient_and_normal_equations_against_dense_twin(rng):
    graph, _, ps, info_rt = _scene(rng, noise=0.02)
    fixed = (0, 2)  # a second fixed pose: its blocks must be skipped, its plane edges still count
    g0, ps0 = _perturb(graph, ps, rng, 0.05, fixed)
    args = (list(g0.poses), g0.edges, g0.measurements, info_rt, list(ps0.planes), ps0.edges, ps0.measurements,
            ps0.information)
    assert pose_graph_cost(g0, ps0) == pytest.approx(NPP.total_cost(*args), rel=1e-10)
    free_col = np.full(g0.n_vertices, -1, dtype=np.int64)
    free = [v for v in range(g0.n_vertices) if v not in fixed]
    free_col[free] = np.arange(len(free)) * 6
    w, wp = np.ones(g0.n_edges), np.ones(ps0.n_edges)
    H, g, _ = PG._normal_equations("SE3", g0.poses, g0.edges, g0.measurements, PG._information_rt(g0), w, free_col,
                                   (ps0.planes, ps0, wp))
    H_n, g_n = NPP.normal_equations(*args, fixed=fixed)
    g_fd = NPP.gradient_fd(*args, fixed=fixed)
    assert H.shape == (6 * 4 + 3 * 3,) * 2
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-5 * np.abs(g_fd).max())
    np.testing.assert_allclose(g, g_n, rtol=1e-5, atol=1e-6 * np.abs(g_n).max())
    np.testing.assert_allclose(H.toarray(), H_n, rtol=1e-5, atol=1e-6 * np.abs(H_n).max())
    np.testing.assert_allclose(H.toarray(), H.toarray().T, atol=1e-9 * np.abs(H_n).max())


def test_a_shared_floor_pulls_back_drifting_roll_pitch_and_height():
    # 25 keyframes 2 m apart over a level floor (sensor 1.2 m above it); the odometry has a bias of
    # 0.01 rad roll and 0.005 rad pitch per step: alone the chain ends ~15 deg tilted and over a
    # metre too high. The floor landmark seen from each keyframe holds roll, pitch and height. (A
    # constant height bias per step along a straight line would be a grade of the floor: a free
    # plane cannot tell it from the truth, so the bias here is rotational, as in a real drift.)
    n = 25
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    truth = np.stack([np.eye(4) for _ in range(n)])
    truth[:, 0, 3] = 2.0 * np.arange(n)
    truth[:, 2, 3] = 1.2
    bias = NP.exp(np.r_[0.01, 0.005, 0.0, 0.0, 0.0, 0.0])
    Z = np.stack([np.linalg.inv(truth[k]) @ truth[k + 1] @ bias for k in range(n - 1)])
    info = np.tile(np.diag([1e2] * 3 + [1e3] * 3), (n - 1, 1, 1))  # (ω, ρ)
    poses = [truth[0]]
    for z in Z:
        poses.append(poses[-1] @ z)
    graph = PoseGraph("SE3", np.arange(n), np.stack(poses), np.c_[np.arange(n - 1), np.arange(1, n)], Z,
                      info[:, TR][:, :, TR])
    meas = np.stack([plane_in_sensor_frame(floor, T) for T in truth])
    ps = PlaneSet(plane_in_sensor_frame(meas[0], np.linalg.inv(truth[0]))[None], np.c_[np.arange(n), np.zeros(n)],
                  meas, np.tile(np.diag([1e4, 1e4, 1e4]), (n, 1, 1)))

    def errors(P):
        roll_pitch = np.degrees(np.arccos(np.clip(P[:, 2, 2], -1, 1)))  # tilt of the sensor's z axis
        return roll_pitch.max(), np.abs(P[:, 2, 3] - 1.2).max()

    alone = optimize_pose_graph(graph)
    with_floor = optimize_pose_graph(graph, None, ps)
    tilt0, dz0 = errors(alone.graph.poses)
    tilt1, dz1 = errors(with_floor.graph.poses)
    assert tilt0 > 10.0 and dz0 > 1.0  # the odometry chain alone keeps its drift
    assert with_floor.status == "converged"
    assert tilt1 < 0.05 and dz1 < 0.005, (tilt1, dz1)
    np.testing.assert_allclose(with_floor.planes.planes[0], floor, atol=1e-3)


def test_gauge_rules_and_input_checks(rng):
    graph, _, ps, _ = _scene(rng)
    # an extra plane nobody observes: its columns would be zero
    lone = PlaneSet(np.r_[ps.planes, [[0, 0, 1.0, 0]]], ps.edges, ps.measurements, ps.information)
    res = optimize_pose_graph(graph, None, lone)
    assert res.status == "failed" and "observed by no pose" in res.reason
    # a pose tied to the rest only through planes is not anchored (a plane fixes z, roll, pitch only)
    keep = ~np.any(graph.edges == graph.n_vertices - 1, axis=1)
    cut = PoseGraph("SE3", graph.ids, graph.poses, graph.edges[keep], graph.measurements[keep],
                    graph.information[keep])
    res = optimize_pose_graph(cut, None, ps)
    assert res.status == "failed" and "not constrained" in res.reason
    with pytest.raises(InputError):
        PlaneSet(ps.planes, ps.edges[:-1], ps.measurements, ps.information)
    with pytest.raises(InputError):
        PlaneSet(ps.planes * 2.0, ps.edges, ps.measurements, ps.information)
    with pytest.raises(InputError):
        optimize_pose_graph(graph, None, PlaneSet(ps.planes, ps.edges + [graph.n_vertices, 0], ps.measurements,
                                                  ps.information))


def test_an_empty_plane_set_changes_nothing(rng):
    graph, _, ps, _ = _scene(rng, noise=0.05)
    g0, _ = _perturb(graph, ps, rng, 0.1)
    a = optimize_pose_graph(g0)
    b = optimize_pose_graph(g0, None, PlaneSet(np.zeros((0, 4)), np.zeros((0, 2)), np.zeros((0, 4)),
                                               np.zeros((0, 3, 3))))
    assert a.graph.poses.tobytes() == b.graph.poses.tobytes() and a.cost_final == b.cost_final
    assert a.planes is None and b.planes.n_planes == 0
