"""Poses from the map itself: each scan of a recording (a scan folder or a bag) aligned
against a map by the forward model's likelihood (``core.alignment``), against a fixed map
(``localize``) or against the map built so far (``replay_refined``, ``replay
--refine-poses``), through the one loop (``mapping.loop.ScanLoop``).

The initial guess of each scan is its pose from the recording's pose source (a pose file
matched by stamp, a bag's odometry or /tf, KISS-ICP); the refined pose is ``C * initial``
with ``C`` the correction found in the map frame, or the initial pose when the correction
is refused (degenerate geometry, no significant gain).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.core.alignment import (
    Alignment,
    AlignOptions,
    FieldPyramid,
    align_scan,
    verify_exact,
)
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.folder_replay import folder_poses
from mfp_mapper.mapping.loop import ScanLoop
from mfp_mapper.mapping.replay import ReplayError, ScanSelection, new_mapper, open_bag_input
from mfp_mapper.sensing.pipeline import PlacedScan, ScanDropped
from mfp_mapper.sensing.poses import Extrinsic, PoseUnavailable, frame_name
from mfp_mapper.sensing.scan_normals import scan_normals
from mfp_mapper.sources import pose_files
from mfp_mapper.sources.bags import open_reader, resolve_bag_path
from mfp_mapper.sources.scan_files import DatasetFormatError
from mfp_mapper.sources.scan_folder import is_scan_folder, open_scan_folder

FloatArray = NDArray[np.float64]

__all__ = [
    "LocalizedScan",
    "PyramidCache",
    "localize",
    "localize_folder",
    "open_input",
    "refine_placed",
    "replay_refined",
    "replay_refined_folder",
]


@dataclass
class LocalizedScan:
    """One scan's initial and refined pose (the pose source's robot frame, map frame)."""

    stamp: float
    index: int
    position: FloatArray
    quaternion: FloatArray
    """Refined pose (xyzw); the initial one when not accepted or not aligned."""
    initial_position: FloatArray
    initial_quaternion: FloatArray
    alignment: Alignment | None
    """None: not aligned (``note`` says why: dropped scan, empty map)."""
    exact_gain: float = math.nan
    """Exact log-likelihood gain (nats, ``core.likelihood``, the rays used), refined - initial."""
    seconds: float = 0.0
    note: str = ""

    def row(self) -> dict[str, object]:
        """A flat record for the confidence file."""
        al = self.alignment
        return {
            "stamp": self.stamp,
            "index": self.index,
            "accepted": bool(al is not None and al.accepted),
            "shift_m": 0.0 if al is None else al.shift_m,
            "angle_deg": 0.0 if al is None else al.angle_deg,
            "gain_per_ray": math.nan if al is None else al.gain_per_ray,
            "exact_gain": self.exact_gain,
            "sigma": [math.nan] * 6 if al is None else [float(v) for v in al.sigma],
            "constraints": -1 if al is None else al.conditioning,
            "rays": 0 if al is None else al.rays,
            "seconds": self.seconds,
            "reason": self.note if al is None else al.reason,
        }


@dataclass
class LocalizeResult:
    scans: list[LocalizedScan] = field(default_factory=list)
    map_frame: str = "map"
    mapper: Mapper | None = None
    pyramid_builds: int = 0
    """How many times the field pyramid was built (``PyramidCache``)."""

    @property
    def accepted(self) -> int:
        return sum(1 for s in self.scans if s.alignment is not None and s.alignment.accepted)


def _prior(mapper: Mapper) -> dict[str, float]:
    """The map's Gamma prior (shape, rate) on the extinction; the uniform prior (1, 1) for
    a Mapper that has none."""
    prior = getattr(mapper, "prior", None)
    if prior is None:
        return {"shape": 1.0, "rate": 1.0}
    return {"shape": float(prior.shape), "rate": float(prior.rate)}


def refine_placed(
    mapper: Mapper,
    pyramid: FieldPyramid,
    placed: PlacedScan,
    options: AlignOptions,
) -> tuple[Alignment, float]:
    """Align a placed scan (map frame, at its initial pose) against ``mapper``'s field
    ``pyramid``; returns the alignment and its exact likelihood gain (nats)."""
    ret = np.ones(len(placed.points), dtype=bool)
    if placed.no_return is not None:
        ret = ~placed.no_return
    pts = placed.points[ret]
    org = placed.origins if np.ndim(placed.origins) == 1 else placed.origins[ret]
    al = align_scan(pyramid, pts, org, options, normals=scan_normals(pts))
    al = verify_exact(
        mapper, al, placed.points, placed.origins, placed.stamp, options,
        no_return=placed.no_return,
    )  # fmt: skip
    return al, al.exact_gain


def _apply(
    al: Alignment, position: FloatArray, rotation: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The refined robot pose C * (position, rotation): (position, quaternion xyzw)."""
    pos = al.rotation @ position + al.translation
    rot = al.rotation @ rotation
    return pos, Rotation.from_matrix(rot).as_quat()


