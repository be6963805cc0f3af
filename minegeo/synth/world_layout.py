"""The drift network of the synthetic mine: levels, ring roadway, helix access, headings and junctions as a graph.

The layout is a graph of nodes (3D points on the drift floor) and drifts (centreline polylines
between two nodes); :func:`_classify` names its junctions (:class:`Intersection`). Everything is
drawn from the seeded generator handed in, so a preset and seed give one network.
The polyline helpers (:func:`_resample`, :func:`_frames`, :func:`_offset_polyline`) serve the
layout and the primitives placed along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minegeo.errors import InputError
from minegeo.synth.world_params import WorldParams


@dataclass(frozen=True, eq=False)
class Drift:
    """One drift (edge of the network): a floor centreline polyline from node ``a`` to ``b``.

    ``kind`` is one of ``main``, ``parallel``, ``crosscut``, ``branch``, ``ring``, ``ramp``,
    ``stub``; ``level`` is the level index (a ramp belongs to its upper level).
    """

    name: str
    a: int
    b: int
    centreline: np.ndarray
    kind: str
    level: int

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.centreline, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Intersection:
    """A junction of three or more drifts: ``type`` is ``"T"``, ``"X"`` or ``"Y"``."""

    node: int
    position: tuple
    type: str
    degree: int
    level: int


def _wiggle(P: np.ndarray, rng: np.random.Generator, amp_m: float) -> np.ndarray:
    """Add a smooth seeded lateral meander (zero at both ends) to a straight polyline."""
    if amp_m <= 0 or len(P) < 3:
        return P
    d = P[-1, :2] - P[0, :2]
    L = float(np.linalg.norm(d))
    if L < 1e-9:
        return P
    n = np.array([-d[1], d[0]]) / L
    s = np.linspace(0.0, 1.0, len(P))
    off = np.zeros(len(P))
    for k in (1, 2, 3):
        off += rng.uniform(-1, 1) * amp_m / k * np.sin(k * np.pi * s)
    Q = P.copy()
    Q[:, :2] += off[:, None] * n[None, :]
    return Q


def _straight(a, b, step_m: float = 2.0) -> np.ndarray:
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    L = float(np.linalg.norm(b[:2] - a[:2]))
    n = max(1, int(math.ceil(L / step_m)))
    s = np.linspace(0.0, 1.0, n + 1)[:, None]
    return a[None, :] * (1 - s) + b[None, :] * s


def _arc(centre, radius, ang0, ang1, z0, z1, step_m: float = 2.0) -> np.ndarray:
    L = abs(ang1 - ang0) * radius
    n = max(2, int(math.ceil(L / step_m)))
    t = np.linspace(0.0, 1.0, n + 1)
    ang = ang0 + (ang1 - ang0) * t
    return np.column_stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), z0 + (z1 - z0) * t])


class _Graph:
    def __init__(self):
        self.nodes: list[np.ndarray] = []
        self.edges: list[tuple[int, int, np.ndarray, str, int]] = []

    def node(self, xyz) -> int:
        self.nodes.append(np.asarray(xyz, float).copy())
        return len(self.nodes) - 1

    def edge(self, a: int, b: int, poly: np.ndarray, kind: str, level: int) -> int:
        poly = np.asarray(poly, float).copy()
        poly[0] = self.nodes[a]
        poly[-1] = self.nodes[b]
        self.edges.append((a, b, poly, kind, level))
        return len(self.edges) - 1


def _level_drifts(g: _Graph, feats: dict, p: WorldParams, rng: np.random.Generator, lev: int, last: bool,
                  start: int, sx: float, y_level: float) -> int:
    """The drifts of one level (main, parallel drive, cross-cuts, X, stubs, Y branch); returns the main's end node."""
    A = g.nodes[start]
    z = A[2]
    Lm = p.main_length_m * (1.0 + rng.uniform(-0.04, 0.04)) * (0.65 if last and p.n_levels > 1 else 1.0)
    ncc = max(2, p.n_crosscuts if not last else max(2, p.n_crosscuts // 2))
    span = Lm - 2 * p.crosscut_spacing_m / 3 if ncc > 1 else Lm / 2
    base = np.linspace(p.crosscut_spacing_m / 3.0, p.crosscut_spacing_m / 3.0 + span * 0.85, ncc)
    cc_x = np.sort(base + rng.uniform(-2.0, 2.0, ncc))
    x_cross = int(ncc // 2)  # this cross-cut continues to the far side: X junction
    y_x = 0.5 * (cc_x[0] + cc_x[1]) + rng.uniform(-2.0, 2.0)  # Y branch between the first two
    stub_x = []
    if p.stubs_per_level:
        stub_x = list(np.linspace(cc_x[1] + 0.5 * p.crosscut_spacing_m, cc_x[-1] - 0.5 * p.crosscut_spacing_m,
                                  p.stubs_per_level))
    marks = sorted([(x, "cc", i) for i, x in enumerate(cc_x)] + [(y_x, "y", 0)]
                   + [(x, "stub", i) for i, x in enumerate(stub_x)])
    prev = start
    main_nodes = {}
    side = -1.0  # parallel drive on the -y side; X extension, Y branch and stubs on the +y side
    for x, what, i in marks + [(Lm, "end", 0)]:
        nid = g.node([A[0] + sx * x, y_level, z])
        poly = _wiggle(_straight(g.nodes[prev], g.nodes[nid]), rng, 0.6)
        g.edge(prev, nid, poly, "main", lev)
        main_nodes[(what, i)] = nid
        prev = nid
    end_node = prev
    # parallel drive and cross-cuts
    par_nodes = []
    for i, x in enumerate(cc_x):
        mn = main_nodes[("cc", i)]
        pn = g.node([A[0] + sx * x + rng.uniform(-1.5, 1.5), y_level + side * p.parallel_offset_m, z])
        g.edge(mn, pn, _wiggle(_straight(g.nodes[mn], g.nodes[pn]), rng, 0.4), "crosscut", lev)
        par_nodes.append(pn)
        if i == x_cross:
            xn = g.node([A[0] + sx * x, y_level - side * 12.0, z])
            g.edge(mn, xn, _straight(g.nodes[mn], g.nodes[xn]), "crosscut", lev)
    for i in range(len(par_nodes) - 1):
        a, b = par_nodes[i], par_nodes[i + 1]
        g.edge(a, b, _wiggle(_straight(g.nodes[a], g.nodes[b]), rng, 0.8), "parallel", lev)
    # stubs (stope accesses) on the far side
    for i, x in enumerate(stub_x):
        mn = main_nodes[("stub", i)]
        sn = g.node([A[0] + sx * x + rng.uniform(-2, 2), y_level - side * p.stub_length_m, z])
        g.edge(mn, sn, _straight(g.nodes[mn], g.nodes[sn]), "stub", lev)
    # Y branch: leaves the main drift at ~40 degrees, gently curved, dead end with a sump
    mn = main_nodes[("y", 0)]
    ang = math.radians(rng.uniform(35.0, 45.0))
    Lb = 26.0
    hdg = np.array([-sx * math.cos(ang), -side * math.sin(ang)])  # back towards the level start
    mid = g.nodes[mn][:2] + hdg * Lb * 0.5
    hdg2 = np.array([-sx * math.cos(ang * 1.6), -side * math.sin(ang * 1.6)])
    endp = mid + hdg2 * Lb * 0.5
    bn = g.node([endp[0], endp[1], z])
    poly = np.vstack([_straight(g.nodes[mn], [mid[0], mid[1], z], 2.0)[:-1],
                      _straight([mid[0], mid[1], z], g.nodes[bn], 2.0)])
    ybranch = g.edge(mn, bn, poly, "branch", lev)
    if feats["sump"] is None:
        feats["sump"] = {"drift": ybranch, "level": lev}
    return end_node


def _ring_roadway(g: _Graph, p: WorldParams, end_node: int, sx: float, lev: int) -> int:
    """Ring roadway (two half circles, a loop) beyond the main drift's end; returns its far node."""
    Rr = p.ring_radius_m
    E = g.nodes[end_node]
    z = E[2]
    C = E[:2] + np.array([sx * Rr, 0.0])
    F = g.node([C[0] + sx * Rr, C[1], z])
    a0 = math.pi if sx > 0 else 0.0
    g.edge(end_node, F, _arc(C, Rr, a0, a0 - math.pi * (1 if sx > 0 else -1), z, z), "ring", lev)
    g.edge(end_node, F, _arc(C, Rr, a0, a0 + math.pi * (1 if sx > 0 else -1), z, z), "ring", lev)
    return F


def _layout(p: WorldParams, rng: np.random.Generator):
    """Seeded drift graph: levels of main drift + parallel drive + cross-cuts (loops), an
    X cross-cut, a Y branch ending in a sump, a ring roadway, stubs, and ramps between levels."""
    g = _Graph()
    feats: dict = {"ramp_slopes_deg": [], "sump": None}
    start = g.node([0.0, 0.0, 0.0])
    sx = 1.0
    y_level = 0.0
    for lev in range(p.n_levels):
        z = g.nodes[start][2]
        last = lev == p.n_levels - 1
        end_node = _level_drifts(g, feats, p, rng, lev, last, start, sx, y_level)
        if last:
            break
        # ring roadway (a loop) beyond the end of the main drift, then the ramp down
        F = _ring_roadway(g, p, end_node, sx, lev)
        slope = math.radians(rng.uniform(*p.ramp_slope_deg))
        feats["ramp_slopes_deg"].append(math.degrees(slope))
        dz = p.level_spacing_m
        Lr = dz / math.tan(slope)
        Rt = p.ramp_turn_radius_m
        Fp = g.nodes[F]
        l1 = 12.0
        l_arc = math.pi * Rt
        l3 = Lr - l1 - l_arc
        if l3 < 5.0:
            raise InputError("level spacing too small for the ramp geometry")
        z1 = z - dz * l1 / Lr
        z2 = z - dz * (l1 + l_arc) / Lr
        P1 = np.array([Fp[0] + sx * l1, Fp[1], z1])
        seg1 = _straight(Fp, P1)
        Ct = np.array([P1[0], P1[1] - Rt])
        th0 = math.pi / 2
        th1 = th0 - sx * math.pi  # turn towards -y and back
        seg2 = _arc(Ct, Rt, th0, th1, z1, z2)
        P3 = np.array([P1[0] - sx * l3, P1[1] - 2 * Rt, z - dz])
        seg3 = _straight(seg2[-1], P3)
        ramp_poly = np.vstack([seg1[:-1], seg2[:-1], seg3])
        nxt = g.node(P3)
        g.edge(F, nxt, ramp_poly, "ramp", lev)
        start = nxt
        y_level = P3[1]
        sx = -sx
    return g, feats


#: length (m) of the access drift from the ring roadway to the helical decline (repeated levels)
HELIX_ACCESS_M = 10.0


def _layout_repeated(p: WorldParams, rng: np.random.Generator):
    """Drift graph of repeated levels: level 0 (as in :func:`_layout`, with its ring roadway and a
    10 m access drift) copied to every level k translated by ``(0, 0, -k dz)``, the levels joined by a
    helical decline of one turn per level (radius ``dz / (2 pi tan slope)``, tangent to the access
    drift's end, which is a T junction on the middle levels).

    Returns ``(graph, features, repeat)`` where ``repeat`` holds ``offset_m`` (the translation of
    one level), ``unit_edges`` (edges of level 0 plus the first decline turn) and ``copies``
    ``{k: {unit edge: its copy on level k}}``.
    """
    g = _Graph()
    feats: dict = {"ramp_slopes_deg": [], "sump": None}
    start = g.node([0.0, 0.0, 0.0])
    end_node = _level_drifts(g, feats, p, rng, 0, False, start, 1.0, 0.0)
    F = _ring_roadway(g, p, end_node, 1.0, 0)
    slope = math.radians(rng.uniform(*p.ramp_slope_deg))
    dz = float(p.level_spacing_m)
    n = int(p.n_levels)
    Fp = g.nodes[F]
    q0 = g.node(Fp + np.array([HELIX_ACCESS_M, 0.0, 0.0]))
    g.edge(F, q0, _straight(Fp, g.nodes[q0]), "crosscut", 0)
    unit_nodes = list(range(len(g.nodes)))
    unit_edges = list(range(len(g.edges)))
    qnode = {0: q0}
    copies: dict[int, dict[int, int]] = {}
    for k in range(1, n):
        off = np.array([0.0, 0.0, -k * dz])
        nm = {i: g.node(g.nodes[i] + off) for i in unit_nodes}
        copies[k] = {e: g.edge(nm[g.edges[e][0]], nm[g.edges[e][1]], g.edges[e][2] + off, g.edges[e][3], k)
                     for e in unit_edges}
        qnode[k] = nm[q0]
    Rh = dz / (2.0 * math.pi * math.tan(slope))
    C = g.nodes[q0][:2] + np.array([Rh, 0.0])
    turn = _arc(C, Rh, math.pi, 3.0 * math.pi, 0.0, -dz)
    h0 = -1
    for k in range(n - 1):
        e = g.edge(qnode[k], qnode[k + 1], turn + np.array([0.0, 0.0, -k * dz]), "ramp", k)
        if k == 0:
            h0 = e
        else:
            copies[k][h0] = e
    feats["ramp_slopes_deg"] = [math.degrees(slope)] * (n - 1)
    rep = {"mode": p.repeat_levels, "offset_m": [0.0, 0.0, -dz], "unit_edges": unit_edges + [h0],
           "copies": copies, "helix_radius_m": Rh}
    return g, feats, rep


def _heading_poly(P0, d_in, leg1_m: float, bend_deg: float, total_m: float, radius_m: float = 8.0) -> np.ndarray:
    """Floor centreline of a heading: straight ``leg1_m`` along ``d_in``, an arc turning by ``bend_deg``
    (positive: to the left), then straight to a total length of ``total_m`` (all horizontal)."""
    P0 = np.asarray(P0, float)
    d = np.array([d_in[0], d_in[1]]) / np.hypot(d_in[0], d_in[1])
    P1 = P0 + np.array([*(d * leg1_m), 0.0])
    sgn = 1.0 if bend_deg > 0 else -1.0
    nrm = sgn * np.array([-d[1], d[0]])
    C = P1[:2] + nrm * radius_m
    a0 = math.atan2(P1[1] - C[1], P1[0] - C[0])
    b = math.radians(abs(bend_deg))
    arc = _arc(C, radius_m, a0, a0 + sgn * b, P0[2], P0[2])
    c, s_ = math.cos(sgn * b), math.sin(sgn * b)
    d2 = np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]])
    leg3 = total_m - leg1_m - radius_m * b
    P3 = arc[-1] + np.array([*(d2 * leg3), 0.0])
    return np.vstack([_straight(P0, P1)[:-1], arc[:-1], _straight(arc[-1], P3)])


