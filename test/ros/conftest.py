"""Fixtures of the ROS tests: one rclpy context per module in a private DDS domain."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from ros_helpers import domain_id, ros_context


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    """rclpy initialised on a DDS domain of this test run, kept on this host."""
    with ros_context(domain_id()) as domain:
        yield domain
