"""Trajectory files: TUM, KITTI poses, GeoSLAM-style text and CSV; plain-text 4x4 transforms.

=========  ================================================================================
format     layout (one pose per line; ``#`` lines are comments)
=========  ================================================================================
tum        ``t x y z qx qy qz qw`` -- TUM RGB-D benchmark (Sturm et al. 2012); time in s,
           position in m, Hamilton unit quaternion, scalar **last**. The CTU cave/mine
           ground-truth files (``# timestamp x y z qx qy qz qw``) are this format.
kitti      12 numbers: the first three rows of ``T_world_body`` row-major (KITTI odometry
           ``poses/XX.txt``). The format has no times: ``times_s = 0, 1, 2, ...``.
geoslam    a header line naming the columns, then rows; minegeo uses the columns
           ``Time X Y Z q0 q1 q2 q3`` (case-insensitive, any order, extra columns ignored)
           and assumes, as GeoSLAM's exported ``*_traj.txt`` do, a **scalar-first**
           quaternion ``q0 = w`` and a pose mapping the scanner into the world frame.
csv        header ``time_s,x,y,z,qx,qy,qz,qw`` (scalar last), comma separated.
=========  ================================================================================

All poses are ``T_<frame>_<body>`` (body -> world).

Every reader here (and :mod:`minegeo.io.frames`, whose times files :func:`read_times` reads)
applies ONE check of a trajectory, :func:`time_problem`, :func:`rotation_problem` and
:func:`quaternion_problem`, and names the file and line of the first problem:

* times finite, within +-:data:`~minegeo.io.limits.MAX_ABS_TIME` (1e20 s: UNIX seconds are
  ~1.7e9, ROS nanosecond stamps ~1.7e18), so every difference ``t_j - t_i`` and every sum is finite
  in float64, and strictly increasing (a duplicated or unsorted stamp is refused). Written with 17
  significant digits, such a time reads back as the same float64;
* rotation blocks (KITTI) proper rotations: ``max |R^T R - I| <= ROTATION_TOLERANCE`` (1e-4; KITTI
  files print 6-7 significant digits, ~1e-6) and ``det R > 0`` (then ``det R = 1`` within 3e-4);
  a reflection (``det R = -1``) is named as such;
* quaternions finite with ``| |q| - 1 | <= QUATERNION_NORM_TOLERANCE`` (1e-2), then renormalised;
  a zero quaternion is named as such.

:func:`write_trajectory` applies the same check, so a file it writes always reads back.
"""

from __future__ import annotations

import logging
import os
import re
import stat
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes
from minegeo.errors import FileFormatError, InputError
from minegeo.io._quat import (
    QUATERNION_NORM_TOLERANCE,
    ROTATION_TOLERANCE,
    matrix_to_quat,
    quat_to_matrix,
    quaternion_problem,
    rotation_problem,
)
from minegeo.io.limits import (
    MAX_ABS_COORDINATE,
    MAX_ABS_TIME,
    MAX_TABLE_FILE_BYTES,
    check_coordinate_range,
    file_kind,
    read_file_bytes,
    read_file_text,
)
from minegeo.io.text import data_line_locator, format_table, is_number, parse_table, unterminated_last_line
from minegeo.io.types import Trajectory

log = logging.getLogger(__name__)

__all__ = ["read_trajectory", "write_trajectory", "read_transform", "read_times", "trajectory_format",
           "time_problem", "rotation_problem", "quaternion_problem", "TRAJECTORY_FORMATS", "ROTATION_TOLERANCE",
           "QUATERNION_NORM_TOLERANCE"]

TRAJECTORY_FORMATS = ("tum", "kitti", "geoslam", "csv")
_SUFFIX = {".tum": "tum", ".kitti": "kitti", ".csv": "csv"}
_CSV_COLS = ("time_s", "x", "y", "z", "qx", "qy", "qz", "qw")
_GEOSLAM_COLS = ("time", "x", "y", "z", "q0", "q1", "q2", "q3")
_ALIASES = {"t": "time_s", "time": "time_s", "timestamp": "time_s", "time_s": "time_s"}
#: a time in a times file: a decimal number (no ``nan``/``inf``, no ``1_000``)
_TIME_TOKEN = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_NOT_FINITE = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}


# ---------------------------------------------------------------------------- the shared check


def _fmt_time(t: float) -> str:
    """``2.000000`` when six decimals show ``t`` exactly, otherwise its shortest exact form."""
    t = float(t)
    six = f"{t:.6f}"
    return six if abs(t) < 1e15 and float(six) == t else repr(t)


