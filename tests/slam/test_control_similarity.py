"""The similarity model of survey control (issue 30): ``ControlParams(mode="rigid", model="similarity")``
and ``minegeo slam --control-mode similarity``, a 7-parameter fit of the control stations after SLAM.

Library: a hand-built drive (tests/slam/_control_common.truth, 240 m) whose SLAM map is too small by a
known factor, the map-to-CRS scale ``S = 1 + 200 ppm``; the fit must return ``S`` within its σ (40
seeded station-noise draws: the standardised error ``(ŝ − S)/σ̂`` behaves as Student's t with
``3·7 − 7 = 14`` degrees of freedom) while the rigid fit of the same stations fails its χ² test.

CLI: 16 small sweeps (1200 points on the faces of a 12 x 8 x 3 m box) along a bending 2.5 m path;
6 stations on frame times (4 control, 2 check), surveyed at the true sensor positions scaled by
1 + 2000 ppm about the first one, σ 2 mm in E, N and H (equal weights: the least-squares similarity
is Umeyama's closed form, computed here from the run's own trajectory.tum as the independent twin).
Each run takes about 1-2 s.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from _control_common import CRS, stations, truth, write_box_drive, write_stations_csv

from minegeo.cli import main
from minegeo.kernels.lie import se3_exp, se3_inverse
from minegeo.slam.control import ControlParams, apply_control

#: the map-to-CRS scale of the hand-built drive: the SLAM map is too small by 1/S
S_TRUE = 1.0 + 200e-6
TIMES = np.array([0.5, 12.5, 24.5, 40.5, 52.5, 66.5, 80.5, 92.5, 104.5, 119.5])
ROLES = ["control", "check", "control", "control", "check", "control", "control", "check", "control", "control"]


def _scaled_map():
    """``(t, T, P, edges, Z, info)``: the truth ``T`` (local CRS frame) and the keyframes ``P`` of a SLAM
    map placed by a rigid ``A`` and shrunk by ``1/S_TRUE``: ``p_local = S_TRUE R_A p_map + t_A`` exactly."""
    t, T = truth()
    A = se3_exp(np.array([0.01, -0.02, 0.8, 5.0, -3.0, 1.0]))
    P = se3_inverse(A) @ T
    P[:, :3, 3] = (T[:, :3, 3] - A[:3, 3]) @ A[:3, :3] / S_TRUE
    k = t.size
    Z = np.stack([se3_inverse(P[i]) @ P[i + 1] for i in range(k - 1)])
    return t, T, P, np.c_[np.arange(k - 1), np.arange(1, k)], Z, np.tile(np.eye(6), (k - 1, 1, 1))


def test_similarity_returns_a_known_scale_within_its_sigma_and_the_rigid_fit_misses():
    t, T, P, edges, Z, info = _scaled_map()
    offset = np.zeros(3)  # the surveyed point at the sensor origin: every point is scaled by S_TRUE exactly
    z, rigid_failed, sim_passed, chk_err = [], 0, 0, {"rigid": [], "similarity": []}
    for seed in range(40):
        st, true = stations(t, T, TIMES, ROLES, np.random.default_rng(seed), offset)
        r = {m: apply_control(t, P, edges, Z, info, st, offset, CRS, ControlParams(mode="rigid", model=m))
             for m in ("rigid", "similarity")}
        s = r["similarity"]
        assert s.model == "similarity" and s.similarity and not r["rigid"].similarity
        assert s.global_chi2.dof == 3 * 7 - 7 and r["rigid"].global_chi2.dof == 3 * 7 - 6
        assert r["rigid"].scale == 1.0 and r["rigid"].scale_std == 0.0
        z.append((s.scale - S_TRUE) / s.scale_std)
        rigid_failed += r["rigid"].global_chi2.passed is False
        sim_passed += s.global_chi2.passed is True
        # the rigid fit leaves the scale in the horizontal residuals (±22 mm at the ends of a ±110 m spread,
        # against 5 mm sigmas): larger at the control stations and at the check stations
        rms_h = {m: np.sqrt(np.mean(r[m].stats.v[:, :2] ** 2)) for m in r}
        assert rms_h["rigid"] > 1.5 * rms_h["similarity"], rms_h
        for m in r:  # the check stations' estimated points against their truth (not their noisy survey)
            chk_err[m].append(r[m].station_enh_local[st.is_check, :2] - true[st.is_check, :2])
        if seed == 0:  # the trajectory in the CRS: s R p + T on every pose, against the truth
            assert np.max(np.abs(s.poses[:, :3, 3] - T[:, :3, 3])) < 0.01
            np.testing.assert_allclose(s.station_enh_local, true, atol=0.02)
    z = np.array(z)
    # t(14): P(|t| < 1) = 0.665, E t = 0; 40 draws: sd of the fraction 0.075, of the mean 0.17
    assert np.all(np.abs(z) < 4.0), z
    assert 0.5 <= np.mean(np.abs(z) < 1.0) <= 0.85, np.mean(np.abs(z) < 1.0)
    assert abs(z.mean()) < 0.55, z.mean()
    # 200 ppm over ~220 m of stations is ~20 mm of misfit against 5 mm sigmas: the rigid fit fails its chi2
    assert rigid_failed >= 36 and sim_passed >= 34, (rigid_failed, sim_passed)
    # measured (40 draws): 9.6 mm rigid, 2.4 mm similarity
    rmse = {m: float(np.sqrt(np.mean(np.square(chk_err[m])))) for m in chk_err}
    assert rmse["rigid"] > 2.0 * rmse["similarity"], rmse


def test_similarity_with_drift_states_or_in_graph_mode_is_refused():
    from minegeo.errors import InputError

    with pytest.raises(InputError, match="drift_states True needs the graph mode"):
        ControlParams(mode="rigid", model="similarity", drift_states=True)
    with pytest.raises(InputError, match="the graph mode has no scale"):
        ControlParams(mode="graph", model="similarity")


def _largest_distance_from_line(X):
    """Naive twin: largest distance of the points from their principal axis (eigenvector of the largest
    eigenvalue of the scatter matrix, through the centroid)."""
    Xc = X - X.mean(axis=0)
    u = np.linalg.eigh(Xc.T @ Xc)[1][:, -1]
    return max(float(np.linalg.norm(x - (x @ u) * u)) for x in Xc)


@pytest.mark.parametrize(("off_m", "refused"), [(0.012, True), (0.06, False)])
def test_control_stations_on_one_line_are_refused_by_the_library(off_m, refused):
    """7 control stations on a line, one moved ``off_m`` across it: within 3 x their largest sigma (10 mm)
    of the best-fitting line they are refused for every mode; further off they are a fit."""
    from dataclasses import replace

    from minegeo.errors import InputError

    t, T, P, edges, Z, info = _scaled_map()
    st, _ = stations(t, T, TIMES, ROLES, np.random.default_rng(0), np.zeros(3))
    enh = st.enh_local.copy()
    c = np.flatnonzero(st.is_control)
    d = np.array([100.0, 40.0, 2.0])
    enh[c] = enh[c[0]] + np.outer(np.linspace(0.0, 1.0, c.size), d)
    enh[c[2]] += off_m * np.array([-d[1], d[0], 0.0]) / np.hypot(d[0], d[1])
    assert (_largest_distance_from_line(enh[c]) <= 0.03) is refused
    st = replace(st, enh_local=enh)
    for mode, model in (("rigid", "similarity"), ("rigid", "rigid"), ("graph", "rigid")):
        if refused:
            with pytest.raises(InputError, match=f"lie on one straight line .* the {'similarity' if model == 'similarity' else mode} mode"):
                apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, ControlParams(mode=mode, model=model))
        else:
            apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, ControlParams(mode=mode, model=model))


# ------------------------------------------------------------------ the CLI

DT = 0.2
SCALE_CLI = 1.0 + 2000e-6
STATIONS_CLI = ((1, "control"), (4, "check"), (7, "control"), (10, "check"), (12, "control"), (15, "control"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("ctl_sim")
    fr = d / "frames"
    fr.mkdir()
    k = np.arange(16)
    pos = np.c_[0.15 * k, 0.004 * k**2, 0.01 * k]
    write_box_drive(fr, 31, 1200, pos, DT)
    a = 0.7
    Rc = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    enh = SCALE_CLI * (pos - pos[0]) @ Rc.T + [219437.25, 612981.5, 214.75]
    write_stations_csv(d / "stations.csv", enh, STATIONS_CLI, DT, "0.002", "0.002")
    base = ["-q", "slam", "--frames", str(fr), "--control", str(d / "stations.csv"), "--keyframe-distance", "0.3"]
    assert main([*base, "--out", str(d / "sim"), "--control-mode", "similarity"]) == 0
    assert main([*base, "--out", str(d / "rigid"), "--control-mode", "rigid"]) == 0
    assert main(["-q", "slam", "--config", str(d / "sim" / "result.json"), "--out", str(d / "repeat")]) == 0
    return {"dir": d, "enh": enh}


def _result(o):
    return json.loads((o / "result.json").read_text())


def _umeyama(x, y):
    """Least-squares ``y ≈ s R x + t`` (Umeyama 1991, equal weights): ``(s, R, t)``."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    U, D, Vt = np.linalg.svd(yc.T @ xc / len(x))
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = float(np.trace(np.diag(D) @ E) / np.mean(np.sum(xc**2, axis=1)))
    return s, R, my - s * R @ mx


