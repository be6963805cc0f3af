"""Variables and factors of the optimiser, and the problem that :func:`minegeo.optim.lm.levenberg_marquardt` solves.

Variables
---------
:class:`Values` holds ``n`` variables of one kind: a pose on SE(3) (``T_world_body``, 4×4) or SE(2)
(3×3), optionally followed by a vector in R^e (e.g. velocity and IMU biases of a navigation state).
A variable's tangent vector is ``δ = (δ_pose, δ_vec)``, the pose part ordered rotation first
(``(φ, ρ)`` rad, m for SE(3); ``(θ, x, y)`` for SE(2)) and applied on the right, the vector part
added: ``T ← T · Exp(δ_pose)``, ``v ← v + δ_vec`` (GTSAM's ``Pose3``/``Pose2`` retraction).

Factors
-------
A factor group (:class:`FactorGroup`) is a set of factors of one type, each on one variable
(unary) or two (binary), with residual ``r ∈ R^k`` and information ``Ω`` (k×k); it returns its
residuals and Jacobians ``∂r/∂δ`` per slot. A Jacobian may cover only the leading (pose)
columns of its variable's tangent space: the rest are zero. Provided here: :class:`BetweenFactors`
(``r = Log(Z⁻¹ T_i⁻¹ T_j)``, GTSAM's ``BetweenFactorPose3``/``Pose2``) and :class:`PriorFactors`
(``r = Log(T_prior⁻¹ T_i)``, GTSAM's ``PriorFactorPose3``); the intersection factors live in
:mod:`minegeo.semantic.factors`, the IMU factors in :mod:`minegeo.optim.imu`.

The cost is ``F = ½ Σ rᵀ Ω r`` over every factor (GTSAM's ``NonlinearFactorGraph.error``), with
the robust kernel of the parameters applied to each factor's whitened residual while optimising.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from minegeo.optim import _kernels as K
from minegeo.optim.blocks import BlockSystem
from minegeo.optim.lm import LMParams, check_result
from minegeo.optim.robust import quadratic_cost, robust_cost, robust_weights

__all__ = ["BetweenFactors", "FactorGroup", "FactorProblem", "PriorFactors", "Values", "between_residuals",
           "between_terms"]


@dataclass(frozen=True)
class Values:
    """``n`` variables: poses (n, k, k) on SE(3) (k = 4) or SE(2) (k = 3), and optionally vectors (n, e).

    Attributes
    ----------
    poses : ndarray (n, k, k)
        ``T_world_body`` (homogeneous, metres).
    vectors : ndarray (n, e) or None
        The R^e part of each variable (None: pose-only variables).
    """

    poses: np.ndarray
    vectors: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.poses.shape[0])

    @property
    def kind(self) -> str:
        return "SE3" if self.poses.shape[-1] == 4 else "SE2"

    @property
    def pose_dof(self) -> int:
        return 6 if self.kind == "SE3" else 3

    @property
    def dim(self) -> int:
        """Tangent dimension of one variable."""
        return self.pose_dof + (0 if self.vectors is None else int(self.vectors.shape[1]))

    def retract(self, col: np.ndarray, delta: np.ndarray) -> Values:
        """``T_v ← T_v · Exp(δ[c:c+p])``, ``x_v ← x_v + δ[c+p:c+d]`` for every ``c = col[v] ≥ 0``."""
        out = np.empty_like(self.poses)
        (K.se3_retract_all if self.kind == "SE3" else K.se2_retract_all)(self.poses, col, delta, out)
        if self.vectors is None:
            return Values(out)
        vec = self.vectors.copy()
        free = col >= 0
        e = vec.shape[1]
        vec[free] += delta[col[free, None] + self.pose_dof + np.arange(e)[None, :]]
        return Values(out, vec)


class FactorGroup(abc.ABC):
    """Factors of one type. Subclasses set :attr:`variables` (m, arity) and :attr:`information`
    (m, k, k) and define :meth:`residuals` and :meth:`linearize`."""

    variables: np.ndarray
    information: np.ndarray

    @property
    def arity(self) -> int:
        return int(self.variables.shape[1])

    @abc.abstractmethod
    def residuals(self, values: Values) -> np.ndarray:
        """Residuals (m, k) at ``values``."""

    @abc.abstractmethod
    def linearize(self, values: Values) -> tuple:
        """``(r, (J_slot0, J_slot1, ...))``: residuals (m, k) and Jacobians (m, k, d_slot) with
        respect to the right-perturbation tangent vector of each slot's variable."""


