"""minegeo.optim: the one nonlinear least-squares optimiser of minegeo.

* :mod:`minegeo.optim.lm`: the Levenberg–Marquardt loop (damping, step acceptance, the stopping
  rule, the check that gates "converged") and its parameters :class:`LMParams`;
* :mod:`minegeo.optim.blocks`: the normal equations, by d×d blocks (block Cholesky in a
  fill-reducing order) or general (sparse LU);
* :mod:`minegeo.optim.robust`: robust kernels (Huber, Cauchy) by iterative reweighting;
* :mod:`minegeo.optim.factors`: variables (poses on SE(3)/SE(2), optionally with a vector part)
  and factor groups (between, prior) with residuals and analytic Jacobians;
* :mod:`minegeo.optim.imu`: IMU preintegration [Forster2017] and the IMU and bias factors.

Pose graphs (:mod:`minegeo.slam.posegraph`) and the intersection factor graph
(:mod:`minegeo.semantic.factors`) are problems solved by the same loop.
"""

from minegeo.optim.blocks import SINGULAR_PIVOT, BlockSystem, SingularSystemError, SparseSystem
from minegeo.optim.factors import (
    BetweenFactors,
    FactorGroup,
    FactorProblem,
    PriorFactors,
    Values,
    between_residuals,
    between_terms,
)
from minegeo.optim.lm import (
    ROTATION_TOL,
    LMOutcome,
    LMParams,
    LMStatus,
    accept_step,
    check_result,
    levenberg_marquardt,
    remaining_decrease,
)
from minegeo.optim.robust import ROBUST, quadratic_cost, robust_cost, robust_weights

__all__ = [
    "ROBUST", "ROTATION_TOL", "SINGULAR_PIVOT", "BetweenFactors", "BlockSystem", "FactorGroup", "FactorProblem",
    "LMOutcome", "LMParams", "LMStatus", "PriorFactors", "SingularSystemError", "SparseSystem", "Values", "accept_step",
    "between_residuals", "between_terms", "check_result", "levenberg_marquardt", "quadratic_cost",
    "remaining_decrease", "robust_cost", "robust_weights",
]
