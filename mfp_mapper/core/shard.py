"""A shard of the store: one hash table and the dense blocks it indexes (see ``store``)."""

from __future__ import annotations

import contextlib
import math
import mmap

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_VOXELS,
    EMPTY_KEY,
    RESERVED_BLOCKS,
    block_key,
    find_block,
    insert_block,
    rebuild_table,
)


@nb.njit(inline="always", cache=True)
def open_block(
    bx: int,
    by: int,
    bz: int,
    shard_arrays: ShardArrays,
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
    table_keys, table_blocks, block_ijk, block_sn, block_t, block_scan = shard_arrays[:6]
    counters, block_scale = shard_arrays[7], shard_arrays[8]
    bkey = block_key(bx, by, bz)
    block = find_block(table_keys, table_blocks, bkey)
    if block < 0:
        used = counters[0]
        if used >= block_t.shape[0] or 2 * used >= table_keys.shape[0]:
            return -1
        block = used
        counters[0] = used + 1
        insert_block(table_keys, table_blocks, bkey, block)
        block_ijk[block, 0] = bx
        block_ijk[block, 1] = by
        block_ijk[block, 2] = bz
        block_t[block] = stamp
        block_scan[block] = scan_id
        block_scale[block] = 1.0
        counters[2] += 1
    elif block_scan[block] != scan_id:
        age = stamp - block_t[block]
        scale = 1.0
        if age >= 0.0:
            if math.isfinite(decay_time) and age > 0.0:
                f = np.float32(math.exp(-age / decay_time))
                for i in range(BLOCK_VOXELS):
                    block_sn[block, i, 0] *= f
                    block_sn[block, i, 1] *= f
            block_t[block] = stamp
        elif math.isfinite(decay_time):
            scale = math.exp(age / decay_time)  # a late scan: its data is scaled, not the map
        block_scale[block] = scale
        block_scan[block] = scan_id
        counters[2] += 1
    return block


ShardArrays = tuple[
    NDArray[np.int64],  # table_keys: block keys of the open-addressing hash (-1 = empty)
    NDArray[np.int32],  # table_blocks: block number of each table entry
    NDArray[np.int32],  # block_ijk (B, 3): block index
    NDArray[np.float32],  # block_sn (B, 512, 2): s and n of every voxel
    NDArray[np.float64],  # block_t (B,): time the block's statistics refer to
    NDArray[np.int64],  # block_scan (B,): last scan that opened the block
    NDArray[np.bool_],  # block_hit (B,): the block holds a return
    NDArray[np.int64],  # counters: blocks used, new voxels, blocks touched, voxel updates
    NDArray[np.float64],  # block_scale (B,): factor of the current scan's data (late data < 1)
]
"""A shard's arrays, as compiled kernels take them."""


class Shard:
    """One hash table and the blocks it indexes.

    The voxel statistics live in one region reserved for ``RESERVED_BLOCKS`` blocks: its
    pages become memory only when a block is first written, so growing the map does not
    copy it (until a map outgrows the reservation; then it doubles, with one copy).
    """

    def __init__(self, block_capacity: int = 1024) -> None:
        self.counters = np.zeros(4, dtype=np.int64)
        self.block_sn = _zeros_on_huge_pages((RESERVED_BLOCKS, BLOCK_VOXELS, 2))
        self.block_ijk: NDArray[np.int32] = np.zeros((0, 3), dtype=np.int32)
        self.block_t: NDArray[np.float64] = np.zeros(0)
        self.block_scan: NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self.block_hit: NDArray[np.bool_] = np.zeros(0, dtype=np.bool_)
        self.block_scale: NDArray[np.float64] = np.zeros(0)
        self._high_water = 0  # most blocks ever used: their pages stay resident
        self._resize_index(block_capacity)

    def _resize_index(self, capacity: int) -> None:
        """Size the per-block arrays and the hash table for ``capacity`` blocks."""
        used = self.used
        block_ijk = np.zeros((capacity, 3), dtype=np.int32)
        block_t = np.full(capacity, -np.inf)
        block_scan = np.full(capacity, -1, dtype=np.int64)
        block_hit = np.zeros(capacity, dtype=np.bool_)
        block_scale = np.ones(capacity)
        if used:
            block_ijk[:used] = self.block_ijk[:used]
            block_t[:used] = self.block_t[:used]
            block_scan[:used] = self.block_scan[:used]
            block_hit[:used] = self.block_hit[:used]
            block_scale[:used] = self.block_scale[:used]
        self.block_ijk, self.block_t, self.block_scan = block_ijk, block_t, block_scan
        self.block_hit, self.block_scale = block_hit, block_scale
        if capacity > self.block_sn.shape[0]:
            reserve = max(capacity, 2 * self.block_sn.shape[0])
            region = _zeros_on_huge_pages((reserve, BLOCK_VOXELS, 2))
            region[:used] = self.block_sn[:used]
            self.block_sn = region
        self.table_keys = np.full(_next_pow2(2 * capacity), EMPTY_KEY, dtype=np.int64)
        self.table_blocks = np.zeros(self.table_keys.shape[0], dtype=np.int32)
        rebuild_table(self.block_ijk, used, self.table_keys, self.table_blocks)

    def arrays(self) -> ShardArrays:
        """The arrays the compiled kernels work on (valid until the shard grows)."""
        return (
            self.table_keys, self.table_blocks, self.block_ijk, self.block_sn, self.block_t,
            self.block_scan, self.block_hit, self.counters, self.block_scale,
        )  # fmt: skip

    @property
    def capacity(self) -> int:
        return int(self.block_t.shape[0])

    @property
    def used(self) -> int:
        return int(self.counters[0])

    def grow(self, min_free: int = 0, at_most: int | None = None) -> None:
        """Double the block capacity (or more, for ``min_free``; no more than ``at_most``
        blocks, when that still leaves ``min_free``), keeping every block."""
        capacity = max(2 * self.capacity, self.used + min_free)
        if at_most is not None:
            capacity = max(min(capacity, at_most), self.used + min_free)
        self._resize_index(capacity)

    def block_distances(self, center: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (block units) from ``center`` to the centre of every used block."""
        return np.linalg.norm(self.block_ijk[: self.used] + 0.5 - center, axis=1)

    def keep_blocks(self, keep: NDArray[np.bool_]) -> int:
        """Drop the blocks where ``keep`` (over used blocks) is False; returns voxels dropped."""
        used = self.used
        dropped = int(np.count_nonzero((self.block_sn[:used][~keep] > 0).any(axis=-1)))
        kept = int(np.count_nonzero(keep))
        for arr in (
            self.block_ijk, self.block_sn, self.block_t, self.block_scan, self.block_hit,
            self.block_scale,
        ):  # fmt: skip
            arr[:kept] = arr[:used][keep]
        _release_blocks(self.block_sn, kept, used)
        self._high_water = kept
        self.block_t[kept:used] = -np.inf
        self.block_scan[kept:used] = -1
        self.block_hit[kept:used] = False
        self.counters[0] = kept
        rebuild_table(self.block_ijk, kept, self.table_keys, self.table_blocks)
        return dropped

    def forget_blocks(self) -> None:
        """Hold no block again, keeping the memory of the statistics resident, for blocks
        whose statistics the caller has zeroed (a merged staged store: the merge zeroes what
        it read): the next blocks reuse those pages instead of fresh ones the system must
        fault in and zero. The per-block arrays and the hash table are as a new shard's."""
        used = self.used
        self.block_ijk[:used] = 0
        self.block_t[:used] = -np.inf
        self.block_scan[:used] = -1
        self.block_hit[:used] = False
        self.block_scale[:used] = 1.0
        self.counters[:] = 0
        self.table_keys.fill(EMPTY_KEY)
        self.table_blocks.fill(0)

    @property
    def nbytes(self) -> int:
        """Memory in use: the blocks' statistics up to the most ever held, and the index."""
        self._high_water = max(self._high_water, self.used)
        index = (
            self.block_ijk, self.block_t, self.block_scan, self.block_hit, self.block_scale,
            self.table_keys, self.table_blocks,
        )  # fmt: skip
        return self._high_water * self.block_sn[0].nbytes + sum(a.nbytes for a in index)


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


def _release_blocks(block_sn: NDArray[np.float32], start: int, stop: int) -> None:
    """Zero blocks ``start..stop`` and give their memory back to the system: pages of the
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
