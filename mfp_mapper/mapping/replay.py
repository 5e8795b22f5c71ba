"""Replay a recording (``sources.recording.Recording``: a bag, a folder of scan files, a
simulation) into a Mapper, offline.

Recordings are opened by ``sources.opener.open_recording``, which says where the poses come
from (odometry, /tf, a pose file, KISS-ICP, the simulator's truth) and the lidar extrinsic.
Every cloud goes through the node's scan pipeline (``sensing.pipeline``): the same parsing,
interpolation, de-skew and height band, and the same drop reasons. Nothing is written here:
the caller saves the map (atomically) only when the replay succeeded, so a failed replay
never leaves a map that looks complete.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mfp_mapper.config.replay_options import ConfigError as ConfigError  # re-exported
from mfp_mapper.config.replay_options import ReplayError as ReplayError  # re-exported
from mfp_mapper.config.replay_options import ReplayOptions, options_from_yaml
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.loop import ScanCallback, ScanConsumer, ScanCounts, ScanLoop
from mfp_mapper.mapping.progress import Progress
from mfp_mapper.sensing import pipeline
from mfp_mapper.sources.opener import opened
from mfp_mapper.sources.recording import Recording

__all__ = [
    "ConfigError",
    "NothingMapped",
    "Progress",
    "ReplayError",
    "ReplayOptions",
    "ReplayResult",
    "ReplaySummary",
    "options_from_yaml",
    "replay",
]


class NothingMapped(ReplayError):
    """The bag was read, but no cloud (in the ``start``/``end`` window) could be mapped."""


class OtherMapFrame(ReplayError):
    """The recording's map frame is not the one of the map it was to be added to."""


# --- summary and progress ---------------------------------------------------------------------


