"""Statistics a surveyor files for control and check stations of a SLAM run (pure NumPy).

Notation: ``n`` stations, each with residuals ``v_k = (v_E, v_N, v_H)`` (m, *adjusted minus
observed*, the sign of :mod:`minegeo.survey.lsq`), stacked station by station into ``v`` (3n,).
``Σll`` (m²) is their a-priori covariance, ``σ0`` the a-priori standard deviation of unit weight
(default 1, dimensionless) and the weight matrix ``P = σ0² Σll⁻¹``.

Variance factor and global test (Ghilani 2010, Ch. 5 and 21) -- (CS1), (CS2)::

    σ̂0² = vᵀ P v / r                                                     (CS1)
    passed  ⇔  χ²_{α/2, r} ≤ vᵀ P v / σ0² ≤ χ²_{1−α/2, r}   (two-sided, α = 0.05)      (CS2)

with ``r`` the redundancy (degrees of freedom) of the adjustment; the test itself is
:func:`minegeo.survey.lsq.chi2_global_test`.

Baarda's w-test (data snooping, Baarda 1968) per observation ``i`` (one coordinate of a station) -- (CS3)::

    w_i = (P v)_i / (σ0 √(P Qvv P)_ii)     (= v_i / (σ0 √(Qvv)_ii) for a diagonal P)   (CS3)
    flagged  ⇔  |w_i| > k,   k = Φ⁻¹(1 − α0/2)   (α0 = 0.001: k = 3.29)

``Qvv`` is the cofactor matrix of the residuals (``Σvv = σ0² Qvv``) from the adjustment. When only
``r`` is known, the redundancy is taken as spread evenly over the observations,
``Qvv ≈ (r / 3n) Qll`` (``Qll = Σll / σ0²``), and the result says so (``qvv_source``): a
uniform-redundancy approximation, not the adjustment's own ``Qvv``.

Check stations (never in the fit) -- (CS4)::

    Δ = estimated − surveyed = (ΔE, ΔN, ΔH);  Δh = √(ΔE² + ΔN²);  Δ3 = √(ΔE² + ΔN² + ΔH²)
    RMSE_E = √(mean ΔE²), ..., RMSE_h = √(mean Δh²), RMSE_3D = √(mean Δ3²)           (CS4)

Class test after ICSM SP1 (Intergovernmental Committee on Surveying and Mapping, *Standard for
the Australian Survey Control Network, Special Publication 1*, v1.7, §1.4) -- (CS5)::

    r_allowed = c (d + 0.2)     r_allowed in mm, d in **kilometres**, c the class constant      (CS5)

(c = 50 for Class D, the class of most underground control; 30 for C, 15 for B, 7.5 for A). SP1
compares ``r_allowed`` with the semi-major axis of the 95 % *relative* error ellipse between the
two stations at distance ``d``. Here each check station is paired with its nearest control
station (horizontal distance ``d``) and tested on (a) its observed relative horizontal error
``|Δh(check) − Δh(control)|`` (Δh the horizontal error vectors, control residuals taken as the
control's error) and, when the 2×2 relative covariance is given, (b) the 95 % relative ellipse's
semi-major axis (:func:`minegeo.survey.ellipse.error_ellipse`, k = 2.4477). A check station passes
when every tested quantity is ≤ ``r_allowed``.

Misclosure ratio -- (CS6)::

    1 : N,   N = L / m                                                                (CS6)

``L`` the traverse length (m, along the trajectory between the stations), ``m`` the misclosure
(m, the horizontal error at its end); ``N = inf`` for a zero misclosure. Conventional figures:
1:5000 for underground traverses of a mine plan.

Residual cofactors of a rigid (6-parameter) or similarity (7-parameter) fit of control stations --
(CS7)::

    Qvv = Qll − A N⁻¹ Aᵀ,    N = Aᵀ P A,    P = Qll⁻¹
    A_k = [ I₃   −[y_k]ₓ   (y_k / s) ]        (last column for the similarity only)

for the model ``x_k = s R p_k + t`` linearised at the fit, ``y_k = s R p_k`` (the station's fitted
point less the translation), the parameters ``(δt, δθ, δs)`` with ``R ← Exp(δθ) R``. ``tr(Qvv P) =
3n − 6`` (rigid) or ``3n − 7`` (similarity): the redundancy numbers of the stations, which the w-test
(CS3) divides by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from minegeo.errors import InputError
from minegeo.geometry.se3 import hat
from minegeo.survey.lsq import Chi2Test, chi2_global_test

__all__ = ["ControlStatistics", "CheckErrors", "ClassTest", "control_statistics", "check_errors",
           "sp1_allowed_mm", "class_test", "misclosure_ratio", "redundancy_share", "SP1_CLASS_CONSTANTS"]

#: ICSM SP1 class constants c (mm) of (CS5).
SP1_CLASS_CONSTANTS = {"3A": 1.0, "2A": 3.0, "A": 7.5, "B": 15.0, "C": 30.0, "D": 50.0, "E": 100.0}
_COMPONENTS = ("E", "N", "H")


def _block_cov(cov, n: int) -> np.ndarray:
    """Σll (3n, 3n) from sigmas (n, 3), per-station blocks (n, 3, 3) or a full (3n, 3n) matrix."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape == (n, 3):
        if np.any(~np.isfinite(c)) or np.any(c <= 0):
            raise InputError("station standard deviations must be finite and > 0")
        return np.diag((c**2).reshape(-1))
    if c.shape == (n, 3, 3):
        full = np.zeros((3 * n, 3 * n))
        for k in range(n):
            full[3 * k:3 * k + 3, 3 * k:3 * k + 3] = c[k]
        c = full
    if c.shape != (3 * n, 3 * n):
        raise InputError(f"covariance of {n} stations: expected sigmas (n, 3), blocks (n, 3, 3) or (3n, 3n), "
                         f"got {c.shape}")
    if not np.all(np.isfinite(c)) or not np.allclose(c, c.T, rtol=1e-12, atol=0.0):
        raise InputError("the station covariance must be finite and symmetric")
    return c


