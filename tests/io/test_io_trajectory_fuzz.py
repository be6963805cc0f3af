"""Fuzzing the trajectory readers (TUM, KITTI, CSV, GeoSLAM) and the times reader with hypothesis.

Properties:

* any bytes, and any damage to a valid file, give either a trajectory that satisfies the readers'
  invariants (checked here independently: times finite, within 1e20 s, strictly increasing; proper
  rotations; finite positions within 1e12) or a :class:`FileFormatError` / :class:`InputError`,
  never another exception and never a NumPy ``RuntimeWarning``;
* for files built from chosen values (some of them wrong: a duplicated or decreasing time, NaN, a
  huge time, a zero or long quaternion, a reflection), the reader accepts exactly the files a naive
  twin of the rules (written here, value by value, in plain Python) accepts, and then returns the
  file's values: times and positions bit for bit, rotations equal to SciPy's ``Rotation.from_quat``;
* write -> read round trips reproduce the trajectory (times and positions exactly; rotations to
  1e-14, or exactly for KITTI), and the writer refuses exactly what the reader would refuse.

Hypothesis is derandomised so CI is deterministic.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from minegeo.errors import FileFormatError, InputError
from minegeo.io import Trajectory, read_trajectory, write_trajectory
from minegeo.io.trajectory import read_times

SETTINGS = settings(max_examples=120, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FORMATS = {"tum": "t.tum", "kitti": "t.kitti", "csv": "t.csv", "geoslam": "t_traj.txt"}
MAX_TIME = 1e20
MAX_COORD = 1e12


def _read(path, **kw):
    """The reader under a RuntimeWarning-is-an-error filter; None when it refuses with a typed error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            return read_trajectory(path, **kw)
        except (FileFormatError, InputError):
            return None


def _assert_invariants(tr: Trajectory) -> None:
    """The readers' promises, computed here without the reader's own check functions."""
    t, P = tr.times_s, tr.poses
    m = t.shape[0]
    assert m >= 1 and P.shape == (m, 4, 4)
    assert all(math.isfinite(v) and abs(v) <= MAX_TIME for v in t.tolist())
    assert all(b > a for a, b in zip(t.tolist(), t.tolist()[1:], strict=False))
    assert np.isfinite(P).all() and (np.abs(P[:, :3, 3]) <= MAX_COORD).all()
    assert (P[:, 3] == [0.0, 0.0, 0.0, 1.0]).all()
    for R in P[:, :3, :3]:
        assert np.abs(R.T @ R - np.eye(3)).max() <= 1e-4
        assert abs(np.linalg.det(R) - 1.0) <= 1e-3


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    from minegeo.geometry.se3 import exp_so3

    d = tmp_path_factory.mktemp("traj_seeds")
    rng = np.random.default_rng(17)
    m = 5
    P = np.tile(np.eye(4), (m, 1, 1))
    for i in range(m):
        P[i, :3, :3] = exp_so3(rng.normal(size=3))
        P[i, :3, 3] = rng.normal(size=3) * 50
    tr = Trajectory(1.6e9 + np.arange(m) * 0.1, P)
    out = {}
    for fmt, name in FORMATS.items():
        t = tr if fmt != "kitti" else Trajectory(np.arange(m, dtype=float), P)
        write_trajectory(d / name, t, format=fmt)
        out[fmt] = (d / name).read_bytes()
        assert _read(d / name) is not None
    (d / "times.txt").write_text("".join(f"{v:.17g}\n" for v in tr.times_s))
    out["times"] = (d / "times.txt").read_bytes()
    return out


NASTY = [b"nan", b"inf", b"-inf", b"1e308", b"-1.7e308", b"1e400", b"0", b"-0", b"1e21", b"abc", b"", b"#", b"\n",
         b",", b";", b"\x00", b"\xff", b"9" * 40, b"1e-320", b"1_0", b"Time X Y Z q0 q1 q2 q3", b"time_s,x,y,z,qx,qy,qz,qw"]


