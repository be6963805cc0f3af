"""A problem whose every variable is held: the optimiser returns the start, checked, as converged
(nothing can move), instead of failing to build its block pattern."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from minegeo.optim.factors import BetweenFactors, FactorProblem, Values
from minegeo.optim.lm import LMParams, levenberg_marquardt


def _pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_every_variable_held_returns_the_start_as_converged():
    P = np.stack([np.eye(4), _pose([0.1, 0.0, 0.0], [1.0, 0.0, 0.0])])
    Z = _pose([0.0, 0.0, 0.0], [1.1, 0.0, 0.0])[None]
    g = BetweenFactors(np.array([[0, 1]]), Z, np.eye(6)[None])
    prob = FactorProblem(2, 6, [g], held=[0, 1], params=LMParams())
    out = levenberg_marquardt(prob, Values(P), LMParams())
    assert out.status == "converged" and "held" in out.reason
    assert np.array_equal(out.values.poses, P)
    # the cost of the one edge, by hand: E = Z^-1 P0^-1 P1 = (rotation 0.1 rad about x, translation
    # 1 - 1.1 = -0.1 m along x); its SE(3) log has omega = (0.1, 0, 0) and, the translation lying on the
    # rotation axis, rho = (-0.1, 0, 0): cost 1/2 (0.1^2 + 0.1^2) = 0.01
    assert abs(out.cost_final - 0.01) < 1e-12 and out.cost_final == out.cost_initial
