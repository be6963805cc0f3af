"""Issue 19, deliverables 3 and 4 end to end: a map and a scan exported as E57 (two scans each, with
poses, written by pye57) go through ``minegeo georef`` and ``minegeo localize --dxf``; the
placement.dxf read back by ezdxf gives the scan origin and the trajectory in the CRS exactly as
result.json and trajectory_global.csv state them; a failed localization draws nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import require_extra

pye57 = require_extra("pye57")
ezdxf = require_extra("ezdxf")

from minegeo.cli import main  # noqa: E402


def _write_e57_two_scans(path, points):
    """Split ``points`` (a frame F) into two E57 scans stored in their own frames with poses back to F."""
    half = len(points) // 2
    poses = [(np.array([np.cos(0.35), 0.0, 0.0, np.sin(0.35)]), np.array([3.0, -2.0, 0.5])),
             (np.array([np.cos(-0.6), np.sin(-0.6) * 0.6, 0.0, np.sin(-0.6) * 0.8]), np.array([-40.0, 25.0, -1.0]))]
    with pye57.E57(str(path), mode="w") as e:
        for i, (part, (q, t)) in enumerate(zip((points[:half], points[half:]), poses, strict=True)):
            w, x, y, z = q
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
            local = (part - t) @ R  # p_scan = R^T (p_F - t)
            e.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]},
                             name=f"setup {i + 1}", rotation=q, translation=t)


@pytest.fixture(scope="module")
def e57_mine(tmp_path_factory):
    from minegeo.io import write_gcps, write_trajectory
    from minegeo.synth import Velodyne16, build_map, build_world, local_scan, make_gcps

    d = tmp_path_factory.mktemp("e57dxf")
    world = build_world("small", 0)
    _write_e57_two_scans(d / "map.e57", build_map(world, seed=1).global_points)
    gcps, _ = make_gcps(world, n=8, seed=2)
    write_gcps(d / "gcps.csv", gcps)
    c, tr, T = local_scan(world, "regular", 20.0, Velodyne16(), seed=3, max_rays=20_000)
    _write_e57_two_scans(d / "ok.e57", c.global_points)
    write_trajectory(d / "ok.txt", tr, format="tum")
    other = build_world("small", 5)
    c2, _, _ = local_scan(other, "curve", 20.0, Velodyne16(), seed=11, max_rays=20_000)
    _write_e57_two_scans(d / "elsewhere.e57", c2.global_points)
    rc = main(["georef", "--map", str(d / "map.e57"), "--gcps", str(d / "gcps.csv"), "--out", str(d / "map_geo.ply"),
               "--report", str(d / "georef")])
    assert rc == 0
    return {"dir": d, "T_map_scan": T}


def test_localize_e57_scan_and_write_placement_dxf(e57_mine, capsys):
    d = e57_mine["dir"]
    out = d / "loc_ok"
    rc = main(["localize", "--map", str(d / "map_geo.ply"), "--scan", str(d / "ok.e57"), "--trajectory",
               str(d / "ok.txt"), "--out", str(out), "--dxf"])
    assert rc == 0
    assert "placement.dxf" in capsys.readouterr().out
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "ok"
    # the E57 scan (two setups merged by their poses) is the synthetic scan: it lands where the truth says
    T = np.asarray(r["T_map_scan"])
    assert np.linalg.norm(T[:3, 3] - e57_mine["T_map_scan"][:3, 3]) < 0.2
    from minegeo._provenance import sha256_file

    assert r["dxf"]["file"] == "placement.dxf" and r["dxf"]["sha256"] == sha256_file(out / "placement.dxf")
    assert r["dxf"]["crs"] == r["crs"] and r["dxf"]["frame"] == "crs"
    doc = ezdxf.readfile(out / "placement.dxf")
    msp = doc.modelspace()
    (pt,) = msp.query('POINT[layer=="MINEGEO_SCAN_ORIGINS"]')
    want = np.asarray(r["T_crs_scan"])[:3, 3]
    assert np.abs(np.array(tuple(pt.dxf.location)) - want).max() < 1e-3
    assert tuple(pt.dxf.location) == tuple(want)  # in fact exactly
    (tr,) = msp.query('POLYLINE[layer=="MINEGEO_TRAJECTORY"]')
    rows = [ln.split(",") for ln in (out / "trajectory_global.csv").read_text().splitlines() if not ln.startswith("#")]
    head, rows = rows[0], rows[1:]
    enh = np.array([[float(r_[head.index(c)]) for c in ("E_m", "N_m", "H_m")] for r_ in rows])
    np.testing.assert_array_equal(np.array([tuple(v) for v in tr.points()]), enh)
    assert len(msp.query('POLYLINE[layer=="MINEGEO_ELLIPSE95"]')) == 1
    assert [t.dxf.text for t in msp.query("TEXT")] == ["ok"]


def test_failed_localization_draws_nothing(e57_mine):
    d = e57_mine["dir"]
    out = d / "loc_failed"
    rc = main(["localize", "--map", str(d / "map_geo.ply"), "--scan", str(d / "elsewhere.e57"), "--out", str(out),
               "--dxf"])
    r = json.loads((out / "result.json").read_text())
    assert rc == 1 and r["status"] in ("failed", "ambiguous")
    doc = ezdxf.readfile(out / "placement.dxf")
    assert len(doc.modelspace()) == 0
    assert "elsewhere (" in dict(doc.header.custom_vars)["MINEGEO_NOT_PLACED"]
    assert r["dxf"]["layers"] == {} and r["dxf"]["placed"] == []


def test_prepare_map_reads_an_e57_map(e57_mine, capsys):
    """``prepare-map`` takes the two-scan E57 map (streamed through ``iter_e57_chunks``)."""
    from minegeo.io import read_point_cloud

    d = e57_mine["dir"]
    assert main(["prepare-map", "--map", str(d / "map.e57"), "--out", str(d / "map_e57.npz")]) == 0
    n = len(read_point_cloud(d / "map.e57"))
    assert f"{n} ->" in capsys.readouterr().out and (d / "map_e57.npz").is_file()