def _station_twin(scene):
    """Umeyama on the control stations: their sensor positions in the run's trajectory.tum (stations on
    frame times, offset 0) onto their E N H in the stations file."""
    tum = np.loadtxt(scene["dir"] / "sim" / "trajectory.tum")
    ctrl = [i for i, r in STATIONS_CLI if r == "control"]
    x = np.array([tum[np.argmin(np.abs(tum[:, 0] - DT * i)), 1:4] for i in ctrl])
    y = np.array([[float(v) for v in ln.split(",")[3:6]] for ln in (scene["dir"] / "stations.csv").read_text()
                  .splitlines()[2:] if ln.endswith("control")])
    return _umeyama(x, y)


def test_cli_similarity_scale_matches_the_umeyama_twin_with_its_degrees_of_freedom(scene):
    rec = _result(scene["dir"] / "sim")
    assert rec["parameters"]["control"]["mode"] == "similarity"
    assert rec["parameters"]["control"]["drift_states"] == "off"
    c = rec["control"]
    s, _, _ = _station_twin(scene)
    assert c["scale"]["scale"] == pytest.approx(s, abs=2e-8)
    assert c["scale"]["scale_ppm"] == pytest.approx((s - 1.0) * 1e6, abs=0.02)
    assert c["scale"]["sigma_ppm"] > 0
    assert c["chi2_test"]["dof"] == c["scale"]["dof"] == 3 * 4 - 7
    assert _result(scene["dir"] / "rigid")["control"]["chi2_test"]["dof"] == 3 * 4 - 6
    assert "scale" not in _result(scene["dir"] / "rigid")["control"]
    html = (scene["dir"] / "sim" / "report.html").read_text()
    m = re.search(r"scale \(similarity\)</t[hd]>\s*<td[^>]*>([+-][0-9.]+) ± ([0-9.]+) ppm", html)
    assert m is not None, "the report's statistics hold the scale in ppm with its sigma"
    assert float(m.group(1)) == pytest.approx(c["scale"]["scale_ppm"], abs=0.06)
    assert float(m.group(2)) == pytest.approx(c["scale"]["sigma_ppm"], abs=0.06)


