"""PWCV and CWC intersection descriptors and their heading-invariant similarity (Liang et al. 2024, Sec. 3).

The paper names the descriptors and their role, not every formula; the definitions here are ours and
are stated exactly in ``docs/intersections.md`` ("Descriptors"). In short, around an invariant point
``c = (cx, cy, cz)`` (``cz`` = floor height at the junction), for a point ``p`` let
``r = |p_xy - c_xy|`` (horizontal range, m), ``theta = atan2(p_y - c_y, p_x - c_x)`` in [0, 2 pi) and
``h = p_z - cz`` (height above the junction floor):

* **PWCV** (polar wall-contour vector), ``N_s`` sectors of ``2 pi / N_s``: over the points with
  ``h`` in the wall band and ``r_min <= r <= R``, ``d_k`` = the smallest ``r`` in sector ``k`` and
  ``v_k = 1 - d_k / R`` (wall *closeness*), ``v_k = 0`` where the sector holds no such point (an
  opening: a drift leaving the junction, or a wall farther than ``R``).
* **CWC** (cylinder wall contour): the same per height band ``[h0 + b dh, h0 + (b + 1) dh)``,
  ``b = 0..N_b - 1``, over every point (walls and roof): a (``N_b``, ``N_s``) matrix; the roof shows
  as a band of closeness near 1, bands above it are 0, so the roof height is encoded.
* **Similarity** of an observed descriptor ``a`` with a reference ``b``: the weighted Ruzicka
  similarity ``sum min(a, b_shift) / sum max(a, b_shift)``, maximised over every circular shift of the
  sectors (the heading of approach); the best shift is the relative yaw. With ``occlusion=True`` the
  cells where the observation is 0 and the reference is not (a reference wall not seen: occluded or
  out of the scan) are left out of both sums.
* **Completeness** ``k_c / k_b``: nonzero sectors of the observed PWCV over those of the reference
  ([Liang2024 Eq. 32] uses it for the intersection covariance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minegeo._params import bounded, validate
from minegeo._validate import as_points, as_transform
from minegeo.errors import InputError
from minegeo.semantic import _kernels_skeleton as K
from minegeo.semantic.skeleton import check_height_band

__all__ = ["DescriptorParams", "Similarity", "pwcv", "cwc", "similarity", "completeness", "stack_keyframes"]


@dataclass(frozen=True)
class DescriptorParams:
    """Descriptor parameters (lengths in m).

    Attributes
    ----------
    radius_m : float
        ``R``: horizontal radius of the descriptor around the invariant point.
    n_sectors : int
        ``N_s``: angular sectors (360 = 1 degree).
    wall_band_m : (float, float)
        Height band (above the junction floor) of the PWCV's wall points; keep it under the lowest roof.
    band_start_m, band_m, n_bands : float, float, int
        CWC bands ``[band_start_m + b band_m, band_start_m + (b + 1) band_m)``, ``b < n_bands``.
    min_range_m : float
        ``r_min``: points closer than this to the invariant point are ignored (the vehicle, noise).

    Each numeric field declares its rule in its metadata (:mod:`minegeo._params`; ``band_start_m``, a
    height above the floor, any finite number); ``wall_band_m`` (an increasing pair of heights) is
    checked here.
    """

    radius_m: float = bounded(12.0, gt=0.0)
    n_sectors: int = bounded(360, ge=8, integer=True)
    wall_band_m: tuple = (0.4, 2.2)
    band_start_m: float = bounded(0.2)
    band_m: float = bounded(0.4, gt=0.0)
    n_bands: int = bounded(12, ge=1, integer=True)
    min_range_m: float = bounded(1.0, ge=0.0)
    max_gap_sectors: int = bounded(3, ge=0, integer=True)
    footprint_m: float = bounded(0.15, ge=0.0)

    def __post_init__(self):
        validate(self)
        check_height_band(self.wall_band_m, "DescriptorParams.wall_band_m")


@dataclass(frozen=True)
class Similarity:
    """Result of :func:`similarity`.

    Attributes
    ----------
    score : float
        Best similarity in [0, 1] over the circular shifts.
    shift : int
        Best shift ``k`` in sectors: ``observed[..., j] ~ reference[..., j - k]``.
    yaw_rad : float
        ``k 2 pi / N_s`` wrapped to (-pi, pi]: the rotation about z taking reference bearings to observed
        bearings (for a cloud rotated by yaw ``psi`` about the invariant point, ``yaw_rad ~ psi``); an
        initial guess for the ICP verification.
    scores : ndarray (N_s,)
        Similarity at every shift.
    """

    score: float
    shift: int
    yaw_rad: float
    scores: np.ndarray


def _offsets(points, centre, params: DescriptorParams):
    P = as_points(points, "points", min_points=0)
    c = np.asarray(centre, np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise InputError("centre must be a finite (x, y, z) invariant point (z = floor height)")
    return (np.ascontiguousarray(P[:, 0] - c[0]), np.ascontiguousarray(P[:, 1] - c[1]), P[:, 2] - c[2])


def _closeness(rng: np.ndarray, radius: float, max_gap: int) -> np.ndarray:
    K.fill_gaps(rng, int(max_gap))
    return np.where(rng > 0.0, 1.0 - rng / radius, 0.0)


def pwcv(points, centre, params: DescriptorParams | None = None) -> np.ndarray:
    """Polar wall-contour vector of the points around an invariant point.

    Parameters
    ----------
    points : array_like (n, 3)
        Points (m, any frame with z up: map frame for the knowledge base, keyframe frame online).
    centre : array_like (3,)
        Invariant point in the same frame, its z the floor height at the junction.
    params : DescriptorParams, optional

    Returns
    -------
    ndarray (N_s,)
        Wall closeness ``1 - d_k / R`` in [0, 1) per sector (0 = opening); sector k covers bearings
        ``[k, k + 1) 2 pi / N_s`` counter-clockwise from +x of the frame.
    """
    params = params or DescriptorParams()
    dx, dy, h = _offsets(points, centre, params)
    band = np.where((h >= params.wall_band_m[0]) & (h <= params.wall_band_m[1]), 0, -1).astype(np.int64)
    out = np.empty((1, int(params.n_sectors)))
    K.polar_min_range(dx, dy, band, 1, int(params.n_sectors), float(params.radius_m), float(params.min_range_m), float(params.footprint_m), out)
    return _closeness(out, params.radius_m, params.max_gap_sectors)[0]


def cwc(points, centre, params: DescriptorParams | None = None) -> np.ndarray:
    """Cylinder wall contour: the PWCV of every height band (walls and roof) around the invariant point.

    Returns
    -------
    ndarray (N_b, N_s)
        Row b: closeness per sector over the points with height ``h`` above the junction floor in
        ``[band_start_m + b band_m, band_start_m + (b + 1) band_m)``; see :func:`pwcv`.
    """
    params = params or DescriptorParams()
    dx, dy, h = _offsets(points, centre, params)
    b = np.floor((h - params.band_start_m) / params.band_m)
    band = np.where((b >= 0) & (b < params.n_bands), b, -1).astype(np.int64)
    out = np.empty((int(params.n_bands), int(params.n_sectors)))
    K.polar_min_range(dx, dy, band, int(params.n_bands), int(params.n_sectors), float(params.radius_m),
                      float(params.min_range_m), float(params.footprint_m), out)
    return _closeness(out, params.radius_m, params.max_gap_sectors)


def _as_descriptor(d, name: str) -> np.ndarray:
    try:
        a = np.asarray(d, np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric descriptor") from exc
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] < 8 or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise InputError(f"{name} must be a finite, non-negative (N_s,) or (N_b, N_s) descriptor, got {a.shape}")
    return np.ascontiguousarray(a)


def similarity(observed, reference, occlusion: bool = True) -> Similarity:
    """Heading-invariant similarity of two PWCV (N_s,) or two CWC (N_b, N_s) descriptors.

    ``S(k) = sum_cells min(a, b_k) / sum_cells max(a, b_k)`` with ``b_k[..., j] = b[..., j - k]``, the
    best over every circular shift ``k`` (exhaustive, N_s^2 N_b operations). With ``occlusion=True``
    the cells with ``a = 0 < b_k`` are left out of both sums: the observation saw no wall where the
    reference has one, which occlusion or a partial scan explains, while a wall seen where the
    reference has an opening (or at another range) still counts against the match. For the symmetric
    comparison of two complete map descriptors use ``occlusion=False``.

    Returns
    -------
    Similarity
        Score in [0, 1] (0 when nothing is comparable), best shift and relative yaw.
    """
    a = _as_descriptor(observed, "observed")
    b = _as_descriptor(reference, "reference")
    if a.shape != b.shape:
        raise InputError(f"descriptors differ in shape: {a.shape} vs {b.shape}")
    n = a.shape[1]
    scores = np.empty(n)
    K.shift_ruzicka(a, b, bool(occlusion), scores)
    k = int(np.argmax(scores))
    best, frac = float(scores[k]), 0.0
    for f in np.arange(-0.5, 0.501, 0.05):   # sub-sector refinement of the best shift
        sf = K.ruzicka_frac(a, b, float(k + f), bool(occlusion))
        if sf > best:
            best, frac = sf, float(f)
    yaw = (k + frac) * 2.0 * np.pi / n
    if yaw > np.pi:
        yaw -= 2.0 * np.pi
    return Similarity(best, k, float(yaw), scores)


def completeness(observed, reference) -> float:
    """Completeness ``k_c / k_b`` of an observed PWCV against the reference (knowledge-base) PWCV.

    ``k_c`` / ``k_b``: number of nonzero (wall) sectors of the observed / reference PWCV, the inputs of
    the intersection noise matrix ``Lambda_I = diag(k_c / k_b)`` [Liang2024 Eq. 32]. Capped at 1 (a
    wall seen where the map has an opening does not make an observation more complete than the map);
    0 when the reference has no wall sector. For CWC input the bands are pooled (cells, not sectors).
    """
    a = _as_descriptor(observed, "observed")
    b = _as_descriptor(reference, "reference")
    if a.shape != b.shape:
        raise InputError(f"descriptors differ in shape: {a.shape} vs {b.shape}")
    kb = int(np.count_nonzero(b))
    return 0.0 if kb == 0 else min(1.0, np.count_nonzero(a) / kb)


def stack_keyframes(clouds, T_curr_his) -> np.ndarray:
    """Dense cloud of the current keyframe and its neighbours, in the current keyframe's frame.

    ``P_dense = P_curr + sum_i T^curr_{his_i} P_{his_i}`` [Liang2024 Eq. 20], with ``+`` the union of
    the point sets: ``clouds[0]`` is the current keyframe (its own frame), ``clouds[i]`` (i >= 1) a
    neighbouring keyframe in its frame and ``T_curr_his[i - 1]`` the 4x4 pose of that keyframe in the
    current one.

    Returns
    -------
    ndarray (n, 3)
        Points (m) in the current keyframe's frame.
    """
    clouds = list(clouds)
    Ts = list(T_curr_his)
    if not clouds or len(Ts) != len(clouds) - 1:
        raise InputError("give the current keyframe and one 4x4 transform per neighbouring keyframe")
    out = [as_points(clouds[0], "clouds[0]", min_points=0)]
    for i, (P, T) in enumerate(zip(clouds[1:], Ts, strict=True), start=1):
        Q = as_points(P, f"clouds[{i}]", min_points=0)
        T = as_transform(T, f"T_curr_his[{i - 1}]")
        out.append(Q @ T[:3, :3].T + T[:3, 3])
    return np.ascontiguousarray(np.concatenate(out))
