"""Sensor streams (minegeo.synth.stream): per-point times of motion-distorted sweeps, determinism, the CLI.

The per-point time checks use a straight flat drift (walls y = +-1.6 m, floor z = 0, roof z = 3 m)
and a curve whose true pose is written here in closed form (linear position, Euler angles through
scipy), independent of the B-spline code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from minegeo.synth.flight import NetworkWorld
from minegeo.synth.imu import ImuParams
from minegeo.synth.motion import curve_from_samples
from minegeo.synth.network import DriftNetwork
from minegeo.synth.sensors import Velodyne16
from minegeo.synth.stream import StreamParams, iter_sweeps, write_stream

HALF_W, ROOF = 1.6, 3.0
T_FRAME = 0.05


@pytest.fixture(scope="module")
def drift_world():
    net = DriftNetwork(np.array([[-100.0, 0.0], [100.0, 0.0]]), np.array([[0, 1]], np.int64), np.array([3.2]),
                       np.array([ROOF, ROOF]), ("", ""), {"kind": "test"})
    return NetworkWorld(net)


def _motion(v, p0, yaw_rate, roll_rate, pitch=0.0):
    """Closed-form truth and the curve built from its samples: p = p0 + v t, yaw = 0.3 + yaw_rate t,
    pitch constant, roll = roll_rate t (all linear, which a cubic B-spline reproduces exactly)."""
    v, p0 = np.asarray(v, float), np.asarray(p0, float)

    def truth(t):
        t = np.asarray(t, float)
        R = Rotation.from_euler("ZYX", np.column_stack([0.3 + yaw_rate * t, np.full_like(t, pitch),
                                                        roll_rate * t])).as_matrix()
        return R, p0 + t[:, None] * v

    ts = np.arange(-0.1, 0.4, 0.01)
    curve = curve_from_samples(ts[0], 0.01, p0 + ts[:, None] * v,
                               np.column_stack([0.3 + yaw_rate * ts, np.full_like(ts, pitch), roll_rate * ts]))
    return curve, truth


def _surface_distance(P):
    """Distance (m) to the nearest analytic surface and its unit normal."""
    d = np.column_stack([np.abs(HALF_W - np.abs(P[:, 1])), np.abs(P[:, 2]), np.abs(ROOF - P[:, 2])])
    k = np.argmin(d, axis=1)
    n = np.zeros_like(P)
    n[k == 0, 1] = 1.0
    n[k != 0, 2] = 1.0
    return d[np.arange(len(P)), k], n


def _sweep(world, curve, noise=0.0, hz=10.0):
    sensor = Velodyne16(azimuth_step_deg=1.0, rotation_rate_hz=hz, range_noise_sigma_m=noise)
    ((tf, P, tt, ring),) = list(iter_sweeps(world, sensor, curve, [T_FRAME], np.random.SeedSequence(5)))
    assert tf == T_FRAME
    return P, tt


@pytest.mark.parametrize("hz", [10.0, 20.0])
def test_points_land_on_the_wall_with_their_own_time_pose(drift_world, hz):
    """Moving 3.2 m/s and turning 86 deg/s: each point, placed with the TRUE pose at frame time + its
    own ``time``, lies on the rock; placed with the frame-time pose the sweep is smeared."""
    curve, truth = _motion([3.0, 0.6, 0.8], [0.0, 0.2, 1.2], 1.5, 0.4, pitch=0.1)
    P, tt = _sweep(drift_world, curve, hz=hz)
    period = 1.0 / hz
    assert len(P) > 0.9 * 360 * 16 and np.all(np.diff(tt) >= 0)
    assert tt.min() >= 0.0 and tt.max() < period and tt.max() > 0.95 * period
    R, o = truth(T_FRAME + tt)
    Pw = np.einsum("nij,nj->ni", R, P) + o
    inside = np.abs(Pw[:, 0]) < 95.0
    d_true, _ = _surface_distance(Pw[inside])
    assert d_true.max() < 1e-6, d_true.max()
    R0, o0 = truth(np.array([T_FRAME]))
    d_frame, _ = _surface_distance((P @ R0[0].T + o0[0])[inside])
    assert np.median(d_frame) > 0.02 and d_frame.max() > 0.2


def test_frame_time_pose_misses_by_velocity_times_offset(drift_world):
    """Pure translation v: the frame-time pose misplaces a point by exactly v * time, so its miss
    from the surface it hit is |n . v| * time (walls: 0.6 m/s, floor/roof: 0.8 m/s)."""
    v = np.array([3.0, 0.6, 0.8])
    curve, truth = _motion(v, [0.0, 0.2, 1.2], 0.0, 0.0)
    P, tt = _sweep(drift_world, curve, noise=0.0)
    R, o = truth(T_FRAME + tt)
    Pw = np.einsum("nij,nj->ni", R, P) + o
    inside = np.abs(Pw[:, 0]) < 95.0
    d_true, n = _surface_distance(Pw[inside])
    assert d_true.max() < 1e-6
    R0, o0 = truth(np.array([T_FRAME]))
    P0 = (P @ R0[0].T + o0[0])[inside]
    miss = np.abs(np.einsum("ij,ij->i", P0 - Pw[inside], n))
    assert np.abs(miss - np.abs(n @ v) * tt[inside]).max() < 1e-9
    assert 0.9 * 0.8 * 0.1 < miss.max() < 0.8 * 0.1 + 1e-9      # up to v_perp x one sweep period


def test_range_noise_along_the_beam(drift_world):
    curve, truth = _motion([3.0, 0.6, 0.8], [0.0, 0.2, 1.2], 1.5, 0.4)
    P, tt = _sweep(drift_world, curve, noise=0.01)
    R, o = truth(T_FRAME + tt)
    Pw = np.einsum("nij,nj->ni", R, P) + o
    inside = np.abs(Pw[:, 0]) < 95.0
    d, _ = _surface_distance(Pw[inside])
    assert d.max() < 6 * 0.01 and np.median(d) > 0.002       # noisy, but only along the beam's range


TINY = dict(duration_s=1.0, lidar_hz=10.0, azimuth_step_deg=4.0, network="loop")


def _files(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_stream_deterministic_and_streams_independent(tmp_path):
    a, b, c, d, e = (tmp_path / k for k in "abcde")
    write_stream(a, StreamParams(preset="handheld", seed=3, imu=ImuParams(rate_hz=100.0), **TINY))
    write_stream(b, StreamParams(preset="handheld", seed=3, imu=ImuParams(rate_hz=100.0), **TINY))
    write_stream(c, StreamParams(preset="handheld", seed=4, imu=ImuParams(rate_hz=100.0), **TINY))
    write_stream(d, StreamParams(preset="handheld", seed=3, imu=ImuParams(rate_hz=100.0,
                                                                         gyroscope_noise_density=1e-3), **TINY))
    write_stream(e, StreamParams(preset="handheld", seed=3, imu=ImuParams(rate_hz=200.0), **TINY))
    fa, fb, fc, fd, fe = _files(a), _files(b), _files(c), _files(d), _files(e)
    assert fa == fb
    assert len([k for k in fa if k.startswith("frames/") and k.endswith(".ply")]) == 10 and "frames/times.txt" in fa
    assert fa["imu.csv"] != fc["imu.csv"] and fa["frames/000003.ply"] != fc["frames/000003.ply"]
    assert fa["groundtruth.txt"] != fc["groundtruth.txt"]                 # the motion's draws differ too
    # another gyro noise density: same motion, same LiDAR noise, same bias walk; only the IMU readings change
    assert all(fa[k] == fd[k] for k in fa if k.startswith("frames/")) and fa["groundtruth.txt"] == fd["groundtruth.txt"]
    ta = np.loadtxt(a / "imu_truth.csv", delimiter=",", skiprows=1)
    td = np.loadtxt(d / "imu_truth.csv", delimiter=",", skiprows=1)
    assert np.array_equal(ta, td) and fa["imu.csv"] != fd["imu.csv"]
    # twice the IMU rate (twice the IMU draws): the sweeps are the same bytes
    assert all(fa[k] == fe[k] for k in fa if k.startswith("frames/")) and fa["imu.csv"] != fe["imu.csv"]


def test_cli_stream_outputs(tmp_path):
    import json

    from minegeo.cli import main
    from minegeo.io import read_point_cloud, read_trajectory

    out = tmp_path / "s"
    assert main(["synth", str(out), "--stream", "vehicle", "--duration-s", "0.5", "--lidar-hz", "20",
                 "--imu-hz", "400", "--seed", "2"]) == 0
    times = np.loadtxt(out / "frames" / "times.txt")  # the SLAM contract's DIR/times.txt
    assert np.allclose(times, 0.5 + 0.05 * np.arange(10))
    gt = read_trajectory(out / "groundtruth.txt")
    assert np.allclose(gt.times_s, times)
    c = read_point_cloud(out / "frames" / "000004.ply")
    assert c.attributes["time"].dtype == np.float64 and 0.0 <= c.attributes["time"].min()
    assert c.attributes["time"].max() < 0.05
    head = (out / "imu.csv").read_text().splitlines()
    assert head[0] == "t,gx,gy,gz,ax,ay,az" and len(head) == 1 + 601      # [0, 1.0 + 0.5] s at 400 Hz
    imu = np.loadtxt(out / "imu.csv", delimiter=",", skiprows=1)
    assert abs(np.median(imu[:, 6]) - 9.80665) < 0.1                      # at rest: +g on the up axis
    rec = json.loads((out / "result.json").read_text())
    assert rec["params"]["imu"]["gyroscope_noise_density"] == ImuParams().gyroscope_noise_density
    assert rec["params"]["lidar_hz"] == 20.0 and rec["n_frames"] == 10


@pytest.mark.parametrize("argv,expect", [
    (["--stream", "drone", "--mast"], "--mast"),
    (["--stream", "drone", "--preset", "paper"], "--preset"),
    (["--duration-s", "2"], "--stream"),
    (["--stream", "drone", "--stream-network", "no_such_edgelist.csv"], "edge list"),
    (["--stream", "drone", "--lidar-hz", "40"], "--lidar-hz"),
])
def test_cli_stream_bad_options(tmp_path, capsys, argv, expect):
    from tests.badinput._contract import assert_user_error

    out = tmp_path / "s"
    assert_user_error("synth", [str(out), *argv], capsys, outputs=[out], expect=expect)
