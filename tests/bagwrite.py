"""Write small ROS bags with ``rosbags`` itself (tests of ``--frames BAG``; needs the ``bag`` extra).

Formats: ``"ros1"`` (a ``.bag`` file), ``"sqlite3"`` and ``"mcap"`` (ROS 2 bag folders, rosbag2
version 9). A LiDAR frame is a ``sensor_msgs/msg/PointCloud2`` with float32 fields ``x y z`` and a
float32 ``time`` (seconds after ``header.stamp``), the layout of the Velodyne ROS driver.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FORMATS = ("ros1", "sqlite3", "mcap")


def bag_path(folder: Path, fmt: str, name: str = "rec") -> Path:
    """Where a bag of ``fmt`` is written: ``name.bag`` (ROS 1) or the folder ``name`` (ROS 2)."""
    return Path(folder) / (f"{name}.bag" if fmt == "ros1" else name)


#: a message type of no ROS distribution (a vendor's own sweep message), registered by :func:`write_bag`
CUSTOM_TYPE = "acme_lidar/msg/Sweep"
CUSTOM_MSG = "std_msgs/Header header\nuint32 n\nuint8[] data\n"


def write_bag(path, fmt: str, messages) -> Path:
    """``messages``: ``(topic, msgtype, log time ns, builder(typestore, ros1) -> message)`` in log order
    (an empty list: a bag without topics)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = fmt == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(CUSTOM_MSG, CUSTOM_TYPE))
    if ros1:
        writer, ser = Writer1(path), ts.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if fmt == "sqlite3" else StoragePlugin.MCAP
        writer, ser = Writer2(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    with writer:
        conns = {}
        for topic, msgtype, ns, build in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], ns, ser(build(ts, ros1), msgtype))
    return Path(path)


def header(ts, ros1: bool, stamp_ns: int, frame: str = "lidar"):
    T = ts.types
    kw = {"seq": 0} if ros1 else {}
    return T["std_msgs/msg/Header"](**kw, stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                                nanosec=stamp_ns % 10**9),
                                    frame_id=frame)


def pointcloud2(ts, ros1: bool, stamp_ns: int, xyz, t=None, frame: str = "lidar"):
    """A PointCloud2 of float32 ``x y z`` (and float32 ``time``, s after the stamp, when ``t`` is given)."""
    T = ts.types
    names = ["x", "y", "z"] + (["time"] if t is not None else [])
    rec = np.zeros(len(xyz), dtype=[(n, "<f4") for n in names])
    for j, c in enumerate("xyz"):
        rec[c] = xyz[:, j]
    if t is not None:
        rec["time"] = t
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * j, datatype=7, count=1) for j, n in enumerate(names)]
    step = rec.dtype.itemsize
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(ts, ros1, stamp_ns, frame), height=1, width=len(rec), fields=fields, is_bigendian=False,
        point_step=step, row_step=step * len(rec), data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True)


def frame_messages(frames, topic: str = "/points"):
    """Messages of :func:`write_bag` for LiDAR ``frames``: ``(stamp_ns, xyz (n, 3), t (n,) or None)``,
    logged 1 ms after their stamps, and in the given order (a stamp that goes back is logged 1 ns
    after the previous message, as a recorder logs a message when it arrives)."""
    out, last = [], None
    for ns, xyz, t in frames:
        log_ns = ns + 1_000_000 if last is None else max(ns + 1_000_000, last + 1)
        out.append((topic, "sensor_msgs/msg/PointCloud2", log_ns,
                    lambda ts, r1, ns=ns, xyz=xyz, t=t: pointcloud2(ts, r1, ns, xyz, t)))
        last = log_ns
    return out


def string_messages(topic: str, stamps_ns):
    """``std_msgs/msg/String`` messages (a topic of a type minegeo does not read as frames)."""
    return [(topic, "std_msgs/msg/String", ns, lambda ts, r1, ns=ns: ts.types["std_msgs/msg/String"](data=f"{ns}"))
            for ns in stamps_ns]


def custom_messages(topic: str, stamps_ns):
    """:data:`CUSTOM_TYPE` messages (a type unknown to minegeo and to every ROS distribution)."""
    return [(topic, CUSTOM_TYPE, ns, lambda ts, r1, ns=ns: ts.types[CUSTOM_TYPE](
        header=header(ts, r1, ns), n=3, data=np.arange(3, dtype=np.uint8))) for ns in stamps_ns]
