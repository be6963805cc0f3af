"""The rules of the SLAM parameter groups as hand-listed bounds (a table of tests/test_params.py, kept here
to hold that module under 800 lines): (class, field) -> (lower op, lower bound, upper op, upper bound,
integer), each from the class's former checks (the commit named with it)."""

from __future__ import annotations

from minegeo.optim import LMParams
from minegeo.optim.imu import ImuNoise
from minegeo.slam.control import ControlParams
from minegeo.slam.inertial import InertialParams
from minegeo.slam.mapping import RoadwayNoiseParams
from minegeo.slam.pipeline import SlamParams
from minegeo.slam.planes import FloorPlaneParams
from minegeo.slam.posegraph import PoseGraphParams

SLAM_BOUNDS = {
    # FloorPlaneParams (its former __post_init__ check, minegeo/slam/planes.py at f50f0e4; max_below_sensor_m
    # > min_below_sensor_m is the check across fields)
    (FloorPlaneParams, "radius_m"): (">", 0.0, None, None, False),
    (FloorPlaneParams, "min_below_sensor_m"): (">=", 0.0, None, None, False),
    (FloorPlaneParams, "distance_threshold_m"): (">", 0.0, None, None, False),
    (FloorPlaneParams, "iterations"): (">=", 1, None, None, True),
    (FloorPlaneParams, "min_inliers"): (">=", 3, None, None, True),
    (FloorPlaneParams, "min_inlier_fraction"): (">=", 0.0, "<=", 1.0, False),
    (FloorPlaneParams, "max_tilt_deg"): (">=", 0.0, "<", 90.0, False),
    # RoadwayNoiseParams (its former __post_init__ checks, minegeo/slam/mapping.py at f50f0e4, plus the angles
    # left open: a heading change > 0, a grade and a surface tilt in (0, 90]; the RNG seed >= 0)
    **{(RoadwayNoiseParams, n): (">", 0.0, None, None, False)
       for n in ("slice_thickness_m", "track_step_m", "max_radius_m", "max_step_m", "max_heading_change_deg",
                 "max_curvature_rad_per_m", "ransac_threshold_m", "noise_threshold_m", "static_radius_m")},
    (RoadwayNoiseParams, "max_grade_deg"): (">", 0.0, "<=", 90.0, False),
    (RoadwayNoiseParams, "max_surface_tilt_deg"): (">", 0.0, "<=", 90.0, False),
    (RoadwayNoiseParams, "ransac_iterations"): (">=", 1, None, None, True),
    (RoadwayNoiseParams, "min_part_points"): (">=", 3, None, None, True),
    (RoadwayNoiseParams, "min_inlier_fraction"): (">=", 0.0, "<=", 1.0, False),
    (RoadwayNoiseParams, "vote_fraction"): (">", 0.0, "<=", 1.0, False),
    (RoadwayNoiseParams, "static_min_keyframes"): (">=", 0, None, None, True),
    (RoadwayNoiseParams, "seed"): (">=", 0, None, None, True),
    # InertialParams (its former __post_init__ check, minegeo/slam/inertial.py at f50f0e4: each a finite number > 0)
    **{(InertialParams, n): (">", 0.0, None, None, False)
       for n in ("max_gap_s", "gravity_window_s", "roll_pitch_sigma_deg", "gyro_bias_sigma", "accel_bias_sigma",
                 "rotation_sigma_deg", "edge_sigma_deg", "edge_sigma_m", "gate_tolerance_deg", "gate_sigmas")},
    # LMParams and its subclass PoseGraphParams (LMParams' former __post_init__ checks, minegeo/optim/lm.py at
    # f50f0e4: max_iterations >= 1, lambda_init and robust_scale > 0 and finite, the tolerances >= 0)
    **{(cls, n): b for cls in (LMParams, PoseGraphParams) for n, b in (
        ("max_iterations", (">=", 1, None, None, True)), ("lambda_init", (">", 0.0, None, None, False)),
        ("relative_cost_tolerance", (">=", 0.0, None, None, False)),
        ("remaining_cost_tolerance", (">=", 0.0, None, None, False)),
        ("step_tolerance", (">=", 0.0, None, None, False)), ("robust_scale", (">", 0.0, None, None, False)))},
    # ControlParams (its former __post_init__ checks, minegeo/slam/control.py at f50f0e4)
    (ControlParams, "class_c"): (">", 0.0, None, None, False),
    (ControlParams, "drift_alpha"): (">", 0.0, "<", 1.0, False),
    # SlamParams (its former __post_init__ check, minegeo/slam/pipeline.py at 7be99ff: the plane association and
    # sigma parameters finite and > 0, plane_smoothing in (0, 1], plane_revisit_distance_m finite and >= 0 (0 turns
    # the linking off); map_voxel_m > 0, as voxel_downsample required of it at the end of the run)
    **{(SlamParams, n): (">", 0.0, None, None, False)
       for n in ("map_voxel_m", "plane_max_angle_deg", "plane_max_offset_m", "plane_sigma_angle_deg",
                 "plane_sigma_offset_m")},
    (SlamParams, "plane_revisit_distance_m"): (">=", 0.0, None, None, False),
    (SlamParams, "plane_smoothing"): (">", 0.0, "<=", 1.0, False),
    # ImuNoise (its former __post_init__ check, minegeo/optim/imu.py at 7be99ff: the densities and random walks
    # finite and > 0, integration_sigma finite and >= 0; the first four are also the keys of a Kalibr imu.yaml)
    **{(ImuNoise, n): (">", 0.0, None, None, False)
       for n in ("gyroscope_noise_density", "accelerometer_noise_density", "gyroscope_random_walk",
                 "accelerometer_random_walk")},
    (ImuNoise, "integration_sigma"): (">=", 0.0, None, None, False),
}
