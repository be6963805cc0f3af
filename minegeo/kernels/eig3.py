"""3x3 symmetric eigen-solvers and the PCA of a neighbourhood covariance ([Baek2022 Eq. 2]).

Three genuinely different solvers are kept, each because a caller's numbers depend on it:

* :func:`fast_eigen3x3` -- Eberly's closed form ported operation by operation from Open3D 0.20
  ``FastEigen3x3`` (mode "open3d" normals reproduce Open3D bit for bit; GICP's normals of
  covariances).
* :func:`jacobi_eigh3` -- cyclic Jacobi with the Demmel-Veselic stopping rule (mode "minegeo"
  normals: eigenvalues to high relative accuracy, where the closed form loses digits for thin
  planes). Its sweeps run on scalars (:func:`jacobi3_sweeps`); :func:`jacobi_min3` (and
  :func:`jacobi_min3_x2`, two matrices interleaved) return only the smallest eigenvector and the
  eigenvalues, the same bits, for GICP's covariance kernel.
* LAPACK ``np.linalg.eigh`` (:func:`pca_normals_eigh_rows`) -- the point-to-plane ICP target
  normals; kept because its eigenvector signs (LAPACK's) enter the ICP results.

:func:`pca_normal` is the one neighbourhood PCA (covariance + solver + status) of
:mod:`minegeo.geometry.normals` and GICP's kNN normals. Contiguous arrays in, no checks.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit

__all__ = ["centred_covariance", "fast_eigen3x3", "jacobi_eigh3", "jacobi3_sweeps", "jacobi_min3", "jacobi_min3_x2", "pca_normal",
           "pca_normals_eigh_rows", "store_normal", "store_too_few",
           "STATUS_OK", "STATUS_TOO_FEW", "STATUS_COLLINEAR", "STATUS_COINCIDENT"]


@njit
def _ev0(a00, a01, a02, a11, a12, a22, lam):
    """Eberly's ComputeEigenvector0 (as in Open3D 0.20): most robust row cross product."""
    r00 = a00 - lam
    r01 = a01
    r02 = a02
    r10 = a01
    r11 = a11 - lam
    r12 = a12
    r20 = a02
    r21 = a12
    r22 = a22 - lam
    # r0 x r1
    x0 = r01 * r12 - r02 * r11
    x1 = r02 * r10 - r00 * r12
    x2 = r00 * r11 - r01 * r10
    # r0 x r2
    y0 = r01 * r22 - r02 * r21
    y1 = r02 * r20 - r00 * r22
    y2 = r00 * r21 - r01 * r20
    # r1 x r2
    z0 = r11 * r22 - r12 * r21
    z1 = r12 * r20 - r10 * r22
    z2 = r10 * r21 - r11 * r20
    d0 = x0 * x0 + x1 * x1 + x2 * x2
    d1 = y0 * y0 + y1 * y1 + y2 * y2
    d2 = z0 * z0 + z1 * z1 + z2 * z2
    dmax = d0
    imax = 0
    if d1 > dmax:
        dmax = d1
        imax = 1
    if d2 > dmax:
        imax = 2
    if imax == 0:
        s = np.sqrt(d0)
        return x0 / s, x1 / s, x2 / s
    elif imax == 1:
        s = np.sqrt(d1)
        return y0 / s, y1 / s, y2 / s
    s = np.sqrt(d2)
    return z0 / s, z1 / s, z2 / s


@njit
def _unit_pair(a, b):
    """``(a, b) / |(a, b)|`` as Open3D's ``ComputeEigenvector1`` computes it: divide by the
    larger magnitude ``t``, then scale by ``1 / sqrt(1 + t²)`` (no overflow)."""
    if abs(a) >= abs(b):
        b /= a
        a = 1.0 / np.sqrt(1.0 + b * b)
        b *= a
    else:
        a /= b
        b = 1.0 / np.sqrt(1.0 + a * a)
        a *= b
    return a, b


