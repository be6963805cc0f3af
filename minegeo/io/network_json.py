"""Survey networks as JSON: the documented structure of ``docs/survey.md``.

:func:`network_from_dict` builds a :class:`~minegeo.io.network_types.Network` from the parsed JSON
(a ``dict``); :func:`minegeo.io.network.read_network` reads ``.json`` files with it. Angles are
given with their unit in the member name (``value_dms``, ``sigma_arcsec``, ``value_gon``, ...),
lengths in metres (``value_m``, ``sigma_m``), a baseline's covariance in m² (``cov_m2``). Every
member is checked (type, finiteness, range) and a mistake names where it is.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io.angles import parse_angle, wrap_2pi
from minegeo.io.limits import MAX_ABS_COORDINATE
from minegeo.io.network_types import (
    ANGULAR,
    AXES,
    KINDS,
    Datum,
    Network,
    Observation,
    check_precisions,
    coord_tokens,
    dimension,
)

__all__ = ["network_from_dict"]


def _json_angle(d: dict, key: str, where: str) -> tuple[float, str]:
    """``(radians, unit)`` of the member ``key_<unit>`` (dms, gon, deg, rad, arcsec, mgon) of ``d``."""
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
        :data:`~minegeo.io.limits.MAX_ABS_COORDINATE` are refused.
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
    points = _json_points(pts_in)
    obs = _json_observations(obs_in, source)
    dim = d.get("dimension", dimension(obs))
    if dim not in (1, 2, 3) or isinstance(dim, bool):
        raise InputError(f"'dimension' must be 1, 2 or 3, got {dim!r}")
    dim = int(dim)
    datum = _json_datum(_jobj(d.get("datum", {"type": "fix", "coordinates": []}), "'datum'"), points, dim, source)
    known = _json_known_azimuths(_jlist(d.get("known_azimuths", []), "'known_azimuths'"))
    restrictions = _jlist(d.get("restrictions", []), "'restrictions'")
    if not all(isinstance(r, str) for r in restrictions):
        raise InputError("'restrictions' must be a list of text expressions")
    return check_precisions(Network(
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


def _json_points(pts_in: dict) -> dict:
    """``{"P": {"x": .., "y": .., "h" | "z": ..}}`` -> ``{"P": {"x", "y", "z"}}`` (members given)."""
    points = {}
    for pid, c in pts_in.items():
        c = _jobj(c, f"point {pid!r}")
        p = {}
        for k_in, k in (("x", "x"), ("y", "y"), ("h", "z"), ("z", "z")):
            if k_in in c and c[k_in] is not None:
                p[k] = _jnum(c[k_in], f"point {pid!r} {k_in}")
        points[str(pid)] = p
    return points


def _json_observations(obs_in: list, source: str) -> list[Observation]:
    """The ``observations`` list; directions are grouped in sets by ``set`` (default: the station)."""
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
        if kind in ANGULAR:
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
    return obs


def _json_datum(dd: dict, points: dict, dim: int, source: str) -> Datum:
    """``{"type": "fix" | "free", "coordinates": [...]}`` or ``{"type": "dyn", "sigma_m": {...}}``
    (or ``"coordinates"`` with a full ``"cov_m2"``)."""
    dt = dd.get("type", "fix")
    if dt == "dyn":
        coords, sig = [], []
        for k, v in _jobj(dd.get("sigma_m", {}), "datum sigma_m").items():
            for c in coord_tokens(k, points, dim, source, 0):
                coords.append(c)
                sig.append(_jnum(v, f"datum sigma_m {k!r}"))
        if "cov_m2" in dd:
            names = _jlist(_jget(dd, "coordinates", "datum with cov_m2"), "datum coordinates")
            coords = [c for k in names for c in coord_tokens(_jid(k, "datum coordinate"), points, dim, source, 0)]
            cov = _jmatrix(dd["cov_m2"], (len(coords), len(coords)), "datum cov_m2")
        else:
            cov = np.diag(np.square(sig))
        return Datum("dyn", tuple(coords), cov)
    if dt in ("fix", "free"):
        names = _jlist(dd.get("coordinates", []), "datum coordinates")
        coords = [c for k in names for c in coord_tokens(_jid(k, "datum coordinate"), points, dim, source, 0)]
        if dt == "free" and not coords:
            coords = [(p, a) for p in points for a in AXES[dim]]
        return Datum(dt, tuple(dict.fromkeys(coords)))
    raise FileFormatError(source, f"datum type must be fix, free or dyn, got {dt!r}")


def _json_known_azimuths(items: list) -> dict:
    """``[{"from": "B", "to": "A", "value_dms": ...}]`` -> ``{(from, to): azimuth rad}``."""
    known = {}
    for j, k in enumerate(items):
        where = f"known_azimuths[{j}]"
        k = _jobj(k, where)
        val, _ = _json_angle(k, "value", where)
        known[(_jid(_jget(k, "from", where), f"{where} 'from'"), _jid(_jget(k, "to", where), f"{where} 'to'"))] = (
            wrap_2pi(val)
        )
    return known
