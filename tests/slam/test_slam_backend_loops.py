"""Loop acceptance for long loops (benchmarks/bench_slam.py, the 667 m synthetic ring): the correction
limit grows with the trajectory distance between the keyframes, and a registration whose inlier RMSE
is above ``max_rmse_m`` is accepted only when another candidate puts the keyframe at the same pose."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from minegeo.geometry.se3 import exp_so3
from minegeo.slam.loops import LoopCandidate, LoopParams, _confirm, find_loop
from minegeo.slam.odometry import OdometryParams, prepare_frame


def _T(t, yaw=0.0):
    T = np.eye(4)
    T[:3, :3] = exp_so3([0.0, 0.0, yaw])
    T[:3, 3] = t
    return T


def _cand(i, rmse):
    return LoopCandidate(i, 50, 1.0, 0.9, rmse, False, "", np.eye(4), np.eye(6))


def test_a_loose_registration_needs_a_second_candidate_that_agrees():
    p = LoopParams()
    # keyframe 50 registered to 10, 11 (agree within 5 cm / 0.2°) and 12 (a look-alike 8 m along the drift)
    tried = [_cand(10, 0.40), _cand(11, 0.42), _cand(12, 0.39)]
    world = [_T([100.0, 0, 0]), _T([100.05, 0, 0], 0.003), _T([108.0, 0, 0])]
    tried = _confirm(tried, world, p)
    assert [bool(c.reason) for c in tried] == [False, False, True]
    assert "no other candidate confirms" in tried[2].reason
    # a tight registration (RMSE below max_rmse_m) needs no confirmation; a lone loose one is rejected
    tried = [_cand(10, 0.25), _cand(12, 0.40)]
    tried = _confirm(tried, [_T([100.0, 0, 0]), _T([108.0, 0, 0])], p)
    assert [bool(c.reason) for c in tried] == [False, True]
    # a candidate already rejected (e.g. low overlap) confirms nothing
    tried = [_cand(10, 0.40), replace(_cand(11, 0.40), reason="overlap 0.20 below 0.50")]
    tried = _confirm(tried, [_T([100.0, 0, 0]), _T([100.0, 0, 0])], p)
    assert tried[0].reason


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
    frames = [prepare_frame(simulate_scan(world, sensor, T, seed=1 + k).points, float(k), odo)
              for k, T in enumerate(P[:3])]
    back_T = P[0] @ _T([0.6, 0.2, 0.0], 0.3)  # back at the first place, seen again with new noise
    frames.append(prepare_frame(simulate_scan(world, sensor, back_T, seed=9).points, 100.0, odo))
    return frames, np.stack([P[0], P[1], P[2], back_T]), odo


def test_the_correction_limit_grows_with_the_loop_length(place):
    frames, truth, odo = place
    poses = truth.copy()
    poses[3] = truth[3] @ _T([3.0, -0.4, 0.1], 0.05)  # 3 m of drift by the time it returns
    p = LoopParams(max_correction_m=1.0, max_correction_per_path=0.01)
    short = find_loop(3, poses, np.array([0.0, 4.0, 8.0, 48.0]), frames, p, odo)  # limit max(1, 0.48) m
    assert not any(c.accepted for c in short) and any("beyond the limits" in c.reason for c in short)
    long = find_loop(3, poses, np.array([0.0, 4.0, 8.0, 400.0]), frames, p, odo)  # limit 4 m after 400 m
    acc = [c for c in long if c.accepted]
    assert len(acc) == 1 and acc[0].i == 0, [(c.i, c.reason) for c in long]
    true_rel = np.linalg.solve(truth[0], truth[3])
    assert np.linalg.norm(acc[0].T_i_j[:3, 3] - true_rel[:3, 3]) < 0.05
