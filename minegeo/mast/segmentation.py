"""Segmentation of a 2D scan into lines and identification of beacon panels.

Simela, Marshall & Daneshmend, section "Data Segmentation", Figure 2 and Table 1.

1. :func:`segment_scan` — sequential PCA line fitting over the scan-ordered points
   (:func:`minegeo.mast._kernels._grow_segments`); consecutive lines share a node.
2. :func:`identify_panels` — for every pair of consecutive lines ``(a, b)`` and every
   pair of consecutive beacon panels ``(X, Y)`` (in the order a clockwise scan meets
   them) four tests are made:

   ``p1``: length of ``a`` matches ``X``; ``p2``: length of ``b`` matches ``Y``;
   ``theta``: signed deflection ``a -> b`` matches the design deflection ``theta_j``;
   ``c``: distance between the centroids of ``a`` and ``b`` matches the design
   distance between the panel midpoints ``c_j``.

   The first satisfied option of Table 1 is recorded::

       option  p1  p2  theta  c     identifies
       1       *   *   *      *     X and Y   (optimal)
       2       *   *   *            X and Y   (optimal)
       3           *   *      *     Y only    (sub-optimal)
       4       *       *      *     X only
       5       *       *            X only
       6           *   *            Y only

The paper gives no numeric thresholds; ours are :class:`SegmentationParams` fields.
A measured line is normally *shorter* than its panel (scan points never fall exactly
on the panel edges), hence the asymmetric length tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from minegeo._params import bounded, validate
from minegeo._validate import as_points
from minegeo.errors import InputError
from minegeo.mast._kernels import _grow_segments, _split_segments
from minegeo.mast.beacons import Beacon

__all__ = [
    "TABLE1_OPTIONS",
    "SegmentationParams",
    "LineSegment",
    "PanelMatch",
    "segment_scan",
    "identify_panels",
]

#: Table 1 of the paper: option -> criteria that must hold.
TABLE1_OPTIONS: dict[int, frozenset] = {
    1: frozenset({"p1", "p2", "theta", "c"}),
    2: frozenset({"p1", "p2", "theta"}),
    3: frozenset({"p2", "theta", "c"}),
    4: frozenset({"p1", "theta", "c"}),
    5: frozenset({"p1", "theta"}),
    6: frozenset({"p2", "theta"}),
}
#: Which of the two panels each option identifies.
OPTION_IDENTIFIES: dict[int, tuple[bool, bool]] = {
    1: (True, True), 2: (True, True), 3: (False, True), 4: (True, False), 5: (True, False), 6: (False, True)
}


@dataclass(frozen=True)
class SegmentationParams:
    """Thresholds of the sequential line fit and of Table 1 (lengths in m, angles in deg).

    Each numeric field declares its bounds in its metadata (:mod:`minegeo._params`): one rule for the
    dataclass and a ``--config`` value; ``options`` (a non-empty subset of 1..6) is checked by the class.

    Attributes
    ----------
    line_tolerance_sigmas : float
        A point joins the current line if it is within
        ``line_tolerance_sigmas * sigma_point + line_tolerance_floor_m`` of it.
    line_tolerance_floor_m : float
    gap_factor : float
        Consecutive points farther apart than ``gap_factor * r * d_beta`` (plus
        ``gap_floor_m``) break the line (a jump or missing returns).
    gap_floor_m : float
    min_points : int
        Lines with fewer points are discarded (>= 3; 3 lets a small far beacon at 0.5 deg still
        be recognised, the final adjustment does not depend on it).
    n_confirm : int
        Consecutive off-line points needed to confirm a break.
    refine_window : int
        Points searched backwards for the best node point of a break.
    split_gain : float
        After growing, a line is split in two at its best node if that lowers the
        orthogonal SSE by more than ``split_gain * sigma_point^2`` (the "split" of
        split-and-merge; catches corners absorbed while a line was short).
    length_short_fraction, length_long_fraction : float
        A line matches a panel of design length ``p`` if
        ``(1 - short) p - abs_tol <= length <= (1 + long) p + abs_tol``.
    length_abs_tolerance_m : float
    deflection_tolerance_deg : float
        ``|theta_measured - theta_design| <= tolerance`` (signed angles).
    centroid_tolerance_fraction : float
        ``|c_measured - c_design| <= fraction * c_design``.
    options : tuple of int
        Table 1 options allowed (default all, tried in order 1..6).
    """

    line_tolerance_sigmas: float = bounded(4.0, gt=0.0)
    line_tolerance_floor_m: float = bounded(0.002, ge=0.0)
    gap_factor: float = bounded(4.0, gt=0.0)
    gap_floor_m: float = bounded(0.02, ge=0.0)
    min_points: int = bounded(3, ge=3, integer=True)
    n_confirm: int = bounded(3, ge=1, integer=True)
    refine_window: int = bounded(24, ge=1, integer=True)
    split_gain: float = bounded(20.0, gt=0.0)
    length_short_fraction: float = bounded(0.25, ge=0.0)
    length_long_fraction: float = bounded(0.10, ge=0.0)
    length_abs_tolerance_m: float = bounded(0.01, ge=0.0)
    deflection_tolerance_deg: float = bounded(10.0, gt=0.0)
    centroid_tolerance_fraction: float = bounded(0.25, gt=0.0)
    options: tuple = (1, 2, 3, 4, 5, 6)

    def __post_init__(self) -> None:
        validate(self)
        bad = [o for o in self.options if o not in TABLE1_OPTIONS]
        if bad or not self.options:
            raise InputError(f"options must be a non-empty subset of 1..6, got {self.options}")


@dataclass(frozen=True)
class LineSegment:
    """A fitted line over scan points ``start..end`` (inclusive, scan order).

    ``direction`` is the unit direction oriented in scan order; ``p_start``/``p_end``
    are the first/last points projected on the line; ``length_m`` their distance.
    """

    start: int
    end: int
    centroid: np.ndarray = field(repr=False)
    direction: np.ndarray = field(repr=False)
    p_start: np.ndarray = field(repr=False)
    p_end: np.ndarray = field(repr=False)
    length_m: float = 0.0
    rms_m: float = 0.0

    @property
    def n_points(self) -> int:
        return self.end - self.start + 1


@dataclass(frozen=True)
class PanelMatch:
    """One Table 1 identification of a consecutive line pair ``(a, b)``.

    ``panel_a``/``panel_b`` are paper panel numbers (0 = P1, 1 = P2, 2 = P3) of the
    design pair; ``identified`` says which of the two lines are identified panels
    (the option's rule). ``node`` is the intersection of the two lines (scanner
    frame), an estimate of the shared vertex ``vertex_node`` (index 0-3).
    """

    beacon_index: int
    beacon_id: str
    seg_a: int
    seg_b: int
    panel_a: int
    panel_b: int
    option: int
    criteria: frozenset
    identified: tuple
    node: np.ndarray = field(repr=False)
    vertex_node: int = 0
    vertex_a_far: int = 0
    vertex_b_far: int = 0


def _fit_line(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    c = xy.mean(axis=0)
    d = xy - c
    cov = d.T @ d / len(xy)
    w, v = np.linalg.eigh(cov)
    u = v[:, 1]
    if u @ (xy[-1] - xy[0]) < 0:
        u = -u
    return c, u, float(math.sqrt(max(w[0], 0.0)))


def segment_scan(
    xy: np.ndarray,
    range_m: np.ndarray,
    bearing_deg: np.ndarray,
    sigma_range_m: float,
    sigma_bearing_deg: float = 0.0,
    params: SegmentationParams | None = None,
) -> list[LineSegment]:
    """Split scan-ordered points into straight lines by sequential PCA fitting.

    Parameters
    ----------
    xy : (n, 2) float64
        Scanner-frame points in clockwise scan order (increasing bearing).
    range_m, bearing_deg : (n,) float64
        Range and bearing of each point (used for per-point tolerances).
    sigma_range_m, sigma_bearing_deg : float
        Noise model; per-point ``sigma_point = sqrt(sr^2 + (r sb)^2)``.
    params : SegmentationParams

    Returns
    -------
    list of LineSegment
    """
    p = params or SegmentationParams()
    xy = as_points(xy, "xy", dim=2, min_points=0)
    n = xy.shape[0]
    range_m = np.asarray(range_m, dtype=np.float64).reshape(-1)
    bearing_deg = np.asarray(bearing_deg, dtype=np.float64).reshape(-1)
    if range_m.size != n or bearing_deg.size != n:
        raise InputError("xy, range_m and bearing_deg must have the same length")
    if n < p.min_points:
        return []
    sb = math.radians(sigma_bearing_deg)
    sig = np.sqrt(sigma_range_m**2 + (range_m * sb) ** 2)
    tol = np.ascontiguousarray(p.line_tolerance_sigmas * sig + p.line_tolerance_floor_m)
    db = np.abs(np.diff(np.radians(bearing_deg), prepend=np.radians(bearing_deg[0])))
    db[0] = db[1] if n > 1 else 0.0
    gap = np.ascontiguousarray(p.gap_factor * range_m * db + p.gap_floor_m)
    xy = np.ascontiguousarray(xy)
    se = _grow_segments(xy, tol, gap, int(p.min_points), int(p.n_confirm), int(p.refine_window))
    if len(se) and p.split_gain > 0:
        sig2 = np.array([np.mean(sig[s : e + 1] ** 2) + (p.line_tolerance_floor_m / 2) ** 2 for s, e in se])
        se = _split_segments(xy, np.ascontiguousarray(se), sig2, float(p.split_gain), int(p.min_points))
    out = []
    for s, e in se:
        pts = xy[s : e + 1]
        c, u, rms = _fit_line(pts)
        a = c + ((pts[0] - c) @ u) * u
        b = c + ((pts[-1] - c) @ u) * u
        out.append(LineSegment(int(s), int(e), c, u, a, b, float(np.linalg.norm(b - a)), rms))
    return out


def _intersect(c0, u0, c1, u1) -> np.ndarray | None:
    den = u0[0] * u1[1] - u0[1] * u1[0]
    if abs(den) < 1e-9:
        return None
    d = c1 - c0
    t = (d[0] * u1[1] - d[1] * u1[0]) / den
    return c0 + t * u0


def _templates(beacons: list[Beacon]) -> list[dict]:
    """Consecutive design panel pairs of every beacon, in clockwise-scan order."""
    out = []
    for bi, b in enumerate(beacons):
        W = b.scan_order_vertices()
        pidx = b.scan_order_panel_index()
        vidx = [0, 1, 2, 3] if b.front_side == -1 else [3, 2, 1, 0]
        d = np.diff(W, axis=0)
        q = np.linalg.norm(d, axis=1)
        mids = 0.5 * (W[:-1] + W[1:])
        for k in range(2):
            turn = math.degrees(math.atan2(d[k, 0] * d[k + 1, 1] - d[k, 1] * d[k + 1, 0], d[k] @ d[k + 1]))
            out.append({
                "beacon_index": bi, "beacon_id": b.beacon_id,
                "len_a": q[k], "len_b": q[k + 1], "theta_deg": turn,
                "c": float(np.linalg.norm(mids[k + 1] - mids[k])),
                "panel_a": pidx[k], "panel_b": pidx[k + 1],
                "v_a_far": vidx[k], "v_node": vidx[k + 1], "v_b_far": vidx[k + 2],
            })
    return out


def identify_panels(
    segments: list[LineSegment],
    beacons: list[Beacon],
    params: SegmentationParams | None = None,
) -> list[PanelMatch]:
    """Identify beacon panels among consecutive line pairs with the Table 1 criteria.

    Only pairs sharing a node point (``b.start <= a.end + 1``) are tested. Every
    (line pair, design pair) combination satisfying an allowed option yields a
    :class:`PanelMatch` (the best option per combination); several beacons may
    match the same lines — :mod:`minegeo.mast.pipeline` resolves that.
    """
    p = params or SegmentationParams()
    temps = _templates(beacons)
    out: list[PanelMatch] = []

    def len_ok(meas, design):
        lo = (1.0 - p.length_short_fraction) * design - p.length_abs_tolerance_m
        hi = (1.0 + p.length_long_fraction) * design + p.length_abs_tolerance_m
        return lo <= meas <= hi

    for ia in range(len(segments) - 1):
        a, b = segments[ia], segments[ia + 1]
        if b.start > a.end + 1:
            continue
        ua, ub = a.direction, b.direction
        theta = math.degrees(math.atan2(ua[0] * ub[1] - ua[1] * ub[0], ua @ ub))
        cdist = float(np.linalg.norm(b.centroid - a.centroid))
        node = _intersect(a.centroid, ua, b.centroid, ub)
        if node is None:
            continue
        for t in temps:
            crit = set()
            if len_ok(a.length_m, t["len_a"]):
                crit.add("p1")
            if len_ok(b.length_m, t["len_b"]):
                crit.add("p2")
            if abs(theta - t["theta_deg"]) <= p.deflection_tolerance_deg:
                crit.add("theta")
            if abs(cdist - t["c"]) <= p.centroid_tolerance_fraction * t["c"]:
                crit.add("c")
            opt = next((o for o in sorted(p.options) if TABLE1_OPTIONS[o] <= crit), None)
            if opt is None:
                continue
            out.append(PanelMatch(
                t["beacon_index"], t["beacon_id"], ia, ia + 1, t["panel_a"], t["panel_b"], opt,
                frozenset(crit), OPTION_IDENTIFIES[opt], node, t["v_node"], t["v_a_far"], t["v_b_far"],
            ))
    return out
