"""Sparse voxel store: a hash of 8x8x8 blocks holding ``(s, n)`` per voxel.

Layout (chosen for speed and memory; docs/performance.md measures it):

* Voxels live in blocks of ``BLOCK_EDGE**3``, in Morton order; a ray stays in one block for
  several steps, so most updates are an array index into the block the walk is already in.
* Blocks are found through open-addressing hash tables, split into ``shards`` by tiles
  of blocks (``blocks.shard_of``); one thread at a time writes to a shard (an integration
  has four shards a thread, ``traversal.SHARDS_PER_THREAD``), so threads need no locks
  (see ``traversal``).
* ``s`` is float32 in chunks of 64 voxels (a 4x4x4 cube, 256 bytes: four cache lines),
  allocated when a ray first reaches the chunk; ``n`` is float32 in chunks of 16 voxels,
  allocated when a return first lands in one (``shard`` says where everything lives). Free
  space pays 4 bytes a voxel of the chunks it reaches. Each block keeps the time ``t`` its
  statistics refer to. Decay (Eq. 28-30) is uniform scaling, so bringing a whole block to
  the current stamp the first time a scan touches it is exactly the per-voxel lazy decay;
  a voxel's ``t_last`` is its block's ``t``. A late scan (older than the block) leaves
  the block and its time alone and adds its data scaled by ``exp(-(t - stamp) / T)``, so
  the map does not depend on the order in which scans arrive.
* No sum stops adding: a voxel's float32 parts are flushed into float64 (per block, after
  the scan) before they grow large enough to lose what a chord adds (``shard.FLUSH_EDGES``,
  ``shard.N_LIMIT``).
* A voxel is *observed* when ``s > 0`` or ``n > 0``.

Every ray's contribution is summed into the store: sums, never deduplication.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_BITS,
    BLOCK_CHUNKS,
    BLOCK_EDGE,
    BLOCK_VOXELS,
    CHUNK_BITS,
    CHUNK_VOXELS,
    MAX_VOXEL_INDEX,
    N_BLOCK_CHUNKS,
    N_CHUNK_VOXELS,
    IndexBox,
    block_key,
    block_origin,
    block_outside,
    find_block,
    index_box,
    insert_block,
    local_coords,
    local_index,
    shard_of,
    tile_bits,
    tile_z_offset,
    voxel_inside,
)
from mfp_mapper.core.layout import (  # noqa: F401 (numba-free, re-exported)
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    VoxelArrays,
    mask_words,
    voxel_problem,
)
from mfp_mapper.core.lockstep import prefetch_line
from mfp_mapper.core.packed import (
    MASK_WORDS,
    BlockChunk,
    PackedBlocks,
    PackedRun,
    PackOutputs,
    hi_starts,
    hit_row_of,
    pack_chunk,
    pack_chunks,
    packed_runs,
    sort_keys,
    voxel_starts,
)
from mfp_mapper.core.shard import (
    HI_USED,
    NCHUNK_USED,
    NREC_USED,
    S_USED,
    Shard,
    ShardArrays,
    block_values,
    chunk_slot,
    init_block,
    n_index,
    open_block,
    s_index,
    voxel_stats,
)

_THREADED_PACK_BLOCKS = 16_384
"""Blocks from which ``BlockStore.export_blocks`` packs half of them in a thread of their
own."""
_THREADED_WRITE_VOXELS = 1_000_000
"""Voxels from which ``BlockStore.assign_blocks`` writes the ``s`` parts in a second
thread while it opens the blocks, then in both (``BlockStore._fill_parts``)."""
_PARTS_AHEAD = 8
"""Blocks ahead whose chunks ``_block_parts`` prefetches."""
_WRITE_PIECE_VOXELS = 1 << 18
"""Voxels of ``s`` a thread writes at a time when two write (1 MiB of values)."""

__all__ = ["BLOCK_EDGE", "MAX_VOXEL_INDEX", "BlockStats", "BlockStore", "VoxelArrays", "index_box"]


@dataclass
class BlockStats:
    """Statistics of a run of blocks (``BlockStore.blocks``): block index ``ijk`` (voxel
    index >> 3), time ``t``, and ``s``, ``n`` of their 512 voxels each in Morton order
    (``blocks.local_coords``); ``has_n[b]`` is False where block b holds no return (its
    ``n`` row is all zeros)."""

    ijk: NDArray[np.int32]
    t: NDArray[np.float64]
    s: NDArray[np.float64]
    n: NDArray[np.float64]
    has_n: NDArray[np.bool_]


@nb.njit(cache=True, nogil=True)
def _open_blocks_of(
    ijk: NDArray[np.int64],
    t: NDArray[np.float64],
    start: int,
    shard: int,
    shard_mask: int,
    sa: ShardArrays,
) -> int:
    """Open the blocks of the voxels of ``shard`` from index ``start`` on, each at the
    latest ``t`` of its voxels. Returns ``len(ijk)``, or the index where blocks ran out."""
    last_key = np.int64(-1)  # map files list voxels block by block: one probe a block
    block = -1
    for j in range(start, ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        key = block_key(bx, by, bz)
        if key != last_key or block < 0:
            if shard_of(bx, by, bz, shard_mask) != shard:
                last_key, block = key, -1
                continue
            block = open_block(bx, by, bz, sa, -1, t[j], math.inf)
            if block < 0:
                return j
            last_key = key
        sa.block_t[block] = max(sa.block_t[block], t[j])
    return ijk.shape[0]


@nb.njit(cache=True, nogil=True)
def _set_voxels(
    ijk: NDArray[np.int64],
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t: NDArray[np.float64],
    start: int,
    shard: int,
    shard_mask: int,
    decay_time: float,
    sa: ShardArrays,
    seen: NDArray[np.uint64],
    counts: NDArray[np.int64],
) -> int:
    """Set the voxels of ``shard`` from index ``start`` on (blocks opened by
    ``_open_blocks_of``), each decayed to its block's time; ``counts[0]`` receives the
    number of observed voxels set. A value at or above its float32 limit (``sa.limits``)
    goes to the block's float64 part. Returns -1 when done; ``-2 - j`` when the pools ran
    out of room at voxel j (make room, call again from j); else the index of a voxel
    listed twice (``seen``: one bit per voxel of each block)."""
    observed = 0
    last_key = np.int64(-1)  # map files list voxels block by block: one probe a block
    block = -1
    s_limit, n_limit = sa.limits[0], sa.limits[1]
    block_chunks, chunk_owner, pools = sa.block_chunks, sa.chunk_owner, sa.pools
    block_nrec, n_recs = sa.block_nrec, sa.n_recs
    flat_s, flat_n = sa.s_pool.reshape(-1), sa.n_pool.reshape(-1)
    marks = flat_s.view(np.uint32)  # 0: unobserved (shard's notes)
    for j in range(start, ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        key = block_key(bx, by, bz)
        if key != last_key:
            last_key = key
            block = (
                find_block(sa.table_keys, sa.table_blocks, key)
                if shard_of(bx, by, bz, shard_mask) == shard
                else -1
            )
        if block < 0:
            continue
        if (
            sa.pools[S_USED] >= sa.chunk_owner.shape[0]
            or sa.pools[NREC_USED] >= sa.n_recs.shape[0]
            or sa.pools[NCHUNK_USED] >= sa.n_pool.shape[0]
            or sa.pools[HI_USED] >= sa.hi_pool.shape[0]
        ):
            counts[0] += observed
            return -2 - j
        local = local_index(ijk[j, 0], ijk[j, 1], ijk[j, 2])
        bit = np.uint64(1) << np.uint64(local & 63)
        if seen[block, local >> 6] & bit:
            counts[0] += observed
            return j
        seen[block, local >> 6] |= bit
        f = 1.0
        if math.isfinite(decay_time):
            f = math.exp(-(sa.block_t[block] - t[j]) / decay_time)
        sj = s[j] * f
        nj = n[j] * f
        if sj >= s_limit or nj >= n_limit:  # beyond what float32 keeps adding to
            hi = sa.block_href[block]
            if hi < 0:
                hi = sa.pools[HI_USED]
                sa.pools[HI_USED] = hi + 1
                sa.block_href[block] = hi
                sa.hi_pool[hi] = 0.0
            sa.hi_pool[hi, local, 0] = sj
            sa.hi_pool[hi, local, 1] = nj
        else:
            if sj != 0.0:
                voxel = -(chunk_slot(block, local >> CHUNK_BITS) + 1) * CHUNK_VOXELS + (local & 63)
                flat_s[s_index(block_chunks, chunk_owner, pools, voxel)] = sj
            if nj != 0.0:
                flat_n[n_index(block_nrec, n_recs, pools, block, local, True)] = nj
        if nj > 0.0:
            sa.block_hit[block] = True
        if sj > 0.0 or nj > 0.0:
            observed += 1
            # its s chunk, -0 there while its float32 s is 0 (shard's notes)
            voxel = -(chunk_slot(block, local >> CHUNK_BITS) + 1) * CHUNK_VOXELS + (local & 63)
            k = s_index(block_chunks, chunk_owner, pools, voxel)
            if marks[k] == 0:
                flat_s[k] = -0.0
    counts[0] += observed
    return -1


_DE_BRUIJN = np.uint64(0x03F79D71B4CB0A89)
"""A de Bruijn sequence: the top 6 bits of ``(1 << k) * _DE_BRUIJN`` differ for every k."""
_LOW_BIT = np.zeros(64, dtype=np.int64)
"""``_LOW_BIT[(1 << k) * _DE_BRUIJN >> 58] == k``: the place of a word's single set bit."""
_LOW_BIT[[((1 << k) * int(_DE_BRUIJN) % (1 << 64)) >> 58 for k in range(64)]] = np.arange(64)


