"""The up direction of an unlevelled scan from its own geometry (issue 15, a minegeo addition).

Why
---
minegeo's levelled machinery (2-point heading + translation RANSAC and the whole-map
correlative 4-DOF search, :mod:`minegeo.localize.correlative`) needs the scan's z axis to be
up. A SLAM frame is usually the first sensor pose, tilted arbitrarily. A mine drift says
where up is through its shape: a flat floor, vertical walls, an arched roof. This module
estimates ``up`` in the scan frame from those cues, says how sure it is, and says what it
*cannot* know: on a straight ramp the floor is tilted about the drift's cross axis by the
unknown slope, so it also returns the residual-tilt range to search.

What each cue fixes (``a`` drift axis, ``c = up x a_h`` its horizontal cross axis, slope ``s``)
------------------------------------------------------------------------------------------------
Write a small error of ``up`` as a rotation ``(delta_along, delta_across)``: ``delta_along``
about ``c`` (tilts up towards the drift axis), ``delta_across`` about the drift axis.

=======================================  ======================  ======================================
cue                                      fixes ``delta_across``  fixes ``delta_along``
=======================================  ======================  ======================================
floor normal ``f = cos s up - sin s a_h``  yes (``f . c = 0``)     only if the floor is level (``s = 0``)
walls, straight drift (normals ``+-c``)  yes (``n . up = 0``)    no
walls of a curve, junction or face       yes                     yes, whatever the slope
drift axis ``a`` (normals are ``_|_ a``)  no                      only if the drift is level
=======================================  ======================  ======================================

So on a straight ramp nothing in the scan gives the slope: ``up`` is known up to a rotation
of the floor normal about ``c`` by ``s``; this module returns the floor-based estimate (the
level hypothesis), its statistical uncertainty, and the search range
``R(c, theta) up, theta in tilt_range_deg`` that contains the truth for slopes up to
``GravityParams.max_slope_deg``. Where the walls also fix ``delta_along`` (curves, junctions)
their own estimate is reported (``evidence.walls_slope_deg``, candidate ``"walls"``) but not
used: on rough rock it is off by several degrees (docs/localization.md).

Method
------
1. Area-uniform sample: at most ``max_points`` points drawn with probability inversely
   proportional to the local density (neighbours within ``density_radius_m``), in a canonical
   order (distance to the exactly summed centroid), so the result does not depend on the
   order of the points; PCA normals (:func:`minegeo.geometry.estimate_normals`).
2. Floor detection (no prior on up): the modes of the area density of the normals
   (:func:`minegeo.localize._kernels_gravity.normal_density`) that look like floors or walls
   are scored by the floor signature (:func:`_column_score`: flat below, arched above); the
   best is the floor, its sign from the arched roof.
3. Floor refinement: iteratively reweighted total least squares of the floor points, Tukey
   weights on the height residual (scale 7 MAD, at most ``floor_residual_scale_m``) and on
   the normal's tilt (``floor_max_tilt_deg``).
4. Walls: surfels above the floor whose normal is within ``wall_max_tilt_deg`` of horizontal
   (Tukey weights, scale 7 MAD of ``n . up``); Gauss-Newton on ``sum w (n . up)^2`` over
   ``delta_across`` (and, as evidence only, over both components when the wall normals spread
   in azimuth, ``min_wall_spread``).
5. Uncertainty: delete-one-block jackknife over ``n_blocks`` slices along the drift axis
   (rough rock is spatially correlated, so per-point least-squares covariances would be far
   too small): ``Sigma = (g - 1) / g sum_k (d_k - d_bar)(d_k - d_bar)^T``. The floor and wall
   estimates are fused with their jackknife covariances (information-weighted) and the fused
   estimator is jackknifed again. The 95 % region uses Hotelling's T^2 with ``g - 1`` degrees
   of freedom: ``r^2 = 2 (g - 1) / (g - 2) F_{2, g-2}(0.95)`` (12.0 for g = 8).

All angles in this module's results are in degrees unless the name says ``rad``; every vector
is in the frame of the input points (the *scan* frame).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError, TooFewPointsError
from minegeo.geometry.neighbors import NeighborIndex
from minegeo.geometry.normals import STATUS_OK, NormalParams, estimate_normals
from minegeo.localize import _kernels_gravity as KG
from minegeo.localize.params import GravityParams

__all__ = ["GravityParams", "UpCandidate", "UpEvidence", "UpEstimate", "estimate_up", "levelling_rotation",
           "hotelling_r2_95", "STATUSES"]

log = logging.getLogger(__name__)

#: Possible values of :attr:`UpEstimate.status`.
STATUSES = ("ok", "ambiguous", "failed")
_EPS_VAR = 1e-24  # rad^2 added before inverting a jackknife covariance (noise-free inputs give 0)
_MAD_TO_TUKEY = 7.0  # Tukey scale = 7 MAD (4.685 sigma of a Gaussian, sigma = 1.4826 MAD)
_MAX_STEP_RAD = math.radians(1.0)  # largest Gauss-Newton step of the wall fit
_MIN_TOL_DEG = 1e-3  # floor of tilt_tolerance_deg (noise-free inputs give a zero jackknife spread)


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
    status : {"ok", "ambiguous", "failed"}
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

    status: str
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


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _tukey(x: np.ndarray) -> np.ndarray:
    y = 1.0 - x * x
    return np.where(np.abs(x) < 1.0, y * y, 0.0)


def _half_sphere(n: int) -> np.ndarray:
    """``n`` Fibonacci axes on the half-sphere z > 0."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.ascontiguousarray(np.c_[r * np.cos(phi), r * np.sin(phi), z])


