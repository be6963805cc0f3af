"""The IMU CSV reader and the T_lidar_imu extrinsic parser (minegeo.io.imu).

Expected values are the ones written into the files; the quaternion -> matrix reference is
SciPy's ``Rotation.from_quat`` (scalar last, as the contract's ``x y z qx qy qz qw``).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from minegeo.errors import FileFormatError, InputError
from minegeo.io.imu import ImuSamples, parse_extrinsic, read_imu_csv, write_imu_csv

HEADER = "t,gx,gy,gz,ax,ay,az\n"


def _rows(n=50, seed=3):
    rng = np.random.default_rng(seed)
    t = 1_700_000_000.0 + np.arange(n) * 0.005
    g = rng.normal(0, 0.2, (n, 3))
    a = rng.normal(0, 0.3, (n, 3)) + [0.0, 0.0, 9.81]
    return t, g, a


def _write(path, t, g, a, header=HEADER):
    lines = [header.rstrip("\n")]
    lines += [",".join(repr(float(v)) for v in (t[i], *g[i], *a[i])) for i in range(len(t))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_values_read_exactly(tmp_path):
    t, g, a = _rows()
    imu = read_imu_csv(_write(tmp_path / "imu.csv", t, g, a))
    assert isinstance(imu, ImuSamples) and len(imu) == 50
    np.testing.assert_array_equal(imu.t_s, t)
    np.testing.assert_array_equal(imu.gyro_rad_s, g)
    np.testing.assert_array_equal(imu.accel_m_s2, a)
    assert imu.frame == "lidar" and imu.T_lidar_imu is None
    assert imu.rate_hz == pytest.approx(200.0, rel=1e-4)  # 1.7e9 s stamps: 2.4e-7 s resolution
    with pytest.raises(ValueError):
        imu.t_s[0] = 0.0
    with pytest.raises(AttributeError):
        imu.frame = "x"


def test_header_spaces_comments_and_roundtrip(tmp_path):
    t, g, a = _rows(5)
    f = _write(tmp_path / "imu.csv", t, g, a, header="# logged by a test\n t, gx, gy, gz, ax, ay, az\n")
    imu = read_imu_csv(f)
    np.testing.assert_array_equal(imu.gyro_rad_s, g)
    back = read_imu_csv(write_imu_csv(tmp_path / "again.csv", imu))
    np.testing.assert_array_equal(back.accel_m_s2, a)
    np.testing.assert_array_equal(back.t_s, t)


def test_extrinsic_given_means_imu_frame(tmp_path):
    t, g, a = _rows(5)
    imu = read_imu_csv(_write(tmp_path / "imu.csv", t, g, a), extrinsic="0.1 0.2 0.3 0 0 0 1")
    assert imu.frame == "imu"
    np.testing.assert_array_equal(imu.T_lidar_imu[:3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(imu.gyro_rad_s, g)  # the samples stay in the IMU frame


@pytest.mark.parametrize("case,edit,expect", [
    ("unsorted", lambda L: L[:10] + [L[11], L[10]] + L[12:], "line 12"),
    ("duplicate", lambda L: L[:10] + [L[9]] + L[11:], "line 11"),
    ("nan", lambda L: L[:7] + [L[7].replace(L[7].split(",")[2], "nan", 1)] + L[8:], "line 8: gy is NaN"),
    ("inf", lambda L: L[:7] + [L[7].rsplit(",", 1)[0] + ",inf"] + L[8:], "line 8: az is NaN or infinite"),
    ("wrong_header", lambda L: ["t,gx,gy,gz,ax,ay"] + L[1:], "expected 't,gx,gy,gz,ax,ay,az'"),
    ("other_order", lambda L: ["t,ax,ay,az,gx,gy,gz"] + L[1:], "line 1: IMU CSV header"),
    ("short_row", lambda L: L[:5] + [L[5].rsplit(",", 1)[0]] + L[6:], "line 6"),
    ("not_a_number", lambda L: L[:5] + [L[5].replace(L[5].split(",")[1], "abc", 1)] + L[6:], "line 6"),
    ("header_only", lambda L: L[:1], "no samples"),
    ("empty", lambda L: [], "empty IMU CSV"),
])
def test_bad_csv_names_the_line(tmp_path, case, edit, expect):
    t, g, a = _rows(20)
    f = _write(tmp_path / "imu.csv", t, g, a)
    lines = f.read_text(encoding="utf-8").splitlines()
    f.write_text("\n".join(edit(lines)) + "\n", encoding="utf-8")
    with pytest.raises(FileFormatError) as ei:
        read_imu_csv(f)
    assert "imu.csv" in str(ei.value) and expect in str(ei.value), str(ei.value)


def test_gap_limit(tmp_path):
    t, g, a = _rows(20)
    t[12:] += 0.5  # a 0.505 s gap before row 12 (line 14)
    f = _write(tmp_path / "imu.csv", t, g, a)
    assert len(read_imu_csv(f)) == 20
    with pytest.raises(FileFormatError, match="line 14: 0.505 s without IMU samples"):
        read_imu_csv(f, max_gap_s=0.1)


def test_accel_in_g_is_flagged(tmp_path, caplog):
    t, g, a = _rows(20)
    read_imu_csv(_write(tmp_path / "imu.csv", t, g, a / 9.81))
    assert "units of g" in caplog.text


def test_extrinsic_seven_numbers_against_scipy():
    q = np.array([0.1, -0.2, 0.3, 0.9])
    q_unit = q / np.linalg.norm(q)
    T = parse_extrinsic("1.5 -2 0.25 " + " ".join(repr(float(v)) for v in q_unit))
    np.testing.assert_allclose(T[:3, :3], Rotation.from_quat(q_unit).as_matrix(), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(T[:3, 3], [1.5, -2.0, 0.25])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_extrinsic_matrix_text_file_and_array(tmp_path):
    R = Rotation.from_euler("zyx", [30, 5, -3], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.05, 0.0, -0.12]
    f = tmp_path / "T_lidar_imu.txt"
    f.write_text("# T_lidar_imu\n" + "\n".join(" ".join(repr(float(v)) for v in row) for row in T) + "\n")
    np.testing.assert_array_equal(parse_extrinsic(str(f)), T)
    np.testing.assert_array_equal(parse_extrinsic(f), T)
    np.testing.assert_array_equal(parse_extrinsic(T), T)
    np.testing.assert_array_equal(parse_extrinsic(T[:3].ravel()), T)


@pytest.mark.parametrize("value,expect", [
    ("1 2 3", "3 numbers"),
    ("0 0 0 0 0 0 0", "is zero"),
    ("0 0 0 0 0 0 2", "norm 2"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    (np.eye(4) * [1.0, 1.1, 1.0, 1.0], "not a rotation"),
    ("1 2 x 0 0 0 1", "expected numbers"),
    ("0 0 nan 0 0 0 1", "NaN"),
])
def test_bad_extrinsic(value, expect):
    with pytest.raises(InputError, match=expect):
        parse_extrinsic(value)


def test_imu_noise_from_a_kalibr_yaml_flat_or_under_one_imu(tmp_path):
    """Kalibr's imu.yaml (flat) and an imu-chain file of one IMU (keys indented under its name) give the
    four figures typed here by hand; quotes, comments and the other keys do not matter."""
    from minegeo.io.imu import read_imu_noise

    want = {"gyroscope_noise_density": 1.6968e-04, "gyroscope_random_walk": 1.9393e-05,
            "accelerometer_noise_density": 2.0e-3, "accelerometer_random_walk": 3.0e-3}
    flat = tmp_path / "imu.yaml"
    flat.write_text("rostopic: /imu0\nupdate_rate: 200.0  # Hz\n"
                    "gyroscope_noise_density: 1.6968e-04\ngyroscope_random_walk: '1.9393e-05'\n"
                    "accelerometer_noise_density: 2.0e-3 # white\naccelerometer_random_walk: \"3.0e-3\"\n")
    chain = tmp_path / "imu_chain.yaml"
    chain.write_text("imu0:\n  T_i_b:\n  - [1.0, 0.0, 0.0, 0.0]\n  accelerometer_noise_density: 2.0e-3\n"
                     "  accelerometer_random_walk: 3.0e-3\n  gyroscope_noise_density: 1.6968e-04\n"
                     "  gyroscope_random_walk: 1.9393e-05\n  model: calibrated\n")
    assert read_imu_noise(flat) == want
    assert read_imu_noise(chain) == want


@pytest.mark.parametrize("text,ok", [("1e-300", True), ("2.5", True), ("1e300", True), ("0", False), ("-0.0", False),
                                     ("-1e-3", False), ("inf", False), ("nan", False), ("0.1.2", False), ("", False)])
@pytest.mark.parametrize("key", ["gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                                 "accelerometer_random_walk"])
def test_imu_noise_value_takes_what_its_field_takes(key, text, ok, tmp_path):
    """Each figure of the file takes what the ImuNoise field of its name takes (a finite number > 0,
    hand-listed here); a refused one names the file, the line and the key with the field's rule."""
    from minegeo.io.imu import IMU_NOISE_KEYS, read_imu_noise

    f = tmp_path / "imu.yaml"
    f.write_text("".join(f"{k}: {text if k == key else '1e-3'}\n" for k in IMU_NOISE_KEYS))
    line = IMU_NOISE_KEYS.index(key) + 1
    if ok:
        assert read_imu_noise(f)[key] == float(text)
    else:
        with pytest.raises(FileFormatError) as exc:
            read_imu_noise(f)
        msg = str(exc.value)
        assert str(f) in msg and f"line {line}: {key} must be a finite number > 0, got {text!r}" in msg, msg
