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
