"""Pose uncertainty of a point-to-plane fit: a data term (formal or cluster-robust) plus named model terms.

The localization pipeline ends with ICP pairs ``(p_i, q_i, n_i)``: a placed scan point, its map
partner and the map normal there. The pose is perturbed about the **scan origin** ``o``
(left perturbation, map axes)::

    x = (ω_x, ω_y, ω_z, t_x, t_y, t_z)      rad, then m
    r_i(x) ≈ r_i + J_i x,   r_i = (p_i − q_i)·n_i,   J_i = [((p_i − o) × n_i)ᵀ, n_iᵀ]

(Low 2004 linearisation of the point-to-plane error; the same ``J`` as
:func:`minegeo.registration.icp.register_icp` but about ``o`` instead of the frame origin),
``H = Σ J_iᵀ J_i`` (the normal matrix), and the pending Gauss-Newton step to the
point-to-plane optimum ``s = −H⁻¹ Σ J_iᵀ r_i`` (0 for a converged point-to-plane ICP).

Estimators
----------
``formal`` (what the pipeline reported before; least squares with i.i.d. residuals)::

    Σ_formal = σ² H⁻¹,    σ² = Σ r_i² / (k − 6)

This is Censi (2007, "An accurate closed-form estimate of ICP's covariance", ICRA, [Censi2007 Eq. 4]:
``cov(x) ≈ (∂²J/∂x²)⁻¹ (∂²J/∂z∂x) cov(z) (∂²J/∂z∂x)ᵀ (∂²J/∂x²)⁻¹``) evaluated with
``cov(z) = σ² I``, i.e. every residual an independent error. It is optimistic on real and
synthetic scans because the residuals of neighbouring pairs are strongly correlated: a scan
voxelised at 0.1 m is matched against a map sampled every 0.2-1 m, so tens of scan points share
one map point and its tangent plane; surface texture that the map does not resolve, map range
noise and normal errors all act on whole patches of the scan at once.

``cluster`` (cluster-robust "sandwich" covariance, CR1; Liang & Zeger 1986; White 1980;
Cameron & Miller 2015, "A practitioner's guide to cluster-robust inference", J. Human
Resources 50(2), [CameronMiller2015 Eqs. 11-12] with the CR1 small-sample factor of their Sec. VI.B)::

    r̂_i   = r_i + J_i s                          residual at the point-to-plane optimum
    g_b   = Σ_{i ∈ b} J_iᵀ r̂_i                  score of spatial block b  (Σ_b g_b = 0)
    Σ_CR1 = c · H⁻¹ (Σ_b g_b g_bᵀ) H⁻¹,    c = G/(G − 1) · (k − 1)/(k − 6)

``jackknife`` (the default; delete-one-block jackknife, CR3 of Cameron & Miller 2015 Sec. VI.B,
MacKinnon & White 1985). Leaving block ``b`` out of the linear least squares moves the estimate
by exactly ``d_b = (H − H_b)⁻¹ g_b`` (``H_b = Σ_{i∈b} J_iᵀ J_i``), so::

    Σ_JK = (G − 1)/G · Σ_b (d_b − d̄)(d_b − d̄)ᵀ

CR1 is biased low when a few blocks carry most of the information on a direction (a drift's
axial position often hangs on a handful of wall features): their scores are partly "fitted
away". The jackknife undoes that leverage; it calibrated better in the study
(``docs/uncertainty.md``) and is the default. A block that alone carries a direction makes
``H − H_b`` nearly singular and ``Σ_JK`` large in that direction — the honest answer.

Blocks ``b`` are cubes of edge ``cluster_size_m`` over the paired scan points, in the
principal-axis frame of those points with the grid anchored at their centroid (so the result
does not depend on the map's axes: a rigid motion of the whole problem rotates the covariance
and nothing else; the grid is symmetric under the sign ambiguity of the axes). Residuals are
allowed to be arbitrarily correlated inside a block and heteroscedastic; blocks are assumed
independent. ``G`` is the number of blocks; with fewer than ``min_clusters`` blocks the edge is
halved until there are enough (``cluster_size_used_m`` records it), because the block
"meat" has rank ``≤ G − 1`` and is noisy for small ``G``.

Data term and model terms
-------------------------
The reported covariance is a sum of named parts (``PoseUncertainty.covariance_data_6x6`` and
``PoseUncertainty.model_terms``; ``to_dict()`` writes them under ``data_term`` and
``model_terms``; the sum is ``covariance_6x6`` exactly)::

    Σ = Σ_data + Σ_small_G + Σ_formal_floor + Σ_pending_step + Σ_registration_floor + Σ_map_floor (+ terms
        added by the caller, e.g. the pipeline's weak_axis_polish)

* **data** (what the scan-to-map residuals determine): ``Σ_JK`` (``jackknife``), ``Σ_CR1``
  (``cluster``) or ``Σ_formal`` (``formal``), as above. The record also gives the fit's information
  ``H``, its normalised constraint eigenvalue ratio and weakest direction (Gelfand et al. 2003,
  :func:`~minegeo.registration.icp.constraint_analysis`), and the largest-σ axis of the data
  term's position block.
* **small_G** ``= (f_G − 1) Σ_data`` with ``f_G = 3 F₃,G−1(0.95) / χ²₃(0.95)``
  (:func:`small_g_factor`; Cameron & Miller Sec. VI.D: Wald tests with a covariance estimated
  from G clusters use ``F(d, G − 1)``): 1.20 for G = 20, 1.04 for G = 100.
* **formal_floor**: what the max rule adds so that the covariance is never smaller than the
  formal one in any direction. With ``Σ_formal = L Lᵀ`` (Cholesky) and
  ``L⁻¹ (f_G Σ_data) L⁻ᵀ = U diag(λ) Uᵀ``, ``f_G Σ_data + Σ_formal_floor = L U diag(max(λ_j, 1)) Uᵀ Lᵀ``,
  so ``vᵀ Σ v ≥ max(vᵀ Σ_formal v, vᵀ f_G Σ_data v)`` for every ``v`` (independent of the square root).
* **pending_step** (``add_pending_step``, default True): ``s sᵀ``. The pose handed in may not be
  the point-to-plane optimum (point-to-point ICP stops early along drifts); its error is
  ``(x_ICP − x_opt) + (x_opt − x_true) = −s + ε``, so the mean-square-error matrix is
  ``s sᵀ + cov(ε)``. Negligible after a converged point-to-plane ICP.
* **registration_floor** (``registration_sigma_m``, default 0.8 mm): ``σ_reg² I₃`` on the
  translation block. A systematic scan-to-map error that no residual reveals: the scan and the
  map sample the same rough surface from different viewpoints (occlusion, voxel centroids of
  curved patches, which map point a scan point pairs with), which biases the fit coherently over
  the whole scan, so it is not in the spread between blocks. Calibrated on the synthetic study
  (``docs/uncertainty.md``, "Two-way calibration"): without it the errors were 1.2x the data
  term in σ in every direction (RMS Mahalanobis / √3 = 1.21); a maximum-likelihood fit over the
  198 ``ok`` scans of the tuning worlds preferred an isotropic floor of 0.83 mm per axis to a
  scale factor (log-likelihood +10), and the fitted floor was 0.7-0.95 mm in every roughness,
  length and frame group. At one fixed place the spread over 16 scan-noise and 12 map-noise
  realisations stayed within the data term: the missing part is fixed by the geometry.
* **map_floor** (``map_sigma_m``, default 0): ``σ_map² I₃``. A prior 1-σ error of the map's
  local position (per axis, m): the scan is fitted to the map, so a rigid local displacement of
  the map (survey / SLAM drift of the map itself) moves the answer by the same amount and no
  residual can reveal it. Independent per-point map noise needs no floor: it is in the residuals
  already and the block estimate sees its sharing between neighbouring pairs.

Not included: the georeferencing error of the map (``T_crs_map``), which is the same for every
scan of the map; combine it with :func:`minegeo.georef.point_covariance_crs`.

95 % regions. The position refers to the **scan origin** (the translation of ``T_map_scan``), the
point the covariance is taken about. ``position_95_radius_m`` is the radius of the ball that holds
the origin with probability 0.95 under ``e ~ N(0, Σ_tt)``, i.e. ``r² = `` the 0.95 quantile of
``Σ_j λ_j χ²₁`` (``λ_j`` the eigenvalues of ``Σ_tt``; :func:`ball_radius`), and
``horizontal_95_radius_m`` the same in plan with ``Σ_xy``. Between ``√(3.841 λ_max)`` (one dominant
axis) and ``√(7.815 λ_max)`` (isotropic). The ball over the largest axis of the 95 % ellipsoid,
``√(7.815 λ_max)``, would hold *more* than 95 % for an elongated ellipsoid (up to 99.5 % when one
axis dominates): too wide by up to ``√(7.815/3.841) = 1.43``.

The calibration against ground truth on the synthetic mine is in ``docs/uncertainty.md``
(``benchmarks/bench_uncertainty_study.py``; the earlier per-estimator study:
``benchmarks/bench_uncertainty.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from minegeo._validate import as_points, as_trusted_points
from minegeo.errors import InputError, TooFewPointsError
from minegeo.localize.params import UNCERTAINTY_METHODS, UncertaintyParams

__all__ = ["UncertaintyParams", "PoseUncertainty", "pose_uncertainty", "block_covariance", "cluster_labels",
           "small_g_factor", "radii_95", "ball_radius", "sum_chi2_cdf", "UNCERTAINTY_METHODS", "MODEL_TERMS",
           "CHI2_3D_95", "CHI2_2D_95"]

#: 95 % quantiles of the chi-square distribution with 3 and 2 degrees of freedom.
CHI2_3D_95 = 7.814727903251178
CHI2_2D_95 = 5.991464547107979
#: Pose parameters (6) + 1: the fewest pairs that leave a residual degree of freedom.
MIN_PAIRS = 7
#: Model terms :func:`pose_uncertainty` may add to the data term, in summation order (a caller may
#: add more with :meth:`PoseUncertainty.with_model_term`, e.g. the pipeline's ``weak_axis_polish``).
MODEL_TERMS = ("small_G", "formal_floor", "pending_step", "registration_floor", "map_floor")
#: Each model term in a surveyor's words (the report and ``model_terms[name]["meaning"]`` of
#: result.json; the names stay the machine-readable keys).
MODEL_TERM_TEXT = {
    "small_G": "allowance for estimating the spread from few blocks of the scan",
    "formal_floor": "raised to at least the textbook least-squares uncertainty in every direction",
    "pending_step": "the last correction the fit had not yet applied",
    "registration_floor": "scan-to-map matching error that no residual shows (calibrated on the synthetic study)",
    "map_floor": "the stated error of the map itself",
    "weak_axis_polish": "the shift of the final polish along the weakly constrained direction",
}
#: Default ``registration_sigma_m`` (m): maximum-likelihood isotropic floor over the tuning worlds


@dataclass(frozen=True)
class PoseUncertainty:
    """Outcome of :func:`pose_uncertainty`. Parameters ``(ω, t)``: rotation (rad) about the scan
    origin then translation (m) of the scan origin, map (work) axes.

    Attributes
    ----------
    covariance_6x6 : (6, 6) ndarray or None
        Reported covariance: ``covariance_data_6x6 + Σ model_terms`` (exactly); None when
        ``degenerate``.
    covariance_formal_6x6 : (6, 6) ndarray or None
        ``σ² H⁻¹`` (for comparison; None when degenerate).
    sigma_m : float
        Residual σ, ``√(Σ r_i² / (k − 6))``, m.
    position_cov_3x3 : (3, 3) ndarray or None
        Translation block of ``covariance_6x6``, m².
    position_sigma_m : (3,) ndarray
        √diag of it, m (inf when degenerate).
    position_95_radius_m, horizontal_95_radius_m : float
        Radius of the ball (circle in plan) holding the scan origin with probability 0.95 under
        ``N(0, position_cov_3x3)`` (:func:`radii_95`), m (inf when degenerate).
    information_6x6 : (6, 6) ndarray
        ``H = Σ J_iᵀ J_i`` about the scan origin (unscaled point-to-plane normal matrix, units
        m² / m / 1 by block); ``σ² H⁻¹`` is the formal covariance.
    information_ratio : float
        ``λ_min / λ_max`` of the normalised constraint matrix (scale-free; small = degenerate).
    n_pairs : int
    n_clusters : int
        Spatial blocks used (0 for ``formal``).
    cluster_size_used_m : float
        Block edge after any halving (nan for ``formal``).
    method : str
    inflation : float
        ``tr(f_G Σ_CR,tt) / tr(Σ_formal,tt)``: how much the cluster-robust position variance
        (with the small-G factor) exceeds the formal one (before the max rule; nan for
        ``formal`` or degenerate). The position block is used because the full trace mixes rad²
        and m².
    pending_step : (6,) ndarray or None
        ``s = −H⁻¹ Jᵀ r`` (None when degenerate).
    degenerate : bool
    reason : str
        Why the covariance is missing (empty otherwise).
    params : UncertaintyParams
    residuals_m : (k,) ndarray
        Point-to-plane residuals ``r_i`` of the pairs at the given pose, m (pair order).
    covariance_data_6x6 : (6, 6) ndarray or None
        The data term: what the residuals of the fit determine (``Σ_JK``, ``Σ_CR1`` or
        ``Σ_formal`` by ``method``), before any model term.
    model_terms : dict of str -> (6, 6) ndarray
        Every model term added, by name, in summation order (:data:`MODEL_TERMS`, then any
        :meth:`with_model_term`); empty when degenerate.
    weakest_constraint_6 : (6,) ndarray or None
        Eigenvector of the smallest eigenvalue of the normalised constraint matrix
        (:func:`~minegeo.registration.icp.constraint_analysis`: ``(L ω, t_c)``, rotation scaled
        by the RMS radius ``L`` of the pairs, translation of their centroid): the direction the
        geometry constrains least.
    weakest_axis : (3,) ndarray or None
        Unit axis (map axes) of the largest standard deviation of the data term's position block.
    weakest_sigma_m : float
        That standard deviation, m.
    position_95_radius_data_m : float
        The 95 % radius of the data term alone, m.
    """

    covariance_6x6: np.ndarray | None
    covariance_formal_6x6: np.ndarray | None
    sigma_m: float
    position_cov_3x3: np.ndarray | None
    position_sigma_m: np.ndarray
    position_95_radius_m: float
    horizontal_95_radius_m: float
    information_6x6: np.ndarray
    information_ratio: float
    n_pairs: int
    n_clusters: int
    cluster_size_used_m: float
    method: str
    inflation: float
    pending_step: np.ndarray | None
    degenerate: bool
    reason: str
    params: UncertaintyParams
    residuals_m: np.ndarray | None = field(default=None, repr=False)
    covariance_data_6x6: np.ndarray | None = None
    model_terms: dict = field(default_factory=dict)
    weakest_constraint_6: np.ndarray | None = None
    weakest_axis: np.ndarray | None = None
    weakest_sigma_m: float = math.inf
    position_95_radius_data_m: float = math.inf

    def with_model_term(self, name: str, cov_6x6) -> PoseUncertainty:
        """A copy with one more model term ``cov_6x6`` (symmetric PSD, ``(ω, t)`` about the scan
        origin) added to ``model_terms`` and to the total; the radii follow. Unchanged when
        degenerate (no covariance)."""
        if self.covariance_6x6 is None:
            return self
        M = np.asarray(cov_6x6, dtype=np.float64)
        if M.shape != (6, 6) or not np.isfinite(M).all():
            raise InputError(f"model term {name!r} must be a finite (6, 6) matrix, got shape {M.shape}")
        if name in self.model_terms:
            raise InputError(f"model term {name!r} is already in the covariance")
        M = 0.5 * (M + M.T)
        terms = {**self.model_terms, name: M}
        return replace(self, model_terms=terms, **_total_fields(self.covariance_data_6x6, terms))

    def terms_record(self) -> dict:
        """The data term and each model term: covariance, position σ and 95 % radius (JSON-ready
        through :meth:`to_dict`). ``data_term.covariance_6x6 + Σ model_terms[*].covariance_6x6 ==
        covariance_6x6``."""
        D = self.covariance_data_6x6
        ps = None if D is None else np.sqrt(np.maximum(np.diag(D)[3:], 0.0))
        data = {"method": self.method, "covariance_6x6": D, "position_sigma_m": ps,
                "position_95_radius_m": self.position_95_radius_data_m, "information_ratio": self.information_ratio,
                "weakest_constraint_6": self.weakest_constraint_6, "weakest_position_axis": self.weakest_axis,
                "weakest_position_sigma_m": self.weakest_sigma_m, "n_pairs": self.n_pairs,
                "n_clusters": self.n_clusters, "sigma_m": self.sigma_m,
                "note": "covariance the residuals of the fit determine (block jackknife / CR1 / formal); "
                        "weakest_constraint_6 = (L*omega, t_centroid) eigenvector of the normalised constraint "
                        "matrix with the smallest eigenvalue (information_ratio = its lambda_min / lambda_max)"}
        model = {}
        for name, M in self.model_terms.items():
            s = np.sqrt(np.maximum(np.diag(M)[3:], 0.0))
            model[name] = {"covariance_6x6": M, "position_sigma_m": s,
                           "position_rms_m": float(math.sqrt(max(float(np.trace(M[3:, 3:])), 0.0))),
                           "meaning": MODEL_TERM_TEXT.get(name, name)}
        return {"data_term": data, "model_terms": model}

    def to_dict(self) -> dict:
        """JSON-ready record (arrays as lists, None kept); the data and model terms under
        ``data_term`` and ``model_terms`` (:meth:`terms_record`)."""
        from minegeo._provenance import to_jsonable

        skip = ("params", "residuals_m", "covariance_data_6x6", "model_terms", "weakest_constraint_6", "weakest_axis",
                "weakest_sigma_m")
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in skip}
        d["params"] = {k: getattr(self.params, k) for k in self.params.__dataclass_fields__}
        d.update(self.terms_record())
        return to_jsonable(d)


def _total_fields(data: np.ndarray, terms: dict) -> dict:
    """``covariance_6x6``, position block, σ and radii of ``data + Σ terms`` (summation in order)."""
    C = data.copy()
    for M in terms.values():
        C = C + M
    pos = C[3:, 3:].copy()
    r95, h95 = radii_95(pos)
    return {"covariance_6x6": C, "position_cov_3x3": pos, "position_sigma_m": np.sqrt(np.maximum(np.diag(pos), 0.0)),
            "position_95_radius_m": r95, "horizontal_95_radius_m": h95}


def sum_chi2_cdf(x: float, lam) -> float:
    """``P(Σ_j λ_j Z_j² ≤ x)`` for 1 to 3 weights ``λ_j ≥ 0`` and independent standard normal ``Z_j``.

    The distribution of a positive quadratic form in normal variables (Imhof 1961, Biometrika
    48:419-426: central, one degree of freedom per weight), here by one exact 1-D integral. Sort
    ``λ₁ ≥ λ₂ ≥ λ₃``; ``Y = λ₂Z₂² + λ₃Z₃²`` has the density (polar coordinates in ``(Z₂, Z₃)``)::

        f_Y(y) = exp(−y(a + b)) I₀(y b) / (2√(λ₂λ₃)),   a = (1/λ₂ + 1/λ₃)/4 − b,  b = (1/λ₃ − 1/λ₂)/4

    (``a + b = (1/λ₂ + 1/λ₃)/4``; ``I₀`` the modified Bessel function, evaluated as ``i0e`` so that
    ``exp(−y(a + b)) I₀(yb) = i0e(yb) exp(−y/(2λ₂))``), and ``P(λ₁Z₁² ≤ u) = erf(√(u/(2λ₁)))``, so::

        P(Q ≤ x) = ∫₀^x f_Y(y) erf(√((x − y)/(2λ₁))) dy          (y = t², dy = 2t dt)

    With two weights ``f_Y`` is the ``λ₂χ²₁`` density. Accuracy ~1e-10 (``scipy.integrate.quad``).
    """
    from scipy.integrate import quad
    from scipy.special import i0e

    w = sorted((float(v) for v in np.asarray(lam, dtype=np.float64).ravel() if v > 0.0), reverse=True)
    if len(w) > 3:
        raise InputError("sum_chi2_cdf takes at most 3 weights")
    if x <= 0.0 or not w:
        return 0.0 if x <= 0.0 else 1.0
    l1 = w[0]
    if len(w) == 1:
        return math.erf(math.sqrt(x / (2.0 * l1)))
    l2 = w[1]
    if len(w) == 2:
        c2 = 2.0 / math.sqrt(2.0 * math.pi * l2)

        def g(t):  # t = √y, y = λ₂ Z² : density of t is 2 φ(t/√λ₂)/√λ₂
            return c2 * math.exp(-t * t / (2.0 * l2)) * math.erf(math.sqrt(max(x - t * t, 0.0) / (2.0 * l1)))
    else:
        l3 = w[2]
        b = 0.25 * (1.0 / l3 - 1.0 / l2)
        c3 = 1.0 / (2.0 * math.sqrt(l2 * l3))

        def g(t):
            y = t * t
            return 2.0 * t * c3 * float(i0e(b * y)) * math.exp(-y / (2.0 * l2)) * math.erf(
                math.sqrt(max(x - y, 0.0) / (2.0 * l1)))
    hi = math.sqrt(x)
    brk = [v for v in (5.0 * math.sqrt(l2),) if v < hi]
    # [Imhof1961] P(Σ λ_j Z_j² ≤ x) as the convolution of f_Y with the λ₁χ²₁ CDF (derivation in the docstring)
    val = quad(g, 0.0, hi, points=brk or None, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
    return float(min(max(val, 0.0), 1.0))


def ball_radius(cov, p: float = 0.95) -> float:
    """Radius ``r`` with ``P(|e| ≤ r) = p`` for ``e ~ N(0, cov)`` (``cov`` 1x1 to 3x3, PSD), m.

    ``|e|² = Σ_j λ_j Z_j²`` (``λ_j`` the eigenvalues of ``cov``), so ``r² `` is the ``p`` quantile of
    :func:`sum_chi2_cdf`, found by Brent's method between ``χ²₁(p) λ_max`` (one dominant axis) and
    ``χ²_d(p) λ_max`` (isotropic), which bracket it."""
    from scipy.optimize import brentq
    from scipy.stats import chi2

    C = np.atleast_2d(np.asarray(cov, dtype=np.float64))
    lam = np.linalg.eigvalsh(0.5 * (C + C.T))
    m = float(lam[-1])
    if not math.isfinite(m):
        return math.inf
    if m <= 0.0:
        return 0.0
    w = [float(v) / m for v in lam if v > 1e-12 * m]
    lo, hi = float(chi2.ppf(p, 1)), float(chi2.ppf(p, len(w)))
    if hi - lo <= 1e-12 * hi:
        return math.sqrt(hi * m)

    def f(x):
        return sum_chi2_cdf(x, w) - p

    if f(hi) <= 0.0:
        return math.sqrt(hi * m)
    if f(lo) >= 0.0:
        return math.sqrt(lo * m)
    return math.sqrt(brentq(f, lo, hi, xtol=1e-12, rtol=1e-12) * m)


def radii_95(pos_cov: np.ndarray) -> tuple[float, float]:
    """95 % radii of a 3x3 position covariance, m: the ball (3-D) and the plan circle (``xy``
    block) that hold the point with probability 0.95 under ``N(0, pos_cov)`` (:func:`ball_radius`).
    Isotropic: ``√(7.815 σ²)`` and ``√(5.991 σ²)``; one dominant axis: ``√(3.841 σ²_max)``."""
    C = np.asarray(pos_cov, dtype=np.float64)
    if not np.isfinite(C).all():
        return math.inf, math.inf
    return ball_radius(C), ball_radius(C[:2, :2])


def _psd_max(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``L U diag(max(λ, 1)) Uᵀ Lᵀ`` with ``A = L Lᵀ``, ``L⁻¹ B L⁻ᵀ = U diag(λ) Uᵀ`` (A pos. def.)."""
    L = np.linalg.cholesky(A)
    Li = np.linalg.inv(L)
    M = Li @ B @ Li.T
    lam, U = np.linalg.eigh(0.5 * (M + M.T))
    C = L @ (U * np.maximum(lam, 1.0)) @ U.T @ L.T
    return 0.5 * (C + C.T)


