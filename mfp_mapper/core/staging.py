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
    N_BLOCK_CHUNKS,
    block_key,
    find_block,
)
from mfp_mapper.core.shard import (
    FLUSH_PENDING,
    NCHUNK_USED,
    NREC_USED,
    S_USED,
    Shard,
    ShardArrays,
    block_values,
    chunk_slot,
    n_index,
    open_block,
    s_index,
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
    s_add = np.empty(BLOCK_VOXELS)
    n_add = np.empty(BLOCK_VOXELS)
    flat_s = sa.s_pool.reshape(-1)
    marks = flat_s.view(np.uint32)  # 0: unobserved (shard's notes)
    flat_n = sa.n_pool.reshape(-1)
    block_chunks, chunk_owner, pools = sa.block_chunks, sa.chunk_owner, sa.pools
    block_nrec, n_recs = sa.block_nrec, sa.n_recs
    for b in range(start, used):
        mb = open_block(
            staged.block_ijk[b, 0], staged.block_ijk[b, 1], staged.block_ijk[b, 2], sa,
            scan_id, stamp, decay_time,
        )  # fmt: skip
        if mb < 0:
            return b
        scale = np.float32(sa.block_scale[mb])
        block_values(staged, b, s_add, n_add)  # the scan's (float32: no float64 part)
        flush = False
        new = 0
        for place in range(BLOCK_VOXELS):
            s, n = np.float32(s_add[place]), np.float32(n_add[place])
            if s == 0.0 and n == 0.0:
                continue
            # every observed voxel has its s chunk, -0 there while its s is 0 (shard's notes;
            # the staged voxel has its chunk too: room for as many)
            voxel = -(chunk_slot(mb, place >> CHUNK_BITS) + 1) * CHUNK_VOXELS
            k = s_index(block_chunks, chunk_owner, pools, voxel + place % CHUNK_VOXELS)
            new += marks[k] == 0
            after = flat_s[k] + s * scale
            flat_s[k] = after if after != 0.0 else -0.0
            flush |= after >= s_limit
            if n != 0.0:
                k = n_index(block_nrec, n_recs, pools, mb, place, True)
                flat_n[k] += n * scale
                flush |= flat_n[k] >= n_limit
        _zero_block(staged, b)  # merged: the staged store is empty again after
        if staged.block_hit[b]:
            sa.block_hit[mb] = True
        if flush:
            sa.block_flush[mb] = True
            sa.pools[FLUSH_PENDING] = 1
        sa.counters[1] += new
    return used


@nb.njit(cache=True, nogil=True)
def _zero_block(sa: ShardArrays, block: int) -> None:
    """Zero the float32 parts of ``block``."""
    for k in range(BLOCK_CHUNKS):
        chunk = sa.block_chunks[chunk_slot(block, k)]
        if chunk >= 0:
            sa.s_pool[chunk] = 0.0
    row = sa.block_nrec[block]
    if row >= 0:
        for k in range(N_BLOCK_CHUNKS):
            chunk = sa.n_recs[row, k]
            if chunk >= 0:
                sa.n_pool[chunk] = 0.0


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
