"""Survey networks (1D levelling, 2D horizontal, 3D): reading, observation equations, adjustment.

A :class:`Network` holds points with approximate coordinates, a datum (fixed coordinates, a
free network with minimum-trace constraints, or a "dynamic" datum with a-priori coordinate
precision) and observations. :func:`adjust_network` builds the observation equations and
runs the Gauss–Markov adjustment of :mod:`minegeo.survey.lsq`.

Conventions
-----------
* Coordinates ``x`` = Easting, ``y`` = Northing, ``z``/``h`` = height, metres.
* Grid azimuth ``α(i→j) = atan2(x_j − x_i, y_j − y_i)`` clockwise from north.
* Direction ``r_ij = α(i→j) − o_k`` with one orientation unknown ``o_k`` per direction set
  (consecutive directions observed at the same station).
* Angle at station ``i`` from backsight ``b`` to foresight ``f``: ``α(i→f) − α(i→b)``.
* Zenith angle ``z = atan2(hd, Δh)``, vertical angle ``v = π/2 − z``, with
  ``Δh = (h_j + h_t) − (h_i + h_i_instr)`` (instrument and target heights), horizontal
  distance ``hd``; no earth curvature or refraction (local networks).
* Levelled height difference ``Δh = h_j − h_i`` with ``σ = σ_km·sqrt(L/1 km)``.
* GNSS baseline ``(Δx, Δy, Δz) = X_j − X_i`` with a 3×3 covariance.

All observation precisions are *absolute* a-priori standard deviations; the a-priori variance
factor is 1 (``W = Σll⁻¹``). The ``[Sigma0]`` line of a Krumm file only rescales weights and is
recorded, not used: adjusted coordinates and a-posteriori standard deviations do not depend on
it. The χ² global test therefore tests ``vᵀΣll⁻¹v`` against χ²(r).

Text format
-----------
The Krumm "Geodetic Network Adjustment Examples" format (see ``docs/survey.md`` and the README of
``shared/data/krumm_gama_adjustment_examples``): sections ``[Coordinates]``, ``[Datum]``,
``[Sigma0]``, ``[Distances]``, ``[HorizontalDistances]``, ``[SpatialDistances]``,
``[Directions]``, ``[ApproximateOrientation]``, ``[Angles]``/``[Winkel]``, ``[Azimuth]``,
``[GridBearings]``, ``[ZenithAngles]``, ``[VerticalAngles]``, ``[LevelledHeightDifferences]``,
``[TrigonometricHeightDifferences]``, ``[3DBaseline]``/``[3DBasislinie]``, ``[Restrictions]``.
Angle sections are in gon unless the header says ``dms``; ``s`` means the standard deviations
are in arc-seconds. A missing standard deviation repeats the previous line's. ``%`` starts a
comment. A JSON equivalent is read by :func:`read_network` for ``.json`` files.
"""

from __future__ import annotations

import ast
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from minegeo.errors import DegenerateGeometryError, FileFormatError, InputError, TooFewPointsError
from minegeo.io._json import load_json_text
from minegeo.io._limits import (
    MAX_ABS_COORDINATE,
    MAX_TABLE_FILE_BYTES,
    MIN_SIGMA_M,
    read_file_bytes,
    read_file_text,
)
from minegeo.survey.angles import RHO_ARCSEC, parse_angle, wrap_2pi, wrap_pi
from minegeo.survey.ellipse import ErrorEllipse, ellipse_scale, point_ellipses, relative_ellipse
from minegeo.survey.lsq import LSQOptions, LSQResult, adjust

__all__ = [
    "Observation",
    "Datum",
    "Network",
    "NetworkResult",
    "PointResult",
    "ObservationResult",
    "parse_krumm",
    "read_network",
    "network_from_dict",
    "adjust_network",
    "read_adj",
]

log = logging.getLogger(__name__)

#: Observation kinds and their units (value, residual display)
KINDS = {
    "distance": "horizontal distance (m)",
    "spatial_distance": "slope distance (m)",
    "direction": "direction (rad)",
    "angle": "horizontal angle (rad)",
    "azimuth": "grid azimuth (rad)",
    "zenith_angle": "zenith angle (rad)",
    "vertical_angle": "vertical angle (rad)",
    "height_difference": "levelled height difference (m)",
    "trig_height_difference": "trigonometric height difference (m)",
    "baseline": "3D coordinate difference (m)",
}
_ANGULAR = {"direction", "angle", "azimuth", "zenith_angle", "vertical_angle"}
_DIM3 = {"spatial_distance", "zenith_angle", "vertical_angle", "baseline"}
_DIM2 = {"distance", "direction", "angle", "azimuth"}
_DIM1 = {"height_difference", "trig_height_difference"}


@dataclass(frozen=True)
class Observation:
    """One observation.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    station, target : str
        From/at point and to point (for an angle: at ``station``, from ``backsight`` to ``target``).
    value : float or ndarray (3,)
        Metres or radians (baseline: 3 components).
    sigma : float or ndarray (3, 3)
        Standard deviation (m or rad); for a baseline the 3×3 covariance (m²).
    backsight : str, optional
        Backsight point of an angle.
    set_id : int, optional
        Direction set (one orientation unknown per set).
    hi, ht : float
        Instrument and target heights (m) for 3D observations.
    unit : str
        Unit the value was given in ("m", "gon", "dms", "rad", "deg") — for reports.
    line : int
        Source line number (0 if not from a file).
    """

    kind: str
    station: str
    target: str
    value: object
    sigma: object
    backsight: str | None = None
    set_id: int | None = None
    hi: float = 0.0
    ht: float = 0.0
    unit: str = "m"
    line: int = 0

    @property
    def label(self) -> str:
        if self.kind == "angle":
            return f"{self.backsight}-{self.station}-{self.target}"
        return f"{self.station}-{self.target}"


@dataclass(frozen=True)
class Datum:
    """Datum definition.

    kind : "fix" | "free" | "dyn"
    coords : tuple of (point, axis) — fixed coordinates ("fix"), coordinates whose partial
        trace is minimised ("free"), or coordinates with a-priori covariance ("dyn").
    cov : ndarray, optional — covariance (m²) of the "dyn" coordinates in ``coords`` order.
    """

    kind: str = "fix"
    coords: tuple = ()
    cov: np.ndarray | None = None


@dataclass
class Network:
    """A survey network: approximate coordinates, datum, observations.

    Attributes
    ----------
    points : dict[str, dict[str, float]]
        Approximate (or fixed) coordinates ``{"x", "y", "z"}`` per point (keys present as given).
    datum : Datum
    observations : list[Observation]
    dim : int
        1 (heights), 2 (plane) or 3 (3D).
    known_azimuths : dict[(str, str), float]
        Errorless azimuths (rad) to points without coordinates (traverse connections).
    restrictions : list[str]
        Non-linear restrictions ``g(x) = 0`` in terms of ``x<pt>``, ``y<pt>``, ``z<pt>``.
    sigma0_text : str
        The ``[Sigma0]`` line as given (informational, see module notes).
    name, description, source : str
    """

    points: dict
    datum: Datum
    observations: list
    dim: int
    known_azimuths: dict = field(default_factory=dict)
    restrictions: list = field(default_factory=list)
    sigma0_text: str = ""
    name: str = ""
    description: str = ""
    source: str = ""

    def axes(self) -> tuple:
        return {1: ("z",), 2: ("x", "y"), 3: ("x", "y", "z")}[self.dim]


# --------------------------------------------------------------------------------------------
# Krumm text format
# --------------------------------------------------------------------------------------------
_SECTION_RE = re.compile(r"^\s*\[([^\]]+)\]\s*$")
# '#' starts a comment at the line start or after white space (point names such as Six#Mile keep it)
_HASH_COMMENT_RE = re.compile(r"(?:^|\s)#")
_UNSUPPORTED = {
    "ellipsoid": "geographic coordinates on an ellipsoid (map projection) are not supported",
    "approximatescale": "a scale unknown is not supported",
    "approximateadditiveconstant": "an additive-constant unknown is not supported",
    "correlateddistances": "correlated distances are not supported",
    "positionangles": "position angles are not supported",
}
_SECTION_KIND = {
    "distances": "distance",
    "horizontaldistances": "distance",
    "spatialdistances": "spatial_distance",
    "directions": "direction",
    "direction": "direction",
    "angles": "angle",
    "winkel": "angle",
    "azimuth": "azimuth",
    "gridbearings": "azimuth",
    "zenithangles": "zenith_angle",
    "verticalangles": "vertical_angle",
    "levelledheightdifferences": "height_difference",
    "trigonometricheightdifferences": "trig_height_difference",
    "3dbaseline": "baseline",
    "3dbasislinie": "baseline",
}


