"""The one registration loop: correspondences → factor → reduction → step on SE(3)/SE(2) → termination.

Every iterative registration of minegeo (:func:`~minegeo.registration.register_icp` point-to-point
and point-to-plane, :func:`~minegeo.registration.register_gicp`, MAST's
:func:`~minegeo.mast.icp_point_to_line`) is :func:`run_loop` with four small pieces, in the
spirit of small_gicp (Koide 2024) and Open3D's ``registration_icp`` (oracle spec §10):

*search*
    ``search(points, previous_matches) -> Matches``: the correspondences of the moved source
    points and their fitness / Euclidean inlier RMSE ([Baek2022 Eq. 19]).
    :class:`NearestInGate` (exact gated nearest neighbour, Open3D §8);
    :class:`minegeo.mast.icp.NearestSegment2D` (perpendicular distance to a line segment, MAST).
*factor*
    ``factor.step(points, pose, matches) -> (delta, singular, aux)``: one pose increment from
    the current pairs. A Gauss-Newton factor (:class:`GaussNewtonFactor`) only writes
    ``linearize(points, pose, matches) -> (H, g, aux)``, the reduction ``H = Σ Jᵢᵀ Wᵢ Jᵢ``,
    ``g = Σ Jᵢᵀ Wᵢ rᵢ`` over the pairs (a fixed-chunk Numba kernel), and inherits the linear
    solve ``H x = -g`` and the manifold's exponential. Factors: :class:`PointToPointFactor`
    (closed form, [Baek2022 Eqs. 10-13]), :class:`PointToPlaneFactor` ([Low2004]),
    :class:`GICPFactor` ([Ren2019 Eqs. 4-6]) and :class:`PointToLine2DFactor` (MAST).
*manifold*
    How an increment acts: :class:`SE3Euler` (Open3D's ``TransformVector6dToMatrix4d``, left
    update ``T ← ΔT T``) and :class:`SE2Points` (``R ← R(β) R``, ``t ← R(β) t + τ``).
*termination*
    :class:`Termination`: Open3D's fitness/RMSE-change test, a step-size test, and a 2-cycle
    of correspondence sets.

A new factor (e.g. SLAM odometry, a loop-closure constraint) is a ``linearize`` method; the
linear solve (:func:`solve_normal_equations`) and the update (:func:`euler6_to_transform`,
:func:`rotation_angle`, :func:`rot2`) are shared with the pose-graph solver. The floating-point
operations of every piece are those of the three loops it replaced, so results are
bit-identical to them (``benchmarks/fingerprint.py``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from minegeo.errors import DegenerateGeometryError, TooFewPointsError
from minegeo.geometry.se3 import rotation_from_euler_xyz
from minegeo.kernels.chunks import PARALLEL_QUERY_ROWS, by_size
from minegeo.kernels.kdtree import (
    kd_nn_warm_parallel,
    kd_nn_warm_serial,
)
from minegeo.kernels.rigid import umeyama_from_moments
from minegeo.registration import _kernels as K
from minegeo.registration._kernels_gicp import gicp_fused_search, gicp_pairs_system
from minegeo.registration._kernels_loop import compact_matches
from minegeo.registration.estimation import RANK_TOL

__all__ = [
    "Matches", "NearestInGate", "GaussNewtonFactor", "PointToPointFactor",
    "PointToPlaneFactor", "GICPFactor", "GICPSystem", "GICPNearestInGate", "PointToLine2DFactor", "SE3Euler", "SE2Points", "Termination",
    "LoopOutcome", "run_loop", "solve_normal_equations", "euler6_to_transform", "rotation_angle", "rot2",
]


# ----------------------------------------------------------------------------- linear solve, Lie helpers


def solve_normal_equations(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve the Gauss-Newton system ``H x = -g`` (n x n, symmetric positive semi-definite).

    Returns ``(x, singular)``: ``numpy.linalg.solve`` when the smallest eigenvalue exceeds
    1e-12 of the largest; otherwise the minimum-norm step (pseudo-inverse on the eigenvectors
    above that threshold) and ``singular=True``; ``(0, True)`` when ``H`` has no positive
    eigenvalue (or is not finite).
    """
    ev, V = np.linalg.eigh(H)
    if not ev[-1] > 0.0:
        return np.zeros(H.shape[0]), True
    if ev[0] > 1e-12 * ev[-1]:
        return np.linalg.solve(H, -g), False
    inv = np.where(ev > 1e-12 * ev[-1], 1.0 / np.where(ev > 0, ev, 1.0), 0.0)
    return -(V @ (inv * (V.T @ g))), True


