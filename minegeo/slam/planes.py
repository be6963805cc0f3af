"""Roadway floor planes as pose-graph landmarks (Ren et al. 2019, Sec. 3.4.2).

Three pieces, each a pure function:

* :func:`extract_floor_plane`: the floor plane of the sub-map around a keyframe: RANSAC on
  3-point samples (the draws made here from ``np.random.default_rng(seed)``, the hypotheses
  scored by :func:`minegeo.slam._kernels_planes.ransac_plane_counts`), then a least-squares
  refit of the inliers (PCA, :func:`minegeo.kernels.eig3.jacobi_eigh3`).
* :func:`plane_in_sensor_frame` / :func:`plane_in_world_frame`: the plane transformation of
  [Ren2019 Eq. 9] and [Ren2019 Eq. 10] for minegeo's ``T_world_sensor``.
* :func:`pose_plane_terms`: the pose–plane error of [Ren2019 Eq. 11] with its analytic
  Jacobians, the factor a pose graph adds for each (keyframe, floor landmark) pair.

Planes are 4-vectors ``π = (n_a, n_b, n_c, d)``, ``n·p + d = 0``, ``|n| = 1`` (d in m). The paper
writes ``ax + by + cz = d`` with ``d > 0``; minegeo's ``d`` is the paper's ``−d``, and with that
sign the paper's [Ren2019 Eq. 10] ``d' = d − t_t·n'`` holds as printed (see
:func:`plane_in_sensor_frame`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import StrEnum

import numpy as np

from minegeo._params import bounded, validate
from minegeo._validate import as_matrix, as_points, as_transform
from minegeo.errors import InputError
from minegeo.kernels.eig3 import jacobi_eigh3
from minegeo.slam import _kernels_planes as KP

__all__ = ["FloorPlaneParams", "PlaneResult", "PlaneStatus", "extract_floor_plane", "plane_in_sensor_frame",
           "plane_in_world_frame", "plane_q_paper", "retract_plane", "pose_plane_residuals",
           "pose_plane_terms"]


@dataclass(frozen=True)
class FloorPlaneParams:
    """Parameters of :func:`extract_floor_plane` (lengths in m, angles in degrees).

    Attributes
    ----------
    radius_m : float
        Sub-map radius: points within this 3-D distance of the keyframe position are candidates
        (the paper uses the LiDAR's measuring range).
    max_below_sensor_m : float
        Candidates lie at most this far below the sensor, measured along ``up``.
    min_below_sensor_m : float
        ... and at least this far below it (removes the roof and the upper walls).
    distance_threshold_m : float
        RANSAC inlier distance ``|n·p + d|``.
    iterations : int
        Number of 3-point samples.
    min_inliers : int
        Fewest inliers of an accepted floor (and fewest candidates worth a RANSAC).
    min_inlier_fraction : float
        Fewest inliers as a fraction of the candidates.
    max_tilt_deg : float
        Largest angle between the floor normal and ``up``: steeper hypotheses (walls, ramps
        beyond the design grade) are rejected.

    Each numeric field declares its bounds in its metadata (:mod:`minegeo._params`); the height band
    is checked across its two fields (``max_below_sensor_m > min_below_sensor_m``).
    """

    radius_m: float = bounded(10.0, gt=0.0)
    max_below_sensor_m: float = bounded(5.0, gt=0.0)
    min_below_sensor_m: float = bounded(0.3, ge=0.0)
    distance_threshold_m: float = bounded(0.05, gt=0.0)
    iterations: int = bounded(200, ge=1, integer=True)
    min_inliers: int = bounded(50, ge=3, integer=True)
    min_inlier_fraction: float = bounded(0.1, ge=0.0, le=1.0)
    max_tilt_deg: float = bounded(20.0, ge=0.0, lt=90.0)

    def __post_init__(self):
        validate(self)
        if not self.max_below_sensor_m > self.min_below_sensor_m:
            raise InputError(f"FloorPlaneParams.max_below_sensor_m ({self.max_below_sensor_m!r}) must be greater "
                             f"than min_below_sensor_m ({self.min_below_sensor_m!r}): the candidates' height band "
                             "below the sensor would be empty")


class PlaneStatus(StrEnum):
    """Status of a floor-plane extraction (:attr:`PlaneResult.status`); each member is its string value."""

    OK = "ok"
    #: fewer than ``min_inliers`` sub-map points below the sensor
    TOO_FEW_POINTS = "too few points"
    #: no valid hypothesis, or the refitted plane failed a check (tilt, height, inliers)
    NO_PLANE = "no plane"


@dataclass(frozen=True)
class PlaneResult:
    """Outcome of :func:`extract_floor_plane`.

    Attributes
    ----------
    plane : ndarray (4,)
        ``(n_a, n_b, n_c, d)`` in the frame of the input points, ``n·p + d = 0``, ``|n| = 1``,
        ``n`` oriented up (``n·up > 0``); NaN unless ``status == "ok"`` (the best RANSAC
        plane, if any, is still in ``ransac_plane``).
    status : PlaneStatus
        ``ok``, ``too few points`` or ``no plane``.
    reason : str
    n_candidates : int
        Points of the sub-map (within the radius, in the height band below the sensor).
    n_inliers : int
        Inliers of the refitted plane within the distance threshold.
    rms_m : float
        RMS distance (m) of those inliers from the refitted plane.
    tilt_deg : float
        Angle between the normal and ``up``.
    sensor_height_m : float
        Signed distance ``n·center + d`` (m) of the sensor above the plane.
    inliers : ndarray of int
        Indices into the input points of the inliers.
    ransac_plane : ndarray (4,)
        The best 3-point hypothesis (NaN if none was valid).
    """

    plane: np.ndarray
    status: PlaneStatus
    reason: str
    n_candidates: int = 0
    n_inliers: int = 0
    rms_m: float = float("nan")
    tilt_deg: float = float("nan")
    sensor_height_m: float = float("nan")
    inliers: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    ransac_plane: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    seed: int = 0
    params: FloorPlaneParams = field(default_factory=FloorPlaneParams)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal ``n`` (3,)."""
        return self.plane[:3]

    @property
    def d(self) -> float:
        """Offset ``d`` (m): ``n·p + d = 0``."""
        return float(self.plane[3])

    def summary(self) -> dict:
        return {"status": self.status, "reason": self.reason, "plane": self.plane.tolist(),
                "n_candidates": self.n_candidates, "n_inliers": self.n_inliers, "rms_m": self.rms_m,
                "tilt_deg": self.tilt_deg, "sensor_height_m": self.sensor_height_m, "seed": self.seed,
                "params": asdict(self.params)}


def _unit(v, name: str) -> np.ndarray:
    v = as_matrix(v, (3,), name)
    nv = float(np.linalg.norm(v))
    if nv == 0:
        raise InputError(f"{name} must be a non-zero vector")
    return v / nv


def _pca_plane(P: np.ndarray) -> np.ndarray:
    """Least-squares plane of ``P`` (k, 3): centroid and the eigenvector of the smallest eigenvalue."""
    c = P.mean(axis=0)
    Q = P - c
    A = np.ascontiguousarray(Q.T @ Q / P.shape[0])
    V, w = np.empty((3, 3)), np.empty(3)
    jacobi_eigh3(A, V, w)  # ascending eigenvalues
    n = V[:, 0].copy()
    return np.r_[n, -float(n @ c)]


def extract_floor_plane(points_world, center, params: FloorPlaneParams | None = None, seed: int = 0,
                        up=(0.0, 0.0, 1.0)) -> PlaneResult:
    """The floor plane below a keyframe, by RANSAC and a least-squares refit of its inliers.

    Parameters
    ----------
    points_world : array_like (N, 3)
        The (sub-)map points, m, in the world frame (any frame works if ``center`` and ``up``
        are given in the same one, e.g. a keyframe scan in its sensor frame with ``center = 0``).
    center : array_like (3,)
        The keyframe (sensor) position, m, same frame.
    params : FloorPlaneParams, optional
    seed : int
        Seed of the 3-point draws (``np.random.default_rng(seed)``); same inputs and seed, same result.
    up : array_like (3,)
        The up direction (normalised here): heights below the sensor, the tilt test and the
        orientation of the normal are measured along it. Default world +z.

    Returns
    -------
    PlaneResult
        ``status`` "ok" with the plane, "too few points" (fewer than ``min_inliers`` candidates),
        or "no plane" (no valid hypothesis, too few inliers, too steep after the refit, or the
        sensor not above the plane), with the reason.
    """
    params = params or FloorPlaneParams()
    P = as_points(points_world, "points_world", min_points=0)
    c = as_matrix(center, (3,), "center")
    u = _unit(up, "up")
    nan4 = np.full(4, np.nan)
    rel = P - c
    h = rel @ u
    cand = np.flatnonzero((np.einsum("ij,ij->i", rel, rel) <= params.radius_m ** 2)
                          & (h <= -params.min_below_sensor_m) & (h >= -params.max_below_sensor_m))
    nc = int(cand.size)
    base = {"n_candidates": nc, "seed": seed, "params": params}
    if nc < params.min_inliers:
        return PlaneResult(nan4, PlaneStatus.TOO_FEW_POINTS, f"{nc} sub-map point(s) below the sensor within "
                           f"{params.radius_m} m; at least {params.min_inliers} are needed", **base)
    Pc = np.ascontiguousarray(P[cand])
    samples = np.ascontiguousarray(np.random.default_rng(seed).integers(0, nc, size=(params.iterations, 3)),
                                   dtype=np.int64)
    counts = np.empty(params.iterations, dtype=np.int64)
    hyp = np.empty((params.iterations, 4))
    cos_tilt = float(np.cos(np.deg2rad(params.max_tilt_deg)))
    KP.ransac_plane_counts(Pc, samples, u, cos_tilt, params.distance_threshold_m, counts, hyp)
    best = int(np.argmax(counts))  # first of equal counts: deterministic
    if counts[best] < 0:
        why = "all samples degenerate" if np.all(counts == -1) else f"every plane steeper than {params.max_tilt_deg} deg"
        return PlaneResult(nan4, PlaneStatus.NO_PLANE, f"no valid 3-point hypothesis in {params.iterations} samples ({why})",
                           **base)
    ransac_plane = hyp[best].copy()
    # least-squares refit of the inliers, inliers re-selected and refitted once more (the first
    # refit averages the noise of the three sample points, the second uses the inliers it finds)
    plane = ransac_plane
    for _ in range(2):
        inl = np.abs(Pc @ plane[:3] + plane[3]) <= params.distance_threshold_m
        if inl.sum() < 3:
            break
        plane = _pca_plane(Pc[inl])
        if plane[:3] @ u < 0:
            plane = -plane
    dist = Pc @ plane[:3] + plane[3]
    inl = np.abs(dist) <= params.distance_threshold_m
    need = max(params.min_inliers, int(np.ceil(params.min_inlier_fraction * nc)))
    tilt = float(np.degrees(np.arccos(np.clip(plane[:3] @ u, -1.0, 1.0))))
    height = float(plane[:3] @ c + plane[3])
    rms = float(np.sqrt(np.mean(dist[inl] ** 2))) if inl.any() else float("nan")
    out = {**base, "n_inliers": int(inl.sum()), "rms_m": rms, "tilt_deg": tilt, "sensor_height_m": height,
           "inliers": cand[inl], "ransac_plane": ransac_plane}
    if tilt > params.max_tilt_deg:
        return PlaneResult(nan4, PlaneStatus.NO_PLANE, f"refitted plane tilted {tilt:.1f} deg > {params.max_tilt_deg} deg", **out)
    if height <= 0:
        return PlaneResult(nan4, PlaneStatus.NO_PLANE, f"the sensor is not above the plane (height {height:.3f} m)", **out)
    if out["n_inliers"] < need:
        return PlaneResult(nan4, PlaneStatus.NO_PLANE, f"refitted plane has {out['n_inliers']} inliers of {nc}; {need} needed",
                           **out)
    return PlaneResult(plane, PlaneStatus.OK, f"{out['n_inliers']} inliers of {nc}, RMS {rms:.4f} m, tilt {tilt:.2f} deg",
                       **out)


def _plane(pl, name: str) -> np.ndarray:
    pl = as_matrix(pl, (4,), name)
    nn = float(np.linalg.norm(pl[:3]))
    if not abs(nn - 1.0) <= 1e-6:
        raise InputError(f"{name} normal must have unit length, got |n| = {nn}")
    return pl


def plane_in_sensor_frame(plane_world, T_world_sensor) -> np.ndarray:
    """A world plane in the sensor frame of ``T_world_sensor`` [Ren2019 Eq. 9] [Ren2019 Eq. 10].

    Parameters
    ----------
    plane_world : array_like (4,)
        ``(n, d)`` in the world frame, ``n·p_w + d = 0``, ``|n| = 1`` (d in m).
    T_world_sensor : array_like (4, 4)
        The sensor pose, ``p_w = R p_s + t`` (m).

    Returns
    -------
    ndarray (4,)
        ``(n_s, d_s)`` with ``n_s·p_s + d_s = 0``: ``n_s = Rᵀ n`` [Ren2019 Eq. 9] and
        ``d_s = d + n·t`` [Ren2019 Eq. 10], because ``n·(R p_s + t) + d = 0``.

    Notes
    -----
    The paper's ``[R_t, t_t]`` maps world to sensor coordinates (``T⁻¹``: ``R_t = Rᵀ``,
    ``t_t = −Rᵀ t``); its ``n' = R_t n`` is then ``Rᵀ n`` and its ``d' = d − t_t·n'`` is
    ``d + (Rᵀt)·(Rᵀn) = d + n·t``, with the paper's ``d`` read as minegeo's (``n·p + d = 0``).
    Written with ``R`` instead of ``Rᵀ`` the formula would be wrong for ``T_world_sensor``.
    """
    return KP.plane_world_to_sensor(as_transform(T_world_sensor, "T_world_sensor"), _plane(plane_world, "plane_world"))


def plane_in_world_frame(plane_sensor, T_world_sensor) -> np.ndarray:
    """Inverse of :func:`plane_in_sensor_frame`: ``n = R n_s``, ``d = d_s − n·t`` (m)."""
    T = as_transform(T_world_sensor, "T_world_sensor")
    pl = _plane(plane_sensor, "plane_sensor")
    n = T[:3, :3] @ pl[:3]
    return np.r_[n, pl[3] - float(n @ T[:3, 3])]


def plane_q_paper(plane) -> np.ndarray:
    """The paper's minimal parametrisation ``q(π) = [azimuth, elevation, d]`` (rad, rad, m) [Ren2019 Eq. 11].

    ``azimuth = atan2(n_a, n_b)`` (the paper's ``atan(n_a/n_b)`` on the full circle) and
    ``elevation = atan2(n_c, hypot(n_a, n_b))``: the paper prints ``atan(n_c/|n|)``, which for a
    unit normal is ``atan(n_c)`` and not the elevation angle; the horizontal norm is meant.
    For a floor (``n ≈ ±e_z``) both angles are singular: the azimuth is undefined at the pole and
    jumps by up to π under a small tilt, and the elevation is ``π/2 − |tilt|``, a cone point that
    has lost the direction of the tilt (non-differentiable; the printed ``atan(n_c)`` is worse still,
    ``≈ π/4 − tilt²/4``, zero slope). Differences of q() and their Jacobians are then meaningless, so
    the factor (:func:`pose_plane_terms`) evaluates this q() in a chart about the measured plane,
    where the measured normal is on the equator. This function documents the paper's form.
    """
    pl = as_matrix(plane, (4,), "plane")
    return np.array([np.arctan2(pl[0], pl[1]), np.arctan2(pl[2], np.hypot(pl[0], pl[1])), pl[3]])


def retract_plane(plane, delta) -> np.ndarray:
    """The plane-landmark update ``(normalize(n + B(n) δ[:2]), d + δ[2])`` (δ in rad, rad, m).

    ``B(n)`` is :func:`minegeo.slam._kernels_planes.plane_tangent_basis` at the current ``n``.
    """
    return KP.plane_retract(_plane(plane, "plane"), as_matrix(delta, (3,), "delta"))


def _edge_arrays(poses, planes, edges, measurements):
    poses = as_matrix(poses, (-1, 4, 4), "poses")
    planes = as_matrix(planes, (-1, 4), "planes")
    meas = as_matrix(measurements, (-1, 4), "measurements")
    e = np.ascontiguousarray(np.asarray(edges, dtype=np.int64))
    if e.ndim != 2 or e.shape[1] != 2 or e.shape[0] != meas.shape[0]:
        raise InputError(f"edges must have shape (m, 2) with m = {meas.shape[0]} measurements, got {e.shape}")
    if e.size and (e[:, 0].min() < 0 or e[:, 0].max() >= poses.shape[0] or e[:, 1].min() < 0
                   or e[:, 1].max() >= planes.shape[0]):
        raise InputError("edges index a pose or plane that does not exist")
    for name, n in (("planes", planes[:, :3]), ("measurements", meas[:, :3])):
        if n.size and not np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6):
            raise InputError(f"{name} normals must have unit length")
    return poses, planes, e, meas


