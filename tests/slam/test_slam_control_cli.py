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


def _run(scene, out, mode, *extra):
    return main(["-q", "slam", "--frames", str(scene["frames"]), "--out", str(out), "--control", str(scene["stations"]),
                 "--station-offset", *(repr(float(v)) for v in OFFSET), "--control-mode", mode, *extra])


DXF_X = 200.0  # the stated exaggeration of the DXF's residual vectors and ellipses


@pytest.fixture(scope="module")
def runs(scene, tmp_path_factory):
    """One run per mode, made when first needed (the graph run also draws the DXF): ``{mode: OUT}``."""
    done = {}

    def get(mode):
        if mode not in done:
            o = tmp_path_factory.mktemp(mode) / "o"
            extra = ["--dxf", str(o.parent / "control.dxf"), "--dxf-exaggeration", repr(DXF_X)] if mode == "graph" else []
            assert _run(scene, o, mode, *extra) == 0
            done[mode] = o
        return done[mode]

    return get


@pytest.mark.parametrize("mode", ["graph", "rigid"])
def test_control_outputs_and_check_errors_recomputed_from_the_trajectory(scene, runs, mode):
    o = runs(mode)
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


def test_map_crs_las_holds_the_epsg_as_wkt_and_the_ply_points_to_the_las_scale(runs):
    """map_crs.laz (LAZ: lazrs is installed with the las extra) read back with laspy alone: its WKT VLR
    parses to the EPSG given, and its points equal map_crs.ply's (origin + stored coordinates, float64)
    within half the LAS scale recorded in result.json."""
    import laspy
    import pyproj

    from minegeo.io import read_point_cloud

    o = runs("graph")
    rec = json.loads((o / "result.json").read_text())["control"]["map_las"]
    assert rec["written"] and rec["file"] == "map_crs.laz"
    las = laspy.read(o / "map_crs.laz")
    assert las.header.version.minor == 4 and las.header.global_encoding.wkt
    wkt = [v for v in las.header.vlrs if type(v).__name__ == "WktCoordinateSystemVlr"]
    assert len(wkt) == 1
    assert pyproj.CRS.from_wkt(wkt[0].string).to_epsg() == 5186
    assert las.header.parse_crs().to_epsg() == 5186
    scale = np.asarray(las.header.scales)
    assert np.array_equal(scale, rec["scale_m"]) and np.array_equal(np.asarray(las.header.offsets), rec["offset_m"])
    xyz = (np.c_[np.asarray(las.X), np.asarray(las.Y), np.asarray(las.Z)].astype(np.float64) * scale
           + np.asarray(las.header.offsets))
    ply = read_point_cloud(o / "map_crs.ply", origin="file")
    ref = np.asarray(ply.points, dtype=np.float64) + np.asarray(ply.origin, dtype=np.float64)
    assert xyz.shape == ref.shape and xyz.shape[0] > 1000
    assert np.abs(xyz - ref).max() <= 0.5 * scale.max() + 1e-6


