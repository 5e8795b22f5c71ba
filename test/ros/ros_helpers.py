"""Helpers for the node tests and the node benchmark: a node process, a feeder, scans.

Every process runs with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and its own
``ROS_DOMAIN_ID`` so that parallel test runs never see each other.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
PARAMS_FILE = ROOT / "config" / "mfp_mapper.yaml"

FLOAT32 = 7
UINT32 = 6
UINT16 = 4
UINT8 = 2
FLOAT64 = 8


def domain_id() -> int:
    """A ROS domain id: ``ROS_DOMAIN_ID`` when set (``./run test`` sets a private one), else
    derived from this process id (10..99)."""
    chosen = os.environ.get("ROS_DOMAIN_ID")
    return int(chosen) if chosen else os.getpid() % 90 + 10


def ros_env(domain: int) -> dict[str, str]:
    """Environment for a ROS process on loopback in ``domain``."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return env


def set_ros_env(domain: int) -> None:
    """Make this process use ``domain`` on loopback (call before rclpy.init)."""
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


@contextmanager
def ros_context(domain: int, env: dict[str, str | None] | None = None) -> Iterator[int]:
    """rclpy initialised on ``domain`` (on loopback), with ``env`` set in this process and
    the nodes it starts (None: unset); the environment is restored afterwards. Fast DDS
    reads its XML profile once per process: a profile set here applies only if no earlier
    test started DDS in this process."""
    import rclpy

    changes: dict[str, str | None] = {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        **(env or {}),
    }
    saved = {k: os.environ.get(k) for k in changes}
    for key, value in changes.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
    rclpy.init(domain_id=domain)
    try:
        yield domain
    finally:
        rclpy.try_shutdown()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _param_arg(name: str, value: Any) -> str:
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, (list, tuple)):
        text = "[" + ",".join(repr(float(v)) for v in value) + "]"
    elif isinstance(value, float):
        text = repr(value)
    else:
        text = str(value) or "''"  # an empty string: quoted, or rcl cannot parse the rule
    return f"{name}:={text}"


