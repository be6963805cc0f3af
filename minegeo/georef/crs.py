"""Coordinate reference systems for georeferencing: validation through pyproj and a local origin.

A mine map is georeferenced into a **projected** CRS whose axes are in **metres** (e.g.
``EPSG:5186`` KGD2002 / Central Belt 2010, the Korean TM grid used by Baek et al. 2022,
Sec. 2.1; or a UTM zone). Geographic CRSs (degrees) and CRSs in feet are refused with a
:class:`~minegeo.errors.CRSError` that says what to use instead, because a least-squares
similarity transformation between a metric map and degrees (or feet) would be meaningless
(or silently scaled). Geocentric Cartesian CRSs (metres, e.g. ``EPSG:4978``) are accepted
only when asked for explicitly (datum-transformation checks such as SK-42 -> SK-95).

Coordinates in projected CRSs are large (10⁵–10⁷ m). float64 has a spacing of 9.3e-10 m at
5·10⁶ m, so every computation here is done on coordinates **relative to a recorded local
origin**: a CRS point rounded to a whole multiple of ``step_m`` (default 1000 m) near the
data. Subtracting such an origin is exact in float64 (Sterbenz lemma: ``x − o`` is exact
when ``o/2 ≤ x ≤ 2o``), so reduced coordinates carry no rounding error of their own.

Axis order: minegeo always stores and reads CRS coordinates as (Easting, Northing, Height),
whatever axis order the EPSG definition lists (EPSG:5186 lists northing first);
:func:`crs_info` records the official axis order so that reports can say so.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from minegeo.errors import CRSError, InputError

log = logging.getLogger(__name__)

__all__ = ["CRSInfo", "validate_crs", "crs_info", "local_origin", "grid_scale_factors", "outside_area_of_use", "same_crs"]

_METRE_NAMES = ("metre", "meter", "m")


def _load(crs):
    try:
        from pyproj import CRS
        from pyproj.exceptions import CRSError as ProjCRSError
    except ImportError as exc:  # pragma: no cover - pyproj is a runtime dependency
        raise CRSError(f"pyproj is needed to interpret coordinate reference systems ({exc})") from None
    if isinstance(crs, CRS):
        return crs
    if crs is None or (isinstance(crs, str) and not crs.strip()):
        raise CRSError(
            "no coordinate reference system given: name the mine grid, e.g. --crs EPSG:5186 "
            "(or a '# crs: EPSG:5186' line in the control-point file)"
        )
    try:
        return CRS.from_user_input(crs.strip() if isinstance(crs, str) else crs)
    except ProjCRSError as exc:
        raise CRSError(
            f"unknown coordinate reference system {crs!r}: pyproj says {exc}. "
            "Give an EPSG code such as EPSG:5186 (Korea Central Belt 2010) or EPSG:32652 (UTM 52N)"
        ) from None


def _horizontal(c):
    """The horizontal component of a compound CRS (or the CRS itself)."""
    if c.is_compound:
        subs = list(c.sub_crs_list)
        return subs[0] if subs else c
    return c


def validate_crs(crs, *, allow_geocentric: bool = False):
    """Parse ``crs`` with pyproj and check it is a projected CRS with metre axes.

    Parameters
    ----------
    crs : str or pyproj.CRS
        ``"EPSG:5186"``, ``"EPSG:5186+5711"`` (compound projected + vertical), WKT, a PROJ
        string, or a :class:`pyproj.CRS`.
    allow_geocentric : bool
        Also accept a geocentric Cartesian CRS in metres (for datum checks; a mine map is
        normally georeferenced into a projected grid).

    Returns
    -------
    pyproj.CRS

    Raises
    ------
    CRSError
        Unknown code (pyproj's message is included), a geographic CRS (degrees: "use the
        projected grid of the mine, e.g. a UTM zone"), or axes not in metres (e.g. US survey
        feet: "convert the control coordinates to metres and use the metric CRS").
    """
    c = _load(crs)
    h = _horizontal(c)
    name = c.name
    if h.is_geographic or c.is_geographic:
        raise CRSError(
            f"{crs} ({name}) is a geographic CRS with coordinates in degrees; georeferencing needs a "
            "projected grid in metres (e.g. the mine's TM grid such as EPSG:5186, or a UTM zone such "
            "as EPSG:32652)"
        )
    if c.is_geocentric and not allow_geocentric:
        raise CRSError(
            f"{crs} ({name}) is a geocentric (Earth-centred X, Y, Z) CRS; a mine map is georeferenced "
            "into a projected grid (Easting, Northing, height), e.g. EPSG:5186 or a UTM zone"
        )
    if not (h.is_projected or (allow_geocentric and c.is_geocentric)):
        raise CRSError(
            f"{crs} ({name}) is not a projected CRS (type {c.type_name!r}); give the projected grid of "
            "the mine, e.g. EPSG:5186"
        )
    for ax in c.axis_info:
        unit = (ax.unit_name or "").lower()
        if unit not in _METRE_NAMES or abs(float(ax.unit_conversion_factor) - 1.0) > 1e-12:
            raise CRSError(
                f"{crs} ({name}) has axis {ax.name or ax.abbrev!r} in {ax.unit_name!r}; minegeo works in "
                "metres: convert the control coordinates to metres and use the metric CRS of the same "
                "grid (maps are scanned in metres)"
            )
    return c


@dataclass(frozen=True)
class CRSInfo:
    """Facts about the CRS recorded with every georeferencing result.

    Attributes
    ----------
    user_input : str
        What the user gave (``"EPSG:5186"``).
    name : str
        pyproj name (``"KGD2002 / Central Belt 2010"``).
    epsg : int or None
        EPSG code if pyproj can identify one (None for compound/custom CRSs).
    kind : str
        ``"projected"``, ``"compound"`` or ``"geocentric"``.
    units : str
        Axis unit (always metres after :func:`validate_crs`).
    axis_order : str
        Official axis order, e.g. ``"north, east"`` (minegeo files always use E, N, H).
    area_of_use : str or None
        Name of the area of use.
    area_bounds_deg : tuple or None
        (west, south, east, north) longitude/latitude bounds of the area of use.
    """

    user_input: str
    name: str
    epsg: int | None
    kind: str
    units: str
    axis_order: str
    area_of_use: str | None
    area_bounds_deg: tuple | None

    def as_dict(self) -> dict:
        return {
            "user_input": self.user_input,
            "name": self.name,
            "epsg": self.epsg,
            "kind": self.kind,
            "units": self.units,
            "axis_order": self.axis_order,
            "area_of_use": self.area_of_use,
            "area_bounds_deg": list(self.area_bounds_deg) if self.area_bounds_deg else None,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CRSInfo:
        b = d.get("area_bounds_deg")
        return cls(
            user_input=str(d.get("user_input", "")),
            name=str(d.get("name", "")),
            epsg=None if d.get("epsg") is None else int(d["epsg"]),
            kind=str(d.get("kind", "")),
            units=str(d.get("units", "metre")),
            axis_order=str(d.get("axis_order", "")),
            area_of_use=d.get("area_of_use"),
            area_bounds_deg=None if b is None else tuple(float(v) for v in b),
        )


def crs_info(crs, *, allow_geocentric: bool = False) -> CRSInfo:
    """Validate ``crs`` (:func:`validate_crs`) and collect its name, EPSG code, units and area of use."""
    c = validate_crs(crs, allow_geocentric=allow_geocentric)
    h = _horizontal(c)
    try:
        epsg = c.to_epsg()
    except Exception:  # pyproj may fail to identify custom definitions
        epsg = None
    area = c.area_of_use or h.area_of_use
    kind = "compound" if c.is_compound else ("geocentric" if c.is_geocentric else "projected")
    units = ", ".join(sorted({ax.unit_name for ax in c.axis_info})) or "metre"
    return CRSInfo(
        user_input=crs if isinstance(crs, str) else c.to_string(),
        name=c.name,
        epsg=epsg,
        kind=kind,
        units=units,
        axis_order=", ".join(ax.direction for ax in c.axis_info),
        area_of_use=None if area is None else area.name,
        area_bounds_deg=None if area is None else tuple(float(v) for v in area.bounds),
    )


def local_origin(points, step_m: float = 1000.0) -> np.ndarray:
    """A recorded local origin: the centroid of ``points`` rounded to a multiple of ``step_m``.

    Parameters
    ----------
    points : array_like (n, 3)
        CRS coordinates (m).
    step_m : float
        Rounding step (m). Whole kilometres keep the origin readable; any value whose
        multiples are exactly representable works.

    Returns
    -------
    ndarray (3,)
        ``round(mean(points) / step_m) · step_m``. Subtracting it from coordinates within a
        factor 2 of it is exact in float64.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0 or not np.isfinite(p).all():
        raise InputError("local_origin needs finite points")
    if not (math.isfinite(step_m) and step_m > 0):
        raise InputError(f"step_m must be > 0, got {step_m!r}")
    # the mean of large numbers is rounded, but it is only used to choose a round number
    return np.round(p.mean(axis=0) / step_m) * step_m


