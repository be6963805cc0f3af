"""Survey networks (1D levelling, 2D horizontal, 3D): observation equations and adjustment.

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

Formats
-------
Networks are read by :mod:`minegeo.io`: :func:`~minegeo.io.network.read_network` (a file),
:func:`~minegeo.io.network_krumm.parse_krumm` (the Krumm/Gama text format: ``[Coordinates]``,
``[Datum]``, ``[Distances]``, ``[Angles]``, ...) and :func:`~minegeo.io.network_json.network_from_dict`
(the JSON form of ``docs/survey.md``); :class:`Observation`, :class:`Datum` and :class:`Network`
are defined in :mod:`minegeo.io.network_types` and exported here. Restrictions are compiled by
:mod:`minegeo.survey.restrictions`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.io.network_types import ANGULAR, Datum, Network, Observation
from minegeo.survey.angles import wrap_2pi, wrap_pi
from minegeo.survey.ellipse import ErrorEllipse, ellipse_scale, point_ellipses, relative_ellipse
from minegeo.survey.lsq import LSQOptions, LSQResult, adjust
from minegeo.survey.restrictions import restriction_constraints

__all__ = [
    "Observation",
    "Datum",
    "Network",
    "NetworkResult",
    "PointResult",
    "ObservationResult",
    "adjust_network",
]

log = logging.getLogger(__name__)


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
        return np.array([o is not None and o.kind in ANGULAR for o, _ in self.rows])

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
        rfun = restriction_constraints(model)
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
                adjusted=F[r] if o.kind not in ANGULAR else wrap_2pi(F[r]),
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