def _basis(up: np.ndarray, axis_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_along, t_across) at ``up``: t_across = unit(up x axis_hint), t_along = t_across x up."""
    tc = np.cross(up, axis_hint)
    n = float(np.linalg.norm(tc))
    if n < 1e-9:  # hint parallel to up: any perpendicular
        e = np.eye(3)[int(np.argmin(np.abs(up)))]
        tc = np.cross(up, e)
        n = float(np.linalg.norm(tc))
    tc = tc / n
    return np.cross(tc, up), tc


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(x, kind="stable")
    cw = np.cumsum(w[o])
    return float(x[o][np.searchsorted(cw, 0.5 * cw[-1])])


def _jackknife(reps: np.ndarray) -> np.ndarray:
    """Delete-one jackknife covariance of replicate rows (g, k)."""
    g = reps.shape[0]
    d = reps - reps.mean(axis=0)
    return (g - 1) / g * (d.T @ d)


# ---------------------------------------------------------------------------------------------- fits

def _fit_plane(Q, W, N, u0, d0, p: GravityParams, max_iter: int = 60):
    """IRLS total-least-squares plane near ``(u0, d0)``: returns (u, d, weights, scale) or None."""
    u, d = u0.copy(), float(d0)
    cmax = float(p.floor_residual_scale_m)
    scale = cmax
    sin_t = math.sin(math.radians(p.floor_max_tilt_deg))
    wts = None
    for _ in range(max_iter):
        r = Q @ u - d
        wn = _tukey(np.sqrt(np.maximum(0.0, 1.0 - (N @ u) ** 2)) / sin_t)
        base = W * wn
        inl = (np.abs(r) < scale) & (base > 0)
        if np.count_nonzero(inl) < 3:
            return None
        mad = _weighted_median(np.abs(r[inl]), base[inl])
        scale = min(cmax, max(_MAD_TO_TUKEY * mad, 1e-9))
        wts = base * _tukey(r / scale)
        sw = float(wts.sum())
        if not sw > 0:
            return None
        m = (wts @ Q) / sw
        X = Q - m
        C = (X * wts[:, None]).T @ X
        _, V = np.linalg.eigh(C)
        un = V[:, 0]
        if un @ u < 0:
            un = -un
        dn = float(m @ un)
        done = abs(1.0 - float(un @ u)) < 1e-16 and abs(dn - d) < 1e-12
        u, d = un, dn
        if done:
            break
    r = Q @ u - d
    wts = W * _tukey(np.sqrt(np.maximum(0.0, 1.0 - (N @ u) ** 2)) / sin_t) * _tukey(r / scale)
    return u, d, wts, scale


def _fit_walls(Q, W, N, mask, u0, axis_hint, along: bool, p: GravityParams, max_iter: int = 60):
    """Up from vertical walls: minimise ``sum w (n . up)^2`` over the tangent rotation.

    Returns (up, weights, A) where A is the 2x2 normal matrix in (t_along, t_across) at up,
    or None when no wall surfel is left.
    """
    u = u0.copy()
    smax = math.sin(math.radians(p.wall_max_tilt_deg))
    scale = smax
    wts = None
    A = np.zeros((2, 2))
    for _ in range(max_iter):
        c = N @ u
        inl = mask & (np.abs(c) < scale)
        if np.count_nonzero(inl) < 3:
            return None
        mad = _weighted_median(np.abs(c[inl]), W[inl])
        scale = min(smax, max(_MAD_TO_TUKEY * mad, 1e-12))
        wts = W * mask * _tukey(c / scale)
        if not wts.sum() > 0:
            return None
        ta, tc = _basis(u, axis_hint)
        G = np.c_[N @ ta, N @ tc]
        A = (G * wts[:, None]).T @ G
        b = (G * wts[:, None]).T @ c
        if along:
            try:
                delta = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return None
        else:
            if not A[1, 1] > 0:
                return None
            delta = np.array([0.0, -b[1] / A[1, 1]])
        step = float(np.linalg.norm(delta))
        if step > _MAX_STEP_RAD:  # damped: a weakly determined direction must not jump to another basin
            delta *= _MAX_STEP_RAD / step
        if float(np.linalg.norm(_tangent(_unit(u + delta[0] * ta + delta[1] * tc), u0, *_basis(u0, axis_hint)))) \
                > math.radians(p.max_slope_deg + p.wall_max_tilt_deg):
            return None  # wandered off: the walls do not determine up here
        un = _unit(u + delta[0] * ta + delta[1] * tc)
        done = float(np.abs(delta).max()) < 1e-15
        u = un
        if done:
            break
    return u, wts, A


def _mode(N: np.ndarray, W: np.ndarray, v0: np.ndarray, cos_m: float, iters: int = 20):
    """Axis mode of the normals near ``v0``: principal axis of the normals within the cone, iterated."""
    v = v0.copy()
    for _ in range(iters):
        sel = np.abs(N @ v) > cos_m
        if not np.any(sel):
            return None
        Ns = N[sel]
        M = (Ns * W[sel][:, None]).T @ Ns
        vn = np.linalg.eigh(M)[1][:, 2]
        if vn @ v < 0:
            vn = -vn
        done = float(vn @ v) > 1.0 - 1e-15
        v = vn
        if done:
            break
    return v


def _tangent(u: np.ndarray, ref: np.ndarray, ta: np.ndarray, tc: np.ndarray) -> np.ndarray:
    """(delta_along, delta_across) of unit ``u`` relative to ``ref`` in the basis (ta, tc), rad."""
    return np.array([math.atan2(float(u @ ta), float(u @ ref)), math.asin(max(-1.0, min(1.0, float(u @ tc))))])


def _from_tangent(ref: np.ndarray, ta: np.ndarray, tc: np.ndarray, d: np.ndarray) -> np.ndarray:
    return _unit(ref + math.tan(d[0]) * ta + math.tan(d[1]) * tc)


def _column_score(Q: np.ndarray, W: np.ndarray, N: np.ndarray, u: np.ndarray, p: GravityParams):
    """Floor signature of the direction ``u``: flat below, arched above (odd in ``u``).

    Returns (score, mask of the flat bottom surfels, area fraction in valid columns).

    The sample is cut into columns along ``u`` (square cells of ``column_cell_m`` in the plane
    perpendicular to ``u``); only columns spanning at least ``min_drift_height_m`` (floor and
    roof both seen) count. In each, the lower half is *bottom*, the upper half *top*; a surfel
    is *flat* when its normal is within ``floor_flat_deg`` of ``+-u`` and *inclined* when it is
    between that and ``roof_flank_max_deg``. With ``A(.)`` the area fraction,

    ``score = A(bottom, flat) - A(top, flat) + A(top, inclined) - A(bottom, inclined)``.

    A horseshoe drift's floor scores the floor minus the roof's crown plus the roof's flanks
    (> 0); a wall faces the other wall and the flanks of the arch are split between both
    sides (about 0); the roof scores the floor's negative. So the sign of up and the floor
    versus wall choice come from the arched roof, not from sizes alone.
    """
    e1, e2 = _basis(u, np.eye(3)[int(np.argmin(np.abs(u)))])
    cell = float(p.column_cell_m)
    ix = np.floor(Q @ e1 / cell).astype(np.int64)
    iy = np.floor(Q @ e2 / cell).astype(np.int64)
    key = ix * np.int64(1 << 31) + iy
    _, inv = np.unique(key, return_inverse=True)
    h = Q @ u
    nk = int(inv.max()) + 1
    lo = np.full(nk, np.inf)
    hi = np.full(nk, -np.inf)
    np.minimum.at(lo, inv, h)
    np.maximum.at(hi, inv, h)
    ext = (hi - lo)[inv]
    valid = ext >= p.min_drift_height_m
    c = np.abs(N @ u)
    flat = c > math.cos(math.radians(p.floor_flat_deg))
    incl = (c > math.cos(math.radians(p.roof_flank_max_deg))) & ~flat
    bot = (h - lo[inv]) < 0.5 * ext
    top = ~bot
    Wv = np.where(valid, W, 0.0)
    score = float(Wv[flat & bot].sum() - Wv[flat & top].sum() + Wv[incl & top].sum() - Wv[incl & bot].sum())
    return score, valid & flat & bot, float(Wv.sum())


# ---------------------------------------------------------------------------------------------- main

def _prepare(points, normals, p: GravityParams):
    """Validated points, area-uniform sample Q with weights W and unit normals N (canonical order)."""
    pts = as_points(points, "points", min_points=1)
    n = pts.shape[0]
    if n < p.min_points:
        raise TooFewPointsError(f"points has {n} point(s); estimating up needs at least {p.min_points}")
    nrm = None
    if normals is not None:
        nrm = as_points(normals, "normals", min_points=1)
        if nrm.shape[0] != n:
            raise InputError(f"normals must have one row per point ({n}), got {nrm.shape[0]}")
        ln = np.linalg.norm(nrm, axis=1)
        if np.any(ln < 0.5) or np.any(ln > 1.5):
            raise InputError("normals must be unit vectors (some rows have length < 0.5 or > 1.5)")
        nrm = nrm / ln[:, None]
    # canonical order: squared distance to the exactly summed centroid (independent of row order)
    cen = np.array([math.fsum(pts[:, k]) / n for k in range(3)])
    X = pts - cen
    d2 = np.einsum("ij,ij->i", X, X)
    order = np.lexsort((X[:, 2], X[:, 1], X[:, 0], d2))
    pts_c = np.ascontiguousarray(X[order])
    nrm_c = None if nrm is None else np.ascontiguousarray(nrm[order])
    cnt = NeighborIndex(pts_c).radius_counts(pts_c, p.density_radius_m).astype(np.float64)
    area = 1.0 / np.maximum(cnt, 1.0)
    valid = np.ones(n, dtype=bool)
    if nrm_c is None:
        nr = estimate_normals(pts_c, NormalParams(radius_m=p.normal_radius_m, max_nn=p.normal_max_nn),
                              orient_towards="none")
        nrm_c = nr.normals
        valid = nr.status == STATUS_OK
    if n > p.max_points:
        rng = np.random.default_rng(p.seed)
        pr = area / area.sum()
        pick = np.sort(rng.choice(n, size=p.max_points, replace=False, p=pr))
        Q, N, ok = pts_c[pick], nrm_c[pick], valid[pick]
        W = np.full(pick.size, 1.0)
    else:
        Q, N, ok, W = pts_c, nrm_c, valid, area.copy()
    W = np.where(ok, W, 0.0)
    if not W.sum() > 0:
        raise InputError("no usable normals: the cloud has no planar neighbourhoods")
    W = W / W.sum()
    return np.ascontiguousarray(Q), np.ascontiguousarray(N), np.ascontiguousarray(W), cen


def _failed(reason: str, p: GravityParams, cands=(), timings=None) -> UpEstimate:
    return UpEstimate(status="failed", reason=reason, up=None, tangent_basis=None, covariance_rad2=None,
                      covariance_3d_rad2=None, sigma_deg=math.nan, cone95_deg=math.nan, r95_squared=math.nan,
                      tilt_axis=None, tilt_range_deg=(math.nan, math.nan), tilt_tolerance_deg=math.nan,
                      candidates=tuple(cands), evidence=None, params=p, timings_s=dict(timings or {}))


@dataclass(frozen=True)
class _Floor:
    """The refined floor plane ``f . x = d`` (sample frame, m) of :func:`_floor`.

    Attributes
    ----------
    score : float
        Floor signature of the chosen normal mode (:func:`_column_score`).
    f : (3,) float64
        Unit floor normal, towards the void (up if the floor is level).
    d : float
        Plane offset (m).
    weights : (m,) float64
        Final IRLS weights of the sample.
    mass, void : float
        Area fractions within ``plane_band_m`` of the plane and above it.
    """

    score: float
    f: np.ndarray
    d: float
    weights: np.ndarray
    mass: float
    void: float


@dataclass(frozen=True)
class _Walls:
    """The wall fits of :func:`_walls` (scan frame).

    Attributes
    ----------
    mask : (m,) bool
        Surfels higher than ``wall_min_height_m`` above the floor.
    fit : tuple or None
        Across-drift fit ``(up, weights, A)`` of :func:`_fit_walls` (None: no walls).
    fit_along : tuple or None
        Both-component fit, only when the walls spread in azimuth (evidence).
    spread : float
        Smallest / largest eigenvalue of the across fit's normal matrix (0 without walls).
    weights : (m,) float64 or None
        Weights of the across fit.
    """

    mask: np.ndarray
    fit: tuple | None
    fit_along: tuple | None
    spread: float
    weights: np.ndarray | None


@dataclass(frozen=True)
class _Fusion:
    """Floor + walls fused in the tangent basis ``(ta, tc)`` at the floor normal (rad).

    Attributes
    ----------
    d_hat : (2,) float64
        Fused ``(delta_along, delta_across)`` relative to the floor normal.
    S : (2, 2) float64
        Jackknife covariance of the fused estimator (rad^2).
    S_f : (2, 2) float64
        Jackknife covariance of the floor normal alone (rad^2).
    g_eff : int
        Jackknife blocks that hold both the floor and (when used) the walls.
    """

    d_hat: np.ndarray
    S: np.ndarray
    S_f: np.ndarray
    g_eff: int


@dataclass(frozen=True)
class _WallsAlone:
    """The walls-alone up (evidence only; NaN / None when the walls do not fix it).

    Attributes
    ----------
    slope_deg, slope_sigma_deg : float
        Floor tilt about the cross axis relative to the walls-alone up, and its 1-sigma (deg).
    up : (3,) float64 or None
    sigma_deg : float
        Its 1-sigma angle (largest axis, deg).
    """

    slope_deg: float = math.nan
    slope_sigma_deg: float = math.nan
    up: np.ndarray | None = None
    sigma_deg: float = math.nan


def _normal_modes(Q: np.ndarray, W: np.ndarray, N: np.ndarray, p: GravityParams) -> list:
    """Floor detection (Method 2): modes of the normals' area density that look like floors or walls, best first.

    Returns a list of ``(|score|, u, valid_fraction)``: the floor signature of the mode
    (:func:`_column_score`), the mode oriented by the signature's sign (scan frame) and the area
    fraction in columns spanning a drift height.
    """
    D = _half_sphere(int(p.n_directions))
    dens = np.empty(D.shape[0])
    cos_m = math.cos(math.radians(p.mode_radius_deg))
    KG.normal_density(N, W, D, cos_m, dens)
    picked: list[np.ndarray] = []
    cos_sep = math.cos(math.radians(p.min_rival_angle_deg / 2.0))
    for k in np.lexsort((np.arange(D.shape[0]), -dens)):
        if len(picked) >= p.n_rivals:
            break
        v = _mode(N, W, D[k], cos_m)
        if v is not None and all(abs(float(v @ q)) < cos_sep for q in picked):
            picked.append(v)
    # a floor (or a wall) has large surfaces perpendicular to it (walls, or floor and roof); a
    # direction through the arch's flank has not: such modes are not candidates
    sin_p = math.sin(math.radians(p.mode_radius_deg))
    own = [float(W[np.abs(N @ v) > cos_m].sum()) for v in picked]
    omax = max(own) if own else 0.0
    picked = [v for v, o in zip(picked, own, strict=True) if o >= p.min_mode_ratio * omax]
    perp = [float(W[np.abs(N @ v) < sin_p].sum()) for v in picked]
    pmax = max(perp) if perp else 0.0
    modes = []
    for v, pf in zip(picked, perp, strict=True):
        if pf < p.min_perp_ratio * pmax:
            continue
        sc, bottom_flat, valid_frac = _column_score(Q, W, N, v, p)
        u = v if sc >= 0.0 else -v
        modes.append((abs(sc), u, valid_frac))
    modes.sort(key=lambda t: -t[0])
    return modes


def _no_floor_reason(modes: list, p: GravityParams) -> str:
    """Why no mode is a floor (the best score is below ``min_floor_score``)."""
    if not modes or max(m[2] for m in modes) < 0.05:
        return ("no drift around the largest flat surface (nothing at least "
                f"{p.min_drift_height_m:g} m from it across the void): a lone plane, its normal's sign is unknown")
    best_sc = modes[0][0] if modes else 0.0
    return (f"no floor: no surface is flat below and arched above (best floor score {best_sc:.3f} < "
            f"{p.min_floor_score:g}; a vertical shaft, or walls and roof alike?)")


def _floor(Q: np.ndarray, W: np.ndarray, N: np.ndarray, modes: list, p: GravityParams) -> tuple[_Floor | None, str]:
    """Floor refinement (Method 3): refine the best mode's plane (IRLS) and check its area; ``(floor, "")`` or ``(None, why)``."""
    f_score, f0, _ = modes[0]
    _, bottom_flat, _ = _column_score(Q, W, N, f0, p)
    hb = Q[bottom_flat] @ f0
    d0 = _weighted_median(hb, W[bottom_flat]) if hb.size else float(np.min(Q @ f0))
    fit = _fit_plane(Q, W, N, f0, d0, p)
    if fit is None:
        return None, "the floor plane could not be fitted"
    f, fd, fw, fscale = fit
    hf = Q @ f - fd
    f_mass = float(W[np.abs(hf) <= 0.5 * p.plane_band_m].sum())
    f_void = float(W[hf > 0.5 * p.plane_band_m].sum())
    if f_mass < p.min_floor_fraction:
        return None, f"the floor plane holds only {f_mass:.1%} of the scan's area (need {p.min_floor_fraction:.0%})"
    if f_void < p.min_void_fraction:
        return None, f"only {f_void:.0%} of the scan lies above the floor plane (need {p.min_void_fraction:.0%})"
    return _Floor(f_score, f, fd, fw, f_mass, f_void), ""


