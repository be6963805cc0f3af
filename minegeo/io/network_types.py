"""Survey-network records: :class:`Observation`, :class:`Datum` and :class:`Network`.

What the network readers (:mod:`minegeo.io.network_krumm`, :mod:`minegeo.io.network_json`,
:func:`minegeo.io.network.read_network`) return and what :func:`minegeo.survey.adjust_network`
adjusts; the observation equations are in :mod:`minegeo.survey.network`. Units: metres and
radians; coordinates ``x`` = Easting, ``y`` = Northing, ``z`` = height. All precisions are
absolute a-priori standard deviations (a baseline carries its 3×3 covariance, m²).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import FileFormatError
from minegeo.io.limits import MIN_SIGMA_M

__all__ = ["KINDS", "ANGULAR", "DIM1", "DIM2", "DIM3", "AXES", "Observation", "Datum", "Network", "dimension",
           "coord_tokens", "check_precisions"]

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
#: Angular kinds (residuals reduced to [-π, π), values in radians)
ANGULAR = {"direction", "angle", "azimuth", "zenith_angle", "vertical_angle"}
#: Kinds that make a network 3D, 2D (plane) or 1D (heights)
DIM3 = {"spatial_distance", "zenith_angle", "vertical_angle", "baseline"}
DIM2 = {"distance", "direction", "angle", "azimuth"}
DIM1 = {"height_difference", "trig_height_difference"}
#: Coordinate axes of a 1D, 2D or 3D network
AXES = {1: ("z",), 2: ("x", "y"), 3: ("x", "y", "z")}


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
        """The coordinate axes of the network: ``("z",)``, ``("x", "y")`` or ``("x", "y", "z")``."""
        return AXES[self.dim]


def dimension(observations) -> int:
    """3 when any observation needs heights and plane coordinates, else 2 when any is planar, else 1."""
    kinds = {o.kind for o in observations}
    if kinds & DIM3:
        return 3
    if kinds & DIM2:
        return 2
    return 1


def coord_tokens(tok: str, points: dict, dim: int, path, lineno) -> list[tuple[str, str]]:
    """The ``(point, axis)`` coordinates a datum entry names.

    ``x<pt>``, ``y<pt>``, ``z<pt>`` or ``H<pt>`` name one coordinate (in a 1D network always the
    height); a bare point name every axis of the network. Separators ``,;`` are stripped; an
    empty token names nothing.

    Raises
    ------
    FileFormatError
        The token is neither a point nor an axis letter followed by a point (``line`` names it).
    """
    tok = tok.strip(",;")
    if not tok:
        return []
    if tok[0] in "xyzXYZH" and tok[1:] in points and tok not in points:
        ax = {"x": "x", "y": "y", "z": "z", "h": "z"}[tok[0].lower()]
        if dim == 1:
            ax = "z"
        return [(tok[1:], ax)]
    if tok in points:
        return [(tok, a) for a in AXES[dim]]
    raise FileFormatError(
        path, f"line {lineno}: [Datum] names {tok!r}, which is neither a point nor x/y/z<point>"
    )


def check_precisions(net: Network) -> Network:
    """Refuse a-priori precisions so small that their weights overflow float64.

    A positive standard deviation below :data:`~minegeo.io.limits.MIN_SIGMA_M` (m or rad;
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
