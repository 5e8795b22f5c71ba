"""The node's map outputs: the degree-of-occupancy, std and reflectivity clouds and the
projected grid.

Selected from the Mapper under the map lock, converted and published outside it, on the
live worker's publishing thread (``LiveIntegrator.request_publish``): integration never
waits for a message to be built. The clouds' changed blocks and the grids are read in
slices of about ``MAP_SLICE_S``, the lock let go between them: a large map's first
publication does not stop integration for its whole read. A publication read in slices
holds every scan integrated before its read began, and of the scans integrated during the
read the blocks its later slices reached; its stamp and map version are those at the
start, so the next publication reads again every block those scans changed.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from mfp_mapper.config.sections import OutputsSection
from mfp_mapper.core.gridmap import (
    BandCells,
    GridReading,
    GridTooLarge,
    HitGrid,
    unobserved_hit_probability,
)
from mfp_mapper.mapping.live import LiveIntegrator
from mfp_mapper.mapping.map_cloud import MAX_RESTARTS, CloudChanges, MapCloud, rows_of
from mfp_mapper.ros.messages import cloud_msg, grid_msg, stamp_msg
from mfp_mapper.sensing.pointcloud import pack_cloud

PUBLISH_DUTY = 0.1
"""Largest share of wall time the map outputs may hold the map lock (integration waits for
it), on average: a token bucket (``LockBudget``). Spacing each publication ``dt / DUTY``
after the last instead halved a 1 Hz rate whose publications held the lock 0.106 s (norlab
at 0.1 m: the timer's next tick came 0.05 s too early, the one after was taken)."""
LOCK_BUDGET_MAX_S = 0.5
"""The most map-lock time the bucket saves up while nothing is published."""
MAP_SLICE_S = 0.025
"""The time a slice of the map outputs' reading aims at: the clouds' changed blocks and the
grids are read in slices of blocks sized to take about this long (``SliceSize``), the map
lock let go between them so that a waiting scan is integrated meanwhile. Holds vary about
2x around it with the blocks' contents and the load. The first publication of a 72 M-voxel
map at 0.1 m held the lock 0.57 s in one go (the grid 0.45 s) on an idle machine, seconds
under load (docs/performance.md)."""
SLICE_PAUSE_S = 0.001
"""How long the outputs let go of the map between two slices (a waiting scan takes it: a
lock released and taken again at once would mostly be taken again by the same thread)."""


class SliceSize:
    """Blocks a slice of the map reads, following the time the last full slices took per
    block so that a slice takes about ``MAP_SLICE_S``."""

    FIRST = 16_384
    LEAST = 1_024

    def __init__(self) -> None:
        self.blocks = self.FIRST

    def took(self, seconds: float) -> None:
        """A slice of ``self.blocks`` blocks (not the last of its read) took ``seconds``."""
        if seconds > 0.0:
            wanted = int(self.blocks * MAP_SLICE_S / seconds)
            # at most doubled at a time: one quick slice of empty blocks is no promise
            self.blocks = max(self.LEAST, min(wanted, 2 * self.blocks))


class LockBudget:
    """The map-lock time the outputs may still hold: it grows by ``duty`` a second of wall
    time, up to ``most`` seconds, and each publication spends what it held; a publication
    may start while it is not negative. Over any long stretch the outputs then hold the lock
    at most ``duty`` of the time (plus ``most``), and after a publication that held it
    ``dt`` seconds the next waits ``dt / duty`` seconds less what was saved up."""

    def __init__(self, duty: float = PUBLISH_DUTY, most: float = LOCK_BUDGET_MAX_S) -> None:
        self._duty, self._most = duty, most
        self._seconds = 0.0
        self._at = time.monotonic()

    def allows(self, now: float | None = None) -> bool:
        """Whether a publication may start now."""
        now = time.monotonic() if now is None else now
        self._seconds = min(self._seconds + (now - self._at) * self._duty, self._most)
        self._at = now
        return self._seconds >= 0.0

    def spend(self, held: float) -> None:
        """A publication held the lock ``held`` seconds."""
        self._seconds -= held


TOPICS = {
    "degree_of_occupancy": "~/degree_of_occupancy",
    "std": "~/std",
    "projected_map": "~/projected_map",
    "reflectivity": "~/reflectivity",
}
"""The map outputs' topics (node-private names)."""
OCTOMAP_TOPICS = {
    "degree_of_occupancy": "octomap_point_cloud_centers",
    "std": "~/std",
    "projected_map": "projected_map",
    "reflectivity": "~/reflectivity",
}
"""With ``octomap_topics``: octomap_server's names (relative: in the node's namespace) for
the voxel-centre cloud and the grid; ``~/std`` and ``~/reflectivity`` have no octomap_server
counterpart."""


@dataclass
class PublishCounters:
    seconds: float = 0.0  # building and sending, without waiting for the map lock
    locked_seconds: float = 0.0  # of which the map lock was held (integration waits)
    locked_max_seconds: float = 0.0  # the longest single hold of the map lock
    slices: int = 0  # map-lock holds of the last publication (its slices, clouds and grid)
    count: int = 0
    last_seconds: float = 0.0
    voxels: int = 0
    blocks_read: int = 0  # by the last publication (-1: the whole map, not by blocks)


class MapOutputs:
    """Publishers of ``~/degree_of_occupancy``, ``~/std`` and ``~/projected_map`` (or
    octomap_server's names, ``OCTOMAP_TOPICS``, with ``octomap_topics``)."""

    def __init__(
        self,
        node: Node,
        worker: LiveIntegrator,
        settings: Callable[[], OutputsSection],
        warn: Callable[[str, str], None],
    ) -> None:
        self._node = node
        self._warn = warn
        self._worker = worker
        self._settings = settings
        """The outputs section now (the node's, replaced whole on a change)."""
        latch = settings().latch
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latch else DurabilityPolicy.VOLATILE,
        )
        names = OCTOMAP_TOPICS if settings().octomap_topics else TOPICS
        self._doo_pub = node.create_publisher(PointCloud2, names["degree_of_occupancy"], qos)
        self._std_pub = node.create_publisher(PointCloud2, names["std"], qos)
        self._grid_pub = node.create_publisher(OccupancyGrid, names["projected_map"], qos)
        self._reflectivity_pub = node.create_publisher(PointCloud2, names["reflectivity"], qos)
        self.publishers = [self._doo_pub, self._std_pub, self._grid_pub, self._reflectivity_pub]
        self.counters = PublishCounters()
        # the map version each output last went out with: a late transient-local subscriber
        # of one output gets it even when the other already went out for this version
        self.published: dict[str, int | None] = {"clouds": None, "grid": None}
        self._cloud = MapCloud()  # the clouds' rows, rebuilt where scans changed the map
        self._grid_cells: BandCells | None = None  # the last ~/projected_map's, continued
        self._budget = LockBudget()
        self._cloud_slice = SliceSize()
        self._grid_slice = SliceSize()

    def invalidate(self) -> None:
        """Publish again at the next chance (e.g. the filters changed)."""
        self.published = dict.fromkeys(self.published)

    def publish(self) -> None:
        """Publish the map outputs if the map changed and someone subscribes."""
        listening = {
            "clouds": self._doo_pub.get_subscription_count()
            + self._std_pub.get_subscription_count()
            + self._reflectivity_pub.get_subscription_count(),
            "grid": self._grid_pub.get_subscription_count(),
        }
        if not any(listening.values()):
            return  # nobody listens: publish when someone does (latched, so they get it)
        if not self._budget.allows():
            return  # the last publications were slow: keep publishing under PUBLISH_DUTY
        worker = self._worker
        with worker.map_lock:
            version = worker.mapper.version
            if not worker.map_frame:
                return  # the map frame is not decided yet (no cloud placed): nothing to latch
        due = {k for k, n in listening.items() if n and self.published[k] != version}
        if not due:
            return
        want_grid, want_clouds = "grid" in due, "clouds" in due
        t0 = time.perf_counter()
        lock_times = [0.0, 0.0, 0.0]  # seconds waited for the lock, held; holds
        if want_grid:
            self._grid_pub.publish(self.grid(lock_times, projected=True, in_slices=True))
        if want_clouds:
            self._publish_clouds(lock_times)
        for key in due:
            self.published[key] = version
        dt = time.perf_counter() - t0 - lock_times[0]
        self._budget.spend(lock_times[1])
        c = self.counters
        c.seconds += dt
        c.locked_seconds += lock_times[1]
        c.count += 1
        c.last_seconds = dt
        c.slices = int(lock_times[2])

    @contextlib.contextmanager
    def _timed_map_lock(self, times: list[float] | None) -> Iterator[None]:
        """The map lock; adds the seconds waited for it and held, and one hold, to ``times``
        (if given: [waited, held, holds]) and keeps the longest hold
        (``PublishCounters.locked_max_seconds``)."""
        t0 = time.perf_counter()
        with self._worker.whole_map:
            t1 = time.perf_counter()
            try:
                yield
            finally:
                held = time.perf_counter() - t1
                self.counters.locked_max_seconds = max(self.counters.locked_max_seconds, held)
                if times is not None:
                    times[0] += t1 - t0
                    times[1] += held
                    times[2] += 1

    def _header_stamp(self, stamp: float | None) -> Any:
        return stamp_msg(stamp) if stamp is not None else self._node.get_clock().now().to_msg()

    def _publish_clouds(self, lock_times: list[float]) -> None:
        """Publish the degree-of-occupancy and std clouds of the filtered voxels, and the
        reflectivity cloud of those holding returns (when the map keeps histograms): per
        voxel the mean intensity of its returns and its fullest intensity bin. With
        ``publish_changed_blocks`` only the blocks scans changed since the last
        publication are read under the map lock (``mapping.map_cloud``; the clouds are the
        whole map's all the same), without it every block; either in slices of about
        ``MAP_SLICE_S``. Without ``publish_changed_blocks`` and with a ``publish_radius``,
        the radius' window is exported in one go (its size bounds the hold)."""
        cfg, worker = self._settings(), self._worker
        radius = cfg.publish_radius
        with self._timed_map_lock(lock_times):
            position = worker.robot_position
            robot = None if position is None else np.asarray(position, dtype=np.float64)
            near = radius > 0.0 and robot is not None
            stamp = worker.mapper.last_stamp
            # by blocks, in slices: what changed, or the whole map; the window of a radius
            # without changed blocks is exported in one go (bounded by the radius)
            incremental = cfg.publish_changed_blocks or not near
            if incremental:
                if not cfg.publish_changed_blocks:
                    self._cloud.clear()  # the whole map, each time
                changes = self._read_cloud_slice(cfg.min_degree_of_occupancy, cfg.min_evidence)
            else:
                window = (robot - radius, robot + radius) if near and robot is not None else None
                vox = worker.mapper.voxels(
                    min_doo=cfg.min_degree_of_occupancy,
                    min_evidence=cfg.min_evidence,
                    bounds=window,
                )
                histograms = worker.mapper.reflectivity(vox.centers)
        while incremental and not changes.complete:
            time.sleep(SLICE_PAUSE_S)  # a scan waiting for the map takes it
            with self._timed_map_lock(lock_times):
                changes = self._read_cloud_slice(
                    cfg.min_degree_of_occupancy, cfg.min_evidence, changes
                )
        if incremental:
            rows = self._cloud.apply(changes, cfg.min_evidence)
            self.counters.blocks_read = self._cloud.last_changed_blocks
            if not cfg.publish_changed_blocks:
                self._cloud.clear()  # (not kept: the next one reads the whole map again)
                self.counters.blocks_read = -1
        else:
            self._cloud.clear()
            rows = rows_of(vox, histograms)
            self.counters.blocks_read = -1
        if near and robot is not None:
            rows = rows.select(np.sum((rows.centers - robot) ** 2, axis=1) <= radius**2)
        xyz = {a: rows.centers[:, k] for k, a in enumerate("xyz")}
        header_stamp = self._header_stamp(stamp)
        frame = worker.map_frame
        doo = pack_cloud({**xyz, "degree_of_occupancy": rows.degree_of_occupancy})
        std = pack_cloud({**xyz, "std": rows.std})
        self._doo_pub.publish(cloud_msg(doo, frame, header_stamp))
        self._std_pub.publish(cloud_msg(std, frame, header_stamp))
        if rows.reflectivity is not None and rows.reflectivity_bin is not None:
            held = ~np.isnan(rows.reflectivity)
            cloud = pack_cloud({
                **{a: v[held] for a, v in xyz.items()},
                "reflectivity": rows.reflectivity[held],
                "reflectivity_bin": rows.reflectivity_bin[held],
            })  # fmt: skip
            self._reflectivity_pub.publish(cloud_msg(cloud, frame, header_stamp))
        self.counters.voxels = len(rows)

    def _read_cloud_slice(
        self, min_doo: float, min_evidence: float, partial: CloudChanges | None = None
    ) -> CloudChanges:
        """The next slice of the clouds' changed blocks (``MapCloud.read``), under the map
        lock; its size follows the last slices' time (``SliceSize``)."""
        size = self._cloud_slice
        t0 = time.perf_counter()
        changes = self._cloud.read(self._worker.mapper, min_doo, min_evidence, size.blocks, partial)
        if not changes.complete:
            size.took(time.perf_counter() - t0)
        return changes

    def grid(
        self,
        lock_times: list[float] | None = None,
        projected: bool = False,
        in_slices: bool = False,
    ) -> OccupancyGrid:
        """The 2D grid of the height band: hit-probability percent (``~/hit_probability_map``)
        or, with ``projected``, ``~/projected_map`` (trinary 100/0/-1 for Nav2 unless
        ``projected_map.trinary`` is false); ``lock_times`` as in ``_timed_map_lock``.
        ``in_slices`` (a publication): read a slice at a time, the map lock let go between
        slices; else in one hold, a grid of whole scans (GetMap's answer)."""
        cfg, worker = self._settings(), self._worker
        trinary = None
        if projected and cfg.projected_map_trinary:
            occupied = cfg.projected_map_occupied_threshold
            free = cfg.projected_map_free_threshold
            if free < 0.0:
                m = worker.mapper
                free = unobserved_hit_probability(m.resolution, m.prior.shape, m.prior.rate)
            trinary = (occupied, min(free, occupied))
        robot = worker.robot_position
        radius = cfg.hit_probability_map_radius
        center = (float(robot[0]), float(robot[1])) if robot is not None and radius > 0 else None
        limit = cfg.hit_probability_map_max_cells
        # ~/projected_map: continued from the last one's cells (the columns scans changed)
        previous = self._grid_cells if projected and cfg.publish_changed_blocks else None
        band = (cfg.occupancy_min_z, cfg.occupancy_max_z)
        reading: GridReading | None = None
        restarts = 0
        while True:
            with self._timed_map_lock(lock_times):
                mapper = worker.mapper
                if reading is None or not mapper.grid_still_valid(reading):
                    if reading is not None:  # reset, clear_box or eviction meanwhile
                        restarts += 1
                    resolution, stamp = mapper.resolution, mapper.last_stamp
                    try:
                        reading = mapper.start_grid(
                            *band,
                            center=center,
                            radius=radius,
                            max_cells=limit,
                            trinary=trinary,
                            previous=previous,
                        )
                    except GridTooLarge as err:
                        if robot is None:
                            raise
                        # the largest square around the robot that fits (the window adds a cell)
                        radius = 0.5 * (math.isqrt(limit) - 2) * resolution
                        center = (float(robot[0]), float(robot[1]))
                        self._warn(
                            "grid_too_large",
                            f"{err}: serving the {2 * radius:.0f} m square around the robot "
                            "(hit_probability_map.max_cells, hit_probability_map.radius)",
                        )
                        reading = mapper.start_grid(
                            *band, center=center, radius=radius, max_cells=limit, trinary=trinary
                        )
                grid = self._read_grid_slice(reading, not in_slices or restarts > MAX_RESTARTS)
            if grid is not None:
                break
            time.sleep(SLICE_PAUSE_S)  # a scan waiting for the map takes it
        if projected:
            self._grid_cells = grid.cells
        now = self._node.get_clock().now().to_msg()
        return grid_msg(
            grid,
            resolution,
            worker.map_frame or worker.mapper.frame_id,
            self._header_stamp(stamp),
            now,
            cfg.occupancy_min_z,
        )

    def _read_grid_slice(self, reading: GridReading, whole: bool) -> HitGrid | None:
        """The next slice of a grid's blocks (``Mapper.read_grid``; all of them when
        ``whole``), under the map lock; the grid once every block was read."""
        size = self._grid_slice
        t0 = time.perf_counter()
        grid = self._worker.mapper.read_grid(reading, None if whole else size.blocks)
        if grid is None:
            size.took(time.perf_counter() - t0)
        return grid