def test_cli_similarity_map_is_the_one_similarity_of_the_twin(scene):
    """map_crs.ply (+ its recorded origin) is ``s R p + t`` of map.ply's points, the twin's (s, R, t)."""
    from minegeo.io import read_point_cloud

    s, R, t = _station_twin(scene)
    m = read_point_cloud(scene["dir"] / "sim" / "map.ply")
    g = read_point_cloud(scene["dir"] / "sim" / "map_crs.ply")
    want = np.asarray(m.points, dtype=np.float64) @ (s * R).T + t
    got = np.asarray(g.points, dtype=np.float64) + np.asarray(g.origin, dtype=np.float64)
    assert got.shape == want.shape
    assert np.max(np.abs(got - want)) < 1e-4


def test_cli_similarity_repeated_byte_identically_from_its_result_json(scene):
    a, b = scene["dir"] / "sim", scene["dir"] / "repeat"
    names = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for n in names:
        if n.suffix in (".json", ".html"):
            continue
        assert (a / n).read_bytes() == (b / n).read_bytes(), n
    ra, rb = _result(a), _result(b)
    assert ra["parameters"] == rb["parameters"]
    ca, cb = (json.dumps(r["control"], sort_keys=True).replace(str(d), "OUT") for r, d in ((ra, a), (rb, b)))
    assert ca == cb
