"""PointCloud2 byte decoding (minegeo.io.bag.decode_pointcloud2) against a naive twin.

The twin reads every point with ``struct.unpack_from`` at ``row * row_step + col * point_step +
offset`` (the layout of sensor_msgs/msg/PointCloud2), one value at a time; hypothesis draws the
layout: field order and padding, datatypes, byte order, height, row padding, NaN points. No
rosbags needed (the message is a plain object with the message's attributes).
"""

from __future__ import annotations

import math
import struct
from types import SimpleNamespace

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from minegeo.io.bag import decode_pointcloud2

_STRUCT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
_SIZE = {k: struct.calcsize(v) for k, v in _STRUCT.items()}


def naive_decode(msg):
    """Twin: per point, per field ``struct.unpack_from``; finite xyz kept; offsets per the contract."""
    end = ">" if msg.is_bigendian else "<"
    f = {fd.name: fd for fd in msg.fields}
    tname = next((n for n in ("time", "t", "timestamp", "offset_time") if n in f), None)
    xyz, ts = [], []
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            p = [struct.unpack_from(end + _STRUCT[f[n].datatype], msg.data, base + f[n].offset)[0] for n in "xyz"]
            if not all(math.isfinite(v) for v in p):
                continue
            xyz.append(p)
            if tname:
                v = struct.unpack_from(end + _STRUCT[f[tname].datatype], msg.data, base + f[tname].offset)[0]
                ts.append(v if f[tname].datatype in (7, 8) else v / 1e9)
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), (np.array(ts) if tname else None), tname


@st.composite
def clouds(draw):
    coord_t = draw(st.sampled_from([7, 8, 5, 3]))  # float32, float64, int32, int16 coordinates
    time_name = draw(st.sampled_from([None, "time", "t", "timestamp", "offset_time"]))
    time_t = draw(st.sampled_from([7, 8, 6, 4, 2]))
    names = ["x", "y", "z"] + ([time_name] if time_name else []) + ["intensity"]
    order = draw(st.permutations(names))
    fields, off = [], 0
    for n in order:
        dt = coord_t if n in "xyz" else (time_t if n == time_name else 7)
        off += draw(st.integers(0, 3))  # padding between fields
        fields.append(SimpleNamespace(name=n, offset=off, datatype=dt, count=1))
        off += _SIZE[dt]
    point_step = off + draw(st.integers(0, 5))
    height = draw(st.integers(1, 3))
    width = draw(st.integers(0, 6))
    row_pad = draw(st.integers(0, 7))
    big = draw(st.booleans())
    seed = draw(st.integers(0, 2**31 - 1))
    nan_share = draw(st.sampled_from([0.0, 0.3]))
    return fields, point_step, height, width, row_pad, big, seed, nan_share, coord_t, time_name


def _build(fields, point_step, height, width, row_pad, big, seed, nan_share, coord_t, time_name):
    rng = np.random.default_rng(seed)
    end = ">" if big else "<"
    row_step = width * point_step + row_pad
    buf = bytearray(rng.integers(0, 256, height * row_step, dtype=np.uint8).tobytes())  # garbage in the gaps
    for r in range(height):
        for c in range(width):
            base = r * row_step + c * point_step
            bad = rng.random() < nan_share and coord_t in (7, 8)
            for fd in fields:
                fmt = end + _STRUCT[fd.datatype]
                if fd.name in "xyz":
                    v = float("nan") if bad and fd.name == "y" else (
                        float(rng.uniform(-50, 50)) if fd.datatype in (7, 8) else int(rng.integers(-100, 100)))
                elif fd.name == time_name:
                    v = float(rng.uniform(0.0, 0.1)) if fd.datatype in (7, 8) else int(
                        rng.integers(0, min(100_000_000, 2 ** (8 * _SIZE[fd.datatype]) - 1)))
                else:
                    v = float(rng.uniform(0, 1))
                struct.pack_into(fmt, buf, base + fd.offset, v)
    return SimpleNamespace(fields=fields, height=height, width=width, point_step=point_step, row_step=row_step,
                           is_bigendian=big, is_dense=nan_share == 0.0, data=np.frombuffer(bytes(buf), np.uint8))


@settings(max_examples=150, deadline=None)
@given(clouds())
def test_decode_matches_naive_twin(spec):
    msg = _build(*spec)
    assume(msg.point_step > 0)
    xyz, t_off, tf, enc, dropped = decode_pointcloud2(msg, "bag", "test message")
    ref_xyz, ref_t, ref_tf = naive_decode(msg)
    np.testing.assert_array_equal(xyz, ref_xyz)
    assert dropped == msg.height * msg.width - ref_xyz.shape[0]
    assert tf == ref_tf
    if ref_t is None:
        assert t_off is None
    else:
        np.testing.assert_array_equal(t_off, ref_t)
        assert enc == ("seconds" if next(f for f in msg.fields if f.name == tf).datatype in (7, 8) else "nanoseconds")
