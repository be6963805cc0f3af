"""ROS bags (minegeo.io.bag): bags written here with rosbags itself, read back exactly.

Each bag (ROS 1 ``.bag``; ROS 2 folder with sqlite3 and with MCAP storage) holds three
PointCloud2 topics that exercise the decoder (little/big endian, float32/float64 coordinates, a
padding field, rows padded beyond ``width * point_step``, NaN points with ``is_dense`` false, each
time field name and dtype) and one Imu topic. The expected values are the ones written: finite rows
of the written records as float64, offsets float64(stored) for float fields and ns / 1e9 for unsigned
integer fields, stamps ``sec + nanosec * 1e-9``.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import require_extra

require_extra("rosbags")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from minegeo.errors import FileFormatError, InputError, OptionalDependencyError  # noqa: E402
from minegeo.io.bag import bag_kind, list_topics, read_bag_frames, read_bag_imu  # noqa: E402

T0 = 1_700_000_123_456_789_000
_DT = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
FORMATS = ("ros1", "sqlite3", "mcap")


def _pc2(ts, ros1, stamp_ns, rec, height=1, row_pad=0, dense=True, frame="lidar"):
    """A PointCloud2 whose data are the bytes of the structured array ``rec`` (height x width)."""
    T = ts.types
    big = rec.dtype[0].byteorder == ">"
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=rec.dtype.fields[n][1],
                                               datatype=_DT[rec.dtype[n].str[1:]], count=1)
              for n in rec.dtype.names if not n.startswith("pad")]
    width = rec.size // height
    step = rec.dtype.itemsize
    rows = rec.reshape(height, width)
    data = b"".join(rows[r].tobytes() + b"\xee" * row_pad for r in range(height))
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, ros1, stamp_ns, frame), height=height, width=width, fields=fields, is_bigendian=big,
        point_step=step, row_step=width * step + row_pad, data=np.frombuffer(data, dtype=np.uint8), is_dense=dense)


def _header(ts, ros1, ns, frame):
    T = ts.types
    kw = {"seq": 0} if ros1 else {}
    return T["std_msgs/msg/Header"](**kw, stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def _imu_msg(ts, ros1, ns, w, a):
    T = ts.types
    V3 = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](
        header=_header(ts, ros1, ns, "imu_link"), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=V3(x=w[0], y=w[1], z=w[2]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=V3(x=a[0], y=a[1], z=a[2]),
        linear_acceleration_covariance=np.zeros(9))


def write_bag(path, fmt: str, messages):
    """``messages``: (topic, msgtype, log time ns, builder(ts, ros1) -> message), written in that order."""
    ros1 = fmt == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        writer, ser = Writer1(path), ts.serialize_ros1
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3 if fmt == "sqlite3" else StoragePlugin.MCAP)
        ser = ts.serialize_cdr
    with writer:
        conns = {}
        for topic, msgtype, ns, build in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], ns, ser(build(ts, ros1), msgtype))
    return path


def _bag_path(tmp, fmt, name="b"):
    return tmp / (f"{name}.bag" if fmt == "ros1" else name)


def _records(k: int):
    """The three topics' records for frame ``k`` (and the expected offsets)."""
    rng = np.random.default_rng(100 + k)
    n = 24
    # /a: little endian float32 xyz, a float32 intensity, 4 padding bytes, uint32 ``t`` (ns)
    a = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("pad0", "<u4"),
                           ("t", "<u4")])
    for c in "xyz":
        a[c] = rng.uniform(-30, 30, n)
    a["t"] = rng.integers(0, 100_000_000, n)
    # /b: big endian float64 xyz, float32 ``time`` (s); 2 rows with 8 padding bytes each; NaN points
    b = np.zeros(n, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("time", ">f4")])
    for c in "xyz":
        b[c] = rng.uniform(-30, 30, n)
    b["time"] = rng.uniform(-0.005, 0.1, n)
    b["x"][[3, 17]] = np.nan
    # /c: float32 xyz with ``timestamp`` (float64 s) and ``offset_time`` (uint32): timestamp wins
    c = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("timestamp", "<f8"), ("offset_time", "<u4")])
    for q in "xyz":
        c[q] = rng.uniform(-30, 30, n)
    c["offset_time"] = 999
    c["timestamp"] = rng.uniform(0.0, 0.1, n)
    return a, b, c


def _messages():
    msgs = []
    for k in range(3):
        a, b, c = _records(k)
        ns = T0 + k * 100_000_000
        msgs.append(("/a", "sensor_msgs/msg/PointCloud2", ns + 1000, lambda ts, r1, a=a, ns=ns: _pc2(ts, r1, ns, a)))
        msgs.append(("/b", "sensor_msgs/msg/PointCloud2", ns + 2000,
                     lambda ts, r1, b=b, ns=ns: _pc2(ts, r1, ns + 7, b, height=2, row_pad=8, dense=False)))
        msgs.append(("/c", "sensor_msgs/msg/PointCloud2", ns + 3000, lambda ts, r1, c=c, ns=ns: _pc2(ts, r1, ns, c)))
    for k, (w, f) in enumerate(_imu_values()):
        ns = T0 + k * 2_500_000
        msgs.append(("/imu", "sensor_msgs/msg/Imu", ns + 500, lambda ts, r1, ns=ns, w=w, f=f: _imu_msg(ts, r1, ns, w, f)))
    return sorted(msgs, key=lambda m: m[2])


