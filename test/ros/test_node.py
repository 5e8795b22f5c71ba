"""The ROS 2 node end to end: real rclpy, real DDS on loopback, the node in its own process.

A feeder (this process) drives a simulated robot through ``synthetic.BoxWorld``: odometry of
the base and de-skewable lidar sweeps (Velodyne and Ouster layouts) in the lidar frame,
1.8 m above the base. The tests then read what the node publishes and serves.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from box_world import BoxWorld
from ros_helpers import (
    Feeder,
    NodeProcess,
    Trajectory,
    cloud_from_columns,
    domain_id,
    odom_msg,
    read_cloud,
    simulate_scan,
)

from mfp_mapper.config.schema import SPECS
from mfp_mapper.sources.scan_pattern import scan_directions

pytestmark = pytest.mark.ros

T0 = 1000.0  # simulated clock (s); the node only compares stamps with each other
LIDAR_HEIGHT = 1.8
RES = 0.2
AZIMUTHS = 360
N_SCANS = 8
ODOM_DT = 0.05
NODE_PARAMS: dict[str, Any] = {
    "resolution": RES,
    "sensor_model.max_range": 20.0,
    "cloud_queue_size": 10,
    "publish_rate": 5.0,
    "status_period": 0.25,
    "lidar.translation": [0.0, 0.0, LIDAR_HEIGHT],
    "odom_wait": 0.5,
    "odom_buffer": 2.0,
    "odom_max_gap": 0.3,
    "occupancy_min_z": 0.25,
    "occupancy_max_z": 2.0,
    "min_degree_of_occupancy": 0.1,
}


class Sim:
    """The simulated robot and what has been sent to the node so far."""

    def __init__(self, feeder: Feeder) -> None:
        self.feeder = feeder
        self.world = BoxWorld()
        self.dirs = scan_directions(azimuths=AZIMUTHS)
        self.traj = Trajectory(T0)
        self.odom_until = T0 - ODOM_DT
        self.layout = 0

    def odom_to(self, t_end: float, start: float | None = None) -> None:
        """Publish odometry every ODOM_DT up to ``t_end`` (from ``start`` to make a gap)."""
        t = self.odom_until + ODOM_DT if start is None else start
        while t <= t_end + 1e-9:
            pos = self.traj.position(t)
            self.feeder.odom_pub.publish(odom_msg(t, pos, float(self.traj.yaw(t))))
            self.odom_until = t
            t += ODOM_DT

    def scan_msg(self, start: float) -> Any:
        """A 0.1 s sweep from ``start``, alternately in Velodyne and Ouster layouts."""
        xyz, offsets = simulate_scan(
            self.world, self.dirs, AZIMUTHS, self.traj, start, LIDAR_HEIGHT
        )
        n = len(xyz)
        cols: dict[str, np.ndarray] = {a: xyz[:, k].astype(np.float32) for k, a in enumerate("xyz")}
        cols["intensity"] = np.full(n, 10.0, np.float32)
        if self.layout % 2 == 0:  # Velodyne: ring uint16, time float32 seconds
            cols["ring"] = (np.arange(n) // AZIMUTHS).astype(np.uint16)
            cols["time"] = offsets.astype(np.float32)
        else:  # Ouster: t uint32 nanoseconds, then reflectivity, ring, ambient, range
            cols["t"] = np.round(offsets * 1e9).astype(np.uint32)
            cols["reflectivity"] = np.zeros(n, np.uint16)
            cols["ring"] = (np.arange(n) // AZIMUTHS).astype(np.uint8)
            cols["ambient"] = np.zeros(n, np.uint16)
            cols["range"] = np.round(np.linalg.norm(xyz, axis=1) * 1000).astype(np.uint32)
        self.layout += 1
        return cloud_from_columns(cols, "lidar", start)

    def odom_until_counted(self, timeout: float) -> bool:
        """Publish odometry a step at a time until the node's status counts some: odometry is
        best effort, so what is sent before the node's reader has matched our writer is lost
        (a cloud from before the first pose the node holds is then dropped ``too_old``)."""
        for _ in range(max(1, round(timeout / ODOM_DT))):
            self.odom_to(self.odom_until + ODOM_DT)
            if self.feeder.wait(
                lambda: self.feeder.status is not None and self.feeder.status["odom_in"] > 0,
                ODOM_DT,
            ):
                return True
        return False

    def send_scan(self, start: float, odom_after: float = 0.15) -> None:
        self.odom_to(start + 0.1 + odom_after)
        self.send_cloud(self.scan_msg(start))

    def send_cloud(self, msg: Any) -> None:
        """Publish until the node counts it: its cloud_in is best effort (sensor data QoS)."""
        for _ in range(3):
            seen = self.status()["clouds_in"] if self.feeder.status else 0
            self.feeder.cloud_pub.publish(msg)
            if self.feeder.wait(
                lambda seen=seen: (
                    self.feeder.status is not None and self.status()["clouds_in"] > seen
                ),
                3.0,
            ):
                return
        raise AssertionError("the node never received a cloud")

    def status(self) -> dict[str, Any]:
        assert self.feeder.status is not None
        return self.feeder.status


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("node")


@pytest.fixture(scope="module")
def node(ros_domain: int, workdir: Path) -> Iterator[NodeProcess]:
    params = {**NODE_PARAMS, "map_path": str(workdir / "map.npz")}
    proc = NodeProcess(ros_domain, params, workdir / "node.log")
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope="module")
def feeder(node: NodeProcess) -> Iterator[Feeder]:
    f = Feeder()
    try:
        assert f.wait_connected(30.0), f"node not discovered:\n{node.log()[-3000:]}"
        yield f
    finally:
        f.destroy()


@pytest.fixture(scope="module")
def sim(feeder: Feeder, node: NodeProcess) -> Sim:
    """The robot has driven N_SCANS sweeps through the box world; all are integrated."""
    s = Sim(feeder)
    assert feeder.wait(lambda: feeder.status is not None, 10.0)
    for k in range(N_SCANS):
        s.send_scan(T0 + 0.1 + 0.2 * k)
    status = feeder.wait_status(lambda st: st["clouds_integrated"] >= N_SCANS, 40.0)
    assert status is not None and status["clouds_integrated"] == N_SCANS, (
        f"status {status}\n{node.log()[-3000:]}"
    )
    return s


def test_parameters_declared_with_descriptions_and_ranges(feeder: Feeder) -> None:
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, SetParameters

    describe = feeder.node.create_client(DescribeParameters, f"{feeder.ns}/describe_parameters")
    assert describe.wait_for_service(10.0)
    names = list(SPECS)
    resp = feeder.call(describe, DescribeParameters.Request(names=names))
    assert [d.name for d in resp.descriptors] == names
    for spec, desc in zip(SPECS.values(), resp.descriptors, strict=True):
        assert desc.description, spec.name
        if spec.lo is not None and not isinstance(spec.default, bool):
            ranges = desc.integer_range or desc.floating_point_range
            assert len(ranges) == 1, spec.name
            assert (ranges[0].from_value, ranges[0].to_value) == (spec.lo, spec.hi)
        assert desc.read_only == (not spec.dynamic), spec.name
    for name in ("sensor_model.max_range", "frame_id", "latch", "decay_time", "publish_rate"):
        assert name in names

    setp = feeder.node.create_client(SetParameters, f"{feeder.ns}/set_parameters")
    assert setp.wait_for_service(10.0)

    def set_double(name: str, value: float) -> bool:
        p = Parameter(
            name=name,
            value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value),
        )
        return bool(feeder.call(setp, SetParameters.Request(parameters=[p])).results[0].successful)

    assert not set_double("resolution", 0.5)  # read-only
    assert not set_double("min_degree_of_occupancy", 1.5)  # out of range
    assert not set_double("occupancy_min_z", 5.0)  # above occupancy_max_z
    assert set_double("min_degree_of_occupancy", 0.1)  # dynamic


def test_map_clouds_published_in_the_odometry_frame(sim: Sim, feeder: Feeder) -> None:
    # the first latched clouds may predate the scans (an emptier map): wait for the full one
    assert feeder.wait(
        lambda: all(m is not None and m.width > 100 for m in (feeder.doo, feeder.std)), 20.0
    )
    status = sim.status()
    assert status["map_frame"] == "odom"
    assert status["rays_no_return"] == 0  # sensor_model.no_return_range is off by default
    assert status["rays_cut_by_budget"] == 0  # every ray walked whole
    for msg, name in ((feeder.doo, "degree_of_occupancy"), (feeder.std, "std")):
        assert msg.header.frame_id == "odom"
        assert [f.name for f in msg.fields] == ["x", "y", "z", name]
        assert all(f.datatype == 7 and f.count == 1 for f in msg.fields)
        assert msg.height == 1 and msg.width > 100
        assert msg.point_step == 16 and len(msg.data) == msg.width * 16
    doo = read_cloud(feeder.doo)
    std = read_cloud(feeder.std)
    assert np.all((doo["degree_of_occupancy"] >= 0.1) & (doo["degree_of_occupancy"] <= 1.0))
    assert np.all((std["std"] >= 0.0) & (std["std"] <= 0.5))  # the most a DoO in [0, 1] has
    assert np.array_equal(doo["x"], std["x"])
    # the walls are where the box world has them: occupied voxels hug its surfaces
    xyz = np.stack([doo["x"], doo["y"], doo["z"]], axis=1)
    face = (np.abs(xyz[:, 0] - 5.0) < 0.3) & (xyz[:, 1] > 3.0) & (xyz[:, 1] < 5.0)
    assert face.sum() >= 5
    inside = (xyz[:, 0] > 5.5) & (xyz[:, 0] < 6.5) & (xyz[:, 1] > 3.5) & (xyz[:, 1] < 4.5)
    assert not inside.any()
    assert np.all(xyz[:, 2] > -0.5)  # nothing below the ground: poses and extrinsic applied


def test_reflectivity_cloud_and_query(sim: Sim, feeder: Feeder) -> None:
    """~/reflectivity: the voxels holding returns of the Velodyne-layout sweeps (intensity 10,
    the map's field: the first cloud's), in bin [8, 16) of the log-spaced edges; ~/query
    answers each point's histogram. The Ouster-layout sweeps' ``reflectivity`` is another
    field: their returns count in n, not in the histograms."""
    from mfp_mapper_msgs.srv import QueryMap
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    got: list[Any] = []
    latched = QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
    )
    sub = feeder.node.create_subscription(
        PointCloud2, f"{feeder.ns}/reflectivity", got.append, latched
    )
    try:
        assert feeder.wait(lambda: bool(got) and got[-1].width > 100, 20.0)
        msg = got[-1]
        assert msg.header.frame_id == "odom"
        assert [f.name for f in msg.fields] == ["x", "y", "z", "reflectivity", "reflectivity_bin"]
        cloud = read_cloud(msg)
        assert np.all(cloud["reflectivity_bin"] == 3)
        np.testing.assert_allclose(cloud["reflectivity"], np.sqrt(8.0 * 16.0), rtol=1e-6)
        client = feeder.node.create_client(QueryMap, f"{feeder.ns}/query")
        assert client.wait_for_service(10.0)
        request = QueryMap.Request()
        request.points_xyz = [float(cloud[a][0]) for a in "xyz"] + [0.0, 0.0, 50.0]
        response = feeder.call(client, request)
        assert response.success, response.message
        assert response.reflectivity_field == "intensity"
        assert list(response.reflectivity_edges) == [2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0]
        counts = np.asarray(response.reflectivity_counts).reshape(2, 8)
        assert counts[0, 3] > 0 and counts[0].sum() == counts[0, 3] and counts[1].sum() == 0
        mean = np.asarray(response.reflectivity_mean)
        assert mean[0] == pytest.approx(np.sqrt(128.0)) and np.isnan(mean[1])
    finally:
        feeder.node.destroy_subscription(sub)


def _grid(resp: Any) -> tuple[np.ndarray, tuple[float, float], float]:
    info = resp.map.info
    data = np.array(resp.map.data, dtype=np.int8).reshape(info.height, info.width)
    return data, (info.origin.position.x, info.origin.position.y), info.resolution


def _cell(grid: np.ndarray, origin: tuple[float, float], res: float, x: float, y: float) -> int:
    col = int(np.floor((x - origin[0]) / res))
    row = int(np.floor((y - origin[1]) / res))
    if 0 <= row < grid.shape[0] and 0 <= col < grid.shape[1]:
        return int(grid[row, col])
    return -1


def test_hit_probability_map_service(sim: Sim, feeder: Feeder) -> None:
    from nav_msgs.srv import GetMap

    resp = feeder.call(feeder.get_map, GetMap.Request())
    assert resp.map.header.frame_id == "odom"
    grid, origin, res = _grid(resp)
    assert res == pytest.approx(RES)
    assert grid.shape[0] > 50 and grid.shape[1] > 50
    assert grid.min() == -1 and grid.max() <= 100
    assert set(np.unique(grid)) <= set(range(-1, 101))
    face = max(_cell(grid, origin, res, 4.9, 4.0), _cell(grid, origin, res, 5.1, 4.0))
    free = _cell(grid, origin, res, 8.0, -2.0)
    assert face >= 30
    assert 0 <= free <= 25 and free < face / 2
    assert _cell(grid, origin, res, 6.0, 4.0) == -1  # inside the box: never observed


def test_projected_map_topic_is_the_service_grid(sim: Sim, feeder: Feeder) -> None:
    """~/projected_map (latched, what Nav2's static layer subscribes to) = the GetMap grid."""
    from nav_msgs.srv import GetMap

    served = feeder.call(feeder.get_map, GetMap.Request()).map
    assert feeder.wait(
        lambda: (
            feeder.projected is not None
            and feeder.projected.info.width == served.info.width
            and feeder.projected.info.height == served.info.height
        ),
        15.0,
    )
    assert feeder.projected.header.frame_id == "odom"
    # the topic is trinary for Nav2 (occupied 0.25, free below p of an unseen voxel: 0.023
    # at 0.2 m with the default prior); the service keeps round(100 p)
    served_data = np.array(served.data, dtype=int)
    projected = np.array(feeder.projected.data, dtype=int)
    assert set(np.unique(projected)) <= {-1, 0, 100}
    assert np.all(projected[served_data == -1] == -1)
    assert np.all(projected[served_data >= 26] == 100) and (served_data >= 26).any()
    assert np.all(projected[(served_data >= 0) & (served_data <= 1)] == 0)
    assert len(set(np.unique(served_data)) - {-1, 0, 100}) > 5  # the service: percentages


def test_hit_probability_query_topic(sim: Sim, feeder: Feeder) -> None:
    points = np.array(
        [[4.9, 4.0, 1.0], [5.1, 4.0, 1.0], [8.0, -2.0, 1.7], [100.0, 100.0, 100.0], [0, 0, 0]],
        dtype=np.float32,
    )
    query = cloud_from_columns({a: points[:, k] for k, a in enumerate("xyz")}, "odom", T0 + 123.4)
    feeder.results.clear()
    feeder.query_pub.publish(query)
    assert feeder.wait(lambda: bool(feeder.results), 10.0)
    result = feeder.results[0]
    assert result.header.frame_id == "odom"
    assert (result.header.stamp.sec, result.header.stamp.nanosec) == (
        query.header.stamp.sec,
        query.header.stamp.nanosec,
    )
    names = ["x", "y", "z", "hit_probability", "degree_of_occupancy", "std"]
    assert [f.name for f in result.fields] == [*names, "mean_free_path", "observed"]
    cols = read_cloud(result)
    assert result.width == len(points)
    assert np.allclose(np.stack([cols["x"], cols["y"], cols["z"]], 1), points)
    hit, observed = cols["hit_probability"], cols["observed"]
    assert max(hit[0], hit[1]) >= 0.3  # the box face
    assert observed[2] == 1.0 and hit[2] < 0.5 * max(hit[0], hit[1])  # free space
    assert cols["degree_of_occupancy"][2] == 0.0
    assert observed[3] == 0.0  # never seen: unknown, no number (the prior's would look free)
    for name in ("hit_probability", "degree_of_occupancy", "std", "mean_free_path"):
        assert np.isnan(cols[name][3]), name


def _malformed_clouds(stamp: float) -> list[tuple[str, Any]]:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(1.0, 5.0, (100, 3)).astype(np.float32)
    cols = {a: xyz[:, k] for k, a in enumerate("xyz")}
    missing_z = cloud_from_columns({"x": cols["x"], "y": cols["y"]}, "lidar", stamp)
    short_step = cloud_from_columns(cols, "lidar", stamp, point_step=8)
    short_step.row_step = 8 * 100
    short_step.data = bytes(short_step.data)[:800]
    truncated = cloud_from_columns(cols, "lidar", stamp)
    truncated.data = bytes(truncated.data)[:600]
    bad_type = cloud_from_columns(cols, "lidar", stamp)
    bad_type.fields[2].datatype = 42
    nan = {a: np.full(100, np.nan, np.float32) for a in "xyz"}
    all_nan = cloud_from_columns(nan, "lidar", stamp)
    empty = cloud_from_columns({a: np.zeros(0, np.float32) for a in "xyz"}, "lidar", stamp)
    return [
        ("malformed", missing_z),
        ("malformed", short_step),
        ("malformed", truncated),
        ("malformed", bad_type),
        ("empty", all_nan),
        ("empty", empty),
    ]


def test_malformed_clouds_leave_the_node_running(
    sim: Sim, feeder: Feeder, node: NodeProcess
) -> None:
    before = sim.status()
    drops0 = dict(before["clouds_dropped"])
    for _, msg in _malformed_clouds(T0 + 1.9):
        sim.send_cloud(msg)
    sim.send_scan(T0 + 1.8, odom_after=0.1)  # a good one afterwards
    integrated = before["clouds_integrated"] + 1

    status = feeder.wait_status(lambda s: s["clouds_integrated"] >= integrated, 15.0)
    drops = status["clouds_dropped"]
    assert drops.get("malformed", 0) - drops0.get("malformed", 0) == 4, status
    assert drops.get("empty", 0) - drops0.get("empty", 0) == 2, status
    assert status["clouds_integrated"] == integrated
    assert status["points_dropped"].get("nonfinite", 0) >= 100
    assert node.alive()
    log = node.log()
    assert "no field z" in log and "dropped cloud (malformed)" in log


def test_clouds_that_cannot_be_placed_are_dropped_not_misplaced(
    sim: Sim, feeder: Feeder, node: NodeProcess
) -> None:
    feeder.wait_status(lambda s: s["queued"] == 0, 5.0)
    before = sim.status()
    drops0 = dict(before["clouds_dropped"])
    version0 = before["map_version"]
    # odometry jumps from T0+2.0 to T0+3.0: a gap longer than odom_max_gap (0.3 s)
    sim.odom_to(T0 + 2.0)
    sim.odom_to(T0 + 3.5, start=T0 + 3.0)
    sim.send_cloud(sim.scan_msg(T0 + 2.5))  # inside the gap
    sim.send_cloud(sim.scan_msg(T0 - 3.0))  # older than odom_buffer (2 s)
    sim.send_cloud(sim.scan_msg(T0 + 60.0))  # odometry never gets there

    def dropped(s: dict[str, Any], reason: str) -> int:
        return s["clouds_dropped"].get(reason, 0) - drops0.get(reason, 0)

    status = feeder.wait_status(
        lambda s: all(dropped(s, r) >= 1 for r in ("gap", "too_old", "too_new")), 10.0
    )
    assert {r: dropped(status, r) for r in ("gap", "too_old", "too_new")} == {
        "gap": 1,
        "too_old": 1,
        "too_new": 1,
    }, status
    assert status["map_version"] == version0  # nothing was placed
    assert status["clouds_integrated"] == before["clouds_integrated"]
    log = node.log()
    for reason in ("gap", "too_old", "too_new"):
        assert f"dropped cloud ({reason})" in log
    # a cloud covered by the odometry after the gap is placed again
    sim.send_scan(T0 + 3.2, odom_after=0.2)
    status = feeder.wait_status(
        lambda s: s["clouds_integrated"] == before["clouds_integrated"] + 1, 10.0
    )
    assert status["clouds_integrated"] == before["clouds_integrated"] + 1
    assert node.alive()


def test_save_load_reset(
    sim: Sim, feeder: Feeder, node: NodeProcess, ros_domain: int, workdir: Path
) -> None:
    from nav_msgs.srv import GetMap
    from std_srvs.srv import Empty, Trigger

    saved = feeder.call(feeder.save, Trigger.Request())
    path = workdir / "map.npz"
    assert saved.success, saved.message
    assert path.is_file() and str(path) in saved.message
    grid, origin, _ = _grid(feeder.call(feeder.get_map, GetMap.Request()))

    # a second node loads the saved map at start and saves it again on shutdown;
    # a third one is given a corrupt file: it starts empty and never overwrites it
    copy = workdir / "copy.npz"
    shutil.copy(path, copy)
    os.utime(copy, (1.0, 1.0))
    bad = workdir / "bad.npz"
    bad.write_bytes(b"not a map")
    common = {
        "resolution": RES,
        "publish_rate": 0.0,
        "save_on_shutdown": True,
        "occupancy_min_z": NODE_PARAMS["occupancy_min_z"],
    }
    loaded = NodeProcess(
        ros_domain, {**common, "map_path": str(copy)}, workdir / "loaded.log", name="mfp_loaded"
    )
    corrupt = NodeProcess(
        ros_domain, {**common, "map_path": str(bad)}, workdir / "bad.log", name="mfp_bad"
    )
    f2 = Feeder(node_name="mfp_loaded", feeder_name="feeder_loaded")
    f3 = Feeder(node_name="mfp_bad", feeder_name="feeder_bad")
    try:
        assert f2.get_map.wait_for_service(30.0), loaded.log()
        assert f3.get_map.wait_for_service(30.0), corrupt.log()
        grid2, origin2, _ = _grid(f2.call(f2.get_map, GetMap.Request()))
        assert origin2 == origin and np.array_equal(grid2, grid)
        empty = f3.call(f3.get_map, GetMap.Request()).map.info
        assert (empty.width, empty.height) == (0, 0)
    finally:
        f2.destroy()
        f3.destroy()
        assert loaded.stop() == 0
        assert corrupt.stop() == 0
    assert copy.stat().st_mtime > 1.0, loaded.log()  # saved on shutdown
    assert bad.read_bytes() == b"not a map"
    assert "cannot load map_path" in corrupt.log()

    # reset: the map is empty and the published clouds say so
    feeder.call(feeder.reset, Empty.Request())
    status = feeder.wait_status(lambda s: s["voxels"] == 0, 5.0)
    assert status["voxels"] == 0
    assert feeder.wait(lambda: feeder.doo is not None and feeder.doo.width == 0, 5.0)
    info = feeder.call(feeder.get_map, GetMap.Request()).map.info
    assert (info.width, info.height) == (0, 0)
    assert node.alive()


def test_a_slow_save_does_not_stall_odometry(
    ros_domain: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """~/save_map writes in the background: while a (held) write is in progress the node,
    spun like ``main`` does, keeps taking odometry; the call then answers with success."""
    import threading

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    import mfp_mapper.ros.map_files as map_files
    import mfp_mapper.ros.node as node_module

    started, release = threading.Event(), threading.Event()
    write = map_files.write_map_path

    def held_write(path: Any, arrays: Any) -> int:
        started.set()
        release.wait(30.0)
        return write(path, arrays)

    monkeypatch.setattr(map_files, "write_map_path", held_write)
    path = tmp_path / "slow.npz"
    mapper_node = node_module.MfpMapperNode(
        cli_args=["--ros-args", "-r", "__node:=mfp_slow_save"],
        parameter_overrides=[
            Parameter("map_path", value=str(path)),
            Parameter("publish_rate", value=0.0),
        ],
    )
    executor = SingleThreadedExecutor()
    executor.add_node(mapper_node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    f = Feeder(node_name="mfp_slow_save", feeder_name="feeder_slow_save")
    try:
        assert f.wait(
            lambda: f.save.service_is_ready() and f.odom_pub.get_subscription_count() > 0, 30.0
        )
        pending = f.save.call_async(Trigger.Request())
        assert f.wait(started.is_set, 10.0), "the save never started"
        for k in range(10):
            f.odom_pub.publish(odom_msg(T0 + 0.05 * k, np.zeros(3), 0.0))
        assert f.wait(lambda: mapper_node.worker.counters.odom_in == 10, 10.0), (
            f"odometry taken during the save: {mapper_node.worker.counters.odom_in} of 10"
        )
        assert not pending.done()
        release.set()
        assert f.wait(pending.done, 20.0), "the save call never answered"
        assert pending.result().success, pending.result().message
        assert path.is_file()

        def broken_write(path: Any, arrays: Any) -> int:
            raise RuntimeError("unexpected")

        monkeypatch.setattr(map_files, "write_map_path", broken_write)
        failed = f.call(f.save, Trigger.Request())  # answered, and the node keeps spinning
        assert not failed.success and "unexpected" in failed.message
        assert spinner.is_alive()
    finally:
        release.set()
        f.destroy()
        executor.shutdown(timeout_sec=5.0)
        mapper_node.close()
        mapper_node.destroy_node()
        spinner.join(timeout=5.0)


def test_large_data_dds_profile_loads(tmp_path: Path) -> None:
    """config/fastdds_large_data.xml parses in the middleware (Fast DDS prints XMLPARSER
    errors and falls back to its defaults for a broken profile)."""
    import subprocess
    import sys

    from ros_helpers import ROOT, ros_env

    profile = ROOT / "config" / "fastdds_large_data.xml"
    env = {**ros_env(domain_id()), "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)}
    code = "import rclpy; rclpy.init(); rclpy.create_node('profile_check'); print('participant up')"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
    )
    log = out.stdout + out.stderr  # Fast DDS logs to stdout
    assert out.returncode == 0 and "participant up" in log, log
    assert "XMLPARSER" not in log and "Error" not in log, log

    broken = tmp_path / "broken.xml"
    broken.write_text(profile.read_text().replace("33554432", "a lot"))
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(broken)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
    )
    assert "XMLPARSER" in out.stdout + out.stderr  # the check above sees a broken profile


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("mfp_mapper:\n  ros__parameters:\n    resolution: [0.1\n", "line 4"),
        ("mfp_mapper:\n  ros__parameters:\n    resolution: 0.1\n   bad: : x\n", "line 4"),
    ],
)
def test_a_params_file_that_is_not_yaml_gives_one_line(
    tmp_path: Path, text: str, where: str
) -> None:
    """rclpy's init rejects the file before the node exists: one line that says where, exit
    2, no traceback."""
    import subprocess
    import sys

    from ros_helpers import ROOT, ros_env

    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    args = [sys.executable, "-m", "mfp_mapper.node", "--ros-args", "--params-file", str(bad)]
    run = subprocess.run(
        args, env=ros_env(domain_id()), cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2, run.stderr
    ours = [line for line in run.stderr.splitlines() if line.startswith("mfp_mapper:")]
    assert len(ours) == 1 and str(bad) in ours[0] and where in ours[0], run.stderr
    assert "Traceback" not in run.stderr


def test_a_cold_start_takes_every_cloud_it_receives(ros_domain: int, tmp_path: Path) -> None:
    """With a cold numba cache the node compiled its kernels while it took clouds: the first
    clouds waited for the compiler and were dropped (9 at 0.2 m on norlab, the first
    integrated 5.5 s late). Configure now compiles them, on a throwaway map of the node's
    settings, before activate subscribes (a lifecycle node's heavy setup). A lidar that
    publishes at 10 Hz from the moment the node subscribes: every cloud the node receives
    is integrated, none dropped, and the log says how long the kernels took."""
    cold = {"NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")}
    params = {**NODE_PARAMS, "cloud_queue_size": 5}
    node = NodeProcess(ros_domain, params, tmp_path / "node.log", name="mfp_cold", env=cold)
    f = Feeder(node_name="mfp_cold", feeder_name="cold_feeder")
    sent = 30

    def subscribed() -> bool:  # this node's subscriptions (the module's node also has them)
        return all(
            any(info.node_name == "mfp_cold" for info in f.node.get_subscriptions_info_by_topic(t))
            for t in ("/cloud_in", "/odom")
        )

    try:
        assert f.wait_connected(300.0) and f.wait(subscribed, 300.0), node.log()[-3000:]
        sim = Sim(f)
        # the node's subscriptions in the graph do not mean its readers have matched our
        # writers yet: the first odometry could be lost, and the first clouds dropped too_old
        assert sim.odom_until_counted(30.0), node.log()[-3000:]
        first = sim.odom_until + ODOM_DT
        for k in range(sent):  # a driver streaming, not waiting for the node
            start = first + 0.1 * k
            sim.odom_to(start + 0.25)
            f.cloud_pub.publish(sim.scan_msg(start))
            f.spin(0.1)
        sim.odom_to(first + 0.1 * sent + 1.0)

        def settled(s: dict[str, Any]) -> bool:
            handled = s["clouds_integrated"] + sum(s["clouds_dropped"].values())
            return s["clouds_in"] > 0 and handled >= s["clouds_in"] and s["queued"] == 0

        status = f.wait_status(settled, 60.0)
        assert status is not None and settled(status), f"{status}\n{node.log()[-3000:]}"
    finally:
        f.destroy()
        node.stop()
    assert status["clouds_in"] >= sent // 2, status  # best effort: a few may be lost
    assert not any(status["clouds_dropped"].values()), status
    assert status["clouds_integrated"] == status["clouds_in"], status
    assert status["kernels"] == "ready", status
    assert "kernels ready in" in node.log() and "before taking clouds" in node.log()