def euler6_to_transform(x: np.ndarray) -> np.ndarray:
    """Open3D's ``TransformVector6dToMatrix4d``: ``x = (α, β, γ, t)`` (rad, m) to the 4x4
    ``[[R_z(γ) R_y(β) R_x(α), t], [0, 1]]`` exactly (no small-angle matrix)."""
    T = np.eye(4)
    T[:3, :3] = rotation_from_euler_xyz(x[0], x[1], x[2])
    T[:3, 3] = x[3:6]
    return T


def rotation_angle(R: np.ndarray) -> float:
    """Rotation angle of the 3x3 ``R`` (rad) as ``atan2(|v|/2, (tr R - 1)/2)``, accurate for tiny angles."""
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(0.5 * np.linalg.norm(v), 0.5 * (np.trace(R) - 1.0)))


def rot2(theta_rad: float) -> np.ndarray:
    """Counter-clockwise 2x2 rotation matrix of ``theta_rad`` (rad)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s], [s, c]])


class SE3Euler:
    """SE(3) with Open3D's update: ``ΔT = euler6_to_transform(x)``, ``T ← ΔT T``, ``p ← ΔT p``.

    The pose is the 4x4 ``T_target_source``; the moved source points are updated in place of a
    recomputation (``P ← ΔT P``, as Open3D), so they carry the same rounding as Open3D's.
    """

    exp = staticmethod(euler6_to_transform)

    @staticmethod
    def identity() -> np.ndarray:
        return np.eye(4)

    @staticmethod
    def compose(delta: np.ndarray, pose: np.ndarray) -> np.ndarray:
        return delta @ pose

    @staticmethod
    def move(points: np.ndarray, pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return K.transform_points_kernel(points, delta)

    @staticmethod
    def step_below(delta: np.ndarray, translation_m: float, rotation_rad: float) -> bool:
        """``|Δt| < translation_m`` and ``angle(ΔR) < rotation_rad``."""
        return (float(np.linalg.norm(delta[:3, 3])) < translation_m
                and rotation_angle(delta[:3, :3]) < rotation_rad)


class SE2Points:
    """SE(2) of a 2-D scan: pose ``(R (2, 2), t (2,))`` = ``T_mine_scan``, increment
    ``x = (β, τ_x, τ_y)`` (rad, m): ``R ← R(β) R``, ``t ← R(β) t + τ``; the moved points are
    recomputed from the scan, ``q = s Rᵀ + t``."""

    def __init__(self, source: np.ndarray):
        self.source = source

    @staticmethod
    def exp(x: np.ndarray) -> np.ndarray:
        return x

    @staticmethod
    def compose(delta: np.ndarray, pose):
        R, t = pose
        Rb = rot2(delta[0])
        return Rb @ R, Rb @ t + delta[1:]

    def move(self, points, pose, delta) -> np.ndarray:
        R, t = pose
        return np.ascontiguousarray(self.source @ R.T + t)

    @staticmethod
    def step_below(delta: np.ndarray, translation_m: float, rotation_rad: float) -> bool:
        """``|β| < rotation_rad`` and ``|τ| < translation_m``."""
        return abs(delta[0]) < rotation_rad and np.hypot(delta[1], delta[2]) < translation_m


# ----------------------------------------------------------------------------- correspondences


@dataclass
class Matches:
    """Correspondences of the moved source points at one pose.

    Attributes
    ----------
    fitness : float
        Fraction of source points with a partner.
    rmse : float
        Euclidean inlier RMSE of the pairs (m, [Baek2022 Eq. 19]); 0 without pairs.
    corr : (k, 2) int64 ndarray
        ``(source index, target index)`` pairs in ascending source index.
    raw : (n,) int64 ndarray or None
        Partner per source point (the target size ``m`` = none), the warm start of the next search.
    extra : ndarray, GICPSystem or None
        Per-pair data of the search (MAST: signed point-to-line distances, m), or the GICP
        normal equations summed by :class:`GICPNearestInGate`.
    """

    fitness: float
    rmse: float
    corr: np.ndarray
    raw: np.ndarray | None = None
    extra: np.ndarray | None = None
    _pairs: tuple | None = field(default=None, repr=False)

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Contiguous ``(source indices, target indices)`` of the pairs (cached)."""
        if self._pairs is None:
            self._pairs = (np.ascontiguousarray(self.corr[:, 0]), np.ascontiguousarray(self.corr[:, 1]))
        return self._pairs


