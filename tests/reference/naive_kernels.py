"""Naive twins of :mod:`minegeo.kernels` (plain NumPy/Python, obviously correct, slow).

Each function states the mathematics directly (brute force, dense matrix exponential, LAPACK),
with no attention to speed or to the kernels' operation order; ``tests/kernels`` compares the
kernels against them.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm, logm


# ----------------------------------------------------------------------------- hash table
def naive_table(keys):
    """``{key: row}`` of distinct keys (what the open-addressing table must answer)."""
    return {int(k): i for i, k in enumerate(keys)}


# ----------------------------------------------------------------------------- search
def naive_knn(Q, P, k):
    """Per row of ``P``: the ``k`` nearest rows of ``Q`` sorted by (squared distance, index)."""
    Q = np.asarray(Q, dtype=np.float64)
    idx = np.full((len(P), k), len(Q), dtype=np.int64)
    sq = np.full((len(P), k), np.inf)
    for i, p in enumerate(np.asarray(P, dtype=np.float64)):
        d = Q - p
        s = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        o = np.lexsort((np.arange(len(Q)), s))[:k]
        idx[i, : o.size] = o
        sq[i, : o.size] = s[o]
    return idx, sq


def naive_kd_build(Q, leaf):
    """The tree of :func:`minegeo.kernels.kdtree.kd_build`, in plain Python: the same sliding-midpoint
    rule (widest box side, split at its middle, ``[s, mid) < sv <= [mid, e)``), the same in-place
    two-ended partition, depth-first node numbering (children numbered when their parent splits)
    and the exact bounding box of every node's points (first of equal extremes kept, as ``<``)."""
    m = len(Q)
    idx = list(range(m))
    Qs = [[float(v) for v in row] for row in np.asarray(Q, dtype=np.float64)]

    def box_of(rows):
        lo = [np.inf, np.inf, np.inf]
        hi = [-np.inf, -np.inf, -np.inf]
        for row in rows:
            for c in range(3):
                if row[c] < lo[c]:
                    lo[c] = row[c]
                if row[c] > hi[c]:
                    hi[c] = row[c]
        return lo + hi

    nodes = [[0, m, -1, 0.0, -1, -1, 0, box_of(Qs)]]  # start, end, dim, split, left, right, level, box
    stack, depth = [0], 0
    while stack:
        nd = stack.pop()
        s, e, _, _, _, _, lev, box = nodes[nd]
        depth = max(depth, lev)
        if e - s <= leaf:
            continue
        k = 0
        for c in (1, 2):
            if box[3 + c] - box[c] > box[3 + k] - box[k]:
                k = c
        if not box[3 + k] - box[k] > 0.0:
            continue
        sv = 0.5 * (box[k] + box[3 + k])
        lows, highs = [], []
        i, j = s, e - 1
        while i <= j:
            if Qs[i][k] < sv:
                lows.append(Qs[i])
                i += 1
            else:
                highs.append(Qs[i])
                idx[i], idx[j] = idx[j], idx[i]
                Qs[i], Qs[j] = Qs[j], Qs[i]
                j -= 1
        if i == s or i == e:
            continue
        lc = len(nodes)
        nodes[nd][2:6] = [k, sv, lc, lc + 1]
        nodes.append([s, i, -1, 0.0, -1, -1, lev + 1, box_of(lows)])
        nodes.append([i, e, -1, 0.0, -1, -1, lev + 1, box_of(highs)])
        stack += [lc, lc + 1]
    col = list(zip(*nodes, strict=True))
    ints = [np.array(col[c], dtype=np.int64) for c in (0, 1, 2)]
    return (np.array(idx, dtype=np.int64), np.array(Qs, dtype=np.float64).reshape(m, 3), *ints,
            np.array(col[3], dtype=np.float64), np.array(col[4], dtype=np.int64), np.array(col[5], dtype=np.int64),
            depth)


def naive_gated_nn(Q, P, d2):
    """Nearest row of ``Q`` with ``sq < d2`` per row of ``P`` (lowest index on ties), ``len(Q)``/inf if none."""
    idx, sq = naive_knn(Q, P, 1)
    idx, sq = idx[:, 0], sq[:, 0]
    none = ~(sq < d2)
    idx[none] = len(Q)
    sq[none] = np.inf
    return idx, sq


