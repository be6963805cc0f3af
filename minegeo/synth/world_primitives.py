"""The signed distance field's primitives and tables: void and solid primitives of the synthetic mine,
the roughness wave tables, the acceleration grid and the Lipschitz bound of the field.

The arrays assembled here (:func:`_assemble`) are what the Numba kernels of ``synth/_kernels.py``
evaluate: ``f(p) = min(max_i g_i(p) + n(p), min_j s_j(p))`` (see :mod:`minegeo.synth.world`).
"""

from __future__ import annotations

import math

import numpy as np

from minegeo.synth import _kernels as K
from minegeo.synth.world_layout import _frames, _Graph, _offset_polyline, _resample
from minegeo.synth.world_params import _OCTAVE_WAVES, WorldParams, roughness_amplitudes

#: smallest sphere-tracing step (m): rock slivers thinner than this along a ray may be missed
#: (the thinnest structure is a cable of 2 cm radius); crossings are refined to 1e-4 m.
MIN_STEP_M = 0.005


def _noise_arrays(p: WorldParams, rng: np.random.Generator, z_period_m: float | None = None):
    """Plane waves and octave table of the roughness (see ``_kernels``), amplitudes from
    :func:`roughness_amplitudes`. With ``z_period_m`` every wave's vertical wavenumber is moved to
    the nearest multiple of ``2 pi / z_period_m`` (its horizontal part rescaled to keep ``|k|``), so
    the field is periodic in z with that period (exact copies of levels); the draws are the same."""
    ob, tex, _ = roughness_amplitudes(p)
    specs = [  # (wavelength m, amplitude m, mode, n waves)
        (6.0, ob[0], 0, _OCTAVE_WAVES[0]),
        (1.5, ob[1], 0, _OCTAVE_WAVES[1]),
        (0.35, tex[0], 1, _OCTAVE_WAVES[2]),
        (0.1, tex[1], 1, _OCTAVE_WAVES[3]),
    ]
    waves, octs, k0 = [], [], 0
    for lam, amp, mode, n in specs:
        v = rng.normal(size=(n, 3))
        v[:, 2] *= 0.8
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        kmag = 2 * np.pi / lam * rng.uniform(0.8, 1.25, n)
        ph = rng.uniform(0, 2 * np.pi, n)
        w = v * kmag[:, None]
        if z_period_m is not None:
            w = _quantise_kz(w, kmag, 2 * np.pi / z_period_m)
        waves.append(np.column_stack([w, ph]))
        octs.append([k0, n, amp, mode])
        k0 += n
    return np.ascontiguousarray(np.vstack(waves)), np.ascontiguousarray(np.array(octs, float))


def _quantise_kz(w: np.ndarray, kmag: np.ndarray, dk: float) -> np.ndarray:
    """Wave vectors with k_z on multiples of ``dk`` (|k_z| < |k|) and the horizontal part rescaled to keep |k|."""
    out = w.copy()
    for i in range(w.shape[0]):
        m = int(round(w[i, 2] / dk))
        while m != 0 and abs(m * dk) >= kmag[i]:
            m -= 1 if m > 0 else -1
        kz = m * dk
        h = math.hypot(w[i, 0], w[i, 1])
        kh = math.sqrt(kmag[i] ** 2 - kz * kz)
        if h > 1e-12:
            out[i, 0], out[i, 1] = w[i, 0] * kh / h, w[i, 1] * kh / h
        else:
            out[i, 0], out[i, 1] = kh, 0.0
        out[i, 2] = kz
    return out


def _capsule_chain(Q: np.ndarray, r: float) -> list:
    return [[*Q[i], *Q[i + 1], r, 0.0] for i in range(len(Q) - 1)]


def _vehicle_model():
    """A parked utility vehicle / loader in its own frame (x forward, z up, origin on the floor)."""
    boxes = [
        [0.0, 0.0, 0.95, 2.4, 0.95, 0.45, 0.0],  # chassis
        [-1.2, -0.4, 1.95, 0.7, 0.5, 0.55, 0.0],  # cab (on the side away from the wall)
        [2.95, 0.0, 0.55, 0.35, 1.05, 0.4, 0.0],  # bucket
        [-2.1, 0.0, 1.55, 0.3, 0.8, 0.2, 0.0],  # engine cover
    ]
    prims = [[*b, 0.0] for b in boxes]
    types = [1] * len(boxes)
    for x in (-1.5, 1.5):
        prims.append([x, -0.55, 0.6, x, 0.55, 0.6, 0.6, 0.0])  # wheel axles as capsules
        types.append(0)
    return np.array(prims, float), np.array(types, np.int64)


