"""A folder of scan files as a recording (``open_folder``): the scans in order, with their
stamps, and their poses from a pose file (``sources.pose_files``), ``identity`` or KISS-ICP
(``sources.lidar_odometry``).

Scan files: ``.pcd`` (binary or ascii), ``.ply`` (ascii or binary little-endian), ``.bin``
(KITTI: float32 x y z intensity) and ``.vtk`` (legacy ASCII POLYDATA); one kind per folder.
Stamps, in order of preference:

1. a times file: ``--times FILE``, else ``times.txt`` in the folder or beside it (KITTI):
   one stamp (seconds) per line, line k for the k-th scan in name order;
2. the file names: ``cloud_<sec>_<nanosec>.<ext>`` (nanoseconds not zero-padded), or a
   numeric stem: with a decimal point it is seconds (``1700000000.25.pcd``), an integer of
   18 or more digits (alone or after ``_``, ``vlp16_1673400149711850138.pcd``) nanoseconds;
3. none of these (``000042.bin``): the scan's position times ``scan_period`` (0.1 s).

Scans are taken in time order when the names carry the time, else in natural name order
(``2.pcd`` before ``10.pcd``). Every file becomes a PointCloud2-like message with all its
columns, so a per-point time field (``time_stamp``, ``time``, ``t``...) reaches the de-skew
exactly as from a bag. The poses are the lidar's (the extrinsic is the identity unless
``--extrinsic`` says they are another body's); their map frame is ``world`` for a pose file.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.replay_options import ReplayError, ReplayOptions
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sources import lidar_odometry
from mfp_mapper.sources.pose_files import IDENTITY, guess_pose_format, read_poses
from mfp_mapper.sources.recording import Poses, RecordedCloud, Recording
from mfp_mapper.sources.scan_files import (
    CloudMessage,
    DatasetFormatError,
    cloud_message_from_columns,
    read_kitti_bin,
    read_pcd,
    read_ply,
    read_vtk,
)

READERS: Mapping[str, Callable[[Path], dict[str, NDArray[np.generic]]]] = {
    ".pcd": read_pcd,
    ".ply": read_ply,
    ".bin": read_kitti_bin,
    ".vtk": read_vtk,
}
"""Scan readers by file extension."""

DEFAULT_SCAN_PERIOD = 0.1
_SEC_NSEC = re.compile(r"^[A-Za-z_]*?_?(\d+)_(\d+)$")
_SECONDS = re.compile(r"^\d+\.\d+$")
_NANOSECONDS = re.compile(r"(?:^|_)(\d{18,})$")


@dataclass(frozen=True)
class ScanFile:
    path: Path
    stamp: float


@dataclass
class ScanFolder:
    """The scans of a folder, in order, and where their stamps came from."""

    directory: Path
    scans: list[ScanFile]
    stamp_source: str
    frame_id: str = "lidar"
    skipped: list[str] = field(default_factory=list)
    """Entries with a scan file's name that are no readable file (dangling links, folders)."""

    def __len__(self) -> int:
        return len(self.scans)

    @property
    def kind(self) -> str:
        return self.scans[0].path.suffix.lower() if self.scans else ""

    def message(self, index: int) -> CloudMessage:
        """Scan ``index`` as a PointCloud2-like message stamped with its time."""
        scan = self.scans[index]
        columns = READERS[scan.path.suffix.lower()](scan.path)
        return cloud_message_from_columns(columns, scan.stamp, self.frame_id)


def is_scan_folder(path: str | Path) -> bool:
    """True for a directory holding scan files (and no ROS 2 bag metadata)."""
    p = Path(path)
    return (
        p.is_dir()
        and not (p / "metadata.yaml").exists()
        and any(f.suffix.lower() in READERS for f in p.iterdir() if f.is_file())
    )


def open_scan_folder(
    directory: str | Path,
    times_file: str | Path | None = None,
    scan_period: float = DEFAULT_SCAN_PERIOD,
    frame_id: str = "lidar",
) -> ScanFolder:
    """The scans of ``directory`` (one file kind) with their stamps; DatasetFormatError
    when there are none, several kinds, or a times file that does not match."""
    folder = Path(directory)
    if not folder.is_dir():
        raise DatasetFormatError(f"{folder}: not a directory")
    entries = [f for f in folder.iterdir() if f.suffix.lower() in READERS]
    files = [f for f in entries if f.is_file()]
    skipped = sorted(f"{f.name} ({_not_a_file(f)})" for f in entries if not f.is_file())
    kinds = sorted({f.suffix.lower() for f in files})
    if not files:
        raise DatasetFormatError(
            f"{folder}: no scan files ({', '.join(sorted(READERS))}) in this directory"
        )
    if len(kinds) > 1:
        raise DatasetFormatError(f"{folder}: several scan kinds ({', '.join(kinds)}): keep one")
    files.sort(key=_natural_key)
    times = _times_path(folder, times_file)
    if times is not None:
        stamps = _read_times(times, len(files))
        source = f"times file {times}"
    else:
        named = [_stamp_from_name(f.stem) for f in files]
        if all(s is not None for s in named):
            stamps = [float(s) for s in named if s is not None]
            source = "file names"
        else:
            stamps = [k * scan_period for k in range(len(files))]
            source = f"none found: position x {scan_period:g} s"
    scans = [ScanFile(f, s) for f, s in zip(files, stamps, strict=True)]
    if source == "file names":
        scans.sort(key=lambda scan: scan.stamp)
    if len({s.stamp for s in scans}) != len(scans):
        raise DatasetFormatError(f"{folder}: two scans have the same stamp ({source})")
    return ScanFolder(folder, scans, source, frame_id, skipped)


