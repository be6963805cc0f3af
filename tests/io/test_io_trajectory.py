"""Trajectory formats (TUM, KITTI, GeoSLAM-style, CSV), quaternion helpers, CTU real files."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from minegeo.errors import FileFormatError, InputError
from minegeo.geometry.se3 import exp_so3
from minegeo.io import (
    Trajectory,
    matrix_to_quat,
    quat_to_matrix,
    read_trajectory,
    read_transform,
    write_trajectory,
)


def _traj(rng, m=30, origin=(0.0, 0.0, 0.0)):
    poses = np.tile(np.eye(4), (m, 1, 1))
    for i in range(m):
        poses[i, :3, :3] = exp_so3(rng.normal(size=3) * 1.5)
        poses[i, :3, 3] = rng.normal(size=3) * 100
    return Trajectory(times_s=1.6e9 + np.cumsum(rng.uniform(0.05, 0.2, m)), poses=poses, origin=origin)


@settings(max_examples=30, deadline=None)
@given(w=hnp.arrays(np.float64, 3, elements=st.floats(-3.1, 3.1)))
def test_quat_matrix_roundtrip_and_scipy(w):
    from scipy.spatial.transform import Rotation

    R = exp_so3(w)
    q = matrix_to_quat(R)
    assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-15
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-14)
    qs = Rotation.from_matrix(R).as_quat()
    np.testing.assert_allclose(q, qs * np.sign(qs[3]) if qs[3] != 0 else q, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(q[[3, 0, 1, 2]], order="wxyz"), R, atol=1e-14)


def test_quat_edge_cases():
    # rotations by pi about each axis exercise every Shepperd branch
    for axis in np.eye(3):
        R = exp_so3(axis * np.pi)
        np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-14)
    with pytest.raises(InputError, match="not unit length"):
        quat_to_matrix([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="proper rotation"):
        matrix_to_quat(np.diag([1.0, 1.0, -1.0]))


@pytest.mark.parametrize("fmt", ["tum", "geoslam", "csv"])
def test_quaternion_formats_roundtrip(tmp_path, rng, fmt):
    t = _traj(rng)
    p = tmp_path / f"t.{fmt}.txt"
    write_trajectory(p, t, format=fmt)
    back = read_trajectory(p)  # format detected from the content
    np.testing.assert_array_equal(back.times_s, t.times_s)
    np.testing.assert_array_equal(back.poses[:, :3, 3], t.poses[:, :3, 3])
    np.testing.assert_allclose(back.poses, t.poses, rtol=0, atol=1e-14)
    assert read_trajectory(p, format=fmt).poses.shape == (30, 4, 4)


def test_kitti_roundtrip_exact(tmp_path, rng):
    t = _traj(rng)
    t = Trajectory(np.arange(len(t), dtype=float), t.poses)
    write_trajectory(tmp_path / "00.txt", t, format="kitti")
    back = read_trajectory(tmp_path / "00.txt")
    np.testing.assert_array_equal(back.poses, t.poses)
    np.testing.assert_array_equal(back.times_s, np.arange(len(t)))


def test_geoslam_is_scalar_first_and_tolerant(tmp_path):
    # 90 deg about z: w = cos45, z = sin45; GeoSLAM order is q0(w) q1 q2 q3
    s = np.sqrt(0.5)
    p = tmp_path / "scan_traj.txt"
    p.write_text(f"Time X Y Z q0 q1 q2 q3 Intensity\n0.0 1 2 3 {s} 0 0 {s} 7\n0.1 1 2 3 1 0 0 0 7\n")
    t = read_trajectory(p)
    np.testing.assert_allclose(t.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_array_equal(t.positions[0], [1, 2, 3])


@pytest.mark.parametrize("suffix,fmt", [(".csv", "csv"), (".kitti", "kitti"), (".tum", "tum"), (".txt", "tum")])
def test_write_infers_the_format_from_the_suffix_as_read_does(tmp_path, rng, suffix, fmt):
    t = _traj(rng)
    p = tmp_path / f"t{suffix}"
    write_trajectory(p, t)
    explicit = tmp_path / f"e{suffix}"
    write_trajectory(explicit, t, format=fmt)
    assert p.read_bytes() == explicit.read_bytes()
    back = read_trajectory(p)
    np.testing.assert_allclose(back.poses[:, :3, 3], t.poses[:, :3, 3], atol=1e-9)


def test_global_local_and_origin(tmp_path, rng):
    t = _traj(rng, origin=(500000.0, 4000000.0, 0.0))
    write_trajectory(tmp_path / "g.tum", t)
    back = read_trajectory(tmp_path / "g.tum", origin=(500000.0, 4000000.0, 0.0))
    np.testing.assert_allclose(back.positions, t.positions, rtol=0, atol=1e-9)
    write_trajectory(tmp_path / "l.tum", t, coordinates="local")
    np.testing.assert_array_equal(read_trajectory(tmp_path / "l.tum").positions, t.positions)


@pytest.mark.parametrize(
    "content,match",
    [
        ("", "empty"),
        ("# only a comment\n", "no numeric pose"),
        ("1 2 3 4 5 6 7\n", "7 numbers per line"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n", "line 2: expected 8 values, found 7"),
        ("0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n", "line 2: a value is NaN"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 2\n", r"line 2: the quaternion \(qx qy qz qw\) = \(0, 0, 0, 2\) has norm 2, not 1"),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 x 1\n", "line 2: 'x' is not a number"),
        ("time_s,x,y,z,qw\n0,0,0,0,1\n", "names no quaternion|lacks"),
    ],
)
def test_trajectory_errors(tmp_path, content, match):
    p = tmp_path / "bad.txt"
    p.write_text(content)
    with pytest.raises(FileFormatError, match=match) as ei:
        read_trajectory(p)
    assert "bad.txt" in str(ei.value)


def test_kitti_non_orthonormal(tmp_path):
    p = tmp_path / "k.txt"
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(FileFormatError, match=r"line 2: the rotation block is not a rotation: max \|R\^T R - I\| = 3"):
        read_trajectory(p)


#: the shared check of every reader: (file text, the line and problem the message must name)
CHECK_CASES = {
    "reflection_kitti": ("# KITTI\n1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 -1 0\n",
                         r"line 3: the rotation block is a reflection \(det R = -1\)"),
    "duplicated_time": ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n",
                        r"line 3: time 1.000000 s is not after the previous pose's 1.000000 s"),
    "decreasing_time": ("5 0 0 0 0 0 0 1\n\n# c\n4.5 0 0 0 0 0 0 1\n",
                        r"line 4: time 4.500000 s is not after the previous pose's 5.000000 s"),
    "huge_time": ("-1.7e308 0 0 0 0 0 0 1\n0 0 0 0 0 0 0 1\n", r"line 1: time -1.7e\+308 s is not a time stamp"),
    "inf_time": ("0 0 0 0 0 0 0 1\ninf 0 0 0 0 0 0 1\n", r"line 2: a value is NaN or inf"),
    "zero_quaternion": ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0\n", r"line 2: the quaternion \(qx qy qz qw\) = \(0, 0, 0, 0\) is zero"),
    "close_times_differ_late": ("1.0000000000000002 0 0 0 0 0 0 1\n1.0000000000000002 0 0 0 0 0 0 1\n",
                                r"line 2: time 1.0000000000000002 s is not after the previous pose's 1.0000000000000002 s"),
    "csv_decreasing": ("time_s,x,y,z,qx,qy,qz,qw\n2,0,0,0,0,0,0,1\n1,0,0,0,0,0,0,1\n", r"line 3: time 1.000000 s"),
    "geoslam_zero_q": ("Time X Y Z q0 q1 q2 q3\n0 0 0 0 1 0 0 0\n1 0 0 0 0 0 0 0\n",
                       r"line 3: the quaternion \(q0 q1 q2 q3\) = \(0, 0, 0, 0\) is zero"),
}


@pytest.mark.parametrize("case", sorted(CHECK_CASES))
def test_the_shared_check_names_file_line_and_problem(tmp_path, case):
    text, match = CHECK_CASES[case]
    p = tmp_path / "t.txt"
    p.write_text(text)
    with pytest.raises(FileFormatError, match=match) as ei:
        read_trajectory(p)
    assert str(ei.value).startswith(str(p) + ": ")


def test_kitti_at_six_digits_is_a_rotation_and_a_small_reflection_is_not(tmp_path):
    """KITTI files print ~6 significant digits (|R^T R - I| ~ 1e-6, the MulRan files): accepted; the same
    matrix with one column negated (det -1, exactly as orthonormal) is refused."""
    R = exp_so3(np.array([0.3, -0.2, 1.1]))
    row = " ".join(f"{v:.6g}" for v in np.c_[R, [1.0, 2.0, 3.0]].ravel())
    p = tmp_path / "k.kitti"
    p.write_text(row + "\n" + row + "\n")
    np.testing.assert_allclose(read_trajectory(p).poses[1, :3, :3], R, atol=1e-6)
    M = np.c_[R[:, :2], -R[:, 2], [1.0, 2.0, 3.0]]
    p.write_text(row + "\n" + " ".join(f"{v:.6g}" for v in M.ravel()) + "\n")
    with pytest.raises(FileFormatError, match="line 2: the rotation block is a reflection"):
        read_trajectory(p)


def test_kitti_times_file(tmp_path, rng):
    from minegeo.io.trajectory import read_times

    t = _traj(rng, m=5)
    write_trajectory(tmp_path / "00.txt", Trajectory(np.arange(5.0), t.poses), format="kitti")
    (tmp_path / "times.txt").write_text("# KITTI\n0.0\n1.0e-1\n0.2 # c\n\n0.35\n4.5e2\n")
    back = read_trajectory(tmp_path / "00.txt", times=tmp_path / "times.txt")
    assert back.times_s.tolist() == [0.0, 0.1, 0.2, 0.35, 450.0]
    (tmp_path / "short.txt").write_text("0\n1\n")
    with pytest.raises(FileFormatError, match="holds 2 times for 5 poses"):
        read_trajectory(tmp_path / "00.txt", times=tmp_path / "short.txt")
    write_trajectory(tmp_path / "t.tum", t)
    with pytest.raises(InputError, match="tum trajectory with its own times"):
        read_trajectory(tmp_path / "t.tum", times=tmp_path / "times.txt")
    for text, match in [("0\n1 2\n", "line 2: 2 values"), ("0\nnan\n", "line 2: 'nan' is not a number of seconds"),
                        ("0\n1_000\n", "line 2: '1_000' is not a time in seconds"), ("", "holds no times"),
                        ("0\n2\n1\n", "line 3: time 1.000000 s is not after the previous pose's 2.000000 s"),
                        ("0\n1e400\n", r"line 2: time inf is not a number"),
                        ("1.7e308\n1.71e308\n", "line 1: time 1.7e\\+308 s is not a time stamp")]:
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(FileFormatError, match=match):
            read_times(tmp_path / "bad.txt")


def test_times_file_that_is_not_a_file_is_named_without_blocking(tmp_path):
    import os

    from minegeo.io.trajectory import read_times

    os.mkfifo(tmp_path / "fifo")  # opening it would block until a writer comes
    (tmp_path / "d").mkdir()
    for path, what in [(tmp_path / "fifo", "is a FIFO"), (tmp_path / "d", "is a folder, not a times file"),
                       ("/dev/zero", "is a character device"), (tmp_path / "none", "no such file")]:
        with pytest.raises(FileFormatError, match=what):
            read_times(path)


def test_write_refuses_what_read_would_refuse(tmp_path, rng):
    t = _traj(rng, m=4)
    times = t.times_s.copy()
    times[2] = times[1]
    with pytest.raises(InputError, match="pose 2: time .* is not after"):
        write_trajectory(tmp_path / "a.tum", Trajectory(times, t.poses))
    with pytest.raises(InputError, match="pose 0: time -1.7e\\+308 s is not a time stamp"):
        write_trajectory(tmp_path / "a.tum", Trajectory([-1.7e308, 0.0, 1.7e308, 1.71e308], t.poses))
    poses = t.poses.copy()
    poses[3, :3, 2] *= -1.0
    with pytest.raises(InputError, match="pose 3: the rotation block is a reflection"):
        write_trajectory(tmp_path / "a.kitti", Trajectory(np.arange(4.0), poses))
    assert not any(tmp_path.iterdir())


CTU = {
    "bull_rock_cave/0_front": 323,
    "bull_rock_cave/1_back": 325,
    "subt_finals/uav21_2": None,
    "subt_finals/uav21_3": None,
    "subt_finals/uav21_4": None,
    "subt_finals/uav21_5": None,
    "subt_finals/uav21_6": None,
    "subt_finals/uav22_1": None,
    "subt_finals/uav22_2": None,
    "subt_finals/uav22_3": None,
    "subt_finals/uav24_1": None,
}


@pytest.mark.parametrize("flight", sorted(CTU))
def test_ctu_ground_truth_trajectories(flight):
    p = shared_data("ctu_cave_mine_uav_trajectories", *flight.split("/"), "trajectory_groundtruth.txt")
    t = read_trajectory(p)
    if CTU[flight] is not None:
        assert len(t) == CTU[flight]
    assert len(t) > 10
    # trajectories start at the zero pose (SOURCE.md)
    np.testing.assert_allclose(t.poses[0], np.eye(4), atol=1e-8)  # file stores ~5e-9 quaternion parts
    assert np.all(np.diff(t.times_s) > 0)
    R = t.poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("mji,mjk->mik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    T_map_fcu = read_transform(p.parent / "fcu_in_map.mat")
    assert T_map_fcu.shape == (4, 4)
    np.testing.assert_allclose(T_map_fcu[:3, :3].T @ T_map_fcu[:3, :3], np.eye(3), atol=1e-6)


def test_ctu_path_length_matches_mission_data():
    p = shared_data("ctu_cave_mine_uav_trajectories", "bull_rock_cave", "0_front", "trajectory_groundtruth.txt")
    t = read_trajectory(p)
    steps = np.linalg.norm(np.diff(t.positions, axis=0), axis=1).sum()
    # mission_data.txt: 731.4 s flight, 475.5 m (on-board, denser sampling); the GT poses are sparser
    assert 350 < steps < 480
    assert abs((t.times_s[-1] - t.times_s[0]) - 739.4) < 1.0


def test_read_transform_variants(tmp_path):
    p = tmp_path / "T.txt"
    p.write_text("1 0 0 1\n0 1 0 2\n0 0 1 3\n")
    np.testing.assert_array_equal(read_transform(p)[:3, 3], [1, 2, 3])
    p.write_text("[[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]")
    np.testing.assert_array_equal(read_transform(p)[3], [0, 0, 0, 1])
    p.write_text("1 0 0 1\n0 1 0 2\n")
    with pytest.raises(FileFormatError, match="12 or 16"):
        read_transform(p)
    T = read_transform(shared_data("small_gicp_pair", "T_target_source.txt"))
    np.testing.assert_allclose(T[0, 3], 0.488882)