def pose_plane_residuals(poses, planes, edges, measurements) -> np.ndarray:
    """Residuals (m, 3) of pose–plane edges [Ren2019 Eq. 11]; see :func:`pose_plane_terms`."""
    poses, planes, e, meas = _edge_arrays(poses, planes, edges, measurements)
    r = np.empty((e.shape[0], 3))
    KP.pose_plane_residuals(poses, planes, e, meas, r)
    return r


def pose_plane_terms(poses, planes, edges, measurements):
    """Residuals and analytic Jacobians of pose–plane edges [Ren2019 Eq. 11].

    Parameters
    ----------
    poses : array_like (P, 4, 4)
        Keyframe poses ``T_world_sensor`` (m).
    planes : array_like (L, 4)
        Plane landmarks ``(n, d)`` in the world frame (unit ``n``, d in m).
    edges : array_like (m, 2) of int
        ``(pose index, plane index)`` per edge.
    measurements : array_like (m, 4)
        The plane observed from that pose, in its sensor frame (unit normal, d in m), e.g.
        :func:`extract_floor_plane` on the keyframe scan with ``center = 0``, or the sub-map
        plane brought into the sensor frame by :func:`plane_in_sensor_frame`.

    Returns
    -------
    r : ndarray (m, 3)
        ``e = q_t(π') − q_t(π_t)`` (rad, rad, m): azimuth and elevation of the predicted normal
        in the measurement's chart (zero at the measured normal) and ``d_s − d_t``.
    J_pose : ndarray (m, 3, 6)
        ``∂r/∂δ`` for ``T ← T · Exp(δ)``, ``δ = (ω, ρ)`` (rad, m).
    J_plane : ndarray (m, 3, 3)
        ``∂r/∂δ`` for the landmark update of :func:`retract_plane`.
    """
    poses, planes, e, meas = _edge_arrays(poses, planes, edges, measurements)
    m = e.shape[0]
    r, Jp, Jl = np.empty((m, 3)), np.empty((m, 3, 6)), np.empty((m, 3, 3))
    KP.pose_plane_edge_terms(poses, planes, e, meas, r, Jp, Jl)
    return r, Jp, Jl
