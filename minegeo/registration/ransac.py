"""Global registration by RANSAC on descriptor correspondences.

Baek et al. (2022), Sec. 2.3.2 ("Match Area Search Using RANSAC"), [Baek2022 Eqs. 7-9], with
the rigid model of [Baek2022 Eqs. 10-13] and the inlier RMSE of [Baek2022 Eq. 19]; parameter defaults
from Table 3. Open3D's ``registration_ransac_based_on_feature_matching`` (spec
``open3d_oracle.md`` Sec. 5-9) is the reference implementation; the differences
are listed in ``docs/registration_features.md``. The settings and result types and the iteration
count are in :mod:`minegeo.registration.ransac_params` (importable here).

References
----------
Baek, J. et al. (2022). 3D global localization in the underground mine environment
using mobile LiDAR mapping and point cloud registration. Sensors 22, 2873.

Buch, A. G. et al. (2013). Pose estimation using local structure-specific shape and
appearance context. ICRA 2013 (edge-length pruning).

Fischler, M. A., Bolles, R. C. (1981). Random sample consensus. CACM 24(6).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import as_points, as_trusted_points
from minegeo.errors import DegenerateGeometryError, InputError, TooFewPointsError
from minegeo.kernels import hashgrid as HG
from minegeo.registration import _kernels_ransac as K
from minegeo.registration import _kernels_ransac_levelled as KL
from minegeo.registration.correspondences import feature_correspondences
from minegeo.registration.ransac_params import RansacParams, RansacResult, RansacStatus, required_iterations

__all__ = [
    "RansacParams",
    "RansacResult",
    "RansacStatus",
    "register_ransac",
    "required_iterations",
    "hypothesis_distance",
]

log = logging.getLogger(__name__)

#: Relative singular-value floor below which a sample is treated as collinear.
_DEGENERATE_TOL = 1e-9
_LEVELLED_MIN_SPREAD_M2 = 0.5  # horizontal spread of a levelled sample below which the yaw is undetermined
#: Hypotheses scored per parallel call (fixed, so results never depend on the thread count).
_SCORE_GROUP = 16
#: Point queries per call above which scoring runs in parallel (a parallel launch costs
#: ~0.05-20 ms depending on machine load; the results are identical either way).
_PARALLEL_WORK = 400_000
#: Largest dense cell table of the target grid (8 bytes per cell).
_DENSE_MAX_CELLS = 8_000_000
#: Relative smallest/largest singular value of a centred cloud below which it is flat.
_FLAT_TOL = 1e-6


def hypothesis_distance(T1, T2, center) -> tuple[float, float]:
    """(distance (m) between ``T1 c`` and ``T2 c``, rotation angle between them (deg))."""
    T1 = np.asarray(T1, dtype=np.float64)
    T2 = np.asarray(T2, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64)
    d = (T1[:3, :3] - T2[:3, :3]) @ c + T1[:3, 3] - T2[:3, 3]
    cosang = (np.trace(T1[:3, :3].T @ T2[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(d)), float(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))))


def _distances_to(Ts: np.ndarray, T: np.ndarray, c: np.ndarray):
    """Vectorised :func:`hypothesis_distance` of a stack ``Ts`` (m, 4, 4) to ``T``."""
    d = np.einsum("mij,j->mi", Ts[:, :3, :3] - T[None, :3, :3], c) + Ts[:, :3, 3] - T[None, :3, 3]
    tr = np.einsum("mij,ij->m", Ts[:, :3, :3], T[:3, :3])
    ang = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
    return np.linalg.norm(d, axis=1), ang


class _Grid:
    """Uniform grid over the target points (cell edge = search radius) for exact radius-NN.

    Dense cell table (one start offset per cell; rows of three cells along x are one
    contiguous range) when it has at most ``_DENSE_MAX_CELLS`` cells, otherwise a hash
    table of the occupied cells (memory proportional to the occupied cells only).
    """

    def __init__(self, points: np.ndarray, cell: float):
        self.origin = points.min(axis=0)
        self.cell = float(cell)
        c = np.floor((points - self.origin) / self.cell).astype(np.int64)
        dims = c.max(axis=0) + 1
        ncells = float(dims[0]) * float(dims[1]) * float(dims[2])
        if ncells > 4e18:
            raise InputError(
                f"distance threshold {cell} m is too small for the target's extent "
                f"{np.ptp(points, axis=0).tolist()} m (grid index overflow)"
            )
        self.dims = dims.astype(np.int64)
        key = (c[:, 2] * dims[1] + c[:, 1]) * dims[0] + c[:, 0]
        self.order = np.argsort(key, kind="stable")
        ks = key[self.order]
        self.points = np.ascontiguousarray(points[self.order])
        if ncells <= _DENSE_MAX_CELLS:
            counts = np.bincount(ks, minlength=int(ncells))
            self.dstart = np.zeros(int(ncells) + 1, dtype=np.int64)
            np.cumsum(counts, out=self.dstart[1:])
            self.tkeys = np.full(1, -1, dtype=np.int64)
            self.tslots = np.full(1, -1, dtype=np.int64)
            self.start = np.zeros(1, dtype=np.int64)
            self.count = np.zeros(1, dtype=np.int64)
        else:
            uniq, start, count = np.unique(ks, return_index=True, return_counts=True)
            self.start = start.astype(np.int64)
            self.count = count.astype(np.int64)
            self.tkeys, self.tslots = HG.new_table(uniq.astype(np.int64), HG.table_bits(uniq.size))
            self.dstart = np.zeros(1, dtype=np.int64)

    def args(self):
        return (self.points, self.origin, self.cell, self.dims, self.dstart, self.tkeys, self.tslots, self.start,
                self.count)

    def nearest(self, queries: np.ndarray, T: np.ndarray, radius: float):
        """Nearest target index (original numbering, -1 if none within radius) and sq distance."""
        R = np.ascontiguousarray(T[:3, :3])
        t = np.ascontiguousarray(T[:3, 3])
        fn = K.grid_nearest_batch if queries.shape[0] > _PARALLEL_WORK else K.grid_nearest_serial
        j, d2 = fn(queries, R, t, *self.args(), radius * radius)
        out = np.where(j >= 0, self.order[np.maximum(j, 0)], -1)
        return out, d2


class _HypothesisStore:
    """Growing arrays (capacity doubling) of the fully scored hypotheses: T, inlier count, SSE."""

    def __init__(self, capacity: int = 64):
        self.T = np.empty((capacity, 4, 4))
        self.c = np.empty(capacity, dtype=np.int64)
        self.s = np.empty(capacity)
        self.n = 0

    def add(self, T: np.ndarray, c: np.ndarray, s: np.ndarray) -> None:
        m = self.n + c.size
        if m > self.c.size:
            cap = max(m, 2 * self.c.size)
            self.T = np.concatenate([self.T[: self.n], np.empty((cap - self.n, 4, 4))])
            self.c = np.concatenate([self.c[: self.n], np.empty(cap - self.n, dtype=np.int64)])
            self.s = np.concatenate([self.s[: self.n], np.empty(cap - self.n)])
        self.T[self.n : m] = T
        self.c[self.n : m] = c
        self.s[self.n : m] = s
        self.n = m

    def view(self, start: int = 0):
        return self.T[start : self.n], self.c[start : self.n], self.s[start : self.n]


ST_TILT = 100  #: rejected by the levelled-frames check (``max_tilt_deg``); Python-side status code


def _check_not_flat(points: np.ndarray, name: str) -> None:
    c = points - points.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] == 0.0:
        raise DegenerateGeometryError(f"all {name} points coincide: no registration is possible")
    if s[1] <= _FLAT_TOL * s[0]:
        raise DegenerateGeometryError(
            f"all {name} points lie on a line: rotation about it and position along it are undetermined"
        )
    if s[2] <= _FLAT_TOL * s[0]:
        raise DegenerateGeometryError(
            f"all {name} points lie on a plane: position within the plane is undetermined by geometry alone"
        )


def _draw_samples(rng: np.random.Generator, R: int, B: int, n: int) -> np.ndarray:
    """``B`` samples of ``n`` correspondence rows, uniform with replacement (``rng.integers``).

    In mode "minegeo" a sample that repeats a row is rejected by the check kernel (it
    counts as an iteration), which makes accepted samples uniform over distinct rows.
    """
    return rng.integers(0, R, size=(B, n), dtype=np.int64)


def _score(grid: _Grid, src: np.ndarray, T: np.ndarray, d: float):
    j, d2 = grid.nearest(src, T, d)
    m = j >= 0
    cnt = int(m.sum())
    sse = float(np.sum(d2[m])) if cnt else 0.0
    return cnt, sse, j


def _better(c1, s1, c2, s2) -> bool:
    """Open3D's order: more inliers, then lower RMSE (strict)."""
    if c1 > c2:
        return True
    return c1 == c2 and c1 > 0 and s1 < s2