@dataclass
class _Input:
    """A recording's clouds ((position, load message) pairs), their pose source, the
    extrinsic of each cloud frame and the map frame; ``close()`` when done."""

    clouds: Iterator[tuple[int, Callable[[], Any]]]
    buffer: Any
    extrinsic_of: Callable[[str], Extrinsic]
    map_frame: str
    close: Callable[[], None]


def _pose_file_buffer(poses: str | Path, opts: ReplayOptions) -> tuple[Any, str]:
    """The poses of a TUM file or an odometry CSV (matched by stamp), for a bag."""
    path = Path(poses)
    try:
        kind = pose_files.guess_pose_format(path)
        if kind == "kitti":
            raise ReplayError(
                f"{path}: KITTI poses have no stamps; a bag's clouds need TUM poses "
                "('t x y z qx qy qz qw') or an odometry CSV, matched by stamp"
            )
        stamps, positions, quaternions = pose_files.read_stamped_poses(path, kind)
        buffer = pose_files.pose_buffer(
            stamps, positions, quaternions, opts.placement.odom_max_gap, str(path)
        )
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    return buffer, f"{path} ({kind.upper()}, T_world_lidar)"


def open_input(
    source: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    times_file: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> _Input:
    """A scan folder (poses: a pose file, or ``opts.replay.odometry``) or a bag (poses: its own
    odometry or /tf, ``opts.replay.odometry``, or a TUM/CSV pose file matched by stamp)."""
    if is_scan_folder(source):
        try:
            folder = open_scan_folder(source, times_file)
        except (DatasetFormatError, OSError) as err:
            raise ReplayError(str(err)) from None
        found = folder_poses(folder, poses, opts, log)
        extrinsic = (
            Extrinsic.from_xyz_rpy(*opts.replay.extrinsic) if opts.replay.extrinsic else Extrinsic()
        )
        return _Input(
            ((k, partial(folder.message, k)) for k in range(len(folder))),
            found.buffer,
            lambda _: extrinsic,
            str(found.map_frame),
            lambda: None,
        )
    if times_file is not None:
        raise ReplayError(f"{source}: --times is for folders of scan files")
    if poses is not None and opts.replay.odometry is not None:
        raise ReplayError("give either --poses or --odometry, not both")
    buffer, what = _pose_file_buffer(poses, opts) if poses is not None else (None, "")
    path = resolve_bag_path(source)
    reader = open_reader(path)
    try:
        bag = open_bag_input(reader, path, opts, log, buffer, what)
    except BaseException:
        reader.close()
        raise
    return _Input(
        bag.clouds(), bag.poses.buffer, bag.extrinsic_of, bag.poses.map_frame, reader.close
    )


class PyramidCache:
    """The field pyramid of a growing map (``replay --refine-poses``), rebuilt only when
    the map has grown enough since the last build: when the scans integrated since then
    reach ``refresh_growth`` times those it holds (the pyramid then lacks at most that
    share of the evidence where the sensor has been), or the sensor has moved more than
    ``refresh_m`` from where it was built (new ground). Building it reads the whole map
    (2-4 s for norlab's 3.6M voxels on a loaded machine): rebuilt before every scan,
    norlab's refinement took 56.1 s, 30.6 s with this rule (same run, README). The exact
    check (``verify_exact``) always reads the current map."""

    def __init__(self, mapper: Mapper, align: AlignOptions) -> None:
        self.mapper = mapper
        self.align = align
        self.pyramid: FieldPyramid | None = None
        self.builds = 0
        self._scans_in = 0
        self._since = 0
        self._where: FloatArray | None = None

    def added(self) -> None:
        """One more scan integrated into the map."""
        self._since += 1

    def get(self, stamp: float, position: FloatArray) -> FieldPyramid | None:
        """The pyramid to align a scan at ``position`` (None: the map is empty)."""
        if self.mapper.num_voxels == 0:
            return None
        stale = (
            self.pyramid is None
            or self._since >= max(1.0, self.align.refresh_growth * self._scans_in)
            or (
                self._where is not None
                and float(np.linalg.norm(position - self._where)) > self.align.refresh_m
            )
        )
        if stale and (self._since > 0 or self.pyramid is None):
            self.pyramid = FieldPyramid.from_mapper(
                self.mapper, stamp=stamp, levels=self.align.levels, **_prior(self.mapper)
            )
            self.builds += 1
            self._scans_in += self._since
            self._since = 0
            self._where = np.asarray(position, dtype=np.float64).copy()
        return self.pyramid


def _run(
    source: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    times_file: str | Path | None,
    align: AlignOptions,
    fixed: Mapper | None,
    log: Callable[[str], None] | None,
    refine: bool = True,
) -> LocalizeResult:
    inp = open_input(source, poses, opts, times_file, log)
    try:
        return _loop(inp, opts, align, fixed, log, refine)
    finally:
        inp.close()


def _loop(
    inp: _Input,
    opts: ReplayOptions,
    align: AlignOptions,
    fixed: Mapper | None,
    log: Callable[[str], None] | None,
    refine: bool,
) -> LocalizeResult:
    import time

    buffer = inp.buffer
    mapper = fixed if fixed is not None else new_mapper(opts, inp.map_frame)
    fixed_pyramid = (
        FieldPyramid.from_mapper(fixed, levels=align.levels, **_prior(fixed))
        if fixed is not None
        else None
    )
    if fixed is None:  # the map this recording builds: sub-voxel corrections are aliasing
        align = replace(
            align, min_correction_voxels=max(align.min_correction_voxels, align.refine_min_voxels)
        )
    cache = PyramidCache(mapper, align)
    result = LocalizeResult(map_frame=inp.map_frame, mapper=mapper)
    loop = ScanLoop(mapper, opts.placement, opts.sensor_model)
    select = ScanSelection(opts)
    for index, load in inp.clouds:
        if select.past_end(index):
            break
        if not select.by_index(index):
            continue
        try:
            prepared = loop.prepare(load())
        except ScanDropped as drop:
            loop.count_drop(drop)
            if log is not None:
                log(f"scan {index}: dropped: {drop.reason} ({drop.detail})")
            continue
        except Exception as err:  # a damaged message: skipped, said
            if log is not None:
                log(f"scan {index}: unreadable ({type(err).__name__}: {err}); skipped")
            continue
        stamp = float(prepared.stamp)
        if not select.by_stamp(stamp, index):
            continue
        select.taken += 1
        try:
            pos0, rot0 = buffer.interpolate(np.array([stamp]))
        except PoseUnavailable as err:
            if log is not None:
                log(f"scan {index}: no initial pose ({err}); skipped")
            continue
        pos0, rot0 = pos0[0], rot0[0]
        q0 = Rotation.from_matrix(rot0).as_quat()
        entry = LocalizedScan(stamp, index, pos0, q0, pos0, q0, None)
        try:
            extrinsic = inp.extrinsic_of(frame_name(prepared.frame_id))
            placed = loop.place(prepared, buffer, extrinsic)
        except ScanDropped as drop:
            loop.count_drop(drop)
            entry.note = f"dropped: {drop.reason} ({drop.detail})"
            result.scans.append(entry)
            continue
        t0 = time.perf_counter()
        pyramid = None
        if refine:
            pyramid = fixed_pyramid if fixed is not None else cache.get(stamp, pos0)
        if pyramid is None:
            entry.note = "not refined" if not refine else "first scan: nothing to align against"
        else:
            al, gain = refine_placed(mapper, pyramid, placed, align)
            entry.alignment, entry.exact_gain = al, gain
            if al.accepted:
                entry.position, entry.quaternion = _apply(al, pos0, rot0)
                placed = PlacedScan(
                    placed.stamp,
                    placed.points @ al.rotation.T + al.translation,
                    np.asarray(placed.origins) @ al.rotation.T + al.translation,
                    placed.deskewed,
                    placed.points_dropped,
                    placed.no_return,
                )
        entry.seconds = time.perf_counter() - t0
        if fixed is None:
            try:
                loop.commit(placed)
                cache.added()
            except ScanDropped as drop:
                loop.count_drop(drop)
                entry.note = f"not integrated: {drop.reason}"
        result.scans.append(entry)
    result.pyramid_builds = cache.builds if fixed is None else 1
    return result


def localize_folder(
    mapper: Mapper,
    directory: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    *,
    times_file: str | Path | None = None,
    align: AlignOptions | None = None,
    log: Callable[[str], None] | None = None,
) -> LocalizeResult:
    """Each scan of ``directory`` (a scan folder or a bag, ``open_input``) aligned against
    the fixed map ``mapper``, starting from its pose in ``poses`` (a pose file), or, with
    None, from the recording's own pose source (a bag's odometry or /tf) or
    ``opts.replay.odometry``."""
    return _run(directory, poses, opts, times_file, align or AlignOptions(), mapper, log)


def replay_refined_folder(
    directory: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    *,
    times_file: str | Path | None = None,
    align: AlignOptions | None = None,
    log: Callable[[str], None] | None = None,
    refine: bool = True,
) -> LocalizeResult:
    """Map ``directory`` (a scan folder or a bag, ``open_input``) scan by scan, each
    aligned against the map built so far before it is integrated at its refined pose (the
    first scan at its initial pose); with ``refine=False`` at its initial pose (to write
    the poses used)."""
    return _run(directory, poses, opts, times_file, align or AlignOptions(), None, log, refine)


localize = localize_folder
"""``localize_folder``: it takes bags too."""
replay_refined = replay_refined_folder
"""``replay_refined_folder``: it takes bags too."""