def test_dxf_layers_counts_and_an_ellipse_against_its_covariance(runs, scene):
    """The DXF of the graph run read back with ezdxf: control and check stations on their own layers,
    one residual vector and one ellipse per station, one trajectory polyline, the exaggeration stated;
    the ellipse of check station S2 has semi-axes x·sqrt(chi2_2(0.95))·sqrt(lambda) of the E N block of
    that station's covariance in result.json (numpy eigvalsh here), its vertex 0 on the major and vertex
    18 on the minor axis, centred at the surveyed point; a residual vector ends at s + x(e - s)."""
    import ezdxf

    o = runs("graph")
    rec = json.loads((o / "result.json").read_text())["control"]
    doc = ezdxf.readfile(o.parent / "control.dxf")
    msp = doc.modelspace()
    by_layer = {}
    for e in msp:
        by_layer.setdefault(e.dxf.layer, []).append(e)
    n = len(scene["roles"])
    n_ctrl = scene["roles"].count("control")
    assert len(by_layer["MINEGEO_CONTROL_STATIONS"]) == n_ctrl
    assert len(by_layer["MINEGEO_CHECK_STATIONS"]) == n - n_ctrl
    assert all(e.dxftype() == "POINT" for e in by_layer["MINEGEO_CONTROL_STATIONS"] + by_layer["MINEGEO_CHECK_STATIONS"])
    assert len(by_layer["MINEGEO_RESIDUALS"]) == n and len(by_layer["MINEGEO_ELLIPSE95"]) == n
    assert len(by_layer["MINEGEO_TRAJECTORY"]) == 1
    assert {"MINEGEO_CONTROL_STATIONS", "MINEGEO_CHECK_STATIONS"} <= {ly.dxf.name for ly in doc.layers}
    props = dict(doc.header.custom_vars)
    assert props["MINEGEO_EXAGGERATION"] == f"{DXF_X:g}" and props["MINEGEO_CRS"] == CRS
    assert rec["dxf"]["exaggeration"] == DXF_X
    # the station S2 (check): surveyed point from the stations file, covariance from result.json
    rows = [ln.split(",") for ln in scene["stations"].read_text().splitlines()[2:]]
    s2 = np.array([float(v) for v in rows[1][3:6]])
    cov = np.array(rec["station_covariance_enh_m2"]["S2"])
    lam = np.linalg.eigvalsh(cov[:2, :2])
    k = np.sqrt(5.991464547107979)
    ells = [np.array([tuple(v.dxf.location) for v in e.vertices]) for e in by_layer["MINEGEO_ELLIPSE95"]]
    e2 = min(ells, key=lambda v: np.linalg.norm(v.mean(axis=0)[:2] - s2[:2]))
    assert e2.shape == (72, 3)
    assert np.allclose(e2.mean(axis=0), s2, atol=1e-6)
    assert np.linalg.norm(e2[0, :2] - s2[:2]) == pytest.approx(DXF_X * k * np.sqrt(lam[1]), rel=1e-9)
    assert np.linalg.norm(e2[18, :2] - s2[:2]) == pytest.approx(DXF_X * k * np.sqrt(lam[0]), rel=1e-9)
    # the residual vector of S2 from result.json's check error
    d2 = np.array(next(s["delta_enh_m"] for s in rec["check"]["stations"] if s["id"] == "S2"))
    vecs = [np.array([tuple(v.dxf.location) for v in e.vertices]) for e in by_layer["MINEGEO_RESIDUALS"]]
    v2 = min(vecs, key=lambda v: np.linalg.norm(v[0] - s2))
    assert np.allclose(v2[0], s2, atol=1e-6) and np.allclose(v2[1], s2 + DXF_X * d2, atol=1e-6)


def test_without_laspy_no_las_a_one_line_note_and_with_it_the_laz(tmp_path, monkeypatch, caplog):
    """The LAS writer of slam --control on its own (no SLAM run): without the las extra (laspy import
    blocked) it writes nothing, says so in one warning line and returns written False; with laspy the
    same call writes map_crs.laz and its sidecar, the CRS in the file."""
    import logging

    import laspy

    from minegeo.cli.slam import _write_map_las
    from minegeo.georef import GeorefParams, georeference
    from minegeo.io.types import ControlPoints

    local = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [10.0, 10.0, 1.0]])
    enh = local + [219437.0, 612981.0, 214.0]
    fit = georeference(ControlPoints(ids=["a", "b", "c", "d"], local_xyz=local, crs_enh=enh,
                                     sigma_enh_m=np.full((4, 3), 0.005), crs=CRS), CRS, GeorefParams(model="rigid"))
    geo = enh - np.asarray(fit.origin)
    cloud = PointCloud(points=geo, origin=fit.origin, crs=CRS, frame="geo")
    no = tmp_path / "no"
    no.mkdir()
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy -> ImportError
    with caplog.at_level(logging.WARNING, logger="minegeo.cli.slam"):
        rec = _write_map_las(no, cloud, fit, {})
    assert rec["written"] is False and "laspy is not installed" in rec["reason"]
    assert list(no.iterdir()) == []
    notes = [r.getMessage() for r in caplog.records if r.name == "minegeo.cli.slam"]
    assert len(notes) == 1 and "\n" not in notes[0] and "map_crs.ply" in notes[0]
    monkeypatch.setitem(sys.modules, "laspy", laspy)
    yes = tmp_path / "yes"
    yes.mkdir()
    rec = _write_map_las(yes, cloud, fit, {})
    assert rec["written"] and sorted(p.name for p in yes.iterdir()) == ["map_crs.laz", "map_crs.laz.georef.json"]
    back = laspy.read(yes / "map_crs.laz")
    assert back.header.parse_crs().to_epsg() == 5186
    assert np.abs(np.c_[back.x, back.y, back.z] - enh).max() <= 0.0005 + 1e-9