@njit
def _ev1(a00, a01, a02, a11, a12, a22, e0, e1, e2, lam):
    """Eberly's ComputeEigenvector1 (as in Open3D 0.20)."""
    if abs(e0) > abs(e1):
        inv = 1.0 / np.sqrt(e0 * e0 + e2 * e2)
        u0 = -e2 * inv
        u1 = 0.0
        u2 = e0 * inv
    else:
        inv = 1.0 / np.sqrt(e1 * e1 + e2 * e2)
        u0 = 0.0
        u1 = e2 * inv
        u2 = -e1 * inv
    # V = e x U
    v0 = e1 * u2 - e2 * u1
    v1 = e2 * u0 - e0 * u2
    v2 = e0 * u1 - e1 * u0
    au0 = a00 * u0 + a01 * u1 + a02 * u2
    au1 = a01 * u0 + a11 * u1 + a12 * u2
    au2 = a02 * u0 + a12 * u1 + a22 * u2
    av0 = a00 * v0 + a01 * v1 + a02 * v2
    av1 = a01 * v0 + a11 * v1 + a12 * v2
    av2 = a02 * v0 + a12 * v1 + a22 * v2
    m00 = u0 * au0 + u1 * au1 + u2 * au2 - lam
    m01 = u0 * av0 + u1 * av1 + u2 * av2
    m11 = v0 * av0 + v1 * av1 + v2 * av2 - lam
    am00 = abs(m00)
    am01 = abs(m01)
    am11 = abs(m11)
    if am00 >= am11:
        if max(am00, am01) > 0.0:
            m00, m01 = _unit_pair(m00, m01)
            return m01 * u0 - m00 * v0, m01 * u1 - m00 * v1, m01 * u2 - m00 * v2
        return u0, u1, u2
    if max(am11, am01) > 0.0:
        m11, m01 = _unit_pair(m11, m01)
        return m11 * u0 - m01 * v0, m11 * u1 - m01 * v1, m11 * u2 - m01 * v2
    return u0, u1, u2


@njit
def fast_eigen3x3(c00, c01, c02, c11, c12, c22, out):
    """Open3D 0.20 ``FastEigen3x3`` (Eberly's robust closed form), ported operation by operation.

    Writes the eigenvector of the smallest eigenvalue to ``out[0:3]`` (the zero vector
    when the largest signed entry is 0) and the three eigenvalues, ascending, to
    ``out[3:6]`` (not part of Open3D's output; used for curvature).
    """
    s = max(c00, c01, c02, c11, c12, c22)  # largest signed entry of the symmetric matrix
    if s == 0.0:
        for j in range(6):
            out[j] = 0.0
        return
    a00 = c00 / s
    a01 = c01 / s
    a02 = c02 / s
    a11 = c11 / s
    a12 = c12 / s
    a22 = c22 / s
    norm = a01 * a01 + a02 * a02 + a12 * a12
    if norm > 0.0:
        q = (a00 + a11 + a22) / 3.0
        b00 = a00 - q
        b11 = a11 - q
        b22 = a22 - q
        p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + norm * 2.0) / 6.0)
        k00 = b11 * b22 - a12 * a12
        k01 = a01 * b22 - a12 * a02
        k02 = a01 * a12 - b11 * a02
        det = (b00 * k00 - a01 * k01 + a02 * k02) / (p * p * p)
        half_det = det * 0.5
        half_det = min(max(half_det, -1.0), 1.0)
        angle = np.arccos(half_det) / 3.0
        beta2 = np.cos(angle) * 2.0
        beta0 = np.cos(angle + 2.09439510239319549) * 2.0
        beta1 = -(beta0 + beta2)
        l0 = q + p * beta0
        l1 = q + p * beta1
        l2 = q + p * beta2
        if half_det >= 0.0:
            v20, v21, v22 = _ev0(a00, a01, a02, a11, a12, a22, l2)
            if l2 < l0 and l2 < l1:
                n0, n1, n2 = v20, v21, v22
            else:
                v10, v11, v12 = _ev1(a00, a01, a02, a11, a12, a22, v20, v21, v22, l1)
                if l1 < l0 and l1 < l2:
                    n0, n1, n2 = v10, v11, v12
                else:
                    n0 = v11 * v22 - v12 * v21
                    n1 = v12 * v20 - v10 * v22
                    n2 = v10 * v21 - v11 * v20
        else:
            v00, v01, v02 = _ev0(a00, a01, a02, a11, a12, a22, l0)
            if l0 < l1 and l0 < l2:
                n0, n1, n2 = v00, v01, v02
            else:
                v10, v11, v12 = _ev1(a00, a01, a02, a11, a12, a22, v00, v01, v02, l1)
                if l1 < l0 and l1 < l2:
                    n0, n1, n2 = v10, v11, v12
                else:
                    n0 = v01 * v12 - v02 * v11
                    n1 = v02 * v10 - v00 * v12
                    n2 = v00 * v11 - v01 * v10
        e0 = l0 * s
        e1 = l1 * s
        e2 = l2 * s
    else:
        if c00 < c11 and c00 < c22:
            n0, n1, n2 = 1.0, 0.0, 0.0
        elif c11 < c00 and c11 < c22:
            n0, n1, n2 = 0.0, 1.0, 0.0
        else:
            n0, n1, n2 = 0.0, 0.0, 1.0
        e0 = c00
        e1 = c11
        e2 = c22
    out[0] = n0
    out[1] = n1
    out[2] = n2
    # eigenvalues ascending (three-element sorting network)
    if e0 > e1:
        e0, e1 = e1, e0
    if e1 > e2:
        e1, e2 = e2, e1
    if e0 > e1:
        e0, e1 = e1, e0
    out[3] = e0
    out[4] = e1
    out[5] = e2


