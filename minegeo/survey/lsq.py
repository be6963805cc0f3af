"""General weighted least squares of indirect observations (Gauss–Markov model) with survey statistics.

Model and notation (Simela et al., "MAST", Sec. *Scanner horizontal position*; Mikhail & Gracie
1981; Ghilani 2010, Ch. 11–12 and 21)::

    v + B·Δ = f                 linearised observation equations, one row per observation
    N = Bᵀ W B,  t = Bᵀ W f     normal equations
    Δ = N⁻¹ t                   correction to the approximate parameters x0 (iterated)
    v = f − B·Δ                 residuals
    σ̂0² = vᵀ W v / r            a-posteriori variance of unit weight, r = n − u (+ constraints)
    Qxx = N⁻¹,  Σxx = σ0²·Qxx   cofactor and covariance of the parameters

For observation equations ``l̂ = F(x)`` (adjusted observation as a function of the parameters)
the sign convention of Mikhail/Simela is ``B = −∂F/∂x`` and ``f = F(x0) − l``; then the residual
``v = f − BΔ = F(x̂) − l = l̂ − l`` is *adjusted minus observed* (Ghilani's ``l + v = l̂``).
:func:`adjust_observations` does this bookkeeping for you when you can write ``F`` and its
Jacobian; :func:`adjust` takes ``(f, B)`` directly.

Weights: ``W`` is the weight matrix with ``Σll = σ0²·W⁻¹``, σ0 being the a-priori standard
deviation of unit weight (default 1: then ``W = Σll⁻¹`` and σ0 is dimensionless).

Statistics reported (Ghilani 2010, Ch. 21; Baarda 1968; Pope 1976):

* cofactor matrix of residuals ``Qvv = W⁻¹ − B Qxx Bᵀ`` and redundancy numbers
  ``r_i = (Qvv W)_ii`` (``Σ r_i = r``; ``r_i < 0.1`` means the observation is barely checked);
* Baarda's **w-test** (data snooping) ``w_i = (Wv)_i / (σ0·sqrt((W Qvv W)_ii))`` with the
  *a-priori* σ0, compared with the two-sided normal quantile (α0 = 0.001 -> 3.29);
* Pope's **tau-test**: the same statistic with the *a-posteriori* σ̂0, compared with the τ
  critical value ``τ = sqrt(r)·t / sqrt(r − 1 + t²)``, ``t = t_{r−1}(1 − α/(2n))`` (α = 0.05);
* the two-tailed **χ² global test** of ``vᵀWv/σ0² ~ χ²(r)`` at 95 % (Ghilani 2010, Ch. 5
  "testing the sample variance" and Ch. 21): passed iff ``χ²_{α/2,r} ≤ vᵀWv/σ0² ≤ χ²_{1−α/2,r}``.

Datum constraints (free networks) and restrictions are handled with a bordered normal matrix
``[[N, Cᵀ], [C, 0]]`` (Ghilani 2010, chapter "constraint equations"; Lagrange multipliers);
each constraint adds one degree of freedom.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy import stats

from minegeo.errors import ConvergenceError, DegenerateGeometryError, InputError, TooFewPointsError

__all__ = [
    "LSQOptions",
    "Chi2Test",
    "LSQResult",
    "adjust",
    "adjust_linear",
    "adjust_observations",
    "weights_from_sigmas",
    "chi2_global_test",
    "tau_critical",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LSQOptions:
    """Options of a least-squares adjustment.

    Attributes
    ----------
    variance : {"aposteriori", "apriori"}
        Which σ0 scales ``Σxx = σ0²·Qxx``: the estimated σ̂0 (what adjustment packages print by
        default) or the a-priori σ0 (use when the observation precisions are trusted).
    sigma0_apriori : float
        A-priori standard deviation of unit weight (dimensionless when ``W = Σll⁻¹``).
    alpha_global : float
        Significance level of the two-tailed χ² global test (0.05 -> 95 %).
    alpha_w : float
        Significance level of Baarda's w-test per observation (0.001 -> |w| > 3.29 flagged).
    alpha_tau : float
        Overall significance level of Pope's tau-test (Bonferroni-divided by n).
    max_iterations : int
        Gauss–Newton iterations for non-linear models.
    tol_rel : float
        Converged when every ``|Δ_i| ≤ tol_rel·σ0·sqrt(Qxx_ii)`` (corrections negligible
        against their own precision) or ``|Δ| ≤ tol_abs``.
    tol_abs : float
        Absolute tolerance on every correction (parameter units).
    min_redundancy : float
        Redundancy numbers below this are flagged "weakly controlled".
    """

    variance: str = "aposteriori"
    sigma0_apriori: float = 1.0
    alpha_global: float = 0.05
    alpha_w: float = 0.001
    alpha_tau: float = 0.05
    max_iterations: int = 50
    tol_rel: float = 1e-9
    tol_abs: float = 1e-12
    min_redundancy: float = 0.1

    def __post_init__(self):
        if self.variance not in ("aposteriori", "apriori"):
            raise InputError(f"variance must be 'aposteriori' or 'apriori', got {self.variance!r}")
        for name in ("sigma0_apriori",):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be > 0, got {v!r}")
        for name in ("alpha_global", "alpha_w", "alpha_tau"):
            v = getattr(self, name)
            if not (0 < v < 1):
                raise InputError(f"{name} must be between 0 and 1, got {v!r}")
        if self.max_iterations < 1:
            raise InputError("max_iterations must be >= 1")


@dataclass(frozen=True)
class Chi2Test:
    """Two-tailed χ² test of the variance factor: ``statistic = vᵀWv/σ0² = r·σ̂0²/σ0²``.

    ``passed`` is None when there is no redundancy (r = 0).
    """

    statistic: float
    dof: int
    alpha: float
    lower: float
    upper: float
    passed: bool | None

    @property
    def verdict(self) -> str:
        if self.passed is None:
            return "NOT TESTABLE (no redundancy)"
        return "PASSED" if self.passed else "FAILED"

    def sigma0_text(self) -> str:
        """``σ̂0 = sqrt(statistic / dof)`` and, when the test failed, on which side of its 95 % interval
        ``sqrt(lower / dof)``-``sqrt(upper / dof)`` it lies and what that side means."""
        dof = max(self.dof, 1)
        s0, lo, hi = (float(np.sqrt(x / dof)) for x in (self.statistic, self.lower, self.upper))
        if self.passed is not False:
            return f"sigma0 {s0:.2f}"
        side, why = (("below", "the factors agree better than their stated uncertainty") if s0 < lo else
                     ("above", "the factors disagree more than their stated uncertainty allows"))
        return f"sigma0 {s0:.2f}, {side} its {100 * (1 - self.alpha):g} % interval {lo:.2f}-{hi:.2f}: {why}"


@dataclass(frozen=True)
class LSQResult:
    """Result of :func:`adjust`.

    Attributes
    ----------
    x : ndarray (u,)
        Adjusted parameters.
    v : ndarray (n,)
        Residuals ``v = l̂ − l`` (adjusted minus observed), in observation units.
    dof : int
        Degrees of freedom ``r = n − u + c`` (c = number of constraints).
    vtwv : float
        ``vᵀ W v``.
    sigma0_apriori, sigma0_sq : float
        A-priori σ0 and a-posteriori variance of unit weight σ̂0² = vᵀWv/r (NaN when r = 0).
    variance_used : str
        "aposteriori" or "apriori": which σ0 scales ``Sigma_xx`` (when r = 0 the a-priori σ0
        is used and this says so).
    Qxx, Sigma_xx : ndarray (u, u)
        Cofactor matrix ``N⁻¹`` (constrained: top-left block of the bordered inverse) and
        covariance ``σ0²·Qxx``.
    qvv_diag, redundancy : ndarray (n,)
        Diagonal of ``Qvv`` and redundancy numbers ``r_i = (Qvv W)_ii``.
    w : ndarray (n,)
        Baarda w statistic (standardised residual with the a-priori σ0).
    tau : ndarray (n,)
        Pope τ statistic (standardised residual with σ̂0).
    w_critical, tau_critical : float
    flags : tuple of str
        Per observation: "" or a comma list of "w-test", "tau-test", "weak r_i", "no check".
    chi2 : Chi2Test
    iterations : int
    converged : bool
    param_names, obs_names : tuple of str
    options : LSQOptions
    """

    x: np.ndarray
    v: np.ndarray
    dof: int
    vtwv: float
    sigma0_apriori: float
    sigma0_sq: float
    variance_used: str
    Qxx: np.ndarray
    Sigma_xx: np.ndarray
    qvv_diag: np.ndarray
    redundancy: np.ndarray
    w: np.ndarray
    tau: np.ndarray
    w_critical: float
    tau_critical: float
    flags: tuple
    chi2: Chi2Test
    iterations: int
    converged: bool
    param_names: tuple
    obs_names: tuple
    options: LSQOptions = field(default_factory=LSQOptions)

    @property
    def sigma0(self) -> float:
        """A-posteriori standard deviation of unit weight σ̂0 (NaN when r = 0)."""
        return math.sqrt(self.sigma0_sq) if np.isfinite(self.sigma0_sq) else float("nan")

    @property
    def sigma_used(self) -> float:
        """The σ0 that scales :attr:`Sigma_xx`."""
        return self.sigma0 if self.variance_used == "aposteriori" else self.sigma0_apriori

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the parameters ``sqrt(diag Σxx)``."""
        return np.sqrt(np.clip(np.diag(self.Sigma_xx), 0.0, None))

    @property
    def standardized_residuals(self) -> np.ndarray:
        """Alias of :attr:`w` (Baarda's standardised residuals)."""
        return self.w

    def index(self, name: str) -> int:
        """Index of a parameter by name."""
        try:
            return self.param_names.index(name)
        except ValueError:
            raise KeyError(f"no parameter named {name!r}") from None

    def suspected_blunder(self) -> int | None:
        """Index of the observation with the largest |w| if it fails the w-test, else None."""
        if self.dof == 0 or not np.isfinite(self.w).any():
            return None
        i = int(np.nanargmax(np.abs(self.w)))
        return i if abs(self.w[i]) > self.w_critical else None