class NearestInGate:
    """Exact gated nearest neighbour (Open3D ``evaluate_registration``, oracle spec §8).

    For every moved source point the target point with the lexicographically smallest
    ``(sq, index)`` among those with ``sq < d²`` (``sq = dx*dx + dy*dy + dz*dz``). With a
    :func:`~minegeo.registration._kernels.kd_build` tree the search is warm-started from the
    previous partners (same answer, fewer nodes) and the pairs and the inlier sum come from one
    kernel; any other index (SciPy ``cKDTree``, pykdtree, ``NeighborIndex``) goes through
    :func:`minegeo.registration.evaluation.nearest_within`.

    Parameters
    ----------
    Q : (m, 3) ndarray
        Target points (target frame, m), C-contiguous float64.
    d : float
        Gate (m).
    tree : PackedKDTree, optional
        ``kd_build(Q, leaf)`` (:class:`~minegeo.kernels.kdtree.PackedKDTree`).
    index : optional
        Another search structure over ``Q`` (used when ``tree`` is None).
    parallel_rows : int
        Queries with at least this many rows use the ``prange`` driver (same results).
    """

    def __init__(self, Q: np.ndarray, d: float, tree=None, index=None, parallel_rows: int = PARALLEL_QUERY_ROWS):
        self.Q, self.d, self.tree, self.index, self.parallel_rows = Q, float(d), tree, index, int(parallel_rows)

    def __call__(self, P: np.ndarray, prev: Matches | None) -> Matches:
        if self.tree is None:
            from minegeo.registration.evaluation import _evaluate_transformed

            return Matches(*_evaluate_transformed(P, self.Q, self.index, self.d))
        n, m = P.shape[0], self.Q.shape[0]
        warm = prev.raw if prev is not None and prev.raw is not None else np.full(n, m, dtype=np.int64)
        idx = np.empty(n, dtype=np.int64)
        sq = np.empty(n)
        by_size(n, self.parallel_rows, kd_nn_warm_serial, kd_nn_warm_parallel)(P, self.Q, self.tree, self.d * self.d,
                                                                                warm, idx, sq)
        corr, total = compact_matches(idx, sq, m)
        k = corr.shape[0]
        if k == 0:
            return Matches(0.0, 0.0, corr, idx)
        return Matches(float(k / n), float(np.sqrt(total / k)), corr, idx)


# ----------------------------------------------------------------------------- factors


class GaussNewtonFactor(ABC):
    """Base of the Gauss-Newton factors: ``linearize`` gives ``(H, g, aux)``, then
    ``x = solve(H, g)`` (``H x = -g``) and the increment ``manifold.exp(x)``. Without pairs the
    increment is the identity (Open3D), unless ``identity_without_pairs`` is False. A factor is a
    subclass that writes ``linearize`` (abstract: the base class cannot be instantiated)."""

    manifold = SE3Euler
    identity_without_pairs = True
    solve = staticmethod(solve_normal_equations)

    @abstractmethod
    def linearize(self, P, pose, matches: Matches):
        """``(H, g, aux)``: the reduced normal equations of the current pairs."""

    def step(self, P, pose, matches: Matches):
        if self.identity_without_pairs and matches.corr.shape[0] == 0:
            return self.manifold.identity(), False, None
        H, g, aux = self.linearize(P, pose, matches)
        x, singular = self.solve(H, g)
        return self.manifold.exp(x), singular, aux


