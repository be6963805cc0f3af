"""``minegeo.io.dxf.write_control_dxf`` on its own (no SLAM run, well under a second): the automatic
exaggeration by hand, a rigid-mode drawing (no covariances: no ellipses, said so), flagged labels,
and the ellipse of a correlated covariance against the closed form of its eigenvalues."""

from __future__ import annotations

import math

import numpy as np
import pytest

from minegeo.io.dxf import nice_exaggeration, write_control_dxf

ezdxf = pytest.importorskip("ezdxf")


@pytest.mark.parametrize(("extent", "largest", "expected"), [
    (100.0, 0.03, 100.0),   # 5 m / 0.03 m = 166.7 -> 100
    (100.0, 0.012, 200.0),  # 416.7 -> 200
    (1000.0, 0.05, 1000.0),  # 1000 exactly
    (40.0, 0.5, 2.0),       # 4 -> 2
    (10.0, 1.0, 1.0),       # 0.5 -> at least 1
    (10.0, 0.0, 1.0),       # no residual
])
def test_nice_exaggeration_by_hand(extent, largest, expected):
    assert nice_exaggeration(extent, largest) == expected


def _stations():
    s = np.array([[220010.0, 613020.0, 150.0], [220060.0, 613025.0, 151.0], [220110.0, 613010.0, 149.5]])
    d = np.array([[0.01, -0.02, 0.005], [0.03, 0.01, -0.01], [-0.015, 0.0, 0.002]])
    return s, s + d


def test_rigid_drawing_without_covariances_has_no_ellipses_and_says_so(tmp_path):
    s, e = _stations()
    out = write_control_dxf(tmp_path / "r.dxf", ids=["A", "B", "C"], is_control=[True, False, True], surveyed_enh=s,
                            estimated_enh=e, cov_enh=None, trajectory_enh=np.r_[s, s[::-1]], crs="EPSG:5186",
                            flagged=["C"])
    doc = ezdxf.readfile(tmp_path / "r.dxf")
    layers = [en.dxf.layer for en in doc.modelspace()]
    assert "MINEGEO_ELLIPSE95" not in layers and out["ellipses"] == 0
    assert layers.count("MINEGEO_CONTROL_STATIONS") == 2 and layers.count("MINEGEO_CHECK_STATIONS") == 1
    props = dict(doc.header.custom_vars)
    assert props["MINEGEO_ELLIPSES"].startswith("none") and props["MINEGEO_FLAGGED"] == "C"
    texts = {t.dxf.text for t in doc.modelspace().query("TEXT")}
    assert {"A", "B", "C (flagged)"} <= texts
    # extent 100 m, longest horizontal residual sqrt(0.03^2 + 0.01^2) = 0.0316 m: 5 m / 0.0316 = 158 -> 100
    assert out["exaggeration"] == 100.0 and props["MINEGEO_EXAGGERATION"] == "100"
    assert any("x100" in t for t in texts)


def test_ellipse_of_a_correlated_covariance_against_the_closed_form(tmp_path):
    """sEE = 4e-4, sNN = 1e-4, sEN = 1.5e-4 m^2: eigenvalues (sEE + sNN)/2 ± sqrt(((sEE - sNN)/2)^2 + sEN^2);
    the major axis at azimuth t (clockwise from north) with tan 2t = 2 sEN / (sNN - sEE) (Ghilani 2010, 19)."""
    s, e = _stations()
    see, snn, sen = 4e-4, 1e-4, 1.5e-4
    cov = np.zeros((3, 3, 3))
    cov[:, :2, :2] = [[see, sen], [sen, snn]]
    cov[:, 2, 2] = 1e-4
    x = 50.0
    write_control_dxf(tmp_path / "g.dxf", ids=["A", "B", "C"], is_control=[True, False, True], surveyed_enh=s,
                      estimated_enh=e, cov_enh=cov, crs="EPSG:5186", exaggeration=x)
    doc = ezdxf.readfile(tmp_path / "g.dxf")
    ells = [np.array([tuple(v.dxf.location) for v in p.vertices]) for p in doc.modelspace().query("POLYLINE")
            if p.dxf.layer == "MINEGEO_ELLIPSE95"]
    assert len(ells) == 3
    m, r = 0.5 * (see + snn), math.hypot(0.5 * (see - snn), sen)
    k = math.sqrt(-2.0 * math.log(0.05))
    v = ells[1]
    c = s[1]
    assert np.allclose(v.mean(axis=0), c, atol=1e-9)
    major = v[0] - c
    assert np.linalg.norm(major[:2]) == pytest.approx(x * k * math.sqrt(m + r), abs=1e-9)  # coordinates near 2e5 m: 4e-11 m spacing
    assert np.linalg.norm((v[18] - c)[:2]) == pytest.approx(x * k * math.sqrt(m - r), abs=1e-9)
    az = math.atan2(major[0], major[1]) % math.pi
    t = 0.5 * math.atan2(2.0 * sen, snn - see) % math.pi  # the axis of the larger eigenvalue
    assert min(abs(az - t), math.pi - abs(az - t)) < 1e-9 or min(abs(az - (t + math.pi / 2) % math.pi),
                                                                   math.pi - abs(az - (t + math.pi / 2) % math.pi)) < 1e-9
    # the residual vector: surveyed -> surveyed + x (estimated - surveyed)
    vec = [np.array([tuple(q.dxf.location) for q in p.vertices]) for p in doc.modelspace().query("POLYLINE")
           if p.dxf.layer == "MINEGEO_RESIDUALS"]
    assert np.allclose(vec[1], [s[1], s[1] + x * (e[1] - s[1])], atol=1e-9)