def small_g_factor(G: int) -> float:
    """``3 F₃,G−1(0.95) / χ²₃(0.95)``: widens a covariance estimated from ``G`` blocks so that the
    χ²-based 95 % regions get the size of the F-based ones (Cameron & Miller 2015, Sec. VI.D: Wald
    tests with cluster-robust variance use ``F(d, G − 1)``); 1.20 for G = 20, 1.04 for G = 100."""
    from scipy.stats import f as f_dist

    if G < 2:
        return math.inf
    return float(3.0 * f_dist.ppf(0.95, 3, G - 1) / CHI2_3D_95)


def block_covariance(J: np.ndarray, r_hat: np.ndarray, labels: np.ndarray, G: int, method: str) -> np.ndarray:
    """Cluster-robust covariance of the linear least-squares step from per-block scores.

    Parameters
    ----------
    J : (k, 6) ndarray
        Rows ``J_i`` of the linearised residuals.
    r_hat : (k,) ndarray
        Residuals at the least-squares optimum (``Σ_i J_iᵀ r̂_i = 0``).
    labels : (k,) int64 ndarray
        Block of every pair, ``0 .. G − 1`` (each used at least once).
    G : int
        Number of blocks (>= 2).
    method : {"cluster", "jackknife"}
        ``cluster``: ``c H⁻¹ (Σ_b g_b g_bᵀ) H⁻¹`` with ``c = G/(G−1)·(k−1)/(k−6)`` (CR1);
        ``jackknife``: ``(G−1)/G Σ_b (d_b − d̄)(d_b − d̄)ᵀ``, ``d_b = (H − H_b)⁻¹ g_b`` — the exact
        change of the least-squares solution when block ``b`` is left out (CR3).

    Returns
    -------
    (6, 6) ndarray
        Symmetric; without the small-G factor and without the max rule.
    """
    k = J.shape[0]
    H = J.T @ J
    S = J * r_hat[:, None]
    g = np.empty((G, 6))
    for j in range(6):
        g[:, j] = np.bincount(labels, weights=S[:, j], minlength=G)
    if method == "cluster":
        Hinv = np.linalg.inv(H)
        cf = (G / (G - 1.0)) * ((k - 1.0) / (k - 6.0))
        C = cf * (Hinv @ (g.T @ g) @ Hinv)
    elif method == "jackknife":
        Hb = np.empty((G, 6, 6))
        for a in range(6):
            for c2 in range(a, 6):
                Hb[:, a, c2] = Hb[:, c2, a] = np.bincount(labels, weights=J[:, a] * J[:, c2], minlength=G)
        D = np.empty((G, 6))
        for b in range(G):
            A = H - Hb[b]
            try:
                D[b] = np.linalg.solve(A, g[b])
            except np.linalg.LinAlgError:
                D[b] = np.linalg.pinv(A) @ g[b]
        D -= D.mean(axis=0)
        C = ((G - 1.0) / G) * (D.T @ D)
    else:
        raise InputError(f"block covariance method must be 'cluster' or 'jackknife', got {method!r}")
    return 0.5 * (C + C.T)


