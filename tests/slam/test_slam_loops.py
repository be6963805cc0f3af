"""Loop closure (Ren et al. 2019 Sec. 3.4.1): a return to a known place is found and corrects the drift;
rules exclude recent keyframes; a correction beyond the limits is rejected and says why."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.geometry.se3 import exp_so3
from minegeo.slam.loops import LoopParams, candidates, find_loop
from minegeo.slam.odometry import OdometryParams, prepare_frame


@pytest.fixture(scope="module")
def place():
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    traj = make_trajectory(world, "drive", length_m=12.0, seed=4)
    P = interpolate_poses(traj, np.linspace(0.0, traj.times_s[-1], 4))
    sensor = Velodyne16(azimuth_step_deg=0.4)
    odo = OdometryParams()
    first = prepare_frame(simulate_scan(world, sensor, P[0], seed=1).points, 0.0, odo)
    mid = [prepare_frame(simulate_scan(world, sensor, T, seed=2 + k).points, 1.0 + k, odo) for k, T in enumerate(P[1:3])]
    # back at the first place later, seen again with new noise, 40 m of path later
    back_T = P[0] @ np.block([[exp_so3([0.0, 0.0, 0.3]), np.array([[0.6], [0.2], [0.0]])],
                              [np.zeros((1, 3)), np.ones((1, 1))]])
    back = prepare_frame(simulate_scan(world, sensor, back_T, seed=9).points, 100.0, odo)
    truth = np.stack([P[0], P[1], P[2], back_T])
    return [first, *mid, back], truth, odo


def _drifted(truth, dx=1.2, dyaw=0.05):
    poses = truth.copy()
    D = np.eye(4)
    D[:3, :3] = exp_so3([0.0, 0.0, dyaw])
    D[:3, 3] = [dx, -0.4, 0.1]
    poses[3] = truth[3] @ D  # the odometry has drifted by the time it returns
    return poses


def test_a_return_is_closed_and_corrects_the_drift(place):
    frames, truth, odo = place
    poses = _drifted(truth)
    path = np.array([0.0, 4.0, 8.0, 48.0])
    tried = find_loop(3, poses, path, frames, LoopParams(), odo)
    acc = [c for c in tried if c.accepted]
    assert len(acc) == 1 and acc[0].i == 0, [(c.i, c.reason) for c in tried]
    true_rel = np.linalg.solve(truth[0], truth[3])
    assert np.linalg.norm(acc[0].T_i_j[:3, 3] - true_rel[:3, 3]) < 0.05
    assert np.all(np.linalg.eigvalsh(acc[0].information) > 0)


def test_rules_exclude_the_recent_past():
    pos = np.array([[0.0, 0, 0], [3.0, 0, 0], [6.0, 0, 0], [2.0, 0, 0]])
    path = np.array([0.0, 3.0, 6.0, 12.0])
    p = LoopParams(min_path_gap_m=10.0, max_distance_m=5.0)
    assert candidates(3, pos, path, p).tolist() == [0]  # keyframes 1 and 2 are only 9 m and 6 m of path back
    assert candidates(3, pos, np.array([0.0, 1.0, 2.0, 30.0]), p).tolist() == [1, 0, 2]  # nearest first
    assert candidates(3, pos, np.array([0.0, 1.0, 2.0, 30.0]), LoopParams(min_path_gap_m=10.0, max_distance_m=1.5,
                                                                          max_candidates=3)).tolist() == [1]


def test_a_correction_beyond_the_limits_is_rejected_with_the_reason(place):
    frames, truth, odo = place
    poses = _drifted(truth, dx=3.0)
    tried = find_loop(3, poses, np.array([0.0, 4.0, 8.0, 48.0]), frames,
                      LoopParams(max_correction_m=1.0), odo)
    assert tried and not any(c.accepted for c in tried)
    assert any("beyond the limits" in c.reason for c in tried)


def test_loop_correction_is_the_disagreement_with_the_current_poses():
    """Hand calculation: keyframe j placed 10 m east of i, its loop measures it 0.3 m further east
    and turned 2° about z: the correction is (T_i⁻¹ T_j)⁻¹ Z_ij = a 0.3 m shift and a 2° turn,
    whatever the keyframes' common world pose."""
    from minegeo.slam.loops import LoopCandidate, loop_correction

    def pose(R, t):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return T

    W = pose(exp_so3(np.array([0.1, -0.2, 0.7])), [5.0, -3.0, 2.0])  # any common world placement
    poses = np.stack([W @ pose(np.eye(3), [0, 0, 0]), W @ pose(np.eye(3), [10.0, 0, 0])])
    Z = pose(exp_so3(np.radians([0.0, 0.0, 2.0])), [10.3, 0.0, 0.0])
    c = LoopCandidate(0, 1, 10.0, 0.9, 0.05, True, "", Z, np.eye(6))
    m, deg = loop_correction(c, poses)
    assert m == pytest.approx(0.3, abs=1e-12) and deg == pytest.approx(2.0, abs=1e-9)
    agree = LoopCandidate(0, 1, 10.0, 0.9, 0.05, True, "", np.linalg.solve(poses[0], poses[1]), np.eye(6))
    assert loop_correction(agree, poses) == pytest.approx((0.0, 0.0), abs=1e-6)
