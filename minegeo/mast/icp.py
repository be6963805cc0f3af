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
and the rotations are summed into ``beta_cum``. Each gate stage is one run of the
registration loop (:func:`minegeo.registration.loop.run_loop`) with the factor
:class:`~minegeo.registration.loop.PointToLine2DFactor` on
:class:`~minegeo.registration.loop.SE2Points`. Correspondences are re-made every
iteration with a distance gate that is tightened in stages (``gates_m``). A stage
ends when the increments are negligible or when the correspondences alternate
between two sets (a point sitting on the gate); the final least squares re-makes
its own correspondences anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo._provenance import StageTimer
from minegeo._validate import as_matrix, as_points
from minegeo.errors import InputError
from minegeo.mast._kernels import _nearest_segment
from minegeo.registration.loop import (
    Matches,
    PointToLine2DFactor,
    SE2Points,
    Termination,
    rot2,
    run_loop,
)

__all__ = ["IcpResult", "icp_point_to_line", "rot2"]


class NearestSegment2D:
    """Correspondence search of the MAST loop: for every moved scan point ``q`` (mine frame, m)
    the nearest panel onto whose interior (minus ``margin_m``) it projects, kept when the
    perpendicular distance is ``<= gate_m``; ``Matches.extra`` holds the signed distances along
    the panels' left normals (m)."""

    def __init__(self, segments: np.ndarray, margin_m: float, gate_m: float):
        self.segments, self.margin_m, self.gate_m = segments, float(margin_m), gate_m

    def __call__(self, q: np.ndarray, prev: Matches | None) -> Matches:
        dist, idx, sd = _nearest_segment(q, self.segments, self.margin_m)
        keep = dist <= self.gate_m
        src = np.flatnonzero(keep)
        corr = np.empty((src.size, 2), dtype=np.int64)
        corr[:, 0] = src
        corr[:, 1] = idx[keep]
        return Matches(src.size / q.shape[0], float("nan"), corr, extra=sd[keep])


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
    se2 = SE2Points(s)
    pose = (np.array(T0[:2, :2], dtype=np.float64), np.array(T0[:2, 2], dtype=np.float64))
    stop = Termination(step_translation=tol_m, step_rotation=tol_rad, stop_on_cycle=True,
                       evaluate_after_last_step=False)
    beta_cum, it, converged, n_in, rms = 0.0, 0, False, 0, float("nan")
    for gate in gates_m:
        out = run_loop(se2.move(None, pose, None), pose, NearestSegment2D(segs, margin_m, gate),
                       PointToLine2DFactor(se2, nrm, gate, min_points), stop, max_iterations - it, StageTimer())
        pose = out.pose
        for x in out.steps:
            beta_cum += float(x[0])
        it += out.iterations
        if out.last_aux is not None:
            n_in, rms = out.last_aux
        converged = out.converged
        if not converged:
            break
    T = np.eye(3)
    T[:2, :2] = pose[0]
    T[:2, 2] = pose[1]
    return IcpResult(T, beta_cum, it, n_in, rms, converged)
