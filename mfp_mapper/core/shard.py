"""A shard of the store: one hash table and the blocks it indexes (see ``store``).

Where a block's statistics live (``ShardArrays``):

* ``s``, float32, in chunks of ``CHUNK_VOXELS`` (a 4x4x4 cube in Morton order) of one pool,
  ``s_pool``; a chunk is allocated when a ray first reaches it. The block's chunk table
  ``block_chunks[BLOCK_CHUNKS * (b + 1) + k]`` holds chunk k's number, or ``-(slot + 1)``
  (its own slot, negated) while unallocated, so that ``entry * CHUNK_VOXELS + place`` is a
  voxel's index in ``s_pool`` or, negative, says which chunk to allocate. Slots 0 to
  ``BLOCK_CHUNKS - 1`` hold ``FOREIGN_CHUNK``: the walk's entry for another shard's block.
* ``n``, float32, in chunks of ``N_CHUNK_VOXELS`` of ``n_pool``, allocated when a return
  first lands in one; ``block_nrec[b]`` is the block's row of ``n_recs`` (-1: no return yet).
* Exact for hours: a voxel's float32 sums take at most ``limits`` (``s`` up to
  ``FLUSH_EDGES`` voxel edges of chord, ``n`` up to ``N_LIMIT``) before its block is flushed
  into a float64 block of ``hi_pool`` (``block_href[b]``) after the scan: a voxel's
  statistics are the float64 sum plus the float32 one (``block_values``, ``voxel_stats``).
* Observed or not in the ``s`` part alone: a voxel's float32 ``s`` is +0 (all bits 0) exactly
  while it is unobserved; an observed voxel whose float32 ``s`` is 0 (a return alone, flushed,
  decayed to 0) holds -0 there, so that a ray counts a new voxel without reading the block's
  ``n`` and float64 parts (those reads cost 1.2x main's adding). Every observed voxel has its
  ``s`` chunk; readers add +0 (-0 reads as +0).
"""

from __future__ import annotations

import contextlib
import math
import mmap
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_CHUNKS,
    BLOCK_VOXELS,
    CHUNK_BITS,
    CHUNK_VOXELS,
    EMPTY_KEY,
    FOREIGN_CHUNK,
    N_BLOCK_CHUNKS,
    N_CHUNK_BITS,
    N_CHUNK_VOXELS,
    RESERVED_BLOCKS,
    block_key,
    find_block,
    insert_block,
    rebuild_table,
)
from mfp_mapper.core.layout import FLUSH_EDGES, N_LIMIT  # noqa: F401 (re-exported)

FOREIGN_LIMIT = FOREIGN_CHUNK * CHUNK_VOXELS + CHUNK_VOXELS
"""A placed visit below this is to another shard's block (``FOREIGN_CHUNK``)."""
_CHUNK_MASK = CHUNK_VOXELS - 1
_N_CHUNK_MASK = N_CHUNK_VOXELS - 1
S_USED, NREC_USED, NCHUNK_USED, HI_USED, FLUSH_PENDING = range(5)
"""Fields of ``ShardArrays.pools``."""


