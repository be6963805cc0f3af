"""Coordinate transformations estimated by weighted least squares: 2D Helmert (4-parameter conformal),
2D affine (6-parameter), 3D Helmert (7-parameter similarity) and 3D rigid (6-parameter).

All estimators observe the *target* coordinates (``dst``) and treat the *source* coordinates
(``src``) as errorless, as in Ghilani (2010), Ch. 18 "coordinate transformations". Large
projected or geocentric coordinates (10⁶–10⁷ m) are reduced to the centroids of ``src`` and
``dst`` before the adjustment (a recorded local origin) and the parameters and their covariance
are then transformed *exactly* back to the un-reduced parameterisation the textbooks print.

2D conformal (Helmert, 4 parameters), Simela et al. (MAST), Sec. "Template matching", and
[Ghilani2010 Eq. 18.1]::

    E = a·x − b·y + Tx          [E]   [x  −y  1  0] [a ]
    N = b·x + a·y + Ty          [N] = [y   x  0  1] [b ]
                                                    [Tx]
    scale  = sqrt(a² + b²)                          [Ty]
    rotation θ = atan2(b, a)   (counter-clockwise from the source x axis to the target E axis)

2D affine (6 parameters): ``E = a0 + a1·x + a2·y``, ``N = b0 + b1·x + b2·y``.

3D similarity (7 parameters), ``X_dst = T + (1 + ds)·R·X_src``. Rotation conventions:

* **position vector** (EPSG method 9606/1033, "Bursa–Wolf"): for small angles
  ``R = [[1, −rz, ry], [rz, 1, −rx], [−ry, rx, 1]]``;
* **coordinate frame** (EPSG method 9607/1032): the same matrix with the signs of rx, ry, rz
  reversed (``R_CF(r) = R_PV(−r)``).

The estimator uses an exact rotation ``R = exp([ω]×)`` (so it also works for the large yaw of a
mine grid versus a local frame); ``ω`` are the position-vector rotations, which equal the
EPSG small-angle parameters to second order (< 1e-11 rad for arc-second rotations). The
coordinate-frame values are ``−ω``. Rotation standard deviations are those of a small rotation
about the target x, y, z axes at the solution (left perturbation ``R = exp([δ]×)·R̂``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.geometry.se3 import exp_so3, hat, log_so3
from minegeo.kernels.rigid import umeyama_centred
from minegeo.survey.angles import RHO_ARCSEC, format_dms, wrap_2pi
from minegeo.survey.lsq import LSQOptions, LSQResult, adjust, adjust_linear

__all__ = [
    "Helmert2DResult",
    "Affine2DResult",
    "Helmert3DResult",
    "helmert2d",
    "affine2d",
    "helmert3d",
    "apply_helmert2d",
    "apply_helmert7",
    "helmert7_matrix",
]


def _weights_2d(n: int, sigma_dst) -> np.ndarray:
    """Weights of the interleaved (E0, N0, E1, N1, …) observations from per-point σ (m)."""
    if sigma_dst is None:
        return np.ones(2 * n)
    s = np.asarray(sigma_dst, dtype=np.float64)
    if s.ndim == 0:
        s = np.full(n, float(s))
    if s.ndim == 1 and s.shape[0] == n:
        s = np.repeat(s[:, None], 2, axis=1)
    if s.shape != (n, 2) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError("sigma_dst must be a scalar, (n,) or (n, 2) array of standard deviations > 0 (m)")
    return 1.0 / s.ravel() ** 2


def _check_spread(src: np.ndarray, need_rank: int, what: str) -> None:
    c = src - src.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    scale = max(float(np.max(np.abs(c))), 1e-300)
    rank = int(np.sum(sv > 1e-9 * scale * math.sqrt(len(src))))
    if rank < need_rank:
        raise DegenerateGeometryError(
            f"{what}: the source points are "
            f"{'coincident' if rank == 0 else 'collinear' if rank == 1 else 'coplanar'}"
            " and cannot determine the transformation; use control points that span the area"
        )


def _point_pairs(src_in, dst_in, names: tuple, dim: int, need: int, what: str, need_rank: int,
                 spread_what: str) -> tuple:
    """Validated point pairs of a transformation fit: ``(src, dst, src centroid, dst centroid)``.

    ``src_in``, ``dst_in``: (n, ``dim``) coordinates (m), called ``names`` in messages. :class:`InputError` for different counts, :class:`TooFewPointsError` for fewer
    than ``need`` pairs (``what`` names the transformation), :class:`DegenerateGeometryError` when
    the source points span fewer than ``need_rank`` dimensions (:func:`_check_spread`)."""
    src = as_points(src_in, names[0], dim=dim)
    dst = as_points(dst_in, names[1], dim=dim)
    if src.shape != dst.shape:
        raise InputError(f"{names[0]} and {names[1]} must have the same number of points ({len(src)} vs {len(dst)})")
    n = src.shape[0]
    if n < need:
        raise TooFewPointsError(f"{what} needs at least {need} point pairs, got {n}")
    _check_spread(src, need_rank, spread_what)
    return src, dst, src.mean(axis=0), dst.mean(axis=0)


@dataclass(frozen=True)
class Helmert2DResult:
    """4-parameter 2D conformal transformation ``E = a·x − b·y + Tx``, ``N = b·x + a·y + Ty``.

    Attributes
    ----------
    params : ndarray (4,)
        ``(a, b, Tx, Ty)`` in the un-reduced parameterisation (as Ghilani prints them).
    cov : ndarray (4, 4)
        Covariance of ``params`` (scaled with σ̂0 or σ0 according to ``lsq.variance_used``).
    std : ndarray (4,)
        Standard deviations of ``params``.
    scale, rotation_rad : float
        ``sqrt(a²+b²)`` and ``atan2(b, a)`` in ``[0, 2π)``.
    scale_std, rotation_std_rad : float
        Their propagated standard deviations.
    residuals : ndarray (n, 2)
        ``v = transformed − observed`` target coordinates (m).
    sigma0 : float
        A-posteriori standard deviation of unit weight (the book's S0).
    dof : int
    src_origin, dst_origin : ndarray (2,)
        Local origins (centroids) subtracted during the adjustment.
    lsq : LSQResult
        Full adjustment of the reduced problem (parameters a, b, t'x, t'y).
    """

    params: np.ndarray
    cov: np.ndarray
    std: np.ndarray
    scale: float
    rotation_rad: float
    scale_std: float
    rotation_std_rad: float
    residuals: np.ndarray
    sigma0: float
    dof: int
    src_origin: np.ndarray
    dst_origin: np.ndarray
    lsq: LSQResult

    @property
    def rotation_dms(self) -> str:
        """Rotation θ as DMS text, e.g. ``183°13'05.0"``."""
        return format_dms(self.rotation_rad, 1)

    def transform(self, points_xy, with_cov: bool = True):
        """Transform source points; returns ``(EN (m,2), cov (m,2,2))`` (cov from parameter uncertainty only)."""
        p = as_points(points_xy, "points_xy", dim=2)
        a, b = self.params[0], self.params[1]
        xr = p - self.src_origin
        # E = a·x̃ − b·ỹ + t'x + E0 (reduced form: no cancellation with 10⁶ m coordinates)
        tpx, tpy = self._reduced_t
        out = np.empty_like(p)
        out[:, 0] = a * xr[:, 0] - b * xr[:, 1] + tpx + self.dst_origin[0]
        out[:, 1] = b * xr[:, 0] + a * xr[:, 1] + tpy + self.dst_origin[1]
        if not with_cov:
            return out
        Q = self.lsq.Sigma_xx
        covs = np.empty((p.shape[0], 2, 2))
        for i, (x, y) in enumerate(xr):
            J = np.array([[x, -y, 1.0, 0.0], [y, x, 0.0, 1.0]])
            covs[i] = J @ Q @ J.T
        return out, covs

    @property
    def _reduced_t(self):
        return self.lsq.x[2], self.lsq.x[3]

    def as_dict(self) -> dict:
        names = ("a", "b", "Tx", "Ty")
        return {
            "model": "2D conformal (Helmert, 4 parameters): E = a*x - b*y + Tx, N = b*x + a*y + Ty",
            "parameters": {k: float(v) for k, v in zip(names, self.params, strict=True)},
            "std": {k: float(v) for k, v in zip(names, self.std, strict=True)},
            "scale": self.scale,
            "scale_std": self.scale_std,
            "rotation_deg": math.degrees(self.rotation_rad),
            "rotation_dms": self.rotation_dms,
            "rotation_std_arcsec": self.rotation_std_rad * RHO_ARCSEC,
            "sigma0": self.sigma0,
            "dof": self.dof,
            "variance_used": self.lsq.variance_used,
            "residuals_m": self.residuals,
            "src_origin": self.src_origin,
            "dst_origin": self.dst_origin,
        }


def helmert2d(src_xy, dst_en, sigma_dst=None, options: LSQOptions | None = None) -> Helmert2DResult:
    """Estimate the 4-parameter 2D conformal (Helmert) transformation from point pairs.

    Parameters
    ----------
    src_xy : array_like (n, 2)
        Source coordinates (x, y), errorless.
    dst_en : array_like (n, 2)
        Target coordinates (E, N) — the observations.
    sigma_dst : float or array_like (n,) or (n, 2), optional
        Standard deviations of the target coordinates (m); unweighted (all 1) if omitted, as in
        Ghilani Ex. 18.1.
    options : LSQOptions, optional

    Returns
    -------
    Helmert2DResult

    Raises
    ------
    TooFewPointsError
        Fewer than 2 point pairs.
    DegenerateGeometryError
        Coincident source points.

    Notes
    -----
    Design matrix per point ``[x −y 1 0; y x 0 1]`` (Simela et al., MAST, Sec. "Template
    matching"; [Ghilani2010 Eq. 18.1]), solved as ``Δ = (BᵀWB)⁻¹BᵀWf`` on centroid-reduced
    coordinates; ``Tx = E0 + t'x − a·x0 + b·y0``, ``Ty = N0 + t'y − b·x0 − a·y0`` and the
    covariance is propagated with the exact Jacobian of that map.
    """
    src, dst, s0, d0 = _point_pairs(src_xy, dst_en, ("src_xy", "dst_en"), 2, 2, "a 2D Helmert transformation", 1,
                                    "2D Helmert")
    n = src.shape[0]
    xr = src - s0
    dr = dst - d0
    B = np.zeros((2 * n, 4))
    B[0::2, 0] = xr[:, 0]
    B[0::2, 1] = -xr[:, 1]
    B[0::2, 2] = 1.0
    B[1::2, 0] = xr[:, 1]
    B[1::2, 1] = xr[:, 0]
    B[1::2, 3] = 1.0
    W = _weights_2d(n, sigma_dst)
    res = adjust_linear(
        B,
        dr.ravel(),
        W,
        options=options,
        param_names=("a", "b", "t'x", "t'y"),
        obs_names=tuple(f"{c}{i}" for i in range(n) for c in ("E", "N")),
    )
    a, b, tpx, tpy = res.x
    x0, y0 = s0
    params = np.array([a, b, d0[0] + tpx - a * x0 + b * y0, d0[1] + tpy - b * x0 - a * y0])
    J = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [-x0, y0, 1, 0], [-y0, -x0, 0, 1]], dtype=np.float64)
    cov = J @ res.Sigma_xx @ J.T
    scale = math.hypot(a, b)
    rot = wrap_2pi(math.atan2(b, a))
    js = np.array([a / scale, b / scale])
    jr = np.array([-b / scale**2, a / scale**2])
    S2 = res.Sigma_xx[:2, :2]
    return Helmert2DResult(
        params=params,
        cov=0.5 * (cov + cov.T),
        std=np.sqrt(np.clip(np.diag(cov), 0, None)),
        scale=scale,
        rotation_rad=rot,
        scale_std=float(math.sqrt(max(js @ S2 @ js, 0.0))),
        rotation_std_rad=float(math.sqrt(max(jr @ S2 @ jr, 0.0))),
        residuals=res.v.reshape(n, 2),
        sigma0=res.sigma0,
        dof=res.dof,
        src_origin=s0,
        dst_origin=d0,
        lsq=res,
    )