def cluster_labels(points: np.ndarray, size_m: float) -> tuple[np.ndarray, int]:
    """Block index of every point: cubes of edge ``size_m`` in the principal-axis frame.

    The grid is anchored at the centroid of ``points`` (cell ``j`` spans
    ``[j·size, (j+1)·size)`` along each principal axis), so it moves with the points under
    a rigid motion and a sign flip of an axis maps the grid onto itself. Returns
    ``(labels (n,) int64 in 0..G-1, G)``; labels follow the lexicographic order of the cells.
    """
    c = points.mean(axis=0)
    X = points - c
    _, V = np.linalg.eigh(X.T @ X)
    U = X @ V
    cells = np.floor(U / size_m).astype(np.int64)
    if cells.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), 0
    cells -= cells.min(axis=0)
    ext = cells.max(axis=0) + 1
    key = (cells[:, 0] * ext[1] + cells[:, 1]) * ext[2] + cells[:, 2]  # lexicographic cell order
    _, inv = np.unique(key, return_inverse=True)
    inv = np.asarray(inv, dtype=np.int64).reshape(-1)
    return inv, int(inv.max()) + 1


def _validate(P_work, Q, Nq, corr, origin_work, check_target: bool = True):
    P = as_points(P_work, "P_work (placed scan points)")
    check = as_points if check_target else as_trusted_points
    Qm = check(Q, "Q (map points)")
    N = check(Nq, "Nq (map normals)")
    if N.shape[0] != Qm.shape[0]:
        raise InputError(f"Nq (map normals) has {N.shape[0]} rows but Q (map points) has {Qm.shape[0]}")
    o = np.asarray(origin_work, dtype=np.float64)
    if o.shape != (3,) or not np.isfinite(o).all():
        raise InputError(f"origin_work must be a finite 3-vector, got shape {o.shape}")
    c = np.asarray(corr)
    if c.ndim != 2 or c.shape[1] != 2:
        raise InputError(f"corr must have shape (k, 2) (scan index, map index), got {c.shape}")
    if c.size and not np.issubdtype(c.dtype, np.integer):
        if not np.issubdtype(c.dtype, np.floating) or not np.isfinite(c).all() or np.any(c != np.round(c)):
            raise InputError("corr must hold integer indices (scan index, map index)")
    c = c.astype(np.int64)
    if c.shape[0] < MIN_PAIRS:
        raise TooFewPointsError(
            f"only {c.shape[0]} scan-to-map pairs: at least {MIN_PAIRS} are needed to estimate a pose "
            "uncertainty (6 pose parameters and one residual degree of freedom)")
    if c[:, 0].min() < 0 or c[:, 0].max() >= P.shape[0]:
        raise InputError(f"corr scan indices must be in 0..{P.shape[0] - 1}")
    if c[:, 1].min() < 0 or c[:, 1].max() >= Qm.shape[0]:
        raise InputError(f"corr map indices must be in 0..{Qm.shape[0] - 1}")
    nn = np.linalg.norm(N[c[:, 1]], axis=1)
    if np.any(np.abs(nn - 1.0) > 1e-3):
        raise InputError("map normals of the pairs must have unit length (estimate normals on the map first)")
    return P, Qm, N, c, o