class ShardArrays(NamedTuple):
    """A shard's arrays, as compiled kernels take them (valid until the shard grows)."""

    table_keys: NDArray[np.int64]
    """Block keys of the open-addressing hash (-1 = empty)."""
    table_blocks: NDArray[np.int32]
    """Block number of each table entry."""
    block_ijk: NDArray[np.int32]
    """(B, 3): block index."""
    block_t: NDArray[np.float64]
    """(B,): time the block's statistics refer to."""
    block_scan: NDArray[np.int64]
    """(B,): last scan that opened the block."""
    block_hit: NDArray[np.bool_]
    """(B,): the block holds a return."""
    counters: NDArray[np.int64]
    """Blocks used, new voxels, blocks touched, voxel updates (the last three per scan)."""
    block_scale: NDArray[np.float64]
    """(B,): factor of the current scan's data (late data < 1)."""
    block_chunks: NDArray[np.int32]
    """(BLOCK_CHUNKS * (B + 1),): the chunk table (module doc)."""
    s_pool: NDArray[np.float32]
    """(chunks, CHUNK_VOXELS): ``s`` (float32 part)."""
    chunk_owner: NDArray[np.int32]
    """(chunks,): the chunk-table slot of each allocated chunk."""
    block_nrec: NDArray[np.int32]
    """(B,): row of ``n_recs``, or -1 while the block holds no return."""
    n_recs: NDArray[np.int32]
    """(rows, N_BLOCK_CHUNKS): ``n_pool`` chunk of each part of a block, or -1."""
    n_pool: NDArray[np.float32]
    """(chunks, N_CHUNK_VOXELS): ``n`` (float32 part)."""
    pools: NDArray[np.int64]
    """Used: s chunks, n rows, n chunks, hi blocks; and whether a flush is pending."""
    block_href: NDArray[np.int32]
    """(B,): block of ``hi_pool``, or -1."""
    hi_pool: NDArray[np.float64]
    """(H, BLOCK_VOXELS, 2): the float64 part of ``s`` and ``n``."""
    block_flush: NDArray[np.bool_]
    """(B,): a voxel of the block passed ``limits`` this scan."""
    limits: NDArray[np.float64]
    """The float32 parts' limits: ``s``, ``n``."""


ValueArrays = tuple[
    NDArray[np.int32],  # block_chunks
    NDArray[np.float32],  # s_pool
    NDArray[np.int32],  # chunk_owner
    NDArray[np.int32],  # block_nrec
    NDArray[np.int32],  # n_recs
    NDArray[np.float32],  # n_pool
    NDArray[np.int32],  # block_href
    NDArray[np.float64],  # hi_pool
    NDArray[np.bool_],  # block_hit
    NDArray[np.bool_],  # block_flush
    NDArray[np.int64],  # pools
    NDArray[np.int64],  # counters
    NDArray[np.float64],  # limits
]
"""The arrays of ``ShardArrays`` that hold or place the statistics, as the walk's additions
take them (``traversal._add_group``)."""


@nb.njit(inline="always", cache=True)
def value_arrays(sa: ShardArrays) -> ValueArrays:
    """The statistics' arrays of ``sa`` (``ValueArrays``)."""
    return (
        sa.block_chunks, sa.s_pool, sa.chunk_owner, sa.block_nrec, sa.n_recs, sa.n_pool,
        sa.block_href, sa.hi_pool, sa.block_hit, sa.block_flush, sa.pools, sa.counters,
        sa.limits,
    )  # fmt: skip


@nb.njit(inline="always", cache=True)
def chunk_slot(block: int, chunk: int) -> int:
    """Slot of chunk ``chunk`` of block ``block`` in the chunk table."""
    return BLOCK_CHUNKS * (block + 1) + chunk


@nb.njit(inline="always", cache=True)
def s_index(
    block_chunks: NDArray[np.int32],
    chunk_owner: NDArray[np.int32],
    pools: NDArray[np.int64],
    voxel: int,
) -> int:
    """``s_pool`` index (flat) of a placed visit ``voxel`` (>= FOREIGN_LIMIT): itself when
    its chunk was allocated when placed, else its chunk's, allocated now if still needed
    (the caller made room: ``Shard.ensure_room``). Helpers take single arrays, not
    ``ShardArrays``: numba counts the references of every array a call takes."""
    if voxel >= 0:
        return voxel
    slot = (-voxel - 1) >> CHUNK_BITS
    chunk = block_chunks[slot]
    if chunk < 0:
        chunk = pools[S_USED]
        pools[S_USED] = chunk + 1
        block_chunks[slot] = chunk
        chunk_owner[chunk] = slot
    return chunk * CHUNK_VOXELS + (voxel & _CHUNK_MASK)


