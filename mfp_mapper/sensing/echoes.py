"""Every echo of a laser shot: which points are echoes of one shot, in the drivers'
conventions, and a shot as one Poisson process along its beam.

Shots (``ParsedCloud.shot``: points with equal values are echoes of one shot):

- Nebula (Autoware): ``return_type`` beside ``channel`` and ``azimuth``: a shot is one
  (channel, azimuth) pair (``nebula_shots``);
- ouster-ros: the second return is a second cloud (``points2``) of the same pixel layout: a
  shot is one pixel of the two clouds of one stamp (``pipeline.with_second_return``);
- Livox (livox_ros_driver2): the return number in bits 4-5 of ``tag``: a shot is one
  (``line``, time) pair of a multi-return cloud (``livox_shots``);
- terrestrial scanner exports (RIEGL, rTLS): ``target_index`` / ``target_count``: echo k of
  a shot is the echo k-1 of the same count seen in the same direction (``target_shots``).

Drivers publish both returns of a dual-return firing, identical when only one return was
seen: within a shot, an echo within ``IDENTICAL_RANGE`` of the one before is removed; in
a cloud without a return field (Hesai's official driver, ros-drivers/velodyne: no shots
known), a point equal to the one before it on its beam (``identical_points``).

A shot is one Poisson process along the beam (docs/model.md, "Every echo of a shot"):
``shot_segments`` turns its echoes, nearest first, into rays the core walks as they are —
sensor -> echo 1, then (echo 1 + blind stretch) -> echo 2, ... — each ending in a return:
``s`` gets the chord up to the last echo except the blind stretch after each echo, ``n``
one count per echo. A later echo inside the blind stretch of the one before adds ``n``
with no chord.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

IDENTICAL_RANGE = 1e-3
"""Two echoes of one shot closer than this (m) are one echo published twice (a dual-return
driver's identical blocks; Nebula's ``return_type`` 6, identical, is then published once)."""
TARGET_ANGLE = np.radians(0.03)
"""Echoes of a ``target_index`` export within this angle of each other (rad) are of one
shot: on tls_conifers (RIEGL VZ-400i, 0.048 deg between neighbouring shots) a second echo
lies a median 0.013 deg (90%: 0.031 deg) from its first; the neighbouring shot's first
echo a median 0.047 deg."""
NEBULA_RETURN_TYPES: dict[int, str] = {
    1: "last", 2: "first", 3: "strongest", 4: "first-weak", 5: "last-weak", 6: "identical",
    7: "second", 8: "second-strongest", 9: "first-strongest", 10: "last-strongest",
}  # fmt: skip
"""Nebula's ``return_type`` values (nebula_common ReturnType). The rank along the beam is
read from the ranges of a shot's echoes, which every type agrees with."""
LIVOX_RETURN_BITS = 0b00110000
"""Livox ``tag`` bits 4-5: the return number of the point (0 in single-return mode)."""


def ranks(values: NDArray[np.generic]) -> NDArray[np.int64]:
    """The rank of each value among the distinct values (0, 1, ... in sorted order).

    A stable sort: np.unique's quicksort took 30 ms on the 15 k packed keys of a real Nebula
    VLP-16 dual-return frame (long runs of equal keys), the stable sort 1 ms."""
    flat = np.asarray(values).reshape(-1)
    order = np.argsort(flat, kind="stable")
    ordered = flat[order]
    step = np.ones(flat.size, dtype=np.bool_)
    step[1:] = ordered[1:] != ordered[:-1]
    out = np.empty(flat.size, dtype=np.int64)
    out[order] = np.cumsum(step) - 1
    return out


def dense_ids(high: NDArray[np.generic], low: NDArray[np.generic]) -> NDArray[np.int64]:
    """One id per distinct pair (``high``, ``low``) of integers (``low`` below 2^32, ``high``
    below 2^31): 0, 1, ... in the pairs' sorted order (one sort of a packed key)."""
    key = (np.asarray(high).astype(np.int64) << 32) | np.asarray(low).astype(np.int64)
    return ranks(key)


def nebula_shots(channel: NDArray[np.generic], azimuth: NDArray[np.generic]) -> NDArray[np.int64]:
    """Shots of a Nebula cloud: one per (``channel``, ``azimuth``) (the returns of a
    dual-return firing share both; equal azimuths, equal float32 bits)."""
    bits = np.ascontiguousarray(azimuth, dtype=np.float32).view(np.uint32)
    return dense_ids(channel, bits)