def _drift_axis(Q: np.ndarray, W: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Principal horizontal direction of the scan (perpendicular to the floor normal ``f``): the drift axis."""
    Xh = Q - np.outer(Q @ f, f)
    mu = W @ Xh
    Ch = ((Xh - mu) * W[:, None]).T @ (Xh - mu)
    ev, V = np.linalg.eigh(Ch)
    axis = V[:, 2] - (V[:, 2] @ f) * f
    axis = _unit(axis)
    if axis[int(np.argmax(np.abs(axis)))] < 0:  # sign convention (does not change the estimate)
        axis = -axis
    return axis


def _walls(Q: np.ndarray, W: np.ndarray, N: np.ndarray, r_floor: np.ndarray, f: np.ndarray, axis: np.ndarray,
           p: GravityParams) -> _Walls:
    """Walls (Method 4): they fix the across-drift component (always), the along one only as evidence."""
    wall_mask = r_floor > p.wall_min_height_m
    wfit = _fit_walls(Q, W, N, wall_mask, f, axis, False, p)
    spread = 0.0
    wall_w = None
    wfit_along = None
    if wfit is not None:
        wall_w = wfit[1]
        lam = np.linalg.eigvalsh(wfit[2])
        spread = float(lam[0] / lam[1]) if lam[1] > 0 else 0.0
        if spread >= p.min_wall_spread:
            wfit_along = _fit_walls(Q, W, N, wall_mask, f, axis, True, p)
    return _Walls(wall_mask, wfit, wfit_along, spread, wall_w)


def _block_replicates(Q: np.ndarray, W: np.ndarray, N: np.ndarray, fl: _Floor, walls: _Walls, axis: np.ndarray,
                      ta: np.ndarray, tc: np.ndarray, p: GravityParams):
    """Uncertainty (Method 5): delete-one-block refits over ``n_blocks`` slices along the drift axis.

    Returns ``(rep_f, rep_w, rep_wa)``: the floor's, the across walls' and the along walls'
    ``(delta_along, delta_across)`` per deleted block (rad, NaN where a fit failed); ``rep_w`` is
    zeros without walls and ``rep_wa`` an empty list without an along fit.
    """
    f, fd = fl.f, fl.d
    wall_mask, wfit, wfit_along = walls.mask, walls.fit, walls.fit_along
    g = int(p.n_blocks)
    s_ax = Q @ axis
    o = np.argsort(s_ax, kind="stable")
    cw = np.cumsum(W[o])
    blk = np.empty(Q.shape[0], dtype=np.int64)
    blk[o] = np.minimum((cw / cw[-1] * g - 1e-12).astype(np.int64), g - 1)
    nan2 = np.full(2, np.nan)
    rep_f, rep_w, rep_wa = [], [], []
    for k in range(g):
        keep = blk != k
        Qk, Wk, Nk, mk = Q[keep], W[keep], N[keep], wall_mask[keep]
        fk = _fit_plane(Qk, Wk, Nk, f, fd, p)
        rep_f.append(nan2 if fk is None else _tangent(fk[0], f, ta, tc))
        if wfit is not None:
            wk = _fit_walls(Qk, Wk, Nk, mk, f, axis, False, p)
            rep_w.append(nan2 if wk is None else _tangent(wk[0], f, ta, tc))
        if wfit_along is not None:
            wk = _fit_walls(Qk, Wk, Nk, mk, f, axis, True, p)
            rep_wa.append(nan2 if wk is None else _tangent(wk[0], f, ta, tc))
    rep_f = np.array(rep_f)
    rep_w = np.array(rep_w) if rep_w else np.zeros((g, 2))
    return rep_f, rep_w, rep_wa


def _fuse(rep_f: np.ndarray, rep_w: np.ndarray, good: np.ndarray, wfit: tuple | None, f: np.ndarray,
          ta: np.ndarray, tc: np.ndarray) -> _Fusion:
    """Fusion (Method 5): floor (both components) + walls (across only), information-weighted, jackknifed again.

    ``good`` marks the blocks whose floor replicate is finite (at least 4).
    """
    g = rep_f.shape[0]
    S_f = _jackknife(rep_f[good]) + _EPS_VAR * np.eye(2)
    I_f = np.linalg.inv(S_f)
    I_w = np.zeros((2, 2))
    d_w = np.zeros(2)
    if wfit is not None:
        gw = good & np.all(np.isfinite(rep_w), axis=1)
        if np.count_nonzero(gw) >= 4:
            good = gw
            d_w = np.array([0.0, _tangent(wfit[0], f, ta, tc)[1]])
            var_c = float(_jackknife(rep_w[good][:, 1:2])[0, 0]) + _EPS_VAR
            I_w[1, 1] = 1.0 / var_c
    Itot = I_f + I_w
    Kf = np.linalg.solve(Itot, I_f)
    Kw = np.linalg.solve(Itot, I_w)
    d_hat = Kw @ d_w  # the floor's own value is 0 in its basis
    reps = np.array([Kf @ rep_f[k] + Kw @ np.array([0.0, rep_w[k, 1]]) for k in range(g) if good[k]])
    S = _jackknife(reps)
    return _Fusion(d_hat, S, S_f, int(reps.shape[0]))


def _walls_alone(wfit_along: tuple | None, rep_wa: list, f: np.ndarray, ta: np.ndarray,
                 tc: np.ndarray) -> _WallsAlone:
    """The walls-alone up and the floor slope it suggests (evidence only), with jackknife sigmas."""
    if wfit_along is not None and rep_wa:
        rep_wa = np.array(rep_wa)
        ga = np.all(np.isfinite(rep_wa), axis=1)
        if np.count_nonzero(ga) >= 4:
            Sa = _jackknife(rep_wa[ga])
            w_up = wfit_along[0]
            w_slope = math.degrees(_tangent(w_up, f, ta, tc)[0])
            w_slope_sig = math.degrees(math.sqrt(max(Sa[0, 0], 0.0)))
            w_sig = math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(Sa)[-1]), 0.0)))
            return _WallsAlone(w_slope, w_slope_sig, w_up, w_sig)
    return _WallsAlone()


def _evidence(Q: np.ndarray, W: np.ndarray, N: np.ndarray, up: np.ndarray, fl: _Floor, walls: _Walls,
              wa: _WallsAlone, r_floor: np.ndarray, ta2: np.ndarray, tc2: np.ndarray, ratio: float,
              g_eff: int) -> UpEvidence:
    """What the estimate rests on (floor and wall fit quality, axes, rival ratio)."""
    cu = N @ up
    ww = walls.weights if walls.weights is not None else np.zeros_like(W)
    wsum = float(ww.sum())
    vert = math.degrees(math.sqrt(float(ww @ np.arcsin(np.clip(cu, -1, 1)) ** 2) / wsum)) if wsum > 0 else math.nan
    fsum = float(fl.weights.sum())
    frms = math.sqrt(float(fl.weights @ r_floor ** 2) / fsum) if fsum > 0 else math.nan
    return UpEvidence(floor_fraction=float(fl.mass), floor_score=float(fl.score), void_fraction=float(fl.void),
                      floor_normal=fl.f.copy(), floor_rms_m=frms, wall_fraction=float(W[ww > 0].sum()),
                      wall_verticality_rms_deg=vert, wall_spread=walls.spread, walls_slope_deg=wa.slope_deg,
                      walls_slope_sigma_deg=wa.slope_sigma_deg, drift_axis=ta2.copy(), cross_axis=tc2.copy(),
                      rival_ratio=ratio, n_points_used=int(Q.shape[0]), n_blocks=g_eff)


def _candidates(up: np.ndarray, fl: _Floor, fu: _Fusion, sig: float, wa: _WallsAlone, spread: float,
                cands: list) -> list:
    """The estimate, the floor (level) hypothesis, the walls' (if any) and the rival modes."""
    f = fl.f
    out_c = [UpCandidate(up=up.copy(), source="estimate", score=float(fl.score), sigma_deg=sig,
                         note="floor (level hypothesis) and walls (across the drift)"),
             UpCandidate(up=f.copy(), source="floor", score=float(fl.score),
                         sigma_deg=math.degrees(math.sqrt(float(np.linalg.eigvalsh(fu.S_f)[-1]))),
                         note=f"floor normal alone: up if the floor is level (slab {fl.mass:.3f} of the area, "
                              f"{fl.void:.3f} above it)")]
    if wa.up is not None:
        out_c.append(UpCandidate(up=wa.up.copy(), source="walls", score=math.nan, sigma_deg=wa.sigma_deg,
                                 note=f"walls alone (seen in several directions, spread {spread:.2f}): "
                                      f"floor slope {wa.slope_deg:.1f} +- {wa.slope_sigma_deg:.1f} deg relative to them"))
    out_c += [c for c in cands if abs(float(c.up @ f)) < math.cos(math.radians(1.0))]
    return out_c


def _search_region(S: np.ndarray, g_eff: int, p: GravityParams) -> tuple:
    """1-sigma angle, 95 % cone, Hotelling ``r95^2``, residual-tilt range and tube half-width (deg).

    ``S`` is the fused jackknife covariance of ``(delta_along, delta_across)`` (rad^2) over
    ``g_eff`` blocks; returns ``(sigma, cone95, r95_squared, lo, hi, tolerance)``.
    """
    lam_max = float(np.linalg.eigvalsh(S)[-1])
    r2 = hotelling_r2_95(g_eff)
    sig = math.degrees(math.sqrt(max(lam_max, 0.0)))
    cone = math.degrees(math.sqrt(r2 * max(lam_max, 0.0)))
    kk = math.sqrt(r2)
    sa = math.degrees(math.sqrt(max(S[0, 0], 0.0)))
    sc = math.degrees(math.sqrt(max(S[1, 1], 0.0)))
    lo, hi = -p.max_slope_deg - kk * sa, p.max_slope_deg + kk * sa
    tol = max(kk * sc, _MIN_TOL_DEG)
    return sig, cone, r2, lo, hi, tol


def _status(up: np.ndarray, rivals: list, ratio: float, fl: _Floor, sig: float, p: GravityParams) -> tuple[str, str]:
    """``("ambiguous", why)`` when a distinct rival floor scores ``ambiguity_ratio`` of the floor's, else ``ok``."""
    if rivals and ratio >= p.ambiguity_ratio:
        r_ang = math.degrees(math.acos(min(1.0, float(rivals[0][1] @ up))))
        status, reason = "ambiguous", (f"a second floor candidate {r_ang:.0f} deg away scores {ratio:.2f} of the "
                                       f"floor's (need < {p.ambiguity_ratio:g}); both are in candidates")
    else:
        status = "ok"
        reason = (f"floor {fl.mass:.0%} of the scan, up 1-sigma {sig:.2f} deg if the floor is level; "
                  f"a ramp of up to {p.max_slope_deg:g} deg is within tilt_range_deg")
    return status, reason


def estimate_up(points, normals=None, params: GravityParams | None = None) -> UpEstimate:
    """Estimate the up direction of a mine-drift scan from its floor and walls.

    Parameters
    ----------
    points : (n, 3) array_like of float
        The scan in its own frame (m), any orientation.
    normals : (n, 3) array_like of float, optional
        Unit normals of ``points`` (any sign). Default: PCA normals within
        ``params.normal_radius_m``.
    params : GravityParams, optional

    Returns
    -------
    UpEstimate
        ``up`` (scan frame), its covariance and 95 % cone under the level-floor hypothesis
        (or the walls' when they fix it), the residual-tilt search for ramps, the candidates
        and the evidence; ``status`` ``failed`` when the scan shows no floor (a lone plane, a
        vertical shaft, no void side) and ``ambiguous`` when a distinct rival floor scores
        almost as well (e.g. a flat roof as large as the floor).

    Raises
    ------
    InputError
        NaN/inf, wrong shapes, normals that are not unit vectors, bad parameters.
    TooFewPointsError
        Fewer than ``params.min_points`` points.

    Notes
    -----
    Deterministic: the same points (in any order) and ``params.seed`` give the same result;
    rotating the points rotates ``up`` (exactly up to floating point when the cloud has at
    most ``max_points`` points and the plane detection picks the same floor).
    """
    p = GravityParams() if params is None else params
    if not isinstance(p, GravityParams):
        raise InputError(f"params must be a GravityParams, got {type(p).__name__}")
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    Q, N, W, _ = _prepare(points, normals, p)
    timings["sample_and_normals"] = time.perf_counter() - t0

    # ---- floor detection: modes of the normals, each scored by the floor signature
    t1 = time.perf_counter()
    modes = _normal_modes(Q, W, N, p)
    timings["floor_detection"] = time.perf_counter() - t1
    cands = [UpCandidate(up=m[1].copy(), source="mode", score=float(m[0]), sigma_deg=math.nan,
                         note=f"normal mode; {m[2]:.0%} of the area in columns spanning a drift height")
             for m in modes]
    if not modes or modes[0][0] < p.min_floor_score:
        return _failed(_no_floor_reason(modes, p), p, cands, timings)
    fl, why = _floor(Q, W, N, modes, p)
    if fl is None:
        return _failed(why, p, cands, timings)
    f = fl.f

    # ---- drift axis and walls
    t2 = time.perf_counter()
    r_floor = Q @ f - fl.d
    axis = _drift_axis(Q, W, f)
    ta, tc = _basis(f, axis)
    walls = _walls(Q, W, N, r_floor, f, axis, p)
    timings["floor_and_walls"] = time.perf_counter() - t2

    # ---- jackknife over blocks along the drift, fusion
    t3 = time.perf_counter()
    rep_f, rep_w, rep_wa = _block_replicates(Q, W, N, fl, walls, axis, ta, tc, p)
    good = np.all(np.isfinite(rep_f), axis=1)
    if np.count_nonzero(good) < 4:
        return _failed("the floor is too small to estimate its uncertainty (fewer than 4 jackknife blocks hold it)",
                       p, cands, timings)
    fu = _fuse(rep_f, rep_w, good, walls.fit, f, ta, tc)
    S, g_eff = fu.S, fu.g_eff
    wa = _walls_alone(walls.fit_along, rep_wa, f, ta, tc)
    timings["jackknife"] = time.perf_counter() - t3

    up = _from_tangent(f, ta, tc, fu.d_hat)
    ta2, tc2 = _basis(up, axis)
    B = np.vstack([ta2, tc2])
    sig, cone, r2, lo, hi, tol = _search_region(S, g_eff, p)

    # ---- evidence, candidates, status
    rivals = [m for m in modes[1:] if math.degrees(math.acos(min(1.0, float(m[1] @ up)))) > p.min_rival_angle_deg]
    ratio = float(rivals[0][0] / fl.score) if rivals else 0.0
    ev_ = _evidence(Q, W, N, up, fl, walls, wa, r_floor, ta2, tc2, ratio, g_eff)
    out_c = _candidates(up, fl, fu, sig, wa, walls.spread, cands)
    status, reason = _status(up, rivals, ratio, fl, sig, p)
    timings["total"] = time.perf_counter() - t0
    log.debug("estimate_up: %s (%s)", status, reason)
    return UpEstimate(status=status, reason=reason, up=up, tangent_basis=B, covariance_rad2=S,
                      covariance_3d_rad2=B.T @ S @ B, sigma_deg=sig, cone95_deg=cone, r95_squared=r2,
                      tilt_axis=tc2.copy(), tilt_range_deg=(float(lo), float(hi)), tilt_tolerance_deg=float(tol),
                      candidates=tuple(out_c), evidence=ev_, params=p, timings_s=timings)


def _warmup() -> None:
    KG._warmup()