class PointToPointFactor:
    """Point-to-point ICP step in closed form (Umeyama/Kabsch on the pairs, [Baek2022 Eqs. 10-13];
    Open3D ``TransformationEstimationPointToPoint``); ``singular`` when the cross-covariance has
    rank < 2 (collinear pairs: the rotation about their line is arbitrary)."""

    manifold = SE3Euler

    def __init__(self, Q: np.ndarray):
        self.Q = Q

    def step(self, P, pose, matches: Matches):
        if matches.corr.shape[0] == 0:
            return np.eye(4), False, None
        si, ti = matches.pairs()
        _, mu_p, mu_q, W, var_p = K.weighted_moments_idx(P, self.Q, si, ti)
        dT, _, S = umeyama_from_moments(mu_p, mu_q, W, var_p, False)
        return dT, bool(S[0] <= 0.0 or S[1] <= RANK_TOL * S[0]), None


class PointToPlaneFactor(GaussNewtonFactor):
    """Point-to-plane ([Low2004]; Open3D §7): ``r = (p - q)·n``, ``J = [p × n, n]``; ``aux`` = ``Σ r²``."""

    def __init__(self, Q: np.ndarray, N: np.ndarray):
        self.Q, self.N = Q, N

    def linearize(self, P, pose, matches: Matches):
        si, ti = matches.pairs()
        return K.point_to_plane_system_idx(P, self.Q, self.N, si, ti)


class GICPFactor(GaussNewtonFactor):
    """Generalized-ICP ([Ren2019 Eqs. 4-6]; Segal 2009): ``d = p - q``, ``M = C_q + R C_p Rᵀ``,
    ``J = [-[p]×, I3]``, ``H = Σ Jᵀ M⁻¹ J``, ``g = Σ Jᵀ M⁻¹ d``; ``aux`` = ``Σ dᵀ M⁻¹ d`` (m²).
    ``Cs`` / ``Ct`` are the per-point covariances in their own clouds' frames.

    With :class:`GICPNearestInGate` the system is summed during the search (one pass) and
    carried in ``matches.extra`` (a :class:`GICPSystem`); ``linearize`` returns it when it was
    summed at the rotation of ``pose`` and sums the pairs again otherwise. ``next_R`` is the
    rotation of the pose the next search runs at: the initial pose's (set by the caller), then
    ``(ΔT T)`` of each step, as :class:`SE3Euler` composes it.
    """

    def __init__(self, Q: np.ndarray, Cs: np.ndarray, Ct: np.ndarray, R0: np.ndarray | None = None):
        self.Q, self.Cs, self.Ct = Q, Cs, Ct
        self.next_R = np.ascontiguousarray(np.eye(3) if R0 is None else R0[:3, :3])

    def linearize(self, P, pose, matches: Matches):
        R = np.ascontiguousarray(pose[:3, :3])
        fused = matches.extra
        if isinstance(fused, GICPSystem) and np.array_equal(fused.R, R):
            return fused.H, fused.g, fused.cost
        si, ti = matches.pairs()
        return gicp_pairs_system(P, self.Q, self.Cs, self.Ct, R, si, ti)

    def step(self, P, pose, matches: Matches):
        delta, singular, aux = super().step(P, pose, matches)
        self.next_R = np.ascontiguousarray(self.manifold.compose(delta, pose)[:3, :3])
        return delta, singular, aux

    def mean_cost(self, P, pose, matches: Matches) -> float:
        """Mean Mahalanobis cost of the pairs (m², inf without pairs)."""
        k = matches.corr.shape[0]
        return math.inf if k == 0 else float(self.linearize(P, pose, matches)[2]) / k


@dataclass
class GICPSystem:
    """The GICP normal equations of one search, summed at rotation ``R`` (3x3): ``H`` (6x6),
    ``g`` (6,), ``cost`` = ``Σ dᵀ M⁻¹ d`` (m²)."""

    R: np.ndarray
    H: np.ndarray
    g: np.ndarray
    cost: float


