"""Stage 5 of :func:`~minegeo.localize.localize_scan`: the pose covariance and the checks that use it.

:func:`pose_covariance` computes ``Σ`` of the final fit about the scan origin (map axes,
parameters ``(ω, t)``: :mod:`minegeo.localize.uncertainty`), the 95 % displacement of the scan's
bounding-box corners and the pending step; :func:`judge_fit` then decides whether a weak
direction, an unsettled ICP or a singular information matrix turns an ``ok`` into ``ambiguous``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from minegeo.geometry.se3 import hat
from minegeo.localize.params import LocalizeParams
from minegeo.localize.result import LocalizeStatus
from minegeo.localize.uncertainty import CHI2_3D_95, pose_uncertainty, radii_95
from minegeo.localize.verification import VerifyContext

__all__ = ["PoseCovariance", "pose_covariance", "judge_fit"]


@dataclass
class PoseCovariance:
    """Outcome of :func:`pose_covariance` (defaults: no final fit).

    Attributes
    ----------
    T_work_scan : (4, 4) ndarray
        The final pose of ``D`` in the work frame (identity without a fit).
    cov : (6, 6) ndarray or None
        ``covariance_6x6``: data term plus model terms, ``(ω, t)`` about the scan origin, map axes.
    sigma : float
        Residual σ of the final pairs, m.
    residuals : ndarray or None
        Point-to-plane residuals of the final pairs, m.
    disp95 : float
        Largest 95 % displacement of the scan's bounding-box corners, m
        (``sqrt(7.815 λ_max(J Σ Jᵀ))``, ``J = [−[q − o]×, I]``); inf without ``cov``.
    unc_record : dict or None
        ``LocalizationResult.uncertainty``.
    pending : float
        Largest scan-point displacement of one more point-to-plane step, m (NaN without one).
    pos_cov, pos_sigma, r95, h95
        Position covariance (m²), its standard deviations (m) and the 95 % radii (m).
    """

    T_work_scan: np.ndarray = field(default_factory=lambda: np.eye(4))
    cov: np.ndarray | None = None
    sigma: float = math.nan
    residuals: np.ndarray | None = None
    disp95: float = math.inf
    unc_record: dict | None = None
    pending: float = math.nan
    pos_cov: np.ndarray | None = None
    pos_sigma: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    r95: float = math.inf
    h95: float = math.inf


def _corner_displacement_95(Pw: np.ndarray, o_work: np.ndarray, cov: np.ndarray) -> float:
    """95 % displacement of the scan's bounding-box corners under the pose covariance (a rigid
    perturbation moves points affinely, so the extreme is at a corner), m."""
    lo, hi = Pw.min(axis=0), Pw.max(axis=0)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    disp95 = 0.0
    for q in corners:
        Jq = np.hstack([-hat(q - o_work), np.eye(3)])
        disp95 = max(disp95, float(np.linalg.eigvalsh(Jq @ cov @ Jq.T)[-1]))
    return float(math.sqrt(CHI2_3D_95 * max(disp95, 0.0)))


def pose_covariance(ctx: VerifyContext, ic_final, polish) -> PoseCovariance:
    """Pose covariance of the final fit ``ic_final`` (None: no fit) about the scan origin.

    ``polish`` is the applied-or-not :class:`~minegeo.localize.verification.Polish` (or None):
    with ``icp.weak_axis_polish_term`` its shift is added as the ``weak_axis_polish`` model term
    when the final pairs constrain some direction weakly.
    """
    p: LocalizeParams = ctx.p
    scan_origin, Dfine = ctx.scan.scan_origin, ctx.scan.icp_points
    if ic_final is None:
        return PoseCovariance()
    out = PoseCovariance(T_work_scan=ic_final.T_target_source)
    T_work_scan = out.T_work_scan
    Pw = Dfine @ T_work_scan[:3, :3].T + T_work_scan[:3, 3]
    # D = scan points - scan_origin, so the scan frame's origin is at D = -scan_origin
    o_work = T_work_scan[:3, :3] @ (-scan_origin) + T_work_scan[:3, 3]
    step = None
    if ic_final.correspondences.shape[0] >= 7:
        unc = pose_uncertainty(Pw, ctx.Qf, ctx.Nf, ic_final.correspondences, o_work,
                               replace(p.uncertainty, degeneracy_ratio=0.0), check_target=False)
        # weak direction: add the polish's shift as a model-error term (see weak_axis_polish_term)
        add_shift = (unc.covariance_6x6 is not None and p.icp.weak_axis_polish_term and polish is not None
                     and polish.record["applied"] and unc.information_ratio < p.uncertainty.degeneracy_ratio)
        if add_shift:
            d6 = np.asarray(polish.record["shift_6"], dtype=np.float64)
            unc = unc.with_model_term("weak_axis_polish", np.outer(d6, d6))
        out.cov, out.sigma, out.residuals, step = unc.covariance_6x6, unc.sigma_m, unc.residuals_m, unc.pending_step
        # record: data term + named model terms, without the top-level matrices
        out.unc_record = unc.to_dict()
        for k in ("covariance_6x6", "covariance_formal_6x6", "position_cov_3x3", "information_6x6"):
            out.unc_record.pop(k, None)
        out.unc_record["weak_axis_polish_term"] = bool(add_shift)
    if out.cov is not None:
        out.disp95 = _corner_displacement_95(Pw, o_work, out.cov)
    if step is not None:
        lever = float(np.sqrt(np.max(np.sum((Pw - o_work) ** 2, axis=1))))
        out.pending = float(np.linalg.norm(step[3:]) + np.linalg.norm(step[:3]) * lever)
    if out.cov is not None:
        out.pos_cov = out.cov[3:, 3:].copy()
        out.pos_sigma = np.sqrt(np.maximum(np.diag(out.pos_cov), 0.0))
        out.r95, out.h95 = radii_95(out.pos_cov)
        if out.unc_record is not None:  # the estimator's own radii, updated for any term added here
            out.unc_record.update(position_95_radius_m=out.r95, horizontal_95_radius_m=out.h95,
                                  position_sigma_m=out.pos_sigma.tolist())
    return out


def judge_fit(status: LocalizeStatus, reason: str, weak: str, pc: PoseCovariance, p: LocalizeParams,
              warnings: list) -> tuple[LocalizeStatus, str]:
    """The covariance-based checks of an ``ok`` decision, in this order: a weak direction whose
    95 % displacement exceeds ``verify.max_weak_displacement_95_m`` (or without covariance), an ICP
    that stopped more than ``verify.max_pending_step_m`` from the surface fit, a singular information
    matrix; each makes it ``ambiguous``. A harmless weak direction is a note in ``warnings``.
    Call only when there is a final fit. Returns ``(status, reason)``."""
    cov, disp95, pending = pc.cov, pc.disp95, pc.pending
    if weak and status == "ok":
        if cov is None or disp95 > p.verify.max_weak_displacement_95_m:
            status = LocalizeStatus.AMBIGUOUS
            reason = ("the fit is not constrained in every direction: " + weak
                      + (f"; the 95 % displacement over the scan reaches {disp95:.3f} m (> "
                         f"{p.verify.max_weak_displacement_95_m:g} m)" if cov is not None else "")
                      + " (e.g. a straight featureless drift: the position along it is uncertain)")
        else:
            # does not change the answer: a note (result.json, report), not a logged warning
            warnings.append(f"note: weakly constrained direction ({weak}), but its 95 % displacement over the "
                            f"scan is only {disp95:.3f} m (<= {p.verify.max_weak_displacement_95_m:g} m) and the "
                            "95 % radius includes it")
    if pending > p.verify.max_pending_step_m and status == "ok":  # NaN (no step) never is
        status = LocalizeStatus.AMBIGUOUS
        reason = (f"ICP stopped {pending:.3f} m (largest displacement over the scan) away from the "
                  f"best surface fit (> {p.verify.max_pending_step_m:g} m): the pose is not settled; try "
                  "--icp point_to_plane or more ICP iterations")
    if cov is None and status == "ok":
        status = LocalizeStatus.AMBIGUOUS
        reason = "the fit leaves at least one pose direction unconstrained (singular information matrix)"
    return status, reason
