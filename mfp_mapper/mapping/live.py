"""The live integration worker, without ROS: queue, waiting, drops and counters.

The node hands it received clouds (``submit``) from its executor thread, and odometry and
transforms to its pose inputs (``worker.pose_inputs``, a ``PoseInputs``). Two threads run
the scan pipeline, in order: the worker parses and places each cloud, then hands it to the
walker, which integrates it while the worker prepares the next one (the walk releases the
GIL; the worker stays at most one placed scan ahead; in localization mode the worker aligns
and integrates each scan itself, a wide search running in the background meanwhile: the
worker keeps taking clouds, keeps the newest for after the search and drops the older ones
``superseded``, never ``queue_full`` for the search's sake). A scan expected to take at most
``DIRECT_MAX_S`` (its rays times the recent CPU seconds per ray: a busy machine that slows
every scan down must not switch to the slower staged path) is integrated straight into the
map under ``whole_map`` (``Mapper.integrate``); a longer one is walked into a store of its
own without any lock (``Mapper.stage``), then added to the map in one merge
(``Mapper.commit``) that lets queries in between chunks. Staging costs a second pass over
every block the scan touched: 2.1x the direct integration for a VLP-32C scan at 0.1 m, which
touches ~147k blocks, nearly the whole map (docs/performance.md). A reader that needs whole
scans (GetMap, saving, reset) takes ``whole_map``; a query takes ``map_lock`` alone: either
waits at most ``DIRECT_MAX_S``, or for a merge, never for a long scan. A cloud its poses do
not cover yet waits (at most ``odom_wait`` seconds) in a list of its own while the clouds
behind it go on: **no head-of-line blocking**, and when the queue is full the oldest
*waiting* cloud is dropped before any placeable one. A thread of its own calls ``publish``
(given to the constructor or ``set_publish``) when ``request_publish`` asked for it, so a
cloud never waits for a publication and the executor never waits for the map. Everything is
counted under the pipeline's names (``pipeline.DROP_REASONS``).
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.sections import PlacementSection, SensorModelSection
from mfp_mapper.core.mapper import IntegrationSummary, Mapper
from mfp_mapper.mapping import loop
from mfp_mapper.mapping.live_localization import pose_matrix
from mfp_mapper.mapping.loop import PreparedScan, ScanCounts, ScanLoop
from mfp_mapper.mapping.pose_correction import NoCorrection, PoseCorrection
from mfp_mapper.mapping.whole_map import MERGE_PAUSE_S, WholeMap
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.pipeline import PlacedScan
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.pose_inputs import Log, PoseCounters, PoseInputs
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer
from mfp_mapper.sensing.tf_tree import TfTree, TransformRecord

if TYPE_CHECKING:
    from mfp_mapper.config.schema import NodeConfig, XyzRpy

STAGES = ("queued", "parse", "place", "handoff", "walk", "merge")
"""The stages of an integrated cloud timed in ``LiveCounters.stage_seconds``: waiting in the
queue (and for poses), parse (with no-return rays), placement (poses, de-skew, band), placed
and waiting for the walker (busy with the scan before), the walk (``Mapper.integrate``
into the map, or ``Mapper.stage`` into a store of its own), then the wait for the map lock
and, for a staged scan, the merge into the map (``Mapper.commit``)."""

RETRY_PERIOD = 0.02
"""Seconds between two tries of a waiting cloud (sooner when new poses arrived)."""
DIRECT_MAX_S = 0.5
"""A scan expected to integrate within this many CPU seconds goes straight into the map
under the map lock (queries wait for it); a longer one is staged and merged (see the module
docstring)."""


@dataclass(frozen=True)
class LiveSettings:
    """The sections the worker reads, replaced whole on a change (a scan sees one of them)."""

    placement: PlacementSection = field(default_factory=PlacementSection)
    sensor_model: SensorModelSection | None = None
    """None: the Mapper's own ray length, unchanged, and no no-return rays."""

    @classmethod
    def of(cls, cfg: NodeConfig) -> LiveSettings:
        """What the worker reads of the node's parameters."""
        return cls(cfg.placement, cfg.sensor_model)

    @functools.cached_property
    def extrinsic_override(self) -> Extrinsic | None:
        """The ``lidar.*`` mounting when set (it overrides /tf_static), made once per change."""
        return _extrinsic(self.placement.lidar_override())