def naive_radius_count(Q, P, r):
    """Number of rows of ``Q`` with squared distance ``< r²`` per row of ``P``."""
    Q = np.asarray(Q, dtype=np.float64)
    return np.array([int(np.count_nonzero(((Q - p) ** 2).sum(axis=1) < r * r)) for p in P], dtype=np.int64)


# ----------------------------------------------------------------------------- eigen / PCA
def naive_eigh3(C):
    """Ascending eigenvalues and eigenvectors (columns) of a symmetric 3x3 matrix (LAPACK)."""
    return np.linalg.eigh(np.asarray(C, dtype=np.float64))


def naive_pca(points):
    """``(normal, eigenvalues ascending)`` of the centred covariance ``Σ (p - p̄)(p - p̄)ᵀ / n``."""
    X = np.asarray(points, dtype=np.float64)
    X = X - X.mean(axis=0)
    w, V = np.linalg.eigh(X.T @ X / len(X))
    return V[:, 0], w


# ----------------------------------------------------------------------------- rigid fits
def naive_similarity(P, Q, with_scale=False):
    """Least-squares ``Q ≈ c R P + t`` by the textbook SVD recipe; returns ``(T 4x4, c)``."""
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    A, B = P - mp, Q - mq
    U, S, Vt = np.linalg.svd(B.T @ A / len(P))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    c = float(np.trace(np.diag(S) @ D) / ((A * A).sum() / len(P))) if with_scale else 1.0
    T = np.eye(4)
    T[:3, :3] = c * R
    T[:3, 3] = mq - c * R @ mp
    return T, c


def naive_yaw_fit(P, Q):
    """Least-squares yaw + translation by a dense scan of θ refined with golden-section search."""
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)

    def cost(th):
        c, s = np.cos(th), np.sin(th)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        X = P @ R.T
        t = (Q - X).mean(axis=0)
        return float(((X + t - Q) ** 2).sum()), t

    ths = np.linspace(-np.pi, np.pi, 3601)
    th0 = ths[int(np.argmin([cost(t)[0] for t in ths]))]
    a, b = th0 - 2e-3, th0 + 2e-3
    g = (np.sqrt(5) - 1) / 2
    for _ in range(100):
        c1, c2 = b - g * (b - a), a + g * (b - a)
        if cost(c1)[0] < cost(c2)[0]:
            b = c2
        else:
            a = c1
    th = 0.5 * (a + b)
    return th, cost(th)[1]


# ----------------------------------------------------------------------------- Lie groups
def naive_hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def naive_se3_hat(xi):
    """4x4 twist matrix of ``ξ = (φ, ρ)`` (rotation first)."""
    X = np.zeros((4, 4))
    X[:3, :3] = naive_hat(xi[:3])
    X[:3, 3] = xi[3:6]
    return X


def naive_so3_exp(w):
    return expm(naive_hat(np.asarray(w, dtype=np.float64)))


def naive_se3_exp(xi):
    return expm(naive_se3_hat(np.asarray(xi, dtype=np.float64)))


def naive_se3_log(T):
    L = np.real(logm(np.asarray(T, dtype=np.float64)))
    return np.r_[L[2, 1], L[0, 2], L[1, 0], L[:3, 3]]


def naive_se2_exp(xi):
    X = np.array([[0.0, -xi[0], xi[1]], [xi[0], 0.0, xi[2]], [0.0, 0.0, 0.0]])
    return expm(X)


def naive_left_jacobian(exp, log, x, h=1e-6):
    """Central finite differences of ``δ ↦ log(exp(x + δ) exp(x)⁻¹)`` at 0 (the left Jacobian)."""
    x = np.asarray(x, dtype=np.float64)
    E0inv = np.linalg.inv(exp(x))
    J = np.empty((x.size, x.size))
    for j in range(x.size):
        e = np.zeros(x.size)
        e[j] = h
        J[:, j] = (log(exp(x + e) @ E0inv) - log(exp(x - e) @ E0inv)) / (2 * h)
    return J
