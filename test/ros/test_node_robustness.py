"""The node under faults, over real DDS on loopback, with the node spun in this process:
late joiners of latched outputs, callbacks that fail, a huge map asked for as a grid,
services while the map is held by a long integration, /diagnostics."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from ros_helpers import Feeder, odom_msg

pytestmark = pytest.mark.ros

T0 = 1_700_000_000.0


class Spun:
    """An MfpMapperNode spun by a SingleThreadedExecutor in a thread, as ``main`` does."""

    def __init__(self, name: str, **params: Any) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter

        from mfp_mapper.ros.node import MfpMapperNode

        self.node = MfpMapperNode(
            cli_args=["--ros-args", "-r", f"__node:={name}"],
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
        )
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.node.close()
        self.node.destroy_node()
        self.thread.join(timeout=5.0)


@pytest.fixture
def spun(ros_domain: int, request: pytest.FixtureRequest) -> Iterator[Spun]:
    name = "mfp_" + "".join(c for c in request.node.originalname if c.isalnum() or c == "_")[:40]
    node = Spun(name, **getattr(request, "param", {}))
    try:
        yield node
    finally:
        node.close()


def _fill(node: Any, points: np.ndarray, origins: Any = None) -> None:
    """Put rays into the node's map directly (what an integrated scan does)."""
    with node.worker.map_lock:
        node.mapper.integrate(points, np.zeros(3) if origins is None else origins, T0)


def _feeder(spun: Spun) -> Feeder:
    f = Feeder(node_name=spun.node.get_name(), feeder_name=f"feeder_{spun.node.get_name()}")
    assert f.wait(lambda: f.get_map.service_is_ready() and f.odom_pub.get_subscription_count())
    return f


@pytest.mark.parametrize("spun", [{"publish_rate": 20.0, "frame_id": "odom"}], indirect=True)
def test_late_joiners_of_every_latched_output_get_the_map(spun: Spun) -> None:
    """The grid goes out to an early subscriber; a late subscriber of the clouds still gets
    them (each output keeps its own published state), without any change of the map."""
    import rclpy
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2

    wall = np.stack([np.full(200, 4.05), np.linspace(-1, 1, 200), np.full(200, 0.5)], axis=1)
    _fill(spun.node, wall)
    early = rclpy.create_node("early_grid_listener")
    grids: list[Any] = []
    _latched_sub_node(early, OccupancyGrid, f"/{spun.node.get_name()}/projected_map", grids)
    try:
        deadline = time.monotonic() + 15.0
        while not grids and time.monotonic() < deadline:
            rclpy.spin_once(early, timeout_sec=0.05)
        assert grids, "the grid never went out"
        version = spun.node.mapper.version
        late = rclpy.create_node("late_cloud_listener")
        clouds: list[Any] = []
        for topic in ("degree_of_occupancy", "std"):
            _latched_sub_node(late, PointCloud2, f"/{spun.node.get_name()}/{topic}", clouds)
        deadline = time.monotonic() + 15.0
        while len(clouds) < 2 and time.monotonic() < deadline:
            rclpy.spin_once(late, timeout_sec=0.05)
        assert len(clouds) == 2 and all(c.width > 0 for c in clouds)
        assert spun.node.mapper.version == version  # nothing changed in between
        late.destroy_node()
    finally:
        early.destroy_node()


def _latched_sub_node(node: Any, msg_type: Any, topic: str, store: list[Any]) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    node.create_subscription(msg_type, topic, store.append, qos)


@pytest.mark.parametrize("spun", [{"publish_rate": 0.0, "frame_id": "odom"}], indirect=True)
def test_failing_callbacks_answer_and_the_node_keeps_spinning(
    spun: Spun, monkeypatch: pytest.MonkeyPatch
) -> None:
    from nav_msgs.srv import GetMap

    from mfp_mapper.sensing.pointcloud import pack_cloud

    f = _feeder(spun)
    try:

        def broken(*args: Any, **kwargs: Any) -> Any:
            raise RuntimeError("broken on purpose")

        monkeypatch.setattr(spun.node.mapper, "hit_probability_grid", broken)
        monkeypatch.setattr(spun.node.mapper, "query", broken)
        served = f.call(f.get_map, GetMap.Request()).map
        assert (served.info.width, served.info.height) == (0, 0)
        assert served.header.frame_id == "odom"
        from ros_helpers import stamp_msg

        from mfp_mapper.ros.messages import cloud_msg

        query = pack_cloud({"x": [1.0], "y": [0.0], "z": [0.0]})
        f.query_pub.publish(cloud_msg(query, "odom", stamp_msg(T0)))
        assert f.wait(lambda: len(f.results) == 1, 10.0), "a failing query is never answered"
        assert f.results[0].width == 0
        assert spun.thread.is_alive()
        f.odom_pub.publish(odom_msg(T0, np.zeros(3), 0.0))
        assert f.wait(lambda: spun.node.worker.counters.odom_in == 1, 10.0)
    finally:
        f.destroy()


