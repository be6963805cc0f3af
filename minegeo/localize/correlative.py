"""Correlative 4-DOF search of a levelled scan over the whole map (a minegeo addition).

Why
---
The paper's candidate generator (FPFH matches + RANSAC, Baek et al. 2022 Secs. 2.3-2.4) can
only propose a placement when enough of the scan's descriptors find their true partner in
the map. Measured on the synthetic paper-preset mine at the true pose, only 0-4 % of the
nearest FPFH matches are right, and for some sections (the sump behind its railings, an
irregular roof seen by a 2-D profiler) *none* are: RANSAC then never proposes the right
place, however long it runs. An IMU-levelled scan (the normal output of a mobile mapping
system) has only four unknowns, heading ``ψ`` and a translation, and the map is small enough
to try every heading at every place a scanner can stand on: this module does that, with a
branch-free hit count, and hands the best distinct placements to the same ICP and
verification as RANSAC's hypotheses (:func:`minegeo.localize.localize_scan`).

Model
-----
* Map occupancy: the cells of edge ``c`` (``cell_size_m``) holding at least one ICP point of
  the map, dilated by ``dilation_cells`` cells (Chebyshev), in a blocked bitmap (8³-cell
  blocks found by hashing, or through a dense block directory when the map's bounding box is
  small enough, :mod:`minegeo.localize._kernels`): a scan point *hits* when its
  cell is in the dilated set, i.e. it lies within roughly ``c`` to ``(1 + dilation) c`` of the
  map surface.
* Anchors: map points whose (void-oriented) normal points up within ``anchor_max_tilt_deg``
  (the floor of a drift: places a scanner can stand over), on the map's feature voxel grid.
* Scan reference: the scan's floor point nearest (horizontally) to its centroid; the scan
  sample ``S`` is a seeded random subset of the scan's feature-level points, relative to it.
* Placement ``(a, ψ)``: ``p ↦ Rz(ψ) (p − r) + a`` for every anchor ``a`` and every heading
  ``ψ`` on a ``yaw_step_deg`` grid, scored by its number of hits (Olson 2009's correlative
  scan matching in 3-D, evaluated exhaustively over anchors instead of a translation grid).
* The best-ranked placement of every (``distinct_m`` cell of the scan centre, ``distinct_deg``
  heading bin), up to ``n_coarse`` of them, is refined by a 4-DOF point-to-plane Gauss-Newton
  in two stages: a screening stage on ``screen_points`` scan points against the map's ICP
  cloud thinned to ``screen_voxel_size_m`` voxels (its nearest-neighbour search is several
  times cheaper than in the full cloud), then the best ``n_refine`` on ``max_refine_points``
  points against the full ICP cloud. The ``n_candidates`` best refined placements that are
  pairwise distinct (scan centre farther than ``distinct_m`` or heading differing by more than
  ``distinct_deg``) are returned as ``T_work_scan`` matrices.

The search is exhaustive over its grid, so it is deterministic (the seed only picks the scan
sample) and independent of the thread count.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from minegeo.errors import InputError
from minegeo.localize import _kernels as K
from minegeo.localize.params import CorrelativeParams

__all__ = ["CorrelativeParams", "CorrelativeResult", "correlative_candidates", "map_occupancy", "placement_grid"]


#: Largest dense block directory (int32 entries, 64 MB; at 0.5 m cells a 4 m block, e.g. a
#: 2 km x 2 km x 250 m box): larger maps are scored through the hash table (~20 % slower).
MAX_DENSE_BLOCKS = 1 << 24

#: Gates (m) of the screening stage's three Gauss-Newton steps.
SCREEN_GATES_M = (1.5, 1.0, 0.7)


@dataclass(frozen=True)
class MapOccupancy:
    """The map side of the search: blocked occupancy bitmap and floor anchors (work frame).

    ``block_keys`` / ``bits`` / ``log2_blocks`` are :func:`_kernels.build_blocked_occupancy`'s
    output (dilated and undilated masks per 8³-cell block); ``table`` / ``table_lo`` its dense
    block directory (:func:`_kernels.dense_block_table`; empty when the map's bounding box
    holds more than ``MAX_DENSE_BLOCKS`` blocks); ``n_cells`` occupied cells, ``n_blocks``
    blocks in use.
    """

    block_keys: np.ndarray
    bits: np.ndarray
    log2_blocks: int
    table: np.ndarray
    table_lo: np.ndarray
    n_cells: int
    n_blocks: int
    anchors: np.ndarray
    cell_size_m: float
    dilation_cells: int
    build_s: float


@dataclass(frozen=True)
class CorrelativeResult:
    """Outcome of :func:`correlative_candidates`.

    Attributes
    ----------
    candidates : list of (T_work_scan (4, 4), hit_fraction)
        Best distinct placements, best first.
    reference_point : (3,) ndarray or None
        The scan floor point ``r`` the placements pivot about (scan frame, m).
    n_anchors, n_yaw, n_sample : int
        Search grid size and scan sample size.
    best_hit_fraction : float
    reason : str
        Why no candidate was produced (empty when there are some).
    params : CorrelativeParams
    timings_s : dict
    coverage : dict or None
        With a ``witness`` placement (:func:`correlative_candidates`): at each stage of the
        cascade (``grid`` bins, ``screen``, ``refine`` + distinct selection) the witness's own
        best score (``*_self``, a fraction of the stage's largest score; NaN when no placement
        of the stage is near the witness), how many placements reach it minus the slack
        (``*_at_least``; -1 without a witness score) and how many the stage kept (``*_kept``);
        ``covered`` is true when every stage found the witness and kept all of the former.
        None without a witness.
    """

    candidates: list
    reference_point: np.ndarray | None
    n_anchors: int
    n_yaw: int
    n_sample: int
    best_hit_fraction: float
    reason: str
    params: CorrelativeParams
    timings_s: dict = field(default_factory=dict)
    coverage: dict | None = None

    def to_dict(self) -> dict:
        d = {"n_candidates": len(self.candidates), "hit_fractions": [float(f) for _, f in self.candidates],
             "reference_point": None if self.reference_point is None else self.reference_point.tolist(),
             "n_anchors": self.n_anchors, "n_yaw": self.n_yaw, "n_sample": self.n_sample,
             "n_placements": self.n_anchors * self.n_yaw, "best_hit_fraction": self.best_hit_fraction,
             "reason": self.reason, "params": asdict(self.params), "timings_s": dict(self.timings_s)}
        if self.coverage is not None:
            d["coverage"] = dict(self.coverage)
        return d


def map_occupancy(icp_points: np.ndarray, points: np.ndarray, normals: np.ndarray,
                  params: CorrelativeParams) -> MapOccupancy:
    """Build the map side of the search (once per map and process; ~1 s for 8e6 points).

    Parameters
    ----------
    icp_points : (k, 3) float64
        Dense map points (work frame, m): the occupancy.
    points, normals : (m, 3) float64
        Feature-level map points and their void-oriented unit normals: the anchors.
    params : CorrelativeParams
    """
    t0 = time.perf_counter()
    c = float(params.cell_size_m)
    cells = K.unique_cells(np.ascontiguousarray(icp_points, dtype=np.float64), c)
    d = int(params.dilation_cells)
    # blocks of 8³ cells: a dilated cell set fits in about n_cells (1 + 2d)³ / 64 blocks (or fewer)
    log2 = max(10, int(math.ceil(math.log2(max(1, cells.shape[0]) * (1 + 2 * d) / 32))) + 1)
    while True:
        block_keys, bits, nb = K.build_blocked_occupancy(cells, d, log2)
        if nb <= (1 << log2) // 2:
            break
        log2 += 1
    table, table_lo = K.dense_block_table(block_keys, MAX_DENSE_BLOCKS)
    up = math.cos(math.radians(params.anchor_max_tilt_deg))
    anchors = np.ascontiguousarray(points[normals[:, 2] >= up], dtype=np.float64)
    return MapOccupancy(block_keys=block_keys, bits=bits, log2_blocks=log2, table=table, table_lo=table_lo,
                        n_cells=int(cells.shape[0]),
                        n_blocks=int(nb), anchors=anchors, cell_size_m=c, dilation_cells=d,
                        build_s=time.perf_counter() - t0)


def _distinct_select(cpos: np.ndarray, yaw: np.ndarray, order: np.ndarray, n_max: int, params) -> list[int]:
    """Greedy non-maximum suppression in ``order``: keep a placement unless an already kept one
    puts the scan centre within ``distinct_m`` *and* has a heading within ``distinct_deg``."""
    chosen: list[int] = []
    dmax2 = float(params.distinct_m) ** 2
    dang = math.radians(float(params.distinct_deg))
    for j in order:
        if chosen:
            cj = np.asarray(chosen)
            d2 = np.sum((cpos[cj] - cpos[j]) ** 2, axis=1)
            da = np.abs((yaw[cj] - yaw[j] + math.pi) % (2 * math.pi) - math.pi)
            if np.any((d2 <= dmax2) & (da <= dang)):
                continue
        chosen.append(int(j))
        if len(chosen) >= n_max:
            break
    return chosen


def placement_grid(S: np.ndarray, yaws: np.ndarray, anchors: np.ndarray, cell_size_m: float):
    """The scoring kernel's inputs in cell units: ``RX, RY`` (n_yaw, m) = the sample's x, y
    rotated by each heading, ``SZ`` (m,) its z, and the anchors, all divided by the cell size
    (the cell of a placed point is then ``floor(RX + a_x), floor(RY + a_y), floor(SZ + a_z)``)."""
    inv = 1.0 / float(cell_size_m)
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    RX = np.ascontiguousarray((c * S[None, :, 0] - s * S[None, :, 1]) * inv)
    RY = np.ascontiguousarray((s * S[None, :, 0] + c * S[None, :, 1]) * inv)
    return RX, RY, np.ascontiguousarray(S[:, 2] * inv), np.ascontiguousarray(anchors * inv)


def _first_of_each_bin(bins: np.ndarray) -> np.ndarray:
    """Index of the first row of every distinct row of ``bins`` (n, k) int64 (the set that
    ``np.unique(bins, axis=0, return_index=True)[1]`` gives, computed on one packed int64 key
    per row when the bin ranges allow it: ~10 times faster)."""
    if bins.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    lo = bins.min(axis=0)
    span = bins.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return np.unique(bins, axis=0, return_index=True)[1]
    key = np.zeros(bins.shape[0], dtype=np.int64)
    for j in range(bins.shape[1]):
        key = key * span[j] + (bins[:, j] - lo[j])
    return np.unique(key, return_index=True)[1]


def _near_witness(Ts: np.ndarray, c: np.ndarray, W: np.ndarray, params) -> np.ndarray:
    """Mask of the placements ``Ts`` (n, 4, 4) that put the scan point ``c`` within ``distinct_m``
    of where ``W`` puts it, with a heading within ``distinct_deg`` of ``W``'s."""
    pos = np.einsum("nij,j->ni", Ts[:, :3, :3], c) + Ts[:, :3, 3]
    wpos = W[:3, :3] @ c + W[:3, 3]
    yaw = np.arctan2(Ts[:, 1, 0], Ts[:, 0, 0])
    da = np.abs((yaw - math.atan2(W[1, 0], W[0, 0]) + math.pi) % (2 * math.pi) - math.pi)
    return (np.sum((pos - wpos) ** 2, axis=1) <= float(params.distinct_m) ** 2) & (
        da <= math.radians(float(params.distinct_deg)))


