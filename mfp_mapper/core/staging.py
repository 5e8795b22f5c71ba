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

from mfp_mapper.core.blocks import BLOCK_VOXELS, block_key, find_block
from mfp_mapper.core.shard import Shard, ShardArrays, open_block
from mfp_mapper.core.store import BlockStore


@nb.njit(cache=True, nogil=True)
def _merge_blocks(
    staged_ijk: NDArray[np.int32],
    staged_sn: NDArray[np.float32],
    staged_hit: NDArray[np.bool_],
    used: int,
    start: int,
    shard_arrays: ShardArrays,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> int:
    """Add staged blocks ``start..used`` to the shard; returns ``used``, or the block
    where the shard ran out of room (grow it and call again from there)."""
    block_sn, block_hit = shard_arrays[3], shard_arrays[6]
    counters, block_scale = shard_arrays[7], shard_arrays[8]
    for b in range(start, used):
        mb = open_block(
            staged_ijk[b, 0], staged_ijk[b, 1], staged_ijk[b, 2], shard_arrays, scan_id, stamp,
            decay_time,
        )  # fmt: skip
        if mb < 0:
            return b
        scale = np.float32(block_scale[mb])
        # every voxel, without a branch (the loop vectorises): a voxel the scan did not
        # reach adds 0 * scale = 0, which leaves its statistics as they are, bit for bit
        staged = staged_sn[b].reshape(-1)
        merged = block_sn[mb].reshape(-1)
        new = 0
        for i in range(0, 2 * BLOCK_VOXELS, 2):
            reached = (staged[i] != 0.0) | (staged[i + 1] != 0.0)
            new += reached & (merged[i] == 0.0) & (merged[i + 1] == 0.0)
            merged[i] += staged[i] * scale
            merged[i + 1] += staged[i + 1] * scale
        staged[:] = 0.0  # merged: the staged store is empty again after
        if staged_hit[b]:
            block_hit[mb] = True
        counters[1] += new
    return used


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
    while start < staged.used:
        stop = min(start + MERGE_CHUNK_BLOCKS, staged.used)
        while (
            start := _merge_blocks(
                staged.block_ijk,
                staged.block_sn,
                staged.block_hit,
                stop,
                start,
                shard.arrays(),
                scan_id,
                stamp,
                decay_time,
            )  # fmt: skip
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
    start, stop = shard.used, min(shard.used + new, shard.block_sn.shape[0])
    if stop > start:
        flat = shard.block_sn[start:stop].reshape(-1)
        flat[:: mmap.PAGESIZE // flat.itemsize] = 0.0  # one write per page


SPARE_MAX_BLOCKS = 32768
"""A merged staged store that held at most this many blocks (128 MiB of statistics) is kept,
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
