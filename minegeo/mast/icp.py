"""2D point-to-line ICP with Low's (2004) small-angle linearisation.

Simela, Marshall & Daneshmend, section "Alignment of Arbitrary Scanner Data to Mine
Reference Frame", second step; Low (2004), *Linear least-squares optimization for
point-to-plane ICP surface registration*, TR04-004 (here reduced to 2D lines).

Each iteration minimises ``sum_i ((M s_i - d_i) . n_i)^2`` over ``M = T(t_x, t_y) R(beta)``
where ``d_i`` is the projection of the (current) point ``s_i`` on its corresponding
beacon panel and ``n_i`` the panel's unit normal. With ``R(beta) ~ [[1, -beta],
[beta, 1]]`` every residual is linear in ``(beta, t_x, t_y)``::

    ((s_i - d_i) . n_i) + beta (s_ix n_iy - s_iy n_ix) + t_x n_ix + t_y n_iy  ->  A x = b

solved as ``x = (A^T A)^-1 A^T b``; the exact rotation ``R(beta)`` is then applied
and the rotations are summed into ``beta_cum``. Correspondences are re-made every
iteration with a distance gate that is tightened in stages (``gates_m``). A stage
ends when the increments are negligible or when the correspondences alternate
between two sets (a point sitting on the gate); the final least squares re-makes
its own correspondences anyway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo._validate import as_matrix, as_points
from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.mast._kernels import _nearest_segment

__all__ = ["IcpResult", "icp_point_to_line", "rot2"]


def rot2(theta_rad: float) -> np.ndarray:
    """Counter-clockwise 2x2 rotation matrix."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s], [s, c]])


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp_point_to_line`.

    Attributes
    ----------
    T_mine_scan : (3, 3) float64
        Homogeneous 2D rigid transform ``p_mine = R p_scan + t`` (local mine frame).
    beta_cum_rad : float
        Sum of the ICP rotation increments (counter-clockwise, rad), the paper's
        ``beta_Cum`` (relative to the initial alignment).
    iterations : int
        Total ICP iterations over all gate stages.
    n_inliers : int
        Correspondences in the last iteration.
    rms_m : float
        RMS point-to-line distance of those correspondences (m).
    converged : bool
    """

    T_mine_scan: np.ndarray
    beta_cum_rad: float
    iterations: int
    n_inliers: int
    rms_m: float
    converged: bool


def icp_point_to_line(
    points_scan: np.ndarray,
    panels: np.ndarray,
    T0: np.ndarray,
    gates_m=(0.20, 0.10, 0.05),
    max_iterations: int = 100,
    tol_rad: float = 1e-10,
    tol_m: float = 1e-9,
    margin_m: float = 0.0,
    min_points: int = 3,
) -> IcpResult:
    """Align scan points to known line segments (beacon panels) by point-to-line ICP.

    Parameters
    ----------
    points_scan : (n, 2) float64
        Points in the scanner frame (m).
    panels : (k, 4) float64
        Panel segments ``[ax, ay, bx, by]`` in the (local) mine frame (m).
    T0 : (3, 3) float64
        Initial ``T_mine_scan`` (e.g. from the four-parameter Helmert fit, scale dropped).
    gates_m : sequence of float
        Correspondence distance gates, applied in stages (each to convergence).
    max_iterations : int
        Total iteration budget over all stages.
    tol_rad, tol_m : float
        Convergence when ``|beta| < tol_rad`` and ``|t| < tol_m``.
    margin_m : float
        Points projecting within this distance of a panel end are not associated.
    min_points : int
        Minimum correspondences (>= 3 for three unknowns).

    Raises
    ------
    TooFewPointsError
        Fewer than ``min_points`` correspondences.
    DegenerateGeometryError
        All correspondences on parallel lines (the normal matrix is singular).
    """
    s = as_points(points_scan, "points_scan", dim=2, min_points=min_points)
    segs = as_matrix(panels, (-1, 4), "panels")
    T0 = as_matrix(T0, (3, 3), "T0")
    if segs.shape[0] == 0 or np.any(np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]) <= 0):
        raise InputError("panels must be non-empty segments of positive length")
    e = segs[:, 2:] - segs[:, :2]
    u = e / np.linalg.norm(e, axis=1)[:, None]
    nrm = np.column_stack([-u[:, 1], u[:, 0]])
    R = np.array(T0[:2, :2], dtype=np.float64)
    t = np.array(T0[:2, 2], dtype=np.float64)
    beta_cum = 0.0
    it = 0
    converged = False
    n_in = 0
    rms = float("nan")
    for gate in gates_m:
        stage_conv = False
        prev_masks: list[bytes] = []
        while it < max_iterations:
            q = np.ascontiguousarray(s @ R.T + t)
            dist, idx, sd = _nearest_segment(q, segs, float(margin_m))
            m = dist <= gate
            key = np.packbits(m).tobytes() + idx[m].tobytes()
            if len(prev_masks) >= 2 and key == prev_masks[-2] and key != prev_masks[-1]:
                # correspondences alternate between two sets (a point on the gate edge): stop here
                stage_conv = True
                break
            prev_masks = (prev_masks + [key])[-2:]
            n_in = int(m.sum())
            if n_in < min_points:
                raise TooFewPointsError(
                    f"ICP: only {n_in} scan point(s) lie within {gate:.3f} m of a beacon panel; "
                    f"at least {min_points} are needed"
                )
            qi = q[m]
            ni = nrm[idx[m]]
            A = np.column_stack([qi[:, 0] * ni[:, 1] - qi[:, 1] * ni[:, 0], ni[:, 0], ni[:, 1]])
            b = -sd[m]
            N = A.T @ A
            sc = 1.0 / np.sqrt(np.maximum(np.diag(N), 1e-300))
            Ns = N * sc[:, None] * sc[None, :]
            if np.linalg.cond(Ns) > 1e10:
                raise DegenerateGeometryError(
                    "ICP: the matched scan points lie on parallel lines, so the scanner position "
                    "along them is undetermined (collinear control)"
                )
            x = np.linalg.solve(N, A.T @ b)
            rms = float(np.sqrt(np.mean(b * b)))
            Rb = rot2(x[0])
            R = Rb @ R
            t = Rb @ t + x[1:]
            beta_cum += float(x[0])
            it += 1
            if abs(x[0]) < tol_rad and np.hypot(x[1], x[2]) < tol_m:
                stage_conv = True
                break
        converged = stage_conv
        if not stage_conv:
            break
    T = np.eye(3)
    T[:2, :2] = R
    T[:2, 2] = t
    return IcpResult(T, beta_cum, it, n_in, rms, converged)