def _cover(scores: np.ndarray, self_mask: np.ndarray, slack: float, n_kept: int, cap: int, adaptive: bool):
    """Coverage of one cascade stage: ``(n_keep, self_score, n_at_least)``.

    ``scores`` are the stage's scores in its ranking order; the witness's score is the best
    one among ``self_mask``; ``n_at_least`` placements score at least that minus ``slack``. With
    ``adaptive`` the stage keeps ``max(n_kept, n_at_least)`` (at most ``cap``)."""
    if not self_mask.any():
        return n_kept, math.nan, -1
    s_self = float(scores[self_mask].max())
    n_at = int(np.count_nonzero(scores >= s_self - slack))
    return (max(n_kept, min(n_at, cap)) if adaptive else n_kept), s_self, n_at


@dataclass(frozen=True)
class _ScanSample:
    """The scan side of one search (scan frame, m).

    Attributes
    ----------
    P : (n, 3) float64
        The scan's feature-level points.
    r : (3,) float64
        Reference floor point: the placements pivot about it.
    near : (k,) int64
        Indices of the points within ``sample_radius_m`` of ``r`` (horizontally).
    order : (m,) int64
        The grid's scan sample: a seeded random subset of ``near``.
    m : int
        Sample size.
    max_miss : int
        Misses allowed by ``min_hit_fraction``.
    centre : (3,) float64
        Mean of ``P[near]``: the scan centre of the distinct-placement tests.
    """

    P: np.ndarray
    r: np.ndarray
    near: np.ndarray
    order: np.ndarray
    m: int
    max_miss: int
    centre: np.ndarray


