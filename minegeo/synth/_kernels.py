"""Numba kernels of the synthetic mine: signed distance field and sphere tracing.

Conventions (see :mod:`minegeo.synth.world`): the field is **positive in free
space (air), negative in rock or inside a solid structure, zero on the surface**.
Kernels take contiguous float64/int64 arrays and do no validation.

Array layouts
-------------
void_prims (nv, 8), void_type (nv,)
    type 0 drift segment ``ax ay az bx by bz R hw`` (floor centreline from a to b,
    half width R, wall height hw; the arched roof is a half circle of radius R);
    type 1 ellipsoid cavity ``cx cy cz rx ry rz 0 0``;
    type 2 yawed box void ``cx cy cz hx hy hz yaw 0`` (a sump pit).
solid_prims (ns, 8), solid_type (ns,)
    type 0 capsule ``ax ay az bx by bz r 0``; type 1 yawed box ``cx cy cz hx hy hz yaw 0``.
grid
    ``grid_f = [x0, y0, z0, cell]``, ``grid_i = [nx, ny, nz]``; CSR lists
    ``v_start/v_items`` and ``s_start/s_items`` of the primitives near each cell.
noise
    ``waves (K, 4) = wx wy wz phase``; ``octaves (O, 4) = start count amplitude mode``
    (mode 0: overbreak in [0, amplitude], scaled by the zone multiplier;
    mode 1: signed texture in [-amplitude, amplitude]); ``zones (Z, 5) = cx cy cz r boost``.
vehicle
    ``veh_T_inv (4, 4)`` maps world into vehicle coordinates, ``veh_prims (nb, 8)``,
    ``veh_type (nb,)`` solids in the vehicle frame, ``veh_sphere = [cx cy cz r]`` in world.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit, njit_parallel, prange

#: value of the rock part of the field far from any listed void primitive (m)
ROCK_CLAMP_M = -1.2
#: value of the structure part of the field far from any listed solid (m)
SOLID_CLAMP_M = 1.5
#: primitives are listed in every grid cell within this distance of their bounding box (m)
GRID_MARGIN_M = 1.5


@njit
def _drift_inner(px, py, pz, ax, ay, az, bx, by, bz, R, hw):
    """Inner distance (positive inside) of a horseshoe drift segment.

    The section is the intersection of the half-space above the floor (v >= 0) and
    the set within R of the vertical half-line {l = 0, v <= hw}: vertical walls up
    to ``hw`` and a half-circle roof of radius R. ``l`` is the horizontal distance
    to the segment's horizontal projection (radial at the rounded ends), ``v`` the
    height above the floor line interpolated along the segment.
    """
    dx = bx - ax
    dy = by - ay
    L2 = dx * dx + dy * dy
    s = 0.0
    if L2 > 0.0:
        s = ((px - ax) * dx + (py - ay) * dy) / L2
        if s < 0.0:
            s = 0.0
        elif s > 1.0:
            s = 1.0
    cx = ax + s * dx
    cy = ay + s * dy
    cz = az + s * (bz - az)
    qx = px - cx
    qy = py - cy
    lat = math.sqrt(qx * qx + qy * qy)
    v = pz - cz
    if v <= hw:
        dB = R - lat
    else:
        dB = R - math.sqrt(lat * lat + (v - hw) * (v - hw))
    return min(v, dB)


@njit
def _box_sdf(px, py, pz, cx, cy, cz, hx, hy, hz, yaw):
    """Exact signed distance to a box yawed about z (positive outside)."""
    c = math.cos(yaw)
    s = math.sin(yaw)
    x0 = px - cx
    y0 = py - cy
    x = c * x0 + s * y0
    y = -s * x0 + c * y0
    z = pz - cz
    qx = abs(x) - hx
    qy = abs(y) - hy
    qz = abs(z) - hz
    ox = max(qx, 0.0)
    oy = max(qy, 0.0)
    oz = max(qz, 0.0)
    outside = math.sqrt(ox * ox + oy * oy + oz * oz)
    inside = min(max(qx, max(qy, qz)), 0.0)
    return outside + inside


@njit
def _capsule_sdf(px, py, pz, ax, ay, az, bx, by, bz, r):
    """Exact signed distance to a capsule (segment a-b swept by a ball of radius r)."""
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    L2 = dx * dx + dy * dy + dz * dz
    t = 0.0
    if L2 > 0.0:
        t = ((px - ax) * dx + (py - ay) * dy + (pz - az) * dz) / L2
        if t < 0.0:
            t = 0.0
        elif t > 1.0:
            t = 1.0
    qx = px - (ax + t * dx)
    qy = py - (ay + t * dy)
    qz = pz - (az + t * dz)
    return math.sqrt(qx * qx + qy * qy + qz * qz) - r


@njit
def _void_inner(px, py, pz, V, i, typ):
    if typ == 0:
        return _drift_inner(px, py, pz, V[i, 0], V[i, 1], V[i, 2], V[i, 3], V[i, 4], V[i, 5], V[i, 6], V[i, 7])
    if typ == 1:
        qx = (px - V[i, 0]) / V[i, 3]
        qy = (py - V[i, 1]) / V[i, 4]
        qz = (pz - V[i, 2]) / V[i, 5]
        rmin = min(V[i, 3], min(V[i, 4], V[i, 5]))
        return (1.0 - math.sqrt(qx * qx + qy * qy + qz * qz)) * rmin
    return -_box_sdf(px, py, pz, V[i, 0], V[i, 1], V[i, 2], V[i, 3], V[i, 4], V[i, 5], V[i, 6])


@njit
def _solid_sdf(px, py, pz, S, i, typ):
    if typ == 0:
        return _capsule_sdf(px, py, pz, S[i, 0], S[i, 1], S[i, 2], S[i, 3], S[i, 4], S[i, 5], S[i, 6])
    return _box_sdf(px, py, pz, S[i, 0], S[i, 1], S[i, 2], S[i, 3], S[i, 4], S[i, 5], S[i, 6])


@njit
def _octave_sum(px, py, pz, waves, k0, n):
    """Normalised sum ``S = sqrt(2 / n) sum_k sin(k . p + phi_k)`` of one octave's waves ``k0..k0+n-1``."""
    acc = 0.0
    for k in range(k0, k0 + n):
        acc += math.sin(waves[k, 0] * px + waves[k, 1] * py + waves[k, 2] * pz + waves[k, 3])
    return acc * math.sqrt(2.0 / n)


