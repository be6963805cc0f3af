"""The control stations' geometry (minegeo.slam.control_graph.rotation_about_line, check_map_geometry):
the standard deviation of the rotation about their line against a hand calculation, control stations on
one line in the SLAM map (a straight drive) while a gross error puts one off it in the survey refused
in every mode, and a map lever just inside the rule accepted, its fit converging even with that gross
error (a large-residual rigid fit: Gauss-Newton alone oscillated about the rotation about the line)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from _control_common import CRS, ORIGIN, write_box_drive, write_stations_csv

from minegeo.errors import InputError
from minegeo.io.stations import Stations
from minegeo.slam.control import ControlParams, apply_control
from minegeo.slam.control_graph import LINE_SIGMAS, rotation_about_line

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "badinput"))
from _contract import assert_user_error  # noqa: E402

SH, SV = 0.005, 0.008
MODES = (("graph", "rigid"), ("rigid", "rigid"), ("rigid", "similarity"))


@pytest.mark.parametrize(("heading", "across"), [(0.0, "horizontal"), (0.7, "horizontal"), (2.1, "vertical")])
def test_rotation_sigma_about_the_line_by_hand(heading, across):
    """Points at -L and +L on a horizontal line (heading ``heading`` rad from E) and one at its middle, ``h`` off
    it horizontally or vertically: about the centroid (``h/3`` from the line) a turn ``θ`` about the line moves
    the three by ``θ h/3``, ``θ h/3``, ``θ 2h/3`` vertically (offset horizontal) or horizontally (offset
    vertical), so ``σ_θ = σ / (h √(2/3))`` with σ = σ_v or σ_h; the weakest axis is the line."""
    L, h = 20.0, 0.04
    u = np.array([np.cos(heading), np.sin(heading), 0.0])
    n = np.array([-np.sin(heading), np.cos(heading), 0.0]) if across == "horizontal" else np.array([0.0, 0.0, 1.0])
    X = np.array([-L * u, L * u, h * n]) + [300.0, 400.0, 80.0]
    g = rotation_about_line(X, np.full(3, SH), np.full(3, SV))
    sigma = SV if across == "horizontal" else SH
    assert g["sigma_rad"] == pytest.approx(sigma / (h * np.sqrt(2.0 / 3.0)), rel=1e-9)
    assert abs(g["axis"] @ u) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(g["off_m"], [h / 3, h / 3, 2 * h / 3], rtol=0, atol=1e-9)


def _straight_drive(bump_m: float):
    """Keyframes every 1 s, 0.6 m apart along E, the path (and the map) straight but for a triangular bump of
    ``bump_m`` across it (N) at 20 s; exact odometry. Control stations at 10, 20, 30 s, a check station at
    35 s, surveyed where the run put them."""
    t = np.arange(41, dtype=np.float64)
    x = 0.6 * t
    P = np.tile(np.eye(4), (t.size, 1, 1))
    P[:, :3, 3] = np.c_[x, bump_m * np.clip(1.0 - np.abs(x - 12.0) / 6.0, 0.0, None), np.zeros(t.size)]
    k = t.size
    edges = np.c_[np.arange(k - 1), np.arange(1, k)]
    Z = np.stack([np.linalg.inv(P[i]) @ P[i + 1] for i in range(k - 1)])
    info = np.tile(np.diag(np.r_[np.full(3, 1e-3), np.full(3, 0.01)] ** -2.0), (k - 1, 1, 1))
    times = np.array([10.0, 20.0, 30.0, 35.0])
    st = Stations(ids=["ST001", "ST002", "ST003", "ST004"], t_start_s=times, t_end_s=times,
                  enh_local=P[times.astype(int), :3, 3] + [1000.0, 2000.0, 200.0], origin_enh=ORIGIN,
                  sigma_h_m=np.full(4, SH), sigma_v_m=np.full(4, SV), roles=["control"] * 3 + ["check"], crs=CRS)
    return t, P, edges, Z, info, st


def _bump_for(sigma_rad: float) -> float:
    """The bump (m) whose control stations' rotation about their line has ``sigma_rad``: the middle station
    ``2b/3`` and the others ``b/3`` from the line, moved vertically by the turn (σ_v): ``σ = σ_v/(b √(2/3))``."""
    return SV / (sigma_rad * np.sqrt(2.0 / 3.0))


def _moved(st, i: int, d) -> Stations:
    from dataclasses import replace

    enh = st.enh_local.copy()
    enh[i] += d
    return replace(st, enh_local=enh)


@pytest.mark.parametrize(("mode", "model"), MODES)
def test_control_on_one_line_in_the_map_off_it_in_the_survey_is_refused(mode, model):
    """A straight drive (the map's control points within 1 mm of their line) with ST002 surveyed 0.5 m off
    it: the survey's geometry passes, the map's does not determine the rotation about the line. Refused
    before any adjustment, in every mode, naming the stations, the map and the survey's offset."""
    t, P, edges, Z, info, st = _straight_drive(0.001)
    st = _moved(st, 1, [0.2, -0.45, 0.0])
    c = st.is_control
    assert rotation_about_line(st.enh_local[c], st.sigma_h_m[c], st.sigma_v_m[c])["sigma_rad"] < 0.1 / LINE_SIGMAS
    with pytest.raises(InputError, match=r"the 3 control stations \(ST001, ST002, ST003\) lie on one straight line "
                                         r"in the SLAM map \(the run's points at their times at most 0\.001 m from it "
                                         r"over 12\.0 m\), though their surveyed coordinates lie up to 0\.299 m off their line"):
        apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, ControlParams(mode=mode, model=model))


