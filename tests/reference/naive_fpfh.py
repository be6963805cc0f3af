"""Naive loop-based FPFH (Rusu 2009; Open3D semantics) used as a twin of the Numba kernels."""

from __future__ import annotations

import math

import numpy as np


def naive_neighborhoods(points, radius, max_nn):
    """Brute-force hybrid search: <= max_nn nearest points strictly within radius, self included."""
    pts = np.asarray(points, dtype=np.float64)
    out = []
    for i in range(pts.shape[0]):
        d2 = ((pts - pts[i]) ** 2).sum(axis=1)
        order = np.lexsort((np.arange(pts.shape[0]), d2))[:max_nn]
        order = order[d2[order] < radius * radius]
        out.append((order, d2[order]))
    return out


def naive_pair_features(p1, n1, p2, n2):
    d = p2 - p1
    f4 = math.sqrt(float(d @ d))
    if f4 == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    a1 = float(n1 @ d) / f4
    a2 = float(n2 @ d) / f4
    if abs(a1) < abs(a2):
        u, m, d, f3 = n2, n1, -d, -a2
    else:
        u, m, f3 = n1, n2, a1
    v = np.cross(d, u)
    vn = math.sqrt(float(v @ v))
    if vn == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    v = v / vn
    w = np.cross(u, v)
    return math.atan2(float(w @ m), float(u @ m)), float(v @ m), f3, f4


def _bin(x):
    return min(max(int(math.floor(x)), 0), 10)


def naive_fpfh(points, normals, neighborhoods, weight="open3d"):
    """FPFH of every point from explicit neighbourhoods [(indices, sq_distances), ...]."""
    pts = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    n = pts.shape[0]
    spfh = np.zeros((n, 33))
    for i, (idx, _) in enumerate(neighborhoods):
        if len(idx) <= 1:
            continue
        inc = 100.0 / (len(idx) - 1)
        for j in idx[1:]:
            f1, f2, f3, _ = naive_pair_features(pts[i], nrm[i], pts[j], nrm[j])
            spfh[i, _bin(11 * (f1 + math.pi) / (2 * math.pi))] += inc
            spfh[i, 11 + _bin(11 * (f2 + 1.0) * 0.5)] += inc
            spfh[i, 22 + _bin(11 * (f3 + 1.0) * 0.5)] += inc
    out = np.zeros((n, 33))
    for i, (idx, d2) in enumerate(neighborhoods):
        if len(idx) <= 1:
            continue
        acc = np.zeros(33)
        for j, s in zip(idx[1:], d2[1:], strict=True):
            if s == 0.0:
                continue
            w = s if weight == "open3d" else math.sqrt(s)
            acc += spfh[j] / w
        for b in range(3):
            tot = acc[11 * b : 11 * b + 11].sum()
            if tot != 0.0:
                acc[11 * b : 11 * b + 11] *= 100.0 / tot
        out[i] = acc + spfh[i]
    return out, spfh
