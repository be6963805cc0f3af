"""A floor driven again after a loop joins the plane node of its first visit (Ren et al. 2019 Sec. 3.4.2:
"the same planar nodes can be observed under different pose nodes"), at the current pose estimate;
another level below, a floor out of reach, or the linking turned off start a new node."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.slam.pipeline import SlamParams, _associate_floors, _plane_set
from minegeo.slam.planes import plane_in_sensor_frame
from minegeo.slam.posegraph import optimize_pose_graph


def _pose(x, y, z, yaw_deg=0.0, pitch_deg=0.0):
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz @ Ry, (x, y, z)
    return T


def _floor(z0, grade_deg=0.0):
    """World plane of a floor at height ``z0`` at x = 0, rising along x by ``grade_deg``."""
    g = np.deg2rad(grade_deg)
    n = np.array([-np.sin(g), 0.0, np.cos(g)])
    return np.r_[n, -n[2] * z0]


def _route():
    """Keyframe poses and world floors: a level drift (x 0..18), a 6° ramp up, a level drift 2 m
    higher, a 6° ramp back down, then the first drift again (x 16..0): the return is 4 sections later."""
    poses, floors = [], []
    for x in range(0, 20, 2):  # 0-9: level drift, floor z = 0
        poses.append(_pose(x, 0, 2.0))
        floors.append(_floor(0.0))
    for k in range(5):  # 10-14: ramp up along +y (a different section)
        poses.append(_pose(20, 2 + 2 * k, 2.0 + 0.2 * k, 90))
        floors.append(np.r_[0.0, -np.sin(0.1), np.cos(0.1), 0.0])
    for k in range(5):  # 15-19: level, 2 m higher
        poses.append(_pose(10 + 2 * k, 14, 4.0))
        floors.append(_floor(2.0))
    for k in range(5):  # 20-24: ramp down (another section)
        poses.append(_pose(4, 12 - 2 * k, 3.5 - 0.3 * k, -90))
        floors.append(np.r_[0.0, np.sin(0.15), np.cos(0.15), -0.3])
    for x in range(16, -1, -2):  # 25-33: the first drift again
        poses.append(_pose(x, 0.3, 2.0, 180))
        floors.append(_floor(0.0))
    poses = np.stack(poses)
    meas = np.stack([plane_in_sensor_frame(f, T) for f, T in zip(floors, poses, strict=True)])
    return poses, meas


def test_a_revisited_floor_joins_its_first_node():
    poses, meas = _route()
    kfs = np.arange(poses.shape[0])
    nodes = _associate_floors(kfs, meas, poses, SlamParams())
    first = nodes[:10]
    assert np.all(first == first[0])
    assert len(set(nodes[10:25].tolist()) & {int(first[0])}) == 0  # the other sections are other nodes
    assert np.all(nodes[25:] == first[0]), nodes  # the return: the first visit's node, not a new one

    off = _associate_floors(kfs, meas, poses, SlamParams(plane_revisit_distance_m=0.0))
    assert np.all(off[:25] == nodes[:25]) and np.all(off[25:] == off[25]) and off[25] not in off[:25]


def test_another_level_or_a_floor_out_of_reach_is_not_linked():
    poses, meas = _route()
    kfs = np.arange(poses.shape[0])
    below = poses.copy()
    below[25:, 2, 3] -= 25.0  # the same x, y one level down: the floor is 25 m lower
    meas_b = np.stack([plane_in_sensor_frame(_floor(-25.0), T) for T in below[25:]])
    nodes = _associate_floors(kfs, np.concatenate([meas[:25], meas_b]), below, SlamParams())
    assert nodes[25] not in nodes[:25]
    far = poses.copy()
    far[25:, 1, 3] += 6.0  # the current estimate puts the return 6 m away from the first visit
    nodes = _associate_floors(kfs, meas, far, SlamParams(plane_revisit_distance_m=4.0))
    assert nodes[25] not in nodes[:25]


def test_the_shared_node_pulls_a_drifted_return_back_to_the_floor():
    """Odometry edges from poses whose return has sunk 0.4 m and pitched 1°; the graph with the
    linked floor brings the return back to the first visit's height (no loop edge)."""
    from minegeo.io.g2o import PoseGraph

    truth, meas = _route()
    n = truth.shape[0]
    est = truth.copy()
    for k in range(10, n):  # drift over the middle sections: the return sits lower and tilted
        f = min(1.0, (k - 9) / 16)
        est[k] = est[k] @ _pose(0, 0, 0, 0, f)
        est[k, 2, 3] -= 0.4 * f
    Z = np.stack([np.linalg.solve(est[k], est[k + 1]) for k in range(n - 1)])
    info = np.tile(np.diag([1e2, 1e2, 1e2, 1e3, 1e3, 1e3]), (n - 1, 1, 1))
    graph = PoseGraph("SE3", np.arange(n), est, np.column_stack([np.arange(n - 1), np.arange(1, n)]), Z, info)
    obs = (np.column_stack([np.arange(n), np.zeros(n, dtype=np.int64)]), meas,
           np.tile(np.diag([1 / np.deg2rad(0.5) ** 2] * 2 + [1 / 0.05 ** 2]), (n, 1, 1)), ["ok"] * n)
    z_err = {}
    for dist in (0.0, 4.0):
        ps = _plane_set(obs, est, SlamParams(plane_revisit_distance_m=dist, plane_max_offset_m=0.5))
        res = optimize_pose_graph(graph, planes=ps)
        z_err[dist] = float(np.abs(res.graph.poses[25:, 2, 3] - truth[25:, 2, 3]).max())
    assert z_err[4.0] < 0.1 < z_err[0.0], z_err


def test_revisit_distance_must_be_non_negative():
    with pytest.raises(InputError):
        SlamParams(plane_revisit_distance_m=-1.0)


def test_a_noisy_level_floor_stays_one_node():
    """Single floors scatter by a few degrees (the sub-map fit): after five level floors, tilts of 1.9°
    towards azimuths 0°, 120°, 240° in turn differ pairwise by 3.3° (> the 3° limit), but each is
    within 3° of the node's running floor."""
    poses = np.stack([_pose(2.0 * k, 0, 2.0) for k in range(30)])
    meas = []
    for k, T in enumerate(poses):
        tilt = np.deg2rad(1.9) if k >= 5 else 0.0
        az = np.deg2rad(120.0 * (k % 3))
        n = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        meas.append(plane_in_sensor_frame(np.r_[n, -float(n @ (T[:3, 3] - [0, 0, 2.0]))], T))
    meas = np.stack(meas)
    kfs = np.arange(30)
    assert np.all(_associate_floors(kfs, meas, poses, SlamParams()) == 0)
    assert _associate_floors(kfs, meas, poses, SlamParams(plane_smoothing=1.0)).max() > 5  # latest floor only
    with pytest.raises(InputError):
        SlamParams(plane_smoothing=0.0)
