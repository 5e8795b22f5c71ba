"""The live integration worker, without ROS: queue, odometry, waiting, drops and counters.

The node hands it received clouds (``submit``) and odometry (``add_odometry``) from its
executor thread; one worker thread takes the clouds in order, waits (at most ``odom_wait``
seconds) until the poses cover a cloud, runs it through the scan pipeline and integrates
it under ``map_lock``. Between two scans it calls ``publish`` when ``request_publish``
asked for it, so publishing never waits for an integration and the executor never waits
for the map. Everything is counted under the pipeline's names (``pipeline.DROP_REASONS``).
"""

from __future__ import annotations

import copy
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.poses import Extrinsic, OdometrySample, PoseBuffer

if TYPE_CHECKING:
    from mfp_mapper.settings import NodeConfig

Log = Callable[[str, str, bool], None]
"""``log(key, text, error)``: a throttled warning (or error) keyed by ``key``."""


@dataclass
class LiveSettings:
    """What the worker reads of the node's settings (replaced whole on a change)."""

    frame_id: str
    deskew: bool
    point_cloud_min_z: float
    point_cloud_max_z: float
    cloud_queue_size: int
    odom_wait: float

    @classmethod
    def of(cls, cfg: NodeConfig) -> LiveSettings:
        """What the worker reads of the node's parameters."""
        return cls(
            frame_id=cfg.frame_id,
            deskew=cfg.deskew,
            point_cloud_min_z=cfg.point_cloud_min_z,
            point_cloud_max_z=cfg.point_cloud_max_z,
            cloud_queue_size=cfg.cloud_queue_size,
            odom_wait=cfg.odom_wait,
        )


@dataclass
class _Pending:
    """A received cloud on its way to the map."""

    received: float  # time.monotonic()
    msg: Any
    cloud: ParsedCloud | None = None
    stamp: float = 0.0
    deadline: float = 0.0  # latest time a pose is needed for


@dataclass
class LiveCounters(pipeline.ScanCounts):
    """The pipeline's counts plus what only a live stream has."""

    clouds_lost: int = 0  # reported lost by the middleware (never received)
    odom_in: int = 0
    odom_rejected: Counter[str] = field(default_factory=Counter)
    integration_cpu: float = 0.0  # CPU seconds: parse + place + integrate (+ core threads)
    integration_wall: float = 0.0
    latency_sum: float = 0.0
    latency_max: float = 0.0
    latency_last: float = float("nan")