def livox_shots(
    tag: NDArray[np.generic], line: NDArray[np.generic] | None, time: NDArray[np.generic] | None
) -> NDArray[np.int64] | None:
    """Shots of a Livox cloud (one per ``line`` and time), or None when no point carries a
    return number above 0 in ``tag`` (single-return mode: every point its own shot)."""
    if line is None or time is None or not np.any(tag.astype(np.int64) & LIVOX_RETURN_BITS):
        return None
    return dense_ids(line, ranks(time))


def identical_points(xyz: FloatArray, ring: NDArray[np.integer]) -> NDArray[np.intp]:
    """Indices of the points equal, coordinate for coordinate, to the point before them on
    their beam (``ring``, in cloud order): the second block of a dual-return firing that saw
    one return, as drivers without a return field publish it (Hesai's official driver,
    ros-drivers/velodyne put the two blocks of a firing next to each other). One stable
    radix sort by beam and one comparison of neighbours: about 2 ms for 200 k points."""
    if len(xyz) < 2:
        return np.zeros(0, dtype=np.intp)
    order = np.argsort(ring.astype(np.int32), kind="stable")
    ordered = xyz[order]
    same = (ordered[1:] == ordered[:-1]).all(axis=1)
    return np.sort(order[1:][same])


def target_shots(
    xyz: FloatArray, target_index: NDArray[np.generic], target_count: NDArray[np.generic]
) -> NDArray[np.int64]:
    """Shots of a terrestrial scan export: echo k (``target_index``, 1-based) joins the
    nearest echo k-1 of the same ``target_count`` in direction (within ``TARGET_ANGLE``,
    closer to the sensor at the origin); an echo whose earlier echo is not in the cloud
    (cropped away) gets the id -1 (``shot_segments`` drops it: the free space before it
    is unknown)."""
    from scipy.spatial import cKDTree

    index = np.asarray(target_index, dtype=np.int64)
    count = np.asarray(target_count, dtype=np.int64)
    rng = np.linalg.norm(xyz, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = xyz / rng[:, None]
    shot = np.full(len(xyz), -1, dtype=np.int64)
    first = np.flatnonzero(index <= 1)
    shot[first] = np.arange(first.size)
    chord = 2.0 * np.sin(TARGET_ANGLE / 2.0)
    for k in range(2, int(index.max(initial=1)) + 1):
        later = np.flatnonzero(index == k)
        before = np.flatnonzero((index == k - 1) & (count >= k) & (shot >= 0))
        if later.size == 0 or before.size == 0:
            continue
        tree = cKDTree(unit[before])
        dist, at = tree.query(unit[later], k=1, distance_upper_bound=chord)
        found = np.isfinite(dist)
        cand = before[np.minimum(at, before.size - 1)]
        found &= count[cand] == count[later]
        found &= rng[cand] < rng[later]
        shot[later[found]] = shot[cand[found]]
    return shot


@dataclass
class Segments:
    """A scan's rays, one per echo, as the core walks them (``shot_segments``)."""

    points: FloatArray
    origins: FloatArray
    """(3,) the sensor, when every ray starts there, or (N, 3): the sensor for a shot's
    first echo, else where the blind stretch after the echo before it ends (the echo itself
    when it lies inside that stretch)."""
    no_return: NDArray[np.bool_] | None
    continued: NDArray[np.bool_]
    """Rays that continue a shot past an earlier echo (``Mapper.integrate``'s flag)."""
    shot: NDArray[np.int64]
    """The shot of each ray (its id in the input)."""
    order: NDArray[np.intp]
    """Index of each ray's input point."""
    dropped: dict[str, int] = field(default_factory=dict)


def shot_segments(
    points: FloatArray,
    origins: FloatArray,
    shot: NDArray[np.int64],
    no_return: NDArray[np.bool_] | None,
    blind_stretch: float,
    max_range: float = np.inf,
    min_range: float = 0.0,
    first_only: bool = False,
) -> Segments:
    """The rays of a scan whose points (map frame, seen from ``origins`` (3,) or (N, 3)) are
    echoes grouped by ``shot`` (ids >= 0; -1: an echo of an unknown shot, dropped as
    ``echo_without_first``).

    A shot of one echo is a ray from the sensor, as without shots. The echoes of a shot of
    several, nearest first: echoes closer than ``min_range`` are dropped
    (``below_min_range``), an echo within ``IDENTICAL_RANGE`` of the one before is the same
    echo twice (``identical_return``); the first echo is a ray from the sensor, each later
    one a ray from ``blind_stretch`` m past the echo before (``continued``). Past
    ``max_range`` from the sensor a later echo's ray is cut there with no return, and the
    echoes after it are dropped (``beyond_max_range``; a first echo is cut by the core).
    ``first_only``: only the first echo of each shot (``later_echo``: the others). The rays
    are in the input order of their points (``order``): the walk keeps the cloud's
    locality, a later echo's ray among the first echoes next to it.
    """
    count = points.shape[0]
    pts = np.ascontiguousarray(points, dtype=np.float64)
    org = np.ascontiguousarray(np.atleast_2d(origins), dtype=np.float64)
    ids = np.ascontiguousarray(shot, dtype=np.int64)
    keep = np.empty(count, dtype=np.bool_)
    slot = np.zeros(count, dtype=np.int32)
    drops = np.zeros(len(_DROPS), dtype=np.int64)
    members = _segment_shots(
        pts, org, ids, int(ids.max(initial=-1)) + 1, float(blind_stretch), float(max_range),
        float(min_range), bool(first_only), keep, slot, drops,
    )  # fmt: skip
    dropped = {name: int(v) for name, v in zip(_DROPS, drops, strict=True) if v}
    any_cut = bool(members.cut.any())
    one_origin = origins.ndim == 1 and not members.continued.any()
    if not dropped and not any_cut and one_origin:  # every point a ray from the sensor
        return Segments(
            points, origins, no_return, np.zeros(count, dtype=np.bool_), ids, np.arange(count),
            dropped,
        )  # fmt: skip
    total = int(np.count_nonzero(keep))
    rows = np.empty(total, dtype=np.int64)
    out_points = np.empty((total, 3))
    out_origins = np.empty((0, 3) if one_origin else (total, 3))
    later = np.empty(total, dtype=np.bool_)
    out_cut = np.empty(total, dtype=np.bool_)
    out_shot = np.empty(total, dtype=np.int64)
    _compact(
        pts, org, ids, keep, slot, members, not one_origin, rows, out_points, out_origins,
        later, out_cut, out_shot,
    )  # fmt: skip
    out_no_return = None
    if no_return is not None or any_cut:
        out_no_return = out_cut if no_return is None else no_return[rows] | out_cut
    return Segments(
        out_points, origins if one_origin else out_origins, out_no_return, later, out_shot,
        rows, dropped,
    )  # fmt: skip


class _Continued(NamedTuple):
    """What ``_segment_shots`` found for the echoes of shots of several (indexed by the
    ``slot`` it gives each such echo, less one): whether the echo continues its shot, where
    its ray starts, whether it is cut at ``max_range`` and where."""

    continued: NDArray[np.bool_]
    starts: FloatArray
    cut: NDArray[np.bool_]
    cut_ends: FloatArray


@nb.njit(cache=True, nogil=True)
def _compact(
    points: FloatArray,
    origins: FloatArray,
    shot: NDArray[np.int64],
    keep: NDArray[np.bool_],
    slot: NDArray[np.int32],
    members: _Continued,
    with_origins: bool,
    rows: NDArray[np.int64],
    out_points: FloatArray,
    out_origins: FloatArray,
    out_continued: NDArray[np.bool_],
    out_cut: NDArray[np.bool_],
    out_shot: NDArray[np.int64],
) -> None:
    """The kept rays of ``_segment_shots`` in one pass: their input rows, shots, ends (cut
    ones at ``max_range``), origins (when ``with_origins``: the sensor, or a continued ray's
    start), flags."""
    per_point = origins.shape[0] > 1
    continued, starts, cut, cut_ends = members
    k = 0
    for i in range(points.shape[0]):
        if not keep[i]:
            continue
        rows[k] = i
        out_shot[k] = shot[i]
        j = slot[i] - 1  # -1: not an echo of a shot of several
        later = j >= 0 and continued[j]
        is_cut = later and cut[j]
        out_continued[k] = later
        out_cut[k] = is_cut
        o = i if per_point else 0
        for axis in range(3):
            out_points[k, axis] = cut_ends[j, axis] if is_cut else points[i, axis]
            if with_origins:
                out_origins[k, axis] = starts[j, axis] if later else origins[o, axis]
        k += 1


_DROPS = (
    "echo_without_first", "below_min_range", "identical_return", "later_echo",
    "beyond_max_range",
)  # fmt: skip
"""The reasons ``shot_segments`` drops an echo, in the order of ``_segment_shots``' counts."""


@nb.njit(cache=True, nogil=True)
def _segment_shots(
    points: FloatArray,
    origins: FloatArray,
    shot: NDArray[np.int64],
    shots: int,
    blind: float,
    max_range: float,
    min_range: float,
    first_only: bool,
    keep: NDArray[np.bool_],
    slot: NDArray[np.int32],
    drops: NDArray[np.int64],
) -> _Continued:
    """``shot_segments`` in two passes over the points and one over the shots of several
    echoes (their members gathered by a counting sort, each shot's few echoes sorted by
    range in place): ``keep``, the drops by reason (``_DROPS``), and for the echoes of
    shots of several (``slot``: their index there plus one, 0 for the others) whether each
    continues its shot, its ray's start, ``cut`` at ``max_range`` and the cut end. Against
    the numpy version it replaced (a lexsort of the grouped echoes, gathers of every point),
    ``shot_segments`` on the 1.05 M echoes of tls_conifers took 0.07-0.10 s instead of
    0.13-0.17 s (the shared 2-CPU development machine under load). The results held per
    echo of a shot of several (12% of the echoes there; they were (N, 3) arrays over every
    point), the shots' ids written by ``_compact`` (not gathered after), 32-bit counts and
    the members filled in place (no copy of the offsets): 0.72-0.78x the time of that
    version, 29.6 ms against 41.0 (median of 21 interleaved rounds, thread CPU, load 8.5)."""
    count = points.shape[0]
    per_point = origins.shape[0] > 1
    echoes = np.zeros(shots + 1, dtype=np.int32)
    for i in range(count):
        keep[i] = shot[i] >= 0
        if keep[i]:
            echoes[shot[i]] += 1
        else:
            drops[0] += 1
    # where each shot of several starts among the members; filled in place: afterwards
    # first[k] is where shot k ends (and shot k + 1 starts)
    first = np.empty(shots + 1, dtype=np.int32)
    first[0] = 0
    for k in range(shots):
        first[k + 1] = first[k] + (echoes[k] if echoes[k] > 1 else 0)
    members = np.empty(first[shots], dtype=np.int64)
    for i in range(count):
        k = shot[i]
        if k >= 0 and echoes[k] > 1:
            members[first[k]] = i
            first[k] += 1
    ranges = np.empty(members.size)
    for j in range(members.size):
        i = members[j]
        o = i if per_point else 0
        dx = points[i, 0] - origins[o, 0]
        dy = points[i, 1] - origins[o, 1]
        dz = points[i, 2] - origins[o, 2]
        ranges[j] = math.sqrt(dx * dx + dy * dy + dz * dz)
    continued = np.zeros(members.size, dtype=np.bool_)
    starts = np.empty((members.size, 3))
    cut = np.zeros(members.size, dtype=np.bool_)
    cut_ends = np.empty((members.size, 3))
    lo = 0
    for k in range(shots):
        hi = first[k]
        for j in range(lo + 1, hi):  # insertion sort by range: a shot has a few echoes
            m, r = members[j], ranges[j]
            q = j - 1
            while q >= lo and ranges[q] > r:
                members[q + 1] = members[q]
                ranges[q + 1] = ranges[q]
                q -= 1
            members[q + 1] = m
            ranges[q + 1] = r
        have = False
        stopped = False
        before = 0.0
        for j in range(lo, hi):
            i, r = members[j], ranges[j]
            slot[i] = j + 1
            if r < min_range:
                keep[i] = False
                drops[1] += 1
                continue
            if not have:  # the first echo: a ray from the sensor
                have = True
                before = r
                continue
            if r - before < IDENTICAL_RANGE:
                keep[i] = False
                drops[2] += 1
                continue
            if first_only:
                keep[i] = False
                drops[3] += 1
                continue
            start = min(before + blind, r)
            if stopped or before >= max_range or start >= max_range:
                keep[i] = False
                drops[4] += 1
                stopped = True
                continue
            o = i if per_point else 0
            continued[j] = True
            for axis in range(3):
                unit = (points[i, axis] - origins[o, axis]) / r
                starts[j, axis] = origins[o, axis] + unit * start if start < r else points[i, axis]
                cut_ends[j, axis] = origins[o, axis] + unit * max_range
            if r > max_range:
                cut[j] = True
                stopped = True
            before = r
        lo = hi
    return _Continued(continued, starts, cut, cut_ends)
