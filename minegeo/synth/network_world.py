"""Exact ray casting against a drift network's surfaces (:class:`NetworkWorld`), the world a simulated sensor scans.

The free space is the union of vertical capsules (half the drift width around each drift's segment)
from the floor z = 0 to the roof of the nearest node; the Numba kernels (``_cast_network`` and its
helpers) give each ray the first of its wall exit, floor and roof hits, moved onto the rough rock
(:func:`~minegeo.synth.network.roughness_field`) when the network has roughness. Lengths in metres;
rays and hits in the network's map frame (z up, floor z = 0).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.errors import InputError
from minegeo.synth.network import surface_offset


# ---------------------------------------------------------------------------------------- ray casting
@njit
def _linear_in(alpha, beta, lo, hi):
    """Interval of t with lo <= alpha + beta t <= hi (empty: t0 > t1)."""
    if abs(beta) < 1e-15:
        if lo <= alpha <= hi:
            return -np.inf, np.inf
        return np.inf, -np.inf
    a, b = (lo - alpha) / beta, (hi - alpha) / beta
    return (a, b) if a < b else (b, a)


@njit
def _disc_interval(ox, oy, dx, dy, cx, cy, r):
    """Interval of t with |o + t d - c| <= r (2-D; empty: t0 > t1)."""
    a = dx * dx + dy * dy
    b = 2.0 * ((ox - cx) * dx + (oy - cy) * dy)
    c = (ox - cx) ** 2 + (oy - cy) ** 2 - r * r
    disc = b * b - 4.0 * a * c
    if disc < 0.0 or a < 1e-24:
        return np.inf, -np.inf
    s = np.sqrt(disc)
    return (-b - s) / (2.0 * a), (-b + s) / (2.0 * a)


@njit
def _capsule_interval(ox, oy, dx, dy, ax, ay, bx, by, r):
    """Interval of t where the 2-D line o + t d lies in the capsule (segment a-b, radius r): a convex set."""
    ux, uy = bx - ax, by - ay
    L2 = max(ux * ux + uy * uy, 1e-24)
    L = np.sqrt(L2)
    nx, ny = -uy / L, ux / L
    p0, p1 = _linear_in(((ox - ax) * ux + (oy - ay) * uy) / L2, (dx * ux + dy * uy) / L2, 0.0, 1.0)
    q0, q1 = _linear_in((ox - ax) * nx + (oy - ay) * ny, dx * nx + dy * ny, -r, r)
    lo, hi = max(p0, q0), min(p1, q1)
    for c in range(2):
        cx, cy = (ax, ay) if c == 0 else (bx, by)
        d0, d1 = _disc_interval(ox, oy, dx, dy, cx, cy, r)
        if d0 <= d1:
            if lo > hi:
                lo, hi = d0, d1
            else:
                lo, hi = min(lo, d0), max(hi, d1)
    return lo, hi


@njit
def _wall_exit(o, d, A, B, rad):
    """Ray parameter where the ray leaves the union of capsules (inf: never; NaN: starts outside)."""
    m = A.shape[0]
    t0 = np.empty(m)
    t1 = np.empty(m)
    inside = False
    for e in range(m):
        t0[e], t1[e] = _capsule_interval(o[0], o[1], d[0], d[1], A[e, 0], A[e, 1], B[e, 0], B[e, 1], rad[e])
        if t0[e] <= 0.0 <= t1[e]:
            inside = True
    if not inside:
        return np.nan
    cur = 0.0
    changed = True
    while changed:
        changed = False
        for e in range(m):
            if t0[e] <= cur + 1e-9 and t1[e] > cur + 1e-12:
                cur = t1[e]
                changed = True
    return cur


@njit
def _roof_hit(o, d, nodes, heights, t_limit):
    """First ray parameter where the ray meets a roof (Voronoi cells of the nodes) before ``t_limit``."""
    n = nodes.shape[0]
    a = np.empty(n)
    b = np.empty(n)
    for j in range(n):
        rx, ry = o[0] - nodes[j, 0], o[1] - nodes[j, 1]
        a[j] = rx * rx + ry * ry
        b[j] = 2.0 * (d[0] * rx + d[1] * ry)
    i = int(np.argmin(a))
    t_cur = 0.0
    for _ in range(n + 1):
        t_next, j_next = np.inf, -1
        for j in range(n):
            if b[j] < b[i] - 1e-15:
                ts = (a[j] - a[i]) / (b[i] - b[j])
                if ts >= t_cur and ts < t_next:
                    t_next, j_next = ts, j
        z = o[2] + t_cur * d[2]
        if t_cur > 0.0 and z >= heights[i]:
            return t_cur                              # a step face between roofs of different height
        if d[2] > 0.0:
            tr = (heights[i] - o[2]) / d[2]
            if tr < t_next:
                return tr
        if j_next < 0 or t_next > t_limit:
            return np.inf
        t_cur, i = t_next, j_next
    return np.inf


@njit
def _wall_normal(p, A, B, rad):
    """Outward (into the rock) horizontal unit normal at a wall point ``p`` of the union of capsules:
    from the axis of the capsule whose boundary ``p`` lies on (the smallest |distance - radius|)."""
    best, nx, ny = np.inf, 0.0, 0.0
    for e in range(A.shape[0]):
        dx, dy = B[e, 0] - A[e, 0], B[e, 1] - A[e, 1]
        L2 = max(dx * dx + dy * dy, 1e-12)
        t = min(max(((p[0] - A[e, 0]) * dx + (p[1] - A[e, 1]) * dy) / L2, 0.0), 1.0)
        rx, ry = p[0] - (A[e, 0] + t * dx), p[1] - (A[e, 1] + t * dy)
        r = np.sqrt(rx * rx + ry * ry)
        if abs(r - rad[e]) < best and r > 1e-9:
            best, nx, ny = abs(r - rad[e]), rx / r, ry / r
    return nx, ny


@njit
def _rough_t(o, d, t, nx, ny, nz, freq, amp, phase):
    """Ray parameter of the rough rock near the smooth hit ``o + t d`` with outward normal n: the
    surface lies h(q) along n from the plane of the hit (:func:`~minegeo.synth.network.roughness_field`),
    so ``t' = t + h(o + t' d) / (d . n)``, solved by fixed-point iteration (4 steps; the field's slope
    is small). Grazing rays are limited to ``d . n >= 0.2``."""
    dn = max(d[0] * nx + d[1] * ny + d[2] * nz, 0.2)
    tt = t
    for _ in range(4):
        tt = t + surface_offset(o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2], freq, amp, phase) / dn
    return tt


@njit_parallel
def _cast_network(O, D, A, B, rad, nodes, heights, max_range, freq, amp, phase, out):
    rough = amp.shape[0] > 0
    for k in prange(O.shape[0]):
        o, d = O[k], D[k]
        tw = _wall_exit(o, d, A, B, rad)
        if np.isnan(tw) or o[2] <= 0.0:
            out[k] = np.nan
            continue
        tf = -o[2] / d[2] if d[2] < 0.0 else np.inf
        lim = min(tw, tf, max_range)
        tr = _roof_hit(o, d, nodes, heights, lim)
        t = min(tw, tf, tr)
        if rough and np.isfinite(t):
            if t == tf:
                t = _rough_t(o, d, t, 0.0, 0.0, -1.0, freq, amp, phase)
            elif t == tw:
                p = o + t * d
                nx, ny = _wall_normal(p, A, B, rad)
                t = _rough_t(o, d, t, nx, ny, 0.0, freq, amp, phase)
            elif d[2] > 0.0:
                # a flat roof (z = its node's height); a step face between two roofs is left smooth
                z = o[2] + t * d[2]
                j = 0
                best = np.inf
                for i in range(nodes.shape[0]):
                    q = (o[0] + t * d[0] - nodes[i, 0]) ** 2 + (o[1] + t * d[1] - nodes[i, 1]) ** 2
                    if q < best:
                        best, j = q, i
                if abs(z - heights[j]) < 1e-9:
                    t = _rough_t(o, d, t, 0.0, 0.0, 1.0, freq, amp, phase)
        out[k] = t if t <= max_range else np.nan


class NetworkWorld:
    """A :class:`DriftNetwork` as a world for :func:`~minegeo.synth.sensors.simulate_scan` (``cast`` only).

    The free space is the union of vertical capsules (``width / 2`` around each drift's segment), from
    the floor z = 0 to the roof of the nearest node (``node_heights``); rays are cast exactly against
    these surfaces, including the vertical step between two roofs of different height. A network
    with ``roughness_m > 0`` has rough rock: floor, walls and flat roofs are displaced along their
    outward normal by the network's :func:`~minegeo.synth.network.roughness_field` (the offsets
    :func:`~minegeo.synth.network.network_cloud` applies to the prior map), and each ray meets that
    surface near its smooth hit (:func:`_rough_t`); step faces between roofs stay smooth.

    Parameters
    ----------
    net : DriftNetwork
    """

    def __init__(self, net):
        self.net = net
        self._A = np.ascontiguousarray(net.nodes[net.edges[:, 0]], dtype=np.float64)
        self._B = np.ascontiguousarray(net.nodes[net.edges[:, 1]], dtype=np.float64)
        self._r = np.ascontiguousarray(0.5 * net.widths, dtype=np.float64)
        self._nodes = np.ascontiguousarray(net.nodes, dtype=np.float64)
        self._h = np.ascontiguousarray(net.node_heights, dtype=np.float64)
        rough = float(getattr(net, "roughness_m", 0.0))
        if rough > 0.0:
            from minegeo.synth.network import roughness_field

            f = roughness_field(rough, int(getattr(net, "roughness_seed", 0)))
            self._rough = (f.freq, f.amp, f.phase)
        else:
            self._rough = (np.zeros((0, 3)), np.zeros(0), np.zeros(0))

    def cast(self, origins, directions, max_range_m: float, with_noise: bool = True) -> np.ndarray:
        """Ranges (m) along unit ``directions`` from ``origins`` (world frame) to the first surface; NaN = none.

        ``with_noise`` is accepted for interface parity with ``MineWorld.cast``; the surfaces are exact.
        """
        O = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        D = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        if O.shape != D.shape:
            raise InputError(f"origins {O.shape} and directions {D.shape} must have the same shape")
        out = np.empty(O.shape[0])
        _cast_network(O, D, self._A, self._B, self._r, self._nodes, self._h, float(max_range_m), *self._rough, out)
        return out
