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
Surveyed beacon vertices may carry an uncertainty ``sigma_vertex``: the vertices then
become parameters with pseudo-observations (their surveyed coordinates), which
propagates the beacon survey error with its full correlation between all returns on a
panel (``dF/dA = -(1 - t) n``, ``dF/dB = -t n``, ``t`` = position along the panel).
The noise model (``sigma_r``, ``sigma_beta``) must be the scanner's: the
Monte Carlo coverage test in ``tests/mast`` and ``benchmarks/bench_mast.py`` is the
check that these weights describe the simulated noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_points
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

    def __post_init__(self) -> None:
        b = np.ascontiguousarray(np.asarray(self.bearing_rad, dtype=np.float64).reshape(-1))
        r = np.ascontiguousarray(np.asarray(self.range_m, dtype=np.float64).reshape(-1))
        n = b.size
        a = as_points(self.line_point, "line_point", dim=2, min_points=0)
        nn = as_points(self.line_normal, "line_normal", dim=2, min_points=0)
        if r.size != n or a.shape[0] != n or nn.shape[0] != n:
            raise InputError("bearing_rad, range_m, line_point and line_normal must have the same length")
        if not (np.isfinite(b).all() and np.isfinite(r).all()) or np.any(r <= 0):
            raise InputError("bearings must be finite and ranges finite and > 0")
        if n and not np.allclose(np.hypot(nn[:, 0], nn[:, 1]), 1.0, atol=1e-9):
            raise InputError("line_normal rows must be unit vectors")
        object.__setattr__(self, "bearing_rad", b)
        object.__setattr__(self, "range_m", r)
        object.__setattr__(self, "line_point", a)
        object.__setattr__(self, "line_normal", nn)

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


def _augmented_model(obs: ResectionObservations, vertex_ab: np.ndarray, nv: int, xall: np.ndarray):
    """Conditions (M5) with the beacon vertices as parameters, plus their pseudo-observations.

    For a return on the panel from vertex ``A`` to ``B`` (``L = |B - A|``, unit direction
    ``u``, left normal ``n``) and ``t = u . (p - A) / L``:
    ``dF/dA = -(1 - t) n`` and ``dF/dB = -t n`` (a vertex error moves the line by its
    interpolated displacement along the normal).
    """
    x = xall[:3]
    V = xall[3:].reshape(nv, 2)
    A = V[vertex_ab[:, 0]]
    Bv = V[vertex_ab[:, 1]]
    e = Bv - A
    L = np.hypot(e[:, 0], e[:, 1])
    u = e / L[:, None]
    nrm = np.column_stack([-u[:, 1], u[:, 0]])
    phi = x[2] + obs.bearing_rad
    sp, cp = np.sin(phi), np.cos(phi)
    q = np.column_stack([x[0] + obs.range_m * sp, x[1] + obs.range_m * cp]) - A
    F = np.einsum("ij,ij->i", nrm, q)
    t = np.einsum("ij,ij->i", u, q) / L
    n = len(obs)
    J = np.zeros((n + 2 * nv, 3 + 2 * nv))
    J[:n, 0] = nrm[:, 0]
    J[:n, 1] = nrm[:, 1]
    J[:n, 2] = obs.range_m * (nrm[:, 0] * cp - nrm[:, 1] * sp)
    rows = np.arange(n)
    for c in range(2):
        np.add.at(J, (rows, 3 + 2 * vertex_ab[:, 0] + c), -(1.0 - t) * nrm[:, c])
        np.add.at(J, (rows, 3 + 2 * vertex_ab[:, 1] + c), -t * nrm[:, c])
    J[n:, 3:] = np.eye(2 * nv)
    return np.concatenate([F, xall[3:]]), J


def resect_scanner_pose(
    obs: ResectionObservations,
    x0,
    sigma_range_m: float,
    sigma_bearing_rad: float = 0.0,
    sigma_panel_m: float = 0.0,
    options: LSQOptions | None = None,
    *,
    vertices_m: np.ndarray | None = None,
    vertex_ab: np.ndarray | None = None,
    sigma_vertex_m: float = 0.0,
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
        Extra per-return line uncertainty, independent from return to return (panel
        flatness), added in quadrature.
    options : LSQOptions, optional
        Default: a-posteriori variance (``Sigma = sigma0^2 (B^T W B)^-1``).
    vertices_m : (V, 2) float64, optional
        Surveyed beacon vertices (local mine frame); with ``vertex_ab`` and
        ``sigma_vertex_m > 0`` they become parameters with pseudo-observations of standard
        deviation ``sigma_vertex_m`` per coordinate, so the survey error of the beacons —
        shared by every return on a panel — is propagated with its full correlation
        (instead of being treated as independent per return).
    vertex_ab : (n, 2) int, optional
        Indices into ``vertices_m`` of the start ``A`` and end ``B`` of each return's panel;
        ``line_normal`` must be the left normal of ``A -> B``.
    sigma_vertex_m : float

    Returns
    -------
    LSQResult
        Parameters ``x_m, y_m, azimuth_rad`` (azimuth not wrapped) first, then the adjusted
        vertex coordinates if they were parameters; ``Sigma_xx`` etc.

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

    opts = options or LSQOptions(variance="aposteriori")
    if sigma_vertex_m > 0:
        if vertices_m is None or vertex_ab is None:
            raise InputError("sigma_vertex_m > 0 needs vertices_m and vertex_ab")
        V = np.asarray(vertices_m, dtype=np.float64)
        ab = np.asarray(vertex_ab, dtype=np.int64)
        if ab.shape != (n, 2) or V.ndim != 2 or V.shape[1] != 2 or ab.min() < 0 or ab.max() >= len(V):
            raise InputError("vertex_ab must be (n, 2) indices into vertices_m (V, 2)")
        nv = len(V)
        l_obs = np.concatenate([np.zeros(n), V.ravel()])
        w_all = np.concatenate([w, np.full(2 * nv, 1.0 / sigma_vertex_m**2)])

        def fun_aug(xall):
            F, J = _augmented_model(obs, ab, nv, xall)
            return F - l_obs, -J

        names = ("x_m", "y_m", "azimuth_rad") + tuple(f"v{k}_{c}" for k in range(nv) for c in "xy")
        return adjust(fun_aug, np.concatenate([x0, V.ravel()]), w_all, options=opts, param_names=names)

    def fun(x):
        F, J, _ = _model(obs, x)
        return F, -J

    return adjust(fun, x0, w, options=opts, param_names=("x_m", "y_m", "azimuth_rad"))


def wrap_deg(a: float) -> float:
    """Azimuth in degrees wrapped to [0, 360)."""
    v = math.fmod(a, 360.0)
    return v + 360.0 if v < 0 else v
