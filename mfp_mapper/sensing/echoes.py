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

Drivers without a return field (Hesai's official driver, ros-drivers/velodyne) publish both
blocks of a dual-return firing, identical when only one return was seen: within a shot,
an echo at the range of the one before (``IDENTICAL_RANGE``) is removed.

A shot is one Poisson process along the beam (docs/model.md, "Every echo of a shot"):
``shot_segments`` turns its echoes, nearest first, into rays the core walks as they are —
sensor -> echo 1, then (echo 1 + blind stretch) -> echo 2, ... — each ending in a return:
``s`` gets the chord up to the last echo except the blind stretch after each echo, ``n``
one count per echo. A later echo inside the blind stretch of the one before adds ``n``
with no chord.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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

    A shot of one echo is a ray from the sensor, as without shots (in the input order, so
    the walk keeps its locality). The echoes of a shot of several, nearest first: echoes
    closer than ``min_range`` are dropped (``below_min_range``), an echo within
    ``IDENTICAL_RANGE`` of the one before is the same echo twice (``identical_return``);
    the first echo is a ray from the sensor, each later one a ray from ``blind_stretch`` m
    past the echo before (``continued``). Past ``max_range`` from the sensor a later echo's
    ray is cut there with no return, and the echoes after it are dropped
    (``beyond_max_range``; a first echo is cut by the core). ``first_only``: only the first
    echo of each shot (``later_echo``: the others). The rays of shots of several echoes
    follow the others.
    """
    count = points.shape[0]
    known = shot >= 0
    dropped = {"echo_without_first": int(count - known.sum())}
    echoes_of = np.bincount(shot[known])
    several = known.copy()
    several[known] = echoes_of[shot[known]] > 1
    single = np.flatnonzero(known & ~several)
    group = np.flatnonzero(several)
    org = np.broadcast_to(origins, (count, 3)) if origins.ndim == 1 else origins
    flags = np.zeros(count, dtype=np.bool_) if no_return is None else no_return
    offset = points[group] - org[group]
    rng = np.sqrt(np.einsum("ij,ij->i", offset, offset))
    near = rng < min_range
    dropped["below_min_range"] = int(near.sum())
    group, rng = group[~near], rng[~near]
    by_shot = np.lexsort((rng, shot[group]))
    order, r = group[by_shot], rng[by_shot]
    sid = shot[order]
    twice = np.zeros(order.size, dtype=np.bool_)
    twice[1:] = (sid[1:] == sid[:-1]) & ((r[1:] - r[:-1]) < IDENTICAL_RANGE)
    dropped["identical_return"] = int(twice.sum())
    order, sid, r = order[~twice], sid[~twice], r[~twice]
    later = np.zeros(order.size, dtype=np.bool_)
    later[1:] = sid[1:] == sid[:-1]
    if first_only:
        dropped["later_echo"] = int(later.sum())
        order, sid, r, later = order[~later], sid[~later], r[~later], later[~later]
    start = np.zeros(order.size)
    prev = np.flatnonzero(later) - 1
    start[later] = np.minimum(r[prev] + blind_stretch, r[later])
    prev_beyond = np.zeros(order.size, dtype=np.bool_)
    prev_beyond[later] = r[prev] >= max_range
    # echoes after one beyond max_range: the ray was cut there, the rest is unknown
    beyond_run = np.maximum.accumulate(np.where(prev_beyond, sid, -1)) == sid
    gone = later & (beyond_run | (start >= max_range))
    dropped["beyond_max_range"] = int(gone.sum())
    order, r, start, later, sid = (a[~gone] for a in (order, r, start, later, sid))
    ends = points[order]
    ray_origin = org[order].copy()
    out_flags = flags[order]
    unit = (ends - ray_origin) / np.where(r > 0, r, 1.0)[:, None]
    cut = later & (r > max_range)
    ends[cut] = ray_origin[cut] + unit[cut] * max_range
    out_flags[cut] = True
    inside = later & (start >= r)  # an echo inside the blind stretch: its return, no chord
    moved = later & ~inside
    ray_origin[moved] = ray_origin[moved] + unit[moved] * start[moved, None]
    ray_origin[inside] = ends[inside]
    dropped = {k: v for k, v in dropped.items() if v}
    if not later.any() and (origins.ndim == 1 or single.size == 0):
        # no ray continues a shot: the rays as without shots (one origin when there is one)
        every = np.concatenate([single, order])
        out_origins = origins if origins.ndim == 1 else origins[every]
        any_flag = no_return is not None or cut.any()
        return Segments(
            points[every],
            out_origins,
            np.concatenate([flags[single], out_flags]) if any_flag else None,
            np.zeros(every.size, dtype=np.bool_),
            shot[every],
            every,
            dropped,
        )
    return Segments(
        np.concatenate([points[single], ends]),
        np.concatenate([org[single], ray_origin]),
        np.concatenate([flags[single], out_flags]) if no_return is not None or cut.any() else None,
        np.concatenate([np.zeros(single.size, dtype=np.bool_), later]),
        np.concatenate([shot[single], sid]),
        np.concatenate([single, order]),
        dropped,
    )
