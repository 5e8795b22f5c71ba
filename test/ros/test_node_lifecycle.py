"""The node as a lifecycle node and where octomap_server stood, over real DDS.

A lifecycle client (lifecycle_msgs ChangeState / GetState, what Nav2's lifecycle manager
calls) brings a node started with ``autostart:=false`` up and down, mapping in between;
run-time parameters and ``~/clear_bbox`` are used on the way. A second node starts from an
octomap_server parameter file under octomap_server's name and topic names.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_helpers import (
    Feeder,
    NodeProcess,
    clear_bbox,
    cloud_from_columns,
    read_cloud,
)
from test_node import NODE_PARAMS, T0, Sim

pytestmark = pytest.mark.ros

N_SCANS = 4


class Lifecycle:
    """A lifecycle client of one node: what Nav2's lifecycle manager uses."""

    def __init__(self, feeder: Feeder, node_name: str = "mfp_mapper") -> None:
        from lifecycle_msgs.srv import ChangeState, GetState

        self.feeder = feeder
        self.change = feeder.node.create_client(ChangeState, f"/{node_name}/change_state")
        self.get = feeder.node.create_client(GetState, f"/{node_name}/get_state")

    def state(self) -> str:
        """The node's state. GetState is asked again when it goes unanswered: right after
        discovery the server may not have matched this client's response reader yet (the
        first request's answer is then lost), and asking is idempotent."""
        from lifecycle_msgs.srv import GetState

        for _ in range(5):
            try:
                answer = self.feeder.call(self.get, GetState.Request(), timeout=5.0)
            except TimeoutError:
                continue
            return str(answer.current_state.label)
        raise TimeoutError("GetState went unanswered 5 times")

    def transition(self, transition_id: int) -> bool:
        from lifecycle_msgs.srv import ChangeState

        request = ChangeState.Request()
        request.transition.id = transition_id
        return bool(self.feeder.call(self.change, request, timeout=60.0).success)


def _services(feeder: Feeder, node_name: str = "mfp_mapper") -> set[str]:
    """The node's services as discovered so far (none before the node is discovered)."""
    try:
        found = feeder.node.get_service_names_and_types_by_node(node_name, "/")
    except RuntimeError:  # rclpy's NodeNameNonExistentError: not discovered yet
        return set()
    return {name for name, _ in found}