def apply_helmert2d(points_xy, tx: float, ty: float, scale: float, rotation_rad: float) -> np.ndarray:
    """Apply ``E = s(x cos θ − y sin θ) + Tx``, ``N = s(x sin θ + y cos θ) + Ty`` (θ counter-clockwise).

    (PROJ's ``+proj=helmert`` 2D form with ``theta`` in arc-seconds uses the opposite rotation
    sense: pass ``rotation_rad = −theta``; see tests.)
    """
    p = as_points(points_xy, "points_xy", dim=2)
    a = scale * math.cos(rotation_rad)
    b = scale * math.sin(rotation_rad)
    return np.column_stack([a * p[:, 0] - b * p[:, 1] + tx, b * p[:, 0] + a * p[:, 1] + ty])


@dataclass(frozen=True)
class Affine2DResult:
    """6-parameter affine transformation ``E = a0 + a1·x + a2·y``, ``N = b0 + b1·x + b2·y``.

    ``params = (a0, a1, a2, b0, b1, b2)``; other attributes as in :class:`Helmert2DResult`.
    """

    params: np.ndarray
    cov: np.ndarray
    std: np.ndarray
    residuals: np.ndarray
    sigma0: float
    dof: int
    src_origin: np.ndarray
    dst_origin: np.ndarray
    lsq: LSQResult

    def transform(self, points_xy) -> np.ndarray:
        p = as_points(points_xy, "points_xy", dim=2) - self.src_origin
        c = self.lsq.x
        return np.column_stack(
            [
                c[0] + c[1] * p[:, 0] + c[2] * p[:, 1] + self.dst_origin[0],
                c[3] + c[4] * p[:, 0] + c[5] * p[:, 1] + self.dst_origin[1],
            ]
        )

    def as_dict(self) -> dict:
        names = ("a0", "a1", "a2", "b0", "b1", "b2")
        return {
            "model": "2D affine (6 parameters): E = a0 + a1*x + a2*y, N = b0 + b1*x + b2*y",
            "parameters": {k: float(v) for k, v in zip(names, self.params, strict=True)},
            "std": {k: float(v) for k, v in zip(names, self.std, strict=True)},
            "sigma0": self.sigma0,
            "dof": self.dof,
            "residuals_m": self.residuals,
        }