class LiveIntegrator:
    """Queue, pose buffer and worker thread of the live node (see the module docstring)."""

    def __init__(
        self,
        mapper: Mapper,
        settings: LiveSettings,
        poses: PoseBuffer,
        *,
        extrinsic_for: Callable[[str], Extrinsic],
        log: Log,
        now: Callable[[], float],
        publish: Callable[[], None] | None = None,
    ) -> None:
        self.mapper = mapper
        self.settings = settings
        self.poses = poses
        self.counters = LiveCounters()
        self.map_lock = threading.Lock()
        self.pose_lock = threading.Lock()
        self.odom_frame: str | None = None
        self.odom_child: str | None = None
        self.robot_position: np.ndarray | None = None
        self._extrinsic_for = extrinsic_for
        self._log = log
        self._now = now
        self._publish = publish
        self._cv = threading.Condition()
        self._queue: deque[_Pending] = deque()
        self._publish_due = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- inputs (any thread) ----------------------------------------------------------------

    def submit(self, msg: Any) -> None:
        """Queue a received cloud; when the queue is full the oldest is dropped."""
        item = _Pending(time.monotonic(), msg)
        with self._cv:
            self.counters.clouds_in += 1
            if len(self._queue) >= self.settings.cloud_queue_size:
                self._queue.popleft()
                self._drop_locked("queue_full", "integration is behind; dropped the oldest cloud")
            self._queue.append(item)
            self._cv.notify_all()

    def clouds_lost(self, count: int) -> int:
        """Count clouds the middleware lost; returns the total."""
        with self._cv:
            self.counters.clouds_lost += count
            return self.counters.clouds_lost

    def add_odometry(self, sample: OdometrySample) -> bool:
        """Store one odometry pose; False (counted, logged) when it is rejected."""
        frame = sample.frame_id
        wanted = self.settings.frame_id
        if wanted and frame and frame != wanted:
            self.counters.odom_rejected["frame"] += 1
            self._log(
                "odom_frame",
                f"odometry is in frame {frame!r} but frame_id is {wanted!r}: ignored "
                "(the map frame must be the odometry frame)",
                True,
            )
            return False
        if self.odom_frame is not None and frame != self.odom_frame:
            self.counters.odom_rejected["frame"] += 1
            self._log(
                "odom_frame_change",
                f"odometry frame changed from {self.odom_frame!r} to {frame!r}: ignored",
                True,
            )
            return False
        with self.pose_lock:
            ok = self.poses.add(sample.stamp, sample.position, sample.quaternion)
        self.counters.odom_in += 1
        if not ok:
            self.counters.odom_rejected["out_of_order_or_invalid"] += 1
            self._log(
                "odom_order", "odometry message not newer than the previous one, or invalid", False
            )
            return False
        if self.odom_frame is None:
            self.odom_frame, self.odom_child = frame, sample.child_frame_id
            # no map lock here: this runs on the executor, which must never wait for a scan
            # (a str attribute is replaced atomically; the voxel count only words a warning)
            if self.mapper.num_voxels and self.mapper.frame_id != self.map_frame:
                self._log(
                    "map_frame",
                    f"loaded map is in frame {self.mapper.frame_id!r}, odometry in "
                    f"{frame!r}: the map is used as if it were in {self.map_frame!r}",
                    False,
                )
            self.mapper.frame_id = self.map_frame
        self.robot_position = np.asarray(sample.position, dtype=np.float64)
        with self._cv:
            self._cv.notify_all()
        return True

    @property
    def map_frame(self) -> str:
        return self.settings.frame_id or self.odom_frame or self.mapper.frame_id

    @property
    def queued(self) -> int:
        with self._cv:
            return len(self._queue)

    def request_publish(self) -> None:
        """Ask the worker to publish between two scans."""
        with self._cv:
            self._publish_due = True
            self._cv.notify_all()

    # --- the worker thread ------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="mfp_integration", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def run(self) -> None:
        """Integrate queued clouds in order; publish between scans when asked."""
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
            if publish and self._publish is not None:
                try:
                    self._publish()
                except Exception as err:  # a failed publication must not stop the worker
                    self._log("publish", f"publishing the map failed: {err!r}", False)
            if current is None:
                continue
            try:
                done = self.process(current)
            except Exception as err:  # keep the node alive whatever a message holds
                self._drop("error", f"{type(err).__name__}: {err}")
                done = True
            if done:
                current = None
            else:
                with self._cv:
                    self._cv.wait(0.02)

    def process(self, item: _Pending) -> bool:
        """Try to integrate one cloud; False when it must wait for poses."""
        cpu0, wall0 = time.thread_time(), time.perf_counter()
        try:
            return self._process(item)
        except pipeline.ScanDropped as drop:
            with self._cv:
                count = self.counters.dropped_scan(drop)
                self._log_drop(drop.reason, drop.detail, count)
            return True
        finally:
            self.counters.integration_cpu += time.thread_time() - cpu0
            self.counters.integration_wall += time.perf_counter() - wall0

    def _process(self, item: _Pending) -> bool:
        cfg = self.settings
        if item.cloud is None:
            item.cloud = pipeline.parse_scan(item.msg)
            item.stamp = pipeline.scan_stamp(item.msg)
            item.deadline = pipeline.pose_deadline(item.cloud, item.stamp, cfg.deskew)
            with self._cv:
                self.counters.points_in += item.cloud.points_in
        with self.pose_lock:
            latest = self.poses.latest_stamp
        if latest is None or latest < item.deadline:
            if time.monotonic() - item.received <= cfg.odom_wait:
                return False
            parse_drops = dict(item.cloud.dropped)
            if latest is None:
                raise pipeline.ScanDropped(
                    "no_poses", f"no odometry within odom_wait {cfg.odom_wait} s", 0, parse_drops
                )
            raise pipeline.ScanDropped(
                "too_new",
                f"stamp {item.deadline:.3f} not covered by odometry (latest {latest:.3f}) "
                f"within odom_wait {cfg.odom_wait} s",
                0,
                parse_drops,
            )
        extrinsic = self._extrinsic_for(item.msg.header.frame_id)
        with self.pose_lock:  # de-skew from a copy: odometry keeps arriving meanwhile
            poses = self.poses.snapshot()
        placed = pipeline.place_scan(item.cloud, item.stamp, poses, extrinsic, cfg)
        own_cpu = time.thread_time()
        with self.map_lock:
            summary = pipeline.integrate_scan(self.mapper, placed)
        own_cpu = time.thread_time() - own_cpu
        latency = self._now() - item.stamp
        with self._cv:
            c = self.counters
            c.add(placed, summary)
            c.latency_last = latency
            c.latency_sum += latency
            c.latency_max = max(c.latency_max, latency)
            c.integration_cpu += max(summary.cpu_seconds - own_cpu, 0.0)  # the core's threads
        return True

    def _drop_locked(self, reason: str, detail: str) -> None:
        self._log_drop(reason, detail, self.counters.drop(reason))

    def _log_drop(self, reason: str, detail: str, count: int) -> None:
        self._log(
            f"drop_{reason}",
            f"dropped cloud ({reason}): {detail} [{count} so far]",
            reason in ("malformed", "error", "no_extrinsic"),
        )

    def _drop(self, reason: str, detail: str) -> None:
        with self._cv:
            self._drop_locked(reason, detail)

    def snapshot(self) -> tuple[LiveCounters, int]:
        """A copy of the counters and the queue length, taken together."""
        with self._cv:
            return copy.deepcopy(self.counters), len(self._queue)


def finite_or_none(value: float) -> float | None:
    """JSON-friendly: None for NaN/Inf."""
    return value if math.isfinite(value) else None
