"""GCP CSV reading/writing, the LZF codec, and ``minegeo info`` end to end."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from helpers import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.cli import main
from minegeo.errors import FileFormatError, InputError
from minegeo.io import ControlPoints, PointCloud, read_gcps, write_gcps, write_point_cloud
from minegeo.io._lzf import lzf_compress, lzf_decompress

# ---------------------------------------------------------------- GCP


def _gcps(rng, k=6, local_sigma=False):
    return ControlPoints(
        ids=[f"GCP{i}" for i in range(k - 1)] + ["mark, with comma"],
        local_xyz=rng.uniform(-50, 50, (k, 3)),
        crs_enh=np.array([201_000.0, 551_000.0, 80.0]) + rng.uniform(0, 100, (k, 3)),
        sigma_enh_m=rng.uniform(0.002, 0.02, (k, 3)),
        sigma_local_m=rng.uniform(0.001, 0.01, (k, 3)) if local_sigma else None,
        crs="EPSG:5186",
    )


@pytest.mark.parametrize("local_sigma", [False, True])
def test_gcp_roundtrip(tmp_path, rng, local_sigma):
    g = _gcps(rng, local_sigma=local_sigma)
    write_gcps(tmp_path / "g.csv", g)
    text = (tmp_path / "g.csv").read_text()
    assert text.startswith("# crs: EPSG:5186\nid,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m")
    b = read_gcps(tmp_path / "g.csv")
    assert b.ids == g.ids and b.crs == "EPSG:5186"
    np.testing.assert_array_equal(b.local_xyz, g.local_xyz)
    np.testing.assert_array_equal(b.crs_enh, g.crs_enh)
    np.testing.assert_array_equal(b.sigma_enh_m, g.sigma_enh_m)
    if local_sigma:
        np.testing.assert_array_equal(b.sigma_local_m, g.sigma_local_m)
    else:
        assert b.sigma_local_m is None


def test_gcp_tolerant_reading(tmp_path, caplog):
    p = tmp_path / "survey.txt"
    p.write_text("# from the total station\n# CRS = EPSG:5186\nName\tX\tY\tZ\tEasting\tNorthing\tHeight\nA\t1\t2\t3\t201000.5\t551000.25\t80.125\n\nB\t4\t5\t6\t201010\t551020\t81\nC\t0\t9\t1\t201030\t551010\t82\n")
    with caplog.at_level(logging.WARNING, logger="minegeo.io"):
        g = read_gcps(p)
    assert g.ids == ["A", "B", "C"] and g.crs == "EPSG:5186"
    np.testing.assert_array_equal(g.sigma_enh_m, np.full((3, 3), 0.01))  # documented default
    assert "no sigma columns" in caplog.text
    assert read_gcps(p, default_sigma_m=0.003).sigma_enh_m[0, 0] == 0.003


@pytest.mark.parametrize(
    "content,match",
    [
        ("", "empty"),
        ("id,x,y,z,E,N\nA,1,2,3,4,5\n", "line 1: header lacks column\\(s\\) H"),
        ("id,x,y,z,E,N,H\n", "no control points"),
        ("id,x,y,z,E,N,H\nA,1,2,3,4,5\n", "line 2: expected 7 fields, found 6"),
        ("id,x,y,z,E,N,H\nA,1,2,3,4,5,six\n", "line 2: H = 'six' is not a number"),
        ("id,x,y,z,E,N,H\nA,1,2,3,4,5,6\n\nA,1,2,3,4,5,6\n", "line 4: duplicate id 'A' \\(first on line 2\\)"),
        ("id,x,y,z,E,N,H\nA,1,2,nan,4,5,6\n", "line 2: z is nan"),
        ("id,x,y,z,E,N,H,sigma_E_m,sigma_N_m,sigma_H_m\nA,1,2,3,4,5,6,0.01,0,0.01\n", "line 2: sigma_N_m = 0 must be > 0"),
        ("id,x,y,z,E,N,H,sigma_E_m\nA,1,2,3,4,5,6,0.01\n", "all three"),
    ],
)
def test_gcp_errors(tmp_path, content, match):
    p = tmp_path / "gcp.csv"
    p.write_text(content)
    with pytest.raises(FileFormatError, match=match) as ei:
        read_gcps(p)
    assert "gcp.csv" in str(ei.value)


def test_gcp_crs_conflict(tmp_path, rng):
    write_gcps(tmp_path / "g.csv", _gcps(rng))
    with pytest.raises(FileFormatError, match="crs"):
        read_gcps(tmp_path / "g.csv", crs="EPSG:32617")
    with pytest.raises(InputError):
        write_gcps(tmp_path / "x.csv", "not gcps")


# ---------------------------------------------------------------- LZF


@settings(max_examples=30, deadline=None)
@given(data=st.binary(max_size=5000), reps=st.integers(1, 40))
def test_lzf_roundtrip(data, reps):
    for d in (data, data * reps):
        c = lzf_compress(d)
        assert len(c) <= len(d) + len(d) // 32 + 1
        assert lzf_decompress(c, len(d)) == d


def test_lzf_known_stream_and_errors():
    # hand-made liblzf stream: literal "abc" then a back reference of length 6 at distance 3
    stream = bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2])
    assert lzf_decompress(stream, 9) == b"abcabcabc"
    with pytest.raises(InputError, match="corrupt"):
        lzf_decompress(bytes([(1 << 5), 5]), 10)  # reference before the start
    with pytest.raises(InputError, match="more than"):
        lzf_decompress(stream, 5)
    with pytest.raises(InputError, match="declares"):
        lzf_decompress(stream, 20)


# ---------------------------------------------------------------- minegeo info


def test_cli_info_cloud_and_json(tmp_path, rng, capsys):
    c = PointCloud(rng.normal(size=(40, 3)) + [201000.0, 551000.0, 80.0], attributes={"intensity": np.arange(40, dtype=np.uint16)}, crs="EPSG:5186")
    write_point_cloud(tmp_path / "c.ply", c)
    assert main(["info", str(tmp_path / "c.ply"), "--json", str(tmp_path / "info.json")]) == 0
    out = capsys.readouterr().out
    assert "points    40" in out and "EPSG:5186" in out and "intensity" in out and "uint16" in out
    doc = json.loads((tmp_path / "info.json").read_text())
    assert doc["result"]["points"] == 40
    assert doc["result"]["crs"] == "EPSG:5186"
    assert doc["provenance"]["inputs"][0]["sha256"] == doc["result"]["sha256"]
    assert "numpy" in doc["provenance"]["versions"]


def test_cli_info_real_subt_zip(capsys):
    p = shared_data("subt_urban_satsop_scan", "Urban_Circuit_LowRes_Scan_alpha_LowerFloor.pcd.zip")
    assert main(["info", str(p), "--json", "-"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["result"]["points"] == 259_086 and doc["result"]["format"] == "pcd"


def test_cli_info_trajectory_and_gcp(tmp_path, rng, capsys):
    p = shared_data("ctu_cave_mine_uav_trajectories", "bull_rock_cave", "1_back", "trajectory_groundtruth.txt")
    assert main(["info", str(p), "--kind", "trajectory"]) == 0
    assert "poses          325" in capsys.readouterr().out
    write_gcps(tmp_path / "g.csv", _gcps(rng))
    assert main(["info", str(tmp_path / "g.csv"), "--kind", "gcp"]) == 0
    assert "EPSG:5186" in capsys.readouterr().out


@pytest.mark.parametrize(
    "name,content,match",
    [
        ("bad.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n", "header declares 3 points but 1"),
        ("bad.xyz", "", "empty"),
        ("bad.fls", "x", "unknown point-cloud file extension"),
        ("missing.ply", None, "no such file"),
    ],
)
def test_cli_info_bad_file_one_line_exit_2(tmp_path, capsys, name, content, match):
    p = tmp_path / name
    if content is not None:
        p.write_text(content)
    assert main(["info", str(p)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.count("\n") == 0, err  # one line, no traceback
    assert err.startswith("minegeo info: error:") and name in err
    assert pytest.importorskip("re").search(match, err), err
    assert "Traceback" not in captured.err + captured.out


@settings(max_examples=30, deadline=None)
@given(data=st.binary(max_size=3000), reps=st.integers(1, 30))
def test_lzf_kernel_matches_naive_decoder(data, reps):
    from reference.naive_lzf import naive_lzf_decompress

    d = data * reps
    assert naive_lzf_decompress(lzf_compress(d)) == d
