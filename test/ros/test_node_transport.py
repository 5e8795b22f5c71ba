"""Transport losses over real DDS: told apart from the node's backlog, one line naming the profile.

Both processes run with Fast DDS's defaults (no large-data profile): 3 MB clouds published
back to back overflow the 208 KiB UDP socket buffer, and the node learns of the lost ones
from the next cloud's sequence number (the middleware's sample-lost event).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from ros_helpers import Feeder, NodeProcess, cloud_from_columns, domain_id, ros_context

from mfp_mapper.ros.transport import PROFILE_ENV

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    """A DDS domain of this test run, Fast DDS defaults in this process and its nodes."""
    with ros_context(domain_id(), {PROFILE_ENV: None}) as domain:
        yield domain


def test_clouds_lost_in_transport_are_counted_and_explained_once(
    ros_domain: int, tmp_path: Path
) -> None:
    params = {"status_period": 0.25, "publish_rate": 0.0, "cloud_queue_size": 1000}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    feeder = Feeder()
    try:
        assert feeder.wait_connected(30.0), node.log()
        assert feeder.wait(lambda: feeder.status is not None, 10.0)
        rng = np.random.default_rng(0)
        xyz = rng.uniform(-20.0, 20.0, (250_000, 3)).astype(np.float32)  # 3 MB
        big = cloud_from_columns({a: xyz[:, k] for k, a in enumerate("xyz")}, "lidar", 1.0)
        for _ in range(30):
            feeder.cloud_pub.publish(big)
            feeder.spin(0.0)
        small = cloud_from_columns({a: xyz[:10, k] for k, a in enumerate("xyz")}, "lidar", 2.0)
        for _ in range(5):  # a loss is seen when a later cloud arrives
            feeder.wait(lambda: False, 0.5)
            feeder.cloud_pub.publish(small)
        status = feeder.wait_status(lambda s: s["clouds_in"] + s["clouds_lost_transport"] >= 31)
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0, log[-3000:]
    lost = status["clouds_lost_transport"]
    if lost == 0:
        pytest.skip("no cloud was lost in transport on this run (nothing to tell apart)")
    # the node's own backlog is not what lost them: its queue had room for every cloud
    assert status["clouds_dropped"].get("queue_full", 0) == 0
    explained = [line for line in log.splitlines() if "lost in transport before" in line]
    assert "fastdds_large_data.xml" in explained[0] and "queue_full" in explained[0]
    assert sum("large-data profile" in line for line in explained) == 1, log[-3000:]