@dataclass(frozen=True)
class _Ranked:
    """Grid placements that hit ``min_hit_fraction`` of the sample, best first.

    Attributes
    ----------
    hits, rank_score : (q,) int
        Hits within ~``c (1 + d)`` and the ranking score (those hits plus the hits within ~``c``).
    ai, yi, ki : (q,) int64
        Anchor, heading (index into the ``yaw_step_deg`` grid) and pass of each placement.
    cpos : (q, 3) float64
        Where each placement puts the scan centre (work frame, m).
    """

    hits: np.ndarray
    rank_score: np.ndarray
    ai: np.ndarray
    yi: np.ndarray
    ki: np.ndarray
    cpos: np.ndarray


def _empty_result(occupancy: MapOccupancy, yaws: np.ndarray, params: CorrelativeParams, timings: dict,
                  t0: float, reason: str, ref=None, m: int = 0) -> CorrelativeResult:
    """A result without candidates, saying ``reason``."""
    timings["total"] = time.perf_counter() - t0
    return CorrelativeResult([], ref, int(occupancy.anchors.shape[0]), int(yaws.size), m, 0.0, reason, params,
                             timings)


def _scan_sample(P: np.ndarray, floor: np.ndarray, params: CorrelativeParams, seed: int,
                 reference_xy) -> _ScanSample:
    """Reference floor point nearest (horizontally) to ``reference_xy`` and the seeded scan sample around it."""
    ch = np.median(P[:, :2], axis=0) if reference_xy is None else np.asarray(reference_xy, dtype=np.float64)[:2]
    r = P[floor[np.argmin(np.sum((P[floor, :2] - ch) ** 2, axis=1))]].copy()
    near = np.flatnonzero(np.sum((P[:, :2] - r[:2]) ** 2, axis=1) <= float(params.sample_radius_m) ** 2)
    rng = np.random.default_rng(seed)
    order = near[rng.permutation(near.size)[: int(params.max_scan_points)]]
    S = np.ascontiguousarray(P[order] - r)
    m = S.shape[0]
    max_miss = int(math.floor((1.0 - float(params.min_hit_fraction)) * m))
    return _ScanSample(P, r, near, order, m, max_miss, P[near].mean(axis=0))