@dataclass
class ReplaySummary:
    """What a replay did; ``format()`` gives the lines printed at the end."""

    bag: str
    cloud_topic: str = ""
    pose_source: str = ""
    map_frame: str = ""
    cloud_frame: str = ""
    extrinsic_source: str = ""
    deskew: bool = False
    scans_total: int = 0
    scans_selected: int = 0
    scans_used: int = 0
    clouds_dropped: dict[str, int] = field(default_factory=dict)
    """Clouds not integrated, by reason (``sensing.pipeline.DROP_REASONS``, as ``~/status``)."""
    points_in: int = 0
    rays_used: int = 0
    rays_truncated: int = 0
    rays_cut_by_budget: int = 0
    """Rays walked part of their way to keep a scan within its block bound (``loop.ScanCounts``)."""
    rays_no_return: int = 0
    """Recovered firings with no return that were integrated (``--no-return-range``)."""
    no_return_note: str = ""
    """Why firings were not (all) recovered, the first time it happened."""
    points_dropped: dict[str, int] = field(default_factory=dict)
    """Points and rays not used, by reason (as ``~/status``)."""
    voxels: int = 0
    memory_bytes: int = 0
    seconds: float = 0.0
    seconds_core: float = 0.0
    seconds_poses: float = 0.0
    first_stamp: float | None = None
    last_stamp: float | None = None
    second_return: dict[str, int] | None = None
    """With a second-return topic paired (``second_return_topic``): the pairer's counts
    (``paired``, ``alone``, ``unpaired_second``, ``mismatched``, as ``~/status``)."""
    second_return_note: str = ""
    """Why a second cloud was not paired with its first (grids that differ), the first time."""

    @property
    def rays_per_second(self) -> float:
        return self.rays_used / self.seconds if self.seconds > 0 else 0.0

    @property
    def share_outside_core(self) -> float:
        """Share of the replay time spent outside Mapper.integrate (reading, parsing, poses)."""
        return 1.0 - self.seconds_core / self.seconds if self.seconds > 0 else 0.0

    @classmethod
    def of(cls, recording: Recording) -> ReplaySummary:
        """A summary of ``recording`` before any cloud is mapped."""
        return cls(
            bag=recording.name,
            cloud_topic=recording.cloud_source,
            pose_source=recording.poses.source,
            map_frame=recording.map_frame,
            cloud_frame=recording.cloud_frame,
            extrinsic_source=recording.extrinsic_source,
            scans_total=recording.cloud_count,
            seconds_poses=recording.seconds_poses,
        )

    def format(self) -> str:
        n_dropped = sum(self.clouds_dropped.values())
        dropped = {k: v for k, v in self.points_dropped.items() if v}
        lines = [
            f"bag          {self.bag}",
            f"clouds       {self.cloud_topic} (frame {self.cloud_frame or '?'})",
            f"poses        {self.pose_source}; map frame {self.map_frame or '?'}",
            f"extrinsic    {self.extrinsic_source}",
            f"de-skew      {'yes (per-point time)' if self.deskew else 'no'}",
            f"scans        {self.scans_used} used of {self.scans_total}"
            + (
                f" ({self.scans_selected} selected)"
                if self.scans_selected != self.scans_total
                else ""
            )
            + (f"; dropped {n_dropped}: {_counts(self.clouds_dropped)}" if n_dropped else ""),
            f"rays         {self.rays_used:,} used of {self.points_in:,} points"
            + (f"; {self.rays_truncated:,} cut at max range" if self.rays_truncated else "")
            + (
                f"; {self.rays_cut_by_budget:,} cut by a scan's block bound"
                if self.rays_cut_by_budget
                else ""
            )
            + (f"; {self.rays_no_return:,} with no return" if self.rays_no_return else ""),
            *([f"2nd returns  {_counts(self.second_return)}"] if self.second_return else []),
            *([f"2nd returns  {self.second_return_note}"] if self.second_return_note else []),
            f"points lost  {_counts(dropped) if dropped else 'none'}",
            *([f"no-return    {self.no_return_note}"] if self.no_return_note else []),
            f"voxels       {self.voxels:,} ({self.memory_bytes / 2**20:.1f} MiB)",
            f"time         {self.seconds:.2f} s, {self.rays_per_second:,.0f} rays/s; "
            f"{100 * self.share_outside_core:.0f}% outside the core "
            f"(+{self.seconds_poses:.2f} s reading poses)",
        ]
        return "\n".join(lines)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v:,}" for k, v in sorted(d.items()))


# --- the replay -------------------------------------------------------------------------------


@dataclass
class ReplayResult:
    mapper: Mapper
    summary: ReplaySummary


def replay(
    recording: Recording | str | Path,
    opts: ReplayOptions | None = None,
    progress: bool | Progress = True,
    log: Callable[[str], None] | None = None,
    on_scan: ScanCallback | None = None,
    into: Mapper | None = None,
    consume: ScanConsumer | None = None,
) -> ReplayResult:
    """Map every selected cloud of ``recording`` (or of the bag at that path, opened and
    closed here); ReplayError (with the reason) when it cannot be done.

    ``on_scan(stamp, points, origins)`` sees every placed cloud (map frame) just before it
    is integrated, e.g. to feed the same rays to another mapper. ``into``: add the clouds
    to this map (built with the same options) instead of a new one (OtherMapFrame, before
    any cloud is read, when its frame is not the recording's). ``consume(mapper, placed)``
    replaces the integration of each placed scan (``loop.ScanConsumer``), e.g. to score
    the scans against another map.
    """
    opts = opts or ReplayOptions()
    with opened(recording, opts, log) as rec:
        summary = ReplaySummary.of(rec)
        mapper = mapper_for(opts, rec.map_frame, into)
        map_scans(rec, opts, mapper, summary, progress, log, on_scan, consume)
    return ReplayResult(mapper, summary)


def new_mapper(opts: ReplayOptions, frame_id: str) -> Mapper:
    """An empty Mapper with the options' map section."""
    return Mapper.of(opts.map, opts.sensor_model, frame_id=frame_id)


