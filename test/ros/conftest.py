"""Fixtures of the ROS tests: one rclpy context per module in a private DDS domain."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from ros_helpers import domain_id, set_ros_env


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    """rclpy initialised on a DDS domain of this test run, kept on this host."""
    import rclpy

    domain = domain_id()
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    set_ros_env(domain)
    rclpy.init(domain_id=domain)
    try:
        yield domain
    finally:
        rclpy.try_shutdown()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
