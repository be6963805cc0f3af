"""LiDAR frames (``minegeo slam --frames DIR|BAG``): a folder of files or a ROS bag, as fixed by the SLAM contract.

* One point cloud per frame, any format :func:`minegeo.io.read_point_cloud` reads (PLY, PCD,
  LAS/LAZ, XYZ/CSV, PTS, 3DTK) plus KITTI Velodyne ``.bin`` (float32 x, y, z, reflectance), in the
  sensor frame, metres.
* Frame order: file names sorted lexicographically (zero-padded numbers, as loggers write them).
* Times: ``DIR/times.txt`` when present (one time in seconds per frame in that order, the KITTI
  odometry convention); otherwise a number in every file name is its time in seconds; otherwise an
  error that says so. A times file elsewhere can be named (``--times FILE``), and the frames chosen
  by a file-name pattern (``--pattern "*.pcd"``) when the folder holds other files (e.g. pose text
  files).
* Every time passes the trajectory readers' one check (:func:`minegeo.io.trajectory.time_problem`):
  finite, within +-1e20 s (so differences are finite and the 17-digit ``trajectory.tum`` written
  from them reads back) and strictly increasing in name order; otherwise an input error naming the
  first offending frame (and the times file's line). A times file is read by
  :func:`minegeo.io.trajectory.read_times`: a folder, FIFO or device is refused without being
  opened, saying what it is.
* Per-point times (:func:`read_frame` with ``with_times=True``): a PLY/PCD/text field ``time``, ``t``,
  ``timestamp`` or ``offset_time`` (the first found) holds each point's offset from the frame time
  (float: seconds; unsigned integer: nanoseconds), within [-0.01 s, 1 s]; LAS/LAZ ``gps_time`` is
  absolute, made an offset with the frame time (:mod:`minegeo.io.times`).
* Times read from names that are consecutive integers from 0 or 1 (``000000.pcd``, ``000001.pcd``,
  ...) are most likely frame numbers, not seconds: :func:`list_frames` logs a warning and says so in
  :attr:`FrameList.times_source` (the run still takes them as seconds, as the contract says).
* A ROS bag (a ROS 1 ``.bag`` file, a ROS 2 bag folder with ``metadata.yaml``, or one ROS 2
  ``.mcap``/``.db3`` file; :func:`minegeo.io.bag.bag_kind` tells it from the content) in place of
  the folder: the frames are the ``sensor_msgs/msg/PointCloud2`` messages of one topic (named, or
  the only PointCloud2 topic of the bag), in log-time order; the frame time is the message's
  ``header.stamp`` (``sec + nanosec * 1e-9``), strictly increasing; per-point times from the same
  fields as in files (:mod:`minegeo.io.bag`). The bag is read twice, one message at a time: once
  for the stamps (checked before any work), once for the points (:func:`iter_frames`), so a bag
  never needs to fit in memory. ``--times`` and ``--pattern`` do not apply to a bag.
"""

from __future__ import annotations

import fnmatch
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError, OptionalDependencyError
from minegeo.io.limits import read_file_bytes
from minegeo.io.pointcloud import _SUFFIX
from minegeo.io.trajectory import read_times, time_problem

__all__ = ["FrameFile", "FrameList", "list_frames", "iter_frames", "read_frame", "read_kitti_bin", "times_source",
           "write_frames_bag"]

log = logging.getLogger(__name__)

#: Largest frame file read (a 128-beam scan is ~ 4 MB).
MAX_FRAME_BYTES = 1 << 30
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class FrameFile:
    """One frame: its file (or bag) and its time (s).

    Attributes
    ----------
    path : Path
        The frame file; for a bag frame, the bag.
    time_s : float
        The frame time (s).
    message : int or None
        Bag frames: the message's number on its topic (0-based, log-time order); None for files.
    label : str or None
        Bag frames: ``"TOPIC#K"``, how the frame is named in messages and ``result.json``.
    stamp_ns : int or None
        Bag frames: ``header.stamp`` in nanoseconds, exact (``time_s`` is it in float64 seconds).
    """

    path: Path
    time_s: float
    message: int | None = None
    label: str | None = None
    stamp_ns: int | None = None

    @property
    def name(self) -> str:
        """The frame's name in messages: the file name, or ``TOPIC#K`` for a bag message."""
        return self.label if self.label is not None else self.path.name


