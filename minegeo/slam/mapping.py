"""Roadway noise removal of the point-cloud map (Ren et al. 2019 Sec. 3.5, Steps 1-4, Fig. 8).

Points inside the roadway that belong to no roadway surface (measurement noise, pedestrians,
vehicles: anything between the sensor and the walls) are removed section by section along the
track:

1. **Normal plane** at each track point: normal = current minus previous track point, plane
   through the current point [Ren2019 Eq. 12]. Track points are skipped as the paper says: a step
   to the previous point longer than ``max_step_m``, a heading change between consecutive track
   segments above ``max_heading_change_deg``, or a curvature (heading change / mean segment length)
   above ``max_curvature_rad_per_m``; also a steep segment (grade above ``max_grade_deg``), where
   "vertical" in the section is undefined. With ``track_step_m`` each accepted segment carries
   sections every ``track_step_m`` (normal = the segment direction), so that the slices tile the
   roadway instead of sampling it at the keyframes only.
2. **Slice**: the points within ``δ/2`` of the plane [Ren2019 Eq. 13] and within
   ``max_radius_m`` of the track point in the plane (another drift crossing the plane far away is
   not part of this section).
3. **Projection and split**: the slice projected on the plane, coordinates ``(u, v)`` = (lateral,
   vertical; lateral = world up × normal). The section box is the 2nd-98th percentile extent of
   ``u`` and ``v``; the parts S1..S4 (floor, right wall, roof, left wall) are the angular sectors
   around the box centre bounded by the directions to its corners.
4. **Fit and remove**: per part, RANSAC (seeded) then a least-squares refit of the inliers: a
   total-least-squares line for the floor and the walls, a parabola ``v = a u² + b u + c`` for
   the roof (flat roofs give ``a ≈ 0``, arched/horseshoe roofs are followed; a circle would need
   the arch to be circular and is unstable on a short flat roof). A fit must hold
   ``min_part_points`` inliers, ``min_inlier_fraction`` of its part, and lie within
   ``max_surface_tilt_deg`` of its expected orientation, otherwise the slice makes no decision.
   A point is an outlier of the slice when it lies more than ``noise_threshold_m`` *inside* every
   one of the four fitted surfaces (signed distance towards the section centre). Points near a
   surface, or behind one (overbreak, a niche, the floor of a crosscut), are never outliers.

A point is removed when at least ``vote_fraction`` of the slices that decided about it (default:
all of them) call it an outlier. Beyond the paper, when the keyframe of each point is given
(``source``), an outlier that points of at least ``static_min_keyframes`` different keyframes
confirm (outliers within ``static_radius_m``) is kept as static structure (a ventilation duct, a
pipe, a parked vehicle): a moving object is at a different place in each keyframe. Only NumPy draws from ``np.random.default_rng(seed)`` are used,
so the result is deterministic.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from minegeo._params import bounded, validate
from minegeo.errors import InputError
from minegeo.slam._kernels_mapping import slice_members

__all__ = ["RoadwayNoiseParams", "NoiseRemovalResult", "remove_roadway_noise", "section_frames"]

_PARTS = ("floor", "right_wall", "roof", "left_wall")  # S1..S4, counter-clockwise from below


@dataclass(frozen=True)
class RoadwayNoiseParams:
    """Parameters of :func:`remove_roadway_noise` (units in the names).

    slice_thickness_m : δ of [Ren2019 Eq. 13]; the slice holds points within δ/2 of the plane.
    track_step_m : sections every this arc length along each accepted track segment (``None``:
        only at the track points, as the paper).
    max_radius_m : in-plane distance from the track point beyond which slice points are ignored.
    max_step_m, max_heading_change_deg, max_curvature_rad_per_m, max_grade_deg : track-point
        rejection (Step 1).
    ransac_threshold_m, ransac_iterations : RANSAC inlier distance and hypotheses per part.
    noise_threshold_m : a point more than this inside all four fitted surfaces is an outlier.
    min_part_points, min_inlier_fraction, max_surface_tilt_deg : fit acceptance per part.
    vote_fraction : fraction of deciding slices that must call a point an outlier.
    static_min_keyframes, static_radius_m : with ``source``, outliers confirmed by this many
        keyframes within this radius are kept as static structure (0: off, the paper).
    seed : RNG seed of the RANSAC draws.

    Each field declares its bounds in its metadata (:mod:`minegeo._params`): the former checks, plus
    the angles the tests compare with (a heading change > 0; a grade and a surface tilt in (0, 90]),
    the seed >= 0 (``np.random.default_rng``).
    """

    slice_thickness_m: float = bounded(0.5, gt=0.0)
    track_step_m: float | None = bounded(0.5, gt=0.0, optional=True)
    max_radius_m: float = bounded(8.0, gt=0.0)
    max_step_m: float = bounded(5.0, gt=0.0)
    max_heading_change_deg: float = bounded(20.0, gt=0.0)
    max_curvature_rad_per_m: float = bounded(0.3, gt=0.0)
    max_grade_deg: float = bounded(45.0, gt=0.0, le=90.0)
    ransac_threshold_m: float = bounded(0.08, gt=0.0)
    ransac_iterations: int = bounded(100, ge=1, integer=True)
    noise_threshold_m: float = bounded(0.2, gt=0.0)
    min_part_points: int = bounded(8, ge=3, integer=True)
    min_inlier_fraction: float = bounded(0.3, ge=0.0, le=1.0)
    max_surface_tilt_deg: float = bounded(30.0, gt=0.0, le=90.0)
    vote_fraction: float = bounded(1.0, gt=0.0, le=1.0)
    static_min_keyframes: int = bounded(3, ge=0, integer=True)
    static_radius_m: float = bounded(0.2, gt=0.0)
    seed: int = bounded(0, ge=0, integer=True)

    def __post_init__(self):
        validate(self)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class NoiseRemovalResult:
    """Outcome of :func:`remove_roadway_noise`.

    keep : (n,) bool, True for the points that stay.
    counts : points per reason: ``removed``, ``kept_near_surface``, ``kept_behind_surface``,
        ``kept_split_vote``, ``kept_static`` (outliers seen from ``static_min_keyframes``
        keyframes), ``kept_undecided`` (only in slices without a decision),
        ``kept_not_in_slice``; and ``slices`` per status.
    slices : list of dict per section: centre, status, points, outliers, inliers and RMS per part.
    params : RoadwayNoiseParams
    """

    keep: np.ndarray
    counts: dict
    slices: list
    params: RoadwayNoiseParams

    @property
    def n_removed(self) -> int:
        return int((~self.keep).sum())


def section_frames(track: np.ndarray, params: RoadwayNoiseParams):
    """Step 1: section centres, normals and the status of every track point.

    Returns ``(centres (s, 3), normals (s, 3), track index (s,), statuses)``; ``statuses[i]`` is
    ``"ok"`` or the reason track point ``i`` was skipped.
    """
    track = np.asarray(track, dtype=np.float64).reshape(-1, 3)
    n = track.shape[0]
    seg = np.diff(track, axis=0)  # segment i-1 → i: the normal vector AB [Ren2019 Eq. 12]
    length = np.linalg.norm(seg, axis=1)
    dirs = seg / np.maximum(length, 1e-12)[:, None]
    turn = np.zeros(n)  # heading change at track point i between segments (i-1, i) and (i, i+1)
    curv = np.zeros(n)
    if n > 2:
        cosang = np.clip(np.sum(dirs[:-1] * dirs[1:], axis=1), -1.0, 1.0)
        turn[1:-1] = np.arccos(cosang)
        curv[1:-1] = turn[1:-1] / np.maximum(0.5 * (length[:-1] + length[1:]), 1e-12)
    max_turn = np.deg2rad(params.max_heading_change_deg)
    sin_grade = np.sin(np.deg2rad(params.max_grade_deg))
    statuses = ["first_point"] + [""] * (n - 1) if n else []
    centres, normals, index = [], [], []
    for i in range(1, n):
        L = length[i - 1]
        if L < 1e-6:
            statuses[i] = "no_motion"
        elif L > params.max_step_m:
            statuses[i] = "step_too_long"
        elif max(turn[i - 1], turn[i]) > max_turn:
            statuses[i] = "heading_change"
        elif max(curv[i - 1], curv[i]) > params.max_curvature_rad_per_m:
            statuses[i] = "curvature"
        elif abs(dirs[i - 1, 2]) > sin_grade:
            statuses[i] = "steep"
        else:
            statuses[i] = "ok"
            if params.track_step_m is None:
                offsets = np.array([L])  # the plane through the current point B [Ren2019 Eq. 12]
            else:
                m = max(int(np.ceil(L / params.track_step_m - 1e-9)), 1)
                offsets = (np.arange(m) + 1.0) * (L / m)
            for o in offsets:
                centres.append(track[i - 1] + o * dirs[i - 1])
                normals.append(dirs[i - 1])
                index.append(i)
    s = len(centres)
    return (np.asarray(centres).reshape(s, 3), np.asarray(normals).reshape(s, 3),
            np.asarray(index, dtype=np.int64), statuses)


def _split_parts(uv: np.ndarray):
    """Step 3: part 0..3 (floor, right wall, roof, left wall) of each point by angle around the box centre."""
    lo = np.percentile(uv, 2.0, axis=0)
    hi = np.percentile(uv, 98.0, axis=0)
    c = 0.5 * (lo + hi)
    ang = np.arctan2(uv[:, 1] - c[1], uv[:, 0] - c[0])
    a_lr = np.arctan2(lo[1] - c[1], hi[0] - c[0])  # lower-right corner (negative)
    a_ur = np.arctan2(hi[1] - c[1], hi[0] - c[0])
    a_ul = np.arctan2(hi[1] - c[1], lo[0] - c[0])
    a_ll = np.arctan2(lo[1] - c[1], lo[0] - c[0])
    part = np.full(uv.shape[0], 3, dtype=np.int64)  # left wall: beyond a_ul or below a_ll
    part[(ang >= a_ll) & (ang < a_lr)] = 0
    part[(ang >= a_lr) & (ang < a_ur)] = 1
    part[(ang >= a_ur) & (ang < a_ul)] = 2
    return part, c


def _fit_line(xy: np.ndarray, rng, params: RoadwayNoiseParams):
    """RANSAC line then a total-least-squares refit of its inliers: (unit normal n, offset d), n·x = d."""
    m = xy.shape[0]
    ij = rng.integers(0, m, size=(params.ransac_iterations, 2))
    d01 = xy[ij[:, 1]] - xy[ij[:, 0]]
    nrm = np.stack([-d01[:, 1], d01[:, 0]], axis=1)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-9
    if not ok.any():
        return None
    nrm = nrm[ok] / ln[ok, None]
    off = np.sum(nrm * xy[ij[ok, 0]], axis=1)
    score = (np.abs(xy @ nrm.T - off) <= params.ransac_threshold_m).sum(axis=0)
    best = int(np.argmax(score))
    inl = np.abs(xy @ nrm[best] - off[best]) <= params.ransac_threshold_m
    if inl.sum() < 2:
        return None
    q = xy[inl]
    mu = q.mean(axis=0)
    _, vec = np.linalg.eigh((q - mu).T @ (q - mu))
    n = vec[:, 0]
    d = float(n @ mu)
    inl = np.abs(xy @ n - d) <= params.ransac_threshold_m
    return n, d, inl


def _parabola_distance(coef, uv):
    """Signed distance below the roof ``v = a u² + b u + c`` (vertical residual over √(1 + f′²))."""
    a, b, c = coef
    f = (a * uv[:, 0] + b) * uv[:, 0] + c
    slope = 2.0 * a * uv[:, 0] + b
    return (f - uv[:, 1]) / np.sqrt(1.0 + slope * slope)


def _circle_distance(coef, uv):
    """Signed distance inside the roof circle ``(centre u, centre v, radius)``: R − ‖p − c‖."""
    return coef[2] - np.hypot(uv[:, 0] - coef[0], uv[:, 1] - coef[1])


def _parabola_hypotheses(uv, idx):
    """Parabolas through the point triples ``idx`` (h, 3) → (h, 3) coefficients, NaN when degenerate."""
    u, v = uv[idx, 0], uv[idx, 1]
    A = np.stack([u ** 2, u, np.ones_like(u)], axis=2)
    ok = np.abs(np.linalg.det(A)) > 1e-9
    out = np.full((idx.shape[0], 3), np.nan)
    out[ok] = np.linalg.solve(A[ok], v[ok][..., None])[..., 0]
    return out


def _circle_hypotheses(uv, idx):
    """Circumcircles of the point triples ``idx`` (h, 3) → (h, 3) ``(cu, cv, R)``, NaN when collinear."""
    p0, p1, p2 = uv[idx[:, 0]], uv[idx[:, 1]], uv[idx[:, 2]]
    a, b = p1 - p0, p2 - p0
    den = 2.0 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    ok = np.abs(den) > 1e-9
    den = np.where(ok, den, 1.0)
    a2, b2 = np.sum(a * a, axis=1), np.sum(b * b, axis=1)
    cu = (b[:, 1] * a2 - a[:, 1] * b2) / den
    cv = (a[:, 0] * b2 - b[:, 0] * a2) / den
    out = np.stack([p0[:, 0] + cu, p0[:, 1] + cv, np.hypot(cu, cv)], axis=1)
    out[~ok] = np.nan
    return out


def _refit_parabola(uv):
    A = np.stack([uv[:, 0] ** 2, uv[:, 0], np.ones(uv.shape[0])], axis=1)
    return np.linalg.lstsq(A, uv[:, 1], rcond=None)[0]


def _refit_circle(uv):
    """Algebraic (Kåsa) least-squares circle: u² + v² = 2 cu u + 2 cv v + (R² − cu² − cv²)."""
    A = np.stack([2.0 * uv[:, 0], 2.0 * uv[:, 1], np.ones(uv.shape[0])], axis=1)
    x = np.linalg.lstsq(A, np.sum(uv * uv, axis=1), rcond=None)[0]
    return np.array([x[0], x[1], np.sqrt(max(x[2] + x[0] ** 2 + x[1] ** 2, 0.0))])


_ROOF_MODELS = {"parabola": (_parabola_hypotheses, _parabola_distance, _refit_parabola),
                "circle": (_circle_hypotheses, _circle_distance, _refit_circle)}


def _fit_roof(uv: np.ndarray, centre: np.ndarray, rng, params: RoadwayNoiseParams):
    """RANSAC circle and RANSAC parabola, each refitted by least squares on its inliers; the
    plausible one (section centre inside it) with more inliers wins. Returns
    ``(model name, coefficients, inliers)`` or None."""
    m = uv.shape[0]
    idx = np.stack([rng.choice(m, size=3, replace=False) for _ in range(params.ransac_iterations)])
    best = None
    for name, (hyp, dist, refit) in _ROOF_MODELS.items():
        H = hyp(uv, idx)
        H = H[np.isfinite(H).all(axis=1)]
        if name == "circle":
            H = H[H[:, 2] < 1e4]
        if H.shape[0] == 0:
            continue
        score = np.stack([np.abs(dist(h, uv)) <= params.ransac_threshold_m for h in H]).sum(axis=1)
        h = H[int(np.argmax(score))]
        inl = np.abs(dist(h, uv)) <= params.ransac_threshold_m
        if inl.sum() < 3:
            continue
        coef = refit(uv[inl])
        if not np.isfinite(coef).all() or dist(coef, centre[None])[0] <= 0:
            continue
        inl = np.abs(dist(coef, uv)) <= params.ransac_threshold_m
        if best is None or inl.sum() > best[2].sum():
            best = (name, coef, inl)
    return best


def _inside_distances(uv, part, centre, rng, params: RoadwayNoiseParams):
    """Step 4 for one slice: signed distance of every point inside each fitted part, or a failure reason.

    Returns ``(dist (m, 4) or None, per-part stats, status)``; positive = towards the section centre.
    """
    dist = np.empty((uv.shape[0], 4))
    stats = {}
    cos_tilt = np.cos(np.deg2rad(params.max_surface_tilt_deg))
    for k, name in enumerate(_PARTS):
        sel = part == k
        npart = int(sel.sum())
        if npart < params.min_part_points:
            return None, stats, f"too_few_points_{name}"
        if k == 2:
            fit = _fit_roof(uv[sel], centre, rng, params)
            if fit is None:
                return None, stats, f"fit_failed_{name}"
            model, coef, inl = fit
            dist_fn = _ROOF_MODELS[model][1]
            dist[:, k] = dist_fn(coef, uv)
            res = dist_fn(coef, uv[sel][inl])
        else:
            fit = _fit_line(uv[sel], rng, params)
            if fit is None:
                return None, stats, f"fit_failed_{name}"
            n, d, inl = fit
            expected = np.array([0.0, 1.0]) if k == 0 else np.array([1.0, 0.0])
            if abs(float(n @ expected)) < cos_tilt:
                return None, stats, f"implausible_{name}"
            if n @ centre - d < 0:  # orient the normal towards the centre
                n, d = -n, -d
            if n @ centre - d <= 0:
                return None, stats, f"implausible_{name}"
            dist[:, k] = uv @ n - d
            res = uv[sel][inl] @ n - d
        ninl = int(inl.sum())
        stats[name] = {"points": npart, "inliers": ninl, "rms_m": float(np.sqrt(np.mean(res ** 2)))}
        if k == 2:
            stats[name]["model"] = model
        if ninl < params.min_part_points or ninl < params.min_inlier_fraction * npart:
            return None, stats, f"weak_fit_{name}"
    return dist, stats, "ok"


def _plane_axes(normal: np.ndarray):
    """Lateral and vertical in-plane axes (Step 3): u = up × n normalised, v = n × u."""
    u = np.cross(np.array([0.0, 0.0, 1.0]), normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _static_outliers(P: np.ndarray, source: np.ndarray, removed: np.ndarray, params: RoadwayNoiseParams):
    """Outliers that outliers of at least ``static_min_keyframes`` keyframes confirm within the radius."""
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(removed)
    static = np.zeros(P.shape[0], dtype=bool)
    if idx.size == 0 or params.static_min_keyframes <= 1:
        return static if params.static_min_keyframes <= 0 else removed.copy()
    near = cKDTree(P[idx]).query_ball_point(P[idx], params.static_radius_m)
    src = source[idx]
    views = np.array([np.unique(src[nb]).size for nb in near])
    static[idx[views >= params.static_min_keyframes]] = True
    return static


def remove_roadway_noise(points_world, trajectory_positions, params: RoadwayNoiseParams | None = None,
                         source=None) -> NoiseRemovalResult:
    """Remove the roadway noise of a world-frame cloud section by section along the track (Sec. 3.5).

    ``points_world`` (n, 3), ``trajectory_positions`` (t, 3) in travel order (the sensor path,
    inside the roadway), ``source`` (n,) optional keyframe index of each point (enables the
    static-structure check). See the module docstring for Steps 1-4.
    """
    params = params or RoadwayNoiseParams()
    P = np.ascontiguousarray(np.asarray(points_world, dtype=np.float64).reshape(-1, 3))
    track = np.asarray(trajectory_positions, dtype=np.float64).reshape(-1, 3)
    if not (np.isfinite(P).all() and np.isfinite(track).all()):
        raise InputError("points and trajectory positions must be finite")
    centres, normals, index, statuses = section_frames(track, params)
    n = P.shape[0]
    in_slice = np.zeros(n, dtype=np.int64)
    decided = np.zeros(n, dtype=np.int64)
    votes = np.zeros(n, dtype=np.int64)
    behind = np.zeros(n, dtype=bool)
    slices = []
    rng = np.random.default_rng(params.seed)
    if centres.shape[0] and n:
        offsets, members = slice_members(P, np.ascontiguousarray(centres), np.ascontiguousarray(normals),
                                          0.5 * params.slice_thickness_m, params.max_radius_m)
    for s in range(centres.shape[0]):
        idx = members[offsets[s]:offsets[s + 1]]
        in_slice[idx] += 1
        info = {"track_index": int(index[s]), "centre": centres[s].tolist(), "points": int(idx.size),
                "outliers": 0, "status": "ok", "parts": {}}
        slices.append(info)
        if idx.size < 4 * params.min_part_points:
            info["status"] = "too_few_points"
            continue
        u, v = _plane_axes(normals[s])
        rel = P[idx] - centres[s]
        uv = np.stack([rel @ u, rel @ v], axis=1)  # projection onto the normal plane (Step 3)
        part, box_c = _split_parts(uv)
        dist, info["parts"], info["status"] = _inside_distances(uv, part, box_c, rng, params)
        if dist is None:
            continue
        out = (dist > params.noise_threshold_m).all(axis=1)
        decided[idx] += 1
        votes[idx] += out
        behind[idx] |= (dist < -params.noise_threshold_m).any(axis=1)
        info["outliers"] = int(out.sum())
    removed = (votes > 0) & (votes >= params.vote_fraction * decided)
    static = np.zeros(n, dtype=bool)
    if source is not None and params.static_min_keyframes > 0:
        source = np.asarray(source).reshape(-1)
        if source.shape[0] != n:
            raise InputError(f"source has {source.shape[0]} entries for {n} points")
        static = _static_outliers(P, source, removed, params)
        removed &= ~static
    keep = ~removed
    slice_status: dict[str, int] = {}
    for info in slices:
        slice_status[info["status"]] = slice_status.get(info["status"], 0) + 1
    counts = {
        "points": n, "removed": int(removed.sum()),
        "kept_static": int(static.sum()),
        "kept_split_vote": int(((votes > 0) & ~removed & ~static).sum()),
        "kept_behind_surface": int((keep & (votes == 0) & behind).sum()),
        "kept_near_surface": int((keep & (votes == 0) & ~behind & (decided > 0)).sum()),
        "kept_undecided": int(((in_slice > 0) & (decided == 0)).sum()),
        "kept_not_in_slice": int((in_slice == 0).sum()),
        "track_points": {st: statuses.count(st) for st in sorted(set(statuses))},
        "slices": slice_status,
    }
    return NoiseRemovalResult(keep, counts, slices, params)