@pytest.mark.parametrize(("mode", "model"), MODES)
@pytest.mark.parametrize(("ratio", "refused"), [(1.25, True), (0.8, False)])
def test_map_lever_across_the_rule(mode, model, ratio, refused):
    """The map's control stations ``ratio`` times the rule's limit (``σ_θ = ratio / LINE_SIGMAS`` rad): above it
    refused; below it placed, status ok with the survey where the run put them (noise of their σ, seeded),
    and with ST002 0.5 m off in
    height (a gross error the fit turns the map about the line for: a large-residual fit) still a converged
    adjustment whose χ² test fails and that says so."""
    t, P, edges, Z, info, st = _straight_drive(_bump_for(ratio / LINE_SIGMAS))
    p = ControlParams(mode=mode, model=model)
    if refused:
        with pytest.raises(InputError, match="lie on one straight line"):
            apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, p)
    else:
        truth = st.enh_local.copy()
        st = _moved(st, slice(None), np.random.default_rng(3).standard_normal((4, 3)) * [SH, SH, SV])
        r = apply_control(t, P, edges, Z, info, st, np.zeros(3), CRS, p)
        assert r.status == "ok", r.reason
        np.testing.assert_allclose(r.station_enh_local, truth, rtol=0, atol=4 * SV)
        r = apply_control(t, P, edges, Z, info, _moved(st, 1, [0.0, 0.0, 0.5]), np.zeros(3), CRS, p)
        assert r.status == "warning" and "chi-square test of the adjustment failed" in r.reason, r.reason


@pytest.fixture(scope="module")
def straight_scene(tmp_path_factory):
    """16 sweeps of a 12 x 8 x 3 m box 0.2 s apart along a straight 2.25 m path; control stations S1, S2, S4
    at frames 1, 7, 14 and a check S3 at frame 10 surveyed at the true sensor positions in EPSG:5186, S2 0.5 m
    across the path (a gross error: the run passed it on the line)."""
    d = tmp_path_factory.mktemp("ctl_line")
    fr = d / "frames"
    fr.mkdir()
    k = np.arange(16)
    pos = np.c_[0.15 * k, np.zeros(16), np.zeros(16)]
    write_box_drive(fr, 30, 1500, pos, 0.2)
    a = 0.7
    Rc = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    enh = pos @ Rc.T + [219437.25, 612981.5, 214.75]
    enh[7] += 0.5 * np.array([-np.sin(a), np.cos(a), 0.0])
    write_stations_csv(d / "stations.csv", enh, ((1, "control"), (7, "control"), (10, "check"), (14, "control")),
                       0.2, "0.005", "0.008")
    return fr, d / "stations.csv"


@pytest.mark.parametrize("mode", ["graph", "rigid", "similarity"])
def test_cli_control_on_one_line_in_the_map_is_one_error_line(mode, straight_scene, tmp_path, capsys):
    """``minegeo slam --control`` on the straight drive: exit 2, one line naming the stations and the map's
    line, nothing written (found after the odometry, before any adjustment)."""
    fr, st = straight_scene
    out = tmp_path / "out"
    assert_user_error("slam", ["--frames", fr, "--out", out, "--control", st, "--control-mode", mode], capsys,
                      inputs=[fr, st], outputs=[out],
                      expect=f"{st}: the 3 control stations (S1, S2, S4) lie on one straight line in the SLAM map")


