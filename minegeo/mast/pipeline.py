"""MAST: position and azimuth of a horizontal 2D scanner from two wall beacons.

Simela, Marshall & Daneshmend, section "MAST Algorithm": for each scan

1. segmentation by sequential PCA line fitting (:func:`~minegeo.mast.segmentation.segment_scan`);
2. template matching of consecutive lines to beacon panels with the Table 1 options
   (:func:`~minegeo.mast.segmentation.identify_panels`) and to beacon ids;
3. alignment: four-parameter Helmert ``N = u R_alpha P + t`` from the identified
   panel edges (:func:`minegeo.survey.helmert2d`), then point-to-line ICP with Low's
   linearisation to convergence (:func:`~minegeo.mast.icp.icp_point_to_line`);
4. scanner position and azimuth by weighted least squares of the range/bearing
   returns on the beacon panels, with ``Sigma = sigma0^2 (B^T W B)^-1``
   (:func:`~minegeo.mast.resection.resect_scanner_pose`).

Azimuth: ``alpha`` is the grid azimuth of the scanner's zero-bearing (forward) axis.
The paper's ``Az_ScanCentre = h_a + 180 deg + beta_Cum`` is the back-azimuth from a
return with scanner bearing ``h_a`` to the scanner centre; with bearings measured
clockwise from the forward axis, ``beta_Cum`` (total clockwise rotation of the scan
into the mine frame = Helmert rotation + ICP rotations) *is* ``alpha``; the final
least squares then refines it together with ``x, y``.

Template matching of beacon ids: several (cluster of lines -> beacon) assignments can
pass Table 1 (two beacons of the same design look alike). Every consistent
assignment is aligned and refined; the one that explains returns on the most beacons
(up to ``min_beacons``), then the most returns, wins, and
if a substantially different pose explains the scan about as well the result is
``failed`` with reason "ambiguous" (never a silent guess).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from scipy import stats

from minegeo._params import bounded, one_of, validate
from minegeo._provenance import StageTimer
from minegeo.errors import (
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MinegeoError,
    TooFewPointsError,
)
from minegeo.mast._kernels import _cast_rays
from minegeo.mast.beacons import Beacon
from minegeo.mast.icp import icp_point_to_line, rot2
from minegeo.mast.resection import ResectionObservations, resect_scanner_pose, wrap_deg
from minegeo.mast.scan import Scan2D, scan_to_xy
from minegeo.mast.segmentation import (
    LineSegment,
    PanelMatch,
    SegmentationParams,
    identify_panels,
    segment_scan,
)
from minegeo.survey import LSQOptions, error_ellipse, format_dms, helmert2d

__all__ = ["MastParams", "MastResult", "MastStatus", "locate_scanner"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MastParams:
    """Parameters of :func:`locate_scanner` (lengths in m, angles in deg).

    Each numeric and choice field declares its rule in its metadata (:mod:`minegeo._params`): the same
    rule checks the dataclass, the ``minegeo mast`` option that sets it (``--sigma-range-m``,
    ``--sigma-bearing-deg``, ``--sigma-panel-m``, ``--sigma-beacon-m``, ``--min-beacons``) and its key in
    a ``--config`` file; ``icp_gates_m`` (positive distances) is checked by the class.

    Attributes
    ----------
    sigma_range_m : float or None
        Range noise of the scanner (one return). None: take it from the scan file.
    sigma_bearing_deg : float or None
        Bearing noise. None: from the scan file, else 0.
    sigma_panel_m : float
        Extra per-return uncertainty of the panel lines, independent between returns
        (panel flatness).
    sigma_beacon_m : float
        Standard deviation of each surveyed beacon vertex coordinate (m). When > 0 the
        vertices become parameters with pseudo-observations in the final adjustment, so the
        survey error (shared by all returns on a panel) is propagated with its correlation.
    segmentation : SegmentationParams
    icp_gates_m : tuple of float
        Staged ICP correspondence gates.
    icp_max_iterations : int
    edge_margin_m : float
        Returns predicted within this distance of a panel edge are not used in the
        final adjustment (their panel is uncertain); ``3 r sigma_beta`` is added.
    residual_gate_sigmas : float
        Returns whose distance to their panel exceeds this many sigma are rejected.
    min_fit_fraction : float
        A beacon is dropped if fewer than this fraction of the returns predicted on its
        panels fit them (beacon moved, knocked off or occluded).
    min_beacons : int
        Beacons that must contribute returns (the paper uses two).
    min_returns_per_beacon : int
    helmert_scale_tolerance : float
        Initial alignments with ``|u - 1|`` above this are rejected (scanner ranges
        are true distances, so the Helmert scale must be close to one).
    max_hypotheses : int
        Beacon-id assignments aligned at most.
    ambiguity_ratio : float
        Another assignment explaining at least this fraction of the best one's
        returns with a different pose makes the result ambiguous.
    variance : {"aposteriori", "apriori"}
        Which sigma0 scales the covariance (issue: ``sigma0^2 (B^T W B)^-1``).
    confidence : float
        Level of the error ellipse and of the azimuth interval.
    """

    sigma_range_m: float | None = bounded(None, ge=0.0, optional=True)
    sigma_bearing_deg: float | None = bounded(None, ge=0.0, optional=True)
    sigma_panel_m: float = bounded(0.0, ge=0.0)
    sigma_beacon_m: float = bounded(0.0, ge=0.0)
    segmentation: SegmentationParams = field(default_factory=SegmentationParams)
    icp_gates_m: tuple = (0.20, 0.10, 0.05)
    icp_max_iterations: int = bounded(100, ge=1, integer=True)
    edge_margin_m: float = bounded(0.005, ge=0.0)
    residual_gate_sigmas: float = bounded(5.0, gt=0.0)
    min_fit_fraction: float = bounded(0.5, ge=0.0, le=1.0)
    min_beacons: int = bounded(2, ge=1, integer=True)
    min_returns_per_beacon: int = bounded(3, ge=1, integer=True)
    helmert_scale_tolerance: float = bounded(0.25, gt=0.0)
    max_hypotheses: int = bounded(16, ge=1, integer=True)
    ambiguity_ratio: float = bounded(0.8, ge=0.0, le=1.0)
    variance: str = one_of("aposteriori", ("aposteriori", "apriori"))
    confidence: float = bounded(0.95, gt=0.0, lt=1.0)

    def __post_init__(self) -> None:
        validate(self)
        if not self.icp_gates_m or any(g <= 0 for g in self.icp_gates_m):
            raise InputError("icp_gates_m must be positive distances")


class MastStatus(StrEnum):
    """Status of a MAST station location (:attr:`MastResult.status`); each member is its string value."""

    OK = "ok"
    #: no position (the ``reason`` says why)
    FAILED = "failed"


@dataclass(frozen=True)
class MastResult:
    """Result of :func:`locate_scanner` (mine frame; ``None`` fields when ``status == "failed"``).

    Attributes
    ----------
    status : MastStatus
        ``ok`` or ``failed``.
    reason : str
        Why it failed ("" when ok).
    x_m, y_m : float
        Scanner centre, mine frame (m), origin added back.
    azimuth_deg : float
        Grid azimuth of the scanner's forward (zero-bearing) axis, [0, 360).
    azimuth_dms : str
    covariance : (3, 3) ndarray
        Covariance of (x, y, azimuth) in units m, m, deg.
    ellipse95 : dict
        ``a_m``, ``b_m`` (semi-axes) and ``orientation_deg`` (azimuth of the major axis).
    azimuth_ci95_deg : float
        Half-width of the azimuth confidence interval (deg).
    sigma0 : float
        A-posteriori standard deviation of unit weight.
    segmentation_option : int or None
        Best Table 1 option among the panel identifications used.
    icp_iterations : int
    details : dict
        Everything else (beacons used, per-beacon options, Helmert, ICP, chi2 test,
        hypotheses, origin, noise model, timings).
    arrays : dict
        For reports: ``points_mine`` (all returns), ``used`` (mask), ``panel`` (index
        into ``panels_mine`` or -1), ``panels_mine``, ``residuals_m``.
    params : MastParams
    """

    status: MastStatus
    reason: str = ""
    x_m: float | None = None
    y_m: float | None = None
    azimuth_deg: float | None = None
    azimuth_dms: str | None = None
    covariance: np.ndarray | None = None
    ellipse95: dict | None = None
    azimuth_ci95_deg: float | None = None
    sigma0: float | None = None
    segmentation_option: int | None = None
    icp_iterations: int = 0
    details: dict = field(default_factory=dict)
    arrays: dict = field(default_factory=dict, repr=False)
    params: MastParams | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def summary(self) -> dict:
        """JSON-ready dict with the issue's result fields plus details (no large arrays)."""
        return {
            "status": self.status,
            "reason": self.reason,
            "x": self.x_m,
            "y": self.y_m,
            "azimuth_deg": self.azimuth_deg,
            "azimuth_dms": self.azimuth_dms,
            "covariance": self.covariance,
            "covariance_units": ["m", "m", "deg"],
            "ellipse95": self.ellipse95,
            "azimuth_ci95_deg": self.azimuth_ci95_deg,
            "sigma0": self.sigma0,
            "segmentation_option": self.segmentation_option,
            "icp_iterations": self.icp_iterations,
            "details": self.details,
        }


