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
_FIT_ROUNDS = 4
"""Alternations of the row offsets and column corrections (converged after 3 on tests)."""
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
        cell=None,
        ring=None,
        no_return=flags,
    )
    return extended, found


def _wrap(angle: FloatArray) -> FloatArray:
    """Angles into [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _directions(elevation: FloatArray, azimuth: FloatArray) -> FloatArray:
    cos_e = np.cos(elevation)
    return np.stack([cos_e * np.cos(azimuth), cos_e * np.sin(azimuth), np.sin(elevation)], -1)


def _angles(xyz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Azimuth and elevation (rad) of points seen from the origin."""
    horizontal = np.hypot(xyz[:, 0], xyz[:, 1])
    return np.arctan2(xyz[:, 1], xyz[:, 0]), np.arctan2(xyz[:, 2], horizontal)


def _group_median(keys: NDArray[np.intp], values: FloatArray, size: int) -> FloatArray:
    """Median of ``values`` per key in [0, size) (NaN where a key has none)."""
    out = np.full(size, np.nan)
    order = np.argsort(keys, kind="stable")
    sorted_keys, sorted_values = keys[order], values[order]
    starts = np.searchsorted(sorted_keys, np.arange(size))
    ends = np.searchsorted(sorted_keys, np.arange(size), side="right")
    for key in np.flatnonzero(ends > starts):
        out[key] = np.median(sorted_values[starts[key] : ends[key]])
    return out


def _organized(cloud: ParsedCloud, height: int, width: int) -> Recovery:
    with_time = cloud.time_offset is not None
    cells = np.arange(len(cloud)) if cloud.cell is None else cloud.cell
    if cells.size == height * width:
        return _none(None, with_time, "organized")
    rows, cols = np.divmod(cells, width)
    azimuth, elevation = _angles(cloud.xyz)
    row_elevation = _group_median(rows, elevation, height)
    # the firing order's azimuth step, from valid neighbours in the same row
    adjacent = np.flatnonzero(np.diff(cells) == 1)
    adjacent = adjacent[rows[adjacent] == rows[adjacent + 1]]
    if adjacent.size < MIN_PAIRS:
        return _none(
            f"organized cloud ({height} x {width}) with only {adjacent.size} neighbouring "
            "valid points: the azimuth step cannot be measured",
            with_time,
        )
    step = float(np.median(_wrap(azimuth[adjacent + 1] - azimuth[adjacent])))
    # each row's azimuth offset (circular mean) and each column's correction, alternately
    in_column = np.bincount(cols, minlength=width)
    seen = np.flatnonzero(in_column)
    correction = np.zeros(width)
    for _ in range(_FIT_ROUNDS):
        phase = np.exp(1j * (azimuth - step * cols - correction[cols]))
        offset = np.angle(
            np.bincount(rows, phase.real, height) + 1j * np.bincount(rows, phase.imag, height)
        )
        residual = _wrap(azimuth - step * cols - offset[rows])
        column_mean = np.bincount(cols, residual, width)[seen] / in_column[seen]
        correction = np.interp(np.arange(width), seen, column_mean, period=width)
    fit = np.abs(_wrap(azimuth - step * cols - offset[rows] - correction[cols]))
    worst = math.degrees(float(np.quantile(fit, 0.95)))
    if worst > MAX_AZIMUTH_RESIDUAL_DEG:
        return _none(
            f"organized cloud ({height} x {width}) whose azimuths do not follow its columns "
            f"(95% within {worst:.2f} deg of the fitted firing order, need "
            f"{MAX_AZIMUTH_RESIDUAL_DEG} deg): not a spinning lidar's row/column layout?",
            with_time,
        )
    missing = np.ones(height * width, dtype=np.bool_)
    missing[cells] = False
    empty_rows = np.isnan(row_elevation)
    missing.reshape(height, width)[empty_rows] = False
    m_rows, m_cols = np.divmod(np.flatnonzero(missing), width)
    directions = _directions(
        row_elevation[m_rows], step * m_cols + offset[m_rows] + correction[m_cols]
    )
    times = None
    if cloud.time_offset is not None:
        column_time = np.bincount(cols, cloud.time_offset, width)[seen] / in_column[seen]
        times = np.interp(m_cols, seen, column_time)
    reason = None
    if empty_rows.any():
        reason = (
            f"{int(empty_rows.sum())} of {height} rows have no valid point: their elevation "
            "is unknown and their firings are not recovered"
        )
    return Recovery(directions, times, "organized", reason)


