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
   band (``no_poses``, ``too_new``, ``too_old``, ``gap``);
4. (``mapping.loop``) integration into the Mapper (``no_usable_rays`` when the core used
   no ray).

A drop is a ``ScanDropped`` exception carrying its ``reason``; point-level losses
(NaN, zero range, height band, the core's own) are counted per reason by the loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.sections import PlacementSection
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
    flags = cloud.no_return
    if keep is not None:
        points = points[keep]
        origins = origins[keep] if origins.ndim == 2 else origins
        flags = flags[keep] if flags is not None else None
    if points.shape[0] == 0:
        bounds = ", ".join(f"{a} [{lo[k]}, {hi[k]}]" for k, a in enumerate("xyz"))
        raise ScanDropped(
            "empty",
            f"all {sum(outside.values())} rays end outside the bounds ({bounds} m)",
            points_dropped=dropped,
        )
    deskewed = bool(settings.deskew and cloud.time_offset is not None)
    return PlacedScan(stamp, points, origins, deskewed, dropped, flags)


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