#: most tokens of one observation line per kind (a longer line is damaged, not silently cut)
_MAX_TOKENS = {"angle": 5, "distance": 5, "height_difference": 5, "baseline": 14}
_LAYOUT = {
    "angle": "at from to value [sigma]",
    "distance": "from to value [sigma_c [sigma_s]]",
    "height_difference": "from to dh length_m [sigma_km]",
    "baseline": "from to dx dy dz [3, 6 or 9 precision values]",
}


def _num(tok: str, path, lineno: int, what: str) -> float:
    """A finite number within ``+-MAX_ABS_COORDINATE`` (NaN, inf, 1e308 are damaged values)."""
    try:
        v = float(tok.rstrip('"″'))
    except ValueError:
        raise FileFormatError(path, f"line {lineno}: cannot read {what} {tok[:40]!r} as a number") from None
    if not math.isfinite(v) or abs(v) > MAX_ABS_COORDINATE:
        raise FileFormatError(
            path, f"line {lineno}: {what} {tok[:40]!r} is not a finite number within +-{MAX_ABS_COORDINATE:.0e}"
        )
    return v


#: largest absolute angle (rad) read from a network file: a few turns are normal
_MAX_ANGLE_RAD = 1e6


def _angle(tok: str, unit: str, path, lineno: int) -> float:
    """An angle token in ``unit`` -> radians; unreadable or non-finite values name the line."""
    try:
        v = parse_angle(tok, unit)
    except (InputError, ValueError, OverflowError) as exc:
        raise FileFormatError(path, f"line {lineno}: {exc}") from None
    if not (math.isfinite(v) and abs(v) <= _MAX_ANGLE_RAD):
        raise FileFormatError(path, f"line {lineno}: angle {tok[:40]!r} is not a finite angle")
    return v


def _angle_units(opts: list[str]) -> tuple[str, str]:
    """(value unit, sigma unit) from section options like ['dms', 's']."""
    o = [x.strip().lower() for x in opts]
    vunit = "dms" if "dms" in o else ("deg" if "deg" in o else "gon")
    if "s" in o:
        sunit = "arcsec"
    elif "mgon" in o:
        sunit = "mgon"
    elif vunit == "dms":
        sunit = "arcsec"
    else:
        sunit = vunit
    return vunit, sunit


def _sigma_angle(tok: str, sunit: str, path, lineno) -> float:
    if tok.endswith('"') or tok.endswith("″"):
        return _num(tok, path, lineno, "standard deviation") / RHO_ARCSEC
    v = _num(tok, path, lineno, "standard deviation")
    return _angle(v, sunit, path, lineno)


def _check_precisions(net: Network) -> Network:
    """Refuse a-priori precisions so small that their weights overflow float64.

    A positive standard deviation below :data:`~minegeo.io._limits.MIN_SIGMA_M` (m or rad;
    1e-9 rad is 0.0002") is a typing or unit mistake; zero and negative values are left to the
    adjustment, which names the observation.
    """
    for i, o in enumerate(net.observations):
        where = f"line {o.line}" if o.line else f"observation {i}"
        if o.kind == "baseline":
            d = np.diag(np.asarray(o.sigma, dtype=np.float64))
            tiny = (d > 0) & (d < MIN_SIGMA_M**2)
        else:
            tiny = np.asarray(0.0 < float(o.sigma) < MIN_SIGMA_M)
        if np.any(tiny):
            raise FileFormatError(
                net.source, f"{where}: {o.kind} {o.label} has an a-priori precision below {MIN_SIGMA_M:g} (m or rad): "
                "a unit mistake? Its weight would overflow"
            )
    cov = np.zeros((0, 0)) if net.datum.cov is None else np.asarray(net.datum.cov, dtype=np.float64)
    d = np.diag(cov) if cov.ndim == 2 else np.zeros(0)
    if np.any((d > 0) & (d < MIN_SIGMA_M**2)):
        raise FileFormatError(net.source, f"[Datum] dyn: an a-priori sigma below {MIN_SIGMA_M:g} m (a unit mistake?)")
    return net