@st.composite
def damaged(draw, seed: bytes) -> bytes:
    b = bytearray(seed)
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "flip", "insert", "nasty", "swap_lines", "duplicate_line"]))
        if not b:
            break
        if op == "truncate":
            del b[draw(st.integers(0, len(b) - 1)):]
        elif op == "flip":
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        elif op == "insert":
            i = draw(st.integers(0, len(b)))
            b[i:i] = draw(st.binary(min_size=1, max_size=12))
        elif op == "nasty":
            i = draw(st.integers(0, len(b)))
            b[i:min(len(b), i + draw(st.integers(0, 8)))] = draw(st.sampled_from(NASTY))
        else:
            lines = bytes(b).split(b"\n")
            i, j = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            if op == "swap_lines":
                lines[i], lines[j] = lines[j], lines[i]
            else:
                lines.insert(i, lines[j])
            b = bytearray(b"\n".join(lines))
    return bytes(b)


# ------------------------------------------------------------------------------- any bytes


@SETTINGS
@given(data=st.binary(max_size=600), fmt=st.sampled_from(sorted(FORMATS)))
def test_any_bytes_give_a_valid_trajectory_or_a_typed_error(tmp_path, data, fmt):
    p = tmp_path / FORMATS[fmt]
    p.write_bytes(data)
    tr = _read(p)
    if tr is not None:
        _assert_invariants(tr)


@SETTINGS
@given(data=st.data(), fmt=st.sampled_from(sorted(FORMATS)))
def test_damaged_files_give_a_valid_trajectory_or_a_typed_error(tmp_path, seeds, data, fmt):
    p = tmp_path / FORMATS[fmt]
    p.write_bytes(data.draw(damaged(seeds[fmt])))
    tr = _read(p)
    event("accepted" if tr is not None else "refused")
    if tr is not None:
        _assert_invariants(tr)


def _read_times(path, count=None):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            return read_times(path, count)
        except FileFormatError:
            return None


@SETTINGS
@given(data=st.data(), raw=st.booleans())
def test_times_reader_on_any_bytes_and_damaged_files(tmp_path, seeds, data, raw):
    p = tmp_path / "times.txt"
    p.write_bytes(data.draw(st.binary(max_size=300)) if raw else data.draw(damaged(seeds["times"])))
    t = _read_times(p)
    if t is not None:
        assert t.dtype == np.float64 and t.ndim == 1 and t.size >= 1
        assert all(math.isfinite(v) and abs(v) <= MAX_TIME for v in t.tolist())
        assert all(b > a for a, b in zip(t.tolist(), t.tolist()[1:], strict=False))


# --------------------------------------------------------------- chosen values, a naive twin

#: wrong (or edge) values, one of which may replace a good one
BAD_TIMES = [float("nan"), float("inf"), -float("inf"), 1.7e308, -1.7e308, 1e20, -1e20, 1.0000001e20, 0.0, -0.0, 5e-324]
BAD_QUATS = [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0), (0.0, 0.0, 0.0, 1.005), (0.0, 0.0, 0.0, 1.02),
             (1e300, 1e300, 0.0, 0.0), (0.0, 0.0, 0.0, float("nan")), (1e-200, 0.0, 0.0, 0.0)]
BAD_POS = [1e12, -1e12, 1.0000001e12, 1e300, float("inf"), float("nan")]
UNIT_QUAT = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(v * v for v in q) > 1e-6).map(
    lambda q: tuple(v / math.sqrt(sum(u * u for u in q)) for v in q))


@st.composite
def time_series(draw, max_size: int = 6) -> list[float]:
    """Increasing times, then at most one fault: a duplicate, a swap, or a wrong or edge value."""
    t = sorted(draw(st.lists(st.floats(-1e10, 1e10), min_size=1, max_size=max_size, unique=True)))
    i = draw(st.integers(0, len(t) - 1))
    fault = draw(st.sampled_from(["none", "none", "duplicate", "swap", "value"]))
    if fault == "duplicate" and len(t) > 1:
        t[i] = t[i - 1]
    elif fault == "swap" and len(t) > 1:
        t[i], t[i - 1] = t[i - 1], t[i]
    elif fault == "value":
        t[i] = draw(st.sampled_from(BAD_TIMES))
    return t


