"""``minegeo info`` on sensor streams (IMU CSV, ROS bags): every user mistake is one line, exit 2,
nothing written, inputs unchanged (the contract of tests/badinput/_contract.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from _contract import assert_user_error, truncated_copy
from helpers import require_extra

HEADER = "t,gx,gy,gz,ax,ay,az"
ROWS = [f"{0.005 * k!r},0.01,-0.02,0.03,0.1,-0.2,9.81" for k in range(12)]


def _csv(tmp: Path, lines, name="imu.csv") -> Path:
    p = tmp / name
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


#: case -> (FILE maker, extra options, text the error line must hold)
IMU_CASES = {
    "unsorted": (lambda t: _csv(t, [HEADER, *ROWS[:6], ROWS[7], ROWS[6], *ROWS[8:]]), [], "line 9"),
    "duplicate_time": (lambda t: _csv(t, [HEADER, *ROWS[:6], ROWS[5], *ROWS[7:]]), [], "line 8"),
    "nan": (lambda t: _csv(t, [HEADER, *ROWS[:3], ROWS[3].replace("0.03", "nan"), *ROWS[4:]]), [], "line 5: gz"),
    "wrong_header": (lambda t: _csv(t, ["t,gx,gy,gz,ax,ay", *ROWS]), [], "expected 't,gx,gy,gz,ax,ay,az'"),
    "degrees_header": (lambda t: _csv(t, ["t,gx_deg,gy_deg,gz_deg,ax,ay,az", *ROWS]), [], "IMU CSV header"),
    "short_row": (lambda t: _csv(t, [HEADER, *ROWS[:4], ROWS[4].rsplit(",", 1)[0], *ROWS[5:]]), [], "line 6"),
    "header_only": (lambda t: _csv(t, [HEADER]), [], "no samples"),
    "points_as_imu": (lambda t: _csv(t, ["x,y,z", "0,0,0", "1,1,1"], "pts.csv"), ["--kind", "imu"], "IMU CSV header"),
    "imu_stream": (lambda t: Path("/dev/zero"), ["--kind", "imu"], ""),
}


@pytest.mark.parametrize("case", sorted(IMU_CASES))
def test_bad_imu_csv(case, tmp_path, capsys):
    make, extra, expect = IMU_CASES[case]
    f = make(tmp_path)
    out = tmp_path / "out" / "info.json"
    assert_user_error("info", [f, *extra, "--json", out], capsys, inputs=[f], outputs=[out], expect=expect or None)


def _tiny_bag(tmp: Path, name: str) -> Path:
    """A ROS 1 bag with one PointCloud2 message, written with rosbags."""
    require_extra("rosbags")
    import numpy as np
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
    rec["x"] = [1, 2, 3]
    f = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * j, datatype=7 if n != "t" else 6, count=1)
         for j, n in enumerate("xyzt")]
    hdr = T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="l")
    msg = T["sensor_msgs/msg/PointCloud2"](header=hdr, height=1, width=3, fields=f, is_bigendian=False, point_step=16,
                                           row_step=48, data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True)
    p = tmp / name
    with Writer(p) as w:
        c = w.add_connection("/p", "sensor_msgs/msg/PointCloud2", typestore=ts)
        w.write(c, 5_000_000_000, ts.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    return p


def _bad_metadata(tmp: Path) -> Path:
    require_extra("rosbags")
    d = tmp / "bag2"
    d.mkdir()
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9\n", encoding="utf-8")
    return d


def _renamed_ros1(tmp: Path) -> Path:
    src = _tiny_bag(tmp, "src.bag")
    dst = tmp / "drive.dat"
    dst.write_bytes(src.read_bytes())
    src.unlink()
    return dst


BAG_CASES = {
    "truncated_bag": (lambda t: truncated_copy(_tiny_bag(t, "full.bag"), t / "half.bag"), [], "unreadable ROS bag"),
    "bad_metadata_yaml": (_bad_metadata, [], "unreadable ROS bag"),
    "ros1_without_bag_suffix": (_renamed_ros1, [], "rename it to *.bag"),
    "kind_bag_on_a_text_file": (lambda t: _csv(t, [HEADER, *ROWS]), ["--kind", "bag"], "not a ROS bag"),
}


@pytest.mark.parametrize("case", sorted(BAG_CASES))
def test_bad_bag(case, tmp_path, capsys):
    make, extra, expect = BAG_CASES[case]
    src = tmp_path / "in"
    src.mkdir()
    f = make(src)
    out = tmp_path / "out" / "info.json"
    assert_user_error("info", [f, *extra, "--json", out], capsys, inputs=[f, src], outputs=[out], expect=expect)
