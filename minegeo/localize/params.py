"""Parameters of map preparation and scan localization.

Every settings dataclass of :mod:`minegeo.localize` that :func:`~minegeo.localize.localize_scan`
or :func:`~minegeo.localize.prepare_map` takes is importable from here (the modules that use them
import them from here; their old module paths still export them): the feature, preparation and
localization settings are defined here, those of the optional stages (correlative search, rival
check, up estimate, uncertainty) in :mod:`minegeo.localize.params_stages`. Keeping them apart from the code that
uses them breaks the import circle between the pipeline and the prepared map (a prepared map
builds the search structures that a :class:`LocalizeParams` will need).

:class:`LocalizeParams` is made of small frozen groups: :class:`IcpParams`, :class:`VerifyParams`,
:class:`AmbiguityParams`, :class:`~minegeo.localize.params_stages.UncertaintyParams`, and the
optional stages (:class:`~minegeo.localize.params_stages.CorrelativeStageParams`,
:class:`~minegeo.localize.params_stages.RivalParams`,
:class:`~minegeo.localize.params_stages.GravityFallbackParams`), each ``None`` when the stage is
off. Their fields declare their bounds and modes once, in the field metadata
(:mod:`minegeo._params`): the same rule checks the dataclass, the command-line option that sets
the field (``minegeo localize --ransac-runs``, ``--voxel``, ``--octree-level``, ``--polish``,
``--fine-tolerance``) and the same key of a ``--config`` file.

Units: lengths in metres (``_m``), angles in degrees (``_deg``) unless named ``_rad``.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, field
from typing import Literal

from minegeo._params import bounded, flag, group, one_of, validate
from minegeo._validate import check_positive
from minegeo.errors import InputError
from minegeo.localize.params_stages import (
    REGISTRATION_SIGMA_M,
    UNCERTAINTY_METHODS,
    CorrelationMode,
    CorrelativeParams,
    CorrelativeStageParams,
    GravityFallbackParams,
    GravityParams,
    RivalParams,
    UncertaintyParams,
)
from minegeo.registration.icp import METHODS as _ICP_METHODS
from minegeo.registration.ransac import RansacParams

__all__ = ["FeatureParams", "FAST_FEATURES", "PrepareParams", "CorrelativeParams", "CorrelativeStageParams",
           "CorrelationMode", "RivalParams", "GravityParams", "GravityFallbackParams", "UncertaintyParams",
           "IcpParams", "IcpMethod", "VerifyParams", "AmbiguityParams", "LocalizeParams", "UNCERTAINTY_METHODS",
           "REGISTRATION_SIGMA_M", "DEFAULT_RANSAC_MAX_ITERATIONS", "ICP_METHODS"]

#: Normal sign rules (``FeatureParams.orientation``).
NormalOrientation = Literal["void", "none", "centroid"]
#: FPFH neighbour weights (``FeatureParams.fpfh_weight``, :class:`minegeo.features.FPFHParams`).
FpfhWeight = Literal["inverse_distance", "open3d"]

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

    normal_radius_m: float = bounded(1.0, gt=0.0)
    normal_max_nn: int = bounded(1000, ge=3, integer=True)
    fpfh_radius_m: float = bounded(2.5, gt=0.0)
    fpfh_max_nn: int = bounded(1000, ge=3, integer=True)
    fpfh_weight: FpfhWeight = one_of("inverse_distance", FpfhWeight)
    orientation: NormalOrientation = one_of("void", NormalOrientation)
    orientation_radius_m: float = bounded(5.0, gt=0.0)

    def __post_init__(self):
        validate(self)


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
#: ICP variants of the localization (``IcpParams.method``).
IcpMethod = Literal["point_to_point", "point_to_plane", "gicp"]
ICP_METHODS = typing.get_args(IcpMethod)
assert ICP_METHODS == (*_ICP_METHODS, "gicp")
#: RANSAC iteration cap of the default parameters (Table 3: 4e8; see LocalizeParams.ransac).
DEFAULT_RANSAC_MAX_ITERATIONS = 4_000_000


@dataclass(frozen=True)
class IcpParams:
    """The ICP refinement of every hypothesis, and the polish of the chosen one.

    Attributes
    ----------
    method : {"point_to_point", "point_to_plane", "gicp"}
        ICP variant (paper: point-to-point). ``"gicp"``: Generalized-ICP
        (:func:`minegeo.registration.register_gicp`, Segal 2009 / [Ren2019 Eqs. 1-6]) against
        plane covariances of the map's ICP cloud built once from its stored normals.
    max_correspondence_m : float
        ICP pair gate, m (Table 3: 0.5 m).
    max_iterations : int
        Iteration cap (Table 3: 30).
    relative_rmse : float
        Convergence threshold on the RMSE change, m (Table 3: 1e-6).
    relative_fitness : float
        Convergence threshold on the fitness change (Open3D default 1e-6).
    coarse_correspondence_m : float or None
        Gate (m) of a coarse point-to-plane ICP of the feature-level scan run on every RANSAC
        hypothesis before the paper's ICP (minegeo addition: RANSAC poses from 0.5-1 m voxels
        can sit ~1 m from the answer, outside the 0.5 m gate). None skips it.
    screen_max_iterations : int
        Iteration cap of the screening ICP (minegeo addition, ``point_to_point`` and
        ``point_to_plane``): when several hypotheses compete, each first gets at most this
        many ICP iterations on the feature-level scan, and only those whose plane fitness is
        then within the ambiguity ratio of the best get the full-resolution ICP (capped at
        ``max_iterations``). The screening only ranks; in a drift the ICP slides slowly
        along the axis, which barely changes the score after ~10 iterations (measured: the same
        decisions on the benchmark's 20 m scans, and 0.45 s less on the curve flash scan's 25
        candidates). Not applied to a small scan (``AmbiguityParams.small_scan_below_points``):
        its rivals are judged on the narrower ``AmbiguityParams.small_scan_ratio`` margin, and a
        capped screen once left out a rival that the full ICP puts at 0.815 of the best.
    screen_max_points : int
        The screening ICP and its score use at most this many feature-level scan points,
        evenly spaced in the downsampled cloud's order (a fine voxel or a deep octree level
        gives thousands; 1000 points measure a plane fitness to about ±1.3 %, well inside the
        ambiguity ratio's margin). Not applied to a small scan either.
    polish_correspondence_m : float or None
        After the decision, the chosen pose gets a point-to-plane ICP of the ICP-level scan
        with this tighter gate (m; None = off), and the final pose and covariance come from
        it (a minegeo addition; the gate used is ``max(this, 3 σ_surf)``). With the 0.5 m gate,
        scan points whose surface the map does not hold (the shadowed inner wall of a bend) pair
        with other surfaces and bias the point-to-plane fit by centimetres to ~0.1 m; a gate of a
        few scan-noise sigmas keeps only surface pairs. The chosen hypothesis and its
        verification scores are not changed (the covariance-based checks, weak-direction
        displacement and pending step, use the polished fit); a polish moving the scan by more
        than ``VerifyParams.max_pending_step_m`` is not applied (warning).
    weak_axis_polish_term : bool
        When the polish was applied and the final pairs constrain some direction weakly
        (normalised constraint eigenvalue ratio below ``UncertaintyParams.degeneracy_ratio``,
        e.g. a straight drift), add ``δ δᵀ`` to the pose covariance, with ``δ`` = the polish's
        pose shift ``(ω, t)`` about the scan origin. Along such a direction the estimate
        depends on which pairs the gate admits, a bias that every jackknife block shares and
        so does not show in their spread; the change between the 0.5 m and the polish gate
        measures that sensitivity (minegeo addition, calibrated in docs/uncertainty.md).
    """

    method: IcpMethod = one_of("point_to_point", IcpMethod)
    max_correspondence_m: float = bounded(0.5, gt=0.0)
    max_iterations: int = bounded(30, ge=0, integer=True)
    relative_rmse: float = bounded(1e-6, ge=0.0)
    relative_fitness: float = bounded(1e-6, ge=0.0)
    coarse_correspondence_m: float | None = bounded(1.5, gt=0.0, optional=True)
    screen_max_iterations: int = bounded(10, ge=1, integer=True)
    screen_max_points: int = bounded(1000, ge=1, integer=True)
    polish_correspondence_m: float | None = bounded(0.25, gt=0.0, optional=True)
    weak_axis_polish_term: bool = flag(True)

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class VerifyParams:
    """How a refined placement is scored and when it is accepted.

    Attributes
    ----------
    plane_tolerance_m : float
        Plane-distance tolerance of the verification score (m): hypotheses are ranked by the
        fraction of scan points within the ICP gate of the map *and* within this distance of
        the map's tangent plane (see :mod:`minegeo.localize.verification`).
    noise_factor : float
        The plane tolerance used is ``max(plane_tolerance_m, noise_factor · σ_surf)`` with
        ``σ_surf`` the scan's own surface noise (median over scan points of the RMS distance of
        their 16 nearest ICP-source neighbours from the neighbourhood's PCA plane,
        ``sqrt(λ_min)`` of [Baek2022 Eq. 2]'s covariance): a noisier sensor gets a wider band so
        its correct placements are not refused; the measure does not depend on any placement,
        so a wrong placement gains nothing. 0 disables it.
    fine_tolerance_m : float or None
        Tolerance of the *fine* agreement (minegeo addition): the fraction of scan points within
        ``tol_fine = min(tol, max(fine_tolerance_m, fine_noise_factor · σ_surf))`` of the map's
        tangent planes. On smooth (shotcrete-like) walls every drift of the same cross-section
        agrees with the scan within 0.1 m, so the plane fitness cannot tell places apart; the
        bumps that do (a few cm) show at this tolerance (measured on the 0.05 m study mine:
        truth 0.79 against 0.37-0.49 for other drifts at 0.04 m, 0.97 against 0.86-0.89 at
        0.1 m). Hypotheses are ranked by it, and a rival is ``ambiguous`` only when it reaches
        the ambiguity ratio at **both** tolerances (an exact copy does, so twins stay ambiguous;
        a chosen placement that is beaten at the fine level by a rival still is). None: off
        (the plane fitness alone).
    fine_noise_factor : float
        See ``fine_tolerance_m`` (a noisier sensor gets a wider fine band).
    min_fitness : float
        ``failed`` below this final ICP fitness (fraction of downsampled scan points).
    max_inlier_rmse_m : float
        ``failed`` above this final ICP inlier RMSE, m.
    min_plane_fitness : float
        ``failed`` below this verification score of the chosen placement.
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
    """

    plane_tolerance_m: float = bounded(0.1, gt=0.0)
    noise_factor: float = bounded(4.0, ge=0.0)
    fine_tolerance_m: float | None = bounded(0.04, gt=0.0, optional=True)
    fine_noise_factor: float = bounded(2.0, ge=0.0)
    min_fitness: float = bounded(0.6, ge=0.0, le=1.0)
    max_inlier_rmse_m: float = bounded(0.35, gt=0.0)
    min_plane_fitness: float = bounded(0.75, ge=0.0, le=1.0)
    max_pending_step_m: float = bounded(0.1, gt=0.0)
    degeneracy_ratio: float = bounded(0.01, ge=0.0, le=1.0)
    max_weak_displacement_95_m: float = bounded(0.15, gt=0.0)

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class AmbiguityParams:
    """When another verified placement makes the result ``ambiguous``.

    Attributes
    ----------
    ratio : float
        A distinct hypothesis with verification score >= ratio × best makes the result ``ambiguous``.
    fine_ratio : float
        The ratio a rival must reach at the fine tolerance (``VerifyParams.fine_tolerance_m``;
        scaled by ``small_scan_ratio / ratio`` for a small scan). Lower than ``ratio``: the fine
        level is noisier; measured 0.90 for an exact twin that the map covers differently on its
        two levels and 0.55-0.65 for other drifts of the smooth-walled study mine.
    distance_m, angle_deg : float
        Two refined hypotheses are distinct if they place the scan centroid farther apart
        than ``distance_m`` (m) or their rotations differ by more than ``angle_deg`` (deg).
    small_scan_ratio : float
        Used instead of ``ratio`` (for the ICP short list and the rival test) for a small scan
        (fewer feature-level points than ``small_scan_below_points``): a small scan carries
        little shape, so it is ``ok`` only when no other verified placement reaches this fraction
        of its plane fitness. Measured: a 10 m railings scan (373 feature points) whose true
        place the search did not propose was placed 219 m away with plane fitness 0.813 against
        a rival at 0.683 (0.84); the 20 m scans' correct answers had no rival above 0.70 of
        theirs (docs/localization.md).
    small_scan_below_points : int
        A scan with fewer feature-level points than this is *small* (1 m voxels: roughly its
        surface in m², e.g. a 10 m handheld flash scan): it gets ``small_scan_ratio``, no ICP
        screening, and in the correlative ``"fallback"`` mode the whole-map search also runs
        after an ``ok`` result (the one wrong ``ok`` seen in the studies was such a scan, for
        which RANSAC had proposed only the wrong place; the whole-map candidates then either
        confirm it or make it ``ambiguous``).
    """

    ratio: float = bounded(0.9, ge=0.0, le=1.0)
    fine_ratio: float = bounded(0.8, ge=0.0, le=1.0)
    distance_m: float = bounded(0.5, gt=0.0)
    angle_deg: float = bounded(5.0, gt=0.0)
    small_scan_ratio: float = bounded(0.8, gt=0.0, le=1.0)
    small_scan_below_points: int = bounded(400, ge=0, integer=True)

    def __post_init__(self):
        validate(self)

    def ratios(self, small_scan: bool) -> tuple[float, float]:
        """``(ratio, fine_ratio)`` a rival must reach at the plane and the fine tolerance: the small
        scan's ratio for a small scan, the fine ratio scaled the same way."""
        amb = float(self.small_scan_ratio) if small_scan else float(self.ratio)
        return amb, float(self.fine_ratio) * amb / float(self.ratio)


