"""Frame sequences for ``minegeo slam`` (``minegeo.synth.sequence``): the route, the frames folder, and
control points read off a map through the estimated poses."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import InputError
from minegeo.io.frames import list_frames, read_frame
from minegeo.io.types import ControlPoints, Trajectory
from minegeo.synth.sequence import DEMO_LOOP, pick_gcps_in_map, route_path, simulate_sequence, write_frames


@pytest.fixture(scope="module")
def world():
    from minegeo.synth.world import build_world

    return build_world("small", 1)


def test_demo_loop_turns_on_arcs_inside_the_drifts(world):
    path = route_path(world, DEMO_LOOP["drifts"], DEMO_LOOP["start_m"], DEMO_LOOP["end_m"])
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    assert 100.0 < seg.sum() < 130.0
    assert np.linalg.norm(path[0, :2] - path[-1, :2]) < 20.0  # it comes back: a loop
    h = np.arctan2(*np.diff(path[:, :2], axis=0).T[::-1])
    turn = np.degrees(np.abs((np.diff(h) + np.pi) % (2 * np.pi) - np.pi))
    assert turn.max() < 20.0  # the 90 degree junction turns are arcs, not corners
    up = path + np.array([0.0, 0.0, 1.5])
    assert (world.sdf(up, with_structures=False) > 1.0).all()  # well inside the drifts


def test_route_errors(world):
    with pytest.raises(InputError, match="no drift"):
        route_path(world, [("nope", True)])
    with pytest.raises(InputError, match="does not start where"):
        route_path(world, [("main_L0_001", True), ("main_L0_003", True)])


def test_frames_folder_round_trip_and_determinism(world, tmp_path):
    path = route_path(world, [("main_L0_002", True)], 0.0, 4.0)
    truth, frames = simulate_sequence(world, path, rate_hz=2.0, seed=4)
    again = simulate_sequence(world, path, rate_hz=2.0, seed=4)
    assert np.array_equal(truth.poses, again[0].poses) and all(np.array_equal(a, b) for a, b in
                                                               zip(frames, again[1], strict=True))
    assert len(frames) >= 2 and frames[0].shape == (180 * 16, 3)  # 2 degree azimuth step, all rays hit
    write_frames(tmp_path / "f", truth.times_s, frames)
    files = list_frames(tmp_path / "f")
    assert [f.time_s for f in files] == pytest.approx(truth.times_s.tolist(), abs=1e-6)
    assert np.array_equal(read_frame(files[1].path), frames[1])
    with pytest.raises(InputError, match="not empty"):
        write_frames(tmp_path / "f", truth.times_s, frames)


def _pose(yaw, t):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def test_picked_targets_follow_the_estimated_pose_of_the_nearest_frame():
    truth = Trajectory(np.array([0.0, 1.0]), np.stack([_pose(0.3, [10, 5, 2]), _pose(0.5, [30, 5, 2])]))
    # the estimate: the truth in the first frame, then the second frame 0.2 m off
    est_poses = np.einsum("ij,njk->nik", np.linalg.inv(truth.poses[0]), truth.poses)
    est_poses[1, :3, 3] += [0.2, 0.0, 0.0]
    est = Trajectory(truth.times_s, est_poses)
    p = np.array([[12.0, 7.0, 3.0], [31.0, 3.0, 3.0], [28.0, 9.0, 3.0], [100.0, 0.0, 0.0]])
    gcps = ControlPoints(ids=["A", "B", "C", "far"], local_xyz=p, crs_enh=p + 1000.0,
                         sigma_enh_m=np.full((4, 3), 0.005), crs="EPSG:5186")
    T0i = np.linalg.inv(truth.poses[0])
    expect = p[:3] @ T0i[:3, :3].T + T0i[:3, 3]
    expect[1:] += [0.2, 0.0, 0.0]  # seen from the second frame: they carry its error
    picked, rows = pick_gcps_in_map(gcps, truth, est, expect)
    assert picked.ids == ["A", "B", "C"] and np.allclose(picked.local_xyz, expect, atol=1e-9)
    assert np.array_equal(picked.crs_enh, gcps.crs_enh[:3])
    assert [r["frame"] for r in rows] == [0, 1, 1, None] and "from the nearest frame" in rows[3]["reason"]
    # a target with no map point near its picked place is not in the map
    with pytest.raises(InputError, match="only 2 control point"):
        pick_gcps_in_map(gcps, truth, est, expect[:2])