def _refit(grid, src, tgt, T, cnt, sse, d, iterations):
    """Least-squares refit ([Baek2022 Eqs. 10-13]) on the inliers, kept only while the score improves."""
    for _ in range(iterations):
        _, _, j = _score(grid, src, T, d)
        m = j >= 0
        if m.sum() < 3:
            break
        R, t, ok = K.umeyama_rigid(np.ascontiguousarray(src[m]), np.ascontiguousarray(tgt[j[m]]), _DEGENERATE_TOL)
        if not ok:
            break
        T2 = np.eye(4)
        T2[:3, :3] = R
        T2[:3, 3] = t
        c2, s2, _ = _score(grid, src, T2, d)
        if _better(c2, s2, cnt, sse):
            T, cnt, sse = T2, c2, s2
        else:
            break
    return T, cnt, sse


# ----------------------------------------------------------------------------- main


def register_ransac(
    source_points,
    target_points,
    source_features=None,
    target_features=None,
    params: RansacParams | None = None,
    seed: int | None = 0,
    source_normals=None,
    target_normals=None,
    correspondences=None,
    *,
    target_feature_index=None,
    check_target: bool = True,
) -> RansacResult:
    """Global rigid registration by RANSAC on descriptor matches (Baek 2022, Sec. 2.3.2).

    Parameters
    ----------
    source_points : array_like (n, 3)
        Source (e.g. local scan) points, m, in the source frame.
    target_points : array_like (m, 3)
        Target (e.g. prior map) points, m, in the target frame. Use a local origin
        for projected coordinates.
    source_features, target_features : array_like (n, d), (m, d)
        Descriptors (e.g. FPFH). Not needed when ``correspondences`` is given.
    params : RansacParams, optional
        Defaults to Baek et al. (2022) Table 3.
    seed : int
        Seed of ``np.random.default_rng``; every random draw comes from it, so
        equal inputs and seed give bit-identical results on any thread count.
    source_normals, target_normals : array_like, optional
        Needed only for the normal-angle check.
    correspondences : array_like (k, 2), optional
        Putative (source, target) index pairs to sample from instead of
        descriptor matches.
    target_feature_index : FeatureIndex, optional
        :func:`minegeo.registration.correspondences.build_feature_index` of this very
        ``target_features`` array, reused across calls (same matches, no rebuild).
    check_target : bool
        True (default) scans ``target_points`` for NaN/inf; False checks only its layout
        (C-contiguous float64 (m, 3)), for a map validated once (a prepared map).

    Returns
    -------
    RansacResult

    Raises
    ------
    InputError
        Bad shapes, NaN/inf rows, mismatched features, missing normals for the
        normal check, out-of-range correspondences.
    TooFewPointsError
        Fewer points or correspondences than ``ransac_n``.
    DegenerateGeometryError
        A cloud is collinear or coplanar (the pose is not determined).

    Notes
    -----
    Each iteration draws ``n`` putative pairs, prunes them with the edge-length
    test ([Baek2022 Eq. 7]), fits ``R, t`` by SVD ([Baek2022 Eqs. 10-13], reflection-corrected), checks
    the sample residuals against epsilon_distance, and scores the hypothesis on
    the whole source cloud: inlier count, then inlier RMSE ([Baek2022 Eq. 19]). After each
    improvement the iteration budget is lowered to [Baek2022 Eq. 8],
    ``N = log(1-p) / log(1-w^n)``, with ``w`` the fraction of putative pairs the
    new best explains, capped by ``max_iterations`` (and ``max_validations``).
    Hypotheses are evaluated in parallel batches but accepted in draw order,
    so the result equals that of the sequential algorithm on the same draws.
    """
    p = RansacParams() if params is None else params
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    n = int(p.ransac_n)
    src, tgt, src_n, tgt_n, use_normals = _checked_inputs(source_points, target_points, source_normals,
                                                           target_normals, p, n, check_target)
    t0 = time.perf_counter()
    corr, mutual_applied = _putative_pairs(src, tgt, source_features, target_features, correspondences, p,
                                           target_feature_index)
    timings["correspondences"] = time.perf_counter() - t0
    if corr.shape[0] < n:
        raise TooFewPointsError(
            f"only {corr.shape[0]} putative correspondence(s); RANSAC with ransac_n={n} needs at least {n}")

    t0 = time.perf_counter()
    d = float(p.distance_threshold_m)
    grid = _Grid(tgt, d)
    csrc = np.ascontiguousarray(src[corr[:, 0]])
    ctgt = np.ascontiguousarray(tgt[corr[:, 1]])
    dummy = np.zeros((1, 3))
    csrc_n = np.ascontiguousarray(src_n[corr[:, 0]]) if use_normals else dummy
    ctgt_n = np.ascontiguousarray(tgt_n[corr[:, 1]]) if use_normals else dummy
    eval_order = np.random.default_rng(0).permutation(src.shape[0]).astype(np.int64)
    center = src.mean(axis=0)
    timings["grid"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    run = _hypotheses(p, seed, src, csrc, ctgt, csrc_n, ctgt_n, use_normals, grid, eval_order, center)
    timings["hypotheses"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    out = _final_answer(p, run, grid, src, tgt, center)
    timings["refit"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    return _result(p, seed, run, out, src.shape[0], corr, mutual_applied, timings)


def _checked_inputs(source_points, target_points, source_normals, target_normals, p: RansacParams, n: int,
                    check_target: bool):
    """Validated ``(src, tgt, src_n, tgt_n, use_normals)`` of :func:`register_ransac`."""
    src = as_points(source_points, "source_points", min_points=n)
    tgt = (as_points(target_points, "target_points", min_points=n) if check_target
           else as_trusted_points(target_points, "target_points", min_points=n))
    use_normals = p.normal_angle_threshold_rad is not None
    if use_normals:
        if source_normals is None or target_normals is None:
            raise InputError("the normal-angle check needs source_normals and target_normals")
    src_n = None if source_normals is None else as_points(source_normals, "source_normals", min_points=n)
    tgt_n = None if target_normals is None else as_points(target_normals, "target_normals", min_points=n)
    if src_n is not None and src_n.shape[0] != src.shape[0]:
        raise InputError(f"source_normals has {src_n.shape[0]} rows but source_points has {src.shape[0]}")
    if tgt_n is not None and tgt_n.shape[0] != tgt.shape[0]:
        raise InputError(f"target_normals has {tgt_n.shape[0]} rows but target_points has {tgt.shape[0]}")
    _check_not_flat(src, "source")
    _check_not_flat(tgt, "target")
    return src, tgt, src_n, tgt_n, use_normals


def _putative_pairs(src, tgt, source_features, target_features, correspondences, p: RansacParams,
                    target_feature_index):
    """``(corr (k, 2) int64, mutual_applied)``: the given pairs (checked) or descriptor matches."""
    if correspondences is not None:
        corr = np.asarray(correspondences)
        if corr.ndim != 2 or corr.shape[1] != 2 or not np.issubdtype(corr.dtype, np.integer):
            raise InputError(f"correspondences must be an integer array of shape (k, 2), got {corr.shape} {corr.dtype}")
        corr = np.ascontiguousarray(corr, dtype=np.int64)
        if corr.size and (
            corr[:, 0].min() < 0 or corr[:, 0].max() >= src.shape[0] or corr[:, 1].min() < 0 or corr[:, 1].max() >= tgt.shape[0]
        ):
            raise InputError("correspondences refer to points that do not exist")
        return corr, False
    if source_features is None or target_features is None:
        raise InputError("give source_features and target_features, or correspondences")
    fs = np.asarray(source_features, dtype=np.float64)
    ft = np.asarray(target_features, dtype=np.float64)
    if fs.ndim != 2 or fs.shape[0] != src.shape[0]:
        raise InputError(f"source_features must have one row per source point ({src.shape[0]}), got {fs.shape}")
    if ft.ndim != 2 or ft.shape[0] != tgt.shape[0]:
        raise InputError(f"target_features must have one row per target point ({tgt.shape[0]}), got {ft.shape}")
    fm = feature_correspondences(fs, ft, mutual_filter=p.mutual_filter, target_index=target_feature_index)
    return fm.pairs, fm.mutual_applied


@dataclass
class _Run:
    """State of the hypothesis loop of :func:`register_ransac` (best so far, budget, store)."""

    stop_at: int
    best_T: np.ndarray = field(default_factory=lambda: np.eye(4))
    best_c: int = 0
    best_s: float = 0.0
    n_valid: int = 0
    iterations: int = 0
    stop_reason: RansacStatus = RansacStatus.MAX_ITERATIONS
    store: _HypothesisStore = field(default_factory=lambda: _HypothesisStore())
    best_moved: bool = False
    prune: int = 0
    n_tilt: int = 0


def _hypotheses(p: RansacParams, seed, src, csrc, ctgt, csrc_n, ctgt_n, use_normals: bool, grid: _Grid,
                eval_order, center) -> _Run:
    """Draw, check and score hypotheses in batches until the [Baek2022 Eq. 8] budget is spent."""
    n = int(p.ransac_n)
    n_corr = csrc.shape[0]
    d = float(p.distance_threshold_m)
    cos_normal = math.cos(p.normal_angle_threshold_rad) if use_normals else -2.0
    rng = np.random.default_rng(seed)
    distinct_rows = p.mode == "minegeo"
    B = int(p.batch_size)
    run = _Run(stop_at=int(p.max_iterations))
    cos_tilt = math.cos(math.radians(float(p.max_tilt_deg))) if p.max_tilt_deg is not None else None
    it0 = 0
    while it0 < run.stop_at:
        nb = min(B, run.stop_at - it0)
        S = _draw_samples(rng, n_corr, nb, n)
        if p.model == "levelled":
            status, Ts = KL.ransac_check_levelled_kernel(csrc, ctgt, S, float(p.edge_length_similarity), d,
                                                         _LEVELLED_MIN_SPREAD_M2, distinct_rows)
        else:
            status, Ts = K.ransac_check_kernel(
                csrc, ctgt, csrc_n, ctgt_n, S, float(p.edge_length_similarity), p.edge_pairs == "all", d,
                use_normals, cos_normal, _DEGENERATE_TOL, distinct_rows,
            )
        if cos_tilt is not None:
            tilted = (status == K.ST_EVALUATED) & (Ts[:, 2, 2] < cos_tilt)
            run.n_tilt += int(np.count_nonzero(tilted[: run.stop_at - it0]))
            status[tilted] = ST_TILT
        passed = np.flatnonzero(status == K.ST_EVALUATED)
        for g0 in range(0, passed.size, _SCORE_GROUP):
            grp = passed[g0 : g0 + _SCORE_GROUP]
            grp = grp[it0 + grp < run.stop_at]
            if grp.size == 0:
                break
            _score_group(p, run, grp, it0, Ts, src, csrc, ctgt, eval_order, grid, center)
        run.iterations = min(it0 + nb, run.stop_at)
        it0 += nb
    return run


def _score_group(p: RansacParams, run: _Run, grp, it0: int, Ts, src, csrc, ctgt, eval_order, grid: _Grid,
                 center) -> None:
    """Score the checked hypotheses ``Ts[grp]`` on the source cloud and accept them in draw order
    (best by inlier count then SSE, [Baek2022 Eq. 8] budget, runner-up pruning bound)."""
    n = int(p.ransac_n)
    n_corr = csrc.shape[0]
    d = float(p.distance_threshold_m)
    score = K.ransac_score_kernel if grp.size * src.shape[0] > _PARALLEL_WORK else K.ransac_score_serial
    cnts, sses, pruned = score(src, eval_order, np.ascontiguousarray(Ts[grp]), np.int64(run.prune), d, *grid.args())
    n_keep = grp.size
    for q, h in enumerate(grp):
        it = it0 + int(h)
        if it >= run.stop_at:
            n_keep = q
            break
        run.n_valid += 1
        if not pruned[q] and _better(int(cnts[q]), float(sses[q]), run.best_c, run.best_s):
            run.best_c, run.best_s, run.best_T = int(cnts[q]), float(sses[q]), Ts[h].copy()
            run.best_moved = True
            res = csrc @ run.best_T[:3, :3].T + run.best_T[:3, 3] - ctgt
            w = float(np.count_nonzero(np.einsum("ij,ij->i", res, res) < d * d)) / n_corr
            k = required_iterations(w, n, float(p.confidence))
            if k < run.stop_at:
                new_stop = max(it + 1, int(math.ceil(k)), int(p.min_iterations))
                if new_stop < run.stop_at:
                    run.stop_at = new_stop
                    run.stop_reason = RansacStatus.CONVERGED
        if p.max_validations is not None and run.n_valid >= p.max_validations:
            if it + 1 < run.stop_at:
                run.stop_at = it + 1
                run.stop_reason = RansacStatus.MAX_VALIDATIONS
            n_keep = q + 1
            break
    keep = np.flatnonzero(pruned[:n_keep] == 0)
    first_new = run.store.n
    if keep.size:
        run.store.add(Ts[grp[keep]], cnts[keep], sses[keep])
    if run.best_c > 0 and run.store.n and int(p.n_hypotheses) <= 2:
        # runner-up bound: best count among scored hypotheses distinct from the best
        lo = 0 if run.best_moved else first_new
        if run.best_moved:
            run.prune = 0
            run.best_moved = False
        allT, allc, _ = run.store.view(lo)
        if allc.size:
            dist, ang = _distances_to(allT, run.best_T, center)
            distinct = (dist > p.distinct_distance) | (ang > p.distinct_angle_deg)
            if distinct.any():
                run.prune = max(run.prune, int(allc[distinct].max()))


def _final_answer(p: RansacParams, run: _Run, grid: _Grid, src, tgt, center) -> dict:
    """Refit the best and the runner-up hypotheses, collect the alternatives and the final inliers."""
    d = float(p.distance_threshold_m)
    top_k = int(p.n_hypotheses)
    best_T, best_c, best_s = run.best_T, run.best_c, run.best_s
    allT, allc, alls = run.store.view(0)
    refits = int(p.refit_iterations) if p.mode == "minegeo" else 0
    if best_c == 0:
        status_s = RansacStatus.FAILED
        reason = (
            f"no hypothesis out of {run.iterations} passed the checks and explained any source point "
            f"({run.n_valid} scored); the clouds may not overlap or the descriptors do not match"
        )
        T = np.eye(4)
        cnt, sse = 0, 0.0
    else:
        T, cnt, sse = _refit(grid, src, tgt, best_T, best_c, best_s, d, refits)
        status_s = run.stop_reason
        if run.stop_reason == "converged":
            reason = f"Eq. 8 reached confidence {p.confidence} after {run.iterations} iterations"
        elif run.stop_reason == "max_validations":
            reason = f"stopped after {run.n_valid} scored hypotheses (max_validations)"
        else:
            reason = f"stopped at max_iterations={p.max_iterations} before Eq. 8 was satisfied"
    # runner-up: best scored hypothesis distinct from the best hypothesis
    sb_T = None
    sb_c, sb_s = -1, math.nan
    sb_dist = sb_ang = math.nan
    if best_c > 0 and allT.shape[0]:
        dist, ang = _distances_to(allT, best_T, center)
        distinct = (dist > p.distinct_distance) | (ang > p.distinct_angle_deg)
        cand = np.flatnonzero(distinct & (allc > 0))
        if cand.size:
            # highest count, then lowest sse, then earliest draw (lexsort: last key primary)
            o = np.lexsort((cand, alls[cand], -allc[cand]))
            h = cand[o[0]]
            sb_T, sb_c, sb_s = _refit(grid, src, tgt, allT[h].copy(), int(allc[h]), float(alls[h]), d, refits)
            sb_dist, sb_ang = hypothesis_distance(T, sb_T, center)
    alternatives = []
    if cnt > 0:
        alternatives.append((T.copy(), cnt / src.shape[0], math.sqrt(sse / cnt)))
        if top_k > 2:
            o = np.lexsort((np.arange(allc.size), alls, -allc))
            chosen = [best_T]
            for h in o:
                if len(alternatives) >= top_k or allc[h] <= 0:
                    break
                dd, aa = _distances_to(np.stack(chosen), allT[h], center)
                if np.all((dd > p.distinct_distance) | (aa > p.distinct_angle_deg)):
                    chosen.append(allT[h])
                    Th, ch, sh = _refit(grid, src, tgt, allT[h].copy(), int(allc[h]), float(alls[h]), d, refits)
                    alternatives.append((Th, ch / src.shape[0], math.sqrt(sh / ch) if ch else 0.0))
        elif sb_T is not None:
            alternatives.append((sb_T.copy(), sb_c / src.shape[0], math.sqrt(sb_s / sb_c) if sb_c > 0 else 0.0))
    j_final = _score(grid, src, T, d)[2] if cnt > 0 else np.full(src.shape[0], -1)
    inl = np.flatnonzero(j_final >= 0)
    inlier_pairs = np.stack([inl, j_final[inl]], axis=1).astype(np.int64)
    return {"T": T, "cnt": cnt, "sse": sse, "status": status_s, "reason": reason, "sb_T": sb_T, "sb_c": sb_c,
            "sb_s": sb_s, "sb_dist": sb_dist, "sb_ang": sb_ang, "alternatives": alternatives,
            "inlier_pairs": inlier_pairs}


def _result(p: RansacParams, seed, run: _Run, out: dict, N: int, corr, mutual_applied: bool,
            timings: dict) -> RansacResult:
    """The :class:`RansacResult` of :func:`register_ransac` from the loop state and the final answer."""
    cnt, sse, sb_c, sb_s = out["cnt"], out["sse"], out["sb_c"], out["sb_s"]
    return RansacResult(
        T_target_source=out["T"],
        fitness=cnt / N,
        inlier_rmse_m=math.sqrt(sse / cnt) if cnt else 0.0,
        n_inliers=int(cnt),
        iterations=int(run.iterations),
        n_validations=int(run.n_valid),
        converged=out["status"] == "converged",
        status=out["status"],
        reason=out["reason"],
        second_best_fitness=(sb_c / N) if sb_c >= 0 else math.nan,
        second_best_rmse_m=math.sqrt(sb_s / sb_c) if sb_c > 0 else math.nan,
        second_best_n_inliers=int(sb_c),
        second_best_distance_m=out["sb_dist"],
        second_best_rotation_deg=out["sb_ang"],
        second_best_T_target_source=out["sb_T"],
        ambiguity_ratio=(sb_c / cnt) if (sb_c > 0 and cnt > 0) else 0.0,
        correspondences=corr,
        inlier_pairs=out["inlier_pairs"],
        mutual_applied=mutual_applied,
        params=p,
        seed=seed,
        timings_s=timings,
        alternatives=tuple(out["alternatives"]),
        n_tilt_rejected=run.n_tilt,
    )


def _warmup() -> None:
    """Compile the RANSAC and correspondence kernels on tiny inputs (dense and hashed grids)."""
    global _DENSE_MAX_CELLS
    rng = np.random.default_rng(0)
    src = rng.normal(size=(24, 3))
    tgt = src + 0.01
    feats = rng.random((24, 33))
    corr = np.stack([np.arange(24), np.arange(24)], axis=1)
    nrm = np.tile(np.array([0.0, 0.0, 1.0]), (24, 1))
    params = RansacParams(distance_threshold_m=0.1, ransac_n=3, max_iterations=64, batch_size=32)
    register_ransac(src, tgt, feats, feats, params, seed=0)
    register_ransac(src, tgt, params=RansacParams(distance_threshold_m=0.1, ransac_n=3, max_iterations=32,
                                                  normal_angle_threshold_rad=1.0, mode="open3d", batch_size=32),
                    seed=0, source_normals=nrm, target_normals=nrm, correspondences=corr)
    saved = _DENSE_MAX_CELLS
    try:
        _DENSE_MAX_CELLS = 0
        g = _Grid(tgt, 0.1)
        g.nearest(src, np.eye(4), 0.1)
    finally:
        _DENSE_MAX_CELLS = saved
    Ts = np.eye(4)[None].copy()
    K.grid_nearest_batch(src, np.eye(3), np.zeros(3), *_Grid(tgt, 0.1).args(), 0.01)
    K.ransac_score_kernel(src, np.arange(24, dtype=np.int64), Ts, np.int64(0), 0.1, *_Grid(tgt, 0.1).args())
    feature_correspondences(feats, feats, mutual_filter=True)
    KL._warmup()
    big = rng.random((300, 33))  # enough rows for the descriptor tree (FEATURE_LEAF * 8)
    feature_correspondences(big[:40], big)