class GICPNearestInGate(NearestInGate):
    """:class:`NearestInGate` on a KD-tree that also sums the GICP system of its pairs in the same
    pass ([Ren2019 Eqs. 4-6]; :func:`gicp_fused_search`), at the rotation ``factor.next_R``.

    The pairs, fitness and RMSE are those of :class:`NearestInGate` bit for bit; the system is
    carried in ``Matches.extra`` as a :class:`GICPSystem` for :meth:`GICPFactor.linearize`.
    """

    def __init__(self, Q: np.ndarray, d: float, tree, factor: GICPFactor,
                 parallel_rows: int = PARALLEL_QUERY_ROWS, lists=None):
        super().__init__(Q, d, tree=tree, parallel_rows=parallel_rows)
        self.factor = factor
        self.lists = lists  # the target's kNN lists (nb, rk): gicp_fused_search's shortcut
        self._last = None  # (matches, points, r1, r2, moved) of the previous call

    def __call__(self, P: np.ndarray, prev: Matches | None) -> Matches:
        n, m = P.shape[0], self.Q.shape[0]
        last = self._last
        if prev is not None and last is not None and prev is last[0] and last[1].shape[0] == n:
            state, warm = last[1:], prev.raw
        else:
            state = (np.empty((0, 3)), np.empty(n), np.empty(n), np.zeros(n))
            warm = prev.raw if prev is not None and prev.raw is not None else np.full(n, m, dtype=np.int64)
        f = self.factor
        R = f.next_R
        idx, sq, H, g, cost = gicp_fused_search(P, self.Q, self.tree, self.d * self.d, warm, f.Cs, f.Ct, R,
                                                n >= self.parallel_rows, state, self.lists)
        corr, total = compact_matches(idx, sq, m)
        k = corr.shape[0]
        system = GICPSystem(R, H, g, cost)
        if k == 0:
            out = Matches(0.0, 0.0, corr, idx, system)
        else:
            out = Matches(float(k / n), float(np.sqrt(total / k)), corr, idx, system)
        self._last = (out, P, *state[1:])
        return out


class PointToLine2DFactor(GaussNewtonFactor):
    """2-D point-to-line ([Low2004] reduced to lines; Simela, second alignment step).

    ``r = (q - d)·n`` (the signed distance to the panel's line), ``J = [q_x n_y - q_y n_x,
    n_x, n_y]`` for ``x = (β, τ_x, τ_y)``; ``H = AᵀA``, ``g = -Aᵀb`` with ``b = -r``;
    ``aux = (pairs, RMS of r)``. Fewer than ``min_points`` pairs raise
    :class:`~minegeo.errors.TooFewPointsError`, a normal matrix whose column-scaled condition
    number exceeds 1e10 (all pairs on parallel lines) :class:`~minegeo.errors.DegenerateGeometryError`.
    """

    identity_without_pairs = False

    def __init__(self, manifold: SE2Points, normals: np.ndarray, gate_m: float, min_points: int):
        self.manifold, self.normals, self.gate_m, self.min_points = manifold, normals, gate_m, min_points

    def linearize(self, q, pose, matches: Matches):
        n_in = matches.corr.shape[0]
        if n_in < self.min_points:
            raise TooFewPointsError(
                f"ICP: only {n_in} scan point(s) lie within {self.gate_m:.3f} m of a beacon panel; "
                f"at least {self.min_points} are needed"
            )
        qi = q[matches.corr[:, 0]]
        ni = self.normals[matches.corr[:, 1]]
        A = np.column_stack([qi[:, 0] * ni[:, 1] - qi[:, 1] * ni[:, 0], ni[:, 0], ni[:, 1]])
        b = -matches.extra
        return A.T @ A, -(A.T @ b), (n_in, b)

    @staticmethod
    def solve(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, bool]:
        sc = 1.0 / np.sqrt(np.maximum(np.diag(H), 1e-300))
        if np.linalg.cond(H * sc[:, None] * sc[None, :]) > 1e10:
            raise DegenerateGeometryError(
                "ICP: the matched scan points lie on parallel lines, so the scanner position "
                "along them is undetermined (collinear control)"
            )
        return np.linalg.solve(H, -g), False

    def step(self, q, pose, matches: Matches):
        x, singular, (n_in, b) = super().step(q, pose, matches)
        return x, singular, (n_in, float(np.sqrt(np.mean(b * b))))


# ----------------------------------------------------------------------------- termination and the loop