def between_terms(kind: str, poses, edges, Z):
    """Residuals ``r = Log(Z⁻¹ T_i⁻¹ T_j)`` (m, d) and Jacobians ``J_i``, ``J_j`` (m, d, d) of between
    factors ``edges`` (m, 2) with measurements ``Z`` (m, k, k) [Sola2018 Sec. 4]."""
    d, m = (6 if kind == "SE3" else 3), edges.shape[0]
    r, Ji, Jj = np.empty((m, d)), np.empty((m, d, d)), np.empty((m, d, d))
    (K.se3_edge_terms if kind == "SE3" else K.se2_edge_terms)(poses, edges, Z, r, Ji, Jj)
    return r, Ji, Jj


def between_residuals(kind: str, poses, edges, Z) -> np.ndarray:
    """Residuals only of :func:`between_terms` (the cost of a trial step)."""
    r = np.empty((edges.shape[0], 6 if kind == "SE3" else 3))
    (K.se3_residuals if kind == "SE3" else K.se2_residuals)(poses, edges, Z, r)
    return r


class BetweenFactors(FactorGroup):
    """``r = Log(Z_ij⁻¹ T_i⁻¹ T_j)`` on pose pairs ``edges`` (m, 2); information in the residual's
    order (rotation first)."""

    def __init__(self, edges, Z, information):
        self.variables = np.ascontiguousarray(edges, dtype=np.int64).reshape(-1, 2)
        self.Z = np.ascontiguousarray(Z, dtype=np.float64)
        self.information = np.ascontiguousarray(information, dtype=np.float64)

    def residuals(self, values: Values) -> np.ndarray:
        return between_residuals(values.kind, values.poses, self.variables, self.Z)

    def linearize(self, values: Values) -> tuple:
        r, Ji, Jj = between_terms(values.kind, values.poses, self.variables, self.Z)
        return r, (Ji, Jj)


class PriorFactors(FactorGroup):
    """``r = Log(T_prior⁻¹ T_i)`` on poses ``index`` (m,) (GTSAM's ``PriorFactorPose3``): a between
    factor from the identity, ``∂r/∂δ_i = J_r⁻¹(r)``."""

    def __init__(self, index, T_prior, information):
        self.variables = np.ascontiguousarray(index, dtype=np.int64).reshape(-1, 1)
        self.Z = np.ascontiguousarray(T_prior, dtype=np.float64)
        self.information = np.ascontiguousarray(information, dtype=np.float64)

    def _with_identity(self, values: Values):
        P = values.poses
        anchor = P.shape[0]
        edges = np.ascontiguousarray(np.c_[np.full(self.variables.shape[0], anchor), self.variables[:, 0]])
        return np.ascontiguousarray(np.concatenate([P, np.eye(P.shape[-1])[None]])), edges

    def residuals(self, values: Values) -> np.ndarray:
        P, edges = self._with_identity(values)
        return between_residuals(values.kind, P, edges, self.Z)

    def linearize(self, values: Values) -> tuple:
        P, edges = self._with_identity(values)
        r, _, Jj = between_terms(values.kind, P, edges, self.Z)
        return r, (Jj,)


def _padded(J: np.ndarray, d: int) -> np.ndarray:
    """``J`` (m, k, w) with zero columns appended up to ``d`` (a Jacobian on the leading columns)."""
    if J.shape[2] == d:
        return J
    out = np.zeros(J.shape[:2] + (d,))
    out[:, :, :J.shape[2]] = J
    return out


