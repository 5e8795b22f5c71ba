"""The one mapping loop: a received cloud -> parsed -> placed -> integrated, counted once.

Every caller that maps clouds goes through ``ScanLoop``: the node's live worker
(``mapping.live``), the replay of a recording (a bag, a scan folder, a simulation:
``mapping.replay``), localization against a map (``mapping.localize``), the fleet's tasks
(which run the replay) and the scorer. The stages themselves live in
``sensing.pipeline`` (parse, no-return rays, placement: no Mapper there); the loop adds the
Mapper, the counters (``ScanCounts``) and the one error ladder:

- ``ScanDropped`` (a reason of ``DROP_REASONS``) is counted under its reason;
- any other exception is a bug: counted as ``error`` with its message, the loop goes on.

``prepare`` and ``finish`` are the two halves a live worker needs (it waits for poses in
between); ``map_cloud`` runs both for a source whose poses are all known (offline).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.sections import PlacementSection, SensorModelSection
from mfp_mapper.core.mapper import IntegrationSummary, Mapper
from mfp_mapper.core.reflectivity import ScanReflectivity
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.deskew import PoseSource
from mfp_mapper.sensing.pipeline import PlacedScan, ScanDropped
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sensing.reflectivity import bins_for

FloatArray = NDArray[np.float64]

ScanCallback = Callable[[float, FloatArray, FloatArray], None]
"""Called with (stamp, points (N, 3), origins (3,) or (N, 3)) for every placed cloud."""
ScanConsumer = Callable[[Mapper, PlacedScan], IntegrationSummary]
"""What the loop does with a placed scan instead of integrating it (``integrate_scan``):
e.g. the scorer (``outputs.score``); returns the summary of the rays used, raises
``ScanDropped`` when none."""


@dataclass
class ScanCounts:
    """What the loop did, under the names of ``DROP_REASONS`` (node ~/status and the
    replay summary report these)."""

    clouds_in: int = 0
    clouds_integrated: int = 0
    clouds_dropped: Counter[str] = field(default_factory=Counter)
    points_in: int = 0
    points_dropped: Counter[str] = field(default_factory=Counter)
    rays_in: int = 0
    rays_used: int = 0
    rays_truncated: int = 0
    rays_cut_by_budget: int = 0
    """Rays walked only part of their way, so that a scan stayed within its block bound
    (``IntegrationSummary.rays_cut_by_budget``): none, unless a scan reaches far into new
    space (or ``max_voxels`` is small)."""
    rays_no_return: int = 0
    """Recovered firings with no return that were integrated (``no_return_range``)."""
    no_return_note: str = ""
    """Why firings were not (all) recovered, the first time it happened; "" if never."""

    def drop(self, reason: str) -> int:
        """Count one dropped cloud; returns how many were dropped for that reason."""
        self.clouds_dropped[reason] += 1
        return self.clouds_dropped[reason]

    def dropped_scan(self, drop: ScanDropped) -> int:
        """Count a dropped cloud and its points; returns the count for its reason."""
        self.points_in += drop.points_in
        self.count_points(drop.points_dropped)
        return self.drop(drop.reason)

    def count_points(self, dropped: dict[str, int]) -> None:
        self.points_dropped.update({k: v for k, v in dropped.items() if v})

    def add(self, placed: PlacedScan, summary: IntegrationSummary) -> None:
        """Count one integrated cloud, its points dropped before the core and the core's."""
        self.count_points(placed.points_dropped)
        self.clouds_integrated += 1
        self.rays_in += summary.rays_in
        self.rays_used += summary.rays_used
        self.rays_truncated += summary.rays_truncated
        self.rays_cut_by_budget += summary.rays_cut_by_budget
        self.rays_no_return += summary.rays_no_return
        self.count_points(summary.dropped)


@dataclass
class PreparedScan:
    """A parsed cloud waiting for its poses: the cloud (recovered no-return rays included),
    its header stamp and the latest time a pose must cover (``pipeline.pose_deadline``)."""

    cloud: ParsedCloud
    stamp: float
    deadline: float
    frame_id: str


