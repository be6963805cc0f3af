"""Numba kernels of :mod:`minegeo.mast` (contiguous float64/int64 arrays in, no checks).

The public functions in :mod:`minegeo.mast` validate their inputs and call these.
Segments are stored as rows ``[ax, ay, bx, by]`` (start and end vertex, metres).

All kernels are serial (``njit``): a 2D scan has ~10^3 returns and a beacon scene
~10^2 segments, so one call takes microseconds to a millisecond and thread start-up
of ``parallel=True`` costs more than it saves (measured 15 ms vs <1 ms per call on a
loaded 2-core machine). Monte Carlo studies parallelise over trials instead.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit


@njit
def _cast_rays(origin, directions, segments, max_range):
    """Exact 2D ray-segment intersection with occlusion (nearest hit wins).

    For ray ``o + t d`` (``t > 0``) and segment ``a + s (b - a)`` (``0 <= s <= 1``)
    ``t = ((a - o) x e) / (d x e)`` and ``s = ((a - o) x d) / (d x e)`` with
    ``e = b - a`` and ``x`` the 2D cross product. Returns, per ray, the range ``t``
    (NaN when nothing is hit within ``max_range``), the index of the segment hit
    (-1 for none) and the segment parameter ``s`` of the hit.
    """
    m = directions.shape[0]
    k = segments.shape[0]
    rng = np.full(m, np.nan)
    idx = np.full(m, -1, dtype=np.int64)
    spar = np.full(m, np.nan)
    for i in range(m):
        dx = directions[i, 0]
        dy = directions[i, 1]
        best = max_range
        bj = -1
        bs = np.nan
        for j in range(k):
            ax = segments[j, 0] - origin[0]
            ay = segments[j, 1] - origin[1]
            ex = segments[j, 2] - segments[j, 0]
            ey = segments[j, 3] - segments[j, 1]
            den = dx * ey - dy * ex
            if den == 0.0:
                continue
            t = (ax * ey - ay * ex) / den
            s = (ax * dy - ay * dx) / den
            if t > 0.0 and t <= best and s >= 0.0 and s <= 1.0:
                best = t
                bj = j
                bs = s
        if bj >= 0:
            rng[i] = best
            idx[i] = bj
            spar[i] = bs
    return rng, idx, spar


@njit
def _nearest_segment(points, segments, margin):
    """Nearest segment to each point, counting only perpendicular projections.

    A point is compared with segment ``j`` only if its projection falls on the
    segment at least ``margin`` metres from either end (points beyond a panel's
    edge, e.g. on the wall beside a beacon, are not attributed to it). Returns the
    absolute perpendicular distance (inf if no segment qualifies), the segment
    index (-1) and the signed distance along the segment's left normal.
    """
    n = points.shape[0]
    k = segments.shape[0]
    dist = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int64)
    sd = np.full(n, np.nan)
    for i in range(n):
        px = points[i, 0]
        py = points[i, 1]
        for j in range(k):
            ex = segments[j, 2] - segments[j, 0]
            ey = segments[j, 3] - segments[j, 1]
            L = np.sqrt(ex * ex + ey * ey)
            ux = ex / L
            uy = ey / L
            qx = px - segments[j, 0]
            qy = py - segments[j, 1]
            along = qx * ux + qy * uy
            if along < margin or along > L - margin:
                continue
            d = -qx * uy + qy * ux
            if abs(d) < dist[i]:
                dist[i] = abs(d)
                idx[i] = j
                sd[i] = d
    return dist, idx, sd


@njit
def _sse_range(P, i, j):
    """Orthogonal-regression (PCA) sum of squared residuals of points i..j (inclusive).

    ``P`` holds prefix sums ``[n, Sx, Sy, Sxx, Sxy, Syy]``; the SSE is
    ``n * lambda_min`` of the 2x2 covariance.
    """
    n = P[j + 1, 0] - P[i, 0]
    sx = P[j + 1, 1] - P[i, 1]
    sy = P[j + 1, 2] - P[i, 2]
    sxx = P[j + 1, 3] - P[i, 3]
    sxy = P[j + 1, 4] - P[i, 4]
    syy = P[j + 1, 5] - P[i, 5]
    mx = sx / n
    my = sy / n
    cxx = sxx / n - mx * mx
    cxy = sxy / n - mx * my
    cyy = syy / n - my * my
    tr = cxx + cyy
    det = cxx * cyy - cxy * cxy
    disc = tr * tr / 4.0 - det
    if disc < 0.0:
        disc = 0.0
    lam = tr / 2.0 - np.sqrt(disc)
    if lam < 0.0:
        lam = 0.0
    return n * lam


@njit
def _line_of(P, i, j, out):
    """PCA line of points i..j: writes ``[cx, cy, ux, uy]`` (centroid, unit direction)."""
    n = P[j + 1, 0] - P[i, 0]
    mx = (P[j + 1, 1] - P[i, 1]) / n
    my = (P[j + 1, 2] - P[i, 2]) / n
    cxx = (P[j + 1, 3] - P[i, 3]) / n - mx * mx
    cxy = (P[j + 1, 4] - P[i, 4]) / n - mx * my
    cyy = (P[j + 1, 5] - P[i, 5]) / n - my * my
    ang = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    out[0] = mx
    out[1] = my
    out[2] = np.cos(ang)
    out[3] = np.sin(ang)


@njit
def _grow_segments(xy, tol, gap_max, min_points, n_confirm, refine_window):
    """Sequential PCA line growing over scan-ordered points (Simela et al., Fig. 2).

    A segment starts with two consecutive points and grows point by point while the
    next point ``j`` lies within ``tol[j]`` (m) of the PCA line of the points so far
    and is closer than ``gap_max[j]`` (m) to its predecessor. A break is confirmed when
    ``n_confirm`` consecutive points all lie off the line (an isolated spike is
    absorbed). The break index is then refined within ``refine_window`` points to
    minimise the summed orthogonal SSE of the two lines; the next segment starts at
    that node point (consecutive lines share a common node, as in the paper).

    Returns an ``(m, 2)`` int64 array of inclusive ``[start, end]`` point indices of
    segments with at least ``min_points`` points.
    """
    n = xy.shape[0]
    out = np.empty((max(n, 1), 2), dtype=np.int64)
    nseg = 0
    if n < 2:
        return out[:0]
    P = _prefix_sums(xy)
    line = np.empty(4)
    i0 = 0
    while i0 < n - 1:
        gx = xy[i0 + 1, 0] - xy[i0, 0]
        gy = xy[i0 + 1, 1] - xy[i0, 1]
        if np.sqrt(gx * gx + gy * gy) > gap_max[i0 + 1]:
            i0 += 1
            continue
        last = i0 + 1
        j = i0 + 2
        next_start = -1
        while j < n:
            gx = xy[j, 0] - xy[j - 1, 0]
            gy = xy[j, 1] - xy[j - 1, 1]
            if np.sqrt(gx * gx + gy * gy) > gap_max[j]:
                next_start = j  # gap: no shared node
                break
            _line_of(P, i0, last, line)
            d = abs(-(xy[j, 0] - line[0]) * line[3] + (xy[j, 1] - line[1]) * line[2])
            if d <= tol[j]:
                last = j
                j += 1
                continue
            # candidate break at j: confirm with the following points
            confirmed = True
            for q in range(j + 1, min(j + n_confirm, n)):
                gx = xy[q, 0] - xy[q - 1, 0]
                gy = xy[q, 1] - xy[q - 1, 1]
                if np.sqrt(gx * gx + gy * gy) > gap_max[q]:
                    break
                dq = abs(-(xy[q, 0] - line[0]) * line[3] + (xy[q, 1] - line[1]) * line[2])
                if dq <= tol[q]:
                    confirmed = False
                    break
            if not confirmed:
                last = j  # isolated spike, keep contiguity
                j += 1
                continue
            # refine the node point m in [j - refine_window, j - 1]
            hi = min(j + n_confirm - 1, n - 1)
            lo = max(i0 + 1, j - refine_window)
            best = np.inf
            bm = j - 1
            for m in range(lo, j):
                if hi - m < 1:
                    continue
                e = _sse_range(P, i0, m) + _sse_range(P, m, hi)
                if e < best:
                    best = e
                    bm = m
            last = bm
            next_start = -2 - bm  # shared node encoded
            break
        if last - i0 + 1 >= min_points:
            out[nseg, 0] = i0
            out[nseg, 1] = last
            nseg += 1
        if next_start == -1:
            if j >= n:
                break
            i0 = j
        elif next_start >= 0:
            i0 = next_start
        else:
            i0 = -2 - next_start  # >= old i0 + 1, so the loop always advances
    return out[:nseg]


@njit
def _prefix_sums(xy):
    """Prefix sums ``[n, Sx, Sy, Sxx, Sxy, Syy]`` (row i = sums over points < i)."""
    n = xy.shape[0]
    P = np.zeros((n + 1, 6))
    for i in range(n):
        x = xy[i, 0]
        y = xy[i, 1]
        P[i + 1, 0] = P[i, 0] + 1.0
        P[i + 1, 1] = P[i, 1] + x
        P[i + 1, 2] = P[i, 2] + y
        P[i + 1, 3] = P[i, 3] + x * x
        P[i + 1, 4] = P[i, 4] + x * y
        P[i + 1, 5] = P[i, 5] + y * y
    return P


@njit
def _split_segments(xy, segs, sigma2, gain_threshold, min_points):
    """Split step of split-and-merge applied to the grown lines (recursive, stack based).

    A line ``i..j`` is split at the node ``m`` (shared by both halves) that minimises
    ``SSE(i..m) + SSE(m..j)`` if the SSE gain exceeds ``gain_threshold * sigma2``
    (``sigma2``: point variance of the line, m^2) and both halves keep
    ``min_points`` points. This catches corners the sequential growth absorbed while
    its line was still short (few, noisy points). Returns inclusive ``[start, end]``
    rows in scan order.
    """
    P = _prefix_sums(xy)
    out = np.empty((xy.shape[0] + segs.shape[0], 2), dtype=np.int64)
    nout = 0
    stack = np.empty((xy.shape[0] + segs.shape[0], 2), dtype=np.int64)
    for s in range(segs.shape[0]):
        stack[0, 0] = segs[s, 0]
        stack[0, 1] = segs[s, 1]
        ns = 1
        while ns > 0:
            ns -= 1
            i = stack[ns, 0]
            j = stack[ns, 1]
            one = _sse_range(P, i, j)
            best = np.inf
            bm = -1
            for m in range(i + min_points - 1, j - min_points + 2):
                e = _sse_range(P, i, m) + _sse_range(P, m, j)
                if e < best:
                    best = e
                    bm = m
            if bm >= 0 and one - best > gain_threshold * sigma2[s]:
                # push right half first so the left half is processed first
                stack[ns, 0] = bm
                stack[ns, 1] = j
                ns += 1
                stack[ns, 0] = i
                stack[ns, 1] = bm
                ns += 1
            else:
                out[nout, 0] = i
                out[nout, 1] = j
                nout += 1
    return out[:nout]
