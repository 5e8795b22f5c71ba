"""Staged scans: a scan integrated into a store of its own, then added to the map at once.

The live node integrates a scan without holding the map: the rays are walked into a fresh
``BlockStore`` that holds only this scan's contributions (every block new, at the scan's
stamp), while services keep reading the map; then ``merge_staged`` adds that store to the
map's, under the map lock, in one pass over the blocks the scan touched. A reader sees the
map before the scan or after it, never part of one.

The merge is what the direct integration computes (``shard.open_block`` brings each block
to the scan's stamp, or scales a late scan's data, as there): only the order of the float32
summation differs (the scan's visits are summed first, then added to the map).
"""

from __future__ import annotations

import mmap
from collections.abc import Callable

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_CHUNKS,
    BLOCK_VOXELS,
    CHUNK_BITS,
    CHUNK_VOXELS,
    block_key,
    find_block,
)
from mfp_mapper.core.shard import (
    NCHUNK_USED,
    NREC_USED,
    S_USED,
    Shard,
    ShardArrays,
    chunk_slot,
    mark_flush,
    n_index,
    open_block,
    s_index,
    voxel_stats,
)
from mfp_mapper.core.store import BlockStore


@nb.njit(cache=True, nogil=True)
def _merge_blocks(
    staged: ShardArrays,
    used: int,
    start: int,
    sa: ShardArrays,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> int:
    """Add staged blocks ``start..used`` to the shard ``sa`` (room made for the staged
    store's chunks: ``Shard.ensure_room``), zeroing what it read; returns ``used``, or the
    block where the shard ran out of blocks (grow it and call again from there)."""
    s_limit, n_limit = sa.limits[0], sa.limits[1]
    flat_s = sa.s_pool.reshape(-1)
    flat_n = sa.n_pool.reshape(-1)
    staged_n = staged.n_pool.reshape(-1)
    for b in range(start, used):
        mb = open_block(
            staged.block_ijk[b, 0], staged.block_ijk[b, 1], staged.block_ijk[b, 2], sa,
            scan_id, stamp, decay_time,
        )  # fmt: skip
        if mb < 0:
            return b
        scale = np.float32(sa.block_scale[mb])
        new = 0
        flush = False
        for k in range(BLOCK_CHUNKS):
            chunk = staged.block_chunks[chunk_slot(b, k)]
            if chunk < 0:
                continue
            slot = chunk_slot(mb, k)
            base = s_index(sa, -(slot + 1) * CHUNK_VOXELS)
            for i in range(CHUNK_VOXELS):
                add = staged.s_pool[chunk, i]
                if add != 0.0:
                    before = flat_s[base + i]
                    if before == 0.0:
                        s, n = voxel_stats(sa, mb, k * CHUNK_VOXELS + i)
                        new += s == 0.0 and n == 0.0
                    flat_s[base + i] = before + add * scale
                    flush |= flat_s[base + i] >= s_limit
                    staged.s_pool[chunk, i] = 0.0  # merged: the staged store is empty after
        if staged.block_nrec[b] >= 0:
            for place in range(BLOCK_VOXELS):
                k = n_index(staged, b, place, False)
                if k < 0 or staged_n[k] == 0.0:
                    continue
                chunk = sa.block_chunks[chunk_slot(mb, place >> CHUNK_BITS)]
                s_before = 0.0 if chunk < 0 else flat_s[chunk * CHUNK_VOXELS + place % 64]
                m = n_index(sa, mb, place, True)
                if s_before == 0.0 and flat_n[m] == 0.0 and staged_s_zero(staged, b, place):
                    s, n = voxel_stats(sa, mb, place)
                    new += s == 0.0 and n == 0.0
                flat_n[m] += staged_n[k] * scale
                flush |= flat_n[m] >= n_limit
                staged_n[k] = 0.0
        if staged.block_hit[b]:
            sa.block_hit[mb] = True
        if flush:
            mark_flush(sa, mb)
        sa.counters[1] += new
    return used


@nb.njit(inline="always", cache=True)
def staged_s_zero(staged: ShardArrays, block: int, place: int) -> bool:
    """Whether the staged ``s`` of a voxel is 0 (then the s pass above did not count it)."""
    chunk = staged.block_chunks[chunk_slot(block, place >> CHUNK_BITS)]
    return chunk < 0 or staged.s_pool[chunk, place % CHUNK_VOXELS] == 0.0


MERGE_CHUNK_BLOCKS = 8192
"""Staged blocks merged between two calls of ``pause`` (32 MiB of statistics)."""


def merge_shard(
    staged: Shard,
    shard: Shard,
    scan_id: int,
    stamp: float,
    decay_time: float,
    pause: Callable[[], None] | None = None,
) -> None:
    """Add one staged shard to the map's shard of the same number (same block hash), in
    chunks of ``MERGE_CHUNK_BLOCKS`` blocks with a call of ``pause`` between two."""
    start = 0
    shard.ensure_room(
        int(staged.pools[S_USED]), int(staged.pools[NCHUNK_USED]), 0, int(staged.pools[NREC_USED])
    )
    while start < staged.used:
        stop = min(start + MERGE_CHUNK_BLOCKS, staged.used)
        while (
            start := _merge_blocks(
                staged.arrays(), stop, start, shard.arrays(), scan_id, stamp, decay_time
            )
        ) < stop:
            shard.grow(min_free=staged.used - start)
        if pause is not None and start < staged.used:
            pause()


@nb.njit(cache=True, nogil=True)
def _count_new_blocks(
    staged_ijk: NDArray[np.int32],
    used: int,
    table_keys: NDArray[np.int64],
    table_blocks: NDArray[np.int32],
) -> int:
    """How many of the staged blocks the map's shard does not hold yet."""
    new = 0
    for b in range(used):
        key = block_key(staged_ijk[b, 0], staged_ijk[b, 1], staged_ijk[b, 2])
        if find_block(table_keys, table_blocks, key) < 0:
            new += 1
    return new


def prefault(staged: Shard, shard: Shard) -> None:
    """Touch the memory of the blocks the merge will create in ``shard``, so that the
    merge (under the map lock) finds it resident: the system's zeroing of fresh pages is
    a large part of adding a scan that reaches new space.

    Runs without the map lock, in the one thread that changes the map: it reads the hash
    table and writes zeros (what the pages already read as) past the used blocks only,
    which no reader looks at."""
    new = _count_new_blocks(staged.block_ijk, staged.used, shard.table_keys, shard.table_blocks)
    chunks = int(staged.pools[S_USED]) * new // max(staged.used, 1)  # about as many a block
    start = int(shard.pools[S_USED])
    stop = min(start + chunks, shard.s_pool.shape[0])
    if stop > start:
        flat = shard.s_pool[start:stop].reshape(-1)
        flat[:: mmap.PAGESIZE // flat.itemsize] = 0.0  # one write per page


SPARE_MAX_BLOCKS = 32768
"""A merged staged store that held at most this many blocks (64 MiB of ``s`` at most) is kept,
emptied, for the next scan (``clear_staged``); a larger one gives its memory back."""


def clear_staged(staged: BlockStore) -> bool:
    """Empty a staged store after its merge (which zeroed its statistics), keeping its
    memory (``BlockStore.forget_blocks``): the next scan staged into it writes pages already
    resident instead of fresh ones the system must fault in and zero (about 48 MB a scan
    for an OS1-128 scan at 0.2 m). False, and the store left alone, when it is too large to
    keep (``SPARE_MAX_BLOCKS``)."""
    if staged.num_blocks > SPARE_MAX_BLOCKS:
        return False
    staged.forget_blocks()
    return True


def staged_updates(staged: BlockStore) -> int:
    """Voxel updates the staged scan made (the direct integration's ``voxels_touched``)."""
    return int(sum(int(sh.counters[3]) for sh in staged.shards))