def _no_search_reason(floor: np.ndarray, occupancy: MapOccupancy, params: CorrelativeParams) -> str:
    """Why no placement can be searched (no scan floor, no map anchors), or ""."""
    if floor.size == 0:
        return ("the scan shows no floor (no normal within "
                f"{params.anchor_max_tilt_deg:g} deg of vertical): is it levelled (z up)?")
    if occupancy.anchors.shape[0] == 0:
        return "the map has no floor points to stand the scan on"
    return ""


def _grid_passes(grid_references, r: np.ndarray) -> tuple[list, np.ndarray]:
    """The grid's pivots ``(q (3,), heading indices or None)`` and their points ``refs`` (p, 3).

    The one pass pivots on the reference point ``r`` unless ``grid_references`` are given.
    """
    if grid_references is None:
        passes = [(r, None)]
    else:
        passes = [(np.asarray(q, dtype=np.float64).reshape(3), None if k is None else np.asarray(k, dtype=np.int64))
                  for q, k in grid_references]
    return passes, np.array([q for q, _ in passes]).reshape(-1, 3)


def _score_grid(occupancy: MapOccupancy, params: CorrelativeParams, smp: _ScanSample, passes: list,
                yaws: np.ndarray):
    """Hit counts of every (anchor, heading) placement of every pass (:func:`_kernels.score_placements`).

    Returns ``(hits, rank_score, ai, yi, ki, best)`` of the placements that reach
    ``min_hit_fraction`` (in grid order, passes one after the other) and the best hit fraction.
    """
    P, order, m, max_miss = smp.P, smp.order, smp.m, smp.max_miss
    hits_l, rank_l, ai_l, yi_l, ki_l = [], [], [], [], []
    best = 0.0
    for k, (q, ysub) in enumerate(passes):
        yk = yaws if ysub is None else yaws[ysub]
        RX, RY, SZ, A = placement_grid(np.ascontiguousarray(P[order] - q), yk, occupancy.anchors,
                                       occupancy.cell_size_m)
        scores, tight = K.score_placements(occupancy.block_keys, occupancy.bits, occupancy.log2_blocks,
                                           occupancy.table, occupancy.table_lo, RX, RY, SZ, A, max_miss,
                                           1.0 - float(params.min_hit_fraction), float(params.early_miss_slack))
        flat = scores.ravel()
        kk = np.flatnonzero(flat >= m - max_miss)
        best = max(best, float(flat.max()) / m if flat.size else 0.0)
        a_k, y_k = np.divmod(kk, yk.size)
        hits_l.append(flat[kk])
        rank_l.append(flat[kk] + tight.ravel()[kk])  # hits within ~c(1+d), plus those within ~c
        ai_l.append(a_k)
        yi_l.append(y_k if ysub is None else ysub[y_k])
        ki_l.append(np.full(kk.size, k, dtype=np.int64))
    hits, rank_score = np.concatenate(hits_l), np.concatenate(rank_l)
    ai, yi, ki = np.concatenate(ai_l), np.concatenate(yi_l), np.concatenate(ki_l)
    return hits, rank_score, ai, yi, ki, best