def _scan_order(bearing_deg: np.ndarray) -> np.ndarray:
    """Indices sorting returns clockwise, starting after the largest angular gap (360 deg scans)."""
    b = np.mod(bearing_deg, 360.0)
    o = np.argsort(b, kind="stable")
    bs = b[o]
    if bs.size < 2:
        return o
    gaps = np.diff(np.concatenate([bs, [bs[0] + 360.0]]))
    k = int(np.argmax(gaps))
    return np.roll(o, -(k + 1))


def _cluster_matches(matches: list[PanelMatch], max_size_m: float) -> list[int]:
    """Cluster id per match: matches whose nodes lie within ``max_size_m`` (one beacon) share it."""
    cid = [-1] * len(matches)
    centres: list[np.ndarray] = []
    for i, m in enumerate(matches):
        for c, cen in enumerate(centres):
            if np.linalg.norm(m.node - cen) <= max_size_m:
                cid[i] = c
                break
        else:
            centres.append(m.node.copy())
            cid[i] = len(centres) - 1
    return cid


def _hypotheses(matches, clusters, limit):
    """Consistent (cluster -> beacon) assignments, best first."""
    cl_ids = sorted(set(clusters))
    cands = []
    for c in cl_ids:
        best: dict[int, int] = {}
        for m, cc in zip(matches, clusters, strict=True):
            if cc == c:
                best[m.beacon_index] = min(best.get(m.beacon_index, 99), m.option)
        cands.append(sorted(best.items(), key=lambda kv: kv[1]) + [(None, 99)])
    out = []
    for combo in itertools.product(*cands):
        used = [b for b, _ in combo if b is not None]
        if not used or len(set(used)) != len(used):
            continue
        score = (-len(used), sum(o for b, o in combo if b is not None))
        out.append((score, {c: b for c, (b, _) in zip(cl_ids, combo, strict=True) if b is not None}))
        if len(out) > 50 * limit:
            break
    out.sort(key=lambda t: t[0])
    return [h for _, h in out[:limit]]