@nb.njit(inline="always", cache=True)
def n_index(
    block_nrec: NDArray[np.int32],
    n_recs: NDArray[np.int32],
    pools: NDArray[np.int64],
    block: int,
    place: int,
    create: bool,
) -> int:
    """``n_pool`` index (flat) of a voxel, created when ``create`` (the caller made room),
    else -1 where the voxel's n chunk does not exist."""
    row = block_nrec[block]
    if row < 0:
        if not create:
            return -1
        row = pools[NREC_USED]
        pools[NREC_USED] = row + 1
        block_nrec[block] = row
        for k in range(N_BLOCK_CHUNKS):
            n_recs[row, k] = -1
    part = place >> N_CHUNK_BITS
    chunk = n_recs[row, part]
    if chunk < 0:
        if not create:
            return -1
        chunk = pools[NCHUNK_USED]
        pools[NCHUNK_USED] = chunk + 1
        n_recs[row, part] = chunk
    return chunk * N_CHUNK_VOXELS + (place & _N_CHUNK_MASK)


@nb.njit(cache=True, nogil=True)
def block_values(
    sa: ShardArrays, block: int, s: NDArray[np.float64], n: NDArray[np.float64]
) -> None:
    """``s`` and ``n`` (float64, 512 each) of every voxel of ``block``: the float32 parts
    plus the float64 parts where the block was flushed. Readers take a block at a time
    (a call per voxel would cost more than the reading)."""
    s[:] = 0.0
    n[:] = 0.0
    for k in range(BLOCK_CHUNKS):
        chunk = sa.block_chunks[chunk_slot(block, k)]
        if chunk >= 0:
            for i in range(CHUNK_VOXELS):
                s[k * CHUNK_VOXELS + i] = np.float64(sa.s_pool[chunk, i]) + 0.0  # (not -0)
    row = sa.block_nrec[block]
    if row >= 0:
        for k in range(N_BLOCK_CHUNKS):
            chunk = sa.n_recs[row, k]
            if chunk >= 0:
                for i in range(N_CHUNK_VOXELS):
                    n[k * N_CHUNK_VOXELS + i] = sa.n_pool[chunk, i]
    hi = sa.block_href[block]
    if hi >= 0:
        for i in range(BLOCK_VOXELS):
            s[i] += sa.hi_pool[hi, i, 0]
            n[i] += sa.hi_pool[hi, i, 1]


@nb.njit(inline="always", cache=True)
def voxel_stats(
    block_chunks: NDArray[np.int32],
    s_pool: NDArray[np.float32],
    block_nrec: NDArray[np.int32],
    n_recs: NDArray[np.int32],
    n_pool: NDArray[np.float32],
    block_href: NDArray[np.int32],
    hi_pool: NDArray[np.float64],
    block: int,
    place: int,
) -> tuple[float, float]:
    """``s`` and ``n`` (float64) of voxel ``place`` of block ``block`` (``block_values`` for
    one voxel)."""
    s = 0.0
    chunk = block_chunks[chunk_slot(block, place >> CHUNK_BITS)]
    if chunk >= 0:
        s = np.float64(s_pool[chunk, place & _CHUNK_MASK]) + 0.0  # (not -0)
    n = 0.0
    row = block_nrec[block]
    if row >= 0:
        chunk = n_recs[row, place >> N_CHUNK_BITS]
        if chunk >= 0:
            n = np.float64(n_pool[chunk, place & _N_CHUNK_MASK])
    hi = block_href[block]
    if hi >= 0:
        s += hi_pool[hi, place, 0]
        n += hi_pool[hi, place, 1]
    return s, n


@nb.njit(inline="always", cache=True)
def init_block(
    sa: ShardArrays, block: int, bx: int, by: int, bz: int, scan_id: int, stamp: float
) -> None:
    """The fields of row ``block``, just taken for the block (bx, by, bz) (its key in the
    table already): its index, time ``stamp`` and scan ``scan_id``, weight 1, no chunks,
    no ``n`` record, no float64 part, no return, not flushed."""
    sa.block_ijk[block, 0] = bx
    sa.block_ijk[block, 1] = by
    sa.block_ijk[block, 2] = bz
    sa.block_t[block] = stamp
    sa.block_scan[block] = scan_id
    sa.block_scale[block] = 1.0
    for k in range(BLOCK_CHUNKS):
        slot = chunk_slot(block, k)
        sa.block_chunks[slot] = -(slot + 1)
    sa.block_nrec[block] = -1
    sa.block_href[block] = -1
    sa.block_hit[block] = False
    sa.block_flush[block] = False