def affine2d(src_xy, dst_en, sigma_dst=None, options: LSQOptions | None = None) -> Affine2DResult:
    """Estimate the 6-parameter 2D affine transformation (Ghilani 2010, Ch. 18, affine transformation).

    Needs at least 3 non-collinear point pairs; see :func:`helmert2d` for the arguments.
    """
    src, dst, s0, d0 = _point_pairs(src_xy, dst_en, ("src_xy", "dst_en"), 2, 3, "a 2D affine transformation", 2,
                                    "2D affine")
    n = src.shape[0]
    xr, dr = src - s0, dst - d0
    B = np.zeros((2 * n, 6))
    B[0::2, 0] = 1.0
    B[0::2, 1] = xr[:, 0]
    B[0::2, 2] = xr[:, 1]
    B[1::2, 3] = 1.0
    B[1::2, 4] = xr[:, 0]
    B[1::2, 5] = xr[:, 1]
    res = adjust_linear(
        B,
        dr.ravel(),
        _weights_2d(n, sigma_dst),
        options=options,
        param_names=("a0'", "a1", "a2", "b0'", "b1", "b2"),
    )
    c = res.x
    x0, y0 = s0
    params = np.array(
        [d0[0] + c[0] - c[1] * x0 - c[2] * y0, c[1], c[2], d0[1] + c[3] - c[4] * x0 - c[5] * y0, c[4], c[5]]
    )
    J = np.eye(6)
    J[0, 1], J[0, 2] = -x0, -y0
    J[3, 4], J[3, 5] = -x0, -y0
    cov = J @ res.Sigma_xx @ J.T
    return Affine2DResult(
        params,
        0.5 * (cov + cov.T),
        np.sqrt(np.clip(np.diag(cov), 0, None)),
        res.v.reshape(n, 2),
        res.sigma0,
        res.dof,
        s0,
        d0,
        res,
    )


