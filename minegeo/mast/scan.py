"""Horizontal 2D scans (range, bearing) and their CSV format.

Scanner frame: ``x_s`` to the right, ``y_s`` forward (the scanner's zero-bearing
axis). Bearings ``beta`` are measured clockwise from forward, in degrees (the same
sense as a theodolite's horizontal circle and as mine azimuths), so a return maps
to ``s = r (sin beta, cos beta)`` in the scanner frame and, for a scanner at
``(x, y)`` with azimuth ``alpha``, to
``p = (x + r sin(alpha + beta), y + r cos(alpha + beta))`` in the mine frame.
Scanners that report counter-clockwise angles must be converted (``beta = -angle``;
``read_scan_csv(..., counter_clockwise=True)`` does it).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.errors import FileFormatError, InputError
from minegeo.io.limits import MAX_ABS_COORDINATE, MAX_TABLE_FILE_BYTES, read_file_text
from minegeo.io.text import unterminated_last_line

__all__ = ["Scan2D", "read_scan_csv", "write_scan_csv", "scan_to_xy", "MAX_ABS_BEARING_DEG"]

log = logging.getLogger(__name__)

#: largest absolute bearing (deg) accepted from a scan file: scanners report 0..360 or
#: -180..180 (a few turns if angles accumulate); float64 still resolves 1e-10 deg here
MAX_ABS_BEARING_DEG = 1e6


@dataclass
class Scan2D:
    """One horizontal scan.

    Attributes
    ----------
    bearing_deg : (n,) float64
        Bearing of each return, degrees clockwise from the scanner's forward axis.
    range_m : (n,) float64
        Measured range (m). Returns without a range are not stored.
    sigma_range_m : float or None
        Standard deviation of one range (m), if stated by the file/user.
    sigma_bearing_deg : float or None
        Standard deviation of one bearing (deg), if stated.
    metadata : dict
        Free-form ``key: value`` pairs from ``#`` comment lines.
    """

    bearing_deg: np.ndarray
    range_m: np.ndarray
    sigma_range_m: float | None = None
    sigma_bearing_deg: float | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        b = np.ascontiguousarray(np.asarray(self.bearing_deg, dtype=np.float64).reshape(-1))
        r = np.ascontiguousarray(np.asarray(self.range_m, dtype=np.float64).reshape(-1))
        if b.shape != r.shape:
            raise InputError(f"bearing_deg and range_m differ in length ({b.size} vs {r.size})")
        if not (np.isfinite(b).all() and np.isfinite(r).all()):
            raise InputError("scan contains NaN/inf bearings or ranges; drop no-return rows first")
        if np.any(r <= 0):
            raise InputError("scan ranges must be > 0 (drop no-return rows)")
        self.bearing_deg = b
        self.range_m = r

    def __len__(self) -> int:
        return int(self.range_m.size)


def scan_to_xy(bearing_deg: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Scanner-frame coordinates ``s = r (sin beta, cos beta)`` (m), shape (n, 2)."""
    b = np.radians(np.asarray(bearing_deg, dtype=np.float64))
    r = np.asarray(range_m, dtype=np.float64)
    return np.ascontiguousarray(np.column_stack([r * np.sin(b), r * np.cos(b)]))


