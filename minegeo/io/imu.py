"""IMU samples: the IMU CSV (``minegeo slam --imu FILE``) and the lever-arm/rotation extrinsic.

The conventions are those of the SLAM contract ("Sensor streams"):

* Header ``t,gx,gy,gz,ax,ay,az`` (exactly these columns in this order; spaces around the commas and
  ``#`` comment lines are allowed).
* ``t``: seconds on the clock of the frame times; rows strictly increasing in time.
* ``gx gy gz``: angular rate, rad/s. ``ax ay az``: specific force, m/s^2, gravity included (a unit at
  rest reads about +9.81 on its up axis).
* Axes: those of the LiDAR frame, unless an extrinsic ``T_lidar_imu`` is given (``--imu-extrinsic``:
  a 4x4 matrix, or ``x y z qx qy qz qw``, inline or in a text file), which maps IMU-frame coordinates
  into the LiDAR frame: ``p_lidar = R p_imu + t``. The samples stay in the IMU frame (rotating a
  specific force measured away from the LiDAR origin into the LiDAR frame needs the angular
  acceleration too, so that is left to the estimator); :attr:`ImuSamples.frame` says which frame.

:func:`read_imu_csv` returns a frozen :class:`ImuSamples`; the bag reader
(:func:`minegeo.io.bag.read_bag_imu`) returns the same record from ``sensor_msgs/msg/Imu`` topics.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from minegeo.errors import FileFormatError, InputError
from minegeo.io._quat import normalize_quat, quat_to_matrix, quaternion_problem, rotation_problem
from minegeo.io.limits import MAX_TABLE_FILE_BYTES, read_file_text
from minegeo.io.text import data_line_locator, parse_table
from minegeo.io.trajectory import time_problem

__all__ = ["ImuSamples", "IMU_CSV_HEADER", "IMU_NOISE_KEYS", "read_imu_csv", "read_imu_noise", "write_imu_csv",
           "parse_extrinsic", "imu_samples"]

#: the noise figures of Kalibr's ``imu.yaml`` (continuous-time: rad/s/√Hz, rad/s²/√Hz, m/s²/√Hz, m/s³/√Hz)
IMU_NOISE_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                  "accelerometer_random_walk")
#: largest IMU noise file read (a Kalibr imu.yaml is a few hundred bytes)
MAX_IMU_NOISE_BYTES = 1 << 20

log = logging.getLogger(__name__)

#: The IMU CSV columns, in order.
IMU_CSV_HEADER = ("t", "gx", "gy", "gz", "ax", "ay", "az")
#: Largest IMU CSV read (a 400 Hz IMU for 2 h is ~ 200 MB of text: read it in parts, or as a bag).
MAX_IMU_CSV_BYTES = 4 * MAX_TABLE_FILE_BYTES


def _readonly(a) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class ImuSamples:
    """Timed IMU samples (arrays read-only).

    Attributes
    ----------
    t_s : (n,) float64
        Sample times, seconds on the frames' clock, strictly increasing.
    gyro_rad_s : (n, 3) float64
        Angular rate about the axes of ``frame``, rad/s.
    accel_m_s2 : (n, 3) float64
        Specific force along the axes of ``frame``, m/s^2, gravity included.
    frame : str
        The frame of the axes: ``"lidar"`` (the CSV default: IMU axes are the LiDAR's), ``"imu"``
        when an extrinsic is given, or a bag message's ``header.frame_id``.
    T_lidar_imu : (4, 4) float64 or None
        Maps IMU-frame coordinates into the LiDAR frame, when given.
    source : str
        The file (or ``bag!topic``) read.
    """

    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    frame: str = "lidar"
    T_lidar_imu: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        t = _readonly(self.t_s).reshape(-1)
        g = _readonly(self.gyro_rad_s)
        a = _readonly(self.accel_m_s2)
        n = t.shape[0]
        if g.shape != (n, 3) or a.shape != (n, 3):
            raise ValueError(f"gyro {g.shape} and accel {a.shape} must be ({n}, 3)")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "gyro_rad_s", g)
        object.__setattr__(self, "accel_m_s2", a)
        if self.T_lidar_imu is not None:
            T = _readonly(self.T_lidar_imu)
            if T.shape != (4, 4):
                raise ValueError(f"T_lidar_imu must be 4x4, got {T.shape}")
            object.__setattr__(self, "T_lidar_imu", T)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def rate_hz(self) -> float | None:
        """Median sample rate (Hz), None for fewer than two samples."""
        if len(self) < 2:
            return None
        return float(1.0 / np.median(np.diff(self.t_s)))


def imu_samples(t_s, gyro, accel, source, *, frame: str = "lidar", T_lidar_imu=None, labels=None,
                max_gap_s: float | None = None) -> ImuSamples:
    """Check timed samples and build :class:`ImuSamples`.

    Checks: at least one sample, every value finite, times valid and strictly increasing
    (:func:`minegeo.io.trajectory.time_problem`), and no gap longer than ``max_gap_s`` when given.
    ``labels[i]`` names sample ``i`` in a message (``"line 12"``, ``"message 3"``).

    Raises
    ------
    FileFormatError
        Naming ``source`` and the first offending sample.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    g = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(accel, dtype=np.float64).reshape(-1, 3)

    def lab(i: int) -> str:
        return labels[i] if labels is not None else f"sample {i}"

    if t.size == 0:
        raise FileFormatError(source, "holds no IMU samples")
    vals = np.column_stack([t, g, a])
    bad = ~np.isfinite(vals).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        cols = [IMU_CSV_HEADER[j] for j in np.flatnonzero(~np.isfinite(vals[i]))]
        raise FileFormatError(source, f"{lab(i)}: {', '.join(cols)} is NaN or infinite")
    prob = time_problem(t, noun="IMU sample")
    if prob is not None:
        raise FileFormatError(source, f"{lab(prob[0])}: {prob[1]}")
    if max_gap_s is not None and t.size > 1:
        gaps = np.diff(t)
        k = int(np.argmax(gaps))
        if gaps[k] > max_gap_s:
            raise FileFormatError(source, f"{lab(k + 1)}: {gaps[k]:.6g} s without IMU samples before it (from "
                                  f"{t[k]:.6f} s to {t[k + 1]:.6f} s), more than the {max_gap_s:g} s allowed")
    if t.size > 10:
        med = float(np.median(np.linalg.norm(a, axis=1)))
        if 0.5 < med < 2.0:
            log.warning("%s: the median specific force is %.3g m/s^2; at rest or in ordinary motion it is near "
                        "9.81 m/s^2: is the accelerometer in units of g? (the IMU CSV is in m/s^2)", source, med)
    return ImuSamples(t, g, a, frame, T_lidar_imu, str(source))


def _header_names(line: str) -> list[str]:
    return [tok.strip().lower() for tok in line.split(",")]


def read_imu_csv(path, *, extrinsic=None, max_gap_s: float | None = None) -> ImuSamples:
    """Read an IMU CSV (see the module docstring).

    Parameters
    ----------
    path : path
        The CSV file (read-only; a folder, FIFO or device is refused without being read).
    extrinsic : str, path, (4, 4) or (7,) array_like, optional
        ``T_lidar_imu`` (:func:`parse_extrinsic`); the samples are then in the ``"imu"`` frame.
    max_gap_s : float, optional
        Longest time allowed between consecutive samples (s); default: no limit.

    Returns
    -------
    ImuSamples

    Raises
    ------
    FileFormatError
        A header other than ``t,gx,gy,gz,ax,ay,az``, a row with another number of values or a value
        that is not a number, NaN or infinite values, times not strictly increasing, a gap above
        ``max_gap_s``, no rows: the line is named.
    InputError
        A malformed extrinsic.
    """
    p = Path(path)
    T = None if extrinsic is None else parse_extrinsic(extrinsic)
    text = read_file_text(p, encoding="utf-8-sig", max_bytes=MAX_IMU_CSV_BYTES, what="IMU CSV")
    lines = text.splitlines(keepends=True)
    hdr_line = None
    for k, ln in enumerate(lines):
        s = ln.strip()
        if s and not s.startswith("#"):
            hdr_line = k
            break
    expected = ",".join(IMU_CSV_HEADER)
    if hdr_line is None:
        raise FileFormatError(p, f"empty IMU CSV (expected the header {expected!r} and one row per sample)")
    names = _header_names(lines[hdr_line])
    if tuple(names) != IMU_CSV_HEADER:
        raise FileFormatError(p, f"line {hdr_line + 1}: IMU CSV header {lines[hdr_line].strip()[:80]!r}; expected "
                              f"{expected!r} (t in s, gyro in rad/s, specific force in m/s^2)")
    body = "".join(lines[hdr_line + 1:])
    first = hdr_line + 2
    table = parse_table(p, body, ncols=len(IMU_CSV_HEADER), first_line=first, delimiter=",", comments="#")
    if table.shape[0] == 0:
        raise FileFormatError(p, "IMU CSV has a header but no samples")
    locate = data_line_locator(body, first, comments="#")
    labels = _LazyLabels(locate, table.shape[0])
    return imu_samples(table[:, 0], table[:, 1:4], table[:, 4:7], p, frame="lidar" if T is None else "imu",
                       T_lidar_imu=T, labels=labels, max_gap_s=max_gap_s)


class _LazyLabels:
    """``labels[i] -> "line N"`` computed only when a message needs it (the error path)."""

    def __init__(self, locate, n: int):
        self._locate, self._n = locate, n

    def __getitem__(self, i: int) -> str:
        line = self._locate(int(i))
        return f"line {line}" if line is not None else f"row {i + 1}"


def write_imu_csv(path, imu: ImuSamples) -> Path:
    """Write ``imu`` as an IMU CSV (17 significant digits: reads back to the same float64)."""
    from minegeo._provenance import atomic_write_bytes
    from minegeo.io.text import format_table

    cols = [imu.t_s, *imu.gyro_rad_s.T, *imu.accel_m_s2.T]
    body = format_table(cols, ["%.17g"] * 7, delimiter=",")
    p = Path(path)
    atomic_write_bytes(p, (",".join(IMU_CSV_HEADER) + "\n" + body).encode("ascii"))
    return p


def parse_extrinsic(value) -> np.ndarray:
    """``T_lidar_imu`` (4x4 float64) from a matrix, seven numbers, or text / a text file holding them.

    Accepted: a (4, 4) or (3, 4) array; 16 or 12 numbers (row-major); 7 numbers ``x y z qx qy qz qw``
    (metres; a Hamilton unit quaternion, scalar last, renormalised when within 1e-2 of norm 1). A
    string that names an existing file is read from it (numbers separated by spaces, commas,
    brackets; ``#`` comments); otherwise the string itself is parsed.

    Raises
    ------
    InputError
        Another count of numbers, a value that is not a finite number, a rotation block that is not
        a proper rotation (tolerance 1e-4), a last row other than ``0 0 0 1``, or a quaternion far from
        unit norm.
    """
    where = "the IMU extrinsic T_lidar_imu"
    if isinstance(value, (str, Path)):
        s = str(value)
        fp = Path(s)
        if isinstance(value, Path) or (len(s) < 4096 and "\n" not in s and fp.is_file()):
            where = f"{fp}"
            s = read_file_text(fp, encoding="utf-8-sig", max_bytes=1 << 16, what="extrinsic file")
        s = " ".join(ln.split("#", 1)[0] for ln in s.splitlines())
        toks = s.replace(",", " ").replace("[", " ").replace("]", " ").replace(";", " ").split()
        try:
            vals = np.array([float(t) for t in toks], dtype=np.float64)
        except ValueError:
            raise InputError(f"{where}: expected numbers (a 4x4 matrix or x y z qx qy qz qw), got {s[:80]!r}") from None
    else:
        try:
            vals = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"{where}: expected a 4x4 matrix or x y z qx qy qz qw") from None
    if not np.isfinite(vals).all():
        raise InputError(f"{where}: holds NaN or infinite values")
    if vals.size == 7:
        prob = quaternion_problem(vals[3:7].reshape(1, 4))
        if prob is not None:
            raise InputError(f"{where}: quaternion qx qy qz qw: {prob[1]}")
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(normalize_quat(vals[3:7]))
        T[:3, 3] = vals[:3]
        return T
    if vals.size == 12:
        vals = np.concatenate([vals, [0.0, 0.0, 0.0, 1.0]])
    if vals.size != 16:
        raise InputError(f"{where}: {vals.size} numbers; expected 16 (4x4), 12 (3x4) or 7 (x y z qx qy qz qw)")
    T = vals.reshape(4, 4)
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{where}: the last row must be 0 0 0 1, got {T[3].tolist()}")
    prob = rotation_problem(T[:3, :3].reshape(1, 3, 3))
    if prob is not None:
        raise InputError(f"{where}: {prob[1]}")
    return T


