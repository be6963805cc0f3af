"""Unit quaternion <-> rotation matrix conversions used by the trajectory formats.

Convention: Hamilton quaternions, stored **x, y, z, w** (vector first, scalar last) as in
the TUM RGB-D and ROS formats, unless ``order="wxyz"`` (scalar first, e.g. GeoSLAM
``q0 q1 q2 q3``). A quaternion ``q`` and ``-q`` are the same rotation;
:func:`matrix_to_quat` returns the representative with ``w >= 0``.

References
----------
Shuster, M. D. (1993). A survey of attitude representations. J. Astronautical Sciences
41(4), 439-517 -- [Shuster1993 Eq. 161] (matrix of a Hamilton quaternion, passive/active note below).
Shepperd, S. W. (1978). Quaternion from rotation matrix. J. Guidance and Control 1(3),
223-224 -- the largest-diagonal branch selection used in :func:`matrix_to_quat`.

The checks every trajectory reader shares for its rotations live here:
:func:`rotation_problem` (orthonormal within :data:`ROTATION_TOLERANCE`, ``det R > 0``; a reflection
named as such) and :func:`quaternion_problem` (finite, norm 1 within
:data:`QUATERNION_NORM_TOLERANCE`; a zero quaternion named as such). :func:`normalize_quat` and
:func:`matrix_to_quat` refuse what they refuse.

Notes
-----
The matrix is the *active* rotation ``p' = R p`` (the usual robotics convention, identical
to ``scipy.spatial.transform.Rotation.from_quat(q).as_matrix()``):

.. math::

    R(q) = \\begin{pmatrix}
        1 - 2(y^2 + z^2) & 2(xy - wz) & 2(xz + wy) \\\\
        2(xy + wz) & 1 - 2(x^2 + z^2) & 2(yz - wx) \\\\
        2(xz - wy) & 2(yz + wx) & 1 - 2(x^2 + y^2)
    \\end{pmatrix}
"""

from __future__ import annotations

import numpy as np

from minegeo.errors import InputError

__all__ = ["quat_to_matrix", "matrix_to_quat", "normalize_quat", "rotation_problem", "quaternion_problem",
           "ROTATION_TOLERANCE", "QUATERNION_NORM_TOLERANCE"]

#: largest ``max |R^T R - I|`` of a rotation block read or written (KITTI files print 6-7 digits: ~1e-6)
ROTATION_TOLERANCE = 1e-4
#: largest ``| |q| - 1 |`` of a quaternion read (it is then renormalised); files print few digits
QUATERNION_NORM_TOLERANCE = 1e-2


def _reorder_in(q: np.ndarray, order: str) -> np.ndarray:
    if order == "xyzw":
        return q
    if order == "wxyz":
        return q[..., [1, 2, 3, 0]]
    raise InputError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")