@dataclass(frozen=True)
class Termination:
    """When :func:`run_loop` stops (each test off when its thresholds are None / False).

    Attributes
    ----------
    relative_fitness, relative_rmse : float or None
        Open3D's test: ``|Δfitness| < relative_fitness`` and ``|Δrmse| < relative_rmse`` (m).
    step_translation, step_rotation : float or None
        The last increment moved less than ``step_translation`` (m) and rotated less than
        ``step_rotation`` (rad).
    stop_on_cycle : bool
        The correspondence set equals the one of two evaluations before, and the last step
        changed it (a 2-cycle).
    cycle_keeps_lower_cost : bool
        On a 2-cycle return the state of lower ``factor.mean_cost`` of the two.
    evaluate_after_last_step : bool
        True (Open3D): every step is followed by a search, and all tests look at it. False
        (MAST): the step test is applied right after the step, the budget's last step is not
        followed by a search, and the cycle test is applied to each new search.
    """

    relative_fitness: float | None = None
    relative_rmse: float | None = None
    step_translation: float | None = None
    step_rotation: float | None = None
    stop_on_cycle: bool = False
    cycle_keeps_lower_cost: bool = False
    evaluate_after_last_step: bool = True

    def step_test(self, manifold, delta) -> bool:
        return self.step_translation is not None and manifold.step_below(
            delta, self.step_translation, self.step_rotation)

    def after_search(self, prev: Matches, cur: Matches, prev2: Matches | None, manifold, delta) -> str:
        """Name of the test that holds after the search that followed ``delta`` (``""``: none)."""
        if (self.relative_fitness is not None and abs(prev.fitness - cur.fitness) < self.relative_fitness
                and abs(prev.rmse - cur.rmse) < self.relative_rmse):
            return "fitness_rmse"
        if self.evaluate_after_last_step and self.step_test(manifold, delta):
            return "step"
        if (self.stop_on_cycle and prev2 is not None and np.array_equal(cur.corr, prev2.corr)
                and not np.array_equal(cur.corr, prev.corr)):
            return "cycle"
        return ""


@dataclass
class LoopOutcome:
    """What :func:`run_loop` ends with: the pose and moved points, the last matches, the history
    of ``(fitness, rmse)`` (initial search, then one per search), the number of steps, the
    stopping test (``reason``, ``""`` when the budget ran out), whether a step was singular, the
    increments in order, the factor's ``aux`` of the last step and the increment of a 2-cycle."""

    pose: object
    points: np.ndarray
    matches: Matches
    history: list
    iterations: int = 0
    reason: str = ""
    singular_step: bool = False
    steps: list = field(default_factory=list)
    last_aux: object = None
    cycle_delta: object = None

    @property
    def converged(self) -> bool:
        return bool(self.reason)


def run_loop(points, pose, search, factor, termination: Termination, max_iterations: int, timer) -> LoopOutcome:
    """Iterate search → factor step → update until a :class:`Termination` test holds.

    Parameters
    ----------
    points : ndarray
        Source points moved by ``pose`` (target frame).
    pose : object
        Initial pose in the representation of ``factor.manifold`` (``T_target_source``).
    search, factor, termination
        The pieces (see the module docstring).
    max_iterations : int
        Step budget (>= 0).
    timer : minegeo._provenance.StageTimer
        Receives the ``search`` and ``estimate`` times.

    Returns
    -------
    LoopOutcome
    """
    manifold = factor.manifold
    with timer("search"):
        cur = search(points, None)
    out = LoopOutcome(pose, points, cur, [(cur.fitness, cur.rmse)])
    prev = None
    for k in range(max_iterations):
        with timer("estimate"):
            delta, singular, out.last_aux = factor.step(points, pose, cur)
            out.singular_step |= singular
            before = (pose, points)
            pose = manifold.compose(delta, pose)
            points = manifold.move(points, pose, delta)
        out.iterations += 1
        out.steps.append(delta)
        if not termination.evaluate_after_last_step:
            if termination.step_test(manifold, delta):
                out.reason = "step"
                break
            if k == max_iterations - 1:
                break
        prev2, prev = prev, cur
        with timer("search"):
            cur = search(points, prev)
        out.history.append((cur.fitness, cur.rmse))
        out.reason = termination.after_search(prev, cur, prev2, manifold, delta)
        if out.reason == "cycle":
            out.cycle_delta = delta
            # the cycle state of lower mean cost, not whichever phase the iteration reached: the
            # choice is then independent of the frame (a rigid motion moves both states alike)
            if termination.cycle_keeps_lower_cost and (
                    factor.mean_cost(before[1], before[0], prev) < factor.mean_cost(points, pose, cur)):
                (pose, points), cur = before, prev
                out.history.append(out.history[-2])
        if out.reason:
            break
    out.pose, out.points, out.matches = pose, points, cur
    return out

