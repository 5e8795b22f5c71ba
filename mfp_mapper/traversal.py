"""Exact voxel traversal (Amanatides & Woo) of lidar rays into the block store, with numba.

A ray runs from its origin to its end point: its first return, or the point where it was
cut at ``max_range``. Every voxel it crosses gets ``s += chord`` — the exact length in
metres of the ray inside that voxel, so a ray's chords add up to its length — and a ray
that ends in a return gives its end voxel ``n += 1`` (the chord from where it entered that
voxel up to the return point is its last chord).

Walk and store update run in one pass: a ray stays in an 8x8x8 block for several steps,
so most updates index the block the walk is already in. Several threads each walk all
the rays and update only the blocks of their own shards.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.store import BLOCK_BITS, Shard, block_key, local_index, open_block, shard_of


def block_bounds(
    origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Upper bound of the blocks each ray can create: Manhattan block distance plus slack."""
    lo = np.floor(origins_vox).astype(np.int64) >> BLOCK_BITS
    hi = np.floor(ends_vox).astype(np.int64) >> BLOCK_BITS
    return np.abs(hi - lo).sum(axis=1) + 2


_CACHE_BITS = 4
_CACHE_MASK = (1 << _CACHE_BITS) - 1
_CACHE_SIZE = 1 << (3 * _CACHE_BITS)
_BATCH_VISITS = 2048
"""Voxel visits gathered (from several rays) before they are applied to the blocks."""