def _build_grid(bmin, bmax, cell, void_boxes, solid_boxes, margin):
    dims = np.maximum(1, np.ceil((bmax - bmin) / cell).astype(np.int64))
    ncell = int(np.prod(dims))

    def csr(boxes):
        lists_c, lists_i = [], []
        for i, (lo, hi) in enumerate(boxes):
            i0 = np.clip(np.floor((lo - margin - bmin) / cell).astype(np.int64), 0, dims - 1)
            i1 = np.clip(np.floor((hi + margin - bmin) / cell).astype(np.int64), 0, dims - 1)
            ix, iy, iz = np.meshgrid(np.arange(i0[0], i1[0] + 1), np.arange(i0[1], i1[1] + 1),
                                     np.arange(i0[2], i1[2] + 1), indexing="ij")
            c = ((ix * dims[1] + iy) * dims[2] + iz).ravel()
            lists_c.append(c)
            lists_i.append(np.full(c.size, i, np.int64))
        if not lists_c:
            return np.zeros(ncell + 1, np.int64), np.zeros(0, np.int64)
        c = np.concatenate(lists_c)
        it = np.concatenate(lists_i)
        order = np.lexsort((it, c))
        c, it = c[order], it[order]
        counts = np.bincount(c, minlength=ncell)
        start = np.zeros(ncell + 1, np.int64)
        np.cumsum(counts, out=start[1:])
        return start, np.ascontiguousarray(it)

    v_start, v_items = csr(void_boxes)
    s_start, s_items = csr(solid_boxes)
    grid_f = np.array([bmin[0], bmin[1], bmin[2], cell], float)
    return grid_f, dims, v_start, v_items, s_start, s_items


def _prim_box(prim, typ, solid: bool):
    p = np.asarray(prim, float)
    if solid:
        if typ == 0:
            lo = np.minimum(p[0:3], p[3:6]) - p[6]
            hi = np.maximum(p[0:3], p[3:6]) + p[6]
        else:
            r = np.hypot(p[3], p[4])
            lo = p[0:3] - np.array([r, r, p[5]])
            hi = p[0:3] + np.array([r, r, p[5]])
        return lo, hi
    if typ == 0:
        R, hw = p[6], p[7]
        lo = np.minimum(p[0:3], p[3:6]) - np.array([R, R, 0.0])
        hi = np.maximum(p[0:3], p[3:6]) + np.array([R, R, hw + R])
        return lo, hi
    if typ == 1:
        return p[0:3] - p[3:6], p[0:3] + p[3:6]
    r = np.hypot(p[3], p[4])
    return p[0:3] - np.array([r, r, p[5]]), p[0:3] + np.array([r, r, p[5]])


def _assemble(void, vtype, solid, stype, waves, octaves, zones, cell, ob_max):
    void = np.ascontiguousarray(np.array(void, float).reshape(-1, 8))
    vtype = np.ascontiguousarray(np.array(vtype, np.int64))
    solid = np.ascontiguousarray(np.array(solid, float).reshape(-1, 8))
    stype = np.ascontiguousarray(np.array(stype, np.int64))
    vboxes = [_prim_box(void[i], vtype[i], False) for i in range(len(void))]
    sboxes = [_prim_box(solid[i], stype[i], True) for i in range(len(solid))]
    lo = np.min([b[0] for b in vboxes], axis=0) - ob_max
    hi = np.max([b[1] for b in vboxes], axis=0) + ob_max
    margin = K.GRID_MARGIN_M
    gmin = lo - margin
    gmax = hi + margin
    grid_f, dims, v_start, v_items, s_start, s_items = _build_grid(gmin, gmax, cell, vboxes, sboxes, margin)
    out = {
        "grid_f": grid_f, "grid_i": dims.astype(np.int64), "void_prims": void, "void_type": vtype,
        "v_start": v_start, "v_items": v_items, "solid_prims": solid, "solid_type": stype,
        "s_start": s_start, "s_items": s_items, "waves": waves, "octaves": octaves,
        "zones": np.ascontiguousarray(np.array(zones, float).reshape(-1, 5)),
        "bounds_min": lo, "bounds_max": hi,
        "noise_min": -float(np.sum(octaves[octaves[:, 3] == 1, 2])) - 1e-9,
    }
    out["ob_factor"], out["step_factor"], out["lipschitz"] = _lipschitz(out)
    return out


