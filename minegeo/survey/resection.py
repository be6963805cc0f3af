"""Resection, intersection and trilateration of one unknown 2D point by least squares.

Thin conveniences over :mod:`minegeo.survey.network`: they build a small network with the known
points fixed, find approximate coordinates when none are given (coarse search of ``vᵀWv`` over
the area, then Gauss–Newton from the best candidates), adjust, and report the point with its
covariance, error ellipses and the adjustment statistics.

* **Resection** (Ghilani 2010, Sec. 15.7, Ex. 15.5): the unknown station observes directions
  (one orientation unknown) and/or distances to known points, or angles between them.
* **Intersection** (Ghilani 2010, Sec. 15.6, Ex. 15.4): known stations observe angles (or
  azimuths) to the unknown point.
* **Trilateration** (Ghilani 2010, Ch. 14, Ex. 14.5): distances between the unknown point and
  known points.

Ambiguity is never resolved silently: if two clearly different positions fit the observations
equally well (two distances, collinear control with distances only, ...), a
:class:`~minegeo.errors.DegenerateGeometryError` lists both (or, with ``on_ambiguity="report"``,
the result carries ``status="ambiguous"`` and the alternatives).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from minegeo.errors import DegenerateGeometryError, InputError, MinegeoError, TooFewPointsError
from minegeo.survey.ellipse import ErrorEllipse
from minegeo.survey.lsq import LSQOptions
from minegeo.survey.network import Datum, Network, NetworkResult, Observation, adjust_network

__all__ = ["StationResult", "StationStatus", "resection_2d", "intersection_2d", "trilateration_2d"]


class StationStatus(StrEnum):
    """Status of a station position (:attr:`StationResult.status`); each member is its string value."""

    OK = "ok"
    #: other positions fit equally well (see ``alternatives``)
    AMBIGUOUS = "ambiguous"


@dataclass(frozen=True)
class StationResult:
    """Adjusted position of one unknown point.

    Attributes
    ----------
    id : str
    e_m, n_m : float
        Adjusted Easting, Northing (m).
    cov : ndarray (2, 2)
        Covariance of (E, N) in m² (a-posteriori σ̂0 unless the options say "apriori").
    se_m, sn_m : float
        Standard deviations (m).
    orientation_rad, orientation_std_rad : float or None
        Orientation unknown of the direction set (resection with directions).
    ellipse_standard, ellipse_95 : ErrorEllipse
    status : StationStatus
        ``ok`` or ``ambiguous``.
    reason : str
    alternatives : tuple of (E, N, vᵀWv)
        Other positions that fit (only when ambiguous).
    network : NetworkResult
        Full adjustment (observations with residuals, redundancy, w/τ tests, χ² test).
    """

    id: str
    e_m: float
    n_m: float
    cov: np.ndarray
    se_m: float
    sn_m: float
    orientation_rad: float | None
    orientation_std_rad: float | None
    ellipse_standard: ErrorEllipse
    ellipse_95: ErrorEllipse
    status: StationStatus
    reason: str
    alternatives: tuple
    network: NetworkResult

    @property
    def sigma0(self) -> float:
        return self.network.sigma0

    @property
    def dof(self) -> int:
        return self.network.dof


def _control(control) -> dict:
    if not isinstance(control, dict) or not control:
        raise InputError("control must be a non-empty dict {point id: (E, N)}")
    out = {}
    for k, v in control.items():
        e, n = (float(t) for t in v[:2])
        if not (math.isfinite(e) and math.isfinite(n)):
            raise InputError(f"control point {k!r} has non-finite coordinates")
        out[str(k)] = {"x": e, "y": n}
    return out


def _sig(value, key, name):
    if isinstance(value, dict):
        if key not in value:
            raise InputError(f"no {name} standard deviation for {key!r}")
        value = value[key]
    v = float(value)
    if not (v > 0 and math.isfinite(v)):
        raise InputError(f"{name} standard deviation must be > 0, got {value!r}")
    return v


def _sig_i(value, i, name):
    """σ of the i-th observation: one value for all, or a sequence with one value each."""
    if value is not None and not np.isscalar(value):
        seq = list(value)
        if i >= len(seq):
            raise InputError(f"{name} standard deviations: {len(seq)} given, observation {i + 1} has none")
        value = seq[i]
    return _sig(value, None, name)


def _angular(kind: str, station: str, target: str, value, sigma: float, **kw) -> Observation:
    """An angular observation (rad) with its value reduced to [0, 2π)."""
    return Observation(kind, station, target, float(value) % (2 * math.pi), sigma, unit="rad", **kw)


def _solve(points, obs, unknown, approx, options, on_ambiguity, n_unknowns_hint) -> StationResult:
    if len(obs) < n_unknowns_hint:
        raise TooFewPointsError(
            f"{len(obs)} observation(s) cannot determine {n_unknowns_hint} unknown(s) "
            f"(E, N{' and the orientation' if n_unknowns_hint == 3 else ''}); add observations"
        )
    ctrl = np.array([[p["x"], p["y"]] for k, p in points.items() if k != unknown])
    fixed = tuple((k, a) for k in points if k != unknown for a in ("x", "y"))
    starts = []
    if approx is not None:
        starts.append(tuple(float(t) for t in approx[:2]))
    else:
        starts = _candidate_starts(points, obs, unknown, ctrl)
    sols = []
    last_err: MinegeoError | None = None
    for e0, n0 in starts:
        pts = dict(points)
        pts[unknown] = {"x": e0, "y": n0}
        net = Network(pts, Datum("fix", fixed), list(obs), 2)
        try:
            res = adjust_network(net, options)
        except MinegeoError as exc:
            last_err = exc
            continue
        p = res.points[unknown]
        sols.append((res.lsq.vtwv, p.x, p.y, res))
    if not sols:
        if isinstance(last_err, DegenerateGeometryError) and any(
            o.kind in ("direction", "angle") for o in obs
        ):
            raise DegenerateGeometryError(
                f"{last_err}. For a resection from directions/angles this happens when the station lies on "
                "(or very near) the circle through the control points (danger circle): add a distance or "
                "another control point off that circle"
            ) from None
        if last_err is not None:
            raise last_err
        raise DegenerateGeometryError("no approximate position led to a converged adjustment")
    sols.sort(key=lambda s: s[0])
    best = sols[0]
    res = best[3]
    p = res.points[unknown]
    tol = max(1e-3, 10.0 * math.sqrt(max(p.cov[0, 0] + p.cov[1, 1], 0.0)))
    alts = []
    for vtwv, e, n, _ in sols[1:]:
        if math.hypot(e - best[1], n - best[2]) > tol and vtwv <= best[0] * (1 + 1e-6) + 1e-9 * max(
            1.0, len(obs)
        ):
            if not any(math.hypot(e - a[0], n - a[1]) <= tol for a in alts):
                alts.append((e, n, vtwv))
    status, reason = StationStatus.OK, ""
    if alts and approx is None:
        collinear = _collinear(ctrl)
        reason = (
            f"ambiguous: {len(alts) + 1} positions fit equally well, e.g. ({best[1]:.4f}, {best[2]:.4f}) and "
            f"({alts[0][0]:.4f}, {alts[0][1]:.4f})"
            + (
                "; the control points are collinear, so the position is only known up to its mirror image"
                if collinear
                else ""
            )
            + "; add an observation that separates them or give approximate coordinates"
        )
        if on_ambiguity == "raise":
            raise DegenerateGeometryError(reason)
        status = StationStatus.AMBIGUOUS
    orient = None
    orient_sd = None
    if res.orientations:
        _, orient, orient_sd = next(iter(res.orientations.values()))
    return StationResult(
        id=unknown,
        e_m=p.x,
        n_m=p.y,
        cov=p.cov[:2, :2].copy(),
        se_m=p.sx_m,
        sn_m=p.sy_m,
        orientation_rad=orient,
        orientation_std_rad=orient_sd,
        ellipse_standard=p.ellipse_standard,
        ellipse_95=p.ellipse_95,
        status=status,
        reason=reason,
        alternatives=tuple(alts),
        network=res,
    )


def _collinear(ctrl: np.ndarray) -> bool:
    if len(ctrl) < 3:
        return True
    c = ctrl - ctrl.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    return bool(sv[1] <= 1e-9 * max(sv[0], 1e-300))


def _grid_misclosures(points, obs, unknown, E, N):
    """Weighted misclosures of every observation for the unknown point at each grid node (vectorised)."""

    def xy(p):
        if p == unknown:
            return E, N
        return points[p]["x"], points[p]["y"]

    def az(a, b):
        (xa, ya), (xb, yb) = xy(a), xy(b)
        return np.arctan2(xb - xa, yb - ya)

    out = []
    sets: dict = {}
    for o in obs:
        if o.kind == "distance":
            (xa, ya), (xb, yb) = xy(o.station), xy(o.target)
            f = np.hypot(xb - xa, yb - ya) - o.value
        elif o.kind == "azimuth":
            f = az(o.station, o.target) - o.value
        elif o.kind == "angle":
            f = az(o.station, o.target) - az(o.station, o.backsight) - o.value
        else:  # direction: orientation removed per set below
            sets.setdefault(o.set_id, []).append((len(out), az(o.station, o.target) - o.value))
            out.append(None)
            continue
        if o.kind != "distance":
            f = np.mod(f + np.pi, 2 * np.pi) - np.pi
        out.append(f / float(o.sigma))
    for members in sets.values():
        d = np.stack([m for _, m in members])
        mean = np.arctan2(np.sin(d).mean(axis=0), np.cos(d).mean(axis=0))
        for (i, m), o_i in zip(members, [obs[i] for i, _ in members], strict=True):
            out[i] = (np.mod(m - mean + np.pi, 2 * np.pi) - np.pi) / float(o_i.sigma)
    return np.stack(out)


def _candidate_starts(points, obs, unknown, ctrl, grid: int = 61, keep: int = 6):
    """Local minima of vᵀWv on a grid over the control area (plus the distances' reach)."""
    lo, hi = ctrl.min(axis=0), ctrl.max(axis=0)
    span = float(max(np.max(hi - lo), 1.0))
    reach = max([float(o.value) for o in obs if o.kind == "distance"], default=0.0)
    pad = max(span, reach)
    es = np.linspace(lo[0] - pad, hi[0] + pad, grid)
    ns = np.linspace(lo[1] - pad, hi[1] + pad, grid)
    E, N = np.meshgrid(es, ns, indexing="ij")
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.sum(_grid_misclosures(points, obs, unknown, E, N) ** 2, axis=0)
    near = np.min(np.hypot(E[..., None] - ctrl[:, 0], N[..., None] - ctrl[:, 1]), axis=-1) < 1e-6 * span
    cost[near | ~np.isfinite(cost)] = np.inf
    cand = []
    for i in range(grid):
        for j in range(grid):
            c = cost[i, j]
            if not np.isfinite(c):
                continue
            if c <= np.min(cost[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2]):
                cand.append((c, float(es[i]), float(ns[j])))
    cand.sort()
    return [(e, n) for _, e, n in cand[:keep]] or [
        (float(np.mean(ctrl[:, 0])) + 0.1 * span, float(np.mean(ctrl[:, 1])) + 0.1 * span)
    ]


def resection_2d(
    control,
    *,
    directions=None,
    distances=None,
    angles=None,
    sigma_direction_rad=None,
    sigma_distance_m=None,
    sigma_angle_rad=None,
    station: str = "P",
    approx=None,
    options: LSQOptions | None = None,
    on_ambiguity: str = "raise",
) -> StationResult:
    """Resect an unknown station from directions, distances and/or angles to known points.

    Parameters
    ----------
    control : dict[str, (float, float)]
        Known points ``{id: (E, N)}`` (m).
    directions : dict[str, float], optional
        Horizontal directions (rad, clockwise circle reading) from the station to control points;
        one orientation unknown is added.
    distances : dict[str, float], optional
        Horizontal distances (m) from the station to control points.
    angles : list of (backsight, foresight, angle_rad), optional
        Clockwise angles at the station from backsight to foresight (Ghilani Ex. 15.5).
    sigma_direction_rad, sigma_distance_m : float or dict
        A-priori standard deviations (one value, or ``{target: σ}``).
    sigma_angle_rad : float or sequence
        One value, or one per angle.
    station : str
        Name of the unknown station.
    approx : (E, N), optional
        Approximate position; searched for when omitted.
    options : LSQOptions, optional
    on_ambiguity : {"raise", "report"}

    Returns
    -------
    StationResult

    Raises
    ------
    TooFewPointsError
        Fewer observations than unknowns.
    DegenerateGeometryError
        Danger circle / collinear or coincident control, or an ambiguous solution.
    """
    pts = _control(control)
    if station in pts:
        raise InputError(f"station name {station!r} is also a control point")
    obs = []
    for tgt, val in (directions or {}).items():
        obs.append(_angular("direction", station, str(tgt), val, _sig(sigma_direction_rad, tgt, "direction"), set_id=1))
    for tgt, val in (distances or {}).items():
        obs.append(
            Observation("distance", station, str(tgt), float(val), _sig(sigma_distance_m, tgt, "distance"))
        )
    for i, (bs, fs, val) in enumerate(angles or []):
        obs.append(_angular("angle", station, str(fs), val, _sig_i(sigma_angle_rad, i, "angle"), backsight=str(bs)))
    for o in obs:
        for p in (o.target, o.backsight):
            if p is not None and p not in pts:
                raise InputError(f"observed point {p!r} is not in the control list")
    if not obs:
        raise TooFewPointsError("a resection needs observations (directions, distances or angles)")
    need = 3 if directions else 2
    return _solve(pts, obs, station, approx, options, on_ambiguity, need)


def intersection_2d(
    control,
    *,
    angles=None,
    azimuths=None,
    sigma_angle_rad=None,
    sigma_azimuth_rad=None,
    target: str = "U",
    approx=None,
    options: LSQOptions | None = None,
    on_ambiguity: str = "raise",
) -> StationResult:
    """Intersect an unknown point from angles or azimuths observed at known stations.

    Parameters
    ----------
    control : dict[str, (float, float)]
    angles : list of (station, backsight, foresight, angle_rad), optional
        Clockwise angles at a known station; one of backsight/foresight is the target
        (Ghilani Ex. 15.4).
    azimuths : dict[str, float], optional
        Grid azimuths (rad) from known stations to the target.
    sigma_angle_rad, sigma_azimuth_rad : float
    target : str
    approx, options, on_ambiguity : see :func:`resection_2d`
    """
    pts = _control(control)
    obs = []
    for i, (st, bs, fs, val) in enumerate(angles or []):
        obs.append(_angular("angle", str(st), str(fs), val, _sig_i(sigma_angle_rad, i, "angle"), backsight=str(bs)))
    for st, val in (azimuths or {}).items():
        obs.append(_angular("azimuth", str(st), target, val, _sig(sigma_azimuth_rad, None, "azimuth")))
    if not obs:
        raise TooFewPointsError("an intersection needs angles or azimuths")
    for o in obs:
        for p in (o.station, o.target, o.backsight):
            if p is not None and p != target and p not in pts:
                raise InputError(f"point {p!r} is not in the control list")
    return _solve(pts, obs, target, approx, options, on_ambiguity, 2)


def trilateration_2d(
    control,
    distances,
    *,
    sigma_distance_m=None,
    target: str = "U",
    approx=None,
    options: LSQOptions | None = None,
    on_ambiguity: str = "raise",
) -> StationResult:
    """Locate an unknown point from horizontal distances to known points (2 are ambiguous, 3+ unique
    unless the control is collinear)."""
    pts = _control(control)
    if sigma_distance_m is None:
        raise InputError("sigma_distance_m is required (a-priori distance standard deviation, m)")
    obs = []
    for tgt, val in distances.items():
        if str(tgt) not in pts:
            raise InputError(f"point {tgt!r} is not in the control list")
        obs.append(
            Observation("distance", target, str(tgt), float(val), _sig(sigma_distance_m, tgt, "distance"))
        )
    return _solve(pts, obs, target, approx, options, on_ambiguity, 2)