class FactorProblem:
    """Factor groups over :class:`Values`, some variables held: what
    :func:`~minegeo.optim.lm.levenberg_marquardt` minimises (block normal equations).

    Parameters
    ----------
    n : int
        Number of variables.
    dim : int
        Tangent dimension of each variable.
    groups : sequence of FactorGroup
    held : sequence of int
        Variables held at their start value (the gauge).
    params : LMParams
        Its robust kernel applies to every factor.
    labels : callable, optional
        ``labels(v) → (name, id)`` of variable ``v`` for the message of a singular system
        (default ``("variable v", v)``).
    hint : str
        Appended to "not positive definite at any damping".
    """

    def __init__(self, n: int, dim: int, groups, held, params: LMParams, labels=None, hint: str = ""):
        self.groups = [g for g in groups if g.variables.shape[0]]
        self.held = tuple(int(h) for h in held)
        self.params = params
        self.dim = int(dim)
        self.hint = hint
        self._labels = labels or (lambda v: (f"variable {v}", int(v)))
        free = np.ones(n, dtype=bool)
        free[list(self.held)] = False
        binary = [g.variables for g in self.groups if g.arity == 2]
        pairs = np.concatenate(binary) if binary else np.zeros((0, 2), dtype=np.int64)
        self.system = BlockSystem(self.dim, n, free, pairs)
        self._slots = [self.system.binary_slots(g.variables) if g.arity == 2
                       else self.system.unary_blocks(g.variables[:, 0]) for g in self.groups]

    def evaluate(self, values: Values) -> list:
        return [g.residuals(values) for g in self.groups]

    def cost(self, res) -> float:
        """``½ Σ rᵀΩr`` over every factor."""
        total = 0.0
        for g, r in zip(self.groups, res, strict=True):
            total += quadratic_cost(r, g.information)
        return total

    def robust_cost(self, res) -> float:
        total = 0.0
        for g, r in zip(self.groups, res, strict=True):
            total += robust_cost(r, g.information, self.params.robust, self.params.robust_scale)
        return total

    def linearize(self, values: Values, res) -> BlockSystem:
        """``H``, ``g`` at ``values``, each factor weighted by the robust kernel at ``res``."""
        s = self.system
        s.reset()
        for g, r_w, slots in zip(self.groups, res, self._slots, strict=True):
            r, J = g.linearize(values)
            w = robust_weights(r_w, g.information, self.params.robust, self.params.robust_scale)
            WO = np.ascontiguousarray(g.information * w[:, None, None])
            J = [np.ascontiguousarray(_padded(j, self.dim)) for j in J]
            if g.arity == 2:
                s.add_binary(slots, r, J[0], J[1], WO)
            else:
                s.add_unary(slots, r, J[0], WO)
        return s

    def gauss_newton_decrease(self, values: Values, res):
        return self.linearize(values, res).gauss_newton_decrease()

    def retract(self, values: Values, delta: np.ndarray) -> Values:
        return values.retract(self.system.col, delta)

    def singular(self, v: int):
        name, vid = self._labels(v)
        return (f"the normal equations are singular at {name}: the information of its factors leaves a "
                "direction of it unconstrained"), vid

    def check(self, values_in: Values, values_out: Values, cost_final: float, cost_initial: float) -> str:
        """:func:`~minegeo.optim.lm.check_result` on the poses, and finite, unmoved held vectors."""
        problem = check_result(values_in.poses, values_out.poses, self.held, cost_final, cost_initial)
        if problem or values_out.vectors is None:
            return problem
        if not np.all(np.isfinite(values_out.vectors)):
            return "a vector part of the result (velocity, bias) is not finite"
        held = list(self.held)
        if held and not np.array_equal(values_out.vectors[held], values_in.vectors[held]):
            return "a held variable moved: the gauge was not kept"
        return ""
