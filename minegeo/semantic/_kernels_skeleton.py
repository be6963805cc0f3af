"""Numba kernels of the intersection knowledge base: thinning, polar binning, shift similarity.

Contiguous arrays in, no checks (the callers in ``skeleton.py`` / ``descriptors.py`` validate).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def zhang_suen(img):
    """Thin a binary image (uint8 0/1, (h, w), border pixels 0) in place to a one-pixel skeleton.

    Zhang & Suen (1984): two sub-iterations, each deleting the boundary pixels p1 with
    2 <= B(p1) <= 6 neighbours, exactly one 0->1 transition A(p1) around p2..p9, and
    p2*p4*p6 = 0, p4*p6*p8 = 0 (first) or p2*p4*p8 = 0, p2*p6*p8 = 0 (second).
    """
    h, w = img.shape
    dele = np.zeros((h * w, 2), np.int64)
    changed = True
    while changed:
        changed = False
        for step in range(2):
            nd = 0
            for i in range(1, h - 1):
                for j in range(1, w - 1):
                    if img[i, j] == 0:
                        continue
                    p2 = img[i - 1, j]
                    p3 = img[i - 1, j + 1]
                    p4 = img[i, j + 1]
                    p5 = img[i + 1, j + 1]
                    p6 = img[i + 1, j]
                    p7 = img[i + 1, j - 1]
                    p8 = img[i, j - 1]
                    p9 = img[i - 1, j - 1]
                    b = p2 + p3 + p4 + p5 + p6 + p7 + p8 + p9
                    if b < 2 or b > 6:
                        continue
                    a = ((p2 == 0 and p3 == 1) + (p3 == 0 and p4 == 1) + (p4 == 0 and p5 == 1)
                         + (p5 == 0 and p6 == 1) + (p6 == 0 and p7 == 1) + (p7 == 0 and p8 == 1)
                         + (p8 == 0 and p9 == 1) + (p9 == 0 and p2 == 1))
                    if a != 1:
                        continue
                    if step == 0:
                        if p2 * p4 * p6 != 0 or p4 * p6 * p8 != 0:
                            continue
                    else:
                        if p2 * p4 * p8 != 0 or p2 * p6 * p8 != 0:
                            continue
                    dele[nd, 0] = i
                    dele[nd, 1] = j
                    nd += 1
            for k in range(nd):
                img[dele[k, 0], dele[k, 1]] = 0
            if nd > 0:
                changed = True
    return img


@njit(cache=True)
def polar_min_range(dx, dy, band, n_bands, n_sectors, radius, r_min, footprint, out):
    """Per (band, sector): the smallest horizontal range of the points in it, or 0 if none within radius.

    ``dx, dy``: horizontal offsets (m) from the invariant point; ``band``: band index per point
    (-1 = not used); sector k covers bearings [k, k + 1) * 2 pi / n_sectors from +x, counter-clockwise.
    A point at range r and bearing t is a disc of radius ``footprint`` (m): it counts in every sector
    overlapping [t - a, t + a], a = atan(footprint / r).
    ``out`` (n_bands, n_sectors) receives the range (m); 0 = no point in [r_min, radius].
    """
    for b in range(n_bands):
        for k in range(n_sectors):
            out[b, k] = np.inf
    two_pi = 2.0 * np.pi
    for i in range(dx.shape[0]):
        b = band[i]
        if b < 0 or b >= n_bands:
            continue
        r = np.sqrt(dx[i] * dx[i] + dy[i] * dy[i])
        if r > radius or r < r_min:
            continue
        t = np.arctan2(dy[i], dx[i])
        a = np.arctan(footprint / r)
        k0 = int(np.floor((t - a) / two_pi * n_sectors))
        k1 = int(np.floor((t + a) / two_pi * n_sectors))
        if k1 - k0 >= n_sectors:
            k1 = k0 + n_sectors - 1
        for kk in range(k0, k1 + 1):
            k = kk % n_sectors
            if r < out[b, k]:
                out[b, k] = r
    for b in range(n_bands):
        for k in range(n_sectors):
            if out[b, k] == np.inf:
                out[b, k] = 0.0
    return out


@njit(cache=True, inline="always")
def _ruzicka_add(x, y, occluded, num, den):
    """One cell of a Ruzicka similarity: ``(num + min(x, y), den + max(x, y))``, or ``(num, den)``
    unchanged when ``occluded`` and the cell is ``x = 0 < y`` (reference wall not seen)."""
    if occluded and x == 0.0 and y > 0.0:
        return num, den
    if x < y:
        return num + x, den + y
    return num + y, den + x


@njit(cache=True)
def shift_ruzicka(a, b, occluded, out):
    """Weighted Ruzicka similarity of ``a`` and ``b`` (n_bands, n) for every circular shift of ``b``.

    ``out[k] = sum min(a_j, b_{j-k}) / sum max(a_j, b_{j-k})`` over all bands and sectors j, where
    with ``occluded`` the cells with ``a = 0 < b_{j-k}`` (reference wall not seen) are left out of both
    sums. ``out[k] = 0`` when the denominator is 0.
    """
    nb, n = a.shape
    for k in range(n):
        num = 0.0
        den = 0.0
        for r in range(nb):
            for j in range(n):
                x = a[r, j]
                jj = j - k
                if jj < 0:
                    jj += n
                num, den = _ruzicka_add(x, b[r, jj], occluded, num, den)
        out[k] = num / den if den > 0.0 else 0.0
    return out


@njit(cache=True)
def fill_gaps(rng, max_gap):
    """Close angular gaps of at most ``max_gap`` empty sectors (0) between two wall sectors, per row,
    circularly, by linear interpolation of the range (m) between the two bounding sectors."""
    nb, n = rng.shape
    for r in range(nb):
        first = -1
        for j in range(n):
            if rng[r, j] > 0.0:
                first = j
                break
        if first < 0:
            continue
        j = first
        for _ in range(n):
            # j is a wall sector: find the next wall sector going counter-clockwise
            g = 1
            while g <= n and rng[r, (j + g) % n] == 0.0:
                g += 1
            if g > n:
                break
            if 1 < g <= max_gap + 1:
                a = rng[r, j]
                b = rng[r, (j + g) % n]
                for t in range(1, g):
                    rng[r, (j + t) % n] = a + (b - a) * t / g
            j = (j + g) % n
            if j == first:
                break
    return rng


@njit(cache=True)
def ruzicka_frac(a, b, shift, occluded):
    """Ruzicka similarity of ``a`` with ``b`` shifted by a real number of sectors ``shift``: the
    shifted reference at sector j is ``b`` linearly interpolated at ``j - shift`` (circularly); the
    occlusion rule of :func:`shift_ruzicka`."""
    nb, n = a.shape
    num = 0.0
    den = 0.0
    for j in range(n):
        x = j - shift
        i0 = int(np.floor(x))
        f = x - i0
        i0 = i0 % n
        i1 = (i0 + 1) % n
        for r in range(nb):
            y = (1.0 - f) * b[r, i0] + f * b[r, i1]
            num, den = _ruzicka_add(a[r, j], y, occluded, num, den)
    return num / den if den > 0.0 else 0.0