def _imu_values():
    rng = np.random.default_rng(9)
    w = rng.normal(0, 0.3, (40, 3))
    f = rng.normal(0, 0.5, (40, 3)) + [0, 0, 9.81]
    return list(zip(w.tolist(), f.tolist(), strict=True))


def _xyz(rec):
    xyz = np.column_stack([rec["x"].astype(np.float64), rec["y"].astype(np.float64), rec["z"].astype(np.float64)])
    return xyz[np.isfinite(xyz).all(axis=1)]


@pytest.fixture(scope="module", params=FORMATS)
def bag(request, tmp_path_factory):
    fmt = request.param
    return fmt, write_bag(_bag_path(tmp_path_factory.mktemp(fmt), fmt), fmt, _messages())


def test_bag_kind(bag):
    fmt, path = bag
    assert bag_kind(path) == {"ros1": "ros1", "sqlite3": "ros2", "mcap": "ros2"}[fmt]


def test_list_topics(bag):
    _, path = bag
    topics = {t.name: t for t in list_topics(path)}
    assert sorted(topics) == ["/a", "/b", "/c", "/imu"]
    a = topics["/a"]
    assert a.msgtype == "sensor_msgs/msg/PointCloud2" and a.count == 3
    assert a.t_start_s == (T0 + 1000) / 1e9 and a.t_end_s == (T0 + 200_001_000) / 1e9
    assert a.rate_hz == pytest.approx(10.0, rel=1e-6)
    assert a.time_field == "t" and a.frame_id == "lidar"
    assert a.fields == (("x", "float32", 0, 1), ("y", "float32", 4, 1), ("z", "float32", 8, 1),
                        ("intensity", "float32", 12, 1), ("t", "uint32", 20, 1))
    assert topics["/b"].time_field == "time" and topics["/c"].time_field == "timestamp"
    imu = topics["/imu"]
    assert imu.msgtype == "sensor_msgs/msg/Imu" and imu.count == 40 and imu.fields is None
    assert imu.rate_hz == pytest.approx(400.0, rel=1e-6) and imu.frame_id == "imu_link"


@pytest.mark.parametrize("topic", ["/a", "/b", "/c"])
def test_frames_exactly_as_written(bag, topic):
    _, path = bag
    frames = read_bag_frames(path, topic)
    assert [f.index for f in frames] == [0, 1, 2]
    for k, fr in enumerate(frames):
        a, b, c = _records(k)
        rec = {"/a": a, "/b": b, "/c": c}[topic]
        stamp = T0 + k * 100_000_000 + (7 if topic == "/b" else 0)
        assert fr.stamp_ns == stamp and fr.time_s == stamp / 1e9 and fr.frame_id == "lidar"
        np.testing.assert_array_equal(fr.points.xyz, _xyz(rec))
        if topic == "/a":
            expect = np.array([int(v) / 1e9 for v in rec["t"]])
            assert fr.points.time_encoding == "nanoseconds"
        elif topic == "/b":
            keep = np.isfinite(rec["x"])
            expect = np.array([float(v) for v in rec["time"][keep]])
            assert fr.dropped_nonfinite == 2
        else:
            expect = np.array([float(v) for v in rec["timestamp"]])
        np.testing.assert_array_equal(fr.points.t_offset_s, expect)
        assert fr.points.time_field == {"/a": "t", "/b": "time", "/c": "timestamp"}[topic]


def test_imu_exactly_as_written(bag):
    _, path = bag
    imu = read_bag_imu(path)  # the only Imu topic
    vals = _imu_values()
    np.testing.assert_array_equal(imu.t_s, [(T0 + k * 2_500_000) / 1e9 for k in range(40)])
    np.testing.assert_array_equal(imu.gyro_rad_s, [w for w, _ in vals])
    np.testing.assert_array_equal(imu.accel_m_s2, [f for _, f in vals])
    assert imu.frame == "imu_link"


def test_topic_choice_errors(bag):
    _, path = bag
    with pytest.raises(InputError, match="3 sensor_msgs/msg/PointCloud2 topics; name one with --lidar-topic"):
        read_bag_frames(path)
    with pytest.raises(InputError, match="no topic '/nope'.*/a \\(sensor_msgs/msg/PointCloud2\\)"):
        read_bag_frames(path, "/nope")
    with pytest.raises(InputError, match="carries sensor_msgs/msg/Imu, not sensor_msgs/msg/PointCloud2"):
        read_bag_frames(path, "/imu")
    with pytest.raises(InputError, match="not sensor_msgs/msg/Imu"):
        read_bag_imu(path, "/a")