@dataclass(frozen=True)
class ControlStatistics:
    """Result of :func:`control_statistics`.

    Attributes
    ----------
    ids : tuple of str
    v : ndarray (n, 3), m
        Residuals E N H.
    dof : int
        Redundancy ``r``.
    vtpv : float
        ``vᵀ P v`` (dimensionless with σ0 = 1).
    sigma0_apriori, sigma0_sq : float
        ``σ0`` and ``σ̂0² = vᵀPv / r`` (CS1) (NaN when r = 0).
    chi2 : Chi2Test
        Two-sided test (CS2).
    w : ndarray (n, 3)
        Baarda w per coordinate (CS3); NaN where ``(PQvvP)_ii`` is zero (an unchecked observation).
    redundancy_numbers : ndarray (n, 3)
        ``(Qvv P)_ii`` per coordinate (sum ``r``).
    w_critical, alpha0 : float
        ``k = Φ⁻¹(1 − α0/2)`` and α0.
    flagged : tuple of (str, str, float)
        ``(station id, component E|N|H, w)`` for each ``|w| > k``, largest |w| first.
    qvv_source : str
        ``"adjustment"`` (Qvv given) or ``"uniform redundancy r/3n (approximation)"``.
    """

    ids: tuple
    v: np.ndarray
    dof: int
    vtpv: float
    sigma0_apriori: float
    sigma0_sq: float
    chi2: Chi2Test
    w: np.ndarray
    redundancy_numbers: np.ndarray
    w_critical: float
    alpha0: float
    flagged: tuple
    qvv_source: str

    @property
    def sigma0(self) -> float:
        """``σ̂0`` (NaN when r = 0)."""
        return math.sqrt(self.sigma0_sq) if np.isfinite(self.sigma0_sq) else float("nan")

    @property
    def flagged_ids(self) -> tuple:
        """Ids of the stations with a flagged coordinate, most suspect first."""
        seen: list[str] = []
        for sid, _c, _w in self.flagged:
            if sid not in seen:
                seen.append(sid)
        return tuple(seen)