@njit
def _overbreak(px, py, pz, waves, octaves, zones):
    """Overbreak part of the roughness (m), >= 0: the mode-0 octaves times the zone factor.

    Random-phase sums of plane waves per octave: for an octave with ``N`` waves,
    ``S = sqrt(2/N) sum_k sin(w_k . p + phi_k)`` has unit variance and is squashed by
    ``S / sqrt(1 + S^2)`` into (-1, 1). Overbreak octaves (mode 0) contribute
    ``a (1 + squash) / 2`` in [0, a], multiplied by the zone factor
    ``1 + sum_j b_j exp(-|p - c_j|^2 / r_j^2)``.
    """
    mult = 1.0
    for j in range(zones.shape[0]):
        dx = px - zones[j, 0]
        dy = py - zones[j, 1]
        dz = pz - zones[j, 2]
        r2 = zones[j, 3] * zones[j, 3]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < 9.0 * r2:
            mult += zones[j, 4] * math.exp(-d2 / r2)
    ob = 0.0
    for o in range(octaves.shape[0]):
        if octaves[o, 3] != 0.0:
            continue
        S = _octave_sum(px, py, pz, waves, int(octaves[o, 0]), int(octaves[o, 1]))
        ob += mult * octaves[o, 2] * 0.5 * (1.0 + S / math.sqrt(1.0 + S * S))
    return ob


@njit
def _texture(px, py, pz, waves, octaves):
    """Texture part of the roughness (m): mode-1 octaves, ``a S / sqrt(1 + S^2)`` in (-a, a)."""
    tex = 0.0
    for o in range(octaves.shape[0]):
        if octaves[o, 3] == 0.0:
            continue
        S = _octave_sum(px, py, pz, waves, int(octaves[o, 0]), int(octaves[o, 1]))
        tex += octaves[o, 2] * S / math.sqrt(1.0 + S * S)
    return tex


@njit
def _noise_parts(px, py, pz, waves, octaves, zones):
    """Seeded multi-scale roughness (m) as (overbreak part, texture part)."""
    return _overbreak(px, py, pz, waves, octaves, zones), _texture(px, py, pz, waves, octaves)


@njit
def _noise(px, py, pz, waves, octaves, zones):
    """Total roughness (m): overbreak + texture (see :func:`_noise_parts`)."""
    ob, tex = _noise_parts(px, py, pz, waves, octaves, zones)
    return ob + tex


