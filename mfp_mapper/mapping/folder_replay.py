"""Replay a folder of scan files (``sources.scan_folder``) into a Mapper, with poses from a
pose file (``sources.pose_files``), ``identity``, or KISS-ICP (``sources.lidar_odometry``).

The clouds go through the same loop as a bag's (``mapping.replay.map_scans``): the node's
scan pipeline, the same drops, summary and progress, and the same selection options.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.loop import ScanConsumer
from mfp_mapper.mapping.progress import Progress
from mfp_mapper.mapping.replay import (
    ReplayOptions,
    ReplayResult,
    ReplaySummary,
    ScanCallback,
    map_scans,
    mapper_for,
)
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sources import lidar_odometry, pose_files
from mfp_mapper.sources.bags import Poses, ReplayError
from mfp_mapper.sources.scan_files import DatasetFormatError
from mfp_mapper.sources.scan_folder import ScanFolder, open_scan_folder

IDENTITY = "identity"


def replay_folder(
    directory: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions | None = None,
    times_file: str | Path | None = None,
    progress: bool | Progress = True,
    log: Callable[[str], None] | None = None,
    on_scan: ScanCallback | None = None,
    into: Mapper | None = None,
    consume: ScanConsumer | None = None,
) -> ReplayResult:
    """Map the scans of ``directory``; ``poses`` is a pose file, ``"identity"``, or None
    with ``opts.replay.odometry == "kiss-icp"``. ReplayError says why when it cannot be done.
    ``into``: add the scans to this map; ``consume``: instead of integrating each scan
    (as ``mapping.replay.replay``)."""
    opts = opts or ReplayOptions()
    try:
        folder = open_scan_folder(directory, times_file)
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    if folder.skipped and log is not None:
        log(f"warning: {folder.directory}: skipped {len(folder.skipped)} entries named like "
            f"scan files: {', '.join(folder.skipped)}")  # fmt: skip
    summary = ReplaySummary(bag=str(folder.directory))
    summary.cloud_topic = f"{len(folder)} {folder.kind} files (stamps: {folder.stamp_source})"
    summary.scans_total = len(folder)
    summary.cloud_frame = folder.frame_id
    t_poses = time.perf_counter()
    found = folder_poses(folder, poses, opts, log)
    summary.seconds_poses = time.perf_counter() - t_poses
    summary.pose_source, summary.map_frame = found.source, found.map_frame
    extrinsic = (
        Extrinsic.from_xyz_rpy(*opts.replay.extrinsic) if opts.replay.extrinsic else Extrinsic()
    )
    summary.extrinsic_source = (
        "given on the command line" if opts.replay.extrinsic else "identity (poses are the lidar's)"
    )
    mapper = mapper_for(opts, found.map_frame, into)

    def clouds() -> Iterator[tuple[int, Callable[[], Any]]]:
        for index in range(len(folder)):
            yield index, partial(folder.message, index)

    map_scans(
        clouds(), found, lambda _: extrinsic, opts, mapper, summary, progress, log, on_scan, consume
    )
    return ReplayResult(mapper, summary)


def folder_poses(
    folder: ScanFolder,
    poses: str | Path | None,
    opts: ReplayOptions,
    log: Callable[[str], None] | None = None,
) -> Poses:
    """The poses of the folder's scans (``Poses.buffer`` is any pose source)."""
    if opts.replay.odometry is not None:
        if poses is not None:
            raise ReplayError("give either --poses or --odometry, not both")

        return lidar_odometry.odometry_poses(
            ((scan.stamp, partial(folder.message, k)) for k, scan in enumerate(folder.scans)),
            opts,
            folder.frame_id,
            len(folder),
            log,
        )
    if poses is None:
        raise ReplayError(
            f"{folder.directory}: a scan folder needs poses: --poses FILE (KITTI, TUM or "
            "odometry CSV), --poses identity (single frames) or --odometry kiss-icp"
        )
    if str(poses) == IDENTITY:
        return Poses(pose_files.FixedPose.identity(), folder.frame_id, folder.frame_id, IDENTITY)  # type: ignore[arg-type]
    path = Path(poses)
    try:
        kind = pose_files.guess_pose_format(path)
        stamps = np.array([scan.stamp for scan in folder.scans])
        if kind == "kitti":
            positions, quaternions = pose_files.read_kitti_poses(path)
            if len(positions) != len(stamps):
                skipped = f"; skipped: {', '.join(folder.skipped)}" if folder.skipped else ""
                raise DatasetFormatError(
                    f"{path}: {len(positions)} KITTI poses for {len(stamps)} scans (one per "
                    f"scan){skipped}"
                )
        else:
            stamps, positions, quaternions = pose_files.read_stamped_poses(path, kind)
        buffer = pose_files.pose_buffer(
            stamps, positions, quaternions, opts.placement.odom_max_gap, str(path)
        )
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    if kind != "kitti" and folder.stamp_source.startswith("none"):
        raise ReplayError(
            f"{path}: {kind.upper()} poses are matched by time, but the scans have no stamps "
            "(give a times file with --times, or name the files by their time)"
        )
    what = "odometry CSV, T_map_body" if kind == "csv" else f"{kind.upper()}, T_world_lidar"
    return Poses(buffer, folder.frame_id, "world", f"{path} ({what})")