def weights_from_sigmas(sigmas, sigma0_apriori: float = 1.0) -> np.ndarray:
    """Diagonal weights ``w_i = σ0²/σ_i²`` from a-priori standard deviations (all > 0)."""
    s = np.asarray(sigmas, dtype=np.float64)
    if s.ndim != 1 or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError("observation standard deviations must be a 1-D array of finite values > 0")
    return (sigma0_apriori / s) ** 2


def chi2_global_test(vtwv: float, dof: int, sigma0_apriori: float = 1.0, alpha: float = 0.05) -> Chi2Test:
    """Two-tailed χ² test of ``vᵀWv/σ0²`` with ``dof`` degrees of freedom (Ghilani 2010, Ch. 5)."""
    stat = float(vtwv) / sigma0_apriori**2
    if dof <= 0:
        return Chi2Test(stat, int(dof), alpha, float("nan"), float("nan"), None)
    lo = float(stats.chi2.ppf(alpha / 2.0, dof))
    hi = float(stats.chi2.ppf(1.0 - alpha / 2.0, dof))
    return Chi2Test(stat, int(dof), alpha, lo, hi, bool(lo <= stat <= hi))


def tau_critical(n_obs: int, dof: int, alpha: float = 0.05) -> float:
    """Pope's τ critical value ``sqrt(r)·t/sqrt(r−1+t²)`` with ``t = t_{r−1}(1−α/(2n))`` (NaN if r < 2)."""
    if dof < 2 or n_obs < 1:
        return float("nan")
    t = float(stats.t.ppf(1.0 - alpha / (2.0 * n_obs), dof - 1))
    return math.sqrt(dof) * t / math.sqrt(dof - 1 + t * t)


