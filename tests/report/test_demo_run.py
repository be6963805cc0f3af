"""``minegeo demo`` end to end: the map is built by ``minegeo slam`` from the synthetic VLP-16 frames,
georeferenced from control points read off it, and the scans of the mapped drifts are localized in
it, close to the truth in EPSG:5186; its report and the slam step's open in Chromium (one full run,
~30 s with a warm Numba cache)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_reports_browser import browser, check_report  # noqa: F401  (browser: the Chromium fixture)

from minegeo.cli import main
from minegeo.io import read_gcps, read_point_cloud

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "d"
    assert main(["-q", "demo", "--out", str(out)]) == 0
    return out, json.loads((out / "result.json").read_text())


def test_the_slam_step_ran_and_wrote_the_map(demo):
    out, rec = demo
    steps = {r["step"]: r for r in rec["steps"]}
    assert [r["step"] for r in rec["steps"]][:5] == ["synth", "sequence", "slam", "georef", "mast"]
    assert steps["slam"]["status"] == "ok" and steps["slam"]["report"] == "slam/report.html"
    s = json.loads((out / "slam" / "result.json").read_text())
    n_frames = len(list((out / "sequence" / "frames").glob("*.ply")))
    assert s["result"]["frames"] == n_frames == rec["parameters"]["sequence"]["frames"] > 50
    assert s["result"]["loops_accepted"] >= 1  # the loop is closed
    assert rec["slam"]["map_points"] == s["result"]["map_points"] == len(read_point_cloud(out / "slam" / "map.ply"))
    assert rec["slam"]["map_points"] > 10_000
    assert rec["slam"]["ate_rmse_m"] < 0.3  # SLAM trajectory against the truth, no alignment
    html = (out / "report.html").read_text()
    assert 'href="slam/report.html"' in html and "sequence" in html
    # the second process that compiles the mast/localize kernels on a cold cache (else not needed)
    bc = rec["background_compilation"]
    assert bc["modules"] == ["minegeo.mast", "minegeo.localize"]
    assert bc["status"] in ("ok", "not needed (kernels already cached)",
                            "not started (one CPU core: a second process would compete with this one)"), bc
    assert "background compilation" in html


def test_georef_takes_the_slam_map_and_control_points_read_off_it(demo):
    out, rec = demo
    g = json.loads((out / "georef" / "result.json").read_text())
    inputs = [p["path"] for p in g["provenance"]["inputs"]]
    assert inputs == [str(out / "slam" / "map.ply"), str(out / "gcps_slam.csv")]
    assert rec["georef"]["map"] == str(out / "slam" / "map.ply") and g["status"] == "ok"
    picked = read_gcps(out / "gcps_slam.csv")
    surveyed = read_gcps(out / "mine" / "gcps.csv")
    assert 3 <= len(picked.ids) == rec["georef"]["n_gcps"] < len(surveyed.ids)  # only the mapped drifts
    # same grid coordinates; map coordinates in the SLAM frame, not the synthetic world frame
    k = [surveyed.ids.index(i) for i in picked.ids]
    assert np.array_equal(picked.crs_enh, surveyed.crs_enh[k])
    assert np.abs(picked.local_xyz - surveyed.local_xyz[k]).max() > 1.0
    assert rec["georef"]["trajectory_error_rms_m"] < 0.2


def test_the_scans_of_the_mapped_drifts_are_localized_close_to_the_truth(demo):
    out, rec = demo
    loc = [r for r in rec["steps"] if r["step"].startswith("localize")]
    assert [r["step"] for r in loc] == [f"localize {n}" for n in rec["parameters"]["localized_scans"]]
    assert len(loc) >= 2 and all(r["status"] == "ok" for r in loc)
    truth = json.loads((out / "mine" / "truth.json").read_text())
    T_crs_map = np.asarray(truth["T_crs_map"])
    for name in rec["parameters"]["localized_scans"]:
        r = json.loads((out / "localize" / name / "result.json").read_text())
        sc = next(s for s in truth["scans"] if s["name"] == name)
        T_true = T_crs_map @ np.asarray(sc["T_map_scan"])
        assert np.linalg.norm(np.asarray(r["T_crs_scan"])[:3, 3] - T_true[:3, 3]) < 0.3, name
    assert rec["status"] == "ok"


def test_demo_report_and_the_slam_report_in_the_browser(demo, browser):  # noqa: F811
    out, rec = demo
    info = check_report(browser, out / "report.html", "OK", min_images=1)  # the plan view
    links = [h for h in info["links"] if not h.startswith("#")]
    assert "slam/report.html" in links and len(links) == sum(1 for r in rec["steps"] if r["report"])
    check_report(browser, out / "slam" / "report.html", "OK")


def test_demo_repeated_from_its_result_json(demo, tmp_path):
    """``minegeo demo --config OUT/result.json`` runs the demo again: every data file (frames, map,
    trajectories, graph, loops, control points, MAST scenario, localized trajectories) byte-identical,
    and the same localized poses; the JSON records and HTML reports differ in times and folder names."""
    out, rec = demo
    assert rec["provenance"]["arguments"]["seed"] == 1
    again = tmp_path / "again"
    assert main(["-q", "demo", "--config", str(out / "result.json"), "--out", str(again)]) == 0

    def data_files(d):
        return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file()
                      and p.suffix not in (".json", ".html", ".npz") and p.name != "report.txt")
    names = data_files(out)
    assert len(names) > 100 and names == data_files(again)
    assert any(n.startswith("slam/") for n in names) and any(n.startswith("localize/") for n in names)
    for n in names:
        assert (out / n).read_bytes() == (again / n).read_bytes(), n
    for name in rec["parameters"]["localized_scans"]:
        a, b = (json.loads((d / "localize" / name / "result.json").read_text()) for d in (out, again))
        assert a["status"] == b["status"] and a["T_crs_scan"] == b["T_crs_scan"], name

