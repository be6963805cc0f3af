"""``minegeo georef`` end to end in tmp_path, the georeferenced-map files, and CLI error handling."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import require_extra

from minegeo.cli import main
from minegeo.errors import FileFormatError
from minegeo.georef import load_georeferenced_map, read_georef, sidecar_path
from minegeo.io import ControlPoints, PointCloud, read_gcps, read_point_cloud, write_gcps, write_point_cloud


@pytest.fixture(scope="module")
def synth_gcps():
    """GCPs on the walls of the synthetic mine (minegeo.synth) with their rigid truth T_crs_map."""
    synth = pytest.importorskip("minegeo.synth")
    world = synth.build_world("small", seed=0)
    gcps, info = synth.make_gcps(world, n=8, seed=1, crs="EPSG:5186", sigma_m=0.005)
    return gcps, info


def _map_cloud(gcps: ControlPoints, n=3000, seed=0):
    """A small stand-in map: points spread over the GCP area plus the GCP marks themselves."""
    rng = np.random.default_rng(seed)
    lo, hi = gcps.local_xyz.min(axis=0) - 5.0, gcps.local_xyz.max(axis=0) + 5.0
    pts = np.vstack([rng.uniform(lo, hi, (n, 3)), gcps.local_xyz])
    return PointCloud(pts, attributes={"intensity": rng.integers(0, 255, len(pts)).astype(np.uint16)})


def _write_inputs(tmp_path, gcps, fmt="ply"):
    mp = tmp_path / f"map.{fmt}"
    write_point_cloud(mp, _map_cloud(gcps))
    gp = tmp_path / "gcps.csv"
    write_gcps(gp, gcps)
    return mp, gp


def test_cli_end_to_end_synth(tmp_path, synth_gcps, capsys):
    gcps, info = synth_gcps
    mp, gp = _write_inputs(tmp_path, gcps)
    out = tmp_path / "geo" / "map_geo.ply"
    rep = tmp_path / "report"
    rc = main(["georef", "--map", str(mp), "--gcps", str(gp), "--crs", "EPSG:5186", "--out", str(out),
               "--report", str(rep), "--model", "rigid"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "status:" in text and "sigma0" in text
    res = json.loads((rep / "result.json").read_text())
    assert res["status"] in ("ok", "warning")
    assert res["result"]["chi2"]["verdict"] in ("PASSED", "FAILED")
    assert len(res["provenance"]["inputs"]) == 2 and len(res["provenance"]["inputs"][0]["sha256"]) == 64
    assert res["parameters"]["model"] == "rigid"
    # truth: rigid T_crs_map of the synthetic mine, recovered to the noise level (sigma 5 mm)
    T_true = np.asarray(info["T_crs_map"])
    T = np.asarray(res["T_crs_map"])
    ang = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1)))
    assert ang < 0.01
    assert np.max(np.abs(T[:3, 3] - T_true[:3, 3])) < 0.05
    # report: self-contained HTML with the tables, verdict and embedded plot
    html = (rep / "report.html").read_text()
    assert "<table>" in html and "GCP01" in html and ("PASSED" in html or "FAILED" in html)
    assert "data:image/png;base64," in html and "src='http" not in html
    assert "EPSG:5186" in html and "KGD2002" in html
    # the georeferenced map: stored relative to the recorded origin, loadable with its georeferencing
    assert sidecar_path(out).exists()
    cloud, r = load_georeferenced_map(out)
    assert cloud.crs == "EPSG:5186" and cloud.frame == "crs"
    np.testing.assert_array_equal(cloud.origin, r.origin)
    assert np.all(np.abs(cloud.points[:, :2]) < 5000.0)  # small numbers in the file
    src = read_point_cloud(mp)
    expected = src.points @ r.T_crs_map[:3, :3].T + r.T_crs_map[:3, 3]
    np.testing.assert_allclose(cloud.global_points, expected, atol=1e-6)
    np.testing.assert_array_equal(cloud.attributes["intensity"], src.attributes["intensity"])
    # the GCP marks (last rows of the map) land on their surveyed coordinates within the noise
    k = len(gcps)
    assert np.max(np.abs(cloud.global_points[-k:] - gcps.crs_enh)) < 0.03
    # the sidecar also loads by its own name, and result.json reads back as the same result
    _, r2 = load_georeferenced_map(sidecar_path(out))
    r3 = read_georef(rep / "result.json")
    np.testing.assert_array_equal(r2.T_crs_map, r.T_crs_map)
    np.testing.assert_array_equal(r3.T_crs_map, r.T_crs_map)


def test_cli_las_output_and_deterministic(tmp_path, synth_gcps, capsys):
    require_extra("laspy")
    gcps, _ = synth_gcps
    mp, gp = _write_inputs(tmp_path, gcps)
    outs = []
    for k in range(2):
        out = tmp_path / f"geo{k}.las"
        assert main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(out),
                     "--report", str(tmp_path / f"rep{k}")]) == 0
        outs.append(out)
    capsys.readouterr()
    assert outs[0].read_bytes() == outs[1].read_bytes()
    # re-running into the same path rewrites bit-identical map and sidecar files
    side0 = sidecar_path(outs[0]).read_bytes()
    map0 = outs[0].read_bytes()
    assert main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(outs[0]),
                 "--report", str(tmp_path / "rep0")]) == 0
    capsys.readouterr()
    assert sidecar_path(outs[0]).read_bytes() == side0 and outs[0].read_bytes() == map0
    a = json.loads((tmp_path / "rep0" / "result.json").read_text())["result"]
    b = json.loads((tmp_path / "rep1" / "result.json").read_text())["result"]
    a.pop("timings_s")
    b.pop("timings_s")
    assert a == b
    cloud, r = load_georeferenced_map(outs[0])
    np.testing.assert_array_equal(cloud.origin, r.origin)
    src = read_point_cloud(mp)
    expected = src.points @ r.T_crs_map[:3, :3].T + (r.T_crs_map[:3, 3] - r.origin)
    assert np.max(np.abs(cloud.points - expected)) <= 0.0005 + 1e-9  # LAS 1 mm integer grid


def test_load_detects_modified_map_and_missing_sidecar(tmp_path, synth_gcps, capsys):
    gcps, _ = synth_gcps
    mp, gp = _write_inputs(tmp_path, gcps)
    out = tmp_path / "map_geo.ply"
    assert main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(out), "--report", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    data = bytearray(out.read_bytes())
    data[-1] ^= 0xFF
    out.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="changed after it was georeferenced"):
        load_georeferenced_map(out)
    with pytest.raises(FileFormatError, match="no georeferencing sidecar"):
        load_georeferenced_map(mp)


def test_cli_unit_mismatch_exit_1_no_map(tmp_path, synth_gcps, capsys):
    gcps, _ = synth_gcps
    o = np.round(gcps.crs_enh.mean(axis=0) / 1000.0) * 1000.0
    km = ControlPoints(gcps.ids, gcps.local_xyz, (gcps.crs_enh - o) / 1000.0 + o, gcps.sigma_enh_m, crs=gcps.crs)
    mp, gp = _write_inputs(tmp_path, km)
    out = tmp_path / "map_geo.ply"
    rc = main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(out), "--report", str(tmp_path / "r")])
    text = capsys.readouterr().out
    assert rc == 1
    assert "FAILED" in text and "kilometres" in text
    assert not out.exists()
    res = json.loads((tmp_path / "r" / "result.json").read_text())
    assert res["status"] == "failed" and "unit check failed" in res["reason"]
    assert "FAILED" in (tmp_path / "r" / "report.html").read_text()


@pytest.mark.parametrize(
    "crs,msg",
    [("EPSG:999999", "unknown coordinate reference system"), ("EPSG:4326", "geographic")],
)
def test_cli_bad_crs_one_line_exit_2(tmp_path, synth_gcps, capsys, crs, msg):
    gcps, _ = synth_gcps
    g = ControlPoints(gcps.ids, gcps.local_xyz, gcps.crs_enh, gcps.sigma_enh_m, crs=None)
    mp, gp = _write_inputs(tmp_path, g)
    rc = main(["georef", "--map", str(mp), "--gcps", str(gp), "--crs", crs, "--out", str(tmp_path / "o.ply"),
               "--report", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2
    assert msg in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_cli_too_few_gcps_exit_2(tmp_path, capsys):
    g = ControlPoints(["A", "B"], [[0, 0, 0], [10, 0, 0]], [[200000, 550000, 100], [200010, 550000, 100]], 0.005,
                      crs="EPSG:5186")
    mp, gp = _write_inputs(tmp_path, g)
    assert read_gcps(gp).crs == "EPSG:5186"
    rc = main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(tmp_path / "o.ply"),
               "--report", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and "at least 3" in err


def test_cli_refuses_to_overwrite_input_map(tmp_path, synth_gcps, capsys):
    gcps, _ = synth_gcps
    mp, gp = _write_inputs(tmp_path, gcps)
    before = mp.read_bytes()
    rc = main(["georef", "--map", str(mp), "--gcps", str(gp), "--out", str(mp), "--report", str(tmp_path / "r")])
    assert rc == 2 and "input map" in capsys.readouterr().err
    assert mp.read_bytes() == before


def test_report_html_flags_escapes_and_no_plot_fallback():
    from minegeo.georef import georeference
    from minegeo.report.georef_report import georef_report_html, plot_georef_png

    rng = np.random.default_rng(5)
    x = rng.uniform(-100, 100, (7, 3))
    X = x + [300000.0, 4100000.0, 50.0] + rng.normal(0, 0.005, (7, 3))
    X[3, 1] += 0.1
    ids = ["A1", "A2", "A3", "<b>bad</b>", "A5", "A6", "A7"]
    r = georeference(ControlPoints(ids, x, X, 0.005, crs="EPSG:32652"))
    assert r.suspected_blunder_id == "<b>bad</b>"
    html = georef_report_html(r, png=None)
    assert "matplotlib is not installed" in html
    assert "&lt;b&gt;bad&lt;/b&gt;" in html and "<b>bad</b>" not in html
    assert "class='flag'" in html and "suspected blunder" in html
    assert "WARNING" in html and "FAILED" in html
    png = plot_georef_png(r)
    if png is not None:
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
