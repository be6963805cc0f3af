"""Robust kernels of the optimiser, applied to a factor's whitened residual norm ``s = sqrt(rᵀΩr)``.

Iteratively reweighted least squares [Nocedal2006 Sec. 10.3]: at each linearisation a factor's
information ``Ω`` is scaled by the weight ``w(s)``, and a trial step is judged by the robust cost
``½ Σ ρ(s)`` (``ρ(s) = s²`` without a kernel, so ``½ Σ ρ`` is the plain cost ``½ Σ rᵀΩr``):

* Huber: ``w = min(1, k/s)``, ``ρ = s²`` for ``s ≤ k`` else ``2ks − k²``;
* Cauchy: ``w = 1/(1 + (s/k)²)``, ``ρ = k² log(1 + s²/k²)``

``k`` is the kernel width in whitened units (1 = one standard deviation).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ROBUST", "quadratic_cost", "robust_cost", "robust_weights"]

#: the robust kernels offered
ROBUST = ("none", "huber", "cauchy")


def quadratic_cost(r: np.ndarray, info: np.ndarray) -> float:
    """``½ Σ_e r_eᵀ Ω_e r_e`` for residuals ``r`` (m, k) and information matrices ``info`` (m, k, k)."""
    return 0.5 * float(np.einsum("ei,eij,ej->", r, info, r))


def robust_weights(r: np.ndarray, info: np.ndarray, kernel: str, scale: float) -> np.ndarray:
    """IRLS weight ``w(s)`` (m,) of every factor; ones for ``kernel="none"``."""
    if kernel == "none":
        return np.ones(r.shape[0])
    s = np.sqrt(np.maximum(np.einsum("ei,eij,ej->e", r, info, r), 0.0))
    k = scale
    if kernel == "huber":
        return np.where(s <= k, 1.0, k / np.maximum(s, k))
    return 1.0 / (1.0 + (s / k) ** 2)


def robust_cost(r: np.ndarray, info: np.ndarray, kernel: str, scale: float) -> float:
    """``½ Σ ρ(s_e)``: :func:`quadratic_cost` for ``kernel="none"``."""
    if kernel == "none":
        return quadratic_cost(r, info)
    s2 = np.maximum(np.einsum("ei,eij,ej->e", r, info, r), 0.0)
    k = scale
    if kernel == "huber":
        s = np.sqrt(s2)
        rho = np.where(s <= k, s2, 2.0 * k * s - k * k)
    else:
        rho = k * k * np.log1p(s2 / (k * k))
    return 0.5 * float(rho.sum())
