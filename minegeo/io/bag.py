"""ROS bags: LiDAR frames (``sensor_msgs/msg/PointCloud2``) and IMU samples (``sensor_msgs/msg/Imu``).

Read through the optional pure-Python package ``rosbags`` (``pip install 'minegeo[bag]'``): a ROS 1
``.bag`` file, a ROS 2 bag folder (``metadata.yaml`` with sqlite3 ``.db3`` or MCAP ``.mcap`` storage),
or a single ROS 2 ``.db3``/``.mcap`` storage file. rosbags deserialises each message; the point data
of a PointCloud2 is decoded here with NumPy from the message's bytes:

* ``fields`` (name, offset, datatype, count), ``point_step``, ``row_step``, ``height``, ``width``,
  ``is_bigendian``: one structured dtype of ``point_step`` bytes with the used fields at their
  offsets and the message's byte order; rows of ``row_step`` bytes (padding after ``width *
  point_step`` skipped). Datatypes 1..8 = int8, uint8, int16, uint16, int32, uint32, float32,
  float64 (``sensor_msgs/msg/PointField``).
* Coordinates ``x y z`` (metres, the message's ``header.frame_id``) as float64; points with a NaN or
  infinite coordinate (organised clouds mark missing returns so, ``is_dense`` false) are dropped
  and counted.
* Per-point times: the first of ``time``, ``t``, ``timestamp``, ``offset_time``; float = seconds
  after the frame time, unsigned integer = nanoseconds (:mod:`minegeo.io.times`); offsets outside
  [-0.01 s, 1 s] are an error that names the message.
* Frame time: the message's ``header.stamp`` (``sec + nanosec * 1e-9``), strictly increasing from
  message to message on a topic; the pose of a frame refers to this time (SLAM contract).
* IMU: ``header.stamp`` (s), ``angular_velocity`` (rad/s), ``linear_acceleration`` (m/s^2, specific
  force), in the message's ``header.frame_id`` axes, checked as the IMU CSV is
  (:func:`minegeo.io.imu.imu_samples`).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError, MinegeoError, OptionalDependencyError
from minegeo.io.imu import ImuSamples, imu_samples
from minegeo.io.times import TimedPoints, check_offsets, find_time_field, offsets_seconds, time_encoding

__all__ = ["BagTopic", "BagFrame", "bag_kind", "list_topics", "iter_bag_frames", "read_bag_frames",
           "bag_frame_stamps", "iter_bag_frame_records", "read_bag_imu", "bag_sha256", "decode_pointcloud2",
           "POINTCLOUD2", "IMU"]

log = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
#: PointField datatype -> NumPy type code (sensor_msgs/msg/PointField constants)
_PF_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_PF_NAMES = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32", 7: "float32", 8: "float64"}
_ROS1_MAGIC = b"#ROSBAG V2.0"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"


def _rosbags():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise OptionalDependencyError("rosbags", "bag") from None
    return AnyReader, Stores, get_typestore


def _why(exc: BaseException) -> str:
    """``Type: message`` of a rosbags error on one line (YAML errors span several), at most 300 characters."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= 300 else text[:297] + "..."