def _beams(cloud: ParsedCloud) -> Recovery:
    assert cloud.ring is not None
    with_time = cloud.time_offset is not None
    azimuth, elevation = _angles(cloud.xyz)
    cut, widest = _widest_gap(azimuth)
    azimuth = (azimuth - cut) % (2.0 * math.pi)  # a partial scan's edges at 0 and 2 pi
    order = np.lexsort((azimuth, cloud.ring))
    ring, az = cloud.ring[order], azimuth[order]
    gap = np.diff(az)
    same = ring[1:] == ring[:-1]
    positive = gap[same & (gap > 0)]
    if positive.size < MIN_PAIRS:
        return _none("too few points per beam to measure the azimuth step", with_time)
    step = float(np.median(positive))
    tiny = 0.25 * step  # dual returns and jitter: the same firing
    steps = gap / step
    off_grid = same & (gap > tiny) & (np.abs(steps - np.round(steps)) > 0.25)
    share = float(off_grid.sum()) / max(int((same & (gap > tiny)).sum()), 1)
    if share > MAX_OFF_GRID_SHARE:
        return _none(
            f"the beams' azimuths are not on a regular grid ({100 * share:.0f}% of the gaps "
            f"are not whole steps of {math.degrees(step):.3f} deg): no recovery",
            with_time,
        )
    beam_ids, first = np.unique(ring, return_index=True)
    last = np.append(first[1:], ring.size) - 1
    beam_elevation = _group_median(np.searchsorted(beam_ids, ring), elevation[order], beam_ids.size)
    spread = _group_median(
        np.searchsorted(beam_ids, ring),
        np.abs(elevation[order] - beam_elevation[np.searchsorted(beam_ids, ring)]),
        beam_ids.size,
    )
    if math.degrees(float(spread.max())) > MAX_ELEVATION_SPREAD_DEG:
        return _none(
            f"the points of one ring/channel spread over {math.degrees(float(spread.max())):.2f} "
            "deg of elevation: the field does not name a beam",
            with_time,
        )
    # gaps of whole steps inside each beam, and around the wrap when the scan is a full turn
    left = np.flatnonzero(same & (np.round(steps) >= 2))
    widths = gap[left]
    full_turn = widest <= 4.0 * step
    if full_turn:
        wrap_gap = az[first] + 2.0 * math.pi - az[last]
        wrap_steps = np.round(wrap_gap / step)
        keep = wrap_steps >= 2
        left = np.concatenate([left, last[keep]])
        widths = np.concatenate([widths, wrap_gap[keep]])
    cuts = np.round(widths / step).astype(np.int64)
    owner = np.repeat(np.arange(left.size), cuts - 1)
    within = np.arange(owner.size) - np.repeat(np.cumsum(cuts - 1) - (cuts - 1), cuts - 1) + 1
    delta = within * widths[owner] / cuts[owner]
    new_az = az[left[owner]] + delta + cut
    beam_of = np.searchsorted(beam_ids, ring[left[owner]])
    directions = _directions(beam_elevation[beam_of], new_az)
    times = None
    if cloud.time_offset is not None:
        t = cloud.time_offset[order]
        pairs = same & (np.round(steps) == 1)
        rate = float(np.median(np.diff(t)[pairs] / gap[pairs])) if pairs.any() else 0.0
        times = t[left[owner]] + delta * rate
    reason = None if full_turn else "the scan is not a full turn: the gap at its edges is left"
    return Recovery(directions, times, "beams", reason)


def _widest_gap(azimuth: FloatArray) -> tuple[float, float]:
    """Where the widest empty sector of all beams together ends (rad), and its width."""
    every = np.sort(azimuth)
    gaps = np.append(np.diff(every), every[0] + 2.0 * math.pi - every[-1])
    widest = int(np.argmax(gaps))
    return float(every[(widest + 1) % every.size]), float(gaps[widest])