def helmert7_matrix(rx: float, ry: float, rz: float, convention: str = "position_vector") -> np.ndarray:
    """EPSG small-angle rotation matrix (radians) for the position-vector (9606) or coordinate-frame (9607) convention."""
    conv = _convention(convention)
    if conv == "coordinate_frame":
        rx, ry, rz = -rx, -ry, -rz
    return np.array([[1.0, -rz, ry], [rz, 1.0, -rx], [-ry, rx, 1.0]])


def _convention(convention: str) -> str:
    c = convention.lower().replace("-", "_").replace(" ", "_")
    if c in ("position_vector", "pv", "9606", "epsg:9606", "bursa_wolf", "1033"):
        return "position_vector"
    if c in ("coordinate_frame", "cf", "9607", "epsg:9607", "1032"):
        return "coordinate_frame"
    raise InputError(
        f"unknown rotation convention {convention!r}: use 'position_vector' (EPSG 9606) or 'coordinate_frame' (EPSG 9607)"
    )


def apply_helmert7(
    points, tx, ty, tz, rx_arcsec, ry_arcsec, rz_arcsec, ds_ppm, convention: str = "position_vector"
) -> np.ndarray:
    """Apply published 7-parameter Helmert parameters exactly as EPSG 9606/9607 define them.

    ``X' = T + (1 + ds·10⁻⁶)·R·X`` with the small-angle matrix of :func:`helmert7_matrix`;
    rotations in arc-seconds, scale difference in ppm, translations in metres.
    """
    p = as_points(points, "points", dim=3)
    R = helmert7_matrix(rx_arcsec / RHO_ARCSEC, ry_arcsec / RHO_ARCSEC, rz_arcsec / RHO_ARCSEC, convention)
    m = 1.0 + ds_ppm * 1e-6
    return m * (p @ R.T) + np.array([tx, ty, tz], dtype=np.float64)