def grid_scale_factors(crs, east_m: float, north_m: float, height_m: float) -> dict | None:
    """Point scale factor of the projection and the height (elevation) factor at a CRS point.

    The distances of a map scanned underground are true (ellipsoidal-surface-free) lengths; grid
    coordinates are scaled by the projection's point scale factor ``k`` and reduced to the
    ellipsoid by ``R/(R + h)``. The *combined factor* ``k·R/(R + h)`` (mean Earth radius
    R = 6 371 000 m; ``h`` ≈ the CRS height, geoid separation ignored) is the scale a 7-parameter
    fit is expected to find; a rigid (6-parameter) fit leaves ``(combined − 1)·distance`` in the
    residuals. Returns None when pyproj cannot compute the factors (e.g. geocentric CRS).
    """
    try:
        from pyproj import Proj, Transformer

        c = validate_crs(crs, allow_geocentric=True)
        if c.is_geocentric:
            return None
        h = _horizontal(c)
        tr = Transformer.from_crs(h, h.geodetic_crs, always_xy=True)
        lon, lat = tr.transform(east_m, north_m)
        if not (math.isfinite(lon) and math.isfinite(lat)):
            return None
        f = Proj(h).get_factors(lon, lat)
        k = float(f.meridional_scale) if abs(f.meridional_scale - f.parallel_scale) < 1e-9 else float(
            math.sqrt(f.areal_scale)
        )
        r_earth = 6_371_000.0
        e = r_earth / (r_earth + float(height_m))
        return {
            "lon_deg": float(lon),
            "lat_deg": float(lat),
            "point_scale_factor": k,
            "height_factor": e,
            "combined_factor": k * e,
            "combined_ppm": (k * e - 1.0) * 1e6,
        }
    except Exception as exc:  # informative only; never fail georeferencing on it
        log.debug("grid scale factor not available: %s", exc)
        return None


