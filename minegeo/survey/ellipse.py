"""Standard and confidence error ellipses (absolute and relative) from a 2×2 covariance.

For a point with covariance ``Σ = [[σEE, σEN], [σEN, σNN]]`` (metres², Easting/Northing) the
standard ellipse has semi-axes equal to the square roots of the eigenvalues of ``Σ``
(Ghilani 2010, Ch. 19 "error ellipse", formulas for S_u, S_v and the orientation t):

    tan 2t = 2σEN / (σNN − σEE)     t = azimuth of the semi-major axis, clockwise from north

A standard ellipse contains the true point with probability 39.4 %. The confidence ellipse at
level ``p`` scales both semi-axes by ``k``:

* **σ0 known** (covariance scaled with the a-priori σ0): ``k = sqrt(χ²(2, p))``; at 95 %
  ``k = 2.4477``.
* **σ0 estimated** (covariance scaled with σ̂0 from r degrees of freedom):
  ``k = sqrt(2·F(2, r, p))`` (Ghilani 2010, Ch. 19, "confidence ellipse", Table of F);
  at r = 10, 95 %: k = sqrt(2·4.1028) = 2.8645.

The relative ellipse between points i and j uses the covariance of the coordinate difference
``Σ_Δ = Σ_ii + Σ_jj − Σ_ij − Σ_ji``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from minegeo.errors import InputError

__all__ = ["ErrorEllipse", "ellipse_scale", "error_ellipse", "relative_ellipse", "point_ellipses"]


@dataclass(frozen=True)
class ErrorEllipse:
    """An error ellipse.

    Attributes
    ----------
    semi_major_m, semi_minor_m : float
        Semi-axes (metres), already multiplied by :attr:`k`.
    azimuth_rad : float
        Grid azimuth of the semi-major axis, clockwise from north, in ``[0, π)``.
    k : float
        Scale applied to the standard ellipse (1 for the standard ellipse).
    confidence : float
        Probability content (0.394 for the standard ellipse with σ0 known).
    basis : str
        How ``k`` was obtained: ``"standard"``, ``"chi2(2) sigma0 known"`` or
        ``"F(2,r) sigma0 estimated, r=…"``.
    """

    semi_major_m: float
    semi_minor_m: float
    azimuth_rad: float
    k: float
    confidence: float
    basis: str

    def scaled(self, k: float, confidence: float, basis: str) -> ErrorEllipse:
        """The same ellipse scaled from standard by ``k`` (only valid on a standard ellipse)."""
        return ErrorEllipse(
            self.semi_major_m * k, self.semi_minor_m * k, self.azimuth_rad, k, confidence, basis
        )

    def as_dict(self) -> dict:
        return {
            "semi_major_m": self.semi_major_m,
            "semi_minor_m": self.semi_minor_m,
            "azimuth_deg": math.degrees(self.azimuth_rad),
            "k": self.k,
            "confidence": self.confidence,
            "basis": self.basis,
        }


def ellipse_scale(
    confidence: float = 0.95, dof: int | None = None, sigma0_known: bool = True
) -> tuple[float, str]:
    """Scale ``k`` from standard to confidence ellipse and a text saying which distribution.

    Parameters
    ----------
    confidence : float
        Probability content, e.g. 0.95.
    dof : int, optional
        Degrees of freedom of σ̂0 (needed when ``sigma0_known`` is False).
    sigma0_known : bool
        True: χ²(2) (σ0 a-priori); False: 2·F(2, r) (σ0 estimated).
    """
    if not 0 < confidence < 1:
        raise InputError(f"confidence must be between 0 and 1, got {confidence}")
    if sigma0_known:
        return math.sqrt(float(stats.chi2.ppf(confidence, 2))), "chi2(2) sigma0 known"
    if dof is None or dof < 1:
        raise InputError("an estimated sigma0 needs dof >= 1 for the F-based ellipse scale")
    return math.sqrt(2.0 * float(stats.f.ppf(confidence, 2, dof))), f"F(2,r) sigma0 estimated, r={int(dof)}"


def error_ellipse(
    cov, confidence: float | None = None, dof: int | None = None, sigma0_known: bool = True
) -> ErrorEllipse:
    """Error ellipse of a 2×2 covariance (Easting, Northing order, metres²).

    Parameters
    ----------
    cov : array_like (2, 2)
        Covariance of (E, N).
    confidence : float, optional
        None for the standard ellipse; else e.g. 0.95 (see :func:`ellipse_scale`).
    dof, sigma0_known
        See :func:`ellipse_scale`.
    """
    S = np.asarray(cov, dtype=np.float64)
    if S.shape != (2, 2) or not np.all(np.isfinite(S)):
        raise InputError(f"ellipse covariance must be a finite 2x2 matrix, got shape {S.shape}")
    see, snn, sen = S[0, 0], S[1, 1], 0.5 * (S[0, 1] + S[1, 0])
    # eigenvalues in closed form (Ghilani: S_u², S_v²)
    mean = 0.5 * (see + snn)
    rad = math.hypot(0.5 * (snn - see), sen)
    lmax, lmin = mean + rad, max(mean - rad, 0.0)
    # orientation of the major axis: azimuth t with tan 2t = 2σEN/(σNN − σEE)
    t = 0.5 * math.atan2(2.0 * sen, snn - see) if rad > 0 else 0.0
    t = t % math.pi
    std = ErrorEllipse(math.sqrt(lmax), math.sqrt(lmin), t, 1.0, 1.0 - math.exp(-0.5), "standard")
    if confidence is None:
        return std
    k, basis = ellipse_scale(confidence, dof, sigma0_known)
    return std.scaled(k, confidence, basis)


def relative_ellipse(
    cov_full, i: int, j: int, confidence: float | None = None, dof=None, sigma0_known=True
) -> ErrorEllipse:
    """Relative ellipse between the 2-D points at block indices ``i`` and ``j``.

    ``cov_full`` is the joint covariance whose rows/cols ``2i, 2i+1`` are point i's (E, N)
    (pass a 4×4 matrix with i=0, j=1 for two points).
    """
    S = np.asarray(cov_full, dtype=np.float64)
    a = slice(2 * i, 2 * i + 2)
    b = slice(2 * j, 2 * j + 2)
    D = S[a, a] + S[b, b] - S[a, b] - S[b, a]
    return error_ellipse(D, confidence, dof, sigma0_known)


def point_ellipses(
    cov, dof: int, sigma0_known: bool, confidence: float = 0.95
) -> tuple[ErrorEllipse, ErrorEllipse]:
    """(standard ellipse, confidence ellipse) of one point; the scale basis follows ``sigma0_known``."""
    std = error_ellipse(cov)
    if not sigma0_known and (dof is None or dof < 1):
        return std, std.scaled(float("nan"), confidence, "undefined (no redundancy to estimate sigma0)")
    k, basis = ellipse_scale(confidence, dof, sigma0_known)
    return std, std.scaled(k, confidence, basis)