_EPS = 2.220446049250313e-16


@njit(inline="always")
def _jacobi_rot(app, aqq, apq, arp, arq):
    """One Jacobi rotation zeroing ``a_pq`` (Numerical Recipes 3rd ed., Sec. 11.1,
    [NumericalRecipes2007 Eqs. 11.1.8-11.1.18]): ``(c, s, new a_rp, new a_rq, new a_pp, new a_qq)``."""
    theta = (aqq - app) / (2.0 * apq)
    if abs(theta) > 1e150:
        t = 0.5 / theta
    else:
        t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
        if theta < 0.0:
            t = -t
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    return c, s, c * arp - s * arq, s * arp + c * arq, app - t * apq, aqq + t * apq



@njit(inline="always")
def _jac01(st):
    """Rotation (p, q, r) = (0, 1, 2) of a sweep on the scalars ``st = (a00, a01, a02, a11, a12, a22,
    v00, .., v22)``, skipped when ``a01`` is 0 or below the Demmel-Veselic test (then set to 0):
    ``(rotated, a.., v..)``."""
    a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22 = st
    rot = False
    if a01 != 0.0:
        if abs(a01) <= _EPS * np.sqrt(abs(a00 * a11)):
            a01 = 0.0
        else:
            rot = True
            c, s, a02, a12, a00, a11 = _jacobi_rot(a00, a11, a01, a02, a12)
            a01 = 0.0
            v00, v01 = c * v00 - s * v01, s * v00 + c * v01
            v10, v11 = c * v10 - s * v11, s * v10 + c * v11
            v20, v21 = c * v20 - s * v21, s * v20 + c * v21
    return rot, a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22


@njit(inline="always")
def _jac02(st):
    """Rotation (0, 2, 1) of a sweep (as :func:`_jac01`)."""
    a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22 = st
    rot = False
    if a02 != 0.0:
        if abs(a02) <= _EPS * np.sqrt(abs(a00 * a22)):
            a02 = 0.0
        else:
            rot = True
            c, s, a01, a12, a00, a22 = _jacobi_rot(a00, a22, a02, a01, a12)
            a02 = 0.0
            v00, v02 = c * v00 - s * v02, s * v00 + c * v02
            v10, v12 = c * v10 - s * v12, s * v10 + c * v12
            v20, v22 = c * v20 - s * v22, s * v20 + c * v22
    return rot, a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22


@njit(inline="always")
def _jac12(st):
    """Rotation (1, 2, 0) of a sweep (as :func:`_jac01`)."""
    a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22 = st
    rot = False
    if a12 != 0.0:
        if abs(a12) <= _EPS * np.sqrt(abs(a11 * a22)):
            a12 = 0.0
        else:
            rot = True
            c, s, a01, a02, a11, a22 = _jacobi_rot(a11, a22, a12, a01, a02)
            a12 = 0.0
            v01, v02 = c * v01 - s * v02, s * v01 + c * v02
            v11, v12 = c * v11 - s * v12, s * v11 + c * v12
            v21, v22 = c * v21 - s * v22, s * v21 + c * v22
    return rot, a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22