def rotation_problem(R, tol: float = ROTATION_TOLERANCE) -> tuple[int, str] | None:
    """The first rotation block that is not a proper rotation: ``(index, sentence)``, or None.

    A proper rotation has ``max |R^T R - I| <= tol`` (orthonormal) and ``det R > 0``; together these
    give ``|det R - 1| <= 3 tol`` to first order. An orthonormal block with ``det R = -1`` is a
    reflection (a mirrored axis: a left-handed frame or a sign error), named as such.

    Parameters
    ----------
    R : (m, 3, 3) array_like
        Rotation blocks.
    tol : float
        Orthonormality tolerance (default :data:`ROTATION_TOLERANCE`).
    """
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.abs(np.einsum("mji,mjk->mik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R) if np.isfinite(R).all() else np.full(R.shape[0], np.nan)
    ok = np.isfinite(R).all(axis=(1, 2)) & (err <= tol) & (det > 0.0)
    if ok.all():
        return None
    i = int(np.flatnonzero(~ok)[0])
    if not np.isfinite(R[i]).all():
        return i, "the rotation block holds NaN or inf"
    if err[i] <= tol:
        return i, (f"the rotation block is a reflection (det R = {det[i]:.6g}), not a rotation: one axis is "
                   "mirrored (a left-handed frame, or a sign error in a row or column)")
    return i, f"the rotation block is not a rotation: max |R^T R - I| = {err[i]:.3g} (tolerance {tol:g})"


def quaternion_problem(q, tol: float = QUATERNION_NORM_TOLERANCE, names: str = "qx qy qz qw") -> tuple[int, str] | None:
    """The first quaternion that is not finite or not of unit norm within ``tol``: ``(index, sentence)``, or None.

    Parameters
    ----------
    q : (m, 4) array_like
        Quaternions in the file's order.
    tol : float
        Largest accepted ``| |q| - 1 |`` (default :data:`QUATERNION_NORM_TOLERANCE`).
    names : str
        The file's names of the four components, for the sentence.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    with np.errstate(over="ignore", invalid="ignore"):
        n = np.sqrt(np.einsum("mi,mi->m", q, q))
        ok = np.isfinite(q).all(axis=1) & (np.abs(n - 1.0) <= tol)
    if ok.all():
        return None
    i = int(np.flatnonzero(~ok)[0])
    vals = ", ".join(f"{v:.6g}" for v in q[i])
    if not np.isfinite(q[i]).all():
        return i, f"the quaternion ({names}) = ({vals}) holds NaN or inf"
    if n[i] == 0.0:
        return i, f"the quaternion ({names}) = ({vals}) is zero: it is not a rotation"
    return i, (f"the quaternion ({names}) = ({vals}) has norm {n[i]:.6g}, not 1 (within {tol:g}): not a unit "
               "quaternion (wrong columns, or a damaged line?)")


def normalize_quat(q, order: str = "xyzw", tol: float = QUATERNION_NORM_TOLERANCE) -> np.ndarray:
    """Return unit quaternions ``q / |q|``; raise if any norm is off by more than ``tol``.

    Parameters
    ----------
    q : (..., 4) array_like
        Quaternions in ``order``.
    order : {"xyzw", "wxyz"}
        Component order of ``q`` (the output keeps the same order).
    tol : float
        Largest accepted ``| |q| - 1 |``; files print quaternions with limited digits, so
        small deviations are renormalised, but a zero or clearly wrong quaternion is an error.

    Raises
    ------
    InputError
        If a quaternion is not finite or its norm differs from 1 by more than ``tol``
        (the message names the first bad row).
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise InputError(f"quaternions must have shape (..., 4), got {q.shape}")
    if order not in ("xyzw", "wxyz"):
        raise InputError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")
    problem = quaternion_problem(q.reshape(-1, 4), tol, names="qx qy qz qw" if order == "xyzw" else "qw qx qy qz")
    if problem is not None:
        raise InputError(f"quaternion(s) not unit length: row {problem[0]}: {problem[1]}")
    return q / np.linalg.norm(q, axis=-1)[..., None]


def quat_to_matrix(q, order: str = "xyzw") -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Parameters
    ----------
    q : (4,) or (m, 4) array_like
        Hamilton quaternions; normalised first (see :func:`normalize_quat`).
    order : {"xyzw", "wxyz"}
        ``"xyzw"`` (TUM/ROS, scalar last) or ``"wxyz"`` (scalar first, e.g. GeoSLAM ``q0..q3``).

    Returns
    -------
    (3, 3) or (m, 3, 3) float64
        Active rotation ``R`` with ``p' = R p`` ([Shuster1993 Eq. 161], transposed for the
        active convention); equal to SciPy's ``Rotation.from_quat(q).as_matrix()``.
    """
    q = normalize_quat(q, order)
    q = _reorder_in(q, order)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - w * z)
    R[..., 0, 2] = 2.0 * (x * z + w * y)
    R[..., 1, 0] = 2.0 * (x * y + w * z)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - w * x)
    R[..., 2, 0] = 2.0 * (x * z - w * y)
    R[..., 2, 1] = 2.0 * (y * z + w * x)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def matrix_to_quat(R, order: str = "xyzw", atol: float = 1e-6) -> np.ndarray:
    """Unit quaternions of rotation matrices (Shepperd 1978), with ``w >= 0``.

    Parameters
    ----------
    R : (3, 3) or (m, 3, 3) array_like
        Proper rotation matrices (``R^T R = I``, ``det R = +1`` within ``atol``).
    order : {"xyzw", "wxyz"}
        Component order of the output.
    atol : float
        Tolerance of the orthonormality check.

    Returns
    -------
    (4,) or (m, 4) float64

    Notes
    -----
    For numerical stability the component with the largest magnitude is computed first
    from the largest of ``(trace, R00, R11, R22)`` and the others from off-diagonal sums
    (Shepperd 1978); e.g. for the trace branch ``w = sqrt(1 + tr R) / 2`` and
    ``x = (R21 - R12) / (4 w)``.

    Raises
    ------
    InputError
        If a matrix is not a proper rotation within ``atol`` (first bad row named).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise InputError(f"rotation matrices must have shape (..., 3, 3), got {R.shape}")
    if order not in ("xyzw", "wxyz"):
        raise InputError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")
    single = R.ndim == 2
    Rm = R.reshape(-1, 3, 3)
    problem = rotation_problem(Rm, atol)
    if problem is not None:
        raise InputError(f"matrix not a proper rotation: row {problem[0]}: {problem[1]}")
    m = Rm.shape[0]
    tr = Rm[:, 0, 0] + Rm[:, 1, 1] + Rm[:, 2, 2]
    choice = np.argmax(np.stack([tr, Rm[:, 0, 0], Rm[:, 1, 1], Rm[:, 2, 2]], axis=1), axis=1)
    q = np.empty((m, 4))  # x y z w
    r = Rm
    # branch 0: w largest
    s = choice == 0
    w = 0.5 * np.sqrt(np.maximum(1.0 + tr[s], 0.0))
    q[s, 3] = w
    q[s, 0] = (r[s, 2, 1] - r[s, 1, 2]) / (4.0 * w)
    q[s, 1] = (r[s, 0, 2] - r[s, 2, 0]) / (4.0 * w)
    q[s, 2] = (r[s, 1, 0] - r[s, 0, 1]) / (4.0 * w)
    # branch 1: x largest
    s = choice == 1
    x = 0.5 * np.sqrt(np.maximum(1.0 + r[s, 0, 0] - r[s, 1, 1] - r[s, 2, 2], 0.0))
    q[s, 0] = x
    q[s, 3] = (r[s, 2, 1] - r[s, 1, 2]) / (4.0 * x)
    q[s, 1] = (r[s, 0, 1] + r[s, 1, 0]) / (4.0 * x)
    q[s, 2] = (r[s, 0, 2] + r[s, 2, 0]) / (4.0 * x)
    # branch 2: y largest
    s = choice == 2
    y = 0.5 * np.sqrt(np.maximum(1.0 - r[s, 0, 0] + r[s, 1, 1] - r[s, 2, 2], 0.0))
    q[s, 1] = y
    q[s, 3] = (r[s, 0, 2] - r[s, 2, 0]) / (4.0 * y)
    q[s, 0] = (r[s, 0, 1] + r[s, 1, 0]) / (4.0 * y)
    q[s, 2] = (r[s, 1, 2] + r[s, 2, 1]) / (4.0 * y)
    # branch 3: z largest
    s = choice == 3
    z = 0.5 * np.sqrt(np.maximum(1.0 - r[s, 0, 0] - r[s, 1, 1] + r[s, 2, 2], 0.0))
    q[s, 2] = z
    q[s, 3] = (r[s, 1, 0] - r[s, 0, 1]) / (4.0 * z)
    q[s, 0] = (r[s, 0, 2] + r[s, 2, 0]) / (4.0 * z)
    q[s, 1] = (r[s, 1, 2] + r[s, 2, 1]) / (4.0 * z)
    q[q[:, 3] < 0] *= -1.0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    if order == "wxyz":
        q = q[:, [3, 0, 1, 2]]
    return q[0] if single else q