@st.composite
def pose_rows(draw):
    """Rows ``(t, x, y, z, qx, qy, qz, qw)``: valid, or with a fault in the times, a position or a quaternion."""
    t = draw(time_series())
    m = len(t)
    xyz = [list(r) for r in draw(st.lists(st.tuples(*[st.floats(-1e6, 1e6)] * 3), min_size=m, max_size=m))]
    q = draw(st.lists(UNIT_QUAT, min_size=m, max_size=m))
    where = draw(st.integers(0, m - 1))
    fault = draw(st.sampled_from(["none", "position", "quaternion"]))
    if fault == "position":
        xyz[where][draw(st.integers(0, 2))] = draw(st.sampled_from(BAD_POS))
    elif fault == "quaternion":
        q[where] = draw(st.sampled_from(BAD_QUATS))
    return [(t[k], *xyz[k], *q[k]) for k in range(m)]


def _tum_twin_valid(rows) -> bool:
    """The rules of the module docstring of minegeo.io.trajectory, value by value."""
    times = [r[0] for r in rows]
    for t, x, y, z, *q in rows:
        if not all(math.isfinite(v) for v in (t, x, y, z, *q)):
            return False
        if abs(t) > MAX_TIME or max(abs(x), abs(y), abs(z)) > MAX_COORD:
            return False
        if not abs(math.sqrt(sum(v * v for v in q)) - 1.0) <= 1e-2:
            return False
    return all(b > a for a, b in zip(times, times[1:], strict=False))


@SETTINGS
@given(rows=pose_rows(), fmt=st.sampled_from(["tum", "csv", "geoslam"]))
def test_quaternion_formats_accept_exactly_what_the_rules_accept(tmp_path, rows, fmt):
    from scipy.spatial.transform import Rotation

    if fmt == "tum":
        text = "".join(" ".join(repr(v) for v in r) + "\n" for r in rows)
    elif fmt == "csv":
        text = "time_s,x,y,z,qx,qy,qz,qw\n" + "".join(",".join(repr(v) for v in r) + "\n" for r in rows)
    else:  # scalar first
        text = "Time X Y Z q0 q1 q2 q3\n" + "".join(
            " ".join(repr(v) for v in (*r[:4], r[7], r[4], r[5], r[6])) + "\n" for r in rows)
    p = tmp_path / FORMATS[fmt]
    p.write_text(text)
    tr = _read(p)
    event("accepted" if tr is not None else "refused")
    assert (tr is not None) == _tum_twin_valid(rows), text
    if tr is not None:
        _assert_invariants(tr)
        assert tr.times_s.tolist() == [r[0] for r in rows]
        assert tr.poses[:, :3, 3].tolist() == [list(r[1:4]) for r in rows]
        np.testing.assert_allclose(tr.poses[:, :3, :3], Rotation.from_quat([r[4:] for r in rows]).as_matrix(),
                                   rtol=0, atol=1e-14)


@SETTINGS
@given(n=st.integers(1, 5), seed=st.integers(0, 2**32 - 1),
       damage=st.sampled_from(["none", "reflect", "scale", "shear", "nan", "huge", "six_digits"]), at=st.integers(0, 4))
def test_kitti_accepts_exactly_the_proper_rotations(tmp_path, n, seed, damage, at):
    from scipy.spatial.transform import Rotation

    at %= n  # the damaged pose
    rng = np.random.default_rng(seed)
    M = np.zeros((n, 3, 4))
    M[:, :, :3] = Rotation.random(n, random_state=seed).as_matrix()
    M[:, :, 3] = rng.normal(size=(n, 3)) * 100
    if damage == "reflect":
        M[at, :, rng.integers(3)] *= -1.0
    elif damage == "scale":
        M[at, :, :3] *= 1.001
    elif damage == "shear":
        M[at, 0, 1] += 1e-3
    elif damage == "nan":
        M[at, 1, 1] = np.nan
    elif damage == "huge":
        M[at, 2, 3] = 1e300
    fmt = "%.6g" if damage == "six_digits" else "%.17g"
    text = "".join(" ".join(fmt % v for v in row.ravel()) + "\n" for row in M)
    p = tmp_path / "t.kitti"
    p.write_text(text)
    tr = _read(p)
    R = np.array([[float(fmt % v) for v in row] for row in M[:, :, :3].reshape(-1, 3)]).reshape(n, 3, 3)
    with np.errstate(invalid="ignore"):
        twin = bool(np.isfinite(M).all() and np.abs(M[:, :, 3]).max() <= MAX_COORD and all(
            np.abs(r.T @ r - np.eye(3)).max() <= 1e-4 and np.linalg.det(r) > 0 for r in R))
    event("accepted" if tr is not None else "refused")
    assert (tr is not None) == twin, (damage, text)
    if tr is not None:
        _assert_invariants(tr)
        np.testing.assert_array_equal(tr.poses[:, :3, :3], R)
        assert tr.times_s.tolist() == list(range(n))


