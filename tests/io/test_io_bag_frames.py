"""Frames from a ROS bag (minegeo.io.frames.list_frames / iter_frames on a bag, io.frames.write_frames_bag).

Expected values are the ones written: the frames folder's float64 coordinates, per-point times and
``times.txt`` times (9 decimals, so whole nanoseconds), and for the hand-made bags the stamps and
float32 records given to ``rosbags`` (tests/bagwrite.py).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from bagwrite import FORMATS, bag_path, frame_messages, write_bag
from helpers import require_extra

require_extra("rosbags")

from minegeo.errors import FileFormatError  # noqa: E402
from minegeo.io import PointCloud, write_point_cloud  # noqa: E402
from minegeo.io.frames import iter_frames, list_frames, write_frames_bag  # noqa: E402

T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """3 frames with a float64 ``time`` field (two of them) and times with 9 decimals."""
    d = tmp_path_factory.mktemp("bag_frames") / "frames"
    d.mkdir()
    rng = np.random.default_rng(5)
    for k in range(3):
        attrs = {"time": rng.uniform(0.0, 0.1, 50)} if k != 1 else {}
        write_point_cloud(d / f"{k:06d}.ply", PointCloud(points=rng.normal(0, 10, (50, 3)), attributes=attrs))
    (d / "times.txt").write_text("1700000000.100000001\n1700000000.200000000\n1700000000.299999999\n")
    return d


@pytest.mark.parametrize("fmt", FORMATS)
def test_write_frames_bag_reads_back_as_the_folder(folder, fmt, tmp_path):
    path = tmp_path / ("rec.bag" if fmt == "ros1" else "rec")
    assert write_frames_bag(folder, path, storage=None if fmt == "ros1" else fmt) == 3
    files, bag = list_frames(folder), list_frames(path)
    assert bag.kind == "bag" and bag.topic == "/points" and bag.times_source == "bag header stamps"
    assert [f.time_s for f in bag] == [f.time_s for f in files]
    assert [f.name for f in bag] == ["/points#0", "/points#1", "/points#2"]
    for (_, xa, ta, ea), (_, xb, tb, eb) in zip(iter_frames(files, True), iter_frames(bag, True), strict=True):
        assert ea is None and eb is None
        np.testing.assert_array_equal(xb, xa)
        assert (ta is None) == (tb is None)
        if ta is not None:
            np.testing.assert_array_equal(tb, ta)
    (rec,) = bag.inputs()
    assert rec["path"] == str(path) and rec["topic"] == "/points" and len(rec["sha256"]) == 64


def _frames(n, bad=()):
    rng = np.random.default_rng(1)
    return [(T0 + k * 100_000_000, rng.normal(0, 5, (40, 3)).astype(np.float32),
             np.full(40, 2.0 if k in bad else 0.05, np.float32)) for k in range(n)]


@pytest.mark.parametrize("fmt", FORMATS)
def test_undecodable_message_is_skipped_not_fatal(fmt, tmp_path):
    """A message whose per-point times lie outside the sweep (2 s) is one unreadable frame: reported
    with its error, the frames around it read."""
    path = write_bag(bag_path(tmp_path, fmt), fmt, frame_messages(_frames(4, bad={2})))
    got = list(iter_frames(list_frames(path), with_times=True))
    assert [f.message for f, *_ in got] == [0, 1, 2, 3]
    assert [e is None for *_, e in got] == [True, True, False, True]
    assert isinstance(got[2][3], FileFormatError) and "topic /points message 2" in str(got[2][3])
    np.testing.assert_array_equal(got[3][1], _frames(4)[3][1].astype(np.float64))
    np.testing.assert_array_equal(got[3][2], np.full(40, np.float32(0.05), np.float64))


def test_bag_changed_between_listing_and_reading(tmp_path):
    a = write_bag(tmp_path / "a.bag", "ros1", frame_messages(_frames(3)))
    b = write_bag(tmp_path / "b.bag", "ros1", frame_messages([(ns + 1, x, t) for ns, x, t in _frames(3)]))
    frames = list_frames(a)
    shutil.copyfile(b, a)
    with pytest.raises(FileFormatError, match="message 0: not the message listed before the run"):
        list(iter_frames(frames))


def test_bag_frames_are_decoded_one_at_a_time(tmp_path, monkeypatch):
    """Streaming: taking one frame from iter_frames decodes one message's points, not the bag's."""
    import minegeo.io.bag as bagmod

    path = write_bag(tmp_path / "s.bag", "ros1", frame_messages(_frames(5)))
    frames = list_frames(path)
    calls = []
    real = bagmod.decode_pointcloud2
    monkeypatch.setattr(bagmod, "decode_pointcloud2", lambda *a, **k: calls.append(1) or real(*a, **k))
    it = iter_frames(frames, with_times=True)
    next(it)
    assert len(calls) == 1
    next(it)
    assert len(calls) == 2
    it.close()