def _rank(hits, rank_score, ai, yi, ki, smp: _ScanSample, refs: np.ndarray, cos_y: np.ndarray,
          sin_y: np.ndarray, anchors: np.ndarray) -> _Ranked:
    """Sort the placements best first (ties in grid order) and place the scan centre with each."""
    m = smp.m
    # best first, ties in grid order; a small integer key lets NumPy's stable sort use radix sort
    key = 2 * m - rank_score
    order_k = np.argsort(key.astype(np.int16) if 2 * m < 2**15 else key, kind="stable")
    hits, rank_score, ai, yi, ki = hits[order_k], rank_score[order_k], ai[order_k], yi[order_k], ki[order_k]
    centre = (smp.centre - refs)[ki]  # the scan centre relative to each placement's pivot
    cy, sy = cos_y[yi], sin_y[yi]
    cpos = np.column_stack([cy * centre[:, 0] - sy * centre[:, 1], sy * centre[:, 0] + cy * centre[:, 1],
                            centre[:, 2]]) + anchors[ai]
    return _Ranked(hits, rank_score, ai, yi, ki, cpos)


def _bin_leaders(rk: _Ranked, yaws: np.ndarray, params: CorrelativeParams) -> np.ndarray:
    """Indices (into ``rk``, best first) of the best-ranked placement per bin.

    One placement per (``distinct_m`` cell of the scan centre, ``distinct_deg`` heading bin).
    """
    # the best-ranked one: np.unique keeps the first occurrence in this ranked order
    dm, dd = float(params.distinct_m), float(params.distinct_deg)
    bins = np.column_stack([np.floor(rk.cpos / dm), np.floor(np.rad2deg(yaws[rk.yi]) / dd)]).astype(np.int64)
    return np.sort(_first_of_each_bin(bins))  # bin leaders, best first


def _grid_coverage(rk: _Ranked, first: np.ndarray, W: np.ndarray | None, smp: _ScanSample, yaws: np.ndarray,
                   params: CorrelativeParams, n_first: int, cover_slack: float,
                   cover_max_factor: float) -> tuple[int, dict | None]:
    """The witness's best grid placement and the bin leaders reaching it minus the slack.

    Returns the (possibly enlarged) number of grid placements to keep and the coverage record
    (``n_first`` and None without a witness ``W``).
    """
    if W is None:
        return n_first, None
    m = smp.m
    dm, dd = float(params.distinct_m), float(params.distinct_deg)
    wpos = W[:3, :3] @ smp.centre + W[:3, 3]
    da = np.abs((yaws[rk.yi] - math.atan2(W[1, 0], W[0, 0]) + math.pi) % (2 * math.pi) - math.pi)
    self_mask = (np.sum((rk.cpos - wpos) ** 2, axis=1) <= dm**2) & (da <= math.radians(dd))
    cap = int(round(float(cover_max_factor) * n_first))
    if self_mask.any():
        s_self = float(rk.rank_score[self_mask].max())
        n_at = int(np.count_nonzero(rk.rank_score[first] >= s_self - float(cover_slack) * 2 * m))
        n_first = max(n_first, min(n_at, cap))
    else:
        s_self, n_at = math.nan, -1
    cov = {"grid_self": s_self / (2 * m), "grid_at_least": n_at, "grid_kept": min(n_first, first.size),
           "grid_self_bin_rank": (int(np.count_nonzero(rk.rank_score[first] > s_self)) + 1
                                  if self_mask.any() else None)}
    return n_first, cov


def _placement_matrices(rk: _Ranked, chosen: np.ndarray, refs: np.ndarray, cos_y: np.ndarray, sin_y: np.ndarray,
                        anchors: np.ndarray, single_pass: bool) -> np.ndarray:
    """``T = [Rz(ψ) | a − Rz(ψ) q]`` (k, 4, 4) of every chosen placement (``q`` its pass's pivot)."""
    cj, sj = cos_y[rk.yi[chosen]], sin_y[rk.yi[chosen]]
    T0s = np.zeros((chosen.size, 4, 4))
    T0s[:, 0, 0], T0s[:, 0, 1], T0s[:, 1, 0], T0s[:, 1, 1] = cj, -sj, sj, cj
    T0s[:, 2, 2] = T0s[:, 3, 3] = 1.0
    if single_pass:
        T0s[:, :3, 3] = anchors[rk.ai[chosen]] - np.einsum("nij,j->ni", T0s[:, :3, :3], refs[0])
    else:
        T0s[:, :3, 3] = anchors[rk.ai[chosen]] - np.einsum("nij,nj->ni", T0s[:, :3, :3], refs[rk.ki[chosen]])
    return T0s