def _correspondences(hyp, matches, clusters, segs: list[LineSegment], beacons_local):
    src, dst, opts = [], [], []
    for m, c in zip(matches, clusters, strict=True):
        if hyp.get(c) != m.beacon_index:
            continue
        V = beacons_local[m.beacon_index].vertices_m
        src.append(m.node)
        dst.append(V[m.vertex_node])
        if "p1" in m.criteria:
            src.append(segs[m.seg_a].p_start)
            dst.append(V[m.vertex_a_far])
        if "p2" in m.criteria:
            src.append(segs[m.seg_b].p_end)
            dst.append(V[m.vertex_b_far])
        opts.append(m)
    return np.array(src), np.array(dst), opts


def _pose_from_T(T: np.ndarray) -> np.ndarray:
    """(x, y, alpha) from ``T_mine_scan``; alpha = clockwise azimuth of the scanner's +y axis."""
    return np.array([T[0, 2], T[1, 2], -math.atan2(T[1, 0], T[0, 0])])


def _associate_by_rays(pose, bearing_rad, range_m, panels, sig_r, sig_b, sig_p, margin, gate_sigmas):
    """Assign returns to the panel their ray is predicted to hit from ``pose`` (with occlusion)."""
    x, y, a = pose
    phi = a + bearing_rad
    dirs = np.ascontiguousarray(np.column_stack([np.sin(phi), np.cos(phi)]))
    _, idx, spar = _cast_rays(np.array([x, y]), dirs, panels, 1e9)
    e = panels[:, 2:] - panels[:, :2]
    L = np.linalg.norm(e, axis=1)
    u = e / L[:, None]
    nrm = np.column_stack([-u[:, 1], u[:, 0]])
    ok = idx >= 0
    j = np.maximum(idx, 0)
    along = spar * L[j]
    marg = margin + 3.0 * range_m * sig_b
    ok &= (along >= marg) & (along <= L[j] - marg)
    p = np.column_stack([x + range_m * np.sin(phi), y + range_m * np.cos(phi)])
    n = nrm[j]
    d = np.einsum("ij,ij->i", n, p - panels[j, :2])
    nu = np.abs(np.einsum("ij,ij->i", n, dirs))
    dadz = range_m * (n[:, 0] * np.cos(phi) - n[:, 1] * np.sin(phi))
    sd = np.sqrt((nu * sig_r) ** 2 + (dadz * sig_b) ** 2 + sig_p**2)
    pred = ok.copy()
    ok &= np.abs(d) <= gate_sigmas * sd
    return ok, np.where(ok, idx, -1), d, nrm, np.where(pred, idx, -1)