def open_folder(
    directory: str | Path,
    opts: ReplayOptions,
    poses: str | Path | None = None,
    times_file: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> Recording:
    """The scans of ``directory`` as a recording; ``poses``: a pose file or ``identity``, or
    None with ``opts.replay.odometry`` (KISS-ICP). ReplayError says why it cannot be used."""
    try:
        folder = open_scan_folder(directory, times_file)
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    if folder.skipped and log is not None:
        log(f"warning: {folder.directory}: skipped {len(folder.skipped)} entries named like "
            f"scan files: {', '.join(folder.skipped)}")  # fmt: skip
    t_poses = time.perf_counter()
    found = folder_poses(folder, poses, opts, log)
    seconds_poses = time.perf_counter() - t_poses
    extrinsic = (
        Extrinsic.from_xyz_rpy(*opts.replay.extrinsic) if opts.replay.extrinsic else Extrinsic()
    )

    def clouds() -> Iterator[RecordedCloud]:
        for index in range(len(folder)):
            yield RecordedCloud(index, partial(folder.message, index))

    return Recording(
        name=str(folder.directory),
        cloud_source=f"{len(folder)} {folder.kind} files (stamps: {folder.stamp_source})",
        cloud_frame=folder.frame_id,
        cloud_count=len(folder),
        poses=found,
        extrinsic_source=(
            "given on the command line"
            if opts.replay.extrinsic
            else "identity (poses are the lidar's)"
        ),
        read_clouds=clouds,
        extrinsic_of=lambda _: extrinsic,
        seconds_poses=seconds_poses,
    )


def folder_poses(
    folder: ScanFolder,
    poses: str | Path | None,
    opts: ReplayOptions,
    log: Callable[[str], None] | None = None,
) -> Poses:
    """The poses of the folder's scans: KISS-ICP (``opts.replay.odometry``), or ``poses``."""
    if opts.replay.odometry is not None:
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
    skipped = f"; skipped: {', '.join(folder.skipped)}" if folder.skipped else ""
    stamps = [scan.stamp for scan in folder.scans]
    found = read_poses(poses, folder.frame_id, opts.placement.odom_max_gap, stamps, skipped)
    if str(poses) != IDENTITY and folder.stamp_source.startswith("none"):
        kind = guess_pose_format(Path(poses))  # read already: a readable file
        if kind != "kitti":
            raise ReplayError(
                f"{poses}: {kind.upper()} poses are matched by time, but the scans have no "
                "stamps (give a times file with --times, or name the files by their time)"
            )
    return found


def _not_a_file(path: Path) -> str:
    if path.is_dir():
        return "a folder"
    return "a dangling link" if path.is_symlink() else "not a regular file"


def _natural_key(path: Path) -> list[object]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _stamp_from_name(stem: str) -> float | None:
    match = _SEC_NSEC.match(stem)
    if match:
        return int(match[1]) + int(match[2]) * 1e-9
    if _SECONDS.match(stem):
        return float(stem)
    match = _NANOSECONDS.search(stem)
    if match:
        return int(match[1]) * 1e-9
    return None


def _times_path(folder: Path, given: str | Path | None) -> Path | None:
    if given is not None:
        path = Path(given)
        if not path.is_file():
            raise DatasetFormatError(f"{path}: times file not found")
        return path
    for candidate in (folder / "times.txt", folder.parent / "times.txt"):
        if candidate.is_file():
            return candidate
    return None


def _read_times(path: Path, scans: int) -> list[float]:
    try:
        values = [float(line.split()[0]) for line in path.read_text().splitlines() if line.strip()]
    except ValueError:
        raise DatasetFormatError(f"{path}: a line does not start with a number") from None
    if len(values) != scans:
        raise DatasetFormatError(f"{path}: {len(values)} stamps for {scans} scan files")
    bad = next((k for k, v in enumerate(values) if not math.isfinite(v)), None)
    if bad is not None:
        raise DatasetFormatError(
            f"{path}: stamp {bad + 1} is {values[bad]}, not a finite number of seconds"
        )
    return values