def time_problem(times, noun: str = "pose") -> tuple[int, str] | None:
    """The first problem of a time series: ``(index, sentence)``, or None when it is valid.

    Valid: every time finite, ``|t| <= MAX_ABS_TIME`` (1e20 s), so that every difference and sum of
    two times is finite in float64 and the 17-digit text minegeo writes reads back as the same
    float64, and strictly increasing (``t[k] > t[k-1]``). The index is the first offending time.

    Parameters
    ----------
    times : (m,) array_like
        Times (s).
    noun : str
        What a time belongs to (``"pose"``, ``"frame"``), for the sentence.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    finite = np.isfinite(t)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        return i, f"time {t[i]} is not a number of seconds (NaN or infinite)"
    big = np.abs(t) > MAX_ABS_TIME
    if big.any():
        i = int(np.flatnonzero(big)[0])
        return i, (f"time {t[i]:.6g} s is not a time stamp (beyond +-{MAX_ABS_TIME:.0e} s; UNIX seconds are "
                   f"~1.7e9, ROS nanoseconds ~1.7e18): the file is damaged or in the wrong units")
    if t.size > 1:
        back = np.flatnonzero(np.diff(t) <= 0.0)  # finite: |t| <= 1e20
        if back.size:
            k = int(back[0]) + 1
            return k, (f"time {_fmt_time(t[k])} s is not after the previous {noun}'s {_fmt_time(t[k - 1])} s: "
                       f"times must increase strictly from {noun} to {noun} (a duplicated or unsorted time stamp)")
    return None


def read_times(path, count: int | None = None, *, noun: str = "pose", labels=None, hint: str = "") -> np.ndarray:
    """Read a times file: one time in seconds per line, checked by :func:`time_problem`.

    The KITTI odometry ``times.txt`` layout (and ``minegeo slam --times``): one decimal number per
    line; blank lines and ``#`` comments (whole line or after the number) are skipped; a UTF-8
    byte-order mark is allowed.

    Parameters
    ----------
    path : str or Path
        The times file. A folder, FIFO, device or socket is refused without being opened (a FIFO
        never blocks).
    count : int, optional
        Number of times the file must hold (one per pose or frame).
    noun : str
        What each time belongs to (``"pose"``, ``"frame"``), for messages.
    labels : sequence of str, optional
        A name for each of the ``count`` items (``"frame 000002.ply"``), added to the line a message names.
    hint : str
        Text appended to the count-mismatch message (how to fix it).

    Returns
    -------
    (m,) float64
        Times (s): finite, within +-1e20 s, strictly increasing.

    Raises
    ------
    FileFormatError
        Not a regular file (``"is a folder, not a times file"``), missing, not UTF-8, a line that is
        not one decimal number, NaN/inf, a count other than ``count``, or times that are not a
        valid series (the line, and the label, of the first offending time are named).
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileFormatError(p, "no such file (a times file: one time in seconds per line)") from None
    except NotADirectoryError:
        raise FileFormatError(p, "no such file: a part of the path is a file, not a folder") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else file_kind(st.st_mode)
        raise FileFormatError(p, f"is {kind}, not a times file (not a regular file; expected text, one time in "
                              "seconds per line)")
    text = read_file_text(p, encoding="utf-8-sig", what="times file")
    vals, lines = [], []
    for k, line in enumerate(text.splitlines(), start=1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        toks = s.replace(",", " ").split()
        if len(toks) != 1:
            raise FileFormatError(p, f"line {k}: {len(toks)} values ({s[:60]!r}); a times file holds one time "
                                  "in seconds per line")
        tok = toks[0]
        if tok.lower() in _NOT_FINITE:
            raise FileFormatError(p, f"line {k}: {tok[:40]!r} is not a number of seconds (NaN or infinite)")
        if not _TIME_TOKEN.fullmatch(tok):
            raise FileFormatError(p, f"line {k}: {tok[:40]!r} is not a time in seconds")
        vals.append(float(tok))
        lines.append(k)
    if count is not None and len(vals) != count:
        raise FileFormatError(p, f"holds {len(vals)} times for {count} {noun}s: one time per {noun}{hint}")
    if not vals:
        raise FileFormatError(p, "holds no times (one time in seconds per line)")
    times = np.asarray(vals, dtype=np.float64)
    bad = time_problem(times, noun)
    if bad is not None:
        i, msg = bad
        where = f"line {lines[i]}" + (f": {labels[i]}" if labels is not None else "")
        raise FileFormatError(p, f"{where}: {msg}")
    return times


def trajectory_format(path, format: str | None = None) -> str:
    """The format :func:`read_trajectory` reads ``path`` as (``format``, else the suffix, else the content).

    Raises
    ------
    InputError, FileFormatError
        An unknown ``format``; a file whose content names no format (as :func:`read_trajectory`).
    """
    if format is not None:
        fmt = str(format).lower()
        if fmt not in TRAJECTORY_FORMATS:
            raise InputError(f"unknown trajectory format {format!r}; choose one of {', '.join(TRAJECTORY_FORMATS)}")
        return fmt
    p = Path(path)
    if p.suffix.lower() in _SUFFIX:
        return _SUFFIX[p.suffix.lower()]
    text = read_file_bytes(p, what="trajectory file").decode("latin-1")
    header, _, _, _, toks = _preamble(p, text)
    if toks is None:
        raise FileFormatError(p, "empty file (no poses)" if not text.strip() else "no numeric pose lines found")
    return _sniff(p, header, len(toks))


def _preamble(path, text: str):
    """(header tokens or None, delimiter, start offset, first line number, first data tokens)."""
    pos = 0
    lineno = 0
    header = None
    while pos < len(text):
        nl = text.find("\n", pos)
        end = len(text) if nl < 0 else nl
        line = text[pos:end].strip()
        start = pos
        lineno += 1
        pos = end + 1
        if not line or line.startswith("#") or line.startswith("//"):
            continue
        delim = "," if "," in line else (";" if ";" in line else None)
        toks = [t.strip() for t in line.split(delim)] if delim else line.split()
        if all(is_number(t) for t in toks):
            return header, delim, start, lineno, toks
        if header is not None:
            raise FileFormatError(path, f"line {lineno}: {line[:80]!r} is not numbers")
        header = (lineno, [t.lower() for t in toks])
    return header, None, len(text), lineno + 1, None


def _sniff(path, header, ntok: int | None) -> str:
    if header is not None:
        names = header[1]
        if "q0" in names:
            return "geoslam"
        if "qw" in names:
            return "csv"
        raise FileFormatError(path, f"line {header[0]}: header {' '.join(names)!r} names no quaternion columns")
    if ntok == 8:
        return "tum"
    if ntok == 12:
        return "kitti"
    raise FileFormatError(
        path, f"cannot tell the trajectory format: {ntok} numbers per line (TUM has 8, KITTI 12); pass format="
    )


def read_trajectory(
    path,
    format: str | None = None,
    *,
    times=None,
    frame: str = "world",
    body: str = "sensor",
    origin=None,
    crs: str | None = None,
) -> Trajectory:
    """Read a trajectory file into a :class:`~minegeo.io.types.Trajectory`.

    Parameters
    ----------
    path : str or Path
    format : {"tum", "kitti", "geoslam", "csv"}, optional
        Default: ``.tum``/``.kitti``/``.csv`` suffix, otherwise detected from the content
        (8 numbers per line: TUM; 12: KITTI; a header with ``q0``: GeoSLAM; with ``qw``: CSV).
    times : str or Path, optional
        A times file (:func:`read_times`, one time per pose) for a KITTI file, which has none
        (without it the times are ``0, 1, 2, ...``). Refused for the other formats, which carry
        their own times.
    frame, body : str
        Frame names recorded in the result (poses are ``T_frame_body``).
    origin : None or (3,) array_like
        Local origin (m) subtracted from the positions (``Trajectory.origin``).
    crs : str, optional
        CRS of the ``frame`` coordinates, recorded in the result.

    Raises
    ------
    FileFormatError
        Empty file, unknown layout, wrong number of values on a line, non-numeric value, NaN/inf,
        a position beyond +-1e12, and every failure of the shared check (module docstring):
        times not finite, beyond +-1e20 s or not strictly increasing; a rotation block that is not
        a proper rotation (a reflection named as such); a quaternion that is zero or not of unit
        norm within 1e-2. The message names the file and the line.
    InputError
        An unknown ``format``, ``times`` given for a format that has its own times, a bad ``origin``.
    """
    p = Path(path)
    text = read_file_bytes(p, what="trajectory file").decode("latin-1")
    if not text.strip():
        raise FileFormatError(p, "empty file (no poses)")
    header, delim, start, first_line, toks = _preamble(p, text)
    if toks is None:
        raise FileFormatError(p, "no numeric pose lines found")
    fmt = trajectory_format(p, format) if format is not None or p.suffix.lower() in _SUFFIX else _sniff(
        p, header, len(toks))
    if times is not None and fmt != "kitti":
        raise InputError(f"{p} is a {fmt} trajectory with its own times: a times file ({times}) is only for KITTI "
                         "poses, which have none")
    if fmt in ("tum", "kitti"):
        table = parse_table(p, text[start:], ncols=8 if fmt == "tum" else 12, first_line=first_line,
                            delimiter=delim)
    else:
        if header is None:
            want = "time_s,x,y,z,qx,qy,qz,qw" if fmt == "csv" else "Time X Y Z q0 q1 q2 q3"
            raise FileFormatError(p, f"{fmt} trajectory needs a header line ({want})")
        names = [_ALIASES.get(n, n) for n in header[1]]
        need = _CSV_COLS if fmt == "csv" else ("time_s",) + _GEOSLAM_COLS[1:]
        missing = [c for c in need if c not in names]
        if missing:
            raise FileFormatError(p, f"line {header[0]}: header lacks column(s) {', '.join(missing)}")
        table = parse_table(p, text[start:], ncols=len(names), first_line=first_line, delimiter=delim)
        table = table[:, [names.index(c) for c in need]]
    m = table.shape[0]
    if m == 0:
        raise FileFormatError(p, "no poses")
    line_of = data_line_locator(text[start:], first_line)  # error path only

    def where(i: int) -> str:
        return f"line {line_of(i)}"

    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FileFormatError(p, f"{where(i)}: a value is NaN or inf ({int(bad.sum())} such line(s))")
    if fmt == "kitti":
        poses = np.tile(np.eye(4), (m, 1, 1))
        poses[:, :3, :] = table.reshape(m, 3, 4)
        # huge finite values would overflow in products and differences
        check_coordinate_range(p, table, "matrix element", where, row_noun="pose")
        problem = rotation_problem(poses[:, :3, :3])
        t = np.arange(m, dtype=np.float64) if times is None else read_times(
            times, m, hint=f" of {p} (the KITTI odometry times.txt layout)")
    else:
        t, xyz, q = table[:, 0], table[:, 1:4], table[:, 4:8]
        check_coordinate_range(p, xyz, "position", where, row_noun="pose")
        order = "wxyz" if fmt == "geoslam" else "xyzw"
        problem = time_problem(t) or quaternion_problem(q, names="q0 q1 q2 q3" if order == "wxyz" else "qx qy qz qw")
        if problem is None:
            poses = np.tile(np.eye(4), (m, 1, 1))
            poses[:, :3, :3] = quat_to_matrix(q, order=order)
            poses[:, :3, 3] = xyz
    if problem is not None:
        raise FileFormatError(p, f"{where(problem[0])}: {problem[1]}")
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    if not (np.isfinite(o).all() and np.abs(o).max() <= MAX_ABS_COORDINATE):
        raise InputError(f"origin must be 3 finite numbers within +-{MAX_ABS_COORDINATE:.0e} (m), got {origin!r}")
    if np.any(o != 0):
        poses[:, :3, 3] -= o
    traj = Trajectory(times_s=t, poses=poses, frame=frame, body=body, origin=o, crs=crs)
    cut = unterminated_last_line(text)
    if cut is not None:  # told once the whole file has been read (see minegeo.io.text)
        log.warning("%s: the last line (%d: %r) has no end-of-line: the file may have been cut short; "
                    "check that its values are complete", p, cut[0], cut[1][:60])
    return traj


def write_trajectory(path, traj: Trajectory, format: str | None = None, *, coordinates: str = "global") -> Path:
    """Write ``traj`` atomically in ``format`` (see the module docstring).

    ``format`` defaults to the one :func:`read_trajectory` infers from the suffix
    (``.tum``/``.kitti``/``.csv``), otherwise ``"tum"``, so a written file reads back as
    written.

    Positions are written as ``t + origin`` (``coordinates="global"``) or ``t``
    (``"local"``), with 17 significant digits (exact float64 round trip). Rotations are
    converted to quaternions (Shepperd's method, ``w >= 0``) for TUM/GeoSLAM/CSV, so a
    round trip reproduces matrices to ~1e-15; KITTI stores the matrix itself (exact) but
    no times (a warning is logged when the times are not 0, 1, 2, ...).

    The trajectory must pass the readers' check (module docstring), so that the file reads back:
    otherwise nothing is written.

    Raises
    ------
    InputError
        Unknown format; times that are not finite, beyond +-1e20 s or not strictly increasing
        (TUM/GeoSLAM/CSV); a rotation that is not proper within 1e-4 (KITTI) or 1e-6 (quaternion
        formats); a written position beyond +-1e12 m. The first offending pose is named.
    """
    if not isinstance(traj, Trajectory):
        raise InputError(f"traj must be a Trajectory, got {type(traj).__name__}")
    fmt = _SUFFIX.get(Path(path).suffix.lower(), "tum") if format is None else str(format).lower()
    if fmt not in TRAJECTORY_FORMATS:
        raise InputError(f"unknown trajectory format {format!r}; choose one of {', '.join(TRAJECTORY_FORMATS)}")
    if coordinates not in ("global", "local"):
        raise InputError(f"coordinates must be 'global' or 'local', got {coordinates!r}")
    T = traj.poses.copy()
    if coordinates == "global":
        T[:, :3, 3] += traj.origin
    problem = rotation_problem(T[:, :3, :3]) or (None if fmt == "kitti" else time_problem(traj.times_s))
    far = np.flatnonzero(~(np.abs(T[:, :3, 3]) <= MAX_ABS_COORDINATE).all(axis=1))
    if problem is None and far.size:
        problem = int(far[0]), f"position beyond +-{MAX_ABS_COORDINATE:.0e} m"
    if problem is not None:
        raise InputError(f"cannot write {path}: pose {problem[0]}: {problem[1]} (the file would not read back)")
    m = len(traj)
    g = "%.17g"
    if fmt == "kitti":
        if not np.array_equal(traj.times_s, np.arange(m, dtype=np.float64)):
            log.warning("KITTI poses have no timestamps: the times of %s are not written", path)
        rows = T[:, :3, :].reshape(m, 12)
        text = format_table([rows[:, j] for j in range(12)], [g] * 12)
    else:
        q = matrix_to_quat(T[:, :3, :3], order="wxyz" if fmt == "geoslam" else "xyzw")
        cols = [traj.times_s, T[:, 0, 3], T[:, 1, 3], T[:, 2, 3], q[:, 0], q[:, 1], q[:, 2], q[:, 3]]
        if fmt == "tum":
            text = "# timestamp x y z qx qy qz qw\n" + format_table(cols, [g] * 8)
        elif fmt == "geoslam":
            text = "Time X Y Z q0 q1 q2 q3\n" + format_table(cols, [g] * 8)
        else:
            text = ",".join(_CSV_COLS) + "\n" + format_table(cols, [g] * 8, delimiter=",")
    return atomic_write_bytes(path, text.encode("ascii"))


def read_transform(path) -> np.ndarray:
    """Read a 4x4 (or 3x4) row-major matrix from a text file, e.g. ``T_target_source.txt``.

    Accepts 12 or 16 numbers separated by whitespace/commas/brackets (``#`` comments
    allowed); a 3x4 matrix gets the row ``0 0 0 1``. Used for the CTU ``fcu_in_map.mat``
    files (plain text despite the suffix).

    Raises
    ------
    FileFormatError
        Not 12/16 numbers, a last row other than ``0 0 0 1``, or non-finite values.
    """
    p = Path(path)
    text = read_file_text(p, encoding="latin-1", max_bytes=MAX_TABLE_FILE_BYTES, what="4x4 matrix file")
    lines = [ln.split("#", 1)[0] for ln in text.splitlines()]
    text = " ".join(lines).replace(",", " ").replace("[", " ").replace("]", " ").replace(";", " ")
    toks = text.split()
    try:
        vals = np.array([float(t) for t in toks], dtype=np.float64)
    except ValueError:
        raise FileFormatError(p, "a 4x4 matrix file must contain only numbers") from None
    if vals.size == 12:
        vals = np.concatenate([vals, [0.0, 0.0, 0.0, 1.0]])
    if vals.size != 16:
        raise FileFormatError(p, f"expected 12 or 16 numbers (3x4 or 4x4 matrix), found {vals.size}")
    T = vals.reshape(4, 4)
    if not np.isfinite(T).all():
        raise FileFormatError(p, "matrix contains NaN or inf")
    check_coordinate_range(p, T, "matrix element", lambda i: f"row {i + 1}", row_noun="row")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise FileFormatError(p, f"last row must be 0 0 0 1, got {T[3].tolist()}")
    return T