@njit(inline="always")
def _jac_result(a00, a11, a22, v00, v01, v02, v10, v11, v12, v20, v21, v22):
    """The ascending sort of :func:`jacobi_eigh3` (strict comparisons): ``(eigenvector of the smallest
    eigenvalue, the eigenvalues ascending)``."""
    d = (a00, a11, a22)
    i0 = 0
    i1 = 1
    i2 = 2
    if d[i0] > d[i1]:
        i0, i1 = i1, i0
    if d[i1] > d[i2]:
        i1, i2 = i2, i1
    if d[i0] > d[i1]:
        i0, i1 = i1, i0
    if i0 == 0:
        return v00, v10, v20, d[i0], d[i1], d[i2]
    if i0 == 1:
        return v01, v11, v21, d[i0], d[i1], d[i2]
    return v02, v12, v22, d[i0], d[i1], d[i2]


@njit
def jacobi3_sweeps(a00, a01, a02, a11, a12, a22):
    """Cyclic Jacobi sweeps of the symmetric 3x3 with upper triangle ``a00 .. a22`` (rotations
    (0,1), (0,2), (1,2); a sweep without a rotation ends it, at most 50): the final
    ``(a00, a01, a02, a11, a12, a22, v00, v01, v02, v10, .., v22)``, diagonal = eigenvalues
    (unsorted), ``V`` (row-major) = the eigenvectors in columns."""
    a = (a00, a01, a02, a11, a12, a22, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    for _sweep in range(50):
        s = _jac01(a)
        r = s[0]
        a = s[1:]
        s = _jac02(a)
        r = r or s[0]
        a = s[1:]
        s = _jac12(a)
        r = r or s[0]
        a = s[1:]
        if not r:
            break
    return a


@njit
def jacobi_min3(a00, a01, a02, a11, a12, a22):
    """:func:`jacobi_eigh3` on scalars (the same sweeps and sort, :func:`jacobi3_sweeps`):
    ``(eigenvector of the smallest eigenvalue, the three eigenvalues ascending)``."""
    a = jacobi3_sweeps(a00, a01, a02, a11, a12, a22)
    return _jac_result(a[0], a[3], a[5], a[6], a[7], a[8], a[9], a[10], a[11], a[12], a[13], a[14])


@njit
def jacobi_min3_x2(A, B):
    """:func:`jacobi_min3` of two matrices (6-tuples ``a00, a01, a02, a11, a12, a22``) with their
    rotations interleaved, so that the two chains of divisions and square roots overlap; each matrix
    goes through exactly its own sweeps (same bits as one at a time)."""
    a = (A[0], A[1], A[2], A[3], A[4], A[5], 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    b = (B[0], B[1], B[2], B[3], B[4], B[5], 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    da = False
    db = False
    for _sweep in range(50):
        ra = False
        rb = False
        if not da:
            s = _jac01(a)
            ra = ra or s[0]
            a = s[1:]
        if not db:
            s = _jac01(b)
            rb = rb or s[0]
            b = s[1:]
        if not da:
            s = _jac02(a)
            ra = ra or s[0]
            a = s[1:]
        if not db:
            s = _jac02(b)
            rb = rb or s[0]
            b = s[1:]
        if not da:
            s = _jac12(a)
            ra = ra or s[0]
            a = s[1:]
        if not db:
            s = _jac12(b)
            rb = rb or s[0]
            b = s[1:]
        da = da or not ra
        db = db or not rb
        if da and db:
            break
    return (_jac_result(a[0], a[3], a[5], a[6], a[7], a[8], a[9], a[10], a[11], a[12], a[13], a[14]),
            _jac_result(b[0], b[3], b[5], b[6], b[7], b[8], b[9], b[10], b[11], b[12], b[13], b[14]))


@njit
def jacobi_eigh3(A, V, w):
    """Cyclic Jacobi eigen-decomposition of the symmetric 3x3 ``A`` (its upper triangle is read).

    On return ``w`` holds the eigenvalues ascending and the columns of ``V`` the matching
    orthonormal eigenvectors; ``A`` is not modified. A rotation (p, q) is applied while
    ``|a_pq| > eps * sqrt(|a_pp a_qq|)`` (Demmel-Veselic stopping rule, which gives
    eigenvalues to high relative accuracy); the sweep loop ends when no rotation was
    needed (at most 50 sweeps; 3x3 matrices converge in a handful): :func:`jacobi3_sweeps`.
    Rotation formulas: Numerical Recipes 3rd ed., Sec. 11.1, [NumericalRecipes2007 Eqs. 11.1.8-11.1.18].
    """
    a = jacobi3_sweeps(A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2])
    d = (a[0], a[3], a[5])
    i0 = 0
    i1 = 1
    i2 = 2
    if d[i0] > d[i1]:  # sort ascending, permuting the eigenvector columns along
        i0, i1 = i1, i0
    if d[i1] > d[i2]:
        i1, i2 = i2, i1
    if d[i0] > d[i1]:
        i0, i1 = i1, i0
    for m in range(3):
        V[m, 0] = a[6 + 3 * m + i0]
        V[m, 1] = a[6 + 3 * m + i1]
        V[m, 2] = a[6 + 3 * m + i2]
    w[0] = d[i0]
    w[1] = d[i1]
    w[2] = d[i2]


# ---------------------------------------------------------------------------------------
# normals (PCA of a neighbourhood; [Baek2022 Eq. 2])
# ---------------------------------------------------------------------------------------

STATUS_OK = 0
STATUS_TOO_FEW = 1
STATUS_COLLINEAR = 2
STATUS_COINCIDENT = 3


@njit(inline="always")
def centred_covariance(points, nbr, cnt, qi):
    """Covariance of the ``cnt >= 1`` neighbour rows ``nbr[:cnt]`` of ``points`` ([Baek2022 Eq. 2]):
    two-pass, the differences taken from the query point ``points[qi]`` (no cancellation at large
    coordinates), then centred on their mean ``m``; ``C = (1/cnt) sum_j (d_j - m)(d_j - m)^T`` with
    ``d_j = p_j - q`` (m^2), returned as the scalars ``(c00, c01, c02, c11, c12, c22)``."""
    q0 = points[qi, 0]
    q1 = points[qi, 1]
    q2 = points[qi, 2]
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for j in range(cnt):
        p = nbr[j]
        m0 += points[p, 0] - q0
        m1 += points[p, 1] - q1
        m2 += points[p, 2] - q2
    fn = float(cnt)
    m0 /= fn
    m1 /= fn
    m2 /= fn
    c00 = 0.0
    c01 = 0.0
    c02 = 0.0
    c11 = 0.0
    c12 = 0.0
    c22 = 0.0
    for j in range(cnt):
        p = nbr[j]
        x = (points[p, 0] - q0) - m0
        y = (points[p, 1] - q1) - m1
        z = (points[p, 2] - q2) - m2
        c00 += x * x
        c01 += x * y
        c02 += x * z
        c11 += y * y
        c12 += y * z
        c22 += z * z
    return c00 / fn, c01 / fn, c02 / fn, c11 / fn, c12 / fn, c22 / fn


@njit(inline="always")
def store_too_few(oi, out_n, out_eval, out_status):
    """Output row ``oi`` of a point with fewer than 3 neighbours: normal ``(0, 0, 1)``, NaN
    eigenvalues, :data:`STATUS_TOO_FEW`."""
    out_n[oi, 0] = 0.0
    out_n[oi, 1] = 0.0
    out_n[oi, 2] = 1.0
    out_eval[oi, 0] = np.nan
    out_eval[oi, 1] = np.nan
    out_eval[oi, 2] = np.nan
    out_status[oi] = STATUS_TOO_FEW


@njit(inline="always")
def store_normal(oi, n0, n1, n2, l0, l1, l2, degenerate_ratio, keep_coincident, out_n, out_eval, out_status):
    """Output row ``oi`` of a neighbourhood PCA: normal ``n``, eigenvalues ``l0 <= l1 <= l2`` and the
    status: :data:`STATUS_COINCIDENT` when ``l2 <= 0`` (the normal then ``(0, 0, 1)`` unless
    ``keep_coincident``, Open3D's convention), :data:`STATUS_COLLINEAR` when
    ``l1 <= degenerate_ratio * l2``, else :data:`STATUS_OK`."""
    status = STATUS_OK
    if l2 <= 0.0:
        status = STATUS_COINCIDENT
        if not keep_coincident:
            n0 = 0.0
            n1 = 0.0
            n2 = 1.0
    elif l1 <= degenerate_ratio * l2:
        status = STATUS_COLLINEAR
    out_n[oi, 0] = n0
    out_n[oi, 1] = n1
    out_n[oi, 2] = n2
    out_eval[oi, 0] = l0
    out_eval[oi, 1] = l1
    out_eval[oi, 2] = l2
    out_status[oi] = status


@njit
def pca_normal(points, nbr, cnt, qi, oi, mode_open3d, degenerate_ratio, A, V, w, tmp,
                           out_n, out_eval, out_status):
    """PCA normal of the point at row ``qi`` of ``points`` from the ``cnt`` neighbour rows in
    ``nbr``; results go to output row ``oi``.

    mode_open3d: raw-moment covariance in absolute coordinates + FastEigen3x3 (Open3D 0.20).
    otherwise: covariance centred on the query point then on the neighbourhood mean
    (two-pass), eigen-decomposed with cyclic Jacobi.
    """
    if cnt < 3:
        store_too_few(oi, out_n, out_eval, out_status)
        return
    if mode_open3d:
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s00 = 0.0
        s01 = 0.0
        s02 = 0.0
        s11 = 0.0
        s12 = 0.0
        s22 = 0.0
        for j in range(cnt):
            p = nbr[j]
            x = points[p, 0]
            y = points[p, 1]
            z = points[p, 2]
            s0 += x
            s1 += y
            s2 += z
            s00 += x * x
            s01 += x * y
            s02 += x * z
            s11 += y * y
            s12 += y * z
            s22 += z * z
        fn = float(cnt)
        s0 /= fn
        s1 /= fn
        s2 /= fn
        s00 /= fn
        s01 /= fn
        s02 /= fn
        s11 /= fn
        s12 /= fn
        s22 /= fn
        c00 = s00 - s0 * s0
        c11 = s11 - s1 * s1
        c22 = s22 - s2 * s2
        c01 = s01 - s0 * s1
        c02 = s02 - s0 * s2
        c12 = s12 - s1 * s2
        fast_eigen3x3(c00, c01, c02, c11, c12, c22, tmp)
        n0 = tmp[0]
        n1 = tmp[1]
        n2 = tmp[2]
        if n0 == 0.0 and n1 == 0.0 and n2 == 0.0:
            n2 = 1.0
        l0 = tmp[3]
        l1 = tmp[4]
        l2 = tmp[5]
    else:
        c00, c01, c02, c11, c12, c22 = centred_covariance(points, nbr, cnt, qi)
        A[0, 0] = c00
        A[0, 1] = c01
        A[0, 2] = c02
        A[1, 0] = c01
        A[1, 1] = c11
        A[1, 2] = c12
        A[2, 0] = c02
        A[2, 1] = c12
        A[2, 2] = c22
        jacobi_eigh3(A, V, w)
        n0 = V[0, 0]
        n1 = V[1, 0]
        n2 = V[2, 0]
        nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        n0 /= nn
        n1 /= nn
        n2 /= nn
        l0 = w[0]
        l1 = w[1]
        l2 = w[2]
    store_normal(oi, n0, n1, n2, l0, l1, l2, degenerate_ratio, mode_open3d, out_n, out_eval, out_status)


@njit
def pca_normals_eigh_rows(Q, nb, out, start, end):
    """Unit normal of rows ``start .. end-1`` of the (m, k) neighbour index array ``nb`` into
    ``Q``: eigenvector of the smallest eigenvalue of the two-pass centred neighbourhood covariance
    (unnormalised; [Baek2022 Eq. 2]) by LAPACK ``np.linalg.eigh``; sign as returned by LAPACK."""
    k = nb.shape[1]
    C = np.empty((3, 3))
    for i in range(start, end):
        mx = 0.0
        my = 0.0
        mz = 0.0
        for a in range(k):
            j = nb[i, a]
            mx += Q[j, 0]
            my += Q[j, 1]
            mz += Q[j, 2]
        mx /= k
        my /= k
        mz /= k
        for r in range(3):
            for c in range(3):
                C[r, c] = 0.0
        for a in range(k):
            j = nb[i, a]
            dx = Q[j, 0] - mx
            dy = Q[j, 1] - my
            dz = Q[j, 2] - mz
            C[0, 0] += dx * dx
            C[0, 1] += dx * dy
            C[0, 2] += dx * dz
            C[1, 1] += dy * dy
            C[1, 2] += dy * dz
            C[2, 2] += dz * dz
        C[1, 0] = C[0, 1]
        C[2, 0] = C[0, 2]
        C[2, 1] = C[1, 2]
        _, V = np.linalg.eigh(C)
        out[i, 0] = V[0, 0]
        out[i, 1] = V[1, 0]
        out[i, 2] = V[2, 0]
