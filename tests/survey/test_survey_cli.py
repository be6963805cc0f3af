"""``minegeo adjust``: result.json schema, reports, JSON network input, typed errors -> exit 2."""

from __future__ import annotations

import json
import math

from helpers import shared_data

from minegeo.cli import main

GHILANI_15_5_JSON = {
    "name": "Ghilani Ex. 15.5 resection (JSON)",
    "points": {
        "P": {"x": 1303.599, "y": 1458.615},
        "Q": {"x": 1636.436, "y": 1310.468},
        "R": {"x": 1503.395, "y": 888.362},
        "S": {"x": 1506.262, "y": 785.061},
        "U": {"x": 1000.030, "y": 999.960},
    },
    "datum": {"type": "fix", "coordinates": ["P", "Q", "R", "S"]},
    "observations": [
        {
            "type": "angle",
            "at": "U",
            "from": "P",
            "to": "Q",
            "value_gon": 33.8805555555556,
            "sigma_gon": 0.00154320987654321,
        },
        {
            "type": "angle",
            "at": "U",
            "from": "Q",
            "to": "R",
            "value_gon": 42.7873456790123,
            "sigma_gon": 0.00185185185185185,
        },
        {
            "type": "angle",
            "at": "U",
            "from": "R",
            "to": "S",
            "value_gon": 11.6657407407407,
            "sigma_gon": 0.00185185185185185,
        },
    ],
}


def test_adjust_cli_writes_result_json_and_reports(tmp_path, capsys):
    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Ghilani21_10_DistanceAngle_fix.dat")
    out = tmp_path / "out"
    assert main(["adjust", str(dat), "--out", str(out)]) == 0
    d = json.loads((out / "result.json").read_text(encoding="utf-8"))
    c = d["points"]["C"]
    assert f"{c['x']:.4f}" == "9787.8250" and f"{c['y']:.4f}" == "8038.5354"
    assert f"{c['sx_m'] * 100:.3f}" == "9.523" and f"{c['sy_m'] * 100:.3f}" == "16.778"
    assert d["dof"] == 10 and d["sigma0"] > 0
    chi = d["chi2_test"]
    assert set(chi) >= {"value", "lower", "upper", "passed"} and chi["passed"] is False
    assert len(d["observations"]) == 14
    for o in d["observations"]:
        assert {"residual", "standardized_residual", "redundancy_number", "flag"} <= set(o)
    flagged = [o for o in d["observations"] if "w-test" in o["flag"]]
    assert any(o["type"] == "angle" and o["station"] == "D" and o["backsight"] == "A" for o in flagged)
    e = d["ellipses"]["points"]["C"]
    assert e["standard"]["semi_major_m"] > 0 and e["confidence_95"]["k"] > 2.4
    assert d["provenance"]["inputs"][0]["sha256"]
    assert "versions" in d["provenance"]
    txt = (out / "report.txt").read_text(encoding="utf-8")
    order = [
        txt.index(s)
        for s in (
            "ADJUSTMENT SUMMARY",
            "STATISTICS",
            "ADJUSTED COORDINATES",
            "OBSERVATIONS AND RESIDUALS",
            "ERROR ELLIPSES",
            "FLAGGED",
        )
    ]
    assert order == sorted(order)
    assert "FAILED" in txt
    html = (out / "report.html").read_text(encoding="utf-8")
    assert html.startswith("<!DOCTYPE html>") and "FAILED" in html
    assert "chi-square test FAILED" in capsys.readouterr().out


def test_json_network_equals_text_network(tmp_path):
    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Ghilani15_5_Angle_fix.dat")
    js = tmp_path / "net.json"
    js.write_text(json.dumps(GHILANI_15_5_JSON), encoding="utf-8")
    assert main(["adjust", str(js), "--out", str(tmp_path / "a")]) == 0
    assert main(["adjust", str(dat), "--out", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "result.json").read_text(encoding="utf-8"))
    b = json.loads((tmp_path / "b" / "result.json").read_text(encoding="utf-8"))
    for k in ("x", "y", "sx_m", "sy_m"):
        assert math.isclose(a["points"]["U"][k], b["points"]["U"][k], rel_tol=0, abs_tol=1e-12)
    assert (f"{a['points']['U']['x']:.4f}", f"{a['points']['U']['y']:.4f}") == ("999.9989", "1000.0253")
    assert a["sigma0"] == b["sigma0"]


def test_apriori_option_uses_chi2_ellipse(tmp_path):
    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Ghilani15_5_Angle_fix.dat")
    assert main(["adjust", str(dat), "--out", str(tmp_path), "--variance", "apriori"]) == 0
    d = json.loads((tmp_path / "result.json").read_text(encoding="utf-8"))
    e = d["ellipses"]["points"]["U"]["confidence_95"]
    assert f"{e['k']:.4f}" == "2.4477" and "chi2" in e["basis"]
    assert d["variance_used"] == "apriori"


def test_bad_inputs_exit_2_with_one_line(tmp_path, capsys):
    few = tmp_path / "few.dat"
    few.write_text(
        "[Coordinates]\nA 0 0\nB 100 0\nU 50 50\n[Datum]\nfix A B\n[Distances]\nA U 70.7 0.01\n",
        encoding="utf-8",
    )
    assert main(["adjust", str(few), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "cannot determine" in err and err.count("\n") == 1
    bad = tmp_path / "bad.dat"
    bad.write_text("[Coordinates]\nA 0 0\n[Datum]\nfix A\n[Bogus]\nA B 1\n", encoding="utf-8")
    assert main(["adjust", str(bad), "--out", str(tmp_path / "o2")]) == 2
    assert "unknown section [Bogus]" in capsys.readouterr().err
    col = tmp_path / "collinear.dat"
    col.write_text(
        "[Coordinates]\nA 0 0\nB 100 100\nU 200 200\n[Datum]\nfix A B\n[GridBearings,dms,s]\nA U 45°00'00\" 1\nB U 45°00'00\" 1\n",
        encoding="utf-8",
    )
    assert main(["adjust", str(col), "--out", str(tmp_path / "o3")]) == 2
    assert "singular" in capsys.readouterr().err
    assert main(["adjust", str(tmp_path / "missing.dat"), "--out", str(tmp_path / "o4")]) == 2