def _head(p: Path, n: int = 16) -> bytes:
    try:
        with open(p, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


def bag_kind(path) -> str | None:
    """``"ros1"`` (a ``.bag`` file), ``"ros2"`` (a folder with ``metadata.yaml``), ``"ros2-mcap"`` /
    ``"ros2-sqlite3"`` (one storage file), told from the content; None when ``path`` is no bag."""
    p = Path(path)
    if p.is_dir():
        return "ros2" if (p / "metadata.yaml").is_file() else None
    if not p.is_file():
        return None
    head = _head(p)
    if head.startswith(_ROS1_MAGIC):
        return "ros1"
    if head.startswith(_MCAP_MAGIC):
        return "ros2-mcap"
    if head.startswith(_SQLITE_MAGIC) and p.suffix.lower() == ".db3":
        return "ros2-sqlite3"
    return None


def bag_sha256(path) -> str:
    """SHA-256 of a bag: of the file, or for a ROS 2 folder of its files (relative names and
    contents, sorted by name), so that a bag folder is recorded like any input file."""
    from minegeo._provenance import sha256_file

    p = Path(path)
    if not p.is_dir():
        return sha256_file(p)
    h = hashlib.sha256()
    for f in sorted(q for q in p.rglob("*") if q.is_file()):
        h.update(str(f.relative_to(p)).encode("utf-8") + b"\0" + bytes.fromhex(sha256_file(f)))
    return h.hexdigest()


def _bag_size(path) -> int:
    p = Path(path)
    return sum(q.stat().st_size for q in p.rglob("*") if q.is_file()) if p.is_dir() else p.stat().st_size


class _Bag:
    """An open bag (context manager) whose rosbags errors become :class:`FileFormatError`."""

    def __init__(self, path):
        self.path = Path(path)
        kind = bag_kind(self.path)
        if kind is None:
            if not self.path.exists():
                raise FileNotFoundError(2, "no such file or folder", str(self.path))
            raise FileFormatError(self.path, "not a ROS bag (a ROS 1 .bag file, or a ROS 2 bag folder holding "
                                  "metadata.yaml, or a ROS 2 .mcap/.db3 file)")
        if kind == "ros1" and self.path.suffix != ".bag":
            raise FileFormatError(self.path, "a ROS 1 bag whose name does not end in .bag: rename it to *.bag")
        self.kind = kind
        AnyReader, Stores, get_typestore = _rosbags()
        try:
            self._reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        except Exception as exc:  # rosbags raises several types for damaged bags
            raise FileFormatError(self.path, f"unreadable ROS bag ({_why(exc)})") from None

    def __enter__(self):
        try:
            self._reader.open()
        except MinegeoError:
            raise
        except Exception as exc:  # rosbags raises several types for damaged bags
            raise FileFormatError(self.path, f"unreadable ROS bag ({_why(exc)})") from None
        return self

    def __exit__(self, *exc):
        try:
            self._reader.close()
        except Exception:  # closing a half-read bag must not hide the first error
            log.debug("closing %s failed", self.path, exc_info=True)
        return False

    def topics(self) -> dict:
        return self._reader.topics

    def connections(self, topic: str) -> list:
        return [c for c in self._reader.connections if c.topic == topic]

    def messages(self, connections):
        """``(index, log time ns, raw bytes, connection)`` of the connections' messages, in log-time order."""
        it = self._reader.messages(connections=connections)
        k = 0
        while True:
            try:
                conn, ts, raw = next(it)
            except StopIteration:
                return
            except MinegeoError:
                raise
            except Exception as exc:
                raise FileFormatError(self.path, f"unreadable message {k} ({_why(exc)}): damaged "
                                      "or truncated bag") from None
            yield k, ts, raw, conn
            k += 1

    def deserialize(self, raw, msgtype: str, where: str):
        try:
            return self._reader.deserialize(raw, msgtype)
        except Exception as exc:
            raise FileFormatError(self.path, f"{where}: cannot decode the {msgtype} message "
                                  f"({_why(exc)})") from None


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag.

    Attributes
    ----------
    name, msgtype : str
        Topic name and ROS 2 style message type (``sensor_msgs/msg/PointCloud2``).
    count : int
        Number of messages.
    t_start_s, t_end_s : float or None
        First and last log (record) time, s.
    rate_hz : float or None
        ``(count - 1) / (t_end_s - t_start_s)``.
    fields : tuple of (name, datatype, offset, count) or None
        PointCloud2 topics: the fields of the first message.
    time_field : str or None
        PointCloud2 topics: the per-point time field (:data:`minegeo.io.times.TIME_FIELDS`).
    frame_id : str or None
        ``header.frame_id`` of the first message (PointCloud2 and Imu topics).
    """

    name: str
    msgtype: str
    count: int
    t_start_s: float | None
    t_end_s: float | None
    rate_hz: float | None
    fields: tuple | None = None
    time_field: str | None = None
    frame_id: str | None = None


@dataclass(frozen=True)
class BagFrame:
    """One PointCloud2 message as a LiDAR frame.

    Attributes
    ----------
    index : int
        Message number on its topic (0-based, log-time order).
    stamp_ns : int
        ``header.stamp`` in nanoseconds (exact).
    time_s : float
        ``header.stamp`` in seconds: the frame time.
    points : TimedPoints
        Finite points (m, ``frame_id`` axes) and per-point offsets from ``time_s`` (or None).
    frame_id : str
        ``header.frame_id``.
    dropped_nonfinite : int
        Points dropped for a NaN or infinite coordinate.
    """

    index: int
    stamp_ns: int
    time_s: float
    points: TimedPoints
    frame_id: str
    dropped_nonfinite: int = 0


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _stamp_text(ns: int) -> str:
    """A stamp in seconds with its 9 decimals exactly as recorded (``ns / 1e9`` in float64 keeps only
    ~7 decimals at UNIX times, so two stamps 100 ns apart would print alike)."""
    sec, rem = divmod(abs(int(ns)), 1_000_000_000)
    return f"{'-' if ns < 0 else ''}{sec}.{rem:09d}"


def _field_dtype(path, where, fields, names: list[str], point_step: int, big: bool):
    """Structured dtype of the named fields at their offsets in a ``point_step``-byte record."""
    byname = {}
    for f in fields:
        byname.setdefault(f.name, f)
    formats, offsets = [], []
    for nm in names:
        f = byname[nm]
        code = _PF_TYPES.get(int(f.datatype))
        if code is None:
            raise FileFormatError(path, f"{where}: field {nm!r} has PointField datatype {f.datatype} (known: 1..8)")
        if int(f.count) != 1:
            raise FileFormatError(path, f"{where}: field {nm!r} has count {f.count}; x, y, z and the time field "
                                  "hold one value per point")
        size = int(code[1])
        if int(f.offset) < 0 or int(f.offset) + size > point_step:
            raise FileFormatError(path, f"{where}: field {nm!r} at byte {f.offset} ({size} bytes) lies outside "
                                  f"the {point_step}-byte point")
        formats.append((">" if big else "<") + code)
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def decode_pointcloud2(msg, path="", where: str = "PointCloud2"):
    """Decode a deserialised PointCloud2 message with NumPy.

    Returns
    -------
    xyz : (m, 3) float64
        Finite points (NaN/inf ones dropped).
    t_offset_s : (m,) float64 or None
        Per-point offsets from the header stamp (s), checked against [-0.01 s, 1 s].
    time_field : str or None
    encoding : str or None
        ``"seconds"`` or ``"nanoseconds"`` (how the field stored them).
    dropped : int
        Points dropped for a non-finite coordinate.

    Raises
    ------
    FileFormatError
        No x, y, z fields, a field outside the point record, an unknown datatype, a data array
        shorter than ``height`` rows of ``row_step`` bytes, a time field stored as a signed integer,
        or offsets outside the sweep range (``where`` names the message).
    """
    names = [f.name for f in msg.fields]
    for c in "xyz":
        if c not in names:
            raise FileFormatError(path, f"{where}: PointCloud2 without field {c!r} (fields: {' '.join(names) or 'none'})")
    tf = find_time_field(names)
    use = ["x", "y", "z"] + ([tf] if tf is not None else [])
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    buf = np.frombuffer(memoryview(msg.data).cast("B") if not isinstance(msg.data, np.ndarray) else msg.data,
                        dtype=np.uint8)
    if point_step <= 0:
        raise FileFormatError(path, f"{where}: point_step {point_step} (must be positive)")
    dt = _field_dtype(path, where, msg.fields, use, point_step, bool(msg.is_bigendian))
    if n == 0:
        arr = np.zeros(0, dtype=dt)
    else:
        line = width * point_step
        if row_step < line:
            raise FileFormatError(path, f"{where}: row_step {row_step} is less than width x point_step = {line}")
        need = (height - 1) * row_step + line
        if buf.size < need:
            raise FileFormatError(path, f"{where}: data holds {buf.size} bytes, {height} rows of {width} points "
                                  f"need {need} (truncated message)")
        if row_step == line:
            rows = buf[: n * point_step]
        else:  # skip the padding at the end of each row
            rows = np.ascontiguousarray(np.lib.stride_tricks.as_strided(
                buf, shape=(height, line), strides=(row_step, 1), writeable=False)).reshape(-1)
        arr = np.frombuffer(rows.tobytes() if not rows.flags.c_contiguous else rows, dtype=dt, count=n)
    xyz = np.column_stack([arr["x"].astype(np.float64), arr["y"].astype(np.float64), arr["z"].astype(np.float64)])
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int(n - np.count_nonzero(finite))
    if dropped:
        xyz = xyz[finite]
    t_off, enc = None, None
    if tf is not None:
        col = arr[tf]
        col = col.astype(col.dtype.newbyteorder("="))
        enc = time_encoding(col.dtype)
        t_off = offsets_seconds(col, tf, f"{path}: {where}")
        if dropped:
            t_off = t_off[finite]
        check_offsets(t_off, f"{path}: {where}", tf)
    return xyz, t_off, tf, enc, dropped


def _ros_time(ns) -> float | None:
    return None if ns is None else ns / 1e9


def list_topics(path) -> list[BagTopic]:
    """The topics of a bag, sorted by name (see :class:`BagTopic`).

    Reads every message's log time (not its payload) and decodes the first message of each
    PointCloud2 and Imu topic (fields, time field, frame id).

    Raises
    ------
    OptionalDependencyError
        ``rosbags`` is not installed (``pip install 'minegeo[bag]'``).
    FileFormatError
        Not a bag, or a damaged one.
    """
    out = []
    with _Bag(path) as bag:
        topics = bag.topics()
        for name in sorted(topics):
            info = topics[name]
            conns = bag.connections(name)
            msgtype = info.msgtype or (conns[0].msgtype if conns else "?")
            first = last = None
            count = 0
            fields = tf = frame_id = None
            for _k, ts, raw, conn in bag.messages(conns):
                if first is None:
                    first = ts
                    if conn.msgtype in (POINTCLOUD2, IMU):
                        msg = bag.deserialize(raw, conn.msgtype, f"topic {name} message 0")
                        frame_id = str(msg.header.frame_id)
                        if conn.msgtype == POINTCLOUD2:
                            fields = tuple((f.name, _PF_NAMES.get(int(f.datatype), str(f.datatype)), int(f.offset),
                                            int(f.count)) for f in msg.fields)
                            tf = find_time_field([f.name for f in msg.fields])
                last = ts
                count += 1
            span = None if first is None else (last - first) / 1e9
            rate = (count - 1) / span if count > 1 and span and span > 0 else None
            out.append(BagTopic(name, msgtype, count, _ros_time(first), _ros_time(last), rate, fields, tf, frame_id))
    return out


def _choose_topic(bag: _Bag, topic: str | None, msgtype: str, option: str) -> str:
    topics = bag.topics()
    if not topics:
        raise InputError(f"{bag.path}: the bag holds no topics and no messages (an empty bag)")
    listing = ", ".join(f"{n} ({topics[n].msgtype})" for n in sorted(topics))
    if topic is None:
        cands = sorted(n for n in topics if topics[n].msgtype == msgtype)
        if len(cands) == 1:
            return cands[0]
        if not cands:
            raise InputError(f"{bag.path}: no {msgtype} topic in the bag (topics: {listing})")
        raise InputError(f"{bag.path}: {len(cands)} {msgtype} topics; name one with {option} (topics: {listing})")
    if topic not in topics:
        raise InputError(f"{bag.path}: no topic {topic!r} in the bag (topics: {listing})")
    if topics[topic].msgtype != msgtype:
        raise InputError(f"{bag.path}: topic {topic!r} carries {topics[topic].msgtype}, not {msgtype}, which is "
                         f"the message type minegeo reads there (convert the topic, or name another with {option})")
    return topic


def _frame_messages(bag: _Bag, name: str):
    """``(index, stamp ns, where, message)`` of the PointCloud2 messages of topic ``name``, header
    stamps checked to increase strictly (as integer nanoseconds and as float64 seconds, the frame
    times the run writes)."""
    prev = None
    for k, _ts, raw, conn in bag.messages(bag.connections(name)):
        msg = bag.deserialize(raw, conn.msgtype, f"topic {name} message {k}")
        stamp = _stamp_ns(msg.header)
        where = f"topic {name} message {k} (stamp {_stamp_text(stamp)} s)"
        if prev is not None and not stamp > prev:
            raise FileFormatError(bag.path, f"{where}: header stamp not after the previous message's "
                                  f"{_stamp_text(prev)} s: frame times must increase strictly")
        if prev is not None and not stamp / 1e9 > prev / 1e9:
            raise FileFormatError(bag.path, f"{where}: header stamp only {stamp - prev} ns after the previous "
                                  f"message's {_stamp_text(prev)} s: the same frame time in float64 seconds (the "
                                  "trajectory's times), so not two frames of one LiDAR")
        prev = stamp
        yield k, stamp, where, msg


def _bag_frame(bag: _Bag, name: str, k: int, stamp: int, where: str, msg) -> BagFrame:
    xyz, t_off, tf, enc, dropped = decode_pointcloud2(msg, bag.path, where)
    if dropped:
        log.debug("%s: %s: dropped %d point(s) with NaN/inf coordinates", bag.path, where, dropped)
    tp = TimedPoints(xyz, t_off, None, tf, enc, f"{bag.path}!{name}#{k}")
    return BagFrame(k, stamp, stamp / 1e9, tp, str(msg.header.frame_id), dropped)


def iter_bag_frames(path, topic: str | None = None) -> Iterator[BagFrame]:
    """The PointCloud2 messages of ``topic`` as LiDAR frames, in log-time order.

    Parameters
    ----------
    path : path
        The bag (file or ROS 2 folder).
    topic : str, optional
        The PointCloud2 topic; default: the only one in the bag.

    Yields
    ------
    BagFrame

    Raises
    ------
    InputError
        An empty bag, no such topic, a topic of another type, or no / several PointCloud2 topics
        when none is named.
    FileFormatError
        A message that cannot be decoded (:func:`decode_pointcloud2`), or header stamps that do not
        increase strictly from message to message (the message is named).
    """
    with _Bag(path) as bag:
        name = _choose_topic(bag, topic, POINTCLOUD2, "--lidar-topic")
        for k, stamp, where, msg in _frame_messages(bag, name):
            yield _bag_frame(bag, name, k, stamp, where, msg)


def bag_frame_stamps(path, topic: str | None = None) -> tuple[str, list[tuple[int, int]]]:
    """The frame times of a bag topic without decoding the points (the first pass of a run).

    Returns
    -------
    (topic, [(index, stamp_ns), ...])
        The chosen PointCloud2 topic and, for each of its messages in log-time order, its number
        on the topic and its ``header.stamp`` (ns); at least one message.

    Raises
    ------
    InputError
        As :func:`iter_bag_frames` for the topic; a topic without messages.
    FileFormatError
        A damaged bag, a message whose header cannot be decoded, or header stamps that do not
        increase strictly (the message is named).
    """
    with _Bag(path) as bag:
        name = _choose_topic(bag, topic, POINTCLOUD2, "--lidar-topic")
        out = [(k, stamp) for k, stamp, _where, _msg in _frame_messages(bag, name)]
    if not out:
        raise InputError(f"{Path(path)}: topic {name} holds no messages (no frames to run on)")
    return name, out


def iter_bag_frame_records(path, topic: str) -> Iterator[tuple[int, int, BagFrame | FileFormatError]]:
    """``(index, stamp_ns, frame or error)`` of each message of the PointCloud2 ``topic``.

    As :func:`iter_bag_frames`, but a message whose points cannot be decoded (no x field, a
    truncated data array, offsets outside the sweep) is yielded as its :class:`FileFormatError`
    (the frame is skipped by the caller, as an unreadable frame file is) instead of ending the
    stream. A damaged bag or stamps out of order still raise.
    """
    with _Bag(path) as bag:
        name = _choose_topic(bag, topic, POINTCLOUD2, "--lidar-topic")
        for k, stamp, where, msg in _frame_messages(bag, name):
            try:
                rec = _bag_frame(bag, name, k, stamp, where, msg)
            except FileFormatError as exc:
                rec = exc
            yield k, stamp, rec


def read_bag_frames(path, topic: str | None = None) -> list[BagFrame]:
    """All frames of :func:`iter_bag_frames` as a list."""
    return list(iter_bag_frames(path, topic))


def read_bag_imu(path, topic: str | None = None, *, max_gap_s: float | None = None) -> ImuSamples:
    """The ``sensor_msgs/msg/Imu`` samples of ``topic`` (default: the only Imu topic).

    ``t_s`` from ``header.stamp``, ``gyro_rad_s`` from ``angular_velocity``, ``accel_m_s2`` from
    ``linear_acceleration``; ``frame`` is the first message's ``header.frame_id``. Checked by
    :func:`minegeo.io.imu.imu_samples` (finite, stamps strictly increasing, gaps up to ``max_gap_s``).

    Raises
    ------
    InputError
        As :func:`iter_bag_frames` for the topic.
    FileFormatError
        NaN values, stamps out of order, a gap too long (the message is named), no messages.
    """
    with _Bag(path) as bag:
        name = _choose_topic(bag, topic, IMU, "--imu-topic")
        t, g, a, labels = [], [], [], []
        frame_id = None
        for k, _ts, raw, conn in bag.messages(bag.connections(name)):
            msg = bag.deserialize(raw, conn.msgtype, f"topic {name} message {k}")
            if frame_id is None:
                frame_id = str(msg.header.frame_id)
            stamp = _stamp_ns(msg.header)
            t.append(stamp / 1e9)
            w, f = msg.angular_velocity, msg.linear_acceleration
            g.append((w.x, w.y, w.z))
            a.append((f.x, f.y, f.z))
            labels.append(f"topic {name} message {k} (stamp {_stamp_text(stamp)} s)")
        return imu_samples(np.asarray(t), np.asarray(g, dtype=np.float64).reshape(-1, 3),
                           np.asarray(a, dtype=np.float64).reshape(-1, 3), f"{bag.path}",
                           frame=frame_id or "imu", labels=labels, max_gap_s=max_gap_s)


def bag_summary(path) -> dict:
    """What ``minegeo info BAG`` reports: kind, topics (:class:`BagTopic` as dicts), size, SHA-256."""
    p = Path(path)
    topics = list_topics(p)
    return {"path": str(p), "kind": "bag", "bag_format": bag_kind(p),
            "topics": [t.__dict__ | {"fields": [list(f) for f in t.fields] if t.fields else None} for t in topics],
            "messages": sum(t.count for t in topics), "size_bytes": _bag_size(p), "sha256": bag_sha256(p)}