def _associate(pose, bearing_rad, range_m, panels, beacon_of_panel, sig_r, sig_b, p: MastParams):
    """Ray-based association plus the per-beacon check that the beacon is really there.

    A beacon whose predicted returns mostly do not fit its panels (fewer than
    ``min_fit_fraction``) is dropped: it was moved, knocked off, or is occluded.
    """
    ok, idx, d, nrm, pred = _associate_by_rays(
        pose, bearing_rad, range_m, panels, sig_r, sig_b, p.sigma_panel_m, p.edge_margin_m,
        p.residual_gate_sigmas,
    )
    nb = int(beacon_of_panel.max()) + 1
    bp = np.where(pred >= 0, beacon_of_panel[np.maximum(pred, 0)], -1)
    bf = np.where(ok, beacon_of_panel[np.maximum(idx, 0)], -1)
    n_pred = np.bincount(bp[bp >= 0], minlength=nb)
    n_fit = np.bincount(bf[bf >= 0], minlength=nb)
    dropped = []
    for b in range(nb):
        if n_pred[b] > 0 and n_fit[b] < p.min_fit_fraction * n_pred[b]:
            ok &= bf != b
            dropped.append((b, int(n_fit[b]), int(n_pred[b])))
    idx = np.where(ok, idx, -1)
    return ok, idx, d, nrm, dropped