@SETTINGS
@given(values=time_series())
def test_times_reader_accepts_exactly_what_the_rules_accept(tmp_path, values):
    p = tmp_path / "times.txt"
    p.write_text("".join(f"{v!r}\n" for v in values))
    t = _read_times(p, len(values))
    twin = all(math.isfinite(v) and abs(v) <= MAX_TIME for v in values) and all(
        b > a for a, b in zip(values, values[1:], strict=False))
    event("accepted" if t is not None else "refused")
    assert (t is not None) == twin, values
    if t is not None:
        assert t.tolist() == values


# --------------------------------------------------------------------------------- round trips

INCREASING = st.lists(st.floats(-1e20, 1e20, allow_nan=False), min_size=1, max_size=8, unique=True).map(sorted)


@st.composite
def trajectories(draw):
    from scipy.spatial.transform import Rotation

    t = np.array(draw(INCREASING), dtype=np.float64)
    m = t.size
    seed = draw(st.integers(0, 2**32 - 1))
    R = Rotation.random(m, random_state=seed).as_matrix().reshape(m, 3, 3)
    if draw(st.booleans()):  # rotations by pi: Shepperd's off-trace branches
        R[0] = np.diag([1.0, -1.0, -1.0]) if draw(st.booleans()) else np.diag([-1.0, -1.0, 1.0])
    P = np.tile(np.eye(4), (m, 1, 1))
    P[:, :3, :3] = R
    P[:, :3, 3] = np.array(draw(st.lists(st.floats(-1e12, 1e12), min_size=3 * m, max_size=3 * m))).reshape(m, 3)
    return Trajectory(t, P)


@SETTINGS
@given(tr=trajectories(), fmt=st.sampled_from(sorted(FORMATS)))
def test_write_then_read_reproduces_the_trajectory(tmp_path, tr, fmt):
    p = tmp_path / FORMATS[fmt]
    if fmt == "kitti":
        tr = Trajectory(np.arange(len(tr), dtype=float), tr.poses)
    write_trajectory(p, tr, format=fmt)
    back = _read(p)
    assert back is not None
    assert back.times_s.tolist() == tr.times_s.tolist()
    assert back.poses[:, :3, 3].tolist() == tr.poses[:, :3, 3].tolist()
    if fmt == "kitti":
        np.testing.assert_array_equal(back.poses, tr.poses)
    else:
        np.testing.assert_allclose(back.poses, tr.poses, rtol=0, atol=1e-14)


@SETTINGS
@given(values=time_series(), fmt=st.sampled_from(["tum", "csv", "geoslam"]))
def test_the_writer_refuses_exactly_what_the_reader_would_refuse(tmp_path, values, fmt):
    m = len(values)
    tr = Trajectory.__new__(Trajectory)  # times the Trajectory type itself refuses (NaN) are built anyway
    tr.times_s, tr.poses, tr.origin = np.asarray(values, dtype=np.float64), np.tile(np.eye(4), (m, 1, 1)), np.zeros(3)
    tr.frame, tr.body, tr.crs = "world", "sensor", None
    p = tmp_path / FORMATS[fmt]
    p.unlink(missing_ok=True)  # tmp_path is shared by the examples
    try:
        write_trajectory(p, tr, format=fmt)
    except InputError:
        assert not p.exists()
        written = False
    else:
        written = True
        back = _read(p)
        assert back is not None and back.times_s.tolist() == values
    twin = all(math.isfinite(v) and abs(v) <= MAX_TIME for v in values) and all(
        b > a for a, b in zip(values, values[1:], strict=False))
    assert written == twin, values


@SETTINGS
@given(values=INCREASING)
def test_times_file_round_trip(tmp_path, values):
    p = tmp_path / "times.txt"
    p.write_text("".join(f"{v:.17g}\n" for v in values))
    assert read_times(p, len(values)).tolist() == values