@nb.njit(inline="always", cache=True)
def open_block(
    bx: int,
    by: int,
    bz: int,
    sa: ShardArrays,
    scan_id: int,
    stamp: float,
    decay_time: float,
) -> int:
    """The block (bx, by, bz), created if new, ready to take the scan ``scan_id`` at ``stamp``.

    Order-independent decay (Eq. 28-30, docs/model.md): the first time a scan opens a block,
    a block older than ``stamp`` is decayed to ``stamp`` and takes its time; a block newer
    than ``stamp`` (a late scan) keeps its statistics and time, and the scan's
    contributions to it are scaled by ``exp(-(t_block - stamp) / decay_time)``, the factor
    left in ``block_scale``. Returns -1 when a new block is needed and there is no room:
    the caller grows the shard and calls again.
    """
    counters = sa.counters
    bkey = block_key(bx, by, bz)
    block = find_block(sa.table_keys, sa.table_blocks, bkey)
    if block < 0:
        used = counters[0]
        if used >= sa.block_t.shape[0] or 2 * used >= sa.table_keys.shape[0]:
            return -1
        block = used
        counters[0] = used + 1
        insert_block(sa.table_keys, sa.table_blocks, bkey, block)
        init_block(sa, block, bx, by, bz, scan_id, stamp)
        counters[2] += 1
    elif sa.block_scan[block] != scan_id:
        age = stamp - sa.block_t[block]
        scale = 1.0
        if age >= 0.0:
            if math.isfinite(decay_time) and age > 0.0:
                _decay_block(sa, block, np.float32(math.exp(-age / decay_time)))
            sa.block_t[block] = stamp
        elif math.isfinite(decay_time):
            scale = math.exp(age / decay_time)  # a late scan: its data is scaled, not the map
        sa.block_scale[block] = scale
        sa.block_scan[block] = scan_id
        counters[2] += 1
    return block


@nb.njit(inline="always", cache=True)
def _decay_block(sa: ShardArrays, block: int, f: np.float32) -> None:
    """Scale every statistic of ``block`` by ``f`` (float32 parts in float32)."""
    for k in range(BLOCK_CHUNKS):
        chunk = sa.block_chunks[chunk_slot(block, k)]
        if chunk >= 0:
            for i in range(CHUNK_VOXELS):
                before = sa.s_pool[chunk, i]
                after = before * f
                sa.s_pool[chunk, i] = after if after != 0.0 or before == 0.0 else -0.0
    row = sa.block_nrec[block]
    if row >= 0:
        for k in range(N_BLOCK_CHUNKS):
            chunk = sa.n_recs[row, k]
            if chunk >= 0:
                for i in range(N_CHUNK_VOXELS):
                    sa.n_pool[chunk, i] *= f
    hi = sa.block_href[block]
    if hi >= 0:
        f64 = np.float64(f)
        for i in range(BLOCK_VOXELS):
            sa.hi_pool[hi, i, 0] *= f64
            sa.hi_pool[hi, i, 1] *= f64