@njit
def noise_parts_many(P, waves, octaves, zones, out_ob, out_tex):
    """Overbreak and texture parts of the roughness at every row of ``P``."""
    for i in prange(P.shape[0]):
        ob, tex = _noise_parts(P[i, 0], P[i, 1], P[i, 2], waves, octaves, zones)
        out_ob[i] = ob
        out_tex[i] = tex


@njit
def _cell_index(px, py, pz, grid_f, grid_i):
    cell = grid_f[3]
    ix = int(math.floor((px - grid_f[0]) / cell))
    iy = int(math.floor((py - grid_f[1]) / cell))
    iz = int(math.floor((pz - grid_f[2]) / cell))
    if ix < 0 or iy < 0 or iz < 0 or ix >= grid_i[0] or iy >= grid_i[1] or iz >= grid_i[2]:
        return -1
    return (ix * grid_i[1] + iy) * grid_i[2] + iz


@njit
def _rock_base(px, py, pz, c, void_prims, void_type, v_start, v_items):
    """Max of the inner distances of the void primitives listed in cell ``c`` (clamped)."""
    best = ROCK_CLAMP_M
    if c >= 0:
        for q in range(v_start[c], v_start[c + 1]):
            i = v_items[q]
            d = _void_inner(px, py, pz, void_prims, i, void_type[i])
            if d > best:
                best = d
    return best


@njit
def _solids(px, py, pz, c, solid_prims, solid_type, s_start, s_items,
            veh_T_inv, veh_prims, veh_type, veh_sphere):
    best = SOLID_CLAMP_M
    if c >= 0:
        for q in range(s_start[c], s_start[c + 1]):
            i = s_items[q]
            d = _solid_sdf(px, py, pz, solid_prims, i, solid_type[i])
            if d < best:
                best = d
    if veh_prims.shape[0] > 0:
        dx = px - veh_sphere[0]
        dy = py - veh_sphere[1]
        dz = pz - veh_sphere[2]
        dsph = math.sqrt(dx * dx + dy * dy + dz * dz) - veh_sphere[3]
        if dsph < best:
            vx = veh_T_inv[0, 0] * px + veh_T_inv[0, 1] * py + veh_T_inv[0, 2] * pz + veh_T_inv[0, 3]
            vy = veh_T_inv[1, 0] * px + veh_T_inv[1, 1] * py + veh_T_inv[1, 2] * pz + veh_T_inv[1, 3]
            vz = veh_T_inv[2, 0] * px + veh_T_inv[2, 1] * py + veh_T_inv[2, 2] * pz + veh_T_inv[2, 3]
            for i in range(veh_prims.shape[0]):
                d = _solid_sdf(vx, vy, vz, veh_prims, i, veh_type[i])
                if d < best:
                    best = d
    return best


@njit
def _sdf_point(px, py, pz, grid_f, grid_i, void_prims, void_type, v_start, v_items,
               solid_prims, solid_type, s_start, s_items, waves, octaves, zones,
               veh_T_inv, veh_prims, veh_type, veh_sphere, with_noise, with_solids):
    c = _cell_index(px, py, pz, grid_f, grid_i)
    rock = _rock_base(px, py, pz, c, void_prims, void_type, v_start, v_items)
    if with_noise:
        rock += _noise(px, py, pz, waves, octaves, zones)
    if with_solids:
        s = _solids(px, py, pz, c, solid_prims, solid_type, s_start, s_items,
                    veh_T_inv, veh_prims, veh_type, veh_sphere)
        if s < rock:
            return s
    return rock


@njit
def sdf_many(P, grid_f, grid_i, void_prims, void_type, v_start, v_items,
             solid_prims, solid_type, s_start, s_items, waves, octaves, zones,
             veh_T_inv, veh_prims, veh_type, veh_sphere, with_noise, with_solids, out):
    """Evaluate the field at every row of ``P`` (n, 3) into ``out`` (n,)."""
    for i in prange(P.shape[0]):
        out[i] = _sdf_point(P[i, 0], P[i, 1], P[i, 2], grid_f, grid_i, void_prims, void_type,
                            v_start, v_items, solid_prims, solid_type, s_start, s_items,
                            waves, octaves, zones, veh_T_inv, veh_prims, veh_type, veh_sphere,
                            with_noise, with_solids)


