"""Closed-form rigid / similarity estimation from point correspondences (SVD, Umeyama).

Frames: ``src`` points are in the *source* frame, ``dst`` points in the *target* frame;
the returned ``T_target_source`` maps source coordinates into the target frame,
``q ≈ c R p + t``.

References
----------
Baek, J., Park, J., Cho, S., Lee, C. (2022). 3D Global Localization in the Underground Mine
Environment Using Mobile LiDAR Mapping and Point Cloud Registration. Sensors 22, 2873.
Sec. 2.4, [Baek2022 Eqs. 10-13].
Umeyama, S. (1991). Least-squares estimation of transformation parameters between two point
patterns. IEEE TPAMI 13(4), 376-380.
Arun, K. S., Huang, T. S., Blostein, S. D. (1987). Least-squares fitting of two 3-D point sets.
IEEE TPAMI 9(5) (the reflection case).
"""

from __future__ import annotations

import numpy as np

from minegeo._validate import as_points
from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.kernels.rigid import umeyama_from_moments
from minegeo.registration import _kernels as K

__all__ = ["umeyama", "kabsch", "pose_covariance"]

#: Relative singular-value level below which the cross-covariance is treated as rank deficient.
RANK_TOL = 1e-12


def _weights(weights, n: int) -> np.ndarray:
    if weights is None:
        return np.ones(n)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise InputError(f"weights must have shape ({n},), got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise InputError("weights must be finite and >= 0")
    if w.sum() <= 0:
        raise InputError("weights sum to zero: at least one correspondence must have a positive weight")
    return np.ascontiguousarray(w)


def umeyama(src, dst, with_scale: bool = False, weights=None, *, allow_degenerate: bool = False):
    """Least-squares rigid (or similarity) transform mapping ``src`` onto ``dst``.

    Parameters
    ----------
    src : (n, 3) array_like
        Source points ``p_i`` (metres, source frame).
    dst : (n, 3) array_like
        Corresponding target points ``q_i`` (metres, target frame), same order as ``src``.
    with_scale : bool
        Also estimate an isotropic scale ``c`` (Umeyama 1991). Default: rigid (``c = 1``).
    weights : (n,) array_like, optional
        Non-negative weights ``w_i`` (default all 1).
    allow_degenerate : bool, keyword-only
        If False (default), raise :class:`DegenerateGeometryError` when the correspondences do
        not determine the rotation (all points coincident or collinear). If True, return the
        (deterministic but arbitrary about the free axis) SVD answer, as Open3D/Eigen do;
        RANSAC minimal samples use this.

    Returns
    -------
    T_target_source : (4, 4) ndarray
        ``[[c R, t], [0, 1]]`` with ``q ≈ c R p + t``.
    scale : float
        ``c`` (1.0 when ``with_scale`` is False).

    Raises
    ------
    InputError
        Shapes differ, NaN/inf rows, bad weights.
    TooFewPointsError
        Fewer than 3 correspondences (a rotation needs 3 non-collinear points).
    DegenerateGeometryError
        Rank of the cross-covariance < 2 (coincident or collinear points) and not ``allow_degenerate``.

    Notes
    -----
    With weighted centroids ``p̄``, ``q̄`` and centred points ([Baek2022 Eq. 10] is written
    without the centring, which is implied by [Baek2022 Eq. 13]):

    .. math::

        W = \\frac{1}{\\sum w_i}\\sum_i w_i (p_i-\\bar p)(q_i-\\bar q)^T \\quad (10), \\qquad
        W = U \\Sigma V^T \\quad (11),

        R = V \\,\\mathrm{diag}(1, 1, d)\\, U^T,\\; d = \\operatorname{sign}\\det(V U^T) \\quad (12),
        \\qquad t = \\bar q - c R \\bar p \\quad (13).

    The ``diag(1, 1, d)`` factor is the reflection fix (Arun 1987, Umeyama 1991): without it a
    planar or noisy configuration can return a reflection (det R = -1). With scaling,
    ``c = tr(Σ diag(1,1,d)) / σ_p²`` with ``σ_p² = Σ w_i |p_i - p̄|² / Σ w_i``.
    This is Eigen's ``umeyama`` (Open3D ``TransformationEstimationPointToPoint``, oracle spec §7)
    written in the paper's notation (Eigen's ``U``/``V`` are this ``V``/``U``).
    """
    P = as_points(src, "src")
    Q = as_points(dst, "dst")
    if P.shape[0] != Q.shape[0]:
        raise InputError(f"src and dst must have the same number of points, got {P.shape[0]} and {Q.shape[0]}")
    if P.shape[0] < 3:
        raise TooFewPointsError(
            f"rigid estimation needs at least 3 correspondences, got {P.shape[0]}"
        )
    w = _weights(weights, P.shape[0])
    _, mu_p, mu_q, W, var_p = K.weighted_moments_kernel(P, Q, w)
    T, c, S = umeyama_from_moments(mu_p, mu_q, W, var_p, bool(with_scale))
    if not allow_degenerate:
        if S[0] <= 0.0 or S[1] <= RANK_TOL * S[0]:
            raise DegenerateGeometryError(
                "the corresponding points are coincident or collinear, so the rotation about their "
                f"common line is undetermined (cross-covariance singular values {S.tolist()}); "
                "use at least 3 well-spread, non-collinear points"
            )
        if with_scale and var_p <= 0.0:
            raise DegenerateGeometryError("all source points coincide: the scale is undetermined")
    return T, float(c)


def kabsch(src, dst, weights=None, *, allow_degenerate: bool = False) -> np.ndarray:
    """Rigid transform ``T_target_source`` (no scale) by the Kabsch/Umeyama SVD solution.

    Same as ``umeyama(src, dst, with_scale=False, weights=weights)[0]``; see :func:`umeyama`
    for the formula ([Baek2022 Eqs. 10-13] with the reflection fix) and the errors raised.
    """
    T, _ = umeyama(src, dst, with_scale=False, weights=weights, allow_degenerate=allow_degenerate)
    return T


def pose_covariance(information_6x6, sigma_m: float) -> np.ndarray:
    """Covariance of a pose from its information matrix: ``Σ = σ² I⁻¹``.

    Parameters
    ----------
    information_6x6 : (6, 6) array_like
        ``Σ J_iᵀ J_i`` as returned by :func:`minegeo.registration.register_icp`
        (parameter order ``(ω_x, ω_y, ω_z, t_x, t_y, t_z)``: rotation in rad first, then
        translation in metres, left-perturbation in the target frame).
    sigma_m : float
        Standard deviation of one residual (metres), e.g. the ICP inlier RMSE or a
        sensor noise figure.

    Returns
    -------
    (6, 6) ndarray
        Covariance in rad² / rad·m / m².

    Raises
    ------
    DegenerateGeometryError
        The information matrix is singular (some direction is unobservable, e.g. a single
        plane, or translation along a featureless tunnel).
    InputError
        Bad shape, not symmetric, or ``sigma_m`` not > 0.
    """
    from minegeo._validate import as_matrix, check_positive

    H = as_matrix(information_6x6, (6, 6), "information_6x6")
    s = check_positive(sigma_m, "sigma_m")
    if not np.allclose(H, H.T, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(H).max()))):
        raise InputError("information_6x6 must be symmetric")
    ev = np.linalg.eigvalsh(H)
    if ev[-1] <= 0.0 or ev[0] <= 1e-12 * ev[-1]:
        raise DegenerateGeometryError(
            f"the information matrix is singular (eigenvalues {ev.tolist()}): at least one pose "
            "direction is not constrained by the geometry, so no covariance exists"
        )
    return s * s * np.linalg.inv(H)
