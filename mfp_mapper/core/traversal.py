"""Exact voxel traversal (Amanatides & Woo) of lidar rays into the block store, with numba.

A ray runs from its origin to its end point: its first return, or the point where it was
cut at ``max_range``. Every voxel it crosses gets ``s += chord`` — the exact length in
metres of the ray inside that voxel, so a ray's chords add up to its length — and a ray
that ends in a return gives its end voxel ``n += 1`` (the chord from where it entered that
voxel up to the return point is its last chord).

Threads: the store has one shard per thread, and a thread alone writes to its shard. Every
thread walks every ray and adds only the visits to its own shard's blocks, in ray order:
the same float32 sums as one thread, bit for bit, and nothing passes between threads. (Each
thread walking its share of the rays and mailing the visits to other shards' blocks, as
before issue 22's lockstep walk, was slower: about half the visits were mail.)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_BITS,
    BLOCK_VOXELS,
    KEY_BITS,
    MAX_VOXEL_INDEX,
    block_key,
    block_of_key,
    find_block,
    local_index,
    shard_of,
)
from mfp_mapper.core.lockstep import (
    FLOAT_ROWS,
    FOREIGN_BASE,
    INT_ROWS,
    LANES,
    place_lanes,
    walk_lanes,
)
from mfp_mapper.core.shard import Shard, ShardArrays, open_block
from mfp_mapper.core.store import BlockStore

_LOCAL_MASK = (1 << BLOCK_BITS) - 1
_SPREAD = np.array([local_index(0, 0, z) for z in range(1 << BLOCK_BITS)], dtype=np.int64)
"""Morton bits of an index in a block along one axis (z; y is this << 1, x this << 2)."""
_READ_CACHE_BITS = 4
"""``read_walk``'s block cache: 2^12 slots, indexed by the low 4 bits of each block index."""
_READ_CACHE_MASK = (1 << _READ_CACHE_BITS) - 1
_WALK_CACHE_BITS = 5
"""The integrating walk's block cache: 2^15 slots, indexed by the low 5 bits of each block
index. Against 2^12 slots (as ``read_walk``'s), cycle-counted on one scan: misses 60 k ->
29 k and the block lookups 13.6 -> 10.1 ms on OS1-128 at 0.2 m (86.9 k -> 69.2 k, 23.8 ->
20.1 ms, hall at 0.1 m); a miss costs about 110 ns (the hash, and a first touch)."""
_WALK_CACHE_MASK = (1 << _WALK_CACHE_BITS) - 1
RETURN_CHORD_FLOOR = 1e-3
"""Least chord (metres) of a return event in ``read_walk``: the range resolution of a lidar
return. A return exactly on a voxel's edge or corner has a chord of 0 in the voxel its
point floors to (the ray only touches it), probability 0 and log-likelihood -inf; the
reflection is known only to within the range resolution (about 1 mm: what lidars report,
and the rounding of exported coordinates), so the event covers at least that much ray
(docs/model.md, "A return on a voxel face")."""


@dataclass
class Rays:
    """Rays in voxel units (metres / resolution), with their lengths in metres."""

    origins_vox: NDArray[np.float64]
    ends_vox: NDArray[np.float64]
    lengths: NDArray[np.float64]
    has_return: NDArray[np.bool_]
    no_return_flagged: int = 0
    """How many of the rays had their ``no_return`` flag set (see ``prepare_rays``)."""
    source: NDArray[np.int64] | None = None
    """Index of each ray's input point (``prepare_rays`` drops some points)."""
    continued: NDArray[np.bool_] | None = None
    """Rays that continue a shot past an earlier echo (``prepare_rays``), or None: none."""

    def __len__(self) -> int:
        return int(self.lengths.shape[0])


