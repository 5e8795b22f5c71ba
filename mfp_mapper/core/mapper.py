"""The mean-free-path map: the one core API the node, the bag replay and the CLI call."""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.config.sections import MapSection, SensorModelSection
from mfp_mapper.core import model, traversal
from mfp_mapper.core.changed_blocks import BlockCursor, changed_returns
from mfp_mapper.core.errors import CoreError, ScanTooLargeError
from mfp_mapper.core.gridmap import (
    BandCells,
    GridReading,
    HitGrid,
    band_grid_result,
    band_grid_step,
    start_band_grid,
)
from mfp_mapper.core.memory_bound import (
    MemoryBound,
    fit_scan_budget,
    scan_block_budget,
    scan_new_blocks,
)
from mfp_mapper.core.packed import PackedBlocks, as_parts, packed_problem
from mfp_mapper.core.reflectivity import (
    ReflectivityArrays,
    ReflectivityBins,
    ReflectivityTable,
    ScanReflectivity,
)
from mfp_mapper.core.shard import FLUSH_EDGES
from mfp_mapper.core.staging import clear_staged, merge_shard, prefault, staged_updates
from mfp_mapper.core.store import (
    BLOCK_EDGE,
    MAX_RESOLUTION,
    MAX_VOXEL_INDEX,
    MIN_RESOLUTION,
    BlockStore,
    VoxelArrays,
    index_box,
    voxel_problem,
)
from mfp_mapper.core.traversal import (
    Rays,
    StoreView,
    integrate_rays,
    prepare_rays,
    read_walk,
    store_view,
    visit_bounds,
)
from mfp_mapper.core.voxel_stats import IntegrationSummary, SegmentStats, VoxelStats, decayed_stats

MAX_RAY_VOXELS = 1 << 15
"""Hard limit of a ray's walk, in voxels (3.3 km at 0.1 m): a ray longer than this (when
``max_range`` allows it) is walked this far and carries no return, so one input point
costs a bounded time and memory whatever its distance."""
ORIGIN_QUANTUM_VOXELS = 1 << 16
"""An origin taken from the first scan is a multiple of this many voxels (6.5 km at 0.1 m):
zero for a robot that starts within half of it from the frame's origin, so ordinary maps
keep ``ijk = floor(p / resolution)``."""

__all__ = [
    "CoreError", "IntegrationSummary", "Mapper", "ScanTooLargeError", "VoxelStats", "mapper_kwargs",
]  # fmt: skip

FloatArray = NDArray[np.float64]


@dataclasses.dataclass
class StagedScan:
    """A scan integrated into a store of its own by ``Mapper.stage``, for ``commit``."""

    inputs: tuple[ArrayLike, ArrayLike, ArrayLike | None, ArrayLike | None]
    """points, origins, no_return, continued"""
    origin: FloatArray | None  # the map origin its rays are relative to
    rays: Rays
    store: BlockStore
    stamp: float
    summary: IntegrationSummary
    reflectivity: ScanReflectivity | None = None
    returns: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
    """The return voxels and intensity bins of its rays (``Mapper._scan_returns``)."""


def _cpu_of(fn: Callable[[int], None], item: int) -> float:
    """Run ``fn(item)``; the CPU seconds this thread spent on it."""
    cpu0 = time.thread_time()
    fn(item)
    return time.thread_time() - cpu0


def mapper_kwargs(map_section: MapSection, sensor_model: SensorModelSection) -> dict[str, Any]:
    """The keyword arguments of ``Mapper`` besides the resolution and frame, in the core's
    units ("<= 0 means no limit" applied); also the overrides a loaded map takes (its own
    resolution stays)."""
    return {
        "max_range": sensor_model.core("max_range"),
        "min_range": sensor_model.min_range,
        "decay_time": map_section.core("decay_time"),
        "threads": map_section.core("threads"),
        "max_voxels": map_section.core("max_voxels"),
        "keep_radius": map_section.core("keep_radius"),
        "prior_shape": map_section.prior_shape,
        "prior_rate": map_section.prior_rate,
        "prior_scale": map_section.prior_scale,
        "reflectivity_bins": map_section.reflectivity_bins,
    }


_DEFAULTS = mapper_kwargs(MapSection(threads=1), SensorModelSection())
"""The defaults of ``Mapper``'s settings: the sections' defaults, in the core's units; one
thread (a library call starts no thread it was not asked for; the node and the replay's
``threads`` default to automatic)."""


