"""A folder of LiDAR frames (``minegeo slam --frames DIR``), as fixed by the SLAM contract.

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
"""

from __future__ import annotations

import fnmatch
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io._limits import read_file_bytes
from minegeo.io.pointcloud import _SUFFIX
from minegeo.io.trajectory import read_times, time_problem

__all__ = ["FrameFile", "list_frames", "read_frame", "read_kitti_bin", "times_source"]

log = logging.getLogger(__name__)

#: Largest frame file read (a 128-beam scan is ~ 4 MB).
MAX_FRAME_BYTES = 1 << 30
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class FrameFile:
    """One frame of the folder: its file and its time (s)."""

    path: Path
    time_s: float


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
        raise InputError(f"--frames {folder}: not a folder")
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
    """Where :func:`list_frames` takes the times from: ``"file"`` or ``"names"``."""
    return "file" if times_file is not None or (Path(folder) / "times.txt").is_file() else "names"


def _looks_like_frame_numbers(times: np.ndarray) -> bool:
    return times.size >= 3 and times[0] in (0.0, 1.0) and bool(np.all(np.diff(times) == 1.0))


def list_frames(folder, times_file=None, pattern: str | None = None) -> list[FrameFile]:
    """The frames of ``folder`` in name order with their times (see the module docstring).

    Parameters
    ----------
    folder : path
        The frames folder.
    times_file : path, optional
        One time (s) per frame in name order; default ``folder/times.txt`` when present, else the
        numbers in the file names.
    pattern : str, optional
        Shell pattern on the file names (``"*.pcd"``); default every point-cloud file.

    Returns
    -------
    list of FrameFile
        At least one frame; times finite, within +-1e20 s and strictly increasing (the check of
        :func:`minegeo.io.trajectory.time_problem`), so a trajectory written from them reads back.

    Raises
    ------
    InputError
        Not a folder, no frames, no number in a frame name, or times from the names that fail the check
        (the first offending frame is named).
    FileFormatError
        A times file that is missing, not a regular file (a folder, FIFO or device, named as such and
        never opened), not one decimal number per line, holding another count of times than of
        frames, or failing the check (its line and frame are named).
    """
    folder = Path(folder)
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
    return [FrameFile(p, float(t)) for p, t in zip(paths, times, strict=True)]