def prepare_rays(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    resolution: float,
    min_range: float,
    max_range: float,
    no_return: NDArray[np.bool_] | None = None,
    continued: NDArray[np.bool_] | None = None,
) -> tuple[Rays, dict[str, int]]:
    """The usable rays in voxel units, and how many were dropped for which reason.

    ``origins`` is one origin (3,) or one per point (N, 3). A ray longer than ``max_range``
    is cut there and carries no return; so does a ray whose ``no_return`` flag (N,) is set:
    its point only marks where its credited free space ends. NaN/Inf, shorter than
    ``min_range`` (or zero), and reaching beyond the indexable range are dropped.

    ``continued`` (N,) flags rays that continue a shot past an earlier echo (their origin is
    that echo plus the blind stretch, not the sensor; ``sensing.echoes``): ``min_range``
    does not apply to them and a zero length is kept (a return with no chord: an echo
    inside the blind stretch of the one before).
    """
    count = points.shape[0]
    source = np.empty(count, dtype=np.int64)
    out = Rays(
        np.empty((count, 3)), np.empty((count, 3)), np.empty(count), np.empty(count, dtype=np.bool_)
    )
    drops = np.zeros(4, dtype=np.int64)  # the 3 reasons, then the flagged rays kept
    flags = np.zeros(0, dtype=np.bool_) if no_return is None else no_return
    if flags.size and flags.shape != (count,):
        raise ValueError(f"no_return must have shape ({count},), got {flags.shape}")
    later = np.zeros(0, dtype=np.bool_) if continued is None else continued
    if later.size and later.shape != (count,):
        raise ValueError(f"continued must have shape ({count},), got {later.shape}")
    used = _prepare_rays(
        points, np.atleast_2d(origins), resolution, min_range, max_range, MAX_VOXEL_INDEX,
        flags, later, out.origins_vox, out.ends_vox, out.lengths, out.has_return, source, drops,
    )  # fmt: skip
    dropped = {
        "nonfinite": int(drops[0]),
        "below_min_range": int(drops[1]),
        "out_of_bounds": int(drops[2]),
    }
    rays = Rays(
        out.origins_vox[:used],
        out.ends_vox[:used],
        out.lengths[:used],
        out.has_return[:used],
        int(drops[3]),
        source[:used],
        later[source[:used]] if later.size else None,
    )
    return rays, dropped