@dataclass(frozen=True)
class Helmert3DResult:
    """3D similarity (7-parameter) or rigid (6-parameter) transformation ``X_dst = T + s·R·X_src``.

    Attributes
    ----------
    R : ndarray (3, 3)
        Exact rotation matrix.
    T : ndarray (3,)
        Translation (m) in the un-reduced parameterisation.
    scale : float
        ``s = 1 + ds`` (1 exactly for the rigid model).
    rotation_pv_rad : ndarray (3,)
        Position-vector rotations ``ω = log(R)`` (EPSG 9606 rx, ry, rz for small angles).
    convention : str
        Convention requested for reporting ("position_vector" or "coordinate_frame").
    cov : ndarray (7, 7) or (6, 6)
        Covariance of ``(Tx, Ty, Tz, δx, δy, δz[, ds])`` — rotations as small rotations about the
        target axes at the solution (rad), ``ds`` dimensionless.
    residuals : ndarray (n, 3)
        ``v = transformed − observed`` (m).
    sigma0 : float
    dof : int
    src_origin, dst_origin : ndarray (3,)
    estimate_scale : bool
    lsq : LSQResult
    """

    R: np.ndarray
    T: np.ndarray
    scale: float
    rotation_pv_rad: np.ndarray
    convention: str
    cov: np.ndarray
    residuals: np.ndarray
    sigma0: float
    dof: int
    src_origin: np.ndarray
    dst_origin: np.ndarray
    estimate_scale: bool
    lsq: LSQResult

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))

    @property
    def rotations_arcsec(self) -> np.ndarray:
        """(rx, ry, rz) in arc-seconds in the requested :attr:`convention`."""
        w = self.rotation_pv_rad * RHO_ARCSEC
        return w if self.convention == "position_vector" else -w

    @property
    def ds_ppm(self) -> float:
        return (self.scale - 1.0) * 1e6

    def transform(self, points, with_cov: bool = False):
        """Apply the estimated transformation (reduced form, exact rotation).

        With ``with_cov=True`` returns ``(xyz (m,3), cov (m,3,3))``: covariance from the parameter
        uncertainty only, ``J = [I, −s[R·x̃]×, R·x̃]`` per point (x̃ = point − src_origin).
        """
        p = as_points(points, "points", dim=3)
        rx = (p - self.src_origin) @ self.R.T
        out = self.scale * rx + self._t_reduced + self.dst_origin
        if not with_cov:
            return out
        S = self.lsq.Sigma_xx
        u = S.shape[0]
        covs = np.empty((p.shape[0], 3, 3))
        for i in range(p.shape[0]):
            J = np.zeros((3, u))
            J[:, :3] = np.eye(3)
            J[:, 3:6] = -self.scale * hat(rx[i])
            if self.estimate_scale:
                J[:, 6] = rx[i]
            covs[i] = J @ S @ J.T
        return out, covs

    @property
    def _t_reduced(self):
        return self.lsq.x[:3]

    def as_dict(self) -> dict:
        sd = self.std
        out = {
            "model": ("3D similarity (7 parameters)" if self.estimate_scale else "3D rigid (6 parameters)")
            + ": X_dst = T + (1 + ds) * R * X_src",
            "convention": self.convention,
            "convention_note": "position_vector = EPSG 9606 (Bursa-Wolf); coordinate_frame = EPSG 9607 (rotations of opposite sign)",
            "T_m": self.T,
            "T_std_m": sd[:3],
            "rotations_arcsec": self.rotations_arcsec,
            "rotations_std_arcsec": sd[3:6] * RHO_ARCSEC,
            "R": self.R,
            "ds_ppm": self.ds_ppm,
            "sigma0": self.sigma0,
            "dof": self.dof,
            "residuals_m": self.residuals,
            "src_origin": self.src_origin,
            "dst_origin": self.dst_origin,
        }
        if self.estimate_scale:
            out["ds_std_ppm"] = sd[6] * 1e6
        return out


