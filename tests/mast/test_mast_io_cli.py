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


# Run in a fresh interpreter so that kernels compiled by earlier tests of this process cannot make
# the check pass. The MAST kernels called from Python (every dispatcher of minegeo.mast._kernels
# imported by another minegeo.mast module; _line_of, _prefix_sums and _sse_range are only called
# from inside other kernels and are linked into them) must have no signature before _warmup(), one
# after it, and the pipeline (simulate a scene, locate_scanner) must then add none: warmup compiled
# (or loaded from Numba's disk cache) exactly the types the pipeline uses. A second _warmup() and
# the pipeline run under a numba:compile listener (the events RunClock times) and must trigger none.
_WARMUP_PROBE = """
import importlib, json, pkgutil
from numba.core import event
from numba.core.registry import CPUDispatcher
import minegeo.mast as M
from minegeo.mast import _kernels as K
kernels = {n: f for n, f in vars(K).items() if isinstance(f, CPUDispatcher)}
entry = set()
for m in pkgutil.iter_modules(M.__path__):
    if m.name != "_kernels":
        mod = importlib.import_module("minegeo.mast." + m.name)
        entry |= {n for n, f in vars(mod).items() if any(f is k for k in kernels.values())}
sigs = lambda: {n: sorted(map(str, kernels[n].signatures)) for n in sorted(entry)}
before = sigs()
M._warmup()
after = sigs()
rec = event.RecordingListener()
with event.install_listener("numba:compile", rec):
    M._warmup()
    sc = M.simulate_mast_scenario(2, position=3)
    res = M.locate_scanner(sc.scan, sc.beacons)
compiled = sorted({ev.data["dispatcher"].py_func.__name__ for _, ev in rec.buffer})
print(json.dumps({"before": before, "after": after, "pipeline": sigs(), "compiled": compiled,
                  "status": res.status}))
"""


def test_warmup_compiles():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _WARMUP_PROBE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(d["before"]) >= {"_cast_rays", "_nearest_segment", "_grow_segments", "_split_segments"}, d
    assert all(v == [] for v in d["before"].values()), d["before"]  # nothing compiled at import
    assert all(len(v) >= 1 for v in d["after"].values()), d["after"]  # every entry kernel compiled
    assert d["pipeline"] == d["after"], d  # the pipeline needed no signature warmup missed
    assert d["compiled"] == [] and d["status"] == "ok", d


def test_package_warmup_times_every_subpackage(monkeypatch):
    """minegeo.warmup() calls each subpackage's _warmup once and returns its time under its name."""
    import importlib
    import time

    import minegeo

    calls = []
    for name in minegeo._WARMUP_MODULES:
        mod = importlib.import_module(name)
        if hasattr(mod, "_warmup"):
            monkeypatch.setattr(mod, "_warmup", lambda name=name: (calls.append(name), time.sleep(0.02)))
    t = minegeo.warmup()
    assert list(t) == list(minegeo._WARMUP_MODULES), t
    assert {"minegeo.geometry", "minegeo.registration", "minegeo.mast", "minegeo.localize"} <= set(t)
    with_kernels = [n for n in minegeo._WARMUP_MODULES if hasattr(importlib.import_module(n), "_warmup")]
    assert calls == with_kernels and "minegeo.mast" in calls
    assert all(t[n] >= 0.02 for n in with_kernels), t  # each time includes its own _warmup
    assert all(0.0 <= v < 5.0 for v in t.values()), t


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
