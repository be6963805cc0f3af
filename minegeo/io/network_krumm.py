"""Survey networks in the Krumm "Geodetic Network Adjustment Examples" text format (GNU Gama examples).

The format (see ``docs/survey.md`` and the README of ``shared/data/krumm_gama_adjustment_examples``):
sections ``[Coordinates]``, ``[Datum]``, ``[Sigma0]``, ``[Distances]``, ``[HorizontalDistances]``,
``[SpatialDistances]``, ``[Directions]``, ``[ApproximateOrientation]``, ``[Angles]``/``[Winkel]``,
``[Azimuth]``, ``[GridBearings]``, ``[ZenithAngles]``, ``[VerticalAngles]``,
``[LevelledHeightDifferences]``, ``[TrigonometricHeightDifferences]``,
``[3DBaseline]``/``[3DBasislinie]``, ``[Restrictions]``. Angle sections are in gon unless the
header says ``dms``; ``s`` means the standard deviations are in arc-seconds. A missing standard
deviation repeats the previous line's. ``%`` starts a comment, and so does ``#`` at the start of a
line or after white space.

Line layouts (standard deviations are absolute a-priori values)::

    [Angles]                     at from to value [sigma]
    [Distances]                  from to value [sigma_c [sigma_s]]   σ² = σ_c² + s[m]·σ_s²
    [Directions] and other angles from to value [sigma [hi ht]]       one set per station run
    [LevelledHeightDifferences]  from to dh length_m [sigma_km]      σ = σ_km·sqrt(L / 1 km)
    [3DBaseline]                 from to dx dy dz [3 std devs | 6 (upper triangle) | 9 cov values]

An ``[Azimuth]`` line without a standard deviation is an errorless azimuth to a point without
coordinates (a traverse connection). The ``[Sigma0]`` line is recorded, not used (see
:mod:`minegeo.survey.network`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io.angles import RHO_ARCSEC, parse_angle, wrap_2pi
from minegeo.io.limits import MAX_ABS_COORDINATE
from minegeo.io.network_types import (
    ANGULAR,
    AXES,
    Datum,
    Network,
    Observation,
    check_precisions,
    coord_tokens,
    dimension,
)

__all__ = ["parse_krumm"]

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

#: largest absolute angle (rad) read from a network file: a few turns are normal
_MAX_ANGLE_RAD = 1e6


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


def _no_sigma(path, lineno: int) -> FileFormatError:
    return FileFormatError(path, f"line {lineno}: no standard deviation given (and none before)")


def _split_sections(text: str, path) -> list[tuple[str, list[str], list[tuple[int, str]]]]:
    """``[(name, options, [(line number, line)])]`` with comments and blank lines removed."""
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
    return sections


@dataclass
class _Parsed:
    """What the sections of one file add up to."""

    points: dict = field(default_factory=dict)
    obs: list = field(default_factory=list)
    known_az: dict = field(default_factory=dict)
    restrictions: list = field(default_factory=list)
    datum_lines: list = field(default_factory=list)
    sigma0_text: str = ""
    name: str = ""
    description_lines: list = field(default_factory=list)
    set_counter: int = 0  # direction sets, numbered over the whole file


@dataclass
class _Section:
    """One observation section while its lines are read (a missing sigma repeats the last one)."""

    key: str
    kind: str
    vunit: str
    sunit: str
    last_sigma: object = None
    last_station: str | None = None


def _read_coordinates(sname: str, opts: list[str], lines, points: dict, path) -> None:
    if any(o.lower().startswith(("bdms", "ldms", "b", "l")) for o in opts):
        raise FileFormatError(path, f"section [{sname},{','.join(opts)}]: geographic coordinates are not supported")
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


def _read_section(sname: str, opts: list[str], lines, acc: _Parsed, path) -> None:
    """Add one section of the file to ``acc``."""
    key = sname.lower()
    if key in ("project",):
        acc.name = " ".join(t for _, t in lines).strip()
        return
    if key in ("source", "quelle"):
        acc.description_lines.extend(t.strip() for _, t in lines)
        return
    if key == "graphics":
        return
    if key in _UNSUPPORTED:
        raise FileFormatError(path, f"section [{sname}]: {_UNSUPPORTED[key]}")
    if key == "coordinates":
        _read_coordinates(sname, opts, lines, acc.points, path)
        return
    if key == "datum":
        acc.datum_lines.extend(lines)
        return
    if key == "sigma0":
        acc.sigma0_text = " ".join(t.strip() for _, t in lines)
        return
    if key == "approximateorientation":
        return  # orientations are computed from the approximate coordinates
    if key == "restrictions":
        acc.restrictions.extend(t.strip() for _, t in lines)
        return
    if key not in _SECTION_KIND:
        raise FileFormatError(path, f"unknown section [{sname}]")
    kind = _SECTION_KIND[key]
    sec = _Section(key, kind, *_angle_units(opts))
    for lineno, t in lines:
        o = _observation(t, lineno, sec, acc, path)
        if o is not None:
            acc.obs.append(o)


def _observation(t: str, lineno: int, sec: _Section, acc: _Parsed, path) -> Observation | None:
    """One observation line; None for an errorless azimuth (recorded in ``acc.known_az``)."""
    kind = sec.kind
    tok = t.split()
    if len(tok) > _MAX_TOKENS.get(kind, 6):
        raise FileFormatError(
            path, f"line {lineno}: {len(tok)} values, more than a {kind.replace('_', ' ')} line has "
            f"({_LAYOUT.get(kind, 'from to value [sigma [hi ht]]')}): a damaged or misplaced line?"
        )
    if kind == "angle":
        return _angle_observation(tok, lineno, sec, path)
    if len(tok) < 3:
        raise FileFormatError(path, f"line {lineno}: expected 'from to value ...', got {t.strip()!r}")
    if kind == "baseline":
        return _baseline_observation(tok, lineno, sec, path)
    if kind in ANGULAR:
        return _angular_observation(tok, lineno, sec, acc, path)
    val = _num(tok[2], path, lineno, "observed value")
    rest = [_num(v, path, lineno, "value") for v in tok[3:]]
    if kind == "height_difference":
        return _levelling_observation(tok, val, rest, lineno, sec, path)
    return _linear_observation(tok, val, rest, lineno, sec, path)


def _angle_observation(tok: list[str], lineno: int, sec: _Section, path) -> Observation:
    """``at from to value [sigma]``: a horizontal angle from backsight to foresight."""
    if len(tok) < 4:
        raise FileFormatError(path, f"line {lineno}: angle needs 'at from to value [sigma]'")
    st, bs, fs = tok[0], tok[1], tok[2]
    val = _angle(tok[3], sec.vunit, path, lineno)
    rest = tok[4:]
    sig = _sigma_angle(rest[0], sec.sunit, path, lineno) if rest else sec.last_sigma
    if sig is None:
        raise _no_sigma(path, lineno)
    sec.last_sigma = sig
    return Observation("angle", st, fs, wrap_2pi(val), sig, backsight=bs, unit=sec.vunit, line=lineno)


def _baseline_observation(tok: list[str], lineno: int, sec: _Section, path) -> Observation:
    """``from to dx dy dz [precision]``: a GNSS baseline with its 3×3 covariance (m²)."""
    st, tg = tok[0], tok[1]
    if len(tok) < 5:
        raise FileFormatError(path, f"line {lineno}: baseline needs 'from to dx dy dz [sigmas|cov]'")
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
    elif not extra and sec.last_sigma is not None:
        cov = sec.last_sigma
    else:
        raise FileFormatError(
            path,
            f"line {lineno}: baseline precision must be 3 std devs, 6 (upper triangle) or 9 covariance values",
        )
    sec.last_sigma = cov
    return Observation("baseline", st, tg, val, cov, unit="m", line=lineno)


def _angular_observation(tok: list[str], lineno: int, sec: _Section, acc: _Parsed, path) -> Observation | None:
    """Directions, azimuths, zenith and vertical angles: ``from to value [sigma [hi ht]]``."""
    kind = sec.kind
    st, tg = tok[0], tok[1]
    val = _angle(tok[2], sec.vunit, path, lineno)
    rest = tok[3:]
    if len(rest) == 2:
        raise FileFormatError(
            path, f"line {lineno}: give both instrument and target height (from to value sigma hi ht)"
        )
    sig = _sigma_angle(rest[0], sec.sunit, path, lineno) if rest else None
    hi = ht = 0.0
    if len(rest) >= 3:
        hi, ht = (
            _num(rest[1], path, lineno, "instrument height"),
            _num(rest[2], path, lineno, "target height"),
        )
    if kind == "azimuth" and sig is None and sec.key == "azimuth":
        acc.known_az[(st, tg)] = wrap_2pi(val)
        return None
    if sig is None:
        sig = sec.last_sigma
    if sig is None:
        raise _no_sigma(path, lineno)
    sec.last_sigma = sig
    set_id = None
    if kind == "direction":
        if st != sec.last_station:
            acc.set_counter += 1
        set_id = acc.set_counter
        sec.last_station = st
        val = wrap_2pi(val)
    return Observation(kind, st, tg, val, sig, set_id=set_id, hi=hi, ht=ht, unit=sec.vunit, line=lineno)


def _levelling_observation(tok, val: float, rest: list[float], lineno: int, sec: _Section, path) -> Observation:
    """``from to dh length_m [sigma_km]``; σ = σ_km·sqrt(L / 1 km)."""
    if not rest:
        raise FileFormatError(path, f"line {lineno}: levelling needs 'from to dh length_m [sigma_km]'")
    length = rest[0]
    if length < 0:
        raise FileFormatError(path, f"line {lineno}: levelling length {length} m must not be negative")
    skm = rest[1] if len(rest) > 1 else sec.last_sigma
    if skm is None:
        raise FileFormatError(path, f"line {lineno}: no standard deviation per km given (and none before)")
    sec.last_sigma = skm
    sig = skm * math.sqrt(length / 1000.0)
    return Observation(sec.kind, tok[0], tok[1], val, sig, unit="m", line=lineno)


def _linear_observation(tok, val: float, rest: list[float], lineno: int, sec: _Section, path) -> Observation:
    """Distances (``[sigma_c [sigma_s]]``), slope distances and trigonometric height differences."""
    kind = sec.kind
    hi = ht = 0.0
    if kind == "distance":
        if val < 0:
            raise FileFormatError(path, f"line {lineno}: distance {tok[2]!r} must not be negative")
        if len(rest) >= 2:
            # README: sigma² = sigma_c² + s[m]·sigma_s²
            sig = math.sqrt(rest[0] ** 2 + val * rest[1] ** 2)
            sec.last_sigma = (rest[0], rest[1])
        elif len(rest) == 1:
            sig = rest[0]
            sec.last_sigma = rest[0]
        else:
            last = sec.last_sigma
            if last is None:
                raise _no_sigma(path, lineno)
            sig = math.sqrt(last[0] ** 2 + val * last[1] ** 2) if isinstance(last, tuple) else last
    else:
        if len(rest) == 2:
            raise FileFormatError(
                path, f"line {lineno}: give both instrument and target height (from to value sigma hi ht)"
            )
        sig = rest[0] if rest else sec.last_sigma
        if sig is None:
            raise _no_sigma(path, lineno)
        sec.last_sigma = sig
        if len(rest) >= 3:
            hi, ht = rest[1], rest[2]
    return Observation(kind, tok[0], tok[1], val, sig, hi=hi, ht=ht, unit="m", line=lineno)


def parse_krumm(text: str, source: str = "<text>") -> Network:
    """Parse a network in the Krumm text format (see the module docstring).

    Parameters
    ----------
    text : str
        The file's text.
    source : str
        Name used in error messages and recorded as :attr:`Network.source`.

    Returns
    -------
    Network

    Raises
    ------
    FileFormatError
        Unknown or unsupported section, malformed line (the line number is given).
    """
    path = source
    acc = _Parsed()
    for sname, opts, lines in _split_sections(text, path):
        _read_section(sname, opts, lines, acc, path)
    if not acc.points:
        raise FileFormatError(path, "no [Coordinates] section (approximate coordinates are required)")
    if not acc.obs:
        raise FileFormatError(path, "no observations")
    dim = dimension(acc.obs)
    datum = _parse_datum(acc.datum_lines, acc.points, dim, path)
    return check_precisions(Network(
        points=acc.points,
        datum=datum,
        observations=acc.obs,
        dim=dim,
        known_azimuths=acc.known_az,
        restrictions=acc.restrictions,
        sigma0_text=acc.sigma0_text,
        name=acc.name,
        description="\n".join(acc.description_lines),
        source=str(source),
    ))


def _parse_datum(lines, points, dim, path) -> Datum:
    """The ``[Datum]`` section: ``fix <coords>``, ``free [<coords>]`` or ``dyn`` with a-priori precisions.

    ``dyn`` rows are ``<coord> sigma`` (independent coordinates) or ``<coord> c_i1 ... c_ii`` /
    a full row of the covariance matrix (m²).
    """
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
                coords.extend(coord_tokens(tok, points, dim, path, lineno))
        return Datum("fix", tuple(dict.fromkeys(coords)))
    if kind in ("free", "fre"):
        coords = []
        for lineno, t in [(lines[0][0], " ".join(first[1:]))] + lines[1:]:
            for tok in t.replace(",", " ").split():
                coords.extend(coord_tokens(tok, points, dim, path, lineno))
        if not coords:
            coords = [(p, a) for p in points for a in AXES[dim]]
        return Datum("free", tuple(dict.fromkeys(coords)))
    if kind in ("dyn", "dynamic"):
        rows = []
        for lineno, t in lines[1:] + ([(lines[0][0], " ".join(first[1:]))] if len(first) > 1 else []):
            tok = t.split()
            rows.append((lineno, tok[0], [_num(v, path, lineno, "datum precision") for v in tok[1:]]))
        names = []
        for lineno, tok0, _ in rows:
            c = coord_tokens(tok0, points, dim, path, lineno)
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