@nb.njit(cache=True, nogil=True)
def _flush_blocks(sa: ShardArrays, blocks: NDArray[np.int64]) -> None:
    """Move the float32 parts of ``blocks`` into their float64 blocks (allocated here: the
    caller made room) and zero them (-0 for an observed voxel's ``s``); the blocks'
    ``block_flush`` cleared."""
    flat_n = sa.n_pool.reshape(-1)
    for b in blocks:
        hi = sa.block_href[b]
        if hi < 0:
            hi = sa.pools[HI_USED]
            sa.pools[HI_USED] = hi + 1
            sa.block_href[b] = hi
            sa.hi_pool[hi] = 0.0
        for k in range(BLOCK_CHUNKS):
            chunk = sa.block_chunks[chunk_slot(b, k)]
            if chunk >= 0:
                for i in range(CHUNK_VOXELS):
                    s = sa.s_pool[chunk, i]
                    sa.hi_pool[hi, k * CHUNK_VOXELS + i, 0] += np.float64(s)
                    if s != 0.0:  # observed: -0 (-0 stays)
                        sa.s_pool[chunk, i] = -0.0
        if sa.block_nrec[b] >= 0:
            for place in range(BLOCK_VOXELS):
                k = n_index(sa.block_nrec, sa.n_recs, sa.pools, b, place, False)
                if k >= 0:
                    sa.hi_pool[hi, place, 1] += np.float64(flat_n[k])
                    flat_n[k] = 0.0
        sa.block_flush[b] = False
    sa.pools[FLUSH_PENDING] = 0


@nb.njit(cache=True, nogil=True)
def _observed_per_block(sa: ShardArrays, used: int, out: NDArray[np.int64]) -> None:
    """``out[b]``: the observed voxels (s > 0 or n > 0) of block b."""
    s = np.empty(BLOCK_VOXELS)
    n = np.empty(BLOCK_VOXELS)
    for b in range(used):
        block_values(sa, b, s, n)
        out[b] = np.count_nonzero((s > 0.0) | (n > 0.0))


def _row_bytes(array: NDArray) -> int:
    return array.itemsize * int(np.prod(array.shape[1:]))