def _as_weight(W, n: int):
    """Return (W as 1-D diagonal or 2-D matrix, is_diag)."""
    Wa = np.asarray(W, dtype=np.float64)
    if Wa.ndim == 1:
        if Wa.shape[0] != n:
            raise InputError(f"weights have {Wa.shape[0]} entries for {n} observations")
        if not np.all(np.isfinite(Wa)) or np.any(Wa <= 0):
            raise InputError("weights must be finite and > 0")
        return Wa, True
    if Wa.shape != (n, n):
        raise InputError(f"weight matrix must be ({n}, {n}), got {Wa.shape}")
    if not np.all(np.isfinite(Wa)) or not np.allclose(Wa, Wa.T, rtol=1e-10, atol=0):
        raise InputError("weight matrix must be finite and symmetric")
    return Wa, False


def _null_space_hint(N: np.ndarray, names: Sequence[str]) -> str:
    d = np.sqrt(np.clip(np.diag(N), 1e-300, None))
    Ns = N / d[:, None] / d[None, :]
    vals, vecs = np.linalg.eigh(Ns)
    vec = vecs[:, 0]
    idx = np.argsort(-np.abs(vec))[:4]
    parts = [names[i] for i in idx if abs(vec[i]) > 0.1 * abs(vec[idx[0]])]
    return ", ".join(parts)


