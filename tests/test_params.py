"""Parameter groups with their rules in field metadata (minegeo/_params.py, minegeo/localize/params.py,
minegeo/registration/ransac_params.py, the SLAM groups of minegeo/slam and minegeo/optim/lm.py, the
``minegeo intersections build`` groups of minegeo/semantic, the mast and georef groups).

* every numeric rule refuses the values on the wrong side of its bound and accepts the others
  (hypothesis: values drawn on both sides of each bound; the expected verdict comes from the bound
  as hand-listed here and in tests/params_slam.py, not from the code's metadata); the checks across fields kept as code refuse
  what they refused before;
* the command line and a ``--config`` file refuse a value with the dataclass's own message
  (exit status 2, one stderr line: the bad-input contract); every option typed by a field's rule
  (``minegeo localize``, ``slam``, ``localize-batch``, ``track``, ``mast``, ``georef``,
  ``intersections build``) is listed, its type accepts exactly what the field accepts (within the
  option's own cap, where it has one) and refuses the rest with the field's message.

The defaults (unchanged by the rules) are tested in tests/test_params_defaults.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re

import pytest
from badinput._contract import assert_user_error
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from params_slam import SLAM_BOUNDS

from minegeo._params import check_field, field_rule
from minegeo.errors import InputError
from minegeo.georef.result import GeorefParams
from minegeo.localize.params import (
    AmbiguityParams,
    CorrelativeParams,
    CorrelativeStageParams,
    FeatureParams,
    GravityFallbackParams,
    GravityParams,
    IcpParams,
    LocalizeParams,
    RivalParams,
    UncertaintyParams,
    VerifyParams,
)
from minegeo.mast.pipeline import MastParams
from minegeo.mast.segmentation import SegmentationParams
from minegeo.optim import LMParams
from minegeo.optim.imu import ImuNoise
from minegeo.registration.ransac_params import RansacParams
from minegeo.semantic.descriptors import DescriptorParams
from minegeo.semantic.knowledge import KBParams
from minegeo.semantic.recognition import RecognitionParams
from minegeo.semantic.skeleton import SkeletonParams
from minegeo.semantic.tracking import TrackParams
from minegeo.slam.control import ControlParams
from minegeo.slam.inertial import InertialParams
from minegeo.slam.loops import LoopParams
from minegeo.slam.mapping import RoadwayNoiseParams
from minegeo.slam.odometry_model import EDGE_FLOOR_FIELDS, KEYFRAME_NOISE_FIELDS, OdometryParams
from minegeo.slam.pipeline import SlamParams
from minegeo.slam.planes import FloorPlaneParams
from minegeo.slam.posegraph import PoseGraphParams

# (class, field) -> (lower op, lower bound, upper op, upper bound, integer): the documented rules
BOUNDS = {
    (IcpParams, "max_correspondence_m"): (">", 0.0, None, None, False),
    (IcpParams, "max_iterations"): (">=", 0, None, None, True),
    (IcpParams, "relative_rmse"): (">=", 0.0, None, None, False),
    (IcpParams, "relative_fitness"): (">=", 0.0, None, None, False),
    (IcpParams, "coarse_correspondence_m"): (">", 0.0, None, None, False),
    (IcpParams, "screen_max_iterations"): (">=", 1, None, None, True),
    (IcpParams, "screen_max_points"): (">=", 1, None, None, True),
    (IcpParams, "polish_correspondence_m"): (">", 0.0, None, None, False),
    (VerifyParams, "plane_tolerance_m"): (">", 0.0, None, None, False),
    (VerifyParams, "noise_factor"): (">=", 0.0, None, None, False),
    (VerifyParams, "fine_tolerance_m"): (">", 0.0, None, None, False),
    (VerifyParams, "fine_noise_factor"): (">=", 0.0, None, None, False),
    (VerifyParams, "min_fitness"): (">=", 0.0, "<=", 1.0, False),
    (VerifyParams, "max_inlier_rmse_m"): (">", 0.0, None, None, False),
    (VerifyParams, "min_plane_fitness"): (">=", 0.0, "<=", 1.0, False),
    (VerifyParams, "max_pending_step_m"): (">", 0.0, None, None, False),
    (VerifyParams, "degeneracy_ratio"): (">=", 0.0, "<=", 1.0, False),
    (VerifyParams, "max_weak_displacement_95_m"): (">", 0.0, None, None, False),
    (AmbiguityParams, "ratio"): (">=", 0.0, "<=", 1.0, False),
    (AmbiguityParams, "fine_ratio"): (">=", 0.0, "<=", 1.0, False),
    (AmbiguityParams, "distance_m"): (">", 0.0, None, None, False),
    (AmbiguityParams, "angle_deg"): (">", 0.0, None, None, False),
    (AmbiguityParams, "small_scan_ratio"): (">", 0.0, "<=", 1.0, False),
    (AmbiguityParams, "small_scan_below_points"): (">=", 0, None, None, True),
    (CorrelativeStageParams, "precheck_ratio"): (">=", 0.0, "<=", 1.0, False),
    (GravityFallbackParams, "tilt_deg"): (">", 0.0, "<=", 90.0, False),
    (LocalizeParams, "scan_voxel_size_m"): (">", 0.0, None, None, False),
    (LocalizeParams, "scan_octree_level"): (">=", 1, "<=", 21, True),
    (LocalizeParams, "scan_icp_voxel_size_m"): (">", 0.0, None, None, False),
    (LocalizeParams, "ransac_runs"): (">=", 1, None, None, True),
    (LocalizeParams, "min_scan_points"): (">=", 1, None, None, True),
    (FeatureParams, "normal_radius_m"): (">", 0.0, None, None, False),
    (FeatureParams, "normal_max_nn"): (">=", 3, None, None, True),
    (FeatureParams, "fpfh_radius_m"): (">", 0.0, None, None, False),
    (FeatureParams, "fpfh_max_nn"): (">=", 3, None, None, True),
    (FeatureParams, "orientation_radius_m"): (">", 0.0, None, None, False),
    (UncertaintyParams, "cluster_size_m"): (">", 0.0, None, None, False),
    (UncertaintyParams, "min_clusters"): (">=", 2, None, None, True),
    (UncertaintyParams, "map_sigma_m"): (">=", 0.0, None, None, False),
    (UncertaintyParams, "registration_sigma_m"): (">=", 0.0, None, None, False),
    (UncertaintyParams, "degeneracy_ratio"): (">=", 0.0, "<", 1.0, False),
    (RivalParams, "precheck_ratio"): (">=", 0.0, "<=", 1.0, False),
    (RivalParams, "precheck_matched_ratio"): (">=", 0.0, "<=", 1.0, False),
    (RivalParams, "max_fine_icp"): (">=", 1, None, None, True),
    (RivalParams, "cover_slack"): (">=", 0.0, "<=", 1.0, False),
    (RivalParams, "cover_max_factor"): (">=", 1.0, None, None, False),
    (RivalParams, "translation_pivots"): (">=", 0, None, None, True),
    (RivalParams, "translation_headings"): (">=", 0, None, None, True),
    (RivalParams, "matched_ratio"): (">=", 0.0, "<=", 1.0, False),
    (RivalParams, "min_common_fraction"): (">=", 0.0, "<=", 1.0, False),
    **{(CorrelativeParams, n): (">", 0.0, None, None, False)
       for n in ("cell_size_m", "yaw_step_deg", "early_miss_slack", "sample_radius_m", "refine_tolerance_m",
                 "screen_voxel_size_m", "distinct_m", "distinct_deg")},
    **{(CorrelativeParams, n): (">=", 1, None, None, True)
       for n in ("max_scan_points", "max_refine_points", "n_coarse", "screen_points", "n_refine", "refine_iterations",
                 "n_candidates")},
    (CorrelativeParams, "dilation_cells"): (">=", 0, None, None, True),
    (CorrelativeParams, "min_hit_fraction"): (">", 0.0, "<=", 1.0, False),
    (CorrelativeParams, "anchor_max_tilt_deg"): (">", 0.0, "<", 90.0, False),
    **{(GravityParams, n): (">", 0.0, None, None, False)
       for n in ("density_radius_m", "normal_radius_m", "plane_band_m", "min_drift_height_m", "floor_residual_scale_m",
                 "wall_min_height_m", "column_cell_m")},
    **{(GravityParams, n): (">", 0.0, "<", 90.0, False)
       for n in ("floor_max_tilt_deg", "wall_max_tilt_deg", "max_slope_deg", "min_rival_angle_deg", "floor_flat_deg",
                 "roof_flank_max_deg", "mode_radius_deg")},
    **{(GravityParams, n): (">=", 0.0, "<=", 1.0, False)
       for n in ("min_wall_spread", "min_floor_fraction", "min_void_fraction", "ambiguity_ratio", "min_floor_score",
                 "min_perp_ratio", "min_mode_ratio")},
    (GravityParams, "normal_max_nn"): (">=", 0, None, None, True),
    (GravityParams, "n_directions"): (">=", 100, None, None, True),
    (GravityParams, "n_blocks"): (">=", 4, None, None, True),
    (GravityParams, "n_rivals"): (">=", 0, None, None, True),
    (GravityParams, "seed"): (">=", 0, None, None, True),
    # RansacParams (its former __post_init__ checks, minegeo/registration/ransac_params.py at 7fb575f)
    (RansacParams, "distance_threshold_m"): (">", 0.0, None, None, False),
    (RansacParams, "edge_length_similarity"): (">=", 0.0, "<=", 1.0, False),
    (RansacParams, "normal_angle_threshold_rad"): (">=", 0.0, "<=", math.pi, False),
    (RansacParams, "max_iterations"): (">=", 1, None, None, True),
    (RansacParams, "max_validations"): (">=", 1, None, None, True),
    (RansacParams, "confidence"): (">=", 0.0, "<=", 1.0, False),
    (RansacParams, "refit_iterations"): (">=", 0, None, None, True),
    (RansacParams, "batch_size"): (">=", 1, None, None, True),
    (RansacParams, "distinct_distance_m"): (">", 0.0, None, None, False),
    (RansacParams, "distinct_angle_deg"): (">", 0.0, None, None, False),
    (RansacParams, "max_tilt_deg"): (">", 0.0, "<=", 180.0, False),
    (RansacParams, "min_iterations"): (">=", 0, None, None, True),
    (RansacParams, "n_hypotheses"): (">=", 2, None, None, True),
    # OdometryParams (its former __post_init__ checks, minegeo/slam/odometry_model.py at 7fb575f; the GICP
    # iteration cap and neighbour count with GICPParams' checks)
    **{(OdometryParams, n): (">", 0.0, None, None, False)
       for n in ("voxel_size_m", "max_correspondence_distance_m", "keyframe_distance_m", "keyframe_angle_deg",
                 "keyframe_interval_s", "sigma_floor_m", "coarse_gate_factor", "translation_observability_ratio",
                 "surface_observability_ratio", "max_speed_m_s", "max_angular_rate_deg_s", "max_acceleration_m_s2",
                 "motion_noise_m")},
    **{(OdometryParams, n): (">=", 0.0, None, None, False) for n in EDGE_FLOOR_FIELDS + KEYFRAME_NOISE_FIELDS},
    (OdometryParams, "gicp_max_iterations"): (">=", 0, None, None, True),
    (OdometryParams, "covariance_neighbours"): (">=", 3, None, None, True),
    (OdometryParams, "covariance_frames"): (">=", 1, None, None, True),
    (OdometryParams, "local_map_keyframes"): (">=", 1, None, None, True),
    (OdometryParams, "min_fitness"): (">=", 0.0, "<=", 1.0, False),
    (OdometryParams, "min_constraint_ratio"): (">=", 0.0, "<", 1.0, False),
    (OdometryParams, "deskew_iterations"): (">=", 0, "<=", 1, True),
    (OdometryParams, "start_deskew_window_s"): (">=", 0.0, None, None, False),
    # LoopParams (its former __post_init__ checks, minegeo/slam/loops.py at 7fb575f: > 0, max_candidates >= 1,
    # min_fitness in [0, 1]; the re-optimisation limits >= 0)
    **{(LoopParams, n): (">", 0.0, None, None, False)
       for n in ("min_path_gap_m", "max_distance_m", "max_rmse_m", "max_correction_m", "max_correction_deg",
                 "max_correction_per_path", "confirmed_rmse_m", "consistency_m", "consistency_deg")},
    (LoopParams, "max_candidates"): (">=", 1, None, None, True),
    (LoopParams, "min_fitness"): (">=", 0.0, "<=", 1.0, False),
    (LoopParams, "reoptimise_m"): (">=", 0.0, None, None, False),
    (LoopParams, "reoptimise_deg"): (">=", 0.0, None, None, False),
    # RecognitionParams (its former __post_init__ checks, minegeo/semantic/recognition.py at 1763486)
    (RecognitionParams, "pwcv_threshold"): (">", 0.0, "<=", 1.0, False),
    (RecognitionParams, "n_his"): (">=", 0, None, None, True),
    (RecognitionParams, "consecutive_required"): (">=", 1, None, None, True),
    (RecognitionParams, "min_wall_points"): (">=", 3, None, None, True),
    **{(RecognitionParams, n): (">", 0.0, None, None, False)
       for n in ("icp_max_distance_m", "icp_gate_m", "gate_m", "gate_yaw_deg", "crop_radius_m", "max_junction_range_m",
                 "carve_step_m", "icp_voxel_m")},
    (RecognitionParams, "cwc_margin"): (">=", 0.0, None, None, False),
    (RecognitionParams, "carve_margin_m"): (">=", 0.0, None, None, False),
    (RecognitionParams, "gate_probability"): (">", 0.0, "<", 1.0, False),
    (RecognitionParams, "icp_min_fitness"): (">=", 0.0, "<=", 1.0, False),
    # TrackParams (its former __post_init__ checks, minegeo/semantic/tracking.py at 1763486)
    **{(TrackParams, n): (">=", 0.0, None, None, False)
       for n in ("gate_drift_fraction", "online_gate_drift_fraction", "same_place_m", "online_add_range_m",
                 "online_merge_m", "revisit_min_path_m", "loop_sigma_deg", "online_icp_max_distance_m",
                 "odometry_sigma_fraction", "odometry_sigma_deg_per_m", "odometry_sigma_mps", "map_factor_after_m")},
    **{(TrackParams, n): (">", 0.0, None, None, False)
       for n in ("intersection_sigma_m", "unchecked_path_m", "map_factor_spacing_m", "map_factor_sigma_m")},
    (TrackParams, "factor_test_probability"): (">", 0.0, "<", 1.0, False),
    (TrackParams, "map_factor_min_ratio"): (">", 0.0, "<", 1.0, False),
    # MastParams and SegmentationParams (their former __post_init__ checks, minegeo/mast/pipeline.py and
    # segmentation.py at 1763486; the fields those left unchecked: counts >= 1, fractions in [0, 1], the
    # Helmert scale tolerance and the split gain > 0)
    **{(MastParams, n): (">=", 0.0, None, None, False)
       for n in ("sigma_range_m", "sigma_bearing_deg", "sigma_panel_m", "sigma_beacon_m", "edge_margin_m")},
    (MastParams, "residual_gate_sigmas"): (">", 0.0, None, None, False),
    (MastParams, "helmert_scale_tolerance"): (">", 0.0, None, None, False),
    (MastParams, "min_fit_fraction"): (">=", 0.0, "<=", 1.0, False),
    (MastParams, "ambiguity_ratio"): (">=", 0.0, "<=", 1.0, False),
    (MastParams, "confidence"): (">", 0.0, "<", 1.0, False),
    **{(MastParams, n): (">=", 1, None, None, True)
       for n in ("icp_max_iterations", "min_beacons", "min_returns_per_beacon", "max_hypotheses")},
    **{(SegmentationParams, n): (">", 0.0, None, None, False)
       for n in ("line_tolerance_sigmas", "gap_factor", "split_gain", "deflection_tolerance_deg",
                 "centroid_tolerance_fraction")},
    **{(SegmentationParams, n): (">=", 0.0, None, None, False)
       for n in ("line_tolerance_floor_m", "gap_floor_m", "length_short_fraction", "length_long_fraction",
                 "length_abs_tolerance_m")},
    (SegmentationParams, "min_points"): (">=", 3, None, None, True),
    (SegmentationParams, "n_confirm"): (">=", 1, None, None, True),
    (SegmentationParams, "refine_window"): (">=", 1, None, None, True),
    # GeorefParams (its former __post_init__ checks, minegeo/georef/result.py at 1763486)
    (GeorefParams, "blunder_alpha"): (">", 0.0, "<", 1.0, False),
    (GeorefParams, "chi2_alpha"): (">", 0.0, "<", 1.0, False),
    (GeorefParams, "sigma_local_m"): (">=", 0.0, None, None, False),
    (GeorefParams, "max_scale_deviation"): (">", 0.0, "<", 1.0, False),
    (GeorefParams, "origin_step_m"): (">", 0.0, None, None, False),
    (GeorefParams, "min_geometry_ratio"): (">=", 0.0, "<", 1.0, False),
    (GeorefParams, "max_sigma0"): (">", 1.0, None, None, False),
    **SLAM_BOUNDS,  # the SLAM groups (tests/params_slam.py)
    # SkeletonParams and DescriptorParams (their former check() methods, minegeo/semantic/skeleton.py and
    # descriptors.py at f50f0e4)
    **{(SkeletonParams, n): (">", 0.0, None, None, False)
       for n in ("cell_m", "floor_cell_m", "min_branch_m", "merge_radius_m", "refine_radius_m", "level_gap_m")},
    **{(SkeletonParams, n): (">=", 0.0, None, None, False) for n in ("max_hole_m2", "min_component_m2", "fill_radius_m")},
    (SkeletonParams, "floor_quantile"): (">=", 0.0, "<", 1.0, False),
    (DescriptorParams, "radius_m"): (">", 0.0, None, None, False),
    (DescriptorParams, "band_m"): (">", 0.0, None, None, False),
    (DescriptorParams, "min_range_m"): (">=", 0.0, None, None, False),
    (DescriptorParams, "footprint_m"): (">=", 0.0, None, None, False),
    (DescriptorParams, "n_sectors"): (">=", 8, None, None, True),
    (DescriptorParams, "n_bands"): (">=", 1, None, None, True),
    (DescriptorParams, "max_gap_sectors"): (">=", 0, None, None, True),
}
#: numeric fields whose rule is "a finite number" (any height above the floor)
FINITE = {(DescriptorParams, "band_start_m")}
#: fields whose rule is joined by a check across fields (GravityParams: 3 <= min_points <= max_points;
#: RansacParams: ransac_n >= 2, >= 3 for the rigid model; FloorPlaneParams: max_below_sensor_m >
#: min_below_sensor_m)
CROSS_CHECKED = {(GravityParams, "min_points"), (GravityParams, "max_points"), (RansacParams, "ransac_n"),
                 (FloorPlaneParams, "max_below_sensor_m"), (KBParams, "cloud_radius_m")}
#: the own rule of a cross-checked field that an option sets (the option's type checks that rule alone)
CROSS_RULES = {(KBParams, "cloud_radius_m"): (">", 0.0, None, None, False)}
#: fields that declare no rule (every value runs: a count or ratio compared with ``<``, a tuple of angles)
UNRULED = {(OdometryParams, n) for n in ("min_points", "keyframe_submap_size", "unconverged_retry_fitness",
                                         "turn_retry_yaw_deg")} | {
    *((TrackParams, n) for n in ("odometry", "recognition", "T_world_start")),  # groups that check themselves; a pose
    (MastParams, "segmentation"), (MastParams, "icp_gates_m"), (SegmentationParams, "options"),
    (GeorefParams, "convention"),
    *((ControlParams, n) for n in ("drift_states", "drift_prior", "drift_walk")),
    (SkeletonParams, "wall_band_m"), (DescriptorParams, "wall_band_m")}  # checked by the class
GROUPS = (IcpParams, VerifyParams, AmbiguityParams, CorrelativeStageParams, GravityFallbackParams, LocalizeParams,
          FeatureParams, UncertaintyParams, RivalParams, CorrelativeParams, GravityParams, RansacParams,
          OdometryParams, LoopParams, RecognitionParams, TrackParams, MastParams, SegmentationParams,
          GeorefParams, FloorPlaneParams, RoadwayNoiseParams, InertialParams, LMParams, PoseGraphParams,
          ControlParams, SkeletonParams, DescriptorParams, KBParams, SlamParams, ImuNoise)
KEYS = sorted(BOUNDS, key=lambda k: (k[0].__name__, k[1]))
_OPS = {">": lambda v, b: v > b, ">=": lambda v, b: v >= b, "<": lambda v, b: v < b, "<=": lambda v, b: v <= b}


def _expected_ok(key, v) -> bool:
    lo_op, lo, hi_op, hi, _ = BOUNDS[key] if key in BOUNDS else CROSS_RULES[key]
    return (lo_op is None or _OPS[lo_op](v, lo)) and (hi_op is None or _OPS[hi_op](v, hi))


def test_every_numeric_field_is_listed():
    """The table above covers every numeric field of the groups (a new field gets its rule checked)."""
    listed = set(BOUNDS) | CROSS_CHECKED | FINITE
    for cls in GROUPS:
        for f in dataclasses.fields(cls):
            if (cls, f.name) in UNRULED:
                with pytest.raises(KeyError, match="declares no rule"):
                    field_rule(cls, f.name)
            elif field_rule(cls, f.name)["kind"] == "number":
                assert (cls, f.name) in listed, (cls.__name__, f.name)
    with pytest.raises(InputError, match="min_points <= max_points"):
        GravityParams(min_points=2)
    with pytest.raises(InputError, match="min_points <= max_points"):
        GravityParams(max_points=199)


#: the checks across fields kept as code after ``validate`` (class, keywords, words of the message); each
#: field alone is within its rule
CROSS_CASES = [
    (FloorPlaneParams, {"max_below_sensor_m": 0.3}, "max_below_sensor_m (0.3) must be greater than min_below_sensor_m"),
    (FloorPlaneParams, {"min_below_sensor_m": 6.0}, "max_below_sensor_m (5.0) must be greater than min_below_sensor_m"),
    (ControlParams, {"model": "similarity"}, "the similarity model is a fit after SLAM (mode 'rigid')"),
    (ControlParams, {"mode": "rigid", "drift_states": "auto"}, "drift_states 'auto' needs the graph mode"),
    (KBParams, {"cloud_radius_m": 11.5}, "KBParams.cloud_radius_m (11.5 m) must be at least the descriptor radius (12 m)"),
    (SkeletonParams, {"wall_band_m": (2.2, 0.4)}, "SkeletonParams.wall_band_m must be an increasing (lo, hi) pair"),
    (SkeletonParams, {"wall_band_m": (0.4, math.nan)}, "SkeletonParams.wall_band_m must be an increasing (lo, hi) pair"),
    (DescriptorParams, {"wall_band_m": (1.0, 1.0)}, "DescriptorParams.wall_band_m must be an increasing (lo, hi) pair"),
    (DescriptorParams, {"wall_band_m": (0.4, 1.0, 2.2)}, "DescriptorParams.wall_band_m must be an increasing"),
    (DescriptorParams, {"wall_band_m": ("low", "high")}, "DescriptorParams.wall_band_m must be an increasing"),
]


@pytest.mark.parametrize("cls,kw,words", CROSS_CASES, ids=[f"{c[0].__name__}-{sorted(c[1])[0]}" for c in CROSS_CASES])
def test_checks_across_fields_are_kept(cls, kw, words):
    for name, v in kw.items():
        if (cls, name) not in UNRULED:
            check_field(cls, name, v)  # within the field's own rule: the check across fields refuses it
    with pytest.raises(InputError, match=re.escape(words)):
        cls(**kw)


@st.composite
def _near_a_bound(draw, key):
    lo_op, lo, hi_op, hi, integer = BOUNDS[key]
    bound = draw(st.sampled_from([b for b in (lo, hi) if b is not None]))
    if integer:
        return bound + draw(st.integers(-3, 3))
    step = draw(st.sampled_from([0.0, 1e-12, 1e-6, 0.25, 3.0]))
    return float(bound) + draw(st.sampled_from([-1.0, 1.0])) * step


@pytest.mark.parametrize("key", KEYS, ids=[f"{c.__name__}.{n}" for c, n in KEYS])
@settings(max_examples=30)
@given(data=st.data())
def test_validator_refuses_the_wrong_side_of_each_bound(key, data):
    cls, name = key
    v = data.draw(_near_a_bound(key))
    if _expected_ok((cls, name), v):
        obj = cls(**{name: v})
        assert getattr(obj, name) == v
    else:
        with pytest.raises(InputError) as exc:
            cls(**{name: v})
        msg = str(exc.value)
        assert msg.startswith(f"{cls.__name__}.{name} must be ") and msg.endswith(f"got {v!r}"), msg


@pytest.mark.parametrize("key", sorted(FINITE, key=lambda k: (k[0].__name__, k[1])))
@given(v=st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([True, "0.2", None]))
def test_finite_fields_take_any_finite_number(key, v):
    cls, name = key
    if isinstance(v, float) and math.isfinite(v):
        assert getattr(cls(**{name: v}), name) == v
    else:
        with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be a finite number, got"):
            cls(**{name: v})


@given(st.sampled_from(KEYS), st.sampled_from([math.nan, math.inf, -math.inf, True, "1", 2.5]))
def test_validator_refuses_non_numbers_and_wrong_kinds(key, v):
    cls, name = key
    integer = BOUNDS[key][4]
    assume(integer or not isinstance(v, float) or not math.isfinite(v))  # 2.5 is a fine float elsewhere
    with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be"):
        cls(**{name: v})


def test_optional_fields_and_stages():
    """None means off where the field says so, and only there."""
    for cls, name in ((IcpParams, "coarse_correspondence_m"), (IcpParams, "polish_correspondence_m"),
                      (VerifyParams, "fine_tolerance_m"), (LocalizeParams, "scan_icp_voxel_size_m"),
                      (RoadwayNoiseParams, "track_step_m")):
        assert getattr(cls(**{name: None}), name) is None
    for cls, name in ((IcpParams, "max_correspondence_m"), (VerifyParams, "min_fitness"), (AmbiguityParams, "ratio"),
                      (RoadwayNoiseParams, "slice_thickness_m")):
        with pytest.raises(InputError, match=f"{cls.__name__}.{name}"):
            cls(**{name: None})
    lp = LocalizeParams(correlative=None, rival=None, gravity_fallback=None)
    assert lp.correlative is None and lp.rival is None and lp.gravity_fallback is None
    for name in ("icp", "verify", "ambiguity", "uncertainty", "features", "ransac"):
        with pytest.raises(InputError, match=f"LocalizeParams.{name}"):
            LocalizeParams(**{name: None})
    with pytest.raises(InputError, match="LocalizeParams.rival"):
        LocalizeParams(rival=IcpParams())
    with pytest.raises(InputError, match="InertialParams.noise must be a ImuNoise, got None"):
        InertialParams(noise=None)
    for cls, name in ((KBParams, "skeleton"), (KBParams, "descriptor"), (RecognitionParams, "skeleton")):
        with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be a "):
            cls(**{name: None})
    with pytest.raises(InputError, match="RecognitionParams.skeleton must be a SkeletonParams"):
        RecognitionParams(skeleton=DescriptorParams())
    assert KBParams(descriptor=DescriptorParams(radius_m=20.0), cloud_radius_m=20.0).cloud_radius_m == 20.0
    for name, other in (("odometry", LoopParams()), ("loops", None), ("posegraph", LMParams()),
                        ("floor", RoadwayNoiseParams()), ("noise", None)):  # SlamParams' stages: their classes
        want = type(getattr(SlamParams(), name)).__name__
        with pytest.raises(InputError, match=f"SlamParams.{name} must be a {want}, got"):
            SlamParams(**{name: other})
    with pytest.raises(InputError, match="ControlParams.lm must be a LMParams, got None"):
        ControlParams(lm=None)
    assert ControlParams(lm=PoseGraphParams()).lm == PoseGraphParams()  # a subclass is an LMParams
    for bad in ("sometimes", None):
        with pytest.raises(InputError, match="drift_states must be True, False or 'auto'"):
            ControlParams(drift_states=bad)
    for name in ("drift_prior", "drift_walk"):
        for bad in ((1.0, 0.0, 1.0), (1.0, 1.0), (1.0, math.inf, 1.0)):
            with pytest.raises(InputError, match=f"{name} must be 3 positive numbers"):
                ControlParams(**{name: bad})
    with pytest.raises(InputError, match="scan_voxel_size_m or"):
        LocalizeParams(scan_voxel_size_m=None)
    assert LocalizeParams(scan_voxel_size_m=None, scan_octree_level=8).scan_octree_level == 8
    for cls, name, good, bad in ((IcpParams, "method", "gicp", "generalised"),
                                 (CorrelativeStageParams, "mode", "always", "off"),
                                 (UncertaintyParams, "method", "formal", "bootstrap"),
                                 (FeatureParams, "orientation", "centroid", "up"),
                                 (FeatureParams, "fpfh_weight", "open3d", "inverse_square")):
        assert getattr(cls(**{name: good}), name) == good
        with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be one of"):
            cls(**{name: bad})
    with pytest.raises(InputError, match="IcpParams.weak_axis_polish_term must be True or False"):
        IcpParams(weak_axis_polish_term=1)


def test_ransac_and_odometry_choices_flags_and_cross_checks():
    """The fixed choices, the flags, None where optional, and the checks across fields (hand-listed
    from the former __post_init__ checks)."""
    for name in ("normal_angle_threshold_rad", "max_validations", "distinct_distance_m", "max_tilt_deg"):
        assert getattr(RansacParams(**{name: None}), name) is None
    for name in ("distance_threshold_m", "max_iterations", "confidence", "min_iterations", "n_hypotheses"):
        with pytest.raises(InputError, match=f"RansacParams.{name} must be"):
            RansacParams(**{name: None})
    for cls, name, good, bad in ((RansacParams, "mode", "open3d", "opencv"),
                                 (RansacParams, "edge_pairs", "polygon", "ring"),
                                 (RansacParams, "model", "levelled", "yaw"),
                                 (OdometryParams, "frame_target", "submap", "map"),
                                 (LMParams, "robust", "cauchy", "l2"), (LMParams, "damping", "diagonal", "levenberg"),
                                 (PoseGraphParams, "robust", "huber", "tukey"),
                                 (PoseGraphParams, "indefinite_information", "refuse", "clip"),
                                 (ControlParams, "mode", "rigid", "similarity"),
                                 (ControlParams, "model", "similarity", "affine")):
        kw = {"ransac_n": 2} if good == "levelled" else {"mode": "rigid"} if good == "similarity" else {}
        assert getattr(cls(**{name: good, **kw}), name) == good
        with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be one of"):
            cls(**{name: bad})
    for cls, name in ((RansacParams, "mutual_filter"), (OdometryParams, "deskew"),
                      (OdometryParams, "edge_covariance_floor"), (ControlParams, "snooping"),
                      (SlamParams, "use_planes"), (SlamParams, "remove_noise")):
        assert getattr(cls(**{name: True}), name) is True and getattr(cls(**{name: False}), name) is False
        with pytest.raises(InputError, match=f"{cls.__name__}.{name} must be True or False"):
            cls(**{name: 1})
    # ransac_n: >= 3 for the rigid model (a sample of 2 pairs does not fix a rotation), >= 2 for the levelled one
    assert RansacParams(ransac_n=3).ransac_n == 3 and RansacParams(model="levelled", ransac_n=2).ransac_n == 2
    with pytest.raises(InputError, match=r"RansacParams.ransac_n must be a whole number >= 3 for the rigid model, got 2"):
        RansacParams(ransac_n=2)
    for bad in (1, 0, 2.0, True):
        with pytest.raises(InputError, match="RansacParams.ransac_n must be a whole number >= 2"):
            RansacParams(model="levelled", ransac_n=bad)
    with pytest.raises(InputError, match="normal-angle check is not available"):
        RansacParams(model="levelled", ransac_n=2, normal_angle_threshold_rad=0.5)


# ------------------------------------------------------------------ the CLI and a config file

# verb, option, value, (class, field, value given to the dataclass), what an off-able option says instead of
# None, the option's own rule where it takes less than the field (its message then adds "; this option takes ...")
CLI_CASES = [
    ("localize", "--ransac-runs", "0", (LocalizeParams, "ransac_runs", 0), None, None),
    ("localize", "--voxel", "-0.5", (LocalizeParams, "scan_voxel_size_m", -0.5), None, None),
    ("localize", "--octree-level", "22", (LocalizeParams, "scan_octree_level", 22), None, None),
    ("localize", "--octree-level", "0", (LocalizeParams, "scan_octree_level", 0), None, None),
    ("localize", "--polish", "-1.0", (IcpParams, "polish_correspondence_m", -1.0), "0 (off)", None),
    ("localize", "--fine-tolerance", "-0.01", (VerifyParams, "fine_tolerance_m", -0.01), "0 (off)", None),
    ("localize", "--ransac-max-iterations", "0", (RansacParams, "max_iterations", 0), None,
     "a whole number in [1, 1000000000]"),
    ("localize", "--ransac-min-iterations", "-1", (RansacParams, "min_iterations", -1), None,
     "a whole number in [0, 1000000000]"),
    ("localize", "--hypotheses", "1", (RansacParams, "n_hypotheses", 1), None, "a whole number in [2, 1000000000]"),
    ("localize", "--levelled", "0", (RansacParams, "max_tilt_deg", 0.0), None, "a finite number in (0, 90]"),
    ("localize", "--levelled", "180.5", (RansacParams, "max_tilt_deg", 180.5), None, "a finite number in (0, 90]"),
    ("slam", "--voxel", "0", (OdometryParams, "voxel_size_m", 0.0), None, None),
    ("slam", "--max-distance", "-1", (OdometryParams, "max_correspondence_distance_m", -1.0), None, None),
    ("slam", "--keyframe-distance", "0", (OdometryParams, "keyframe_distance_m", 0.0), None, None),
    ("slam", "--keyframe-angle", "-10", (OdometryParams, "keyframe_angle_deg", -10.0), None,
     "a finite number in (0, 180]"),
    ("slam", "--keyframe-interval", "-10", (OdometryParams, "keyframe_interval_s", -10.0), None, None),
    ("slam", "--deskew-iterations", "2", (OdometryParams, "deskew_iterations", 2), None, None),
    ("slam", "--deskew-iterations", "-1", (OdometryParams, "deskew_iterations", -1), None, None),
    ("slam", "--max-speed", "0", (OdometryParams, "max_speed_m_s", 0.0), None, None),
    ("slam", "--max-angular-rate", "-5", (OdometryParams, "max_angular_rate_deg_s", -5.0), None, None),
    ("slam", "--max-acceleration", "-1", (OdometryParams, "max_acceleration_m_s2", -1.0), None, None),
    ("slam", "--loop-gap", "0", (LoopParams, "min_path_gap_m", 0.0), None, None),
    ("slam", "--loop-radius", "-2", (LoopParams, "max_distance_m", -2.0), None, None),
    ("slam", "--imu-max-gap", "0", (InertialParams, "max_gap_s", 0.0), None, None),
    ("slam", "--class-constant", "0", (ControlParams, "class_c", 0.0), None, None),
    ("slam", "--map-voxel", "0", (SlamParams, "map_voxel_m", 0.0), None, None),
    ("localize-batch", "--levelled", "0", (RansacParams, "max_tilt_deg", 0.0), None, "a finite number in (0, 90]"),
    ("localize-batch", "--voxel", "-0.5", (LocalizeParams, "scan_voxel_size_m", -0.5), None, None),
    ("localize-batch", "--octree-level", "0", (LocalizeParams, "scan_octree_level", 0), None, None),
    ("track", "--voxel", "0", (OdometryParams, "voxel_size_m", 0.0), None, None),
    ("track", "--keyframe-distance", "-1", (OdometryParams, "keyframe_distance_m", -1.0), None, None),
    ("track", "--pwcv-threshold", "0", (RecognitionParams, "pwcv_threshold", 0.0), None, None),
    ("track", "--pwcv-threshold", "1.5", (RecognitionParams, "pwcv_threshold", 1.5), None, None),
    ("track", "--n-his", "-1", (RecognitionParams, "n_his", -1), None, None),
    ("track", "--consecutive", "0", (RecognitionParams, "consecutive_required", 0), None, None),
    ("track", "--icp-max-distance", "0", (RecognitionParams, "icp_max_distance_m", 0.0), None, None),
    ("track", "--gate", "-3", (RecognitionParams, "gate_m", -3.0), None, None),
    ("track", "--gate-drift", "-0.1", (TrackParams, "gate_drift_fraction", -0.1), None, None),
    ("track", "--unchecked-path", "0", (TrackParams, "unchecked_path_m", 0.0), None, None),
    ("track", "--imu-max-gap", "-0.05", (InertialParams, "max_gap_s", -0.05), None, None),
    ("mast", "--sigma-range-m", "-0.001", (MastParams, "sigma_range_m", -0.001), None, None),
    ("mast", "--sigma-bearing-deg", "-1", (MastParams, "sigma_bearing_deg", -1.0), None, None),
    ("mast", "--sigma-panel-m", "-0.5", (MastParams, "sigma_panel_m", -0.5), None, None),
    ("mast", "--sigma-beacon-m", "-0.01", (MastParams, "sigma_beacon_m", -0.01), None, None),
    ("mast", "--min-beacons", "0", (MastParams, "min_beacons", 0), None, None),
    ("georef", "--sigma-local-m", "-0.01", (GeorefParams, "sigma_local_m", -0.01), None, None),
    ("georef", "--blunder-alpha", "1", (GeorefParams, "blunder_alpha", 1.0), None, None),
    ("georef", "--max-scale-deviation", "0", (GeorefParams, "max_scale_deviation", 0.0), None, None),
    ("georef", "--max-sigma0", "1", (GeorefParams, "max_sigma0", 1.0), None, "a finite number in (1, 1000000000000]"),
    ("intersections build", "--cloud-radius", "0", (KBParams, "cloud_radius_m", 0.0), None, None),
    ("intersections build", "--floor-cell", "-1", (SkeletonParams, "floor_cell_m", -1.0), None, None),
    ("posegraph", "--max-iterations", "0", (PoseGraphParams, "max_iterations", 0), None,
     "a whole number in [1, 100000]"),
    ("posegraph", "--robust-scale", "-1", (PoseGraphParams, "robust_scale", -1.0), None, None),
]
_CLI_IDS = [f"{c[0]}{c[1]}={c[2]}" for c in CLI_CASES]

# values the field takes but the option does not (its own cap): verb, option, value, (class, field, value),
# the option's rule, the field's rule
LIMIT_CASES = [
    ("localize", "--levelled", "91", (RansacParams, "max_tilt_deg", 91.0), "a finite number in (0, 90]",
     "a finite number in (0, 180]"),
    ("localize", "--hypotheses", "1000000001", (RansacParams, "n_hypotheses", 1_000_000_001),
     "a whole number in [2, 1000000000]", "a whole number >= 2"),
    ("localize", "--ransac-max-iterations", "1000000001", (RansacParams, "max_iterations", 1_000_000_001),
     "a whole number in [1, 1000000000]", "a whole number >= 1"),
    ("localize", "--ransac-min-iterations", "1000000001", (RansacParams, "min_iterations", 1_000_000_001),
     "a whole number in [0, 1000000000]", "a whole number >= 0"),
    ("slam", "--keyframe-angle", "180.5", (OdometryParams, "keyframe_angle_deg", 180.5), "a finite number in (0, 180]",
     "a finite number > 0"),
    ("georef", "--max-sigma0", "1e13", (GeorefParams, "max_sigma0", 1e13), "a finite number in (1, 1000000000000]",
     "a finite number > 1"),
    ("posegraph", "--max-iterations", "100001", (PoseGraphParams, "max_iterations", 100001),
     "a whole number in [1, 100000]", "a whole number >= 1"),
]
_LIMIT_IDS = [f"{c[0]}{c[1]}={c[2]}" for c in LIMIT_CASES]


def _base(verb, tmp_path) -> list:
    """The arguments after the verb's first word (a subcommand's name first: ``intersections build``)."""
    if verb == "posegraph":
        return [tmp_path / "no_graph.g2o", "--out", tmp_path / "out"]
    if verb == "intersections build":
        return ["build", "--map", tmp_path / "no_map.ply", "--out", tmp_path / "out"]
    if verb == "localize":
        return ["--map", tmp_path / "no_map.ply", "--scan", tmp_path / "no_scan.ply", "--out", tmp_path / "out"]
    if verb == "localize-batch":
        return ["--map", tmp_path / "no_map.ply", "--scans", tmp_path / "no_scans", "--out", tmp_path / "out"]
    if verb == "georef":
        return ["--map", tmp_path / "no_map.ply", "--gcps", tmp_path / "no_gcps.csv", "--out", tmp_path / "geo.ply",
                "--report", tmp_path / "out"]
    if verb == "mast":
        return ["--scan", tmp_path / "no_scan.csv", "--beacons", tmp_path / "no_beacons.csv", "--out", tmp_path / "out"]
    if verb == "track":
        return ["--frames", tmp_path / "no_frames", "--db", tmp_path / "no_kb.json", "--out", tmp_path / "out"]
    return ["--frames", tmp_path / "no_frames", "--out", tmp_path / "out"]


def _dataclass_message(cls, name, v, off_text) -> str:
    """The dataclass's message for ``v``; an option cannot give None, so its "or None" is dropped
    (or reads "or 0 (off)" for an option whose 0 means None)."""
    with pytest.raises(InputError) as exc:
        cls(**{name: v})
    return str(exc.value).replace(" or None,", "," if off_text is None else f" or {off_text},")


def _want(target, off_text, limit) -> str:
    return _dataclass_message(*target, off_text) + ("" if limit is None else f"; this option takes {limit}")


def _limit_want(target, option_rule, field_rule_text) -> str:
    cls, name, v = target
    assert getattr(cls(**{name: v}), name) == v  # the library takes it
    return f"this option takes {option_rule}, got {v!r} ({cls.__name__}.{name} itself takes {field_rule_text})"


@pytest.mark.parametrize("verb,opt,text,target,off_text,limit", CLI_CASES, ids=_CLI_IDS)
def test_cli_option_refused_with_the_dataclass_message(verb, opt, text, target, off_text, limit, tmp_path, capsys):
    want = _want(target, off_text, limit)
    line = assert_user_error(verb.split()[0], [*_base(verb, tmp_path), opt, text], capsys, outputs=[tmp_path / "out"])
    assert line.endswith(f"argument {opt}: {want} (see minegeo {verb} --help)"), (line, want)


@pytest.mark.parametrize("verb,opt,text,target,off_text,limit", CLI_CASES, ids=_CLI_IDS)
def test_config_file_value_refused_with_the_dataclass_message(verb, opt, text, target, off_text, limit, tmp_path,
                                                              capsys):
    cfg = tmp_path / "bad.json"
    cfg.write_text(json.dumps({opt.lstrip("-"): target[2]}), encoding="utf-8")  # a whole number stays one
    want = _want(target, off_text, limit)
    line = assert_user_error(verb.split()[0], [*_base(verb, tmp_path), "--config", cfg], capsys, inputs=[cfg],
                             outputs=[tmp_path / "out"])
    assert f"key {opt.lstrip('-')!r}: {want}" in line, (line, want)


@pytest.mark.parametrize("verb,opt,text,target,option_rule,field_rule_text", LIMIT_CASES, ids=_LIMIT_IDS)
def test_option_cap_below_the_field_bound_is_kept(verb, opt, text, target, option_rule, field_rule_text, tmp_path,
                                                  capsys):
    """An option that deliberately takes less than its field (--levelled at most 90 deg, the counts at
    most 1e9, --keyframe-angle at most 180 deg) refuses the rest, on the command line and in a file."""
    want = _limit_want(target, option_rule, field_rule_text)
    line = assert_user_error(verb.split()[0], [*_base(verb, tmp_path), opt, text], capsys, outputs=[tmp_path / "out"])
    assert line.endswith(f"argument {opt}: {want} (see minegeo {verb} --help)"), (line, want)
    cfg = tmp_path / "bad.json"
    cfg.write_text(json.dumps({opt.lstrip("-"): target[2]}), encoding="utf-8")
    line = assert_user_error(verb.split()[0], [*_base(verb, tmp_path), "--config", cfg], capsys, inputs=[cfg],
                             outputs=[tmp_path / "out"])
    assert f"key {opt.lstrip('-')!r}: {want}" in line, (line, want)


# (verb, option) -> (class, field, the option's own upper bound or None, the value meaning "off" or None)
OPTION_FIELDS = {
    ("localize", "--ransac-runs"): (LocalizeParams, "ransac_runs", None, None),
    ("localize", "--voxel"): (LocalizeParams, "scan_voxel_size_m", None, None),
    ("localize", "--octree-level"): (LocalizeParams, "scan_octree_level", None, None),
    ("localize", "--polish"): (IcpParams, "polish_correspondence_m", None, 0.0),
    ("localize", "--fine-tolerance"): (VerifyParams, "fine_tolerance_m", None, 0.0),
    ("localize", "--ransac-max-iterations"): (RansacParams, "max_iterations", 10**9, None),
    ("localize", "--ransac-min-iterations"): (RansacParams, "min_iterations", 10**9, None),
    ("localize", "--hypotheses"): (RansacParams, "n_hypotheses", 10**9, None),
    ("localize", "--levelled"): (RansacParams, "max_tilt_deg", 90.0, None),
    ("slam", "--voxel"): (OdometryParams, "voxel_size_m", None, None),
    ("slam", "--max-distance"): (OdometryParams, "max_correspondence_distance_m", None, None),
    ("slam", "--keyframe-distance"): (OdometryParams, "keyframe_distance_m", None, None),
    ("slam", "--keyframe-angle"): (OdometryParams, "keyframe_angle_deg", 180.0, None),
    ("slam", "--keyframe-interval"): (OdometryParams, "keyframe_interval_s", None, None),
    ("slam", "--deskew-iterations"): (OdometryParams, "deskew_iterations", None, None),
    ("slam", "--max-speed"): (OdometryParams, "max_speed_m_s", None, None),
    ("slam", "--max-angular-rate"): (OdometryParams, "max_angular_rate_deg_s", None, None),
    ("slam", "--max-acceleration"): (OdometryParams, "max_acceleration_m_s2", None, None),
    ("slam", "--loop-gap"): (LoopParams, "min_path_gap_m", None, None),
    ("slam", "--loop-radius"): (LoopParams, "max_distance_m", None, None),
    ("slam", "--imu-max-gap"): (InertialParams, "max_gap_s", None, None),
    ("slam", "--class-constant"): (ControlParams, "class_c", None, None),
    ("slam", "--map-voxel"): (SlamParams, "map_voxel_m", None, None),
    ("localize-batch", "--levelled"): (RansacParams, "max_tilt_deg", 90.0, None),
    ("localize-batch", "--voxel"): (LocalizeParams, "scan_voxel_size_m", None, None),
    ("localize-batch", "--octree-level"): (LocalizeParams, "scan_octree_level", None, None),
    ("track", "--voxel"): (OdometryParams, "voxel_size_m", None, None),
    ("track", "--keyframe-distance"): (OdometryParams, "keyframe_distance_m", None, None),
    ("track", "--pwcv-threshold"): (RecognitionParams, "pwcv_threshold", None, None),
    ("track", "--n-his"): (RecognitionParams, "n_his", None, None),
    ("track", "--consecutive"): (RecognitionParams, "consecutive_required", None, None),
    ("track", "--icp-max-distance"): (RecognitionParams, "icp_max_distance_m", None, None),
    ("track", "--gate"): (RecognitionParams, "gate_m", None, None),
    ("track", "--gate-drift"): (TrackParams, "gate_drift_fraction", None, None),
    ("track", "--unchecked-path"): (TrackParams, "unchecked_path_m", None, None),
    ("track", "--imu-max-gap"): (InertialParams, "max_gap_s", None, None),
    ("mast", "--sigma-range-m"): (MastParams, "sigma_range_m", None, None),
    ("mast", "--sigma-bearing-deg"): (MastParams, "sigma_bearing_deg", None, None),
    ("mast", "--sigma-panel-m"): (MastParams, "sigma_panel_m", None, None),
    ("mast", "--sigma-beacon-m"): (MastParams, "sigma_beacon_m", None, None),
    ("mast", "--min-beacons"): (MastParams, "min_beacons", None, None),
    ("georef", "--sigma-local-m"): (GeorefParams, "sigma_local_m", None, None),
    ("georef", "--blunder-alpha"): (GeorefParams, "blunder_alpha", None, None),
    ("georef", "--max-scale-deviation"): (GeorefParams, "max_scale_deviation", None, None),
    ("georef", "--max-sigma0"): (GeorefParams, "max_sigma0", 1e12, None),
    ("intersections build", "--cloud-radius"): (KBParams, "cloud_radius_m", None, None),
    ("intersections build", "--floor-cell"): (SkeletonParams, "floor_cell_m", None, None),
    ("posegraph", "--max-iterations"): (PoseGraphParams, "max_iterations", 100000, None),
    ("posegraph", "--robust-scale"): (PoseGraphParams, "robust_scale", None, None),
}
OPTIONS = sorted(OPTION_FIELDS)


def _verb_actions(verb) -> dict:
    from minegeo.cli import build_parser

    *names, = verb.split()  # "intersections build": the subcommand's parser
    parser = build_parser(names[:1])
    for name in names:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    return {s: a for a in parser._actions for s in a.option_strings}


def test_every_option_typed_by_a_field_rule_is_listed():
    """Each option whose type is a field's rule (arg_type) is in OPTION_FIELDS and is exercised end to
    end by CLI_CASES; the options the task names are such options."""
    from minegeo._params import arg_type

    rule_type = type(arg_type(RansacParams, "max_iterations"))
    for verb in ("localize", "slam", "localize-batch", "track", "mast", "georef", "intersections build",
                 "posegraph"):
        typed = {o for o, a in _verb_actions(verb).items() if o.startswith("--") and isinstance(a.type, rule_type)}
        assert typed == {o for v, o in OPTION_FIELDS if v == verb}, verb
    assert {(c[0], c[1]) for c in CLI_CASES} == set(OPTION_FIELDS)


@st.composite
def _near_an_option_bound(draw, key):
    cls, name, cap, off = OPTION_FIELDS[key]
    lo_op, lo, hi_op, hi, integer = BOUNDS.get((cls, name)) or CROSS_RULES[(cls, name)]
    bound = draw(st.sampled_from([b for b in (lo, hi, cap, off) if b is not None]))
    if integer:
        return int(bound) + draw(st.integers(-3, 3))
    step = draw(st.sampled_from([0.0, 1e-12, 1e-6, 0.25, 3.0]))
    return float(bound) + draw(st.sampled_from([-1.0, 1.0])) * step


@pytest.mark.parametrize("key", OPTIONS, ids=[f"{v}{o}" for v, o in OPTIONS])
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_option_type_takes_what_the_field_takes(key, data):
    """Near each bound of the field and of the option's own cap: the option's type accepts a value iff
    the field does (and the cap allows it, or it is the option's "off" value); a refused value gets
    the field's message (expected verdicts from the hand-listed BOUNDS)."""
    cls, name, cap, off = OPTION_FIELDS[key]
    v = data.draw(_near_an_option_bound(key))
    parse = _verb_actions(key[0])[key[1]].type
    field_ok = _expected_ok((cls, name), v)
    text = str(v) if isinstance(v, int) else repr(v)
    if (off is not None and v == off) or (field_ok and (cap is None or v <= cap)):
        got = parse(text)
        assert got == v and type(got) is type(v)
    else:
        with pytest.raises(argparse.ArgumentTypeError) as exc:
            parse(text)
        msg = str(exc.value)
        if field_ok:
            assert msg.startswith("this option takes ") and f"got {v!r} ({cls.__name__}.{name} itself" in msg, msg
        else:
            assert msg.startswith(_dataclass_message(cls, name, v, None if off is None else "0 (off)")), msg


def test_cli_zero_means_off_and_values_reach_the_groups():
    import argparse

    from minegeo.cli import localize as C

    ap = argparse.ArgumentParser()
    C.add_arguments(ap)
    base = ["--map", "m", "--scan", "s", "--out", "o"]
    lp = C.params_from_args(ap.parse_args([*base, "--polish", "0", "--fine-tolerance", "0", "--ransac-runs", "3",
                                           "--no-gravity-fallback"]))[1]
    assert lp.icp.polish_correspondence_m is None and lp.verify.fine_tolerance_m is None
    assert lp.ransac_runs == 3 and lp.gravity_fallback is None
    lp = C.params_from_args(ap.parse_args([*base, "--polish", "0.3", "--fine-tolerance", "0.05", "--levelled", "3",
                                           "--correlative", "off"]))[1]
    assert lp.icp.polish_correspondence_m == 0.3 and lp.verify.fine_tolerance_m == 0.05 and lp.correlative is None
    # the CLI's fixed choices are the dataclass Literals (plus "off" = None)
    assert C.ICP_CHOICES == tuple(field_rule(IcpParams, "method")["choices"])
    assert C.CORRELATIVE_CHOICES == (*field_rule(CorrelativeStageParams, "mode")["choices"], "off")