def _result(fit: dict, data, terms, cov_f, G, size_used, infl, step, degenerate, reason) -> PoseUncertainty:
    """The :class:`PoseUncertainty` of a fit (``fit``: the pairs' ``sigma``, ``H``, ``ratio``, ``k``,
    ``p``, ``r`` and the weakest constraint ``cV``) and its data term ``data`` (None: degenerate)."""
    if data is None:
        tot = {"covariance_6x6": None, "position_cov_3x3": None, "position_sigma_m": np.full(3, np.inf),
               "position_95_radius_m": math.inf, "horizontal_95_radius_m": math.inf}
        wax, wsig, r95d = None, math.inf, math.inf
    else:
        tot = _total_fields(data, terms)
        lam, V = np.linalg.eigh(data[3:, 3:])
        wax = V[:, -1] * (1.0 if V[np.argmax(np.abs(V[:, -1])), -1] >= 0 else -1.0)  # sign: largest comp. > 0
        wsig = float(math.sqrt(max(float(lam[-1]), 0.0)))
        r95d = radii_95(data[3:, 3:])[0]
    return PoseUncertainty(covariance_formal_6x6=cov_f, sigma_m=fit["sigma"], information_6x6=fit["H"],
                           information_ratio=float(fit["ratio"]), n_pairs=int(fit["k"]), n_clusters=int(G),
                           cluster_size_used_m=float(size_used), method=fit["p"].method, inflation=float(infl),
                           pending_step=step, degenerate=bool(degenerate), reason=reason, params=fit["p"],
                           residuals_m=fit["r"], covariance_data_6x6=data, model_terms=dict(terms),
                           weakest_constraint_6=fit["cV"][:, 0].copy(), weakest_axis=wax, weakest_sigma_m=wsig,
                           position_95_radius_data_m=r95d, **tot)


