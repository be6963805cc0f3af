"""The Levenberg–Marquardt loop of minegeo: damping, step acceptance, stopping rule, result check.

One loop serves every factor graph (pose graphs, the intersection factor graph, IMU factors). A
*problem* (:class:`minegeo.optim.factors.FactorProblem`, or any object with the same methods)
evaluates residuals and costs, assembles the normal equations (:mod:`minegeo.optim.blocks`) and
retracts a step; this module decides which steps to take and when to stop:

.. math::

    (H + \\lambda D)\\, \\delta = -g, \\qquad x \\leftarrow x \\oplus \\delta

with ``D = I`` (GTSAM's default damping) or ``D = diag(H)`` (Marquardt's, ``damping="diagonal"``).
A trial step is accepted when its cost is finite, not negative and not above the current cost
(:func:`accept_step`; λ ÷ 10), else rejected (λ × 10) [Nocedal2006 Sec. 10.3]; a damped matrix that
is not positive definite is rejected like a step that raises the cost. The loop stops when the last
relative decrease ``ε_k`` is below ``relative_cost_tolerance``, or when both estimates of the
decrease still to come are below ``remaining_cost_tolerance`` (the Gauss–Newton model's
``m_k = −½ gᵀδ / F`` and Aitken's ``ε_k ρ/(1 − ρ)``, :func:`remaining_decrease`), or when the
largest step component is below ``step_tolerance``, or at ``max_iterations``. "converged" is reported only when the stopping test held **and** the undamped
normal equations at the result are positive definite **and** the result passed :func:`check_result`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, one_of, validate
from minegeo.optim.blocks import SingularSystemError
from minegeo.optim.robust import ROBUST

__all__ = ["LMOutcome", "LMParams", "LMStatus", "ROTATION_TOL", "accept_step", "check_result", "levenberg_marquardt",
           "remaining_decrease"]

#: rotations of a result orthonormal to this (max |RRᵀ − I|, |det R − 1|)
ROTATION_TOL = 1e-9


@dataclass(frozen=True)
class LMParams:
    """Parameters of :func:`levenberg_marquardt`.

    Attributes
    ----------
    max_iterations : int
        Largest number of linearisations.
    lambda_init : float
        Initial damping λ (see ``damping``).
    relative_cost_tolerance : float
        Stop when an accepted step lowers the cost by less than this fraction ``ε_k = (F_{k-1} − F_k)/F_{k-1}``.
    remaining_cost_tolerance : float
        Stop after an accepted step when both estimates of the decrease still to come are below this
        fraction of the cost: the Gauss–Newton model's decrease of the iteration, ``m_k = −½ gᵀδ / F``,
        which measures the quadratic phase, and Aitken's ``ε_k ρ / (1 − ρ)``, ``ρ = ε_k / ε_{k−1}``,
        which measures the linear phase.
    step_tolerance : float
        Stop when the largest step component (rad, m, or the variable's unit) is below this.
    robust : {"none", "huber", "cauchy"}
        Robust kernel on every factor's whitened residual norm (:mod:`minegeo.optim.robust`).
    robust_scale : float
        Kernel width ``k`` in whitened units (1 = one standard deviation).
    damping : {"diagonal", "identity"}
        Damping matrix ``D``: ``diag(H)`` (Marquardt, unit-free) or ``I`` (GTSAM's default).

    Each field declares its rule in its metadata (:mod:`minegeo._params`); a subclass's fields
    (:class:`minegeo.slam.posegraph.PoseGraphParams`) are checked by the same ``validate``.
    """

    max_iterations: int = bounded(500, ge=1, integer=True)
    lambda_init: float = bounded(1e-5, gt=0.0)
    relative_cost_tolerance: float = bounded(1e-10, ge=0.0)
    remaining_cost_tolerance: float = bounded(1e-8, ge=0.0)
    step_tolerance: float = bounded(1e-10, ge=0.0)
    robust: str = one_of("none", ROBUST)
    robust_scale: float = bounded(1.0, gt=0.0)
    damping: str = one_of("identity", ("diagonal", "identity"))

    def __post_init__(self):
        validate(self)  # every field with a rule, a subclass's too (PoseGraphParams)


class LMStatus(StrEnum):
    """Status of a Levenberg–Marquardt solve (:attr:`LMOutcome.status`); each member is its string value."""

    #: the stopping test held, the undamped normal equations are positive definite and the result passed its check
    CONVERGED = "converged"
    #: ``max_iterations`` reached before the stopping test held (the result passed its check)
    MAX_ITERATIONS = "max_iterations"
    #: no result: a non-finite start, a singular system or a result that failed its check
    FAILED = "failed"


@dataclass(frozen=True)
class LMOutcome:
    """What :func:`levenberg_marquardt` returns.

    Attributes
    ----------
    status : LMStatus
        ``converged``, ``max_iterations`` or ``failed``.
    reason : str
    cost_initial, cost_final : float
        The plain cost ``½ Σ rᵀΩr`` (no robust kernel) before and after (``cost_initial`` twice when failed).
    iterations : int
    history : list of dict
        Per damping trial: iteration, cost, lambda, accepted, step (largest component).
    values : object
        The result (the start values when failed).
    convergence : dict
        ``relative_decrease``, ``geometric_remaining_relative_decrease``, ``model_relative_decrease``,
        ``predicted_relative_decrease`` (``½ gᵀH⁻¹g / F`` at the result; None when not computed) and,
        when the normal equations are singular, ``singular_vertex``.
    """

    status: LMStatus
    reason: str
    cost_initial: float
    cost_final: float
    iterations: int
    history: list
    values: object
    convergence: dict = field(default_factory=dict)


def accept_step(cost_trial: float, cost: float) -> bool:
    """Whether an LM trial step is accepted: its cost is finite, not negative and not above ``cost``.

    A cost ``½ Σ rᵀΩr`` with positive semi-definite ``Ω`` (and every robust kernel here) cannot be
    negative; a negative trial cost means the problem is not the one stated, and is never accepted.
    """
    return bool(np.isfinite(cost_trial) and 0.0 <= cost_trial <= cost)


def remaining_decrease(rel: float, rel_prev: float) -> float:
    """Aitken's estimate of the relative cost decrease still to come, ``ε ρ / (1 − ρ)``, ``ρ = ε / ε_prev``
    (``inf`` when the decreases do not shrink or there is no previous one)."""
    if not (rel_prev > 0.0 and np.isfinite(rel_prev)) or not rel >= 0.0:
        return float("inf")
    rho = rel / rel_prev
    return rel * rho / (1.0 - rho) if rho < 1.0 else float("inf")


def check_result(poses_in: np.ndarray, poses_out: np.ndarray, held, cost_final: float, cost_initial: float) -> str:
    """Why an optimised result may not be reported as converged ("" when it may).

    Checks: the cost is finite and not negative (rounding allowance ``1e-12 · F₀``); every held
    pose (rows ``held``) is bit-identical to its input; every pose is a proper rigid transform
    (rotation orthonormal, ``det R = +1`` and last row ``(0, …, 0, 1)`` to :data:`ROTATION_TOL`).
    """
    if not np.isfinite(cost_final) or cost_final < -1e-12 * max(abs(cost_initial), 1e-300):
        return f"the final cost {cost_final!r} is not a finite non-negative number"
    held = list(held)
    if held and not np.array_equal(poses_out[held], poses_in[held]):
        return "a held (fixed) pose moved: the gauge was not kept"
    d = poses_out.shape[-1] - 1
    R = poses_out[:, :d, :d]
    ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(d)).max(axis=(1, 2))
    det = np.linalg.det(R)
    last = np.abs(poses_out[:, d, :] - np.eye(d + 1)[d]).max(axis=1)
    bad = np.flatnonzero(~((ortho <= ROTATION_TOL) & (np.abs(det - 1.0) <= ROTATION_TOL) & (last <= ROTATION_TOL)))
    if bad.size:
        return f"{bad.size} optimised pose(s) are not rigid transforms (first: row {int(bad[0])})"
    return ""


def _stop_reason(rel, rest, model, step, params: LMParams) -> str:
    """The stopping rule after an accepted step ("" to go on)."""
    if (rel < params.relative_cost_tolerance or max(rest, model) < params.remaining_cost_tolerance
            or step < params.step_tolerance):
        return (f"relative cost decrease {rel:.2e}, estimated decrease to come {max(rest, model):.2e}, "
                f"largest step {step:.2e}")
    return ""


def levenberg_marquardt(problem, values, params: LMParams) -> LMOutcome:
    """Minimise ``problem``'s cost from ``values`` by Levenberg–Marquardt.

    ``problem`` provides ``evaluate(values) → residuals``, ``cost(residuals)`` (plain),
    ``robust_cost(residuals)``, ``linearize(values, residuals) → system`` (with ``g``,
    ``solve(λ, relative)`` → step or None), ``retract(values, δ)``, ``gauss_newton_decrease(values,
    residuals) → (½ gᵀH⁻¹g or None, index of a singular variable or -1)``,
    ``check(values_in, values_out, cost_final, cost_initial) → str`` and
    ``singular(index) → (reason, id)``; and ``hint``, a phrase appended when no damping helps.

    Returns
    -------
    LMOutcome
        ``"converged"`` only when the stopping rule held, the undamped normal equations at the
        result are positive definite (where the system computes that) and ``problem.check`` passed;
        ``"max_iterations"`` with how far from converged; ``"failed"`` with the start values.
    """
    values0 = values
    res = problem.evaluate(values)
    cost0 = problem.cost(res)

    def failed(reason, it, history, conv=None):
        return LMOutcome(LMStatus.FAILED, reason, cost0, cost0, it, history, values0, conv or {})

    if not np.isfinite(cost0):
        return failed("the initial cost is not finite", 0, [])
    cost = problem.robust_cost(res)
    lam, history, rel, rel_prev, rest = params.lambda_init, [], float("nan"), float("nan"), float("inf")
    model = float("inf")  # the Gauss-Newton model's relative decrease of the current iteration
    status, reason, it, step = LMStatus.MAX_ITERATIONS, "", 0, float("inf")
    for it in range(1, params.max_iterations + 1):
        system = problem.linearize(values, res)
        accepted, factorised = False, False
        while lam < 1e12:
            try:
                delta = system.solve(lam, params.damping == "diagonal")
            except SingularSystemError as exc:
                return failed(str(exc), it, history, {"singular_vertex": -1})
            if delta is None:  # H + λD not positive definite: more damping
                history.append({"iteration": it, "cost": cost, "lambda": lam, "accepted": False, "step": 0.0,
                                "factorised": False})
                lam *= 10.0
                continue
            if delta.size == 0:  # every variable held: the start is the only point there is
                factorised, status, reason = True, LMStatus.CONVERGED, "every variable is held: nothing to optimise"
                break
            trial = problem.retract(values, delta)
            if not factorised:
                model = -0.5 * float(system.g @ delta) / max(cost, 1e-300)
            factorised = True
            res_t = problem.evaluate(trial)
            cost_trial = problem.robust_cost(res_t)
            step = float(np.abs(delta).max()) if delta.size else 0.0
            if accept_step(cost_trial, cost):
                history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": True, "step": step})
                rel_prev, rel = rel, (cost - cost_trial) / max(cost, 1e-300)
                rest = remaining_decrease(rel, rel_prev)
                values, res, cost, accepted = trial, res_t, cost_trial, True
                lam = max(lam / 10.0, 1e-12)
                break
            history.append({"iteration": it, "cost": cost_trial, "lambda": lam, "accepted": False, "step": step})
            lam *= 10.0
        if status == "converged":
            break
        if not accepted and not factorised:
            return failed("the damped normal equations are not positive definite at any damping" + problem.hint,
                          it, history)
        if not accepted:
            status, reason = LMStatus.CONVERGED, "no step lowers the cost (damping exhausted): at a minimum"
            break
        reason = _stop_reason(rel, rest, model, step, params)
        if reason:
            status = LMStatus.CONVERGED
            break
    cost_final = problem.cost(res)
    conv = {"relative_decrease": rel, "geometric_remaining_relative_decrease": rest,
            "model_relative_decrease": model, "predicted_relative_decrease": None}
    pred, v = problem.gauss_newton_decrease(values, res)  # the undamped system at the result
    if v >= 0:
        why, vid = problem.singular(v)
        conv["singular_vertex"] = vid
        return failed(why, it, history, conv)
    if pred is not None:
        conv["predicted_relative_decrease"] = pred / max(cost, 1e-300)
    if status == "max_iterations":
        pred = conv["predicted_relative_decrease"]
        reason = (f"stopped after {params.max_iterations} iterations short of convergence: last relative decrease "
                  f"{rel:.2e}, estimated decrease to come {max(rest, model):.2e} of the cost"
                  + (f", Gauss-Newton predicted decrease {pred:.2e}" if pred is not None else ""))
    problem_found = problem.check(values0, values, cost_final, cost0)
    if problem_found:
        return failed(f"the result failed its check: {problem_found}", it, history, conv)
    return LMOutcome(status, reason, cost0, cost_final, it, history, values, conv)