class Mapper:
    """A degree-of-occupancy voxel map built from lidar rays (Berquin & Zell 2021).

    ``integrate`` adds rays; ``query`` and ``voxels`` read the map; ``from_arrays`` builds
    one from voxel arrays (map files: ``mfp_mapper.mapio.load_map``/``save_map``). Not
    thread-safe: callers that share a
    Mapper between threads hold a lock around every call.
    """

    def __init__(
        self,
        resolution: float = MapSection.resolution,
        *,
        max_range: float = _DEFAULTS["max_range"],
        min_range: float = _DEFAULTS["min_range"],
        decay_time: float = _DEFAULTS["decay_time"],
        frame_id: str = "map",
        threads: int = _DEFAULTS["threads"],
        max_voxels: int | None = _DEFAULTS["max_voxels"],
        keep_radius: float | None = _DEFAULTS["keep_radius"],
        origin: ArrayLike | None = None,
        prior_shape: float = _DEFAULTS["prior_shape"],
        prior_rate: float = _DEFAULTS["prior_rate"],
        prior_scale: float = _DEFAULTS["prior_scale"],
        reflectivity_bins: int = _DEFAULTS["reflectivity_bins"],
    ) -> None:
        _check_settings(
            resolution, max_range, min_range, decay_time, threads, max_voxels, keep_radius
        )
        self.prior = model.resolve_prior(
            float(resolution), float(prior_shape), float(prior_rate), float(prior_scale)
        )
        """Gamma prior on the extinction (``model.Prior``; 1, 1: the paper's uniform prior;
        by default the family ``model.family_prior``: a ``prior_shape`` or ``prior_rate``
        of 0 takes the family's value for ``prior_scale`` at this resolution):
        read by every estimate (mean, std, intervals, p_hit, grids, likelihood), never stored
        in the statistics, so it may be changed at any time."""
        self.resolution = float(resolution)
        self.max_range = float(max_range)
        self.min_range = float(min_range)
        self.decay_time = float(decay_time)
        self.frame_id = frame_id
        self.threads = int(threads)
        self.max_voxels = max_voxels
        self.keep_radius = keep_radius
        self._bound = MemoryBound(
            max_voxels,
            None if keep_radius is None else keep_radius / (self.resolution * BLOCK_EDGE),
        )
        self._origin_given = origin is not None
        self._origin: FloatArray | None = None
        if origin is not None:
            self._origin = np.asarray(origin, dtype=np.float64).reshape(3).copy()
            if not np.isfinite(self._origin).all():
                raise ValueError(f"origin must be 3 finite metres, got {origin}")
        self.last_stamp: float | None = None
        self.last_origin: FloatArray | None = None
        self.version = 0
        self.epoch = 0
        """Bumped whenever voxels change other than by scans adding to their blocks (reset,
        clear_box, blocks evicted by the memory bound): what ``changed_voxels`` said since an
        earlier scan no longer tells the whole change."""
        self._store = BlockStore(shard_count(self.threads), FLUSH_EDGES * self.resolution)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self._worker_cpu = 0.0  # CPU seconds of the pool threads in the current integrate()
        self._spare_stage: BlockStore | None = None  # an emptied staged store, for reuse
        if not 0 <= int(reflectivity_bins) <= 64:
            raise ValueError(f"reflectivity_bins must lie in [0, 64], got {reflectivity_bins}")
        self.reflectivity_bins = int(reflectivity_bins)
        """J, the bins of the reflectivity histograms a source should give (0: none kept):
        a setting for the sensing layer, which chooses the edges (``takes_reflectivity``)."""
        self._reflectivity: ReflectivityTable | None = None

    @classmethod
    def of(
        cls,
        map_section: MapSection,
        sensor_model: SensorModelSection,
        frame_id: str = "map",
        origin: ArrayLike | None = None,
    ) -> Mapper:
        """An empty map with the settings of the map and sensor-model sections."""
        return cls(
            map_section.resolution,
            frame_id=frame_id,
            origin=origin,
            **mapper_kwargs(map_section, sensor_model),
        )

    # --- writing ----------------------------------------------------------------------

    def integrate(
        self,
        points: ArrayLike,
        origins: ArrayLike,
        stamp: float,
        no_return: ArrayLike | None = None,
        reflectivity: ScanReflectivity | None = None,
        continued: ArrayLike | None = None,
    ) -> IntegrationSummary:
        """Add one scan: rays from ``origins`` ((3,) or (N, 3)) to ``points`` (N, 3), map frame.

        Each point is a first return, unless the ray is longer than ``max_range`` or its
        ``no_return`` flag (N,) is set: then it is walked up to its point (at most
        ``max_range``) and carries no return. Rays shorter than ``min_range`` and rays with
        NaN/Inf are dropped and counted.

        ``reflectivity``: the intensity of each point and its bins (Appendix B): each
        return adds to its voxel's histogram (``takes_reflectivity`` says which bins the
        map takes: ValueError for others, the map unchanged).

        ``continued`` (N,): rays that continue a shot past its previous echo (a later echo:
        its origin is where that echo's blind stretch ends; see ``traversal.prepare_rays``):
        kept whatever their length, zero included (a return with no chord), and not counted
        in the scan's mean sensor position.
        """
        t0, cpu0 = time.perf_counter(), time.thread_time()
        self._worker_cpu = 0.0
        if not math.isfinite(stamp):
            raise ValueError(f"stamp must be finite seconds, got {stamp}")
        self._check_reflectivity(reflectivity, points)
        rays, pts, dropped = self._place(
            points, origins, no_return, set_origin=True, continued=continued
        )
        summary = self._summary(rays, pts, dropped)
        if len(rays):
            budget = scan_block_budget(self.max_voxels)
            rays, summary.rays_cut_by_budget = fit_scan_budget(rays, budget, self.resolution)
            blocks = self._store.num_blocks
            self._bound.make_room(self._store, rays.origins_vox, rays.ends_vox, self._center())
            self._prune_if_evicted(blocks)
            scan_id = self._store.begin_scan()
            summary.rays_cut_by_budget += integrate_rays(
                self._store,
                rays,
                scan_id,
                stamp,
                self.decay_time,
                self._run_parallel,
                scan_new_blocks(self.max_voxels),
            )
            summary.new_voxels, summary.blocks_touched, summary.voxels_touched = (
                self._store.finish_scan()
            )
            self._add_returns(reflectivity, self._scan_returns(rays, reflectivity), stamp)
            self.last_stamp = (
                float(stamp) if self.last_stamp is None else max(self.last_stamp, stamp)
            )
            self.last_origin = _mean_origin(rays) * self.resolution + self._offset
            blocks = self._store.num_blocks
            self._bound.enforce(self._store, self._center())
            self._prune_if_evicted(blocks)
            self.version += 1
        summary.seconds = time.perf_counter() - t0
        summary.cpu_seconds = time.thread_time() - cpu0 + self._worker_cpu
        return summary

    def stage(
        self,
        points: ArrayLike,
        origins: ArrayLike,
        stamp: float,
        no_return: ArrayLike | None = None,
        reflectivity: ScanReflectivity | None = None,
        continued: ArrayLike | None = None,
    ) -> StagedScan:
        """Integrate one scan (as ``integrate``) into a store of its own, leaving the map
        untouched: the long part of an integration, which needs no lock around the map
        (readers may use it meanwhile; one ``stage`` at a time per Mapper). ``commit`` then
        adds it to the map in one pass over the blocks it touched (``core.staging``)."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        self._worker_cpu = 0.0
        if not math.isfinite(stamp):
            raise ValueError(f"stamp must be finite seconds, got {stamp}")
        self._check_reflectivity(reflectivity, points)
        origin, org = self._origin, np.asarray(origins, dtype=np.float64)
        if origin is None and org.shape[-1:] == (3,):  # bad shapes: _place names them
            origin = self._origin_from(org.reshape(-1, 3))
        rays, pts, dropped = self._place(
            points, origins, no_return, set_origin=False, at=origin, continued=continued
        )
        summary = self._summary(rays, pts, dropped)
        store, self._spare_stage = self._spare_stage, None
        if store is None:
            store = BlockStore(shards=len(self._store.shards))
        if len(rays):
            budget = scan_block_budget(self.max_voxels)
            rays, summary.rays_cut_by_budget = fit_scan_budget(rays, budget, self.resolution)
            # a scan too large for max_voxels is refused before it takes any memory
            self._bound.make_room(store, rays.origins_vox, rays.ends_vox, None)
            summary.rays_cut_by_budget += integrate_rays(
                store,
                rays,
                0,
                stamp,
                self.decay_time,
                self._run_parallel,
                scan_new_blocks(self.max_voxels),
            )
            for staged_shard, shard in zip(store.shards, self._store.shards, strict=True):
                prefault(staged_shard, shard)
        summary.seconds = time.perf_counter() - t0
        summary.cpu_seconds = time.thread_time() - cpu0 + self._worker_cpu
        return StagedScan(
            (points, origins, no_return, continued), origin, rays, store, float(stamp),
            summary, reflectivity, self._scan_returns(rays, reflectivity),
        )  # fmt: skip

    def commit(
        self, staged: StagedScan, pause: Callable[[], None] | None = None
    ) -> IntegrationSummary:
        """Add a scan prepared by ``stage`` to the map (the caller holds the map's lock):
        the memory bound first, then one merge of its blocks; returns its summary. A scan
        staged before ``reset`` cleared an origin it depended on is integrated again.

        ``pause``: called between chunks of ``staging.MERGE_CHUNK_BLOCKS`` blocks (a caller
        may let readers in there: they then see the scan in part, each voxel before or
        after it)."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        summary = staged.summary
        if staged.origin is not None and self._origin is not None:
            if not np.array_equal(staged.origin, self._origin):  # reset in between
                points, origins, no_return, continued = staged.inputs
                return self.integrate(
                    points, origins, staged.stamp, no_return, staged.reflectivity, continued
                )
        elif staged.origin is not None:
            self._origin = staged.origin
        rays = staged.rays
        if len(rays):
            self._check_reflectivity(staged.reflectivity, staged.inputs[0])  # a reset between
            blocks = self._store.num_blocks
            self._bound.make_room(self._store, rays.origins_vox, rays.ends_vox, self._center())
            self._prune_if_evicted(blocks)
            scan_id = self._store.begin_scan()
            # one shard after the other: pause is not thread-safe; merging is memory-bound
            for k, shard in enumerate(self._store.shards):
                merge_shard(
                    staged.store.shards[k], shard, scan_id, staged.stamp, self.decay_time, pause
                )
            summary.new_voxels, summary.blocks_touched, _ = self._store.finish_scan()
            summary.voxels_touched = staged_updates(staged.store)
            self._add_returns(staged.reflectivity, staged.returns, staged.stamp)
            self._scan_added(rays, staged.stamp)
            if clear_staged(staged.store):  # merged whole: its memory serves the next stage
                self._spare_stage = staged.store
        summary.commit_seconds = time.perf_counter() - t0
        summary.seconds += summary.commit_seconds
        summary.cpu_seconds += time.thread_time() - cpu0
        return summary

    def _summary(self, rays: Rays, pts: FloatArray, dropped: dict[str, int]) -> IntegrationSummary:
        """What a scan's placement says of its rays (``integrate`` and ``stage``)."""
        summary = IntegrationSummary(rays_in=pts.shape[0], dropped=dropped)
        summary.rays_used = len(rays)
        summary.rays_unindexable = dropped["out_of_bounds"]
        summary.rays_no_return = rays.no_return_flagged
        cut = int(np.count_nonzero(~rays.has_return)) - rays.no_return_flagged
        if self.max_range > MAX_RAY_VOXELS * self.resolution:
            summary.rays_beyond_walk_limit = cut
        else:
            summary.rays_truncated = cut
        return summary

    def _scan_added(self, rays: Rays, stamp: float) -> None:
        """After a scan went into the store: its stamp and place, the memory bound."""
        self.last_stamp = float(stamp) if self.last_stamp is None else max(self.last_stamp, stamp)
        self.last_origin = _mean_origin(rays) * self.resolution + self._offset
        blocks = self._store.num_blocks
        self._bound.enforce(self._store, self._center())
        self._prune_if_evicted(blocks)
        self.version += 1

    # --- the reflectivity field (core.reflectivity) --------------------------------------

    def takes_reflectivity(self, bins: ReflectivityBins) -> bool:
        """Whether ``integrate`` takes intensities binned by ``bins``: the map keeps
        histograms (``reflectivity_bins`` > 0, or a loaded table) and holds none yet or
        ones with the same bins."""
        if self._reflectivity is not None:
            return self._reflectivity.bins == bins
        return self.reflectivity_bins > 0

    @property
    def reflectivity_scale(self) -> ReflectivityBins | None:
        """The bins of the map's histograms; None while it holds none."""
        return None if self._reflectivity is None else self._reflectivity.bins

    def _check_reflectivity(self, reflectivity: ScanReflectivity | None, points: ArrayLike) -> None:
        """ValueError (nothing changed) for intensities the map cannot take."""
        if reflectivity is None:
            return
        if not self.takes_reflectivity(reflectivity.bins):
            raise ValueError(
                f"reflectivity binned as {reflectivity.bins} but the map "
                + (
                    "keeps none (reflectivity_bins 0)"
                    if self._reflectivity is None
                    else f"holds {self._reflectivity.bins}"
                )
            )
        count = np.shape(points)[0] if np.ndim(points) else 0
        if np.shape(reflectivity.values) != (count,):
            raise ValueError(
                f"reflectivity values must have shape ({count},), got "
                f"{np.shape(reflectivity.values)}"
            )

    def _scan_returns(
        self, rays: Rays, reflectivity: ScanReflectivity | None
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
        """The voxel (the one whose ``n`` it adds to: floor of its end, as the walk) and
        bin of every return of the rays."""
        if reflectivity is None or not len(rays) or rays.source is None:
            return None
        returned = rays.has_return
        ijk = np.floor(rays.ends_vox[returned]).astype(np.int64)
        values = np.asarray(reflectivity.values)[rays.source[returned]]
        return ijk, reflectivity.bins.bin_of(values)

    def _add_returns(
        self,
        reflectivity: ScanReflectivity | None,
        returns: tuple[NDArray[np.int64], NDArray[np.int64]] | None,
        stamp: float,
    ) -> None:
        if reflectivity is None or returns is None:
            return
        if self._reflectivity is None:
            self._reflectivity = ReflectivityTable(reflectivity.bins)
        self._reflectivity.add(returns[0], returns[1], stamp, self.decay_time)

    def _prune_if_evicted(self, blocks_before: int) -> None:
        """After the memory bound evicted blocks: drop the histograms of voxels that no
        longer hold a return."""
        if self._store.num_blocks < blocks_before:
            self.epoch += 1
            if self._reflectivity is not None:
                self._drop_lost_histograms()

    def _drop_lost_histograms(self) -> None:
        assert self._reflectivity is not None
        ijk = self._reflectivity.voxel_indices().astype(np.int64)
        self._reflectivity.keep(self._store.lookup(ijk).n > 0)

    def reflectivity(
        self, points: ArrayLike, stamp: float | None = None
    ) -> tuple[ReflectivityBins, FloatArray] | None:
        """The bins and the reflectivity histogram (M, J: decayed return counts per bin,
        zeros where none) of the voxel containing each point, decayed to ``stamp`` when
        given; None when the map holds no histograms."""
        if self._reflectivity is None:
            return None
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            valid = np.all(np.abs((pts - self._offset) / self.resolution) < MAX_VOXEL_INDEX, axis=1)
        ijk = self.voxel_index(np.where(valid[:, None], pts, self._offset))
        counts, _ = self._reflectivity.histograms(ijk, stamp, self.decay_time)
        counts[~valid] = 0.0
        return self._reflectivity.bins, counts

    def stored_reflectivity(self) -> ReflectivityArrays | None:
        """The histograms as stored (index relative to ``origin``, counts, the time they
        refer to): what a map file holds; None when the map holds none."""
        return None if self._reflectivity is None else self._reflectivity.export()

    def place_rays(
        self,
        points: ArrayLike,
        origins: ArrayLike,
        no_return: ArrayLike | None = None,
        continued: ArrayLike | None = None,
    ) -> tuple[Rays, dict[str, int]]:
        """The rays ``integrate`` would walk for this scan (voxel units of the store, the
        same checks, cuts and drops), and the drops by reason; the map is not changed
        (an empty map's origin is not set). ``Rays.source`` indexes the input points."""
        rays, _, dropped = self._place(
            points, origins, no_return, set_origin=False, continued=continued
        )
        return rays, dropped

    def _place(
        self,
        points: ArrayLike,
        origins: ArrayLike,
        no_return: ArrayLike | None,
        set_origin: bool,
        at: FloatArray | None = None,
        continued: ArrayLike | None = None,
    ) -> tuple[Rays, FloatArray, dict[str, int]]:
        """The rays in voxel units of the store (``at``: of a map with that origin, when
        the map has none yet), the points as float64 and the drops by reason."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        org = np.asarray(origins, dtype=np.float64)
        if org.shape != (3,) and org.shape != pts.shape:
            raise ValueError(f"origins must have shape (3,) or {pts.shape}, got {org.shape}")
        if self._origin is None and set_origin:
            self._origin = self._origin_from(org)
        offset = self._origin if self._origin is not None else at
        reach = min(self.max_range, MAX_RAY_VOXELS * self.resolution)
        flags = None if no_return is None else np.asarray(no_return, dtype=np.bool_)
        if flags is not None and flags.shape != (pts.shape[0],):
            raise ValueError(f"no_return must have shape ({pts.shape[0]},), got {flags.shape}")
        later = None if continued is None else np.asarray(continued, dtype=np.bool_)
        if later is not None and later.shape != (pts.shape[0],):
            raise ValueError(f"continued must have shape ({pts.shape[0]},), got {later.shape}")
        rays, dropped = prepare_rays(
            pts, org, self.resolution, self.min_range, reach, flags, later, offset
        )
        return rays, pts, dropped

    def store_view(self) -> tuple[StoreView, int]:
        """The store's arrays for read-only compiled kernels (``traversal.read_walk``) and
        its shard mask; valid until the next ``integrate``, ``reset`` or eviction."""
        return store_view(self._store), self._store.shard_mask

    @property
    def prior_shape(self) -> float:
        return self.prior.shape

    @property
    def prior_rate(self) -> float:
        return self.prior.rate

    def _origin_from(self, sensor_origins: FloatArray) -> FloatArray | None:
        """The origin a first scan gives the map: its first finite sensor position, rounded
        to a multiple of ``ORIGIN_QUANTUM_VOXELS`` voxels (None: no finite position)."""
        rows = sensor_origins.reshape(-1, 3)
        if len(rows) and np.isfinite(rows[0]).all():  # (the usual case: no pass over all)
            first = rows[0]
        else:
            finite = rows[np.isfinite(rows).all(axis=1)]
            if not len(finite):
                return None
            first = finite[0]
        quantum = ORIGIN_QUANTUM_VOXELS * self.resolution
        return np.round(first / quantum) * quantum

    def _run_parallel(self, fn: Callable[[int], None], items: Sequence[int]) -> None:
        if self._pool is None or len(items) == 1:
            for item in items:
                fn(item)
        else:
            self._worker_cpu += sum(self._pool.map(functools.partial(_cpu_of, fn), items))

    def _center(self) -> FloatArray | None:
        """The latest sensor position in block units of the store (None before a scan)."""
        if self.last_origin is None:
            return None
        return (self.last_origin - self._offset) / (self.resolution * BLOCK_EDGE)

    def reset(self) -> None:
        """Forget every voxel (parameters stay)."""
        self._store = BlockStore(len(self._store.shards), FLUSH_EDGES * self.resolution)
        if self._reflectivity is not None:
            self._reflectivity = ReflectivityTable(self._reflectivity.bins)
        self.last_stamp = None
        self.last_origin = None
        if not self._origin_given:
            self._origin = None
        self.version += 1
        self.epoch += 1

    def clear_box(self, corner_a: ArrayLike, corner_b: ArrayLike) -> int:
        """Reset to unknown (never observed) every voxel whose centre lies in the axis-aligned
        box between two corners (metres, map frame, any order; +-inf for an open side), as
        octomap_server's ``clear_bbox``; returns how many observed voxels were cleared."""
        a = np.asarray(corner_a, dtype=np.float64).reshape(3)
        b = np.asarray(corner_b, dtype=np.float64).reshape(3)
        if np.isnan(a).any() or np.isnan(b).any():
            raise ValueError(f"box corners must be numbers, got {a.tolist()}, {b.tolist()}")
        lo, hi = self._index_bounds((np.minimum(a, b), np.maximum(a, b)))
        cleared = self._store.clear_box(lo, hi)
        if self._reflectivity is not None:
            self._reflectivity.clear_box(lo, hi)
        if cleared:
            self.version += 1
            self.epoch += 1
        return cleared

    # --- reading ----------------------------------------------------------------------

    @property
    def origin(self) -> tuple[float, float, float] | None:
        """Map-frame position (metres) of the corner of voxel (0, 0, 0); None until the
        first scan sets it (when not given to the constructor)."""
        if self._origin is None:
            return None
        x, y, z = (float(v) for v in self._origin)
        return x, y, z

    @property
    def _offset(self) -> FloatArray:
        return self._origin if self._origin is not None else np.zeros(3)

    def voxel_index(self, points: ArrayLike) -> NDArray[np.int64]:
        """floor((point - origin) / resolution): the map-file voxel index of each point."""
        rel = np.asarray(points, dtype=np.float64) - self._offset
        return np.floor(rel / self.resolution).astype(np.int64)

    def query(self, points: ArrayLike, stamp: float | None = None) -> VoxelStats:
        """Statistics of the voxel containing each point, decayed to ``stamp`` when given."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            valid: NDArray[np.bool_] = np.all(
                np.abs((pts - self._offset) / self.resolution) < MAX_VOXEL_INDEX, axis=1
            )
        ijk = self.voxel_index(np.where(valid[:, None], pts, self._offset))
        raw = self._store.lookup(ijk)
        raw.ijk = ijk.astype(np.int32)
        for arr in (raw.s, raw.n):
            arr[~valid] = 0.0
        raw.t_last[~valid] = -np.inf
        return self._stats(raw, stamp)

    def query_segments(
        self, starts: ArrayLike, ends: ArrayLike, stamp: float | None = None
    ) -> SegmentStats:
        """Whether straight lines of sight are clear: for each segment from ``starts[i]`` to
        ``ends[i]`` (map frame, metres), the probability that a ray passes unreflected and
        the length through never-observed voxels, decayed to ``stamp`` when given.

        The voxels and exact chords are those of the read-only walk of the scan likelihood
        (``traversal.read_walk``): a segment is a ray without a return. Read-only, like
        ``query``. ValueError for a non-finite point, or a segment reaching beyond the map's
        index range or longer than ``MAX_RAY_VOXELS`` voxels.
        """
        a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        if a.shape != b.shape:
            raise ValueError(f"{len(a)} segment starts but {len(b)} ends")
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise ValueError("segment ends must be finite numbers")
        length = np.linalg.norm(b - a, axis=1)
        longest = float(length.max(initial=0.0))
        if longest > MAX_RAY_VOXELS * self.resolution:
            raise ValueError(
                f"a segment is {longest:.6g} m long: at most {MAX_RAY_VOXELS} voxels "
                f"({MAX_RAY_VOXELS * self.resolution:g} m) are walked"
            )
        log_clear = np.zeros(len(a))
        unknown = np.zeros(len(a))
        walked = np.flatnonzero(length > 0.0)
        offset = self._offset
        rays, dropped = prepare_rays(
            b[walked] - offset, a[walked] - offset, self.resolution, 0.0, math.inf,
            np.ones(len(walked), dtype=np.bool_),
        )  # fmt: skip
        if dropped["out_of_bounds"]:
            raise ValueError(
                f"{dropped['out_of_bounds']} segment(s) reach beyond the map's index range "
                f"({MAX_VOXEL_INDEX} voxels from its origin {tuple(offset.tolist())})"
            )
        if len(rays):
            capacity = int(visit_bounds(rays.origins_vox, rays.ends_vox).sum())
            ray = np.empty(capacity, dtype=np.int64)
            s, n, chord = np.empty(capacity), np.empty(capacity), np.empty(capacity)
            view, shard_mask = self.store_view()
            per_ray = np.empty(len(rays))
            at = float(stamp) if stamp is not None and math.isfinite(self.decay_time) else None
            used = read_walk(
                rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return, view,
                shard_mask, 0.0 if at is None else at,
                math.inf if at is None else self.decay_time, self.prior.shape, self.prior.rate,
                per_ray, True, ray,
                np.empty((capacity, 3), dtype=np.int32), s, n, chord,
                np.empty(capacity, dtype=np.bool_),
            )  # fmt: skip
            unseen = ~model.observed(s[:used], n[:used])
            segment = walked[np.asarray(rays.source)]
            log_clear[segment] = per_ray
            unknown[segment] = np.bincount(
                ray[:used][unseen], weights=chord[:used][unseen], minlength=len(rays)
            )
        return SegmentStats(length, np.exp(log_clear), unknown)

    def stored_voxels(self) -> VoxelArrays:
        """Every observed voxel as stored (index relative to ``origin``, s, n, the time they
        refer to), without the derived statistics of ``voxels``: what a map file holds."""
        return self._store.export()

    def stored_blocks(self) -> PackedBlocks:
        """Every observed voxel as stored, packed block by block (``core.packed``): what a
        map file holds, without an index array per voxel; ``from_blocks`` inverts it."""
        return self._store.export_blocks()

    def voxels(
        self,
        stamp: float | None = None,
        *,
        min_doo: float = 0.0,
        min_evidence: float = 0.0,
        bounds: tuple[ArrayLike, ArrayLike] | None = None,
    ) -> VoxelStats:
        """Observed voxels, decayed to ``stamp`` when given.

        Filters, applied in compiled code before any array of the whole map is built:
        ``min_doo`` (most likely degree of occupancy), ``min_evidence`` (metres of rays, s,
        after decay) and ``bounds`` = (lower corner, upper corner) in metres, map frame, on
        voxel centres (use +-inf for an open side).
        """
        if not 0.0 <= min_doo <= 1.0:
            raise ValueError(f"min_doo must lie in [0, 1], got {min_doo}")
        lo, hi = self._index_bounds(bounds) if bounds is not None else (None, None)
        min_extinction = math.inf if min_doo >= 1.0 else -math.log1p(-min_doo)
        stats = self._stats(self._store.export(min_extinction, lo, hi), stamp)
        if min_evidence > 0.0:
            stats = stats.select(stats.s >= min_evidence)
        return stats

    def changed_voxels(
        self, since: int, min_doo: float
    ) -> tuple[VoxelStats, NDArray[np.int32], int]:
        """The voxels of most likely degree of occupancy >= ``min_doo`` in the blocks
        scans changed since scan ``since`` (every block: -1), statistics as stored (as
        ``voxels`` without ``stamp``: with ``min_doo`` 0 every observed voxel); the index
        (voxel index >> 3, (B, 3)) of every such block holding a return (``min_doo`` 0:
        every such block); and the ``since`` that asks for the changes after this call. A
        cache of ``voxels`` per block stays exact while ``epoch`` stays the same
        (``core.changed_blocks``; ``mapping.map_cloud``)."""
        voxels, blocks, next_since, _ = self.changed_voxels_from(since, min_doo)
        return voxels, blocks, next_since

    def changed_voxels_from(
        self,
        since: int,
        min_doo: float,
        cursor: BlockCursor | None = None,
        max_blocks: int | None = None,
    ) -> tuple[VoxelStats, NDArray[np.int32], int, BlockCursor | None]:
        """``changed_voxels`` in slices: the blocks from ``cursor`` (None: a new read), at
        most ``max_blocks`` of the store's, changed or not; also the cursor of the next
        slice (None: the read is complete). Read with the map lock let go between slices,
        every block the map had when the read began is read once, as it was at its slice,
        while ``epoch`` stays the same (``core.changed_blocks.BlockCursor``)."""
        if not 0.0 <= min_doo <= 1.0:
            raise ValueError(f"min_doo must lie in [0, 1], got {min_doo}")
        min_extinction = math.inf if min_doo >= 1.0 else -math.log1p(-min_doo)
        shards = [(sh.arrays(), sh.used) for sh in self._store.shards]
        (blocks, ijk, s, n, t), after = changed_returns(
            shards, since, min_extinction, cursor, max_blocks
        )
        voxels = self._stats(VoxelArrays(ijk, s, n, t), None)
        return voxels, blocks, self._store.next_scan, after

    def _index_bounds(
        self, bounds: tuple[ArrayLike, ArrayLike]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The voxel index range whose centres lie in ``bounds`` (metres, +-inf allowed)."""
        with np.errstate(invalid="ignore", over="ignore"):
            lo_m, hi_m = (
                (np.asarray(b, dtype=np.float64) - self._offset) / self.resolution - 0.5
                for b in bounds
            )
            lo = np.ceil(np.clip(lo_m, -MAX_VOXEL_INDEX - 1, MAX_VOXEL_INDEX + 1))
            hi = np.floor(np.clip(hi_m, -MAX_VOXEL_INDEX - 1, MAX_VOXEL_INDEX + 1))
        return lo.astype(np.int64), hi.astype(np.int64)

    def hit_probability_grid(
        self,
        z_min: float,
        z_max: float,
        *,
        center: tuple[float, float] | None = None,
        radius: float = 0.0,
        max_cells: int | None = None,
        trinary: tuple[float, float] | None = None,
        previous: BandCells | None = None,
    ) -> HitGrid:
        """The height band ``[z_min, z_max]`` projected onto a 2D grid (``gridmap``): per
        cell ``round(100 p)``, ``p`` the largest hit probability of a voxel edge in the
        column (with the map's prior), -1 where never observed; the square of half side
        ``radius`` around ``center``, or the extent of the observed band. Statistics at their
        last update (no decay to a later stamp), read straight from the blocks.
        ``gridmap.GridTooLarge`` (nothing allocated) when the grid would exceed
        ``max_cells``. ``trinary=(occupied, free)``: cells 100 / 0 / -1 by those
        hit-probability thresholds (Nav2). ``previous``: the ``cells`` of an earlier grid of
        the whole band with the same settings, from which only the columns scans changed
        since are computed again (``gridmap.start_band_grid``; the whole band when anything else
        changed the map: ``epoch``)."""
        reading = self.start_grid(
            z_min, z_max, center=center, radius=radius, max_cells=max_cells,
            trinary=trinary, previous=previous,
        )  # fmt: skip
        grid = self.read_grid(reading)
        assert grid is not None
        return grid

    def start_grid(
        self,
        z_min: float,
        z_max: float,
        *,
        center: tuple[float, float] | None = None,
        radius: float = 0.0,
        max_cells: int | None = None,
        trinary: tuple[float, float] | None = None,
        previous: BandCells | None = None,
    ) -> GridReading:
        """``hit_probability_grid`` to be read in slices of blocks (``read_grid``): its
        extent and the columns to compute, no block's values read yet."""
        lo_m, hi_m = [-math.inf, -math.inf, z_min], [math.inf, math.inf, z_max]
        if center is not None and radius > 0.0:  # only the blocks near the window are read
            margin = radius + self.resolution
            lo_m[:2] = [center[0] - margin, center[1] - margin]
            hi_m[:2] = [center[0] + margin, center[1] + margin]
        lo, hi = self._index_bounds((lo_m, hi_m))
        shards = [(sh.arrays(), sh.used) for sh in self._store.shards]
        ox, oy, oz = (float(v) for v in self._offset)
        return start_band_grid(
            shards,
            self.resolution,
            z_min - oz,
            z_max - oz,
            index_box(lo),
            index_box(hi),
            center=None if center is None else (center[0] - ox, center[1] - oy),
            radius=radius,
            max_cells=max_cells,
            trinary=trinary,
            prior=(self.prior.shape, self.prior.rate),
            previous=previous,
            since=self._store.next_scan,
            key=(id(self), self.epoch, z_min, z_max, trinary, self.prior, ox, oy, oz),
        )

    def grid_still_valid(self, reading: GridReading) -> bool:
        """Whether ``reading`` (``start_grid``) may go on: same map, same epoch (no block
        moved: reset, clear_box and eviction move them), same prior."""
        return reading.key[:2] == (id(self), self.epoch) and reading.key[5] == self.prior

    def read_grid(self, reading: GridReading, max_blocks: int | None = None) -> HitGrid | None:
        """Read ``reading``'s next blocks, at most ``max_blocks`` of the store's (all:
        None); the grid once every block was read, else None (call again, the map lock
        may be let go in between: ``gridmap.GridReading``). ``ValueError`` when
        ``grid_still_valid`` is not."""
        if not self.grid_still_valid(reading):
            raise ValueError("read_grid: the map changed under the grid (start again)")
        shards = [(sh.arrays(), sh.used) for sh in self._store.shards]
        band_grid_step(reading, shards, max_blocks)
        if reading.cursor is not None:
            return None
        grid = band_grid_result(reading, self.resolution)
        ox, oy = float(reading.key[6]), float(reading.key[7])  # type: ignore[arg-type]
        if ox == 0.0 and oy == 0.0:
            return grid
        return dataclasses.replace(grid, origin=(grid.origin[0] + ox, grid.origin[1] + oy))

    def _stats(self, raw: VoxelArrays, stamp: float | None) -> VoxelStats:
        return decayed_stats(
            raw.ijk, raw.s, raw.n, raw.t_last, stamp, self.decay_time, self.resolution,
            self._offset, self.prior,
        )  # fmt: skip

    @property
    def num_voxels(self) -> int:
        return self._store.num_voxels

    @property
    def num_blocks(self) -> int:
        return self._store.num_blocks

    @property
    def memory_bytes(self) -> int:
        """Bytes of the map: the blocks and, when kept, the reflectivity histograms."""
        table = 0 if self._reflectivity is None else self._reflectivity.nbytes
        return self._store.nbytes + table

    # --- arrays -------------------------------------------------------------------------

    @classmethod
    def from_arrays(
        cls,
        voxels: VoxelArrays,
        *,
        resolution: float,
        origin: ArrayLike = (0.0, 0.0, 0.0),
        reflectivity: ReflectivityArrays | None = None,
        **settings: object,
    ) -> Mapper:
        """A Mapper holding these voxels (indices relative to ``origin``, as in the map file;
        each voxel once), and the reflectivity histograms (``stored_reflectivity``) when
        given. ``settings`` are the constructor's keyword arguments. Raises
        ``ValueError`` on bad settings, voxels or histograms."""
        problem = voxel_problem(voxels.ijk, voxels.s, voxels.n, voxels.t_last)
        if problem:
            raise ValueError(problem)
        count = voxels.ijk.shape[0]
        if voxels.ijk.shape != (count, 3) or any(
            a.shape != (count,) for a in (voxels.s, voxels.n, voxels.t_last)
        ):
            raise ValueError("voxels need ijk (N, 3) and s, n, t_last (N,)")
        mapper = cls(resolution, origin=origin, **settings)  # type: ignore[arg-type]
        mapper._store.assign(voxels, mapper.decay_time)
        if reflectivity is not None:
            mapper._reflectivity = ReflectivityTable(reflectivity.bins)
            mapper._reflectivity.assign(reflectivity, mapper.decay_time)
        finite_t = voxels.t_last[np.isfinite(voxels.t_last)]
        mapper.last_stamp = float(finite_t.max()) if finite_t.size else None
        mapper.version += 1
        return mapper

    @classmethod
    def from_blocks(
        cls,
        packed: PackedBlocks,
        *,
        resolution: float,
        origin: ArrayLike = (0.0, 0.0, 0.0),
        reflectivity: ReflectivityArrays | None = None,
        checked: bool = False,
        **settings: object,
    ) -> Mapper:
        """A Mapper holding packed blocks (``stored_blocks``; indices relative to
        ``origin``), and the reflectivity histograms when given (as ``from_arrays``);
        ``settings`` are the constructor's keyword arguments; ``checked``: the caller found
        no ``packed_problem`` (a map file's reader: not checked twice). Raises
        ``ValueError`` on bad settings, blocks or histograms."""
        problem = None if checked else packed_problem(packed)
        if problem:
            raise ValueError(problem)
        mapper = cls(resolution, origin=origin, **settings)  # type: ignore[arg-type]
        mapper._store.assign_blocks(as_parts(packed))  # values kept exactly (float64 too)
        if reflectivity is not None:
            mapper._reflectivity = ReflectivityTable(reflectivity.bins)
            mapper._reflectivity.assign(reflectivity, mapper.decay_time)
        mapper.last_stamp = float(packed.block_t.max()) if packed.block_t.size else None
        mapper.version += 1
        return mapper

    def close(self) -> None:
        """Stop the worker threads (the map stays readable)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def shard_count(threads: int) -> int:
    """Shards of the store for ``threads`` threads: 1 for one thread, else the power of
    two at least ``traversal.SHARDS_PER_THREAD`` per thread."""
    if threads <= 1:
        return 1
    shards = 1
    while shards < traversal.SHARDS_PER_THREAD * threads:
        shards *= 2
    return shards


def _check_settings(
    resolution: float,
    max_range: float,
    min_range: float,
    decay_time: float,
    threads: int,
    max_voxels: int | None,
    keep_radius: float | None,
) -> None:
    """ValueError naming the first setting of a Mapper out of its range."""
    if not (math.isfinite(resolution) and MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
        raise ValueError(
            f"resolution must be a positive number of metres in [{MIN_RESOLUTION}, "
            f"{MAX_RESOLUTION}], got {resolution}"
        )
    if not max_range > min_range >= 0:
        raise ValueError(f"need max_range > min_range >= 0, got {max_range}, {min_range}")
    if not decay_time > 0:
        raise ValueError(f"decay_time must be > 0 seconds (inf = static), got {decay_time}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    if max_voxels is not None and max_voxels < 1:
        raise ValueError(f"max_voxels must be >= 1 or None, got {max_voxels}")
    if keep_radius is not None and not keep_radius > 0:
        raise ValueError(f"keep_radius must be > 0 metres or None, got {keep_radius}")


def _mean_origin(rays: Rays) -> FloatArray:
    """The rays' mean sensor position in voxel units (the origins of rays that continue a
    shot past an echo left out), as ``prepare_rays`` summed it while placing them (a pass
    over the origins after took 0.4 ms of an OS1-128 scan)."""
    if rays.mean_origin is None:
        raise ValueError("rays not placed by prepare_rays: no mean origin")
    return rays.mean_origin


def compile_kernels(resolution: float = 0.5, **settings: Any) -> float:
    """Run the compiled kernels of a live node once, on a throwaway ``Mapper(resolution,
    **settings)`` (the node's settings: its ``threads`` walk other kernels than one
    thread): a synthetic scan integrated directly and staged + committed, without and with
    reflectivity histograms, then ``query``, ``query_segments``, ``reflectivity``, the
    histograms' fresh rows merged (``stored_reflectivity``; a long run merges them),
    ``voxels``, the clouds' changed blocks (``changed_voxels_from``) and the projected grids
    (whole, continued, windowed), so that numba compiles them, or loads them from its cache, before
    the first real scan or publication; returns the seconds it took. The scan's 256 rays
    start at a corner of eight of the threaded walk's tiles (voxel (0, 0, 0)'s centre), so
    its split and every shard get some, and end with a return inside the sensor model's
    range (up to three of the largest tiles, 16 blocks: ``blocks.tile_bits``)."""
    t0 = time.perf_counter()
    mapper = Mapper(resolution, origin=np.zeros(3), **settings)
    try:
        at = np.arange(256) + 0.5  # a Fibonacci sphere of directions
        z = 1.0 - 2.0 * at / 256
        azimuth = np.pi * (1.0 + 5.0**0.5) * at
        ring = np.sqrt(1.0 - z * z)
        directions = np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)
        origin = np.full(3, 0.5 * mapper.resolution)  # a voxel's centre
        # returns inside the sensor model's range (beyond max_range a ray keeps none)
        reach = min(3 * 16 * BLOCK_EDGE * mapper.resolution, 0.9 * mapper.max_range)
        reach = max(reach, mapper.min_range + 2 * mapper.resolution)
        points = origin + directions * reach
        bins = ReflectivityBins("warm-up", (2.0,))
        values = ScanReflectivity(np.ones(len(points)), bins)
        for reflectivity in (None, values):  # clouds without and with an intensity
            mapper.integrate(points, origin, 1.0, reflectivity=reflectivity)
            mapper.commit(mapper.stage(points, origin, 1.1, None, reflectivity))
        nearer = origin + directions * max(0.5 * reach, mapper.min_range + mapper.resolution)
        # (returns in new voxels: the histogram table grows)
        mapper.integrate(nearer, origin, 1.15, reflectivity=values)
        # every ray crosses half of the sensor's voxel: within these scans its block is
        # flushed to float64 (``FLUSH_EDGES``), as a live node's is in its first second
        for scan in range(8):
            mapper.integrate(points, origin, 1.2 + 0.1 * scan)
        mapper.query(points[:8])
        mapper.query_segments(points[:4], points[4:8])
        mapper.reflectivity(points[:8], 2.0)
        mapper.stored_reflectivity()  # the histograms' fresh rows merged into the settled
        mapper.voxels(min_doo=0.1, bounds=(np.full(3, -5.0), np.full(3, 5.0)))
        mapper.changed_voxels_from(-1, 0.1, None, 64)
        grid = mapper.hit_probability_grid(-1.0, 1.0, trinary=(0.25, 0.01))
        mapper.integrate(points[:8], origin, 3.0)
        mapper.hit_probability_grid(-1.0, 1.0, trinary=(0.25, 0.01), previous=grid.cells)
        mapper.hit_probability_grid(-1.0, 1.0, center=(0.0, 0.0), radius=2.0)
    finally:
        mapper.close()
    return time.perf_counter() - t0