def _screen_stage(Sa: np.ndarray, T0s: np.ndarray, screen, screen_grid, params: CorrelativeParams,
                  tol: float) -> tuple[np.ndarray, np.ndarray]:
    """A few cheap 4-DOF Gauss-Newton steps of every grid placement against the thinned map.

    ``screen`` is ``(GatedKDTree, points, normals)`` of the thinned ICP cloud (work frame);
    returns the screened placements and their plane counts on ``Sa``.
    """
    Ta = np.empty_like(T0s)
    ca = np.zeros(T0s.shape[0], dtype=np.int64)
    s_index, Qs_, Ns_ = screen
    Qs_, Ns_ = np.ascontiguousarray(Qs_), np.ascontiguousarray(Ns_)
    gates2 = np.array(SCREEN_GATES_M) ** 2
    if screen_grid is not None and params.screen_grid:
        # Gauss-Newton steps on the lookup grid, then the exact score (no step, KD-tree)
        Tg = np.empty_like(T0s)
        K.steps_4dof_grid(Sa, T0s, Qs_, Ns_, *screen_grid, gates2, Tg)
        K.refine_placements_4dof(Sa, Tg, Qs_, Ns_, s_index.packed, np.zeros(0), tol, 0.25, Ta, ca)
    else:
        K.refine_placements_4dof(Sa, T0s, Qs_, Ns_, s_index.packed, gates2, tol, 0.25, Ta, ca)
    return Ta, ca


def _distinct_refined(Ts: list, fr: list, smp: _ScanSample, W, params: CorrelativeParams, cov: dict | None,
                      cover_slack: float, cover_max_factor: float) -> list[int]:
    """Indices of the ``n_candidates`` best pairwise distinct refined placements (more with a witness).

    With a witness ``W`` every distinct placement reaching its refined score minus the slack is
    kept (up to ``cover_max_factor`` times ``n_candidates``) and ``cov`` is updated.
    """
    cen = smp.centre
    cpos2 = np.array([T[:3, :3] @ cen + T[:3, 3] for T in Ts])
    yaw2 = np.array([math.atan2(T[1, 0], T[0, 0]) for T in Ts])
    rank = np.argsort(-np.asarray(fr), kind="stable")
    n_cand = int(params.n_candidates)
    if W is None:
        return _distinct_select(cpos2, yaw2, rank, n_cand, params)
    # every distinct placement reaching the witness's refined score minus the slack
    fra = np.asarray(fr)[rank]
    sm = _near_witness(np.asarray(Ts)[rank], cen, W, params) if Ts else np.zeros(0, bool)
    s_self = float(fra[sm].max()) if sm.any() else math.nan
    cap = int(round(float(cover_max_factor) * n_cand))
    sel = _distinct_select(cpos2, yaw2, rank, len(Ts), params)  # every distinct one, best first
    n_at = (int(sum(fr[j] >= s_self - float(cover_slack) for j in sel)) if sm.any() else -1)
    n_cand = max(n_cand, min(n_at, cap))
    cov.update(refine_self=s_self, refine_at_least=n_at, candidates_kept=min(n_cand, len(sel)))
    return sel[:n_cand]


