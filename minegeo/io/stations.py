"""Control and check stations of a SLAM run (``minegeo slam --control FILE``): the stations CSV.

Layout (slam_contract.md, "Sensor streams", control stations)::

    # crs: EPSG:5186
    id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role
    S01,12.0,17.0,201345.112,551203.447,87.402,0.005,0.010,control
    S02,95.5,100.5,201402.880,551388.019,86.911,0.005,0.010,check

* ``id``: station name (unique, non-empty).
* ``t_start t_end``: the time span (s, on the clock of the frame times) during which the scanner
  stands still on the station; ``t_end >= t_start``; the spans of two stations never overlap
  (the scanner stands on one station at a time).
* ``E N H``: easting, northing, height of the surveyed point in the CRS (projected grid, m).
* ``sigma_h_m``: a-priori standard deviation of E and of N (each, m); ``sigma_v_m``: of H (m).
* ``role``: ``control`` (used in the fit) or ``check`` (withheld, only compared). At least one
  control station.

The surveyed point is the sensor origin plus the offset ``--station-offset x y z`` (m, sensor
frame; :func:`parse_station_offset`). Header names are case-insensitive, in any order; fields are
separated by commas (``;`` or tab also read); ``#`` lines are comments, ``# crs: ...`` names the
CRS. Coordinates are kept in float64 relative to a recorded local origin
(:func:`minegeo.georef.crs.local_origin`, whole kilometres, the way minegeo keeps projected
coordinates): ``E N H = enh_local + origin_enh`` exactly for survey-grade magnitudes.

Every problem is a :class:`~minegeo.errors.FileFormatError` naming the file and the line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io._table import check_sigma, new_id, number, read_table, table_writer
from minegeo.io.limits import (
    MAX_ABS_COORDINATE,
    MAX_ABS_TIME,
    MAX_TABLE_FILE_BYTES,
    read_file_text,
)

__all__ = ["StationRole", "Stations", "STATIONS_HEADER", "read_stations", "write_stations", "is_stations_header",
           "parse_station_offset", "MAX_STATION_OFFSET_M"]

#: The stations CSV columns (the order :func:`write_stations` writes; any order is read).
STATIONS_HEADER = ("id", "t_start", "t_end", "E", "N", "H", "sigma_h_m", "sigma_v_m", "role")
#: Largest accepted ``--station-offset`` length (m): a pole or tripod, not a wrong unit.
MAX_STATION_OFFSET_M = 10.0


class StationRole(StrEnum):
    """What a station is used for: ``control`` enters the fit, ``check`` is withheld and compared."""

    CONTROL = "control"
    CHECK = "check"


@dataclass(frozen=True, eq=False)
class Stations:
    """Stations read from a stations CSV (see the module docstring).

    Attributes
    ----------
    ids : tuple of str
        Station names, in file order.
    t_start_s, t_end_s : ndarray (n,) float64, s
        Span during which the scanner stood still on the station.
    enh_local : ndarray (n, 3) float64, m
        ``E N H`` minus :attr:`origin_enh`.
    origin_enh : ndarray (3,) float64, m
        Recorded local origin in the CRS (a multiple of 1000 m).
    sigma_h_m, sigma_v_m : ndarray (n,) float64, m
        A-priori standard deviation of E and of N (each), and of H.
    roles : tuple of StationRole
    crs : str or None
        From the ``# crs:`` line or the caller.
    lines : tuple of int
        Line of each station in the file (for messages).
    source : str or None
        The file read.
    """

    ids: tuple
    t_start_s: np.ndarray
    t_end_s: np.ndarray
    enh_local: np.ndarray
    origin_enh: np.ndarray
    sigma_h_m: np.ndarray
    sigma_v_m: np.ndarray
    roles: tuple
    crs: str | None = None
    lines: tuple = ()
    source: str | None = None

    def __post_init__(self):
        n = len(self.ids)
        for name in ("t_start_s", "t_end_s", "sigma_h_m", "sigma_v_m"):
            a = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            if a.shape != (n,):
                raise InputError(f"Stations.{name}: expected {n} values, got {a.shape}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        for name, shape in (("enh_local", (n, 3)), ("origin_enh", (3,))):
            a = np.array(getattr(self, name), dtype=np.float64).reshape(shape)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "ids", tuple(str(i) for i in self.ids))
        object.__setattr__(self, "roles", tuple(StationRole(r) for r in self.roles))
        object.__setattr__(self, "lines", tuple(int(v) for v in self.lines) or tuple(range(2, n + 2)))

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def enh(self) -> np.ndarray:
        """``E N H`` (n, 3) in the CRS (m): ``enh_local + origin_enh``."""
        return self.enh_local + self.origin_enh

    @property
    def is_control(self) -> np.ndarray:
        """(n,) bool: role ``control``."""
        return np.array([r is StationRole.CONTROL for r in self.roles], dtype=bool)

    @property
    def is_check(self) -> np.ndarray:
        """(n,) bool: role ``check``."""
        return ~self.is_control

    @property
    def t_mid_s(self) -> np.ndarray:
        """(n,) s: middle of each span."""
        return 0.5 * (self.t_start_s + self.t_end_s)

    def covariance(self) -> np.ndarray:
        """A-priori covariance (n, 3, 3) of ``E N H`` (m^2): ``diag(sigma_h^2, sigma_h^2, sigma_v^2)``."""
        c = np.zeros((len(self), 3, 3))
        c[:, 0, 0] = c[:, 1, 1] = self.sigma_h_m**2
        c[:, 2, 2] = self.sigma_v_m**2
        return c

    def check_time_span(self, t_min_s: float, t_max_s: float, what: str = "the run") -> None:
        """Raise :class:`InputError` naming the first station whose span is not inside ``[t_min_s, t_max_s]``."""
        for i in np.argsort(self.t_start_s, kind="stable"):
            if self.t_start_s[i] < t_min_s or self.t_end_s[i] > t_max_s:
                raise InputError(
                    f"{self.source or 'stations'}: line {self.lines[i]}: station {self.ids[i]} stands "
                    f"[{self.t_start_s[i]:.3f}, {self.t_end_s[i]:.3f}] s, outside {what} "
                    f"[{t_min_s:.3f}, {t_max_s:.3f}] s (another clock or another run?)")


def _canon(name: str) -> str:
    n = name.strip().lower()
    return {"e": "E", "n": "N", "h": "H"}.get(n, n)


def is_stations_header(names) -> bool:
    """True when the header names (any case, any order) are exactly the stations CSV columns."""
    canon = [_canon(n) for n in names]
    return len(canon) == len(STATIONS_HEADER) and set(canon) == set(STATIONS_HEADER)


def read_stations(path, crs: str | None = None) -> Stations:
    """Read a stations CSV (see the module docstring).

    Parameters
    ----------
    path : str or Path
    crs : str, optional
        CRS when the file has no ``# crs:`` line (a conflicting line is an error).

    Returns
    -------
    Stations
        Spans in s, coordinates in m relative to a recorded local origin.

    Raises
    ------
    FileFormatError
        Naming the file and the line: missing or unknown columns, a wrong number of fields, a value
        that is not a finite number, ``t_end < t_start``, a sigma <= 0 (or below
        :data:`~minegeo.io.limits.MIN_SIGMA_M`), an unknown role, a duplicate id, overlapping
        spans, no control station, an empty file.
    """
    from minegeo.georef.crs import local_origin

    p = Path(path)
    text = read_file_text(p, encoding="utf-8-sig", max_bytes=MAX_TABLE_FILE_BYTES, what="stations file")

    def check_header(lineno: int, names: list[str], canon: list[str]) -> None:
        missing = [c for c in STATIONS_HEADER if c not in canon]
        extra = [n for n, c in zip(names, canon, strict=True) if c not in STATIONS_HEADER]
        if missing or extra or len(set(canon)) != len(canon):
            what = (f"lacks column(s) {', '.join(missing)}" if missing else
                    f"has unknown column(s) {', '.join(extra)}" if extra else "repeats a column")
            raise FileFormatError(p, f"line {lineno}: the stations header {what} "
                                     f"(found: {', '.join(names)}; expected {','.join(STATIONS_HEADER)})")

    table = read_table(p, text, _canon, check_header)
    if table is None:
        raise FileFormatError(p, "empty file (no header, no stations)")
    file_crs = table.crs
    ids: list[str] = []
    rows: list[list[float]] = []
    roles: list[StationRole] = []
    lines: list[int] = []
    for lineno, rec in table.rows:
        vals = {}
        for c in STATIONS_HEADER[1:-1]:
            limit = MAX_ABS_TIME if c.startswith("t_") else MAX_ABS_COORDINATE
            vals[c] = v = number(p, lineno, c, rec[c], limit)
            if c.startswith("sigma_"):
                check_sigma(p, lineno, c, rec[c], v, " (a station's a-priori standard deviation in metres)")
        sid = new_id(p, lineno, rec["id"], ids, lines)
        if vals["t_end"] < vals["t_start"]:
            raise FileFormatError(p, f"line {lineno}: station {sid}: t_end {vals['t_end']:g} s is before t_start "
                                     f"{vals['t_start']:g} s")
        role = rec["role"].strip().lower()
        if role not in (StationRole.CONTROL, StationRole.CHECK):
            raise FileFormatError(p, f"line {lineno}: station {sid}: role {rec['role']!r} is neither 'control' "
                                     "nor 'check'")
        ids.append(sid)
        roles.append(StationRole(role))
        rows.append([vals[c] for c in STATIONS_HEADER[1:-1]])
        lines.append(lineno)
    if not ids:
        raise FileFormatError(p, "no stations after the header")
    if crs is not None and file_crs is not None and crs != file_crs:
        raise FileFormatError(p, f"file says crs {file_crs!r} but crs={crs!r} was given")
    T = np.array(rows, dtype=np.float64)
    order = np.argsort(T[:, 0], kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        if T[b, 0] < T[a, 1]:
            first, second = (a, b) if lines[a] > lines[b] else (b, a)
            raise FileFormatError(
                p, f"line {lines[first]}: station {ids[first]} [{T[first, 0]:g}, {T[first, 1]:g}] s overlaps "
                   f"station {ids[second]} (line {lines[second]}) [{T[second, 0]:g}, {T[second, 1]:g}] s: the "
                   "scanner stands on one station at a time")
    if StationRole.CONTROL not in roles:
        raise FileFormatError(p, f"no station has role 'control' ({len(ids)} check station(s)): at least one "
                                 "control station is needed")
    enh = T[:, 2:5]
    origin = local_origin(enh)
    return Stations(ids=tuple(ids), t_start_s=T[:, 0], t_end_s=T[:, 1], enh_local=enh - origin, origin_enh=origin,
                    sigma_h_m=T[:, 5], sigma_v_m=T[:, 6], roles=tuple(roles), crs=file_crs or crs,
                    lines=tuple(lines), source=str(p))


def write_stations(path, stations: Stations) -> Path:
    """Write ``stations`` as a stations CSV, atomically (``# crs:`` line when known, the header
    :data:`STATIONS_HEADER`, numbers in Python's shortest exact ``repr`` of ``E N H``)."""
    from minegeo._provenance import atomic_write_text

    if not isinstance(stations, Stations):
        raise InputError(f"stations must be Stations, got {type(stations).__name__}")
    buf, w = table_writer(stations.crs)
    w.writerow(STATIONS_HEADER)
    enh = stations.enh
    for i, sid in enumerate(stations.ids):
        nums = [stations.t_start_s[i], stations.t_end_s[i], *enh[i], stations.sigma_h_m[i], stations.sigma_v_m[i]]
        w.writerow([sid, *(repr(float(v)) for v in nums), str(stations.roles[i])])
    return atomic_write_text(path, buf.getvalue())


def parse_station_offset(value) -> np.ndarray:
    """The ``--station-offset`` value: the surveyed point in the sensor frame (x y z, m).

    Parameters
    ----------
    value : str or sequence of 3 numbers
        ``"0 0 -1.25"`` (spaces or commas) or three numbers.

    Returns
    -------
    ndarray (3,) float64, m

    Raises
    ------
    InputError
        Not three finite numbers, or longer than :data:`MAX_STATION_OFFSET_M` (wrong units?).
    """
    toks = [t for t in re.split(r"[\s,;]+", value.strip()) if t] if isinstance(value, str) else list(value)
    try:
        off = np.array([float(t) for t in toks], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"--station-offset: expected three numbers x y z in metres, got {value!r}") from None
    if off.shape != (3,) or not np.all(np.isfinite(off)):
        raise InputError(f"--station-offset: expected three finite numbers x y z in metres, got {value!r}")
    if float(np.linalg.norm(off)) > MAX_STATION_OFFSET_M:
        raise InputError(f"--station-offset: {np.linalg.norm(off):g} m from the sensor origin is longer than "
                         f"{MAX_STATION_OFFSET_M:g} m (metres expected; wrong units?)")
    return off
