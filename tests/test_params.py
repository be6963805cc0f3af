"""Parameter groups with their rules in field metadata (minegeo/_params.py, minegeo/localize/params.py).

* every numeric rule refuses the values on the wrong side of its bound and accepts the others
  (hypothesis: values drawn on both sides of each bound; the expected verdict comes from the bound
  as hand-listed here, not from the code's metadata);
* the command line and a ``--config`` file refuse a value with the dataclass's own message
  (exit status 2, one stderr line: the bad-input contract);
* ``LocalizeParams()`` holds the values of the flat parameter set it replaced, field by field
  (hand-listed from the former ``minegeo/localize/params.py``).
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from badinput._contract import assert_user_error
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo._params import field_rule
from minegeo.errors import InputError
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
}
#: fields whose rule is joined by a check across fields (GravityParams: 3 <= min_points <= max_points)
CROSS_CHECKED = {(GravityParams, "min_points"), (GravityParams, "max_points")}
GROUPS = (IcpParams, VerifyParams, AmbiguityParams, CorrelativeStageParams, GravityFallbackParams, LocalizeParams,
          FeatureParams, UncertaintyParams, RivalParams, CorrelativeParams, GravityParams)
KEYS = sorted(BOUNDS, key=lambda k: (k[0].__name__, k[1]))
_OPS = {">": lambda v, b: v > b, ">=": lambda v, b: v >= b, "<": lambda v, b: v < b, "<=": lambda v, b: v <= b}


def _expected_ok(key, v) -> bool:
    lo_op, lo, hi_op, hi, _ = BOUNDS[key]
    return (lo_op is None or _OPS[lo_op](v, lo)) and (hi_op is None or _OPS[hi_op](v, hi))


def test_every_numeric_field_is_listed():
    """The table above covers every numeric field of the groups (a new field gets its rule checked)."""
    listed = set(BOUNDS) | CROSS_CHECKED
    for cls in GROUPS:
        for f in dataclasses.fields(cls):
            if field_rule(cls, f.name)["kind"] == "number":
                assert (cls, f.name) in listed, (cls.__name__, f.name)
    with pytest.raises(InputError, match="min_points <= max_points"):
        GravityParams(min_points=2)
    with pytest.raises(InputError, match="min_points <= max_points"):
        GravityParams(max_points=199)


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
                      (VerifyParams, "fine_tolerance_m"), (LocalizeParams, "scan_icp_voxel_size_m")):
        assert getattr(cls(**{name: None}), name) is None
    for cls, name in ((IcpParams, "max_correspondence_m"), (VerifyParams, "min_fitness"), (AmbiguityParams, "ratio")):
        with pytest.raises(InputError, match=f"{cls.__name__}.{name}"):
            cls(**{name: None})
    lp = LocalizeParams(correlative=None, rival=None, gravity_fallback=None)
    assert lp.correlative is None and lp.rival is None and lp.gravity_fallback is None
    for name in ("icp", "verify", "ambiguity", "uncertainty", "features", "ransac"):
        with pytest.raises(InputError, match=f"LocalizeParams.{name}"):
            LocalizeParams(**{name: None})
    with pytest.raises(InputError, match="LocalizeParams.rival"):
        LocalizeParams(rival=IcpParams())
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


# ------------------------------------------------------------------ the CLI and a config file

# option, value, (class, field, value given to the dataclass), what an off-able option says instead of None
CLI_CASES = [
    ("--ransac-runs", "0", (LocalizeParams, "ransac_runs", 0), None),
    ("--voxel", "-0.5", (LocalizeParams, "scan_voxel_size_m", -0.5), None),
    ("--octree-level", "22", (LocalizeParams, "scan_octree_level", 22), None),
    ("--octree-level", "0", (LocalizeParams, "scan_octree_level", 0), None),
    ("--polish", "-1.0", (IcpParams, "polish_correspondence_m", -1.0), "0 (off)"),
    ("--fine-tolerance", "-0.01", (VerifyParams, "fine_tolerance_m", -0.01), "0 (off)"),
]


def _dataclass_message(cls, name, v, off_text) -> str:
    """The dataclass's message for ``v``; an option cannot give None, so its "or None" is dropped
    (or reads "or 0 (off)" for an option whose 0 means None)."""
    with pytest.raises(InputError) as exc:
        cls(**{name: v})
    return str(exc.value).replace(" or None,", "," if off_text is None else f" or {off_text},")


@pytest.mark.parametrize("opt,text,target,off_text", CLI_CASES, ids=[f"{c[0]}={c[1]}" for c in CLI_CASES])
def test_cli_option_refused_with_the_dataclass_message(opt, text, target, off_text, tmp_path, capsys):
    base = ["--map", tmp_path / "no_map.ply", "--scan", tmp_path / "no_scan.ply", "--out", tmp_path / "out"]
    want = _dataclass_message(*target, off_text)
    line = assert_user_error("localize", [*base, opt, text], capsys, outputs=[tmp_path / "out"])
    assert line.endswith(f"argument {opt}: {want} (see minegeo localize --help)"), (line, want)


@pytest.mark.parametrize("opt,text,target,off_text", CLI_CASES, ids=[f"{c[0]}={c[1]}" for c in CLI_CASES])
def test_config_file_value_refused_with_the_dataclass_message(opt, text, target, off_text, tmp_path, capsys):
    cfg = tmp_path / "bad.json"
    value = int(text) if target[0] is LocalizeParams and target[1] in ("ransac_runs", "scan_octree_level") \
        else float(text)
    cfg.write_text(json.dumps({opt.lstrip("-"): value}), encoding="utf-8")
    base = ["--map", tmp_path / "no_map.ply", "--scan", tmp_path / "no_scan.ply", "--out", tmp_path / "out"]
    want = _dataclass_message(*target, off_text)
    line = assert_user_error("localize", [*base, "--config", cfg], capsys, inputs=[cfg], outputs=[tmp_path / "out"])
    assert f"key {opt.lstrip('-')!r}: {want}" in line, (line, want)


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


# ------------------------------------------------------------------ the defaults

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