@nb.njit(cache=True, nogil=True)
def _walk_into_shard(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    room_needed: NDArray[np.int64],
    first: int,
    shard: int,
    shard_mask: int,
    table_keys: NDArray[np.int64],
    table_blocks: NDArray[np.int32],
    block_ijk: NDArray[np.int32],
    block_sn: NDArray[np.float32],
    block_t: NDArray[np.float64],
    block_scan: NDArray[np.int64],
    counters: NDArray[np.int64],
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> int:
    """Walk rays ``first..`` (voxel units), adding their chords and returns to ``shard``.

    Rays are walked in batches: the walk records each visit (block, voxel, chord, return)
    in a buffer; the buffer is then applied in two passes, one that only loads the voxels'
    cache lines (independent loads, so their memory latencies overlap) and one that adds.
    Before each ray, checks there is room for the blocks it may create; returns the index
    of the first ray not walked (the caller grows the shard and calls again), or N.
    """
    capacity = min(block_t.shape[0], table_keys.shape[0] // 2)
    # blocks opened in this call, direct-mapped by their low index bits: neighbouring rays
    # cross the same blocks, and this small table stays in cache where the hash does not
    cache_keys = np.full(_CACHE_SIZE, -1, dtype=np.int64)
    cache_blocks = np.empty(_CACHE_SIZE, dtype=np.int64)
    longest = 0
    for r in range(first, lengths.shape[0]):
        longest = max(longest, _visit_bound(origins_vox[r], ends_vox[r]))
    visit_block = np.empty(_BATCH_VISITS + longest, dtype=np.int64)
    visit_local = np.empty(_BATCH_VISITS + longest, dtype=np.int64)
    visit_chord = np.empty(_BATCH_VISITS + longest, dtype=np.float32)
    visit_return = np.empty(_BATCH_VISITS + longest, dtype=np.float32)
    count = 0
    for r in range(first, lengths.shape[0] + 1):
        if (
            count >= _BATCH_VISITS
            or r == lengths.shape[0]
            or counters[0] + room_needed[r] > capacity
        ):
            _apply_visits(
                block_sn, visit_block, visit_local, visit_chord, visit_return, count, counters
            )
            count = 0
            if r == lengths.shape[0] or counters[0] + room_needed[r] > capacity:
                return r
        ox = origins_vox[r, 0]
        oy = origins_vox[r, 1]
        oz = origins_vox[r, 2]
        dx = ends_vox[r, 0] - ox
        dy = ends_vox[r, 1] - oy
        dz = ends_vox[r, 2] - oz
        length = lengths[r]
        vx = int(np.floor(ox))
        vy = int(np.floor(oy))
        vz = int(np.floor(oz))
        ex = int(np.floor(ends_vox[r, 0]))
        ey = int(np.floor(ends_vox[r, 1]))
        ez = int(np.floor(ends_vox[r, 2]))
        # ray parameter t in [0, 1]; t_max_*: where the next face on that axis is crossed.
        # An axis already at the end voxel's index is never stepped again (t_max = inf), so
        # the walk takes exactly `steps` steps and ends in floor(end), whatever the rounding.
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
        t_prev = 0.0
        bx = by = bz = 0
        block = -1
        new_block = True
        while True:
            if new_block:
                # written out here, not called: a call with array arguments costs more than
                # the whole step (reference counting of every array)
                bx = vx >> BLOCK_BITS
                by = vy >> BLOCK_BITS
                bz = vz >> BLOCK_BITS
                block = -1
                if shard_of(bx, by, bz, shard_mask) == shard:
                    slot = (
                        ((bx & _CACHE_MASK) << (2 * _CACHE_BITS))
                        | ((by & _CACHE_MASK) << _CACHE_BITS)
                        | (bz & _CACHE_MASK)
                    )
                    key = block_key(bx, by, bz)
                    if cache_keys[slot] == key:
                        block = cache_blocks[slot]
                    else:
                        block = open_block(
                            bx,
                            by,
                            bz,
                            table_keys,
                            table_blocks,
                            block_ijk,
                            block_sn,
                            block_t,
                            block_scan,
                            counters,
                            scan_id,
                            stamp,
                            decay_time,
                        )
                        cache_keys[slot] = key
                        cache_blocks[slot] = block
            # the end voxel takes the rest of the ray and the return; an end point exactly
            # on a face gets a zero chord there, still with its return
            final = steps == 0
            t_next = 1.0 if final else min(t_max_x, t_max_y, t_max_z, 1.0)
            chord = (t_next - t_prev) * length
            returns = final and has_return[r]
            if block >= 0 and (chord > 0.0 or returns):
                visit_block[count] = block
                visit_local[count] = local_index(vx, vy, vz)
                visit_chord[count] = chord
                visit_return[count] = 1.0 if returns else 0.0
                count += 1
            if final:
                break
            t_prev = t_next
            steps -= 1
            if t_max_x <= t_max_y and t_max_x <= t_max_z:
                vx += step_x
                t_max_x = t_max_x + t_delta_x if vx != ex else np.inf
            elif t_max_y <= t_max_z:
                vy += step_y
                t_max_y = t_max_y + t_delta_y if vy != ey else np.inf
            else:
                vz += step_z
                t_max_z = t_max_z + t_delta_z if vz != ez else np.inf
            new_block = (
                (vx >> BLOCK_BITS) != bx or (vy >> BLOCK_BITS) != by or (vz >> BLOCK_BITS) != bz
            )
    return lengths.shape[0]


@nb.njit(inline="always", cache=True)
def _visit_bound(origin: NDArray[np.float64], end: NDArray[np.float64]) -> int:
    """Most voxels a walk from ``origin`` to ``end`` (voxel units) can visit."""
    return (
        abs(int(np.floor(end[0])) - int(np.floor(origin[0])))
        + abs(int(np.floor(end[1])) - int(np.floor(origin[1])))
        + abs(int(np.floor(end[2])) - int(np.floor(origin[2])))
        + 2
    )


@nb.njit(cache=True, nogil=True)
def _apply_visits(
    block_sn: NDArray[np.float32],
    visit_block: NDArray[np.int64],
    visit_local: NDArray[np.int64],
    visit_chord: NDArray[np.float32],
    visit_return: NDArray[np.float32],
    count: int,
    counters: NDArray[np.int64],
) -> None:
    """Add the buffered visits, in order, to their voxels: s += chord, n += return."""
    # first only load every visited cache line: the loads do not depend on each other, so
    # the processor keeps many misses in flight; the additions then find the lines in cache
    touch = np.float32(0.0)
    for i in range(count):
        touch += block_sn[visit_block[i], visit_local[i], 1]
    new = 0
    for i in range(count):
        b = visit_block[i]
        v = visit_local[i]
        if block_sn[b, v, 0] == 0.0 and block_sn[b, v, 1] == 0.0:
            new += 1
        block_sn[b, v, 0] += visit_chord[i]
        block_sn[b, v, 1] += visit_return[i]
    counters[1] += new
    counters[3] += count + (touch < 0.0)  # touch is never negative; using it keeps the loads


def walk_into_shard(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    shard: Shard,
    shard_id: int,
    shard_mask: int,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> None:
    """Add every ray's contribution that falls in one shard, growing the shard as needed.

    Coordinates are in voxel units (metres / resolution); ``lengths`` in metres.
    """
    room = block_bounds(origins_vox, ends_vox)
    first = 0
    while True:
        first = _walk_into_shard(
            origins_vox,
            ends_vox,
            lengths,
            has_return,
            room,
            first,
            shard_id,
            shard_mask,
            shard.table_keys,
            shard.table_blocks,
            shard.block_ijk,
            shard.block_sn,
            shard.block_t,
            shard.block_scan,
            shard.counters,
            scan_id,
            stamp,
            decay_time,
        )
        if first >= lengths.shape[0]:
            return
        shard.grow(min_free=int(room[first]))