def outside_area_of_use(crs, east_north, margin_deg: float = 1.0) -> str | None:
    """Return a message if CRS points lie outside the CRS's area of use, else None.

    Converts (E, N) to longitude/latitude with pyproj and compares with the area-of-use bounds
    widened by ``margin_deg``. Coordinates of the wrong zone/grid (a wrong EPSG code) usually
    land far outside, or do not invert at all.
    """
    try:
        from pyproj import Transformer

        c = validate_crs(crs, allow_geocentric=True)
        if c.is_geocentric:
            return None
        h = _horizontal(c)
        area = c.area_of_use or h.area_of_use
        if area is None:
            return None
        en = np.asarray(east_north, dtype=np.float64).reshape(-1, 2)
        tr = Transformer.from_crs(h, h.geodetic_crs, always_xy=True)
        lon, lat = tr.transform(en[:, 0], en[:, 1])
        lon = np.atleast_1d(np.asarray(lon, dtype=np.float64))
        lat = np.atleast_1d(np.asarray(lat, dtype=np.float64))
    except Exception as exc:  # informative only
        log.debug("area-of-use check not available: %s", exc)
        return None
    w, s, e, n = area.bounds
    ok = np.isfinite(lon) & np.isfinite(lat)
    if e < w:  # area crossing the antimeridian
        inside_lon = (lon >= w - margin_deg) | (lon <= e + margin_deg)
    else:
        inside_lon = (lon >= w - margin_deg) & (lon <= e + margin_deg)
    inside = ok & inside_lon & (lat >= s - margin_deg) & (lat <= n + margin_deg)
    if inside.all():
        return None
    k = int(np.flatnonzero(~inside)[0])
    where = f"lon {lon[k]:.4f}°, lat {lat[k]:.4f}°" if ok[k] else "no valid longitude/latitude"
    return (
        f"{int((~inside).sum())} of {inside.size} control point(s) lie outside the area of use of "
        f"{c.name} ({area.name}; first: E {en[k, 0]:.3f}, N {en[k, 1]:.3f} -> {where}): check the EPSG "
        "code, the zone, and that the columns are Easting then Northing"
    )


def same_crs(a: str, b: str) -> bool:
    """True when the CRS names ``a`` and ``b`` are the same text (case-insensitive) or pyproj finds
    them equal (e.g. ``"EPSG:5186"`` and its WKT); False when either cannot be interpreted."""
    if a.strip().upper() == b.strip().upper():
        return True
    try:
        from pyproj import CRS

        return CRS.from_user_input(a) == CRS.from_user_input(b)
    except Exception:
        return False
