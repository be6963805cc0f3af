"""The defaults of the parameter groups whose rules moved into field metadata (issue 31) are the values
they had before, field by field (hand-listed from the former sources; a bound that refused its own
default would fail here, at import, or both).

* ``LocalizeParams()`` holds the values of the flat parameter set it replaced (hand-listed from the
  former ``minegeo/localize/params.py``);
* the SLAM groups (floor planes, roadway noise, LiDAR-inertial, Levenberg-Marquardt, pose graph,
  survey control) and the ``minegeo intersections build`` groups (skeleton, descriptor, knowledge
  base) hold the defaults of their sources at f50f0e4; the SLAM run's own parameters
  (``SlamParams``) and the IMU noise (``ImuNoise``) those at 7be99ff.
"""

from __future__ import annotations

import dataclasses

import pytest

from minegeo.localize.params import (
    CorrelativeParams,
    FeatureParams,
    GravityParams,
    LocalizeParams,
    RivalParams,
    UncertaintyParams,
)
from minegeo.optim import LMParams
from minegeo.optim.imu import ImuNoise
from minegeo.semantic.descriptors import DescriptorParams
from minegeo.semantic.knowledge import KBParams
from minegeo.semantic.skeleton import SkeletonParams
from minegeo.slam.control import ControlParams
from minegeo.slam.inertial import InertialParams
from minegeo.slam.loops import LoopParams
from minegeo.slam.mapping import RoadwayNoiseParams
from minegeo.slam.odometry_model import OdometryParams
from minegeo.slam.pipeline import SlamParams
from minegeo.slam.planes import FloorPlaneParams
from minegeo.slam.posegraph import PoseGraphParams

#: the flat LocalizeParams defaults before the groups (minegeo/localize/params.py at d1cd455),
#: old name -> (path in the grouped LocalizeParams, value)
OLD_DEFAULTS = {
    "scan_voxel_size_m": ("scan_voxel_size_m", 0.5),
    "scan_octree_level": ("scan_octree_level", None),
    "scan_icp_voxel_size_m": ("scan_icp_voxel_size_m", 0.1),
    "ransac_runs": ("ransac_runs", 1),
    "icp_method": ("icp.method", "point_to_point"),
    "icp_max_correspondence_m": ("icp.max_correspondence_m", 0.5),
    "icp_max_iterations": ("icp.max_iterations", 30),
    "icp_relative_rmse": ("icp.relative_rmse", 1e-6),
    "icp_relative_fitness": ("icp.relative_fitness", 1e-6),
    "min_scan_points": ("min_scan_points", 30),
    "min_fitness": ("verify.min_fitness", 0.6),
    "max_inlier_rmse_m": ("verify.max_inlier_rmse_m", 0.35),
    "verify_plane_tolerance_m": ("verify.plane_tolerance_m", 0.1),
    "verify_noise_factor": ("verify.noise_factor", 4.0),
    "verify_fine_tolerance_m": ("verify.fine_tolerance_m", 0.04),
    "verify_fine_noise_factor": ("verify.fine_noise_factor", 2.0),
    "fine_ambiguity_ratio": ("ambiguity.fine_ratio", 0.8),
    "min_plane_fitness": ("verify.min_plane_fitness", 0.75),
    "ambiguity_ratio": ("ambiguity.ratio", 0.9),
    "ambiguity_distance_m": ("ambiguity.distance_m", 0.5),
    "ambiguity_angle_deg": ("ambiguity.angle_deg", 5.0),
    "degeneracy_ratio": ("verify.degeneracy_ratio", 0.01),
    "max_pending_step_m": ("verify.max_pending_step_m", 0.1),
    "icp_coarse_correspondence_m": ("icp.coarse_correspondence_m", 1.5),
    "icp_screen_max_iterations": ("icp.screen_max_iterations", 10),
    "icp_screen_max_points": ("icp.screen_max_points", 1000),
    "max_weak_displacement_95_m": ("verify.max_weak_displacement_95_m", 0.15),
    "correlative": ("correlative.mode", "fallback"),
    "correlative_confirm_below_points": ("ambiguity.small_scan_below_points", 400),
    "correlative_precheck_ratio": ("correlative.precheck_ratio", 0.7),
    "small_scan_ambiguity_ratio": ("ambiguity.small_scan_ratio", 0.8),
    "icp_polish_correspondence_m": ("icp.polish_correspondence_m", 0.25),
    "weak_axis_polish_term": ("icp.weak_axis_polish_term", True),
    "gravity_fallback_tilt_deg": ("gravity_fallback.tilt_deg", 3.0),
    # nested objects: their own defaults, with the two overrides the flat class had
    "ransac.max_iterations": ("ransac.max_iterations", 4_000_000),
    "ransac.mutual_filter": ("ransac.mutual_filter", True),
    "gravity_params.max_points": ("gravity_fallback.estimate.max_points", 5000),
}


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.mark.parametrize("old", sorted(OLD_DEFAULTS))
def test_defaults_equal_the_flat_parameters(old):
    path, value = OLD_DEFAULTS[old]
    got = _get(LocalizeParams(), path)
    assert got == value and type(got) is type(value), (old, path, got)


