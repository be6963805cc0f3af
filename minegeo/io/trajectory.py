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

All poses are ``T_<frame>_<body>`` (body -> world). Quaternions are renormalised when
their norm is within 1e-2 of 1, otherwise the file is rejected.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_bytes
from minegeo.errors import FileFormatError, InputError
from minegeo.io._limits import (
    MAX_ABS_COORDINATE,
    MAX_ABS_TIME,
    MAX_TABLE_FILE_BYTES,
    check_coordinate_range,
    read_file_bytes,
    read_file_text,
)
from minegeo.io._quat import matrix_to_quat, quat_to_matrix
from minegeo.io._text import format_table, is_number, parse_table, unterminated_last_line
from minegeo.io.types import Trajectory

log = logging.getLogger(__name__)

__all__ = ["read_trajectory", "write_trajectory", "read_transform", "TRAJECTORY_FORMATS"]

TRAJECTORY_FORMATS = ("tum", "kitti", "geoslam", "csv")
_SUFFIX = {".tum": "tum", ".kitti": "kitti", ".csv": "csv"}
_CSV_COLS = ("time_s", "x", "y", "z", "qx", "qy", "qz", "qw")
_GEOSLAM_COLS = ("time", "x", "y", "z", "q0", "q1", "q2", "q3")
_ALIASES = {"t": "time_s", "time": "time_s", "timestamp": "time_s", "time_s": "time_s"}


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
    frame, body : str
        Frame names recorded in the result (poses are ``T_frame_body``).
    origin : None or (3,) array_like
        Local origin (m) subtracted from the positions (``Trajectory.origin``).
    crs : str, optional
        CRS of the ``frame`` coordinates, recorded in the result.

    Raises
    ------
    FileFormatError
        Empty file, unknown layout, wrong number of values on a line, non-numeric value,
        NaN, a quaternion that is not unit length (the line is named).
    """
    p = Path(path)
    text = read_file_bytes(p, what="trajectory file").decode("latin-1")
    if not text.strip():
        raise FileFormatError(p, "empty file (no poses)")
    header, delim, start, first_line, toks = _preamble(p, text)
    if toks is None:
        raise FileFormatError(p, "no numeric pose lines found")
    fmt = (format or _SUFFIX.get(p.suffix.lower()) or _sniff(p, header, len(toks))).lower()
    if fmt not in TRAJECTORY_FORMATS:
        raise InputError(f"unknown trajectory format {format!r}; choose one of {', '.join(TRAJECTORY_FORMATS)}")
    if fmt in ("tum", "kitti"):
        ncols = 8 if fmt == "tum" else 12
        table = parse_table(p, text[start:], ncols=ncols, first_line=first_line, delimiter=delim)
        if fmt == "kitti":
            m = table.shape[0]
            poses = np.tile(np.eye(4), (m, 1, 1))
            poses[:, :3, :] = table.reshape(m, 3, 4)
            times = np.arange(m, dtype=np.float64)
            qrows = None
        else:
            times = table[:, 0]
            xyz = table[:, 1:4]
            qrows = table[:, 4:8]
            order = "xyzw"
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
        idx = [names.index(c) for c in need]
        times = table[:, idx[0]]
        xyz = table[:, idx[1:4]]
        qrows = table[:, idx[4:8]]
        order = "xyzw" if fmt == "csv" else "wxyz"
    if table.shape[0] == 0:
        raise FileFormatError(p, "no poses")
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FileFormatError(p, f"{int(bad.sum())} pose(s) contain NaN or inf (first: pose {i}, data row {i + 1})")

    def where(i: int) -> str:
        return f"pose {i}, data row {i + 1}"

    # huge finite values would overflow in quaternion norms, time differences and positions
    check_coordinate_range(p, times, "time", where, limit=MAX_ABS_TIME, row_noun="pose")
    if qrows is not None:
        check_coordinate_range(p, xyz, "position", where, row_noun="pose")
        check_coordinate_range(p, qrows, "quaternion component", where, row_noun="pose")
    else:
        check_coordinate_range(p, poses[:, :3, :].reshape(-1, 12), "matrix element", where, row_noun="pose")
    if qrows is not None:
        try:
            R = quat_to_matrix(qrows, order=order)
        except InputError as exc:
            raise FileFormatError(p, str(exc).replace("row", "pose")) from None
        poses = np.tile(np.eye(4), (table.shape[0], 1, 1))
        poses[:, :3, :3] = R
        poses[:, :3, 3] = xyz
    else:
        err = np.abs(np.einsum("mji,mjk->mik", poses[:, :3, :3], poses[:, :3, :3]) - np.eye(3)).max(axis=(1, 2))
        if np.any(err > 1e-4):
            i = int(np.argmax(err > 1e-4))
            raise FileFormatError(p, f"pose {i}: rotation block is not orthonormal (|R^T R - I| = {err[i]:.2g})")
    if times.size > 1 and np.any(np.diff(times) <= 0):
        log.warning("%s: timestamps are not strictly increasing", p)
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    if not (np.isfinite(o).all() and np.abs(o).max() <= MAX_ABS_COORDINATE):
        raise InputError(f"origin must be 3 finite numbers within +-{MAX_ABS_COORDINATE:.0e} (m), got {origin!r}")
    if np.any(o != 0):
        poses[:, :3, 3] -= o
    traj = Trajectory(times_s=times, poses=poses, frame=frame, body=body, origin=o, crs=crs)
    cut = unterminated_last_line(text)
    if cut is not None:  # told once the whole file has been read (see minegeo.io._text)
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

    Raises
    ------
    InputError
        Unknown format, or a pose whose rotation is not orthonormal within 1e-6.
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