def _set_parameters(feeder: Feeder, node_name: str, values: dict[str, Any]) -> list[Any]:
    """SetParameters on the node (``ros2 param set``); the results, in order."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    client = feeder.node.create_client(SetParameters, f"/{node_name}/set_parameters")
    try:
        assert client.wait_for_service(10.0)
        request = SetParameters.Request()
        request.parameters = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        return list(feeder.call(client, request).results)
    finally:
        feeder.node.destroy_client(client)


def _query(feeder: Feeder, points: np.ndarray) -> dict[str, np.ndarray]:
    query = cloud_from_columns(
        {a: points[:, k].astype(np.float32) for k, a in enumerate("xyz")}, "odom", T0
    )
    feeder.results.clear()
    feeder.query_pub.publish(query)
    assert feeder.wait(lambda: bool(feeder.results), 10.0)
    return read_cloud(feeder.results[0])


def test_a_lifecycle_client_brings_the_node_up_and_down_mapping_in_between(
    ros_domain: int, tmp_path: Path
) -> None:
    from lifecycle_msgs.msg import Transition
    from nav_msgs.srv import GetMap

    map_path = tmp_path / "map.npz"
    params = {**NODE_PARAMS, "autostart": False, "map_path": str(map_path)}
    params["save_on_shutdown"] = True
    node = NodeProcess(ros_domain, params, tmp_path / "node.log")
    feeder = Feeder()
    try:
        life = Lifecycle(feeder)
        assert life.get.wait_for_service(30.0), node.log()
        assert life.state() == "unconfigured"
        assert "/mfp_mapper/save_map" not in _services(feeder)
        assert feeder.cloud_pub.get_subscription_count() == 0

        # configure: the map and its services, no inputs yet
        assert life.transition(Transition.TRANSITION_CONFIGURE), node.log()
        assert life.state() == "inactive"
        assert feeder.save.wait_for_service(10.0) and feeder.get_map.wait_for_service(10.0)
        assert feeder.call(feeder.get_map, GetMap.Request()).map.info.width == 0
        assert feeder.cloud_pub.get_subscription_count() == 0

        # activate: map
        assert life.transition(Transition.TRANSITION_ACTIVATE), node.log()
        assert life.state() == "active"
        assert feeder.wait_connected(20.0), node.log()
        sim = Sim(feeder)
        assert feeder.wait(lambda: feeder.status is not None, 10.0)
        for k in range(N_SCANS):
            sim.send_scan(T0 + 0.1 + 0.2 * k)
        status = feeder.wait_status(lambda s: s["clouds_integrated"] >= N_SCANS, 40.0)
        assert status["clouds_integrated"] == N_SCANS, node.log()[-3000:]

        # the height band and max_range change at run time, validated as at start
        ok = _set_parameters(
            feeder, "mfp_mapper", {"point_cloud_max_z": 50.0, "sensor_model.max_range": 4.0}
        )
        assert all(r.successful for r in ok), [r.reason for r in ok]
        bad = _set_parameters(feeder, "mfp_mapper", {"point_cloud_min_z": 60.0})
        assert not bad[0].successful and "point_cloud_min_z" in bad[0].reason
        truncated = status["rays_truncated"]
        sim.send_scan(T0 + 0.1 + 0.2 * N_SCANS)
        status = feeder.wait_status(lambda s: s["clouds_integrated"] >= N_SCANS + 1, 20.0)
        assert status["rays_truncated"] > truncated  # rays now end at 4 m

        # clear_bbox: the box's voxels become unknown
        probe = np.array([[4.9, 4.0, 1.0], [5.1, 4.0, 1.0], [8.0, -2.0, 1.7]])
        before = _query(feeder, probe)
        assert before["observed"][:2].any() and before["observed"][2]  # a face, free space
        lo, hi = np.array([4.0, 3.0, 0.5]), np.array([6.0, 5.0, 1.5])
        answer = clear_bbox(feeder, "mfp_mapper", hi, lo)  # corners in any order
        assert answer.success and answer.cleared > 0, answer.message
        after = _query(feeder, probe)
        assert not after["observed"][:2].any() and after["observed"][2]

        # deactivate: no inputs, the services still answer
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        assert life.state() == "inactive"
        assert feeder.wait(lambda: feeder.cloud_pub.get_subscription_count() == 0, 10.0)
        assert feeder.call(feeder.get_map, GetMap.Request()).map.info.width > 0

        # activate again: mapping resumes
        assert life.transition(Transition.TRANSITION_ACTIVATE)
        assert feeder.wait_connected(20.0)
        done = feeder.status["clouds_integrated"] if feeder.status else 0
        sim.send_scan(T0 + 0.3 + 0.2 * N_SCANS)
        status = feeder.wait_status(lambda s: s["clouds_integrated"] > done, 20.0)
        assert status["clouds_integrated"] > done, node.log()[-3000:]

        # deactivate + cleanup (what the lifecycle manager does on shutdown): saved
        assert life.transition(Transition.TRANSITION_DEACTIVATE)
        assert life.transition(Transition.TRANSITION_CLEANUP)
        assert life.state() == "unconfigured"
        assert map_path.is_file(), node.log()
        assert feeder.wait(lambda: "/mfp_mapper/save_map" not in _services(feeder), 10.0)

        # configure again: the saved map, cleared box included, is loaded
        assert life.transition(Transition.TRANSITION_CONFIGURE)
        assert feeder.get_map.wait_for_service(10.0)
        assert feeder.query_pub.get_subscription_count() > 0 or feeder.wait(
            lambda: feeder.query_pub.get_subscription_count() > 0, 10.0
        )
        reloaded = _query(feeder, probe)
        assert not reloaded["observed"][:2].any() and reloaded["observed"][2]
        saved = re.search(r"saved (\d+) voxels", node.log())
        assert saved is not None and f"loaded {saved.group(1)} voxels" in node.log()

        assert life.transition(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        assert life.state() == "finalized"
        assert node.alive()
    finally:
        feeder.destroy()
        code = node.stop()
    assert code == 0, node.log()[-3000:]
    assert "Traceback" not in node.log()


OCTOMAP_FILE = """\
octomap_server:
  ros__parameters:
    frame_id: odom
    base_frame_id: base_link
    resolution: 0.2
    sensor_model.max_range: 20.0
    sensor_model.hit: 0.7
    sensor_model.miss: 0.4
    sensor_model.min: 0.12
    sensor_model.max: 0.97
    point_cloud_min_z: -1.0
    point_cloud_max_z: 3.0
    point_cloud_min_x: -50.0
    point_cloud_max_x: 50.0
    occupancy_min_z: 0.25
    occupancy_max_z: 2.0
    filter_ground_plane: false
    filter_speckles: true
    latch: true
    incremental_2D_projection: false
    publish_free_space: false