@pytest.mark.parametrize(
    "spun",
    [{"publish_rate": 0.0, "frame_id": "odom", "hit_probability_map.max_cells": 40_000}],
    indirect=True,
)
def test_get_map_of_a_huge_map_is_bounded(spun: Spun) -> None:
    """Voxels 60 km apart: the grid would hold 3.6e11 cells at 0.1 m. Without a robot
    position the call answers an empty map; with one, the largest square around it."""
    from nav_msgs.srv import GetMap

    far = np.array([[1.0, 0.05, 0.55], [60_000.0, 60_000.05, 0.55]])
    _fill(spun.node, far, far - [1.0, 0.0, 0.0])  # 1 m rays at both ends
    f = _feeder(spun)
    try:
        served = f.call(f.get_map, GetMap.Request()).map
        assert (served.info.width, served.info.height) == (0, 0)
        f.odom_pub.publish(odom_msg(T0, np.array([1.0, 0.0, 0.0]), 0.0))
        assert f.wait(lambda: spun.node.worker.robot_position is not None, 10.0)
        served = f.call(f.get_map, GetMap.Request()).map
        cells = served.info.width * served.info.height
        assert 0 < cells <= 40_000
        data = np.array(served.data, dtype=np.int8).reshape(served.info.height, -1)
        col = int((0.55 - served.info.origin.position.x) / served.info.resolution)
        row = int((0.05 - served.info.origin.position.y) / served.info.resolution)
        assert data[row, col] >= 0  # the voxel near the robot is in the window
        assert spun.thread.is_alive()
    finally:
        f.destroy()


@pytest.mark.parametrize("spun", [{"publish_rate": 0.0, "frame_id": "odom"}], indirect=True)
def test_services_and_odometry_while_the_map_is_held(spun: Spun) -> None:
    """A long integration holds the map lock (here: held by the test for 3 s). Odometry is
    still taken and the GetMap call, pending meanwhile, answers once the map is free."""
    from nav_msgs.srv import GetMap

    _fill(spun.node, np.array([[3.0, 0.0, 0.5]]))
    f = _feeder(spun)
    try:
        lock = spun.node.worker.map_lock
        lock.acquire()
        held_since = time.monotonic()
        try:
            pending = f.get_map.call_async(GetMap.Request())
            for k in range(20):
                f.odom_pub.publish(odom_msg(T0 + 0.05 * k, np.zeros(3), 0.0))
            assert f.wait(lambda: spun.node.worker.counters.odom_in == 20, 10.0), (
                f"odometry taken while the map was held: {spun.node.worker.counters.odom_in}"
            )
            assert not pending.done()
            f.wait(lambda: time.monotonic() - held_since > 3.0, 5.0)
        finally:
            lock.release()
        assert f.wait(pending.done, 10.0)
        assert pending.result().map.info.width > 0
    finally:
        f.destroy()


@pytest.mark.parametrize(
    "spun", [{"publish_rate": 0.0, "frame_id": "odom", "status_period": 0.3}], indirect=True
)
def test_diagnostics_report_the_mapping_health(spun: Spun) -> None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    listener = rclpy.create_node("diag_listener")
    got: list[Any] = []
    listener.create_subscription(DiagnosticArray, "/diagnostics", got.append, 10)
    try:
        deadline = time.monotonic() + 10.0
        mine = []
        while not mine and time.monotonic() < deadline:
            rclpy.spin_once(listener, timeout_sec=0.05)
            mine = [s for m in got for s in m.status if spun.node.get_name() in s.name]
        assert mine, "no /diagnostics entry of the node"
        entry = mine[-1]
        assert entry.level == DiagnosticStatus.WARN and "no cloud received" in entry.message
        keys = {kv.key for kv in entry.values}
        assert {"clouds_in", "clouds_integrated", "voxels"} <= keys
    finally:
        listener.destroy_node()


@pytest.mark.skip(
    reason="cannot be done with best-effort DDS: a reader learns of a lost sample only from "
    "the sequence number of a later one (Fast DDS message-lost events, docs/robot.md, 'The "
    "DDS profile for large clouds'), so clouds_lost counts a loss when the next cloud arrives, "
    "never earlier"
)
def test_clouds_lost_counted_when_the_loss_happens() -> None:
    """Issue 9 asks for clouds_lost at the moment of the loss; see the skip reason."""


def test_status_says_when_integration_falls_behind() -> None:
    """Clouds the worker skipped for being behind (queue_full) since the last report make
    ``behind`` true and the health a warning that says so."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from mfp_mapper.mapping.live import LiveCounters
    from mfp_mapper.ros.map_outputs import PublishCounters
    from mfp_mapper.ros.status import health, next_window, status_report

    c = LiveCounters(clouds_in=10, clouds_integrated=8)
    c.drop("gap")
    c.drop("queue_full")
    window = next_window(c)
    c.clouds_in, c.clouds_integrated = 30, 14
    for _ in range(12):
        c.drop("queue_full")
    c.drop("gap")
    status = status_report(c, 5, (0, 0, 0), PublishCounters(), window, {})
    assert status["behind"] is True
    level, text = health(status, window)
    assert level == DiagnosticStatus.WARN
    assert "behind" in text and "6 of 20 clouds integrated, 12 skipped" in text, text
    assert "1 dropped otherwise" in text, text
    assert status_report(c, 0, (0, 0, 0), PublishCounters(), next_window(c), {})["behind"] is False
