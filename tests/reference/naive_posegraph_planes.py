"""Naive twin of the pose graph with plane landmarks: dense matrices, the total cost written out
(between-edges of :mod:`reference.naive_posegraph` plus the pose–plane edges of
:mod:`reference.naive_planes`), finite-difference gradients and Jacobians under the same
retractions (``T ← T·Exp(δ)``, ``π ← retract_plane(π, δ)``). Slow and obviously right; tiny graphs."""

from __future__ import annotations

import numpy as np
from reference import naive_planes as NPL
from reference import naive_posegraph as NP


def total_cost(poses, edges, Z, info_rt, planes, pedges, pmeas, pinfo):
    """``½ Σ rᵀΩr + ½ Σ eᵀΩe`` over the between- and pose–plane edges."""
    c = NP.cost(poses, edges, Z, info_rt)
    for k, (i, l) in enumerate(pedges):
        e = NPL.residual(poses[i], planes[l], pmeas[k])
        c += 0.5 * float(e @ pinfo[k] @ e)
    return c


def _columns(n_poses, n_planes, fixed):
    free = [v for v in range(n_poses) if v not in fixed]
    col = {("pose", v): 6 * k for k, v in enumerate(free)}
    col.update({("plane", l): 6 * len(free) + 3 * l for l in range(n_planes)})
    return col, 6 * len(free) + 3 * n_planes


def perturbed(poses, planes, delta, fixed):
    """Poses and planes moved by the stacked step ``delta`` (free poses 6 each, then planes 3 each)."""
    col, _ = _columns(len(poses), len(planes), fixed)
    P = [T @ NP.exp(delta[col[("pose", v)]:col[("pose", v)] + 6]) if ("pose", v) in col else T.copy()
         for v, T in enumerate(poses)]
    L = [NPL.retract_plane(pl, delta[col[("plane", l)]:col[("plane", l)] + 3]) for l, pl in enumerate(planes)]
    return P, L


def gradient_fd(poses, edges, Z, info_rt, planes, pedges, pmeas, pinfo, fixed=(0,), h=1e-6):
    """Central differences of :func:`total_cost` along every free coordinate."""
    _, n = _columns(len(poses), len(planes), fixed)
    g = np.zeros(n)
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        cp = total_cost(*_mix(perturbed(poses, planes, e, fixed), edges, Z, info_rt, pedges, pmeas, pinfo))
        cm = total_cost(*_mix(perturbed(poses, planes, -e, fixed), edges, Z, info_rt, pedges, pmeas, pinfo))
        g[k] = (cp - cm) / (2 * h)
    return g


def _mix(pl, edges, Z, info_rt, pedges, pmeas, pinfo):
    P, L = pl
    return P, edges, Z, info_rt, L, pedges, pmeas, pinfo


def normal_equations(poses, edges, Z, info_rt, planes, pedges, pmeas, pinfo, fixed=(0,)):
    """Dense Gauss–Newton ``H = JᵀΩJ`` and ``g = JᵀΩr`` from the stacked finite-difference Jacobian."""
    col, n = _columns(len(poses), len(planes), fixed)
    H, g = np.zeros((n, n)), np.zeros(n)
    for k, (i, j) in enumerate(edges):
        r = NP.residual(poses[i], poses[j], Z[k])
        Ji, Jj = NP.numeric_jacobians(poses[i], poses[j], Z[k])
        J = np.zeros((6, n))
        for v, Jv in ((i, Ji), (j, Jj)):
            if ("pose", v) in col:
                J[:, col[("pose", v)]:col[("pose", v)] + 6] += Jv
        H += J.T @ info_rt[k] @ J
        g += J.T @ info_rt[k] @ r
    for k, (i, l) in enumerate(pedges):
        r = NPL.residual(poses[i], planes[l], pmeas[k])
        Jp, Jl = NPL.numeric_jacobians(poses[i], planes[l], pmeas[k])
        J = np.zeros((3, n))
        if ("pose", i) in col:
            J[:, col[("pose", i)]:col[("pose", i)] + 6] = Jp
        J[:, col[("plane", l)]:col[("plane", l)] + 3] = Jl
        H += J.T @ pinfo[k] @ J
        g += J.T @ pinfo[k] @ r
    return H, g
