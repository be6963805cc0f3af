"""The ``--imu`` options shared by ``minegeo slam`` and ``minegeo track``: their arguments, the IMU
read and checked before any work, and its coverage of the frames (docs/slam.md, "LiDAR-inertial SLAM").

* :func:`add_imu_arguments`: ``--imu IMU.csv``, ``--imu-extrinsic T``, ``--imu-max-gap S``,
  ``--imu-noise imu.yaml``.
* :func:`read_imu`: the samples (:class:`minegeo.io.imu.ImuSamples`) of an IMU CSV or a ROS bag's
  ``sensor_msgs/Imu`` topic, or None without ``--imu`` (``--imu-extrinsic``/``--imu-max-gap`` without
  ``--imu`` are refused).
* :func:`inertial_params`: the LiDAR-inertial parameters of the options (the IMU's noise from
  ``--imu-noise``, Kalibr's ``imu.yaml``; :func:`minegeo.io.imu.read_imu_noise`), or None.
* :func:`check_imu`: the samples cover the frames' time span without a gap over ``--imu-max-gap``
  (:func:`minegeo.slam.inertial.check_imu_for_frames`).

Every failure is an :class:`~minegeo.errors.InputError` (one line, exit 2).
"""

from __future__ import annotations

from pathlib import Path

from minegeo._params import arg_type

__all__ = ["add_imu_arguments", "read_imu", "inertial_params", "check_imu"]

#: the parameter class whose field rule ``--imu-max-gap`` uses (imported when the option is parsed)
_INERTIAL = "minegeo.slam.inertial:InertialParams"


def add_imu_arguments(parser, uses: str) -> None:
    """The IMU argument group; ``uses`` says what the verb does with the IMU (the ``--imu`` help's end)."""
    i = parser.add_argument_group("IMU (docs/slam.md, 'LiDAR-inertial SLAM')")
    i.add_argument("--imu", default=None, metavar="IMU.csv",
                   help="IMU CSV t,gx,gy,gz,ax,ay,az (s on the frames' clock, rad/s, m/s^2 specific force with "
                   f"gravity, LiDAR axes unless --imu-extrinsic): {uses}")
    i.add_argument("--imu-extrinsic", default=None, metavar="T",
                   help="T_lidar_imu: 16 numbers (4x4, row-major) or 'x y z qx qy qz qw', inline or in a file")
    i.add_argument("--imu-max-gap", type=arg_type(_INERTIAL, "max_gap_s"), default=None, metavar="S",
                   help="longest time without an IMU sample within the frames' span (s, default 0.05)")
    i.add_argument("--imu-noise", default=None, metavar="imu.yaml",
                   help="the IMU's noise as Kalibr's imu.yaml gives it (gyroscope_noise_density rad/s/sqrt(Hz), "
                        "gyroscope_random_walk, accelerometer_noise_density, accelerometer_random_walk); default: "
                        "an ADIS16448-class MEMS IMU (minegeo.optim.imu.ImuNoise)")


def read_imu(args):
    """The ``--imu`` samples (:class:`minegeo.io.imu.ImuSamples`), or None without ``--imu``; read and
    checked before any work (rows in time order, finite; the extrinsic). A ROS bag's IMU topic gives
    the same record (:func:`minegeo.io.bag.read_bag_imu`). The span and gaps against the frames:
    :func:`check_imu`."""
    from dataclasses import replace

    from minegeo.errors import InputError

    if getattr(args, "imu", None) is None:
        for opt, name in (("imu_extrinsic", "--imu-extrinsic"), ("imu_max_gap", "--imu-max-gap"),
                          ("imu_noise", "--imu-noise")):
            if getattr(args, opt, None) is not None:
                raise InputError(f"{name} needs --imu IMU.csv (the IMU it applies to)")
        return None
    from minegeo.io.bag import bag_kind, read_bag_imu
    from minegeo.io.imu import parse_extrinsic, read_imu_csv

    if Path(args.imu).is_dir() and bag_kind(args.imu) is None:
        raise InputError(f"--imu {args.imu} is a folder: name the IMU CSV (t,gx,gy,gz,ax,ay,az) or a ROS bag")
    if bag_kind(args.imu) is None:
        return read_imu_csv(args.imu, extrinsic=args.imu_extrinsic)
    imu = read_bag_imu(args.imu, getattr(args, "imu_topic", None))
    if args.imu_extrinsic is None:
        return imu
    return replace(imu, T_lidar_imu=parse_extrinsic(args.imu_extrinsic), frame="imu")


def inertial_params(args):
    """:class:`~minegeo.slam.inertial.InertialParams` of the options (``--imu-noise``, ``--imu-max-gap``),
    or None without ``--imu`` (read before any work: a bad noise file is one line, exit 2)."""
    if getattr(args, "imu", None) is None:
        return None
    from dataclasses import replace

    from minegeo.io.imu import read_imu_noise
    from minegeo.optim.imu import ImuNoise
    from minegeo.slam.inertial import InertialParams

    p = InertialParams()
    if getattr(args, "imu_noise", None) is not None:
        p = replace(p, noise=ImuNoise(**read_imu_noise(args.imu_noise)))
    if getattr(args, "imu_max_gap", None) is not None:
        p = replace(p, max_gap_s=float(args.imu_max_gap))
    return p


def check_imu(imu, files, args) -> None:
    """The IMU covers the frames' time span without a gap over ``--imu-max-gap`` (exit 2 otherwise)."""
    from minegeo.slam.inertial import InertialParams, check_imu_for_frames

    if imu is not None and files:
        gap = args.imu_max_gap if args.imu_max_gap is not None else InertialParams().max_gap_s
        check_imu_for_frames(imu, files[0].time_s, files[-1].time_s, gap, f"--imu {args.imu}")

