"""The stations CSV reader/writer and the ``--station-offset`` parser (minegeo.io.stations).

Expected values are the numbers written into the files (hand-made), not the reader's output."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import FileFormatError, InputError
from minegeo.io.stations import StationRole, Stations, parse_station_offset, read_stations, write_stations

TEXT = """# crs: EPSG:5186
# two control stations and a check station
ID;T_START;T_END;e;n;h;SIGMA_H_M;SIGMA_V_M;ROLE
S1;10.0;15.0;201345.112;551203.447;87.402;0.005;0.010;control
S2;40.25;45.5;201402.880;551388.019;86.911;0.004;0.012;Check
S3;70.0;70.0;201512.004;551502.771;86.100;0.006;0.011;CONTROL
"""


def test_read_values_roles_and_origin(tmp_path):
    f = tmp_path / "st.csv"
    f.write_text(TEXT, encoding="utf-8")
    st = read_stations(f)
    assert st.ids == ("S1", "S2", "S3")
    assert st.roles == (StationRole.CONTROL, StationRole.CHECK, StationRole.CONTROL)
    assert st.roles[1] == "check" and isinstance(st.roles[1], StationRole)
    assert st.is_control.tolist() == [True, False, True]
    assert st.crs == "EPSG:5186" and st.lines == (4, 5, 6)
    np.testing.assert_array_equal(st.t_start_s, [10.0, 40.25, 70.0])
    np.testing.assert_array_equal(st.t_end_s, [15.0, 45.5, 70.0])
    # origin: the centroid rounded to whole kilometres (201420.0 -> 201000, 551364.7 -> 551000, 86.8 -> 0)
    np.testing.assert_array_equal(st.origin_enh, [201000.0, 551000.0, 0.0])
    np.testing.assert_array_equal(st.enh_local[0], [201345.112 - 201000.0, 551203.447 - 551000.0, 87.402])
    np.testing.assert_array_equal(st.enh[1], [201402.880, 551388.019, 86.911])
    np.testing.assert_array_equal(st.sigma_h_m, [0.005, 0.004, 0.006])
    np.testing.assert_array_equal(st.covariance()[1], np.diag([0.004**2, 0.004**2, 0.012**2]))
    assert st.enh_local.dtype == np.float64 and not st.enh_local.flags.writeable
    with pytest.raises(InputError, match="station S3 stands"):
        st.check_time_span(0.0, 69.0)
    st.check_time_span(10.0, 70.0)


def test_write_read_roundtrip_exact(tmp_path):
    rng = np.random.default_rng(5)
    n = 7
    enh = np.column_stack([rng.uniform(2e5, 2.1e5, n), rng.uniform(5.5e5, 5.6e5, n), rng.uniform(-300, 300, n)])
    t0 = np.sort(rng.uniform(0, 1000, n)) + np.arange(n) * 10.0
    st = Stations(ids=[f"P{i}" for i in range(n)], t_start_s=t0, t_end_s=t0 + rng.uniform(0, 5, n),
                  enh_local=enh - [2e5, 5.5e5, 0.0], origin_enh=[2e5, 5.5e5, 0.0], sigma_h_m=rng.uniform(0.001, 0.01, n),
                  sigma_v_m=rng.uniform(0.001, 0.01, n), roles=["control", "check"] * 3 + ["control"], crs="EPSG:5186")
    back = read_stations(write_stations(tmp_path / "s.csv", st))
    np.testing.assert_array_equal(back.enh, st.enh)
    np.testing.assert_array_equal(back.t_start_s, t0)
    np.testing.assert_array_equal(back.t_end_s, st.t_end_s)
    np.testing.assert_array_equal(back.sigma_v_m, st.sigma_v_m)
    assert back.roles == st.roles and back.ids == st.ids and back.crs == "EPSG:5186"


def test_crs_conflict(tmp_path):
    f = tmp_path / "st.csv"
    f.write_text(TEXT, encoding="utf-8")
    with pytest.raises(FileFormatError, match="EPSG:5186"):
        read_stations(f, crs="EPSG:32652")


@pytest.mark.parametrize("value, expected", [("0 0 -1.25", [0, 0, -1.25]), ("0.1,-0.2,0.3", [0.1, -0.2, 0.3]),
                                             ([0, 0.5, 0], [0, 0.5, 0])])
def test_station_offset(value, expected):
    np.testing.assert_array_equal(parse_station_offset(value), expected)


@pytest.mark.parametrize("value", ["0 0", "0 0 1 2", "a b c", "0 0 nan", "0 0 1250", [0, 0]])
def test_station_offset_refused(value):
    with pytest.raises(InputError, match="--station-offset"):
        parse_station_offset(value)
