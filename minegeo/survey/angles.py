"""Angles for surveyors: DMS and gon parsing/formatting, grid azimuths, bearings, polar <-> rectangular.

Conventions (used by every module of :mod:`minegeo.survey`)
-----------------------------------------------------------
* Plane coordinates are ``(x, y) = (Easting, Northing)`` in metres.
* A **grid azimuth** is measured **clockwise from grid north** (the +y axis) and lies in
  ``[0, 2π)``: ``α = atan2(ΔE, ΔN)``. East is 90°, south 180°, west 270°.
* A **quadrant bearing** is ``N/S angle E/W`` with the angle in ``[0°, 90°]`` measured from the
  north or south end of the meridian, e.g. ``S 40°10'00" E`` = azimuth 139°50'00".
* A horizontal **angle** at station ``A`` from backsight ``B`` to foresight ``F`` is measured
  clockwise: ``α(A→F) − α(A→B)`` reduced to ``[0, 2π)``.
* Internally every angle is in radians (float64); gon (grads, 400 per circle) and DMS are
  parsed/formatted only at the edges.

References
----------
Ghilani, C. D. (2010). *Adjustment Computations: Spatial Data Analysis*, 5th ed., Wiley,
Ch. 14–15 (azimuth from coordinates, [Ghilani2010 Eq. 15.6] angle as a difference of azimuths).
"""

from __future__ import annotations

import math
import re

import numpy as np

from minegeo.errors import InputError

# parsing lives with the network readers (io may not import survey); re-exported here
from minegeo.io.angles import RHO_ARCSEC, parse_angle, parse_dms, wrap_2pi

__all__ = [
    "RHO_ARCSEC",
    "deg_to_rad",
    "rad_to_deg",
    "gon_to_rad",
    "rad_to_gon",
    "arcsec_to_rad",
    "rad_to_arcsec",
    "parse_dms",
    "parse_angle",
    "format_dms",
    "format_gon",
    "wrap_2pi",
    "wrap_pi",
    "azimuth",
    "azimuth_distance",
    "polar_to_rect",
    "azimuth_to_bearing",
    "bearing_to_azimuth",
]


_TWO_PI = 2.0 * math.pi


def deg_to_rad(deg):
    """Decimal degrees -> radians."""
    return np.deg2rad(deg)


def rad_to_deg(rad):
    """Radians -> decimal degrees."""
    return np.rad2deg(rad)


def gon_to_rad(gon):
    """Gon (grads, 400 gon per full circle) -> radians."""
    return (
        np.asarray(gon, dtype=np.float64) * (math.pi / 200.0)
        if np.ndim(gon)
        else float(gon) * (math.pi / 200.0)
    )


def rad_to_gon(rad):
    """Radians -> gon."""
    return (
        np.asarray(rad, dtype=np.float64) * (200.0 / math.pi)
        if np.ndim(rad)
        else float(rad) * (200.0 / math.pi)
    )


def arcsec_to_rad(sec):
    """Arc-seconds -> radians."""
    return np.asarray(sec, dtype=np.float64) / RHO_ARCSEC if np.ndim(sec) else float(sec) / RHO_ARCSEC


def rad_to_arcsec(rad):
    """Radians -> arc-seconds."""
    return np.asarray(rad, dtype=np.float64) * RHO_ARCSEC if np.ndim(rad) else float(rad) * RHO_ARCSEC


# degrees, then optional minutes, then optional seconds; separators ° d - : ' ′ m " ″ s or spaces
def format_dms(angle_rad: float, decimals: int = 1, signed: bool = False, width_deg: int = 0) -> str:
    """Format an angle (radians) as ``DDD°MM'SS.s"``, carrying rounding correctly (59.96″ -> next minute).

    Parameters
    ----------
    angle_rad : float
        Angle in radians.
    decimals : int
        Decimals of the arc-seconds field.
    signed : bool
        Always write the sign (``+``/``-``); otherwise only ``-`` for negative angles.
    width_deg : int
        Zero-pad the degrees to this width (e.g. 3 for azimuths ``005°…``).

    Examples
    --------
    >>> import math
    >>> format_dms(math.radians(355.1674444444))
    '355°10\\'02.8"'
    """
    if not math.isfinite(angle_rad):
        return "nan"
    total = abs(angle_rad) * RHO_ARCSEC
    scale = 10**decimals
    units = round(total * scale)  # integer count of the last printed digit: exact carry
    sec_units = units % (60 * scale)
    minutes_total = units // (60 * scale)
    deg, mins = divmod(minutes_total, 60)
    sec = sec_units / scale
    sign = "-" if angle_rad < 0 and units != 0 else ("+" if signed else "")
    sec_txt = f"{sec:0{3 + decimals if decimals else 2}.{decimals}f}"
    return f"{sign}{deg:0{width_deg}d}°{mins:02d}'{sec_txt}\""