class FrameList(list):
    """The frames of a run (a list of :class:`FrameFile` in time order) and where they come from.

    Attributes
    ----------
    source : Path
        The ``--frames`` folder or bag.
    kind : str
        ``"folder"`` or ``"bag"``.
    times_source : str
        ``"file"`` (times.txt or --times), ``"names"`` (numbers in the file names, possibly frame
        numbers: a warning was logged) or ``"bag header stamps"``.
    topic : str or None
        The bag's PointCloud2 topic.
    """

    def __init__(self, frames, source, kind: str, times_source: str, topic: str | None = None):
        super().__init__(frames)
        self.source = Path(source)
        self.kind = kind
        self.times_source = times_source
        self.topic = topic

    def inputs(self) -> list[dict]:
        """Provenance records ``{"path", "sha256"}``: each frame file, or the bag once (a ROS 2 folder
        hashed over its files, :func:`minegeo.io.bag.bag_sha256`)."""
        from minegeo._provenance import sha256_file

        if self.kind == "bag":
            from minegeo.io.bag import bag_sha256

            return [{"path": str(self.source), "sha256": bag_sha256(self.source), "topic": self.topic}]
        return [{"path": str(f.path), "sha256": sha256_file(f.path)} for f in self]


def read_kitti_bin(path) -> np.ndarray:
    """Points (n, 3) float64 of a KITTI Velodyne ``.bin`` (float32 x, y, z, reflectance records).

    Raises
    ------
    FileFormatError
        The size is not a multiple of 16 bytes (truncated or not a KITTI scan), or a value is not finite.
    """
    data = read_file_bytes(path, max_bytes=MAX_FRAME_BYTES, what="KITTI .bin frame")
    if len(data) % 16:
        raise FileFormatError(path, f"{len(data)} bytes is not a whole number of 16-byte KITTI records "
                              "(float32 x, y, z, reflectance): truncated, or not a KITTI scan")
    rec = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    pts = rec[:, :3].astype(np.float64)
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise FileFormatError(path, f"record {int(np.flatnonzero(bad)[0])} holds a NaN or infinite coordinate")
    return pts


def read_frame(path, *, with_times: bool = False, time_s: float | None = None):
    """Points (n, 3) float64 of one frame file (sensor frame, m), and on request their times.

    Parameters
    ----------
    path : path
        The frame file.
    with_times : bool
        ``False`` (default): the (n, 3) array. ``True``: a :class:`~minegeo.io.times.TimedPoints`
        whose ``t_offset_s`` holds each point's seconds after the frame time (PLY/PCD/text time
        fields, :mod:`minegeo.io.times`), None when the file has no time field (KITTI ``.bin`` never
        has one).
    time_s : float, optional
        The frame time (s). Needed only for LAS/LAZ frames, whose ``gps_time`` is absolute: their
        offsets are ``gps_time - time_s`` (same clock as the frame times).

    Raises
    ------
    FileFormatError
        As the readers; with ``with_times``, per-point offsets outside [-0.01 s, 1 s] or NaN, or a
        time field stored as a signed integer (the frame file is named).
    """
    if Path(path).suffix.lower() == ".bin":
        pts = read_kitti_bin(path)
        if not with_times:
            return pts
        from minegeo.io.times import TimedPoints

        return TimedPoints(pts, None, source=str(path))
    from minegeo.io.pointcloud import read_point_cloud, read_points

    if not with_times:
        cloud = read_point_cloud(path)
        return cloud.points + cloud.origin
    tp = read_points(path, with_times=True)
    if tp.t_abs_s is not None and time_s is not None:
        from minegeo.io.times import offsets_from_absolute

        tp = offsets_from_absolute(tp, time_s)
    return tp


def _frame_files(folder: Path, pattern: str | None = None) -> list[Path]:
    if not folder.is_dir():
        if not folder.exists():
            raise InputError(f"--frames {folder}: no such folder or file")
        raise InputError(f"--frames {folder}: neither a folder of frames nor a ROS bag (a ROS 1 .bag file, a ROS 2 "
                         "bag folder with metadata.yaml, or a .mcap/.db3 file)")
    names = sorted(p for p in folder.iterdir() if p.is_file() and (p.suffix.lower() in _SUFFIX or p.suffix.lower() == ".bin")
                   and p.name != "times.txt" and p.suffix.lower() != ".zip"
                   and (pattern is None or fnmatch.fnmatch(p.name, pattern)))
    if not names:
        what = f" matching {pattern!r}" if pattern else ""
        raise InputError(f"--frames {folder}: no point-cloud frames{what} (.ply .pcd .las .laz .xyz .csv .pts .3d .bin) "
                         "in it")
    return names


def _times_from_file(path: Path, paths: list[Path]) -> np.ndarray:
    return read_times(path, len(paths), noun="frame", labels=[f"frame {p.name}" for p in paths],
                      hint=", in the frames' name order (choose the frames with --pattern if the folder holds "
                      "other files)")


def _times_from_names(paths: list[Path]) -> np.ndarray:
    out = []
    for p in paths:
        m = _NUMBER.findall(p.stem)
        if not m:
            raise InputError(f"frame {p.name} has no number in its name and there is no times.txt: give the times "
                             "in times.txt (one per frame, seconds) or name the frames by their time")
        out.append(float(m[-1]))
    return np.asarray(out)


