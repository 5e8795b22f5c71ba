"""The ``mfp_mapper`` ROS 2 node: live mapping from PointCloud2 + Odometry.

ROS wiring only: subscriptions hand clouds and odometry to the ROS-free worker
(``mfp_mapper.mapping.live``: queue, odometry wait, the scan pipeline, drops, counters);
``map_outputs`` publishes the map; ``map_files`` loads it and saves it (``~/save_map``,
the autosave, on shutdown); ``localization`` is the localization mode (map -> odom,
``/initialpose``, ``~/pose``); services query, reset and clear the map. Run it with
``python -m mfp_mapper.node --ros-args ...`` or ``ros2 run mfp_mapper mfp_mapper``;
parameters are in ``mfp_mapper.config.schema``. A lifecycle node: with ``autostart`` (the
default) it configures and activates itself; else a lifecycle manager drives it
(``on_configure``... below).

Threads: the input thread (``ros.input_thread``) takes clouds, odometry and TF and their
events (its callbacks only queue clouds and store poses); one executor thread runs every
other ROS callback (services, timers, queries; rclpy's multi-threaded executor cost about
70% of a core in overhead). The worker threads parse, place and integrate
(``mapping.live``); the map outputs are built and sent on a publishing thread of their own;
``~/save_map`` and the autosave write in a thread of their own. ``worker.map_lock`` guards
the Mapper: the walker holds it through a quick scan (``Mapper.integrate``, at most
``live.DIRECT_MAX_S`` expected) or only to merge a long one it walked without it
(``Mapper.stage``/``commit``), letting queries in between chunks; GetMap, saving and reset
take ``worker.whole_map`` (no scan half merged). So services answer during a long scan.
SIGINT / SIGTERM stop it as ``ros.shutdown`` says: the executor stops between callbacks,
then the final save.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import rclpy
import rclpy.exceptions
import rclpy.logging
import rclpy.task
import rclpy.time
import rclpy.utilities
from diagnostic_msgs.msg import DiagnosticArray
from mfp_mapper_msgs.srv import ClearBbox, QueryMap
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.srv import GetMap
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.service import Service
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Empty
from tf2_msgs.msg import TFMessage

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.param_file import ParamFileError, read_sections
from mfp_mapper.config.schema import SPECS, NodeConfig
from mfp_mapper.core.mapper import Mapper, compile_kernels, mapper_kwargs
from mfp_mapper.mapping.live import LiveIntegrator, LiveSettings, thread_cpu
from mfp_mapper.mapping.live_localization import compile_alignment_kernels
from mfp_mapper.ros.guarded_node import GuardedLifecycleNode, tracked
from mfp_mapper.ros.input_thread import InputThread
from mfp_mapper.ros.localization import Localization
from mfp_mapper.ros.map_files import MapFiles
from mfp_mapper.ros.map_outputs import MapOutputs
from mfp_mapper.ros.messages import cloud_msg
from mfp_mapper.ros.params import declare_parameters, usage
from mfp_mapper.ros.query_service import QueryService
from mfp_mapper.ros.shutdown import SpinUntilSignal
from mfp_mapper.ros.status import (
    StatusWindow,
    diagnostics,
    localization_diagnostic,
    localization_line,
    next_window,
    startup_text,
    status_report,
)
from mfp_mapper.ros.tf_cdr import odometry_from_cdr, tf_records
from mfp_mapper.ros.transport import transport_loss_text
from mfp_mapper.sensing.pointcloud import CloudFormatError, pack_cloud, read_xyz, stamp_seconds
from mfp_mapper.sensing.poses import PoseBuffer
from mfp_mapper.sensing.return_pairs import PAIR_TIMEOUT, ReturnPairer
from mfp_mapper.sensing.tf_tree import TfTree, TransformUnavailable

NODE_NAME = "mfp_mapper"
RESULT_FIELDS = (
    "x", "y", "z", "hit_probability", "degree_of_occupancy", "std", "mean_free_path", "observed"
)  # fmt: skip

"""The fields of a ~/hit_probability/result cloud."""
INFO_KEYS = frozenset({"no_return", "odom_frame"})
"""Keys of the worker's log lines that inform (logged at INFO), not warn."""
FRAME_PARAMETERS = ("base_frame_id", "cloud_frame_id")
"""Frame names of the placement section (with the map's frame_id: tf1's leading slash stripped)."""

