"""``ros.tf_cdr``: /tf and odometry read from their CDR bytes give what rclpy's own
deserialization gives, for names of every length (CDR alignment after each string), odd
stamps, non-finite values and an empty message; bytes that are not such a message raise as
rclpy does."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from tf2_msgs.msg import TFMessage

from mfp_mapper.ros.tf_cdr import odometry_from_cdr, tf_records
from mfp_mapper.sensing.poses import odometry_sample
from mfp_mapper.sensing.tf_tree import transform_records


def _message(rng: np.random.Generator, count: int) -> TFMessage:
    tfs = []
    for k in range(count):
        tf = TransformStamped()
        tf.header.frame_id = "p" * int(rng.integers(0, 9)) + ("/odom" if k % 3 else "ödom")
        tf.child_frame_id = "c" * int(rng.integers(0, 9)) + str(k)
        tf.header.stamp.sec = int(rng.integers(-5, 2**31 - 1))
        tf.header.stamp.nanosec = int(rng.integers(0, 10**9))
        v = rng.normal(size=7) * 10.0 ** rng.integers(-3, 6)
        if k == 2:
            v[0], v[4] = math.nan, math.inf
        t, q = tf.transform.translation, tf.transform.rotation
        t.x, t.y, t.z, q.x, q.y, q.z, q.w = (float(x) for x in v)
        tfs.append(tf)
    return TFMessage(transforms=tfs)


@pytest.mark.parametrize("count", [0, 1, 2, 7, 100])
def test_the_cdr_reading_equals_rclpys(count: int) -> None:
    rng = np.random.default_rng(count)
    for _ in range(5):
        msg = _message(rng, count)
        data = serialize_message(msg)
        expected = transform_records(deserialize_message(data, TFMessage))
        got = tf_records(data)
        assert len(got) == count
        for a, b in zip(got, expected, strict=True):
            assert a[:2] == b[:2]
            assert np.array_equal(np.array(a[2:]), np.array(b[2:]), equal_nan=True), (a, b)


def test_bytes_that_are_not_a_tf_message_raise() -> None:
    data = serialize_message(_message(np.random.default_rng(1), 3))
    with pytest.raises(Exception):  # noqa: B017 - rclpy's own error, whatever its type
        tf_records(data[:-20])


def _odometry(rng: np.random.Generator, k: int) -> Odometry:
    msg = Odometry()
    msg.header.frame_id = "o" * int(rng.integers(0, 9)) + ("/odom" if k % 2 else "ödom")
    msg.child_frame_id = "b" * int(rng.integers(0, 9)) + "base_link"
    msg.header.stamp.sec = int(rng.integers(-5, 2**31 - 1))
    msg.header.stamp.nanosec = int(rng.integers(0, 10**9))
    v = rng.normal(size=7) * 10.0 ** rng.integers(-3, 6)
    if k == 3:
        v[1], v[5] = math.nan, -math.inf
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(x) for x in v)
    msg.pose.covariance = rng.normal(size=36)
    msg.twist.twist.linear.x = float(rng.normal())
    return msg


def test_odometry_from_its_bytes_equals_rclpys() -> None:
    """Frame names of every length (the alignment after each), a leading slash stripped as
    ``odometry_sample`` strips it, odd stamps and non-finite values."""
    rng = np.random.default_rng(7)
    for k in range(40):
        data = serialize_message(_odometry(rng, k))
        expected = odometry_sample(deserialize_message(data, Odometry))
        got = odometry_from_cdr(data)
        assert (got.stamp, got.frame_id, got.child_frame_id) == (
            expected.stamp,
            expected.frame_id,
            expected.child_frame_id,
        )
        assert np.array_equal(got.position, expected.position, equal_nan=True)
        assert np.array_equal(got.quaternion, expected.quaternion, equal_nan=True)


def test_bytes_that_are_not_odometry_raise() -> None:
    data = serialize_message(_odometry(np.random.default_rng(2), 0))
    with pytest.raises(Exception):  # noqa: B017 - rclpy's own error, whatever its type
        odometry_from_cdr(data[:40])