def parse_krumm(text: str, source: str = "<text>") -> Network:
    """Parse a network in the Krumm text format (see module docstring).

    Raises
    ------
    FileFormatError
        Unknown or unsupported section, malformed line (the line number is given).
    """
    path = source
    sections: list[tuple[str, list[str], list[tuple[int, str]]]] = []
    cur = None
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = _HASH_COMMENT_RE.split(raw.split("%", 1)[0], maxsplit=1)[0].rstrip()
        m = _SECTION_RE.match(line)
        if m:
            parts = [p.strip() for p in m.group(1).split(",")]
            cur = (parts[0], parts[1:], [])
            sections.append(cur)
            continue
        if not line.strip():
            continue
        if cur is None:
            raise FileFormatError(path, f"line {lineno}: data before the first [Section] header")
        cur[2].append((lineno, line))

    points: dict[str, dict[str, float]] = {}
    obs: list[Observation] = []
    known_az: dict = {}
    restrictions: list[str] = []
    datum_lines: list[tuple[int, str]] = []
    sigma0_text = ""
    name = ""
    description_lines: list[str] = []
    set_counter = 0
    raw_kinds: set[str] = set()

    for sname, opts, lines in sections:
        key = sname.lower()
        if key in ("project",):
            name = " ".join(t for _, t in lines).strip()
            continue
        if key in ("source", "quelle"):
            description_lines.extend(t.strip() for _, t in lines)
            continue
        if key == "graphics":
            continue
        if key in _UNSUPPORTED:
            raise FileFormatError(path, f"section [{sname}]: {_UNSUPPORTED[key]}")
        if key == "coordinates":
            if any(o.lower().startswith(("bdms", "ldms", "b", "l")) for o in opts):
                raise FileFormatError(
                    path, f"section [{sname},{','.join(opts)}]: geographic coordinates are not supported"
                )
            for lineno, t in lines:
                tok = t.split()
                vals = [_num(v, path, lineno, "coordinate") for v in tok[1:]]
                pid = tok[0]
                if pid in points:
                    raise FileFormatError(path, f"line {lineno}: point {pid!r} listed twice in [Coordinates]")
                if len(vals) == 1:
                    points[pid] = {"z": vals[0]}
                elif len(vals) == 2:
                    points[pid] = {"x": vals[0], "y": vals[1]}
                elif len(vals) == 3:
                    points[pid] = {"x": vals[0], "y": vals[1], "z": vals[2]}
                else:
                    raise FileFormatError(path, f"line {lineno}: expected 'id [x y] [H]', got {t.strip()!r}")
            continue
        if key == "datum":
            datum_lines.extend(lines)
            continue
        if key == "sigma0":
            sigma0_text = " ".join(t.strip() for _, t in lines)
            continue
        if key == "approximateorientation":
            continue  # orientations are computed from the approximate coordinates
        if key == "restrictions":
            restrictions.extend(t.strip() for _, t in lines)
            continue
        if key not in _SECTION_KIND:
            raise FileFormatError(path, f"unknown section [{sname}]")
        kind = _SECTION_KIND[key]
        raw_kinds.add(kind)
        vunit, sunit = _angle_units(opts)
        last_sigma = None
        last_station = None
        for lineno, t in lines:
            tok = t.split()
            if len(tok) > _MAX_TOKENS.get(kind, 6):
                raise FileFormatError(
                    path, f"line {lineno}: {len(tok)} values, more than a {kind.replace('_', ' ')} line has "
                    f"({_LAYOUT.get(kind, 'from to value [sigma [hi ht]]')}): a damaged or misplaced line?"
                )
            if kind == "angle":
                if len(tok) < 4:
                    raise FileFormatError(path, f"line {lineno}: angle needs 'at from to value [sigma]'")
                st, bs, fs = tok[0], tok[1], tok[2]
                val = _angle(tok[3], vunit, path, lineno)
                rest = tok[4:]
                sig = _sigma_angle(rest[0], sunit, path, lineno) if rest else last_sigma
                if sig is None:
                    raise FileFormatError(
                        path, f"line {lineno}: no standard deviation given (and none before)"
                    )
                last_sigma = sig
                obs.append(
                    Observation("angle", st, fs, wrap_2pi(val), sig, backsight=bs, unit=vunit, line=lineno)
                )
                continue
            if len(tok) < 3:
                raise FileFormatError(path, f"line {lineno}: expected 'from to value ...', got {t.strip()!r}")
            st, tg = tok[0], tok[1]
            if kind == "baseline":
                if len(tok) < 5:
                    raise FileFormatError(
                        path, f"line {lineno}: baseline needs 'from to dx dy dz [sigmas|cov]'"
                    )
                val = np.array([_num(v, path, lineno, "baseline component") for v in tok[2:5]])
                extra = [_num(v, path, lineno, "baseline precision") for v in tok[5:]]
                if len(extra) == 3:
                    cov = np.diag(np.square(extra))
                elif len(extra) == 6:
                    a = extra
                    cov = np.array([[a[0], a[1], a[2]], [a[1], a[3], a[4]], [a[2], a[4], a[5]]])
                elif len(extra) == 9:
                    cov = np.array(extra).reshape(3, 3)
                    cov = 0.5 * (cov + cov.T)
                elif not extra and last_sigma is not None:
                    cov = last_sigma
                else:
                    raise FileFormatError(
                        path,
                        f"line {lineno}: baseline precision must be 3 std devs, 6 (upper triangle) or 9 covariance values",
                    )
                last_sigma = cov
                obs.append(Observation("baseline", st, tg, val, cov, unit="m", line=lineno))
                continue
            if kind in _ANGULAR:
                val = _angle(tok[2], vunit, path, lineno)
                rest = tok[3:]
                if len(rest) == 2:
                    raise FileFormatError(
                        path, f"line {lineno}: give both instrument and target height (from to value sigma hi ht)"
                    )
                sig = _sigma_angle(rest[0], sunit, path, lineno) if rest else None
                hi = ht = 0.0
                if len(rest) >= 3:
                    hi, ht = (
                        _num(rest[1], path, lineno, "instrument height"),
                        _num(rest[2], path, lineno, "target height"),
                    )
                if kind == "azimuth" and sig is None and key == "azimuth":
                    known_az[(st, tg)] = wrap_2pi(val)
                    continue
                if sig is None:
                    sig = last_sigma
                if sig is None:
                    raise FileFormatError(
                        path, f"line {lineno}: no standard deviation given (and none before)"
                    )
                last_sigma = sig
                set_id = None
                if kind == "direction":
                    if st != last_station:
                        set_counter += 1
                    set_id = set_counter
                    last_station = st
                    val = wrap_2pi(val)
                obs.append(
                    Observation(kind, st, tg, val, sig, set_id=set_id, hi=hi, ht=ht, unit=vunit, line=lineno)
                )
                continue
            val = _num(tok[2], path, lineno, "observed value")
            rest = [_num(v, path, lineno, "value") for v in tok[3:]]
            if kind == "height_difference":
                if not rest:
                    raise FileFormatError(
                        path, f"line {lineno}: levelling needs 'from to dh length_m [sigma_km]'"
                    )
                length = rest[0]
                if length < 0:
                    raise FileFormatError(path, f"line {lineno}: levelling length {length} m must not be negative")
                skm = rest[1] if len(rest) > 1 else last_sigma
                if skm is None:
                    raise FileFormatError(
                        path, f"line {lineno}: no standard deviation per km given (and none before)"
                    )
                last_sigma = skm
                sig = skm * math.sqrt(length / 1000.0)
                obs.append(Observation(kind, st, tg, val, sig, unit="m", line=lineno))
                continue
            hi = ht = 0.0
            if kind == "distance":
                if val < 0:
                    raise FileFormatError(path, f"line {lineno}: distance {tok[2]!r} must not be negative")
                if len(rest) >= 2:
                    # README: sigma² = sigma_c² + s[m]·sigma_s²
                    sig = math.sqrt(rest[0] ** 2 + val * rest[1] ** 2)
                    last_sigma = (rest[0], rest[1])
                elif len(rest) == 1:
                    sig = rest[0]
                    last_sigma = rest[0]
                else:
                    if last_sigma is None:
                        raise FileFormatError(
                            path, f"line {lineno}: no standard deviation given (and none before)"
                        )
                    sig = (
                        math.sqrt(last_sigma[0] ** 2 + val * last_sigma[1] ** 2)
                        if isinstance(last_sigma, tuple)
                        else last_sigma
                    )
            else:
                if len(rest) == 2:
                    raise FileFormatError(
                        path, f"line {lineno}: give both instrument and target height (from to value sigma hi ht)"
                    )
                sig = rest[0] if rest else last_sigma
                if sig is None:
                    raise FileFormatError(
                        path, f"line {lineno}: no standard deviation given (and none before)"
                    )
                last_sigma = sig
                if len(rest) >= 3:
                    hi, ht = rest[1], rest[2]
            obs.append(Observation(kind, st, tg, val, sig, hi=hi, ht=ht, unit="m", line=lineno))

    if not points:
        raise FileFormatError(path, "no [Coordinates] section (approximate coordinates are required)")
    if not obs:
        raise FileFormatError(path, "no observations")
    kinds = {o.kind for o in obs}
    if kinds & _DIM3:
        dim = 3
    elif kinds & _DIM2:
        dim = 2
    else:
        dim = 1
    datum = _parse_datum(datum_lines, points, dim, path)
    return _check_precisions(Network(
        points=points,
        datum=datum,
        observations=obs,
        dim=dim,
        known_azimuths=known_az,
        restrictions=restrictions,
        sigma0_text=sigma0_text,
        name=name,
        description="\n".join(description_lines),
        source=str(source),
    ))


def _coord_tokens(tok: str, points: dict, dim: int, path, lineno) -> list[tuple[str, str]]:
    tok = tok.strip(",;")
    if not tok:
        return []
    if tok[0] in "xyzXYZH" and tok[1:] in points and tok not in points:
        ax = {"x": "x", "y": "y", "z": "z", "h": "z"}[tok[0].lower()]
        if dim == 1:
            ax = "z"
        return [(tok[1:], ax)]
    if tok in points:
        axes = {1: ("z",), 2: ("x", "y"), 3: ("x", "y", "z")}[dim]
        return [(tok, a) for a in axes]
    raise FileFormatError(
        path, f"line {lineno}: [Datum] names {tok!r}, which is neither a point nor x/y/z<point>"
    )


def _parse_datum(lines, points, dim, path) -> Datum:
    if not lines:
        raise FileFormatError(
            path, "no [Datum] section: say which coordinates are fixed ('fix xA yA ...'), 'free ...' or 'dyn'"
        )
    first = lines[0][1].split()
    kind = first[0].lower()
    if kind in ("fix", "fixed"):
        coords = []
        for lineno, t in [(lines[0][0], " ".join(first[1:]))] + lines[1:]:
            for tok in t.replace(",", " ").split():
                coords.extend(_coord_tokens(tok, points, dim, path, lineno))
        return Datum("fix", tuple(dict.fromkeys(coords)))
    if kind in ("free", "fre"):
        coords = []
        for lineno, t in [(lines[0][0], " ".join(first[1:]))] + lines[1:]:
            for tok in t.replace(",", " ").split():
                coords.extend(_coord_tokens(tok, points, dim, path, lineno))
        if not coords:
            axes = {1: ("z",), 2: ("x", "y"), 3: ("x", "y", "z")}[dim]
            coords = [(p, a) for p in points for a in axes]
        return Datum("free", tuple(dict.fromkeys(coords)))
    if kind in ("dyn", "dynamic"):
        rows = []
        for lineno, t in lines[1:] + ([(lines[0][0], " ".join(first[1:]))] if len(first) > 1 else []):
            tok = t.split()
            rows.append((lineno, tok[0], [_num(v, path, lineno, "datum precision") for v in tok[1:]]))
        names = []
        for lineno, tok0, _ in rows:
            c = _coord_tokens(tok0, points, dim, path, lineno)
            names.append(c)
        if all(len(v) == 1 for _, _, v in rows):
            coords, sig = [], []
            for c, (_, _, v) in zip(names, rows, strict=True):
                for cc in c:
                    coords.append(cc)
                    sig.append(v[0])
            cov = np.diag(np.square(sig))
            return Datum("dyn", tuple(coords), cov)
        coords = [cc for c in names for cc in c]
        if any(len(c) != 1 for c in names):
            raise FileFormatError(
                path, "[Datum] dyn with a covariance matrix must name single coordinates per row"
            )
        m = len(coords)
        cov = np.zeros((m, m))
        for i, (lineno, _, v) in enumerate(rows):
            if len(v) == m:
                cov[i, :] = v
            elif len(v) == i + 1:
                cov[i, : i + 1] = v
                cov[: i + 1, i] = v
            else:
                raise FileFormatError(
                    path, f"line {lineno}: covariance row must have {i + 1} (lower triangle) or {m} values"
                )
        return Datum("dyn", tuple(coords), 0.5 * (cov + cov.T))
    raise FileFormatError(
        path, f"line {lines[0][0]}: [Datum] must start with 'fix', 'free' or 'dyn', got {first[0]!r}"
    )