CLOCK_GRACE = 3.0
"""Wall seconds after start before a missing /clock (use_sim_time) is reported."""


class StartError(RuntimeError):
    """``autostart``: configuring or activating the node failed (logged)."""


class MfpMapperNode(GuardedLifecycleNode):
    """Mean-free-path mapping node (see the module docstring and README "## The node").

    A lifecycle node (``rclpy.lifecycle``): parameters are declared at construction;
    configure loads the map and creates the outputs and services; activate subscribes and
    starts the integration worker; deactivate stops both; cleanup saves (``save_on_shutdown``)
    and drops the map. With ``autostart`` (the default) it configures and activates itself at
    construction, a plain node as before.
    """

    def __init__(self, stop_requested: Callable[[], bool] | None = None, **kwargs: Any) -> None:
        """``stop_requested``: whether a stop signal came (``ros.shutdown``), so that
        configure stops waiting for the kernels at once."""
        super().__init__(NODE_NAME, **kwargs)
        self._stop_requested = stop_requested or (lambda: False)
        self.cfg: NodeConfig = declare_parameters(self)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._started = time.monotonic()
        self._queries = 0
        self._maps_served = 0
        self.files = MapFiles(self, lambda: self.cfg)
        self.query_service = QueryService(
            self,
            lambda: (self.mapper, self.worker.map_lock),
            lambda points, frame, stamp: self.worker.to_map_frame(points, frame, stamp),
            lambda: self.map_frame or self.mapper.frame_id,
            lambda: self.cfg.query,
        )
        self._transport_explained = False
        self._pairer: ReturnPairer | None = None
        """Pairs the clouds of ``cloud_in`` and ``second_return_topic`` (when set)."""
        self._clock_warned = False
        self._inputs = InputThread(
            self.context, lambda text: self.warn_throttled("inputs", text, error=True)
        )
        """Takes clouds, odometry and TF (``ros.input_thread``), from activate to deactivate."""
        self.worker: LiveIntegrator  # set by configure
        self.localization: Localization | None = None  # localization.enabled
        self.outputs: MapOutputs
        self._configured = False
        self._configured_once = False
        self._entities: list[Any] = []  # what configure creates (cleanup destroys)
        self._active: list[Any] = []  # what activate creates (deactivate destroys)
        self._kernels = "compiling"  # numba's kernels: compiling, ready (or failed)
        if self.cfg.node.autostart:
            steps = (("configure", self.trigger_configure), ("activate", self.trigger_activate))
            for step, trigger in steps:
                if self._stop_requested():
                    break  # stopped while configuring: not mapping, the node closes
                if trigger() != TransitionCallbackReturn.SUCCESS:
                    raise StartError(f"the node could not {step} (see the log above)")

    # --- lifecycle transitions ---------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load the map (``map_path``), create the worker, the outputs and the services."""
        try:
            self._configure()
        except Exception as err:  # rclpy would turn it into ERROR without a word
            self.get_logger().error(f"configure failed: {type(err).__name__}: {err}")
            self._release(save=False)
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def _configure(self) -> None:
        self._kernels = "compiling"
        compiling = threading.Thread(target=self._compile_kernels, name="mfp_compile", daemon=True)
        compiling.start()  # meanwhile the map loads
        self._map_figures = (0, 0, 0)
        self._status_window = StatusWindow(time.monotonic())
        self._last_window = self._status_window
        mapper = self.files.load()
        self._warn_slashes()
        self.localization = (
            Localization(self, lambda: self.cfg, mapper, self._now)
            if self.cfg.localization.enabled
            else None
        )
        self.worker = LiveIntegrator(
            mapper,
            LiveSettings.of(self.cfg),
            PoseBuffer(
                max_age=self.cfg.placement.odom_buffer, max_gap=self.cfg.placement.odom_max_gap
            ),
            tree=TfTree(buffer_length=self.cfg.placement.tf_buffer),
            log=self._worker_log,
            info=self.get_logger().info,
            now=self._now,
            map_frame=self.cfg.map.frame_id or (mapper.frame_id if mapper.num_voxels else ""),
            correction=None if self.localization is None else self.localization.correction,
        )
        if self.localization is not None:
            self.localization.start(self.worker)
        self.files.keep(self.worker)
        self.outputs = MapOutputs(self, self.worker, lambda: self.cfg.outputs, self.warn_throttled)
        self.worker.set_publish(self.outputs.publish)
        self._entities += self.outputs.publishers
        self._configured = self._configured_once = True
        self.reopen()
        self._create_services()
        self._wait_for_kernels(compiling)
        self.get_logger().info(
            startup_text(self.cfg, self.resolve_topic_name, self.mapper, self.map_frame)
        )

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Subscribe to clouds, odometry and TF; start integrating and publishing."""
        self._create_interfaces()
        self.worker.start()
        self.outputs.invalidate()  # latch the map again for whoever subscribed meanwhile
        if not self.cfg.node.autostart:
            self.get_logger().info("active: mapping")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop taking clouds (the map, its services and queries stay)."""
        self._inputs.stop()
        self._destroy(self._active)
        self.worker.stop()
        self.get_logger().info("inactive: not mapping (services answer)")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Save (``save_on_shutdown``), then drop the map, the outputs and the services."""
        self._release(save=True)
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """From any state: stop mapping, save (``save_on_shutdown``) and release the map."""
        self._release(save=True)
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition failed: release everything, back to unconfigured (nothing saved)."""
        self._release(save=False)
        return TransitionCallbackReturn.SUCCESS

    def _release(self, save: bool) -> None:
        """Undo configure (and activate): stop, wait for jobs, save when asked, release."""
        self._inputs.stop()
        self._destroy(self._active)
        if self._configured:
            # a scan being walked is not waited for: it is not in the map yet, and the map
            # saved holds whole scans; callbacks in flight get a short grace
            self.wait_idle(timeout=2.0)
            self.worker.stop(timeout=0.5)
            if save:
                self.files.save_on_shutdown()
            if not self.worker.running:
                self.mapper.close()
            self._configured = False
        self._destroy(self._entities)

    def _destroy(self, entities: list[Any]) -> None:
        for entity in entities:
            if isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            elif isinstance(entity, Service):
                self.destroy_service(entity)
            elif isinstance(entity, Timer):
                self.destroy_timer(entity)
            elif isinstance(entity, Publisher):
                self.destroy_publisher(entity)
        entities.clear()

    def _create_services(self) -> None:
        """What configure creates: status and map outputs, queries and services (answered
        while inactive too)."""
        status_qos = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self._status_pub = self.create_publisher(String, "~/status", status_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._result_pub = self.create_publisher(PointCloud2, "~/hit_probability/result", 10)
        self._entities += [self._status_pub, self._diag_pub, self._result_pub]
        if self.localization is not None:
            self._entities += self.localization.create_publishers()
        # what needs the map runs in a thread of its own and is awaited (a coroutine), so the
        # executor keeps taking odometry and clouds while a long scan holds the map; their
        # own group: a pending call must not hold the default group
        group = ReentrantCallbackGroup()
        self._entities += [
            self.create_subscription(
                PointCloud2, "~/hit_probability/query", self._on_query, 10, callback_group=group
            ),
            self.create_service(
                GetMap, "~/hit_probability_map", self._on_get_map, callback_group=group
            ),
            self.files.create_service(group),
            self.create_service(Empty, "~/reset", self._on_reset, callback_group=group),
            self.create_service(
                ClearBbox, "~/clear_bbox", self._on_clear_bbox, callback_group=group
            ),
            self.create_service(QueryMap, "~/query", self._on_query_map, callback_group=group),
        ]

    def _create_interfaces(self) -> None:
        """What activate creates: the inputs (taken on the input thread) and the timers."""
        group = self._inputs.group  # the executor never runs these: the input thread does
        streams = [
            self.create_subscription(
                PointCloud2,
                "cloud_in",
                self._on_cloud,
                qos_profile_sensor_data,
                callback_group=group,
                event_callbacks=SubscriptionEventCallbacks(message_lost=self._on_clouds_lost),
            )
        ]
        second_topic = self.cfg.placement.second_return_topic
        self._pairer = ReturnPairer() if second_topic else None
        if second_topic:
            streams.append(
                self.create_subscription(
                    PointCloud2,
                    second_topic,
                    self._on_second_return,
                    qos_profile_sensor_data,
                    callback_group=group,
                    event_callbacks=SubscriptionEventCallbacks(message_lost=self._on_clouds_lost),
                )
            )
        odom_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.BEST_EFFORT
        )
        # raw: read from the CDR bytes (ros.tf_cdr), not as rclpy's Python objects
        streams.append(
            self.create_subscription(
                Odometry, "odom", self._on_odom, odom_qos, raw=True, callback_group=group
            )
        )
        tf_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE
        )
        tf_static_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=100,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        # raw: read from the CDR bytes (ros.tf_cdr), not as rclpy's Python objects (a flood)
        streams += [
            self.create_subscription(
                TFMessage, "/tf", self._on_tf, tf_qos, raw=True, callback_group=group
            ),
            self.create_subscription(
                TFMessage,
                "/tf_static",
                self._on_tf_static,
                tf_static_qos,
                raw=True,
                callback_group=group,
            ),
        ]
        self._active += streams
        # the pairer is used on the input thread only: its timeout is ticked there
        pair_tick = (self._on_pair_timer, PAIR_TIMEOUT / 4.0) if second_topic else None
        self._inputs.start(streams, *(pair_tick or ()))
        # wall-clock timers: with use_sim_time and no /clock the ROS clock stands still,
        # and the map, ~/status and /diagnostics must still go out
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        if self.cfg.outputs.publish_rate > 0.0:
            self._active.append(
                self.create_timer(
                    1.0 / self.cfg.outputs.publish_rate, self._on_publish_timer, clock=wall
                )
            )
        if self.cfg.node.status_period > 0.0:
            self._active.append(
                self.create_timer(self.cfg.node.status_period, self._on_status, clock=wall)
            )
        self._clock_warned = False
        self._active.append(self.create_timer(1.0, self._check_clock, clock=wall))
        if self.localization is not None:
            self._active += self.localization.create_inputs(wall)
        self._active += self.files.create_timer(wall)

    # --- set-up ----------------------------------------------------------------------------

    @property
    def mapper(self) -> Mapper:
        return self.worker.mapper

    @property
    def map_frame(self) -> str:
        """The run's map frame ("" until decided at the first cloud placed)."""
        return self.worker.map_frame

    def _warn_slashes(self) -> None:
        frames = (self.cfg.map, "frame_id"), *((self.cfg.placement, n) for n in FRAME_PARAMETERS)
        for section, name in frames:
            value = getattr(section, name)
            if value.startswith("/"):
                self.get_logger().warning(
                    f"parameter {name} {value!r} has a leading slash: using "
                    f"{frame_name(value)!r} (tf2 and RViz reject such frame names)"
                )
        cfg = self.cfg
        self.cfg = replace(
            cfg,
            map=replace(cfg.map, frame_id=frame_name(cfg.map.frame_id)),
            placement=replace(
                cfg.placement,
                base_frame_id=frame_name(cfg.placement.base_frame_id),
                cloud_frame_id=frame_name(cfg.placement.cloud_frame_id),
            ),
        )

    def _compile_kernels(self) -> None:
        """Compile (or load from numba's cache) the kernels a scan and a publication run,
        on a throwaway map of the node's settings (``core.mapper.compile_kernels``), and with
        localization enabled the alignment's (``compile_alignment_kernels``): with a cold
        cache that takes tens of seconds, and clouds taken meanwhile waited for it (a cold
        start dropped the first clouds; the first alignment took 2.4 s, not 0.2).
        ``~/status`` ``kernels``: ``ready``."""
        try:
            cfg = self.cfg
            seconds = compile_kernels(
                cfg.map.resolution, **mapper_kwargs(cfg.map, cfg.sensor_model)
            )
            if cfg.localization.enabled:
                seconds += compile_alignment_kernels(cfg.localization, cfg.map.resolution)
        except Exception as err:  # the first scan compiles them then
            self._kernels = "failed"
            self.get_logger().error(f"compiling the kernels ahead failed: {err!r}")
            return
        self._kernels = "ready"
        self.get_logger().info(f"kernels ready in {seconds:.1f} s (before taking clouds)")

    def _wait_for_kernels(self, compiling: threading.Thread) -> None:
        """The end of configure: the kernels are compiled before activate takes clouds, as
        a lifecycle node does its heavy setup (a cold numba cache: tens of seconds, said in
        the log). A stop signal meanwhile ends the wait at once (the node then closes)."""
        announce_at = time.monotonic() + 2.0  # a warm cache takes a fraction of a second
        announced = False
        while compiling.is_alive():
            if self._stop_requested() or not rclpy.ok(context=self.context):
                self.get_logger().info("stopping: not waiting for the kernels")
                return
            compiling.join(timeout=0.1)
            if compiling.is_alive() and not announced and time.monotonic() > announce_at:
                self.get_logger().info(
                    "compiling the kernels before taking clouds (numba's cache is cold: "
                    "up to a minute)"
                )
                announced = True

    @tracked
    def _check_clock(self) -> None:
        """One clear line when use_sim_time is true and /clock never came (a bag played
        without --clock); one more when it comes."""
        sim = self.get_parameter("use_sim_time").value
        if not sim or time.monotonic() - self._started < CLOCK_GRACE:
            return
        stopped = self.get_clock().now().nanoseconds == 0
        if stopped and not self._clock_warned:
            self._clock_warned = True
            self.get_logger().error(
                f"use_sim_time is true and /clock has not been received in {CLOCK_GRACE:g} s: "
                "stamps cannot be checked and clouds wait for a clock that stands still "
                "(play the bag with --clock, or set use_sim_time false)"
            )
        elif not stopped and self._clock_warned:
            self._clock_warned = False
            self.get_logger().info("/clock received: simulated time runs")

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
        if self._configured:
            self.worker.settings = LiveSettings.of(new)  # the next scan uses it
            if self.localization is not None:
                self.localization.reconfigure(new)
            self.outputs.invalidate()  # republish with the new filter
        return SetParametersResult(successful=True)

    def _now(self) -> float:
        return float(self.get_clock().now().nanoseconds) * 1e-9

    def _worker_log(self, key: str, text: str, error: bool) -> None:
        """The worker's throttled lines: informational ones at INFO."""
        if key in INFO_KEYS and not error:
            self.info_throttled(key, text)
        else:
            self.warn_throttled(key, text, error)

    # --- inputs ----------------------------------------------------------------------------

    @tracked
    def _on_cloud(self, msg: PointCloud2) -> None:
        self.worker.observe_clock(self._now())
        pairer = self._pairer
        for ready in [msg] if pairer is None else pairer.first(msg):
            self.worker.submit(ready)

    @tracked
    def _on_pair_timer(self) -> None:
        """First-return clouds whose second never came are mapped alone."""
        pairer = self._pairer
        if pairer is not None:
            for ready in pairer.expired():
                self.worker.submit(ready)

    @tracked
    def _on_second_return(self, msg: PointCloud2) -> None:
        """A cloud of second returns (``second_return_topic``): mapped with its first."""
        pairer = self._pairer
        if pairer is not None:
            for ready in pairer.second(msg):
                self.worker.submit(ready)

    @tracked
    def _on_tf(self, data: bytes) -> None:
        self.worker.observe_clock(self._now())
        self.worker.add_transforms(tf_records(data), static=False)

    @tracked
    def _on_tf_static(self, data: bytes) -> None:
        self.worker.add_transforms(tf_records(data), static=True)

    def _on_clouds_lost(self, info: Any) -> None:
        """The middleware reports clouds that never reached this node (transport losses,
        told apart from the node's own backlog, which drops queued clouds as queue_full)."""
        total = self.worker.clouds_lost(info.total_count_change)
        if not self._transport_explained:  # the first time: the whole story, once
            self._transport_explained = True
            queue = (self.worker.queued, self.cfg.placement.cloud_queue_size)
            self.warn_throttled("clouds_lost", transport_loss_text(info.total_count_change, queue))
            return
        self.warn_throttled(
            "clouds_lost",
            f"{info.total_count_change} cloud(s) lost in transport before reaching the node "
            f"[clouds_lost_transport {total}]",
        )

    @tracked
    def _on_odom(self, data: bytes) -> None:
        self.worker.observe_clock(self._now())
        self.worker.add_odometry(odometry_from_cdr(data))

    @tracked
    def _on_publish_timer(self) -> None:
        """Ask for a publication, once the kernels are loaded: a publication that compiled
        them would hold the map lock meanwhile (seconds)."""
        if self._kernels != "compiling":
            self.worker.request_publish()

    # --- queries and services ----------------------------------------------------------------

    @tracked
    async def _on_query(self, msg: PointCloud2) -> None:
        frame = msg.header.frame_id
        try:
            points = read_xyz(msg)
        except CloudFormatError as err:
            self.warn_throttled("query_bad", f"malformed hit_probability query: {err}", error=True)
            self._answer_nothing(msg)
            return
        try:
            in_map = self.worker.to_map_frame(points, frame, stamp_seconds(msg.header.stamp))
        except TransformUnavailable as err:
            self.warn_throttled(
                "query_frame",
                f"hit_probability query in frame {frame!r}, not the map frame "
                f"{self.map_frame!r}, and TF cannot transform it ({err}): answered with no point",
                error=True,
            )
            self._answer_nothing(msg)
            return

        def query() -> Any:
            with self.worker.map_lock:
                return self.mapper.query(in_map)

        try:
            stats = await self.off_executor(query)
        except Exception:
            self._answer_nothing(msg)  # an answer, never silence; the error is logged
            raise
        self._queries += 1
        unseen = ~stats.observed  # unknown: NaN, never the prior's numbers (they look free)
        columns = {
            "x": points[:, 0],
            "y": points[:, 1],
            "z": points[:, 2],
            "hit_probability": np.where(unseen, np.nan, stats.hit_probability),
            "degree_of_occupancy": np.where(unseen, np.nan, stats.most_likely_doo),
            "std": np.where(unseen, np.nan, stats.std),
            "mean_free_path": np.where(unseen, np.nan, stats.mean_free_path),
            "observed": stats.observed.astype(np.float32),
        }
        self._result_pub.publish(cloud_msg(pack_cloud(columns), frame, msg.header.stamp))

    def _answer_nothing(self, query: PointCloud2) -> None:
        empty = pack_cloud({name: np.zeros(0, np.float32) for name in RESULT_FIELDS})
        self._result_pub.publish(cloud_msg(empty, query.header.frame_id, query.header.stamp))

    @tracked
    async def _on_get_map(
        self, request: GetMap.Request, response: GetMap.Response
    ) -> GetMap.Response:
        try:
            response.map = await self.off_executor(self.outputs.grid)
        except Exception:
            response.map = OccupancyGrid()  # an empty map, in the map frame: never silence
            response.map.header.frame_id = self.map_frame or self.mapper.frame_id
            response.map.header.stamp = self.get_clock().now().to_msg()
            raise
        self._maps_served += 1
        return response

    @tracked
    async def _on_reset(self, request: Empty.Request, response: Empty.Response) -> Empty.Response:
        def reset() -> None:
            with self.worker.whole_map:
                self.mapper.reset()

        await self.off_executor(reset)
        self._map_changed()
        self.get_logger().info("map reset")
        return response

    @tracked
    async def _on_query_map(
        self, request: QueryMap.Request, response: QueryMap.Response
    ) -> QueryMap.Response:
        """``~/query``: points and segments (``ros.query_service``)."""
        return await self.query_service.on_request(request, response)

    @tracked
    async def _on_clear_bbox(
        self, request: ClearBbox.Request, response: ClearBbox.Response
    ) -> ClearBbox.Response:
        """Reset the voxels in the box to unknown (octomap_server's ``~/clear_bbox``)."""
        corners = [(p.x, p.y, p.z) for p in (request.min, request.max)]

        def clear() -> int:
            with self.worker.whole_map:  # never between two chunks of a merge
                return self.mapper.clear_box(*corners)

        try:
            response.cleared = await self.off_executor(clear)
        except ValueError as err:  # NaN corners: an answer, never a traceback
            response.success, response.message = False, f"not cleared: {err}"
            return response
        response.success = True
        self._map_changed()
        response.message = (
            f"reset {response.cleared} voxels between {corners[0]} and {corners[1]} to unknown"
        )
        self.get_logger().info(f"clear_bbox: {response.message}")
        return response

    def _map_changed(self) -> None:
        """After a reset or a cleared box: the localization's field is rebuilt."""
        if self.localization is not None:
            self.localization.map_changed()

    # --- health ----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Counters and rates since the previous call (also published on ~/status)."""
        c, queued = self.worker.snapshot()
        # never wait for a long integration: report the last map figures instead
        if self.worker.map_lock.acquire(timeout=0.05):
            try:
                m = self.mapper
                self._map_figures = (m.num_voxels, m.memory_bytes, m.version)
            finally:
                self.worker.map_lock.release()
        extra = {
            "uptime_s": round(time.monotonic() - self._started, 3),
            **self.worker.describe_poses(),
            "sim_time_without_clock": self._clock_warned,
            "kernels": self._kernels,
            "queries": self._queries,
            "query_service": {
                "answered": self.query_service.answered,
                "refused": self.query_service.refused,
            },
            "maps_served": self._maps_served,
            # CPU seconds so far: the process, this (executor) thread, the input thread, the
            # worker's threads
            "cpu_s": {
                "process": round(time.process_time(), 4),
                "executor": round(time.thread_time(), 4),
                **{
                    k: round(v, 4)
                    for k, v in (
                        thread_cpu({"inputs": self._inputs.ident}) | self.worker.thread_cpu()
                    ).items()
                },
            },
        }
        if self.localization is not None:
            extra["localization"] = self.localization.report()
        pairer = self._pairer
        if pairer is not None:
            extra["second_return"] = pairer.counts()
        report = status_report(
            c, queued, self._map_figures, self.outputs.counters, self._status_window, extra
        )
        self._last_window, self._status_window = self._status_window, next_window(c)
        return report

    @tracked
    def _on_status(self) -> None:
        s = self.status()
        drops = ", ".join(f"{k} {v}" for k, v in sorted(s["clouds_dropped"].items())) or "none"
        self.get_logger().info(
            f"{s['rays_per_s']:.0f} rays/s, {s['clouds_integrated']}/{s['clouds_in']} clouds "
            f"integrated, drops: {drops}, {s['voxels']} voxels, "
            f"{s['memory_bytes'] / 1e6:.1f} MB, integration CPU "
            f"{100 * s['integration_cpu_share']:.0f}%{localization_line(s)}"
        )
        self._status_pub.publish(String(data=json.dumps(s)))
        name = f"{self.get_name()}: mapping"
        stamp = self.get_clock().now().to_msg()
        diag = diagnostics(s, self._last_window, name, self.get_name(), stamp)
        if "localization" in s:
            diag.status.append(
                localization_diagnostic(
                    s["localization"], f"{self.get_name()}: localization", self.get_name()
                )
            )
        self._diag_pub.publish(diag)

    @property
    def worker_running(self) -> bool:
        """Whether the integration thread is still alive (a long scan being walked)."""
        return self._configured_once and self.worker.running

    def close(self) -> None:
        """Stop the worker; save the map when save_on_shutdown (never over a map_path that
        failed to load: beside it, ``recovery_path``)."""
        self._release(save=True)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run mfp_mapper mfp_mapper`` and ``python -m mfp_mapper.ros.node``."""
    # rcl parses the ROS arguments (a --params-file) before the node exists: a broken file
    # gives one line, no traceback
    try:
        own_args = rclpy.utilities.remove_ros_args(args if args is not None else sys.argv)[1:]
        if any(a in ("-h", "--help") for a in own_args):
            print(usage())
            return 0
        # rclpy's handlers would shut the context down under a running executor: ros.shutdown
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:
        print(f"mfp_mapper: {ros_args_problem(args, err)}", file=sys.stderr)
        return 2
    node: MfpMapperNode | None = None
    executor: SingleThreadedExecutor | None = None
    code = 0
    logger = rclpy.logging.get_logger(NODE_NAME)
    # the handler stays until the process ends: a signal after the save is ignored (exit 0)
    with SpinUntilSignal(logger.info, keep_after_exit=True) as stopper:
        try:
            node = MfpMapperNode(stop_requested=stopper.stop.is_set)
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            stopper.spin(executor)
            stopper.answer_calls(executor, node)  # ~/save_map callers get their answer
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except (ValueError, rclpy.exceptions.ParameterException) as err:
            print(f"mfp_mapper: invalid parameters: {err}", file=sys.stderr)
            code = 2
        except StartError as err:
            print(f"mfp_mapper: {err}", file=sys.stderr)
            code = 1
        finally:
            if executor is not None:
                executor.shutdown(timeout_sec=5.0)  # no callback may run past the context
            if node is not None:
                node.close()
                node.destroy_node()
            rclpy.try_shutdown()
    if node is not None and node.worker_running:
        # a scan still being walked (not in the map, which is saved): do not wait for it
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def ros_args_problem(args: list[str] | None, err: Exception) -> str:
    """What rclpy.init rejected, on one line: a ``--params-file`` that is not a ROS 2
    parameter file says where (line, column), else rcl's first line."""
    argv = list(args if args is not None else sys.argv)
    for flag, path in zip(argv, argv[1:], strict=False):
        if flag == "--params-file":
            try:
                read_sections(path)
            except ParamFileError as problem:
                return f"--params-file {path}: {problem}"
    first = str(err).splitlines()[0] if str(err) else type(err).__name__
    return f"invalid ROS arguments: {first}"


if __name__ == "__main__":
    sys.exit(main())
