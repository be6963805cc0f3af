"""Settings of the localization's optional stages: the correlative search, the rival check, the up estimate, the uncertainty.

These dataclasses are fields (or parts of fields) of :class:`~minegeo.localize.params.LocalizeParams` and are importable
from :mod:`minegeo.localize.params`.

Units: lengths in metres (``_m``), angles in degrees (``_deg``) unless named ``_rad``.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import Literal

from minegeo._params import bounded, flag, group, one_of, validate
from minegeo.errors import InputError


# ----------------------------------------------------------------------------- whole-map searches
@dataclass(frozen=True)
class CorrelativeParams:
    """Settings of the correlative 4-DOF search (see the module docstring).

    Attributes
    ----------
    cell_size_m : float
        Occupancy cell edge ``c`` (m).
    dilation_cells : int
        Occupied cells are dilated by this many cells (tolerance of a hit ~ ``c (1 + d)``).
    yaw_step_deg : float
        Heading grid step (deg); its half times the scan's half-length must stay within the
        hit tolerance (1.5 deg at 15 m: 0.39 m).
    max_scan_points : int
        Size of the scan sample scored per placement.
    early_miss_slack : float
        A placement is abandoned as soon as more than ``(1 - min_hit_fraction) i + slack`` of
        its first ``i`` sample points missed.
    max_refine_points : int
        Scan points (within ``sample_radius_m``) used by the local refinement and its score.
    sample_radius_m : float
        The sample is drawn from scan points within this horizontal distance of the reference
        point (a long-range sensor sees 100 m along a straight drift: far points would turn a
        half heading step into metres).
    n_coarse : int
        Grid placements passed to the local refinement: the best-ranked one of each
        (``distinct_m`` cell of the scan centre, ``distinct_deg`` heading bin), best first.
    screen_points : int
        Refinement cascade, first stage: every one of the ``n_coarse`` placements gets three
        Gauss-Newton steps (gates 1.5, 1.0, 0.7 m) on this many scan points and is scored.
    screen_voxel_size_m : float or None
        The first stage searches the map's ICP cloud thinned to one point per voxel of this
        edge (centroid and mean normal, :meth:`minegeo.localize.PreparedMap.screen_target`);
        None: the full ICP cloud.
    screen_grid : bool
        The first stage's Gauss-Newton steps take each sample point's map neighbour from a
        lookup grid of cells of edge ``screen_voxel_size_m`` that stores the thinned point
        nearest to every cell's centre (:func:`_kernels.build_nearest_grid`, :func:`_kernels.steps_4dof_grid`, reaching
        ``SCREEN_GATES_M[0]``), instead of a KD-tree search: an approximation within about a
        cell, its steps ~5 times faster (the stage ~2 times: its score, which ranks the
        placements, still uses the exact nearest neighbours). Needs ``screen_voxel_size_m``.
    n_refine : int
        Second stage: the best ``n_refine`` of them get ``refine_iterations`` more steps
        (gates 1.0 m → 0.5 m, linearly) on ``max_refine_points`` points and the final score.
    refine_iterations : int
        Gauss-Newton iterations of the second stage.
    refine_tolerance_m : float
        After refinement, a placement's score is the fraction of the refinement points within
        this distance of the map's tangent planes (and 0.5 m of a map point).
    min_hit_fraction : float
        Placements hitting fewer than this fraction of the sample are discarded (and their
        count is abandoned early).
    anchor_max_tilt_deg : float
        A map point is an anchor (floor) when its normal is within this angle of +z; the same
        test picks the scan's floor points.
    n_candidates : int
        Distinct placements returned.
    distinct_m, distinct_deg : float
        Two placements are distinct when the scan centre moves more than ``distinct_m`` or
        the heading differs by more than ``distinct_deg``.
    """

    cell_size_m: float = bounded(0.5, gt=0.0)
    dilation_cells: int = bounded(1, ge=0, integer=True)
    yaw_step_deg: float = bounded(3.0, gt=0.0)
    max_scan_points: int = bounded(96, ge=1, integer=True)
    early_miss_slack: float = bounded(4.0, gt=0.0)
    max_refine_points: int = bounded(200, ge=1, integer=True)
    min_hit_fraction: float = bounded(0.6, gt=0.0, le=1.0)
    anchor_max_tilt_deg: float = bounded(25.0, gt=0.0, lt=90.0)
    sample_radius_m: float = bounded(15.0, gt=0.0)
    n_coarse: int = bounded(8000, ge=1, integer=True)
    screen_points: int = bounded(64, ge=1, integer=True)
    screen_voxel_size_m: float | None = bounded(0.5, gt=0.0, optional=True)
    screen_grid: bool = flag(True)
    n_refine: int = bounded(300, ge=1, integer=True)
    refine_iterations: int = bounded(4, ge=1, integer=True)
    refine_tolerance_m: float = bounded(0.2, gt=0.0)
    n_candidates: int = bounded(24, ge=1, integer=True)
    distinct_m: float = bounded(1.5, gt=0.0)
    distinct_deg: float = bounded(10.0, gt=0.0)

    def __post_init__(self):
        validate(self)


#: When the correlative search of a levelled scan runs (``CorrelativeStageParams.mode``).
CorrelationMode = Literal["fallback", "always"]


@dataclass(frozen=True)
class CorrelativeStageParams:
    """The correlative stage of a levelled localization (``LocalizeParams.correlative``; None there: off).

    Attributes
    ----------
    mode : {"fallback", "always"}
        ``"fallback"`` (default): the whole-map candidates are added only when the RANSAC
        hypotheses do not give an ``ok`` result, or after an ``ok`` result of a small scan
        (``AmbiguityParams.small_scan_below_points``); ``"always"``: on every levelled scan.
    precheck_ratio : float
        The whole-map candidates are first scored without ICP (plane fitness of the
        feature-level scan at the refined 4-DOF placement, the same test as the
        verification); only those reaching this fraction of the best such score get ICP and
        the full verification (0 keeps all). The ambiguity test compares *refined* scores
        with ``AmbiguityParams.ratio`` (0.9): a placement below 0.7 of the best before ICP would
        have to gain ~30 % more than the best by ICP to become a rival (not seen in the
        studies; measured in docs/localization.md). Their pre-check scores are recorded.
    search : CorrelativeParams
        Its grid and refinement settings.
    """

    mode: CorrelationMode = one_of("fallback", CorrelationMode)
    precheck_ratio: float = bounded(0.7, ge=0.0, le=1.0)
    search: CorrelativeParams = group(CorrelativeParams)

    def __post_init__(self):
        validate(self)


@dataclass(frozen=True)
class RivalParams:
    """Settings of :func:`search_rivals` (module docstring).

    Attributes
    ----------
    search : CorrelativeParams
        Grid and cascade of the whole-map search (default: the correlative search's own, 0.5 m
        cells, 3° headings, 8000 bins screened, 300 refined, 24 candidates; the map structures
        are shared with it when the cell settings agree).
    precheck_ratio : float
        A rival gets the full-resolution ICP when its plane fitness before ICP (feature-level
        scan, at the search's refined placement) reaches this fraction of the chosen placement's
        (at its converged pose; the pipeline's own measurement: every rival reaching 0.9 after ICP
        had a pre-check ratio >= 0.84) ...
    precheck_matched_ratio : float
        ... or its support-matched ratio there reaches this (with ``min_common_fraction``).
    max_fine_icp : int
        Most rivals given the full-resolution ICP (closest to a test first); more is recorded
        (``n_fine_cut``) and makes ``covered`` false.
    cover_slack : float
        Witness coverage: at each stage every placement within this fraction of the stage's
        largest score below the chosen placement's own is kept ...
    cover_max_factor : float
        ... up to this factor times the stage's usual size (``n_coarse``, ``n_refine``,
        ``n_candidates``).
    translation_pivots : int
        Further pivots for translated copies (module docstring).
    translation_headings : int
        Their headings: the chosen one ± this many grid steps.
    matched_ratio : float
        Support-matched ambiguity test (module docstring): ratio of the plane agreement on the
        points the map covers at both placements.
    min_common_fraction : float
        ... applied when at least this fraction of the scan points is covered at both.
    """

    search: CorrelativeParams = group(CorrelativeParams)
    precheck_ratio: float = bounded(0.8, ge=0.0, le=1.0)
    precheck_matched_ratio: float = bounded(0.9, ge=0.0, le=1.0)
    max_fine_icp: int = bounded(8, ge=1, integer=True)
    cover_slack: float = bounded(0.15, ge=0.0, le=1.0)
    cover_max_factor: float = bounded(4.0, ge=1.0)
    translation_pivots: int = bounded(4, ge=0, integer=True)
    translation_headings: int = bounded(1, ge=0, integer=True)
    matched_ratio: float = bounded(0.95, ge=0.0, le=1.0)
    min_common_fraction: float = bounded(0.5, ge=0.0, le=1.0)

    def __post_init__(self):
        validate(self)


# ----------------------------------------------------------------------------- gravity
@dataclass(frozen=True)
class GravityParams:
    """Settings of :func:`estimate_up` (lengths in m, angles in degrees).

    Attributes
    ----------
    max_points : int
        Size of the area-uniform sample the estimate uses (all points when fewer).
    min_points : int
        Fewer input points raise :class:`~minegeo.errors.TooFewPointsError`.
    density_radius_m : float
        Radius of the neighbour count that sets each point's area weight.
    normal_radius_m, normal_max_nn : float, int
        PCA normals (hybrid search) when ``normals`` are not given.
    n_directions : int
        Axes of the normal-density grid (Fibonacci half-sphere; 2000 is ~3.2 deg apart).
    plane_band_m : float
        Slab thickness of the floor plane's support (``evidence.floor_fraction``).
    min_drift_height_m : float
        A column counts in the floor signature only when it spans at least this (a drift's height
        or width is more).
    floor_residual_scale_m : float
        Largest Tukey scale of the floor's height residuals.
    floor_max_tilt_deg : float
        Tukey scale of a floor surfel's normal tilt from up.
    wall_max_tilt_deg : float
        Largest Tukey scale of a wall surfel's normal tilt from horizontal.
    wall_min_height_m : float
        Wall surfels must be at least this far above the floor plane's support.
    min_wall_spread : float
        The walls fix ``delta_along`` only when the smallest / largest eigenvalue of their
        2x2 normal matrix reaches this (0.1: azimuths spread by ~+-20 deg, a curve or a junction).
    max_slope_deg : float
        Largest floor slope (ramp) the residual-tilt range must cover.
    n_blocks : int
        Jackknife blocks along the drift (>= 4).
    min_floor_fraction : float
        The floor slab must hold at least this fraction of the scan's area.
    min_floor_score : float
        Smallest floor signature (:func:`_column_score`) of a floor; below it: no floor.
    mode_radius_deg : float
        Cone radius of the normal-density modes (floor and wall directions) tried as up.
    min_mode_ratio : float
        A normal mode is an up candidate only when its own area (normals within
        ``mode_radius_deg``) is at least this fraction of the largest mode's.
    min_perp_ratio : float
        A normal mode is an up candidate only when the area of surfels perpendicular to it
        (within ``mode_radius_deg``) is at least this fraction of the largest such area among
        the modes: floors and walls qualify, directions through the roof's flanks do not.
    column_cell_m : float
        Column size of the floor signature.
    floor_flat_deg, roof_flank_max_deg : float
        A surfel is flat within ``floor_flat_deg`` of the candidate up, inclined up to
        ``roof_flank_max_deg`` (the roof's flanks).
    min_void_fraction : float
        At least this fraction must lie on the void side of the floor (else: a lone plane).
    ambiguity_ratio : float
        A distinct rival floor whose score reaches this fraction of the best makes the result
        ``ambiguous``.
    min_rival_angle_deg : float
        Rival floors closer than this to the chosen up are the same hypothesis.
    n_rivals : int
        Normal modes refined and tried as up candidates.
    seed : int
        Seed of the area-uniform sample (used only when the cloud has more than
        ``max_points`` points).
    """

    max_points: int = bounded(20000, ge=0, integer=True)
    min_points: int = bounded(200, ge=0, integer=True)
    density_radius_m: float = bounded(0.5, gt=0.0)
    normal_radius_m: float = bounded(0.5, gt=0.0)
    normal_max_nn: int = bounded(64, ge=0, integer=True)
    n_directions: int = bounded(2000, ge=100, integer=True)
    plane_band_m: float = bounded(0.3, gt=0.0)
    min_drift_height_m: float = bounded(2.0, gt=0.0)
    floor_residual_scale_m: float = bounded(0.6, gt=0.0)
    floor_max_tilt_deg: float = bounded(45.0, gt=0.0, lt=90.0)
    wall_max_tilt_deg: float = bounded(25.0, gt=0.0, lt=90.0)
    wall_min_height_m: float = bounded(0.4, gt=0.0)
    min_wall_spread: float = bounded(0.1, ge=0.0, le=1.0)
    max_slope_deg: float = bounded(15.0, gt=0.0, lt=90.0)
    n_blocks: int = bounded(8, ge=4, integer=True)
    min_floor_fraction: float = bounded(0.04, ge=0.0, le=1.0)
    min_floor_score: float = bounded(0.04, ge=0.0, le=1.0)
    mode_radius_deg: float = bounded(15.0, gt=0.0, lt=90.0)
    min_mode_ratio: float = bounded(0.5, ge=0.0, le=1.0)
    min_perp_ratio: float = bounded(0.5, ge=0.0, le=1.0)
    column_cell_m: float = bounded(1.0, gt=0.0)
    floor_flat_deg: float = bounded(25.0, gt=0.0, lt=90.0)
    roof_flank_max_deg: float = bounded(70.0, gt=0.0, lt=90.0)
    min_void_fraction: float = bounded(0.15, ge=0.0, le=1.0)
    ambiguity_ratio: float = bounded(0.8, ge=0.0, le=1.0)
    min_rival_angle_deg: float = bounded(30.0, gt=0.0, lt=90.0)
    n_rivals: int = bounded(8, ge=0, integer=True)
    seed: int = bounded(0, ge=0, integer=True)

    def __post_init__(self):
        validate(self)
        if self.min_points < 3 or self.max_points < max(self.min_points, 3):
            raise InputError("GravityParams: need 3 <= min_points <= max_points")


def _fallback_gravity() -> GravityParams:
    return GravityParams(max_points=5000)


@dataclass(frozen=True)
class GravityFallbackParams:
    """The gravity fallback of a failed 6-DOF scan (``LocalizeParams.gravity_fallback``; None there: off).

    Attributes
    ----------
    tilt_deg : float
        Tilt tolerance of the levelled attempt (as ``--levelled``), deg, raised to the up
        estimate's own 95 % cone when that is wider.
    estimate : GravityParams
        Settings of the up estimate (a 5 000-point area-uniform sample: 4x faster than the
        estimator's default 20 000, the same accuracy on the study scans: 0.25-0.4 deg on level
        drifts).
    """

    tilt_deg: float = bounded(3.0, gt=0.0, le=90.0)
    estimate: GravityParams = group(GravityParams, _fallback_gravity)

    def __post_init__(self):
        validate(self)


# ----------------------------------------------------------------------------- pose uncertainty
#: Pose covariance estimators (``UncertaintyParams.method``).
UncertaintyMethod = Literal["formal", "cluster", "jackknife"]
#: Available estimators.
UNCERTAINTY_METHODS = typing.get_args(UncertaintyMethod)
#: of the two-way calibration study (docs/uncertainty.md).
REGISTRATION_SIGMA_M = 8e-4


@dataclass(frozen=True)
class UncertaintyParams:
    """Parameters of :func:`pose_uncertainty`.

    Attributes
    ----------
    method : {"formal", "cluster", "jackknife"}
        ``formal``: ``σ² H⁻¹`` (independent residuals). ``cluster``: the CR1 cluster-robust
        sandwich over spatial blocks. ``jackknife`` (default): the delete-one-block jackknife
        (CR3). The last two are never below the formal one (module docstring).
    cluster_size_m : float
        Edge of the spatial blocks, m (default 4 m, about one drift width: chosen by the
        calibration study in docs/uncertainty.md; the residuals of the synthetic mine stay
        correlated over several metres of wall, and 2 m blocks under-covered).
    min_clusters : int
        Fewest blocks accepted; the edge is halved (at most 8 times) until reached.
    map_sigma_m : float
        Prior 1-σ local position error of the map itself, per axis, m, added to the translation
        block as ``σ_map² I₃`` (model term ``map_floor``; default 0: the map is taken as the
        reference).
    registration_sigma_m : float
        1-σ per axis (m) of the systematic scan-to-map registration error that the residuals do
        not reveal, added to the translation block as ``σ_reg² I₃`` (model term
        ``registration_floor``; default 0.8 mm, calibrated on the synthetic study,
        docs/uncertainty.md). 0 gives the data-only estimator (plus the other model terms).
    add_pending_step : bool
        Add ``s sᵀ`` (the remaining Gauss-Newton step to the point-to-plane optimum).
    degeneracy_ratio : float
        The covariance is not reported (None, radii inf, ``degenerate`` True) when the
        normalised constraint matrix (:func:`minegeo.registration.icp.constraint_analysis`) has
        ``λ_min / λ_max`` below this: a direction the surfaces do not constrain (sliding along a
        straight featureless drift, in-plane motion on one plane) gets no honest small number.
        Default 0.01, the pipeline's ``VerifyParams.degeneracy_ratio``.
    """

    method: UncertaintyMethod = one_of("jackknife", UncertaintyMethod)
    cluster_size_m: float = bounded(4.0, gt=0.0)
    min_clusters: int = bounded(12, ge=2, integer=True)
    map_sigma_m: float = bounded(0.0, ge=0.0)
    registration_sigma_m: float = bounded(REGISTRATION_SIGMA_M, ge=0.0)
    add_pending_step: bool = flag(True)
    degeneracy_ratio: float = bounded(1e-2, ge=0.0, lt=1.0)

    def __post_init__(self):
        validate(self)
