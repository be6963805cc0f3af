"""Bad input: typed errors or a clear failed status with the reason."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import DegenerateGeometryError, FileFormatError, InputError, TooFewPointsError
from minegeo.mast import (
    Beacon,
    MastParams,
    ResectionObservations,
    Scan2D,
    locate_scanner,
    read_beacons_csv,
    read_scan_csv,
    resect_scanner_pose,
    simulate_mast_scenario,
)


def _obs(n, normals):
    b = np.radians(np.linspace(-40, 40, n))
    r = np.full(n, 5.0)
    pts = np.column_stack([r * np.sin(b), r * np.cos(b)])
    nrm = np.asarray(normals, dtype=float)[np.arange(n) % len(normals)]
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    return ResectionObservations(b, r, pts, nrm)


def test_fewer_observations_than_unknowns():
    with pytest.raises(TooFewPointsError, match="3 unknowns"):
        resect_scanner_pose(_obs(2, [[0, 1], [1, 0]]), [0, 0, 0], 0.003)


def test_collinear_control_in_resection():
    # every return on lines with the same normal: position along the lines is undetermined
    with pytest.raises(DegenerateGeometryError):
        resect_scanner_pose(_obs(30, [[0.0, 1.0]]), [0, 0, 0], 0.003)


def test_exact_resection_recovers_pose():
    obs = _obs(30, [[0.0, 1.0], [1.0, 0.2], [-0.5, 1.0]])
    res = resect_scanner_pose(obs, [0.01, -0.02, 0.003], 0.003)
    np.testing.assert_allclose(res.x, [0, 0, 0], atol=1e-10)


def test_collinear_beacon_is_rejected():
    v = np.array([[0, 0], [0.3, 0], [0.8, 0], [1.0, 0]], dtype=float)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        Beacon("B9", v)


def test_beacon_out_of_view_fails_with_reason():
    sc = simulate_mast_scenario(1, position=4, visible_beacons=("B2",))
    res = locate_scanner(sc.scan, sc.beacons)
    assert res.status == "failed"
    assert "B1" in res.reason and "out of view" in res.reason
    assert res.x_m is None and res.covariance is None
    # with the requirement lowered, one beacon of distinct chirality fixes the pose
    one = locate_scanner(sc.scan, sc.beacons, MastParams(min_beacons=1))
    assert one.ok, one.reason
    d = np.array([one.x_m - sc.truth["x_m"], one.y_m - sc.truth["y_m"]])
    assert d @ np.linalg.solve(np.asarray(one.covariance)[:2, :2], d) < 13.8  # inside its 99.9 % ellipse
    assert one.details["beacons_used"] == ["B2"]


def test_scan_without_beacons_fails_with_reason():
    sc = simulate_mast_scenario(1, position=4, visible_beacons=())
    res = locate_scanner(sc.scan, sc.beacons)
    assert res.status == "failed"
    assert "no beacon panel was recognised" in res.reason


def test_missing_noise_model_and_bad_scan():
    sc = simulate_mast_scenario(1, position=4)
    scan = Scan2D(sc.scan.bearing_deg, sc.scan.range_m)  # no sigma stated
    with pytest.raises(InputError, match="noise model"):
        locate_scanner(scan, sc.beacons)
    with pytest.raises(InputError):
        Scan2D([0.0, 1.0], [1.0, np.nan])
    with pytest.raises(TooFewPointsError):
        locate_scanner(Scan2D([0.0, 1.0], [1.0, 2.0], sigma_range_m=0.003), sc.beacons)
    with pytest.raises(TooFewPointsError):
        locate_scanner(sc.scan, sc.beacons[:1])
    with pytest.raises(InputError, match="duplicate"):
        locate_scanner(sc.scan, [sc.beacons[0], sc.beacons[0]])


def test_bad_files(tmp_path):
    p = tmp_path / "b.csv"
    p.write_text("beacon_id,vertex,x_m\nB1,0,1.0\n")
    with pytest.raises(FileFormatError, match="missing column"):
        read_beacons_csv(p)
    p.write_text("beacon_id,vertex,x_m,y_m\nB1,0,1.0,2.0\nB1,1,1.5,2.5\n")
    with pytest.raises(FileFormatError, match="vertices 0,1,2,3"):
        read_beacons_csv(p)
    p.write_text("beacon_id,vertex,x_m,y_m\nB1,0,abc,2.0\n")
    with pytest.raises(FileFormatError, match="row 2"):
        read_beacons_csv(p)
    s = tmp_path / "s.csv"
    s.write_text("angle,dist\n1,2\n")
    with pytest.raises(FileFormatError, match="header"):
        read_scan_csv(s)
    s.write_text("bearing_deg,range_m\n1,x\n")
    with pytest.raises(FileFormatError, match="line 2"):
        read_scan_csv(s)


@pytest.mark.parametrize("position", [1, 4])
def test_point_symmetric_identical_beacons_are_reported_ambiguous(position):
    sc = simulate_mast_scenario(1, position=position, point_symmetric_beacons=True)
    res = locate_scanner(sc.scan, sc.beacons)
    assert res.status == "failed"
    assert "ambiguous" in res.reason and res.x_m is None