def _refine_cascade(T0s: np.ndarray, smp: _ScanSample, refine_target, screen_target, screen_grid,
                    params: CorrelativeParams, seed: int, W, cov: dict | None, cover_slack: float,
                    cover_max_factor: float) -> tuple[list, list]:
    """Screening, full 4-DOF refinement and distinct selection; returns ``(Ts, fractions)``, best first.

    Every grid placement gets a few cheap steps on a small subset against the thinned map, the
    best ``n_refine`` of them the full refinement on all refinement points against the full ICP
    cloud (:func:`_kernels.refine_placements_4dof`).
    """
    P, near = smp.P, smp.near
    index, Q, Nq = refine_target
    Q = np.ascontiguousarray(Q)
    Nq = np.ascontiguousarray(Nq)
    perm = near[np.random.default_rng(seed + 1).permutation(near.size)[: int(params.max_refine_points)]]
    tol = float(params.refine_tolerance_m)
    Sa = np.ascontiguousarray(P[perm[: int(params.screen_points)]])
    screen = (index, Q, Nq) if screen_target is None else screen_target
    Ta, ca = _screen_stage(Sa, T0s, screen, screen_grid, params, tol)
    n_ref = int(params.n_refine)
    if W is not None:
        o = np.argsort(-ca, kind="stable")
        n_ref, s_self, n_at = _cover(ca[o].astype(np.float64), _near_witness(Ta[o], smp.centre, W, params),
                                     float(cover_slack) * Sa.shape[0], n_ref,
                                     int(round(float(cover_max_factor) * n_ref)), True)
        cov.update(screen_self=s_self / Sa.shape[0], screen_at_least=n_at, screen_kept=min(n_ref, ca.size))
    top = np.argsort(-ca, kind="stable")[:n_ref]
    Sr = np.ascontiguousarray(P[perm])
    Tb = np.empty((top.size, 4, 4))
    cb = np.zeros(top.size, dtype=np.int64)
    gates2 = np.linspace(1.0, 0.5, int(params.refine_iterations)) ** 2
    K.refine_placements_4dof(Sr, np.ascontiguousarray(Ta[top]), Q, Nq, index.packed, gates2, tol, 0.25, Tb, cb)
    Ts = [Tb[k] for k in range(top.size)]
    fr = [int(cb[k]) / Sr.shape[0] for k in range(top.size)]
    sel = _distinct_refined(Ts, fr, smp, W, params, cov, cover_slack, cover_max_factor)
    return [Ts[j] for j in sel], [fr[j] for j in sel]


def _finish_coverage(cov: dict, cover_slack: float) -> None:
    """``covered``: every stage found the witness and kept all placements reaching its score."""
    cov["covered"] = bool(0 <= cov.get("grid_at_least", -1) <= cov.get("grid_kept", -1)
                          and 0 <= cov.get("screen_at_least", -1) <= cov.get("screen_kept", -1)
                          and 0 <= cov.get("refine_at_least", -1) <= cov.get("candidates_kept", -1))
    cov["slack"] = float(cover_slack)