@dataclass
class _Pending:
    """A received cloud on its way to the map."""

    received: float  # time.monotonic()
    msg: Any
    prepared: PreparedScan | None = None
    tried: int = -1  # the pose generation of the last try (-1: never tried)
    next_try: float = 0.0  # time.monotonic()
    parse_s: float = 0.0  # wall seconds of its parse
    started: float = 0.0  # time.monotonic() when the worker first took it


@dataclass
class _Placed:
    """A cloud placed by the worker, on its way to the walker."""

    item: _Pending
    placed: PlacedScan
    placing: float  # time.monotonic() when its placement began
    placed_at: float  # and ended (localization: and aligned)
    robot_pose: Callable[[float], np.ndarray | None] | None = None


@dataclass
class LiveCounters(ScanCounts, PoseCounters):
    """The pipeline's counts, the pose inputs' and what only a live stream has."""

    clouds_lost_transport: int = 0  # reported lost by the middleware (never received)
    clouds_localized: int = 0  # localization with a frozen map: placed, aligned, not integrated
    integration_cpu: float = 0.0  # CPU seconds: parse + place + integrate (+ core threads)
    integration_wall: float = 0.0
    latency_sum: float = 0.0
    latency_max: float = 0.0
    latency_last: float = float("nan")
    received_latency_sum: float = 0.0  # cloud received -> integrated (s)
    received_latency_max: float = 0.0
    map_wait_max: float = 0.0  # the longest wait of a scan for the map lock (s)
    stage_seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    """Wall seconds of the integrated clouds by stage (``STAGES``), summed."""


