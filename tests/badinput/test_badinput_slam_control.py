"""``minegeo slam --control STATIONS.csv`` (issue 30, bad input of the acceptance): a station outside the
run's time span, a station in a gap of the trajectory, fewer control stations than a mode needs,
control stations on one line, duplicated ids, a CRS that is not projected, ``--dxf`` without
``--control`` (and the other DXF option mistakes), the drift-state and class-constant options out of
range, contradicting ``--control-mode rigid`` or ``similarity`` (fits after SLAM, without drift states)
or without ``--control``: each one error line, exit 2, nothing written, inputs unchanged
(tests/badinput/_contract.py).

The frames are small (600 points on the walls of a room each) at 0.1 s, with a 1.7 s gap between
0.3 and 2.0 s. Every case but the last is refused before the odometry; the last (frames skipped as
unreadable leave a gap under a station) after it, still with nothing written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _contract import assert_user_error, copy_tree

TIMES = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 2.0, 2.1, 2.2, 2.3]
HEADER = "id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role"
ROWS = ["S1,0.05,0.15,201345.112,551203.447,87.402,0.005,0.010,control",
        "S2,0.35,0.45,201346.880,551204.019,86.911,0.005,0.010,check",
        "S3,0.55,0.65,201348.004,551202.771,86.100,0.005,0.010,control",
        "S4,2.05,2.15,201349.004,551205.771,86.100,0.005,0.010,control"]


@pytest.fixture(scope="module")
def frames_src(tmp_path_factory):
    from minegeo.io import PointCloud, write_point_cloud

    d = tmp_path_factory.mktemp("ctl_frames") / "frames"
    d.mkdir()
    rng = np.random.default_rng(30)
    for k, _t in enumerate(TIMES):
        u = rng.uniform(-1.0, 1.0, (600, 3)) * [3.0, 2.0, 1.5]
        face = rng.integers(0, 3, 600)
        u[np.arange(600), face] = np.sign(u[np.arange(600), face]) * np.array([3.0, 2.0, 1.5])[face]
        write_point_cloud(d / f"{k:06d}.ply", PointCloud(points=u + [0.05 * k, 0.0, 0.0]))
    (d / "times.txt").write_text("".join(f"{t:.6f}\n" for t in TIMES))
    return d


@pytest.fixture
def frames(frames_src, tmp_path):
    return copy_tree(frames_src, tmp_path / "frames")


def _stations(d: Path, rows, crs: str | None = "EPSG:5186") -> Path:
    p = d / "stations.csv"
    p.write_text("\n".join(([f"# crs: {crs}"] if crs else []) + [HEADER, *rows]) + "\n", encoding="utf-8")
    return p


def _sub(i: int, old: str, new: str) -> list[str]:
    rows = list(ROWS)
    rows[i] = rows[i].replace(old, new, 1)
    return rows


#: case -> (stations rows, stations CRS line, extra argv, text the error line must hold)
CASES = {
    "station_before_the_run": (_sub(0, "0.05,0.15", "-3.0,-2.0"), "EPSG:5186", [],
                               "station S1 stands [-3.000, -2.000] s, outside the frames of --frames"),
    "station_after_the_run": (_sub(3, "2.05,2.15", "9.0,12.0"), "EPSG:5186", [],
                              "station S4 stands [9.000, 12.000] s, outside the frames"),
    "station_in_a_gap": (_sub(1, "0.35,0.45", "1.0,1.2"), "EPSG:5186", [],
                         "station S2 at 1.100 s falls in a gap of the trajectory: no frame of the frames of --frames"),
    "too_few_controls_graph": (_sub(2, ",control", ",check"), "EPSG:5186", [],
                               "2 control station(s); the graph mode needs at least 3"),
    "too_few_controls_rigid": (_sub(2, ",control", ",check"), "EPSG:5186", ["--control-mode", "rigid"],
                               "2 control station(s); the rigid mode needs at least 3"),
    "too_few_controls_similarity": (_sub(2, ",control", ",check"), "EPSG:5186", ["--control-mode", "similarity"],
                                    "2 control station(s); the similarity mode needs at least 3"),
    # S4 moved onto the line through S1 and S3 (S1 + 2 (S3 - S1)), 3 mm off it: within 3 sigma
    "collinear_controls_similarity": (_sub(3, "201349.004,551205.771,86.100", "201350.899,551202.095,84.798"),
                                      "EPSG:5186", ["--control-mode", "similarity"],
                                      "the 3 control stations (S1, S3, S4) lie on one straight line (at most 0.00"),
    "collinear_controls_graph": (_sub(3, "201349.004,551205.771,86.100", "201350.896,551202.095,84.798"),
                                 "EPSG:5186", [], "lie on one straight line (at most 0.000 m from it over 6.5 m): the "
                                 "rotation about that line is not determined (standard deviation over 180 deg from the "
                                 "stations' sigma, more than 19.1 deg); the graph mode needs at least 3 not on one line"),
    "control_mode_unknown": (ROWS, "EPSG:5186", ["--control-mode", "helmert"],
                             "argument --control-mode: invalid choice: 'helmert' (choose from 'rigid', 'similarity', "
                             "'graph')"),
    "duplicated_id": (_sub(2, "S3,", "S1,"), "EPSG:5186", [], "line 5: duplicate id 'S1' (first on line 3)"),
    "geographic_crs_in_file": (ROWS, "EPSG:4326", [], "the '# crs:' line of --control "),
    "geographic_crs_option": (ROWS, None, ["--crs", "EPSG:4326"],
                              "--crs EPSG:4326: EPSG:4326 (WGS 84) is a geographic CRS"),
    "geocentric_crs": (ROWS, None, ["--crs", "EPSG:4978"], "--crs EPSG:4978: EPSG:4978"),
    "no_crs": (ROWS, None, [], "no CRS (give --crs EPSG:"),
    "dxf_exaggeration_without_dxf": (ROWS, "EPSG:5186", ["--dxf-exaggeration", "100"],
                                     "--dxf-exaggeration needs --dxf FILE.dxf"),
    "dxf_exaggeration_zero": (ROWS, "EPSG:5186", ["--dxf", "OUTDXF", "--dxf-exaggeration", "0"],
                              "--dxf-exaggeration"),
    # drift states and the class constant (issue 30)
    "drift_states_unknown": (ROWS, "EPSG:5186", ["--drift-states", "sometimes"],
                             "argument --drift-states: invalid choice: 'sometimes' (choose from 'off', 'on', 'auto')"),
    "drift_states_with_rigid": (ROWS, "EPSG:5186", ["--drift-states", "auto", "--control-mode", "rigid"],
                                "--drift-states auto contradicts --control-mode rigid"),
    "drift_states_on_with_similarity": (ROWS, "EPSG:5186", ["--control-mode", "similarity", "--drift-states", "on"],
                                        "--drift-states on contradicts --control-mode similarity (drift states are "
                                        "variables of the pose graph; a similarity fit has none)"),
    "drift_states_auto_with_similarity": (ROWS, "EPSG:5186", ["--drift-states", "auto", "--control-mode", "similarity"],
                                          "--drift-states auto contradicts --control-mode similarity"),
    "drift_walk_zero": (ROWS, "EPSG:5186", ["--drift-states", "on", "--drift-walk", "2e-5", "0", "1e-7"],
                        "argument --drift-walk: '0' must be greater than 0"),
    "drift_walk_two_values": (ROWS, "EPSG:5186", ["--drift-states", "on", "--drift-walk", "2e-5", "1e-7"],
                              "argument --drift-walk: expected 3 arguments"),
    "drift_walk_without_drift_states": (ROWS, "EPSG:5186", ["--drift-walk", "2e-5", "1e-7", "1e-7"],
                                        "--drift-walk needs --drift-states on or auto"),
    "drift_prior_with_drift_states_off": (ROWS, "EPSG:5186", ["--drift-states", "off", "--drift-prior", "0.01", "1e-4",
                                                              "1e-4"], "--drift-prior needs --drift-states on or auto"),
    "drift_prior_infinite": (ROWS, "EPSG:5186", ["--drift-states", "on", "--drift-prior", "inf", "1e-4", "1e-4"],
                             "argument --drift-prior: 'inf' is not a finite number"),
    "class_constant_zero": (ROWS, "EPSG:5186", ["--class-constant", "0"],
                            "argument --class-constant: ControlParams.class_c must be a finite number > 0, got 0.0"),
    "class_constant_negative": (ROWS, "EPSG:5186", ["--class-constant", "-50"],
                                "argument --class-constant: ControlParams.class_c must be a finite number > 0, "
                                "got -50.0"),
    "class_constant_not_a_number": (ROWS, "EPSG:5186", ["--class-constant", "D"],
                                    "argument --class-constant: 'D' is not a number"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_control_input(case, frames, tmp_path, capsys):
    rows, crs, extra, expect = CASES[case]
    st = _stations(tmp_path, rows, crs)
    out, dxf = tmp_path / "out", tmp_path / "control.dxf"
    extra = [str(dxf) if a == "OUTDXF" else a for a in extra]
    assert_user_error("slam", ["--frames", frames, "--out", out, "--control", st, *extra], capsys,
                      inputs=[frames, st], outputs=[out, dxf], expect=expect)


def test_dxf_without_control(frames, tmp_path, capsys):
    out, dxf = tmp_path / "out", tmp_path / "control.dxf"
    assert_user_error("slam", ["--frames", frames, "--out", out, "--dxf", dxf], capsys, inputs=[frames],
                      outputs=[out, dxf], expect="--dxf needs --control STATIONS.csv")


@pytest.mark.parametrize("extra", [["--class-constant", "30"], ["--drift-states", "on"],
                                   ["--drift-walk", "2e-5", "1e-7", "1e-7"], ["--drift-prior", "0.01", "1e-4", "1e-4"]])
def test_control_options_without_control(extra, frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", frames, "--out", out, *extra], capsys, inputs=[frames], outputs=[out],
                      expect=f"{extra[0]} needs --control STATIONS.csv")


def test_dxf_is_a_folder(frames, tmp_path, capsys):
    st = _stations(tmp_path, ROWS)
    out, dxf = tmp_path / "out", tmp_path / "drawings"
    dxf.mkdir()
    assert_user_error("slam", ["--frames", frames, "--out", out, "--control", st, "--dxf", dxf], capsys,
                      inputs=[frames, st], outputs=[out, dxf], expect="is a folder; name a file")


def test_station_over_frames_the_run_skipped(frames, tmp_path, capsys):
    """Frames 0.3-0.5 s unreadable (skipped by the run, reported): station S2 (0.35-0.45 s) stands in the
    gap they leave in the trajectory; found after the odometry, nothing written."""
    for k in (3, 4, 5):
        (frames / f"{k:06d}.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    st = _stations(tmp_path, ROWS)
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", frames, "--out", out, "--control", st], capsys, inputs=[frames, st],
                      outputs=[out], expect="station S2 at 0.400 s falls in a gap of the trajectory: no frame of "
                                            "the frames of --frames")