def _seg_dist_2d(P, A, B):
    """Horizontal distances (len(P), len(A)) from points P to segments A-B."""
    d = B[None, :, :2] - A[None, :, :2]
    L2 = np.maximum(np.sum(d * d, axis=2), 1e-12)
    u = np.clip(np.sum((P[:, None, :2] - A[None, :, :2]) * d, axis=2) / L2, 0.0, 1.0)
    q = A[None, :, :2] + u[..., None] * d - P[:, None, :2]
    return np.sqrt(np.sum(q * q, axis=2))


def _add_headings(g: _Graph, p: WorldParams, seed: int) -> list[int]:
    """Append ``p.unmapped_headings`` headings continuing dead ends (not the sump branches).

    Drawn from ``np.random.default_rng([seed, 0x4EAD])``. A candidate is kept when every
    centreline point beyond its first ``2 R + 4`` m is at least ``2 R + 3`` m (horizontally) from every other
    drift segment within ``H + 3`` m of its height; otherwise another bend, then another dead end
    is tried. Returns the new edge indices (kind ``"heading"``).
    """
    rng = np.random.default_rng([int(seed), 0x4EAD])
    R = p.width_m / 2.0
    H = p.wall_height_m + R
    deg = np.zeros(len(g.nodes), int)
    inc: dict[int, tuple[int, np.ndarray]] = {}
    for k, (a, b, poly, kind, _lev) in enumerate(g.edges):
        deg[a] += 1
        deg[b] += 1
        if kind != "branch":  # the sump branches keep their dead end
            inc[a] = (k, poly[min(2, len(poly) - 1), :2] - poly[0, :2])
            inc[b] = (k, poly[max(-3, -len(poly)), :2] - poly[-1, :2])
    cands = [i for i in range(len(g.nodes)) if deg[i] == 1 and i in inc
             and g.edges[inc[i][0]][3] != "branch"]
    out: list[int] = []
    for ci in rng.permutation(len(cands)):
        if len(out) == p.unmapped_headings:
            break
        node = cands[int(ci)]
        k_par, d_back = inc[node]
        d_in = -d_back / max(np.linalg.norm(d_back), 1e-12)
        segs = [(poly[:-1], poly[1:]) for (_a, _b, poly, _k, _l) in g.edges]
        A = np.vstack([s[0] for s in segs])
        B = np.vstack([s[1] for s in segs])
        zmid = 0.5 * (A[:, 2] + B[:, 2])
        for _ in range(6):
            bend = rng.uniform(60.0, 90.0) * (1.0 if rng.uniform() < 0.5 else -1.0)
            poly = _heading_poly(g.nodes[node], d_in, 12.0, bend, p.heading_length_m)
            Q = _densify_2d(poly, 1.0)
            s_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Q[:, :2], axis=0), axis=1))])
            Q = Q[s_arc > 2 * R + 4.0]  # the mouth is where it meets its parent
            near_z = np.abs(zmid - g.nodes[node][2]) < H + 3.0
            if not near_z.any() or _seg_dist_2d(Q, A[near_z], B[near_z]).min() >= 2 * R + 3.0:
                out.append(g.edge(node, g.node(poly[-1]), poly, "heading", g.edges[k_par][4]))
                break
    if len(out) < p.unmapped_headings:
        raise InputError(f"only {len(out)} of {p.unmapped_headings} unmapped headings fit in this layout "
                         f"(each continues a dead end; {len(cands)} candidates)")
    return out