def format_gon(angle_rad: float, decimals: int = 4) -> str:
    """Format an angle (radians) in gon with ``decimals`` decimals, e.g. ``'33.8806 gon'``."""
    return f"{rad_to_gon(angle_rad):.{decimals}f} gon"


def wrap_pi(a):
    """Reduce angle(s) to ``[-π, π)`` (used for residuals of directions and angles)."""
    r = np.mod(np.asarray(a, dtype=np.float64) + math.pi, _TWO_PI) - math.pi
    return float(r) if np.ndim(r) == 0 else r


def azimuth(de, dn):
    """Grid azimuth (radians, clockwise from north, in ``[0, 2π)``) of the vector ``(ΔE, ΔN)``.

    ``α = atan2(ΔE, ΔN)`` handles all four quadrants (Ghilani 2010, Sec. 15.2). A zero vector
    has no azimuth and raises :class:`InputError`.
    """
    de = np.asarray(de, dtype=np.float64)
    dn = np.asarray(dn, dtype=np.float64)
    if np.any((de == 0.0) & (dn == 0.0)):
        raise InputError("azimuth of a zero-length line is undefined (the two points coincide)")
    a = wrap_2pi(np.arctan2(de, dn))
    return float(a) if np.ndim(a) == 0 else a


def azimuth_distance(e0, n0, e1, n1) -> tuple[float, float]:
    """Inverse problem: grid azimuth (rad) and horizontal distance (m) from point 0 to point 1."""
    de, dn = float(e1) - float(e0), float(n1) - float(n0)
    return azimuth(de, dn), math.hypot(de, dn)


def polar_to_rect(e0, n0, azimuth_rad, distance_m) -> tuple[float, float]:
    """Forward problem: coordinates of the point at ``distance_m`` along grid azimuth ``azimuth_rad``.

    ``E = E0 + s·sin α``, ``N = N0 + s·cos α``.
    """
    return float(e0) + distance_m * math.sin(azimuth_rad), float(n0) + distance_m * math.cos(azimuth_rad)


def azimuth_to_bearing(azimuth_rad: float, decimals: int = 1) -> str:
    """Quadrant bearing text of a grid azimuth, e.g. ``2.4435 rad -> 'S 40°00'00.0" E'``."""
    a = wrap_2pi(azimuth_rad)
    deg = math.degrees(a)
    if deg <= 90.0:
        ns, ew, ang = "N", "E", a
    elif deg <= 180.0:
        ns, ew, ang = "S", "E", math.pi - a
    elif deg <= 270.0:
        ns, ew, ang = "S", "W", a - math.pi
    else:
        ns, ew, ang = "N", "W", _TWO_PI - a
    return f"{ns} {format_dms(ang, decimals)} {ew}"


_BEARING_RE = re.compile(r"^\s*([NSns])\s*(.+?)\s*([EWew])\s*$")


def bearing_to_azimuth(text: str) -> float:
    """Parse a quadrant bearing such as ``S 40°10'00" E`` or ``N45-30-00W`` and return the azimuth (rad).

    Raises
    ------
    InputError
        Not a bearing, or the angle exceeds 90°.
    """
    m = _BEARING_RE.match(text or "")
    if not m:
        raise InputError(f"cannot read {text!r} as a quadrant bearing (expected e.g. N 45°30'00\" E)")
    ang = math.radians(parse_dms(m.group(2)))
    if ang < 0 or ang > math.pi / 2 + 1e-15:
        raise InputError(f"bearing angle must be between 0° and 90° in {text!r}")
    ns, ew = m.group(1).upper(), m.group(3).upper()
    if ns == "N" and ew == "E":
        return wrap_2pi(ang)
    if ns == "S" and ew == "E":
        return wrap_2pi(math.pi - ang)
    if ns == "S" and ew == "W":
        return wrap_2pi(math.pi + ang)
    return wrap_2pi(_TWO_PI - ang)