class NodeProcess:
    """``python -m mfp_mapper.node`` in a subprocess; ``stop()`` ends it by PID."""

    def __init__(
        self,
        domain: int,
        params: dict[str, Any],
        log_path: Path,
        *,
        name: str | None = None,
        params_file: Path | None = PARAMS_FILE,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
    ) -> None:
        """``cwd``: the checkout whose ``mfp_mapper`` runs (default: this one)."""
        args = [sys.executable, "-m", "mfp_mapper.node", "--ros-args"]
        if name:
            args += ["-r", f"__node:={name}"]
        if params_file is not None:
            args += ["--params-file", str(params_file)]
        for key, value in params.items():
            args += ["-p", _param_arg(key, value)]
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            args,
            env={**ros_env(domain), **(env or {})},
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=cwd or ROOT,
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT (clean shutdown), then SIGTERM, then SIGKILL; returns the exit code."""
        if self.proc.poll() is None:
            for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0)):
                self.proc.send_signal(sig)
                try:
                    self.proc.wait(wait)
                    break
                except subprocess.TimeoutExpired:
                    continue
            else:
                self.proc.kill()
                self.proc.wait(5.0)
        self._log.close()
        return int(self.proc.returncode)


# --- messages --------------------------------------------------------------------------------


def stamp_msg(seconds: float) -> Any:
    from builtin_interfaces.msg import Time

    sec = math.floor(seconds)
    return Time(sec=int(sec), nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


def cloud_from_columns(
    columns: dict[str, np.ndarray],
    frame_id: str,
    stamp: float,
    *,
    point_step: int | None = None,
    bigendian: bool = False,
) -> Any:
    """A PointCloud2 with one field per column, in the columns' own dtypes (feeder side);
    ``point_step`` overrides the packed one (to build malformed clouds)."""
    from mfp_mapper.ros.messages import cloud_msg
    from mfp_mapper.sensing.pointcloud import pack_columns

    packed = pack_columns(columns, big_endian=bigendian)
    msg = cloud_msg(packed, frame_id, stamp_msg(stamp))
    if point_step is not None:
        msg.point_step = point_step
        msg.row_step = point_step * packed.width
    msg.is_dense = False
    return msg


def read_cloud(msg: Any) -> dict[str, np.ndarray]:
    """The float32/uint fields of a received PointCloud2 as columns (test side)."""
    codes = {2: "u1", 4: "u2", 6: "u4", 7: "f4", 8: "f8"}
    dtype = np.dtype(
        {
            "names": [f.name for f in msg.fields],
            "formats": [
                ("<" if not msg.is_bigendian else ">") + codes[f.datatype] for f in msg.fields
            ],
            "offsets": [f.offset for f in msg.fields],
            "itemsize": msg.point_step,
        }
    )
    rec = np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)
    return {f.name: np.asarray(rec[f.name]) for f in msg.fields}


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def odom_msg(stamp: float, position: np.ndarray, yaw: float, frame="odom", child="base_link"):
    from nav_msgs.msg import Odometry

    msg = Odometry()
    msg.header.frame_id = frame
    msg.header.stamp = stamp_msg(stamp)
    msg.child_frame_id = child
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = (
        float(v) for v in position
    )
    q = yaw_quaternion(yaw)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = q
    return msg


# --- simulated robot -------------------------------------------------------------------------


class Trajectory:
    """Base pose over time: constant velocity and yaw rate from the origin at ``t0``."""

    def __init__(self, t0: float, velocity=(1.0, 0.2, 0.0), yaw_rate: float = 0.3) -> None:
        self.t0 = t0
        self.velocity = np.asarray(velocity, dtype=np.float64)
        self.yaw_rate = yaw_rate

    def position(self, t: np.ndarray | float) -> np.ndarray:
        dt = np.asarray(t, dtype=np.float64) - self.t0
        return dt[..., None] * self.velocity

    def yaw(self, t: np.ndarray | float) -> np.ndarray:
        return (np.asarray(t, dtype=np.float64) - self.t0) * self.yaw_rate


def rot_z(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def simulate_scan(
    world: Any,
    directions: np.ndarray,
    azimuths: int,
    traj: Trajectory,
    start: float,
    lidar_height: float,
    sweep: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """A spinning-lidar sweep seen from a moving base: points in the lidar frame, times.

    ``directions`` are beam-major (``scan_directions``); azimuth column ``a`` is fired at
    ``start + a / azimuths * sweep``. The lidar sits ``lidar_height`` above the base, axes
    aligned with it. Returns (points (N, 3) lidar frame, time offsets (N,) s); rays with no
    return are left out.
    """
    n = directions.shape[0]
    offsets = (np.arange(n) % azimuths) / azimuths * sweep
    t = start + offsets
    rot = rot_z(traj.yaw(t))
    origins = traj.position(t) + np.array([0.0, 0.0, lidar_height])
    world_dirs = np.einsum("nij,nj->ni", rot, directions)
    rng = world.cast(origins, world_dirs)
    keep = np.isfinite(rng)
    return directions[keep] * rng[keep, None], offsets[keep]


def wait_for(predicate: Callable[[], bool], timeout: float, spin: Callable[[], None]) -> bool:
    """Spin until ``predicate()`` is true or ``timeout`` seconds passed."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        spin()
    return predicate()


