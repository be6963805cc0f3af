"""Global localization of a local scan in a prior (georeferenced) mine map (Baek et al. 2022, Sec. 2).

Pipeline (:func:`localize_scan`), each stage timed:

1. ``downsample`` the scan (Sec. 2.2: voxel size or octree level), ``normals`` ([Baek2022 Eq. 2]),
   ``fpfh`` ([Baek2022 Eqs. 3-6]) with the map's :class:`~minegeo.localize.prepared.FeatureParams`;
2. ``ransac``: FPFH correspondences + RANSAC with edge-length pruning ([Baek2022 Eqs. 7-9]), Table 3
   parameters, via :func:`minegeo.registration.ransac.register_ransac`;
3. ``icp``: every *distinct* RANSAC hypothesis (the best one and the runner-up, optionally
   more from extra RANSAC runs) is refined by ICP (Sec. 2.4, [Baek2022 Eqs. 10-16]; point-to-point as
   in the paper, point-to-plane selectable; GICP is not available yet). The refined
   hypothesis with the highest ICP fitness wins (multi-hypothesis verification: mine drifts
   repeat themselves, and a RANSAC score alone can prefer a look-alike drift);
4. ``decision``: ``status`` = ``ok`` / ``ambiguous`` / ``failed`` with the reason (below); an
   ``ok`` decision is first checked by the whole-map rival search (``rival_search``);
5. ``covariance``: ``Σ = σ² (JᵀJ)⁻¹`` of the final fit and the 95 % position uncertainty of
   the scan origin;
6. ``trajectory``: the sensor trajectory moved into the map and the CRS ([Baek2022 Eq. 18]):
   ``T_map_sensor(τ) = T_map_scan · T_scan_sensor(τ)``.

Frames
------
``scan``  the local scan's own frame (its first sensor pose, as SLAM gives it).
``map``   the prior map's frame before georeferencing — for a map written by
          ``minegeo georef`` the frame of the map file it was made from (the ``map`` of
          ``T_crs_map``). **``T_map_scan`` always refers to this frame**:
          ``p_map = R p_scan + t``.
``geo``   CRS coordinates minus the georeferencing origin; ``T_geo_scan`` is obtained with
          :func:`~minegeo.localize.georef.pose_to_crs` (the position goes through the
          similarity, the orientation only through its rotation, so the pose stays rigid).
``crs``   full projected coordinates = ``geo`` + origin (only added when printing).

Decision rules (all thresholds in :class:`LocalizeParams`)
----------------------------------------------------------
``failed``     RANSAC found no hypothesis; or the chosen placement's verification score (fraction
               of scan points within ``verify_plane_tolerance_m`` of the map's tangent planes)
               is below ``min_plane_fitness``; or the best ICP fitness (fraction of scan points
               with a map point within the ICP gate) is below ``min_fitness``; or its inlier
               RMSE ([Baek2022 Eq. 19]) exceeds ``max_inlier_rmse_m``.
``ambiguous``  another refined hypothesis placing the scan more than ``ambiguity_distance_m``
               (or ``ambiguity_angle_deg``) away reaches ``ambiguity_ratio`` × the best ICP
               fitness (a look-alike drift); or, before an ``ok``, the **whole-map rival
               search** at the chosen attitude (``rival_search``, :mod:`minegeo.localize.rivals`)
               finds a placement that reaches that ratio or, on the scan points the map covers
               at both places, fits as well (``RivalParams.matched_ratio``: an exact copy of the
               drift on another level); or the ICP constraint matrix is degenerate
               (smallest / largest eigenvalue of the normalised point-to-plane constraint
               matrix < ``degeneracy_ratio``, e.g. sliding along a straight featureless drift).
``ok``         otherwise; ``rival_search`` then names the best rival and the margin.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from minegeo._provenance import to_jsonable
from minegeo._validate import as_points, check_positive
from minegeo.errors import InputError, MinegeoError, TooFewPointsError
from minegeo.geometry.se3 import hat, invert, log_so3, rotation_angle
from minegeo.io.types import PointCloud, Trajectory
from minegeo.localize._progress import FEATURE_STEPS, ProgressFn, StepTimings, announce
from minegeo.localize.correlative import CorrelativeParams, correlative_candidates
from minegeo.localize.gravity import GravityParams
from minegeo.localize.prepared import FAST_FEATURES, FeatureParams, PreparedMap, prepare_cloud_features
from minegeo.localize.rivals import RivalParams, matched_support, rival_test, search_rivals
from minegeo.localize.uncertainty import UncertaintyParams, pose_uncertainty, radii_95
from minegeo.registration.gicp import GICPParams, register_gicp
from minegeo.registration.icp import METHODS as _ICP_METHODS
from minegeo.registration.icp import ICPParams, register_icp
from minegeo.registration.ransac import RansacParams, hypothesis_distance, register_ransac

ICP_METHODS = (*_ICP_METHODS, "gicp")

__all__ = ["LocalizeParams", "LocalizationResult", "localize_scan", "CHI2_3D_95", "CHI2_2D_95", "STATUSES",
           "ANSWER_FIELDS", "rejected_candidates"]

log = logging.getLogger(__name__)

#: 95 % quantile of the chi-square distribution with 3 and 2 degrees of freedom.
CHI2_3D_95 = 7.814727903251178
CHI2_2D_95 = 5.991464547107979
#: RANSAC iteration cap of the default parameters (Table 3: 4e8; see LocalizeParams.ransac).
DEFAULT_RANSAC_MAX_ITERATIONS = 4_000_000
#: Possible values of ``LocalizationResult.status``.
STATUSES = ("ok", "ambiguous", "failed")


@dataclass(frozen=True)
class LocalizeParams:
    """Parameters of :func:`localize_scan` (defaults: Baek et al. 2022, Table 3, plus minegeo's checks).

    Attributes
    ----------
    scan_voxel_size_m : float or None
        Voxel size for the scan, m (Table 3: 0.5 m). Ignored when ``scan_octree_level`` is set.
    scan_octree_level : int or None
        Octree level for the scan instead (Sec. 4.1 studies levels 6, 8, 10, 12).
    scan_icp_voxel_size_m : float or None
        ICP source: the paper refines with the whole local cloud (Sec. 2.4); minegeo uses
        its voxel centroids at this edge (m, default 0.1 m); None = every scan point.
    features : FeatureParams
        Normals / FPFH settings (Table 3); must equal the prepared map's.
    ransac : RansacParams
        RANSAC settings (Table 3: ε_distance 2.5 m, 4 correspondences, edge-length 0.9,
        500 validations; confidence 0.999 for [Baek2022 Eq. 8]). One deviation: the iteration cap is
        ``DEFAULT_RANSAC_MAX_ITERATIONS`` (4e6) instead of Table 3's 4e8 (Open3D's budget),
        which at ~1-5 µs per draw would let a hopeless search (scan outside the map) run
        for 10-30 min; [Baek2022 Eq. 8] normally stops far earlier. One addition: mutual FPFH
        matches (``mutual_filter=True``, Open3D's option; Table 3 is silent), which about
        doubles the inlier fraction w and so divides [Baek2022 Eq. 8]'s iterations by ~16 for n = 4.
        :meth:`paper_table3` gives exactly the paper's values.
    ransac_runs : int
        Independent RANSAC runs (seeds derived from ``seed``); their distinct hypotheses are
        all verified by ICP. 1 = the paper.
    icp_method : {"point_to_point", "point_to_plane", "gicp"}
        ICP variant (paper: point-to-point). ``"gicp"``: Generalized-ICP
        (:func:`minegeo.registration.register_gicp`, Segal 2009 / [Ren2019 Eqs. 1-6]) against
        plane covariances of the map's ICP cloud built once from its stored normals.
    icp_max_correspondence_m : float
        ICP pair gate, m (Table 3: 0.5 m).
    icp_max_iterations : int
        Table 3: 30.
    icp_coarse_correspondence_m : float or None
        Gate (m) of a coarse point-to-plane ICP of the feature-level scan run on every RANSAC
        hypothesis before the paper's ICP (minegeo addition: RANSAC poses from 0.5-1 m voxels
        can sit ~1 m from the answer, outside the 0.5 m gate). None skips it.
    icp_screen_max_iterations : int
        Iteration cap of the screening ICP (minegeo addition, ``point_to_point`` and
        ``point_to_plane``): when several hypotheses compete, each first gets at most this
        many ICP iterations on the feature-level scan, and only those whose plane fitness is
        then within the ambiguity ratio of the best get the full-resolution ICP (capped at
        ``icp_max_iterations``). The screening only ranks; in a drift the ICP slides slowly
        along the axis, which barely changes the score after ~10 iterations (measured: the same
        decisions on the benchmark's 20 m scans, and 0.45 s less on the curve flash scan's 25
        candidates). Not applied to a small scan (``correlative_confirm_below_points``): its
        rivals are judged on the narrower ``small_scan_ambiguity_ratio`` margin, and a capped
        screen once left out a rival that the full ICP puts at 0.815 of the best.
    icp_screen_max_points : int
        The screening ICP and its score use at most this many feature-level scan points,
        evenly spaced in the downsampled cloud's order (a fine voxel or a deep octree level
        gives thousands; 1000 points measure a plane fitness to about ±1.3 %, well inside the
        ambiguity ratio's margin). Not applied to a small scan either.
    icp_relative_rmse : float
        Convergence threshold on the RMSE change, m (Table 3: 1e-6).
    icp_relative_fitness : float
        Convergence threshold on the fitness change (Open3D default 1e-6).
    min_scan_points : int
        Fewer downsampled scan points than this is a :class:`TooFewPointsError`.
    min_fitness : float
        ``failed`` below this final ICP fitness (fraction of downsampled scan points).
    max_inlier_rmse_m : float
        ``failed`` above this final ICP inlier RMSE, m.
    verify_plane_tolerance_m : float
        Plane-distance tolerance of the verification score (m): hypotheses are ranked by the
        fraction of scan points within the ICP gate of the map *and* within this distance of
        the map's tangent plane (see ``_verify``).
    verify_noise_factor : float
        The plane tolerance actually used is ``max(verify_plane_tolerance_m, factor · σ_surf)``
        with ``σ_surf`` the scan's own surface noise (median over scan points of the RMS
        distance of their 16 nearest ICP-source neighbours from the neighbourhood's PCA
        plane, ``sqrt(λ_min)`` of [Baek2022 Eq. 2]'s covariance): a noisier sensor gets a wider band
        so its correct placements are not refused; the measure does not depend on any
        placement, so a wrong placement gains nothing. 0 disables it.
    verify_fine_tolerance_m : float or None
        Tolerance of the *fine* agreement (minegeo addition, issue 15): the fraction of scan
        points within ``tol_fine = min(tol, max(verify_fine_tolerance_m, verify_fine_noise_factor
        · σ_surf))`` of the map's tangent planes. On smooth (shotcrete-like) walls every drift of
        the same cross-section agrees with the scan within 0.1 m, so the plane fitness cannot
        tell places apart; the bumps that do (a few cm) show at this tolerance (measured on the
        0.05 m study mine: truth 0.79 against 0.37-0.49 for other drifts at 0.04 m, 0.97 against
        0.86-0.89 at 0.1 m). Hypotheses are ranked by it, and a rival is ``ambiguous`` only
        when it reaches the ambiguity ratio at **both** tolerances (an exact copy does, so twins
        stay ambiguous; a chosen placement that is beaten at the fine level by a rival still is).
        None: off (the plane fitness alone, as before).
    verify_fine_noise_factor : float
        See ``verify_fine_tolerance_m`` (a noisier sensor gets a wider fine band).
    gravity_fallback : bool
        6-DOF scans only (``ransac.model == "rigid"``; minegeo addition, issue 15): when the
        6-DOF pipeline finds no placement (``failed``), estimate the scan's up direction from its
        own geometry (:func:`minegeo.localize.gravity.estimate_up`: floor, roof, walls), level the
        scan with it and run the levelled pipeline (2-point heading + translation RANSAC and the
        whole-map correlative search) once more; its result (``ok`` or ``ambiguous``) replaces
        the failure, in the original scan frame. Only when the estimate is ``ok``. A scan on a
        ramp is levelled to its floor, off by the slope about the drift's cross axis, which
        nothing in a straight scan shows: the levelled attempt is repeated with the up
        direction tilted about that axis by 0, ±2t, ±4t, ... degrees (``t`` the tilt tolerance)
        within the estimate's ``tilt_range_deg`` (±15.5° by default), first non-failed wins.
    gravity_fallback_tilt_deg : float
        Tilt tolerance of the levelled attempt (``--levelled``), raised to the estimate's own
        95 % cone when that is wider.
    gravity_params : GravityParams
        Settings of the up estimate (a 5 000-point area-uniform sample: 4x faster than the
        estimator's default 20 000, the same accuracy on the study scans: 0.25-0.4 deg on level drifts).
    fine_ambiguity_ratio : float
        The ratio a rival must reach at the fine tolerance (scaled by ``small_scan_ambiguity_ratio
        / ambiguity_ratio`` for a small scan). Lower than ``ambiguity_ratio``: the fine level is
        noisier; measured 0.90 for an exact twin that the map covers differently on its two
        levels and 0.55-0.65 for other drifts of the smooth-walled study mine.
    min_plane_fitness : float
        ``failed`` below this verification score of the chosen placement.
    ambiguity_ratio : float
        A distinct hypothesis with verification score >= ratio × best makes the result ``ambiguous``.
    ambiguity_distance_m, ambiguity_angle_deg : float
        Two refined hypotheses are distinct if they place the scan centroid farther apart
        than this (m) or their rotations differ by more than this (deg).
    max_pending_step_m : float
        ``ambiguous`` when one point-to-plane Gauss-Newton step from the ICP answer would still
        move some scan point by more than this (m): ICP (point-to-point converges slowly along
        drifts) stopped before the surfaces fit.
    degeneracy_ratio : float
        A pose direction is *weak* when the normalised ICP constraint matrix has
        ``λ_min / λ_max`` below this (see :func:`minegeo.registration.constraint_analysis`);
        the result is then ``ambiguous`` if the pose covariance lets some scan point move by
        more than ``max_weak_displacement_95_m`` (95 %), e.g. along a straight featureless
        drift. A weak but well-determined direction (roll in a round drift, thousands of
        points) only adds a warning.
    max_weak_displacement_95_m : float
        See ``degeneracy_ratio`` (m).
    correlative : {"fallback", "always", "off"}
        Levelled scans only (``ransac.model == "levelled"``): the correlative 4-DOF search of
        the whole map (:mod:`minegeo.localize.correlative`, a minegeo addition) adds its best
        distinct placements to RANSAC's hypotheses, either only when the RANSAC hypotheses
        do not give an ``ok`` result (``"fallback"``, default: the fast path stays as fast)
        or always. Extra candidates can never turn a true ambiguity into ``ok``: the rival
        that made it ambiguous is still verified.
        Its candidates go through the same ICP, verification and ambiguity test.
    correlative_params : CorrelativeParams
        Its grid and refinement settings.
    correlative_confirm_below_points : int
        In ``"fallback"`` mode the search also runs after an ``ok`` result when the scan has
        fewer feature-level points than this (1 m voxels: roughly its surface in m², e.g. a
        10 m handheld flash scan): a small scan carries little shape, and the one wrong ``ok``
        seen in the studies was such a scan, for which RANSAC had proposed only the wrong
        place. The whole-map candidates then either confirm it or make it ``ambiguous``.
    small_scan_ambiguity_ratio : float
        Used instead of ``ambiguity_ratio`` (for the ICP short list and the rival test) when
        the scan has fewer feature-level points than ``correlative_confirm_below_points``: a
        small scan carries little shape, so it is ``ok`` only when no other verified placement
        reaches this fraction of its plane fitness. Measured: a 10 m railings scan (373
        feature points) whose true place the search did not propose was placed 219 m away
        with plane fitness 0.813 against a rival at 0.683 (0.84); the 20 m scans' correct
        answers had no rival above 0.70 of theirs (docs/localization.md).
    correlative_precheck_ratio : float
        The whole-map candidates are first scored without ICP (plane fitness of the
        feature-level scan at the refined 4-DOF placement, the same test as the
        verification); only those reaching this fraction of the best such score get ICP and
        the full verification (0 keeps all). The ambiguity test compares *refined* scores
        with ``ambiguity_ratio`` (0.9): a placement below 0.7 of the best before ICP would
        have to gain ~30 % more than the best by ICP to become a rival (not seen in the
        studies; measured in docs/localization.md). Their pre-check scores are recorded.
    uncertainty : UncertaintyParams
        Pose covariance estimator (:mod:`minegeo.localize.uncertainty`; default the
        delete-one-block jackknife over 4 m blocks, calibrated in docs/uncertainty.md).
    icp_polish_correspondence_m : float or None
        After the decision, the chosen pose gets a point-to-plane ICP of the ICP-level scan
        with this tighter gate (m; None = off), and the final pose and covariance come from
        it (a minegeo addition; the gate used is ``max(this, 3 σ_surf)``). With the 0.5 m gate, scan points whose surface the map does
        not hold (the shadowed inner wall of a bend) pair with other surfaces and bias the
        point-to-plane fit by centimetres to ~0.1 m; a gate of a few scan-noise sigmas keeps
        only surface pairs. The chosen hypothesis and its verification scores are not changed
        (the covariance-based checks, weak-direction displacement and pending step, use the
        polished fit); a polish moving the scan by more than ``max_pending_step_m`` is not
        applied (warning).
    weak_axis_polish_term : bool
        When the polish was applied and the final pairs constrain some direction weakly
        (normalised constraint eigenvalue ratio below ``uncertainty.degeneracy_ratio``, e.g.
        a straight drift), add ``δ δᵀ`` to the pose covariance, with ``δ`` = the polish's
        pose shift ``(ω, t)`` about the scan origin. Along such a direction the estimate
        depends on which pairs the gate admits, a bias that every jackknife block shares and
        so does not show in their spread; the change between the 0.5 m and the polish gate
        measures that sensitivity (minegeo addition, calibrated in docs/uncertainty.md).
    rival_search : bool
        Before a result is ``ok``, search the whole map for another placement that explains
        the scan nearly as well (:mod:`minegeo.localize.rivals`, a minegeo addition; issue 15:
        mines repeat their level layouts, and an exact copy of a drift that RANSAC did not
        propose made a coin flip ``ok``): the exhaustive correlative search at the chosen
        placement's attitude (its tilt; every floor anchor × every heading of the 3° grid
        aligned with the chosen heading), its distinct candidates refined by the same ICP and
        verified by the same plane fitness; a rival reaching the ambiguity ratio (the small-scan
        one for a small scan), or ``rival_params.matched_ratio`` of the chosen placement's plane
        agreement on the scan points the map covers at both places (a survey map covers two
        copies of a drift differently), makes the result ``ambiguous`` with both placements
        listed. The
        best rival, its distance and the margin (chosen / rival plane fitness) are recorded
        (``LocalizationResult.rival_search``). Runs for 6-DOF and levelled scans alike, only
        when the result would otherwise be ``ok``. Default True; False gives the behaviour
        before it (no search, no record).
    rival_params : RivalParams
        Its grid, cascade and checks (:class:`~minegeo.localize.rivals.RivalParams`; the grid is
        the correlative search's, whose map structures it shares).
    """

    scan_voxel_size_m: float | None = 0.5
    scan_octree_level: int | None = None
    scan_icp_voxel_size_m: float | None = 0.1
    features: FeatureParams = field(default_factory=FeatureParams)
    ransac: RansacParams = field(default_factory=lambda: RansacParams(max_iterations=DEFAULT_RANSAC_MAX_ITERATIONS,
                                                                      mutual_filter=True))
    ransac_runs: int = 1
    icp_method: str = "point_to_point"
    icp_max_correspondence_m: float = 0.5
    icp_max_iterations: int = 30
    icp_relative_rmse: float = 1e-6
    icp_relative_fitness: float = 1e-6
    min_scan_points: int = 30
    min_fitness: float = 0.6
    max_inlier_rmse_m: float = 0.35
    verify_plane_tolerance_m: float = 0.1
    verify_noise_factor: float = 4.0
    verify_fine_tolerance_m: float | None = 0.04
    verify_fine_noise_factor: float = 2.0
    fine_ambiguity_ratio: float = 0.8
    min_plane_fitness: float = 0.75
    ambiguity_ratio: float = 0.9
    ambiguity_distance_m: float = 0.5
    ambiguity_angle_deg: float = 5.0
    degeneracy_ratio: float = 0.01
    max_pending_step_m: float = 0.1
    icp_coarse_correspondence_m: float | None = 1.5
    icp_screen_max_iterations: int = 10
    icp_screen_max_points: int = 1000
    max_weak_displacement_95_m: float = 0.15
    uncertainty: UncertaintyParams = field(default_factory=UncertaintyParams)
    correlative: str = "fallback"
    correlative_params: CorrelativeParams = field(default_factory=CorrelativeParams)
    correlative_confirm_below_points: int = 400
    correlative_precheck_ratio: float = 0.7
    small_scan_ambiguity_ratio: float = 0.8
    icp_polish_correspondence_m: float | None = 0.25
    weak_axis_polish_term: bool = True
    rival_search: bool = True
    rival_params: RivalParams = field(default_factory=RivalParams)
    gravity_fallback: bool = True
    gravity_fallback_tilt_deg: float = 3.0
    gravity_params: GravityParams = field(default_factory=lambda: GravityParams(max_points=5000))

    def __post_init__(self):
        if not isinstance(self.weak_axis_polish_term, (bool, np.bool_)):
            raise InputError(f"weak_axis_polish_term must be True or False, got {self.weak_axis_polish_term!r}")
        if not isinstance(self.rival_search, (bool, np.bool_)):
            raise InputError(f"rival_search must be True or False, got {self.rival_search!r}")
        if not isinstance(self.rival_params, RivalParams):
            raise InputError("rival_params must be a RivalParams")
        if self.correlative not in ("off", "fallback", "always"):
            raise InputError(f"correlative must be 'off', 'fallback' or 'always', got {self.correlative!r}")
        if not 0.0 < float(self.small_scan_ambiguity_ratio) <= 1.0:
            raise InputError(f"small_scan_ambiguity_ratio must be in (0, 1], got {self.small_scan_ambiguity_ratio!r}")
        if not 0.0 <= float(self.correlative_precheck_ratio) <= 1.0:
            raise InputError(f"correlative_precheck_ratio must be in [0, 1], got {self.correlative_precheck_ratio!r}")
        if not isinstance(self.correlative_params, CorrelativeParams):
            raise InputError("correlative_params must be a CorrelativeParams")
        if self.scan_octree_level is None:
            if self.scan_voxel_size_m is None:
                raise InputError("give scan_voxel_size_m or scan_octree_level")
            check_positive(self.scan_voxel_size_m, "scan_voxel_size_m")
        elif isinstance(self.scan_octree_level, bool) or int(self.scan_octree_level) != self.scan_octree_level \
                or not 1 <= self.scan_octree_level <= 21:
            raise InputError(f"scan_octree_level must be an integer in 1..21, got {self.scan_octree_level!r}")
        if not isinstance(self.features, FeatureParams):
            raise InputError("features must be a FeatureParams")
        if not isinstance(self.ransac, RansacParams):
            raise InputError("ransac must be a RansacParams")
        if self.icp_method not in ICP_METHODS:
            raise InputError(f"icp_method must be one of {ICP_METHODS}, got {self.icp_method!r}")
        check_positive(self.icp_max_correspondence_m, "icp_max_correspondence_m")
        if self.scan_icp_voxel_size_m is not None:
            check_positive(self.scan_icp_voxel_size_m, "scan_icp_voxel_size_m")
        if self.icp_coarse_correspondence_m is not None:
            check_positive(self.icp_coarse_correspondence_m, "icp_coarse_correspondence_m")
        if self.icp_polish_correspondence_m is not None:
            check_positive(self.icp_polish_correspondence_m, "icp_polish_correspondence_m")
        check_positive(self.max_inlier_rmse_m, "max_inlier_rmse_m")
        check_positive(self.ambiguity_distance_m, "ambiguity_distance_m")
        check_positive(self.ambiguity_angle_deg, "ambiguity_angle_deg")
        check_positive(self.verify_plane_tolerance_m, "verify_plane_tolerance_m")
        check_positive(self.max_pending_step_m, "max_pending_step_m")
        check_positive(self.max_weak_displacement_95_m, "max_weak_displacement_95_m")
        if not isinstance(self.uncertainty, UncertaintyParams):
            raise InputError("uncertainty must be an UncertaintyParams")
        if self.verify_fine_tolerance_m is not None:
            check_positive(self.verify_fine_tolerance_m, "verify_fine_tolerance_m")
        if not (math.isfinite(float(self.verify_fine_noise_factor)) and float(self.verify_fine_noise_factor) >= 0.0):
            raise InputError(f"verify_fine_noise_factor must be a finite number >= 0, got {self.verify_fine_noise_factor!r}")
        if not (math.isfinite(float(self.verify_noise_factor)) and float(self.verify_noise_factor) >= 0.0):
            raise InputError(f"verify_noise_factor must be a finite number >= 0, got {self.verify_noise_factor!r}")
        for name in ("min_fitness", "min_plane_fitness", "ambiguity_ratio", "fine_ambiguity_ratio", "degeneracy_ratio"):
            v = float(getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise InputError(f"{name} must be in [0, 1], got {v!r}")
        for name in ("ransac_runs", "icp_max_iterations", "icp_screen_max_iterations", "icp_screen_max_points",
                     "min_scan_points", "correlative_confirm_below_points"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < (
                    0 if name in ("icp_max_iterations", "correlative_confirm_below_points") else 1):
                raise InputError(f"{name} must be a positive integer, got {v!r}")

    @classmethod
    def paper_table3(cls, **overrides) -> LocalizeParams:
        """Exactly the paper's Table 3, including its 4e8 RANSAC iteration cap."""
        kw = {"ransac": RansacParams()}
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def fast(cls, **overrides) -> LocalizeParams:
        """minegeo's fast profile (pair it with :meth:`PrepareParams.fast` for the map).

        Coarser descriptors (voxel 1 m, normal radius 2 m, FPFH radius 5 m: the Table 3 ratios
        at twice the voxel), mutual FPFH matches, 3-point RANSAC samples, always 1e6 draws
        (``min_iterations``: [Baek2022 Eq. 8] computed from a wrong but drift-like best placement stops
        the search too early, see :class:`~minegeo.registration.RansacParams`),
        point-to-plane ICP. Not the paper's parameters: measured faster and more successful
        on the synthetic mine (docs/localization.md).
        """
        kw = {"scan_voxel_size_m": 1.0, "features": FAST_FEATURES,
              "ransac": RansacParams(ransac_n=3, mutual_filter=True, max_iterations=1_000_000,
                                     min_iterations=1_000_000),
              "icp_method": "point_to_plane"}
        kw.update(overrides)
        return cls(**kw)

    def ambiguity_ratios(self, small_scan: bool) -> tuple[float, float]:
        """``(ratio, fine_ratio)`` a rival must reach at the plane and the fine tolerance: the small
        scan's ratio for a small scan, the fine ratio scaled the same way."""
        amb = float(self.small_scan_ambiguity_ratio) if small_scan else float(self.ambiguity_ratio)
        return amb, float(self.fine_ambiguity_ratio) * amb / float(self.ambiguity_ratio)

    def describe_downsampling(self) -> str:
        if self.scan_octree_level is not None:
            return f"octree level {self.scan_octree_level}"
        return f"voxel {self.scan_voxel_size_m:g} m"


@dataclass
class LocalizationResult:
    """Outcome of :func:`localize_scan`.

    Attributes
    ----------
    status : str
        ``"ok"``, ``"ambiguous"`` or ``"failed"`` (module docstring).
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
        Plane-distance tolerance used by the verification (m; see ``verify_noise_factor``).
    scan_noise_m : float
        The scan's surface noise ``σ_surf`` (m; NaN when not measured).
    n_scan_points, n_scan_down, n_scan_icp : int
        Scan points read, after downsampling (features, RANSAC) and in the ICP source.
    correlative : dict or None
        Record of the correlative search when it ran (``CorrelativeResult.to_dict``, plus
        ``precheck_plane_fitness`` of every candidate and the ``precheck_ratio`` that kept
        some of them), else None.
    polish : dict or None
        Record of the tight-gate polish (``LocalizeParams.icp_polish_correspondence_m``):
        gate, whether it was applied, largest shift of a scan point (m), its ICP statistics.
        When applied, ``T_map_scan`` and the covariance come from it; ``fitness``,
        ``inlier_rmse_m`` and ``icp`` stay those of the decision's ICP.
    gravity : dict or None
        Record of ``LocalizeParams.gravity_fallback`` when it ran: the up estimate (status,
        ``up_scan``, 95 % cone), the levelled attempt's status and reason, ``R_levelled_scan``.
    rival_search : dict or None
        Record of the whole-map rival search (``LocalizeParams.rival_search``) when it ran
        (the result would otherwise have been ``ok``): ``best_rival`` (the strongest distinct
        verified placement other than the chosen one, from this search or the pipeline's own
        hypotheses: ``T_map_scan`` and ``origin_map_m`` in the map frame, **not a position** —
        a rejected rival —, ``plane_fitness``, ``distance_to_chosen_m``,
        ``rotation_to_chosen_deg``, ``common_fraction``, ``matched_ratio``, ``test_passed``,
        ``source``), ``margin`` (chosen / best rival plane fitness; inf without a rival),
        ``matched_ratio``, ``ambiguity_ratio``, ``self_rank`` / ``self_found``, ``covered``,
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

    status: str
    reason: str
    T_map_scan: np.ndarray
    T_geo_scan: np.ndarray | None
    T_crs_scan: np.ndarray | None
    fitness: float
    inlier_rmse_m: float
    ransac: object
    icp: object
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
    map_params: object
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
                "method": self.params.icp_method, "fitness": ic.fitness, "inlier_rmse_m": ic.inlier_rmse_m,
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


# ----------------------------------------------------------------------------- helpers
def _scan_points(scan) -> tuple[np.ndarray, np.ndarray]:
    """(points relative to the scan's origin, the origin) — the scan frame is origin + points."""
    if isinstance(scan, PointCloud):
        pts, org = scan.points, np.asarray(scan.origin, dtype=np.float64)
    else:
        pts, org = scan, np.zeros(3)
    P = np.asarray(pts, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"scan points must have shape (n, 3), got {P.shape}")
    if P.shape[0] == 0:
        raise TooFewPointsError("the scan is empty: there is nothing to localize")
    return as_points(P, "scan points", min_points=1), org


def _icp_params(p: LocalizeParams) -> ICPParams:
    return ICPParams(max_correspondence_distance_m=float(p.icp_max_correspondence_m),
                     max_iterations=int(p.icp_max_iterations), relative_fitness=float(p.icp_relative_fitness),
                     relative_rmse=float(p.icp_relative_rmse), method=p.icp_method,
                     degeneracy_ratio_threshold=float(p.degeneracy_ratio) if p.degeneracy_ratio > 0 else 1e-12)


#: Step test of minegeo's own ICP stages (coarse pull-in, screening, polish): stop once an
#: update moves less than 0.1 mm and 1e-5 rad (see ``ICPParams.step_translation_m``).
STAGE_STEP_M, STAGE_STEP_RAD = 1e-4, 1e-5


def _plane_icp_params(gate_m: float, p: LocalizeParams) -> ICPParams:
    """Point-to-plane ICP settings of minegeo's extra stages (coarse pull-in, polish): the given
    gate, the paper's iteration cap, 1e-6 convergence or a step below ``STAGE_STEP_M`` /
    ``STAGE_STEP_RAD``, no degeneracy verdict (the decision's)."""
    return ICPParams(max_correspondence_distance_m=float(gate_m), max_iterations=int(p.icp_max_iterations),
                     relative_fitness=1e-6, relative_rmse=1e-6, method="point_to_plane",
                     degeneracy_ratio_threshold=1e-12, step_translation_m=STAGE_STEP_M,
                     step_rotation_rad=STAGE_STEP_RAD)


def _verify(P: np.ndarray, T: np.ndarray, Q: np.ndarray, N: np.ndarray, tree, gate: float, tol: float,
            tol_fine: float | None = None):
    """Point-to-plane agreement of a placement: ``(plane_fitness, plane_rmse_m, fine_fitness)``.

    ``plane_fitness`` = fraction of the scan points whose nearest map point is within ``gate``
    **and** whose distance to that point's tangent plane, ``|(R p + t − q)·n_q|``, is below
    ``tol``; ``plane_rmse_m`` = RMS of those plane distances over the pairs within ``gate``.
    Unlike the point-to-point fitness it is not blurred by the map's point spacing.
    ``fine_fitness``: the same fraction with ``tol_fine`` (``plane_fitness`` when None;
    ``LocalizeParams.verify_fine_tolerance_m``).
    """
    X = P @ T[:3, :3].T + T[:3, 3]
    dist, idx = tree.query(X, k=1, distance_upper_bound=gate)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    m = idx < Q.shape[0]
    if not m.any():
        return 0.0, math.nan, 0.0
    j = idx[m]
    r = np.abs(np.einsum("ij,ij->i", X[m] - Q[j], N[j]))
    pf = float(np.count_nonzero(r < tol)) / P.shape[0]
    pff = pf if tol_fine is None else float(np.count_nonzero(r < tol_fine)) / P.shape[0]
    return pf, float(math.sqrt(float(np.mean(r * r)))), pff


def surface_noise_m(P: np.ndarray, k: int = 16, max_points: int = 20000) -> float:
    """Scan surface noise ``σ_surf`` (m): median of ``sqrt(λ_min)`` of the k-neighbour PCA ([Baek2022 Eq. 2]).

    Evaluated on an evenly strided subset of at most ``max_points`` points (deterministic);
    neighbours from the whole cloud. Independent of any placement in the map.
    """
    from pykdtree.kdtree import KDTree

    n = P.shape[0]
    if n < k + 1:
        return 0.0
    sub = P[:: max(1, n // max_points)]
    _, idx = KDTree(P).query(sub, k=k)
    N = P[np.asarray(idx, dtype=np.int64)]
    N = N - N.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", N, N) / k
    lam = np.linalg.eigvalsh(C)[:, 0]
    return float(np.median(np.sqrt(np.maximum(lam, 0.0))))


def _placement_distance(Ta: np.ndarray, Tb: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    return hypothesis_distance(Ta, Tb, centre)


# ----------------------------------------------------------------------------- main
def localize_scan(prepared_map: PreparedMap, scan_cloud, trajectory: Trajectory | None = None,
                  params: LocalizeParams | None = None, seed: int = 0, *,
                  progress: ProgressFn | None = None) -> LocalizationResult:
    """Find where a local scan (and its sensor trajectory) lies in a prepared prior map.

    Parameters
    ----------
    prepared_map : PreparedMap
        From :func:`~minegeo.localize.prepared.prepare_map` / ``PreparedMap.load``; its
        feature parameters must equal ``params.features``.
    scan_cloud : PointCloud or (n, 3) array_like
        The local scan in its own frame (m).
    trajectory : Trajectory, optional
        Sensor poses ``T_scan_sensor`` in the scan frame (as written by a SLAM system and by
        ``minegeo synth``); moved into the map and the CRS with [Baek2022 Eq. 18].
    params : LocalizeParams, optional
        Defaults to Baek et al. (2022) Table 3 plus the decision thresholds.
    seed : int
        Seeds every random choice (RANSAC sampling); equal inputs and seed give
        bit-identical results.
    progress : callable, optional
        ``progress(step)`` is called when each step starts (``"downsample"``, ``"normals"``,
        ``"FPFH"``, ``"RANSAC"``, ``"ICP verification"``, ``"correlative search"`` and
        ``"rival search"`` when they run, ``"polish"``, ``"uncertainty"``, ``"trajectory"``), e.g. to drive a progress bar
        (:mod:`minegeo.localize._progress`). Nothing is printed by this function.

    Returns
    -------
    LocalizationResult
        Never a silent wrong pose: check ``status`` (``ok`` / ``ambiguous`` / ``failed``) and
        ``reason``. Only an ``ok`` result carries an answer; for the others ``T_map_scan`` and
        its uncertainty describe the best *rejected* candidate (``to_dict`` writes them under
        ``rejected_candidates``, never as the pose).

    Notes
    -----
    **Degeneracy is reported once, where it matters.** Every ICP of every candidate (screening,
    full resolution, rivals) analyses its own constraint matrix, and a weak direction of a
    *rejected or rival* candidate says nothing about the answer; those per-candidate messages of
    :func:`~minegeo.registration.register_icp` / ``register_gicp`` are logged at DEBUG level
    only (the same thread, during this call). The chosen fit's weak direction is judged once,
    after the covariance: if its 95 % displacement over the scan exceeds
    ``max_weak_displacement_95_m`` the result is ``ambiguous`` and ``reason`` says so;
    otherwise it does not change the answer (the covariance, hence the 95 % radius, already
    contains it) and it is a note in ``warnings`` (result.json and the report), not a logged
    warning. The outcome itself is logged at DEBUG level: the caller reports ``status``.

    Raises
    ------
    TooFewPointsError
        Empty scan, or fewer than ``params.min_scan_points`` points after downsampling.
    DegenerateGeometryError
        The downsampled scan is collinear or planar (its pose cannot be determined).
    InputError
        Feature parameters differ from the prepared map's, bad shapes or parameters.
    """
    p = LocalizeParams() if params is None else params
    if not isinstance(p, LocalizeParams):
        raise InputError(f"params must be a LocalizeParams, got {type(p).__name__}")
    if not isinstance(prepared_map, PreparedMap):
        raise InputError(f"prepared_map must be a PreparedMap, got {type(prepared_map).__name__}")
    prepared_map.check_params(p.features)
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise InputError(f"seed must be an integer >= 0, got {seed!r}")
    seed = int(seed)
    with _CandidateICPMessages():
        res = _localize_scan(prepared_map, scan_cloud, trajectory, p, seed, progress)
        if res.status in ("failed", "ambiguous") and p.gravity_fallback and p.ransac.model == "rigid":
            res = _gravity_fallback(prepared_map, scan_cloud, trajectory, p, seed, progress, res)
        return res


def _gravity_fallback(prepared_map, scan_cloud, trajectory, p: LocalizeParams, seed: int, progress, res_6dof):
    """``LocalizeParams.gravity_fallback``: level a failed 6-DOF scan by its own up estimate and
    localize it again with the levelled machinery; the result in the original scan frame.

    With ``R`` the levelling rotation (``p_lev = R p_scan``, :func:`~minegeo.localize.gravity.levelling_rotation`)
    and the levelled run's ``T_map_lev``: ``T_map_scan = T_map_lev · [R | 0]``. The covariance
    (map axes, about the scan origin, which ``R`` fixes) and the placed trajectory (map frame)
    carry over unchanged.
    """
    from minegeo.localize.gravity import _rotate, estimate_up, levelling_rotation

    t0 = time.perf_counter()
    P_raw, org = _scan_points(scan_cloud)
    announce(progress, "gravity")
    try:
        est = estimate_up(P_raw + org, params=p.gravity_params)
    except MinegeoError as e:  # too few points for the estimate: keep the 6-DOF answer
        log.debug("gravity fallback: no up estimate (%s)", e)
        return res_6dof
    t_est = time.perf_counter() - t0
    rec = {"status": est.status, "reason": est.reason, "cone95_deg": float(est.cone95_deg),
           "up_scan": None if est.up is None else np.asarray(est.up).tolist()}  # no times in the record (equal inputs, equal record): see timings_s
    if est.status != "ok" or est.up is None:
        res_6dof.timings_s["gravity"] = t_est
        res_6dof.warnings.append(f"gravity fallback not tried: up estimate {est.status} ({est.reason})")
        return res_6dof
    tilt = max(float(p.gravity_fallback_tilt_deg), float(est.cone95_deg)) if math.isfinite(est.cone95_deg) \
        else float(p.gravity_fallback_tilt_deg)
    # residual-tilt search (a straight ramp: the floor is tilted about the drift's cross axis by the
    # unknown slope): up rotated about est.tilt_axis by 0, +-2 tilt, +-4 tilt, ... within tilt_range_deg
    thetas = [0.0]
    lo, hi = (float(est.tilt_range_deg[0]), float(est.tilt_range_deg[1])) if est.tilt_axis is not None else (0.0, 0.0)
    k = 1
    while 2.0 * tilt * k <= max(-lo, hi) + tilt:
        for sgn in (1.0, -1.0):
            th = sgn * 2.0 * tilt * k
            if lo - tilt <= th <= hi + tilt:
                thetas.append(th)
        k += 1
    p_l = replace(p, ransac=replace(p.ransac, model="levelled", ransac_n=2, max_tilt_deg=min(90.0, tilt),
                                    normal_angle_threshold_rad=None), gravity_fallback=False)
    attempts: list[dict] = []
    attempt_s: list[float] = []  # seconds per levelled attempt -> timings_s["gravity_attempt_k"]
    res_l = R4 = None
    for th in thetas:
        up = np.asarray(est.up, dtype=np.float64)
        if th != 0.0:
            ax = np.asarray(est.tilt_axis, dtype=np.float64)
            up = _rotate(up, ax / np.linalg.norm(ax), math.radians(th))  # up tilted about the cross axis
        R = levelling_rotation(up)
        R4 = np.eye(4)
        R4[:3, :3] = R
        # the scan re-expressed in the levelled frame (a rotation about the scan frame's origin)
        if isinstance(scan_cloud, PointCloud):
            cloud_l = PointCloud(points=P_raw @ R.T, origin=R @ org)
        else:
            cloud_l = np.ascontiguousarray(P_raw @ R.T)
        traj_l = trajectory
        if isinstance(trajectory, Trajectory):
            traj_l = replace(trajectory, poses=np.einsum("ij,njk->nik", R4, np.asarray(trajectory.poses)),
                             origin=R @ np.asarray(trajectory.origin, dtype=np.float64))
        res_l = _localize_scan(prepared_map, cloud_l, traj_l, p_l, seed, progress)
        attempts.append({"tilt_about_cross_axis_deg": th, "status": res_l.status, "reason": res_l.reason})
        attempt_s.append(float(res_l.timings_s.get("total", math.nan)))
        if res_l.status != "failed":
            break
    rec.update({"levelled_status": res_l.status, "levelled_reason": res_l.reason, "tilt_tolerance_deg": tilt,
                "R_levelled_scan": R4[:3, :3].tolist(), "attempts": attempts,
                "tilt_range_deg": [lo, hi], "six_dof_status": res_6dof.status})
    if res_6dof.status == "ambiguous" and res_l.status != "failed":
        # an ambiguous 6-DOF result is replaced only by an ``ok`` that none of the 6-DOF run's own
        # verified placements rivals (the same two-level test, against the levelled answer)
        rival = _six_dof_rival(res_6dof, _rebase(res_l, R4), p, P_raw.mean(axis=0) + org) if res_l.status == "ok" else None
        if res_l.status != "ok" or rival is not None:
            res_6dof.timings_s["gravity"] = time.perf_counter() - t0
            res_6dof.timings_s.update({f"gravity_attempt_{k}": v for k, v in enumerate(attempt_s)})
            why = (f"the levelled search says {res_l.status}" if res_l.status != "ok" else
                   f"its answer has a rival among the 6-DOF placements ({rival})")
            res_6dof.warnings.append(f"gravity fallback: levelled by the scan's own up estimate; {why}: "
                                     "the result stays ambiguous")
            res_6dof.gravity = rec
            return res_6dof
    if res_l.status == "failed":
        res_6dof.timings_s["gravity"] = time.perf_counter() - t0
        res_6dof.timings_s.update({f"gravity_attempt_{k}": v for k, v in enumerate(attempt_s)})
        res_6dof.warnings.append(f"gravity fallback: levelled by the scan's own up estimate (95 % cone "
                                 f"{est.cone95_deg:.1f} deg; residual tilts {', '.join(f'{a:g}' for a in thetas)} "
                                 f"deg tried), the levelled search failed too ({res_l.reason})")
        res_6dof.gravity = rec
        return res_6dof
    out = _rebase(res_l, R4)
    out.timings_s["gravity"] = t_est
    out.timings_s.update({f"gravity_attempt_{k}": v for k, v in enumerate(attempt_s)})
    out.timings_s["six_dof_attempt"] = float(res_6dof.timings_s.get("total", math.nan))
    out.timings_s["total"] = time.perf_counter() - t0 + float(res_6dof.timings_s.get("total", 0.0))
    first = "found no placement" if res_6dof.status == "failed" else "could not tell places apart"
    out.warnings.insert(0, f"the 6-DOF search {first} ({res_6dof.reason}); this result levels the scan "
                           f"by its own up direction (floor/roof/walls, 95 % cone {est.cone95_deg:.1f} deg) and "
                           f"searches heading and position (tilt tolerance {tilt:.1f} deg, residual tilt "
                           f"{attempts[-1]['tilt_about_cross_axis_deg']:g} deg about the drift's cross axis)")
    out.gravity = rec
    return out


def _six_dof_rival(res_6dof, res_ok, p: LocalizeParams, centre: np.ndarray) -> str | None:
    """A verified placement of the 6-DOF run that is a rival of ``res_ok``'s answer (both in the
    original scan frame; ``centre`` the scan's centroid in that frame), by the pipeline's
    two-level plane test; None when there is none."""
    hyps_ok = res_ok.hypotheses or []
    if not hyps_ok:
        return "no verified placement"
    pf_a, pff_a = float(hyps_ok[0]["plane_fitness"]), float(hyps_ok[0].get("fine_fitness", hyps_ok[0]["plane_fitness"]))
    amb, fine = p.ambiguity_ratios(res_ok.n_scan_down < int(p.correlative_confirm_below_points))
    for h in res_6dof.hypotheses or []:
        if "screened out" in h["source"]:
            continue
        dist, ang = hypothesis_distance(res_ok.T_map_scan, h["T_map_scan"], centre)
        if dist <= p.ambiguity_distance_m and ang <= p.ambiguity_angle_deg:
            continue
        pff = float(h.get("fine_fitness", h["plane_fitness"]))
        if float(h["plane_fitness"]) >= amb * pf_a and pff >= fine * pff_a:
            return (f"{dist:.1f} m / {ang:.1f} deg away, plane fitness {h['plane_fitness']:.3f} vs {pf_a:.3f}, fine "
                    f"agreement {pff:.3f} vs {pff_a:.3f}")
    return None


def _rebase(res, R4: np.ndarray):
    """A levelled-frame result expressed for the original scan frame: every ``T_*_scan`` pose
    (the answer, the hypotheses, the rival search) right-multiplied by ``R4`` (``p_lev = R4 p``)."""
    def conv(obj, key=""):
        if isinstance(obj, dict):
            return {k: conv(v, k) for k, v in obj.items()}
        if isinstance(obj, list):
            return [conv(v, key) for v in obj]
        if key.startswith("T_") and key.endswith("_scan") and obj is not None:
            a = np.asarray(obj, dtype=np.float64)
            if a.shape == (4, 4):
                return a @ R4
        return obj

    kw = {}
    for f in ("T_map_scan", "T_geo_scan", "T_crs_scan", "ransac_T_map_scan"):
        v = getattr(res, f, None)
        if v is not None:
            kw[f] = np.asarray(v, dtype=np.float64) @ R4
    kw["hypotheses"] = conv(res.hypotheses) if res.hypotheses is not None else None
    if getattr(res, "rival_search", None) is not None:
        kw["rival_search"] = conv(res.rival_search)
    return replace(res, **kw)


class _CandidateICPMessages(logging.Filter):
    """Context: the per-candidate ICP/GICP degeneracy warnings of this thread go to DEBUG.

    See *Notes* of :func:`localize_scan`: the pipeline judges the chosen fit's degeneracy
    itself, once. Messages of other threads pass unchanged.
    """

    LOGGERS = ("minegeo.registration.icp", "minegeo.registration.gicp")

    def __init__(self):
        super().__init__()
        self._thread = threading.get_ident()
        self.n = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if (threading.get_ident() == self._thread and record.levelno == logging.WARNING
                and str(record.msg).startswith(("ICP result is degenerate", "GICP result is degenerate"))):
            self.n += 1
            log.debug("candidate fit: %s", record.getMessage())
            return False
        return True

    def __enter__(self):
        for name in self.LOGGERS:
            logging.getLogger(name).addFilter(self)
        return self

    def __exit__(self, *exc):
        for name in self.LOGGERS:
            logging.getLogger(name).removeFilter(self)
        return False


def _localize_scan(prepared_map: PreparedMap, scan_cloud, trajectory, p: LocalizeParams, seed: int,
                   progress: ProgressFn | None) -> LocalizationResult:
    """The body of :func:`localize_scan` (arguments already checked)."""
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    warnings: list[str] = []

    # 1. scan features
    P_raw, scan_origin = _scan_points(scan_cloud)
    announce(progress, "downsample")
    feat_t = StepTimings(progress, FEATURE_STEPS)
    D, Nd, F = prepare_cloud_features(P_raw, p.scan_voxel_size_m, p.scan_octree_level, p.features, feat_t)
    timings.update(feat_t)
    if D.shape[0] < p.min_scan_points:
        raise TooFewPointsError(
            f"the scan has only {D.shape[0]} points after downsampling ({p.describe_downsampling()}; "
            f"{P_raw.shape[0]} read); at least {p.min_scan_points} are needed to localize it"
        )
    if np.count_nonzero(np.any(F != 0.0, axis=1)) < p.ransac.ransac_n:
        raise TooFewPointsError(
            f"the scan's points are too sparse for FPFH within {p.features.fpfh_radius_m} m: no descriptor to match"
        )
    # the scan frame is scan_origin + points; keep D relative to scan_origin, fold it into T at the end
    t0 = time.perf_counter()
    if p.scan_icp_voxel_size_m is None:
        Dfine = P_raw
    else:
        from minegeo.geometry import voxel_downsample

        Dfine = np.ascontiguousarray(voxel_downsample(P_raw, float(p.scan_icp_voxel_size_m)).points)
    timings["downsample"] += time.perf_counter() - t0
    Q = prepared_map.points
    Qf = prepared_map.icp_points
    Nf = prepared_map.icp_normals

    # 2. RANSAC (one or more runs)
    announce(progress, "RANSAC")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    run_seeds = [seed] + [int(s) for s in rng.integers(0, 2**31 - 1, size=p.ransac_runs - 1)]
    f_index = prepared_map.feature_index  # built once per map and process (timed in the first scan's RANSAC)
    ransacs = [register_ransac(D, Q, F, prepared_map.features, p.ransac, seed=s, target_feature_index=f_index,
                               check_target=False) for s in run_seeds]
    timings["ransac"] = time.perf_counter() - t0
    r0 = ransacs[0]
    centre = D.mean(axis=0)

    cand: list[tuple[str, np.ndarray, float, float]] = []
    for i, rr in enumerate(ransacs):
        if rr.n_inliers > 0:
            cand.append((f"ransac[{i}] best", rr.T_target_source, rr.fitness, rr.inlier_rmse_m))
            if len(rr.alternatives) > 1:
                for a, (Ta, fa, ea) in enumerate(rr.alternatives[1:]):
                    cand.append((f"ransac[{i}] " + ("runner-up" if a == 0 else f"hypothesis {a + 2}"), Ta, fa, ea))
            elif rr.second_best_T_target_source is not None:
                cand.append((f"ransac[{i}] runner-up", rr.second_best_T_target_source, rr.second_best_fitness,
                             rr.second_best_rmse_m))
    # drop duplicates (same placement as an earlier candidate)
    uniq: list[tuple[str, np.ndarray, float, float]] = []
    def _distinct(Ta, Tb) -> bool:
        dist, ang = _placement_distance(Ta, Tb, centre)
        return max(dist / p.ambiguity_distance_m, ang / p.ambiguity_angle_deg) > 1.0

    for c in cand:
        if all(_distinct(c[1], u[1]) for u in uniq):
            uniq.append(c)

    # 3. ICP of every distinct hypothesis: screening on the feature-level scan (cheap), then the
    #    full-resolution ICP (from the candidate's pose) for the leader and any close rival
    t0 = time.perf_counter()
    # a small scan must beat its rivals by a wider margin (and more of them get the full ICP)
    small_scan = D.shape[0] < int(p.correlative_confirm_below_points)
    amb_ratio, fine_ratio = p.ambiguity_ratios(small_scan)
    if p.icp_method == "gicp":
        gicp_p = GICPParams(max_correspondence_distance_m=float(p.icp_max_correspondence_m),
                            max_iterations=int(p.icp_max_iterations),
                            degeneracy_ratio_threshold=float(p.degeneracy_ratio) if p.degeneracy_ratio > 0 else 1e-12)
        gicp_cov, gicp_index = prepared_map.gicp_target(gicp_p)

        def _refine(P_src, T_init, screening=False):
            return register_gicp(P_src, Qf, T_init, gicp_p, target_covariances=gicp_cov, target_index=gicp_index,
                                 check_target=False)
    else:
        icp_p = _icp_params(p)
        # the screening (a minegeo stage) also stops once the pose stops moving, and after
        # icp_screen_max_iterations (not for a small scan: its rivals are decided on a narrower
        # margin, so an under-converged screen must not drop one); the full-resolution ICP
        # keeps the paper's convergence test
        icp_screen = replace(icp_p, step_translation_m=STAGE_STEP_M, step_rotation_rad=STAGE_STEP_RAD,
                             max_iterations=icp_p.max_iterations if small_scan else
                             min(icp_p.max_iterations, int(p.icp_screen_max_iterations)))

        def _refine(P_src, T_init, screening=False):
            return register_icp(P_src, Qf, T_init, icp_screen if screening else icp_p, target_normals=Nf,
                                target_index=tree, check_target=False)
    tree = prepared_map.kdtree
    gate, tol = float(p.icp_max_correspondence_m), float(p.verify_plane_tolerance_m)
    scan_noise = surface_noise_m(Dfine) if p.verify_noise_factor > 0 else math.nan
    if p.verify_noise_factor > 0:
        tol = max(tol, float(p.verify_noise_factor) * scan_noise)
    tol_fine = None
    if p.verify_fine_tolerance_m is not None:
        tol_fine = float(p.verify_fine_tolerance_m)
        if p.verify_fine_noise_factor > 0 and math.isfinite(scan_noise):
            tol_fine = max(tol_fine, float(p.verify_fine_noise_factor) * scan_noise)
        tol_fine = min(tol_fine, tol)
    memo: dict = {}
    # the screening ICP runs on at most icp_screen_max_points evenly spaced feature-level points
    # (a small scan: on all of them, as with the iteration cap)
    n_scr = int(p.icp_screen_max_points)
    D_screen = D if small_scan or D.shape[0] <= n_scr else np.ascontiguousarray(
        D[np.unique(np.linspace(0, D.shape[0] - 1, n_scr).round().astype(np.int64))])

    def _once(stage, name, T, fn):
        """ICP results of one candidate, computed once: the fallback re-evaluates RANSAC's
        candidates together with the correlative ones (deterministic, so reuse is exact)."""
        key = (stage, name, T.tobytes())
        if key not in memo:
            memo[key] = fn()
        return memo[key]

    def _evaluate(uniq, may_defer=False):
        """Steps 3-4 on a candidate list: returns the decision state (see below).

        ``may_defer``: the correlative fallback will follow if this list gives no ``ok``;
        when the screening already shows that it cannot (best screened plane fitness below
        ``min_plane_fitness``) or that only the full-resolution ICP could separate distinct
        rivals, stop before that ICP (status ``"deferred"``): the fallback's evaluation
        refines the same candidates (memoised) if they still lead."""
        warnings_e: list[str] = []
        t0 = time.perf_counter()
        # coarse pull-in (minegeo addition): RANSAC poses are often ~1 m off (4-DOF levelled
        # hypotheses, 1 m voxels), beyond the 0.5 m ICP gate; a point-to-plane ICP of the
        # feature-level scan with a wider gate brings them into the fine ICP's basin first.
        if p.icp_coarse_correspondence_m is not None and uniq:
            coarse_p = _plane_icp_params(p.icp_coarse_correspondence_m, p)
            # (correlative candidates were already refined with gates down to 0.5 m)
            uniq = [(name, T0 if name.startswith("correlative") else _once(
                        "coarse", name, T0, lambda T0=T0: register_icp(D, Qf, T0, coarse_p, target_normals=Nf,
                                                                      target_index=tree,
                                                                      check_target=False).T_target_source),
                     rf, rrmse) for name, T0, rf, rrmse in uniq]
        screened = []
        if len(uniq) > 1:
            def _screen(T0):
                ic = _refine(D_screen, T0, screening=True)
                return (ic, *_verify(D_screen, ic.T_target_source, Qf, Nf, tree, gate, tol, tol_fine))

            for c in uniq:
                screened.append(_once("screen", c[0], c[1], lambda T0=c[1]: _screen(T0)))
            scores = [x[1] for x in screened]
            if may_defer and max(scores) < p.min_plane_fitness:
                return {"status": "deferred", "t_icp": time.perf_counter() - t0, "t_decision": 0.0}
            fine_set = {i for i, pf in enumerate(scores) if pf >= amb_ratio * max(scores)}
            fine_set.add(int(np.argmax(scores)))
            # candidates that the screening ICP brought to the same placement (within the
            # ambiguity distance and angle) are one hypothesis: only the best-screened of them
            # gets the full-resolution ICP (they could never be each other's rival)
            kept: list[int] = []
            for i in sorted(fine_set, key=lambda i: (-scores[i], i)):
                Ti = screened[i][0].T_target_source
                if all(_distinct(Ti, screened[j][0].T_target_source) for j in kept):
                    kept.append(i)
            same_place = fine_set - set(kept)
            fine_set = set(kept)
            log.debug("screened %d hypotheses: best plane fitness %.3f, %d distinct within ratio %.2f",
                      len(scores), max(scores), len(fine_set), amb_ratio)
            if may_defer and len(fine_set) > 1:
                # distinct rivals on the screen: the whole-map candidates may hold a clearly
                # better placement, and if they do not, the same rivals are refined there
                return {"status": "deferred", "t_icp": time.perf_counter() - t0, "t_decision": 0.0}
        else:
            fine_set = {0} if uniq else set()
            same_place = set()
        refined = []
        for i, (name, T0, rf, rrmse) in enumerate(uniq):
            if i in fine_set:
                def _fine(T_start):
                    ic = _refine(Dfine, T_start)
                    return (ic, *_verify(Dfine, ic.T_target_source, Qf, Nf, tree, gate, tol, tol_fine))

                # from the candidate's own pose, not the screened one: the feature-level ICP can
                # settle ~0.1 m off along a curved drift and the fine ICP then stays there
                # (curve flash scan, 12 m map: 0.117 m instead of 0.028 m)
                ic, pf, prm, pff = _once("fine", name, T0, lambda T0=T0: _fine(T0))
                refined.append((name, T0, rf, rrmse, ic, pf, prm, pff))
            else:  # screened out: keep the coarse ICP's score for the record
                ic, pf, prm, pff = screened[i]
                why = ("screened out: same placement as a better-screened one" if i in same_place
                       else "screened out on the coarse scan")
                refined.append((f"{name} ({why})", T0, rf, rrmse, ic, pf, prm, pff))
        t_icp = time.perf_counter() - t0

        # 4. decision
        t0 = time.perf_counter()
        hyps = []
        best = None
        if refined:
            # fully refined hypotheses first (screened-out ones lost on the coarse scan already), then
            # by the fine agreement (verify_fine_tolerance_m; = the plane fitness when off)
            order = sorted(range(len(refined)),
                           key=lambda i: ("screened out" in refined[i][0], -refined[i][7], -refined[i][5],
                                          -refined[i][4].fitness, i))
            best = refined[order[0]]
            Tb = best[4].T_target_source
            for rank, i in enumerate(order):
                name, T0, rf, rrmse, ic, pf, prm, pff = refined[i]
                dist, ang = _placement_distance(ic.T_target_source, Tb, centre)
                hyps.append({
                    "rank": rank, "source": name, "ransac_fitness": rf, "ransac_inlier_rmse_m": rrmse,
                    "icp_fitness": ic.fitness, "icp_inlier_rmse_m": ic.inlier_rmse_m, "icp_iterations": ic.iterations,
                    "plane_fitness": pf, "plane_rmse_m": prm, "fine_fitness": pff,
                    "distance_to_chosen_m": dist, "rotation_to_chosen_deg": ang,
                    "T_map_scan": _to_map(ic.T_target_source, scan_origin, prepared_map.work_origin),
                })
        status, reason = "ok", ""
        weak = ""
        ic_best = best[4] if best is not None else None
        if best is None:
            status = "failed"
            reason = f"RANSAC found no placement of the scan in the map ({r0.reason})"
        else:
            f, e = ic_best.fitness, ic_best.inlier_rmse_m
            pf_best, pff_best = best[5], best[7]
            rivals = [h for h in hyps[1:] if "screened out" not in h["source"] and (
                      h["distance_to_chosen_m"] > p.ambiguity_distance_m
                                               or h["rotation_to_chosen_deg"] > p.ambiguity_angle_deg)
                      and h["plane_fitness"] >= amb_ratio * pf_best and h["fine_fitness"] >= fine_ratio * pff_best]
            if pf_best < p.min_plane_fitness:
                status = "failed"
                reason = (f"the best placement has only {100 * pf_best:.0f} % of the scan points within "
                          f"{tol:.3g} m of the map surface (need {100 * p.min_plane_fitness:.0f} %; "
                          f"ICP fitness {f:.3f}): no placement matches the drift's shape — the scan is probably not in "
                          "the mapped area, the map changed there, or the right place was not found")
            elif f < p.min_fitness:
                status = "failed"
                reason = (f"the best placement explains only {100 * f:.0f} % of the scan points within "
                          f"{p.icp_max_correspondence_m:g} m of the map (need {100 * p.min_fitness:.0f} %): the scan is "
                          "probably not in the mapped area, or the map changed there")
            elif e > p.max_inlier_rmse_m:
                status = "failed"
                reason = (f"the inlier RMSE {e:.3f} m exceeds {p.max_inlier_rmse_m:g} m: the scan does not fit the map "
                          "closely enough")
            elif rivals:
                h = rivals[0]
                status = "ambiguous"
                reason = (f"another placement {h['distance_to_chosen_m']:.1f} m / {h['rotation_to_chosen_deg']:.1f} deg "
                          f"away fits almost as well (plane fitness {h['plane_fitness']:.3f} vs {pf_best:.3f}, fine "
                          f"agreement {h['fine_fitness']:.3f} vs {pff_best:.3f}, ratios >= "
                          f"{amb_ratio:g} / {fine_ratio:.3g}{' for a small scan' if small_scan else ''}): the drift "
                          "repeats itself; "
                          "extend the scan past a distinctive feature")
            if status == "ok" and ic_best.degeneracy_ratio < p.degeneracy_ratio:
                # decided after the covariance: a weak direction matters only if it leaves the pose uncertain
                weak = (ic_best.degeneracy_reason or
                        f"eigenvalue ratio {ic_best.degeneracy_ratio:.2e} < {p.degeneracy_ratio:g}")
            if status == "ok":
                reason = (f"ICP fitness {f:.3f}, inlier RMSE {e:.3f} m, plane fitness {pf_best:.3f}; "
                          + (f"{len(hyps) - 1} other hypothesis(es) verified and clearly worse"
                             if len(hyps) > 1 else "no competing hypothesis found by RANSAC"))
            if r0.ambiguity_ratio >= p.ambiguity_ratio and not (status == "ambiguous" and rivals):
                warnings_e.append(f"RANSAC's runner-up scored {r0.ambiguity_ratio:.2f} of the best; ICP verification "
                                "separated them")
        return {"uniq": uniq, "refined": refined, "hyps": hyps, "best": best, "status": status, "reason": reason,
                "weak": weak, "ic_best": ic_best, "warnings": warnings_e, "t_icp": t_icp,
                "t_decision": time.perf_counter() - t0}

    # correlative 4-DOF search (minegeo addition, levelled scans only): proposes places that
    # FPFH + RANSAC cannot (few or no correct descriptor matches); see correlative.py
    use_corr = p.ransac.model == "levelled" and p.correlative != "off"
    corr = None
    corr_precheck: list[float] = []

    def _with_correlative(uniq):
        nonlocal corr
        announce(progress, "correlative search")
        t0 = time.perf_counter()
        cp = p.correlative_params
        occ = prepared_map.occupancy(cp)
        ref_xy = None
        if trajectory is not None and isinstance(trajectory, Trajectory) and len(trajectory.poses):
            ref_xy = np.median(np.asarray(trajectory.poses)[:, :2, 3] + np.asarray(trajectory.origin)[:2]
                               - scan_origin[:2], axis=0)
        corr = correlative_candidates(occ, D, Nd, p.correlative_params, seed=seed, reference_xy=ref_xy,
                                      refine_target=(prepared_map.target_index(), Qf, Nf),
                                      screen_target=prepared_map.screen_target(cp.screen_voxel_size_m),
                                      screen_grid=(prepared_map.screen_grid(cp.screen_voxel_size_m)
                                                   if cp.screen_grid and cp.screen_voxel_size_m is not None else None))
        # pre-check without ICP: plane fitness of the feature-level scan at each refined placement
        pre = [_verify(D, Tc, Qf, Nf, tree, gate, tol)[0] for Tc, _ in corr.candidates]
        bar = float(p.correlative_precheck_ratio) * max(pre, default=0.0)
        corr_precheck.extend(pre)
        out = list(uniq)
        for k, (Tc, frac) in enumerate(corr.candidates):
            if pre[k] >= bar and all(_distinct(Tc, u[1]) for u in out):
                out.append((f"correlative #{k + 1}", Tc, frac, math.nan))
        timings["correlative"] = time.perf_counter() - t0
        return out

    if use_corr and p.correlative == "always":
        uniq = _with_correlative(uniq)
    fallback = use_corr and p.correlative == "fallback"
    confirm = fallback and small_scan
    # a small scan's result is always confirmed against the whole map: no need to decide twice
    if not confirm:
        announce(progress, "ICP verification")
    ev = {"status": "deferred", "t_icp": 0.0, "t_decision": 0.0} if confirm else _evaluate(uniq, may_defer=fallback)
    if fallback and (ev["status"] != "ok" or confirm):
        t_first = ev["t_icp"] + ev["t_decision"]
        uniq_c = _with_correlative(uniq)
        announce(progress, "ICP verification")
        ev = _evaluate(uniq_c)
        ev["t_icp"] += t_first
    timings["icp"] = ev["t_icp"]
    timings["decision"] = ev["t_decision"]
    warnings.extend(ev["warnings"])
    hyps, status, reason, weak, ic_best = ev["hyps"], ev["status"], ev["reason"], ev["weak"], ev["ic_best"]
    rival_record = None
    if p.rival_search and status == "ok" and ic_best is not None:
        # 4a. whole-map rival search at the chosen attitude (minegeo addition, issue 15): no `ok`
        #     before it is established that no other placement explains the scan nearly as well
        announce(progress, "rival search")
        t0 = time.perf_counter()
        status, reason, rival_record = _rival_check(
            prepared_map, p, D, Nd, Dfine, ic_best, (float(ev["best"][5]), float(ev["best"][7])), hyps, reason,
            (amb_ratio, fine_ratio), small_scan, centre, scan_origin, trajectory, seed, _refine, _verify,
            (Qf, Nf, tree, gate, tol, tol_fine), warnings,
            timings)
        timings["rival_search"] = time.perf_counter() - t0
        b = (rival_record or {}).get("best_rival")
        pf0, pff0 = float(ev["best"][5]), float(ev["best"][7])
        if (status == "ambiguous" and tol_fine is not None and b is not None and b.get("score_level") == "full"
                and b["plane_fitness"] >= amb_ratio * pf0 and b["fine_fitness"] * fine_ratio > pff0):
            # the search found a placement that fits better than the first choice, by so much at the fine
            # level that the first choice would not be *its* rival: verify it with the pipeline's own
            # candidates and, if it wins there, search for rivals around it (once; it never switches back)
            t0 = time.perf_counter()
            T_r = _from_map(b["T_map_scan"], scan_origin, prepared_map.work_origin)
            first = (f"{b['distance_to_chosen_m']:.1f} m from the first choice, plane fitness {b['plane_fitness']:.3f} "
                     f"vs {pf0:.3f}, fine agreement {b['fine_fitness']:.3f} vs {pff0:.3f}")
            ev2 = _evaluate(list(ev["uniq"]) + [("rival search: fits better than the first choice", T_r, math.nan,
                                                 math.nan)])
            if ev2["status"] == "ok" and ev2["best"][0].startswith("rival search"):
                ev = ev2
                warnings.extend(ev2["warnings"])
                hyps, status, reason, weak, ic_best = ev["hyps"], ev["status"], ev["reason"], ev["weak"], ev["ic_best"]
                status, reason, rival_record = _rival_check(
                    prepared_map, p, D, Nd, Dfine, ic_best, (float(ev["best"][5]), float(ev["best"][7])), hyps,
                    reason, (amb_ratio, fine_ratio), small_scan, centre, scan_origin, trajectory, seed, _refine,
                    _verify, (Qf, Nf, tree, gate, tol, tol_fine), warnings, timings)
                warnings.append(f"the whole-map rival search found a placement that fits better than the first "
                                f"choice ({first}); it was verified like every candidate and chosen")
            timings["rival_switch"] = time.perf_counter() - t0
    polish = None
    ic_final = ic_best  # pose and covariance; the reported ICP statistics stay the decision's
    if p.icp_polish_correspondence_m is not None and ic_best is not None:
        # 4b. polish (minegeo addition): point-to-plane with a tight gate from the chosen pose
        announce(progress, "polish")
        t0 = time.perf_counter()
        pol_gate = float(p.icp_polish_correspondence_m)
        if math.isfinite(scan_noise):
            pol_gate = max(pol_gate, 3.0 * scan_noise)
        pol_p = _plane_icp_params(pol_gate, p)
        ic_pol = register_icp(Dfine, Qf, ic_best.T_target_source, pol_p, target_normals=Nf, target_index=tree,
                              check_target=False)
        Ta, Tp = ic_best.T_target_source, ic_pol.T_target_source
        Pa = Dfine @ Ta[:3, :3].T + Ta[:3, 3]
        shift = float(np.sqrt(np.max(np.sum((Dfine @ Tp[:3, :3].T + Tp[:3, 3] - Pa) ** 2, axis=1))))
        applied = ic_pol.correspondences.shape[0] >= 7 and shift <= p.max_pending_step_m
        # the same shift as a pose increment (ω, t) about the placed scan origin, map axes
        dT = Tp @ invert(Ta)
        o_a = Ta[:3, :3] @ (-scan_origin) + Ta[:3, 3]
        shift6 = np.r_[log_so3(dT[:3, :3]), dT[:3, :3] @ o_a + dT[:3, 3] - o_a]
        polish = {"gate_m": pol_gate, "applied": bool(applied), "largest_shift_m": shift, "shift_6": shift6.tolist(),
                  "iterations": int(ic_pol.iterations), "fitness": float(ic_pol.fitness),
                  "inlier_rmse_m": float(ic_pol.inlier_rmse_m), "n_pairs": int(ic_pol.correspondences.shape[0])}
        if applied:
            ic_final = ic_pol
        else:
            warnings.append(f"the tight-gate polish would move the scan by {shift:.3f} m (> "
                            f"{p.max_pending_step_m:g} m) or left too few pairs: not applied")
        timings["polish"] = time.perf_counter() - t0

    # 5. covariance (about the scan origin, work frame)
    announce(progress, "uncertainty")
    t0 = time.perf_counter()
    T_work_scan = ic_final.T_target_source if ic_final is not None else np.eye(4)
    cov = None
    sigma = math.nan
    residuals = None
    disp95 = math.inf
    unc_record = None
    pos_cov = None
    pending = math.nan
    pos_sigma = np.full(3, np.inf)
    r95 = h95 = math.inf
    if ic_final is not None:
        Pw = Dfine @ T_work_scan[:3, :3].T + T_work_scan[:3, 3]
        # D = scan points - scan_origin, so the scan frame's origin is at D = -scan_origin
        o_work = T_work_scan[:3, :3] @ (-scan_origin) + T_work_scan[:3, 3]
        unc = None
        if ic_final.correspondences.shape[0] >= 7:
            unc = pose_uncertainty(Pw, Qf, Nf, ic_final.correspondences, o_work,
                                   replace(p.uncertainty, degeneracy_ratio=0.0), check_target=False)
            # weak direction: add the polish's shift as a model-error term (see weak_axis_polish_term)
            add_shift = (unc.covariance_6x6 is not None and p.weak_axis_polish_term and polish is not None
                         and polish["applied"] and unc.information_ratio < p.uncertainty.degeneracy_ratio)
            if add_shift:
                d6 = np.asarray(polish["shift_6"], dtype=np.float64)
                unc = unc.with_model_term("weak_axis_polish", np.outer(d6, d6))
            cov, sigma, residuals, step = unc.covariance_6x6, unc.sigma_m, unc.residuals_m, unc.pending_step
            # record: data term + named model terms (issue 15 item 6), without the top-level matrices
            unc_record = unc.to_dict()
            for k in ("covariance_6x6", "covariance_formal_6x6", "position_cov_3x3", "information_6x6"):
                unc_record.pop(k, None)
            unc_record["weak_axis_polish_term"] = bool(add_shift)
        else:
            step = None
        if cov is not None:
            # 95 % displacement of the scan's bounding-box corners under the pose covariance
            # (a rigid perturbation moves points affinely, so the extreme is at a corner)
            lo, hi = Pw.min(axis=0), Pw.max(axis=0)
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
            disp95 = 0.0
            for q in corners:
                Jq = np.hstack([-hat(q - o_work), np.eye(3)])
                disp95 = max(disp95, float(np.linalg.eigvalsh(Jq @ cov @ Jq.T)[-1]))
            disp95 = float(math.sqrt(CHI2_3D_95 * max(disp95, 0.0)))
        if weak and status == "ok":
            if cov is None or disp95 > p.max_weak_displacement_95_m:
                status = "ambiguous"
                reason = ("the fit is not constrained in every direction: " + weak
                          + (f"; the 95 % displacement over the scan reaches {disp95:.3f} m (> "
                             f"{p.max_weak_displacement_95_m:g} m)" if cov is not None else "")
                          + " (e.g. a straight featureless drift: the position along it is uncertain)")
            else:
                # does not change the answer: a note (result.json, report), not a logged warning
                warnings.append(f"note: weakly constrained direction ({weak}), but its 95 % displacement over the "
                                f"scan is only {disp95:.3f} m (<= {p.max_weak_displacement_95_m:g} m) and the "
                                "95 % radius includes it")
        if step is not None:
            lever = float(np.sqrt(np.max(np.sum((Pw - o_work) ** 2, axis=1))))
            pending = float(np.linalg.norm(step[3:]) + np.linalg.norm(step[:3]) * lever)
            if pending > p.max_pending_step_m and status == "ok":
                status = "ambiguous"
                reason = (f"ICP stopped {pending:.3f} m (largest displacement over the scan) away from the "
                          f"best surface fit (> {p.max_pending_step_m:g} m): the pose is not settled; try "
                          "--icp point_to_plane or more ICP iterations")
        if cov is not None:
            pos_cov = cov[3:, 3:].copy()
            pos_sigma = np.sqrt(np.maximum(np.diag(pos_cov), 0.0))
            r95, h95 = radii_95(pos_cov)
            if unc_record is not None:  # the estimator's own radii, updated for any term added here
                unc_record.update(position_95_radius_m=r95, horizontal_95_radius_m=h95,
                                  position_sigma_m=pos_sigma.tolist())
        elif status == "ok":
            status = "ambiguous"
            reason = "the fit leaves at least one pose direction unconstrained (singular information matrix)"
    timings["covariance"] = time.perf_counter() - t0

    T_map_scan = _to_map(T_work_scan, scan_origin, prepared_map.work_origin)

    # 6. trajectory and CRS ([Baek2022 Eq. 18])
    announce(progress, "trajectory")
    t0 = time.perf_counter()
    g = prepared_map.georef_result
    T_geo_scan = T_crs_scan = None
    georef_origin = None
    crs = prepared_map.crs
    if g is not None:
        from minegeo.localize.georef import pose_to_crs

        T_geo_scan = pose_to_crs(T_map_scan, g, allow_failed=True)
        T_crs_scan = T_geo_scan.copy()
        T_crs_scan[:3, 3] += g.origin
        georef_origin = np.asarray(g.origin, dtype=np.float64)
        if g.status == "failed":
            warnings.append("the map's georeferencing is marked failed: CRS coordinates are not reliable")
    elif crs:
        T_crs_scan = T_map_scan.copy()
    traj_map = traj_geo = traj_sigma = None
    if trajectory is not None:
        if not isinstance(trajectory, Trajectory):
            raise InputError(f"trajectory must be a Trajectory, got {type(trajectory).__name__}")
        poses = np.asarray(trajectory.poses, dtype=np.float64).copy()
        poses[:, :3, 3] += np.asarray(trajectory.origin, dtype=np.float64)
        Tm = np.einsum("ij,njk->nik", T_map_scan, poses)
        traj_map = Trajectory(times_s=np.asarray(trajectory.times_s, dtype=np.float64).copy(), poses=Tm, frame="map",
                              body=trajectory.body)
        if g is not None:
            from minegeo.localize.georef import pose_to_crs

            Tg = pose_to_crs(Tm, g, allow_failed=True)
            traj_geo = Trajectory(times_s=traj_map.times_s.copy(), poses=Tg, frame="crs", body=trajectory.body,
                                  origin=np.asarray(g.origin, dtype=np.float64).copy(), crs=g.crs)
        if cov is not None:
            # position of each pose: dp = -[p - o]x omega + t  (perturbation about the scan origin o)
            o_map = T_map_scan[:3, :3] @ np.zeros(3) + T_map_scan[:3, 3]
            d = Tm[:, :3, 3] - o_map
            traj_sigma = np.empty(d.shape[0])
            for i, di in enumerate(d):
                J = np.hstack([-hat(di), np.eye(3)])
                traj_sigma[i] = math.sqrt(max(float(np.trace(J @ cov @ J.T)), 0.0))
    timings["trajectory"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    # the caller reports the outcome (the CLI prints it once); see Notes of localize_scan
    log.debug("localization %s: %s", status, reason)
    res = LocalizationResult(
        status=status, reason=reason, T_map_scan=T_map_scan, T_geo_scan=T_geo_scan, T_crs_scan=T_crs_scan,
        fitness=float(ic_best.fitness) if ic_best is not None else 0.0,
        inlier_rmse_m=float(ic_best.inlier_rmse_m) if ic_best is not None else math.nan,
        ransac=r0, icp=ic_best, hypotheses=hyps, covariance_6x6=cov, sigma_m=sigma, position_cov_3x3=pos_cov,
        position_sigma_m=pos_sigma, position_95_radius_m=r95, horizontal_95_radius_m=h95, pending_step_m=pending,
        trajectory_map=traj_map, trajectory_geo=traj_geo, trajectory_sigma_m=traj_sigma, crs=crs,
        georef_origin=georef_origin, displacement_95_m=disp95, uncertainty=unc_record, plane_tolerance_m=tol, scan_noise_m=scan_noise, n_scan_points=int(P_raw.shape[0]), n_scan_down=int(D.shape[0]), n_scan_icp=int(Dfine.shape[0]),
        params=p, map_params=prepared_map.params, seed=seed, timings_s=timings, warnings=warnings,
        ransac_T_map_scan=_to_map(r0.T_target_source, scan_origin, prepared_map.work_origin),
        scan_points_down=D + scan_origin, residuals_m=residuals,
        correlative=None if corr is None else {**corr.to_dict(), "precheck_plane_fitness": list(corr_precheck),
                                                "precheck_ratio": float(p.correlative_precheck_ratio)},
        polish=polish, rival_search=rival_record,
    )
    return res


#: Label of the best rival of an ``ok`` result (``result.json`` ``rival_search.best_rival.note``).
REJECTED_RIVAL = ("NOT a position: the strongest other placement of the scan, checked and rejected by the "
                  "whole-map rival search (kept to show the margin)")


def _rival_check(pm: PreparedMap, p: LocalizeParams, D, Nd, Dfine, ic_best, pf_best_pair: tuple, hyps: list,
                 reason: str, amb_ratios: tuple, small_scan: bool, centre, scan_origin, trajectory, seed: int,
                 refine, verify, target, warnings: list, timings: dict) -> tuple[str, str, dict]:
    """Step 4a of :func:`localize_scan`: the whole-map rival search (:func:`~minegeo.localize.rivals.search_rivals`)
    around an ``ok`` decision, with the pipeline's own ICP (``refine``) and verification (``verify``).

    Appends the search's fully verified rivals to ``hyps`` (source ``"rival search #k"``) and
    returns ``(status, reason, record)``: ``ambiguous`` when a distinct, fully verified placement
    other than the chosen one (the search's or the pipeline's own hypotheses) passes
    :func:`~minegeo.localize.rivals.rival_test`; otherwise ``ok`` with the best rival and the
    margin added to the reason. ``record`` is ``LocalizationResult.rival_search`` (no times in
    it, so equal inputs give an equal record); the times go to ``timings`` (``rival_search_*``).
    """
    Qf, Nf, tree, gate, tol, tol_fine = target
    pf_best, pff_best = pf_best_pair
    amb_ratio, fine_ratio = amb_ratios
    fine_scale = amb_ratio / fine_ratio if tol_fine is not None else None
    rp = p.rival_params
    cp = rp.search
    t0 = time.perf_counter()
    occ = pm.occupancy(cp)
    screen_target = pm.screen_target(cp.screen_voxel_size_m)
    screen_grid = (pm.screen_grid(cp.screen_voxel_size_m)
                   if cp.screen_grid and cp.screen_voxel_size_m is not None else None)
    timings["rival_search_map_structures"] = time.perf_counter() - t0
    ref = None
    if trajectory is not None and isinstance(trajectory, Trajectory) and len(trajectory.poses):
        ref = np.median(np.asarray(trajectory.poses)[:, :3, 3] + np.asarray(trajectory.origin) - scan_origin, axis=0)

    def _masks(P, Ts):
        """Per point of ``P`` at each placement: map point within the gate, within the plane
        tolerance of its tangent plane and within the fine tolerance (the numbers of ``_verify``,
        one KD-tree query)."""
        n = P.shape[0]
        X = np.concatenate([P @ T[:3, :3].T + T[:3, 3] for T in Ts])
        _, idx = tree.query(X, k=1, distance_upper_bound=gate)
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        sup = idx < Qf.shape[0]
        r = np.full(X.shape[0], np.inf)
        j = idx[sup]
        r[sup] = np.abs(np.einsum("ij,ij->i", X[sup] - Qf[j], Nf[j]))
        on = r < tol
        on_f = r < (tol if tol_fine is None else tol_fine)
        return [(sup[k * n:(k + 1) * n], on[k * n:(k + 1) * n], on_f[k * n:(k + 1) * n]) for k in range(len(Ts))]

    def _fine(T):
        ic = refine(Dfine, T)
        return (ic, *verify(Dfine, ic.T_target_source, Qf, Nf, tree, gate, tol, tol_fine))

    def _support(Ts, level):
        return _masks(D if level == "feature" else Dfine, Ts) if Ts else []

    Tb = ic_best.T_target_source
    rs = search_rivals(occ, D, Nd, Tb, params=rp, seed=seed, centre=centre,
                       ambiguity_distance_m=float(p.ambiguity_distance_m),
                       ambiguity_angle_deg=float(p.ambiguity_angle_deg), support=_support, fine=_fine,
                       reference_point=ref, refine_target=(pm.target_index(), Qf, Nf), screen_target=screen_target,
                       screen_grid=screen_grid, fine_scale=fine_scale)

    parts = rs.timings_s.get("search_parts", {})
    timings["rival_search_grid"] = parts.get("setup", 0.0) + parts.get("score", 0.0) + parts.get("select", 0.0)
    timings["rival_search_refine"] = parts.get("refine", 0.0)
    timings["rival_search_checks"] = sum(rs.timings_s.get(k, 0.0) for k in ("precheck", "fine"))

    def to_map(T):
        return _to_map(T, scan_origin, pm.work_origin)

    def from_map(T):
        return _from_map(T, scan_origin, pm.work_origin)

    n_hyp = len(hyps)
    for c in rs.candidates:
        if c.stage != "fine":
            continue
        hyps.append({
            "rank": len(hyps), "source": f"rival search #{c.rank}" + (
                "" if c.distinct else " (ICP brought it onto the chosen placement)"),
            "ransac_fitness": math.nan, "ransac_inlier_rmse_m": math.nan, "icp_fitness": c.icp_fitness,
            "icp_inlier_rmse_m": c.icp_inlier_rmse_m, "icp_iterations": c.icp_iterations,
            "plane_fitness": c.plane_fitness, "plane_rmse_m": c.plane_rmse_m, "fine_fitness": c.fine_fitness,
            "distance_to_chosen_m": c.final_distance_m, "rotation_to_chosen_deg": c.final_rotation_deg,
            "common_fraction": c.common_fraction, "matched_ratio": c.matched_ratio,
            "T_map_scan": to_map(c.T_final)})
    # every distinct scored placement other than the chosen one: the search's (at the deepest stage it
    # reached) and the pipeline's own fully verified hypotheses (support-matched against the chosen one too)
    pool = []
    for c in rs.candidates:
        if c.stage == "fine" and c.distinct:
            pool.append({"source": f"rival search #{c.rank}", "score_level": "full", "T_map_scan": to_map(c.T_final),
                         "plane_fitness": c.plane_fitness, "chosen_plane_fitness": pf_best,
                         "fine_fitness": c.fine_fitness, "chosen_fine_fitness": pff_best,
                         "common_fraction": c.common_fraction, "matched_ratio": c.matched_ratio,
                         "distance_to_chosen_m": c.final_distance_m, "rotation_to_chosen_deg": c.final_rotation_deg})
        elif c.stage == "precheck" and c.distinct:
            pool.append({"source": f"rival search #{c.rank}", "score_level": "pre-check",
                         "T_map_scan": to_map(c.T_search), "plane_fitness": c.precheck,
                         "chosen_plane_fitness": rs.precheck_self, "fine_fitness": math.nan,
                         "chosen_fine_fitness": math.nan, "common_fraction": c.pre_common_fraction,
                         "matched_ratio": c.pre_matched_ratio, "distance_to_chosen_m": c.distance_m,
                         "rotation_to_chosen_deg": c.rotation_deg})
    own = [h for h in hyps[1:n_hyp] if "screened out" not in h["source"]
           and (h["distance_to_chosen_m"] > p.ambiguity_distance_m or h["rotation_to_chosen_deg"] > p.ambiguity_angle_deg)]
    if own:
        m = _masks(Dfine, [Tb] + [from_map(h["T_map_scan"]) for h in own])
        for h, mk in zip(own, m[1:], strict=True):
            frac, ratio = matched_support(m[0], mk, fine_scale=fine_scale)
            h["common_fraction"], h["matched_ratio"] = frac, ratio
            pool.append({"source": h["source"], "score_level": "full", "T_map_scan": np.asarray(h["T_map_scan"]),
                         "plane_fitness": h["plane_fitness"], "chosen_plane_fitness": pf_best,
                         "fine_fitness": h["fine_fitness"], "chosen_fine_fitness": pff_best,
                         "common_fraction": frac, "matched_ratio": ratio,
                         "distance_to_chosen_m": h["distance_to_chosen_m"],
                         "rotation_to_chosen_deg": h["rotation_to_chosen_deg"]})
    for b in pool:
        b["margin"] = (b["chosen_plane_fitness"] / b["plane_fitness"]) if b["plane_fitness"] > 0 else math.inf
        b["test_passed"] = rival_test(pf_best, b["plane_fitness"], b["common_fraction"], b["matched_ratio"],
                                      amb_ratio, rp, chosen_fine_fitness=pff_best,
                                      fine_fitness=b["fine_fitness"], fine_ratio=fine_ratio) \
            if b["score_level"] == "full" else ""
        # how close to either test (1 = on a threshold)
        closeness = b["plane_fitness"] / (amb_ratio * b["chosen_plane_fitness"]) if b["chosen_plane_fitness"] > 0 else 0
        if math.isfinite(b["fine_fitness"]) and b["chosen_fine_fitness"] > 0:  # both tolerances must pass
            closeness = min(closeness, b["fine_fitness"] / (fine_ratio * b["chosen_fine_fitness"]))
        if b["common_fraction"] >= rp.min_common_fraction and math.isfinite(b["matched_ratio"]):
            closeness = max(closeness, b["matched_ratio"] / rp.matched_ratio)
        b["closeness"] = float(closeness)
    pool.sort(key=lambda b: (not b["test_passed"], -b["closeness"], b["source"]))
    best_r = pool[0] if pool else None
    record = {**rs.to_dict(to_map), "ambiguity_ratio": amb_ratio, "chosen_plane_fitness": pf_best,
              "fine_ambiguity_ratio": fine_ratio, "chosen_fine_fitness": pff_best, "fine_tolerance_m": tol_fine,
              "margin": best_r["margin"] if best_r else math.inf,
              "matched_ratio": best_r["matched_ratio"] if best_r else math.nan,
              "margin_note": ("margin = chosen / best rival plane fitness, both scored the same way (score_level: "
                              "'full' = after the full-resolution ICP, 'pre-check' = feature-level points, the rival "
                              "at the search's refined placement without ICP, for rivals out of reach of both tests "
                              "there); the result is "
                              f"ambiguous when a fully verified rival reaches the ambiguity ratio (margin <= "
                              f"{1.0 / amb_ratio:.3f}) or, on the points the map covers at both placements (common "
                              f"fraction >= {rp.min_common_fraction:g}), {rp.matched_ratio:g} of the chosen "
                              "placement's agreement (matched_ratio); best_rival = the rival closest to either test"),
              "best_rival": None}
    if best_r is not None:
        T = best_r["T_map_scan"]
        record["best_rival"] = {"note": REJECTED_RIVAL, **best_r, "origin_map_m": T[:3, 3].tolist()}
    if not rs.self_found:
        warnings.append("the whole-map rival search did not recover the chosen placement itself among its "
                        f"{len(rs.candidates)} candidates ({rs.reason or 'ranked lower'}): its guarantee does not hold "
                        "for this scan")
    elif not rs.covered:
        warnings.append("the whole-map rival search kept fewer placements than reach the chosen placement's own "
                        "score minus its slack at some stage (caps; result.json rival_search.coverage): a rival "
                        "scoring like the chosen placement may not have been checked")
    if best_r is not None and best_r["test_passed"]:
        b = best_r
        how = (f"plane fitness {b['plane_fitness']:.3f} vs {pf_best:.3f}, fine agreement {b['fine_fitness']:.3f} vs "
               f"{pff_best:.3f}, ratios >= {amb_ratio:g} / {fine_ratio:.3g}"
               f"{' for a small scan' if small_scan else ''}" if b["test_passed"] == "plane fitness" else
               f"on the {100 * b['common_fraction']:.0f} % of scan points that the map covers at both places, its "
               f"share on the map surface is {b['matched_ratio']:.2f} of the chosen placement's, >= "
               f"{rp.matched_ratio:g}; plane fitness {b['plane_fitness']:.3f} vs {pf_best:.3f} only because the map "
               "covers the two places differently")
        where = ("the whole-map rival search at the chosen attitude" if b["source"].startswith("rival")
                 else "the hypotheses")
        return "ambiguous", (
            f"another placement {b['distance_to_chosen_m']:.1f} m / {b['rotation_to_chosen_deg']:.1f} deg away, found "
            f"by {where}, fits almost as well ({how}): the scan cannot tell the two places apart (a repeated drift "
            "or level); extend the scan past a distinctive feature"), record
    if best_r is None:
        reason += "; whole-map rival search at its attitude: no other placement found"
    else:
        reason += (f"; best rival (whole-map search at its attitude and the hypotheses) "
                   f"{best_r['distance_to_chosen_m']:.1f} m away, plane fitness {best_r['plane_fitness']:.3f} against "
                   f"{best_r['chosen_plane_fitness']:.3f} ({best_r['score_level']} level; margin {best_r['margin']:.2f}, "
                   f"ambiguous at <= {1.0 / amb_ratio:.2f}; support-matched {best_r['matched_ratio']:.2f}, ambiguous "
                   f"at >= {rp.matched_ratio:g})")
    return "ok", reason, record


def _to_map(T_work_D: np.ndarray, scan_origin: np.ndarray, work_origin: np.ndarray) -> np.ndarray:
    """``T_map_scan`` from a transform of the origin-subtracted scan ``D = scan − scan_origin`` into ``work``.

    ``p_work = R (p_scan − o_s) + t``  ⇒  ``p_map = R p_scan + (t − R o_s + o_w)``.
    """
    T = np.array(T_work_D, dtype=np.float64, copy=True)
    T[:3, 3] = T[:3, 3] - T[:3, :3] @ scan_origin + work_origin
    return T


def _from_map(T_map_scan, scan_origin: np.ndarray, work_origin: np.ndarray) -> np.ndarray:
    """The inverse of :func:`_to_map`: a ``T_map_scan`` as a transform of ``D`` into ``work``."""
    T = np.array(T_map_scan, dtype=np.float64, copy=True)
    T[:3, 3] = T[:3, 3] + T[:3, :3] @ scan_origin - work_origin
    return T


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