def _densify_2d(P: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` (or closer) along a polyline, vertices included."""
    out = [P[:1]]
    for a, b in zip(P[:-1], P[1:], strict=True):
        m = max(1, int(math.ceil(np.linalg.norm(b - a) / step_m)))
        out.append(a[None] + (b - a)[None] * (np.arange(1, m + 1) / m)[:, None])
    return np.vstack(out)


def _classify(g: _Graph):
    """Intersections (degree >= 3) typed T/X/Y from the directions the drifts leave the node."""
    inc: dict[int, list[np.ndarray]] = {i: [] for i in range(len(g.nodes))}
    for a, b, poly, _k, _l in g.edges:
        da = poly[min(2, len(poly) - 1), :2] - poly[0, :2]
        db = poly[max(-3, -len(poly)), :2] - poly[-1, :2]
        inc[a].append(da / np.linalg.norm(da))
        inc[b].append(db / np.linalg.norm(db))
    out, dead = [], []
    for i, dirs in inc.items():
        deg = len(dirs)
        if deg == 1:
            dead.append(i)
        if deg < 3:
            continue
        if deg >= 4:
            typ = "X"
        else:
            typ = "Y"
            for u in range(3):
                for v in range(u + 1, 3):
                    if np.dot(dirs[u], dirs[v]) < -0.94:  # collinear pair (within ~20 deg)
                        w = 3 - u - v
                        c = abs(float(np.dot(dirs[w], dirs[u])))
                        typ = "T" if c < 0.5 else "Y"  # third leg within 60-120 deg: T
        level = 0
        for a, b, _p, _k, lev in g.edges:
            if i in (a, b):
                level = lev
                break
        out.append(Intersection(i, tuple(float(x) for x in g.nodes[i]), typ, deg, level))
    return tuple(out), tuple(dead)


def _frames(poly: np.ndarray):
    """Per-segment unit horizontal tangent and left normal of a polyline."""
    d = np.diff(poly[:, :2], axis=0)
    L = np.linalg.norm(d, axis=1)
    t = d / L[:, None]
    n = np.column_stack([-t[:, 1], t[:, 0]])
    return t, n, L


def _resample(poly: np.ndarray, step_m: float):
    """Points every ``step_m`` of horizontal arc length along a polyline, with tangent/normal."""
    t, n, L = _frames(poly)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    s = np.arange(step_m / 2, cum[-1] - 1e-9, step_m)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1)
    u = (s - cum[k]) / L[k]
    P = poly[k] * (1 - u)[:, None] + poly[k + 1] * u[:, None]
    return P, t[k], n[k], s


def _offset_polyline(poly: np.ndarray, lateral_m: float, height_m: float) -> np.ndarray:
    """Polyline offset sideways (mitred at vertices) and raised: for pipes, cables, the duct."""
    t, n, _ = _frames(poly)
    nv = np.zeros((len(poly), 2))
    nv[0], nv[-1] = n[0], n[-1]
    for i in range(1, len(poly) - 1):
        m = n[i - 1] + n[i]
        m /= np.linalg.norm(m)
        nv[i] = m / max(0.5, float(np.dot(m, n[i])))
    Q = poly.copy()
    Q[:, :2] += lateral_m * nv
    Q[:, 2] += height_m
    return Q


def _curve_and_parking(g: _Graph, feats: dict, reg: int) -> list:
    """Marks the first ring/ramp drift as ``feats["curve"]`` and returns the vehicle's parking
    poses, left of the centreline in the regular section: [0] where it is parked during the
    survey, [1] moved 5 m back along the drift (also in ``feats["parking_sites"]``)."""
    ring_edges = [k for k, e in enumerate(g.edges) if e[3] in ("ring", "ramp")]
    ce = ring_edges[0]
    feats["curve"] = {"drift": ce, "s_m": float(np.linalg.norm(np.diff(g.edges[ce][2], axis=0), axis=1).sum() / 2)}
    parking = []
    for k, back_m in ((reg, 0.0), (reg, 5.0)):
        P, t, n, s = _resample(g.edges[k][2], 0.5)
        jj = max(0, len(P) // 2 - int(back_m / 0.5))
        T = np.eye(4)
        xa = np.array([t[jj][0], t[jj][1], 0.0])
        ya = np.array([n[jj][0], n[jj][1], 0.0])
        T[:3, 0], T[:3, 1], T[:3, 2] = xa, ya, [0, 0, 1]
        T[:3, 3] = P[jj] + ya * 1.15 + np.array([0, 0, 0.01])  # 0.15 m from the left wall
        parking.append(T)
        feats.setdefault("parking_sites", []).append({"drift": k, "s_m": float(s[jj])})
    return parking