class Feeder:
    """The test side: publishers, subscribers and service clients around the node."""

    def __init__(self, node_name: str = "mfp_mapper", feeder_name: str = "feeder") -> None:
        import rclpy
        from nav_msgs.msg import OccupancyGrid, Odometry
        from nav_msgs.srv import GetMap
        from rclpy.qos import (
            DurabilityPolicy,
            QoSProfile,
            ReliabilityPolicy,
            qos_profile_sensor_data,
        )
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String
        from std_srvs.srv import Empty, Trigger

        self.rclpy = rclpy
        self.node = rclpy.create_node(feeder_name)
        ns = f"/{node_name}"
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        del qos_profile_sensor_data  # the node's subscription is best effort: reliable matches
        self.cloud_pub = self.node.create_publisher(PointCloud2, "cloud_in", reliable)
        self.odom_pub = self.node.create_publisher(Odometry, "odom", QoSProfile(depth=200))
        self.query_pub = self.node.create_publisher(
            PointCloud2, f"{ns}/hit_probability/query", reliable
        )
        self.status: dict[str, Any] | None = None
        self.doo: Any = None
        self.std: Any = None
        self.projected: Any = None
        self.results: list[Any] = []
        self.node.create_subscription(String, f"{ns}/status", self._on_status, latched)
        self.node.create_subscription(
            PointCloud2, f"{ns}/degree_of_occupancy", lambda m: setattr(self, "doo", m), latched
        )
        self.node.create_subscription(
            PointCloud2, f"{ns}/std", lambda m: setattr(self, "std", m), latched
        )
        self.node.create_subscription(
            PointCloud2, f"{ns}/hit_probability/result", self.results.append, reliable
        )
        self.node.create_subscription(
            OccupancyGrid, f"{ns}/projected_map", lambda m: setattr(self, "projected", m), latched
        )
        self.get_map = self.node.create_client(GetMap, f"{ns}/hit_probability_map")
        self.save = self.node.create_client(Trigger, f"{ns}/save_map")
        self.reset = self.node.create_client(Empty, f"{ns}/reset")
        self.ns = ns

    def _on_status(self, msg: Any) -> None:
        self.status = json.loads(msg.data)

    def spin(self, timeout: float = 0.02) -> None:
        self.rclpy.spin_once(self.node, timeout_sec=timeout)

    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
        return wait_for(predicate, timeout, self.spin)

    def wait_connected(self, timeout: float = 20.0) -> bool:
        """Discovery: the node's subscriptions see our publishers, its services are up."""
        return self.wait(
            lambda: (
                self.cloud_pub.get_subscription_count() > 0
                and self.odom_pub.get_subscription_count() > 0
                and self.query_pub.get_subscription_count() > 0
                and self.get_map.service_is_ready()
                and self.save.service_is_ready()
                and self.reset.service_is_ready()
            ),
            timeout,
        )

    def call(self, client: Any, request: Any, timeout: float = 10.0) -> Any:
        future = client.call_async(request)
        self.rclpy.spin_until_future_complete(self.node, future, timeout_sec=timeout)
        if not future.done():
            raise TimeoutError(f"service {client.srv_name} did not answer in {timeout} s")
        return future.result()

    def wait_status(self, predicate: Callable[[dict[str, Any]], bool], timeout: float = 10.0):
        """Spin until a status message satisfies ``predicate``; return it (or the last)."""
        self.wait(lambda: self.status is not None and predicate(self.status), timeout)
        return self.status

    def destroy(self) -> None:
        self.node.destroy_node()


def tf_publishers(node: Any) -> tuple[Any, Any]:
    """Publishers of ``/tf`` and of ``/tf_static`` (transient-local, as tf2 latches it)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage

    static = QoSProfile(
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    return (
        node.create_publisher(TFMessage, "/tf", QoSProfile(depth=100)),
        node.create_publisher(TFMessage, "/tf_static", static),
    )


def clear_bbox(feeder: Feeder, node_name: str, corner_a: Any, corner_b: Any) -> Any:
    """Call ``~/clear_bbox`` (mfp_mapper_msgs/srv/ClearBbox) of ``node_name``; the response."""
    from geometry_msgs.msg import Point
    from mfp_mapper_msgs.srv import ClearBbox

    client = feeder.node.create_client(ClearBbox, f"/{node_name}/clear_bbox")
    try:
        assert client.wait_for_service(10.0), f"/{node_name}/clear_bbox not found"
        request = ClearBbox.Request()
        request.min, request.max = (
            Point(x=float(c[0]), y=float(c[1]), z=float(c[2])) for c in (corner_a, corner_b)
        )
        return feeder.call(client, request)
    finally:
        feeder.node.destroy_client(client)
