"""DXF delivery into the mine plan (issue 19, deliverable 4): every point and polyline read back by
ezdxf to the millimetre (in fact exactly), in the CRS, on named layers; failed results carry no
coordinates. The ``localize --dxf`` run is in ``tests/localize/test_localize_e57_dxf_cli.py``."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
from helpers import require_extra

ezdxf = require_extra("ezdxf")

from minegeo.cli import main  # noqa: E402
from minegeo.errors import InputError, OptionalDependencyError  # noqa: E402
from minegeo.io.dxf import (  # noqa: E402
    ELLIPSE_VERTICES,
    DxfDrawing,
    ellipse_from_covariance,
    ellipse_vertices,
    write_localize_dxf,
)
from minegeo.survey.ellipse import error_ellipse  # noqa: E402

E0, N0, H0 = 512345.678912345, 4123456.789123456, -812.345678901


def _rot(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ok_result(name, origin, yaw_map, yaw_geo, cov, trajectory_csv=None):
    T_map = np.eye(4)
    T_map[:3, :3] = _rot(yaw_map)
    T_map[:3, 3] = [10.0, 20.0, 1.0]
    T_crs = np.eye(4)
    T_crs[:3, :3] = _rot(yaw_geo)
    T_crs[:3, 3] = origin
    return {"status": "ok", "name": name, "crs": "EPSG:5186", "T_map_scan": T_map.tolist(),
            "T_crs_scan": T_crs.tolist(), "position_cov_3x3": np.asarray(cov).tolist(),
            "trajectory_csv": trajectory_csv}


def _failed(name, status):
    # a rejected candidate's coordinates live only under rejected_candidates (map frame)
    return {"status": status, "name": name, "crs": "EPSG:5186", "T_map_scan": None, "T_crs_scan": None,
            "position_cov_3x3": None, "rejected_candidates": {"candidates": [{"origin_map_m": [777.0, 888.0, 9.0]}]}}


def _entities(doc, layer, kind):
    return [e for e in doc.modelspace() if e.dxf.layer == layer and e.dxftype() == kind]


def _write_traj_csv(folder, P):
    lines = ["# sensor trajectory placed by minegeo localize", "# crs: EPSG:5186; status: ok",
             "time_s,x_map_m,y_map_m,z_map_m,E_m,N_m,H_m,qx,qy,qz,qw,sigma_3d_m,status"]
    for i, p in enumerate(P):
        lines.append(f"{i * 0.1:.6f},0,0,0,{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},0,0,0,1,0.02,ok")
    (folder / "trajectory_global.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture
def batch(tmp_path):
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3)) * 0.02
    cov = A @ A.T
    folder = tmp_path / "res_a"
    folder.mkdir()
    traj = np.array([E0, N0, H0]) + np.cumsum(rng.normal(size=(40, 3)) * 0.5, axis=0)
    traj = np.round(traj, 4)  # as written to trajectory_global.csv (0.1 mm)
    _write_traj_csv(folder, traj)
    a = _ok_result("scan_a", [E0, N0, H0], 0.3, 1.1, cov, "trajectory_global.csv")
    a["result_dir"] = str(folder)
    b = _ok_result("scan_b", [E0 + 250.125, N0 - 80.5, H0 + 3.25], -0.4, 0.2, cov * 4)
    results = [a, _failed("scan_c", "failed"), b, _failed("scan_d", "ambiguous")]
    return results, traj, cov


def test_localize_dxf_reads_back_exactly_in_the_crs(batch, tmp_path):
    results, traj, cov = batch
    path = tmp_path / "placed.dxf"
    summary = write_localize_dxf(path, results)
    doc = ezdxf.readfile(path)
    assert doc.header["$INSUNITS"] == 6 and doc.units == 6
    pts = _entities(doc, "MINEGEO_SCAN_ORIGINS", "POINT")
    got = np.array([tuple(e.dxf.location) for e in pts])
    want = np.array([r["T_crs_scan"] for r in results if r["status"] == "ok"])[:, :3, 3]
    np.testing.assert_array_equal(got, want)  # exactly; a fortiori to the millimetre
    assert np.abs(got - want).max() < 1e-3
    labels = {e.dxf.text: tuple(e.dxf.insert) for e in _entities(doc, "MINEGEO_LABELS", "TEXT")}
    assert labels == {"scan_a": tuple(want[0]), "scan_b": tuple(want[1])}
    (tr,) = _entities(doc, "MINEGEO_TRAJECTORY", "POLYLINE")
    np.testing.assert_array_equal(np.array([tuple(v) for v in tr.points()]), traj)
    assert tr.is_3d_polyline and not tr.is_closed
    ells = _entities(doc, "MINEGEO_ELLIPSE95", "POLYLINE")
    assert len(ells) == 2 and all(e.is_closed and len(list(e.points())) == ELLIPSE_VERTICES for e in ells)
    assert summary["layers"] == {"MINEGEO_ELLIPSE95": 2, "MINEGEO_LABELS": 2, "MINEGEO_SCAN_ORIGINS": 2,
                                 "MINEGEO_TRAJECTORY": 1}
    assert summary["placed"] == ["scan_a", "scan_b"] and summary["frame"] == "crs" and summary["crs"] == "EPSG:5186"
    assert [n["name"] for n in summary["not_placed"]] == ["scan_c", "scan_d"]


def test_ellipse_is_the_95_percent_ellipse_in_crs_axes(batch, tmp_path):
    """Semi-axes and azimuth of the drawn 72-gon equal survey.error_ellipse of the covariance rotated
    from map axes into CRS axes (R_crs_map = R_crs_scan R_map_scan^T)."""
    results, _, cov = batch
    path = tmp_path / "e.dxf"
    write_localize_dxf(path, results[:1])
    (e,) = _entities(ezdxf.readfile(path), "MINEGEO_ELLIPSE95", "POLYLINE")
    V = np.array([tuple(v) for v in e.points()])
    c = np.array(results[0]["T_crs_scan"])[:3, 3]
    R = _rot(1.1 - 0.3)
    ref = error_ellipse((R @ cov @ R.T)[:2, :2], confidence=0.95)
    d = np.linalg.norm(V[:, :2] - c[:2], axis=1)
    assert np.all(V[:, 2] == c[2])
    assert d.max() == pytest.approx(ref.semi_major_m, rel=1e-9)
    assert d.min() == pytest.approx(ref.semi_minor_m, rel=2e-3)  # 72 vertices: the minor axis is a vertex too
    az = math.atan2(V[0, 0] - c[0], V[0, 1] - c[1]) % math.pi
    assert az == pytest.approx(ref.azimuth_rad, abs=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_ellipse_from_covariance_equals_the_survey_ellipse(seed):
    A = np.random.default_rng(seed).normal(size=(2, 2))
    S = A @ A.T
    a, b, az = ellipse_from_covariance(S)
    ref = error_ellipse(S, confidence=0.95)
    assert (a, b) == pytest.approx((ref.semi_major_m, ref.semi_minor_m), rel=1e-12)
    assert az == pytest.approx(ref.azimuth_rad, abs=1e-12)
    V = ellipse_vertices((E0, N0, H0), a, b, az)
    q = V[:, :2] - [E0, N0]
    u = np.array([math.sin(az), math.cos(az)])
    v = np.array([math.cos(az), -math.sin(az)])
    np.testing.assert_allclose((q @ u / a) ** 2 + (q @ v / b) ** 2, 1.0, rtol=0, atol=1e-6)


def test_failed_and_ambiguous_results_carry_no_coordinates(tmp_path):
    results = [_failed("scan_c", "failed"), _failed("scan_d", "ambiguous")]
    path = tmp_path / "none.dxf"
    summary = write_localize_dxf(path, results)
    doc = ezdxf.readfile(path)
    assert len(doc.modelspace()) == 0 and summary["placed"] == [] and summary["layers"] == {}
    props = dict(doc.header.custom_vars)
    assert "scan_c (failed: no position)" in props["MINEGEO_NOT_PLACED"]
    assert "scan_d (ambiguous: no position)" in props["MINEGEO_NOT_PLACED"]
    assert "777" not in path.read_text()


def test_result_folders_and_layer_prefix(batch, tmp_path):
    """A result folder is read from its result.json; a layer prefix renames every layer."""
    results, traj, _ = batch
    folder = tmp_path / "res_a"
    (folder / "result.json").write_text(json.dumps({k: v for k, v in results[0].items() if k != "result_dir"}))
    summary = write_localize_dxf(tmp_path / "p.dxf", [folder], layer_prefix="SURVEY_2026",
                                 trajectories={"scan_a": traj[:5]})
    doc = ezdxf.readfile(tmp_path / "p.dxf")
    assert {ly.dxf.name for ly in doc.layers} >= {"SURVEY_2026_SCAN_ORIGINS", "SURVEY_2026_TRAJECTORY"}
    (tr,) = _entities(doc, "SURVEY_2026_TRAJECTORY", "POLYLINE")
    assert len(list(tr.points())) == 5 and summary["placed"] == ["scan_a"]
    with pytest.raises(InputError):
        DxfDrawing(layer_prefix="BAD/NAME")


def test_without_ezdxf_the_error_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ezdxf", None)
    with pytest.raises(OptionalDependencyError, match=r"minegeo\[dxf\]"):
        write_localize_dxf(tmp_path / "x.dxf", [])
    assert not (tmp_path / "x.dxf").exists()


# -- mast and adjust --dxf ----------------------------------------------------------------------------------------


def test_mast_dxf(tmp_path, capsys):
    from minegeo.mast import read_beacons_csv, write_mast_scenario

    paths = write_mast_scenario(tmp_path / "sc", seed=3, position=2, beacon1_rotation_deg=10.0,
                                mine_origin_m=(500000.0, 6000000.0))
    out = tmp_path / "out"
    assert main(["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]), "--out", str(out),
                 "--dxf"]) == 0
    assert "mast.dxf" in capsys.readouterr().out
    r = json.loads((out / "result.json").read_text())
    f = out / "mast.dxf"
    from minegeo._provenance import sha256_file

    assert r["dxf"]["file"] == "mast.dxf" and r["dxf"]["sha256"] == sha256_file(f)
    doc = ezdxf.readfile(f)
    (st,) = _entities(doc, "MINEGEO_STATIONS", "POINT")
    assert tuple(st.dxf.location) == (r["x"], r["y"], 0.0)
    beacons = {b.beacon_id: b.vertices_m for b in read_beacons_csv(paths["beacons"])}
    polys = _entities(doc, "MINEGEO_BEACONS", "POLYLINE")
    assert len(polys) == len(beacons)
    got = sorted(np.array([tuple(v) for v in p.points()])[:, :2].tolist() for p in polys)
    assert got == sorted(v.tolist() for v in beacons.values())
    (e,) = _entities(doc, "MINEGEO_ELLIPSE95", "POLYLINE")
    d = np.linalg.norm(np.array([tuple(v) for v in e.points()])[:, :2] - [r["x"], r["y"]], axis=1)
    assert d.max() == pytest.approx(r["ellipse95"]["a_m"], abs=1e-8)  # E, N ~ 6e6 m: float64 spacing 1e-9 m


def test_adjust_dxf(tmp_path, capsys):
    from helpers import shared_data

    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Ghilani21_10_DistanceAngle_fix.dat")
    out = tmp_path / "adj"
    assert main(["adjust", str(dat), "--out", str(out), "--dxf"]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["dxf"]["file"] == "adjusted.dxf" and r["dxf"]["confidence"] == 0.95
    doc = ezdxf.readfile(out / "adjusted.dxf")
    labels = {e.dxf.text: tuple(e.dxf.insert) for e in _entities(doc, "MINEGEO_LABELS", "TEXT")}
    assert set(labels) == set(r["points"])
    for layer in ("MINEGEO_ADJUSTED_POINTS", "MINEGEO_FIXED_POINTS"):
        for e in _entities(doc, layer, "POINT"):
            x, y, z = e.dxf.location
            (pid,) = [k for k, v in labels.items() if v == (x, y, z)]
            p = r["points"][pid]
            assert (x, y) == (p["x"], p["y"]) and z == p.get("h", 0.0)
            assert (layer == "MINEGEO_FIXED_POINTS") == ("x" in p["fixed"] and "y" in p["fixed"])
    ells = _entities(doc, "MINEGEO_ELLIPSE95", "POLYLINE")
    free = [k for k, p in r["points"].items() if not ("x" in p["fixed"] and "y" in p["fixed"])]
    assert len(ells) == len(free) > 0
    for e in ells:
        V = np.array([tuple(v) for v in e.points()])
        pid = min(free, key=lambda k: np.hypot(*(V[:, :2].mean(axis=0) - [r["points"][k]["x"], r["points"][k]["y"]])))
        ref = r["ellipses"]["points"][pid]["confidence_95"]
        d = np.linalg.norm(V[:, :2] - [r["points"][pid]["x"], r["points"][pid]["y"]], axis=1)
        assert d.max() == pytest.approx(ref["semi_major_m"], rel=1e-9)


def test_the_same_drawing_gives_the_same_bytes(tmp_path, capsys):
    """Same inputs, same DXF bytes: ezdxf's clock time and random GUIDs ($TDCREATE, $TDUPDATE,
    $VERSIONGUID, $FINGERPRINTGUID, its marker) are written as fixed values; a drawing made a second
    later is byte-identical, and ezdxf's global option is left as it was."""
    import time

    from minegeo.mast import write_mast_scenario

    paths = write_mast_scenario(tmp_path / "sc", seed=3, position=2, beacon1_rotation_deg=10.0,
                                mine_origin_m=(500000.0, 6000000.0))
    blobs = []
    for k in range(2):
        out = tmp_path / f"out{k}"
        assert main(["-q", "mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]),
                     "--out", str(out), "--dxf"]) == 0
        blobs.append((out / "mast.dxf").read_bytes())
        time.sleep(1.1)  # the header's dates have a resolution of a second or finer
    assert blobs[0] == blobs[1]
    assert not ezdxf.options.write_fixed_meta_data_for_testing
    d = DxfDrawing(crs="EPSG:5186")
    d.doc.modelspace().add_point((1.0, 2.0, 3.0))
    a = d.to_bytes()
    time.sleep(1.1)
    assert a == d.to_bytes()