@nb.njit(cache=True, nogil=True)
def _prepare_rays(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    resolution: float,
    min_range: float,
    max_range: float,
    max_index: float,
    no_return: NDArray[np.bool_],
    continued: NDArray[np.bool_],
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    source: NDArray[np.int64],
    drops: NDArray[np.int64],
) -> int:
    """One pass over the points: fill the first rays of the outputs, count the drops
    ([nonfinite, below_min_range, out_of_bounds], then the flagged rays kept); returns how
    many rays are usable; ``source`` receives each ray's point index.
    ``no_return`` is empty (every point a return) or one flag per point; ``continued`` is
    empty (every ray from the sensor) or one flag per point."""
    k = 0
    per_point = origins.shape[0] > 1
    flagged = no_return.shape[0] > 0
    any_continued = continued.shape[0] > 0
    for i in range(points.shape[0]):
        o = i if per_point else 0
        dx = points[i, 0] - origins[o, 0]
        dy = points[i, 1] - origins[o, 1]
        dz = points[i, 2] - origins[o, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not math.isfinite(length):  # NaN or Inf in the point or its origin
            drops[0] += 1
            continue
        if (length < min_range or length == 0.0) and not (any_continued and continued[i]):
            drops[1] += 1
            continue
        reach = min(length, max_range)
        scale = reach / length if length > 0.0 else 1.0
        inside = True
        for axis, d in ((0, dx), (1, dy), (2, dz)):
            o_vox = origins[o, axis] / resolution
            # the end, divided exactly as Mapper.voxel_index does: a return lands in floor(p/res)
            e_vox = (points[i, axis] if scale == 1.0 else origins[o, axis] + d * scale) / resolution
            inside = inside and abs(o_vox) < max_index and abs(e_vox) < max_index
            origins_vox[k, axis] = o_vox
            ends_vox[k, axis] = e_vox
        if not inside:
            drops[2] += 1
            continue
        lengths[k] = reach
        if flagged and no_return[i]:
            has_return[k] = False
            drops[3] += 1
        else:
            has_return[k] = length <= max_range
        source[k] = i
        k += 1
    return k


def integrate_rays(
    store: BlockStore,
    rays: Rays,
    scan_id: int,
    stamp: float,
    decay_time: float,
    run_parallel: Callable[[Callable[[int], None], Sequence[int]], object],
    max_new_blocks: int | None = None,
) -> int:
    """Add every ray's chords and returns to the store (scan ``scan_id`` at ``stamp``), one
    thread per shard, each walking every ray into its own shard.
    ``run_parallel(fn, items)`` calls ``fn`` on every item, in parallel.

    ``max_new_blocks``: the blocks the scan may add (its share in each shard): a shard that
    would grow beyond its share cuts the rays it has not walked yet (``cut_to_blocks``), so
    a scan's memory is bounded whatever its rays. Returns the rays cut (most of any shard)."""
    scan = ScanStamp(scan_id, float(stamp), float(decay_time))
    shards = len(store.shards)
    share = None if max_new_blocks is None else -(-int(max_new_blocks) // shards)
    cut = [0] * shards

    def walk(k: int) -> None:
        cut[k] = _walk_part(rays, store.shards[k], k, store.shard_mask, scan, share)

    run_parallel(walk, range(shards))
    return max(cut)


def block_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Upper bound of the blocks each ray can create: Manhattan block distance plus slack."""
    return ray_bounds(origins_vox, ends_vox)[0]


def visit_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Upper bound of the voxels each ray visits: Manhattan voxel distance plus one."""
    return ray_bounds(origins_vox, ends_vox)[1]


@nb.njit(cache=True, nogil=True)
def ray_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``block_bounds`` and ``visit_bounds`` in one pass (ten numpy passes took 2 ms of a
    50 ms scan at 0.2 m)."""
    count = origins_vox.shape[0]
    blocks = np.empty(count, dtype=np.int64)
    visits = np.empty(count, dtype=np.int64)
    for r in range(count):
        block_steps = 0
        steps = 0
        for axis in range(3):
            lo = int(np.floor(origins_vox[r, axis]))
            hi = int(np.floor(ends_vox[r, axis]))
            steps += abs(hi - lo)
            block_steps += abs((hi >> BLOCK_BITS) - (lo >> BLOCK_BITS))
        blocks[r] = block_steps + 2
        visits[r] = steps + 1
    return blocks, visits


class RayArrays(NamedTuple):
    """The rays of one walk, as the compiled walk takes them (voxel units)."""

    origins_vox: NDArray[np.float64]
    ends_vox: NDArray[np.float64]
    lengths: NDArray[np.float64]
    has_return: NDArray[np.bool_]
    room_needed: NDArray[np.int64]
    """Upper bound of the blocks each ray can create (``block_bounds``)."""
    visits_needed: NDArray[np.int64]
    """Upper bound of the voxels each ray visits (``visit_bounds``)."""


class ScanStamp(NamedTuple):
    """The scan being integrated: its id, its time, and the map's decay time (s)."""

    scan_id: int
    stamp: float
    decay_time: float


def _walk_part(
    rays: Rays,
    shard: Shard,
    shard_id: int,
    shard_mask: int,
    scan: ScanStamp,
    share: int | None = None,
) -> int:
    """Walk ``rays`` into ``shard`` (its visits only), growing it when it runs out of room,
    by at most ``share`` blocks (None: no bound): beyond, the rays not walked yet are cut
    (``cut_to_blocks``). Returns how many were cut."""
    room, visits = ray_bounds(rays.origins_vox, rays.ends_vox)
    walk = RayArrays(rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return, room, visits)
    limit = None if share is None else shard.used + share
    first, cut, cut_done = 0, 0, False
    while first < len(rays):
        first = _walk_rays(walk, first, shard_id, shard_mask, shard.arrays(), scan)
        if first < len(rays):  # the next group of rays (see _walk_rays) did not fit
            need = int(walk.room_needed[first : first + LANES].sum())
            if limit is not None and shard.used + need > limit and not cut_done:
                rest = cut_to_blocks(walk, first, limit - shard.used)
                if rest is None:  # not even a step each: the rest is not walked
                    return len(rays) - first
                (walk, cut), cut_done = rest, True
                continue
            shard.grow(min_free=need, at_most=limit)  # the limit is checked at each growth
    return cut


def cut_to_blocks(walk: RayArrays, first: int, blocks: int) -> tuple[RayArrays, int] | None:
    """``walk`` with rays ``first:`` shortened (no return where cut) so that their block
    bounds (``ray_bounds``) add up to at most ``blocks``: one cap on their length, the
    longest cut first (bisection); the rays cut; None when even zero-length rays do not fit."""
    origins, ends = walk.origins_vox[first:], walk.ends_vox[first:]
    span = ends - origins
    length = np.sqrt((span * span).sum(axis=1))

    def capped(cap: float) -> NDArray[np.float64]:
        scale = np.minimum(1.0, cap / np.maximum(length, 1e-12))
        return np.ascontiguousarray(origins + span * scale[:, None])

    def cost(cap: float) -> int:
        return int(ray_bounds(origins, capped(cap))[0].sum())

    if cost(0.0) > blocks:
        return None
    lo, hi = 0.0, float(length.max(initial=0.0))
    while hi - lo > 1.0:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cost(mid) <= blocks else (lo, mid)
    new_ends = capped(lo)
    shortened = length > lo
    scale = np.where(shortened, lo / np.maximum(length, 1e-12), 1.0)
    room, visits = ray_bounds(origins, new_ends)
    cat = np.concatenate
    rays = RayArrays(
        walk.origins_vox,
        cat([walk.ends_vox[:first], new_ends]),
        cat([walk.lengths[:first], walk.lengths[first:] * scale]),
        cat([walk.has_return[:first], walk.has_return[first:] & ~shortened]),
        cat([walk.room_needed[:first], room]),
        cat([walk.visits_needed[:first], visits]),
    )
    return rays, int(shortened.sum())


@nb.njit(cache=True, nogil=True, inline="always")
def _ray_start(origins_vox, ends_vox, r):  # type: ignore[no-untyped-def]
    """Ray ``r``'s start for a voxel walk (voxel units): first voxel, end voxel, steps per
    axis, where each axis' next face is crossed (ray parameter t in [0, 1]), t between faces,
    and the number of steps. An axis already at the end voxel's index is never stepped again
    (t_max = inf), so a walk takes exactly ``steps`` steps and ends in floor(end), whatever
    the rounding. Shared by ``_walk_rays`` and ``read_walk``: same voxels, same chords."""
    ox = origins_vox[r, 0]
    oy = origins_vox[r, 1]
    oz = origins_vox[r, 2]
    dx = ends_vox[r, 0] - ox
    dy = ends_vox[r, 1] - oy
    dz = ends_vox[r, 2] - oz
    vx = int(np.floor(ox))
    vy = int(np.floor(oy))
    vz = int(np.floor(oz))
    ex = int(np.floor(ends_vox[r, 0]))
    ey = int(np.floor(ends_vox[r, 1]))
    ez = int(np.floor(ends_vox[r, 2]))
    step_x = 1 if ex > vx else -1
    step_y = 1 if ey > vy else -1
    step_z = 1 if ez > vz else -1
    t_max_x = ((vx + (dx > 0)) - ox) / dx if ex != vx else np.inf
    t_max_y = ((vy + (dy > 0)) - oy) / dy if ey != vy else np.inf
    t_max_z = ((vz + (dz > 0)) - oz) / dz if ez != vz else np.inf
    t_delta_x = abs(1.0 / dx) if ex != vx else 0.0
    t_delta_y = abs(1.0 / dy) if ey != vy else 0.0
    t_delta_z = abs(1.0 / dz) if ez != vz else 0.0
    steps = abs(ex - vx) + abs(ey - vy) + abs(ez - vz)
    return (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
            t_delta_x, t_delta_y, t_delta_z, steps)  # fmt: skip


@nb.njit(cache=True, nogil=True)
def _walk_rays(
    rays: RayArrays,
    first: int,
    shard: int,
    shard_mask: int,
    shard_arrays: ShardArrays,
    scan: ScanStamp,
) -> int:
    """Walk rays ``first..`` (voxel units) and add their visits to ``shard``'s blocks (the
    visits to other shards' blocks are left to their threads).

    The rays go ``LANES`` at a time, a group. ``lockstep.walk_lanes`` steps them all at
    once and writes every step out; for each ray the blocks it enters are gathered and
    looked up (lookups independent of each other, so their memory latencies overlap);
    ``lockstep.place_lanes`` turns the steps into store indices and weighted chords and
    starts loading their cache lines. Then the group before, whose lines were loaded
    meanwhile, is added (``_add_group``), ray by ray in ray order. Before each group,
    checks there is room for the blocks it may create; returns the index of the first ray
    not walked (the caller grows and calls again), or N.
    """
    origins_vox, ends_vox, lengths, has_return, room_needed, visits_needed = rays
    scan_id, stamp, decay_time = scan
    table_keys, _, _, block_sn, block_t, _, block_hit, counters, block_scale = shard_arrays
    capacity = min(block_t.shape[0], table_keys.shape[0] // 2)
    # blocks opened in this call, direct-mapped by their low index bits: neighbouring rays
    # cross the same blocks, and this table (768 KiB) stays in cache where the hash does not
    cache_keys = np.full(1 << (3 * _WALK_CACHE_BITS), -1, dtype=np.int64)
    cache_bases = np.empty(cache_keys.shape[0], dtype=np.int64)  # first voxel, or FOREIGN_BASE
    cache_weights = np.empty(cache_keys.shape[0])  # the scan's weight there (< 1: a late scan)
    total = lengths.shape[0]
    longest = 1
    for r in range(first, total):
        longest = max(longest, visits_needed[r])
    # the group's steps (step k of lane l at k * LANES + l) and the blocks each ray enters
    step_code = np.empty(longest * LANES, dtype=np.int16)
    entered_key = np.empty((LANES, longest), dtype=np.int64)
    entered_base = np.empty((LANES, longest), dtype=np.int64)
    entered_weight = np.empty((LANES, longest))
    lane_blocks = np.empty(LANES, dtype=np.int64)
    lane_floats = np.empty((FLOAT_ROWS, LANES))
    lane_ints = np.empty((INT_ROWS, LANES), dtype=np.int64)
    # placed visits of two groups: the one being walked and the one waiting to be added
    placed_voxel = np.empty((2, longest * LANES), dtype=np.int64)
    placed_chord = np.empty((2, longest * LANES))  # the steps' chords, then weighted
    placed_steps = np.zeros((2, LANES), dtype=np.int64)
    return_weight = np.zeros((2, LANES))  # 0: no return (or another shard's end voxel)
    lines = block_sn.reshape(-1)
    pairs = lines.view(np.uint64)  # a voxel's s and n as one word: 0 when unobserved
    group = 0
    waiting = 0  # rays of the group waiting to be added
    group_first = first
    while True:
        lanes = min(LANES, total - group_first)
        blocks_needed = 0
        for lane in range(lanes):
            blocks_needed += room_needed[group_first + lane]
        if lanes == 0 or counters[0] + blocks_needed > capacity:
            _add_group(
                lines, pairs, block_hit, placed_voxel[1 - group], placed_chord[1 - group],
                placed_steps[1 - group], return_weight[1 - group], waiting, counters,
            )  # fmt: skip
            return group_first
        steps = 0
        for lane in range(LANES):  # lanes past the last ray repeat the group's first ray
            r = group_first + (lane if lane < lanes else 0)
            (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
             t_delta_x, t_delta_y, t_delta_z, ray_steps) = _ray_start(
                origins_vox, ends_vox, r)  # fmt: skip
            lane_floats[0, lane] = t_max_x
            lane_floats[1, lane] = t_max_y
            lane_floats[2, lane] = t_max_z
            lane_floats[3, lane] = t_delta_x
            lane_floats[4, lane] = t_delta_y
            lane_floats[5, lane] = t_delta_z
            lane_floats[6, lane] = 0.0
            lane_floats[7, lane] = lengths[r]
            lane_ints[0, lane] = vx
            lane_ints[1, lane] = vy
            lane_ints[2, lane] = vz
            lane_ints[3, lane] = step_x
            lane_ints[4, lane] = step_y
            lane_ints[5, lane] = step_z
            lane_ints[6, lane] = ex
            lane_ints[7, lane] = ey
            lane_ints[8, lane] = ez
            lane_ints[9, lane] = ray_steps
            placed_steps[group, lane] = ray_steps
            steps = max(steps, ray_steps + 1)
        step_chord = placed_chord[group]
        walk_lanes(  # type: ignore[call-arg]
            lane_floats, lane_ints, steps, entered_key, lane_blocks, step_code, step_chord
        )  # fmt: skip
        weighted = False  # a block where the scan is late (weight < 1)
        for lane in range(lanes):
            r = group_first + lane
            blocks = lane_blocks[lane]
            # the blocks the ray enters
            for b in range(blocks):
                key = entered_key[lane, b]
                # the low index bits of the block (KEY_OFFSET is a multiple of the cache)
                slot = (
                    (((key >> (2 * KEY_BITS)) & _WALK_CACHE_MASK) << (2 * _WALK_CACHE_BITS))
                    | (((key >> KEY_BITS) & _WALK_CACHE_MASK) << _WALK_CACHE_BITS)
                    | (key & _WALK_CACHE_MASK)
                )
                if cache_keys[slot] != key:
                    bx, by, bz = block_of_key(key)
                    block = -1
                    if shard_of(bx, by, bz, shard_mask) == shard:
                        block = open_block(bx, by, bz, shard_arrays, scan_id, stamp, decay_time)
                    cache_keys[slot] = key
                    cache_bases[slot] = block * BLOCK_VOXELS if block >= 0 else FOREIGN_BASE
                    cache_weights[slot] = block_scale[block] if block >= 0 else 1.0
                entered_base[lane, b] = cache_bases[slot]
                entered_weight[lane, b] = cache_weights[slot]
                weighted |= cache_weights[slot] != 1.0
            ends_here = has_return[r] and entered_base[lane, blocks - 1] >= 0
            return_weight[group, lane] = entered_weight[lane, blocks - 1] if ends_here else 0.0
        place_lanes(
            step_code, step_chord, entered_base, entered_weight, weighted, steps, lines,
            placed_voxel[group],
        )  # fmt: skip
        _add_group(
            lines, pairs, block_hit, placed_voxel[1 - group], placed_chord[1 - group],
            placed_steps[1 - group], return_weight[1 - group], waiting, counters,
        )  # fmt: skip
        waiting = lanes
        group = 1 - group
        group_first += lanes


@nb.njit(cache=True, nogil=True)
def _add_group(
    lines: NDArray[np.float32],
    pairs: NDArray[np.uint64],
    block_hit: NDArray[np.bool_],
    voxels: NDArray[np.int64],
    chords: NDArray[np.float64],
    steps: NDArray[np.int64],
    return_weight: NDArray[np.float64],
    lanes: int,
    counters: NDArray[np.int64],
) -> None:
    """Add a group's placed visits (``lockstep.place_lanes``) to the blocks, ray by ray in
    order (``lines``: the blocks' s and n, flat; ``pairs``: the same memory, one word a
    voxel, which is 0 exactly when s and n are: they are never -0): ``s += float32(chord)``
    for every chord above 0 in float32 in this shard, then the ray's return,
    ``n += float32(return_weight)`` in its end voxel (none where the weight is 0), whose
    block is marked. Counts the voxels that
    became observed (``counters[1]``) and the visits (``counters[3]``)."""
    observed = 0
    visits = 0
    for lane in range(lanes):
        last = steps[lane]
        for k in range(last + 1):
            voxel = voxels[k * LANES + lane]
            chord = chords[k * LANES + lane]
            c = np.float32(chord)
            if c > 0.0 and voxel >= 0:  # (a chord below float32's least is no update)
                observed += pairs[voxel] == 0
                lines[2 * voxel] += c
                visits += 1
        # the end voxel takes the return; an end point exactly on a face gives a zero
        # chord there, still with its return
        if return_weight[lane] > 0.0:
            voxel = voxels[last * LANES + lane]
            observed += pairs[voxel] == 0
            lines[2 * voxel + 1] += np.float32(return_weight[lane])
            block_hit[voxel // BLOCK_VOXELS] = True
            visits += chords[last * LANES + lane] <= 0.0
    counters[1] += observed
    counters[3] += visits


StoreView = tuple[
    tuple[NDArray[np.int64], ...],  # table_keys of each shard
    tuple[NDArray[np.int32], ...],  # table_blocks of each shard
    tuple[NDArray[np.float32], ...],  # block_sn of each shard
    tuple[NDArray[np.float64], ...],  # block_t of each shard
]
"""The arrays of every shard that a read-only walk reads (``store_view``)."""


def store_view(store: BlockStore) -> StoreView:
    """The store's arrays for ``read_walk`` (valid until the store next changes)."""
    return (
        tuple(sh.table_keys for sh in store.shards),
        tuple(sh.table_blocks for sh in store.shards),
        tuple(sh.block_sn for sh in store.shards),
        tuple(sh.block_t for sh in store.shards),
    )


@nb.njit(cache=True, nogil=True)
def read_walk(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    view: StoreView,
    shard_mask: int,
    stamp: float,
    decay_time: float,
    shape: float,
    rate: float,
    ray_log_likelihood: NDArray[np.float64],
    record: bool,
    event_ray: NDArray[np.int64],
    event_ijk: NDArray[np.int32],
    event_s: NDArray[np.float64],
    event_n: NDArray[np.float64],
    event_chord: NDArray[np.float64],
    event_hit: NDArray[np.bool_],
) -> int:
    """The read-only twin of ``_walk_rays``: the same steps and chords, nothing written
    to the store. Returns the number of events.

    Events of a ray: every voxel it crosses with a positive chord before its end voxel is a
    pass over that chord; its end voxel is a return over the voxel's FULL chord (from where
    the ray entered it to where it would leave it) when the ray has a return, else a pass
    over the chord up to the end point. A voxel's statistics are its block's, decayed to
    ``stamp`` by ``exp(-|stamp - t_block| / decay_time)`` (``model.decay``); absent blocks
    are never observed (s = n = 0). With the Gamma(``shape``, ``rate``) prior on the
    extinction the pass probability over a chord l is ``((s+rate)/(s+rate+l))^(n+shape)``
    and a return's probability 1 minus that. ``ray_log_likelihood[r]`` receives the sum
    of the log-probabilities of ray r's events. With ``record``, event k is written to the
    ``event_*`` arrays (ray, voxel index, decayed s and n, chord, whether a return),
    which must hold ``visit_bounds`` events per ray.
    """
    tables_keys, tables_blocks, blocks_sn, blocks_t = view
    decays = math.isfinite(decay_time)
    events = 0
    # blocks found so far (block number, -1 when absent; shard), direct-mapped as in
    # _walk_rays: neighbouring rays cross the same blocks and the hash costs more
    cache_keys = np.full(1 << (3 * _READ_CACHE_BITS), -1, dtype=np.int64)
    cache_blocks = np.empty(cache_keys.shape[0], dtype=np.int64)
    tiny = 1e-280
    for r in range(lengths.shape[0]):
        length = lengths[r]
        # the stepping below is _walk_rays' (test_likelihood checks the chords); the ray's
        # origin and direction are also needed where it would leave its end voxel
        ox, oy, oz = origins_vox[r, 0], origins_vox[r, 1], origins_vox[r, 2]
        dx, dy, dz = ends_vox[r, 0] - ox, ends_vox[r, 1] - oy, ends_vox[r, 2] - oz
        (vx, vy, vz, ex, ey, ez, step_x, step_y, step_z, t_max_x, t_max_y, t_max_z,
         t_delta_x, t_delta_y, t_delta_z, steps) = _ray_start(origins_vox, ends_vox, r)  # fmt: skip
        t_prev = 0.0
        morton_x = _SPREAD[vx & _LOCAL_MASK] << 2
        morton_y = _SPREAD[vy & _LOCAL_MASK] << 1
        morton_z = _SPREAD[vz & _LOCAL_MASK]
        wrap_x = 0 if step_x > 0 else _LOCAL_MASK
        wrap_y = 0 if step_y > 0 else _LOCAL_MASK
        wrap_z = 0 if step_z > 0 else _LOCAL_MASK
        shard = 0
        block = -1
        f = 1.0  # decay factor of the current block
        total = 0.0
        # passes of voxels without returns (exponent ``shape``): their ratios are
        # multiplied, one log at the end (a division per voxel instead of a log)
        product = 1.0
        new_block = True
        while True:
            if new_block:
                bx = vx >> BLOCK_BITS
                by = vy >> BLOCK_BITS
                bz = vz >> BLOCK_BITS
                shard = shard_of(bx, by, bz, shard_mask)
                key = block_key(bx, by, bz)
                slot = (
                    ((bx & _READ_CACHE_MASK) << (2 * _READ_CACHE_BITS))
                    | ((by & _READ_CACHE_MASK) << _READ_CACHE_BITS)
                    | (bz & _READ_CACHE_MASK)
                )
                if cache_keys[slot] == key:
                    block = cache_blocks[slot]
                else:
                    block = find_block(tables_keys[shard], tables_blocks[shard], key)
                    cache_keys[slot] = key
                    cache_blocks[slot] = block
                f = 1.0
                if block >= 0 and decays:
                    f = math.exp(-abs(stamp - blocks_t[shard][block]) / decay_time)
            local = morton_x | morton_y | morton_z
            cx, cy, cz = vx, vy, vz
            s = 0.0
            n = 0.0
            if block >= 0:
                s = blocks_sn[shard][block, local, 0] * f
                n = blocks_sn[shard][block, local, 1] * f
            if steps == 0:
                break
            if t_max_x <= t_max_y and t_max_x <= t_max_z:
                t_next = t_max_x
                vx += step_x
                t_max_x = t_max_x + t_delta_x if vx != ex else np.inf
                axis_local = vx & _LOCAL_MASK
                morton_x = _SPREAD[axis_local] << 2
                new_block = axis_local == wrap_x
            elif t_max_y <= t_max_z:
                t_next = t_max_y
                vy += step_y
                t_max_y = t_max_y + t_delta_y if vy != ey else np.inf
                axis_local = vy & _LOCAL_MASK
                morton_y = _SPREAD[axis_local] << 1
                new_block = axis_local == wrap_y
            else:
                t_next = t_max_z
                vz += step_z
                t_max_z = t_max_z + t_delta_z if vz != ez else np.inf
                axis_local = vz & _LOCAL_MASK
                morton_z = _SPREAD[axis_local]
                new_block = axis_local == wrap_z
            t_next = min(t_next, 1.0)
            chord = (t_next - t_prev) * length
            t_prev = t_next
            steps -= 1
            if chord > 0.0:
                # log P(pass) = (n + shape) log((s + rate) / (s + rate + chord))
                if n == 0.0:
                    product *= (s + rate) / (s + rate + chord)
                    if product < tiny:
                        total += shape * math.log(product)
                        product = 1.0
                else:
                    total -= (n + shape) * math.log1p(chord / (s + rate))
                if record:
                    event_ray[events] = r
                    event_ijk[events, 0] = cx
                    event_ijk[events, 1] = cy
                    event_ijk[events, 2] = cz
                    event_s[events] = s
                    event_n[events] = n
                    event_chord[events] = chord
                    event_hit[events] = False
                events += 1
        # the end voxel (vx, vy, vz)
        if has_return[r]:
            # where the ray would leave the end voxel: its nearest exit face beyond the end
            t_exit = np.inf
            if dx != 0.0:
                t_exit = min(t_exit, ((vx + (dx > 0)) - ox) / dx)
            if dy != 0.0:
                t_exit = min(t_exit, ((vy + (dy > 0)) - oy) / dy)
            if dz != 0.0:
                t_exit = min(t_exit, ((vz + (dz > 0)) - oz) / dz)
            chord = max((max(t_exit, 1.0) - t_prev) * length, RETURN_CHORD_FLOOR)
            total += math.log(-math.expm1(-(n + shape) * math.log1p(chord / (s + rate))))
            hit = True
        else:
            chord = (1.0 - t_prev) * length
            hit = False
            if chord > 0.0:
                total -= (n + shape) * math.log1p(chord / (s + rate))
        total += shape * math.log(product)
        if hit or chord > 0.0:
            if record:
                event_ray[events] = r
                event_ijk[events, 0] = vx
                event_ijk[events, 1] = vy
                event_ijk[events, 2] = vz
                event_s[events] = s
                event_n[events] = n
                event_chord[events] = chord
                event_hit[events] = hit
            events += 1
        ray_log_likelihood[r] = total
    return events
