"""The ``mfp_mapper`` ROS 2 node: live mapping from PointCloud2 + Odometry.

Thin wiring around the ROS-free core: parsing (``mfp_mapper.sensing.pointcloud``), poses
(``mfp_mapper.sensing.poses``), the map (``mfp_mapper.Mapper``) and the 2D projection
(``mfp_mapper.core.gridmap``). Run it with ``python -m mfp_mapper.ros.node --ros-args ...`` or
``ros2 run mfp_mapper mfp_mapper``; parameters are in ``mfp_mapper.settings``.

Threads: one executor thread runs every ROS callback (rclpy's multi-threaded executor
cost about 70% of a core in overhead); subscription callbacks only queue clouds and store
poses. A worker thread parses each cloud, waits (bounded) until odometry covers its stamp,
places it with the pose interpolated at its stamp and integrates it, and publishes the map
clouds between scans when the publish timer asks; ``~/save_map`` writes in a thread of its
own. One lock guards the Mapper for integration, publishing, queries and services.
"""

from __future__ import annotations

import array
import contextlib
import functools
import json
import math
import os
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy
import rclpy.exceptions
import rclpy.task
import rclpy.time
import rclpy.utilities
from builtin_interfaces.msg import Time as TimeMsg
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.srv import GetMap
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import String
from std_srvs.srv import Empty, Trigger

from mfp_mapper.core.mapfile import MapFileError, map_arrays, write_map_arrays
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.ros.params import declare_parameters
from mfp_mapper.sensing.pointcloud import (
    CloudFormatError,
    PackedCloud,
    ParsedCloud,
    pack_cloud,
    parse_pointcloud2,
    read_xyz,
    stamp_seconds,
)
from mfp_mapper.sensing.poses import (
    Extrinsic,
    PoseBuffer,
    PoseUnavailable,
    cloud_to_map,
    z_band,
)
from mfp_mapper.settings import SPECS, NodeConfig

try:  # optional: not installable from PyPI
    import tf2_ros  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the installation
    tf2_ros = None

NODE_NAME = "mfp_mapper"
DROP_REASONS = (
    "malformed",  # the message is not a parsable cloud (no x/y/z, bad layout, truncated)
    "empty",  # no valid point left
    "queue_full",  # oldest queued cloud dropped to make room
    "no_poses",  # no odometry at all within odom_wait
    "too_new",  # odometry did not cover the stamp within odom_wait
    "too_old",  # stamp before the odometry kept (odom_buffer)
    "gap",  # stamp between two odometry messages more than odom_max_gap apart
    "error",  # unexpected exception (logged with its type)
)
PUBLISH_DUTY = 0.1
"""Largest share of wall time the map clouds may take: after a publication that took
``dt`` seconds, the next one waits at least ``dt * (1 / PUBLISH_DUTY - 1)``."""


def _stamp_msg(seconds: float) -> TimeMsg:
    sec = math.floor(seconds)
    return TimeMsg(sec=int(sec), nanosec=min(int(round((seconds - sec) * 1e9)), 999_999_999))


def cloud_msg(packed: PackedCloud, frame_id: str, stamp: Any) -> PointCloud2:
    """A sensor_msgs/PointCloud2 from a ``sensing.pointcloud.PackedCloud``."""
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.height = packed.height
    msg.width = packed.width
    msg.fields = [
        PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
        for f in packed.fields
    ]
    msg.is_bigendian = packed.is_bigendian
    msg.point_step = packed.point_step
    msg.row_step = packed.row_step
    msg.data = packed.data
    msg.is_dense = True
    return msg


def _tracked(callback: Callable[..., Any]) -> Callable[..., Any]:
    """Count a ROS callback as in flight, so close() can wait for it (rclpy's executor
    shutdown does not wait for running callbacks, and destroying a node under a running
    callback can crash the process). Callbacks that start after close() do nothing."""

    @functools.wraps(callback)
    def wrapper(self: MfpMapperNode, *args: Any) -> Any:
        if not self._begin_work():
            return args[-1] if len(args) == 2 else None  # a service returns its response
        try:
            return callback(self, *args)
        finally:
            self._end_work()

    return wrapper