class LiveIntegrator:
    """Queue and worker thread of the live node (see the module docstring); its pose
    inputs (odometry, TF, the clock, the map frame) are ``self.pose_inputs``."""

    def __init__(
        self,
        mapper: Mapper,
        settings: LiveSettings,
        poses: PoseBuffer,
        *,
        tree: TfTree | None = None,
        log: Log,
        now: Callable[[], float],
        info: Callable[[str], None] | None = None,
        publish: Callable[[], None] | None = None,
        map_frame: str = "",
        correction: PoseCorrection | None = None,
    ) -> None:
        """``map_frame``: the run's map frame when known at start (``frame_id``, a loaded
        map's frame); empty: decided at the first cloud placed (``PoseInputs``).
        ``correction``: how placed clouds reach the map frame (``mapping.pose_correction``;
        default ``NoCorrection``, mapping: placed in the map frame)."""
        self.mapper = mapper
        self.correction: PoseCorrection = correction or NoCorrection()
        map_frame = self.correction.placement_frame(map_frame)
        self.settings = settings
        self.counters = LiveCounters()
        self.map_lock = threading.Lock()
        self.whole_map = WholeMap(threading.Lock(), self.map_lock)
        self.pose_inputs = PoseInputs(
            poses,
            tree if tree is not None else TfTree(),
            self.counters,
            frame_id=map_frame,
            log=log,
            info=info or (lambda text: log("info", text, False)),
            now=now,
            frame_role=(
                "map frame"
                if self.correction.names_map
                else "frame the clouds are placed in (then localized into the map frame)"
            ),
        )
        if self.pose_inputs.map_frame is not None and self.correction.names_map:
            mapper.frame_id = self.pose_inputs.map_frame
        self._warned: set[str] = set()
        self._log = log
        self._now = now
        self._publish = publish
        self._cv = threading.Condition()
        self._queue: deque[_Pending] = deque()
        self._waiting: list[_Pending] = []
        self._publish_due = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._walker: threading.Thread | None = None
        self._publisher: threading.Thread | None = None
        self._seconds_per_ray = 0.0  # CPU seconds a ray of the last scans took (0: none yet)
        self._handoff: _Placed | None = None  # placed, waiting for the walker (under _cv)
        self._searching: _Placed | None = None  # its wide search runs in the background
        self._held: _Placed | None = None  # the newest cloud placed meanwhile (under _cv)
        self._prepare_at = 0.0  # time.monotonic() from which the worker takes the next cloud
        self._walk_s = 0.0  # moving averages (s): a scan's walk + merge, its parse + place
        self._prepare_s = 0.0
        self.loop = ScanLoop(
            mapper,
            settings.placement,
            settings.sensor_model or SensorModelSection(),
            counts=self.counters,
            counts_lock=self._cv,
            consume=self._consume,
        )

    def _consume(self, mapper: Mapper, placed: PlacedScan) -> IntegrationSummary:
        """A placed scan into the map: directly under ``whole_map`` when expected within
        ``DIRECT_MAX_S``, else staged and merged (module docstring)."""
        rays = len(placed.points)
        if 0.0 < self._seconds_per_ray * rays <= DIRECT_MAX_S:
            with self._map_for_scan():
                summary = loop.integrate_scan(mapper, placed)
            cpu = summary.cpu_seconds
        else:
            summary = loop.merge_scan(mapper, placed, self._map_for_scan(), self._let_readers_in)
            # the estimate is of a direct integration: the staged walk alone (at least as
            # long), not the merge that only staging pays, else a scan once staged kept the
            # next ones staged (norlab at 0.1 m: ~600 ms CPU a scan staged, ~250 direct)
            walked = 1.0 - summary.commit_seconds / summary.seconds if summary.seconds else 1.0
            cpu = summary.cpu_seconds * walked
        if rays:  # down at once (the first scans load kernels and fault memory in)
            per_ray, mean = cpu / rays, self._seconds_per_ray
            self._seconds_per_ray = per_ray if per_ray < mean else _average(mean, per_ray)
        return summary

    @contextlib.contextmanager
    def _map_for_scan(self) -> Iterator[None]:
        """``whole_map`` for a scan, counting the longest wait for it (``map_wait_max``:
        what a publication or a service holding the map cost the integration)."""
        asked = time.perf_counter()
        with self.whole_map:
            waited = time.perf_counter() - asked
            with self._cv:
                self.counters.map_wait_max = max(self.counters.map_wait_max, waited)
            yield

    def _let_readers_in(self) -> None:
        """Between two chunks of a merge: a reader waiting for ``map_lock`` takes it."""
        self.map_lock.release()
        try:
            time.sleep(MERGE_PAUSE_S)
        finally:
            self.map_lock.acquire()

    @property
    def running(self) -> bool:
        """Whether the worker, walker or publishing thread is still alive (e.g. walking a
        long scan)."""
        threads = (self._thread, self._walker, self._publisher)
        return any(t is not None and t.is_alive() for t in threads)

    def set_publish(self, publish: Callable[[], None] | None) -> None:
        """What the publishing thread calls after ``request_publish``."""
        self._publish = publish

    @property
    def map_frame(self) -> str:
        """The run's map frame ("" until decided; the global frame when localizing)."""
        return self.correction.map_frame(self.pose_inputs.map_frame or "")

    def describe_poses(self) -> dict[str, Any]:
        """What ``~/status`` says of the poses (``PoseInputs.describe``) with the run's map
        frame; when localizing, the frame clouds are placed in as ``placement_frame``."""
        out = self.pose_inputs.describe()
        placed_in = out["map_frame"]
        out["map_frame"] = self.map_frame or None
        if not self.correction.names_map:
            out["placement_frame"] = placed_in
        return out

    @property
    def robot_position(self) -> Any:
        return self.correction.position(self.pose_inputs.robot_position)

    def to_map_frame(self, points: np.ndarray, frame: str, stamp: float) -> np.ndarray:
        """Points given in ``frame`` in the map frame (``PoseInputs.to_map_frame``; when
        localizing: through the odometry frame and the correction); raises
        TransformUnavailable."""
        return self.correction.to_map_frame(
            points, frame, lambda p, f: self.pose_inputs.to_map_frame(p, f, stamp)
        )

    # --- inputs (any thread) ----------------------------------------------------------------

    def submit(self, msg: Any) -> None:
        """Queue a received cloud; when the queue is full the oldest waiting cloud (one its
        poses do not cover yet) is dropped, else the oldest."""
        item = _Pending(time.monotonic(), msg)
        with self._cv:
            self.counters.clouds_in += 1
            if len(self._queue) + len(self._waiting) >= self.settings.placement.cloud_queue_size:
                if self._waiting:
                    self._waiting.pop(0)
                    detail = "the oldest cloud still waiting for its poses was dropped"
                else:
                    self._queue.popleft()
                    detail = "integration is behind; dropped the oldest cloud"
                self._drop_locked("queue_full", detail)
            self._queue.append(item)
            self._cv.notify_all()

    def add_odometry(self, sample: Any) -> bool:
        """``poses.add_odometry``, then wake the worker."""
        ok = self.pose_inputs.add_odometry(sample)
        self._wake()
        return ok

    def add_transforms(self, records: Sequence[TransformRecord], static: bool) -> int:
        """``pose_inputs.add_transforms`` (one message's transforms), then wake the worker."""
        kept = self.pose_inputs.add_transforms(records, static)
        self._wake()
        return kept

    def observe_clock(self, now: float) -> bool:
        """Note the node clock; on a jump back (bag loop) clear poses, TF and the queue."""
        jump = self.pose_inputs.observe_clock(now)
        if jump is None:
            return False
        with self._cv:
            dropped = len(self._queue) + len(self._waiting)
            self._queue.clear()
            self._waiting.clear()
            for _ in range(dropped):
                self.counters.drop("clock_jump")
        self.correction.clock_jumped(now)
        self._log(
            "clock_jump",
            f"clock jumped back {jump:.3f} s (to {now:.3f}): pose and TF buffers "
            f"cleared, {dropped} queued cloud(s) dropped; the map is kept",
            False,
        )
        return True

    def _wake(self) -> None:
        with self._cv:
            self._cv.notify_all()

    def clouds_lost(self, count: int) -> int:
        """Count clouds the middleware lost; returns the total."""
        with self._cv:
            self.counters.clouds_lost_transport += count
            return self.counters.clouds_lost_transport

    @property
    def queued(self) -> int:
        """Clouds received and not integrated or dropped yet (but the one being walked)."""
        with self._cv:
            return self._queued_locked()

    def _queued_locked(self) -> int:
        pending = (self._handoff, self._searching, self._held)
        return len(self._queue) + len(self._waiting) + sum(job is not None for job in pending)

    def thread_cpu(self) -> dict[str, float]:
        """CPU seconds so far of the worker (parse, place), walker (integrate) and publishing
        threads, those running (``~/status`` ``cpu_s``; ``thread_cpu``)."""
        threads = {"worker": self._thread, "walker": self._walker, "publisher": self._publisher}
        return thread_cpu(
            {k: t.ident if t is not None and t.is_alive() else None for k, t in threads.items()}
        )

    def request_publish(self) -> None:
        """Ask the publishing thread to publish (at once unless it is still publishing)."""
        with self._cv:
            self._publish_due = True
            self._cv.notify_all()

    # --- the worker thread ------------------------------------------------------------------

    def start(self) -> None:
        """Start the worker thread (again after ``stop``: a lifecycle node reactivated)."""
        self._stop.clear()
        self._prepare_at = 0.0
        self._thread = threading.Thread(target=self.run, name="mfp_integration", daemon=True)
        self._walker = threading.Thread(target=self._walk, name="mfp_walk", daemon=True)
        self._publisher = threading.Thread(
            target=self._publish_loop, name="mfp_publish", daemon=True
        )
        self._thread.start()
        self._walker.start()
        self._publisher.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        end = time.monotonic() + timeout
        for thread in (self._thread, self._walker, self._publisher):
            if thread is not None:
                thread.join(timeout=max(end - time.monotonic(), 0.0))
        with self._cv:
            self._queue.clear()  # stale when the worker starts again
            self._handoff = None

    def _next(self) -> _Pending | None:
        """The next cloud to try (under ``_cv``): a new one first, else a waiting one that
        is due (new poses since its last try, or ``RETRY_PERIOD`` passed); none while the
        walker has a placed scan still to take, nor before ``_prepare_at``: the next cloud
        is parsed and placed so as to be ready when the walker is, not earlier (a scan
        placed early would wait for the walk, and a later pick may be a newer cloud)."""
        if self._handoff is not None or time.monotonic() < self._prepare_at:
            return None
        if self._queue:
            return self._queue.popleft()
        now, generation = time.monotonic(), self.pose_inputs.generation
        for i, item in enumerate(self._waiting):
            if item.next_try <= now and (
                item.tried != generation or now - item.received > self.settings.placement.odom_wait
            ):
                return self._waiting.pop(i)
        return None

    def run(self) -> None:
        """Integrate clouds in order, a waiting one not blocking those behind it."""
        while not self._stop.is_set():
            with self._cv:
                item = self._next()
                while item is None and not (self._stop.is_set() or self._search_ended()):
                    wait = RETRY_PERIOD if self._waiting else 0.5
                    if self._queue and self._handoff is None:  # the walker is busy
                        wait = min(wait, max(self._prepare_at - time.monotonic(), 0.001))
                    self._cv.wait(wait)
                    item = self._next()
                if self._stop.is_set():
                    return
                ended = self._search_ended()
            if ended:
                self._after_search()
            if item is not None:
                self._try(item)

    def _publish_loop(self) -> None:
        """The publishing thread: ``publish`` whenever ``request_publish`` asked for it
        (requests made meanwhile become one)."""
        while True:
            with self._cv:
                while not (self._publish_due or self._stop.is_set()):
                    self._cv.wait(0.5)
                if self._stop.is_set():
                    return
                self._publish_due = False
            if self._publish is not None:
                try:
                    self._publish()
                except Exception as err:  # a failed publication must not stop the thread
                    self._log("publish", f"publishing the map failed: {err!r}", False)

    def _try(self, item: _Pending) -> None:
        generation = self.pose_inputs.generation
        try:
            done = self.process(item)
        except Exception as err:  # keep the node alive whatever a message holds
            self._drop("error", f"{type(err).__name__}: {err}")
            done = True
        if not done:
            item.tried, item.next_try = generation, time.monotonic() + RETRY_PERIOD
            with self._cv:
                self._waiting.append(item)

    def drain(self, timeout: float = 10.0) -> None:
        """Process every queued and waiting cloud on the calling thread (what ``run`` does;
        for tests and tools that do not start the thread)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._cv:
                item = self._next()
                ended = self._search_ended()
                if item is None and not (self._waiting or self._searching or ended):
                    return
            if ended:
                self._after_search()
            if item is not None:
                self._try(item)
            elif not ended:
                time.sleep(0.005)

    def process(self, item: _Pending) -> bool:
        """Try to integrate one cloud; False when it must wait for poses."""
        cpu0, wall0 = time.thread_time(), time.perf_counter()
        try:
            return self._process(item)
        except pipeline.ScanDropped as drop:
            self._log_drop(drop.reason, drop.detail, self.loop.count_drop(drop))
            return True
        finally:
            with self._cv:  # the walker adds its own
                self.counters.integration_cpu += time.thread_time() - cpu0
                self.counters.integration_wall += time.perf_counter() - wall0

    def _process(self, item: _Pending) -> bool:
        settings = self.settings
        cfg = settings.placement
        self.loop.placement = cfg  # parameters changed at run time reach the pipeline
        self.loop.sensor_model = settings.sensor_model or SensorModelSection()
        if item.prepared is None:
            item.started = time.monotonic()
            item.prepared = self.loop.prepare(item.msg)
            item.parse_s = time.monotonic() - item.started
            if self.counters.no_return_note:
                self._warn_once("no_return", f"no-return rays: {self.counters.no_return_note}")
            self._warn_time_field(item.prepared.cloud)
            self._check_stamp(item.prepared)
        prepared = item.prepared
        parse_drops = dict(prepared.cloud.dropped)
        frame = self._cloud_frame(prepared.frame_id, parse_drops)
        waited = time.monotonic() - item.received
        try:
            placement = self.pose_inputs.placement(
                frame, frame_name(cfg.base_frame_id), settings.extrinsic_override
            )
        except pipeline.ScanDropped as drop:
            if waited <= cfg.odom_wait and drop.reason != "tf_conflict":
                return False  # the transforms may still come
            raise pipeline.ScanDropped(drop.reason, drop.detail, 0, parse_drops) from None
        latest = placement.poses.latest_stamp
        if latest is None or latest < prepared.deadline:
            if waited <= cfg.odom_wait:
                return False
            if latest is None:
                raise pipeline.ScanDropped(
                    "no_poses",
                    f"no pose ({placement.source}) within odom_wait {cfg.odom_wait} s",
                    0,
                    parse_drops,
                )
            lost = self.counters.clouds_lost_transport
            starved = (
                f"; {lost} cloud(s) were lost in transport: DDS may starve /tf and odometry "
                "too (the large-data profile, README 'Large clouds over DDS')"
                if lost
                else ""
            )
            raise pipeline.ScanDropped(
                "too_new",
                f"stamp {prepared.deadline:.3f} (the cloud's last point, time base "
                f"{prepared.cloud.time_base or 'none'}) not covered by the poses "
                f"({placement.source}; latest {latest:.3f}) within odom_wait {cfg.odom_wait} s"
                f"{starved}",
                0,
                parse_drops,
            )
        if self.mapper.frame_id != placement.map_frame and self.correction.names_map:
            self.mapper.frame_id = placement.map_frame  # the run's frame, decided once
        t_place = time.monotonic()
        placed = self.loop.place(prepared, placement.poses, placement.extrinsic)
        self.pose_inputs.note_robot(placement, prepared.stamp, frame_name(cfg.base_frame_id))
        job = _Placed(item, placed, t_place, time.monotonic(), _robot_pose(placement))
        if self.correction.aligns:
            self._localize(job)
        elif self._walker is not None and self._walker.is_alive():
            self._hand_over(job)
        else:
            self._integrate(job)  # drain(): all on the calling thread
        return True

    # --- localization: a wide search never holds the clouds up -------------------------------

    def _localize(self, job: _Placed) -> None:
        """Align a placed scan and integrate it, on this thread. A wide search runs in the
        background while the worker thread runs (not under ``drain``): the clouds placed
        meanwhile are not aligned against a correction about to change; the newest one is
        kept for after the search, an older one kept is dropped ``superseded``."""
        with self._cv:
            if self._searching is not None:
                stale, self._held = self._held, job
                if stale is not None:
                    self._drop_locked(
                        "superseded",
                        "placed while the localization's wide search ran, and a newer cloud "
                        "came: the newest is aligned after the search",
                    )
                return
        background = self._thread is not None and self._thread.is_alive()
        assert job.robot_pose is not None
        corrected = self.correction.correct(
            job.placed, job.robot_pose, self._wake if background else None
        )
        if corrected is None:
            with self._cv:
                self._searching = job
            return
        job.placed, job.placed_at = corrected, time.monotonic()
        self._integrate(job)

    def _search_ended(self) -> bool:
        """(under ``_cv``) A background search ended and its cloud waits to be taken."""
        return self._searching is not None and not self.correction.searching

    def _after_search(self) -> None:
        """The searched cloud into the map at the correction found, then the newest cloud
        placed during the search aligned (by tracking once localized: the wide search again
        else)."""
        with self._cv:
            job, self._searching = self._searching, None
            held, self._held = self._held, None
        if job is not None:
            self._guarded(self._integrate_searched, job)
        if held is not None:
            self._guarded(self._localize, held)

    def _integrate_searched(self, job: _Placed) -> None:
        corrected = self.correction.finished()
        if corrected is None:  # not expected: the search always leaves its cloud
            raise RuntimeError("the wide search ended without its cloud")
        job.placed, job.placed_at = corrected, time.monotonic()
        self._integrate(job)

    def _guarded(self, step: Callable[[_Placed], None], job: _Placed) -> float:
        """``step(job)`` counted as ``process`` counts a cloud: a drop or an error is
        counted, never raised. Returns the wall seconds it took."""
        cpu0, wall0 = time.thread_time(), time.perf_counter()
        try:
            step(job)
        except pipeline.ScanDropped as drop:
            self._log_drop(drop.reason, drop.detail, self.loop.count_drop(drop))
        except Exception as err:  # keep the node alive whatever a message holds
            self._drop("error", f"{type(err).__name__}: {err}")
        finally:
            with self._cv:
                self.counters.integration_cpu += time.thread_time() - cpu0
                self.counters.integration_wall += time.perf_counter() - wall0
        return time.perf_counter() - wall0

    # --- the walker thread: the placed scans into the map, in order --------------------------

    def _hand_over(self, job: _Placed) -> None:
        """Give a placed scan to the walker; waits while it still holds the previous one (so
        the worker prepares at most one scan ahead of the walk)."""
        with self._cv:
            while self._handoff is not None and not self._stop.is_set():
                self._cv.wait(0.5)
            if not self._stop.is_set():
                self._handoff = job
                self._cv.notify_all()

    def _walk(self) -> None:
        """The walker thread: integrates the scans the worker placed, one after the other,
        while the worker parses and places the next (the walk releases the GIL)."""
        while True:
            with self._cv:
                while self._handoff is None and not self._stop.is_set():
                    self._cv.wait(0.5)
                job = self._handoff
                if job is None or self._stop.is_set():
                    return
                self._handoff = None
                self._prepare_at = time.monotonic() + self._walk_s - self._prepare_s
                self._cv.notify_all()
            wall = self._guarded(self._integrate, job)
            with self._cv:
                self._walk_s = _average(self._walk_s, wall)
                self._prepare_s = _average(
                    self._prepare_s, job.placed_at - job.placing + job.item.parse_s
                )
                self._prepare_at = 0.0
                self._cv.notify_all()

    def _integrate(self, job: _Placed) -> None:
        """A placed scan into the map (``ScanLoop.commit``), with its latency and timing."""
        sensor_model = self.settings.sensor_model
        t_commit = time.monotonic()
        own_cpu = time.thread_time()
        max_range = None if sensor_model is None else sensor_model.core("max_range")
        if max_range is not None and self.mapper.max_range != max_range:
            with self.map_lock:  # sensor_model.max_range changed at run time
                self.mapper.max_range = max_range
        summary = None  # None: localized against a frozen map, not integrated
        if self.correction.integrates:
            summary = self.loop.commit(job.placed)
            self.correction.map_grew(self.mapper, self.whole_map)
        done = time.monotonic()
        own_cpu = time.thread_time() - own_cpu
        latency = self._now() - job.placed.stamp
        item = job.item
        with self._cv:
            c = self.counters
            c.latency_last = latency
            c.latency_sum += latency
            c.latency_max = max(c.latency_max, latency)
            c.received_latency_sum += done - item.received
            c.received_latency_max = max(c.received_latency_max, done - item.received)
            times = c.stage_seconds
            times["queued"] += job.placing - item.received - item.parse_s
            times["parse"] += item.parse_s
            times["place"] += job.placed_at - job.placing
            times["handoff"] += t_commit - job.placed_at
            if summary is None:
                c.clouds_localized += 1
            else:  # the core's threads
                walk = summary.seconds - summary.commit_seconds
                times["walk"] += walk
                times["merge"] += done - t_commit - walk
                c.integration_cpu += max(summary.cpu_seconds - own_cpu, 0.0)

    def _check_stamp(self, prepared: PreparedScan) -> None:
        """A cloud stamped further ahead of the node clock than a pose may be is dropped
        at once (it would only wait: ``ahead_of_clock``)."""
        now = self._now()
        limit = self.pose_inputs.tree.max_future
        if now > 0.0 and prepared.stamp > now + limit:
            raise pipeline.ScanDropped(
                "ahead_of_clock",
                f"stamp {prepared.stamp:.3f} is {prepared.stamp - now:.1f} s ahead of the node "
                "clock "
                f"({now:.3f}; at most {limit:g} s allowed): check the sensor's clock or "
                "use_sim_time",
                0,
                dict(prepared.cloud.dropped),
            )

    def _cloud_frame(self, frame: str, parse_drops: dict[str, int]) -> str:
        """The cloud's frame: tf1's leading slash stripped (warned once); an empty one is
        ``cloud_frame_id`` or a drop (``no_frame``)."""
        if frame.startswith("/"):
            self._warn_once(
                "cloud_slash",
                f"cloud frame_id {frame!r} has a leading slash: read as {frame_name(frame)!r} "
                "(tf2 rejects such names; fix the driver)",
            )
            frame = frame_name(frame)
        if frame:
            return frame
        cloud_frame_id = frame_name(self.settings.placement.cloud_frame_id)
        if cloud_frame_id:
            return cloud_frame_id
        raise pipeline.ScanDropped(
            "no_frame",
            "the cloud's header.frame_id is empty: set the parameter cloud_frame_id to the "
            "frame such clouds are in (e.g. the lidar frame)",
            0,
            parse_drops,
        )

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self._log(key, text, False)

    def _warn_time_field(self, cloud: ParsedCloud) -> None:
        if cloud.unknown_time_field and self.settings.placement.deskew:
            self._warn_once(
                "time_field",
                f"clouds have a field {cloud.unknown_time_field!r} that looks like per-point "
                "time but is not one of t, time, time_stamp, timestamp: de-skew is off for "
                "them",
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
            return copy.deepcopy(self.counters), self._queued_locked()


def thread_cpu(idents: dict[str, int | None]) -> dict[str, float]:
    """CPU seconds so far of the named running threads (``threading`` idents; None: not
    running, left out); empty where the system has no per-thread CPU clock."""
    out = {}
    for name, ident in idents.items():
        if ident is None:
            continue
        try:
            out[name] = time.clock_gettime(time.pthread_getcpuclockid(ident))
        except (AttributeError, OSError):  # not Linux, or the thread just ended
            continue
    return out


def _average(mean: float, value: float) -> float:
    """A moving average (the last few values weigh most; the first one is taken whole)."""
    return value if mean == 0.0 else 0.8 * mean + 0.2 * value


def _robot_pose(placement: Any) -> Callable[[float], np.ndarray | None]:
    """The robot's pose (4x4, placement frame) at a stamp, None where not covered."""

    def pose(stamp: float) -> np.ndarray | None:
        if not placement.source_moves:
            return None
        try:
            t, r = placement.poses.interpolate([stamp])
        except Exception:  # PoseUnavailable, or a stamp outside the poses
            return None
        return pose_matrix(t[0], r[0])

    return pose


def finite_or_none(value: float) -> float | None:
    """JSON-friendly: None for NaN/Inf."""
    return value if math.isfinite(value) else None


def _extrinsic(mounting: XyzRpy | None) -> Extrinsic | None:
    """The configured ``lidar.*`` mounting as an ``Extrinsic`` (None when not set)."""
    return None if mounting is None else Extrinsic.from_xyz_rpy(*mounting)