def _grown(array: NDArray, rows: int, fill: float | int = 0) -> NDArray:
    """``array`` with at least ``rows`` rows (1.25 times as many when it must grow)."""
    if array.shape[0] >= rows:
        return array
    shape = (max(rows, array.shape[0] * 5 // 4 + 16), *array.shape[1:])
    out = np.zeros(shape, array.dtype) if fill == 0 else np.full(shape, fill, array.dtype)
    out[: array.shape[0]] = array
    return out


class Shard:
    """One hash table and the blocks it indexes.

    The ``s`` chunks live in one region reserved for ``RESERVED_BLOCKS`` blocks' worth: its
    pages become memory only when a chunk is first written, so growing the map does not
    copy it (until a map outgrows the reservation; then it doubles, with one copy).
    ``flush_s``: the float32 limit of ``s`` (``FLUSH_EDGES`` voxel edges; inf: never
    flushed, for a store of one scan).
    """

    def __init__(self, block_capacity: int = 1024, flush_s: float = math.inf) -> None:
        self.counters = np.zeros(4, dtype=np.int64)
        self.pools = np.zeros(5, dtype=np.int64)
        self.limits = np.array([flush_s, N_LIMIT])
        self.s_pool = _zeros_on_huge_pages((RESERVED_BLOCKS * BLOCK_CHUNKS, CHUNK_VOXELS))
        self.chunk_owner: NDArray[np.int32] = np.zeros(0, dtype=np.int32)
        self.n_recs: NDArray[np.int32] = np.full((0, N_BLOCK_CHUNKS), -1, dtype=np.int32)
        self.n_pool: NDArray[np.float32] = np.zeros((0, N_CHUNK_VOXELS), dtype=np.float32)
        self.hi_pool: NDArray[np.float64] = np.zeros((0, BLOCK_VOXELS, 2))
        self.block_ijk: NDArray[np.int32] = np.zeros((0, 3), dtype=np.int32)
        self.block_t: NDArray[np.float64] = np.zeros(0)
        self.block_scan: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self.block_hit: NDArray[np.bool_] = np.zeros(0, dtype=np.bool_)
        self.block_scale: NDArray[np.float64] = np.zeros(0)
        self.block_chunks: NDArray[np.int32] = np.full(BLOCK_CHUNKS, FOREIGN_CHUNK, np.int32)
        self.block_nrec: NDArray[np.int32] = np.zeros(0, dtype=np.int32)
        self.block_href: NDArray[np.int32] = np.zeros(0, dtype=np.int32)
        self.block_flush: NDArray[np.bool_] = np.zeros(0, dtype=np.bool_)
        self._high_water = 0  # most s chunks ever used: their pages stay resident
        self._resize_index(block_capacity)

    def _resize_index(self, capacity: int) -> None:
        """Size the per-block arrays and the hash table for ``capacity`` blocks."""
        used = self.used
        # rows past the used blocks are written by open_block before they are read, so
        # their memory stays untouched (not resident) until then
        names = (
            "block_ijk", "block_t", "block_scan", "block_hit", "block_scale", "block_nrec",
            "block_href", "block_flush",
        )  # fmt: skip
        for name in names:
            old = getattr(self, name)
            new = np.empty((capacity, *old.shape[1:]), dtype=old.dtype)
            new[:used] = old[:used]
            setattr(self, name, new)
        chunks = np.empty(BLOCK_CHUNKS * (capacity + 1), dtype=np.int32)
        chunks[: BLOCK_CHUNKS * (used + 1)] = self.block_chunks[: BLOCK_CHUNKS * (used + 1)]
        self.block_chunks = chunks
        self.table_keys = np.full(_next_pow2(2 * capacity), EMPTY_KEY, dtype=np.int64)
        self.table_blocks = np.zeros(self.table_keys.shape[0], dtype=np.int32)
        rebuild_table(self.block_ijk, used, self.table_keys, self.table_blocks)

    def ensure_room(
        self, s_chunks: int, n_parts: int = 0, hi_blocks: int = 0, n_rows: int | None = None
    ) -> None:
        """Room for ``s_chunks`` more s chunks, ``n_parts`` more n chunks, ``n_rows`` more n
        rows (None: as many, or a quarter of those used, if fewer) and ``hi_blocks`` more
        float64 blocks (``ShardArrays`` changes: take ``arrays()`` again)."""
        pools = self.pools
        need = int(pools[S_USED]) + s_chunks
        if need > self.s_pool.shape[0]:
            region = _zeros_on_huge_pages((max(need, 2 * self.s_pool.shape[0]), CHUNK_VOXELS))
            region[: pools[S_USED]] = self.s_pool[: pools[S_USED]]
            self.s_pool = region
        self.chunk_owner = _grown(self.chunk_owner, need)
        rows = min(n_parts, int(pools[NREC_USED]) // 4 + 64) if n_rows is None else n_rows
        self.n_recs = _grown(self.n_recs, int(pools[NREC_USED]) + rows)  # rows set when made
        self.n_pool = _grown(self.n_pool, int(pools[NCHUNK_USED]) + n_parts)
        self.hi_pool = _grown(self.hi_pool, int(pools[HI_USED]) + hi_blocks)

    def flush(self) -> None:
        """Move the float32 parts of the blocks marked this scan (``block_flush``) into
        float64, so that no sum stops adding (``FLUSH_EDGES``, ``N_LIMIT``)."""
        if not self.pools[FLUSH_PENDING]:
            return
        blocks = np.flatnonzero(self.block_flush[: self.used])
        self.ensure_room(0, 0, int(np.count_nonzero(self.block_href[blocks] < 0)))
        _flush_blocks(self.arrays(), blocks.astype(np.int64))

    def arrays(self) -> ShardArrays:
        """The arrays the compiled kernels work on (valid until the shard grows)."""
        return ShardArrays(
            self.table_keys, self.table_blocks, self.block_ijk, self.block_t, self.block_scan,
            self.block_hit, self.counters, self.block_scale, self.block_chunks, self.s_pool,
            self.chunk_owner, self.block_nrec, self.n_recs, self.n_pool, self.pools,
            self.block_href, self.hi_pool, self.block_flush, self.limits,
        )  # fmt: skip

    @property
    def capacity(self) -> int:
        return int(self.block_t.shape[0])

    @property
    def used(self) -> int:
        return int(self.counters[0])

    def grow(self, min_free: int = 0, at_most: int | None = None) -> None:
        """Grow the block capacity by a quarter (or more, for ``min_free``; no more than ``at_most``
        blocks, when that still leaves ``min_free``), keeping every block."""
        capacity = max(self.capacity * 5 // 4, self.used + min_free)
        if at_most is not None:
            capacity = max(min(capacity, at_most), self.used + min_free)
        self._resize_index(capacity)

    def block_distances(self, center: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (block units) from ``center`` to the centre of every used block."""
        return np.linalg.norm(self.block_ijk[: self.used] + 0.5 - center, axis=1)

    def observed_per_block(self) -> NDArray[np.int64]:
        """The observed voxels of every used block."""
        out = np.zeros(self.used, dtype=np.int64)
        _observed_per_block(self.arrays(), self.used, out)
        return out

    def keep_blocks(self, keep: NDArray[np.bool_]) -> int:
        """Drop the blocks where ``keep`` (over used blocks) is False; returns voxels dropped."""
        used = self.used
        dropped = int(self.observed_per_block()[~keep].sum())
        kept_blocks = np.flatnonzero(keep)
        kept = kept_blocks.shape[0]
        for arr in (
            self.block_ijk, self.block_t, self.block_scan, self.block_hit, self.block_scale,
            self.block_flush,
        ):  # fmt: skip
            arr[:kept] = arr[:used][keep]
        # s chunks: the kept blocks' chunks renumbered in block order
        table = self.block_chunks[BLOCK_CHUNKS:].reshape(-1, BLOCK_CHUNKS)[:used][keep]
        slots = BLOCK_CHUNKS * (np.arange(kept)[:, None] + 1) + np.arange(BLOCK_CHUNKS)
        have = table >= 0
        old_chunks = table[have]
        s_used = int(self.pools[S_USED])
        self.s_pool[: old_chunks.shape[0]] = self.s_pool[old_chunks]
        table[have] = np.arange(old_chunks.shape[0], dtype=np.int32)
        table[~have] = -(slots[~have] + 1)
        self.block_chunks[BLOCK_CHUNKS : BLOCK_CHUNKS * (kept + 1)] = table.reshape(-1)
        self.block_chunks[BLOCK_CHUNKS * (kept + 1) : BLOCK_CHUNKS * (used + 1)] = FOREIGN_CHUNK
        self.chunk_owner[: old_chunks.shape[0]] = slots[have]
        self.pools[S_USED] = old_chunks.shape[0]
        _release_rows(self.s_pool, old_chunks.shape[0], s_used)
        self._high_water = old_chunks.shape[0]
        # n rows and chunks, float64 blocks: kept ones renumbered, in block order
        rows = self.block_nrec[:used][keep]
        has_row = rows >= 0
        recs = self.n_recs[rows[has_row]]
        have_n = recs >= 0
        n_values = self.n_pool[recs[have_n]]
        recs[have_n] = np.arange(n_values.shape[0], dtype=np.int32)
        self.n_pool[: n_values.shape[0]] = n_values
        self.n_pool[n_values.shape[0] : self.pools[NCHUNK_USED]] = 0.0  # new chunks read 0
        self.n_recs[: recs.shape[0]] = recs
        rows[has_row] = np.arange(recs.shape[0], dtype=np.int32)
        self.block_nrec[:kept] = rows
        self.pools[NREC_USED], self.pools[NCHUNK_USED] = recs.shape[0], n_values.shape[0]
        his = self.block_href[:used][keep]
        has_hi = his >= 0
        hi_values = self.hi_pool[his[has_hi]]
        self.hi_pool[: hi_values.shape[0]] = hi_values
        his[has_hi] = np.arange(hi_values.shape[0], dtype=np.int32)
        self.block_href[:kept] = his
        self.pools[HI_USED] = hi_values.shape[0]
        self.counters[0] = kept
        rebuild_table(self.block_ijk, kept, self.table_keys, self.table_blocks)
        return dropped

    def forget_blocks(self) -> None:
        """Hold no block again, keeping the memory of the statistics resident, for blocks
        whose statistics the caller has zeroed (a merged staged store: the merge zeroes what
        it read): the next blocks reuse those pages instead of fresh ones the system must
        fault in and zero. The per-block arrays and the hash table are as a new shard's."""
        self.counters[:] = 0
        self.pools[:] = 0
        self.table_keys.fill(EMPTY_KEY)
        self.table_blocks.fill(0)

    @property
    def nbytes(self) -> int:
        """Memory in use (what Bonxai's ``memUsage`` counts, too): the s chunks up to the
        most ever held, the rows used of the n and float64 parts and of the per-block arrays
        (rows past them are never written before they are used: not resident), and the
        hash table."""
        self._high_water = max(self._high_water, int(self.pools[S_USED]))
        rows = (
            (self.s_pool, self._high_water), (self.chunk_owner, self._high_water),
            (self.n_recs, self.pools[NREC_USED]), (self.n_pool, self.pools[NCHUNK_USED]),
            (self.hi_pool, self.pools[HI_USED]),
            (self.block_chunks, BLOCK_CHUNKS * (self.used + 1)),
        )  # fmt: skip
        per_block = (
            self.block_ijk, self.block_t, self.block_scan, self.block_hit, self.block_scale,
            self.block_nrec, self.block_href, self.block_flush,
        )  # fmt: skip
        return (
            sum(_row_bytes(a) * int(used) for a, used in rows)
            + self.used * sum(_row_bytes(a) for a in per_block)
            + self.table_keys.nbytes
            + self.table_blocks.nbytes
        )


def _zeros_on_huge_pages(shape: tuple[int, ...]) -> NDArray[np.float32]:
    """A zeroed float32 array in fresh anonymous memory, advised to use huge pages.

    Pages are zeroed by the kernel when first touched, so unused capacity costs no time
    and no resident memory. With 4 KiB pages every 4 KiB block would be its own page and
    the far-field updates of a scan would miss the TLB one after another.
    """
    nbytes = int(np.prod(shape)) * 4
    try:
        flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_NORESERVE", 0)
        region = mmap.mmap(-1, max(nbytes, 1), flags=flags)
    except (OSError, AttributeError, ValueError):  # no anonymous mmap here: plain memory
        return np.zeros(shape, dtype=np.float32)
    if hasattr(region, "madvise") and hasattr(mmap, "MADV_HUGEPAGE"):
        with contextlib.suppress(OSError):
            region.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(region, dtype=np.float32, count=int(np.prod(shape))).reshape(shape)


def _release_rows(block_sn: NDArray[np.float32], start: int, stop: int) -> None:
    """Zero rows ``start..stop`` and give their memory back to the system: pages of the
    anonymous region are dropped (``MADV_DONTNEED``) and read as zeros when touched again.
    Where that is not possible the blocks are zeroed in place (memory stays resident)."""
    if stop <= start:
        return
    region = block_sn.base
    while region is not None and not isinstance(region, mmap.mmap):
        region = region.obj if isinstance(region, memoryview) else getattr(region, "base", None)
    block_bytes = block_sn[0].nbytes
    first, last = start * block_bytes, stop * block_bytes
    page = mmap.PAGESIZE
    lo, hi = -(-first // page) * page, last // page * page  # whole pages inside the range
    if isinstance(region, mmap.mmap) and hasattr(mmap, "MADV_DONTNEED") and hi > lo:
        try:
            region.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
        except OSError:
            lo = hi = first
        block_sn.reshape(-1)[first // 4 : lo // 4] = 0.0  # partial pages at the edges
        block_sn.reshape(-1)[hi // 4 : last // 4] = 0.0
        return
    block_sn[start:stop] = 0.0


def _next_pow2(x: int) -> int:
    return 1 << max(int(x - 1).bit_length(), 4)