# --------------------------------------------------------------------------------------------
# JSON format
# --------------------------------------------------------------------------------------------
def _json_angle(d: dict, key: str, where: str) -> tuple[float, str]:
    for suffix, unit in (
        ("_dms", "dms"),
        ("_gon", "gon"),
        ("_deg", "deg"),
        ("_rad", "rad"),
        ("_arcsec", "arcsec"),
        ("_mgon", "mgon"),
    ):
        if key + suffix in d:
            v = d[key + suffix]
            if isinstance(v, bool) or not isinstance(v, (str, int, float)):
                raise InputError(f"{where}: {key + suffix} must be a number or text, got {_json_type(v)}")
            try:
                val = parse_angle(v, unit)
            except (ValueError, OverflowError):
                raise InputError(f"{where}: cannot read {key + suffix} = {str(v)[:40]!r} as an angle") from None
            if not (math.isfinite(val) and abs(val) <= _MAX_JSON_ANGLE_RAD):
                raise InputError(f"{where}: {key + suffix} = {str(v)[:40]!r} is not a finite angle")
            return val, unit
    raise InputError(f"{where}: give {key}_dms, {key}_gon, {key}_deg or {key}_rad")


#: largest absolute angle (rad) read from JSON: a few turns are normal, 10^6 rad is a damaged value
_MAX_JSON_ANGLE_RAD = 1e6


def _json_type(v) -> str:
    return {dict: "an object", list: "a list", str: "text", bool: "true/false", type(None): "null"}.get(
        type(v), "a number"
    )


def _jobj(v, where: str) -> dict:
    if not isinstance(v, dict):
        raise InputError(f"{where} must be a JSON object {{...}}, got {_json_type(v)}")
    return v


def _jlist(v, where: str) -> list:
    if not isinstance(v, list):
        raise InputError(f"{where} must be a JSON list [...], got {_json_type(v)}")
    return v


def _jget(d: dict, key: str, where: str):
    if key not in d:
        raise InputError(f"{where}: missing {key!r}")
    return d[key]


