"""``minegeo slam|track --frames BAG``: every mistake in a ROS bag input is one line, exit 2, nothing
written, the bag unchanged (issue 29: "a bag without the named topic or with an unknown message
type: one clear error line (exit 2)").

The bags are written here with ``rosbags`` (tests/bagwrite.py) in each format (ROS 1 ``.bag``, ROS 2
sqlite3 and MCAP folders): 4 frames of a few hundred points each; every case fails before the
odometry (the bag's stamps and topics are checked before any work).
"""

from __future__ import annotations

import numpy as np
import pytest
from _contract import a_folder, assert_user_error
from bagwrite import FORMATS, bag_path, custom_messages, frame_messages, string_messages, write_bag
from helpers import require_extra

require_extra("rosbags")

T0 = 1_700_000_000_000_000_000
DT = 100_000_000


def _frames(stamps, fields_ok=True):
    rng = np.random.default_rng(29)
    out = []
    for ns in stamps:
        xyz = (rng.uniform(-1, 1, (300, 3)) * [6.0, 4.0, 3.0]).astype(np.float32)
        out.append((ns, xyz, np.linspace(0.0, 0.09, 300, dtype=np.float32)))
    return out


def _msgs(case: str):
    ok = [T0 + k * DT for k in range(4)]
    chatter = string_messages("/chatter", [T0 + 5])
    return {
        "missing_topic": frame_messages(_frames(ok)) + chatter,
        "unknown_type": frame_messages(_frames(ok)) + custom_messages("/acme/sweep", ok),
        "other_type": frame_messages(_frames(ok)) + chatter,
        "no_pointcloud2": chatter + custom_messages("/acme/sweep", ok),
        "two_pointcloud2": frame_messages(_frames(ok)) + frame_messages(_frames(ok), "/points2"),
        "empty_bag": [],
        "stamps_backwards": frame_messages(_frames([ok[0], ok[1], ok[1] - DT // 2, ok[3]])),
        "stamps_repeated": frame_messages(_frames([ok[0], ok[1], ok[1], ok[3]])),
        # 1 ns apart: in order as integers, one float64 second value at UNIX times (the trajectory's times)
        "stamps_1ns_apart": frame_messages(_frames([ok[0], ok[1], ok[1] + 1, ok[3]])),
    }[case]


#: case -> (extra arguments, text the error line must hold)
CASES = {
    "missing_topic": (["--lidar-topic", "/velodyne_points"], "no topic '/velodyne_points' in the bag (topics: "
                      "/chatter (std_msgs/msg/String), /points (sensor_msgs/msg/PointCloud2))"),
    "unknown_type": (["--lidar-topic", "/acme/sweep"], "topic '/acme/sweep' carries acme_lidar/msg/Sweep, not "
                     "sensor_msgs/msg/PointCloud2"),
    "other_type": (["--lidar-topic", "/chatter"], "carries std_msgs/msg/String, not sensor_msgs/msg/PointCloud2"),
    "no_pointcloud2": ([], "no sensor_msgs/msg/PointCloud2 topic in the bag (topics: /acme/sweep (acme_lidar/msg/Sweep), "
                       "/chatter (std_msgs/msg/String))"),
    "two_pointcloud2": ([], "2 sensor_msgs/msg/PointCloud2 topics; name one with --lidar-topic (topics: /points "),
    "empty_bag": ([], "the bag holds no topics and no messages (an empty bag)"),
    "stamps_backwards": ([], "topic /points message 2 (stamp 1700000000.050000000 s): header stamp not after the "
                         "previous message's 1700000000.100000000 s"),
    "stamps_1ns_apart": ([], "message 2 (stamp 1700000000.100000001 s): header stamp only 1 ns after the previous "
                         "message's 1700000000.100000000 s"),
    "stamps_repeated": ([], "message 2 (stamp 1700000000.100000000 s): header stamp not after"),
}


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_bags")
    return {(case, fmt): write_bag(bag_path(root, fmt, f"{case}_{fmt}"), fmt, _msgs(case))
            for case in CASES for fmt in FORMATS}


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_bag_slam(case, fmt, bags, tmp_path, capsys):
    bag = bags[case, fmt]
    extra, expect = CASES[case]
    out = tmp_path / "out"
    line = assert_user_error("slam", ["--frames", bag, "--out", out, *extra], capsys, inputs=[bag], outputs=[out],
                             expect=expect)
    assert str(bag) in line  # the bag is named


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("good_bag") / "rec.bag", "ros1",
                     frame_messages(_frames([T0 + k * DT for k in range(4)])))


OPTION_CASES = {
    "times_with_bag": (lambda t, bag: ["--frames", bag, "--times", _times(t)], "--times"),
    "pattern_with_bag": (lambda t, bag: ["--frames", bag, "--pattern", "*.ply"], "--pattern *.ply applies to a folder"),
    "topic_with_folder": (lambda t, bag: ["--frames", _ply_folder(t), "--lidar-topic", "/points"],
                          "--lidar-topic /points applies to a ROS bag"),
    "not_a_bag": (lambda t, bag: ["--frames", _fake_bag(t)], "not a ROS bag"),
    "missing": (lambda t, bag: ["--frames", t / "nope.bag"], "nope.bag: no such folder or file"),
    "a_text_file": (lambda t, bag: ["--frames", _text(t)], "neither a folder of frames nor a ROS bag"),
    "truncated_bag": (lambda t, bag: ["--frames", _truncated(t, bag)], "unreadable ROS bag"),
}


def _times(t):
    p = t / "times.txt"
    p.write_text("0\n0.1\n0.2\n0.3\n")
    return p


def _ply_folder(t):
    from minegeo.io import PointCloud, write_point_cloud

    d = a_folder(t, "frames")
    for k, (_, xyz, _) in enumerate(_frames([T0 + k * DT for k in range(4)])):
        write_point_cloud(d / f"{k}.ply", PointCloud(points=xyz.astype(np.float64)))
    return d


def _text(t):
    p = t / "notes.txt"
    p.write_text("frames are elsewhere\n")
    return p


def _fake_bag(t):
    p = t / "rec.bag"
    p.write_bytes(b"ply\nformat ascii 1.0\n")
    return p


def _truncated(t, bag):
    p = t / "cut.bag"
    p.write_bytes(bag.read_bytes()[:200])
    return p


@pytest.fixture(scope="module")
def kb(tmp_path_factory):
    """An intersection base (``minegeo intersections build``) of a small crossing, for ``track``."""
    from minegeo.cli import main
    from minegeo.io import PointCloud, write_point_cloud
    from minegeo.synth.network import DriftNetwork, network_cloud

    d = tmp_path_factory.mktemp("bag_kb")
    nodes = [(0, 0), (-20, 0), (20, 0), (0, 20), (0, -20)]
    net = DriftNetwork(np.array(nodes, float), np.array([(1, 0), (0, 2), (0, 3), (0, 4)]), np.full(4, 4.5),
                       np.full(len(nodes), 3.6))
    write_point_cloud(d / "map.ply", PointCloud(points=network_cloud(net, seed=1).points))
    assert main(["-q", "intersections", "build", "--map", str(d / "map.ply"), "--out", str(d / "kb.npz")]) == 0
    return d / "kb.npz"


@pytest.mark.parametrize("verb", ["slam", "track"])
@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_bad_bag_option(case, verb, good_bag, kb, tmp_path, capsys):
    make, expect = OPTION_CASES[case]
    argv = [str(a) for a in make(tmp_path, good_bag)]
    out = tmp_path / "out"
    extra = ["--db", str(kb)] if verb == "track" else []
    ins = [good_bag, kb] + [a for a in argv if a.startswith(str(tmp_path))]
    assert_user_error(verb, [*argv, *extra, "--out", out], capsys, inputs=ins, outputs=[out], expect=expect)


@pytest.mark.parametrize("case", ["missing_topic", "unknown_type", "stamps_backwards", "empty_bag"])
def test_bad_bag_track(case, bags, kb, tmp_path, capsys):
    bag = bags[case, "mcap"]
    extra, expect = CASES[case]
    out = tmp_path / "out"
    assert_user_error("track", ["--frames", bag, "--db", kb, "--out", out, *extra], capsys, inputs=[bag, kb],
                      outputs=[out], expect=expect)
