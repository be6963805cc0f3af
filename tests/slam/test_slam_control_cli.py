"""``minegeo slam --control STATIONS.csv``: the trajectory, stations and map in the CRS, the check-station
errors in result.json recomputed independently from ``trajectory_crs.tum``, the offset and the true
station points, and the bad combinations refused with one line before any work (issue 30).

The frames are simulated VLP-16 sweeps along an 18 m drive (as in ``test_slam_run_cli.py``) that stops
for 1 s (4 more frames of the same pose) on each of 5 stations; the true station points are ``T_crs_world (p(t) + R(t) a)`` of the simulator's own pose at the station time.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from minegeo.cli import main
from minegeo.io import PointCloud, read_trajectory, write_point_cloud

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "badinput"))
from _contract import assert_user_error  # noqa: E402

OFFSET = np.array([0.1, -0.05, -0.6])
CRS = "EPSG:5186"


def _T_crs_world():
    c, s = np.cos(0.7), np.sin(0.7)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [219437.25, 612981.5, 214.75]
    return T


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from minegeo.synth.sensors import Velodyne16, simulate_scan
    from minegeo.synth.trajectory import interpolate_poses, make_trajectory
    from minegeo.synth.world import build_world

    world = build_world("small", 1)
    traj = make_trajectory(world, "drive", length_m=18.0, seed=5)
    t_drive = np.arange(0.0, traj.times_s[-1], 0.25)
    P_drive = interpolate_poses(traj, t_drive)
    # stop and go: at 5 frames the sensor stands still for STOP more frames (1 s), the clock runs on;
    # control, check alternating (3 + 2)
    kk = np.linspace(3, t_drive.size - 4, 5).round().astype(int)
    stop = 4
    idx, ts, t_span = [], [], []
    for k in range(t_drive.size):
        n = 1 + (stop if k in kk else 0)
        t0 = t_drive[k] + 0.25 * len(idx) - 0.25 * k
        if k in kk:
            t_span.append((t0, t0 + 0.25 * stop))
        idx += [k] * n
        ts += [t0 + 0.25 * j for j in range(n)]
    ts = np.array(ts)
    sensor = Velodyne16(azimuth_step_deg=0.4)
    d = tmp_path_factory.mktemp("ctl")
    fr = d / "frames"
    fr.mkdir()
    for m, k in enumerate(idx):
        write_point_cloud(fr / f"{m:06d}.ply", PointCloud(points=simulate_scan(world, sensor, P_drive[k], seed=m).points))
    (fr / "times.txt").write_text("".join(f"{t:.6f}\n" for t in ts))
    roles = ["control", "check", "control", "check", "control"]
    Tcw = _T_crs_world()
    P = P_drive[kk]
    truth = np.array([(Tcw @ np.r_[T[:3, :3] @ OFFSET + T[:3, 3], 1.0])[:3] for T in P])
    rows = [f"# crs: {CRS}", "id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role"]
    for i, (a, b) in enumerate(t_span):
        rows.append(f"S{i + 1},{a:.6f},{b:.6f},{float(truth[i, 0])!r},{float(truth[i, 1])!r},{float(truth[i, 2])!r},"
                    f"0.005,0.008,{roles[i]}")
    (d / "stations.csv").write_text("\n".join(rows) + "\n")
    t_mid = np.array([0.5 * (a + b) for a, b in t_span])
    return {"frames": fr, "stations": d / "stations.csv", "truth": truth, "t": t_mid, "roles": roles}


def _run(scene, out, mode):
    return main(["-q", "slam", "--frames", str(scene["frames"]), "--out", str(out), "--control", str(scene["stations"]),
                 "--station-offset", *(repr(float(v)) for v in OFFSET), "--control-mode", mode])


@pytest.mark.parametrize("mode", ["graph", "rigid"])
def test_control_outputs_and_check_errors_recomputed_from_the_trajectory(scene, tmp_path, mode):
    o = tmp_path / "o"
    assert _run(scene, o, mode) == 0
    for name in ("trajectory_crs.tum", "trajectory_crs.csv", "stations_result.csv", "map_crs.ply",
                 "map_crs.ply.georef.json", "result.json", "report.html"):
        assert (o / name).is_file(), name
    rec = json.loads((o / "result.json").read_text())["control"]
    assert rec["mode"] == mode and rec["crs"] == CRS
    origin = np.array(rec["origin_enh"])
    tr = read_trajectory(o / "trajectory_crs.tum")
    # independent: the station point from the written trajectory at the station time, plus the offset
    chk = [i for i, r in enumerate(scene["roles"]) if r == "check"]
    est = []
    for i in chk:
        k = int(np.flatnonzero(np.abs(tr.times_s - scene["t"][i]) < 1e-6)[0])  # the middle frame of the stop
        est.append(tr.poses[k][:3, :3] @ OFFSET + tr.poses[k][:3, 3] + origin)
    delta = np.array(est) - scene["truth"][chk]
    got = np.array([s["delta_enh_m"] for s in rec["check"]["stations"]])
    assert np.allclose(got, delta, atol=2e-4), (got, delta)  # TUM stores 4 decimals of the local frame
    h = np.hypot(delta[:, 0], delta[:, 1])
    assert rec["check"]["rmse_horizontal_m"] == pytest.approx(np.sqrt(np.mean(h**2)), abs=2e-4)
    assert rec["check"]["rmse_horizontal_m"] < 0.10  # an 18 m drive in a textured drift
    # the CSV holds the absolute E N H of the same poses
    csv = np.loadtxt(o / "trajectory_crs.csv", delimiter=",", skiprows=1)
    assert np.allclose(csv[:, 1:4], tr.poses[:, :3, 3] + origin, atol=6e-4)
    assert "Survey control" in (o / "report.html").read_text()


def test_bad_control_combinations_are_one_line(scene, tmp_path, capsys):
    out = tmp_path / "o"
    base = ["--frames", str(scene["frames"]), "--out", str(out)]
    assert_user_error("slam", base + ["--control-mode", "rigid"], inputs=[scene["stations"]], outputs=[out],
                      capsys=capsys, expect="--control-mode needs --control")
    bad_role = tmp_path / "role.csv"
    bad_role.write_text(scene["stations"].read_text().replace("check", "checkpoint", 1))
    assert_user_error("slam", base + ["--control", str(bad_role)], inputs=[bad_role], outputs=[out], capsys=capsys,
                      expect="checkpoint")
    late = tmp_path / "late.csv"
    lines = scene["stations"].read_text().splitlines()
    f = lines[-1].split(",")
    f[1], f[2] = "900.0", "903.0"
    late.write_text("\n".join([*lines[:-1], ",".join(f)]) + "\n")
    assert_user_error("slam", base + ["--control", str(late)], inputs=[late], outputs=[out], capsys=capsys,
                      expect="station S5")
    few = tmp_path / "few.csv"
    few.write_text("\n".join(ln.replace("control", "check") if ln.startswith(("S3", "S5")) else ln
                             for ln in lines) + "\n")
    assert_user_error("slam", base + ["--control", str(few)], inputs=[few], outputs=[out], capsys=capsys,
                      expect="1 control station(s)")
    assert_user_error("slam", base + ["--control", str(scene["stations"]), "--crs", "EPSG:32652"],
                      inputs=[scene["stations"]], outputs=[out], capsys=capsys, expect="contradicts")
