"""The stages of the scan pipeline: a received cloud -> placed rays in the map frame, or a
drop with a reason. No Mapper here: the one loop (``mapping.loop.ScanLoop``), which the live
node's worker and every offline replay run, chains these stages, integrates the placed rays
and counts everything under the names of ``DROP_REASONS``:

1. ``parse_scan``: PointCloud2 (any object with its attributes) -> ``ParsedCloud``
   (``malformed``, ``empty``); ``add_no_return_rays`` (``no_return_range`` > 0) appends
   the firings that returned nothing (``sensing.no_return``) as flagged rays, which are
   de-skewed, placed and banded like the returns and integrated with no return;
2. ``pose_deadline``: the latest time a pose must cover (the stamp, or the last point's
   time when de-skewing) — the live worker waits for odometry up to it;
3. ``place_scan``: points into the map frame at the poses of their times, then the height
   band (``no_poses``, ``too_new``, ``too_old``, ``gap``); ``echo_rays``: a cloud whose
   points carry shots (``ParsedCloud.shot``: several echoes per laser shot) becomes one ray
   per echo, a shot one process along its beam (``sensing.echoes``); a ``ReturnPair``
   (ouster-ros ``points`` + ``points2``) is parsed as one cloud by ``parse_pair``;
4. (``mapping.loop``) integration into the Mapper (``no_usable_rays`` when the core used
   no ray).

A drop is a ``ScanDropped`` exception carrying its ``reason``; point-level losses
(NaN, zero range, height band, the core's own) are counted per reason by the loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.sections import PlacementSection, SensorModelSection
from mfp_mapper.sensing import echoes
from mfp_mapper.sensing.deskew import PoseSource, cloud_to_map
from mfp_mapper.sensing.no_return import with_no_return_rays
from mfp_mapper.sensing.pointcloud import (
    CloudFormatError,
    ParsedCloud,
    parse_pointcloud2,
    stamp_seconds,
)
from mfp_mapper.sensing.poses import Extrinsic, PoseUnavailable

FloatArray = NDArray[np.float64]

DROP_REASONS: dict[str, str] = {
    "queue_full": "integration fell behind; the oldest queued cloud was dropped (live only)",
    "superseded": "placed while the localization's wide search ran, and a newer cloud came: "
    "the newest is aligned after the search (live localization only)",
    "clock_jump": "queued when the clock jumped back (bag loop): buffers cleared (live only)",
    "malformed": "not a parsable cloud: no x/y/z, fields beyond point_step, truncated data, "
    "unknown datatypes",
    "empty": "no valid point (all NaN/Inf or zero range), or none in the height band",
    "no_frame": "the cloud's header.frame_id is empty (parameter cloud_frame_id says what it "
    "means)",
    "ahead_of_clock": "stamped further ahead of the node clock than any pose can be (live only)",
    "no_poses": "no pose at all (no odometry or transform received)",
    "tf_conflict": "a frame of the TF chain gets its parent alternately from two publishers",
    "too_new": "the poses never reached the cloud's time (live: within odom_wait)",
    "too_old": "the cloud is older than the poses kept",
    "gap": "the cloud lies between two poses further apart than odom_max_gap",
    "no_extrinsic": "the lidar pose in the robot frame is unknown",
    "no_usable_rays": "the core could use none of its rays (e.g. all out of the indexable range)",
    "error": "an unexpected error (a bug): logged with its message",
}
"""Every reason a whole cloud is dropped, by the live node and the replay alike."""


class ScanDropped(Exception):
    """A cloud that cannot be mapped; ``reason`` is a key of ``DROP_REASONS``.

    ``points_in`` and ``points_dropped`` are the points of the cloud not counted yet (an
    empty cloud's NaN points, say), so that point counts stay complete.
    """

    def __init__(
        self,
        reason: str,
        detail: str,
        points_in: int = 0,
        points_dropped: dict[str, int] | None = None,
    ) -> None:
        if reason not in DROP_REASONS:
            raise ValueError(f"unknown drop reason {reason!r}")
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
        self.points_in = points_in
        self.points_dropped = points_dropped or {}


@dataclass
class PlacedScan:
    """Rays of one cloud in the map frame: ends ``points`` (N, 3) seen from ``origins``
    ((3,) or (N, 3) when de-skewed), at ``stamp``; ``points_dropped`` by reason."""

    stamp: float
    points: FloatArray
    origins: FloatArray
    deskewed: bool
    points_dropped: dict[str, int] = field(default_factory=dict)
    no_return: NDArray[np.bool_] | None = None
    """Rays that end without a return (recovered firings), or None."""
    intensity: NDArray[np.float32] | None = None
    """Each ray's return intensity (``ParsedCloud.intensity``), or None."""
    intensity_field: str | None = None
    """The cloud field ``intensity`` came from (``ParsedCloud.intensity_field``)."""
    shot: NDArray[np.int64] | None = None
    """Which laser shot each ray belongs to (``ParsedCloud.shot``: ids >= 0 after
    ``echo_rays``, which drops the -1), or None: every ray its own shot."""
    continued: NDArray[np.bool_] | None = None
    """Rays that continue their shot past an earlier echo (``echo_rays``), or None."""


@dataclass(frozen=True)
class ReturnPair:
    """A cloud of first returns and the cloud of the second returns of the same firings
    (ouster-ros ``points`` and ``points2``: same stamp, same pixel layout), mapped as one
    cloud (``parse_pair``). Its header is the first cloud's."""

    first: Any
    second: Any

    @property
    def header(self) -> Any:
        return self.first.header


def parse_pair(pair: ReturnPair, no_return_range: float) -> tuple[ParsedCloud, str]:
    """The points of both clouds of ``pair`` as one cloud whose shots are the pixels (the
    first cloud's no-return firings recovered first, see ``add_no_return_rays``); raises
    ScanDropped ``malformed`` (either cloud, or layouts that differ) or ``empty``."""
    first = parse_scan(pair.first)
    if first.shot is None:
        first.shot = pixel_shots(first)
    first, note = add_no_return_rays(first, no_return_range)
    try:
        second = parse_pointcloud2(pair.second)
    except CloudFormatError as err:
        raise ScanDropped("malformed", f"second-return cloud: {err}") from None
    if second.grid_shape != (int(pair.first.height), int(pair.first.width)):
        raise ScanDropped(
            "malformed",
            f"second-return cloud of {second.grid_shape[0]} x {second.grid_shape[1]} points "
            f"for a first-return cloud of {pair.first.height} x {pair.first.width}: the two "
            "returns of a pixel must be at the same place of both clouds",
            first.points_in,
            first.dropped,
        )
    return with_second_return(first, second), note


def pixel_shots(cloud: ParsedCloud) -> NDArray[np.int64]:
    """Shots of an organized cloud's points: their pixels (row * width + column)."""
    return (
        np.arange(len(cloud), dtype=np.int64) if cloud.cell is None else cloud.cell.astype(np.int64)
    )


def with_second_return(first: ParsedCloud, second: ParsedCloud) -> ParsedCloud:
    """One cloud of ``first`` (its ``shot`` set: pixels, and maybe recovered no-return
    firings) and ``second``, a cloud of the second returns in the same pixel layout
    (ouster-ros ``points2``): a point of ``second`` joins the shot of its pixel. Per-point
    times and intensities are kept when both clouds have them."""
    assert first.shot is not None
    shot = np.concatenate([first.shot, pixel_shots(second)])
    both = len(first) + len(second)

    def joined(a: NDArray[Any] | None, b: NDArray[Any] | None) -> NDArray[Any] | None:
        return None if a is None or b is None else np.concatenate([a, b])

    flags = None
    if first.no_return is not None:
        flags = np.concatenate([first.no_return, np.zeros(len(second), dtype=np.bool_)])
    dropped = dict(first.dropped)
    for reason, count in second.dropped.items():
        dropped[reason] = dropped.get(reason, 0) + count
    return replace(
        first,
        xyz=np.concatenate([first.xyz, second.xyz]),
        time_offset=joined(first.time_offset, second.time_offset),
        intensity=joined(first.intensity, second.intensity),
        points_in=first.points_in + second.points_in,
        dropped=dropped,
        grid_shape=(1, both),
        cell=None,
        ring=None,
        no_return=flags,
        bad_times=first.bad_times + second.bad_times,
        shot=shot,
        echo_field="second_return",
    )


def parse_scan(msg: Any) -> ParsedCloud:
    """The valid points of a PointCloud2; ScanDropped ``malformed`` or ``empty``."""
    try:
        cloud = parse_pointcloud2(msg)
    except CloudFormatError as err:
        raise ScanDropped("malformed", str(err)) from None
    if len(cloud) == 0:
        why = (
            f"; its per-point time field {cloud.time_field!r} is NaN/Inf at "
            f"{cloud.bad_times} points with a valid position"
            if cloud.bad_times
            else ""
        )
        raise ScanDropped(
            "empty",
            f"none of its {cloud.points_in} points is valid{why}",
            cloud.points_in,
            cloud.dropped,
        )
    return cloud


def add_no_return_rays(cloud: ParsedCloud, no_return_range: float) -> tuple[ParsedCloud, str]:
    """With ``no_return_range`` > 0: ``cloud`` plus its recovered no-return firings as
    flagged points that far along them, and why firings could not (all) be recovered ("" if
    they could). With 0: ``cloud`` unchanged."""
    if not no_return_range > 0:
        return cloud, ""
    extended, found = with_no_return_rays(cloud, no_return_range)
    return extended, found.reason or ""


def scan_stamp(msg: Any) -> float:
    """The cloud's header stamp in seconds."""
    return stamp_seconds(msg.header.stamp)


def pose_deadline(cloud: ParsedCloud, stamp: float, deskew: bool) -> float:
    """The latest time a pose is needed for: the stamp, or its last point's time."""
    if deskew and cloud.time_offset is not None and cloud.time_offset.size:
        return stamp + max(float(cloud.time_offset.max()), 0.0)
    return stamp


def place_scan(
    cloud: ParsedCloud,
    stamp: float,
    poses: PoseSource,
    extrinsic: Extrinsic,
    settings: PlacementSection,
) -> PlacedScan:
    """Points into the map frame at their poses, then the height band.

    Raises ScanDropped (``no_poses``, ``too_new``, ``too_old``, ``gap``), or
    ``empty`` when the height band leaves no ray; either carries the points parsing dropped.
    """
    try:
        points, origins = cloud_to_map(cloud, stamp, poses, extrinsic, deskew=settings.deskew)
    except PoseUnavailable as err:
        raise ScanDropped(err.reason, str(err), points_dropped=dict(cloud.dropped)) from None
    dropped = dict(cloud.dropped)
    lo = tuple(getattr(settings, f"point_cloud_min_{a}") for a in "xyz")
    hi = tuple(getattr(settings, f"point_cloud_max_{a}") for a in "xyz")
    keep, outside = band_mask(points, lo, hi)
    dropped.update({k: v for k, v in outside.items() if v})
    flags, shot = cloud.no_return, cloud.shot
    intensity = cloud.intensity
    if keep is not None:
        points = points[keep]
        origins = origins[keep] if origins.ndim == 2 else origins
        flags = flags[keep] if flags is not None else None
        shot = shot[keep] if shot is not None else None
        intensity = intensity[keep] if intensity is not None else None
    if points.shape[0] == 0:
        bounds = ", ".join(f"{a} [{lo[k]}, {hi[k]}]" for k, a in enumerate("xyz"))
        raise ScanDropped(
            "empty",
            f"all {sum(outside.values())} rays end outside the bounds ({bounds} m)",
            points_dropped=dropped,
        )
    deskewed = bool(settings.deskew and cloud.time_offset is not None)
    return PlacedScan(
        stamp, points, origins, deskewed, dropped, flags, intensity, cloud.intensity_field, shot
    )


def echo_rays(placed: PlacedScan, settings: SensorModelSection) -> PlacedScan:
    """A placed scan whose points carry shots (``shot``) as the core's rays, one per echo
    (``echoes.shot_segments``: a shot's later echoes continue its ray past the blind
    stretch; only the first echoes with ``first_echo_only``); unchanged without shots.
    Raises ScanDropped ``empty`` when no ray is left."""
    if placed.shot is None:
        return placed
    seg = echoes.shot_segments(
        placed.points,
        placed.origins,
        placed.shot,
        placed.no_return,
        settings.echo_blind_stretch,
        settings.core("max_range"),
        settings.min_range,
        settings.first_echo_only,
    )
    dropped = dict(placed.points_dropped)
    for reason, count in seg.dropped.items():
        dropped[reason] = dropped.get(reason, 0) + count
    if seg.points.shape[0] == 0:
        raise ScanDropped("empty", "no echo of any shot is usable", points_dropped=dropped)
    return replace(
        placed,
        points=seg.points,
        origins=seg.origins,
        points_dropped=dropped,
        no_return=seg.no_return,
        intensity=None if placed.intensity is None else placed.intensity[seg.order],
        shot=seg.shot,
        continued=seg.continued if seg.continued.any() else None,
    )


def band_mask(
    points: FloatArray, lo: tuple[float, ...], hi: tuple[float, ...]
) -> tuple[NDArray[np.bool_] | None, dict[str, int]]:
    """Which rays end inside the box ``[lo, hi]`` (map frame x, y, z); None when all do.
    The others are counted as ``xy_band`` (outside in x or y) or ``z_band`` (in x and y,
    outside in z)."""
    xy = (points[:, 0] >= lo[0]) & (points[:, 0] <= hi[0])
    xy &= (points[:, 1] >= lo[1]) & (points[:, 1] <= hi[1])
    z = (points[:, 2] >= lo[2]) & (points[:, 2] <= hi[2])
    keep = xy & z
    if keep.all():
        return None, {}
    xy_out = int(keep.size - xy.sum())
    return keep, {"xy_band": xy_out, "z_band": int(keep.size - keep.sum()) - xy_out}
