"""Georeferencing validated on published answers through :func:`minegeo.georef.georeference`.

* SK-42 -> SK-95 (20 real geocentric points, ~6e6 m): helmparms3d parameters and the GOST
  32453-2017 datum definitions (``shared/data/sk42_sk95_helmert7``).
* PROJ test vectors (``shared/data/proj_helmert_gigs``): coordinate-frame (EPSG 9607, Jivall
  ITRF2008 -> ETRS89) and position-vector (EPSG 9606, ITRF2000 -> ITRF93 at 2017.0) Helmert,
  and the EPSG Guidance Note 7-2 similarity example (EPSG 9621, ED50 -> ETRS89 UTM 31N).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import shared_data

from minegeo.georef import GeorefParams, georeference
from minegeo.io import ControlPoints
from minegeo.survey import apply_helmert7, helmert7_matrix
from minegeo.survey.angles import RHO_ARCSEC

KRASSOVSKY_GEOCENTRIC = "+proj=geocent +ellps=krass +units=m +no_defs"


def _sk():
    d = shared_data("sk42_sk95_helmert7")
    return np.loadtxt(d / "SK-42-points.txt"), np.loadtxt(d / "SK-95-points.txt"), d


def test_sk42_sk95_published_parameters():
    a, b, d = _sk()
    # SK-95 values are exact transforms of the SK-42 values rounded to 1 mm: sd 1 mm / sqrt(12)
    sigma = 0.001 / np.sqrt(12.0)
    g = ControlPoints([str(i + 1) for i in range(len(a))], a, b, sigma)
    r = georeference(g, KRASSOVSKY_GEOCENTRIC, GeorefParams(allow_geocentric=True))
    assert r.status == "ok", r.warnings
    assert r.chi2["verdict"] == "PASSED"
    assert 0.7 < r.sigma0 < 1.3
    assert r.crs_info.kind == "geocentric"
    # helmparms3d v1.0.5 (a different estimator): T within 0.5 mm, R to its printed digits
    np.testing.assert_allclose(r.translation_m, [-0.8780025419, -10.0450090237, 1.7447787357], atol=5e-4)
    ref_R = np.loadtxt(d / "SK-42-SK-95-param-1.0.5.txt", max_rows=3)
    np.testing.assert_allclose(r.R, ref_R, atol=6e-11)
    assert [f"{v:.4f}" for v in r.rotation_arcsec] == ["0.0006", "0.3492", "0.6599"]
    assert f"{r.ds_ppm:.4f}" == "0.0008"
    assert np.max(np.abs(r.residuals_m)) < 6e-4
    calc = np.loadtxt(d / "SK-42-SK-95-calc-1.0.5.txt")
    fitted = a @ r.T_crs_map[:3, :3].T + r.T_crs_map[:3, 3]
    assert np.max(np.abs(fitted - calc)) < 5e-4
    # coordinate-frame reporting flips the rotation signs only
    rc = georeference(g, KRASSOVSKY_GEOCENTRIC, GeorefParams(allow_geocentric=True, convention="coordinate_frame"))
    np.testing.assert_allclose(rc.rotation_arcsec, -r.rotation_arcsec, atol=1e-12)


def test_sk42_sk95_against_gost_datum_definitions():
    """Compose the GOST definitions (WGS84 -> SK, coordinate frame): SK95 = B95(B42^-1(SK42))."""
    a, b, _ = _sk()

    def bursa(t, r_arcsec, m):
        return np.array(t), m * helmert7_matrix(*(np.array(r_arcsec) / RHO_ARCSEC), "coordinate_frame")

    t42, M42 = bursa([-23.57, 140.95, 79.80], [0.0, 0.35, 0.79], 1.00000022)
    t95, M95 = bursa([-24.47, 130.89, 81.56], [0.0, 0.0, 0.13], 1.00000022)
    M = M95 @ np.linalg.inv(M42)
    T = t95 - M @ t42
    assert np.max(np.abs(a @ M.T + T - b)) < 5e-4  # the composition reproduces the data
    g = ControlPoints([str(i) for i in range(len(a))], a, b, 0.001 / np.sqrt(12.0))
    r = georeference(g, KRASSOVSKY_GEOCENTRIC, GeorefParams(allow_geocentric=True))
    # the estimated transformation agrees with the official one at the points to < 0.5 mm ...
    fitted = a @ r.T_crs_map[:3, :3].T + r.T_crs_map[:3, 3]
    assert np.max(np.abs(fitted - (a @ M.T + T))) < 5e-4
    # ... and its translation (a 6e6 m lever arm) lies within 2 sigma of the official one
    assert np.all(np.abs(r.translation_m - T) < 2.0 * r.translation_std_m)
    # rotations: official rz = 0.66", ry = 0.35" (position vector), to 0.002"
    w_official = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]]) / 2 * RHO_ARCSEC
    np.testing.assert_allclose(r.rotation_arcsec, w_official, atol=2e-3)


def _cloud_around(p0, n=12, spread=50_000.0, seed=0):
    rng = np.random.default_rng(seed)
    return p0 + rng.uniform(-spread, spread, (n, 3))


@pytest.mark.parametrize(
    "case",
    [
        # Jivall ITRF2008 -> ETRS89, coordinate frame (EPSG 9607), tolerance 1 um
        dict(
            conv="coordinate_frame",
            crs="EPSG:4936",
            p=(0.67678, 0.65495, -0.52827, -0.022742, 0.012667, 0.022704, -0.01070),
            accept=(3565285.0, 855949.0, 5201383.0),
            expect=(3565285.41342351, 855948.67986759, 5201382.72939791),
            tol=1e-6,
        ),
        # ITRF2000 -> ITRF93 at epoch 2017.0 (rates x 29 years), position vector (EPSG 9606), 0.03 mm
        dict(
            conv="position_vector",
            crs="EPSG:4915",
            p=(
                0.0127 - 0.0029 * 29,
                0.0065 - 0.0002 * 29,
                -0.0209 - 0.0006 * 29,
                -0.00039 - 0.00011 * 29,
                0.00080 - 0.00019 * 29,
                -0.00114 + 0.00007 * 29,
                0.00195 + 0.00001 * 29,
            ),
            accept=(3370658.37800, 711877.31400, 5349787.08600),
            expect=(3370658.18890, 711877.42370, 5349787.12430),
            tol=3e-5,
        ),
    ],
    ids=["jivall_cf_9607", "itrf_pv_9606"],
)
def test_proj_helmert_conventions(case):
    shared_data("proj_helmert_gigs", "proj_more_builtins_helmert_excerpt.gie")
    tx, ty, tz, rx, ry, rz, ds = case["p"]
    # the published parameters, applied as EPSG defines them, give PROJ's answer
    out = apply_helmert7([case["accept"]], tx, ty, tz, rx, ry, rz, ds, case["conv"])
    np.testing.assert_allclose(out[0], case["expect"], atol=case["tol"])
    # estimation through the georeferencing path recovers them from exact point pairs
    src = _cloud_around(np.array(case["accept"]))
    dst = apply_helmert7(src, tx, ty, tz, rx, ry, rz, ds, case["conv"])
    g = ControlPoints([f"P{i}" for i in range(len(src))], src, dst, 0.001)
    r = georeference(g, case["crs"], GeorefParams(allow_geocentric=True, convention=case["conv"]))
    np.testing.assert_allclose(r.rotation_arcsec, [rx, ry, rz], atol=1e-6)
    assert abs(r.ds_ppm - ds) < 1e-6
    np.testing.assert_allclose(r.translation_m, [tx, ty, tz], atol=1e-4)
    p = np.array(case["accept"])
    np.testing.assert_allclose(p @ r.T_crs_map[:3, :3].T + r.T_crs_map[:3, 3], case["expect"], atol=case["tol"])
    # the other convention reports the same transformation with opposite rotation signs
    other = "position_vector" if case["conv"] == "coordinate_frame" else "coordinate_frame"
    ro = georeference(g, case["crs"], GeorefParams(allow_geocentric=True, convention=other))
    np.testing.assert_allclose(ro.rotation_arcsec, [-rx, -ry, -rz], atol=1e-6)
    np.testing.assert_array_equal(ro.T_crs_map, r.T_crs_map)


def test_epsg_9621_similarity_guidance_note_7_2():
    """EPSG:5166 (ED50 -> ETRS89 UTM 31N, method 9621) recovered from projected control points.

    ``E_T = XT0 + M(cos θ E + sin θ N)``, ``N_T = YT0 + M(−sin θ E + cos θ N)``: a 2D similarity,
    extended to 3D by scaling heights with M too (so that it is an exact 3D similarity).
    """
    shared_data("proj_helmert_gigs", "proj_cs2cs_similarity_epsg_gn7-2_excerpt.yaml")
    xt0, yt0, m, theta = -129.549, -208.185, 1.0000015504, 1.56504 / RHO_ARCSEC

    def sim(p):
        c, s = np.cos(theta), np.sin(theta)
        return np.column_stack(
            [xt0 + m * (c * p[:, 0] + s * p[:, 1]), yt0 + m * (-s * p[:, 0] + c * p[:, 1]), m * p[:, 2]]
        )

    gn = np.array([[300000.0, 4500000.0, 0.0]])
    np.testing.assert_allclose(sim(gn)[0, :2], [299905.060, 4499796.515], atol=5e-4)
    rng = np.random.default_rng(3)
    src = np.array([300000.0, 4500000.0, 0.0]) + rng.uniform(-5000, 5000, (8, 3)) * [1, 1, 0.02]
    g = ControlPoints([f"S{i}" for i in range(8)], src, sim(src), 0.001, crs="EPSG:25831")
    r = georeference(g)
    assert abs(r.scale - m) < 1e-12
    assert abs(r.euler_zyx_rad[2] + theta) < 1e-11  # EPSG θ is clockwise: yaw = −θ
    assert np.all(np.abs(r.euler_zyx_rad[:2]) < 1e-11)
    out = gn @ r.T_crs_map[:3, :3].T + r.T_crs_map[:3, 3]
    np.testing.assert_allclose(out[0, :2], [299905.060, 4499796.515], atol=5e-4)
    assert r.crs_info.epsg == 25831


@pytest.mark.parametrize("model", ["rigid", "similarity"])
def test_niosh_mine_fiducials_real_layout(model):
    """Real surveyed fiducial layout of the DARPA SubT EX course (NIOSH mine portal) -> UTM 17N.

    The UTM coordinates are computed from DARPA's published EX->UTM matrix (only the matrix is
    published) plus 3 mm survey noise, so this checks the fit on a real, weak mine-portal geometry
    (17 marks within 30 m x 3.5 m x 2.6 m) against a known answer: yaw −2.09661182 rad, scale 1.
    """
    import csv

    d = shared_data("subt_tunnel_niosh_mine")
    rows = [r for r in csv.DictReader(open(d / "fiducials_local_derived.csv", encoding="utf-8")) if r["course"] == "EX"]
    x = np.array([[float(r[k]) for k in ("x_m", "y_m", "z_m")] for r in rows])
    T = np.loadtxt(d / "darpa_to_utm17n_approx_derived.txt", comments="#")[4:8]
    assert abs(np.arctan2(T[1, 0], T[0, 0]) + 2.09661182) < 1e-8
    rng = np.random.default_rng(17)
    X = x @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, 0.003, x.shape)
    g = ControlPoints([r["name"] for r in rows], x, X, 0.003, crs="EPSG:32617")
    r = georeference(g, params=GeorefParams(model=model))
    assert r.status in ("ok", "warning") and not r.blunder.any()
    assert r.chi2["verdict"] == "PASSED"
    assert 0.05 < r.geometry_ratio < 0.2  # elongated portal layout, not flagged as collinear
    assert abs(r.euler_zyx_rad[2] + 2.09661182) < 3 * r.rotation_std_rad[2]
    assert np.all(np.abs(r.translation_m - T[:3, 3]) < 3 * r.translation_std_m)
    # grid factors at the mine: UTM k = k0 (1 + x^2 / 2R^2) with x = E - 500 km (to 2 ppm)
    k_tm = 0.9996 * (1 + (X[:, 0].mean() - 500000.0) ** 2 / (2 * 6371000.0**2))
    assert abs(r.grid_factors["point_scale_factor"] - k_tm) < 2e-6
    assert abs(r.grid_factors["lat_deg"] - 40.30497) < 1e-3
    if model == "rigid":
        # DARPA's matrix has no scale although the combined grid factor is about -351 ppm:
        # minegeo says what that costs over this GCP extent
        assert any("combined scale factor" in w for w in r.warnings)


def test_gigs_5101_tm_inverse_used_by_grid_factors():
    """The pyproj path behind the grid-factor and area-of-use checks reproduces IOGP GIGS 5101
    (Transverse Mercator, the method of EPSG:5186) reference points: (E, N) -> (lon, lat)."""
    from minegeo.georef import grid_scale_factors

    path = shared_data("proj_helmert_gigs", "gigs_5101.1-jhs.gie")
    text = path.read_text(encoding="utf-8")
    first = text.split("operation")[1]  # the forward block: accept (lon, lat) -> expect (E, N)
    lines = [ln.split() for ln in first.splitlines()]
    acc = [tuple(map(float, t[1:3])) for t in lines if t and t[0] == "accept"]
    exp = [tuple(map(float, t[1:3])) for t in lines if t and t[0] == "expect"]
    pairs = [(a, e) for a, e in zip(acc, exp, strict=True) if abs(a[1]) <= 60 and abs(a[0] + 2) <= 5][:12]
    assert len(pairs) >= 5
    crs = "+proj=tmerc +lat_0=49 +lon_0=-2 +k_0=0.9996012717 +x_0=400000 +y_0=-100000 +ellps=WGS84 +units=m +no_defs"
    for (lon, lat), (e, n) in pairs:
        gf = grid_scale_factors(crs, e, n, 0.0)
        # GIGS tolerance 0.03 m ~ 3e-7 degrees
        assert abs(gf["lon_deg"] - lon) < 5e-7 and abs(gf["lat_deg"] - lat) < 5e-7, (lon, lat, gf)
        assert gf["point_scale_factor"] >= 0.9996012717 - 1e-9  # TM: k >= k0 (pyproj numerical factors)
        assert gf["height_factor"] == 1.0