@dataclass
class Outcome:
    """What ``map_cloud`` did with one cloud: integrated (with its summary and placement) or
    dropped (with the reason and a one-line detail)."""

    placed: PlacedScan | None = None
    summary: IntegrationSummary | None = None
    reason: str = ""
    detail: str = ""
    count: int = 0
    """For a drop: how many clouds were dropped for that reason so far."""

    @property
    def integrated(self) -> bool:
        return self.summary is not None


class ScanLoop:
    """The loop that runs clouds through the pipeline into one Mapper, with one set of
    counters (``counts``, guarded by ``counts_lock``) and one error ladder."""

    def __init__(
        self,
        mapper: Mapper,
        placement: PlacementSection,
        sensor_model: SensorModelSection,
        *,
        counts: ScanCounts | None = None,
        counts_lock: AbstractContextManager[Any] | None = None,
        on_placed: ScanCallback | None = None,
        fatal: tuple[type[Exception], ...] = (),
        consume: ScanConsumer | None = None,
    ) -> None:
        self.mapper = mapper
        self.placement = placement
        """How clouds are placed (de-skew, the box); the live worker replaces it on a change."""
        self.sensor_model = sensor_model
        """Which rays are used (``no_return_range``); replaced like ``placement``."""
        self.counts = counts if counts is not None else ScanCounts()
        self.counts_lock: AbstractContextManager[Any] = (
            counts_lock if counts_lock is not None else threading.RLock()
        )
        self.on_placed = on_placed
        self.consume: ScanConsumer = consume if consume is not None else integrate_scan
        """What is done with each placed scan (default: integrated into ``mapper``; the
        live worker's: ``staged``, walked without a lock and merged under one)."""
        self.fatal = fatal
        """Exceptions that end the loop instead of dropping one cloud (the replay's
        ``ReplayError``: no extrinsic for a frame, say)."""

    # --- the two halves ------------------------------------------------------------------

    def prepare(self, msg: Any) -> PreparedScan:
        """Parse a PointCloud2 (any object with its attributes) or a ``ReturnPair``, add its
        no-return rays and count its points; raises ``ScanDropped`` (``malformed``,
        ``empty``)."""
        if isinstance(msg, pipeline.ReturnPair):
            cloud, note = pipeline.parse_pair(msg, self.sensor_model.no_return_range)
        else:
            cloud, note = pipeline.add_no_return_rays(
                pipeline.parse_scan(msg), self.sensor_model.no_return_range
            )
        stamp = pipeline.scan_stamp(msg)
        with self.counts_lock:
            self.counts.points_in += cloud.points_in
            if note and not self.counts.no_return_note:
                self.counts.no_return_note = note
        deadline = pipeline.pose_deadline(cloud, stamp, self.placement.deskew)
        return PreparedScan(cloud, stamp, deadline, str(msg.header.frame_id))

    def finish(
        self, prepared: PreparedScan, poses: PoseSource, extrinsic: Extrinsic
    ) -> tuple[PlacedScan, IntegrationSummary]:
        """Place a prepared cloud at its poses and integrate it (``place``, then
        ``commit``); raises ``ScanDropped`` (placement's reasons, ``no_usable_rays``)."""
        placed = self.place(prepared, poses, extrinsic)
        return placed, self.commit(placed)

    def place(self, prepared: PreparedScan, poses: PoseSource, extrinsic: Extrinsic) -> PlacedScan:
        """A prepared cloud's rays in the map frame at its poses (de-skew, extrinsic, height
        band, the echoes of a shot as one process: ``pipeline.echo_rays``); raises
        ``ScanDropped`` (``no_poses``, ``too_new``, ``too_old``, ``gap``,
        ``empty``). A caller may move the placed rays (pose refinement) before ``commit``."""
        placed = pipeline.echo_rays(
            pipeline.place_scan(prepared.cloud, prepared.stamp, poses, extrinsic, self.placement),
            self.sensor_model,
        )
        if self.on_placed is not None:
            self.on_placed(placed.stamp, placed.points, placed.origins)
        return placed

    def commit(self, placed: PlacedScan) -> IntegrationSummary:
        """Integrate placed rays (``consume``) and count them; raises ``ScanDropped``
        (``no_usable_rays``)."""
        summary = self.consume(self.mapper, placed)
        with self.counts_lock:
            self.counts.add(placed, summary)
        return summary

    # --- the error ladder ----------------------------------------------------------------

    def count_drop(self, drop: ScanDropped) -> int:
        """Count a dropped cloud and its points; returns the count for its reason."""
        with self.counts_lock:
            return self.counts.dropped_scan(drop)

    def count_error(self, err: BaseException) -> tuple[str, int]:
        """Count an unexpected exception as an ``error`` drop; returns its one-line text and
        the count of errors so far."""
        with self.counts_lock:
            return f"{type(err).__name__}: {err}", self.counts.drop("error")

    def map_cloud(
        self, msg: Any, poses: PoseSource, extrinsic_of: Callable[[str], Extrinsic]
    ) -> Outcome:
        """One received cloud through both halves and the ladder (its poses are known):
        never raises for a bad cloud, a missing pose or a bug; the outcome says what
        happened. ``extrinsic_of(frame_id)`` gives the cloud frame's extrinsic."""
        with self.counts_lock:
            self.counts.clouds_in += 1
        try:
            prepared = self.prepare(msg)
            placed, summary = self.finish(
                prepared, poses, extrinsic_of(frame_name(prepared.frame_id))
            )
        except ScanDropped as drop:
            return Outcome(reason=drop.reason, detail=drop.detail, count=self.count_drop(drop))
        except self.fatal:
            raise
        except Exception as err:  # a bug: counted as the node does; the loop goes on
            detail, count = self.count_error(err)
            return Outcome(reason="error", detail=detail, count=count)
        return Outcome(placed, summary)