"""


def test_an_octomap_server_parameter_file_starts_the_node_under_its_names(
    ros_domain: int, tmp_path: Path
) -> None:
    params_file = tmp_path / "octomap_server.yaml"
    params_file.write_text(OCTOMAP_FILE)
    extra = {"octomap_topics": True, "lidar.translation": [0.0, 0.0, 1.8], "status_period": 0.25}
    node = NodeProcess(
        ros_domain, extra, tmp_path / "octo.log", name="octomap_server", params_file=params_file
    )
    feeder = Feeder(node_name="octomap_server", feeder_name="feeder_octo")
    try:
        from nav_msgs.msg import OccupancyGrid
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        got: dict[str, Any] = {}
        feeder.node.create_subscription(
            OccupancyGrid, "/projected_map", lambda m: got.__setitem__("grid", m), latched
        )
        feeder.node.create_subscription(
            PointCloud2,
            "/octomap_point_cloud_centers",
            lambda m: got.__setitem__("centers", m),
            latched,
        )
        assert feeder.get_map.wait_for_service(30.0), node.log()
        assert feeder.wait(
            lambda: "/octomap_server/clear_bbox" in _services(feeder, "octomap_server"), 10.0
        )
        sim = Sim(feeder)
        assert feeder.wait(lambda: feeder.status is not None, 10.0), node.log()
        for k in range(3):
            sim.send_scan(T0 + 0.1 + 0.2 * k)
        assert feeder.wait(lambda: "grid" in got and "centers" in got, 20.0), node.log()
        assert got["grid"].header.frame_id == "odom" and got["grid"].info.resolution == (
            pytest.approx(0.2)
        )
        assert got["centers"].header.frame_id == "odom"
    finally:
        feeder.destroy()
        code = node.stop()
    log = node.log()
    assert code == 0, log[-3000:]
    warnings = [line for line in log.splitlines() if "octomap_server parameter(s)" in line]
    assert len(warnings) == 1, log[-3000:]
    for name in ("sensor_model.hit", "filter_ground_plane", "incremental_2D_projection"):
        assert name in warnings[0]
    assert "point_cloud_min_x" not in warnings[0]  # used, not ignored

    # a genuine typo still stops the node, naming it
    params_file.write_text(OCTOMAP_FILE + "    resolutoin: 0.1\n")
    typo = NodeProcess(
        ros_domain, {}, tmp_path / "typo.log", name="octomap_server", params_file=params_file
    )
    try:
        typo.proc.wait(60.0)
    finally:
        code = typo.stop()
    assert code == 2, typo.log()
    assert "resolutoin" in typo.log() and "Traceback" not in typo.log()


REFUSED_AT = {
    # state: transition ids the state machine does not allow there (99: callback error, an
    # internal transition; 0 create and 8 destroy are never sent by a manager)
    "active": (0, 1, 2, 3, 5, 6, 8, 99),
    "inactive": (0, 1, 4, 5, 7, 8, 99),
    "unconfigured": (0, 2, 3, 4, 6, 7, 8, 99),
    "finalized": (0, 1, 2, 3, 4, 5, 6, 7, 8, 99),
}


def test_a_transition_not_allowed_is_refused_at_every_state(
    ros_domain: int, tmp_path: Path
) -> None:
    """Nav2's lifecycle manager sends configure to an autostarted node: refused, with a
    warning, the node unharmed; the same for every id not allowed from each state (rclpy's
    own handler raised RCLError out of spin: a traceback and exit 1)."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    node = NodeProcess(ros_domain, dict(NODE_PARAMS), tmp_path / "node.log")  # autostart
    feeder = Feeder()
    try:
        life = Lifecycle(feeder)
        assert life.get.wait_for_service(30.0), node.log()
        path = (
            ("active", Transition.TRANSITION_DEACTIVATE),
            ("inactive", Transition.TRANSITION_CLEANUP),
            ("unconfigured", Transition.TRANSITION_UNCONFIGURED_SHUTDOWN),
            ("finalized", None),
        )
        for state, next_transition in path:
            assert life.state() == state, node.log()[-3000:]
            for refused in REFUSED_AT[state]:
                assert not life.transition(refused), (state, refused)
                assert node.alive(), node.log()[-3000:]
                assert life.state() == state, (state, refused)
            if state == "active":  # by label as well
                request = ChangeState.Request()
                request.transition.label = "configure"
                assert not feeder.call(life.change, request, timeout=30.0).success
            if next_transition is not None:
                assert life.transition(next_transition), node.log()[-3000:]
        log = node.log()
        assert "transition id 1 refused: not allowed from state 'active'" in log, log[-3000:]
        assert node.alive()
    finally:
        feeder.destroy()
        code = node.stop()
    assert code == 0, node.log()[-3000:]
    assert "Traceback" not in node.log() and "RCLError" not in node.log()


def test_a_stop_signal_while_configure_compiles_ends_the_node_at_once(
    ros_domain: int, tmp_path: Path
) -> None:
    """Configure compiles the kernels before the node takes clouds (tens of seconds with a
    cold numba cache): a SIGINT meanwhile ends the wait at once and the node exits 0,
    never subscribed to clouds, well inside launch's 5 s before SIGTERM."""
    import signal
    import time

    cold = {"NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")}
    node = NodeProcess(ros_domain, dict(NODE_PARAMS), tmp_path / "node.log", env=cold)
    try:
        deadline = time.monotonic() + 120.0
        while "compiling the kernels" not in node.log() and time.monotonic() < deadline:
            assert node.alive(), node.log()[-3000:]
            time.sleep(0.1)
        assert "compiling the kernels" in node.log(), node.log()[-3000:]
        node.proc.send_signal(signal.SIGINT)
        code = node.proc.wait(timeout=5.0)
    finally:
        node.stop()
    log = node.log()
    assert code == 0, log[-3000:]
    assert "not waiting for the kernels" in log and "kernels ready" not in log, log[-3000:]
