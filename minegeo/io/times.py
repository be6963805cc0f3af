"""Per-point times of LiDAR frames: which field holds them, their units, and the range check.

The conventions are those of the SLAM contract ("Sensor streams"):

* **Frame time**: the time of a frame (``times.txt``, a frame file name, or a bag message's header
  stamp); the pose written for a frame is the sensor pose at that time.
* **Per-point time fields** (PLY/PCD property names, PointCloud2 field names; the first of
  :data:`TIME_FIELDS` found wins, names compared case-insensitively): a floating-point field holds
  seconds after the frame time; an unsigned integer field holds nanoseconds after it (the Ouster
  ``t`` field, ``uint32``), converted here to float64 seconds, ``t_s = ns / 1e9``. A signed integer
  field is neither and is refused.
* **Range**: every offset must lie within :data:`OFFSET_RANGE_S` = [-0.01 s, 1 s] (a sweep lasts at
  most a second, with a little clock slack before its stamp); otherwise the frame is refused with an
  error that names it.
* **LAS/LAZ**: ``gps_time`` (float64 seconds, absolute: the LAS header's GPS time convention), kept as
  absolute times; :func:`offsets_from_absolute` turns them into offsets from a frame time.

:class:`TimedPoints` is what :func:`minegeo.io.pointcloud.read_points` and
:func:`minegeo.io.frames.read_frame` return when times are asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo.errors import FileFormatError

__all__ = [
    "TIME_FIELDS",
    "OFFSET_RANGE_S",
    "LAS_TIME_FIELD",
    "TimedPoints",
    "find_time_field",
    "time_encoding",
    "offsets_seconds",
    "offset_problem",
    "check_offsets",
    "offsets_from_absolute",
    "timed_points",
    "times_summary",
]

#: Per-point time field names, in order of preference (the first one present wins).
TIME_FIELDS = ("time", "t", "timestamp", "offset_time")
#: Allowed per-point offsets from the frame time, seconds (inclusive).
OFFSET_RANGE_S = (-0.01, 1.0)
#: The LAS/LAZ per-point time dimension (absolute GPS time, s).
LAS_TIME_FIELD = "gps_time"


def _readonly(a: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class TimedPoints:
    """Points of one file or frame with their per-point times (arrays read-only).

    Attributes
    ----------
    xyz : (n, 3) float64
        Coordinates as stored in the file (global: the file's own offset added), metres; the
        sensor frame for LiDAR frames.
    t_offset_s : (n,) float64 or None
        Seconds after the frame time (``None`` when the file holds no time field, or for a
        LAS/LAZ file until :func:`offsets_from_absolute` is given the frame time).
    t_abs_s : (n,) float64 or None
        Absolute times, seconds (LAS/LAZ ``gps_time``); ``None`` otherwise.
    time_field : str or None
        The field the times were read from (``"t"``, ``"gps_time"``, ...).
    time_encoding : str or None
        ``"seconds"`` (a float field), ``"nanoseconds"`` (an unsigned integer field, converted) or
        ``"gps_time"`` (LAS, absolute seconds).
    source : str
        The file (or ``bag!topic#index``) the points came from, for messages.
    """

    xyz: np.ndarray
    t_offset_s: np.ndarray | None
    t_abs_s: np.ndarray | None = None
    time_field: str | None = None
    time_encoding: str | None = None
    source: str = ""

    def __post_init__(self) -> None:
        xyz = np.asarray(self.xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz must have shape (n, 3), got {xyz.shape}")
        object.__setattr__(self, "xyz", _readonly(xyz))
        for name in ("t_offset_s", "t_abs_s"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                if v.shape[0] != xyz.shape[0]:
                    raise ValueError(f"{name} has {v.shape[0]} values for {xyz.shape[0]} points")
                object.__setattr__(self, name, _readonly(v))

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def has_times(self) -> bool:
        """True when the points carry times (offsets or absolute)."""
        return self.t_offset_s is not None or self.t_abs_s is not None


def find_time_field(names) -> str | None:
    """The per-point time field among ``names``: the first of :data:`TIME_FIELDS` present
    (compared case-insensitively), returned as spelled in ``names``; None if there is none."""
    low = {}
    for n in names:
        low.setdefault(str(n).lower(), n)
    for cand in TIME_FIELDS:
        if cand in low:
            return low[cand]
    return None


def time_encoding(dtype) -> str | None:
    """``"seconds"`` for a floating-point dtype, ``"nanoseconds"`` for an unsigned integer one,
    None for anything else (signed integers are neither, by the contract)."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return "seconds"
    if dt.kind == "u":
        return "nanoseconds"
    return None


def offsets_seconds(values, field: str, where) -> np.ndarray:
    """Per-point offsets in float64 seconds from a stored time field (see the module docstring).

    ``t_s = float64(value)`` for a float field; ``t_s = float64(ns) / 1e9`` for an unsigned integer
    field (exact integers below 2^53 ns, one correctly rounded division).

    Raises
    ------
    FileFormatError
        The field is not one value per point, or is a signed integer / non-numeric field; names
        ``where`` (the file, or the bag message).
    """
    v = np.asarray(values)
    if v.ndim != 1:
        raise FileFormatError(where, f"time field {field!r} holds {v.shape[1] if v.ndim == 2 else '?'} values "
                              "per point; a per-point time is one value")
    enc = time_encoding(v.dtype)
    if enc == "seconds":
        return v.astype(np.float64)
    if enc == "nanoseconds":
        return v.astype(np.float64) / 1e9
    raise FileFormatError(where, f"time field {field!r} is stored as {v.dtype}: per-point times are floating point "
                          "(seconds after the frame time) or unsigned integers (nanoseconds after it)")


def offset_problem(t_offset_s: np.ndarray) -> str | None:
    """Why offsets are not a sweep's (NaN, or outside :data:`OFFSET_RANGE_S`), else None."""
    t = np.asarray(t_offset_s, dtype=np.float64)
    if t.size == 0:
        return None
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return f"{int(bad.sum())} per-point time(s) are NaN or infinite (first: point {i})"
    lo, hi = float(t.min()), float(t.max())
    if lo < OFFSET_RANGE_S[0] or hi > OFFSET_RANGE_S[1]:
        i = int(np.argmin(t)) if lo < OFFSET_RANGE_S[0] else int(np.argmax(t))
        return (f"per-point times run from {lo:.6g} s to {hi:.6g} s after the frame time (point {i}: {t[i]:.6g} s), "
                f"outside [{OFFSET_RANGE_S[0]:g} s, {OFFSET_RANGE_S[1]:g} s]: a sweep's offsets are seconds after its "
                "frame time (absolute times, or another unit?)")
    return None


def check_offsets(t_offset_s: np.ndarray, where, field: str | None = None) -> None:
    """Raise :class:`FileFormatError` naming ``where`` (the file or frame) when :func:`offset_problem`
    finds one."""
    msg = offset_problem(t_offset_s)
    if msg is not None:
        raise FileFormatError(where, (f"time field {field!r}: " if field else "") + msg)


def offsets_from_absolute(tp: TimedPoints, frame_time_s: float) -> TimedPoints:
    """``tp`` with ``t_offset_s = t_abs_s - frame_time_s`` (checked by :func:`check_offsets`).

    For LAS/LAZ frames whose ``gps_time`` is on the clock of the frame times. A record that already
    has offsets, or has no times, is returned unchanged.
    """
    if tp.t_offset_s is not None or tp.t_abs_s is None:
        return tp
    ft = float(frame_time_s)
    off = tp.t_abs_s - ft
    check_offsets(off, tp.source, tp.time_field)
    return TimedPoints(tp.xyz, off, tp.t_abs_s, tp.time_field, tp.time_encoding, tp.source)


def timed_points(xyz: np.ndarray, attributes: dict, source, fmt: str | None = None, *,
                 check: bool = True) -> TimedPoints:
    """A :class:`TimedPoints` from coordinates and the per-point attributes a reader returned.

    ``fmt`` ``"las"``/``"laz"``: the ``gps_time`` dimension as absolute times. Otherwise the first
    :data:`TIME_FIELDS` attribute as offsets, checked against :data:`OFFSET_RANGE_S` when ``check``.
    """
    if fmt in ("las", "laz"):
        if LAS_TIME_FIELD in attributes:
            t = np.asarray(attributes[LAS_TIME_FIELD], dtype=np.float64)
            if not np.isfinite(t).all():
                raise FileFormatError(source, "gps_time holds NaN or infinite values")
            return TimedPoints(xyz, None, t, LAS_TIME_FIELD, "gps_time", str(source))
        return TimedPoints(xyz, None, None, None, None, str(source))
    field = find_time_field(attributes)
    if field is None:
        return TimedPoints(xyz, None, None, None, None, str(source))
    off = offsets_seconds(attributes[field], field, source)
    if check:
        check_offsets(off, source, field)
    return TimedPoints(xyz, off, None, field, time_encoding(np.asarray(attributes[field]).dtype), str(source))


def times_summary(attributes: dict, fmt: str | None = None) -> dict | None:
    """What ``minegeo info`` says about per-point times: field, stored dtype, encoding, the span of
    the offsets (s) or of the absolute times, and the problem :func:`offset_problem` finds (never
    raises: ``info`` shows a file as it is). None when there are no times."""
    if fmt in ("las", "laz"):
        if LAS_TIME_FIELD not in attributes:
            return None
        t = np.asarray(attributes[LAS_TIME_FIELD], dtype=np.float64)
        fin = t[np.isfinite(t)]
        return {"field": LAS_TIME_FIELD, "dtype": str(np.asarray(attributes[LAS_TIME_FIELD]).dtype),
                "encoding": "gps_time (absolute seconds)",
                "min_s": float(fin.min()) if fin.size else None, "max_s": float(fin.max()) if fin.size else None,
                "span_s": float(fin.max() - fin.min()) if fin.size else None, "problem": None}
    field = find_time_field(attributes)
    if field is None:
        return None
    v = np.asarray(attributes[field])
    enc = time_encoding(v.dtype)
    out = {"field": field, "dtype": str(v.dtype), "encoding": None, "min_s": None, "max_s": None, "span_s": None,
           "problem": None}
    if enc is None or v.ndim != 1:
        out["problem"] = f"stored as {v.dtype}{'' if v.ndim == 1 else ' with several values per point'}: not a per-point time"
        return out
    out["encoding"] = "seconds after the frame time" if enc == "seconds" else "nanoseconds after the frame time"
    t = offsets_seconds(v, field, "")
    fin = t[np.isfinite(t)]
    if fin.size:
        out.update(min_s=float(fin.min()), max_s=float(fin.max()), span_s=float(fin.max() - fin.min()))
    out["problem"] = offset_problem(t)
    return out
