"""Write a tiny ROS bag with rosbags: LiDAR sweeps with per-point times and an IMU, then read it back.

What a surveyor learns: what minegeo reads from a robot's bag (``minegeo info BAG``, docs/io.md
"Sensor streams"): a ``sensor_msgs/msg/PointCloud2`` topic whose points carry an Ouster-style ``t``
field (uint32 nanoseconds after the message's header stamp, the frame time) and a
``sensor_msgs/msg/Imu`` topic (rad/s, m/s^2 specific force: about +9.81 on the up axis at rest).
The scene is a 4 m x 3 m x 3 m box seen from its centre, 10 sweeps at 10 Hz of 16 x 90 points, and a
200 Hz IMU at rest; no noise, so what is read back equals what was written.

Usage: ``python examples/write_tiny_bag.py OUT [--storage mcap|sqlite3]`` writes a ROS 2 bag folder
``OUT``; ``OUT`` ending in ``.bag`` writes a ROS 1 bag. Needs ``pip install 'minegeo[bag]'`` (rosbags).
"""

import argparse
import sys
from pathlib import Path

import numpy as np

try:
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore
except ImportError:  # the optional 'bag' extra: say so in one line, as minegeo's verbs do
    print("write_tiny_bag.py: error: this example needs the optional package rosbags: pip install 'minegeo[bag]'",
          file=sys.stderr)
    sys.exit(2)

T0_NS = 1_700_000_000_000_000_000  # first frame stamp (ns since the UNIX epoch)
SWEEP_NS = 100_000_000  # 10 Hz
HALF = np.array([2.0, 1.5, 1.5])  # half the box size (m)


def sweep(k: int):
    """One sweep: (n, 3) float32 points on the box walls and their uint32 ns offsets."""
    az = np.linspace(0.0, 2 * np.pi, 90, endpoint=False) + 0.01 * k
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    A, E = np.meshgrid(az, el)
    d = np.column_stack([(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(), np.sin(E).ravel()])
    s = np.min(HALF / np.maximum(np.abs(d), 1e-12), axis=1)  # ray to the nearest wall
    t_ns = (np.tile(np.arange(90), 16) * (SWEEP_NS // 90)).astype(np.uint32)  # points in azimuth order
    return (d * s[:, None]).astype(np.float32), t_ns


def messages(ts, ros1: bool):
    """(topic, msgtype, stamp ns, message) of the 10 sweeps and 200 IMU samples."""
    T = ts.types
    Time, PointField = T["builtin_interfaces/msg/Time"], T["sensor_msgs/msg/PointField"]

    def header(ns, frame):
        kw = {"seq": 0} if ros1 else {}
        return T["std_msgs/msg/Header"](**kw, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    fields = [PointField(name=n, offset=4 * j, datatype=7, count=1) for j, n in enumerate("xyz")]
    fields.append(PointField(name="t", offset=12, datatype=6, count=1))
    out = []
    for k in range(10):
        pts, t_ns = sweep(k)
        rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
        rec["x"], rec["y"], rec["z"], rec["t"] = pts[:, 0], pts[:, 1], pts[:, 2], t_ns
        ns = T0_NS + k * SWEEP_NS
        msg = T["sensor_msgs/msg/PointCloud2"](
            header=header(ns, "lidar"), height=1, width=len(pts), fields=fields, is_bigendian=False,
            point_step=16, row_step=16 * len(pts), data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True)
        out.append(("/lidar/points", "sensor_msgs/msg/PointCloud2", ns, msg))
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    for k in range(200):
        ns = T0_NS + k * 5_000_000  # 200 Hz
        msg = T["sensor_msgs/msg/Imu"](
            header=header(ns, "lidar"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9), angular_velocity=V3(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=V3(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9))
        out.append(("/imu/data", "sensor_msgs/msg/Imu", ns, msg))
    return sorted(out, key=lambda m: m[2])


def write_bag(path: Path, storage: str = "mcap") -> Path:
    """Write the tiny bag at ``path`` (ROS 1 when it ends in ``.bag``, else a ROS 2 folder)."""
    ros1 = path.suffix == ".bag"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        writer = Writer1(path)
        ser = ts.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        ser = ts.serialize_cdr
    with writer:
        conns = {}
        for topic, msgtype, ns, msg in messages(ts, ros1):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], ns, ser(msg, msgtype))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="bag to write (a folder for ROS 2; *.bag for ROS 1); must not exist")
    ap.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="ROS 2 storage (default mcap)")
    args = ap.parse_args()
    write_bag(args.out, args.storage)
    from minegeo.io.bag import read_bag_frames, read_bag_imu

    frames, imu = read_bag_frames(args.out), read_bag_imu(args.out)
    pts, t_ns = sweep(0)
    same = np.array_equal(frames[0].points.xyz, pts.astype(np.float64)) and np.array_equal(
        frames[0].points.t_offset_s, t_ns / 1e9)
    print(f"wrote {args.out}: {len(frames)} PointCloud2 frames of {len(frames[0].points)} points "
          f"(per-point field {frames[0].points.time_field!r}, {frames[0].points.time_encoding}), "
          f"{len(imu)} Imu samples at {imu.rate_hz:.0f} Hz")
    print(f"read back: frame 0 at {frames[0].time_s:.3f} s, offsets {frames[0].points.t_offset_s.min():.4f}.."
          f"{frames[0].points.t_offset_s.max():.4f} s, identical to what was written: {same}")


if __name__ == "__main__":
    main()
