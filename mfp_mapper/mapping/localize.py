"""Poses from the map itself: each scan of a folder aligned against a map by the forward
model's likelihood (``core.alignment``), against a fixed map (``localize_folder``) or against
the map built so far (``replay_refined_folder``, ``replay --refine-poses``).

The initial guess of each scan is its pose from the folder's pose source (a pose file,
KISS-ICP); the refined pose is ``C * initial`` with ``C`` the correction found in the map
frame, or the initial pose when the correction is refused (degenerate geometry, no gain).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.core.alignment import Alignment, AlignOptions, FieldPyramid, align_scan, verify_exact
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping.folder_replay import folder_poses
from mfp_mapper.mapping.loop import ScanLoop
from mfp_mapper.mapping.replay import ReplayError, new_mapper
from mfp_mapper.sensing.pipeline import PlacedScan, ScanDropped
from mfp_mapper.sensing.poses import Extrinsic, PoseUnavailable
from mfp_mapper.sensing.scan_normals import scan_normals
from mfp_mapper.sources.scan_files import DatasetFormatError
from mfp_mapper.sources.scan_folder import ScanFolder, open_scan_folder

FloatArray = NDArray[np.float64]

__all__ = ["LocalizedScan", "localize_folder", "refine_placed", "replay_refined_folder"]


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


def _open(
    directory: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    times_file: str | Path | None,
    log: Callable[[str], None] | None,
) -> tuple[ScanFolder, object, Extrinsic]:
    try:
        folder = open_scan_folder(directory, times_file)
    except (DatasetFormatError, OSError) as err:
        raise ReplayError(str(err)) from None
    found = folder_poses(folder, poses, opts, log)
    extrinsic = Extrinsic.from_xyz_rpy(*opts.extrinsic) if opts.extrinsic else Extrinsic()
    return folder, found, extrinsic


def _run(
    directory: str | Path,
    poses: str | Path | None,
    opts: ReplayOptions,
    times_file: str | Path | None,
    align: AlignOptions,
    fixed: Mapper | None,
    log: Callable[[str], None] | None,
    refine: bool = True,
) -> LocalizeResult:
    import time

    folder, found, extrinsic = _open(directory, poses, opts, times_file, log)
    buffer = found.buffer  # type: ignore[attr-defined]
    mapper = fixed if fixed is not None else new_mapper(opts, found.map_frame)  # type: ignore[attr-defined]
    pyramid = (
        FieldPyramid.from_mapper(fixed, levels=align.levels, **_prior(fixed))
        if fixed is not None
        else None
    )
    result = LocalizeResult(map_frame=str(found.map_frame), mapper=mapper)  # type: ignore[attr-defined]
    loop = ScanLoop(mapper, opts)
    for index, scan in enumerate(folder.scans):
        stamp = float(scan.stamp)
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
            placed = loop.place(loop.prepare(folder.message(index)), buffer, extrinsic)
        except ScanDropped as drop:
            loop.count_drop(drop)
            entry.note = f"dropped: {drop.reason}"
            result.scans.append(entry)
            continue
        t0 = time.perf_counter()
        if not refine:
            pyramid = None
        elif fixed is None and mapper.num_voxels > 0:
            pyramid = FieldPyramid.from_mapper(
                mapper, stamp=stamp, levels=align.levels, **_prior(mapper)
            )
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
            except ScanDropped as drop:
                loop.count_drop(drop)
                entry.note = f"not integrated: {drop.reason}"
        result.scans.append(entry)
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
    """Each scan of ``directory`` aligned against the fixed map ``mapper``, starting from
    its pose in ``poses`` (a pose file, or None with ``opts.odometry``)."""
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
    """Map ``directory`` scan by scan, each aligned against the map built so far before it
    is integrated at its refined pose (the first scan at its initial pose); with
    ``refine=False`` at its initial pose (to write the poses used)."""
    return _run(directory, poses, opts, times_file, align or AlignOptions(), None, log, refine)
