"""``/tf`` and ``/tf_static`` read from their serialized bytes (a raw subscription).

rclpy turns each TFMessage into Python objects, six per transform, each with its checked
setters: under a flood of 10,000 frames a second (100 transforms a message) that was about
half of the executor's time (cProfile of a node under the flood: ``take_message`` 1.8 s,
the TF buffer's insert 1.5 s). Here the CDR bytes are read straight into
``TransformRecord`` values; a representation other than plain little/big-endian CDR is left
to rclpy's own deserialization. Checked against rclpy's serializer in the tests.
"""

from __future__ import annotations

import struct

from rclpy.serialization import deserialize_message
from tf2_msgs.msg import TFMessage

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
    if len(data) >= _HEADER + 4 and data[0] == 0 and data[1] in (0, 1):
        try:
            return _plain_cdr(data, "<" if data[1] == 1 else ">")
        except (struct.error, ValueError):
            pass  # rclpy says what is wrong with it
    return transform_records(deserialize_message(data, TFMessage))


def _plain_cdr(data: bytes, endian: str) -> list[TransformRecord]:
    u32, time, values = _FORMATS[endian]
    (count,) = u32.unpack_from(data, _HEADER)
    pos, end = _HEADER + 4, len(data)
    out: list[TransformRecord] = []
    for _ in range(count):
        pos += -(pos - _HEADER) % 4
        sec, nanosec = time.unpack_from(data, pos)
        parent, pos = _string(data, pos + 8, u32, end)
        pos += -(pos - _HEADER) % 4
        child, pos = _string(data, pos, u32, end)
        pos += -(pos - _HEADER) % 8
        x, y, z, qx, qy, qz, qw = values.unpack_from(data, pos)
        pos += 56
        out.append((parent, child, float(sec) + float(nanosec) * _NS, x, y, z, qx, qy, qz, qw))
    return out


def _string(data: bytes, pos: int, u32: struct.Struct, end: int) -> tuple[str, int]:
    """A CDR string at ``pos`` (aligned): its text and the position after it."""
    (length,) = u32.unpack_from(data, pos)
    pos += 4
    if pos + length > end:
        raise ValueError("string beyond the message")
    text = data[pos : pos + length].decode("utf-8")
    return text[:-1] if text.endswith("\0") else text, pos + length
