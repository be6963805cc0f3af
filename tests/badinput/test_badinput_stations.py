"""``minegeo info STATIONS.csv`` on a bad stations CSV (slam_contract.md, control stations): every
mistake is one line naming the line of the file, exit 2, nothing written, the input unchanged
(the contract of tests/badinput/_contract.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from _contract import assert_user_error

HEADER = "id,t_start,t_end,E,N,H,sigma_h_m,sigma_v_m,role"
ROWS = ["S1,10.0,15.0,201345.112,551203.447,87.402,0.005,0.010,control",
        "S2,40.0,45.0,201402.880,551388.019,86.911,0.005,0.010,check",
        "S3,70.0,75.0,201512.004,551502.771,86.100,0.005,0.010,control"]


def _csv(tmp: Path, rows, header=HEADER) -> Path:
    p = tmp / "stations.csv"
    p.write_text("\n".join(["# crs: EPSG:5186", header, *rows]) + "\n", encoding="utf-8")
    return p


def _sub(i: int, old: str, new: str) -> list[str]:
    rows = list(ROWS)
    rows[i] = rows[i].replace(old, new, 1)
    return rows


#: case -> (rows, text the error line must hold); line numbers count the '# crs:' line and the header
CASES = {
    "unknown_role": (_sub(1, ",check", ",chek"), "line 4: station S2: role 'chek'"),
    "end_before_start": (_sub(1, "40.0,45.0", "45.0,40.0"), "line 4: station S2: t_end 40 s is before"),
    "overlapping_spans": (_sub(2, "70.0,75.0", "44.0,75.0"), "line 5: station S3 [44, 75] s overlaps station S2"),
    "sigma_zero": (_sub(0, "0.005,0.010", "0,0.010"), "line 3: sigma_h_m = 0 must be > 0"),
    "sigma_negative": (_sub(2, "0.005,0.010", "0.005,-0.01"), "line 5: sigma_v_m = -0.01 must be > 0"),
    "duplicate_id": (_sub(2, "S3,", "S1,"), "line 5: duplicate id 'S1' (first on line 3)"),
    "no_control": ([r.replace(",control", ",check") for r in ROWS], "no station has role 'control'"),
    "not_a_number": (_sub(1, "201402.880", "201402,880"), "line 4: expected 9 fields, found 10"),
    "nan_time": (_sub(0, "10.0", "nan"), "line 3: t_start is nan"),
    "header_only": ([], "no stations after the header"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_stations_csv(case, tmp_path, capsys):
    rows, expect = CASES[case]
    f = _csv(tmp_path, rows)
    out = tmp_path / "out" / "info.json"
    assert_user_error("info", [f, "--json", out], capsys, inputs=[f], outputs=[out], expect=expect)


def test_bad_stations_header(tmp_path, capsys):
    f = _csv(tmp_path, ROWS, header="id,t_start,t_end,E,N,H,sigma_h_m,role")
    assert_user_error("info", [f], capsys, inputs=[f], expect="line 2: the stations header lacks column(s) sigma_v_m")


#: minegeo synth --stream ... stations options -> (extra argv, text of the error line)
SYNTH_CASES = {
    "control_every_without_spacing": (["--stream", "vehicle", "--control-every", "3"], "--station-spacing-m"),
    "offset_without_spacing": (["--stream", "vehicle", "--station-offset", "0", "0", "1"], "--station-spacing-m"),
    "offset_wrong_units": (["--stream", "vehicle", "--station-spacing-m", "50", "--station-offset", "0", "0", "-450"],
                           "wrong units"),
    "geographic_crs": (["--stream", "vehicle", "--station-spacing-m", "50", "--crs", "EPSG:4326"], "projected"),
    "spacing_too_short": (["--stream", "vehicle", "--station-spacing-m", "2"], "--station-spacing-m"),
    "no_station_in_run": (["--stream", "vehicle", "--station-spacing-m", "300", "--duration-s", "2"],
                          "no station stop falls inside the 2 s run"),
}


@pytest.mark.parametrize("case", sorted(SYNTH_CASES))
def test_bad_synth_station_options(case, tmp_path, capsys):
    extra, expect = SYNTH_CASES[case]
    out = tmp_path / "out"
    assert_user_error("synth", [out, *extra], capsys, outputs=[out / "stations.csv"], expect=expect)
    assert not out.exists()
