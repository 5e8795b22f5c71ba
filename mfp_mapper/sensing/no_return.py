"""Rays that returned nothing, recovered from the scan pattern.

A spinning lidar fires every beam at every step of its rotation; drivers leave out the
firings without a return (sky, open space, a dark or glossy target) or mark them NaN
(velodyne ``organize_cloud``) or zero (Ouster). Those rays crossed space all the same, and
dropping them biases the map's ``n/s`` upward. Here the direction of each missing firing is
recovered from the points that did return:

- **organized clouds** (height > 1: rows are beams, columns the firing sequence): the row's
  elevation is the median elevation of its valid points; the azimuth of cell (row, column)
  is ``step * column + offset[row] + correction[column]``, with ``step`` the firing order's
  azimuth step, ``offset`` each beam's azimuth (Ouster's staggered beams) and
  ``correction`` what the column's valid neighbours say about uneven rotation;
- **unorganized clouds with a beam field** (``ring``/``channel``: Velodyne, Hesai/Nebula):
  the points of each beam, sorted by azimuth, must lie on a regular azimuth grid; each gap
  of that grid is a missing firing.

Rows or beams without any valid point are left alone (their elevation is unknown). When the
pattern is not regular enough to trust, nothing is recovered and ``Recovery.reason`` says
why. Directions are in the sensor frame, from its origin: the beams' own small offsets from
that origin (Ouster's beam-origin offset) are not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.sensing import no_return_kernels as kernels
from mfp_mapper.sensing.pointcloud import ParsedCloud

FloatArray = NDArray[np.float64]

MAX_AZIMUTH_RESIDUAL_DEG = 0.2
"""An organized grid is trusted when 95% of its valid points lie this close (deg) to the
fitted azimuth model."""
MAX_OFF_GRID_SHARE = 0.05
"""A beam pattern is trusted when at most this share of azimuth gaps are not a whole number
of steps (within a quarter step)."""
MAX_ELEVATION_SPREAD_DEG = 0.3
"""... and the points of one beam agree on the elevation within this (deg, median)."""
MIN_PAIRS = 8
_SECTORS = 7200
"""Sectors (0.05 deg) on which the widest empty sector of a ring/channel cloud is found."""
_FIT_ROUNDS = 2
"""Alternations of the row offsets and column corrections (the test layouts: 0.03 deg worst
after 2, 0.004 deg after 3; each costs about 0.2 ms on a VLP-16 scan)."""
"""Neighbouring valid points needed to measure the azimuth step."""


@dataclass
class Recovery:
    """Directions (M, 3) of the firings with no return (unit vectors, sensor frame), their
    times (seconds from the header stamp, when the cloud has per-point time), which
    ``pattern`` gave them (``organized``, ``beams`` or ``none``) and, when nothing or not
    everything could be recovered, the ``reason``."""

    directions: FloatArray
    time_offset: FloatArray | None
    pattern: str
    reason: str | None = None

    def __len__(self) -> int:
        return int(self.directions.shape[0])


def _none(reason: str | None, with_time: bool, pattern: str = "none") -> Recovery:
    return Recovery(np.empty((0, 3)), np.empty(0) if with_time else None, pattern, reason)


def recover_no_return(cloud: ParsedCloud) -> Recovery:
    """The missing firings of ``cloud`` (see the module docstring)."""
    height, width = cloud.grid_shape
    with_time = cloud.time_offset is not None
    if height > 1 and width > 1:
        return _organized(cloud, height, width)
    if cloud.ring is None:
        return _none(
            "unorganized cloud without a ring/channel field: the scan pattern (which beam "
            "fired where) cannot be recovered",
            with_time,
        )
    return _beams(cloud)


def with_no_return_rays(cloud: ParsedCloud, no_return_range: float) -> tuple[ParsedCloud, Recovery]:
    """``cloud`` with one point per recovered firing at ``no_return_range`` metres along it,
    flagged in ``no_return``; and the recovery itself (its ``reason`` for the log)."""
    if not no_return_range > 0:
        raise ValueError(f"no_return_range must be > 0 m, got {no_return_range}")
    found = recover_no_return(cloud)
    count = len(found)
    if count == 0:
        return cloud, found
    time = None
    if cloud.time_offset is not None and found.time_offset is not None:
        time = np.concatenate([cloud.time_offset, found.time_offset])
    intensity = None
    if cloud.intensity is not None:
        intensity = np.concatenate([cloud.intensity, np.zeros(count, dtype=np.float32)])
    flags = np.zeros(len(cloud) + count, dtype=np.bool_)
    flags[len(cloud) :] = True
    if cloud.no_return is not None:
        flags[: len(cloud)] = cloud.no_return
    extended = replace(
        cloud,
        xyz=np.concatenate([cloud.xyz, found.directions * no_return_range]),
        time_offset=time,
        intensity=intensity,
        grid_shape=(1, len(cloud) + count),
        cell=None,
        ring=None,
        no_return=flags,
        shot=_with_new_shots(cloud.shot, count, cloud.grid_shape[0] * cloud.grid_shape[1]),
    )
    return extended, found


def _with_new_shots(
    shot: NDArray[np.int64] | None, count: int, cells: int
) -> NDArray[np.int64] | None:
    """``shot`` and ``count`` new shots of one ray each (the recovered firings), numbered
    past both ``shot`` and the ``cells`` of the cloud's grid (a shot may be a pixel)."""
    if shot is None:
        return None
    first = max(int(shot.max(initial=-1)) + 1, cells)
    return np.concatenate([shot, np.arange(first, first + count, dtype=np.int64)])