def times_source(folder, times_file=None) -> str:
    """Where :func:`list_frames` takes the times from: ``"file"``, ``"names"`` or ``"bag header stamps"``."""
    from minegeo.io.bag import bag_kind

    if bag_kind(folder) is not None:
        return "bag header stamps"
    return "file" if times_file is not None or (Path(folder) / "times.txt").is_file() else "names"


def _looks_like_frame_numbers(times: np.ndarray) -> bool:
    return times.size >= 3 and times[0] in (0.0, 1.0) and bool(np.all(np.diff(times) == 1.0))


def _bag_frames(bag, times_file, pattern, topic: str | None) -> FrameList:
    from minegeo.io.bag import bag_frame_stamps

    for opt, v in (("--times", times_file), ("--pattern", pattern)):
        if v is not None:
            raise InputError(f"{opt} {v} applies to a folder of frame files; the frames of the bag {bag} are its "
                             "PointCloud2 messages, timed by their header stamps: drop " + opt)
    name, stamps = bag_frame_stamps(bag, topic)
    frames = [FrameFile(bag, ns / 1e9, k, f"{name}#{k}", ns) for k, ns in stamps]
    bad = time_problem([f.time_s for f in frames], noun="frame")
    if bad is not None:
        raise FileFormatError(bag, f"topic {name} message {frames[bad[0]].message}: {bad[1]}")
    return FrameList(frames, bag, "bag", "bag header stamps", name)


def list_frames(folder, times_file=None, pattern: str | None = None, topic: str | None = None) -> FrameList:
    """The frames of ``folder`` (or of a bag) in time order with their times (see the module docstring).

    Parameters
    ----------
    folder : path
        The frames folder, or a ROS bag (:func:`minegeo.io.bag.bag_kind`).
    times_file : path, optional
        One time (s) per frame in name order; default ``folder/times.txt`` when present, else the
        numbers in the file names. Not for a bag.
    pattern : str, optional
        Shell pattern on the file names (``"*.pcd"``); default every point-cloud file. Not for a bag.
    topic : str, optional
        The bag's PointCloud2 topic (``--lidar-topic``); default the only one. Only for a bag.

    Returns
    -------
    FrameList
        At least one frame; times finite, within +-1e20 s and strictly increasing (the check of
        :func:`minegeo.io.trajectory.time_problem`), so a trajectory written from them reads back.

    Raises
    ------
    InputError
        Not a folder, no frames, no number in a frame name, or times from the names that fail the check
        (the first offending frame is named); a bag with ``times_file``/``pattern``, a folder with
        ``topic``; an empty bag, a topic missing or of another type than PointCloud2, no or several
        PointCloud2 topics when none is named, a topic without messages.
    FileFormatError
        A times file that is missing, not a regular file (a folder, FIFO or device, named as such and
        never opened), not one decimal number per line, holding another count of times than of
        frames, or failing the check (its line and frame are named); a damaged bag, or header
        stamps that do not increase strictly (the message is named).
    """
    from minegeo.io.bag import bag_kind

    folder = Path(folder)
    if bag_kind(folder) is not None or (folder.is_file() and folder.suffix.lower() in (".bag", ".mcap", ".db3")):
        return _bag_frames(folder, times_file, pattern, topic)
    if topic is not None:
        raise InputError(f"--lidar-topic {topic} applies to a ROS bag; --frames {folder} is not one (a ROS 1 .bag "
                         "file, a ROS 2 bag folder with metadata.yaml, or a .mcap/.db3 file)")
    paths = _frame_files(folder, pattern)
    if times_file is not None:
        times = _times_from_file(Path(times_file), paths)
    elif (folder / "times.txt").is_file():
        times = _times_from_file(folder / "times.txt", paths)
    else:
        times = _times_from_names(paths)
        bad = time_problem(times, noun="frame")
        if bad is not None:
            raise InputError(f"frame {paths[bad[0]].name}: {bad[1]} (times taken from the file names)")
        if _looks_like_frame_numbers(times):
            log.warning("the frame names of %s are consecutive numbers from %g: they are taken as times in seconds; "
                        "if they are frame numbers, give the times with --times FILE or DIR/times.txt", folder, times[0])
    return FrameList([FrameFile(p, float(t)) for p, t in zip(paths, times, strict=True)], folder, "folder",
                     times_source(folder, times_file))


