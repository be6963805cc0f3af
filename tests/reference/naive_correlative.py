"""Naive twin of minegeo.localize._kernels: occupancy as a Python set, placements scored one by one."""

from __future__ import annotations

import math


def dilated_cells(points, cell, radius):
    occ = {(math.floor(x / cell), math.floor(y / cell), math.floor(z / cell)) for x, y, z in points}
    out = set()
    for ix, iy, iz in occ:
        for dx in range(-radius, radius + 1):
            for dy in range(-radius, radius + 1):
                for dz in range(-radius, radius + 1):
                    out.add((ix + dx, iy + dy, iz + dz))
    return out


def score_placements(cells, cell, S, anchors, yaws):
    """Hit count of every (anchor, yaw) placement ``Rz(yaw) s + a`` (no early stop)."""
    out = []
    for a in anchors:
        row = []
        for psi in yaws:
            c, s = math.cos(psi), math.sin(psi)
            hits = 0
            for x, y, z in S:
                p = (c * x - s * y + a[0], s * x + c * y + a[1], z + a[2])
                hits += (math.floor(p[0] / cell), math.floor(p[1] / cell), math.floor(p[2] / cell)) in cells
            row.append(hits)
        out.append(row)
    return out


def nearest_grid(Q, cell, band):
    """Every cell within Chebyshev distance ``band`` of a point's cell -> index of the point
    nearest to the cell centre among those points (ties: the lower index)."""
    best = {}
    for j, (x, y, z) in enumerate(Q):
        c = (math.floor(x / cell), math.floor(y / cell), math.floor(z / cell))
        for dx in range(-band, band + 1):
            for dy in range(-band, band + 1):
                for dz in range(-band, band + 1):
                    k = (c[0] + dx, c[1] + dy, c[2] + dz)
                    centre = ((k[0] + 0.5) * cell, (k[1] + 0.5) * cell, (k[2] + 0.5) * cell)
                    d = sum((a - b) ** 2 for a, b in zip(centre, (x, y, z), strict=True))
                    if k not in best or d < best[k][0]:
                        best[k] = (d, j)
    return {k: j for k, (d, j) in best.items()}
