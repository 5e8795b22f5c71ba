"""The live integration worker, without ROS: queue, odometry, waiting, drops and counters.

The node hands it received clouds (``submit``) and odometry (``add_odometry``) from its
executor thread; one worker thread takes the clouds in order, waits (at most ``odom_wait``
seconds) until the poses cover a cloud, runs it through the scan pipeline and integrates
it: walked into a store of its own without any lock (``Mapper.stage``), then added to the
map in one merge (``Mapper.commit``, a few percent of the scan's time). A reader that needs
whole scans (GetMap, saving) takes ``whole_map()``: it waits at most for a merge, never for
a scan; a query takes ``map_lock`` alone, which the merge lets go between chunks. Between
two scans it calls ``publish`` when ``request_publish`` asked for it, so publishing never
waits for an integration and the executor never waits for the map. Everything is counted
under the pipeline's names (``pipeline.DROP_REASONS``).
"""

from __future__ import annotations

import contextlib
import copy
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.placement import Odometry, Placement, StampGuard, resolve_placement
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.pose_inputs import Log, PoseInputs
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer
from mfp_mapper.sensing.tf_tree import TfTree

if TYPE_CHECKING:
    from mfp_mapper.settings import NodeConfig


MERGE_PAUSE_S = 0.0005
"""How long a merge lets go of the map between two chunks (a waiting reader takes it)."""


@dataclass
class LiveSettings:
    """What the worker reads of the node's settings (replaced whole on a change)."""

    frame_id: str
    deskew: bool
    point_cloud_min_z: float
    point_cloud_max_z: float
    cloud_queue_size: int
    odom_wait: float
    no_return_range: float = 0.0
    """> 0: recover the firings with no return as rays this long (``sensing.no_return``)."""
    base_frame_id: str = ""
    extrinsic_override: Extrinsic | None = None

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
            base_frame_id=cfg.base_frame_id,
            extrinsic_override=cfg.extrinsic_override(),
            no_return_range=cfg.sensor_model_no_return_range,
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


class LiveIntegrator(PoseInputs):
    """Queue and worker thread of the live node (see the module docstring); its pose
    inputs (odometry, TF, the clock) are those of ``PoseInputs``."""

    def __init__(
        self,
        mapper: Mapper,
        settings: LiveSettings,
        poses: PoseBuffer,
        *,
        tree: TfTree | None = None,
        log: Log,
        now: Callable[[], float],
        publish: Callable[[], None] | None = None,
    ) -> None:
        self.mapper = mapper
        self.settings = settings
        self.poses = poses
        self.counters = LiveCounters()
        self.map_lock = threading.Lock()
        self.scan_gate = threading.Lock()  # held through a merge (``whole_map``)
        self.pose_lock = threading.Lock()
        self.odom_frame: str | None = None
        self.odom_child: str | None = None
        self.robot_position: np.ndarray | None = None
        self.tree = tree if tree is not None else TfTree()
        self.tf_map_frame: str | None = None
        self.placement_source = "none yet"
        self._odom_guard = StampGuard(self.tree.max_jump, self.tree.max_future)
        self._last_clock: float | None = None
        self._warned_time_field = False
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

    @property
    def running(self) -> bool:
        """Whether the worker thread is still alive (e.g. walking a long scan)."""
        return self._thread is not None and self._thread.is_alive()

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
            item.cloud, note = pipeline.add_no_return_rays(
                pipeline.parse_scan(item.msg), cfg.no_return_range
            )
            if note and not self.counters.no_return_note:
                self.counters.no_return_note = note
                self._log("no_return", f"no-return rays: {note}", False)
            item.stamp = pipeline.scan_stamp(item.msg)
            item.deadline = pipeline.pose_deadline(item.cloud, item.stamp, cfg.deskew)
            with self._cv:
                self.counters.points_in += item.cloud.points_in
            self._warn_time_field(item.cloud)
        waited = time.monotonic() - item.received
        try:
            placement = self._placement(item.msg.header.frame_id)
        except pipeline.ScanDropped as drop:
            if waited <= cfg.odom_wait:
                return False  # the transforms may still come
            raise pipeline.ScanDropped(
                drop.reason, drop.detail, 0, dict(item.cloud.dropped)
            ) from None
        latest = placement.poses.latest_stamp
        if latest is None or latest < item.deadline:
            if waited <= cfg.odom_wait:
                return False
            parse_drops = dict(item.cloud.dropped)
            if latest is None:
                raise pipeline.ScanDropped(
                    "no_poses",
                    f"no pose ({placement.source}) within odom_wait {cfg.odom_wait} s",
                    0,
                    parse_drops,
                )
            raise pipeline.ScanDropped(
                "too_new",
                f"stamp {item.deadline:.3f} (the cloud's last point, time base "
                f"{item.cloud.time_base or 'none'}) not covered by the poses "
                f"({placement.source}; latest {latest:.3f}) within odom_wait {cfg.odom_wait} s",
                0,
                parse_drops,
            )
        if self.placement_source != placement.source:
            self.placement_source = placement.source
            self._log("placement", f"clouds placed by {placement.source}", False)
        placed = pipeline.place_scan(
            item.cloud, item.stamp, placement.poses, placement.extrinsic, cfg
        )
        own_cpu = time.thread_time()
        mapper = self.mapper
        # the scan is walked into a store of its own without the map lock (services keep
        # reading the map), then added in one merge: readers see whole scans only
        staged = mapper.stage(placed.points, placed.origins, placed.stamp, placed.no_return)
        pipeline.require_rays(staged.summary, placed)
        with self.scan_gate, self.map_lock:
            summary = mapper.commit(staged, pause=self._let_readers_in)
        del staged  # its store's memory goes back now, not at the next scan
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

    def _let_readers_in(self) -> None:
        """Between two chunks of a merge: a reader waiting for ``map_lock`` takes it."""
        self.map_lock.release()
        try:
            time.sleep(MERGE_PAUSE_S)
        finally:
            self.map_lock.acquire()

    @contextlib.contextmanager
    def whole_map(self) -> Iterator[None]:
        """The map lock, at a time no scan is half merged: what a reader that must see
        whole scans (GetMap, saving) or that replaces the map (reset) holds. A merge
        takes a few percent of its scan's integration; ``map_lock`` alone (a query) is
        also free between chunks of a merge."""
        with self.scan_gate, self.map_lock:
            yield

    def _placement(self, cloud_frame: str) -> Placement:
        """Pose source and extrinsic of a cloud, from copies taken under the pose lock (the
        executor keeps adding odometry and TF meanwhile)."""
        cfg = self.settings
        with self.pose_lock:
            tree = self.tree.snapshot()
            odometry = None
            if self.odom_frame is not None and len(self.poses):
                odometry = Odometry(self.odom_frame, self.odom_child or "", self.poses.snapshot())
        placement = resolve_placement(
            cloud_frame, tree, odometry, cfg.frame_id, cfg.base_frame_id, cfg.extrinsic_override
        )
        if odometry is None and self.tf_map_frame is None:
            self.tf_map_frame = placement.map_frame
            self._adopt_map_frame()
        return placement

    def _warn_time_field(self, cloud: ParsedCloud) -> None:
        if cloud.unknown_time_field and self.settings.deskew and not self._warned_time_field:
            self._warned_time_field = True
            self._log(
                "time_field",
                f"clouds have a field {cloud.unknown_time_field!r} that looks like per-point "
                "time but is not one of t, time, time_stamp, timestamp: de-skew is off for "
                "them",
                False,
            )

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