def integrate_scan(mapper: Mapper, placed: PlacedScan) -> IntegrationSummary:
    """Integrate placed rays; ScanDropped ``no_usable_rays`` when the core used none
    (the map is then unchanged; the drop carries the placed scan's and the core's point
    drops; on success ``ScanCounts.add`` counts both)."""
    return require_rays(
        mapper.integrate(
            placed.points, placed.origins, placed.stamp, placed.no_return,
            scan_reflectivity(mapper, placed), placed.continued,
        ),
        placed,
    )  # fmt: skip


def scan_reflectivity(mapper: Mapper, placed: PlacedScan) -> ScanReflectivity | None:
    """The placed rays' intensities and the bins the map takes them in: the map's own bins
    when it holds histograms of the same field, else ``reflectivity_bins`` bins of the
    field's edges (``sensing.reflectivity``); None without an intensity field, with
    ``reflectivity_bins`` 0, or when the map holds histograms of another field."""
    field_name = placed.intensity_field
    if placed.intensity is None or field_name is None:
        return None
    held = mapper.reflectivity_scale
    if held is not None:
        bins = held if held.field == field_name else None
    else:
        bins = bins_for(field_name, mapper.reflectivity_bins)
    return None if bins is None else ScanReflectivity(placed.intensity, bins)


def merge_scan(
    mapper: Mapper,
    placed: PlacedScan,
    merge_lock: AbstractContextManager[Any],
    pause: Callable[[], None] | None = None,
) -> IntegrationSummary:
    """``integrate_scan`` in two steps: walked without any lock (``Mapper.stage``), merged
    under ``merge_lock`` (``Mapper.commit``, ``pause`` between chunks)."""
    staged = mapper.stage(
        placed.points, placed.origins, placed.stamp, placed.no_return,
        scan_reflectivity(mapper, placed), placed.continued,
    )  # fmt: skip
    require_rays(staged.summary, placed)
    with merge_lock:
        return mapper.commit(staged, pause=pause)


def require_rays(summary: IntegrationSummary, placed: PlacedScan) -> IntegrationSummary:
    """``summary``, or ScanDropped ``no_usable_rays`` when the core used none of the placed
    scan's rays (see ``integrate_scan``)."""
    if summary.rays_used == 0:
        lost = ", ".join(f"{k} {v}" for k, v in summary.dropped.items() if v) or "none"
        dropped = Counter(placed.points_dropped)
        dropped.update({k: v for k, v in summary.dropped.items() if v})
        raise ScanDropped(
            "no_usable_rays",
            f"the core used none of its {summary.rays_in} rays (dropped: {lost})",
            points_dropped=dict(dropped),
        )
    return summary