def _cluster_data_term(p: UncertaintyParams, J, r, step, pp, cov_f, terms: dict):
    """Cluster-robust (``cluster``) or jackknife data term over spatial blocks of the pairs ``pp``
    (edge halved until ``min_clusters``), adding ``small_G`` and ``formal_floor`` to ``terms``.
    Returns ``(data, G, size_used, inflation)``; the formal ``cov_f`` when fewer than 2 blocks."""
    data = cov_f.copy()
    infl = math.nan
    rh = r + J @ step
    size_used = float(p.cluster_size_m)
    labels, G = cluster_labels(pp, size_used)
    halvings = 0
    while G < p.min_clusters and halvings < 8:
        size_used *= 0.5
        halvings += 1
        labels, G = cluster_labels(pp, size_used)
    if G >= 2:  # else every pair within a few cm: no between-block spread, the formal one is the data term
        data = block_covariance(J, rh, labels, G, p.method)
        fG = small_g_factor(G)
        terms["small_G"] = (fG - 1.0) * data  # [CameronMiller2015 Sec. VI.D]
        scaled = fG * data
        infl = float(np.trace(scaled[3:, 3:]) / np.trace(cov_f[3:, 3:]))
        fl = _psd_max(cov_f, scaled) - scaled  # never below [Censi2007 Eq. 4] formal, in any direction
        terms["formal_floor"] = 0.5 * (fl + fl.T)
    return data, G, size_used, infl


