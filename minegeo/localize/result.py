"""The outcome of :func:`~minegeo.localize.localize_scan`: :class:`LocalizationResult` and its JSON record.

Only an ``ok`` result carries an answer: for a ``failed`` or ``ambiguous`` one the pose fields
(:data:`ANSWER_FIELDS`) are written as ``null`` and the placements that were tried go under
``rejected_candidates`` (map frame only, labelled :data:`NOT_A_POSITION`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np

from minegeo._provenance import to_jsonable
from minegeo.geometry.se3 import rotation_angle
from minegeo.io.types import Trajectory
from minegeo.localize.params import LocalizeParams
from minegeo.localize.uncertainty import CHI2_2D_95, CHI2_3D_95

if TYPE_CHECKING:
    from minegeo.localize.params import PrepareParams
    from minegeo.registration.icp import ICPResult
    from minegeo.registration.ransac_params import RansacResult

__all__ = ["LocalizationResult", "LocalizeStatus", "STATUSES", "ANSWER_FIELDS", "NOT_A_POSITION", "rejected_candidates",
           "error_vs_truth", "CHI2_3D_95", "CHI2_2D_95"]

class LocalizeStatus(StrEnum):
    """Status of a localization (:attr:`LocalizationResult.status`); each member is its string value."""

    #: one placement, verified, with its covariance: the answer
    OK = "ok"
    #: placements the checks cannot tell apart, or a fit not constrained in every direction: no answer
    AMBIGUOUS = "ambiguous"
    #: no placement passed the checks: no answer
    FAILED = "failed"


#: Possible values of ``LocalizationResult.status``.
STATUSES = tuple(LocalizeStatus)


@dataclass(frozen=True)
class LocalizationResult:
    """Outcome of :func:`localize_scan`.

    Attributes
    ----------
    status : LocalizeStatus
        ``ok``, ``ambiguous`` or ``failed`` (module docstring).
    reason : str
        Why, in words a surveyor understands.
    T_map_scan : (4, 4) ndarray
        Scan frame -> map frame (``p_map = R p_scan + t``), final (ICP) estimate. **An answer
        only when** ``status == "ok"``: otherwise it is the best *rejected* candidate (identity,
        i.e. the map's work origin, if RANSAC found nothing), which :meth:`to_dict` writes under
        ``rejected_candidates`` and never as ``T_map_scan`` (the same holds for ``T_geo_scan``,
        ``T_crs_scan``, the covariance and the radii: :data:`ANSWER_FIELDS`).
    T_geo_scan, T_crs_scan : (4, 4) ndarray or None
        The scan pose in the ``geo`` frame and in full CRS coordinates (None without CRS).
    fitness, inlier_rmse_m : float
        Final ICP fitness and inlier RMSE ([Baek2022 Eq. 19]), m.
    ransac : RansacResult
        The (first) RANSAC run.
    icp : ICPResult or None
        ICP of the chosen hypothesis.
    hypotheses : list of dict
        Every verified hypothesis: its origin, RANSAC and ICP scores, distance to the chosen one.
    covariance_6x6 : (6, 6) ndarray or None
        Pose covariance of the final point-to-plane fit, the data term plus named model terms
        (:mod:`minegeo.localize.uncertainty`; both listed in ``uncertainty``), with parameters
        ``(ω_x, ω_y, ω_z, t_x, t_y, t_z)``: a small rotation
        (rad) about the scan origin and a translation (m) of the scan origin, both in map
        axes (left perturbation ``T ← exp(δ) T`` taken about the scan origin). None when
        the geometry does not constrain all six directions.
    sigma_m : float
        σ: RMS of the point-to-plane residuals of the final pairs (m), with ``n - 6`` dof.
    position_cov_3x3 : (3, 3) ndarray or None
        Covariance of the scan origin (map axes), m².
    position_sigma_m : (3,) ndarray
        Its standard deviations along x, y, z (map axes), m (inf when unconstrained).
    position_95_radius_m : float
        3-D radius of the ball that holds the scan origin with probability 0.95 under
        ``N(0, position_cov)`` (:func:`~minegeo.localize.uncertainty.radii_95`: between
        ``sqrt(3.841 λ_max)`` for one dominant axis and ``sqrt(7.815 λ_max)`` isotropic).
    horizontal_95_radius_m : float
        Same in plan (the xy block; ``sqrt(5.991 σ²)`` isotropic).
    pending_step_m : float
        Largest scan-point displacement of one more point-to-plane step from the final pose, m.
    trajectory_map, trajectory_geo : Trajectory or None
        Sensor trajectory in the map and geo frames ([Baek2022 Eq. 18]), when a trajectory was given.
    trajectory_sigma_m : (m,) ndarray or None
        1-σ 3-D position uncertainty of each trajectory pose from ``covariance_6x6``, m.
    crs : str or None
    georef_origin : (3,) ndarray or None
        Origin of the ``geo`` frame (CRS coordinates), m.
    displacement_95_m : float
        Largest 95 % displacement of the scan's bounding-box corners under ``covariance_6x6``, m
        (``sqrt(7.815 λ_max(J Σ Jᵀ))``, ``J = [−[q − o]×, I]``); inf without covariance.
    uncertainty : dict or None
        The estimator's record (:meth:`~minegeo.localize.uncertainty.PoseUncertainty.to_dict`
        without its top-level matrices): method, blocks, inflation over the formal covariance, σ,
        ``data_term`` (the covariance the residuals determine, the information ratio and the
        weakest direction) and ``model_terms`` (each added term by name, e.g.
        ``registration_floor``, ``pending_step``, ``weak_axis_polish``; data + terms = ``covariance_6x6``).
    plane_tolerance_m : float
        Plane-distance tolerance used by the verification (m; see ``verify.noise_factor``).
    scan_noise_m : float
        The scan's surface noise ``σ_surf`` (m; NaN when not measured).
    n_scan_points, n_scan_down, n_scan_icp : int
        Scan points read, after downsampling (features, RANSAC) and in the ICP source.
    correlative : dict or None
        Record of the correlative search when it ran (``CorrelativeResult.to_dict``, plus
        ``precheck_plane_fitness`` of every candidate and the ``precheck_ratio`` that kept
        some of them), else None.
    polish : dict or None
        Record of the tight-gate polish (``LocalizeParams.icp.polish_correspondence_m``):
        gate, whether it was applied, largest shift of a scan point (m), its ICP statistics.
        When applied, ``T_map_scan`` and the covariance come from it; ``fitness``,
        ``inlier_rmse_m`` and ``icp`` stay those of the decision's ICP.
    gravity : dict or None
        Record of ``LocalizeParams.gravity_fallback`` when it ran: the up estimate (status,
        ``up_scan``, 95 % cone), the levelled attempt's status and reason, ``R_levelled_scan``.
    rival_search : dict or None
        Record of the whole-map rival search (``LocalizeParams.rival``) when it ran
        (the result would otherwise have been ``ok``): ``best_rival`` (the strongest distinct
        verified placement other than the chosen one, from this search or the pipeline's own
        hypotheses: ``T_map_scan`` and ``origin_map_m`` in the map frame, **not a position** —
        a rejected rival —, ``plane_fitness``, ``distance_to_chosen_m``,
        ``rotation_to_chosen_deg``, ``common_fraction``, ``matched_ratio``, ``test_passed``,
        ``source``), ``margin`` (chosen / best rival plane fitness; inf without a rival),
        ``matched_ratio``, ``ambiguity.ratio``, ``self_rank`` / ``self_found``, ``covered``,
        ``guarantee`` and the search's ``candidates``
        (:meth:`~minegeo.localize.rivals.RivalSearch.to_dict`). No times (they are in
        ``timings_s``: ``rival_search`` and its parts ``rival_search_*``), so equal inputs give
        an equal record. None when it did not run.
    params : LocalizeParams
    map_params : PrepareParams
    seed : int
    timings_s : dict
        Seconds per stage (``downsample``, ``normals``, ``fpfh``, ``ransac``, ``icp``,
        ``covariance``, ``trajectory``, ``total``).
    warnings : list of str
    """

    status: LocalizeStatus
    reason: str
    T_map_scan: np.ndarray
    T_geo_scan: np.ndarray | None
    T_crs_scan: np.ndarray | None
    fitness: float
    inlier_rmse_m: float
    ransac: RansacResult
    icp: ICPResult | None
    hypotheses: list
    covariance_6x6: np.ndarray | None
    sigma_m: float
    position_cov_3x3: np.ndarray | None
    position_sigma_m: np.ndarray
    position_95_radius_m: float
    horizontal_95_radius_m: float
    pending_step_m: float
    trajectory_map: Trajectory | None
    trajectory_geo: Trajectory | None
    trajectory_sigma_m: np.ndarray | None
    crs: str | None
    georef_origin: np.ndarray | None
    displacement_95_m: float
    uncertainty: dict | None
    plane_tolerance_m: float
    scan_noise_m: float
    n_scan_points: int
    n_scan_down: int
    n_scan_icp: int
    params: LocalizeParams
    map_params: PrepareParams
    seed: int
    timings_s: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    ransac_T_map_scan: np.ndarray | None = None
    scan_points_down: np.ndarray | None = field(default=None, repr=False)
    residuals_m: np.ndarray | None = field(default=None, repr=False)
    correlative: dict | None = None
    polish: dict | None = None
    rival_search: dict | None = None
    gravity: dict | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self) -> dict:
        """The JSON record (``result.json`` fields of the CLI contract, without ``inputs``).

        For a ``failed`` or ``ambiguous`` result the pose fields (:data:`ANSWER_FIELDS`) are
        ``None`` and ``hypotheses`` moves under ``rejected_candidates`` (see
        :func:`_without_answer`): nothing in the record reads as a position."""
        r = self.ransac
        ic = self.icp
        d = {
            "status": self.status,
            "reason": self.reason,
            "T_map_scan": self.T_map_scan,
            "T_geo_scan": self.T_geo_scan,
            "T_crs_scan": self.T_crs_scan,
            "frames": {
                "T_map_scan": "scan -> map frame of the prior map before georeferencing (p_map = R p_scan + t)",
                "T_geo_scan": "scan -> CRS minus georef_origin (pose_to_crs: rigid, position through the similarity)",
                "T_crs_scan": "scan -> full CRS coordinates (T_geo_scan with georef_origin added)",
            },
            "fitness": self.fitness,
            "inlier_rmse_m": self.inlier_rmse_m,
            "ransac": None if r is None else {
                "fitness": r.fitness, "inlier_rmse_m": r.inlier_rmse_m, "n_inliers": r.n_inliers,
                "iterations": r.iterations, "n_validations": r.n_validations, "status": r.status,
                "second_best_score": r.ambiguity_ratio, "second_best_fitness": r.second_best_fitness,
                "second_best_distance_m": r.second_best_distance_m,
                "second_best_rotation_deg": r.second_best_rotation_deg,
                "n_correspondences": int(r.correspondences.shape[0]), "T_map_scan": self.ransac_T_map_scan,
            },
            "icp": None if ic is None else {
                "method": self.params.icp.method, "fitness": ic.fitness, "inlier_rmse_m": ic.inlier_rmse_m,
                "iterations": ic.iterations, "converged": ic.converged, "status": ic.status,
                "degenerate": ic.degenerate, "degeneracy_ratio": ic.degeneracy_ratio,
                "degeneracy_reason": ic.degeneracy_reason,
                "n_correspondences": int(ic.correspondences.shape[0]),
            },
            "hypotheses": self.hypotheses,
            "covariance_6x6": self.covariance_6x6,
            "covariance_parameters": "(omega_x, omega_y, omega_z) rad about the scan origin, (t_x, t_y, t_z) m of the "
                                     "scan origin, map axes; data term + model terms of 'uncertainty', point-to-plane J",
            "sigma_m": self.sigma_m,
            "position_cov_3x3": self.position_cov_3x3,
            "position_sigma_m": self.position_sigma_m,
            "position_95_radius_m": self.position_95_radius_m,
            "horizontal_95_radius_m": self.horizontal_95_radius_m,
            "pending_step_m": self.pending_step_m,
            "uncertainty_note": "point-to-plane pose covariance about the scan origin from the final ICP pairs, "
                                "estimator in 'uncertainty' (default: delete-one-block jackknife over spatial "
                                "blocks, which accounts for correlated residuals; docs/uncertainty.md) plus the model "
                                "terms listed in 'uncertainty.model_terms'; 95 % radius = radius of the ball holding the "
                                "scan origin with probability 0.95 under that covariance; georeferencing error is not "
                                "included (see the georef report)",
            "crs": self.crs,
            "georef_origin": self.georef_origin,
            "displacement_95_m": self.displacement_95_m,
            "uncertainty": self.uncertainty,
            "plane_tolerance_m": self.plane_tolerance_m,
            "scan_noise_m": self.scan_noise_m,
            "n_scan_points": self.n_scan_points,
            "n_scan_down": self.n_scan_down,
            "n_scan_icp": self.n_scan_icp,
            "correlative": self.correlative,
            "polish": self.polish,
            "rival_search": self.rival_search,
            "gravity": self.gravity,
            "params": {"localize": asdict(self.params), "map": asdict(self.map_params) if self.map_params else None},
            "seed": self.seed,
            "timings_s": self.timings_s,
            "warnings": self.warnings,
        }
        if self.status != "ok":
            d = _without_answer(d, self)
        return to_jsonable(d)


#: ``result.json`` fields that state the answer (the pose and its uncertainty): only an ``ok``
#: result has them; otherwise they are ``null`` and the rejected best candidate's values are
#: under ``rejected_candidates["best"]``.
ANSWER_FIELDS = ("T_map_scan", "T_geo_scan", "T_crs_scan", "covariance_6x6", "position_cov_3x3",
                 "position_sigma_m", "position_95_radius_m", "horizontal_95_radius_m", "displacement_95_m",
                 "uncertainty")

#: The note that every rejected candidate carries.
NOT_A_POSITION = ("NOT a position: placements of the scan that were tried and rejected (status {status}); "
                  "none of them is where the scan is. They are kept to explain the decision.")


def rejected_candidates(res) -> list[dict]:
    """The verified hypotheses of a non-``ok`` result as rejected candidates (map frame only).

    Each entry: ``rank``, ``source``, ``origin_map_m`` (the scan origin placed by the candidate,
    map frame, m — *not a position*), ``distance_to_best_m``, ``rotation_to_best_deg``,
    ``plane_fitness``, ``icp_fitness``, ``icp_inlier_rmse_m``. Empty when RANSAC (and the
    correlative search) proposed nothing.
    """
    out = []
    for h in res.hypotheses or []:
        T = np.asarray(h["T_map_scan"], dtype=np.float64)
        out.append({"rank": int(h["rank"]), "source": h["source"], "origin_map_m": T[:3, 3].tolist(),
                    "distance_to_best_m": float(h["distance_to_chosen_m"]),
                    "rotation_to_best_deg": float(h["rotation_to_chosen_deg"]),
                    "plane_fitness": float(h["plane_fitness"]), "icp_fitness": float(h["icp_fitness"]),
                    "icp_inlier_rmse_m": float(h["icp_inlier_rmse_m"])})
    return out


def _without_answer(d: dict, res) -> dict:
    """``to_dict`` of a failed / ambiguous result: no field reads as an answer.

    The pose fields and their uncertainty (:data:`ANSWER_FIELDS`) become ``null``; what the
    pipeline tried is kept under ``rejected_candidates`` (labelled :data:`NOT_A_POSITION`),
    in the map frame only (no CRS coordinates that could be copied as a position).
    """
    d = dict(d)
    best = {k: d[k] for k in ("T_map_scan", "covariance_6x6", "position_sigma_m", "position_95_radius_m",
                              "uncertainty")} if res.hypotheses else None
    for k in ANSWER_FIELDS:
        d[k] = None
    if d.get("ransac") is not None:
        d["ransac"] = {**d["ransac"], "T_map_scan": None}
    d["rejected_candidates"] = {
        "note": NOT_A_POSITION.format(status=res.status),
        "frame": "map (scan origin placed by each candidate; not georeferenced on purpose)",
        "candidates": rejected_candidates(res),
        "best": best,
        "ransac_T_map_scan": res.ransac_T_map_scan if res.ransac is not None and res.ransac.n_inliers > 0 else None,
        "hypotheses": d.pop("hypotheses"),
    }
    return d


def error_vs_truth(T_est, T_true, points=None) -> dict:
    """Translation (m) and rotation (deg) error of ``T_est`` against ``T_true``; with ``points`` (scan
    frame) also the max / RMS displacement of those points (e.g. trajectory positions), m."""
    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    out = {"translation_m": float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
           "rotation_deg": float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])))}
    if points is not None:
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.linalg.norm((P @ T_est[:3, :3].T + T_est[:3, 3]) - (P @ T_true[:3, :3].T + T_true[:3, 3]), axis=1)
        out["max_point_error_m"] = float(d.max()) if d.size else 0.0
        out["rms_point_error_m"] = float(np.sqrt(np.mean(d * d))) if d.size else 0.0
    return out