def helmert3d(
    src_xyz,
    dst_xyz,
    sigma_dst=None,
    *,
    estimate_scale: bool = True,
    convention: str = "position_vector",
    options: LSQOptions | None = None,
) -> Helmert3DResult:
    """Estimate a 7-parameter 3D Helmert (similarity) or 6-parameter rigid transformation by weighted LSQ.

    Parameters
    ----------
    src_xyz, dst_xyz : array_like (n, 3)
        Source (errorless) and target (observed) coordinates, metres. Geocentric or projected
        magnitudes are fine: both sets are reduced to their centroids first.
    sigma_dst : float or array_like (n,) or (n, 3), optional
        Standard deviations of the target coordinates (m); unit weights if omitted.
    estimate_scale : bool
        True: 7 parameters (similarity); False: 6 parameters (rigid, s = 1).
    convention : {"position_vector", "coordinate_frame"}
        How rotations are *reported* (EPSG 9606 vs 9607); the estimate is the same.
    options : LSQOptions, optional

    Returns
    -------
    Helmert3DResult

    Notes
    -----
    Start values from the closed-form solution of Umeyama (1991); then Gauss–Newton on
    ``X̃_dst = s·exp([δ]×)·R̂·X̃_src + t'`` (reduced coordinates), with the design matrix
    ``[I, −s[R̂X̃]×, R̂X̃]`` per point. ``T = X0_dst + t' − s·R·X0_src``, covariance propagated
    with its exact Jacobian ``[I, s[R·X0_src]×, −R·X0_src]``.
    """
    src, dst, s0, d0 = _point_pairs(src_xyz, dst_xyz, ("src_xyz", "dst_xyz"), 3, 3,
                                    f"a 3D {'similarity' if estimate_scale else 'rigid'} transformation", 2,
                                    "3D Helmert")
    n = src.shape[0]
    conv = _convention(convention)
    xs, xd = src - s0, dst - d0
    R0, sc0 = umeyama_centred(xs, xd, estimate_scale)
    if sigma_dst is None:
        W = np.ones(3 * n)
    else:
        sd = np.asarray(sigma_dst, dtype=np.float64)
        if sd.ndim == 0:
            sd = np.full((n, 3), float(sd))
        elif sd.ndim == 1 and sd.shape[0] == n:
            sd = np.repeat(sd[:, None], 3, axis=1)
        if sd.shape != (n, 3) or not np.all(np.isfinite(sd)) or np.any(sd <= 0):
            raise InputError(
                "sigma_dst must be a scalar, (n,) or (n, 3) array of standard deviations > 0 (m)"
            )
        W = 1.0 / sd.ravel() ** 2
    state = {"R": R0}
    u = 7 if estimate_scale else 6

    # parameters: t'(3), δ(3) [small rotation applied on the left of the current R], ds
    def fun(x):
        R = exp_so3(x[3:6]) @ state["R"]
        s = 1.0 + x[6] if estimate_scale else 1.0
        rx = xs @ R.T
        pred = s * rx + x[:3]
        f = (pred - xd).ravel()
        B = np.zeros((3 * n, u))
        for k in range(3):
            B[k::3, k] = -1.0
        for i in range(n):
            B[3 * i : 3 * i + 3, 3:6] = s * hat(rx[i])  # −∂(s·exp(δ)Rx)/∂δ = +s[Rx]×
        if estimate_scale:
            B[:, 6] = -rx.ravel()
        return f, B

    x0 = np.zeros(u)
    if estimate_scale:
        x0[6] = sc0 - 1.0
    res = adjust(
        fun,
        x0,
        W,
        options=options,
        param_names=("t'x", "t'y", "t'z", "dx_rot", "dy_rot", "dz_rot", "ds")[:u],
        obs_names=tuple(f"{c}{i}" for i in range(n) for c in "XYZ"),
    )
    R = exp_so3(res.x[3:6]) @ R0
    s = 1.0 + res.x[6] if estimate_scale else 1.0
    T = d0 + res.x[:3] - s * (R @ s0)
    J = np.zeros((u, u))
    J[:3, :3] = np.eye(3)
    J[:3, 3:6] = s * hat(R @ s0)
    if estimate_scale:
        J[:3, 6] = -(R @ s0)
        J[6, 6] = 1.0
    J[3:6, 3:6] = np.eye(3)
    cov = J @ res.Sigma_xx @ J.T
    return Helmert3DResult(
        R=R,
        T=T,
        scale=float(s),
        rotation_pv_rad=log_so3(R),
        convention=conv,
        cov=0.5 * (cov + cov.T),
        residuals=res.v.reshape(n, 3),
        sigma0=res.sigma0,
        dof=res.dof,
        src_origin=s0,
        dst_origin=d0,
        estimate_scale=estimate_scale,
        lsq=res,
    )
