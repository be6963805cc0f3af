"""Scan/beacon CSV round trips, scenario writer, and the ``minegeo mast`` CLI end to end."""

from __future__ import annotations

import json

import numpy as np

from minegeo.cli import main
from minegeo.mast import (
    read_beacons_csv,
    read_scan_csv,
    simulate_mast_scenario,
    write_beacons_csv,
    write_mast_scenario,
    write_scan_csv,
)


def test_csv_round_trip(tmp_path):
    sc = simulate_mast_scenario(2, position=3, beacon1_rotation_deg=-10.0, sigma_bearing_deg=0.005)
    write_scan_csv(tmp_path / "scan.csv", sc.scan)
    write_beacons_csv(tmp_path / "beacons.csv", sc.beacons)
    scan = read_scan_csv(tmp_path / "scan.csv")
    np.testing.assert_allclose(scan.range_m, sc.scan.range_m, atol=1e-6)
    np.testing.assert_allclose(scan.bearing_deg, sc.scan.bearing_deg, atol=1e-8)
    assert scan.sigma_range_m == 0.003 and scan.sigma_bearing_deg == 0.005
    bs = read_beacons_csv(tmp_path / "beacons.csv")
    assert [b.beacon_id for b in bs] == ["B1", "B2"]
    np.testing.assert_allclose(bs[0].vertices_m, sc.beacons[0].vertices_m, atol=1e-6)
    ccw = read_scan_csv(tmp_path / "scan.csv", counter_clockwise=True)
    np.testing.assert_allclose(ccw.bearing_deg, -scan.bearing_deg)


def test_no_return_rows_are_skipped(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text("# sigma_range_m: 0.002\nbearing_deg,range_m\n0.0,1.5\n0.5,\n1.0,0\n1.5,nan\n2.0,1.6\n")
    s = read_scan_csv(p)
    assert len(s) == 2 and s.metadata["no_return_rows"] == 3 and s.sigma_range_m == 0.002


def test_cli_end_to_end(tmp_path, capsys):
    paths = write_mast_scenario(tmp_path / "sc", seed=3, position=2, beacon1_rotation_deg=10.0,
                                mine_origin_m=(500000.0, 6000000.0))
    truth = json.loads(paths["truth"].read_text())
    out = tmp_path / "out"
    rc = main(["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]), "--out", str(out)])
    assert rc == 0
    r = json.loads((out / "result.json").read_text())
    for key in ("status", "x", "y", "azimuth_deg", "azimuth_dms", "covariance", "ellipse95", "sigma0",
                "segmentation_option", "icp_iterations"):
        assert key in r
    assert r["status"] == "ok"
    assert abs(r["x"] - truth["x_m"]) < 0.003 and abs(r["y"] - truth["y_m"]) < 0.003
    assert np.asarray(r["covariance"]).shape == (3, 3)
    assert set(r["ellipse95"]) == {"a_m", "b_m", "orientation_deg"}
    assert r["provenance"]["inputs"][0]["sha256"]
    assert sorted(f.name for f in out.iterdir()) == ["report.html", "result.json"]
    html = (out / "report.html").read_text(encoding="utf-8")
    assert 'data-status="OK"' in html and "95 % error ellipse" in html and "Parameters used" in html
    printed = capsys.readouterr().out
    assert "x = " in printed
    assert f"written: {out / 'result.json'}, {out / 'report.html'}" in printed


def test_cli_failed_status_and_user_error(tmp_path, capsys):
    paths = write_mast_scenario(tmp_path / "sc", seed=3, position=4, visible_beacons=())
    out = tmp_path / "out"
    rc = main(["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"]), "--out", str(out)])
    assert rc == 1
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "failed" and r["reason"]
    assert "FAILED" in capsys.readouterr().out
    assert 'data-status="FAILED"' in (out / "report.html").read_text(encoding="utf-8")
    rc = main(["mast", "--scan", str(tmp_path / "missing.csv"), "--beacons", str(paths["beacons"]),
               "--out", str(out)])
    assert rc == 2
    assert "error" in capsys.readouterr().err


def test_scenario_files_bit_identical_under_seed(tmp_path):
    a = write_mast_scenario(tmp_path / "a", seed=9, position=5, beacon1_rotation_deg=10.0, sigma_bearing_deg=0.01)
    b = write_mast_scenario(tmp_path / "b", seed=9, position=5, beacon1_rotation_deg=10.0, sigma_bearing_deg=0.01)
    for key in ("scan", "beacons"):
        assert a[key].read_bytes() == b[key].read_bytes()
    c = write_mast_scenario(tmp_path / "c", seed=10, position=5, beacon1_rotation_deg=10.0, sigma_bearing_deg=0.01)
    assert a["scan"].read_bytes() != c["scan"].read_bytes()


def test_warmup_compiles():
    from minegeo.mast import _warmup

    _warmup()


def test_cli_beacon_survey_sigma_enlarges_ellipse(tmp_path):
    paths = write_mast_scenario(tmp_path / "sc", seed=4, position=4)
    args = ["mast", "--scan", str(paths["scan"]), "--beacons", str(paths["beacons"])]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    assert main(args + ["--out", str(tmp_path / "b"), "--sigma-beacon-m", "0.002"]) == 0
    a = json.loads((tmp_path / "a" / "result.json").read_text())
    b = json.loads((tmp_path / "b" / "result.json").read_text())
    assert b["details"]["noise_model"]["sigma_beacon_m"] == 0.002
    assert b["ellipse95"]["a_m"] > 1.2 * a["ellipse95"]["a_m"]
    assert b["details"]["dof"] == a["details"]["dof"]  # pseudo-observations add as many unknowns