@njit
def _field_parts(px, py, pz, grid_f, grid_i, void_prims, void_type, v_start, v_items,
                 solid_prims, solid_type, s_start, s_items, veh_T_inv, veh_prims, veh_type, veh_sphere):
    c = _cell_index(px, py, pz, grid_f, grid_i)
    base = _rock_base(px, py, pz, c, void_prims, void_type, v_start, v_items)
    s = _solids(px, py, pz, c, solid_prims, solid_type, s_start, s_items,
                veh_T_inv, veh_prims, veh_type, veh_sphere)
    return base, s


@njit_parallel
def cast_rays(O, D, max_range, step_factor, min_step, max_iter, tol,
              grid_f, grid_i, void_prims, void_type, v_start, v_items,
              solid_prims, solid_type, s_start, s_items, waves, octaves, zones,
              veh_T_inv, veh_prims, veh_type, veh_sphere, with_noise, noise_min, ob_factor, out_t, out_iter):
    """Sphere tracing (Hart 1996) of rays ``O + t D`` (unit D) against the field.

    Three regimes per step. Far from the rock (``g + n_min > 0.1`` with ``g`` the smooth
    void distance, Lipschitz <= 1/cos(8 deg), and ``n_min`` the lowest texture value)
    the cheap bound ``b = min(g + n_min, s)`` (``s``: exact structure distance) is a
    lower bound of the rough field, and ``t <- t + 0.97 b`` cannot cross the surface.
    Closer, the overbreak ``n_ob`` is evaluated: ``b2 = g + n_ob + n_min`` bounds the
    field from below and has Lipschitz constant ``1/ob_factor`` (smooth part plus the
    slowly varying overbreak), so ``t <- t + min(ob_factor b2, 0.97 s)`` is safe while
    ``b2, s > 0.02 m``. At the last centimetres the full field ``f`` (with the
    fast-varying texture) is used: ``t <- t + max(step_factor f, min_step)``. When ``f <= 0`` the crossing is bracketed and refined by bisection
    until the bracket is below ``tol``; the free-space end of the bracket is returned,
    so ``|f(hit)| <= ~tol``. ``out_t[i]`` is the range (m) or NaN when nothing is hit
    within ``max_range`` (or the origin is in rock, or ``max_iter`` is reached);
    ``out_iter[i]`` the number of marching steps taken (a cost diagnostic).
    """
    for i in prange(O.shape[0]):
        ox = O[i, 0]
        oy = O[i, 1]
        oz = O[i, 2]
        dx = D[i, 0]
        dy = D[i, 1]
        dz = D[i, 2]
        result = np.nan
        n_it = 0
        t_prev = 0.0
        t = 0.0
        for it in range(max_iter):
            n_it = it + 1
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            base, s = _field_parts(px, py, pz, grid_f, grid_i, void_prims, void_type, v_start, v_items,
                                   solid_prims, solid_type, s_start, s_items,
                                   veh_T_inv, veh_prims, veh_type, veh_sphere)
            lb = base + noise_min
            if s < lb:
                lb = s
            if lb > 0.1:
                step = 0.97 * lb
            else:
                lb2 = base
                ob = 0.0
                if with_noise:
                    ob = _overbreak(px, py, pz, waves, octaves, zones)
                    lb2 += ob + noise_min
                if lb2 > 0.02 and s > 0.02:
                    f = lb2  # f >= lb2 > 0: no crossing here, the texture is not needed
                else:
                    f = base
                    if with_noise:
                        f += ob + _texture(px, py, pz, waves, octaves)
                    if s < f:
                        f = s
                if f <= 0.0:
                    if it == 0:
                        break  # origin inside rock or a structure
                    lo = t_prev
                    hi = t
                    for _k in range(64):
                        if hi - lo <= tol:
                            break
                        mid = 0.5 * (lo + hi)
                        fm = _sdf_point(ox + mid * dx, oy + mid * dy, oz + mid * dz, grid_f, grid_i,
                                        void_prims, void_type, v_start, v_items, solid_prims,
                                        solid_type, s_start, s_items, waves, octaves, zones,
                                        veh_T_inv, veh_prims, veh_type, veh_sphere, with_noise, True)
                        if fm > 0.0:
                            lo = mid
                        else:
                            hi = mid
                    result = lo
                    break
                if lb2 > 0.02 and s > 0.02:
                    # smooth part + overbreak with its own Lipschitz bound: larger safe steps
                    step = ob_factor * lb2
                    if 0.97 * s < step:
                        step = 0.97 * s
                else:
                    step = step_factor * f
                    if step < min_step:
                        step = min_step
            if t >= max_range:
                break
            t_prev = t
            t = t + step
            if t > max_range:
                t = max_range
        out_t[i] = result
        out_iter[i] = n_it