def pose_uncertainty(P_work, Q, Nq, corr, origin_work, params: UncertaintyParams | None = None, *,
                     check_target: bool = True) -> PoseUncertainty:
    """Covariance of a point-to-plane pose fit about the scan origin, formal or cluster-robust.

    Parameters
    ----------
    P_work : (n, 3) array_like
        Placed scan points (final pose), work/map frame, m.
    Q : (m, 3) array_like
        Map points, same frame, m.
    Nq : (m, 3) array_like
        Unit map normals.
    corr : (k, 2) int array_like
        Pairs ``[scan index into P_work, map index into Q]`` (the final ICP pairs).
    origin_work : (3,) array_like
        The scan origin placed in the work frame, m (the point the rotation is taken about).
    params : UncertaintyParams, optional
        Default: delete-one-block jackknife over 4 m blocks, 0.8 mm registration floor.
    check_target : bool
        True (default) scans ``Q`` and ``Nq`` for NaN/inf; False checks only their layout
        (C-contiguous float64 (m, 3)), for a map validated once (a prepared map). The normals of
        the paired rows are checked for unit length either way.

    Returns
    -------
    PoseUncertainty
        ``covariance_6x6`` over ``(ω, t)`` (rad, m; map axes) = the data term
        (``covariance_data_6x6``) + the named ``model_terms``, the 95 % radii of the scan
        origin, the normal matrix, the pending step and the diagnostics. When the geometry
        leaves a direction unconstrained the covariance is None, the radii inf and
        ``degenerate`` True with the reason.

    Raises
    ------
    InputError
        Wrong shapes, NaN/inf, indices out of range, non-unit normals, bad parameters.
    TooFewPointsError
        Fewer than 7 pairs.

    Notes
    -----
    Formulas and references in the module docstring (formal: [Censi2007 Eq. 4] with i.i.d.
    residuals; cluster: [CameronMiller2015 Eqs. 11-12], CR1 factor; jackknife: their CR3). Deterministic: no
    random numbers, block labels in lexicographic cell order, sums in pair order
    (``np.bincount``), so equal inputs give bit-identical outputs; permuting the pairs changes
    the result only by floating-point summation order.
    """
    p = UncertaintyParams() if params is None else params
    if not isinstance(p, UncertaintyParams):
        raise InputError(f"params must be an UncertaintyParams, got {type(p).__name__}")
    P, Qm, N, c, o = _validate(P_work, Q, Nq, corr, origin_work, check_target)
    from minegeo.registration.icp import constraint_analysis

    k = c.shape[0]
    pp = P[c[:, 0]]
    n = N[c[:, 1]]
    r = np.einsum("ij,ij->i", pp - Qm[c[:, 1]], n)
    J = np.hstack([np.cross(pp - o, n), n])
    H = J.T @ J
    H = 0.5 * (H + H.T)
    sigma = float(math.sqrt(float(r @ r) / (k - 6)))
    _, cV, ratio, creason = constraint_analysis(pp, n, max(p.degeneracy_ratio, 1e-300))
    ev = np.linalg.eigvalsh(H)

    fit = {"sigma": sigma, "H": H, "ratio": ratio, "k": k, "p": p, "r": r, "cV": cV}

    if ev[-1] <= 0.0 or ev[0] <= 1e-12 * ev[-1] or ratio < p.degeneracy_ratio:
        why = creason or f"normalised constraint eigenvalue ratio {ratio:.2e}"
        return _result(fit, None, {}, None, 0, math.nan, math.nan, None, True,
                       "the scan-to-map pairs do not constrain every pose direction (" + why + "): the position "
                       "along the free direction is unknown, so no covariance is reported")
    if sigma == 0.0:
        return _result(fit, None, {}, None, 0, math.nan, math.nan, np.zeros(6), True,
                       "the residuals are exactly zero: there is no noise estimate to scale the covariance")
    Hinv = np.linalg.inv(H)
    Hinv = 0.5 * (Hinv + Hinv.T)
    step = -(Hinv @ (J.T @ r))  # pending Gauss-Newton step: normal equations of [Low2004] linearisation
    cov_f = sigma * sigma * Hinv  # [Censi2007 Eq. 4] with cov(z) = σ² I
    G = 0
    size_used = math.nan
    infl = math.nan
    terms: dict[str, np.ndarray] = {}
    data = cov_f.copy()
    if p.method != "formal":
        data, G, size_used, infl = _cluster_data_term(p, J, r, step, pp, cov_f, terms)
    if p.add_pending_step:
        terms["pending_step"] = np.outer(step, step)
    # isotropic position floors σ² I₃ (module docstring; registration floor calibrated in docs/uncertainty.md)
    for name, sd in (("registration_floor", p.registration_sigma_m), ("map_floor", p.map_sigma_m)):
        if sd > 0.0:
            M = np.zeros((6, 6))
            M[3:, 3:] = (sd * sd) * np.eye(3)
            terms[name] = M
    return _result(fit, data, terms, cov_f, G, size_used, infl, step, False, "")