def read_imu_noise(path) -> dict[str, float]:
    """The four noise figures of an IMU from a Kalibr ``imu.yaml``.

    The file holds ``key: value`` lines (Kalibr's format; ``#`` starts a comment; other keys such as
    ``rostopic`` and ``update_rate`` are ignored; a key may be indented under one IMU's name):

    ``gyroscope_noise_density`` σ_g (rad/s/√Hz), ``gyroscope_random_walk`` σ_bg (rad/s²/√Hz),
    ``accelerometer_noise_density`` σ_a (m/s²/√Hz), ``accelerometer_random_walk`` σ_ba (m/s³/√Hz),
    the continuous-time densities of Allan-variance analysis (Kalibr's IMU noise model wiki;
    Forster et al. 2017 Sec. IV).

    Returns
    -------
    dict
        ``{key: value}`` for the four :data:`IMU_NOISE_KEYS`, each within the rule of the
        :class:`~minegeo.optim.imu.ImuNoise` field of that name (finite and > 0).

    Raises
    ------
    FileFormatError
        A key missing or given twice (a file of several IMUs), a value its field's rule refuses
        (``"line 2: accelerometer_noise_density must be a finite number > 0, got '-1e-3'"``); the
        file and line are named.
    """
    from minegeo._params import check_field, field_rule, rule_text
    from minegeo.optim.imu import ImuNoise

    p = Path(path)
    text = read_file_text(p, encoding="utf-8-sig", max_bytes=MAX_IMU_NOISE_BYTES, what="IMU noise file")
    found: dict[str, tuple[float, int]] = {}
    for k, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        key, sep, value = line.partition(":")
        key = key.strip().strip("'\"")
        if not sep or key not in IMU_NOISE_KEYS:
            continue
        if key in found:
            raise FileFormatError(p, f"line {k}: {key} given again (line {found[key][1]}); give the noise of one IMU")
        try:
            v = float(value.strip().strip("'\""))
        except ValueError:
            v = float("nan")
        try:
            check_field(ImuNoise, key, v)  # the field's own rule (minegeo._params)
        except InputError:
            raise FileFormatError(p, f"line {k}: {key} must be {rule_text(field_rule(ImuNoise, key))}, "
                                     f"got {value.strip()[:40]!r}") from None
        found[key] = (v, k)
    missing = [key for key in IMU_NOISE_KEYS if key not in found]
    if missing:
        raise FileFormatError(p, f"IMU noise file (Kalibr imu.yaml) without {', '.join(missing)}")
    return {key: found[key][0] for key in IMU_NOISE_KEYS}
