"""MAST beacon model: three flat panels in length ratio 2:3:1 bolted on a drift wall.

Simela, Marshall & Daneshmend, *Automated laser scanner 2D positioning and orienting
by method of triangulation for underground mine surveying* ("MAST"), section
"Beacon Design and Placement" and Figure 1.

Frames and conventions
----------------------
* Mine frame: ``x`` = Easting, ``y`` = Northing (metres). Azimuths are clockwise
  from grid north (+y), in degrees.
* A beacon seen from above is a polyline of four vertical panel edges
  ``V0, V1, V2, V3`` (the paper's four unique x-y coordinate pairs). Panel
  ``P1 = V0-V1``, ``P2 = V1-V2``, ``P3 = V2-V3``; ``V0`` and ``V3`` touch the wall.
* The *front* of the beacon (the side a scanner in the drift sees) is the side of
  the chord ``V0-V3`` on which ``V1`` and ``V2`` lie; it is derived from the
  coordinates, so the vertex order in the file can start at either wall end.
* The deflection angle ``theta_j`` is the signed turn between consecutive panel
  directions (``theta_1`` at ``V1``, ``theta_2`` at ``V2``).

The paper's Figure 1 is not reproduced in the text, so the design geometry used by
:class:`BeaconDesign` is our interpretation (documented in ``docs/mast.md``): P1
leaves the wall and reaches the beacon depth ``h`` at ``V1``; P2 is deflected by
``theta_1``; P3 returns to the wall, so ``theta_2`` follows from ``h`` (the paper:
"theta_2 ... is always calculated as a function of the depth of the beacon h").
The positioning itself only uses the surveyed vertex coordinates.
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo._provenance import atomic_write_text
from minegeo.errors import DegenerateGeometryError, FileFormatError, InputError
from minegeo.io.limits import MAX_ABS_COORDINATE, MAX_TABLE_FILE_BYTES, read_file_text
from minegeo.io.text import unterminated_last_line

__all__ = [
    "Beacon",
    "BeaconDesign",
    "place_beacon",
    "read_beacons_csv",
    "write_beacons_csv",
    "beacons_to_csv_text",
]

BEACONS_CSV_HEADER = ("beacon_id", "vertex", "x_m", "y_m")

log = logging.getLogger(__name__)


def _turn(d0: np.ndarray, d1: np.ndarray) -> float:
    """Signed turn angle (rad, counter-clockwise positive) from direction d0 to d1."""
    return math.atan2(d0[0] * d1[1] - d0[1] * d1[0], d0[0] * d1[0] + d0[1] * d1[1])


@dataclass(frozen=True)
class Beacon:
    """One surveyed beacon: four panel-edge vertices in the mine frame.

    Attributes
    ----------
    beacon_id : str
        Identifier used in results (e.g. ``"B1"``).
    vertices_m : (4, 2) float64
        ``V0..V3`` (x, y) in the mine frame, metres, in order along the beacon.
    """

    beacon_id: str
    vertices_m: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_m, dtype=np.float64)
        if v.shape != (4, 2):
            raise InputError(f"beacon {self.beacon_id}: expected 4 vertices (x, y), got shape {v.shape}")
        if not np.isfinite(v).all():
            raise InputError(f"beacon {self.beacon_id}: vertex coordinates contain NaN or inf")
        lengths = np.linalg.norm(np.diff(v, axis=0), axis=1)
        if np.any(lengths < 1e-3):
            raise DegenerateGeometryError(
                f"beacon {self.beacon_id}: a panel is shorter than 1 mm (repeated vertex); check the survey"
            )
        d = np.diff(v, axis=0) / lengths[:, None]
        turns = [_turn(d[0], d[1]), _turn(d[1], d[2])]
        if min(abs(t) for t in turns) < math.radians(2.0):
            raise DegenerateGeometryError(
                f"beacon {self.beacon_id}: panels are (nearly) collinear (deflection angles "
                f"{math.degrees(turns[0]):.1f} deg, {math.degrees(turns[1]):.1f} deg); a beacon needs "
                "deflected panels to be recognised and to fix the position"
            )
        object.__setattr__(self, "vertices_m", np.ascontiguousarray(v))

    @property
    def panel_lengths_m(self) -> np.ndarray:
        """Lengths of P1, P2, P3 (m)."""
        return np.linalg.norm(np.diff(self.vertices_m, axis=0), axis=1)

    @property
    def deflection_angles_deg(self) -> np.ndarray:
        """Signed deflections ``theta_1`` (at V1) and ``theta_2`` (at V2), degrees, CCW positive."""
        d = np.diff(self.vertices_m, axis=0)
        return np.degrees([_turn(d[0], d[1]), _turn(d[1], d[2])])

    @property
    def front_side(self) -> int:
        """+1 if the front (drift side) is on the left walking V0->V3, -1 if on the right."""
        v = self.vertices_m
        c = v[3] - v[0]
        mid = 0.5 * (v[1] + v[2]) - v[0]
        s = c[0] * mid[1] - c[1] * mid[0]
        return 1 if s > 0 else -1

    def panels(self) -> np.ndarray:
        """(3, 4) rows ``[ax, ay, bx, by]`` of P1, P2, P3 (V0->V3 order)."""
        v = self.vertices_m
        return np.hstack([v[:3], v[1:]])

    def scan_order_vertices(self) -> np.ndarray:
        """Vertices in the order a clockwise scan sweeps the front face (front on the right).

        A scanner sweeping clockwise (increasing bearing) traverses any face it sees
        with that face's front on its right-hand side, so ``V0->V3`` for a beacon with
        ``front_side == -1`` and ``V3->V0`` otherwise.
        """
        return self.vertices_m if self.front_side == -1 else self.vertices_m[::-1].copy()

    def scan_order_panel_index(self) -> list[int]:
        """Panel numbers (0=P1, 1=P2, 2=P3) in clockwise-scan order."""
        return [0, 1, 2] if self.front_side == -1 else [2, 1, 0]


@dataclass(frozen=True)
class BeaconDesign:
    """Design of a MAST beacon (our reading of the paper's Figure 1).

    Parameters
    ----------
    total_length_m : float
        ``p1 + p2 + p3`` (m). The paper tested 0.499-1.996 m.
    depth_m : float or None
        Beacon depth ``h`` (m): the height of V1 above the wall line. None gives
        ``0.2 * total_length_m`` (the paper's 0.100-0.400 m for 0.5-2.0 m beacons).
    ratio : tuple of 3 floats
        Panel length ratio ``p1:p2:p3`` (paper: 2:3:1).
    v2_depth_fraction : float
        Height of V2 above the wall as a fraction of ``p3``; sets ``theta_1``. Must
        be in (0, 1) so that P3 can return to the wall; ``theta_2`` then follows
        from the depth.
    """

    total_length_m: float = 1.0
    depth_m: float | None = None
    ratio: tuple = (2.0, 3.0, 1.0)
    v2_depth_fraction: float = 0.5

    def local_vertices(self) -> np.ndarray:
        """(4, 2) vertices in the beacon frame: ``u`` along the wall, ``w`` into the drift.

        ``V0 = (0, 0)``; ``V1`` at height ``h`` after ``p1``; ``V2`` at height
        ``v2_depth_fraction * p3`` after ``p2``; ``V3`` back on the wall (``w = 0``).
        """
        r = np.asarray(self.ratio, dtype=np.float64)
        if r.shape != (3,) or np.any(r <= 0):
            raise InputError(f"ratio must be three positive numbers, got {self.ratio}")
        L = float(self.total_length_m)
        if not (L > 0 and math.isfinite(L)):
            raise InputError(f"total_length_m must be > 0, got {self.total_length_m}")
        p = L * r / r.sum()
        h = 0.2 * L if self.depth_m is None else float(self.depth_m)
        f = float(self.v2_depth_fraction)
        if not (0.0 < f < 1.0):
            raise InputError(f"v2_depth_fraction must be in (0, 1), got {f}")
        if not (0.0 < h < p[0]):
            raise InputError(f"depth_m must be in (0, p1={p[0]:.3f} m), got {h}")
        w2 = f * p[2]
        s2 = (w2 - h) / p[1]
        if abs(s2) >= 1.0:
            raise InputError("beacon design impossible: P2 cannot reach the required height")
        v = np.zeros((4, 2))
        v[1] = [math.sqrt(p[0] ** 2 - h**2), h]
        v[2] = v[1] + [p[1] * math.sqrt(1.0 - s2**2), w2 - h]
        v[3] = v[2] + [math.sqrt(p[2] ** 2 - w2**2), -w2]
        return v


def place_beacon(
    design: BeaconDesign,
    beacon_id: str,
    centre_xy_m,
    wall_azimuth_deg: float,
    front: str,
) -> Beacon:
    """Place a beacon on a wall in the mine frame.

    Parameters
    ----------
    design : BeaconDesign
    beacon_id : str
    centre_xy_m : (2,) array_like
        Mine coordinates of the midpoint of the wall chord ``V0-V3`` (m).
    wall_azimuth_deg : float
        Azimuth of the direction ``V0 -> V3`` along the wall (degrees clockwise from north).
    front : {"left", "right"}
        Side of the wall (walking ``V0 -> V3``) on which the drift lies.
    """
    if front not in ("left", "right"):
        raise InputError(f"front must be 'left' or 'right', got {front!r}")
    loc = design.local_vertices()
    loc = loc - [0.5 * loc[3, 0], 0.0]
    a = math.radians(wall_azimuth_deg)
    u = np.array([math.sin(a), math.cos(a)])
    left = np.array([-u[1], u[0]])
    w = left if front == "left" else -left
    c = np.asarray(centre_xy_m, dtype=np.float64).reshape(2)
    return Beacon(beacon_id, c + loc[:, :1] * u + loc[:, 1:] * w)


def beacons_to_csv_text(beacons: list[Beacon], origin_xy_m=(0.0, 0.0)) -> str:
    """CSV text of beacons: header ``beacon_id,vertex,x_m,y_m``, one row per vertex."""
    o = np.asarray(origin_xy_m, dtype=np.float64)
    lines = [",".join(BEACONS_CSV_HEADER)]
    for b in beacons:
        for k, (x, y) in enumerate(b.vertices_m + o):
            lines.append(f"{b.beacon_id},{k},{x:.6f},{y:.6f}")
    return "\n".join(lines) + "\n"


def write_beacons_csv(path, beacons: list[Beacon], origin_xy_m=(0.0, 0.0)) -> Path:
    """Write ``beacons.csv`` atomically (format: :func:`read_beacons_csv`)."""
    return atomic_write_text(path, beacons_to_csv_text(beacons, origin_xy_m))


def read_beacons_csv(path) -> list[Beacon]:
    """Read surveyed beacon vertices.

    Format (UTF-8 CSV, header required, ``#`` comment lines allowed)::

        beacon_id,vertex,x_m,y_m
        B1,0,16.0123,6.4012
        B1,1,...

    One row per vertical panel edge; ``vertex`` is 0..3 in order along the beacon
    (V0 and V3 touch the wall). Coordinates are mine-frame Easting/Northing in metres.

    Raises
    ------
    FileFormatError
        Missing columns, non-numeric values, a coordinate beyond
        :data:`~minegeo.io.limits.MAX_ABS_COORDINATE`, a beacon without exactly vertices
        0-3, a file that is not a regular UTF-8 file of at most
        :data:`~minegeo.io.limits.MAX_TABLE_FILE_BYTES`. A last line without end-of-line
        (a file cut short?) is read and logged as a warning.
    """
    path = Path(path)
    text = read_file_text(path, encoding="utf-8", max_bytes=MAX_TABLE_FILE_BYTES, what="beacon CSV")
    rows = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise FileFormatError(path, "empty beacon file")
    verts: dict[str, dict[int, tuple[float, float]]] = {}
    try:
        reader = csv.DictReader(rows)
        cols = [c.strip() for c in (reader.fieldnames or [])]
        reader.fieldnames = cols
        missing = [c for c in BEACONS_CSV_HEADER if c not in cols]
        if missing:
            raise FileFormatError(
                path, f"missing column(s) {missing}; expected header {','.join(BEACONS_CSV_HEADER)}"
            )
        for line_no, row in enumerate(reader, start=2):
            try:
                bid = row["beacon_id"].strip()
                k = int(row["vertex"])
                xy = (float(row["x_m"]), float(row["y_m"]))
            except (TypeError, ValueError, AttributeError):
                raise FileFormatError(path, f"data row {line_no}: cannot read beacon_id/vertex/x_m/y_m") from None
            if not bid:
                raise FileFormatError(path, f"data row {line_no}: empty beacon_id")
            if not all(math.isfinite(c) for c in xy):
                raise FileFormatError(path, f"data row {line_no}: non-finite coordinate")
            if max(abs(c) for c in xy) > MAX_ABS_COORDINATE:
                raise FileFormatError(
                    path, f"data row {line_no}: coordinate beyond +-{MAX_ABS_COORDINATE:.0e} m (damaged file or "
                    "wrong units?)"
                )
            verts.setdefault(bid, {})
            if k in verts[bid]:
                raise FileFormatError(path, f"beacon {bid}: vertex {k} given twice")
            verts[bid][k] = xy
    except csv.Error as exc:
        raise FileFormatError(path, f"unreadable CSV ({exc})") from None
    out = []
    for bid, d in verts.items():
        if sorted(d) != [0, 1, 2, 3]:
            raise FileFormatError(path, f"beacon {bid}: needs vertices 0,1,2,3, got {sorted(d)}")
        out.append(Beacon(bid, np.array([d[k] for k in range(4)])))
    cut = unterminated_last_line(text)
    if cut is not None:
        log.warning("%s: the last line (%d: %r) has no end-of-line: the file may have been cut short; "
                    "check that its values are complete", path, cut[0], cut[1][:60])
    return out