def write_scan_csv(path, scan: Scan2D, comments: dict | None = None) -> Path:
    """Write a scan as CSV ``bearing_deg,range_m`` (atomically).

    ``#`` comment lines carry ``sigma_range_m``, ``sigma_bearing_deg`` and any extra
    ``comments`` as ``# key: value``.
    """
    lines = ["# minegeo MAST 2D scan: bearing clockwise from scanner forward axis (deg), range (m)"]
    meta = dict(scan.metadata)
    if scan.sigma_range_m is not None:
        meta["sigma_range_m"] = scan.sigma_range_m
    if scan.sigma_bearing_deg is not None:
        meta["sigma_bearing_deg"] = scan.sigma_bearing_deg
    meta.update(comments or {})
    for k, v in meta.items():
        lines.append(f"# {k}: {v}")
    lines.append("bearing_deg,range_m")
    lines += [f"{b:.8f},{r:.6f}" for b, r in zip(scan.bearing_deg, scan.range_m, strict=True)]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_scan_csv(path, counter_clockwise: bool = False) -> Scan2D:
    """Read a 2D scan CSV.

    Format: optional ``# key: value`` comment lines (``sigma_range_m`` and
    ``sigma_bearing_deg`` are recognised), a header ``bearing_deg,range_m`` and one
    return per row. Rows whose range is empty, ``0``, ``nan`` or ``inf`` are "no
    return" and are skipped (their count is stored in ``metadata["no_return_rows"]``); a
    negative range is an error (a rangefinder cannot measure one: a damaged file or a sign
    error would otherwise be dropped without a word).

    Raises
    ------
    FileFormatError
        Missing header columns, a negative range, a row with more or fewer values than the header, a last
        row cut short (no end-of-line and no range), unreadable numbers, a bearing beyond
        :data:`MAX_ABS_BEARING_DEG` or a range beyond
        :data:`~minegeo.io.limits.MAX_ABS_COORDINATE`, a negative or non-finite sigma comment, a
        file that is not a regular UTF-8 file of at most
        :data:`~minegeo.io.limits.MAX_TABLE_FILE_BYTES`. A last line without end-of-line
        (a file cut short?) is read and logged as a warning.
    """
    path = Path(path)
    text = read_file_text(path, encoding="utf-8", max_bytes=MAX_TABLE_FILE_BYTES, what="2D scan CSV")
    meta: dict = {}
    header = None
    bs, rs = [], []
    skipped = 0
    lines = text.splitlines()
    # the last line of a file cut short has no end-of-line: an incomplete row there is an error,
    # not a "no return" (an empty range is indistinguishable from a cut after the comma)
    cut_tail = len(lines) if lines and not text.endswith(("\n", "\r")) else 0
    for line_no, raw in enumerate(lines, start=1):
        ln = raw.strip()
        if not ln:
            continue
        if ln.startswith("#"):
            body = ln[1:].strip()
            if ":" in body:
                k, v = body.split(":", 1)
                meta[k.strip()] = v.strip()
            continue
        cells = [c.strip() for c in ln.split(",")]
        if header is None:
            header = cells
            if "bearing_deg" not in header or "range_m" not in header:
                raise FileFormatError(path, f"line {line_no}: header must contain bearing_deg,range_m, got {ln!r}")
            ib, ir = header.index("bearing_deg"), header.index("range_m")
            continue
        if len(cells) != len(header):
            what = " (the file ends in the middle of this line: cut short?)" if line_no == cut_tail else ""
            raise FileFormatError(
                path, f"line {line_no}: {len(cells)} values, the header {','.join(header)} has {len(header)}{what}"
            )
        if line_no == cut_tail and cells[ir] == "":
            raise FileFormatError(
                path, f"line {line_no}: {ln!r} has no range and no end-of-line: the file was cut short"
            )
        try:
            b = float(cells[ib])
            r = float(cells[ir]) if cells[ir] not in ("", "nan", "NaN") else math.nan
        except (ValueError, IndexError):
            raise FileFormatError(path, f"line {line_no}: cannot read bearing/range from {ln!r}") from None
        if not math.isfinite(b):
            raise FileFormatError(path, f"line {line_no}: bearing is not a finite number")
        if abs(b) > MAX_ABS_BEARING_DEG:
            raise FileFormatError(
                path, f"line {line_no}: bearing {b:g} deg is beyond +-{MAX_ABS_BEARING_DEG:g} deg (damaged file?)"
            )
        if r < 0:  # impossible for a rangefinder: a damaged file or a sign error, never a "no return"
            raise FileFormatError(
                path, f"line {line_no}: range {r:g} m is negative; write a return that is missing as an empty "
                      "range, 0 or nan (the \"no return\" markers)"
            )
        if not (math.isfinite(r) and r > 0):
            skipped += 1
            continue
        if r > MAX_ABS_COORDINATE:
            raise FileFormatError(
                path, f"line {line_no}: range {r:g} m is beyond {MAX_ABS_COORDINATE:.0e} m (damaged file or wrong units?)"
            )
        bs.append(-b if counter_clockwise else b)
        rs.append(r)
    if header is None:
        raise FileFormatError(path, "no header line bearing_deg,range_m found")

    def _f(key):
        if key not in meta:
            return None
        try:
            v = float(meta[key])
        except ValueError:
            raise FileFormatError(path, f"comment {key!r} is not a number: {meta[key]!r}") from None
        if not (math.isfinite(v) and v >= 0):
            raise FileFormatError(path, f"comment {key!r} must be a finite number >= 0, got {meta[key]!r}")
        return v

    meta["no_return_rows"] = skipped
    scan = Scan2D(np.array(bs, dtype=np.float64), np.array(rs, dtype=np.float64), _f("sigma_range_m"),
                  _f("sigma_bearing_deg"), meta)
    cut = unterminated_last_line(text)
    if cut is not None:
        log.warning("%s: the last line (%d: %r) has no end-of-line: the file may have been cut short; "
                    "check that its values are complete", path, cut[0], cut[1][:60])
    return scan
