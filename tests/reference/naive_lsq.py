"""Naive NumPy twin of minegeo.survey.lsq: textbook formulas with explicit inverses, no scaling."""

from __future__ import annotations

import numpy as np


def naive_gauss_markov(A, l, W):
    """``l + v = A x``: returns x, v, sigma0², Qxx, Qvv, redundancy, w (σ0 = 1) for full W."""
    A = np.asarray(A, dtype=float)
    l = np.asarray(l, dtype=float)
    W = np.asarray(W, dtype=float)
    if W.ndim == 1:
        W = np.diag(W)
    N = A.T @ W @ A
    Qxx = np.linalg.inv(N)
    x = Qxx @ A.T @ W @ l
    v = A @ x - l
    r = A.shape[0] - A.shape[1]
    s02 = float(v @ W @ v) / r
    Qvv = np.linalg.inv(W) - A @ Qxx @ A.T
    red = np.diag(Qvv @ W)
    WQW = W @ Qvv @ W
    w = (W @ v) / np.sqrt(np.diag(WQW))
    return x, v, s02, Qxx, Qvv, red, w