def test_default_objects_and_stages():
    lp = LocalizeParams()
    assert lp.features == FeatureParams() and lp.uncertainty == UncertaintyParams()
    assert lp.correlative.search == CorrelativeParams() and lp.rival == RivalParams()  # rival_search=True before
    assert lp.gravity_fallback.estimate == GravityParams(max_points=5000)  # gravity_fallback=True before
    fast = LocalizeParams.fast()
    assert fast.icp.method == "point_to_plane" and fast.scan_voxel_size_m == 1.0
    assert dataclasses.replace(fast, icp=lp.icp, scan_voxel_size_m=0.5, features=lp.features, ransac=lp.ransac) == lp
    assert LocalizeParams.paper_table3().ransac.max_iterations == 400_000_000


_LM = {"max_iterations": 500, "lambda_init": 1e-5, "relative_cost_tolerance": 1e-10, "remaining_cost_tolerance": 1e-8,
       "step_tolerance": 1e-10, "robust": "none", "robust_scale": 1.0, "damping": "identity"}
_WALL_BAND = (0.4, 2.2)
#: class -> its defaults before issue 31's rules (minegeo/slam/*.py, minegeo/optim/lm.py, minegeo/semantic/*.py
#: at f50f0e4)
FORMER_DEFAULTS = {
    FloorPlaneParams: {"radius_m": 10.0, "max_below_sensor_m": 5.0, "min_below_sensor_m": 0.3,
                       "distance_threshold_m": 0.05, "iterations": 200, "min_inliers": 50, "min_inlier_fraction": 0.1,
                       "max_tilt_deg": 20.0},
    RoadwayNoiseParams: {"slice_thickness_m": 0.5, "track_step_m": 0.5, "max_radius_m": 8.0, "max_step_m": 5.0,
                         "max_heading_change_deg": 20.0, "max_curvature_rad_per_m": 0.3, "max_grade_deg": 45.0,
                         "ransac_threshold_m": 0.08, "ransac_iterations": 100, "noise_threshold_m": 0.2,
                         "min_part_points": 8, "min_inlier_fraction": 0.3, "max_surface_tilt_deg": 30.0,
                         "vote_fraction": 1.0, "static_min_keyframes": 3, "static_radius_m": 0.2, "seed": 0},
    InertialParams: {"noise": ImuNoise(), "max_gap_s": 0.05, "gravity_window_s": 1.0, "roll_pitch_sigma_deg": 0.3,
                     "gyro_bias_sigma": 0.05, "accel_bias_sigma": 0.5, "rotation_sigma_deg": 0.05,
                     "edge_sigma_deg": 0.05, "edge_sigma_m": 0.005, "gate_tolerance_deg": 2.0, "gate_sigmas": 4.0},
    LMParams: _LM,
    PoseGraphParams: {**_LM, "indefinite_information": "gtsam"},
    ControlParams: {"mode": "graph", "model": "rigid", "class_c": 50.0, "lm": LMParams(), "drift_states": False,
                    "drift_prior": (0.02, 1e-4, 1e-4), "drift_walk": (2e-5, 1e-7, 1e-7), "drift_alpha": 0.05,
                    "snooping": True},
    SkeletonParams: {"cell_m": 0.25, "floor_cell_m": 2.0, "floor_quantile": 0.02, "wall_band_m": _WALL_BAND,
                     "max_hole_m2": 4.0, "min_component_m2": 20.0, "min_branch_m": 4.0, "merge_radius_m": 3.0,
                     "refine_radius_m": 3.0, "fill_radius_m": 1.5, "level_gap_m": 6.0},
    DescriptorParams: {"radius_m": 12.0, "n_sectors": 360, "wall_band_m": _WALL_BAND, "band_start_m": 0.2,
                       "band_m": 0.4, "n_bands": 12, "min_range_m": 1.0, "max_gap_sectors": 3, "footprint_m": 0.15},
    KBParams: {"skeleton": SkeletonParams(), "descriptor": DescriptorParams(), "cloud_radius_m": 15.0},
    # minegeo/slam/pipeline.py at 7be99ff, but the pose graph's damping: lambda diag(H) since issue 29 (with
    # lambda I the drifted ring of tests/slam/test_slam_ring.py crawled 500 iterations unconverged)
    SlamParams: {"odometry": OdometryParams(), "loops": LoopParams(), "posegraph": PoseGraphParams(damping="diagonal"),
                 "map_voxel_m": 0.1,
                 "use_planes": True, "floor": FloorPlaneParams(min_below_sensor_m=1.0, max_below_sensor_m=3.5),
                 "plane_max_angle_deg": 3.0, "plane_max_offset_m": 0.3, "plane_sigma_angle_deg": 0.5,
                 "plane_sigma_offset_m": 0.05, "plane_revisit_distance_m": 4.0, "plane_smoothing": 0.2,
                 "remove_noise": True, "noise": RoadwayNoiseParams()},
    # minegeo/optim/imu.py at 7be99ff
    ImuNoise: {"gyroscope_noise_density": 1.7e-4, "accelerometer_noise_density": 2.0e-3, "gyroscope_random_walk": 1.9e-5,
               "accelerometer_random_walk": 3.0e-3, "integration_sigma": 0.0},
}


@pytest.mark.parametrize("cls", list(FORMER_DEFAULTS), ids=[c.__name__ for c in FORMER_DEFAULTS])
def test_defaults_are_the_former_ones(cls):
    want = FORMER_DEFAULTS[cls]
    got = cls()
    assert [f.name for f in dataclasses.fields(cls)] == list(want)  # no field added, dropped or reordered
    for name, value in want.items():
        v = getattr(got, name)
        assert v == value and type(v) is type(value), (cls.__name__, name, v)
    assert cls(**want) == got  # the defaults, given explicitly, pass the rules
