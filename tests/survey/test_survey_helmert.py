"""Helmert / affine transformations against published answers (Ghilani Ex. 18.1, SK-42->SK-95, PROJ)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from helpers import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import DegenerateGeometryError, TooFewPointsError
from minegeo.geometry.se3 import exp_so3
from minegeo.survey import affine2d, apply_helmert2d, apply_helmert7, helmert2d, helmert3d
from minegeo.survey.angles import RHO_ARCSEC


def _ghilani18():
    d = shared_data("ghilani_ex18_1_2d_conformal")
    rows = list(csv.DictReader(open(d / "control_points.csv", encoding="utf-8")))
    src = np.array([[float(r["x_source"]), float(r["y_source"])] for r in rows])
    dst = np.array([[float(r["E_target"]), float(r["N_target"])] for r in rows])
    pts = list(csv.DictReader(open(d / "points_to_transform.csv", encoding="utf-8")))
    par = {r["parameter"]: r for r in csv.DictReader(open(d / "expected_parameters.csv", encoding="utf-8"))}
    return src, dst, pts, par


def test_ghilani_ex18_1_parameters_to_printed_digits():
    src, dst, _, par = _ghilani18()
    r = helmert2d(src, dst)
    for i, (name, dec) in enumerate([("a", 5), ("b", 5), ("Tx", 3), ("Ty", 3)]):
        assert f"{r.params[i]:.{dec}f}" == f"{float(par[name]['value']):.{dec}f}", name
        assert f"{r.std[i]:.{dec}f}" == f"{float(par[name]['std_dev']):.{dec}f}", name
    assert f"{r.sigma0:.4f}" == "0.1398"
    assert r.dof == 2
    assert f"{r.scale:.6f}" == "4.519621"
    assert r.rotation_dms.startswith("183°13'05")
    np.testing.assert_allclose(
        r.residuals, [[0.0038, -0.0291], [0.1009, -0.0767], [-0.1047, 0.1059]], atol=6e-5
    )


def test_ghilani_ex18_1_transformed_points_and_sigmas():
    src, dst, pts, _ = _ghilani18()
    r = helmert2d(src, dst)
    xy = np.array([[float(p["x_source"]), float(p["y_source"])] for p in pts])
    exp = np.array([[float(p["E_expected"]), float(p["N_expected"])] for p in pts])
    en, cov = r.transform(xy)
    assert np.all(np.abs(en - exp) <= 0.0005 + 1e-9)
    sig = np.sqrt(cov[:, 0, 0])
    assert [f"{s:.3f}" for s in sig] == ["0.135", "0.271", "0.368", "0.484"]
    np.testing.assert_allclose(np.sqrt(cov[:, 1, 1]), sig, rtol=1e-9)


def test_sk42_sk95_seven_parameters():
    d = shared_data("sk42_sk95_helmert7")
    a = np.loadtxt(d / "SK-42-points.txt")
    b = np.loadtxt(d / "SK-95-points.txt")
    h = helmert3d(a, b, convention="position_vector")
    # helmparms3d prints T = (-0.8780, -10.0450, 1.7448); that estimator differs from
    # Gauss-Markov LSQ by < 0.5 mm (sigma_T = 2-4 cm): agree within 0.5 mm.
    np.testing.assert_allclose(h.T, [-0.8780025419, -10.0450090237, 1.7447787357], atol=5e-4)
    assert np.all(h.std[:3] > 0.01)
    rot = h.rotations_arcsec
    assert [f"{v:.4f}" for v in rot] == ["0.0006", "0.3492", "0.6599"]
    assert f"{h.ds_ppm:.4f}" == "0.0008"
    ref_R = np.array(
        [[1, -0.0000031994, 0.0000016928], [0.0000031994, 1, -0.0000000028], [-0.0000016928, 0.0000000028, 1]]
    )
    np.testing.assert_allclose(h.R, ref_R, atol=6e-11)
    assert np.max(np.abs(h.residuals)) < 0.0006
    # coordinate-frame reading reverses the rotation signs only
    hc = helmert3d(a, b, convention="coordinate_frame")
    np.testing.assert_allclose(hc.rotations_arcsec, -rot, atol=1e-12)
    # reproduces the published transformed coordinates (helmparms3d calc file) within 0.5 mm
    calc = np.loadtxt(d / "SK-42-SK-95-calc-1.0.5.txt")
    assert np.max(np.abs(h.transform(a) - calc)) < 5e-4


def test_rigid_six_parameters_exact():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(6, 3)) * 100 + [500000.0, 7000000.0, 300.0]
    R = exp_so3([0.1, -0.2, 2.1])
    t = np.array([12.0, -3.0, 0.5])
    dst = src @ R.T + t
    h = helmert3d(src, dst, estimate_scale=False)
    np.testing.assert_allclose(h.R, R, atol=1e-12)
    # T has a 7e6 m lever arm: float64 rounding of dst alone moves it by ~1e-5 m
    np.testing.assert_allclose(h.T, t, atol=1e-4)
    np.testing.assert_allclose(h.transform(src), dst, atol=1e-8)
    assert h.scale == 1.0
    assert h.cov.shape == (6, 6)


def test_proj_coordinate_frame_example():
    # PROJ more_builtins.gie (Jivall, ITRF2008 -> ETRS89), coordinate frame, tolerance 1 µm
    shared_data("proj_helmert_gigs", "proj_more_builtins_helmert_excerpt.gie")
    out = apply_helmert7(
        [[3565285.0, 855949.0, 5201383.0]],
        0.67678,
        0.65495,
        -0.52827,
        -0.022742,
        0.012667,
        0.022704,
        -0.01070,
        "coordinate_frame",
    )
    np.testing.assert_allclose(out[0], [3565285.41342351, 855948.67986759, 5201382.72939791], atol=1e-6)


def test_proj_sewrpc_2d_helmert_apply_and_estimate():
    shared_data("proj_helmert_gigs", "proj_more_builtins_helmert_excerpt.gie")
    theta = -1.244048 / RHO_ARCSEC  # PROJ theta is clockwise
    out = apply_helmert2d([[2546506.957, 542256.609]], -9597.3572, 0.6112, 0.304794780637, -theta)
    np.testing.assert_allclose(out[0], [766563.675, 165282.277], atol=1e-3)
    # estimation recovers the SEWRPC parameters from exact pairs around point 203
    src = np.array(
        [
            [2546506.957, 542256.609],
            [2556506.957, 542256.609],
            [2546506.957, 552256.609],
            [2551000.0, 547000.0],
        ]
    )
    dst = apply_helmert2d(src, -9597.3572, 0.6112, 0.304794780637, -theta)
    r = helmert2d(src, dst)
    np.testing.assert_allclose(r.params[2:], [-9597.3572, 0.6112], atol=1e-6)
    assert abs(r.scale - 0.304794780637) < 1e-12
    assert abs(r.rotation_rad - (-theta)) < 1e-12


def test_affine_exact_and_errors():
    src = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [70.0, 40.0]]) + 1e6
    A = np.array([[1.001, 0.002], [-0.003, 0.998]])
    dst = (src - 1e6) @ A.T + [5e5, 7e6]
    r = affine2d(src, dst)
    np.testing.assert_allclose(r.transform(src), dst, atol=1e-6)
    with pytest.raises(TooFewPointsError):
        affine2d(src[:2], dst[:2])
    with pytest.raises(DegenerateGeometryError):
        affine2d([[0, 0], [1, 1], [2, 2]], [[0, 0], [1, 1], [2, 2]])
    with pytest.raises(DegenerateGeometryError):
        helmert2d([[5, 5], [5, 5]], [[0, 0], [1, 1]])


@settings(max_examples=20, deadline=None)
@given(
    st.floats(-3.1, 3.1), st.floats(0.5, 2.0), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(1.0, 1e3)
)
def test_helmert2d_weight_scaling_invariance(theta, s, tx, ty, k):
    rng = np.random.default_rng(7)
    src = rng.uniform(-100, 100, size=(5, 2)) + [4e5, 5e6]
    dst = apply_helmert2d(src, tx, ty, s, theta) + rng.normal(scale=0.01, size=(5, 2))
    sig = rng.uniform(0.005, 0.02, size=5)
    r1 = helmert2d(src, dst, sigma_dst=sig)
    r2 = helmert2d(src, dst, sigma_dst=sig * k)
    np.testing.assert_allclose(r1.params, r2.params, rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(r1.cov, r2.cov, rtol=1e-6, atol=1e-10 * np.abs(r1.cov).max())


def test_helmert3d_point_covariance_matches_numeric_jacobian():
    rng = np.random.default_rng(11)
    src = rng.uniform(-50, 50, size=(8, 3)) + [4.5e5, 5.2e6, 200.0]
    R = exp_so3([0.0, 0.0, -2.09661182])
    dst = 1.00002 * (src @ R.T) + [586601.143, 4462104.996, 273.405] + rng.normal(scale=0.003, size=(8, 3))
    h = helmert3d(src, dst, sigma_dst=0.003)
    q = np.array([[4.5e5 + 80.0, 5.2e6 - 60.0, 210.0]])
    xyz, cov = h.transform(q, with_cov=True)
    # numeric Jacobian of the transformed point w.r.t. the reduced parameters
    eps = 1e-7
    x0 = h.lsq.x.copy()

    def f(x):
        Rk = exp_so3(x[3:6] - x0[3:6]) @ h.R  # rotation covariance = small left rotation at R̂
        return (1.0 + x[6]) * ((q[0] - h.src_origin) @ Rk.T) + x[:3]  # without the 1e6 m origin

    J = np.column_stack(
        [(f(x0 + eps * np.eye(7)[k]) - f(x0 - eps * np.eye(7)[k])) / (2 * eps) for k in range(7)]
    )
    np.testing.assert_allclose(cov[0], J @ h.lsq.Sigma_xx @ J.T, rtol=1e-4, atol=1e-12)
    np.testing.assert_allclose(xyz[0] - h.dst_origin, f(x0), atol=1e-6)


def test_epsg_9621_similarity_guidance_note_example():
    # EPSG GN 7-2, EPSG:23031 -> 25831 (operation EPSG:5166): XT0, YT0, M, θ (clockwise)
    shared_data("proj_helmert_gigs", "proj_cs2cs_similarity_epsg_gn7-2_excerpt.yaml")
    th = 1.56504 / RHO_ARCSEC
    fwd = apply_helmert2d([[300000.0, 4500000.0]], -129.549, -208.185, 1.0000015504, -th)[0]
    assert [f"{v:.3f}" for v in fwd] == ["299905.060", "4499796.515"]


def test_estimated_rotations_follow_the_requested_epsg_convention():
    rng = np.random.default_rng(5)
    src = rng.uniform(-3e5, 3e5, size=(10, 3)) + [3.9e6, 0.9e6, 4.9e6]
    tx, ty, tz, rx, ry, rz, ds = 446.448, -125.157, 542.06, 0.1502, 0.247, 0.8421, -20.4894
    for conv in ("position_vector", "coordinate_frame"):
        dst = apply_helmert7(src, tx, ty, tz, rx, ry, rz, ds, conv)
        h = helmert3d(src, dst, convention=conv)
        # the EPSG matrix is not exactly orthogonal: agreement to its linearisation level (~1e-12 rad)
        np.testing.assert_allclose(h.rotations_arcsec, [rx, ry, rz], atol=1e-6)
        assert abs(h.ds_ppm - ds) < 2e-5
        np.testing.assert_allclose(h.T, [tx, ty, tz], atol=1e-4)
