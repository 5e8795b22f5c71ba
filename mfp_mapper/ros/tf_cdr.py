"""``/tf``, ``/tf_static`` and odometry read from their serialized bytes (raw
subscriptions).

rclpy turns each TFMessage into Python objects, six per transform, each with its checked
setters: under a flood of 10,000 frames a second (100 transforms a message) that was about
half of the executor's time (cProfile of a node under the flood: ``take_message`` 1.8 s,
the TF buffer's insert 1.5 s). An Odometry message is 13 Python objects and two 36-value
covariance arrays, of which the node reads the stamp, the two frames and the pose: taking it
cost ~0.1 ms, 50 times a second. Here the CDR bytes are read straight into
``TransformRecord`` values and ``OdometrySample``; a representation other than plain
little/big-endian CDR is left to rclpy's own deserialization. Checked against rclpy's
serializer in the tests.
"""

from __future__ import annotations

import struct

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from tf2_msgs.msg import TFMessage

from mfp_mapper.config.frames import frame_name
from mfp_mapper.sensing.poses import OdometrySample, odometry_sample
from mfp_mapper.sensing.tf_tree import TransformRecord, transform_records

_NS = 1e-9
_FORMATS = {
    endian: (
        struct.Struct(endian + "I"),
        struct.Struct(endian + "iI"),
        struct.Struct(endian + "7d"),
    )
    for endian in "<>"
}
_HEADER = 4
"""The encapsulation header (representation id, options); CDR alignment counts from after it."""


def tf_records(data: bytes) -> list[TransformRecord]:
    """The transforms of a serialized tf2_msgs/TFMessage; raises what rclpy raises on bytes
    that are not one."""
    if _plain(data):
        try:
            return _plain_cdr(data, "<" if data[1] == 1 else ">")
        except (struct.error, ValueError):
            pass  # rclpy says what is wrong with it
    return transform_records(deserialize_message(data, TFMessage))


def odometry_from_cdr(data: bytes) -> OdometrySample:
    """``poses.odometry_sample`` of a serialized nav_msgs/Odometry; raises what rclpy raises
    on bytes that are not one."""
    if _plain(data):
        try:
            record, _ = _stamped_pose(data, _HEADER, "<" if data[1] == 1 else ">")
        except (struct.error, ValueError):
            pass  # rclpy says what is wrong with it
        else:
            parent, child, stamp, *pose = record
            return OdometrySample(
                stamp,
                frame_name(parent),
                frame_name(child),
                np.array(pose[:3], dtype=np.float64),
                np.array(pose[3:], dtype=np.float64),
            )
    return odometry_sample(deserialize_message(data, Odometry))


def _plain(data: bytes) -> bool:
    """Plain CDR (big- or little-endian), the representation read here."""
    return len(data) >= _HEADER + 4 and data[0] == 0 and data[1] in (0, 1)


def _plain_cdr(data: bytes, endian: str) -> list[TransformRecord]:
    (count,) = _FORMATS[endian][0].unpack_from(data, _HEADER)
    pos = _HEADER + 4
    out: list[TransformRecord] = []
    for _ in range(count):
        record, pos = _stamped_pose(data, pos, endian)
        out.append(record)
    return out


def _stamped_pose(data: bytes, pos: int, endian: str) -> tuple[TransformRecord, int]:
    """A header, a child frame and seven doubles from ``pos`` (a TransformStamped, the start
    of an Odometry): the record and the position after it."""
    u32, time, values = _FORMATS[endian]
    end = len(data)
    pos += -(pos - _HEADER) % 4
    sec, nanosec = time.unpack_from(data, pos)
    parent, pos = _string(data, pos + 8, u32, end)
    pos += -(pos - _HEADER) % 4
    child, pos = _string(data, pos, u32, end)
    pos += -(pos - _HEADER) % 8
    x, y, z, qx, qy, qz, qw = values.unpack_from(data, pos)
    record = (parent, child, float(sec) + float(nanosec) * _NS, x, y, z, qx, qy, qz, qw)
    return record, pos + 56


def _string(data: bytes, pos: int, u32: struct.Struct, end: int) -> tuple[str, int]:
    """A CDR string at ``pos`` (aligned): its text and the position after it."""
    (length,) = u32.unpack_from(data, pos)
    pos += 4
    if pos + length > end:
        raise ValueError("string beyond the message")
    text = data[pos : pos + length].decode("utf-8")
    return text[:-1] if text.endswith("\0") else text, pos + length