def _jnum(v, where: str, limit: float = MAX_ABS_COORDINATE) -> float:
    """A finite number within ``+-limit`` (numbers given as text are accepted)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise InputError(f"{where} must be a number, got {_json_type(v)}")
    try:
        f = float(v)
    except (ValueError, OverflowError):
        raise InputError(f"{where} must be a number, got {str(v)[:40]!r}") from None
    if not math.isfinite(f) or abs(f) > limit:
        raise InputError(f"{where} = {str(v)[:40]} is not a finite number within +-{limit:.0e}")
    return f


def _jid(v, where: str) -> str:
    if isinstance(v, bool) or not isinstance(v, (str, int)) or str(v) == "":
        raise InputError(f"{where} must be a point name (text), got {_json_type(v) if v != '' else 'empty text'}")
    return str(v)


def _jmatrix(v, shape: tuple, where: str) -> np.ndarray:
    rows = _jlist(v, where)
    if len(shape) == 1:
        if len(rows) != shape[0]:
            raise InputError(f"{where} must hold {shape[0]} numbers, got {len(rows)}")
        return np.array([_jnum(x, f"{where}[{i}]") for i, x in enumerate(rows)], dtype=np.float64)
    if len(rows) != shape[0]:
        raise InputError(f"{where} must be a {shape[0]}x{shape[1]} matrix (list of {shape[0]} rows)")
    return np.array([_jmatrix(r, shape[1:], f"{where}[{i}]") for i, r in enumerate(rows)], dtype=np.float64)


def network_from_dict(d: dict, source: str = "<dict>") -> Network:
    """Build a network from the documented JSON structure (see ``docs/survey.md``)::

    {"name": "...", "points": {"P": {"x": .., "y": .., "h": ..}, ...},
     "datum": {"type": "fix", "coordinates": ["xP", "yP", "Q"]}
            | {"type": "free", "coordinates": [...]}
            | {"type": "dyn", "sigma_m": {"xB": 0.01, ...}},
     "known_azimuths": [{"from": "B", "to": "A", "value_dms": "68°15'20.7\\""}],
     "observations": [
        {"type": "distance", "from": "A", "to": "B", "value_m": 3111.291, "sigma_m": 0.010},
        {"type": "angle", "at": "U", "from": "P", "to": "Q", "value_dms": "...", "sigma_arcsec": 5},
        {"type": "direction", "at": "A", "to": "B", "set": 1, "value_gon": 0.0, "sigma_mgon": 1},
        {"type": "azimuth", "from": "A", "to": "B", "value_deg": .., "sigma_arcsec": ..},
        {"type": "height_difference", "from": "A", "to": "B", "value_m": .., "sigma_m": ..},
        {"type": "spatial_distance" | "zenith_angle" | "vertical_angle", ..., "hi_m": .., "ht_m": ..},
        {"type": "baseline", "from": "A", "to": "B", "value_m": [dx, dy, dz], "cov_m2": [[...]]}]}

    Raises
    ------
    FileFormatError
        A missing or mistyped member, naming where it is (``observation 3: missing 'to'``);
        non-finite numbers and coordinates beyond
        :data:`~minegeo.io._limits.MAX_ABS_COORDINATE` are refused.
    """
    try:
        return _network_from_dict(d, source)
    except FileFormatError:
        raise
    except InputError as exc:
        raise FileFormatError(source, str(exc)) from None


def _network_from_dict(d, source: str) -> Network:
    if not isinstance(d, dict) or "points" not in d or "observations" not in d:
        raise FileFormatError(source, "JSON network needs 'points' and 'observations'")
    pts_in = _jobj(d["points"], "'points'")
    obs_in = _jlist(d["observations"], "'observations'")
    points = {}
    for pid, c in pts_in.items():
        c = _jobj(c, f"point {pid!r}")
        p = {}
        for k_in, k in (("x", "x"), ("y", "y"), ("h", "z"), ("z", "z")):
            if k_in in c and c[k_in] is not None:
                p[k] = _jnum(c[k_in], f"point {pid!r} {k_in}")
        points[str(pid)] = p
    obs = []
    set_ids: dict = {}
    for i, o in enumerate(obs_in):
        where = f"observation {i}"
        o = _jobj(o, where)
        kind = o.get("type")
        if not isinstance(kind, str) or kind not in KINDS:
            raise FileFormatError(source, f"{where}: unknown type {kind!r}; use one of {', '.join(KINDS)}")
        if kind == "angle":
            val, unit = _json_angle(o, "value", where)
            sig, _ = _json_angle(o, "sigma", where)
            obs.append(
                Observation(
                    "angle",
                    _jid(_jget(o, "at", where), f"{where} 'at'"),
                    _jid(_jget(o, "to", where), f"{where} 'to'"),
                    wrap_2pi(val),
                    sig,
                    backsight=_jid(_jget(o, "from", where), f"{where} 'from'"),
                    unit=unit,
                )
            )
            continue
        st = _jid(o["at"] if "at" in o else _jget(o, "from", where), f"{where} 'from'")
        tg = _jid(_jget(o, "to", where), f"{where} 'to'")
        if kind == "baseline":
            obs.append(
                Observation(
                    "baseline",
                    st,
                    tg,
                    _jmatrix(_jget(o, "value_m", where), (3,), f"{where} value_m"),
                    _jmatrix(_jget(o, "cov_m2", where), (3, 3), f"{where} cov_m2"),
                )
            )
            continue
        hi, ht = _jnum(o.get("hi_m", 0.0), f"{where} hi_m"), _jnum(o.get("ht_m", 0.0), f"{where} ht_m")
        if kind in _ANGULAR:
            val, unit = _json_angle(o, "value", where)
            sig, _ = _json_angle(o, "sigma", where)
            sid = None
            if kind == "direction":
                key = o.get("set", st)
                if not isinstance(key, (str, int, float)):
                    raise InputError(f"{where}: 'set' must be a number or a name, got {_json_type(key)}")
                sid = set_ids.setdefault(key, len(set_ids) + 1)
                val = wrap_2pi(val)
            obs.append(Observation(kind, st, tg, val, sig, set_id=sid, hi=hi, ht=ht, unit=unit))
        else:
            obs.append(Observation(kind, st, tg, _jnum(_jget(o, "value_m", where), f"{where} value_m"),
                                   _jnum(_jget(o, "sigma_m", where), f"{where} sigma_m"), hi=hi, ht=ht))
    kinds = {o.kind for o in obs}
    dim = d.get("dimension", 3 if kinds & _DIM3 else 2 if kinds & _DIM2 else 1)
    if dim not in (1, 2, 3) or isinstance(dim, bool):
        raise InputError(f"'dimension' must be 1, 2 or 3, got {dim!r}")
    dim = int(dim)
    dd = _jobj(d.get("datum", {"type": "fix", "coordinates": []}), "'datum'")
    dt = dd.get("type", "fix")
    if dt == "dyn":
        coords, sig = [], []
        for k, v in _jobj(dd.get("sigma_m", {}), "datum sigma_m").items():
            for c in _coord_tokens(k, points, dim, source, 0):
                coords.append(c)
                sig.append(_jnum(v, f"datum sigma_m {k!r}"))
        if "cov_m2" in dd:
            names = _jlist(_jget(dd, "coordinates", "datum with cov_m2"), "datum coordinates")
            coords = [c for k in names for c in _coord_tokens(_jid(k, "datum coordinate"), points, dim, source, 0)]
            cov = _jmatrix(dd["cov_m2"], (len(coords), len(coords)), "datum cov_m2")
        else:
            cov = np.diag(np.square(sig))
        datum = Datum("dyn", tuple(coords), cov)
    elif dt in ("fix", "free"):
        names = _jlist(dd.get("coordinates", []), "datum coordinates")
        coords = [c for k in names for c in _coord_tokens(_jid(k, "datum coordinate"), points, dim, source, 0)]
        if dt == "free" and not coords:
            axes = {1: ("z",), 2: ("x", "y"), 3: ("x", "y", "z")}[dim]
            coords = [(p, a) for p in points for a in axes]
        datum = Datum(dt, tuple(dict.fromkeys(coords)))
    else:
        raise FileFormatError(source, f"datum type must be fix, free or dyn, got {dt!r}")
    known = {}
    for j, k in enumerate(_jlist(d.get("known_azimuths", []), "'known_azimuths'")):
        where = f"known_azimuths[{j}]"
        k = _jobj(k, where)
        val, _ = _json_angle(k, "value", where)
        known[(_jid(_jget(k, "from", where), f"{where} 'from'"), _jid(_jget(k, "to", where), f"{where} 'to'"))] = (
            wrap_2pi(val)
        )
    restrictions = _jlist(d.get("restrictions", []), "'restrictions'")
    if not all(isinstance(r, str) for r in restrictions):
        raise InputError("'restrictions' must be a list of text expressions")
    return _check_precisions(Network(
        points,
        datum,
        obs,
        dim,
        known,
        list(restrictions),
        str(d.get("sigma0", "")),
        str(d.get("name", "")),
        str(d.get("description", "")),
        source,
    ))


def read_network(path) -> Network:
    """Read a network file: ``.json`` (see :func:`network_from_dict`) or Krumm text (anything else).

    Raises
    ------
    FileFormatError
        Unreadable or malformed file.
    """
    p = Path(path)
    data = read_file_bytes(p, max_bytes=MAX_TABLE_FILE_BYTES, what="survey network file")
    if p.suffix.lower() == ".json":
        # depth, duplicate keys (a point given twice), NaN/Infinity: all refused with the path
        d = load_json_text(data, p)
        return network_from_dict(d, str(p))
    try:
        text = data.decode("utf-8-sig")  # tolerate a byte-order mark
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return parse_krumm(text, str(p))


# --------------------------------------------------------------------------------------------
# Adjustment
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PointResult:
    """Adjusted point: coordinates (m), standard deviations (m, 0 for fixed), covariance block."""

    id: str
    x: float | None
    y: float | None
    h: float | None
    sx_m: float | None
    sy_m: float | None
    sh_m: float | None
    fixed: tuple
    dx_m: float | None
    dy_m: float | None
    dh_m: float | None
    cov: np.ndarray
    ellipse_standard: ErrorEllipse | None = None
    ellipse_95: ErrorEllipse | None = None


@dataclass(frozen=True)
class ObservationResult:
    """One observation equation with its statistics (residual v = adjusted − observed).

    ``component`` is "dx"/"dy"/"dz" for the rows of a GNSS baseline, else None. Values in
    metres or radians; ``sigma`` is the a-priori standard deviation of this row.
    """

    obs: Observation
    observed: float
    adjusted: float
    residual: float
    sigma: float
    redundancy: float
    w: float
    tau: float
    flag: str
    component: str | None = None


@dataclass(frozen=True)
class NetworkResult:
    """Result of :func:`adjust_network`.

    Attributes
    ----------
    network : Network
    lsq : LSQResult
    points : dict[str, PointResult]
        Every point that takes part in the adjustment (fixed points with σ = 0).
    orientations : dict[int, tuple[str, float, float]]
        Direction set -> (station, orientation rad, σ rad).
    observations : list[ObservationResult]
        In input order; baselines contribute one entry per component.
    relative_ellipses : list[(str, str, ErrorEllipse, ErrorEllipse)]
        Standard and 95 % relative ellipses between observed pairs of points that are both
        adjusted (2D/3D; with one end fixed the relative ellipse equals the absolute one).
    sigma0_known : bool
        Whether the covariance was scaled with the a-priori σ0 (then 95 % ellipses use χ²(2)).
    ellipse_note : str
    unused_points : tuple[str, ...]
        Points in the coordinate list without observations (not adjusted).
    local_origin : dict[str, float]
        Round values subtracted from the coordinates during the adjustment (x, y[, z]).
    datum_defects : tuple[str, ...]
        Free network: the datum defects removed by the inner constraints.
    """

    network: Network
    lsq: LSQResult
    points: dict
    orientations: dict
    observations: list
    relative_ellipses: list
    sigma0_known: bool
    ellipse_note: str
    unused_points: tuple
    local_origin: dict = field(default_factory=dict)
    datum_defects: tuple = ()

    @property
    def sigma0(self) -> float:
        return self.lsq.sigma0

    @property
    def dof(self) -> int:
        return self.lsq.dof


class _Model:
    """Parameters and observation equations of a network."""

    def __init__(self, net: Network):
        self.net = net
        axes = net.axes()
        used = set()
        for o in net.observations:
            used.add(o.station)
            used.add(o.target)
            if o.backsight:
                used.add(o.backsight)
        for pid in used:
            if pid not in net.points and not any(k[1] == pid for k in net.known_azimuths):
                raise InputError(f"point {pid!r} is observed but has no (approximate) coordinates")
        for pid, c in net.points.items():
            if pid in used:
                missing = [a for a in axes if a not in c]
                if missing:
                    raise InputError(
                        f"point {pid!r} needs coordinate(s) {', '.join(missing)} for a {net.dim}D network"
                    )
        fixed = set()
        dyn_zero = set()
        if net.datum.kind == "fix":
            fixed = {c for c in net.datum.coords if c[1] in axes}
        elif net.datum.kind == "dyn":
            d = np.diag(net.datum.cov) if net.datum.cov is not None else np.zeros(0)
            dyn_zero = {c for c, v in zip(net.datum.coords, d, strict=True) if v <= 0}
            fixed = set(dyn_zero)
        self.fixed = fixed
        self.unused = tuple(p for p in net.points if p not in used)
        self.pids = [p for p in net.points if p in used]
        # local origin: coordinates are reduced by a round value near the centroid so that
        # 10^6 m grid coordinates keep full float64 precision in differences and corrections
        self.origin = {}
        for a in axes:
            vals = [net.points[p][a] for p in self.pids]
            c = float(np.mean(vals)) if vals else 0.0
            self.origin[a] = float(np.round(c, -3)) if abs(c) >= 1000.0 else 0.0
        self.loc = {p: {a: v - self.origin.get(a, 0.0) for a, v in c.items()} for p, c in net.points.items()}
        self.index: dict[tuple[str, str], int] = {}
        names = []
        x0 = []
        for p in self.pids:
            for a in axes:
                if (p, a) in fixed:
                    continue
                self.index[(p, a)] = len(names)
                names.append(f"{'h' if (a == 'z' and net.dim == 1) else a}{p}")
                x0.append(self.loc[p][a])
        self.n_coord = len(names)
        # orientation unknowns
        self.set_index: dict[int, int] = {}
        self.set_station: dict[int, str] = {}
        sets: dict[int, list[Observation]] = {}
        for o in net.observations:
            if o.kind == "direction":
                sets.setdefault(o.set_id, []).append(o)
        for sid, lst in sets.items():
            st = lst[0].station
            diffs = []
            for o in lst:
                a = self._az_approx(st, o.target)
                diffs.append(a - o.value)
            o0 = math.atan2(np.mean(np.sin(diffs)), np.mean(np.cos(diffs)))
            self.set_index[sid] = len(names)
            self.set_station[sid] = st
            names.append(f"o{st}[{sid}]")
            x0.append(wrap_2pi(o0))
        self.names = tuple(names)
        self.x0 = np.array(x0, dtype=np.float64)
        # observation rows
        rows = []
        for o in net.observations:
            if o.kind == "baseline":
                rows.extend([(o, k) for k in range(3)])
            else:
                rows.append((o, None))
        # dyn datum pseudo-observations
        self.dyn = []
        if net.datum.kind == "dyn":
            keep = [i for i, c in enumerate(net.datum.coords) if c not in dyn_zero and c[1] in axes]
            self.dyn = [net.datum.coords[i] for i in keep]
            self.dyn_cov = net.datum.cov[np.ix_(keep, keep)] if keep else np.zeros((0, 0))
            for c in self.dyn:
                rows.append((None, c))
        self.rows = rows
        self.obs_names = tuple(
            (f"{o.kind} {o.label}" + (f" d{'xyz'[k]}" if k is not None else ""))
            if o is not None
            else f"datum {k[1]}{k[0]}"
            for o, k in rows
        )
        self.W = self._weights()

    def _az_approx(self, st, tg):
        if tg not in self.net.points:
            return self.net.known_azimuths[(st, tg)]
        dx = self.loc[tg]["x"] - self.loc[st]["x"]
        dy = self.loc[tg]["y"] - self.loc[st]["y"]
        if dx == 0 and dy == 0:
            raise InputError(f"points {st!r} and {tg!r} have identical approximate coordinates")
        return math.atan2(dx, dy)

    def _weights(self):
        n = len(self.rows)
        full = any(o is not None and o.kind == "baseline" for o, _ in self.rows) or (
            len(self.dyn) > 1 and np.count_nonzero(self.dyn_cov - np.diag(np.diag(self.dyn_cov)))
        )
        if not full:
            w = np.empty(n)
            j = 0
            for i, (o, _k) in enumerate(self.rows):
                if o is None:
                    w[i] = 1.0 / self.dyn_cov[j, j]
                    j += 1
                else:
                    s = float(o.sigma)
                    if not (s > 0 and math.isfinite(s)):
                        raise InputError(
                            f"observation {o.label} (line {o.line}) has standard deviation {s}; it must be > 0"
                        )
                    w[i] = 1.0 / s**2
            return w
        W = np.zeros((n, n))
        i = 0
        dyn_start = None
        while i < n:
            o, k = self.rows[i]
            if o is None:
                dyn_start = i
                break
            if o.kind == "baseline":
                C = np.asarray(o.sigma, dtype=float)
                try:
                    np.linalg.cholesky(C)
                    W[i : i + 3, i : i + 3] = np.linalg.inv(C)
                except np.linalg.LinAlgError:
                    raise InputError(
                        f"baseline {o.label} (line {o.line}) covariance is not positive definite"
                    ) from None
                i += 3
            else:
                W[i, i] = 1.0 / float(o.sigma) ** 2
                i += 1
        if dyn_start is not None:
            m = len(self.dyn)
            try:
                W[dyn_start : dyn_start + m, dyn_start : dyn_start + m] = np.linalg.inv(self.dyn_cov)
            except np.linalg.LinAlgError:
                raise InputError("the [Datum] dyn covariance matrix is singular") from None
        return W

    def coord(self, x, p, a):
        """Local (origin-reduced) coordinate ``a`` of point ``p`` at parameters ``x``."""
        i = self.index.get((p, a))
        return x[i] if i is not None else self.loc[p][a]

    def _grad(self, row, p, a, val):
        i = self.index.get((p, a))
        if i is not None:
            row[i] += val

    def evaluate(self, x):
        """F(x) and J = ∂F/∂x for every row."""
        n = len(self.rows)
        u = x.size
        F = np.empty(n)
        J = np.zeros((n, u))
        is3 = self.net.dim == 3
        for r, (o, k) in enumerate(self.rows):
            row = J[r]
            if o is None:
                p, a = k
                F[r] = self.coord(x, p, a)
                self._grad(row, p, a, 1.0)
                continue
            kind = o.kind
            if kind in ("height_difference", "trig_height_difference"):
                F[r] = self.coord(x, o.target, "z") - self.coord(x, o.station, "z")
                self._grad(row, o.target, "z", 1.0)
                self._grad(row, o.station, "z", -1.0)
                if kind == "trig_height_difference":
                    F[r] += o.ht - o.hi
                continue
            if kind == "baseline":
                ax = "xyz"[k]
                F[r] = self.coord(x, o.target, ax) - self.coord(x, o.station, ax)
                self._grad(row, o.target, ax, 1.0)
                self._grad(row, o.station, ax, -1.0)
                continue
            if kind == "angle":
                a_f, g_f = self._azimuth(x, o.station, o.target)
                a_b, g_b = self._azimuth(x, o.station, o.backsight)
                F[r] = wrap_2pi(a_f - a_b)
                for (p, a), v in g_f:
                    self._grad(row, p, a, v)
                for (p, a), v in g_b:
                    self._grad(row, p, a, -v)
                continue
            if kind in ("azimuth", "direction"):
                az, g = self._azimuth(x, o.station, o.target)
                for (p, a), v in g:
                    self._grad(row, p, a, v)
                if kind == "direction":
                    j = self.set_index[o.set_id]
                    F[r] = wrap_2pi(az - x[j])
                    row[j] = -1.0
                else:
                    F[r] = az
                continue
            # distances and vertical geometry
            xs, ys = self.coord(x, o.station, "x"), self.coord(x, o.station, "y")
            xt, yt = self.coord(x, o.target, "x"), self.coord(x, o.target, "y")
            dx, dy = xt - xs, yt - ys
            hd = math.hypot(dx, dy)
            if kind == "distance":
                if hd == 0:
                    raise DegenerateGeometryError(f"distance {o.label}: the two points coincide")
                F[r] = hd
                gx, gy = dx / hd, dy / hd
                self._grad(row, o.target, "x", gx)
                self._grad(row, o.target, "y", gy)
                self._grad(row, o.station, "x", -gx)
                self._grad(row, o.station, "y", -gy)
                continue
            if not is3:
                raise InputError(f"{kind} needs a 3D network (heights)")
            dz = (self.coord(x, o.target, "z") + o.ht) - (self.coord(x, o.station, "z") + o.hi)
            S2 = hd * hd + dz * dz
            if kind == "spatial_distance":
                S = math.sqrt(S2)
                if S == 0:
                    raise DegenerateGeometryError(f"slope distance {o.label}: the two points coincide")
                F[r] = S
                g = (dx / S, dy / S, dz / S)
            else:
                if hd == 0:
                    raise DegenerateGeometryError(f"{kind} {o.label}: target is vertically above the station")
                # zenith z = atan2(hd, dz); ∂z/∂hd = dz/S², ∂z/∂dz = −hd/S²
                dzh = dz / S2
                g = (dzh * dx / hd, dzh * dy / hd, -hd / S2)
                if kind == "zenith_angle":
                    F[r] = math.atan2(hd, dz)
                else:
                    F[r] = math.atan2(dz, hd)
                    g = tuple(-v for v in g)
            for a, v in zip("xyz", g, strict=True):
                self._grad(row, o.target, a, v)
                self._grad(row, o.station, a, -v)
        return F, J

    def _azimuth(self, x, st, tg):
        if tg not in self.net.points:
            if (st, tg) not in self.net.known_azimuths:
                raise InputError(f"point {tg!r} has no coordinates and no known azimuth from {st!r}")
            return self.net.known_azimuths[(st, tg)], []
        xs, ys = self.coord(x, st, "x"), self.coord(x, st, "y")
        xt, yt = self.coord(x, tg, "x"), self.coord(x, tg, "y")
        dx, dy = xt - xs, yt - ys
        s2 = dx * dx + dy * dy
        if s2 == 0:
            raise DegenerateGeometryError(f"azimuth {st}-{tg}: the two points coincide")
        az = math.atan2(dx, dy)
        gx, gy = dy / s2, -dx / s2
        return az, [((tg, "x"), gx), ((tg, "y"), gy), ((st, "x"), -gx), ((st, "y"), -gy)]

    def observed_vector(self):
        lv = np.empty(len(self.rows))
        for r, (o, k) in enumerate(self.rows):
            if o is None:
                lv[r] = self.loc[k[0]][k[1]]
            elif o.kind == "baseline":
                lv[r] = o.value[k]
            else:
                lv[r] = o.value
        return lv

    def angular_mask(self):
        return np.array([o is not None and o.kind in _ANGULAR for o, _ in self.rows])

    def _datum_candidates(self, x):
        """Candidate datum-defect vectors (shifts, rotation, scale) over the coordinate unknowns at ``x``."""
        net = self.net
        axes = net.axes()
        dcoords = [c for c in net.datum.coords if c in self.index]
        pts = sorted({p for p, _ in dcoords}, key=self.pids.index)
        cur = {p: {a: self.coord(x, p, a) for a in axes} for p in self.pids}
        cen = {a: float(np.mean([cur[p][a] for p in pts])) for a in axes}
        cands = []
        for a in axes:  # translations
            g = np.zeros(self.n_coord)
            for (_p, aa), i in self.index.items():
                if aa == a:
                    g[i] = 1.0
            cands.append((f"shift {a}", g))
        if net.dim >= 2:
            g = np.zeros(self.n_coord)
            s = np.zeros(self.n_coord)
            for (p, aa), i in self.index.items():
                if aa == "x":
                    g[i] = -(cur[p]["y"] - cen["y"])
                    s[i] = cur[p]["x"] - cen["x"]
                elif aa == "y":
                    g[i] = cur[p]["x"] - cen["x"]
                    s[i] = cur[p]["y"] - cen["y"]
                elif aa == "z":
                    s[i] = cur[p]["z"] - cen["z"]
            cands.append(("rotation", g))
            cands.append(("scale", s))
        return dcoords, cands

    def _datum_rows(self, x, labels):
        dcoords, cands = self._datum_candidates(x)
        u = len(self.names)
        rows = []
        for label, g in cands:
            if label in labels:
                c = np.zeros(u)
                for p, a in dcoords:
                    c[self.index[(p, a)]] = g[self.index[(p, a)]]
                rows.append(c)
        return np.array(rows)

    def free_constraints(self):
        """Inner constraints ``Gᵀ·Δ = 0`` on the datum coordinates of a free network.

        The datum defects (shifts, rotation, scale) are found numerically: a candidate vector
        ``g`` is a defect when ``J·g`` vanishes after the best compensation by the other unknowns
        (orientations). Constraint rows are ``g`` restricted to the listed datum coordinates
        (partial minimum-trace datum, S-transformation), re-evaluated at the current
        coordinates in every iteration like GNU Gama.

        Returns
        -------
        (callable or None, list of str)
            ``constraints(x) -> (C, 0)`` for :func:`adjust`, and the defect names.
        """
        dcoords = [c for c in self.net.datum.coords if c in self.index]
        if not dcoords:
            raise InputError("free network: the [Datum] lists no adjustable coordinates")
        _, J = self.evaluate(self.x0)
        Jc = J[:, : self.n_coord]
        Jn = J[:, self.n_coord :]
        _, cands = self._datum_candidates(self.x0)
        defects = []
        jn = np.linalg.norm(Jc)
        for label, g in cands:
            if not np.any(g):
                continue
            r = Jc @ g
            if Jn.shape[1]:
                h, *_ = np.linalg.lstsq(Jn, -r, rcond=None)
                r = r + Jn @ h
            if np.linalg.norm(r) <= 1e-9 * jn * np.linalg.norm(g):
                defects.append(label)
        if not defects:
            log.info("free network: no datum defect found; adjusting without constraints")
            return None, defects

        def constraints(x):
            C = self._datum_rows(x, defects)
            return C, np.zeros(C.shape[0])

        return constraints, defects

    def restriction_constraints(self):
        exprs = [_compile_restriction(e, self) for e in self.net.restrictions]

        def fun(x):
            C = np.zeros((len(exprs), x.size))
            c = np.zeros(len(exprs))
            for k, (code, syms) in enumerate(exprs):
                env = {s: self.coord(x, p, a) + self.origin.get(a, 0.0) for s, (p, a) in syms.items()}
                g0 = float(eval(code, {"__builtins__": {}}, env))  # noqa: S307 - AST-whitelisted
                c[k] = -g0
                for s, (p, a) in syms.items():
                    i = self.index.get((p, a))
                    if i is None:
                        continue
                    h = 1e-6 * max(1.0, abs(env[s]))
                    e1 = dict(env)
                    e1[s] = env[s] + h
                    e2 = dict(env)
                    e2[s] = env[s] - h
                    C[k, i] = (
                        eval(code, {"__builtins__": {}}, e1) - eval(code, {"__builtins__": {}}, e2)
                    ) / (2 * h)  # noqa: S307
            return C, c

        return fun


_ALLOWED_AST = (
    ast.Expression,
    ast.BinOp,
    ast.UnaryOp,
    ast.Constant,
    ast.Name,
    ast.Load,
    ast.Add,
    ast.Sub,
    ast.Mult,
    ast.Div,
    ast.Pow,
    ast.USub,
    ast.UAdd,
)


def _compile_restriction(expr: str, model: _Model):
    """Compile ``g(x) = 0`` written with x<pt>/y<pt>/z<pt>, numbers, + − * / ^ and parentheses."""
    text = expr.replace("^", "**")
    names = {}

    def repl(m):
        tok = m.group(0)
        if tok[0] in "xyz" and tok[1:] in model.net.points:
            sym = f"_v{len(names)}"
            names[sym] = (tok[1:], tok[0])
            return sym
        raise InputError(f"restriction {expr!r}: unknown symbol {tok!r} (use x<point>, y<point>, z<point>)")

    text = re.sub(r"[A-Za-z_][A-Za-z0-9_#@-]*", repl, text)
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError:
        raise InputError(f"restriction {expr!r} is not a valid expression") from None
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED_AST):
            raise InputError(f"restriction {expr!r}: only numbers, coordinates, + - * / ^ and () are allowed")
    return compile(tree, "<restriction>", "eval"), names


def adjust_network(
    net: Network, options: LSQOptions | None = None, confidence: float = 0.95
) -> NetworkResult:
    """Adjust a network by least squares and compute point precisions, ellipses and tests.

    Parameters
    ----------
    net : Network
    options : LSQOptions, optional
        ``variance="aposteriori"`` (default, like adjustment packages) scales the covariance with
        σ̂0 and the 95 % ellipses use ``sqrt(2F(2,r))``; ``"apriori"`` uses σ0 = 1 and χ²(2).
    confidence : float
        Confidence level of the confidence ellipses.

    Raises
    ------
    TooFewPointsError
        Fewer observations than unknowns.
    DegenerateGeometryError
        Singular normal equations (collinear control, missing datum, ...).
    """
    opts = options or LSQOptions()
    model = _Model(net)
    if not model.names:
        raise InputError("nothing to adjust: every coordinate is fixed and there are no orientation unknowns")
    lv = model.observed_vector()
    ang = model.angular_mask()
    n_obs = len(lv)
    u = len(model.names)
    constraints = None
    defects = []
    if net.datum.kind == "free":
        C, defects = model.free_constraints()
        constraints = C
    if net.restrictions:
        rfun = model.restriction_constraints()
        if constraints is not None:
            Cf = constraints

            def both(x, _C=Cf, _r=rfun):
                C1, c1 = _C(x)
                C2, c2 = _r(x)
                return np.vstack([C1, C2]), np.concatenate([c1, c2])

            constraints = both
        else:
            constraints = rfun
    m = len(net.restrictions) + len(defects)
    if n_obs + m < u:
        raise TooFewPointsError(
            f"{n_obs} observation(s) cannot determine {u} unknown(s) ({model.n_coord} coordinates, "
            f"{u - model.n_coord} orientations): add observations or fix more coordinates"
        )

    def fun(x):
        F, J = model.evaluate(x)
        f = F - lv
        if ang.any():
            f[ang] = wrap_pi(f[ang])
        return f, -J

    res = adjust(
        fun,
        model.x0,
        model.W,
        constraints=constraints,
        options=opts,
        param_names=model.names,
        obs_names=model.obs_names,
    )
    return _collect(net, model, res, confidence, defects)


def _collect(net: Network, model: _Model, res: LSQResult, confidence: float, defects) -> NetworkResult:
    axes = net.axes()
    S = res.Sigma_xx
    sigma0_known = res.variance_used == "apriori"
    dof = res.dof
    points = {}
    for p in model.pids:
        idx = [model.index.get((p, a)) for a in axes]
        cov = np.zeros((len(axes), len(axes)))
        for i, ii in enumerate(idx):
            for j, jj in enumerate(idx):
                if ii is not None and jj is not None:
                    cov[i, j] = S[ii, jj]
        loc = {a: (res.x[idx[k]] if idx[k] is not None else model.loc[p][a]) for k, a in enumerate(axes)}
        vals = {a: loc[a] + model.origin[a] for a in axes}
        sd = {a: math.sqrt(max(cov[k, k], 0.0)) for k, a in enumerate(axes)}
        corr = {a: loc[a] - model.loc[p][a] for a in axes}
        fixed = tuple(a for k, a in enumerate(axes) if idx[k] is None)
        e_std = e_95 = None
        if net.dim >= 2 and not ("x" in fixed and "y" in fixed):
            e_std, e_95 = point_ellipses(cov[:2, :2], dof, sigma0_known, confidence)
        points[p] = PointResult(
            id=p,
            x=vals.get("x"),
            y=vals.get("y"),
            h=vals.get("z"),
            sx_m=sd.get("x"),
            sy_m=sd.get("y"),
            sh_m=sd.get("z"),
            fixed=fixed,
            dx_m=corr.get("x"),
            dy_m=corr.get("y"),
            dh_m=corr.get("z"),
            cov=cov,
            ellipse_standard=e_std,
            ellipse_95=e_95,
        )
    orient = {}
    for sid, j in model.set_index.items():
        orient[sid] = (model.set_station[sid], wrap_2pi(res.x[j]), math.sqrt(max(S[j, j], 0.0)))
    # observations
    F, _ = model.evaluate(res.x)
    lv = model.observed_vector()
    obs_res = []
    for r, (o, k) in enumerate(model.rows):
        if o is None:
            continue
        sig = float(o.sigma) if o.kind != "baseline" else math.sqrt(float(np.asarray(o.sigma)[k, k]))
        obs_res.append(
            ObservationResult(
                obs=o,
                observed=lv[r],
                adjusted=F[r] if o.kind not in _ANGULAR else wrap_2pi(F[r]),
                residual=res.v[r],
                sigma=sig,
                redundancy=float(res.redundancy[r]),
                w=float(res.w[r]),
                tau=float(res.tau[r]),
                flag=res.flags[r],
                component=None if k is None else ("dx", "dy", "dz")[k],
            )
        )
    # relative ellipses between observed pairs of adjusted points
    rel = []
    if net.dim >= 2:
        seen = set()
        for o in net.observations:
            for a, b in ((o.station, o.target),) + (((o.station, o.backsight),) if o.backsight else ()):
                key = tuple(sorted((a, b)))
                if key in seen or a not in points or b not in points:
                    continue
                seen.add(key)
                ia = [model.index.get((a, ax)) for ax in ("x", "y")]
                ib = [model.index.get((b, ax)) for ax in ("x", "y")]
                if all(i is None for i in ia) or all(i is None for i in ib):
                    continue  # one end fixed: the relative ellipse is the absolute one
                idx = ia + ib
                C4 = np.zeros((4, 4))
                for i1, q1 in enumerate(idx):
                    for i2, q2 in enumerate(idx):
                        if q1 is not None and q2 is not None:
                            C4[i1, i2] = S[q1, q2]
                e1 = relative_ellipse(C4, 0, 1)
                if not sigma0_known and dof < 1:
                    continue
                kk, basis = ellipse_scale(confidence, dof, sigma0_known)
                rel.append((key[0], key[1], e1, e1.scaled(kk, confidence, basis)))
    note = (
        "95% ellipses scaled by sqrt(chi2(2, 0.95)) = 2.4477 (sigma0 known a priori)"
        if sigma0_known
        else f"95% ellipses scaled by sqrt(2 F(2, r={dof}, 0.95)) (sigma0 estimated from the adjustment)"
    )
    if defects:
        note += f"; free-network datum removes: {', '.join(defects)}"
    return NetworkResult(
        net,
        res,
        points,
        orient,
        obs_res,
        rel,
        sigma0_known,
        note,
        model.unused,
        dict(model.origin),
        tuple(defects),
    )


# --------------------------------------------------------------------------------------------
# Published answers (.adj files of the Krumm examples)
# --------------------------------------------------------------------------------------------
def read_adj(path) -> dict[str, dict[str, float]]:
    """Read a Krumm ``.adj`` file of published adjusted coordinates.

    Returns ``{id: {...}}`` with, for 2D lines (8 tokens) ``x, dx_cm, sx_cm, y, dy_cm, sy_cm,
    sp_cm``; for 3D lines (11 tokens) additionally ``z, dz_cm, sz_cm``; for 1D lines (4 tokens)
    ``h, dh_mm, sh_mm``. Comment lines (``#``) and XML are skipped.
    """
    text = read_file_text(path, encoding="utf-8", max_bytes=MAX_TABLE_FILE_BYTES, what="Krumm .adj file")
    out = {}
    for raw in text.splitlines():
        line = raw.strip().replace("−", "-")
        if not line or line.startswith("#") or line.startswith("<"):
            continue
        tok = line.split()
        try:
            vals = [float(t) for t in tok[1:]]
        except ValueError:
            continue
        if len(vals) == 7:
            out[tok[0]] = dict(
                zip(("x", "dx_cm", "sx_cm", "y", "dy_cm", "sy_cm", "sp_cm"), vals, strict=True)
            )
        elif len(vals) == 10:
            out[tok[0]] = dict(
                zip(
                    ("x", "dx_cm", "sx_cm", "y", "dy_cm", "sy_cm", "z", "dz_cm", "sz_cm", "sp_cm"),
                    vals,
                    strict=True,
                )
            )
        elif len(vals) == 3:
            out[tok[0]] = dict(zip(("h", "dh_mm", "sh_mm"), vals, strict=True))
    return out