def _solve_normal(N, t, C, c, names):
    """Solve (bordered) normal equations with Jacobi scaling; return Δ, Qxx."""
    u = N.shape[0]
    diag = np.diag(N).copy()
    if C is None or C.shape[0] == 0:
        if np.any(diag <= 0):
            bad = [names[i] for i in np.flatnonzero(diag <= 0)]
            raise DegenerateGeometryError(
                f"no observation determines parameter(s) {', '.join(bad[:6])}; add observations or fix them"
            )
        d = 1.0 / np.sqrt(diag)
        Ns = N * d[:, None] * d[None, :]
        ev = np.linalg.eigvalsh(Ns)
        if ev[0] <= 1e-12 * ev[-1]:
            raise DegenerateGeometryError(
                "the normal matrix is singular (condition "
                f"{ev[-1] / max(ev[0], 1e-300):.1e}): the observations do not determine "
                f"{_null_space_hint(N, names)} — e.g. collinear or coincident control, a missing datum "
                "(fix a point/orientation or use a free-network datum) or too few observations"
            )
        cf = scipy.linalg.cho_factor(Ns, lower=False, check_finite=False)
        delta = d * scipy.linalg.cho_solve(cf, d * t, check_finite=False)
        Qxx = d[:, None] * scipy.linalg.cho_solve(cf, np.diag(d), check_finite=False)
        return delta, 0.5 * (Qxx + Qxx.T)
    m = C.shape[0]
    scale = np.where(diag > 0, 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    Ns = N * scale[:, None] * scale[None, :]
    Cs = C * scale[None, :]
    rn = np.linalg.norm(Cs, axis=1, keepdims=True)
    rn[rn == 0] = 1.0
    Cs = Cs / rn
    K = np.zeros((u + m, u + m))
    K[:u, :u] = Ns
    K[:u, u:] = Cs.T
    K[u:, :u] = Cs
    sv = np.linalg.svd(K, compute_uv=False)
    if sv[-1] <= 1e-12 * sv[0]:
        raise DegenerateGeometryError(
            "the constrained normal matrix is singular: the datum constraints do not remove the "
            "network's datum defect (or observations are missing) — check the [Datum] points/coordinates"
        )
    Kinv = np.linalg.inv(K)
    rhs = np.concatenate([scale * t, np.asarray(c, dtype=np.float64) / rn[:, 0]])
    sol = Kinv @ rhs
    delta = scale * sol[:u]
    Qxx = Kinv[:u, :u] * scale[:, None] * scale[None, :]
    return delta, 0.5 * (Qxx + Qxx.T)


def _linearise(fun, x):
    """``fun(x)`` as float64 arrays: misclosures ``f`` (n,) and design matrix ``B``."""
    f, B = fun(x)
    return np.asarray(f, dtype=np.float64).ravel(), np.asarray(B, dtype=np.float64)


def _iterate(fun, x, f, B, C, c, Wm, is_diag, opts, names, constraints, linear, damped: bool):
    """The iterations of :func:`adjust` from ``x`` (``f``, ``B``, ``C``, ``c`` there): full Gauss–Newton
    steps, or (``damped``) each step through :func:`_line_search`. Returns ``(x, f, B, C, c, Δ, Qxx,
    iterations, converged, σ of the parameters, float64 floor)``."""
    converged, it, delta, Qxx, sd, floor = False, 0, None, None, None, None
    for it_ in range(1, opts.max_iterations + 1):
        it = it_
        WB, N = _normal_matrix(B, Wm, is_diag)
        t = WB.T @ f
        delta, Qxx = _solve_normal(N, t, C, c, names)
        if linear:
            x = x + delta
            converged = True
            break
        sd = opts.sigma0_apriori * np.sqrt(np.clip(np.diag(Qxx), 0.0, None))
        # negligible against the parameter's precision, or at the float64 resolution of x
        floor = np.maximum(opts.tol_abs, 16.0 * np.spacing(np.abs(x + delta)))
        small = np.all((np.abs(delta) <= opts.tol_rel * sd) | (np.abs(delta) <= floor))
        if damped:
            x, f, B = _line_search(fun, x, delta, f, t, Wm, is_diag)
        else:
            x = x + delta
            f, B = _linearise(fun, x)
        C, c = constraints(x)
        if small:
            converged = True
            break
    return x, f, B, C, c, delta, Qxx, it, converged, sd, floor


def _cost(f, Wm, is_diag: bool) -> float:
    """``vᵀ W v`` of the misclosures ``f``."""
    return float(f @ (Wm * f)) if is_diag else float(f @ Wm @ f)


#: the Gauss–Newton step is accepted when it lowers ``vᵀWv`` by at least this fraction of the decrease
#: its linear model predicts (Armijo's condition; Nocedal & Wright 2006, Sec. 3.1)
ARMIJO_C = 1e-4


#: a change of ``vᵀWv`` within this fraction of it is taken for rounding by :func:`_line_search`
COST_ROUNDING = 1e-12


def _line_search(fun, x, delta, f, t, Wm, is_diag: bool):
    """``(x + αΔ, f, B)``: the Gauss–Newton step ``Δ``, shortened when it does not lower ``φ(α) = vᵀWv``.

    The full step ``α = 1`` is taken when ``φ(1) ≤ φ(0) + c α φ'(0) + ρ φ(0)`` (Armijo's condition,
    ``c`` = :data:`ARMIJO_C`, with ``φ(0)``'s rounding ``ρ`` = :data:`COST_ROUNDING`), with
    ``φ'(0) = −2 tᵀΔ < 0`` (``t = BᵀWf``: the Gauss–Newton step is a descent direction). Else ``α`` is
    the minimum of the parabola through ``φ(0)``, ``φ'(0)`` and ``φ(α)``, kept in ``[0.1 α, 0.5 α]``
    (Nocedal & Wright 2006, Sec. 3.5), until the condition holds or ``α < 1e-10`` (then the full step).

    The fallback of :func:`adjust` when full steps do not converge: a large-residual problem, where
    the misfit's curvature exceeds ``BᵀWB`` along a weakly determined parameter (e.g. the rotation
    about the line of nearly collinear points with a gross error), makes Gauss–Newton oscillate about
    the minimum with a growing amplitude; the shortened steps converge to it (linearly). The relative
    rounding ``ρ φ(0)`` is what such a problem's ``vᵀWv`` (far from 0) is known to.
    """
    phi0 = _cost(f, Wm, is_diag)
    slope = -2.0 * float(t @ delta)
    alpha = 1.0
    while True:
        xa = x + alpha * delta
        fa, Ba = _linearise(fun, xa)
        phi = _cost(fa, Wm, is_diag)
        if not slope < 0.0 or (np.isfinite(phi) and phi <= phi0 + ARMIJO_C * alpha * slope + COST_ROUNDING * phi0):
            return xa, fa, Ba
        curv = phi - phi0 - slope * alpha
        nxt = -slope * alpha**2 / (2.0 * curv) if np.isfinite(phi) and curv > 0.0 else 0.5 * alpha
        alpha = float(np.clip(nxt, 0.1 * alpha, 0.5 * alpha))
        if alpha < 1e-10:
            xa = x + delta
            fa, Ba = _linearise(fun, xa)
            return xa, fa, Ba


def _normal_matrix(B, Wm, is_diag: bool):
    """``W·B`` and the normal matrix ``N = Bᵀ W B`` (``Wm`` diagonal as a vector when ``is_diag``)."""
    if is_diag:
        WB = B * Wm[:, None]
    else:
        WB = Wm @ B
    return WB, B.T @ WB


def _constraint_function(constraints):
    """``x -> (C, c)`` for the constraints argument of :func:`adjust` (``(None, None)`` without)."""

    def _constraints(xc):
        if constraints is None:
            return None, None
        if callable(constraints):
            C, c = constraints(xc)
            C = np.atleast_2d(np.asarray(C, dtype=np.float64))
            return C, np.asarray(c, dtype=np.float64).ravel()
        C = np.atleast_2d(np.asarray(constraints, dtype=np.float64))
        return C, np.zeros(C.shape[0])

    return _constraints


def _labels(param_names, obs_names, u: int, n: int) -> tuple[tuple, tuple]:
    """Parameter and observation labels (``p0..``, ``l0..`` by default), checked against the model size."""
    names = tuple(param_names) if param_names is not None else tuple(f"p{i}" for i in range(u))
    onames = tuple(obs_names) if obs_names is not None else tuple(f"l{i}" for i in range(n))
    if len(names) != u or len(onames) != n:
        raise InputError("param_names / obs_names lengths do not match the model")
    return names, onames


def _redundancy(n: int, u: int, C) -> int:
    """Degrees of freedom ``r = n − u + m`` (m constraints); raises when negative."""
    m = 0 if C is None else C.shape[0]
    if C is not None and C.shape[1] != u:
        raise InputError(f"constraint matrix must have {u} columns, got {C.shape}")
    dof = n - u + m
    if dof < 0:
        raise TooFewPointsError(
            f"{n} observation(s) and {m} constraint(s) cannot determine {u} unknown(s): "
            f"at least {u - m} observations are needed"
        )
    return dof


def adjust(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    weights,
    *,
    constraints: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | np.ndarray | None = None,
    options: LSQOptions | None = None,
    param_names: Sequence[str] | None = None,
    obs_names: Sequence[str] | None = None,
    linear: bool = False,
) -> LSQResult:
    """Iterated weighted least squares of indirect observations ``v + BΔ = f``.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (f, B)``: misclosure vector ``f`` (n,) and design matrix ``B`` (n, u) at the
        current parameters ``x`` (convention above: ``B = −∂F/∂x``, ``f = F(x) − l``, so that
        ``v = f − BΔ`` is adjusted-minus-observed). Angular misclosures must already be wrapped
        to (−π, π].
    x0 : array_like (u,)
        Approximate parameters.
    weights : array_like (n,) or (n, n)
        Weights ``W`` (diagonal as a vector, or a full symmetric positive-definite matrix).
    constraints : callable or ndarray, optional
        Datum constraints / restrictions ``C·Δ = c``. An ndarray ``C`` (m, u) means ``c = 0``
        (inner/free-network constraints on the corrections); a callable ``constraints(x) ->
        (C, c)`` is re-linearised every iteration (non-linear restrictions ``g(x) = 0`` give
        ``C = ∂g/∂x``, ``c = −g(x)``).
    options : LSQOptions, optional
    param_names, obs_names : sequence of str, optional
        Labels used in messages and reports.
    linear : bool
        The model is linear: one solve, no iteration.

    Returns
    -------
    LSQResult

    Raises
    ------
    TooFewPointsError
        Fewer observations (+ constraints) than unknowns.
    DegenerateGeometryError
        The normal matrix is singular (collinear control, missing datum, ...).
    ConvergenceError
        No convergence within ``options.max_iterations``.

    Notes
    -----
    Simela et al. (MAST paper), Sec. "Scanner Horizontal Position": ``N = BᵀWB``,
    ``t = BᵀWf``, ``Δ = N⁻¹t``, ``v = f − BΔ``, ``Σ = σ0²N⁻¹``. The normal matrix is solved by
    Cholesky (``scipy.linalg.cho_solve``) after symmetric Jacobi scaling so that mixed units
    (metres, radians) do not hurt the conditioning. Converged when the full Gauss–Newton step ``Δ``
    is negligible (``tol_rel``, ``tol_abs``). Without constraints, when full steps do not converge in
    ``max_iterations``, the iteration restarts from ``x0`` with each step through a backtracking line
    search on ``vᵀWv`` (:func:`_line_search`; the reported iterations count both runs).
    """
    opts = options or LSQOptions()
    x = np.array(x0, dtype=np.float64, copy=True).ravel()
    u = x.size
    f, B = _linearise(fun, x)
    n = f.size
    if B.shape != (n, u):
        raise InputError(f"design matrix B must be ({n}, {u}), got {B.shape}")
    Wm, is_diag = _as_weight(weights, n)
    names, onames = _labels(param_names, obs_names, u, n)
    _constraints = _constraint_function(constraints)
    C, c = _constraints(x)
    dof = _redundancy(n, u, C)

    x0v, f0, B0 = x, f, B
    x, f, B, C, c, delta, Qxx, it, converged, sd, floor = _iterate(fun, x, f, B, C, c, Wm, is_diag, opts, names,
                                                                  _constraints, linear, damped=False)
    if not converged and C is None:  # large residuals along a weak parameter: Gauss–Newton with a line search
        x, f, B, C, c, delta, Qxx, it2, converged, sd, floor = _iterate(fun, x0v, f0, B0, C, c, Wm, is_diag, opts,
                                                                       names, _constraints, linear, damped=True)
        it += it2
    if not converged:
        k = int(np.argmax(np.abs(delta) / np.maximum(sd, floor)))
        raise ConvergenceError(
            f"least squares did not converge in {opts.max_iterations} iterations"
            f"{' (nor with a line search)' if C is None else ''}: the last correction to {names[k]} is {delta[k]:.3e} ({abs(delta[k]) / max(sd[k], 1e-300):.3g} times "
            f"its standard deviation {sd[k]:.3e}): the observations barely determine it or contradict each "
            "other (a gross error); check approximate coordinates, observation units and the geometry"
        )
    if linear:
        v = f - B @ delta
    else:
        # residuals at the solution: one more linearisation, Δ ≈ 0 so v = f (exactly F(x̂) − l)
        v = f.copy()
        WB, N = _normal_matrix(B, Wm, is_diag)
        _, Qxx = _solve_normal(N, WB.T @ f, C, c, names)
    return _statistics(x, v, B, Wm, is_diag, Qxx, dof, opts, it, converged, names, onames)


def _statistics(x, v, B, Wm, is_diag, Qxx, dof, opts, it, converged, names, onames) -> LSQResult:
    n = v.size
    if is_diag:
        Wv = Wm * v
        vtwv = float(v @ Wv)
        BQ = B @ Qxx
        bqb = np.einsum("ij,ij->i", BQ, B)
        qvv = 1.0 / Wm - bqb
        # W Qvv W diagonal = w_i² qvv_i ; redundancy (Qvv W)_ii = qvv_i w_i
        wqw = Wm * Wm * qvv
        red = qvv * Wm
    else:
        Wv = Wm @ v
        vtwv = float(v @ Wv)
        Qll = np.linalg.inv(Wm)
        Qvv = Qll - B @ Qxx @ B.T
        WQW = Wm @ Qvv @ Wm
        wqw = np.diag(WQW).copy()
        qvv = np.diag(Qvv).copy()
        red = np.einsum("ij,ji->i", Qvv, Wm)
    s0 = opts.sigma0_apriori
    sigma0_sq = vtwv / dof if dof > 0 else float("nan")
    if opts.variance == "aposteriori" and dof > 0:
        variance_used = "aposteriori"
        Sigma = sigma0_sq * Qxx
    else:
        variance_used = "apriori"
        if opts.variance == "aposteriori":
            log.warning("no redundancy (r = 0): covariance scaled with the a-priori sigma0")
        Sigma = s0**2 * Qxx
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = np.sqrt(np.clip(wqw, 0.0, None))
        rel_floor = 1e-10 * np.sqrt(np.abs(Wm if is_diag else np.diag(Wm)))
        ok = wqw > rel_floor**2
        w = np.where(ok, Wv / (s0 * np.where(ok, denom, 1.0)), np.nan)
        s0hat = math.sqrt(sigma0_sq) if dof > 0 and sigma0_sq > 0 else float("nan")
        tau = (
            np.where(ok, Wv / (s0hat * np.where(ok, denom, 1.0)), np.nan)
            if np.isfinite(s0hat)
            else np.full(n, np.nan)
        )
    w_crit = float(stats.norm.ppf(1.0 - opts.alpha_w / 2.0))
    t_crit = tau_critical(n, dof, opts.alpha_tau)
    flags = []
    for i in range(n):
        fl = []
        if not ok[i]:
            fl.append("no check")
        else:
            if abs(w[i]) > w_crit:
                fl.append("w-test")
            # |τ| ≤ sqrt(r) always; for small r the critical value approaches that bound, so a
            # relative margin keeps rounding from flagging |τ| == τ_crit
            if np.isfinite(tau[i]) and np.isfinite(t_crit) and abs(tau[i]) > t_crit * (1.0 + 1e-9):
                fl.append("tau-test")
            if red[i] < opts.min_redundancy:
                fl.append("weak r_i")
        flags.append(",".join(fl))
    chi2 = chi2_global_test(vtwv, dof, s0, opts.alpha_global)
    return LSQResult(
        x=x,
        v=v,
        dof=int(dof),
        vtwv=vtwv,
        sigma0_apriori=s0,
        sigma0_sq=sigma0_sq,
        variance_used=variance_used,
        Qxx=Qxx,
        Sigma_xx=0.5 * (Sigma + Sigma.T),
        qvv_diag=qvv,
        redundancy=red,
        w=w,
        tau=tau,
        w_critical=w_crit,
        tau_critical=t_crit,
        flags=tuple(flags),
        chi2=chi2,
        iterations=it,
        converged=converged,
        param_names=names,
        obs_names=onames,
        options=opts,
    )


def adjust_linear(
    B, l, weights, *, c=None, options=None, param_names=None, obs_names=None, constraints=None
) -> LSQResult:
    """Linear Gauss–Markov model ``l + v = B·x + c`` (ordinary regression sign convention).

    Parameters
    ----------
    B : array_like (n, u)
        Design matrix ``∂l/∂x``.
    l : array_like (n,)
        Observations.
    weights : array_like (n,) or (n, n)
    c : array_like (n,), optional
        Constant term (default 0).

    Returns
    -------
    LSQResult
        ``x`` are the estimated parameters; ``v = Bx̂ + c − l``.
    """
    A = np.asarray(B, dtype=np.float64)
    lv = np.asarray(l, dtype=np.float64).ravel()
    cv = np.zeros_like(lv) if c is None else np.asarray(c, dtype=np.float64).ravel()
    u = A.shape[1]

    def fun(x):
        return A @ x + cv - lv, -A

    return adjust(
        fun,
        np.zeros(u),
        weights,
        options=options,
        param_names=param_names,
        obs_names=obs_names,
        linear=True,
        constraints=constraints,
    )


def adjust_observations(
    model: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    observed,
    *,
    sigmas=None,
    cov=None,
    weights=None,
    angular=None,
    options: LSQOptions | None = None,
    param_names=None,
    obs_names=None,
    constraints=None,
) -> LSQResult:
    """Non-linear observation equations ``l̂ = F(x)``: give ``F`` and its Jacobian, get the adjustment.

    Parameters
    ----------
    model : callable
        ``model(x) -> (F(x), J)`` with ``J = ∂F/∂x`` (n, u).
    x0 : array_like (u,)
        Approximate parameters.
    observed : array_like (n,)
        Observations ``l``.
    sigmas : array_like (n,), optional
        A-priori standard deviations (``W = σ0²/σ²``).
    cov : array_like (n, n), optional
        A-priori covariance ``Σll`` (``W = σ0²·Σll⁻¹``).
    weights : array_like, optional
        Weights directly.
    angular : array_like of bool (n,), optional
        Observations that are angles (radians): their misclosures are wrapped to (−π, π].
    """
    opts = options or LSQOptions()
    lv = np.asarray(observed, dtype=np.float64).ravel()
    n = lv.size
    given = sum(a is not None for a in (sigmas, cov, weights))
    if given != 1:
        raise InputError("give exactly one of sigmas, cov or weights")
    if sigmas is not None:
        W = weights_from_sigmas(sigmas, opts.sigma0_apriori)
    elif cov is not None:
        S = np.asarray(cov, dtype=np.float64)
        if S.shape != (n, n):
            raise InputError(f"cov must be ({n}, {n})")
        try:
            cf = scipy.linalg.cho_factor(S)
        except np.linalg.LinAlgError:
            raise InputError("observation covariance is not positive definite") from None
        W = opts.sigma0_apriori**2 * scipy.linalg.cho_solve(cf, np.eye(n))
        W = 0.5 * (W + W.T)
    else:
        W = weights
    ang = np.zeros(n, dtype=bool) if angular is None else np.asarray(angular, dtype=bool)

    def fun(x):
        Fx, J = model(x)
        f = np.asarray(Fx, dtype=np.float64).ravel() - lv
        if ang.any():
            f[ang] = np.mod(f[ang] + np.pi, 2 * np.pi) - np.pi
        return f, -np.asarray(J, dtype=np.float64)

    return adjust(
        fun, x0, W, options=opts, param_names=param_names, obs_names=obs_names, constraints=constraints
    )