@nb.njit(cache=True, nogil=True, inline="always")
def _no_room_for_block(sa: ShardArrays) -> bool:
    """Whether opening one more whole block (its table entry, every chunk, an ``n``
    record, a float64 part) could overrun the shard's arrays: the loaders make room then."""
    used, pools = sa.counters[0], sa.pools
    return (
        used >= sa.block_t.shape[0]
        or 2 * used >= sa.table_keys.shape[0]
        or pools[S_USED] + BLOCK_CHUNKS > sa.chunk_owner.shape[0]
        or pools[NREC_USED] + 1 > sa.n_recs.shape[0]
        or pools[NCHUNK_USED] + N_BLOCK_CHUNKS > sa.n_pool.shape[0]
        or pools[HI_USED] + 1 > sa.hi_pool.shape[0]
    )


@nb.njit(cache=True, nogil=True)
def _set_blocks(
    packed_ijk: NDArray[np.int32],
    packed_t: NDArray[np.float64],
    observed: NDArray[np.uint64],
    s: NDArray[np.floating],
    s_start: NDArray[np.int64],
    hit_row: NDArray[np.int64],
    hit: NDArray[np.uint64],
    n: NDArray[np.floating],
    n_start: NDArray[np.int64],
    start: int,
    shard: int,
    shard_mask: int,
    sa: ShardArrays,
    counts: NDArray[np.int64],
) -> int:
    """Set the packed blocks of ``shard`` (``packed.PackedBlocks``: ``s_start`` and
    ``n_start`` their first values, ``hit_row`` each block's row of ``hit`` or -1) from
    block ``start`` on, exactly as ``_set_voxels`` sets their voxel lists (same chunks,
    float64 parts and -0 marks, allocated in the same order) with one table probe a block
    and no index arrays; ``counts[0]`` receives the observed voxels set. Returns the number
    of blocks when done, else the block where the shard ran out of room (make room, call
    again from there)."""
    observed_count = 0
    s_limit, n_limit = sa.limits[0], sa.limits[1]
    block_chunks, chunk_owner, pools = sa.block_chunks, sa.chunk_owner, sa.pools
    block_nrec, n_recs = sa.block_nrec, sa.n_recs
    flat_s, flat_n = sa.s_pool.reshape(-1), sa.n_pool.reshape(-1)
    for b in range(start, packed_ijk.shape[0]):
        bx, by, bz = packed_ijk[b, 0], packed_ijk[b, 1], packed_ijk[b, 2]
        if shard_of(bx, by, bz, shard_mask) != shard:
            continue
        if _no_room_for_block(sa):
            counts[0] += observed_count
            return b
        block = open_block(bx, by, bz, sa, -1, packed_t[b], math.inf)
        sa.block_t[block] = max(sa.block_t[block], packed_t[b])
        js = s_start[b]
        row = hit_row[b]
        jn = n_start[row] if row >= 0 else 0
        for w in range(BLOCK_VOXELS // 64):  # a mask word is an s chunk (64 voxels)
            mo = observed[b, w]
            if mo == 0:
                continue
            mh = hit[row, w] if row >= 0 else np.uint64(0)
            slot = chunk_slot(block, w)
            while mo:  # the set bits, lowest first (a branch per voxel kept, not per bit)
                bit = mo & (np.uint64(0) - mo)
                mo ^= bit
                i = _LOW_BIT[(bit * _DE_BRUIJN) >> np.uint64(58)]
                sj = np.float64(s[js])
                js += 1
                nj = 0.0
                if mh & bit:
                    nj = np.float64(n[jn])
                    jn += 1
                if not (sj > 0.0 or nj > 0.0):
                    continue  # not observed after all: nothing set (as ``_set_voxels``)
                chunk = block_chunks[slot]  # allocated by the first observed voxel
                if chunk < 0:
                    chunk = pools[S_USED]
                    pools[S_USED] = chunk + 1
                    block_chunks[slot] = chunk
                    chunk_owner[chunk] = slot
                value = np.float32(0.0)
                if sj >= s_limit or nj >= n_limit:  # beyond what float32 keeps adding to
                    hi = sa.block_href[block]
                    if hi < 0:
                        hi = pools[HI_USED]
                        pools[HI_USED] = hi + 1
                        sa.block_href[block] = hi
                        sa.hi_pool[hi] = 0.0
                    sa.hi_pool[hi, w * 64 + i, 0] = sj
                    sa.hi_pool[hi, w * 64 + i, 1] = nj
                else:
                    value = np.float32(sj)
                    if nj != 0.0:
                        flat_n[n_index(block_nrec, n_recs, pools, block, w * 64 + i, True)] = nj
                if nj > 0.0:
                    sa.block_hit[block] = True
                # observed: -0 while its float32 s is 0 (shard's notes)
                flat_s[chunk * CHUNK_VOXELS + i] = value if value != 0.0 else np.float32(-0.0)
                observed_count += 1
    counts[0] += observed_count
    return packed_ijk.shape[0]


@nb.njit(cache=True, nogil=True)
def _open_parts(
    packed_ijk: NDArray[np.int32],
    packed_t: NDArray[np.float64],
    observed: NDArray[np.uint64],
    hit_row: NDArray[np.int64],
    hit: NDArray[np.uint64],
    n: NDArray[np.float32],
    n_start: NDArray[np.int64],
    hi_row: NDArray[np.int64],
    hi_s: NDArray[np.float64],
    hi_n: NDArray[np.float64],
    hi_s_start: NDArray[np.int64],
    hi_n_start: NDArray[np.int64],
    rows: NDArray[np.int64],
    sa: ShardArrays,
) -> None:
    """Open the packed blocks (held as parts, ``packed.PackedBlocks.parts``) of ``rows``
    (increasing; ``rows[0] < 0``: every block) in an empty shard sized for them
    (``Shard.grow``, ``Shard.ensure_room``), in order: each block, the ``s`` chunks of its
    observed voxels (numbered in block order: from the masks alone, ``_write_parts``
    knows them), its ``n`` (float32 parts, voxels with a return) and its float64 part
    where it has one, as the store held them; the ``s`` values are left to
    ``_write_parts`` (the bulk, in another thread meanwhile). The blocks are new and
    distinct (sorted, checked): each takes the next row and its key goes into the table
    without a search (``open_block``'s probe for an existing block cost 3.5 times as
    long on the norlab map, docs/performance.md)."""
    block_chunks, chunk_owner, pools = sa.block_chunks, sa.chunk_owner, sa.pools
    block_nrec, n_recs = sa.block_nrec, sa.n_recs
    flat_n = sa.n_pool.reshape(-1)
    every = rows.shape[0] > 0 and rows[0] < 0
    count = packed_ijk.shape[0] if every else rows.shape[0]
    chunk = pools[S_USED]
    for k in range(count):
        b = k if every else rows[k]
        bx, by, bz = packed_ijk[b, 0], packed_ijk[b, 1], packed_ijk[b, 2]
        insert_block(sa.table_keys, sa.table_blocks, block_key(bx, by, bz), k)
        init_block(sa, k, bx, by, bz, -1, packed_t[b])
        for w in range(BLOCK_VOXELS // 64):  # a mask word is an s chunk (64 voxels)
            if observed[b, w] != 0:
                slot = chunk_slot(k, w)
                block_chunks[slot] = chunk
                chunk_owner[chunk] = slot
                chunk += 1
        f = hi_row[b]
        href = -1
        if f >= 0:
            href = pools[HI_USED]
            pools[HI_USED] = href + 1
            sa.block_href[k] = href
            sa.hi_pool[href] = 0.0
            ks = hi_s_start[f]
            for w in range(BLOCK_VOXELS // 64):
                m = observed[b, w]
                while m:  # the set bits, lowest first
                    bit = m & (np.uint64(0) - m)
                    m ^= bit
                    i = w * 64 + _LOW_BIT[(bit * _DE_BRUIJN) >> np.uint64(58)]
                    sa.hi_pool[href, i, 0] = hi_s[ks]
                    ks += 1
        row = hit_row[b]
        if row < 0:
            continue
        jn = n_start[row]
        kn = hi_n_start[f] if f >= 0 else 0
        for w in range(BLOCK_VOXELS // 64):
            mh = hit[row, w]
            if mh:
                sa.block_hit[k] = True
            while mh:
                bit = mh & (np.uint64(0) - mh)
                mh ^= bit
                i = w * 64 + _LOW_BIT[(bit * _DE_BRUIJN) >> np.uint64(58)]
                flat_n[n_index(block_nrec, n_recs, pools, k, i, True)] = n[jn]
                jn += 1
                if f >= 0:
                    sa.hi_pool[href, i, 1] = hi_n[kn]
                    kn += 1
    pools[S_USED] = chunk
    sa.counters[0] = count
    sa.counters[2] += count


@nb.njit(cache=True, nogil=True)
def _write_parts(
    observed: NDArray[np.uint64],
    s: NDArray[np.float32],
    s_start: NDArray[np.int64],
    chunk_first: NDArray[np.int64],
    s_pool: NDArray[np.float32],
    lo: int,
    hi: int,
) -> None:
    """The float32 parts of ``s`` of the packed blocks ``lo`` to ``hi`` into their chunks:
    block b's observed mask words take the chunks ``chunk_first[b]``, ``chunk_first[b] +
    1``, ... in order (as ``_open_parts`` numbers them; -1: another shard's block); -0 for
    an observed voxel whose part is 0 (shard's notes). Touches ``s_pool`` alone, and only
    those blocks' chunks: it runs beside ``_open_parts`` and another ``_write_parts``."""
    marks = s_pool.reshape(-1).view(np.uint32)
    s_bits = s.view(np.uint32)
    sign = np.uint32(0x80000000)
    for b in range(lo, hi):
        c = chunk_first[b]
        if c < 0:
            continue
        js = s_start[b]
        for w in range(BLOCK_VOXELS // 64):
            m = observed[b, w]
            if m == 0:
                continue
            base = c * CHUNK_VOXELS
            c += 1
            while m:  # the set bits, lowest first
                bit = m & (np.uint64(0) - m)
                m ^= bit
                i = _LOW_BIT[(bit * _DE_BRUIJN) >> np.uint64(58)]
                v = s_bits[js]
                js += 1
                marks[base + i] = v if v & ~sign else sign


@nb.njit(cache=True, nogil=True)
def _block_parts(
    sa: ShardArrays, blocks: NDArray[np.int64], s: NDArray[np.float32], n: NDArray[np.float32]
) -> None:
    """The float32 parts of ``s`` and ``n`` (len(blocks) x 512, as stored: -0 marks kept)
    of ``blocks``. The chunks of the block ``_PARTS_AHEAD`` on are prefetched (and its
    chunk-table row twice as far ahead): on a map built by integration the chunks of
    blocks in sorted order lie far apart, and waiting for each in turn took twice as long
    (norlab, 0.148 against 0.075 s CPU; docs/performance.md)."""
    count = blocks.shape[0]
    for k in range(count):
        if k + 2 * _PARTS_AHEAD < count:
            prefetch_line(sa.block_chunks, chunk_slot(blocks[k + 2 * _PARTS_AHEAD], 0))  # type: ignore[call-arg]
        if k + _PARTS_AHEAD < count:
            ahead = blocks[k + _PARTS_AHEAD]
            for c in range(BLOCK_CHUNKS):
                chunk = sa.block_chunks[chunk_slot(ahead, c)]
                if chunk >= 0:
                    for line in range(0, CHUNK_VOXELS, 16):  # 64-byte lines
                        prefetch_line(sa.s_pool, chunk * CHUNK_VOXELS + line)  # type: ignore[call-arg]
        b = blocks[k]
        for c in range(BLOCK_CHUNKS):
            chunk = sa.block_chunks[chunk_slot(b, c)]
            if chunk >= 0:
                for i in range(CHUNK_VOXELS):
                    s[k, c * CHUNK_VOXELS + i] = sa.s_pool[chunk, i]
            else:
                for i in range(CHUNK_VOXELS):
                    s[k, c * CHUNK_VOXELS + i] = 0.0
        row = sa.block_nrec[b]
        for c in range(N_BLOCK_CHUNKS):
            chunk = sa.n_recs[row, c] if row >= 0 else -1
            if chunk >= 0:
                for i in range(N_CHUNK_VOXELS):
                    n[k, c * N_CHUNK_VOXELS + i] = sa.n_pool[chunk, i]
            else:
                for i in range(N_CHUNK_VOXELS):
                    n[k, c * N_CHUNK_VOXELS + i] = 0.0


def _sorted_blocks(sh: Shard) -> NDArray[np.int64]:
    """The shard's blocks in sorted order (``packed.sort_keys``)."""
    return np.argsort(sort_keys(sh.block_ijk[: sh.used]), kind="stable")


def _shard_chunks(
    sh: Shard, blocks: NDArray[np.int64], max_blocks: int = 4096
) -> Iterator[BlockChunk]:
    """``BlockStore.block_chunks`` of the blocks ``blocks`` of one shard, in that order
    (runs of at most ``max_blocks``, through one buffer)."""
    s_buffer = np.empty((min(max_blocks, blocks.shape[0]), BLOCK_VOXELS), dtype=np.float32)
    n_buffer = np.empty_like(s_buffer)
    for start in range(0, blocks.shape[0], max_blocks):
        run = blocks[start : start + max_blocks]
        s, n = s_buffer[: run.shape[0]], n_buffer[: run.shape[0]]
        _block_parts(sh.arrays(), run, s, n)
        href = sh.block_href[run]
        flushed = href >= 0
        hi_row = np.full(run.shape[0], -1, dtype=np.int64)
        hi_row[flushed] = np.arange(np.count_nonzero(flushed))
        hi = sh.hi_pool[href[flushed]]
        yield sh.block_ijk[run], sh.block_t[run], s, n, hi_row, hi


@nb.njit(cache=True, nogil=True)
def _lookup(
    ijk: NDArray[np.int64],
    shard_mask: int,
    shard: int,
    sa: ShardArrays,
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t: NDArray[np.float64],
) -> None:
    """Statistics of each voxel index of ``shard`` (left as given elsewhere, and where its
    block is absent)."""
    block_chunks, s_pool, block_nrec, n_recs = sa.block_chunks, sa.s_pool, sa.block_nrec, sa.n_recs
    n_pool, block_href, hi_pool = sa.n_pool, sa.block_href, sa.hi_pool
    for j in range(ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        if shard_of(bx, by, bz, shard_mask) != shard:
            continue
        block = find_block(sa.table_keys, sa.table_blocks, block_key(bx, by, bz))
        if block >= 0:
            s[j], n[j] = voxel_stats(
                block_chunks, s_pool, block_nrec, n_recs, n_pool, block_href, hi_pool, block,
                local_index(ijk[j, 0], ijk[j, 1], ijk[j, 2]),
            )  # fmt: skip
            t[j] = sa.block_t[block]


@nb.njit(cache=True, nogil=True)
def _select_voxels(
    sa: ShardArrays,
    used: int,
    min_extinction: float,
    lo: IndexBox,
    hi: IndexBox,
    keep: NDArray[np.bool_],
    kept_per_block: NDArray[np.int64],
) -> int:
    """Mark observed voxels with n >= min_extinction * s inside [lo, hi]; returns the count.
    ``kept_per_block`` receives how many voxels each block contributes.

    Whole blocks outside the bounds, or without a return when one is needed, are skipped
    without reading their voxels.
    """
    count = 0
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(used):
        if min_extinction > 0.0 and not sa.block_hit[b]:
            continue  # no return in the block: no voxel has n >= min_extinction * s > 0
        x0, y0, z0 = block_origin(sa.block_ijk, b)
        if block_outside(x0, y0, z0, lo, hi):
            continue
        last = BLOCK_EDGE - 1
        inside = voxel_inside(x0, y0, z0, lo, hi) and voxel_inside(
            x0 + last, y0 + last, z0 + last, lo, hi
        )
        block_values(sa, b, s_block, n_block)
        for i in range(BLOCK_VOXELS):
            s, n = s_block[i], n_block[i]
            # s == 0 < n: a return on a face, most likely DoO 1 (kept by any threshold)
            if (s > 0.0 and n >= min_extinction * s) or (s == 0.0 and n > 0.0):
                if not inside:
                    dx, dy, dz = local_coords(i)
                    if not voxel_inside(x0 + dx, y0 + dy, z0 + dz, lo, hi):
                        continue
                keep[b, i] = True
                kept_per_block[b] += 1
                count += 1
    return count


@nb.njit(cache=True, nogil=True)
def _gather_voxels(
    sa: ShardArrays,
    keep: NDArray[np.bool_],
    kept_per_block: NDArray[np.int64],
    ijk: NDArray[np.int32],
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t_last: NDArray[np.float64],
) -> None:
    """Write the voxels marked in ``keep`` (blocks x voxels) to the output arrays, in order."""
    j = 0
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(keep.shape[0]):
        if kept_per_block[b] == 0:
            continue
        x0, y0, z0 = block_origin(sa.block_ijk, b)
        block_values(sa, b, s_block, n_block)
        for i in range(BLOCK_VOXELS):
            if keep[b, i]:
                dx, dy, dz = local_coords(i)
                ijk[j, 0] = x0 + dx
                ijk[j, 1] = y0 + dy
                ijk[j, 2] = z0 + dz
                s[j], n[j] = s_block[i], n_block[i]
                t_last[j] = sa.block_t[b]
                j += 1


@nb.njit(cache=True, nogil=True)
def _block_stats(
    sa: ShardArrays, start: int, s: NDArray[np.float64], n: NDArray[np.float64]
) -> None:
    """``s`` and ``n`` (blocks x 512) of blocks ``start..start + len(s)``."""
    for k in range(s.shape[0]):
        block_values(sa, start + k, s[k], n[k])


@nb.njit(cache=True, nogil=True)
def _clear_voxels(
    sa: ShardArrays,
    used: int,
    lo: IndexBox,
    hi: IndexBox,
    emptied: NDArray[np.bool_],
) -> int:
    """Zero the observed voxels with index in [lo, hi]; returns how many. ``emptied[b]``
    becomes True for each block that no longer holds an observed voxel."""
    count = 0
    flat_s = sa.s_pool.reshape(-1)
    flat_n = sa.n_pool.reshape(-1)
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(used):
        x0, y0, z0 = block_origin(sa.block_ijk, b)
        if block_outside(x0, y0, z0, lo, hi):
            continue
        left = 0
        href = sa.block_href[b]
        block_values(sa, b, s_block, n_block)
        for i in range(BLOCK_VOXELS):
            if s_block[i] == 0.0 and n_block[i] == 0.0:
                continue
            dx, dy, dz = local_coords(i)
            if voxel_inside(x0 + dx, y0 + dy, z0 + dz, lo, hi):
                chunk = sa.block_chunks[chunk_slot(b, i >> CHUNK_BITS)]
                if chunk >= 0:
                    flat_s[chunk * CHUNK_VOXELS + (i % CHUNK_VOXELS)] = 0.0
                k = n_index(sa.block_nrec, sa.n_recs, sa.pools, b, i, False)
                if k >= 0:
                    flat_n[k] = 0.0
                if href >= 0:
                    sa.hi_pool[href, i, 0] = 0.0
                    sa.hi_pool[href, i, 1] = 0.0
                count += 1
            else:
                left += 1
        emptied[b] = left == 0
    return count


class BlockStore:
    """All shards together: the map's memory, with lookup, export, loading and eviction.

    ``flush_s``: the float32 part of a voxel's ``s`` beyond which its block is flushed into
    float64 (``shard.FLUSH_EDGES`` voxel edges for a map; inf for a store of one scan)."""

    def __init__(self, shards: int = 1, flush_s: float = math.inf) -> None:
        if shards < 1 or shards & (shards - 1):
            raise ValueError(f"shards must be a power of two, got {shards}")
        self.shards = [Shard(flush_s=flush_s) for _ in range(shards)]
        self.shard_mask = shards - 1
        self.num_voxels = 0
        self._scan_id = 0

    def forget_blocks(self) -> None:
        """Hold no block again, keeping the statistics' memory (``Shard.forget_blocks``:
        the caller has zeroed every block's statistics)."""
        for shard in self.shards:
            shard.forget_blocks()
        self.num_voxels = 0

    @property
    def next_scan(self) -> int:
        """The id the next scan will take (``begin_scan``): blocks it opens get it."""
        return self._scan_id

    def begin_scan(self) -> int:
        """Start a scan: clears the per-scan counters; returns the scan's id."""
        for sh in self.shards:
            sh.counters[1:] = 0
        return self._scan_id

    def finish_scan(self) -> tuple[int, int, int]:
        """Close the scan (flushing the blocks that need it into float64); returns (voxels
        observed for the first time, blocks touched, voxel updates)."""
        for sh in self.shards:
            sh.flush()
        totals = np.sum([sh.counters[1:] for sh in self.shards], axis=0)
        new, touched, updates = (int(x) for x in totals)
        self.num_voxels += new
        self._scan_id += 1
        return new, touched, updates

    def assign(self, voxels: VoxelArrays, decay_time: float) -> None:
        """Set the given voxels of an empty store, e.g. from a map file.

        Voxels of one block that refer to different times are decayed to the latest.
        Raises ``ValueError`` naming a voxel listed twice (the store is then incomplete:
        discard it).
        """
        if self.num_blocks:
            raise ValueError("assign needs an empty store")
        ijk = np.ascontiguousarray(voxels.ijk, dtype=np.int64)
        s, n, t = (
            np.ascontiguousarray(a, dtype=np.float64) for a in (voxels.s, voxels.n, voxels.t_last)
        )
        counts = np.zeros(1, dtype=np.int64)
        for sid, sh in enumerate(self.shards):
            start = 0
            while (
                start := _open_blocks_of(ijk, t, start, sid, self.shard_mask, sh.arrays())
            ) < ijk.shape[0]:
                sh.grow()
            seen = np.zeros((sh.used, BLOCK_VOXELS // 64), dtype=np.uint64)
            start = 0
            room = max(1024, ijk.shape[0] // (8 * len(self.shards)))
            while True:
                sh.ensure_room(room, room // 4 + 16, room // 64 + 1, room // 16 + 16)
                done = _set_voxels(
                    ijk, s, n, t, start, sid, self.shard_mask, decay_time, sh.arrays(), seen,
                    counts,
                )  # fmt: skip
                if done >= -1:
                    break
                start, room = -2 - done, 2 * room
            if done >= 0:
                raise ValueError(f"ijk lists voxel {ijk[done].tolist()} more than once")
        self.num_voxels = int(counts[0])

    def block_chunks(self, max_blocks: int = 4096) -> Iterator[BlockChunk]:
        """Every block's index, time, the float32 parts of ``s`` and ``n`` of its 512 voxels
        ((k, 512) each, Morton order) and its float64 part where it was flushed, runs of
        at most ``max_blocks`` blocks shard by shard, each shard's in sorted order
        (``packed.sort_keys``: a store of one shard packs without moving its values): a
        block-level export without per-voxel index arrays (``packed.BlockChunk``). The
        float32 parts of a run are overwritten by the next (one buffer, not a fresh one
        the system must fault in each time): use each run before taking the next."""
        for sh in self.shards:
            yield from _shard_chunks(sh, _sorted_blocks(sh), max_blocks)

    def export_blocks(self) -> PackedBlocks:
        """Every observed voxel, packed block by block (``packed``; a copy):
        ``packed.pack_chunks`` of ``block_chunks``; on maps of ``_THREADED_PACK_BLOCKS``
        blocks or more where two cores are there, the second half of each shard's blocks
        is packed in a thread of its own meanwhile (the same blocks, bit for bit)."""
        orders = [(sh, _sorted_blocks(sh)) for sh in self.shards]
        if self.num_blocks < _THREADED_PACK_BLOCKS or (os.cpu_count() or 1) < 2:
            return pack_chunks(self.block_chunks(), self.num_voxels)
        halves = [(sh, order[: order.shape[0] // 2]) for sh, order in orders]
        halves += [(sh, order[order.shape[0] // 2 :]) for sh, order in orders]
        share = self.num_voxels // 2 + BLOCK_VOXELS

        def pack(
            part: list[tuple[Shard, NDArray[np.int64]]],
        ) -> tuple[list[PackedRun], PackOutputs]:
            out = PackOutputs(share)
            chunks = (c for sh, blocks in part for c in _shard_chunks(sh, blocks))
            return [pack_chunk(c, out) for c in chunks], out

        with ThreadPoolExecutor(1) as pool:
            second = pool.submit(pack, halves[len(orders) :])
            runs, out = pack(halves[: len(orders)])
            more, out2 = second.result()
        joined = PackOutputs(0)
        joined.s = np.concatenate([out.s[: out.places[0]], out2.s[: out2.places[0]]])
        joined.n = np.concatenate([out.n[: out.places[1]], out2.n[: out2.places[1]]])
        joined.places[:] = joined.s.shape[0], joined.n.shape[0]
        return packed_runs(runs + more, joined)

    def assign_blocks(self, packed: PackedBlocks) -> None:
        """Set the voxels of packed blocks (checked by ``packed_problem``) in an empty
        store; the inverse of ``export_blocks``. Compiled, block by block: blocks held as
        parts (``PackedBlocks.parts``, what ``export_blocks`` gives) get their float32 and
        float64 parts back as they were (``_fill_parts``); blocks holding values are set as
        ``assign`` sets their voxel lists (``packed.voxel_arrays_of``), bit for bit
        (``_set_blocks``), which it replaces because building and probing per-voxel index
        arrays cost 5-10 times as long (docs/performance.md)."""
        if self.num_blocks:
            raise ValueError("assign_blocks needs an empty store")
        rows = packed.block_ijk.shape[0]
        block_ijk = np.ascontiguousarray(packed.block_ijk, dtype=np.int32)
        block_t = np.ascontiguousarray(packed.block_t, dtype=np.float64)
        observed = np.ascontiguousarray(packed.observed, dtype=np.uint64)
        hit = np.ascontiguousarray(packed.hit, dtype=np.uint64).reshape(-1, MASK_WORDS)
        s, n = np.ascontiguousarray(packed.s), np.ascontiguousarray(packed.n)
        hit_row = hit_row_of(packed)
        s_start, n_start = voxel_starts(observed), voxel_starts(hit)
        if packed.parts:
            hi_row = np.full(rows, -1, dtype=np.int64)
            hi_row[packed.hi_block] = np.arange(packed.hi_block.shape[0])
            hi_s_start, hi_n_start = hi_starts(packed)
            hi_s = np.ascontiguousarray(packed.hi_s, dtype=np.float64)
            hi_n = np.ascontiguousarray(packed.hi_n, dtype=np.float64)
            s, n = s.astype(np.float32, copy=False), n.astype(np.float32, copy=False)
            words = mask_words(observed)
        if self.shard_mask:
            z_offset, bits = tile_z_offset(self.shard_mask), tile_bits(self.shard_mask)
            tile_ijk = block_ijk.astype(np.int64) + np.array([0, 0, z_offset])
            tiles = (tile_ijk >> bits).sum(axis=1) & self.shard_mask  # shard_of
        counts = np.zeros(1, dtype=np.int64)
        for sid, sh in enumerate(self.shards):
            if self.shard_mask:
                mine = tiles == sid
                hits_mine = mine[packed.hit_block]
                blocks, hit_blocks = int(np.count_nonzero(mine)), int(np.count_nonzero(hits_mine))
                chunks = int(np.count_nonzero(observed[mine]))
                n_chunks = int(np.count_nonzero(hit[hits_mine].view(np.uint16)))
                hi_blocks = int(np.count_nonzero(mine[packed.hi_block])) if packed.parts else 0
            else:
                blocks, hit_blocks = rows, packed.hit_block.shape[0]
                chunks = int(np.count_nonzero(observed))
                n_chunks = int(np.count_nonzero(hit.view(np.uint16)))
                hi_blocks = packed.hi_block.shape[0] if packed.parts else 0
            sh.grow(min_free=blocks)
            sh.ensure_room(  # what the blocks need (and a block's worth: the kernel's check)
                chunks + BLOCK_CHUNKS, n_chunks + N_BLOCK_CHUNKS, hi_blocks + 1, hit_blocks + 1
            )
            if packed.parts:
                self._fill_parts(
                    sh, mine if self.shard_mask else None, words,
                    (block_ijk, block_t, observed, hit_row, hit, n, n_start, hi_row, hi_s, hi_n,
                     hi_s_start, hi_n_start),
                    s, s_start,
                )  # fmt: skip
                mine_voxels = np.diff(s_start)[mine].sum() if self.shard_mask else s.shape[0]
                counts[0] += int(mine_voxels)
                continue
            hi_room = 1
            start = 0
            while (
                start := _set_blocks(
                    block_ijk,
                    block_t,
                    observed,
                    s,
                    s_start,
                    hit_row,
                    hit,
                    n,
                    n_start,
                    start,
                    sid,
                    self.shard_mask,
                    sh.arrays(),
                    counts,
                )  # fmt: skip
            ) < rows:  # out of float64 blocks (values at the float32 limit): more, go on
                hi_room *= 2
                sh.ensure_room(BLOCK_CHUNKS, N_BLOCK_CHUNKS, hi_room, 1)
        self.num_voxels = int(counts[0])

    def _fill_parts(
        self,
        sh: Shard,
        mine: NDArray[np.bool_] | None,
        words: NDArray[np.int64],
        opening: tuple[Any, ...],
        s: NDArray[np.float32],
        s_start: NDArray[np.int64],
    ) -> None:
        """Set the packed blocks (parts) of an empty shard sized for them (``mine``: its
        rows; None: all): ``_open_parts``, and ``_write_parts`` of the ``s`` parts (their
        chunks numbered from the masks, ``words`` nonzero mask words a block). On maps of
        a million voxels or more where two cores are there, a second thread writes while
        this one opens the blocks, then both write: pieces of ``_WRITE_PIECE_VOXELS``
        taken in turn (the same store as one after the other)."""
        counted = words if mine is None else np.where(mine, words, 0)
        first = np.cumsum(counted) - counted + int(sh.pools[S_USED])
        chunk_first = first if mine is None else np.where(mine, first, -1)
        rows = np.full(1, -1, dtype=np.int64) if mine is None else np.flatnonzero(mine)
        observed = opening[2]
        blocks = observed.shape[0]
        if s.shape[0] < _THREADED_WRITE_VOXELS or (os.cpu_count() or 1) < 2:
            _open_parts(*opening, rows, sh.arrays())  # type: ignore[call-arg]
            _write_parts(observed, s, s_start, chunk_first, sh.s_pool, 0, blocks)
            return
        heads = np.searchsorted(s_start, np.arange(0, s.shape[0], _WRITE_PIECE_VOXELS))
        ends = np.append(heads[1:], blocks)
        taken = itertools.count()  # its next() is atomic: each piece goes to one thread

        def write() -> None:
            for k in iter(taken.__next__, None):
                if k >= heads.shape[0]:
                    return
                lo, hi = int(heads[k]), int(ends[k])
                _write_parts(observed, s, s_start, chunk_first, sh.s_pool, lo, hi)

        with ThreadPoolExecutor(1) as pool:
            writer = pool.submit(write)
            try:
                _open_parts(*opening, rows, sh.arrays())  # type: ignore[call-arg]
                write()
            finally:
                writer.result()

    def lookup(self, ijk: NDArray[np.int64]) -> VoxelArrays:
        """Statistics of these voxels (zeros and t_last=-inf where never observed)."""
        count = ijk.shape[0]
        s = np.zeros(count)
        n = np.zeros(count)
        t = np.full(count, -np.inf)
        ijk64 = np.ascontiguousarray(ijk, dtype=np.int64)
        for sid, sh in enumerate(self.shards):
            _lookup(ijk64, self.shard_mask, sid, sh.arrays(), s, n, t)
        return VoxelArrays(ijk.astype(np.int32), s, n, t)

    def export(
        self,
        min_extinction: float = 0.0,
        lo: NDArray[np.int64] | None = None,
        hi: NDArray[np.int64] | None = None,
    ) -> VoxelArrays:
        """Observed voxels with n >= min_extinction * s and index within [lo, hi]."""
        lo_ = index_box(np.full(3, -MAX_VOXEL_INDEX - 1) if lo is None else lo)
        hi_ = index_box(np.full(3, MAX_VOXEL_INDEX + 1) if hi is None else hi)
        selections = []
        for sh in self.shards:
            keep = np.zeros((sh.used, BLOCK_VOXELS), dtype=np.bool_)
            per_block = np.zeros(sh.used, dtype=np.int64)
            count = _select_voxels(sh.arrays(), sh.used, min_extinction, lo_, hi_, keep, per_block)
            selections.append((keep, per_block, count))
        total = sum(count for _, _, count in selections)
        out = VoxelArrays(
            np.empty((total, 3), dtype=np.int32), np.empty(total), np.empty(total), np.empty(total)
        )
        start = 0
        for sh, (keep, per_block, count) in zip(self.shards, selections, strict=True):
            part = slice(start, start + count)
            _gather_voxels(
                sh.arrays(), keep, per_block,
                out.ijk[part], out.s[part], out.n[part], out.t_last[part],
            )  # fmt: skip
            start += count
        return out

    def blocks(self, max_blocks: int = 4096) -> Iterator[BlockStats]:
        """Every block's statistics, at most ``max_blocks`` blocks at a time (shard by shard,
        in the order blocks were created): a block-level export without per-voxel index
        arrays. A block may hold no observed voxel (then every ``s`` and ``n`` is 0)."""
        for sh in self.shards:
            for start in range(0, sh.used, max_blocks):
                stop = min(start + max_blocks, sh.used)
                s = np.empty((stop - start, BLOCK_VOXELS))
                n = np.empty((stop - start, BLOCK_VOXELS))
                _block_stats(sh.arrays(), start, s, n)
                yield BlockStats(
                    sh.block_ijk[start:stop].copy(),
                    sh.block_t[start:stop].copy(),
                    s,
                    n,
                    (sh.block_nrec[start:stop] >= 0) | (sh.block_href[start:stop] >= 0),
                )

    def clear_box(self, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> int:
        """Make the voxels with index in [lo, hi] unobserved (s = n = 0); blocks left
        with no observed voxel are dropped. Returns how many observed voxels were cleared."""
        lo_, hi_ = index_box(lo), index_box(hi)
        cleared = 0
        for sh in self.shards:
            emptied = np.zeros(sh.used, dtype=np.bool_)
            cleared += _clear_voxels(sh.arrays(), sh.used, lo_, hi_, emptied)
            if emptied.any():
                sh.keep_blocks(~emptied)
        self.num_voxels -= cleared
        return cleared

    def evict_beyond(self, center: NDArray[np.float64], radius: float) -> int:
        """Drop the blocks whose centre is farther than ``radius`` from ``center`` (both in
        block units); returns the number of voxels dropped."""
        dropped = 0
        for sh in self.shards:
            keep = sh.block_distances(center) <= radius
            if not keep.all():
                dropped += sh.keep_blocks(keep)
        self.num_voxels -= dropped
        return dropped

    def evict_farthest(self, center: NDArray[np.float64], max_voxels: int) -> None:
        """Drop the blocks farthest from ``center`` (block units) until at most
        ``max_voxels`` voxels remain (at most half of the blocks per round)."""
        while self.num_voxels > max_voxels:
            distances = np.concatenate([sh.block_distances(center) for sh in self.shards])
            share_to_drop = min(0.5, 1.0 - max_voxels / self.num_voxels)
            if self.evict_beyond(center, float(np.quantile(distances, 1.0 - share_to_drop))) == 0:
                return

    def evict_farthest_blocks(self, center: NDArray[np.float64], max_blocks: int) -> None:
        """Drop the blocks farthest from ``center`` (block units) until at most
        ``max_blocks`` remain (blocks at the same distance as the last kept may stay)."""
        distances = np.concatenate([sh.block_distances(center) for sh in self.shards])
        if distances.shape[0] <= max_blocks:
            return
        if max_blocks <= 0:
            self.evict_beyond(center, -1.0)
            return
        self.evict_beyond(center, float(np.partition(distances, max_blocks - 1)[max_blocks - 1]))

    @property
    def num_blocks(self) -> int:
        return sum(sh.used for sh in self.shards)

    @property
    def nbytes(self) -> int:
        return sum(sh.nbytes for sh in self.shards)