def test_rigid_fit_with_a_gross_error_reaches_the_least_squares_minimum():
    """The rigid fit of ``test_map_lever_across_the_rule`` (map lever at 0.8 of the rule's limit, ST002 0.5 m off
    in height): a large-residual problem along the rotation about the line. The Helmert adjustment converges
    to the weighted least-squares minimum that scipy's trust-region solver (an independent oracle, started
    from the identity) finds: the same rotation and translation, the same ``vᵀPv``."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from minegeo.survey.helmert import helmert3d

    t, P, edges, Z, info, st = _straight_drive(_bump_for(0.8 / LINE_SIGMAS))
    c = st.is_control
    src = P[[10, 20, 30], :3, 3]
    dst = _moved(st, 1, [0.0, 0.0, 0.5]).enh_local[c]
    sig = np.array([[SH, SH, SV]] * 3)
    h = helmert3d(src, dst, sig, estimate_scale=False)

    def res(p):
        return ((src @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:] - dst) / sig).ravel()

    o = least_squares(res, np.r_[0.0, 0.0, 0.0, dst.mean(axis=0) - src.mean(axis=0)], method="trf", xtol=1e-15,
                      ftol=1e-15, gtol=1e-15)
    # the same minimum to what float64 resolves of it: vᵀPv ≈ 2265 is flat along the rotation about the line to
    # within its rounding (~1e-12 relative) over ~1e-6 rad
    assert float(h.lsq.vtwv) == pytest.approx(2.0 * o.cost, rel=1e-12)
    np.testing.assert_allclose(h.R, Rotation.from_rotvec(o.x[:3]).as_matrix(), rtol=0, atol=1e-5)
    np.testing.assert_allclose(h.T, o.x[3:], rtol=0, atol=1e-6)
    assert np.degrees(np.arccos(np.clip((np.trace(h.R) - 1.0) / 2.0, -1.0, 1.0))) > 10.0  # turned far about the line


def test_a_rigid_fit_that_does_not_converge_names_the_stations(monkeypatch):
    """A :class:`ConvergenceError` of the rigid fit reaches the surveyor as the fit of the named control
    stations, with the station farthest from its surveyed point after the closed-form fit."""
    import minegeo.georef as georef
    from minegeo.errors import ConvergenceError

    def no_convergence(*args, **kwargs):
        raise ConvergenceError("least squares did not converge in 100 iterations")

    monkeypatch.setattr(georef, "georeference", no_convergence)
    t, P, edges, Z, info, st = _straight_drive(_bump_for(0.8 / LINE_SIGMAS))
    with pytest.raises(ConvergenceError, match=r"the rigid fit of the 3 control stations \(ST001, ST002, ST003\) to "
                                               r"the run's points at their times did not converge: least squares did "
                                               r"not converge in 100 iterations; after the closed-form rigid fit "
                                               r"station ST002 is 0\.3\d\d m from its surveyed point"):
        apply_control(t, P, edges, Z, info, _moved(st, 1, [0.0, 0.0, 0.5]), np.zeros(3), CRS,
                      ControlParams(mode="rigid"))


@pytest.mark.parametrize(("sigma0", "side"), [(0.37, "below"), (2.32, "above")])
def test_warning_reason_says_on_which_side_the_global_test_failed(sigma0, side):
    """A σ̂0 below the χ² interval (the factors agree better than stated) and above it (a model error or
    a blunder) call for different checks: the reason names the side and the interval in σ̂0 units,
    ``sqrt(χ²_{α/2, r} / r)`` and ``sqrt(χ²_{1−α/2, r} / r)`` (reference: scipy.stats.chi2)."""
    from types import SimpleNamespace

    from scipy import stats as sst

    from minegeo.slam.control import _warning_reason
    from minegeo.survey.lsq import chi2_global_test

    r = 6978
    g = chi2_global_test(sigma0**2 * r, r)
    assert g.passed is False
    reason = _warning_reason(g, SimpleNamespace(flagged=()), ((), ()))
    lo, hi = (np.sqrt(sst.chi2.ppf(q, r) / r) for q in (0.025, 0.975))
    assert reason == (f"the chi-square test of the adjustment failed (sigma0 {sigma0:.2f}, {side} its 95 % interval "
                      f"{lo:.2f}-{hi:.2f}: " + ("the factors agree better than their stated uncertainty" if side == "below"
                                               else "the factors disagree more than their stated uncertainty allows") + ")")