def _organized(cloud: ParsedCloud, height: int, width: int) -> Recovery:
    with_time = cloud.time_offset is not None
    cells = np.arange(len(cloud)) if cloud.cell is None else cloud.cell
    if cells.size == height * width:
        return _none(None, with_time, "organized")
    pairs, step, offset, correction, row_elevation, outside = kernels.organized_fit(
        cloud.xyz, cells.astype(np.int64), height, width, _FIT_ROUNDS,
        math.radians(MAX_AZIMUTH_RESIDUAL_DEG),
    )  # fmt: skip
    if pairs < MIN_PAIRS:
        return _none(
            f"organized cloud ({height} x {width}) with only {pairs} neighbouring valid "
            "points: the azimuth step cannot be measured",
            with_time,
        )
    if outside > 0.05:
        return _none(
            f"organized cloud ({height} x {width}) whose azimuths do not follow its columns "
            f"({100 * outside:.0f}% of the points farther than {MAX_AZIMUTH_RESIDUAL_DEG} deg "
            "from the fitted firing order): not a spinning lidar's row/column layout?",
            with_time,
        )
    disorder = _column_disorder(cells, width, step, correction)
    if disorder > MAX_OFF_GRID_SHARE:
        return _none(
            f"organized cloud ({height} x {width}) whose columns are not in firing order "
            f"({100 * disorder:.0f}% of neighbouring columns more than half an azimuth step "
            "off the next): the missing firings' directions cannot be trusted",
            with_time,
        )
    times = np.empty(0) if cloud.time_offset is None else cloud.time_offset
    directions, out_times = kernels.organized_missing(
        cells.astype(np.int64), height, width, step, offset, correction, row_elevation, times
    )
    empty_rows = int(np.isnan(row_elevation).sum())
    reason = None
    if empty_rows:
        reason = (
            f"{empty_rows} of {height} rows have no valid point: their elevation is unknown "
            "and their firings are not recovered"
        )
    return Recovery(directions, out_times if with_time else None, "organized", reason)


def _column_disorder(
    cells: NDArray[np.int64], width: int, step: float, correction: FloatArray
) -> float:
    """Share of neighbouring columns (both with points) whose fitted azimuths differ by more
    than half a step from one step apart: 0 for a lidar's firing order, large when the
    columns were shuffled (the per-column corrections then absorb any order)."""
    seen = np.zeros(width, dtype=bool)
    seen[np.asarray(cells) % width] = True
    pairs = np.flatnonzero(seen[1:] & seen[:-1])
    if not len(pairs) or step == 0:
        return 0.0
    jump = correction[pairs + 1] - correction[pairs]
    jump = (jump + math.pi) % (2.0 * math.pi) - math.pi
    return float(np.mean(np.abs(jump) > 0.5 * abs(step)))


def _beams(cloud: ParsedCloud) -> Recovery:
    assert cloud.ring is not None
    with_time = cloud.time_offset is not None
    ring = cloud.ring.astype(np.int64)
    # turned so that a partial scan's edges are at 0 and 2 pi; sorted by ring, then azimuth
    azimuth, sine, key, cut, widest = kernels.beam_angles(cloud.xyz, ring, _SECTORS)
    order = np.argsort(key)
    ring, azimuth, sine = ring[order], azimuth[order], sine[order]
    gaps, step, off_grid, spread = kernels.beam_grid(ring, azimuth, sine)
    if gaps < MIN_PAIRS:
        return _none("too few points per beam to measure the azimuth step", with_time)
    if off_grid > MAX_OFF_GRID_SHARE or not step > 0:
        return _none(
            f"the beams' azimuths are not on a regular grid ({100 * off_grid:.0f}% of the "
            f"gaps are not whole steps of {math.degrees(step):.3f} deg): no recovery",
            with_time,
        )
    if math.degrees(spread) > MAX_ELEVATION_SPREAD_DEG:  # a sine: about radians here
        return _none(
            f"the points of one ring/channel spread over {math.degrees(spread):.2f} deg of "
            "elevation: the field does not name a beam",
            with_time,
        )
    full_turn = widest <= 4.0 * step
    times = np.empty(0) if cloud.time_offset is None else cloud.time_offset[order]
    directions, out_times = kernels.beam_gaps(ring, azimuth, sine, times, step, full_turn)
    if cut != 0.0:  # rotate back
        c, s = math.cos(cut), math.sin(cut)
        x, y = directions[:, 0].copy(), directions[:, 1].copy()
        directions[:, 0], directions[:, 1] = c * x - s * y, s * x + c * y
    reason = None if full_turn else "the scan is not a full turn: the gap at its edges is left"
    return Recovery(directions, out_times if with_time else None, "beams", reason)