def _default_ransac() -> RansacParams:
    return RansacParams(max_iterations=DEFAULT_RANSAC_MAX_ITERATIONS, mutual_filter=True)


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
    min_scan_points : int
        Fewer downsampled scan points than this is a :class:`TooFewPointsError`.
    icp : IcpParams
        The ICP of every hypothesis (Table 3: point-to-point, 0.5 m gate, 30 iterations) and
        minegeo's coarse, screening and polish passes.
    verify : VerifyParams
        Verification scores and the acceptance thresholds of a placement.
    ambiguity : AmbiguityParams
        When a distinct verified placement makes the result ``ambiguous``.
    uncertainty : UncertaintyParams
        Pose covariance estimator (:mod:`minegeo.localize.uncertainty`; default the
        delete-one-block jackknife over 4 m blocks, calibrated in docs/uncertainty.md).
    correlative : CorrelativeStageParams or None
        Levelled scans only (``ransac.model == "levelled"``): the correlative 4-DOF search of
        the whole map (:mod:`minegeo.localize.correlative`, a minegeo addition) adds its best
        distinct placements to RANSAC's hypotheses, only when the RANSAC hypotheses do not give
        an ``ok`` result (``mode="fallback"``, default: the fast path stays as fast) or always.
        Extra candidates can never turn a true ambiguity into ``ok``: the rival that made it
        ambiguous is still verified. Its candidates go through the same ICP, verification and
        ambiguity test. None: no correlative search.
    rival : RivalParams or None
        Before a result is ``ok``, search the whole map for another placement that explains
        the scan nearly as well (:mod:`minegeo.localize.rivals`, a minegeo addition: mines
        repeat their level layouts, and an exact copy of a drift that RANSAC did not propose
        would make a coin flip ``ok``): the exhaustive correlative search at the chosen
        placement's attitude (its tilt; every floor anchor × every heading of the 3° grid
        aligned with the chosen heading), its distinct candidates refined by the same ICP and
        verified by the same plane fitness; a rival reaching the ambiguity ratio (the small-scan
        one for a small scan), or ``RivalParams.matched_ratio`` of the chosen placement's plane
        agreement on the scan points the map covers at both places (a survey map covers two
        copies of a drift differently), makes the result ``ambiguous`` with both placements
        listed. The best rival, its distance and the margin (chosen / rival plane fitness) are
        recorded (``LocalizationResult.rival_search``). Runs for 6-DOF and levelled scans alike,
        only when the result would otherwise be ``ok``. None: no search, no record.
    gravity_fallback : GravityFallbackParams or None
        6-DOF scans only (``ransac.model == "rigid"``, a minegeo addition): when the 6-DOF
        pipeline finds no placement (``failed``), estimate the scan's up direction from its own
        geometry (:func:`minegeo.localize.gravity.estimate_up`: floor, roof, walls), level the
        scan with it and run the levelled pipeline (2-point heading + translation RANSAC and the
        whole-map correlative search) once more; its result (``ok`` or ``ambiguous``) replaces
        the failure, in the original scan frame. Only when the estimate is ``ok``. A scan on a
        ramp is levelled to its floor, off by the slope about the drift's cross axis, which
        nothing in a straight scan shows: the levelled attempt is repeated with the up
        direction tilted about that axis by 0, ±2t, ±4t, ... degrees (``t`` the tilt tolerance,
        :class:`GravityFallbackParams`) within the estimate's ``tilt_range_deg`` (±15.5° by
        default), first non-failed wins. None: a failed 6-DOF scan stays failed.
    """

    scan_voxel_size_m: float | None = bounded(0.5, gt=0.0, optional=True)
    scan_octree_level: int | None = bounded(None, ge=1, le=21, integer=True, optional=True)
    scan_icp_voxel_size_m: float | None = bounded(0.1, gt=0.0, optional=True)
    features: FeatureParams = group(FeatureParams)
    ransac: RansacParams = group(RansacParams, _default_ransac)
    ransac_runs: int = bounded(1, ge=1, integer=True)
    min_scan_points: int = bounded(30, ge=1, integer=True)
    icp: IcpParams = group(IcpParams)
    verify: VerifyParams = group(VerifyParams)
    ambiguity: AmbiguityParams = group(AmbiguityParams)
    uncertainty: UncertaintyParams = group(UncertaintyParams)
    correlative: CorrelativeStageParams | None = group(CorrelativeStageParams, optional=True)
    rival: RivalParams | None = group(RivalParams, optional=True)
    gravity_fallback: GravityFallbackParams | None = group(GravityFallbackParams, optional=True)

    def __post_init__(self):
        validate(self)
        if self.scan_octree_level is None and self.scan_voxel_size_m is None:
            raise InputError("give LocalizeParams.scan_voxel_size_m or LocalizeParams.scan_octree_level")

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
              "icp": IcpParams(method="point_to_plane")}
        kw.update(overrides)
        return cls(**kw)

    def describe_downsampling(self) -> str:
        """One line: the scan's downsampling (octree level or voxel edge)."""
        if self.scan_octree_level is not None:
            return f"octree level {self.scan_octree_level}"
        return f"voxel {self.scan_voxel_size_m:g} m"
