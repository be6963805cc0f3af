"""The cues of the up direction in a scan: the floor and wall fits, the normal modes, the block jackknife and the fusion.

Steps 2-5 of the method of :mod:`minegeo.localize.gravity`: the modes of the area density of the
normals scored by the floor signature (:func:`_column_score`), the floor refined by iteratively
reweighted total least squares (:func:`_fit_plane`), the walls by Gauss-Newton on
``sum w (n . up)^2`` (:func:`_fit_walls`), the delete-one-block jackknife over slices along the
drift axis (:func:`_block_replicates`, :func:`_jackknife`) and the information-weighted fusion
(:func:`_fuse`). Angles in radians inside; vectors in the scan frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo.localize import _kernels_gravity as KG
from minegeo.localize.gravity_result import _EPS_VAR
from minegeo.localize.params import GravityParams

_MAD_TO_TUKEY = 7.0  # Tukey scale = 7 MAD (4.685 sigma of a Gaussian, sigma = 1.4826 MAD)
_MAX_STEP_RAD = math.radians(1.0)  # largest Gauss-Newton step of the wall fit


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