@dataclass
class _Pending:
    """A received cloud on its way to the map."""

    received: float  # time.monotonic()
    msg: Any
    cloud: ParsedCloud | None = None
    stamp: float = 0.0
    need_until: float = 0.0  # latest stamp a pose is needed for


@dataclass
class _Counters:
    clouds_in: int = 0
    clouds_lost: int = 0  # reported lost by the middleware (never received)
    clouds_integrated: int = 0
    dropped: Counter = field(default_factory=Counter)  # clouds, by reason
    points_dropped: Counter = field(default_factory=Counter)  # points/rays, by reason
    rays_in: int = 0
    rays_used: int = 0
    rays_truncated: int = 0
    odom_in: int = 0
    odom_rejected: Counter = field(default_factory=Counter)
    integration_cpu: float = 0.0  # thread CPU seconds: parse + place + integrate
    integration_wall: float = 0.0
    latency_sum: float = 0.0
    latency_max: float = 0.0
    latency_last: float = float("nan")
    publish_seconds: float = 0.0  # building and sending, without waiting for the map lock
    publish_locked_seconds: float = 0.0  # of which the map lock was held (integration waits)
    publish_count: int = 0
    publish_last_seconds: float = 0.0
    published_voxels: int = 0
    queries: int = 0
    maps_served: int = 0


