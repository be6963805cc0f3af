"""Angles (DMS, gon, azimuths, bearings) and error ellipses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minegeo.errors import InputError
from minegeo.survey import (
    azimuth,
    azimuth_distance,
    azimuth_to_bearing,
    bearing_to_azimuth,
    ellipse_scale,
    error_ellipse,
    format_dms,
    parse_angle,
    parse_dms,
    polar_to_rect,
    relative_ellipse,
)


def test_dms_examples():
    assert format_dms(math.radians(parse_dms("355°10'02.8\""))) == "355°10'02.8\""
    assert abs(parse_dms("355-10-02.8") - (355 + 10 / 60 + 2.8 / 3600)) < 1e-12
    assert abs(parse_dms("-0°06'24.5\"") + (6 / 60 + 24.5 / 3600)) < 1e-12
    assert parse_dms("240°") == 240.0
    assert format_dms(math.radians(59.9999999)) == "60°00'00.0\""  # rounding carries
    assert format_dms(math.radians(183.2180556), 0) == "183°13'05\""
    assert abs(parse_angle("33.8805555555556", "gon") - 33.8805555555556 * math.pi / 200) < 1e-15
    with pytest.raises(InputError):
        parse_dms("12°75'00\"")
    with pytest.raises(InputError):
        parse_dms("north")


@settings(max_examples=30, deadline=None)
@given(st.floats(0, 359.9999))
def test_dms_roundtrip(deg):
    txt = format_dms(math.radians(deg), 3)
    assert abs(parse_dms(txt) - deg) <= 0.0005 / 3600 + 1e-12 or abs(parse_dms(txt) - deg - 360) < 1e-6


def test_azimuth_quadrants_and_bearings():
    assert azimuth(0, 1) == 0.0
    assert abs(azimuth(1, 0) - math.pi / 2) < 1e-15
    assert abs(azimuth(0, -1) - math.pi) < 1e-15
    assert abs(azimuth(-1, 0) - 1.5 * math.pi) < 1e-15
    assert abs(azimuth(-1, 1) - 1.75 * math.pi) < 1e-15
    assert azimuth_to_bearing(math.radians(139 + 50 / 60)) == "S 40°10'00.0\" E"
    assert azimuth_to_bearing(math.radians(315)) == "N 45°00'00.0\" W"
    assert abs(bearing_to_azimuth("S 40°10'00\" E") - math.radians(139 + 50 / 60)) < 1e-12
    assert abs(bearing_to_azimuth("N45-00-00W") - math.radians(315)) < 1e-12
    with pytest.raises(InputError):
        bearing_to_azimuth("N 95°00'00\" E")
    with pytest.raises(InputError):
        azimuth(0.0, 0.0)


@settings(max_examples=30, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(0, 2 * math.pi - 1e-9), st.floats(0.01, 5000))
def test_forward_inverse_roundtrip(e0, n0, az, s):
    e1, n1 = polar_to_rect(e0, n0, az, s)
    a2, s2 = azimuth_distance(e0, n0, e1, n1)
    assert abs(s2 - s) < 1e-9 * max(1.0, abs(e0) + abs(n0))
    d = (a2 - az + math.pi) % (2 * math.pi) - math.pi
    assert abs(d) * s < 1e-8 * max(1.0, abs(e0) + abs(n0))


def test_ellipse_scales_and_orientation():
    k, basis = ellipse_scale(0.95, sigma0_known=True)
    assert f"{k:.4f}" == "2.4477" and "chi2" in basis
    k2, basis2 = ellipse_scale(0.95, dof=10, sigma0_known=False)
    assert f"{k2:.4f}" == "2.8645" and "F(2,r)" in basis2
    e = error_ellipse([[1.0, 0.0], [0.0, 4.0]])
    assert e.semi_major_m == 2.0 and e.semi_minor_m == 1.0 and e.azimuth_rad == 0.0
    e = error_ellipse([[4.0, 0.0], [0.0, 1.0]], confidence=0.95)
    assert abs(e.azimuth_rad - math.pi / 2) < 1e-15 and abs(e.semi_major_m - 2 * k) < 1e-12
    e = error_ellipse([[2.0, 1.0], [1.0, 2.0]])  # major axis towards north-east
    assert abs(e.azimuth_rad - math.pi / 4) < 1e-12


def test_relative_ellipse_of_identical_errors_is_zero():
    C = np.array([[1.0, 0.2], [0.2, 2.0]])
    full = np.block([[C, C], [C, C]])
    r = relative_ellipse(full, 0, 1)
    assert r.semi_major_m == 0.0 and r.semi_minor_m == 0.0
    full = np.block([[C, np.zeros((2, 2))], [np.zeros((2, 2)), C]])
    r = relative_ellipse(full, 0, 1)
    assert abs(r.semi_major_m**2 - 2 * error_ellipse(C).semi_major_m ** 2) < 1e-12
