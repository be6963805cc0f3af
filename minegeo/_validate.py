"""Input validation shared by every public function (kernels never validate)."""

from __future__ import annotations

import numpy as np

from minegeo.errors import InputError, InternalError, TooFewPointsError

__all__ = ["as_points", "as_trusted_points", "as_matrix", "as_transform", "internal_transform", "check_positive"]

#: How far (``‖RᵀR − I‖`` entries, last row) a transform the package made itself may be from SE(3)
#: before it is a bug: re-projected poses are at rounding level (about 1e-15).
INTERNAL_TRANSFORM_ATOL = 1e-9


def as_points(arr, name: str = "points", dim: int = 3, min_points: int = 1) -> np.ndarray:
    """Return ``arr`` as a C-contiguous float64 ``(n, dim)`` array, or raise a typed error.

    Raises
    ------
    InputError
        Wrong shape, non-numeric, or containing NaN/inf (the first bad row is named).
    TooFewPointsError
        Fewer than ``min_points`` rows.
    """
    try:
        a = np.asarray(arr, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric, got {type(arr).__name__}: {exc}") from None
    if a.ndim != 2 or a.shape[1] != dim:
        raise InputError(f"{name} must have shape (n, {dim}), got {a.shape}")
    if a.shape[0] < min_points:
        raise TooFewPointsError(f"{name} has {a.shape[0]} point(s); at least {min_points} are needed")
    if not np.isfinite(a).all():  # one flat pass (~10x faster than a per-row test on 10^6 rows)
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        raise InputError(
            f"{name} contains {bad.size} row(s) with NaN or inf (first at row {int(bad[0])}); "
            "remove or fix them before processing"
        )
    return np.ascontiguousarray(a)


def as_trusted_points(arr, name: str = "points", dim: int = 3, min_points: int = 1) -> np.ndarray:
    """Layout-only check for arrays the caller has already validated (``check_target=False``).

    Accepts only a C-contiguous float64 ``(n, dim)`` ndarray with at least ``min_points`` rows
    and returns it unchanged, **without** the finiteness scan of :func:`as_points` (for a map
    validated once, e.g. a :class:`minegeo.localize.PreparedMap`, and searched many times).

    Raises
    ------
    InputError
        Not such an array (no conversion is attempted: convert and validate with :func:`as_points`).
    TooFewPointsError
        Fewer than ``min_points`` rows.
    """
    if not (isinstance(arr, np.ndarray) and arr.dtype == np.float64 and arr.ndim == 2 and arr.shape[1] == dim
            and arr.flags.c_contiguous):
        got = f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr).__name__
        raise InputError(f"{name}: without checks it must be a C-contiguous float64 (n, {dim}) array, got {got}; "
                         "pass it with the checks on")
    if arr.shape[0] < min_points:
        raise TooFewPointsError(f"{name} has {arr.shape[0]} point(s); at least {min_points} are needed")
    return arr


def as_matrix(arr, shape: tuple, name: str) -> np.ndarray:
    """Return a finite float64 array of exactly ``shape`` (``-1`` entries are free)."""
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim != len(shape) or any(s != -1 and s != t for s, t in zip(shape, a.shape, strict=True)):
        raise InputError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name} contains NaN or inf")
    return np.ascontiguousarray(a)


def as_transform(T, name: str = "T", atol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform given by a user (orthonormal rotation, det +1, last row 0 0 0 1).

    ``atol`` is the tolerance of a typed or file-read matrix (its digits). A transform the package
    composed itself is not user input: check it with :func:`internal_transform`.

    Raises
    ------
    InputError
        Not a finite (4, 4) array, last row not ``[0, 0, 0, 1]``, or ``|RᵀR − I| > atol`` / ``det R < 0``.
    """
    T = as_matrix(T, (4, 4), name)
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=atol):
        raise InputError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise InputError(f"{name} rotation block is not a proper rotation (orthonormal, det=+1)")
    return T


def internal_transform(T, name: str = "T", atol: float = INTERNAL_TRANSFORM_ATOL) -> np.ndarray:
    """Check the invariant "``T`` is a rigid transform" of a transform the package made itself
    (a chained, inverted or interpolated pose, already re-projected with
    :func:`minegeo.geometry.se3.project`), and return it re-projected onto SE(3) (a float64 copy).

    Raises
    ------
    InternalError
        Not a finite float (4, 4) array, or off SE(3) by more than ``atol`` (last row, ``RᵀR − I``,
        ``det R``): a bug (a composition that skipped the re-projection, a NaN from a solver), never
        the user's input.
    """
    from minegeo.kernels.lie import se3_project

    a = np.asarray(T)
    if a.shape != (4, 4) or a.dtype.kind != "f" or not np.isfinite(a).all():
        raise InternalError(f"{name}: an internal transform is not a finite 4x4 float matrix "
                            f"(shape {a.shape}, dtype {a.dtype})")
    a = a.astype(np.float64)
    R = a[:3, :3]
    drift = float(np.abs(R.T @ R - np.eye(3)).max())
    row = float(np.abs(a[3] - [0.0, 0.0, 0.0, 1.0]).max())
    if not (drift <= atol and row <= atol and np.linalg.det(R) > 0):
        raise InternalError(f"{name}: an internal transform has left SE(3) (|RᵀR − I| = {drift:.2e}, last row off by "
                            f"{row:.2e}, det R = {np.linalg.det(R):.6f}; tolerance {atol:.0e})")
    return se3_project.py_func(a)


def check_positive(value, name: str, allow_zero: bool = False) -> float:
    """Return ``float(value)`` if finite and > 0 (or >= 0), else raise :class:`InputError`."""
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return v


def is_permutation(a: np.ndarray, n: int) -> bool:
    """Whether the integer array ``a`` holds each of ``0 .. n-1`` exactly once."""
    a = np.asarray(a)
    if a.shape != (n,):
        return False
    if n == 0:
        return True
    if a.dtype.kind not in "iu" or int(a.min()) < 0 or int(a.max()) >= n:  # before bincount allocates max+1
        return False
    return bool(np.array_equal(np.bincount(a, minlength=n), np.ones(n)))
