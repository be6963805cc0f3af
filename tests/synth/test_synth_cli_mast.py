"""``minegeo synth --mast-only`` writes a MAST scenario that ``minegeo mast`` solves."""

import json

from minegeo.cli import main


def test_synth_writes_solvable_mast_scenario(tmp_path):
    out = tmp_path / "m"
    assert main(["synth", str(out), "--mast-only", "--seed", "4"]) == 0
    assert {p.name for p in out.iterdir()} == {"scan.csv", "beacons.csv", "truth.json", "result.json"}
    res = tmp_path / "res"
    assert main(["mast", "--scan", str(out / "scan.csv"), "--beacons", str(out / "beacons.csv"),
                 "--out", str(res)]) == 0
    r = json.loads((res / "result.json").read_text())
    t = json.loads((out / "truth.json").read_text())
    assert r["status"] == "ok"
    assert abs(r["x"] - t["x_m"]) < 0.01 and abs(r["y"] - t["y_m"]) < 0.01
