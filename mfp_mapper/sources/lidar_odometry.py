"""Poses estimated from the clouds themselves with KISS-ICP (``--odometry kiss-icp``), for
recordings without odometry: a bag with clouds only, or a folder of scans.

KISS-ICP (Vizzo et al. 2023, ``kiss-icp`` on PyPI) is an optional dependency: only this
module imports it, and a clear error names the package when it is absent. Its map frame is
the lidar frame of the first scan (``MAP_FRAME``). When clouds carry per-point time and
de-skew is on, KISS-ICP de-skews each scan to the time of its LAST point, so its pose
belongs to that time (``stamp + max time offset``); without per-point time, to the stamp.
The first scan has no motion to de-skew with (KISS-ICP takes it as static): its pose also
holds at its first point's time, so that the replay can place it.
The poses are then interpolated by the scan pipeline like odometry.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from mfp_mapper.config.replay_options import ReplayError
from mfp_mapper.sensing.pointcloud import parse_pointcloud2, stamp_seconds
from mfp_mapper.sources.pose_files import matrix_to_quaternion, pose_buffer
from mfp_mapper.sources.recording import Poses

KISS_ICP = "kiss-icp"
MAP_FRAME = "kiss_icp_map"
"""The map frame of estimated poses: the lidar frame at the first scan."""
FEW_POINTS = 100
"""A cloud with fewer points gives KISS-ICP too little to register: warned."""


def kiss_icp_available() -> bool:
    try:
        import kiss_icp  # type: ignore[import-untyped]  # noqa: F401
    except ImportError:
        return False
    return True


def _kiss(opts: Any, deskew: bool) -> Any:
    try:
        from kiss_icp.config import KISSConfig  # type: ignore[import-untyped]
        from kiss_icp.kiss_icp import KissICP  # type: ignore[import-untyped]
    except ImportError:
        raise ReplayError(
            "--odometry kiss-icp needs the Python package kiss-icp: pip install kiss-icp "
            "(pinned in requirements-dev.txt; ./run setup installs it)"
        ) from None
    config = KISSConfig()
    config.data.max_range = float(opts.sensor_model.core("max_range"))
    config.data.min_range = float(opts.sensor_model.min_range)
    config.data.deskew = deskew
    config.mapping.voxel_size = (
        float(opts.sensor_model.core("max_range")) / 100.0
    )  # KISS-ICP's own default rule
    config.registration.max_num_threads = int(opts.map.core("threads"))
    return KissICP(config)


def estimate_poses(
    clouds: Iterable[tuple[float | None, Callable[[], Any]]],
    opts: Any,
    total: int = 0,
    log: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """KISS-ICP over ``clouds`` ((stamp or None, load PointCloud2-like message)): the
    stamps (N,) and 4x4 poses (N, 4, 4) of the lidar in the first scan's lidar frame.
    Clouds that do not parse are left out (counted in the log line)."""
    icp: Any = None
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    skipped = 0
    sparse: list[int] = []  # point counts of the clouds too small to register
    started = time.perf_counter()
    for _, load in clouds:
        try:
            msg = load()
            stamp = stamp_seconds(msg.header.stamp)
            cloud = parse_pointcloud2(msg)
        except Exception:  # malformed: the replay counts it again later
            skipped += 1
            continue
        if len(cloud) == 0:  # empty: likewise
            skipped += 1
            continue
        if len(cloud) < FEW_POINTS:
            sparse.append(len(cloud))
        times = cloud.time_offset
        deskew = bool(opts.placement.deskew and times is not None and np.ptp(times) > 0)
        if icp is None:
            icp = _kiss(opts, deskew)
        xyz = np.ascontiguousarray(cloud.xyz, dtype=np.float64)
        offsets = times if deskew and times is not None else np.zeros(len(xyz))
        icp.register_frame(xyz, np.ascontiguousarray(offsets, dtype=np.float64))
        if deskew and not stamps:  # KISS-ICP took the first scan as static: same pose at its start
            stamps.append(stamp + float(offsets.min()))
            poses.append(icp.last_pose.copy())
        end = stamp + (float(offsets.max()) if deskew else 0.0)
        if stamps and end <= stamps[-1]:
            skipped += 1  # a cloud not after the previous one: no pose from it
            continue
        stamps.append(end)
        poses.append(icp.last_pose.copy())
    if not poses:
        raise ReplayError(f"KISS-ICP: none of the {skipped} clouds could be read")
    if log is not None:
        log(
            f"KISS-ICP: {len(poses)} poses of {total or len(poses) + skipped} clouds in "
            f"{time.perf_counter() - started:.1f} s"
            + (f" ({skipped} unreadable)" if skipped else "")
        )
        if sparse:
            log(
                f"warning: KISS-ICP: {len(sparse)} of {len(poses) + skipped} clouds have fewer "
                f"than {FEW_POINTS} points (smallest {min(sparse)}): too few to register, "
                "the poses estimated from them are unreliable"
            )
    return np.array(stamps), np.array(poses)


def odometry_poses(
    clouds: Iterable[tuple[float | None, Callable[[], Any]]],
    opts: Any,
    cloud_frame: str,
    total: int = 0,
    log: Callable[[str], None] | None = None,
) -> Poses:
    """``Poses`` of the lidar (body = ``cloud_frame``) estimated by KISS-ICP."""
    if opts.replay.odometry != KISS_ICP:
        raise ReplayError(f"unknown odometry {opts.replay.odometry!r} (known: {KISS_ICP})")
    stamps, matrices = estimate_poses(clouds, opts, total, log)
    buffer = pose_buffer(
        stamps,
        matrices[:, :3, 3],
        matrix_to_quaternion(matrices[:, :3, :3]),
        opts.placement.odom_max_gap,
        "KISS-ICP poses",
    )
    source = f"KISS-ICP on the clouds ({len(stamps)} poses; {MAP_FRAME} = first lidar frame)"
    return Poses(buffer, cloud_frame, MAP_FRAME, source)