def _final_adjustment(pose0, bearing_rad, range_m, panels, beacon_of_panel, sig_r, sig_b, p: MastParams,
                      vertices=None):
    pose = np.array(pose0, dtype=np.float64)
    prev = None
    res = None
    dropped: list = []
    for _ in range(4):
        ok, idx, _, nrm, dropped = _associate(pose, bearing_rad, range_m, panels, beacon_of_panel,
                                              sig_r, sig_b, p)
        if prev is not None and np.array_equal(ok, prev):
            break
        prev = ok
        sel = np.flatnonzero(ok)
        obs = ResectionObservations(
            bearing_rad[sel], range_m[sel], np.ascontiguousarray(panels[idx[sel], :2]),
            np.ascontiguousarray(nrm[idx[sel]]),
        )
        j = idx[sel]
        vab = np.column_stack([4 * (j // 3) + j % 3, 4 * (j // 3) + j % 3 + 1])
        res = resect_scanner_pose(obs, pose, sig_r, sig_b, p.sigma_panel_m, LSQOptions(variance=p.variance),
                                  vertices_m=vertices, vertex_ab=vab, sigma_vertex_m=p.sigma_beacon_m)
        pose = res.x[:3].copy()
    return pose, res, ok, idx, dropped


def _fail(reason: str, params: MastParams, details: dict, arrays=None, option=None, iters=0) -> MastResult:
    log.info("MAST failed: %s", reason)
    return MastResult(
        MastStatus.FAILED, reason, params=params, details=details, arrays=arrays or {}, segmentation_option=option,
        icp_iterations=iters,
    )


def _noise_model(scan: Scan2D, beacons: list[Beacon], p: MastParams) -> tuple[float, float, float]:
    """Range sigma (m), bearing sigma (deg and rad) from the parameters or the scan file; checks the inputs."""
    sig_r = p.sigma_range_m if p.sigma_range_m is not None else scan.sigma_range_m
    if sig_r is None:
        raise InputError(
            "no range noise model: give sigma_range_m (e.g. --sigma-range-m 0.003) or a "
            "'# sigma_range_m: ...' line in the scan file"
        )
    sig_bd = p.sigma_bearing_deg if p.sigma_bearing_deg is not None else (scan.sigma_bearing_deg or 0.0)
    sig_b = math.radians(sig_bd)
    if not (sig_r > 0 or sig_b > 0 or p.sigma_panel_m > 0):
        raise InputError("the noise model is zero: sigma_range_m must be > 0")
    if len(beacons) < p.min_beacons:
        raise TooFewPointsError(
            f"{len(beacons)} beacon(s) given; MAST needs at least {p.min_beacons} surveyed beacons"
        )
    ids = [b.beacon_id for b in beacons]
    if len(set(ids)) != len(ids):
        raise InputError(f"duplicate beacon ids in the beacon list: {ids}")
    if len(scan) < 3:
        raise TooFewPointsError(f"the scan has {len(scan)} return(s); at least 3 are needed for x, y, azimuth")
    return sig_r, sig_bd, sig_b


def _match_records(matches: list[PanelMatch], segs: list[LineSegment]) -> list[dict]:
    """The panel matches as JSON-ready records (``details["panel_matches"]``)."""
    return [
        {"beacon_id": m.beacon_id, "option": m.option, "panels": [f"P{m.panel_a + 1}", f"P{m.panel_b + 1}"],
         "identified": list(m.identified), "criteria": sorted(m.criteria),
         "points": [[segs[m.seg_a].start, segs[m.seg_a].end], [segs[m.seg_b].start, segs[m.seg_b].end]]}
        for m in matches
    ]


def _align_hypothesis(h: dict, matches, clusters, segs, bl, obs: dict, p: MastParams) -> dict:
    """Aligns one beacon-id assignment: Helmert from the panel edges, then point-to-line ICP.

    ``obs`` holds the scan (``xy``, ``bearing_rad``, ``range_m``), the panels with their
    beacon indices and the noise (``sig_r``, ``sig_b``). Returns the record of the
    hypothesis: its ``pose``, ``icp``, returns and beacons explained, or why it was ``rejected``.
    """
    src, dst, used = _correspondences(h, matches, clusters, segs, bl)
    rec = {"assignment": {str(c): bl[b].beacon_id for c, b in h.items()}}
    if len(src) < 2 or np.ptp(dst, axis=0).max() < 1e-6:
        rec["rejected"] = "fewer than two distinct panel edges"
        return rec
    try:
        hr = helmert2d(src, dst)
    except MinegeoError as exc:
        rec["rejected"] = f"Helmert: {exc}"
        return rec
    rec["helmert_scale"] = hr.scale
    rec["helmert_rotation_deg"] = math.degrees(hr.rotation_rad)
    if abs(hr.scale - 1.0) > p.helmert_scale_tolerance:
        rec["rejected"] = f"Helmert scale {hr.scale:.3f} (scanner ranges must give scale ~1)"
        return rec
    # drop the scale u but keep the centroid of the edges where Helmert put it
    R0 = rot2(hr.rotation_rad)
    c_src = src.mean(axis=0)
    T0 = np.eye(3)
    T0[:2, :2] = R0
    T0[:2, 2] = hr.scale * (R0 @ c_src) + hr.params[2:] - R0 @ c_src
    # ICP first on the beacons of this hypothesis only (a beacon that is listed but
    # missing must not pull the pose), then on all beacons with the tight gates.
    xy, panels, beacon_of_panel = obs["xy"], obs["panels"], obs["beacon_of_panel"]
    hyp_panels = np.isin(beacon_of_panel, list(h.values()))
    try:
        icp1 = icp_point_to_line(xy, panels[hyp_panels], T0, p.icp_gates_m, p.icp_max_iterations)
        icp = icp_point_to_line(xy, panels, icp1.T_mine_scan, p.icp_gates_m[-1:],
                                p.icp_max_iterations)
    except (TooFewPointsError, DegenerateGeometryError) as exc:
        rec["rejected"] = f"ICP: {exc}"
        return rec
    icp = replace(icp, iterations=icp1.iterations + icp.iterations,
                  beta_cum_rad=icp1.beta_cum_rad + icp.beta_cum_rad)
    pose = _pose_from_T(icp.T_mine_scan)
    ok, idx, _, _, _ = _associate(pose, obs["bearing_rad"], obs["range_m"], panels, beacon_of_panel, obs["sig_r"],
                                  obs["sig_b"], p)
    per_b = np.bincount(beacon_of_panel[idx[ok]], minlength=len(bl))
    rec.update(pose=pose, icp=icp, n_explained=int(ok.sum()), used=used,
               n_beacons=int(min((per_b >= p.min_returns_per_beacon).sum(), p.min_beacons)))
    return rec


def _ambiguity(good: list[dict], p: MastParams) -> str | None:
    """Why the best aligned hypothesis (``good[0]``) is ambiguous, or None when it is unique."""
    best = good[0]
    for other in good[1:]:
        if other["n_beacons"] < best["n_beacons"]:
            break
        dpos = float(np.hypot(*(other["pose"][:2] - best["pose"][:2])))
        dang = abs(math.remainder(other["pose"][2] - best["pose"][2], 2 * math.pi))
        if other["n_explained"] >= p.ambiguity_ratio * best["n_explained"] and (dpos > 0.05 or dang > 0.01):
            return (
                f"ambiguous beacon identification: assignments {best['assignment']} and "
                f"{other['assignment']} explain {best['n_explained']} and {other['n_explained']} returns "
                f"with poses {dpos:.2f} m / {math.degrees(dang):.1f} deg apart (beacons of identical "
                "design mounted point-symmetrically?); mount them so their panel order differs"
            )
    return None


def _ok_result(pose, res, ok, best: dict, obs: dict, origin, p: MastParams, seg_option: int, details: dict,
               arrays: dict, timer: StageTimer) -> MastResult:
    """The ``ok`` result of the final adjustment: covariance (m, m, deg), ellipse, azimuth interval."""
    bearing_rad, rng_m = obs["bearing_rad"], obs["range_m"]
    icp = best["icp"]
    x, y, a = pose
    S = res.Sigma_xx[:3, :3].copy()
    J = np.diag([1.0, 1.0, math.degrees(1.0)])
    cov = J @ S @ J.T
    known = res.variance_used == "apriori"
    ell = error_ellipse(S[:2, :2], p.confidence, res.dof, sigma0_known=known)
    tq = stats.norm.ppf(0.5 + p.confidence / 2) if known else stats.t.ppf(0.5 + p.confidence / 2, res.dof)
    az = wrap_deg(math.degrees(a))
    arrays["points_mine"] = np.column_stack(
        [x + rng_m * np.sin(a + bearing_rad), y + rng_m * np.cos(a + bearing_rad)]
    ) + origin
    n_obs = int(ok.sum())
    arrays["residuals_m"] = res.v[:n_obs]
    details.update(
        n_observations=n_obs, dof=res.dof, sigma0_apriori=res.sigma0_apriori,
        variance_used=res.variance_used, adjustment_iterations=res.iterations,
        chi2_global_test={"statistic": res.chi2.statistic, "lower": res.chi2.lower, "upper": res.chi2.upper,
                          "passed": res.chi2.passed},
        std_x_m=math.sqrt(cov[0, 0]), std_y_m=math.sqrt(cov[1, 1]), std_azimuth_arcsec=3600 * math.sqrt(cov[2, 2]),
        ellipse95_basis=ell.basis, beta_cum_deg=wrap_deg(math.degrees(best["pose"][2])),
        timings_s=timer.as_dict(),
    )
    return MastResult(
        MastStatus.OK, "", float(x + origin[0]), float(y + origin[1]), az, format_dms(math.radians(az), 1, width_deg=3),
        cov, {"a_m": ell.semi_major_m, "b_m": ell.semi_minor_m, "orientation_deg": math.degrees(ell.azimuth_rad)},
        float(tq * math.sqrt(cov[2, 2])), float(res.sigma0), seg_option, icp.iterations, details, arrays, p,
    )


def _adjust_best(best: dict, matches, bl, obs: dict, origin, p: MastParams, best_option: int, details: dict,
                 arrays: dict, timer: StageTimer) -> MastResult:
    """Final least-squares adjustment from the chosen hypothesis; the result (``ok`` or ``failed``)."""
    icp = best["icp"]
    panels, beacon_of_panel = obs["panels"], obs["beacon_of_panel"]
    used_opts = [m.option for m in best["used"]]
    seg_option = min(used_opts) if used_opts else best_option
    details["per_beacon_option"] = {
        bl[b].beacon_id: min(m.option for m in best["used"] if m.beacon_index == b)
        for b in sorted({m.beacon_index for m in best["used"]})
    }
    details["icp"] = {"iterations": icp.iterations, "rms_m": icp.rms_m, "n_inliers": icp.n_inliers,
                      "converged": icp.converged, "beta_cum_deg": -math.degrees(icp.beta_cum_rad)}
    with timer("adjustment"):
        try:
            pose, res, ok, idx, dropped = _final_adjustment(best["pose"], obs["bearing_rad"], obs["range_m"], panels,
                                                            beacon_of_panel, obs["sig_r"], obs["sig_b"], p,
                                                            np.vstack([b.vertices_m for b in bl]))
        except (TooFewPointsError, DegenerateGeometryError, ConvergenceError) as exc:
            return _fail(f"final adjustment impossible: {exc}", p, details, arrays, seg_option, icp.iterations)
    counts = np.bincount(beacon_of_panel[idx[ok]], minlength=len(bl))
    used_b = [bl[i].beacon_id for i in range(len(bl)) if counts[i] >= p.min_returns_per_beacon]
    details["returns_per_beacon"] = {bl[i].beacon_id: int(counts[i]) for i in range(len(bl))}
    details["beacons_dropped"] = [
        f"{bl[b].beacon_id}: only {nf} of {npred} returns predicted on its panels fit them "
        "(moved, missing or occluded beacon?)" for b, nf, npred in dropped
    ]
    details["beacons_used"] = used_b
    arrays.update(
        used=ok, panel=idx, panels_mine=panels + np.tile(origin, 2), bearing_deg=obs["bearing_deg"],
        range_m=obs["range_m"],
    )
    if len(used_b) < p.min_beacons:
        missing = [b.beacon_id for b in bl if b.beacon_id not in used_b]
        return _fail(
            f"only {len(used_b)} beacon(s) ({', '.join(used_b) or 'none'}) have at least "
            f"{p.min_returns_per_beacon} returns; {', '.join(missing)} out of view or not reached "
            f"(min_beacons={p.min_beacons})"
            + ("; " + "; ".join(details["beacons_dropped"]) if details["beacons_dropped"] else ""),
            p, details, arrays, seg_option, icp.iterations,
        )
    if not res.converged:
        return _fail("final adjustment did not converge", p, details, arrays, seg_option, icp.iterations)
    return _ok_result(pose, res, ok, best, obs, origin, p, seg_option, details, arrays, timer)


def locate_scanner(scan: Scan2D, beacons: list[Beacon], params: MastParams | None = None) -> MastResult:
    """Scanner 2D position and azimuth in the mine frame from one horizontal scan (MAST).

    Parameters
    ----------
    scan : Scan2D
        Returns ``(bearing_deg, range_m)``; bearings clockwise from the scanner's forward axis.
    beacons : list of Beacon
        Surveyed beacons (mine frame). At least ``params.min_beacons``.
    params : MastParams, optional

    Returns
    -------
    MastResult
        ``status == "ok"`` with pose, covariance (m, m, deg), 95 % ellipse and azimuth
        interval; or ``status == "failed"`` with a ``reason`` (no beacon in the scan,
        beacons out of view, ambiguous identification, degenerate geometry, too few
        returns on the panels).

    Raises
    ------
    InputError
        No noise model (``sigma_range_m`` neither given nor in the scan file), or
        duplicate beacon ids.
    TooFewPointsError
        Fewer beacons than ``min_beacons`` or a scan with fewer than 3 returns.
    """
    p = params or MastParams()
    timer = StageTimer()
    sig_r, sig_bd, sig_b = _noise_model(scan, beacons, p)
    # beacons in a local frame about a whole-metre origin
    origin = np.round(np.mean(np.vstack([b.vertices_m for b in beacons]), axis=0), 0)
    bl = [Beacon(b.beacon_id, b.vertices_m - origin) for b in beacons]
    panels = np.ascontiguousarray(np.vstack([b.panels() for b in bl]))
    beacon_of_panel = np.repeat(np.arange(len(bl)), 3)
    noise = {"sigma_range_m": sig_r, "sigma_bearing_deg": sig_bd, "sigma_panel_m": p.sigma_panel_m,
             "sigma_beacon_m": p.sigma_beacon_m}
    details: dict = {"origin_m": origin, "noise_model": noise, "n_returns": len(scan)}

    with timer("segmentation"):
        order = _scan_order(scan.bearing_deg)
        bearing = scan.bearing_deg[order]
        rng_m = scan.range_m[order]
        xy = scan_to_xy(bearing, rng_m)
        segs = segment_scan(xy, rng_m, bearing, sig_r, sig_bd, p.segmentation)
        matches = identify_panels(segs, bl, p.segmentation)
    details["n_lines"] = len(segs)
    details["panel_matches"] = _match_records(matches, segs)
    arrays = {"points_scan": xy, "order": order, "segments": [(s.start, s.end) for s in segs]}
    if not matches:
        return _fail(
            f"no beacon panel was recognised among the {len(segs)} straight lines of the scan "
            "(beacons out of view, too far for the angular resolution, or the scan is not of this site)",
            p, details, arrays,
        )
    size = max(float(b.panel_lengths_m.sum()) for b in bl)
    clusters = _cluster_matches(matches, size)
    hyps = _hypotheses(matches, clusters, p.max_hypotheses)
    obs = {"xy": xy, "bearing_deg": bearing, "bearing_rad": np.radians(bearing), "range_m": rng_m,
           "panels": panels, "beacon_of_panel": beacon_of_panel, "sig_r": sig_r, "sig_b": sig_b}
    with timer("alignment"):
        evaluated = [_align_hypothesis(h, matches, clusters, segs, bl, obs, p) for h in hyps]
    good = [r for r in evaluated if "pose" in r]
    details["hypotheses"] = [
        {k: v for k, v in r.items() if k in ("assignment", "rejected", "helmert_scale", "n_explained", "n_beacons")}
        for r in evaluated
    ]
    best_option = min(m.option for m in matches)
    if not good:
        reasons = "; ".join(sorted({r.get("rejected", "") for r in evaluated}))
        return _fail(f"beacon panels were recognised but no consistent alignment was found ({reasons})",
                     p, details, arrays, best_option)
    # prefer poses that explain returns on enough beacons, then the most returns
    good.sort(key=lambda r: (-r["n_beacons"], -r["n_explained"], -len(r["assignment"]), r["icp"].rms_m))
    best = good[0]
    reason = _ambiguity(good, p)
    if reason is not None:
        return _fail(reason, p, details, arrays, best_option, best["icp"].iterations)
    return _adjust_best(best, matches, bl, obs, origin, p, best_option, details, arrays, timer)
