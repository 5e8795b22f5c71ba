"""Compiled passes of the no-return recovery (``sensing.no_return``): one pass per step, so
recovering a VLP-16 scan costs a small share of integrating it."""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_TWO_PI = 2.0 * math.pi
_TURNS_PER_RADIAN = 1.0 / _TWO_PI


@nb.njit(cache=True, inline="always")
def _wrap(angle: float) -> float:
    """An angle into [-pi, pi) (a floor, not a division: this runs per point and round)."""
    return angle - _TWO_PI * math.floor(angle * _TURNS_PER_RADIAN + 0.5)


@nb.njit(cache=True, inline="always")
def _typical(values: FloatArray, count: int) -> float:
    """A robust mean of ``values[:count]``: the mean of those within 25% of the median of
    the first 101 (a full median of every value costs a sort)."""
    guess = np.median(values[: min(count, 101)])
    total, used = 0.0, 0
    for k in range(count):
        if abs(values[k] - guess) <= 0.25 * abs(guess):
            total += values[k]
            used += 1
    return total / used if used else guess


@nb.njit(cache=True, nogil=True)
def angles(xyz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Azimuth (rad) and the sine of the elevation of each point seen from the origin."""
    n = xyz.shape[0]
    azimuth, sine = np.empty(n), np.empty(n)
    for i in range(n):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        azimuth[i] = math.atan2(y, x)
        sine[i] = z / math.sqrt(x * x + y * y + z * z)
    return azimuth, sine


@nb.njit(cache=True, inline="always")
def _fill_gaps(values: FloatArray, seen: NDArray[np.bool_], periodic: bool) -> None:
    """Linear interpolation of ``values`` where not ``seen``, from the nearest seen entries
    on either side (around the end when ``periodic``, else the nearest one at the ends)."""
    size = values.shape[0]
    first = -1
    for k in range(size):
        if seen[k]:
            first = k
            break
    if first < 0:
        return
    last = first
    for k in range(size - 1, -1, -1):
        if seen[k]:
            last = k
            break
    prev = last - size if periodic else -1
    k = 0
    while k < size:
        if seen[k]:
            prev = k
            k += 1
            continue
        nxt = k
        while nxt < size and not seen[nxt]:
            nxt += 1
        nxt_i = nxt if nxt < size else (first + size if periodic else -1)
        for j in range(k, min(nxt, size)):
            if prev < 0 and not periodic:
                values[j] = values[first]
            elif nxt_i < 0:
                values[j] = values[last]
            else:
                a, b = values[prev % size], values[nxt_i % size]
                values[j] = a + (b - a) * (j - prev) / (nxt_i - prev)
        k = nxt


@nb.njit(cache=True, nogil=True)
def organized_fit(
    xyz: FloatArray, cells: IntArray, height: int, width: int, rounds: int, tolerance: float
) -> tuple[int, float, FloatArray, FloatArray, FloatArray, float]:
    """Firing-order model of an organized cloud whose valid points are ``cells`` (sorted):
    (neighbour pairs, azimuth step, row offsets, column corrections, row elevations (the
    mean of the row's points; NaN: none), share of points farther than ``tolerance`` rad
    from the model)."""
    n = cells.shape[0]
    rows, cols = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    azimuth, sine = np.empty(n), np.empty(n)
    for i in range(n):
        rows[i], cols[i] = cells[i] // width, cells[i] % width
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        azimuth[i] = math.atan2(y, x)
        sine[i] = z / math.sqrt(x * x + y * y + z * z)
    row_elevation = np.arcsin(_row_means(sine, rows, height))
    diffs = np.empty(n)
    pairs = 0
    for i in range(n - 1):
        if cells[i + 1] == cells[i] + 1 and cols[i + 1] != 0:
            diffs[pairs] = _wrap(azimuth[i + 1] - azimuth[i])
            pairs += 1
    offset, correction = np.zeros(height), np.zeros(width)
    if pairs == 0:
        return 0, 0.0, offset, correction, row_elevation, 1.0
    step = _typical(diffs, pairs)
    sums, counts = np.zeros(width), np.zeros(width)
    seen = np.zeros(width, dtype=np.bool_)
    for i in range(n):
        seen[cols[i]] = True
    reference = np.full(height, np.nan)
    for _ in range(rounds):
        # the row's circular mean, as a mean of wrapped differences to its first point
        total, used = np.zeros(height), np.zeros(height)
        for i in range(n):
            row, col = rows[i], cols[i]
            a = azimuth[i] - step * col - correction[col]
            if used[row] == 0:
                reference[row] = a
            total[row] += _wrap(a - reference[row])
            used[row] += 1.0
        for row in range(height):
            if used[row] > 0:
                offset[row] = reference[row] + total[row] / used[row]
        sums[:] = 0.0
        counts[:] = 0.0
        for i in range(n):
            row, col = rows[i], cols[i]
            sums[col] += _wrap(azimuth[i] - step * col - offset[row])
            counts[col] += 1.0
        for col in range(width):
            correction[col] = sums[col] / counts[col] if counts[col] > 0 else 0.0
        _fill_gaps(correction, seen, True)
    outside = 0
    for i in range(n):
        row, col = rows[i], cols[i]
        if abs(_wrap(azimuth[i] - step * col - offset[row] - correction[col])) > tolerance:
            outside += 1
    return pairs, step, offset, correction, row_elevation, outside / max(n, 1)


@nb.njit(cache=True, inline="always")
def _row_means(values: FloatArray, rows: IntArray, height: int) -> FloatArray:
    """Mean of ``values`` per row of the grid (NaN: no point in the row)."""
    total, used = np.zeros(height), np.zeros(height)
    for i in range(rows.shape[0]):
        row = rows[i]
        total[row] += values[i]
        used[row] += 1.0
    out = np.full(height, np.nan)
    for row in range(height):
        if used[row] > 0:
            out[row] = total[row] / used[row]
    return out


@nb.njit(cache=True, nogil=True)
def organized_missing(
    cells: IntArray, height: int, width: int, step: float, offset: FloatArray,
    correction: FloatArray, row_elevation: FloatArray, times: FloatArray,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Directions (M, 3) of the missing cells of rows that have a point, and their times
    (the mean time of the column's valid points, interpolated; empty without ``times``)."""
    valid = np.zeros(height * width, dtype=np.bool_)
    for i in range(cells.shape[0]):
        valid[cells[i]] = True
    count = 0
    for row in range(height):
        if not math.isnan(row_elevation[row]):
            for col in range(width):
                count += not valid[row * width + col]
    directions = np.empty((count, 3))
    with_time = times.shape[0] > 0
    column_time = np.zeros(width)
    if with_time:
        counts = np.zeros(width)
        for i in range(cells.shape[0]):
            column_time[cells[i] % width] += times[i]
            counts[cells[i] % width] += 1.0
        for col in range(width):
            if counts[col] > 0:
                column_time[col] /= counts[col]
        _fill_gaps(column_time, counts > 0, False)
    out_times = np.empty(count if with_time else 0)
    # azimuth = column angle + row offset: one cosine and sine per column and per row
    col_cos, col_sin = np.empty(width), np.empty(width)
    for col in range(width):
        col_cos[col] = math.cos(step * col + correction[col])
        col_sin[col] = math.sin(step * col + correction[col])
    k = 0
    for row in range(height):
        elevation = row_elevation[row]
        if math.isnan(elevation):
            continue
        cos_e, sin_e = math.cos(elevation), math.sin(elevation)
        row_cos, row_sin = math.cos(offset[row]), math.sin(offset[row])
        for col in range(width):
            if valid[row * width + col]:
                continue
            directions[k, 0] = cos_e * (col_cos[col] * row_cos - col_sin[col] * row_sin)
            directions[k, 1] = cos_e * (col_sin[col] * row_cos + col_cos[col] * row_sin)
            directions[k, 2] = sin_e
            if with_time:
                out_times[k] = column_time[col]
            k += 1
    return directions, out_times


@nb.njit(cache=True, nogil=True)
def beam_grid(
    ring: IntArray, azimuth: FloatArray, sine: FloatArray
) -> tuple[int, float, float, float]:
    """Of points sorted by (ring, azimuth): the azimuth step (typical positive gap within a
    beam) and how many gaps it is measured on, the share of gaps that are not whole steps,
    and the largest mean deviation of a beam's elevation sines from their mean."""
    n = ring.shape[0]
    gaps = np.empty(n)
    count = 0
    for i in range(n - 1):
        gap = azimuth[i + 1] - azimuth[i]
        if ring[i + 1] == ring[i] and gap > 0:
            gaps[count] = gap
            count += 1
    if count == 0:
        return 0, 0.0, 1.0, 0.0
    step = _typical(gaps, count)
    counted = off = 0
    for k in range(count):
        if gaps[k] > 0.25 * step:
            counted += 1
            steps = gaps[k] / step
            off += abs(steps - round(steps)) > 0.25
    spread = 0.0
    start = 0
    while start < n:
        end = start
        while end < n and ring[end] == ring[start]:
            end += 1
        values = sine[start:end]
        spread = max(spread, np.mean(np.abs(values - np.mean(values))))
        start = end
    return count, step, off / max(counted, 1), spread


@nb.njit(cache=True, nogil=True)
def beam_gaps(
    ring: IntArray, azimuth: FloatArray, sine: FloatArray, times: FloatArray,
    step: float, full_turn: bool,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Directions of the firings missing from each beam's gaps of whole ``step``s (and
    around the end when ``full_turn``), azimuths rotated back by nothing: the caller adds
    its cut. Times are interpolated along the beam's time per radian."""
    n = ring.shape[0]
    with_time = times.shape[0] > 0
    rates = np.empty(n)
    count_rates = 0
    if with_time:
        for i in range(n - 1):
            gap = azimuth[i + 1] - azimuth[i]
            if ring[i + 1] == ring[i] and abs(gap / step - 1.0) < 0.25:
                rates[count_rates] = (times[i + 1] - times[i]) / gap
                count_rates += 1
    rate = _typical(rates, count_rates) if count_rates else 0.0
    none = np.empty((0, 3))
    total = _beam_pass(ring, azimuth, sine, times, step, full_turn, rate, none, times, False)
    directions = np.empty((total, 3))
    out_times = np.empty(total if with_time else 0)
    _beam_pass(ring, azimuth, sine, times, step, full_turn, rate, directions, out_times, True)
    return directions, out_times


@nb.njit(cache=True, nogil=True)
def _beam_pass(
    ring: IntArray, azimuth: FloatArray, sine: FloatArray, times: FloatArray,
    step: float, full_turn: bool, rate: float, directions: FloatArray, out_times: FloatArray,
    fill: bool,
) -> int:  # fmt: skip
    """Count (``fill`` False) or write the missing firings of ``beam_gaps``."""
    n = ring.shape[0]
    with_time = times.shape[0] > 0
    k = 0
    start = 0
    while start < n:
        end = start
        while end < n and ring[end] == ring[start]:
            end += 1
        sin_e = np.mean(sine[start:end]) if fill else 0.0
        cos_e = math.sqrt(max(1.0 - sin_e * sin_e, 0.0))
        last = end - 1 if full_turn else end - 2
        for i in range(start, last + 1):
            right = azimuth[i + 1] if i + 1 < end else azimuth[start] + _TWO_PI
            width = right - azimuth[i]
            cuts = int(round(width / step))
            if cuts < 2:
                continue
            if not fill:
                k += cuts - 1
                continue
            # rotate by one cut at a time: no cosine per firing
            turn_cos, turn_sin = math.cos(width / cuts), math.sin(width / cuts)
            c, s = math.cos(azimuth[i]), math.sin(azimuth[i])
            for j in range(1, cuts):
                c, s = c * turn_cos - s * turn_sin, s * turn_cos + c * turn_sin
                directions[k, 0] = cos_e * c
                directions[k, 1] = cos_e * s
                directions[k, 2] = sin_e
                if with_time:
                    out_times[k] = times[i] + j * width / cuts * rate
                k += 1
        start = end
    return k


@nb.njit(cache=True, nogil=True)
def beam_angles(
    xyz: FloatArray, ring: IntArray, bins: int
) -> tuple[FloatArray, FloatArray, FloatArray, float, float]:
    """Azimuths turned so that the widest empty sector of the scan (found on ``bins``
    sectors) ends at 0, the sines of the elevations, a sort key (ring, then azimuth), the
    turn (rad) and the width of that empty sector (rad)."""
    n = xyz.shape[0]
    azimuth, sine = angles(xyz)
    occupied = np.zeros(bins, dtype=np.bool_)
    for i in range(n):
        occupied[min(int((azimuth[i] + math.pi) * _TURNS_PER_RADIAN * bins), bins - 1)] = True
    best_end, best_length, length = 0, -1, 0
    for k in range(2 * bins):  # twice round: a run may cross the end
        if occupied[k % bins]:
            if length > best_length:
                best_end, best_length = k % bins, length
            length = 0
        else:
            length += 1
    cut = best_end / bins * _TWO_PI - math.pi
    key = np.empty(n)
    low, high = _TWO_PI, 0.0
    base = ring.min() if n else 0
    for i in range(n):
        a = azimuth[i] - cut
        a -= _TWO_PI * math.floor(a * _TURNS_PER_RADIAN)
        azimuth[i] = a
        low, high = min(low, a), max(high, a)
        key[i] = (ring[i] - base) * 8.0 + a
    return azimuth, sine, key, cut, _TWO_PI - high + low