def correlative_candidates(occupancy: MapOccupancy, scan_points: np.ndarray, scan_normals: np.ndarray,
                           params: CorrelativeParams, seed: int = 0, reference_xy=None,
                           refine_target=None, screen_target=None, screen_grid=None, *, grid_references=None,
                           witness=None, cover_slack: float = 0.1, cover_max_factor: float = 1.0) -> CorrelativeResult:
    """Best distinct 4-DOF placements of a levelled scan (z up) in the map.

    Parameters
    ----------
    occupancy : MapOccupancy
        From :func:`map_occupancy` (same ``cell_size_m`` and ``dilation_cells``).
    scan_points, scan_normals : (n, 3) float64
        The scan's feature-level points (scan frame, z up within a few degrees, m) and their
        void-oriented normals.
    params : CorrelativeParams
    seed : int
        Picks the scan sample.
    reference_xy : (2,) array_like, optional
        Where the scanner was (scan frame, m), e.g. the middle of its trajectory; the
        reference floor point is the one nearest to it (default: the median of the points).
    refine_target : (GatedKDTree, points (k, 3), normals (k, 3)), optional
        The map's ICP cloud (work frame) and its gated KD-tree
        (:func:`minegeo.registration.build_target_index`) for the local 4-DOF refinement of the
        ``n_coarse`` best grid placements (:func:`_kernels.refine_placements_4dof`, ``prange``
        over placements); without it the grid placements are returned as they are.
    screen_target : (GatedKDTree, points (k, 3), normals (k, 3)), optional
        The thinned ICP cloud the first refinement stage searches
        (:meth:`minegeo.localize.PreparedMap.screen_target`); default: ``refine_target``.
    screen_grid : (block_keys, nearest, log2_blocks, cell_m), optional
        Nearest-point lookup grid over ``screen_target``'s points
        (:meth:`minegeo.localize.PreparedMap.screen_grid`) for the screening stage's
        Gauss-Newton steps (``params.screen_grid``); its score stays exact.
    grid_references : sequence of ((3,) array_like, heading indices or None), optional
        The grid's pivots instead of the one reference floor point: each ``(q, k)`` scores
        every anchor × the headings ``k`` (indices into the ``yaw_step_deg`` grid; None = all)
        with the placements ``p ↦ Rz(ψ) (p − q) + a``; all passes are ranked together (ties:
        earlier pass first). The scan sample is still drawn around the reference point. Used by
        the rival search (:mod:`minegeo.localize.rivals`) to pivot on scan floor points that
        land on mapped floor.
    witness : (4, 4) ndarray, optional
        A placement known to be right (``scan_points`` → work frame; the rival search passes
        the chosen placement): at each stage of the cascade (grid bins, screening, refinement,
        distinct selection) its own best score ``s`` is found (the best placement within
        ``distinct_m`` / ``distinct_deg`` of it) and the number of placements scoring at least
        ``s − cover_slack × (largest score)`` is recorded (``CorrelativeResult.coverage``).
        Needs ``refine_target``.
    cover_slack : float
        See ``witness`` (a fraction of the stage's largest possible score).
    cover_max_factor : float
        With a witness, a stage keeps more than its ``n_coarse`` / ``n_refine`` /
        ``n_candidates`` when more placements reach the witness's score minus the slack, up to
        this factor times it (1: the fixed sizes, coverage only recorded).

    Returns
    -------
    CorrelativeResult
        ``candidates`` holds ``T_work_scan`` with ``R = Rz(ψ)``, ``t = a − R r`` (refined when
        ``refine_target`` is given), best first, and their hit fractions (grid) or plane
        fractions (refined).
    """
    if occupancy.cell_size_m != float(params.cell_size_m) or occupancy.dilation_cells != int(params.dilation_cells):
        raise InputError("the map occupancy was built with other cell settings than these CorrelativeParams")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    P = np.ascontiguousarray(scan_points, dtype=np.float64)
    N = np.ascontiguousarray(scan_normals, dtype=np.float64)
    up = math.cos(math.radians(params.anchor_max_tilt_deg))
    floor = np.flatnonzero(N[:, 2] >= up)
    yaws = np.deg2rad(np.arange(0.0, 360.0, float(params.yaw_step_deg)))
    why = _no_search_reason(floor, occupancy, params)
    if why:
        return _empty_result(occupancy, yaws, params, timings, t0, why)
    smp = _scan_sample(P, floor, params, seed, reference_xy)
    r, m = smp.r, smp.m
    timings["setup"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    passes, refs = _grid_passes(grid_references, r)
    hits, rank_score, ai, yi, ki, best = _score_grid(occupancy, params, smp, passes, yaws)
    timings["score"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    if rank_score.size == 0:
        return _empty_result(occupancy, yaws, params, timings, t0,
                             f"no placement hits {100 * params.min_hit_fraction:.0f} % of the scan sample "
                             f"(best {100 * best:.0f} %)", r, m)
    cos_y, sin_y = np.cos(yaws), np.sin(yaws)
    rk = _rank(hits, rank_score, ai, yi, ki, smp, refs, cos_y, sin_y, occupancy.anchors)
    n_first = int(params.n_coarse) if refine_target is not None else int(params.n_candidates)
    first = _bin_leaders(rk, yaws, params)
    W = None if witness is None or refine_target is None else np.asarray(witness, dtype=np.float64)
    n_first, cov = _grid_coverage(rk, first, W, smp, yaws, params, n_first, cover_slack, cover_max_factor)
    chosen = first[:n_first]
    T0s = _placement_matrices(rk, chosen, refs, cos_y, sin_y, occupancy.anchors, len(passes) == 1)
    Ts = list(T0s)
    fr = (rk.hits[chosen] / m).tolist()
    timings["select"] = time.perf_counter() - t1
    if refine_target is not None:
        t1 = time.perf_counter()
        Ts, fr = _refine_cascade(T0s, smp, refine_target, screen_target, screen_grid, params, seed, W, cov,
                                 cover_slack, cover_max_factor)
        timings["refine"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0
    if cov is not None:
        _finish_coverage(cov, cover_slack)
    return CorrelativeResult(list(zip(Ts, fr, strict=True)), r, int(occupancy.anchors.shape[0]), int(yaws.size), m, best, "",
                             params, timings, cov)


def _warmup() -> None:
    """Compile the search's kernels on a tiny map: occupancy, scoring, the lookup grid and both
    refinement kernels (KD-tree and grid)."""
    from minegeo.registration import build_target_index

    rng = np.random.default_rng(0)
    Q = rng.uniform(0, 4, (200, 3))
    Nq = np.tile([0.0, 0.0, 1.0], (200, 1))
    cp = CorrelativeParams(n_coarse=4, n_refine=2, n_candidates=2)
    occ = map_occupancy(Q, Q, Nq, cp)
    index = build_target_index(Q)
    keys, nearest, nb = K.build_nearest_grid(Q, 0.5, 1, 10)
    correlative_candidates(occ, Q[:50], Nq[:50], cp, refine_target=(index, Q, Nq), screen_target=(index, Q, Nq),
                           screen_grid=(keys, nearest, 10, 0.5))