def mapper_for(opts: ReplayOptions, frame_id: str, into: Mapper | None) -> Mapper:
    """``into`` when given (OtherMapFrame unless its frame is ``frame_id``), else a new map."""
    if into is None:
        return new_mapper(opts, frame_id)
    if into.frame_id != frame_id:
        raise OtherMapFrame(
            f"its map frame {frame_id!r} is not {into.frame_id!r}, the frame of the "
            "recordings before it: maps of different frames cannot be added up"
        )
    return into


class ScanSelection:
    """Which clouds a replay maps: ``start_index``/``end_index``, ``start``/``end``
    (absolute, or ``*_offset`` after the first cloud), one in ``every``, ``max_scans``."""

    def __init__(self, opts: ReplayOptions) -> None:
        if opts.replay.every < 1:
            raise ReplayError(f"every must be >= 1, got {opts.replay.every}")
        if opts.replay.start_index < 0 or (
            opts.replay.end_index is not None and opts.replay.end_index < 0
        ):
            raise ReplayError("scan indices start at 0")
        self.opts = opts
        self.first_stamp: float | None = None
        self.taken = 0
        self.in_window = 0

    def by_index(self, index: int) -> bool:
        """False when ``index`` is outside ``[start_index, end_index)`` (cheap: no read)."""
        end = self.opts.replay.end_index
        return index >= self.opts.replay.start_index and (end is None or index < end)

    def past_end(self, index: int) -> bool:
        end, cap = self.opts.replay.end_index, self.opts.replay.max_scans
        return (end is not None and index >= end) or (cap is not None and self.taken >= cap)

    def by_stamp(self, stamp: float, index: int) -> bool:
        """True when the cloud at ``stamp`` is in the time window and its turn in ``every``."""
        if self.first_stamp is None:
            self.first_stamp = stamp
        lo, hi = self._window()
        if stamp < lo or stamp >= hi:
            return False
        turn = self.in_window % self.opts.replay.every == 0
        self.in_window += 1
        return turn

    def _window(self) -> tuple[float, float]:
        o, first = self.opts.replay, self.first_stamp or 0.0
        lo = max(
            o.start if o.start is not None else -math.inf,
            first + o.start_offset if o.start_offset is not None else -math.inf,
        )
        hi = min(
            o.end if o.end is not None else math.inf,
            first + o.end_offset if o.end_offset is not None else math.inf,
        )
        return lo, hi