def control_statistics(v, cov, *, qvv=None, dof: int | None = None, ids=None, sigma0_apriori: float = 1.0,
                       alpha: float = 0.05, alpha0: float = 0.001) -> ControlStatistics:
    """σ̂0², the χ² test and Baarda's w-tests of control-station residuals (CS1)-(CS3).

    Parameters
    ----------
    v : array_like (n, 3), m
        Residuals E N H of the control stations (adjusted minus observed).
    cov : array_like
        A-priori covariance ``Σll`` (m²): sigmas (n, 3) (m), blocks (n, 3, 3) or full (3n, 3n).
    qvv : array_like (3n, 3n), optional
        Cofactor matrix of the residuals from the adjustment (``Σvv = σ0² Qvv``, m² for σ0 = 1).
        Without it ``dof`` is needed and ``Qvv ≈ (r / 3n) Qll``.
    dof : int, optional
        Redundancy ``r``. With ``qvv`` it defaults to ``round(trace(Qvv P))`` (which must be an
        integer to 1e-6).
    ids : sequence of str, optional
        Station names (default ``"1" ... "n"``).
    sigma0_apriori : float
        ``σ0``: ``P = σ0² Σll⁻¹``.
    alpha, alpha0 : float
        Significance of the χ² test (two-sided) and of each w-test.

    Raises
    ------
    InputError
        Shapes that do not agree, a covariance that is not positive definite, ``r`` missing or
        outside ``[0, 3n]``, ``trace(Qvv P)`` not an integer, α outside (0, 1).
    """
    V = np.asarray(v, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < 1 or not np.all(np.isfinite(V)):
        raise InputError(f"residuals: expected finite (n, 3) values E N H, got shape {V.shape}")
    n = V.shape[0]
    ids = tuple(str(i) for i in (ids if ids is not None else range(1, n + 1)))
    if len(ids) != n:
        raise InputError(f"{len(ids)} ids for {n} stations")
    for name, a in (("alpha", alpha), ("alpha0", alpha0)):
        if not (0.0 < a < 1.0):
            raise InputError(f"{name} must lie in (0, 1), got {a!r}")
    if not (math.isfinite(sigma0_apriori) and sigma0_apriori > 0):
        raise InputError(f"sigma0_apriori must be > 0, got {sigma0_apriori!r}")
    S = _block_cov(cov, n)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InputError("the station covariance is not positive definite") from None
    Sinv = np.linalg.solve(L.T, np.linalg.solve(L, np.eye(3 * n)))
    P = sigma0_apriori**2 * Sinv
    vf = V.reshape(-1)
    if qvv is not None:
        Q = np.asarray(qvv, dtype=np.float64)
        if Q.shape != (3 * n, 3 * n) or not np.all(np.isfinite(Q)):
            raise InputError(f"Qvv: expected a finite ({3 * n}, {3 * n}) matrix, got {Q.shape}")
        tr = float(np.trace(Q @ P))
        if dof is None:
            if abs(tr - round(tr)) > 1e-6 * max(1.0, tr):
                raise InputError(f"trace(Qvv P) = {tr:.9g} is not an integer redundancy: Qvv and the covariance "
                                 "do not come from the same adjustment")
            dof = int(round(tr))
        source = "adjustment"
    else:
        if dof is None:
            raise InputError("give the redundancy dof (or the adjustment's Qvv)")
        Q = (dof / (3.0 * n)) * S / sigma0_apriori**2
        source = "uniform redundancy r/3n (approximation)"
    dof = int(dof)
    if not 0 <= dof <= 3 * n:
        raise InputError(f"redundancy {dof} outside [0, {3 * n}] for {n} stations")
    Pv = P @ vf
    vtpv = float(vf @ Pv)
    chi2 = chi2_global_test(vtpv, dof, sigma0_apriori, alpha)                                  # (CS2)
    sigma0_sq = vtpv / dof if dof > 0 else float("nan")                                         # (CS1)
    PQP = np.einsum("ij,jk,ki->i", P, Q, P)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = PQP > 1e-20 * np.diag(P) ** 2
        w = np.where(ok, Pv / (sigma0_apriori * np.sqrt(np.where(ok, PQP, 1.0))), np.nan)      # (CS3)
    red = np.einsum("ij,ji->i", Q, P)
    k = float(stats.norm.ppf(1.0 - alpha0 / 2.0))
    order = np.argsort(-np.nan_to_num(np.abs(w), nan=-1.0), kind="stable")
    flagged = tuple((ids[i // 3], _COMPONENTS[i % 3], float(w[i])) for i in order if ok[i] and abs(w[i]) > k)
    return ControlStatistics(ids=ids, v=V, dof=dof, vtpv=vtpv, sigma0_apriori=float(sigma0_apriori),
                             sigma0_sq=sigma0_sq, chi2=chi2, w=w.reshape(n, 3), redundancy_numbers=red.reshape(n, 3),
                             w_critical=k, alpha0=float(alpha0), flagged=flagged, qvv_source=source)


def redundancy_share(qvv, cov) -> int:
    """The redundancy the residuals of ``n`` stations carry in a larger adjustment: the sum of their
    redundancy numbers ``Σ r_i = tr(Qvv P)``, ``P = Σll⁻¹`` (σ0 = 1), rounded to a whole number in
    ``[0, 3n]`` for :func:`control_statistics`.

    In a pose graph whose odometry is a chain the stations carry the whole redundancy of the graph;
    loop closures and extra odometry edges carry a part of it, which the graph's own χ² test counts
    and the stations' does not.

    Parameters
    ----------
    qvv : array_like (3n, 3n)
        Cofactors of the residuals (m², σ0 = 1).
    cov : array_like
        A-priori covariance of the stations (m²), as in :func:`control_statistics`.
    """
    Q = np.asarray(qvv, dtype=np.float64)
    S = _block_cov(cov, Q.shape[0] // 3)
    share = float(np.trace(np.linalg.solve(S, Q.T).T))  # tr(Q S⁻¹)
    return int(round(min(max(share, 0.0), float(Q.shape[0]))))


@dataclass(frozen=True)
class CheckErrors:
    """Errors of check stations (CS4), m.

    Attributes
    ----------
    ids : tuple of str
    delta : ndarray (n, 3)
        ``estimated − surveyed`` E N H.
    horizontal, d3 : ndarray (n,)
        ``√(ΔE² + ΔN²)`` and ``√(ΔE² + ΔN² + ΔH²)``.
    rmse_enh : ndarray (3,)
        RMSE of ΔE, ΔN, ΔH.
    rmse_horizontal, rmse_vertical, rmse_3d : float
    """

    ids: tuple
    delta: np.ndarray
    horizontal: np.ndarray
    d3: np.ndarray
    rmse_enh: np.ndarray
    rmse_horizontal: float
    rmse_vertical: float
    rmse_3d: float


def fit_residual_cofactors(y, cov, *, scale: bool) -> np.ndarray:
    """Cofactors ``Qvv`` (3n, 3n; m² for σ0 = 1) of the residuals of a rigid or similarity fit of
    ``n`` control stations (CS7).

    Parameters
    ----------
    y : array_like (n, 3), m
        ``s R p_k``: each station's fitted point less the fit's translation (E N H).
    cov : array_like
        A-priori covariance ``Qll`` of the stations (m²), as in :func:`control_statistics`.
    scale : bool
        True for the similarity (scale estimated), False for the rigid fit.

    Returns
    -------
    numpy.ndarray (3n, 3n)
        ``Qll − A (Aᵀ P A)⁻¹ Aᵀ``; its ``tr(Qvv P)`` is ``3n − 6`` or ``3n − 7``.
    """
    Y = np.asarray(y, dtype=np.float64)
    n = Y.shape[0]
    Q = _block_cov(cov, n)
    A = np.zeros((3 * n, 7 if scale else 6))
    for k, y_k in enumerate(Y):
        A[3 * k:3 * k + 3, :3] = np.eye(3)
        A[3 * k:3 * k + 3, 3:6] = -hat(y_k)
    if scale:  # the column y_k / s scaled by s: A N⁻¹ Aᵀ depends only on the space A's columns span
        A[:, 6] = Y.reshape(-1)
    P = np.linalg.inv(Q)
    N = A.T @ P @ A
    Qvv = Q - A @ np.linalg.solve(N, A.T)
    return 0.5 * (Qvv + Qvv.T)


def check_errors(estimated_enh, surveyed_enh, ids=None) -> CheckErrors:
    """Errors and RMSE of check stations (CS4).

    Parameters
    ----------
    estimated_enh, surveyed_enh : array_like (n, 3), m
        The station point from the run (sensor pose at its time ⊕ offset) and its surveyed E N H
        (both relative to the same origin, or both absolute).
    ids : sequence of str, optional
    """
    est = np.asarray(estimated_enh, dtype=np.float64)
    sur = np.asarray(surveyed_enh, dtype=np.float64)
    if est.shape != sur.shape or est.ndim != 2 or est.shape[1] != 3 or est.shape[0] < 1:
        raise InputError(f"check stations: estimated {est.shape} and surveyed {sur.shape} must both be (n >= 1, 3)")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(sur))):
        raise InputError("check stations: coordinates must be finite")
    n = est.shape[0]
    ids = tuple(str(i) for i in (ids if ids is not None else range(1, n + 1)))
    d = est - sur
    h = np.hypot(d[:, 0], d[:, 1])
    d3 = np.sqrt(h**2 + d[:, 2] ** 2)
    rm = np.sqrt(np.mean(d**2, axis=0))
    return CheckErrors(ids=ids, delta=d, horizontal=h, d3=d3, rmse_enh=rm,
                       rmse_horizontal=float(np.sqrt(np.mean(h**2))), rmse_vertical=float(rm[2]),
                       rmse_3d=float(np.sqrt(np.mean(d3**2))))


def sp1_allowed_mm(d_m, c: float = 50.0) -> np.ndarray:
    """ICSM SP1 allowed relative error (CS5): ``r = c (d_km + 0.2)`` mm for a distance ``d_m`` in metres."""
    if not (math.isfinite(c) and c > 0):
        raise InputError(f"class constant c must be > 0, got {c!r}")
    d = np.asarray(d_m, dtype=np.float64)
    return c * (d / 1000.0 + 0.2)


@dataclass(frozen=True)
class ClassTest:
    """Result of :func:`class_test` per check station (CS5).

    Attributes
    ----------
    ids, nearest_control : tuple of str
    distance_m : ndarray (n,)
        Horizontal distance to the nearest control station (m).
    allowed_mm : ndarray (n,)
        ``c (d_km + 0.2)``.
    relative_error_mm : ndarray (n,)
        ``|Δh(check) − Δh(control)|`` (mm).
    ellipse_semi_major_mm : ndarray (n,) or None
        95 % relative error ellipse semi-major axis (mm), when the relative covariance is given.
    passed : ndarray (n,) bool
    c : float
    """

    ids: tuple
    nearest_control: tuple
    distance_m: np.ndarray
    allowed_mm: np.ndarray
    relative_error_mm: np.ndarray
    ellipse_semi_major_mm: np.ndarray | None
    passed: np.ndarray
    c: float


def class_test(check_enh, check_delta, control_enh, control_delta, *, check_ids=None, control_ids=None,
               c: float = 50.0, relative_cov_h=None) -> ClassTest:
    """ICSM SP1-style class test of each check station against its nearest control station (CS5).

    Parameters
    ----------
    check_enh, control_enh : array_like (n, 3), (m, 3), m
        Surveyed positions (the distance ``d`` is horizontal, between these).
    check_delta, control_delta : array_like (n, 3), (m, 3), m
        Errors ``estimated − surveyed`` (control: the residuals of the fit).
    check_ids, control_ids : sequence of str, optional
    c : float
        Class constant (mm); 50 = Class D (:data:`SP1_CLASS_CONSTANTS`).
    relative_cov_h : array_like (n, 2, 2), optional
        Covariance (m²) of ``E N`` of each check station relative to its nearest control station.
    """
    from minegeo.survey.ellipse import error_ellipse

    ce, cd = np.asarray(check_enh, np.float64), np.asarray(check_delta, np.float64)
    ke, kd = np.asarray(control_enh, np.float64), np.asarray(control_delta, np.float64)
    if ce.shape != cd.shape or ke.shape != kd.shape or ce.ndim != 2 or ke.ndim != 2 or ce.shape[1:] != (3,) \
            or ke.shape[1:] != (3,) or len(ke) < 1:
        raise InputError("class test: check and control positions and errors must be (n, 3) arrays, >= 1 control")
    n, m = len(ce), len(ke)
    cids = tuple(str(i) for i in (check_ids if check_ids is not None else range(1, n + 1)))
    kids = tuple(str(i) for i in (control_ids if control_ids is not None else range(1, m + 1)))
    dist = np.hypot(ce[:, None, 0] - ke[None, :, 0], ce[:, None, 1] - ke[None, :, 1])
    j = np.argmin(dist, axis=1) if n else np.zeros(0, int)
    d = dist[np.arange(n), j] if n else np.zeros(0)
    allowed = sp1_allowed_mm(d, c)
    rel = 1000.0 * np.hypot(cd[:, 0] - kd[j, 0], cd[:, 1] - kd[j, 1])
    passed = rel <= allowed
    semi = None
    if relative_cov_h is not None:
        C = np.asarray(relative_cov_h, np.float64)
        if C.shape != (n, 2, 2):
            raise InputError(f"relative_cov_h: expected ({n}, 2, 2), got {C.shape}")
        semi = np.array([1000.0 * error_ellipse(C[i], confidence=0.95).semi_major_m for i in range(n)])
        passed = passed & (semi <= allowed)
    return ClassTest(ids=cids, nearest_control=tuple(kids[i] for i in j), distance_m=d, allowed_mm=allowed,
                     relative_error_mm=rel, ellipse_semi_major_mm=semi, passed=passed, c=float(c))


def misclosure_ratio(traverse_length_m, misclosure_m) -> np.ndarray:
    """``N`` of the ratio 1:N (CS6): traverse length / misclosure (both m); ``inf`` for a zero misclosure."""
    L = np.asarray(traverse_length_m, np.float64)
    mis = np.abs(np.asarray(misclosure_m, np.float64))
    if np.any(~np.isfinite(L)) or np.any(L < 0) or np.any(~np.isfinite(mis)):
        raise InputError("misclosure ratio: lengths must be finite and >= 0, misclosures finite")
    with np.errstate(divide="ignore"):
        return np.where(mis > 0, L / np.where(mis > 0, mis, 1.0), np.inf)
