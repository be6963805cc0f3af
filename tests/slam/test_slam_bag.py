"""``minegeo slam --frames BAG``: a ROS 1 bag and ROS 2 bags (sqlite3, MCAP) give the trajectory of
the same frames as files (issue 29 acceptance).

The data: 16 sweeps of a short simulated vehicle stream (``minegeo.synth.stream``, 10 Hz, each point
at its own firing time, motion-smeared), coordinates and per-point times rounded to float32 (as a
Velodyne driver publishes them). The same numbers are written twice: as a frames folder (PLY with
float32 ``x y z`` and a float32 ``time`` property, ``times.txt`` holding the stamps as decimal
seconds with 9 digits) and as PointCloud2 messages (float32 ``x y z time``) stamped at the frame
times on a UNIX epoch (``sec``, ``nanosec``).

Expected: ``trajectory.tum`` byte-identical to the one from the files. Why exact: both readers hand
the odometry the same float64 values: float32 -> float64 is exact; the frame time
``float("S.NNNNNNNNN")`` and ``ns / 1e9`` are both the float64 nearest to the same rational number
(a correctly rounded parse and a correctly rounded division of two exact integers below 2**53); and
the run is deterministic (seeded, one thread of work per frame, no choice from machine load). Any
difference therefore means the bag path changed a frame, its time, its per-point times or the order.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from bagwrite import FORMATS, bag_path, frame_messages, write_bag
from helpers import require_extra

require_extra("rosbags")

#: UNIX epoch of the recording: the stream's frame times are added to it (stamps ~1.7e9 s, as ROS writes)
EPOCH_NS = 1_700_000_000_000_000_000
N_FRAMES = 16


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """``(frames folder, {fmt: bag}, stamps_ns, true path length m)`` of the same 16 sweeps."""
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.flight import NetworkWorld
    from minegeo.synth.stream import StreamParams, iter_sweeps, simulate_stream

    st = simulate_stream(StreamParams(preset="vehicle", duration_s=3.0, lidar_hz=10.0, azimuth_step_deg=1.5, seed=3))
    ft = st.frame_times[10:10 + N_FRAMES]
    root = tmp_path_factory.mktemp("bag_recording")
    folder = root / "frames"
    folder.mkdir()
    frames, stamps = [], []
    for k, (t, P, tau, _ring) in enumerate(iter_sweeps(NetworkWorld(st.net), st.sensor, st.curve, ft, st.lidar_seed)):
        ns = EPOCH_NS + int(round(t * 1e9))
        xyz = P.astype(np.float32)
        tt = tau.astype(np.float32)
        write_point_cloud(folder / f"{k:06d}.ply", PointCloud(points=xyz.astype(np.float64), attributes={"time": tt}),
                          dtype="float32")
        frames.append((ns, xyz, tt))
        stamps.append(ns)
    (folder / "times.txt").write_text("".join(f"{ns // 10**9}.{ns % 10**9:09d}\n" for ns in stamps))
    bags = {fmt: write_bag(bag_path(root, fmt, f"rec_{fmt}"), fmt, frame_messages(frames)) for fmt in FORMATS}
    P = st.curve.poses(ft)
    return folder, bags, stamps, float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum())


def _slam(frames, out, *extra):
    from minegeo.cli import main

    assert main(["-q", "slam", "--frames", str(frames), "--out", str(out), "--no-planes", "--no-noise-removal",
                 *extra]) == 0
    return (out / "trajectory.tum").read_bytes(), json.loads((out / "result.json").read_text())


@pytest.fixture(scope="module")
def from_files(recording, tmp_path_factory):
    folder, _, _, _ = recording
    return _slam(folder, tmp_path_factory.mktemp("slam_files") / "out")


@pytest.mark.parametrize("fmt", FORMATS)
def test_bag_gives_the_trajectory_of_the_files(recording, from_files, fmt, tmp_path):
    _, bags, stamps, path_m = recording
    tum_files, res_files = from_files
    # a real run on the files: every frame registered, the path within 10 % of the simulated 1.5 m
    assert res_files["result"]["failed_frames"] == 0
    assert abs(res_files["result"]["path_length_m"] - path_m) < 0.1 * path_m, (res_files["result"], path_m)
    # the only PointCloud2 topic is taken by default (ros1); named with either option name (ROS 2)
    topic = {"ros1": [], "sqlite3": ["--points-topic", "/points"], "mcap": ["--lidar-topic", "/points"]}[fmt]
    tum_bag, res_bag = _slam(bags[fmt], tmp_path / "out", *topic)
    # every sweep used and deskewed from its own per-point times (the bag kept them)
    assert res_bag["result"]["frames"] == N_FRAMES and not res_bag["result"]["skipped_frames"]
    assert res_bag["result"]["deskew"]["frames_deskewed"] == res_files["result"]["deskew"]["frames_deskewed"] > 0
    assert res_bag["result"]["times_from"] == "bag header stamps"
    times = [float(line.split()[0]) for line in tum_bag.decode().splitlines() if not line.startswith("#")]
    assert times == [ns / 1e9 for ns in stamps]  # header stamps as frame times, none reordered or lost
    assert tum_bag == tum_files
    (rec,) = [i for i in res_bag["provenance"]["inputs"] if i["path"] == str(bags[fmt])]
    assert rec["topic"] == "/points"


@pytest.fixture(scope="module")
def crossing(tmp_path_factory):
    """``minegeo track`` inputs: the base of a 4-way crossing (``intersections build``), and a drive
    through it (x = -12 .. 10 m, 1.2 m steps at 2 Hz, no per-point times) as files and as a ROS 2 MCAP
    bag holding the same float32 coordinates and the stamps of ``times.txt``."""
    import sys
    from pathlib import Path

    from minegeo.cli import main
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.network import DriftNetwork, network_cloud

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "semantic"))
    from _netsim import drive

    d = tmp_path_factory.mktemp("bag_track")
    nodes = [(0, 0), (-16, 0), (16, 0), (0, 16), (0, -16)]
    edges = [(1, 0), (0, 2), (0, 3), (0, 4)]
    net = DriftNetwork(np.array(nodes, float), np.array(edges), np.full(len(edges), 4.5), np.full(len(nodes), 3.6))
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(d / "kb.npz")]) == 0
    frames, truth = drive(net, [(-12.0, 0.0), (10.0, 0.0)], step_m=1.2, seed=3)
    (d / "frames").mkdir()
    msgs = []
    for k, (t, P) in enumerate(frames):
        ns = EPOCH_NS + int(round(t * 1e9))
        xyz = P.astype(np.float32)
        write_point_cloud(d / "frames" / f"{k:06d}.ply", PointCloud(points=xyz.astype(np.float64)), dtype="float32")
        msgs.append((ns, xyz, None))
    (d / "frames" / "times.txt").write_text("".join(f"{ns // 10**9}.{ns % 10**9:09d}\n" for ns, _, _ in msgs))
    bags = {fmt: write_bag(bag_path(d, fmt, f"drive_{fmt}"), fmt, frame_messages(msgs)) for fmt in ("mcap",)}
    T = truth[0]
    start = ["--start", *(f"{v:.6f}" for v in (*T[:3, 3], np.degrees(np.arctan2(T[1, 0], T[0, 0]))))]
    return d, bags, start


def _track(frames, db, out, start):
    from minegeo.cli import main

    code = main(["-q", "track", "--frames", str(frames), "--db", str(db), "--out", str(out), *start])
    return code, (out / "trajectory.tum").read_bytes(), json.loads((out / "result.json").read_text())


def test_track_bag_gives_the_trajectory_of_the_files(crossing, tmp_path):
    d, bags, start = crossing
    code, tum_files, res_files = _track(d / "frames", d / "kb.npz", tmp_path / "files", start)
    assert code == 0 and res_files["result"]["factors"] >= 1  # a real run: the crossing recognised
    for fmt, bag in bags.items():
        code_b, tum_bag, res_bag = _track(bag, d / "kb.npz", tmp_path / fmt, start)
        assert code_b == code and tum_bag == tum_files, fmt
        assert res_bag["result"]["factors"] == res_files["result"]["factors"]
        assert res_bag["result"]["times_from"] == "bag header stamps"