class MfpMapperNode(Node):
    """Mean-free-path mapping node (see the module docstring and README "## The node")."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.cfg: NodeConfig = declare_parameters(self)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._map_lock = threading.Lock()
        self._pose_lock = threading.Lock()
        self._cv = threading.Condition()
        self._queue: deque[_Pending] = deque()
        self._stop = threading.Event()
        self._counters = _Counters()
        self._warned: dict[str, float] = {}
        self._started = time.monotonic()
        self._load_failed = False
        self._closing = False
        self._map_figures = (0, 0, 0)
        self._inflight = 0
        self._inflight_cv = threading.Condition()

        self.poses = PoseBuffer(max_age=self.cfg.odom_buffer, max_gap=self.cfg.odom_max_gap)
        self._odom_frame: str | None = None
        self._odom_child: str | None = None
        self._robot_position: np.ndarray | None = None
        self._param_extrinsic = self.cfg.extrinsic()
        self._identity = Extrinsic()
        self.mapper = self._initial_mapper()
        self._published_version: int | None = None
        self._publish_not_before = 0.0
        self._publish_due = False  # set by the publish timer, served by the worker

        self._tf_buffer = None
        if self.cfg.use_tf:
            if tf2_ros is None:
                self.get_logger().warning(
                    "use_tf is true but tf2_ros is not importable: using lidar.translation "
                    "and lidar.rpy"
                )
            else:  # pragma: no cover - tf2_ros is not installable in the test environment
                self._tf_buffer = tf2_ros.Buffer()
                self._tf_listener = tf2_ros.TransformListener(self._tf_buffer, self)

        # --- ROS interfaces ----------------------------------------------------------------
        self.create_subscription(
            PointCloud2,
            "cloud_in",
            self._on_cloud,
            qos_profile_sensor_data,
            event_callbacks=SubscriptionEventCallbacks(message_lost=self._on_clouds_lost),
        )
        odom_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.BEST_EFFORT
        )
        self.create_subscription(Odometry, "odom", self._on_odom, odom_qos)
        map_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=(
                DurabilityPolicy.TRANSIENT_LOCAL if self.cfg.latch else DurabilityPolicy.VOLATILE
            ),
        )
        self._doo_pub = self.create_publisher(PointCloud2, "~/degree_of_occupancy", map_qos)
        self._std_pub = self.create_publisher(PointCloud2, "~/std", map_qos)
        self._grid_pub = self.create_publisher(OccupancyGrid, "~/projected_map", map_qos)
        status_qos = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self._status_pub = self.create_publisher(String, "~/status", status_qos)
        self._result_pub = self.create_publisher(PointCloud2, "~/hit_probability/result", 10)
        self.create_subscription(PointCloud2, "~/hit_probability/query", self._on_query, 10)
        self.create_service(GetMap, "~/hit_probability_map", self._on_get_map)
        # its own callback group: while a save runs in the background, its pending call must
        # not hold the default group (which every other callback is in)
        self.create_service(
            Trigger, "~/save_map", self._on_save, callback_group=MutuallyExclusiveCallbackGroup()
        )
        self.create_service(Empty, "~/reset", self._on_reset)
        # wakes the executor when a background save finishes (its service call resumes)
        self._wake = self.create_guard_condition(lambda: None)
        self._save_lock = threading.Lock()
        if self.cfg.publish_rate > 0.0:
            self.create_timer(1.0 / self.cfg.publish_rate, self._on_publish_timer)
        self._status_window = (time.monotonic(), 0, 0.0, 0.0)
        if self.cfg.status_period > 0.0:
            self.create_timer(self.cfg.status_period, self._on_status)

        self._worker = threading.Thread(target=self._work, name="mfp_integration", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"mfp_mapper ready: resolution {self.mapper.resolution} m, max_range "
            f"{self.cfg.max_range} m, decay_time {self.cfg.decay} s, deskew {self.cfg.deskew}, "
            f"map frame {self.cfg.frame_id or '<odometry frame>'}"
        )

    # --- set-up ----------------------------------------------------------------------------

    def _initial_mapper(self) -> Mapper:
        path = self.cfg.map_path
        if path and os.path.exists(path):
            try:
                mapper = Mapper.load(path, **self.cfg.mapper_settings())
            except (MapFileError, ValueError, OSError) as err:
                self._load_failed = True
                self.get_logger().error(
                    f"cannot load map_path {path!r}: {err}; starting an empty map (and not "
                    "saving over that file on shutdown)"
                )
            else:
                if mapper.resolution != self.cfg.resolution:
                    self.get_logger().warning(
                        f"map {path!r} has resolution {mapper.resolution} m, parameter "
                        f"resolution is {self.cfg.resolution} m: keeping the map's"
                    )
                if self.cfg.frame_id:
                    mapper.frame_id = self.cfg.frame_id
                self.get_logger().info(
                    f"loaded {mapper.num_voxels} voxels from {path!r} (frame {mapper.frame_id})"
                )
                return mapper
        return Mapper(
            self.cfg.resolution, frame_id=self.cfg.frame_id or "map", **self.cfg.mapper_settings()
        )

    def _on_set_parameters(self, params: list[Any]) -> SetParametersResult:
        values = self.cfg.values()
        for p in params:
            spec = SPECS.get(p.name)
            if spec is None:  # use_sim_time and other rclpy parameters
                continue
            if not spec.dynamic:
                return SetParametersResult(successful=False, reason=f"{p.name} is read-only")
            values[p.name] = p.value
        try:
            new = NodeConfig.from_values(values)
        except (ValueError, TypeError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        self.cfg = new  # one assignment: a reader never sees half of a change
        self._published_version = None  # republish with the new filter
        return SetParametersResult(successful=True)

    def _warn_throttled(
        self, key: str, text: str, period: float = 5.0, error: bool = False
    ) -> None:
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) < period:
            return
        self._warned[key] = now
        # rclpy ties one severity to each call site: keep the two calls apart
        if error:
            self.get_logger().error(text)
        else:
            self.get_logger().warning(text)

    @property
    def map_frame(self) -> str:
        return self.cfg.frame_id or self._odom_frame or self.mapper.frame_id

    # --- inputs ----------------------------------------------------------------------------

    @_tracked
    def _on_cloud(self, msg: PointCloud2) -> None:
        item = _Pending(time.monotonic(), msg)
        with self._cv:
            self._counters.clouds_in += 1
            if len(self._queue) >= self.cfg.cloud_queue_size:
                self._queue.popleft()
                self._drop_locked("queue_full", "integration is behind; dropped the oldest cloud")
            self._queue.append(item)
            self._cv.notify_all()

    def _on_clouds_lost(self, info: Any) -> None:
        """The middleware reports clouds that never reached this node (transport losses)."""
        with self._cv:
            self._counters.clouds_lost += info.total_count_change
        self._warn_throttled(
            "clouds_lost",
            f"{info.total_count_change} cloud(s) lost in transport before reaching the node "
            f"[{self._counters.clouds_lost} so far]",
        )

    @_tracked
    def _on_odom(self, msg: Odometry) -> None:
        frame = msg.header.frame_id
        if self.cfg.frame_id and frame and frame != self.cfg.frame_id:
            self._counters.odom_rejected["frame"] += 1
            self._warn_throttled(
                "odom_frame",
                f"odometry is in frame {frame!r} but frame_id is {self.cfg.frame_id!r}: ignored "
                "(the map frame must be the odometry frame)",
                error=True,
            )
            return
        if self._odom_frame is not None and frame != self._odom_frame:
            self._counters.odom_rejected["frame"] += 1
            self._warn_throttled(
                "odom_frame_change",
                f"odometry frame changed from {self._odom_frame!r} to {frame!r}: ignored",
                error=True,
            )
            return
        p = msg.pose.pose.position
        o = msg.pose.pose.orientation
        position = np.array([p.x, p.y, p.z])
        with self._pose_lock:
            ok = self.poses.add(
                stamp_seconds(msg.header.stamp), position, np.array([o.x, o.y, o.z, o.w])
            )
        self._counters.odom_in += 1
        if not ok:
            self._counters.odom_rejected["out_of_order_or_invalid"] += 1
            self._warn_throttled(
                "odom_order", "odometry message not newer than the previous one, or invalid"
            )
            return
        if self._odom_frame is None:
            self._odom_frame = frame
            self._odom_child = msg.child_frame_id
            with self._map_lock:
                if self.mapper.num_voxels and self.mapper.frame_id != self.map_frame:
                    self.get_logger().warning(
                        f"loaded map is in frame {self.mapper.frame_id!r}, odometry in "
                        f"{frame!r}: the map is used as if it were in {self.map_frame!r}"
                    )
                self.mapper.frame_id = self.map_frame
        self._robot_position = position
        with self._cv:
            self._cv.notify_all()

    # --- integration worker ----------------------------------------------------------------

    def _drop_locked(self, reason: str, detail: str) -> None:
        self._counters.dropped[reason] += 1
        self._warn_throttled(
            f"drop_{reason}",
            f"dropped cloud ({reason}): {detail} [{self._counters.dropped[reason]} so far]",
            error=reason in ("malformed", "error"),
        )

    def _drop(self, reason: str, detail: str) -> None:
        with self._cv:
            self._drop_locked(reason, detail)

    def _work(self) -> None:
        """The worker: integrates queued clouds in order and publishes the map clouds when
        the timer asks (between scans, so publishing never waits for the map lock and the
        executor never blocks on it)."""
        current: _Pending | None = None
        while not self._stop.is_set():
            with self._cv:
                while not (
                    current is not None or self._queue or self._publish_due or self._stop.is_set()
                ):
                    self._cv.wait(0.5)
                if self._stop.is_set():
                    return
                publish, self._publish_due = self._publish_due, False
                if current is None and self._queue:
                    current = self._queue.popleft()
            if publish:
                try:
                    self._publish_map_clouds()
                except Exception as err:  # a failed publication must not stop the worker
                    self._warn_throttled("publish", f"publishing the map failed: {err!r}")
            if current is None:
                continue
            try:
                done = self._process(current)
            except Exception as err:  # keep the node alive whatever a message holds
                self._drop("error", f"{type(err).__name__}: {err}")
                done = True
            if done:
                current = None
            else:
                with self._cv:
                    self._cv.wait(0.02)

    def _process(self, item: _Pending) -> bool:
        """Try to integrate one cloud; False when it must wait for odometry."""
        cpu0, wall0 = time.thread_time(), time.perf_counter()
        if item.cloud is None:
            try:
                cloud = parse_pointcloud2(item.msg)
            except CloudFormatError as err:
                self._drop("malformed", str(err))
                return True
            self._count_points(cloud.dropped)
            if len(cloud) == 0:
                self._drop("empty", f"none of its {cloud.points_in} points is valid")
                return True
            item.cloud = cloud
            item.stamp = stamp_seconds(item.msg.header.stamp)
            item.need_until = item.stamp
            if self.cfg.deskew and cloud.time_offset is not None:
                item.need_until += max(float(cloud.time_offset.max()), 0.0)
        with self._pose_lock:
            latest = self.poses.latest_stamp
        if latest is None or latest < item.need_until:
            if time.monotonic() - item.received <= self.cfg.odom_wait:
                self._add_time(cpu0, wall0)
                return False
            if latest is None:
                self._drop("no_poses", f"no odometry within odom_wait {self.cfg.odom_wait} s")
            else:
                self._drop(
                    "too_new",
                    f"stamp {item.need_until:.3f} not covered by odometry (latest "
                    f"{latest:.3f}) within odom_wait {self.cfg.odom_wait} s",
                )
            return True
        extrinsic = self._extrinsic(item.msg.header.frame_id)
        with self._pose_lock:  # de-skew from a copy: odometry keeps arriving meanwhile
            poses = self.poses.snapshot()
        try:
            points, origins = cloud_to_map(
                item.cloud, item.stamp, poses, extrinsic, deskew=self.cfg.deskew
            )
        except PoseUnavailable as err:
            self._drop(err.reason, str(err))
            return True
        points, origins, outside = z_band(
            points, origins, self.cfg.point_cloud_min_z, self.cfg.point_cloud_max_z
        )
        if outside:
            self._count_points({"z_band": outside})
        own_cpu = time.thread_time()
        with self._map_lock:
            summary = self.mapper.integrate(points, origins, item.stamp)
        own_cpu = time.thread_time() - own_cpu
        now = self.get_clock().now().nanoseconds * 1e-9
        latency = now - item.stamp
        with self._cv:
            c = self._counters
            c.clouds_integrated += 1
            c.rays_in += summary.rays_in
            c.rays_used += summary.rays_used
            c.rays_truncated += summary.rays_truncated
            c.points_dropped.update({k: v for k, v in summary.dropped.items() if v})
            c.latency_last = latency
            c.latency_sum += latency
            c.latency_max = max(c.latency_max, latency)
            c.integration_cpu += max(summary.cpu_seconds - own_cpu, 0.0)  # the core's threads
        self._add_time(cpu0, wall0)
        return True

    def _add_time(self, cpu0: float, wall0: float) -> None:
        self._counters.integration_cpu += time.thread_time() - cpu0
        self._counters.integration_wall += time.perf_counter() - wall0

    def _count_points(self, dropped: dict[str, int]) -> None:
        with self._cv:
            self._counters.points_dropped.update({k: v for k, v in dropped.items() if v})

    def _extrinsic(self, cloud_frame: str) -> Extrinsic:
        if cloud_frame and cloud_frame == self._odom_child:
            return self._identity
        if self._tf_buffer is not None:  # pragma: no cover - needs tf2_ros
            target = self.cfg.base_frame_id or self._odom_child or ""
            try:
                tf = self._tf_buffer.lookup_transform(target, cloud_frame, rclpy.time.Time())
            except Exception as err:
                self._warn_throttled("tf", f"TF {target} <- {cloud_frame} unavailable: {err}")
            else:
                t, r = tf.transform.translation, tf.transform.rotation
                return Extrinsic(np.array([t.x, t.y, t.z]), np.array([r.x, r.y, r.z, r.w]))
        return self._param_extrinsic

    # --- outputs ---------------------------------------------------------------------------

    @_tracked
    def _on_publish_timer(self) -> None:
        with self._cv:
            self._publish_due = True
            self._cv.notify_all()

    def _publish_map_clouds(self) -> None:
        want_clouds = (
            self._doo_pub.get_subscription_count() + self._std_pub.get_subscription_count()
        )
        want_grid = self._grid_pub.get_subscription_count()
        if not (want_clouds or want_grid):
            return  # nobody listens: publish when someone does (latched, so they get it)
        if time.monotonic() < self._publish_not_before:
            return  # the last publication was slow: keep publishing under PUBLISH_DUTY
        with self._map_lock:
            version = self.mapper.version
            if version == self._published_version:
                return
            if not (self.cfg.frame_id or self._odom_frame or self.mapper.num_voxels):
                return  # an empty map in a frame not known yet: nothing worth latching
        t0 = time.perf_counter()
        lock_times = [0.0, 0.0]  # waited for, held
        if want_grid:
            self._grid_pub.publish(self._hit_probability_grid(lock_times))
        if want_clouds:
            self._publish_clouds(lock_times)
        self._published_version = version
        dt = time.perf_counter() - t0 - lock_times[0]
        self._publish_not_before = time.monotonic() + dt * (1.0 / PUBLISH_DUTY - 1.0)
        c = self._counters
        c.publish_seconds += dt
        c.publish_locked_seconds += lock_times[1]
        c.publish_count += 1
        c.publish_last_seconds = dt

    @contextlib.contextmanager
    def _timed_map_lock(self, times: list[float] | None) -> Iterator[None]:
        """The map lock; adds the seconds waited for it and held to ``times`` (if given)."""
        t0 = time.perf_counter()
        with self._map_lock:
            t1 = time.perf_counter()
            try:
                yield
            finally:
                if times is not None:
                    times[0] += t1 - t0
                    times[1] += time.perf_counter() - t1

    def _publish_clouds(self, lock_times: list[float]) -> None:
        """Publish the degree-of-occupancy and std clouds of the filtered voxels."""
        with self._timed_map_lock(lock_times):
            robot = self._robot_position
            radius = self.cfg.publish_radius
            window = None
            if radius > 0.0 and robot is not None:
                window = (np.asarray(robot) - radius, np.asarray(robot) + radius)
            vox = self.mapper.voxels(
                min_doo=self.cfg.min_degree_of_occupancy,
                min_evidence=self.cfg.min_evidence,
                bounds=window,
            )
            stamp = self.mapper.last_stamp
        sel = vox
        if window is not None and robot is not None:
            sel = vox.select(np.sum((vox.centers - robot) ** 2, axis=1) <= radius**2)
        xyz = {a: sel.centers[:, k] for k, a in enumerate("xyz")}
        header_stamp = _stamp_msg(stamp) if stamp is not None else self.get_clock().now().to_msg()
        frame = self.map_frame
        doo_msg = cloud_msg(
            pack_cloud({**xyz, "degree_of_occupancy": sel.most_likely_doo}), frame, header_stamp
        )
        std_msg = cloud_msg(pack_cloud({**xyz, "std": sel.std}), frame, header_stamp)
        self._doo_pub.publish(doo_msg)
        self._std_pub.publish(std_msg)
        self._counters.published_voxels = len(sel)

    @_tracked
    def _on_query(self, msg: PointCloud2) -> None:
        frame = msg.header.frame_id
        if frame and frame != self.map_frame:
            self._warn_throttled(
                "query_frame",
                f"hit_probability query in frame {frame!r}, expected the map frame "
                f"{self.map_frame!r}: not answered",
                error=True,
            )
            return
        try:
            points = read_xyz(msg)
        except CloudFormatError as err:
            self._warn_throttled("query_bad", f"malformed hit_probability query: {err}", error=True)
            return
        with self._map_lock:
            stats = self.mapper.query(points)
        self._counters.queries += 1
        columns = {
            "x": points[:, 0],
            "y": points[:, 1],
            "z": points[:, 2],
            "hit_probability": stats.hit_probability,
            "degree_of_occupancy": stats.most_likely_doo,
            "std": stats.std,
            "mean_free_path": stats.mean_free_path,
            "observed": stats.observed.astype(np.float32),
        }
        self._result_pub.publish(cloud_msg(pack_cloud(columns), frame, msg.header.stamp))

    @_tracked
    def _on_get_map(self, request: GetMap.Request, response: GetMap.Response) -> GetMap.Response:
        response.map = self._hit_probability_grid()
        self._counters.maps_served += 1
        return response

    def _hit_probability_grid(self, lock_times: list[float] | None = None) -> OccupancyGrid:
        """The 2D hit-probability grid of the height band (``~/hit_probability_map``,
        ``~/projected_map``); ``lock_times`` as in ``_timed_map_lock``."""
        cfg = self.cfg
        zmin = cfg.occupancy_min_z
        radius = cfg.hit_probability_map_radius
        robot = self._robot_position
        center = (float(robot[0]), float(robot[1])) if robot is not None and radius > 0 else None
        with self._timed_map_lock(lock_times):
            grid = self.mapper.hit_probability_grid(
                zmin, cfg.occupancy_max_z, center=center, radius=radius
            )
            res = self.mapper.resolution
            stamp = self.mapper.last_stamp
        out = OccupancyGrid()
        out.header.frame_id = self.map_frame
        out.header.stamp = (
            _stamp_msg(stamp) if stamp is not None else self.get_clock().now().to_msg()
        )
        out.info.map_load_time = self.get_clock().now().to_msg()
        out.info.resolution = float(res)
        out.info.width = grid.width
        out.info.height = grid.height
        out.info.origin.position.x = grid.origin[0]
        out.info.origin.position.y = grid.origin[1]
        out.info.origin.position.z = float(zmin)
        out.info.origin.orientation.w = 1.0
        out.data = array.array("b", grid.data.tobytes())
        return out

    async def _on_save(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        """Save in a background thread: writing a large map takes seconds, and meanwhile
        the executor keeps taking odometry and clouds (this call resumes when it is done)."""
        done = rclpy.task.Future()

        def save() -> None:
            try:
                done.set_result(self.save_map())
            except Exception as err:  # an unexpected failure answers the call, never kills spin
                self.get_logger().error(f"saving the map failed: {err!r}")
                done.set_result((False, f"saving failed: {err!r}"))
            finally:
                self._end_work()
                self._wake.trigger()

        if not self._begin_work():  # close() waits for the save thread, not for this call
            response.success, response.message = False, "node is shutting down"
            return response
        threading.Thread(target=save, name="mfp_save_map", daemon=True).start()
        response.success, response.message = await done
        return response

    def save_map(self) -> tuple[bool, str]:
        """Write the map to ``map_path`` (one save at a time); returns (success, message)."""
        path = self.cfg.map_path
        if not path:
            return False, "parameter map_path is empty: nowhere to save"
        try:
            with self._save_lock:
                with self._map_lock:  # snapshot only: compressing and writing run unlocked
                    self.mapper.frame_id = self.map_frame
                    arrays = map_arrays(self.mapper)
                write_map_arrays(path, arrays)
            count = len(arrays["s"])
        except (OSError, ValueError, MapFileError) as err:
            self.get_logger().error(f"saving the map to {path!r} failed: {err}")
            return False, f"saving to {path!r} failed: {err}"
        self.get_logger().info(f"saved {count} voxels to {path!r}")
        return True, f"saved {count} voxels to {path}"

    @_tracked
    def _on_reset(self, request: Empty.Request, response: Empty.Response) -> Empty.Response:
        with self._map_lock:
            self.mapper.reset()
        self.get_logger().info("map reset")
        return response

    # --- health ----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Counters and rates since the previous call (also published on ~/status)."""
        now = time.monotonic()
        c = self._counters
        with self._cv:
            t_prev, rays_prev, cpu_prev, wall_prev = self._status_window
            self._status_window = (now, c.rays_used, c.integration_cpu, c.integration_wall)
            queued = len(self._queue)
        # never wait for a long integration: report the last map figures instead
        if self._map_lock.acquire(timeout=0.05):
            try:
                self._map_figures = (
                    self.mapper.num_voxels,
                    self.mapper.memory_bytes,
                    self.mapper.version,
                )
            finally:
                self._map_lock.release()
        voxels, memory, version = self._map_figures
        span = max(now - t_prev, 1e-9)
        n_int = max(c.clouds_integrated, 1)
        return {
            "uptime_s": round(now - self._started, 3),
            "map_frame": self.map_frame,
            "clouds_in": c.clouds_in,
            "clouds_lost": c.clouds_lost,
            "clouds_integrated": c.clouds_integrated,
            "clouds_dropped": dict(c.dropped),
            "points_dropped": dict(c.points_dropped),
            "queued": queued,
            "rays_in": c.rays_in,
            "rays_used": c.rays_used,
            "rays_truncated": c.rays_truncated,
            "rays_per_s": round((c.rays_used - rays_prev) / span, 1),
            "integration_cpu_share": round((c.integration_cpu - cpu_prev) / span, 4),
            "integration_cpu_s": round(c.integration_cpu, 4),
            "integration_wall_s": round(c.integration_wall, 4),
            "latency_last_s": c.latency_last if math.isfinite(c.latency_last) else None,
            "latency_mean_s": c.latency_sum / n_int if c.clouds_integrated else None,
            "latency_max_s": c.latency_max if c.clouds_integrated else None,
            "odom_in": c.odom_in,
            "odom_rejected": dict(c.odom_rejected),
            "voxels": voxels,
            "memory_bytes": memory,
            "map_version": version,
            "publish_count": c.publish_count,
            "publish_last_s": round(c.publish_last_seconds, 5),
            "publish_total_s": round(c.publish_seconds, 4),
            "publish_locked_total_s": round(c.publish_locked_seconds, 4),
            "published_voxels": c.published_voxels,
            "queries": c.queries,
            "maps_served": c.maps_served,
        }

    @_tracked
    def _on_status(self) -> None:
        s = self.status()
        drops = ", ".join(f"{k} {v}" for k, v in sorted(s["clouds_dropped"].items())) or "none"
        self.get_logger().info(
            f"{s['rays_per_s']:.0f} rays/s, {s['clouds_integrated']}/{s['clouds_in']} clouds "
            f"integrated, drops: {drops}, {s['voxels']} voxels, "
            f"{s['memory_bytes'] / 1e6:.1f} MB, integration CPU "
            f"{100 * s['integration_cpu_share']:.0f}%"
        )
        self._status_pub.publish(String(data=json.dumps(s)))

    def _begin_work(self) -> bool:
        """Count work in flight that close() must wait for; False once the node closes."""
        with self._inflight_cv:
            if self._closing:
                return False
            self._inflight += 1
            return True

    def _end_work(self) -> None:
        with self._inflight_cv:
            self._inflight -= 1
            self._inflight_cv.notify_all()

    def close(self) -> None:
        """Stop the worker; save the map when save_on_shutdown (not over an unreadable file)."""
        with self._inflight_cv:
            self._closing = True
            self._inflight_cv.wait_for(lambda: self._inflight == 0, timeout=10.0)
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        self._worker.join(timeout=10.0)
        if self.cfg.save_on_shutdown:
            if self._load_failed:
                self.get_logger().error(
                    "save_on_shutdown: not overwriting the map file that failed to load"
                )
            else:
                self.save_map()
        self.mapper.close()


def usage() -> str:
    """What ``--help`` prints: how to start the node and its parameters with defaults."""
    lines = [
        "usage: ros2 run mfp_mapper mfp_mapper [--ros-args -p NAME:=VALUE ... "
        "--params-file config/mfp_mapper.yaml]",
        "",
        "Degree-of-occupancy mapping node (cloud_in: PointCloud2, odom: Odometry).",
        "Parameters:",
    ]
    for spec in SPECS.values():
        lines.append(f"  {spec.name} (default {spec.default!r}): {spec.description}")
    return "\n".join(lines)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run mfp_mapper mfp_mapper`` and ``python -m mfp_mapper.ros.node``."""
    own_args = rclpy.utilities.remove_ros_args(args if args is not None else sys.argv)[1:]
    if any(a in ("-h", "--help") for a in own_args):
        print(usage())
        return 0
    rclpy.init(args=args)
    node: MfpMapperNode | None = None
    executor: SingleThreadedExecutor | None = None
    code = 0
    try:
        node = MfpMapperNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, rclpy.exceptions.ParameterException) as err:
        print(f"mfp_mapper: invalid parameters: {err}", file=sys.stderr)
        code = 2
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=5.0)  # no callback may run past the context
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
