"""The result of the up-direction estimate (:class:`UpEstimate`, its candidates and evidence) and the levelling rotation.

All angles are in degrees unless the name says ``rad``; every vector is in the frame of the input
points (the *scan* frame). See :mod:`minegeo.localize.gravity` for the method.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from enum import StrEnum

import numpy as np

from minegeo._validate import check_positive
from minegeo.errors import InputError
from minegeo.localize.params import GravityParams


class UpStatus(StrEnum):
    """Status of an up-direction estimate (:attr:`UpEstimate.status`); each member is its string value."""

    OK = "ok"
    #: a distinct rival floor scores ``ambiguity_ratio`` of the floor's
    AMBIGUOUS = "ambiguous"
    #: the scan shows no floor: no estimate
    FAILED = "failed"


#: Possible values of :attr:`UpEstimate.status`.
STATUSES = tuple(UpStatus)
_EPS_VAR = 1e-24  # rad^2 added before inverting a jackknife covariance (noise-free inputs give 0)


@dataclass(frozen=True)
class UpCandidate:
    """One up hypothesis (scan frame).

    Attributes
    ----------
    up : (3,) float64
        Unit vector.
    source : str
        ``"estimate"`` (the fused answer), ``"floor"`` (floor normal: level hypothesis),
        ``"walls"`` (walls alone, when they fix both components), or ``"plane"`` (a rival
        plane of the floor detection, its void-side normal).
    score : float
        Floor signature of the direction (:func:`_column_score`;
        NaN for ``"walls"``).
    sigma_deg : float
        1-sigma angle (largest axis; NaN when not estimated).
    note : str
    """

    up: np.ndarray
    source: str
    score: float
    sigma_deg: float
    note: str = ""


@dataclass(frozen=True)
class UpEvidence:
    """What the estimate rests on (fractions are of the scan's area; vectors in the scan frame).

    Attributes
    ----------
    floor_fraction : float
        Fraction within ``plane_band_m`` of the floor plane.
    floor_score : float
        Floor signature of the chosen plane (see :func:`_column_score`; 0 for a wall or a shaft,
        about 0.1-0.3 for a horseshoe drift's floor).
    void_fraction : float
        Fraction on the void side of the floor (above it).
    floor_normal : (3,) float64
        Refined floor normal (up if the floor is level).
    floor_rms_m : float
        Weighted RMS of the floor points' heights about the floor plane.
    wall_fraction : float
        Weight fraction of the wall surfels used.
    wall_verticality_rms_deg : float
        Weighted RMS of ``asin(n . up)`` over the wall surfels (0 for exactly vertical walls).
    wall_spread : float
        Smallest / largest eigenvalue of the walls' 2x2 normal matrix (0: straight drift,
        0.5: normals all around).
    walls_slope_deg : float
        Where the walls are seen in several directions (``wall_spread >= min_wall_spread``):
        the floor's tilt about the cross axis relative to the walls-alone up, i.e. the slope
        they suggest (NaN otherwise). Evidence only: on rough rock it is off by several
        degrees (see docs/localization.md), so it neither moves ``up`` nor narrows the search.
    walls_slope_sigma_deg : float
        Its jackknife 1-sigma.
    drift_axis : (3,) float64
        Principal horizontal direction of the scan (perpendicular to ``up``).
    cross_axis : (3,) float64
        ``up x drift_axis``: the residual-tilt axis.
    rival_ratio : float
        Best distinct rival floor's score / the floor's score (0 when none).
    n_points_used : int
        Size of the area-uniform sample.
    n_blocks : int
        Jackknife blocks.
    """

    floor_fraction: float
    floor_score: float
    void_fraction: float
    floor_normal: np.ndarray
    floor_rms_m: float
    wall_fraction: float
    wall_verticality_rms_deg: float
    wall_spread: float
    walls_slope_deg: float
    walls_slope_sigma_deg: float
    drift_axis: np.ndarray
    cross_axis: np.ndarray
    rival_ratio: float
    n_points_used: int
    n_blocks: int


@dataclass(frozen=True)
class UpEstimate:
    """Result of :func:`estimate_up` (all vectors in the scan frame, angles in degrees).

    Attributes
    ----------
    status : UpStatus
        ``ok``, ``ambiguous`` or ``failed``.
    reason : str
        One line a surveyor can act on.
    up : (3,) float64 or None
        Unit up vector (None when ``failed``).
    tangent_basis : (2, 3) float64 or None
        Rows ``t_along`` (= ``cross_axis x up``: tilting up towards the drift axis) and
        ``t_across`` (= ``cross_axis``); a small error of ``up`` is
        ``delta_along t_along + delta_across t_across`` (rad).
    covariance_rad2 : (2, 2) float64 or None
        Covariance of ``(delta_along, delta_across)`` (rad^2), under the level-floor hypothesis
        unless the walls fix the along component.
    covariance_3d_rad2 : (3, 3) float64 or None
        The same as a (rank 2) covariance of the ``up`` vector.
    sigma_deg : float
        1-sigma angle: square root of the largest eigenvalue of ``covariance_rad2``.
    cone95_deg : float
        Half-angle of the cone around ``up`` that holds the 95 % ellipse
        (``sqrt(r95^2 lambda_max)``, Hotelling's ``r95^2``, see the module docstring).
    r95_squared : float
        The Mahalanobis radius^2 of the 95 % ellipse.
    tilt_axis : (3,) float64 or None
        Axis of the residual-tilt search (the drift's cross axis).
    tilt_range_deg : (float, float)
        Search ``R(tilt_axis, theta) up`` for ``theta`` in this range (right-handed about
        ``tilt_axis``): the truth is within ``tilt_tolerance_deg`` of it when the floor is a
        ramp of at most ``max_slope_deg``.
    tilt_tolerance_deg : float
        95 % half-width of the search tube across the drift (at least 0.001 deg).
    candidates : tuple of UpCandidate
        The estimate, the floor (level) hypothesis, the walls' (if any) and the rival planes.
    evidence : UpEvidence or None
    params : GravityParams
    timings_s : dict
    """

    status: UpStatus
    reason: str
    up: np.ndarray | None
    tangent_basis: np.ndarray | None
    covariance_rad2: np.ndarray | None
    covariance_3d_rad2: np.ndarray | None
    sigma_deg: float
    cone95_deg: float
    r95_squared: float
    tilt_axis: np.ndarray | None
    tilt_range_deg: tuple
    tilt_tolerance_deg: float
    candidates: tuple
    evidence: UpEvidence | None
    params: GravityParams
    timings_s: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when ``status == "ok"``."""
        return self.status == "ok"

    def levelling_rotation(self, up=None) -> np.ndarray:
        """Rotation ``R_levelled_scan`` (3x3) that maps ``up`` (default: the estimate) onto +z.

        See :func:`levelling_rotation`.
        """
        if up is None:
            if self.up is None:
                raise InputError(f"no up estimate ({self.status}: {self.reason})")
            up = self.up
        return levelling_rotation(up)

    def tilt_candidates(self, step_deg: float = 2.0) -> np.ndarray:
        """Up vectors of the residual-tilt search, (k, 3), from ``tilt_range_deg`` in ``step_deg`` steps.

        The range's ends are included; 0 (the estimate itself) is always one of them.
        """
        check_positive(step_deg, "step_deg")
        if self.up is None or self.tilt_axis is None:
            raise InputError(f"no up estimate ({self.status}: {self.reason})")
        lo, hi = self.tilt_range_deg
        thetas = np.unique(np.concatenate([np.arange(0.0, lo, -step_deg), np.arange(0.0, hi, step_deg), [lo, hi]]))
        return np.array([_rotate(self.up, self.tilt_axis, math.radians(t)) for t in thetas])

    def assess(self, up_true) -> dict:
        """Compare with a known up (evaluation only): angle, Mahalanobis distance, coverage.

        Returns
        -------
        dict
            ``angle_deg``; ``mahalanobis2`` of ``(delta_along, delta_across)``; ``in_ellipse95``
            (``mahalanobis2 <= r95_squared``); ``in_cone95`` (``angle_deg <= cone95_deg``);
            ``tilt_deg`` (rotation about ``tilt_axis`` that best brings ``up`` to it) and
            ``cross_deg`` (what remains); ``in_search`` (tilt within ``tilt_range_deg`` and
            ``|cross_deg| <= tilt_tolerance_deg``).
        """
        u = np.asarray(up_true, dtype=np.float64).reshape(3)
        u = u / np.linalg.norm(u)
        if self.up is None:
            return {"angle_deg": math.nan, "mahalanobis2": math.nan, "in_ellipse95": False, "in_cone95": False,
                    "tilt_deg": math.nan, "cross_deg": math.nan, "in_search": False}
        ang = math.degrees(math.acos(min(1.0, max(-1.0, float(u @ self.up)))))
        ta, tc = self.tangent_basis
        d = np.array([math.atan2(float(u @ ta), float(u @ self.up)), math.asin(min(1.0, max(-1.0, float(u @ tc))))])
        C = self.covariance_rad2 + _EPS_VAR * np.eye(2)
        m2 = float(d @ np.linalg.solve(C, d))
        tilt = math.degrees(d[0])
        cross = math.degrees(d[1])
        lo, hi = self.tilt_range_deg
        return {"angle_deg": ang, "mahalanobis2": m2, "in_ellipse95": m2 <= self.r95_squared,
                "in_cone95": ang <= self.cone95_deg, "tilt_deg": tilt, "cross_deg": cross,
                "in_search": (lo <= tilt <= hi) and abs(cross) <= self.tilt_tolerance_deg}

    def to_dict(self) -> dict:
        """JSON-ready dictionary (arrays as lists)."""

        def conv(v):
            if isinstance(v, np.ndarray):
                return v.tolist()
            if isinstance(v, (np.floating, np.integer, np.bool_)):
                return v.item()
            if isinstance(v, dict):
                return {k: conv(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [conv(x) for x in v]
            return v

        d = {k: getattr(self, k) for k in ("status", "reason", "up", "tangent_basis", "covariance_rad2",
                                           "covariance_3d_rad2", "sigma_deg", "cone95_deg", "r95_squared",
                                           "tilt_axis", "tilt_range_deg", "tilt_tolerance_deg", "timings_s")}
        d["candidates"] = [asdict(c) for c in self.candidates]
        d["evidence"] = None if self.evidence is None else asdict(self.evidence)
        d["params"] = asdict(self.params)
        d["frame"] = "scan"
        return conv(d)


# ---------------------------------------------------------------------------------------------- helpers

def hotelling_r2_95(g: int) -> float:
    """Squared Mahalanobis radius of a 95 % region for a 2-vector whose covariance is a
    jackknife over ``g`` blocks (``g - 1`` degrees of freedom): Hotelling's
    ``T^2 = 2 (g - 1) / (g - 2) F_{2, g-2}(0.95)``, with the closed-form F quantile
    ``F_{2, nu}(p) = nu / 2 ((1 - p)^(-2 / nu) - 1)``."""
    if g < 4:
        raise InputError(f"need at least 4 blocks, got {g}")
    nu = g - 2
    f = nu / 2.0 * (0.05 ** (-2.0 / nu) - 1.0)
    return 2.0 * (g - 1) / nu * f


def levelling_rotation(up) -> np.ndarray:
    """The smallest rotation ``R`` (3x3) with ``R @ up = [0, 0, 1]`` (Rodrigues' formula).

    Parameters
    ----------
    up : (3,) array_like
        Up direction in the scan frame (need not be unit length).

    Returns
    -------
    (3, 3) float64
        ``R_levelled_scan``: ``p_levelled = R p_scan`` has z up; its heading is arbitrary (the
        levelled search solves for it).
    """
    u = np.asarray(up, dtype=np.float64).reshape(3)
    nu = float(np.linalg.norm(u))
    if not np.isfinite(nu) or nu == 0.0:
        raise InputError("up must be a finite non-zero 3-vector")
    u = u / nu
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s = float(np.linalg.norm(v))
    c = float(u @ z)
    if s < 1e-15:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K * ((1.0 - c) / (s * s))


def _rotate(v: np.ndarray, axis: np.ndarray, ang: float) -> np.ndarray:
    """Rodrigues rotation of ``v`` about the unit ``axis`` by ``ang`` rad."""
    c, s = math.cos(ang), math.sin(ang)
    return v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)
