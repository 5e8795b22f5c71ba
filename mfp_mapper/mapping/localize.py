"""Poses from the map itself: each scan of a recording (``sources.recording.Recording``)
aligned against a map by the forward model's likelihood (``core.alignment``), against a fixed
map (``localize``) or against the map built so far (``replay_refined``, ``replay
--refine-poses``), through the one loop (``mapping.loop.ScanLoop``).

The initial guess of each scan is its pose from the recording's pose source (a pose file,
a bag's odometry or /tf, KISS-ICP, the simulator's truth); the refined pose is ``C * initial``
with ``C`` the correction found in the map frame, or the initial pose when the correction
is refused (degenerate geometry, no significant gain).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.replay_options import ReplayOptions
from mfp_mapper.core.alignment import (
    Alignment,
    AlignOptions,
    FieldPyramid,
    align_scan,
    verify_exact,
)
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.model import ALIGNMENT_PRIOR
from mfp_mapper.mapping.loop import ScanLoop
from mfp_mapper.mapping.replay import ScanSelection, new_mapper
from mfp_mapper.sensing.pipeline import PlacedScan, ScanDropped
from mfp_mapper.sensing.poses import PoseUnavailable
from mfp_mapper.sensing.scan_normals import scan_normals
from mfp_mapper.sources.opener import opened
from mfp_mapper.sources.recording import Recording

FloatArray = NDArray[np.float64]

__all__ = [
    "LocalizedScan",
    "PyramidCache",
    "localize",
    "refine_placed",
    "replay_refined",
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


def _prior(_mapper: Mapper) -> dict[str, float]:
    """The Gamma prior (shape, rate) alignment scores with: ``model.ALIGNMENT_PRIOR``, not
    the map's own (the objective localization was tuned on)."""
    return {"shape": ALIGNMENT_PRIOR.shape, "rate": ALIGNMENT_PRIOR.rate}


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


class PyramidCache:
    """The field pyramid of a growing map (``replay --refine-poses``), rebuilt only when
    the map has grown enough since the last build: when the scans integrated since then
    reach ``refresh_growth`` times those it holds (the pyramid then lacks at most that
    share of the evidence where the sensor has been), or the sensor has moved more than
    ``refresh_m`` from where it was built (new ground). Building it reads the whole map
    (2-4 s for norlab's 3.6M voxels on a loaded machine): rebuilt before every scan,
    norlab's refinement took 56.1 s, 30.6 s with this rule (same run, docs/performance.md).
    The exact check (``verify_exact``) always reads the current map."""

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


def _loop(
    recording: Recording,
    opts: ReplayOptions,
    align: AlignOptions,
    fixed: Mapper | None,
    log: Callable[[str], None] | None,
    refine: bool,
) -> LocalizeResult:
    buffer = recording.pose_source
    mapper = fixed if fixed is not None else new_mapper(opts, recording.map_frame)
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
    result = LocalizeResult(map_frame=recording.map_frame, mapper=mapper)
    loop = ScanLoop(mapper, opts.placement, opts.sensor_model)
    select = ScanSelection(opts)
    for index, load in recording.clouds():
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
            extrinsic = recording.extrinsic_of(frame_name(prepared.frame_id))
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
                placed = replace(  # the shots and continued rays go with it
                    placed,
                    points=placed.points @ al.rotation.T + al.translation,
                    origins=np.asarray(placed.origins) @ al.rotation.T + al.translation,
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


def localize(
    mapper: Mapper,
    recording: Recording | str | Path,
    opts: ReplayOptions,
    *,
    align: AlignOptions | None = None,
    log: Callable[[str], None] | None = None,
) -> LocalizeResult:
    """Each selected scan of ``recording`` (or of the bag at that path) aligned against the
    fixed map ``mapper``, starting from its pose in the recording's pose source."""
    with opened(recording, opts, log) as rec:
        return _loop(rec, opts, align or AlignOptions(), mapper, log, True)


def replay_refined(
    recording: Recording | str | Path,
    opts: ReplayOptions,
    *,
    align: AlignOptions | None = None,
    log: Callable[[str], None] | None = None,
    refine: bool = True,
) -> LocalizeResult:
    """Map ``recording`` (or the bag at that path) scan by scan, each aligned against the
    map built so far before it is integrated at its refined pose (the first scan at its
    initial pose); with ``refine=False`` at its initial pose (to write the poses used)."""
    with opened(recording, opts, log) as rec:
        return _loop(rec, opts, align or AlignOptions(), None, log, refine)
