"""Scanner position and azimuth by weighted least squares of range/bearing observations.

Simela, Marshall & Daneshmend, section "Scanner Horizontal Position and Azimuth
Orientation": adjustment of indirect observations ``v + B Delta = f`` with
``N = B^T W B``, ``t = B^T W f``, ``Delta = N^-1 t`` and
``Sigma_DeltaDelta = sigma0^2 (B^T W B)^-1``; solved by
:func:`minegeo.survey.adjust` (iterated to convergence).

Deviation from the paper (to make the covariance honest)
--------------------------------------------------------
The paper writes ``X_p = G_x + h_d sin(Az)``, ``Y_p = G_y + h_d cos(Az)`` with the
ICP-adjusted point ``G`` treated as known. But ``G`` is computed from the same
ranges and from the pose being estimated, so that formulation double-counts the
data and gives a covariance that does not describe the real error (the paper's
Table 2 prints 0.0000 m confidence intervals). We instead use one condition per
scan return ``i`` that fell on an identified beacon panel ``j`` (known line through
``a_j`` with unit normal ``n_j`` in the mine frame): the return's mine position
must lie on the panel::

    F_i(x, y, alpha) = n_j . ( (x + r_i sin(alpha + beta_i), y + r_i cos(alpha + beta_i)) - a_j ) = 0

with ``(r_i, beta_i)`` the measured range and bearing and ``alpha`` the scanner
azimuth (of bearing 0, clockwise from grid north). Each condition involves only its
own two observations, so the Gauss-Helmert model reduces to indirect observations
of the pseudo-observation ``0`` with the propagated variance::

    sigma_Fi^2 = (n_j . u_i)^2 sigma_r^2 + (r_i (n_jx cos phi_i - n_jy sin phi_i))^2 sigma_beta^2 + sigma_panel^2

(``phi_i = alpha + beta_i``, ``u_i = (sin phi_i, cos phi_i)``), weight
``w_i = 1 / sigma_Fi^2`` (sigma0 a priori = 1). The design row is
``B_i = -dF_i/d(x, y, alpha) = -(n_jx, n_jy, r_i (n_jx cos phi_i - n_jy sin phi_i))``.
The noise model (``sigma_r``, ``sigma_beta``) must be the scanner's: the
Monte Carlo coverage test in ``tests/mast`` and ``benchmarks/bench_mast.py`` is the
check that these weights describe the simulated noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo.errors import InputError, TooFewPointsError
from minegeo.survey import LSQOptions, LSQResult, adjust

__all__ = ["ResectionObservations", "condition_sigmas", "resect_scanner_pose"]


@dataclass(frozen=True)
class ResectionObservations:
    """Range/bearing returns assigned to known lines (local mine frame).

    Attributes
    ----------
    bearing_rad, range_m : (n,) float64
        Measured bearing (clockwise from the scanner's forward axis) and range.
    line_point : (n, 2) float64
        A point ``a_j`` on the panel line of each return (m, local mine frame).
    line_normal : (n, 2) float64
        Unit normal ``n_j`` of that line.
    """

    bearing_rad: np.ndarray
    range_m: np.ndarray
    line_point: np.ndarray
    line_normal: np.ndarray

    def __len__(self) -> int:
        return int(self.range_m.size)


def _model(obs: ResectionObservations, x: np.ndarray):
    phi = x[2] + obs.bearing_rad
    sp, cp = np.sin(phi), np.cos(phi)
    px = x[0] + obs.range_m * sp
    py = x[1] + obs.range_m * cp
    nx, ny = obs.line_normal[:, 0], obs.line_normal[:, 1]
    F = nx * (px - obs.line_point[:, 0]) + ny * (py - obs.line_point[:, 1])
    dadz = obs.range_m * (nx * cp - ny * sp)
    J = np.column_stack([nx, ny, dadz])
    return F, J, nx * sp + ny * cp


def condition_sigmas(
    obs: ResectionObservations, x, sigma_range_m: float, sigma_bearing_rad: float, sigma_panel_m: float = 0.0
) -> np.ndarray:
    """Standard deviation of each condition ``F_i`` from the range/bearing noise (m).

    ``sigma_Fi^2 = (dF/dr)^2 sr^2 + (dF/dbeta)^2 sb^2 + s_panel^2`` with
    ``dF/dr = n . u`` and ``dF/dbeta = dF/dalpha``.
    """
    _, J, nu = _model(obs, np.asarray(x, dtype=np.float64))
    return np.sqrt((nu * sigma_range_m) ** 2 + (J[:, 2] * sigma_bearing_rad) ** 2 + sigma_panel_m**2)


def resect_scanner_pose(
    obs: ResectionObservations,
    x0,
    sigma_range_m: float,
    sigma_bearing_rad: float = 0.0,
    sigma_panel_m: float = 0.0,
    options: LSQOptions | None = None,
) -> LSQResult:
    """Weighted least-squares scanner pose ``(x_m, y_m, azimuth_rad)`` from returns on known lines.

    Parameters
    ----------
    obs : ResectionObservations
    x0 : (3,) array_like
        Approximate ``(x, y, alpha)`` (m, m, rad) in the local mine frame (e.g. from ICP).
    sigma_range_m, sigma_bearing_rad : float
        Scanner noise model (one range, one bearing).
    sigma_panel_m : float
        Extra per-return line uncertainty (panel flatness, beacon survey), added in quadrature.
    options : LSQOptions, optional
        Default: a-posteriori variance (``Sigma = sigma0^2 (B^T W B)^-1``).

    Returns
    -------
    LSQResult
        Parameters ``x_m, y_m, azimuth_rad`` (azimuth not wrapped), ``Sigma_xx`` etc.

    Raises
    ------
    TooFewPointsError
        Fewer than 3 returns (unknowns: x, y, azimuth).
    DegenerateGeometryError
        Returns on parallel lines only (position along them undetermined).
    InputError
        Zero noise model (weights undefined).
    """
    n = len(obs)
    if n < 3:
        raise TooFewPointsError(
            f"{n} beacon return(s) cannot determine the 3 unknowns (x, y, azimuth); at least 3 are needed"
        )
    if not (sigma_range_m > 0 or sigma_bearing_rad > 0 or sigma_panel_m > 0):
        raise InputError("the noise model is zero: give sigma_range_m (and/or sigma_bearing_deg) > 0")
    x0 = np.asarray(x0, dtype=np.float64).reshape(3)
    sig = condition_sigmas(obs, x0, sigma_range_m, sigma_bearing_rad, sigma_panel_m)
    floor = 1e-6 * max(sigma_range_m, sigma_panel_m, 1e-9)
    sig = np.maximum(sig, floor)
    w = 1.0 / sig**2

    def fun(x):
        F, J, _ = _model(obs, x)
        return F, -J

    return adjust(
        fun, x0, w, options=options or LSQOptions(variance="aposteriori"),
        param_names=("x_m", "y_m", "azimuth_rad"),
    )


def wrap_deg(a: float) -> float:
    """Azimuth in degrees wrapped to [0, 360)."""
    v = math.fmod(a, 360.0)
    return v + 360.0 if v < 0 else v
