"""Sparse voxel store: a hash of dense 8x8x8 blocks holding ``(s, n)`` per voxel.

Layout (chosen for speed and memory, see ANCHORS.md):

* Voxels live in dense blocks of ``BLOCK_EDGE**3``; a ray stays in one block for several
  steps, so most updates are an array index into the block the walk is already in.
* Blocks are found through open-addressing hash tables, split into ``shards`` by block
  parity so that several threads can merge one scan's contributions without locks.
* ``s`` and ``n`` are float32, side by side (8 bytes a voxel), and the voxels of a block
  are in Morton order, so one 64-byte cache line holds a 2x2x2 cube of voxels: a ray
  crossing it finds its next voxel in the same line. Each block keeps the time ``t`` its
  statistics refer to. Decay (Eq. 28-30) is uniform scaling, so bringing a whole block to
  the current stamp the first time a scan touches it is exactly the per-voxel lazy decay;
  a voxel's ``t_last`` is its block's ``t``.
* A voxel is *observed* when ``s > 0`` or ``n > 0``.

Per scan, every contribution is summed into the store: sums, never deduplication.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.traversal import KEY_BITS, KEY_MASK, KEY_OFFSET

BLOCK_BITS = 3
BLOCK_EDGE = 1 << BLOCK_BITS
BLOCK_VOXELS = BLOCK_EDGE**3
_LOCAL_MASK = BLOCK_EDGE - 1
_EMPTY = -1
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)

# merge status codes
MERGE_DONE = 0
MERGE_FULL = 1


@nb.njit(inline="always", cache=True)
def _block_key(bx: int, by: int, bz: int) -> int:
    return ((bx + KEY_OFFSET) << (2 * KEY_BITS)) | ((by + KEY_OFFSET) << KEY_BITS) | (bz + KEY_OFFSET)


@nb.njit(inline="always", cache=True)
def _shard_of(bx: int, by: int, bz: int, shard_mask: int) -> int:
    return (bx + by + bz) & shard_mask


@nb.njit(inline="always", cache=True)
def _slot_index(key: int, table_mask: int) -> int:
    return int((np.uint64(key) * _HASH_MULT) >> np.uint64(40)) & table_mask


@nb.njit(inline="always", cache=True)
def _find(table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32], key: int) -> int:
    """Block number of ``key``, or -1."""
    mask = table_keys.shape[0] - 1
    i = _slot_index(key, mask)
    while True:
        k = table_keys[i]
        if k == key:
            return int(table_blocks[i])
        if k == _EMPTY:
            return -1
        i = (i + 1) & mask


@nb.njit(inline="always", cache=True)
def _insert(table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32], key: int, block: int) -> None:
    mask = table_keys.shape[0] - 1
    i = _slot_index(key, mask)
    while table_keys[i] != _EMPTY:
        i = (i + 1) & mask
    table_keys[i] = key
    table_blocks[i] = block


@nb.njit(inline="always", cache=True)
def _spread_bits(v: int) -> int:
    """The 3 low bits of ``v`` placed 3 apart (b0 -> 0, b1 -> 3, b2 -> 6)."""
    return (v & 1) | ((v & 2) << 2) | ((v & 4) << 4)


@nb.njit(inline="always", cache=True)
def _local_index(vx: int, vy: int, vz: int) -> int:
    """Morton (z-order) index of a voxel inside its block."""
    return (
        (_spread_bits(vx & _LOCAL_MASK) << 2)
        | (_spread_bits(vy & _LOCAL_MASK) << 1)
        | _spread_bits(vz & _LOCAL_MASK)
    )


@nb.njit(cache=True, nogil=True)
def _merge_shard(
    keys: NDArray[np.int64],
    chords: NDArray[np.float32],
    hits: NDArray[np.int64],
    ranges: NDArray[np.int64],
    hit_ranges: NDArray[np.int64],
    progress: NDArray[np.int64],
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
    """Sum one scan's contributions that fall in ``shard`` into its blocks.

    ``ranges``/``hit_ranges`` are (chunks, 2) [start, stop) regions of the contribution
    arrays, taken in order; ``progress`` = [phase, chunk, index] lets a call that ran out of
    block capacity (returns MERGE_FULL) resume after the caller grew the arrays.
    ``counters`` = [blocks used, new voxels, blocks touched this scan].
    """
    decays = math.isfinite(decay_time)
    capacity = block_sn.shape[0]
    max_blocks_for_table = table_keys.shape[0] // 2
    cached_key = -1
    cached_block = -1
    for phase in range(progress[0], 2):
        regions = ranges if phase == 0 else hit_ranges
        source = keys if phase == 0 else hits
        first_chunk = progress[1] if phase == progress[0] else 0
        for c in range(first_chunk, regions.shape[0]):
            start = progress[2] if (phase == progress[0] and c == progress[1]) else regions[c, 0]
            for j in range(start, regions[c, 1]):
                key = source[j]
                vx = ((key >> (2 * KEY_BITS)) & KEY_MASK) - KEY_OFFSET
                vy = ((key >> KEY_BITS) & KEY_MASK) - KEY_OFFSET
                vz = (key & KEY_MASK) - KEY_OFFSET
                bx = vx >> BLOCK_BITS
                by = vy >> BLOCK_BITS
                bz = vz >> BLOCK_BITS
                if _shard_of(bx, by, bz, shard_mask) != shard:
                    continue
                bkey = _block_key(bx, by, bz)
                if bkey != cached_key:
                    block = _find(table_keys, table_blocks, bkey)
                    if block < 0:
                        used = counters[0]
                        if used >= capacity or used >= max_blocks_for_table:
                            progress[0] = phase
                            progress[1] = c
                            progress[2] = j
                            return MERGE_FULL
                        block = used
                        counters[0] = used + 1
                        _insert(table_keys, table_blocks, bkey, block)
                        block_ijk[block, 0] = bx
                        block_ijk[block, 1] = by
                        block_ijk[block, 2] = bz
                        block_t[block] = stamp
                        block_scan[block] = scan_id
                        counters[2] += 1
                    elif block_scan[block] != scan_id:
                        if decays:
                            f = np.float32(math.exp(-abs(stamp - block_t[block]) / decay_time))
                            for i in range(BLOCK_VOXELS):
                                block_sn[block, i, 0] *= f
                                block_sn[block, i, 1] *= f
                        block_t[block] = stamp
                        block_scan[block] = scan_id
                        counters[2] += 1
                    cached_key = bkey
                    cached_block = block
                local = _local_index(vx, vy, vz)
                if block_sn[cached_block, local, 0] == 0.0 and block_sn[cached_block, local, 1] == 0.0:
                    counters[1] += 1
                if phase == 0:
                    block_sn[cached_block, local, 0] += chords[j]
                else:
                    block_sn[cached_block, local, 1] += 1.0
    progress[0] = 2
    return MERGE_DONE


@nb.njit(cache=True, nogil=True)
def _assign_shard(
    ijk: NDArray[np.int64],
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t: NDArray[np.float64],
    start: int,
    shard: int,
    shard_mask: int,
    table_keys: NDArray[np.int64],
    table_blocks: NDArray[np.int32],
    block_ijk: NDArray[np.int32],
    block_sn: NDArray[np.float32],
    block_t: NDArray[np.float64],
    counters: NDArray[np.int64],
) -> int:
    """Set voxels (all referring to their block's time ``t``) from ``start`` on.

    Returns the index reached: ``len(ijk)`` when done, less when the blocks ran out.
    """
    capacity = block_sn.shape[0]
    max_blocks_for_table = table_keys.shape[0] // 2
    for j in range(start, ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        if _shard_of(bx, by, bz, shard_mask) != shard:
            continue
        bkey = _block_key(bx, by, bz)
        block = _find(table_keys, table_blocks, bkey)
        if block < 0:
            used = counters[0]
            if used >= capacity or used >= max_blocks_for_table:
                return j
            block = used
            counters[0] = used + 1
            _insert(table_keys, table_blocks, bkey, block)
            block_ijk[block, 0] = bx
            block_ijk[block, 1] = by
            block_ijk[block, 2] = bz
        local = _local_index(ijk[j, 0], ijk[j, 1], ijk[j, 2])
        block_sn[block, local, 0] = s[j]
        block_sn[block, local, 1] = n[j]
        block_t[block] = t[j]
    return ijk.shape[0]


@nb.njit(cache=True, nogil=True)
def _lookup(
    keys: NDArray[np.int64],
    shard_mask: int,
    tables_keys: tuple[NDArray[np.int64], ...],
    tables_blocks: tuple[NDArray[np.int32], ...],
    out_shard: NDArray[np.int64],
    out_block: NDArray[np.int64],
    out_local: NDArray[np.int64],
) -> None:
    """For each voxel key: its shard, block number (-1 when absent) and index in the block."""
    for j in range(keys.shape[0]):
        key = keys[j]
        vx = ((key >> (2 * KEY_BITS)) & KEY_MASK) - KEY_OFFSET
        vy = ((key >> KEY_BITS) & KEY_MASK) - KEY_OFFSET
        vz = (key & KEY_MASK) - KEY_OFFSET
        bx = vx >> BLOCK_BITS
        by = vy >> BLOCK_BITS
        bz = vz >> BLOCK_BITS
        shard = _shard_of(bx, by, bz, shard_mask)
        out_shard[j] = shard
        out_block[j] = _find(tables_keys[shard], tables_blocks[shard], _block_key(bx, by, bz))
        out_local[j] = _local_index(vx, vy, vz)


@nb.njit(cache=True, nogil=True)
def _rebuild_table(block_ijk: NDArray[np.int32], used: int, table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32]) -> None:
    table_keys[:] = _EMPTY
    for b in range(used):
        _insert(table_keys, table_blocks, _block_key(block_ijk[b, 0], block_ijk[b, 1], block_ijk[b, 2]), b)


def _local_offsets() -> NDArray[np.int32]:
    offsets = np.zeros((BLOCK_VOXELS, 3), dtype=np.int32)
    for x in range(BLOCK_EDGE):
        for y in range(BLOCK_EDGE):
            for z in range(BLOCK_EDGE):
                offsets[_local_index(x, y, z)] = (x, y, z)
    return offsets


LOCAL_OFFSETS = _local_offsets()
"""(BLOCK_VOXELS, 3) offset of each in-block index from the block's first voxel."""


BlockPredicate = Callable[[NDArray[np.int32], NDArray[np.float64]], NDArray[np.bool_]]
"""Given used blocks' index (B, 3) and time (B,), which blocks to keep."""


@dataclass
class VoxelArrays:
    """Raw statistics of a set of voxels: index, s, n and the time they refer to."""

    ijk: NDArray[np.int32]
    s: NDArray[np.float64]
    n: NDArray[np.float64]
    t_last: NDArray[np.float64]


class Shard:
    """One hash table and the blocks it indexes."""

    def __init__(self, block_capacity: int = 256) -> None:
        self.counters = np.zeros(3, dtype=np.int64)
        self._allocate(block_capacity)

    def _allocate(self, capacity: int) -> None:
        self.block_ijk = np.zeros((capacity, 3), dtype=np.int32)
        self.block_sn = np.zeros((capacity, BLOCK_VOXELS, 2), dtype=np.float32)
        self.block_t = np.full(capacity, -np.inf)
        self.block_scan = np.full(capacity, -1, dtype=np.int64)
        self.table_keys = np.full(_next_pow2(2 * capacity), _EMPTY, dtype=np.int64)
        self.table_blocks = np.zeros(self.table_keys.shape[0], dtype=np.int32)

    @property
    def used(self) -> int:
        return int(self.counters[0])

    def grow(self) -> None:
        """Double the block capacity (and the table), keeping every block."""
        used = self.used
        old = (self.block_ijk, self.block_sn, self.block_t, self.block_scan)
        self._allocate(max(self.block_sn.shape[0] * 3 // 2, 256))
        for new, prev in zip(
            (self.block_ijk, self.block_sn, self.block_t, self.block_scan), old, strict=True
        ):
            new[:used] = prev[:used]
        _rebuild_table(self.block_ijk, used, self.table_keys, self.table_blocks)

    def keep_blocks(self, keep: NDArray[np.bool_]) -> int:
        """Drop the blocks where ``keep`` (over used blocks) is False; returns voxels dropped."""
        used = self.used
        dropped = int(np.count_nonzero((self.block_sn[:used][~keep] > 0).any(axis=-1)))
        kept = int(np.count_nonzero(keep))
        for arr in (self.block_ijk, self.block_sn, self.block_t, self.block_scan):
            arr[:kept] = arr[:used][keep]
        self.block_sn[kept:used] = 0.0
        self.block_t[kept:used] = -np.inf
        self.block_scan[kept:used] = -1
        self.counters[0] = kept
        _rebuild_table(self.block_ijk, kept, self.table_keys, self.table_blocks)
        return dropped

    @property
    def nbytes(self) -> int:
        arrays = (self.block_ijk, self.block_sn, self.block_t, self.block_scan)
        return sum(a.nbytes for a in arrays) + self.table_keys.nbytes + self.table_blocks.nbytes


def _next_pow2(x: int) -> int:
    return 1 << max(int(x - 1).bit_length(), 4)


class BlockStore:
    """All shards together: the map's memory, with merge, lookup and export."""

    def __init__(self, shards: int = 1) -> None:
        if shards < 1 or shards & (shards - 1):
            raise ValueError(f"shards must be a power of two, got {shards}")
        self.shards = [Shard() for _ in range(shards)]
        self.shard_mask = shards - 1
        self.num_voxels = 0
        self._scan_id = 0

    def merge(
        self,
        keys: NDArray[np.int64],
        chords: NDArray[np.float32],
        hits: NDArray[np.int64],
        ranges: NDArray[np.int64],
        hit_ranges: NDArray[np.int64],
        stamp: float,
        decay_time: float,
        shard_ids: range | list[int],
    ) -> int:
        """Add one scan's contributions to the given shards; returns blocks touched."""
        touched = 0
        for sid in shard_ids:
            shard = self.shards[sid]
            shard.counters[1:] = 0
            progress = np.zeros(3, dtype=np.int64)
            while (
                _merge_shard(
                    keys, chords, hits, ranges, hit_ranges, progress, sid, self.shard_mask,
                    shard.table_keys, shard.table_blocks, shard.block_ijk, shard.block_sn,
                    shard.block_t, shard.block_scan, shard.counters,
                    self._scan_id, stamp, decay_time,
                )
                == MERGE_FULL
            ):
                shard.grow()
            touched += int(shard.counters[2])
        return touched

    def finish_scan(self) -> int:
        """Close the scan merged into every shard; returns the voxels it observed first."""
        new = sum(int(sh.counters[1]) for sh in self.shards)
        for sh in self.shards:
            sh.counters[1:] = 0
        self.num_voxels += new
        self._scan_id += 1
        return new

    def assign(self, voxels: VoxelArrays, decay_time: float) -> None:
        """Set the given voxels (replacing any statistics they had), e.g. from a map file.

        Voxels of one block that refer to different times are decayed to the latest.
        """
        ijk = voxels.ijk.astype(np.int64)
        block_keys = (ijk >> BLOCK_BITS) @ np.array([1 << 42, 1 << 21, 1], dtype=np.int64)
        _, inverse = np.unique(block_keys, return_inverse=True)
        t_block = np.full(inverse.max(initial=-1) + 1, -np.inf)
        np.maximum.at(t_block, inverse, voxels.t_last)
        t = t_block[inverse]
        f = np.ones_like(t)
        if math.isfinite(decay_time):
            f = np.exp(-np.abs(t - voxels.t_last) / decay_time)
        s, n = voxels.s * f, voxels.n * f
        for sid, sh in enumerate(self.shards):
            start = 0
            while (start := _assign_shard(
                ijk, s, n, t, start, sid, self.shard_mask, sh.table_keys, sh.table_blocks,
                sh.block_ijk, sh.block_sn, sh.block_t, sh.counters,
            )) < ijk.shape[0]:
                sh.grow()
        self.num_voxels = sum(
            int(np.count_nonzero((sh.block_sn[: sh.used] > 0).any(axis=-1)))
            for sh in self.shards
        )

    def lookup(self, keys: NDArray[np.int64]) -> VoxelArrays:
        """Statistics of the voxels with these keys (zeros and t_last=-inf when absent)."""
        count = keys.shape[0]
        shard_of = np.empty(count, dtype=np.int64)
        block = np.empty(count, dtype=np.int64)
        local = np.empty(count, dtype=np.int64)
        _lookup(
            keys, self.shard_mask, tuple(sh.table_keys for sh in self.shards),
            tuple(sh.table_blocks for sh in self.shards), shard_of, block, local,
        )
        s = np.zeros(count)
        n = np.zeros(count)
        t = np.full(count, -np.inf)
        for sid, sh in enumerate(self.shards):
            sel = (shard_of == sid) & (block >= 0)
            b, li = block[sel], local[sel]
            s[sel] = sh.block_sn[b, li, 0]
            n[sel] = sh.block_sn[b, li, 1]
            t[sel] = sh.block_t[b]
        return VoxelArrays(np.empty((count, 3), dtype=np.int32), s, n, t)

    def export(self) -> VoxelArrays:
        """Every observed voxel."""
        parts = []
        for sh in self.shards:
            used = sh.used
            obs = (sh.block_sn[:used] > 0).any(axis=-1)
            b, li = np.nonzero(obs)
            ijk = sh.block_ijk[b] * BLOCK_EDGE + LOCAL_OFFSETS[li]
            parts.append(
                VoxelArrays(
                    ijk.astype(np.int32),
                    sh.block_sn[b, li, 0].astype(np.float64),
                    sh.block_sn[b, li, 1].astype(np.float64),
                    sh.block_t[b],
                )
            )
        return VoxelArrays(
            np.concatenate([p.ijk for p in parts]).reshape(-1, 3),
            np.concatenate([p.s for p in parts]),
            np.concatenate([p.n for p in parts]),
            np.concatenate([p.t_last for p in parts]),
        )

    def evict(self, keep_block: BlockPredicate) -> int:
        """Drop the blocks the predicate rejects; returns the number of voxels dropped."""
        dropped = 0
        for sh in self.shards:
            used = sh.used
            keep = keep_block(sh.block_ijk[:used], sh.block_t[:used])
            if not keep.all():
                dropped += sh.keep_blocks(keep)
        self.num_voxels -= dropped
        return dropped

    @property
    def num_blocks(self) -> int:
        return sum(sh.used for sh in self.shards)

    @property
    def nbytes(self) -> int:
        return sum(sh.nbytes for sh in self.shards)