def _one_topic(tmp_path, recs, stamps, fmt="mcap"):
    msgs = [("/p", "sensor_msgs/msg/PointCloud2", T0 + k, lambda ts, r1, r=r, s=s: _pc2(ts, r1, s, r))
            for k, (r, s) in enumerate(zip(recs, stamps, strict=True))]
    return write_bag(_bag_path(tmp_path, fmt, "bad"), fmt, msgs)


def _rec(t, dtype="<f4"):
    r = np.zeros(len(t), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", dtype)])
    r["x"] = np.arange(len(t))
    r["t"] = t
    return r


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_offsets_outside_sweep_name_the_message(tmp_path, fmt):
    ok = _rec([0.0, 0.05])
    bad = _rec([0.0, 1.5])
    path = _one_topic(tmp_path, [ok, bad], [T0, T0 + 100_000_000], fmt)
    with pytest.raises(FileFormatError) as ei:
        read_bag_frames(path, "/p")
    msg = str(ei.value)
    assert "topic /p message 1" in msg and "outside [-0.01 s, 1 s]" in msg and "'t'" in msg


def test_integer_nanoseconds_outside_sweep(tmp_path):
    path = _one_topic(tmp_path, [_rec([0, 2_000_000_000], "<u4")], [T0])
    with pytest.raises(FileFormatError, match="message 0.*2 s"):
        read_bag_frames(path, "/p")


def test_stamps_must_increase(tmp_path):
    r = _rec([0.0, 0.01])
    path = _one_topic(tmp_path, [r, r, r], [T0, T0 + 100_000_000, T0 + 50_000_000])
    with pytest.raises(FileFormatError, match="message 2 .*not after the previous message"):
        read_bag_frames(path, "/p")


def test_missing_xyz_and_truncated_data(tmp_path):
    r = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("q", "<f4")])
    path = _one_topic(tmp_path, [r], [T0])
    with pytest.raises(FileFormatError, match="without field 'z'"):
        read_bag_frames(path, "/p")

    def short(ts, r1):
        m = _pc2(ts, r1, T0, _rec([0.0, 0.01, 0.02]))
        m.data = m.data[:-5]
        return m

    path = write_bag(tmp_path / "short", "sqlite3", [("/p", "sensor_msgs/msg/PointCloud2", T0, short)])
    with pytest.raises(FileFormatError, match="truncated message"):
        read_bag_frames(path, "/p")


def test_imu_stamps_out_of_order(tmp_path):
    msgs = [("/imu", "sensor_msgs/msg/Imu", T0 + k, lambda ts, r1, s=s: _imu_msg(ts, r1, s, (0, 0, 0), (0, 0, 9.8)))
            for k, s in enumerate([T0, T0 + 5_000_000, T0 + 4_000_000])]
    path = write_bag(tmp_path / "imu", "mcap", msgs)
    with pytest.raises(FileFormatError, match="message 2 .*not after the previous"):
        read_bag_imu(path)


def test_not_a_bag(tmp_path):
    d = tmp_path / "folder"
    d.mkdir()
    with pytest.raises(FileFormatError, match="not a ROS bag"):
        list_topics(d)
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9\n")
    with pytest.raises(FileFormatError, match="unreadable ROS bag"):
        list_topics(d)
    f = tmp_path / "x.bag"
    f.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 40)
    with pytest.raises(FileFormatError, match="unreadable ROS bag"):
        list_topics(f)


def test_missing_rosbags_names_the_extra(monkeypatch, tmp_path):
    import builtins

    real = builtins.__import__

    def no_rosbags(name, *a, **k):
        if name.startswith("rosbags"):
            raise ImportError("No module named 'rosbags'")
        return real(name, *a, **k)

    f = tmp_path / "x.bag"
    f.write_bytes(b"#ROSBAG V2.0\n")
    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(OptionalDependencyError, match=r"pip install 'minegeo\[bag\]'"):
        list_topics(f)


def test_cli_info_lists_topics(bag, capsys):
    from minegeo.cli import main

    _, path = bag
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "ROS bag" in out
    assert "/a  sensor_msgs/msg/PointCloud2  3 msgs  10.000 Hz" in out
    assert "/imu  sensor_msgs/msg/Imu  40 msgs  400.000 Hz" in out
    assert "time     per-point field 't'" in out and "t:uint32@20" in out


def test_ros2_storage_file_read_alone(bag):
    """A ROS 2 ``.db3`` / ``.mcap`` storage file without its folder reads as the folder does."""
    fmt, path = bag
    files = [path] if fmt == "ros1" else sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3"))
    assert len(files) == 1
    assert bag_kind(files[0]) == {"ros1": "ros1", "sqlite3": "ros2-sqlite3", "mcap": "ros2-mcap"}[fmt]
    whole, alone = read_bag_frames(path, "/b"), read_bag_frames(files[0], "/b")
    assert [f.stamp_ns for f in alone] == [f.stamp_ns for f in whole]
    for a, w in zip(alone, whole, strict=True):
        np.testing.assert_array_equal(a.points.xyz, w.points.xyz)
        np.testing.assert_array_equal(a.points.t_offset_s, w.points.t_offset_s)