def map_scans(
    recording: Recording,
    opts: ReplayOptions,
    mapper: Mapper,
    summary: ReplaySummary,
    progress: bool | Progress,
    log: Callable[[str], None] | None,
    on_scan: ScanCallback | None,
    consume: ScanConsumer | None = None,
) -> None:
    """Run the selected clouds of ``recording`` through the scan pipeline into ``mapper``
    (or ``consume``); fills ``summary``; ReplayError when no cloud could be mapped."""
    select = ScanSelection(opts)
    if opts.replay.max_scans is not None:
        summary.scans_total = min(summary.scans_total, opts.replay.max_scans)
    bar = (
        progress
        if isinstance(progress, Progress)
        else Progress(summary.scans_total, enabled=bool(progress))
    )
    loop = ScanLoop(
        mapper,
        opts.placement,
        opts.sensor_model,
        on_placed=on_scan,
        fatal=(ReplayError,),
        consume=consume,
    )
    counts = loop.counts
    bad_example = error_example = empty_example = ""
    cloud_span = [math.inf, -math.inf]
    t_loop = time.perf_counter()
    try:
        for index, load in recording.clouds():
            if select.past_end(index):
                break
            if not select.by_index(index):
                continue
            try:
                msg = load()
                stamp = pipeline.scan_stamp(msg)
            except Exception as err:  # a damaged message: skip, count, say what it was
                counts.clouds_in += 1
                counts.drop("malformed")
                bad_example = bad_example or f"{type(err).__name__}: {err}"
                continue
            if not select.by_stamp(stamp, index):
                continue
            select.taken += 1
            cloud_span = [min(cloud_span[0], stamp), max(cloud_span[1], stamp)]
            outcome = loop.map_cloud(msg, recording.pose_source, recording.extrinsic_of)
            if outcome.reason == "malformed":
                bad_example = bad_example or outcome.detail
            elif outcome.reason == "error":
                error_example = error_example or outcome.detail
            elif outcome.reason == "empty":
                empty_example = empty_example or outcome.detail
            if outcome.placed is None or outcome.summary is None:
                continue
            summary.seconds_core += outcome.summary.seconds
            summary.deskew |= outcome.placed.deskewed
            first = summary.first_stamp if summary.first_stamp is not None else stamp
            last = summary.last_stamp if summary.last_stamp is not None else stamp
            summary.first_stamp, summary.last_stamp = min(first, stamp), max(last, stamp)
            bar.update(index + 1, counts.rays_used)
        bar.update(summary.scans_total, counts.rays_used, force=True)
    finally:
        bar.close()
    _fill(summary, counts, mapper)
    pairer = recording.second_returns()
    if pairer is not None:
        summary.second_return = pairer.counts()
        summary.second_return_note = pairer.mismatch_note
        if pairer.mismatch_note and log is not None:
            log(f"warning: {pairer.mismatched} second-return cloud(s) not paired: "
                f"{pairer.mismatch_note}")  # fmt: skip
    summary.scans_selected = counts.clouds_in
    summary.seconds = time.perf_counter() - t_loop
    examples = "".join(
        f"; first {what}: {text}"
        for what, text in (
            ("bad cloud", bad_example),
            ("empty cloud", empty_example),
            ("error", error_example),
        )
        if text
    )
    if summary.scans_used == 0:
        raise NothingMapped(_nothing_mapped(summary, recording, examples, cloud_span, opts))
    if summary.clouds_dropped and log is not None:
        log(
            f"warning: {sum(summary.clouds_dropped.values())} of {summary.scans_selected} "
            f"scans dropped ({_counts(summary.clouds_dropped)}){examples}"
        )


def _fill(summary: ReplaySummary, counts: ScanCounts, mapper: Mapper) -> None:
    summary.scans_used = counts.clouds_integrated
    summary.clouds_dropped = dict(counts.clouds_dropped)
    summary.points_in = counts.points_in
    summary.rays_used = counts.rays_used
    summary.rays_truncated = counts.rays_truncated
    summary.rays_cut_by_budget = counts.rays_cut_by_budget
    summary.rays_no_return = counts.rays_no_return
    summary.no_return_note = counts.no_return_note
    summary.points_dropped = dict(counts.points_dropped)
    summary.voxels = mapper.num_voxels
    summary.memory_bytes = mapper.memory_bytes


def _nothing_mapped(
    summary: ReplaySummary,
    recording: Recording,
    examples: str,
    cloud_span: list[float],
    opts: ReplayOptions,
) -> str:
    reasons = _counts(summary.clouds_dropped) or "none"
    text = (
        f"no cloud could be mapped ({summary.scans_selected} of {summary.scans_total} clouds "
        f"selected; dropped: {reasons})"
    )
    if (opts.replay.start is not None or opts.replay.end is not None) and cloud_span[
        0
    ] > cloud_span[1]:
        text += f"; no cloud stamp lies in the window [{opts.replay.start}, {opts.replay.end}) s"
    text += examples
    if {"no_poses", "too_new", "too_old", "gap"} & set(summary.clouds_dropped):
        poses = recording.poses
        text += (
            f". No pose covers the clouds: poses from {poses.source} span "
            f"[{poses.buffer.earliest_stamp:.3f}, {poses.buffer.latest_stamp:.3f}] s, "
            f"the clouds (header stamps) [{cloud_span[0]:.3f}, {cloud_span[1]:.3f}] s"
            f" (max gap between poses {poses.buffer.max_gap} s)"
        )
    return text