def iter_frames(frames: FrameList, with_times: bool = False):
    """Read the frames of :func:`list_frames` one at a time, in order.

    Yields
    ------
    (frame, xyz, t_offset_s, error)
        ``frame`` the :class:`FrameFile`; ``xyz`` (n, 3) float64 in the sensor frame (m);
        ``t_offset_s`` (n,) float64 seconds after the frame time, or None (``with_times`` false, or
        no time field); ``error`` None, or the :class:`~minegeo.errors.MinegeoError`/``OSError`` of a
        frame that cannot be read (``xyz`` then None): the caller skips it, as the contract says.

    Raises
    ------
    FileFormatError
        A bag that is damaged, or whose messages no longer match the listing (stamps out of order,
        or the bag changed since :func:`list_frames`).
    """
    from minegeo.errors import MinegeoError

    if frames.kind == "bag":
        yield from _iter_bag(frames, with_times)
        return
    for f in frames:
        try:
            if with_times:
                tp = read_frame(f.path, with_times=True, time_s=f.time_s)
                xyz, tau = tp.xyz, tp.t_offset_s
            else:
                xyz, tau = read_frame(f.path), None
        except (MinegeoError, OSError) as exc:
            yield f, None, None, exc
            continue
        yield f, xyz, tau, None


def _iter_bag(frames: FrameList, with_times: bool):
    from minegeo.io.bag import iter_bag_frame_records

    it = iter(frames)
    for k, stamp, rec in iter_bag_frame_records(frames.source, frames.topic):
        f = next(it, None)
        if f is None or f.message != k or f.stamp_ns != stamp:
            raise FileFormatError(frames.source, f"topic {frames.topic} message {k}: not the message listed before "
                                  "the run (the bag changed while it was read)")
        if isinstance(rec, Exception):
            yield f, None, None, rec
        else:
            yield f, rec.points.xyz, rec.points.t_offset_s if with_times else None, None
    if next(it, None) is not None:
        raise FileFormatError(frames.source, f"topic {frames.topic}: fewer messages than listed before the run "
                              "(the bag changed while it was read)")


def write_frames_bag(frames, path, topic: str = "/points", frame_id: str = "lidar", storage: str | None = None):
    """Write a frames folder (:func:`list_frames`) as a ROS bag of PointCloud2 messages.

    Each frame becomes one message on ``topic``: float64 fields ``x y z`` (m, sensor frame) and,
    when the frame's points carry times, a float64 ``time`` (seconds after the stamp), so the bag
    holds exactly the values the files hold; ``header.stamp`` is the frame time rounded to whole
    nanoseconds (``round(t * 1e9)``, exact for times written with at most 9 decimals, as
    ``times.txt`` of ``minegeo synth`` is); the log time is the stamp. An example input for
    ``minegeo slam --frames BAG``, written with ``rosbags``.

    Parameters
    ----------
    frames : path
        The frames folder (``times.txt`` or times in the names).
    path : path
        The bag: ``*.bag`` gives a ROS 1 bag, any other name a ROS 2 bag folder.
    topic, frame_id : str
        Topic and ``header.frame_id``.
    storage : {"mcap", "sqlite3"}, optional
        ROS 2 storage (default ``"mcap"``).

    Returns
    -------
    int
        Messages written.
    """
    from minegeo.io.bag import POINTCLOUD2

    try:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise OptionalDependencyError("rosbags", "bag") from None

    path = Path(path)
    ros1 = path.suffix == ".bag"
    if storage not in (None, "mcap", "sqlite3") or (ros1 and storage is not None):
        raise InputError(f"storage {storage!r}: 'mcap' or 'sqlite3', for a ROS 2 bag (not a .bag name)")
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    if ros1:
        writer, ser = Writer1(path), ts.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        writer, ser = Writer2(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    n = 0
    with writer:
        conn = writer.add_connection(topic, POINTCLOUD2, typestore=ts)
        for f, xyz, tau, exc in iter_frames(list_frames(frames), with_times=True):
            if exc is not None:
                raise exc
            names = ["x", "y", "z"] + (["time"] if tau is not None else [])
            rec = np.zeros(xyz.shape[0], dtype=[(nm, "<f8") for nm in names])
            for j, c in enumerate("xyz"):
                rec[c] = xyz[:, j]
            if tau is not None:
                rec["time"] = tau
            ns = int(round(f.time_s * 1e9))
            sec, nsec = divmod(ns, 1_000_000_000)
            hdr = T["std_msgs/msg/Header"](**({"seq": n} if ros1 else {}), frame_id=frame_id,
                                           stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec))
            msg = T[POINTCLOUD2](header=hdr, height=1, width=rec.size, is_bigendian=False, point_step=rec.itemsize,
                                 row_step=rec.itemsize * rec.size, is_dense=True,
                                 fields=[T["sensor_msgs/msg/PointField"](name=nm, offset=8 * j, datatype=8, count=1)
                                         for j, nm in enumerate(names)],
                                 data=np.frombuffer(rec.tobytes(), dtype=np.uint8))
            writer.write(conn, ns, ser(msg, POINTCLOUD2))
            n += 1
    return n
