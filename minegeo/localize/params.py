"""Parameters of map preparation and scan localization.

Every settings dataclass of :mod:`minegeo.localize` that :func:`~minegeo.localize.localize_scan`
or :func:`~minegeo.localize.prepare_map` takes is importable from here (the modules that use them
import them from here; their old module paths still export them): the feature, preparation and
localization settings are defined here, those of the optional stages (correlative search, rival
check, up estimate, uncertainty) in :mod:`minegeo.localize.params_stages`. Keeping them apart from the code that
uses them breaks the import circle between the pipeline and the prepared map (a prepared map
builds the search structures that a :class:`LocalizeParams` will need).

Units: lengths in metres (``_m``), angles in degrees (``_deg``) unless named ``_rad``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from minegeo._validate import check_positive
from minegeo.errors import InputError
from minegeo.localize.params_stages import (
    REGISTRATION_SIGMA_M,
    UNCERTAINTY_METHODS,
    CorrelativeParams,
    GravityParams,
    RivalParams,
    UncertaintyParams,
)
from minegeo.registration.icp import METHODS as _ICP_METHODS
from minegeo.registration.ransac import RansacParams

__all__ = ["FeatureParams", "FAST_FEATURES", "PrepareParams", "CorrelativeParams", "RivalParams", "GravityParams",
           "UncertaintyParams", "LocalizeParams", "UNCERTAINTY_METHODS", "REGISTRATION_SIGMA_M",
           "DEFAULT_RANSAC_MAX_ITERATIONS", "ICP_METHODS"]

_ORIENTATIONS = ("void", "none", "centroid")

@dataclass(frozen=True)
class FeatureParams:
    """Normal and FPFH settings shared by the map and the scan (defaults: Baek et al. 2022, Table 3).

    Attributes
    ----------
    normal_radius_m : float
        Sphere radius of the PCA normal neighbourhood ([Baek2022 Eq. 2]), m. Table 3: 1 m.
    normal_max_nn : int
        At most this many neighbours for a normal. Table 3: 1000.
    fpfh_radius_m : float
        FPFH sphere radius r ([Baek2022 Eqs. 3-6]), m. Table 3: 2.5 m.
    fpfh_max_nn : int
        At most this many FPFH neighbours. Table 3: 1000.
    fpfh_weight : {"inverse_distance", "open3d"}
        Neighbour weight of [Baek2022 Eq. 6] (``1/ω`` as the paper, or ``1/ω²`` as Open3D).
    orientation : {"void", "none", "centroid"}
        Normal sign rule (module docstring). Not in the paper (Open3D leaves signs to the
        solver); "void" makes the descriptors independent of the scan's orientation.
    orientation_radius_m : float
        Half-edge of the cube whose centroid the "void" rule points to, m (about a drift width).
    """

    normal_radius_m: float = 1.0
    normal_max_nn: int = 1000
    fpfh_radius_m: float = 2.5
    fpfh_max_nn: int = 1000
    fpfh_weight: str = "inverse_distance"
    orientation: str = "void"
    orientation_radius_m: float = 5.0

    def __post_init__(self):
        check_positive(self.normal_radius_m, "FeatureParams.normal_radius_m")
        check_positive(self.fpfh_radius_m, "FeatureParams.fpfh_radius_m")
        check_positive(self.orientation_radius_m, "FeatureParams.orientation_radius_m")
        for name in ("normal_max_nn", "fpfh_max_nn"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 3:
                raise InputError(f"FeatureParams.{name} must be an integer >= 3, got {v!r}")
        if self.orientation not in _ORIENTATIONS:
            raise InputError(f"FeatureParams.orientation must be one of {_ORIENTATIONS}, got {self.orientation!r}")


#: Feature settings of the fast profile (Table 3 ratios at a 1 m voxel).
FAST_FEATURES = FeatureParams(normal_radius_m=2.0, fpfh_radius_m=5.0)


@dataclass(frozen=True)
class PrepareParams:
    """How the map is prepared (defaults: Baek et al. 2022, Table 3).

    Attributes
    ----------
    voxel_size_m : float or None
        Voxel-centroid downsampling edge, m (Table 3: 0.5 m). Ignored when ``octree_level``
        is given.
    octree_level : int or None
        Octree subsampling level instead (Sec. 2.2: the point nearest to each occupied cell
        centre; the paper used level 10 for its map). The cell edge is the map's bounding
        cube edge / 2^level.
    features : FeatureParams
        Normals and FPFH settings; a scan must be localized with the same ones.
    icp_voxel_size_m : float or None
        The ICP target: the paper aligns against the full-resolution global cloud
        ``Q_init`` (Sec. 2.4); minegeo keeps a voxel-centroid copy at this edge (m, default
        0.1 m, about the survey's noise level) so that the prepared file stays bounded.
        None keeps every map point. The coarse (``voxel_size_m``) cloud quantises nearest-
        neighbour distances to ~0.2 m and cannot tell a correct placement from a near miss.
    """

    voxel_size_m: float | None = 0.5
    octree_level: int | None = None
    features: FeatureParams = field(default_factory=FeatureParams)
    icp_voxel_size_m: float | None = 0.1

    def __post_init__(self):
        if self.octree_level is None:
            if self.voxel_size_m is None:
                raise InputError("give voxel_size_m or octree_level")
            check_positive(self.voxel_size_m, "PrepareParams.voxel_size_m")
        else:
            lv = self.octree_level
            if isinstance(lv, bool) or int(lv) != lv or not 1 <= lv <= 21:
                raise InputError(f"octree_level must be an integer in 1..21, got {lv!r}")
        if not isinstance(self.features, FeatureParams):
            raise InputError("PrepareParams.features must be a FeatureParams")
        if self.icp_voxel_size_m is not None:
            check_positive(self.icp_voxel_size_m, "PrepareParams.icp_voxel_size_m")

    @classmethod
    def fast(cls, **overrides) -> PrepareParams:
        """The map side of :meth:`LocalizeParams.fast` (voxel 1 m, normals 2 m, FPFH 5 m)."""
        kw = {"voxel_size_m": 1.0, "features": FAST_FEATURES}
        kw.update(overrides)
        return cls(**kw)

    def describe(self) -> str:
        """One line: the downsampling used."""
        if self.octree_level is not None:
            return f"octree level {self.octree_level}"
        return f"voxel {self.voxel_size_m:g} m"


# ----------------------------------------------------------------------------- localization
ICP_METHODS = (*_ICP_METHODS, "gicp")
#: RANSAC iteration cap of the default parameters (Table 3: 4e8; see LocalizeParams.ransac).
DEFAULT_RANSAC_MAX_ITERATIONS = 4_000_000


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
