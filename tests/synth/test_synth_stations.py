"""Stop-and-go survey stations of the synthetic sensor stream (minegeo.synth.stream, issue 30 item 5).

References are independent of the code under test: poses from ``MotionCurve.poses`` (4x4
matrices) mapped with T_crs_world, the CRS origin from pyproj directly, gravity from the constant."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.io.stations import StationRole, read_stations
from minegeo.synth.stream import PRESETS, StreamParams, _write_stations, simulate_stream, stream_stations

OFFSET = (0.12, -0.3, -0.45)


@pytest.fixture(scope="module", params=["vehicle", "drone"])
def stream(request):
    return simulate_stream(StreamParams(preset=request.param, duration_s=55.0, station_spacing_m=12.0,
                                        control_every=3, station_offset_m=OFFSET, seed=4))


def test_still_on_every_station(stream):
    spans = stream.station_spans
    assert len(spans) >= 3
    np.testing.assert_allclose(spans[:, 1] - spans[:, 0], 3.0, atol=1e-9)
    for a, b in spans:
        T = stream.curve.poses(np.linspace(a, b, 257))
        assert np.abs(T - T[0]).max() <= 1e-9
        st = stream.curve.state(np.linspace(a, b, 257))
        assert np.abs(st.v).max() <= 1e-9 and np.abs(st.omega).max() <= 1e-9
    # the noise-free IMU at rest reads R^T (-g) = R^T (0, 0, +9.80665) and no rotation
    imu = stream.imu
    for a, b in spans:
        m = (imu.t >= a) & (imu.t <= b)
        assert m.sum() >= 500
        R = stream.curve.poses(imu.t[m])[:, :3, :3]
        expected = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, 9.80665]))
        np.testing.assert_allclose(imu.accel_true[m], expected, atol=1e-9, rtol=0)
        np.testing.assert_allclose(imu.gyro_true[m], 0.0, atol=1e-9)
        assert np.abs(imu.accel[m] - imu.accel_true[m]).max() > 0           # the measured IMU is noisy


def test_moves_between_stations_within_the_preset_limits(stream):
    p = stream.params
    pre = PRESETS[p.preset]
    t = np.arange(stream.curve.t_start, stream.station_spans[-1, 1], 0.01)
    s = stream.curve.state(t)
    spans = stream.station_spans
    mids = 0.5 * (spans[1:, 0] + spans[:-1, 1])
    moved = np.linalg.norm(np.diff(stream.curve.poses(np.r_[spans[0, 0], mids[:1], spans[1, 0]])[:, :3, 3], axis=0),
                           axis=1)
    assert moved.min() > 3.0                                               # it drives between the stops
    v = s.v[:, :2]
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() <= pre.speed_mps * 1.05
    if p.preset == "vehicle":                                              # no sway: the path's own deceleration
        u = v / np.maximum(speed, 1e-9)[:, None]
        along = np.abs(np.einsum("ij,ij->i", s.a[:, :2], u))[speed > 0.05]
        assert along.max() <= 1.1 * pre.accel_mps2


def test_station_coordinates_are_the_true_pose_in_the_crs(stream, tmp_path):
    from pyproj import Transformer

    from minegeo.synth.dataset import MINE_LAT_DEG, MINE_LON_DEG

    stations, truth = stream_stations(stream)
    T = truth["T_crs_world"]
    E0, N0 = Transformer.from_crs("EPSG:4326", "EPSG:5186", always_xy=True).transform(MINE_LON_DEG, MINE_LAT_DEG)
    np.testing.assert_allclose(T[:2, 3], [E0, N0], atol=6e-4)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert T[2, 2] == 1.0
    # independent recomputation: T_crs_world T_world_sensor(t) [offset; 1], at the middle of each span
    spans = stream.station_spans
    P = np.einsum("ij,njk,k->ni", T, stream.curve.poses(spans.mean(axis=1)), np.r_[OFFSET, 1.0])[:, :3]
    np.testing.assert_allclose(truth["enh_true"], P, atol=1e-6, rtol=0)
    # the surveyed coordinates: truth + survey noise (sigma 5 / 8 mm)
    err = stations.enh - P
    assert np.abs(err[:, :2]).max() < 5 * 0.005 and np.abs(err[:, 2]).max() < 5 * 0.008
    assert np.abs(err).max() > 0
    # written and read back per the contract, roles control every 3rd from the first
    _write_stations(tmp_path, stream)
    back = read_stations(tmp_path / "stations.csv")
    np.testing.assert_array_equal(back.enh, stations.enh)
    np.testing.assert_array_equal(back.t_start_s, spans[:, 0])
    assert back.crs == "EPSG:5186"
    assert [r is StationRole.CONTROL for r in back.roles] == [i % 3 == 0 for i in range(len(spans))]
    tr = np.genfromtxt(tmp_path / "stations_truth.csv", delimiter=",", skip_header=2, usecols=(3, 4, 5))
    np.testing.assert_allclose(tr.reshape(-1, 3), P, atol=1e-6, rtol=0)


def test_deterministic_and_stream_without_stations_unchanged(tmp_path):
    kw = dict(preset="handheld", duration_s=25.0, seed=9)
    a = simulate_stream(StreamParams(**kw, station_spacing_m=10.0))
    b = simulate_stream(StreamParams(**kw, station_spacing_m=10.0))
    for name, st in (("a", a), ("b", b)):
        (tmp_path / name).mkdir()
        _write_stations(tmp_path / name, st)
    for f in ("stations.csv", "stations_truth.csv"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    # without stations the IMU noise and bias streams are those of the stations run (the fifth seed child
    # does not shift them), and the stations run is still where it stands
    plain = simulate_stream(StreamParams(**kw))
    assert len(plain.station_spans) == 0 and plain.station_seed is None
    np.testing.assert_array_equal(plain.imu.bias_accel, a.imu.bias_accel)


def test_standing_curve_exact_far_from_the_origin():
    """Equal control points (a stop) give an exactly constant pose and zero rates even at survey-grid
    magnitudes (5e5 m), where a plain sum of basis-weighted points leaves ~1e-7 m/s^2 of rounding."""
    from minegeo.synth.motion import MotionCurve

    ctrl = np.tile([512345.678, 4123456.789, 231.5, 1.1, 0.02, -0.03], (8, 1))
    st = MotionCurve(t0_s=0.0, dt_knot_s=0.01, ctrl=ctrl).state(np.linspace(0.0, 0.05, 101))
    assert np.all(st.p == ctrl[0, :3]) and np.all(st.a == 0.0) and np.all(st.v == 0.0) and np.all(st.omega == 0.0)
