"""Angle tokens of survey text files: DMS, gon, degrees, radians, arc-seconds -> radians.

The network readers of :mod:`minegeo.io` (Krumm/Gama text, JSON) convert the angles they read
here, so that :mod:`minegeo.io` needs nothing from :mod:`minegeo.survey` (which imports the
readers). :mod:`minegeo.survey.angles` documents the conventions and holds the rest of the
angle toolbox (formatting, azimuths, bearings).
"""

from __future__ import annotations

import math
import re

import numpy as np

from minegeo.errors import InputError

__all__ = ["RHO_ARCSEC", "parse_dms", "parse_angle", "wrap_2pi"]

#: Arc-seconds per radian (ρ″ = 206 264.806…).
RHO_ARCSEC = 180.0 * 3600.0 / math.pi

_TWO_PI = 2.0 * math.pi


# degrees, then optional minutes, then optional seconds; separators ° d - : ' ′ m " ″ s or spaces
_DMS_RE = re.compile(
    r"""^\s*(?P<sign>[+-])?\s*
        (?P<d>\d+(?:\.\d*)?)\s*(?:°|º|d|deg|-|:|\s)?\s*
        (?:(?P<m>\d+(?:\.\d*)?)\s*(?:'|′|m|min|-|:|\s)?\s*)?
        (?:(?P<s>\d+(?:\.\d*)?)\s*(?:"|″|''|s|sec)?\s*)?$""",
    re.VERBOSE,
)


def parse_dms(text: str) -> float:
    """Parse a degrees-minutes-seconds string and return **decimal degrees**.

    Accepted forms: ``355°10'02.8"``, ``355d10m02.8s``, ``355-10-02.8``, ``355:10:02.8``,
    ``355 10 02.8``, ``240°``, ``0°6'24.5"``, with an optional leading sign. Minutes and
    seconds must be below 60.

    Raises
    ------
    InputError
        The text is not a DMS angle (the message quotes it).

    Examples
    --------
    >>> round(parse_dms("355°10'02.8\\""), 9)
    355.167444444
    """
    if not isinstance(text, str):
        raise InputError(f"DMS angle must be text, got {type(text).__name__}")
    t = text.strip().replace("’", "'").replace("”", '"')
    m = _DMS_RE.match(t)
    if not m or (m.group("m") is None and m.group("s") is not None):
        raise InputError(f"cannot read {text!r} as degrees-minutes-seconds (expected e.g. 355°10'02.8\")")
    d = float(m.group("d"))
    mi = float(m.group("m")) if m.group("m") else 0.0
    s = float(m.group("s")) if m.group("s") else 0.0
    if mi >= 60.0 or s >= 60.0:
        raise InputError(f"minutes and seconds must be below 60 in {text!r}")
    if (m.group("m") and "." in m.group("d")) or (m.group("s") and m.group("m") and "." in m.group("m")):
        raise InputError(f"only the last DMS field may have decimals in {text!r}")
    val = d + mi / 60.0 + s / 3600.0
    return -val if m.group("sign") == "-" else val


def parse_angle(text, unit: str = "dms") -> float:
    """Parse an angle given as text or number in ``unit`` and return **radians**.

    Parameters
    ----------
    text : str or float
        The angle. Numbers are accepted for ``deg``, ``gon``, ``rad`` and ``arcsec``.
    unit : {"dms", "deg", "gon", "rad", "arcsec", "mgon"}
        Unit of ``text``. ``dms`` accepts the forms of :func:`parse_dms`.
    """
    u = unit.lower()
    if u == "dms":
        return math.radians(parse_dms(str(text)))
    try:
        val = float(str(text).strip().rstrip('"″'))
    except ValueError:
        raise InputError(f"cannot read {text!r} as an angle in {unit}") from None
    if u == "deg":
        return math.radians(val)
    if u == "gon":
        return val * math.pi / 200.0
    if u == "mgon":
        return val * math.pi / 200000.0
    if u == "rad":
        return val
    if u in ("arcsec", "s", "sec"):
        return val / RHO_ARCSEC
    raise InputError(f"unknown angle unit {unit!r}; use dms, deg, gon, mgon, rad or arcsec")


def wrap_2pi(a):
    """Reduce angle(s) to ``[0, 2π)``."""
    r = np.mod(a, _TWO_PI)
    if np.ndim(r) == 0:
        r = float(r)
        return 0.0 if r >= _TWO_PI else r
    r[r >= _TWO_PI] = 0.0
    return r