def _lipschitz(a, n: int = 4000, h: float = 1e-5):
    """Numerical Lipschitz estimates of the roughness (finite differences at seeded points).

    Returns the step factor of the overbreak bound ``1 / (1.02 + 1.5 L_ob)``, the
    full-field step factor ``min(0.45, 1 / (1.02 + 1.5 L_all))`` and the estimates; the
    1.5 safety factor covers the maximum not being sampled exactly. 1.02 bounds the
    smooth drift field (1/cos of the steepest ramp).
    """
    rng = np.random.default_rng(12345)
    lo, hi = a["bounds_min"], a["bounds_max"]
    P = rng.uniform(lo, hi, size=(n, 3))
    if a["zones"].shape[0]:
        zc = a["zones"][rng.integers(0, a["zones"].shape[0], n)]
        P = np.vstack([P, zc[:, :3] + rng.normal(0.0, 1.0, (n, 3)) * zc[:, 3:4]])
    P = np.ascontiguousarray(P)

    def parts(Q):
        ob = np.empty(Q.shape[0])
        tex = np.empty(Q.shape[0])
        K.noise_parts_many(np.ascontiguousarray(Q), a["waves"], a["octaves"], a["zones"], ob, tex)
        return ob, tex

    ob0, tx0 = parts(P)
    g_ob = np.zeros((P.shape[0], 3))
    g_all = np.zeros((P.shape[0], 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        ob1, tx1 = parts(P + e)
        g_ob[:, k] = (ob1 - ob0) / h
        g_all[:, k] = (ob1 + tx1 - ob0 - tx0) / h
    L_ob = float(np.linalg.norm(g_ob, axis=1).max())
    L_all = float(np.linalg.norm(g_all, axis=1).max())
    return 1.0 / (1.02 + 1.5 * L_ob), min(0.45, 1.0 / (1.02 + 1.5 * L_all)), {"overbreak": L_ob, "total": L_all}


def _smooth_field(a, P):
    """Smooth design field (no roughness, no structures) at points P."""
    P = np.ascontiguousarray(P, dtype=float)
    out = np.empty(P.shape[0])
    K.sdf_many(P, a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], a["v_start"], a["v_items"],
               a["solid_prims"], a["solid_type"], a["s_start"], a["s_items"], a["waves"], a["octaves"], a["zones"],
               np.eye(4), np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(4), False, False, out)
    return out


def _cast_arrays(a, O, D, max_range, step_factor, with_solids=True):
    out = np.empty(O.shape[0])
    ss = a["s_start"] if with_solids else np.zeros_like(a["s_start"])
    K.cast_rays(np.ascontiguousarray(O), np.ascontiguousarray(D), float(max_range), step_factor, MIN_STEP_M, 4000, 1e-4,
                a["grid_f"], a["grid_i"], a["void_prims"], a["void_type"], a["v_start"], a["v_items"],
                a["solid_prims"], a["solid_type"], ss, a["s_items"], a["waves"], a["octaves"], a["zones"],
                np.eye(4), np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(4), True, a["noise_min"], a["ob_factor"], out, np.empty(out.shape[0], np.int64))
    return out


class _Prims:
    """Growing primitive rows with their kernel type codes and the drift each belongs to."""

    def __init__(self):
        self.rows, self.types, self.owners = [], [], []

    def add(self, row, typ: int, owner: int) -> None:
        self.rows.append(row)
        self.types.append(typ)
        self.owners.append(owner)


def _level_offset(k: int, dz: float) -> np.ndarray:
    """Translation of level copy ``k`` (``dz`` below per level)."""
    return np.array([0.0, 0.0, -k * dz])


def _section_drifts(g: _Graph) -> tuple[int, int]:
    """The first level's longest main drift (irregular roof) and the second longest (regular, meshed)."""
    main0 = [k for k, e in enumerate(g.edges) if e[3] == "main" and e[4] == 0]
    main_len = [float(np.linalg.norm(np.diff(g.edges[k][2][:, :2], axis=0), axis=1).sum()) for k in main0]
    long_mains = [k for k, _L in sorted(zip(main0, main_len, strict=True), key=lambda z: -z[1])]
    irr = long_mains[0]
    reg = long_mains[1] if len(long_mains) > 1 else long_mains[0]
    return irr, reg


def _fall_outs(void: _Prims, poly, owner: int, H: float, rng: np.random.Generator):
    """Roof fall-outs (ellipsoid cavities) around the middle of ``poly``; returns the resampled
    points, their arc lengths and the middle index."""
    P, t, n, s = _resample(poly, 1.0)
    mid = len(P) // 2
    for j in range(max(0, mid - 8), min(len(P), mid + 8)):
        if rng.uniform() < 0.75:
            c = P[j] + np.array([*(n[j] * rng.uniform(-0.9, 0.9)), H - rng.uniform(0.2, 0.5)])
            void.add([c[0], c[1], c[2], rng.uniform(0.8, 1.6), rng.uniform(0.8, 1.6), rng.uniform(0.45, 0.9), 0, 0],
                     1, owner)
    return P, s, mid


def _sump_pit(void: _Prims, g: _Graph, feats: dict) -> dict:
    """The sump pit near the end of the Y branch, offset to one side of the centreline.

    Returns the pit's site: ``drift``, ``centre`` (pit centre), ``yaw``, ``floor`` (the branch
    point beside it) and ``side`` (+1: the pit lies left of the centreline).
    """
    sb = feats["sump"]["drift"]
    Pb, tb, nb, sbs = _resample(g.edges[sb][2], 0.5)
    j_pit = max(0, len(Pb) - 1 - int(5.0 / 0.5))
    side = 1.0
    pit_c = Pb[j_pit] + np.array([*(nb[j_pit] * side * 1.45), -0.65])
    yaw = math.atan2(tb[j_pit][1], tb[j_pit][0])
    void.add([pit_c[0], pit_c[1], pit_c[2], 1.8, 0.7, 0.85, yaw, 0.0], 2, sb)
    feats["sump"].update({"s_m": float(sbs[j_pit]), "centre": [float(x) for x in Pb[j_pit]]})
    return {"drift": sb, "centre": pit_c, "yaw": yaw, "floor": Pb[j_pit], "side": side}


def _repeat_voids(void: _Prims, zones: list, g: _Graph, rep: dict, irr: int, cavities: range, pit: dict,
                  H: float, dz: float, rng: np.random.Generator) -> None:
    """Rough zones, roof fall-outs and the sump pit of every level copy (``rep["copies"]``).

    An exact copy repeats the fall-outs ``cavities`` of level 0; a near copy draws them anew
    around the same place.
    """
    exact = rep["mode"] == "exact"
    # zones reach 3 r (kernel cut-off): keep them within one level so copies do not leak into each other
    rmax = (dz - H - 0.5) / 3.0
    for z in zones:
        z[3] = min(z[3], rmax)
    zones0 = [list(z) for z in zones]
    for k, cm in rep["copies"].items():
        o = _level_offset(k, dz)
        zones.extend([[*(np.array(z[:3]) + o), z[3], z[4]] for z in zones0])
        if exact:  # the same fall-outs
            for i in cavities:
                void.add([*(np.array(void.rows[i][:3]) + o), *void.rows[i][3:]], 1, cm[irr])
        else:  # near copy: fall-outs drawn anew around the same place
            _fall_outs(void, g.edges[cm[irr]][2], cm[irr], H, rng)
        void.add([*(pit["centre"] + o), 1.8, 0.7, 0.85, pit["yaw"], 0.0], 2, cm[pit["drift"]])


def _void_primitives(g: _Graph, feats: dict, params: WorldParams, rep: dict | None, rng: np.random.Generator):
    """Void primitives (drift segments, roof fall-outs, sump pit) and rough zones of the mine.

    Fills ``feats`` (``irregular_roof``, ``regular``, ``sump``); returns the voids, the rough
    zones, the regular (meshed) drift and the sump pit's site (see :func:`_sump_pit`).
    """
    R = params.width_m / 2.0
    hw = params.wall_height_m
    H = hw + R
    void = _Prims()
    for k, (_a, _b, poly, _kind, _lev) in enumerate(g.edges):
        for i in range(len(poly) - 1):
            void.add([*poly[i], *poly[i + 1], R, hw], 0, k)
    # section types on the first level's main drift: irregular roof, meshed, regular
    irr, reg = _section_drifts(g)
    zones = []
    cav0 = len(void.rows)
    P, s, mid = _fall_outs(void, g.edges[irr][2], irr, H, rng)
    cav1 = len(void.rows)
    zc = P[mid] + np.array([0, 0, H - 0.5])
    zones.append([*zc, 6.0, 0.9])
    feats["irregular_roof"] = {"drift": irr, "s_m": float(s[mid])}
    feats["regular"] = {"drift": reg, "s_m": float(np.linalg.norm(np.diff(g.edges[reg][2], axis=0), axis=1).sum() / 2)}
    # a second, milder rough zone somewhere else on the first level
    par0 = [k for k, e in enumerate(g.edges) if e[3] == "parallel" and e[4] == 0]
    if par0:
        Pp, _, _, _ = _resample(g.edges[par0[0]][2], 1.0)
        zones.append([*(Pp[len(Pp) // 2] + np.array([0, 0, 2.0])), 8.0, 0.5])
    pit = _sump_pit(void, g, feats)
    if rep is not None:
        _repeat_voids(void, zones, g, rep, irr, range(cav0, cav1), pit, H, float(params.level_spacing_m), rng)
    return void, zones, reg, pit


def _bolt_rays(g: _Graph, params: WorldParams, skip: set, mesh_edge: int, rng: np.random.Generator):
    """Rays from the drift axis at wall height to where the rock bolts go.

    Rings every ``bolt_spacing_m`` (none within 3 m of a junction or end, so bolts do not
    float in intersections), 5 bolts over the arch at seeded angles. Returns origins,
    directions, the drift of each ray and the ray indices of each ring of ``mesh_edge``.
    """
    hw = params.wall_height_m
    bolt_ok_kinds = ("main", "parallel", "ramp", "ring", "crosscut", "branch", "heading")
    Os, Ds, Downer = [], [], []
    strap_rings = []
    for k, (_a, _b, poly, kind, _lev) in enumerate(g.edges):
        if kind not in bolt_ok_kinds or k in skip:
            continue
        P, t, n, s = _resample(poly, params.bolt_spacing_m)
        # skip rings within 3 m of a junction/end so bolts do not float in intersections
        L = s[-1] + params.bolt_spacing_m / 2 if len(s) else 0
        keep = (s > 3.0) & (s < L - 3.0)
        for j in np.flatnonzero(keep):
            ring = []
            for ang in (-60.0, -30.0, 0.0, 30.0, 60.0):
                a = math.radians(ang + rng.uniform(-5, 5))
                d = np.array([*(n[j] * math.sin(a)), math.cos(a)])
                Os.append(P[j] + np.array([0, 0, hw]))
                Ds.append(d)
                Downer.append(k)
                ring.append(len(Os) - 1)
            if k == mesh_edge:
                strap_rings.append(ring)
    return Os, Ds, Downer, strap_rings


def _rock_bolts(solid: _Prims, g: _Graph, feats: dict, params: WorldParams, base: dict, skip: set, mesh_edge: int,
                rng: np.random.Generator) -> None:
    """Rock bolts placed on the rough surface of ``base`` and, on ``mesh_edge``, the steel straps
    ("mesh") linking the bolt heads of a ring; sets ``feats["meshed"]``."""
    Os, Ds, Downer, strap_rings = _bolt_rays(g, params, skip, mesh_edge, rng)
    if not Os:
        return
    O = np.array(Os)
    D = np.array(Ds)
    r = _cast_arrays(base, O, D, 6.0, params.trace_step_factor, with_solids=False)
    ok = np.isfinite(r)
    hit = O + D * np.where(ok, r, 0.0)[:, None]
    for i in np.flatnonzero(ok):
        a = hit[i] + D[i] * 0.03  # 3 cm inside the rock
        b = hit[i] - D[i] * 0.07  # plate + nut stand 7 cm proud
        solid.add([*a, *b, 0.06, 0.0], 0, Downer[i])
    for ring in strap_rings:  # "mesh": steel straps linking the bolt heads of a ring
        for u, v in zip(ring[:-1], ring[1:], strict=True):
            if ok[u] and ok[v]:
                a = hit[u] - D[u] * 0.05
                b = hit[v] - D[v] * 0.05
                solid.add([*a, *b, 0.025, 0.0], 0, mesh_edge)
    feats["meshed"] = {"drift": mesh_edge, "s_m": feats["regular"]["s_m"]}


def _services(solid: _Prims, g: _Graph, params: WorldParams, base: dict, skip: set) -> None:
    """Services along main drifts and ramps: pipe (left wall), two cables (right wall), duct under the roof."""
    R = params.width_m / 2.0
    H = params.wall_height_m + R
    for k, (_a, _b, poly, kind, _lev) in enumerate(g.edges):
        if kind not in ("main", "ramp") or k in skip:
            continue
        _, nseg, _ = _frames(poly)
        for lat, hgt, rad in ((R - 0.35, 1.9, 0.08), (-(R - 0.2), 2.55, 0.025), (-(R - 0.2), 2.7, 0.02)):
            Q = _offset_polyline(poly, lat, hgt)
            mids = 0.5 * (Q[:-1] + Q[1:])
            behind = mids + np.column_stack([nseg * math.copysign(0.8, lat), np.zeros(len(mids))])
            open_ = _smooth_field(base, behind) > 0.0  # no wall behind: a junction mouth, the service is routed over it
            for i in np.flatnonzero(~open_):
                solid.add([*Q[i], *Q[i + 1], rad, 0.0], 0, k)
        solid.rows.extend(_capsule_chain(_offset_polyline(poly, -0.9, H - 0.85), 0.4))
        solid.types.extend([0] * (len(poly) - 1))
        solid.owners.extend([k] * (len(poly) - 1))


def _railings(solid: _Prims, pit: dict) -> None:
    """Railings along the sump pit (posts every ~1.2 m, rails at 0.5 m and 1.05 m)."""
    c, yawp, side, sb = pit["centre"], pit["yaw"], pit["side"], pit["drift"]
    ca, sa = math.cos(yawp), math.sin(yawp)
    along = np.array([ca, sa, 0.0])
    across = np.array([-sa, ca, 0.0])
    floor_z = pit["floor"][2]  # the branch is flat: any of its points gives the floor height
    edge_c = np.array([c[0], c[1], floor_z]) - across * side * (0.7 + 0.12)
    posts = [edge_c + along * x for x in np.linspace(-1.8, 1.8, 4)]
    for q in posts:
        solid.add([q[0], q[1], floor_z - 0.05, q[0], q[1], floor_z + 1.05, 0.03, 0.0], 0, sb)
    for hgt in (0.5, 1.05):
        a = posts[0] + np.array([0, 0, hgt])
        b = posts[-1] + np.array([0, 0, hgt])
        solid.add([*a, *b, 0.025, 0.0], 0, sb)


def _repeat_solids(solid: _Prims, rep: dict, rail0: int, dz: float) -> None:
    """Copies on every level copy: every structure of the unit (exact) or the railings (rows
    from ``rail0`` on) only (near)."""
    exact = rep["mode"] == "exact"
    n0 = len(solid.rows)
    for k, cm in rep["copies"].items():
        o6 = np.array([*_level_offset(k, dz), *_level_offset(k, dz), 0.0, 0.0])
        for i in range(n0):
            if (exact and solid.owners[i] in cm) or (not exact and i >= rail0):
                solid.add(list(np.asarray(solid.rows[i], float) + o6), solid.types[i], cm[solid.owners[i]])


def _solid_primitives(g: _Graph, feats: dict, params: WorldParams, base: dict, rep: dict | None, reg: int,
                      pit: dict, rng: np.random.Generator) -> _Prims:
    """Solid structures: rock bolts and straps, services, sump railings and their level copies."""
    exact = rep is not None and rep["mode"] == "exact"
    # structures of an exact level copy are copied from level 0, not placed anew
    skip = {e for cm in rep["copies"].values() for e in cm.values()} if exact else set()
    solid = _Prims()
    _rock_bolts(solid, g, feats, params, base, skip, reg, rng)
    _services(solid, g, params, base, skip)
    rail0 = len(solid.rows)
    _railings(solid, pit)
    if rep is not None:
        _repeat_solids(solid, rep, rail0, float(params.level_spacing_m))
    return solid
