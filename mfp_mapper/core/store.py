"""Sparse voxel store: a hash of dense 8x8x8 blocks holding ``(s, n)`` per voxel.

Layout (chosen for speed and memory, see ANCHORS.md):

* Voxels live in dense blocks of ``BLOCK_EDGE**3``; a ray stays in one block for several
  steps, so most updates are an array index into the block the walk is already in.
* Blocks are found through open-addressing hash tables, split into ``shards`` by block
  parity; each thread of an integration writes only to its own shard, so threads need
  no locks (see ``traversal``).
* ``s`` and ``n`` are float32, side by side (8 bytes a voxel), and the voxels of a block
  are in Morton order, so one 64-byte cache line holds a 2x2x2 cube of voxels: a ray
  crossing it finds its next voxel in the same line. Each block keeps the time ``t`` its
  statistics refer to. Decay (Eq. 28-30) is uniform scaling, so bringing a whole block to
  the current stamp the first time a scan touches it is exactly the per-voxel lazy decay;
  a voxel's ``t_last`` is its block's ``t``. A late scan (older than the block) leaves
  the block and its time alone and adds its data scaled by ``exp(-(t - stamp) / T)``, so
  the map does not depend on the order in which scans arrive.
* A voxel is *observed* when ``s > 0`` or ``n > 0``.

Every ray's contribution is summed into the store: sums, never deduplication.
"""

from __future__ import annotations

import contextlib
import math
import mmap
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

BLOCK_BITS = 3
BLOCK_EDGE = 1 << BLOCK_BITS
BLOCK_VOXELS = BLOCK_EDGE**3
_LOCAL_MASK = BLOCK_EDGE - 1
_EMPTY = -1
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
RESERVED_BLOCKS = 1 << 18
"""Blocks (4 KiB each) of address space a shard reserves up front: 1 GiB, not resident."""
MAX_VOXEL_INDEX = (_KEY_OFFSET << BLOCK_BITS) - BLOCK_EDGE
"""Largest |voxel index| the store can hold (block indices are packed in 21 bits each)."""

IndexBox = tuple[int, int, int]
"""A corner of an inclusive voxel index range, as kernels take it: a tuple, not an array
(numba reference-counts array arguments on every call, even of inlined helpers)."""


def index_box(corner: NDArray[np.int64] | tuple[int, int, int]) -> IndexBox:
    x, y, z = (int(v) for v in corner)
    return x, y, z


@nb.njit(inline="always", cache=True)
def block_key(bx: int, by: int, bz: int) -> int:
    return (
        ((bx + _KEY_OFFSET) << (2 * _KEY_BITS))
        | ((by + _KEY_OFFSET) << _KEY_BITS)
        | (bz + _KEY_OFFSET)
    )


@nb.njit(inline="always", cache=True)
def block_of_key(key: int) -> tuple[int, int, int]:
    """The block index packed in ``key`` by ``block_key``."""
    mask = (1 << _KEY_BITS) - 1
    return (
        ((key >> (2 * _KEY_BITS)) & mask) - _KEY_OFFSET,
        ((key >> _KEY_BITS) & mask) - _KEY_OFFSET,
        (key & mask) - _KEY_OFFSET,
    )


@nb.njit(inline="always", cache=True)
def shard_of(bx: int, by: int, bz: int, shard_mask: int) -> int:
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
def _insert(
    table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32], key: int, block: int
) -> None:
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
def local_index(vx: int, vy: int, vz: int) -> int:
    """Morton (z-order) index of a voxel inside its block."""
    return (
        (_spread_bits(vx & _LOCAL_MASK) << 2)
        | (_spread_bits(vy & _LOCAL_MASK) << 1)
        | _spread_bits(vz & _LOCAL_MASK)
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

    Order-independent decay (MODEL.md, Eq. 28-30): the first time a scan opens a block,
    a block older than ``stamp`` is decayed to ``stamp`` and takes its time; a block newer
    than ``stamp`` (a late scan) keeps its statistics and time, and the scan's
    contributions to it are scaled by ``exp(-(t_block - stamp) / decay_time)``, the factor
    left in ``block_scale``. Returns -1 when a new block is needed and there is no room:
    the caller grows the shard and calls again.
    """
    table_keys, table_blocks, block_ijk, block_sn, block_t, block_scan = shard_arrays[:6]
    counters, block_scale = shard_arrays[7], shard_arrays[8]
    bkey = block_key(bx, by, bz)
    block = _find(table_keys, table_blocks, bkey)
    if block < 0:
        used = counters[0]
        if used >= block_t.shape[0] or 2 * used >= table_keys.shape[0]:
            return -1
        block = used
        counters[0] = used + 1
        _insert(table_keys, table_blocks, bkey, block)
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


@nb.njit(cache=True, nogil=True)
def _open_blocks_of(
    ijk: NDArray[np.int64],
    t: NDArray[np.float64],
    start: int,
    shard: int,
    shard_mask: int,
    shard_arrays: ShardArrays,
) -> int:
    """Open the blocks of the voxels of ``shard`` from index ``start`` on, each at the
    latest ``t`` of its voxels. Returns ``len(ijk)``, or the index where blocks ran out."""
    block_t = shard_arrays[4]
    for j in range(start, ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        if shard_of(bx, by, bz, shard_mask) != shard:
            continue
        block = open_block(bx, by, bz, shard_arrays, -1, t[j], math.inf)
        if block < 0:
            return j
        block_t[block] = max(block_t[block], t[j])
    return ijk.shape[0]


@nb.njit(cache=True, nogil=True)
def _set_voxels(
    ijk: NDArray[np.int64],
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t: NDArray[np.float64],
    shard: int,
    shard_mask: int,
    decay_time: float,
    shard_arrays: ShardArrays,
    seen: NDArray[np.uint64],
    counts: NDArray[np.int64],
) -> int:
    """Set the voxels of ``shard`` (blocks opened by ``_open_blocks_of``), each decayed to
    its block's time; ``counts[0]`` receives the number of observed voxels set. Returns -1,
    or the index of a voxel listed twice (``seen``: one bit per voxel of each block)."""
    table_keys, table_blocks, _, block_sn, block_t = shard_arrays[:5]
    block_hit = shard_arrays[6]
    observed = 0
    for j in range(ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        if shard_of(bx, by, bz, shard_mask) != shard:
            continue
        block = _find(table_keys, table_blocks, block_key(bx, by, bz))
        local = local_index(ijk[j, 0], ijk[j, 1], ijk[j, 2])
        bit = np.uint64(1) << np.uint64(local & 63)
        if seen[block, local >> 6] & bit:
            return j
        seen[block, local >> 6] |= bit
        f = 1.0
        if math.isfinite(decay_time):
            f = math.exp(-(block_t[block] - t[j]) / decay_time)
        block_sn[block, local, 0] = s[j] * f
        block_sn[block, local, 1] = n[j] * f
        if block_sn[block, local, 1] > 0.0:
            block_hit[block] = True
        if block_sn[block, local, 0] > 0.0 or block_sn[block, local, 1] > 0.0:
            observed += 1
    counts[0] += observed
    return -1


@nb.njit(cache=True, nogil=True)
def _lookup(
    ijk: NDArray[np.int64],
    shard_mask: int,
    tables_keys: tuple[NDArray[np.int64], ...],
    tables_blocks: tuple[NDArray[np.int32], ...],
    out_shard: NDArray[np.int64],
    out_block: NDArray[np.int64],
    out_local: NDArray[np.int64],
) -> None:
    """For each voxel index: its shard, block number (-1 when absent) and index in the block."""
    for j in range(ijk.shape[0]):
        bx = ijk[j, 0] >> BLOCK_BITS
        by = ijk[j, 1] >> BLOCK_BITS
        bz = ijk[j, 2] >> BLOCK_BITS
        shard = shard_of(bx, by, bz, shard_mask)
        out_shard[j] = shard
        out_block[j] = _find(tables_keys[shard], tables_blocks[shard], block_key(bx, by, bz))
        out_local[j] = local_index(ijk[j, 0], ijk[j, 1], ijk[j, 2])


@nb.njit(cache=True, nogil=True)
def _select_voxels(
    block_ijk: NDArray[np.int32],
    block_sn: NDArray[np.float32],
    block_hit: NDArray[np.bool_],
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
    for b in range(used):
        if min_extinction > 0.0 and not block_hit[b]:
            continue  # no return in the block: no voxel has n >= min_extinction * s > 0
        x0, y0, z0 = block_origin(block_ijk, b)
        if block_outside(x0, y0, z0, lo, hi):
            continue
        last = BLOCK_EDGE - 1
        inside = voxel_inside(x0, y0, z0, lo, hi) and voxel_inside(
            x0 + last, y0 + last, z0 + last, lo, hi
        )
        for i in range(BLOCK_VOXELS):
            s = block_sn[b, i, 0]
            n = block_sn[b, i, 1]
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
    block_ijk: NDArray[np.int32],
    block_sn: NDArray[np.float32],
    block_t: NDArray[np.float64],
    keep: NDArray[np.bool_],
    kept_per_block: NDArray[np.int64],
    ijk: NDArray[np.int32],
    s: NDArray[np.float64],
    n: NDArray[np.float64],
    t_last: NDArray[np.float64],
) -> None:
    """Write the voxels marked in ``keep`` (blocks x voxels) to the output arrays, in order."""
    j = 0
    for b in range(keep.shape[0]):
        if kept_per_block[b] == 0:
            continue
        for i in range(BLOCK_VOXELS):
            if keep[b, i]:
                x0, y0, z0 = block_origin(block_ijk, b)
                dx, dy, dz = local_coords(i)
                ijk[j, 0] = x0 + dx
                ijk[j, 1] = y0 + dy
                ijk[j, 2] = z0 + dz
                s[j] = block_sn[b, i, 0]
                n[j] = block_sn[b, i, 1]
                t_last[j] = block_t[b]
                j += 1


@nb.njit(inline="always", cache=True)
def _unspread_bits(v: int) -> int:
    """Inverse of ``_spread_bits``: bits 0, 3, 6 of ``v`` gathered into bits 0, 1, 2."""
    return (v & 1) | ((v >> 2) & 2) | ((v >> 4) & 4)


@nb.njit(inline="always", cache=True)
def local_coords(i: int) -> tuple[int, int, int]:
    """Offsets (x, y, z) in its block of the voxel with Morton index ``i`` (``local_index``
    inverted)."""
    return _unspread_bits(i >> 2), _unspread_bits(i >> 1), _unspread_bits(i)


@nb.njit(inline="always", cache=True)
def block_origin(block_ijk: NDArray[np.int32], b: int) -> tuple[int, int, int]:
    """Voxel index of the first voxel (lowest corner) of block ``b``."""
    return (
        np.int64(block_ijk[b, 0]) * BLOCK_EDGE,
        np.int64(block_ijk[b, 1]) * BLOCK_EDGE,
        np.int64(block_ijk[b, 2]) * BLOCK_EDGE,
    )


@nb.njit(inline="always", cache=True)
def block_outside(x0: int, y0: int, z0: int, lo: IndexBox, hi: IndexBox) -> bool:
    """Whether the block at voxel index (x0, y0, z0) lies wholly outside [lo, hi]."""
    return (
        x0 + BLOCK_EDGE <= lo[0]
        or x0 > hi[0]
        or y0 + BLOCK_EDGE <= lo[1]
        or y0 > hi[1]
        or z0 + BLOCK_EDGE <= lo[2]
        or z0 > hi[2]
    )


@nb.njit(inline="always", cache=True)
def voxel_inside(x: int, y: int, z: int, lo: IndexBox, hi: IndexBox) -> bool:
    """Whether voxel index (x, y, z) lies in [lo, hi] (inclusive)."""
    return lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]


@nb.njit(cache=True, nogil=True)
def _rebuild_table(
    block_ijk: NDArray[np.int32],
    used: int,
    table_keys: NDArray[np.int64],
    table_blocks: NDArray[np.int32],
) -> None:
    table_keys[:] = _EMPTY
    for b in range(used):
        _insert(
            table_keys,
            table_blocks,
            block_key(block_ijk[b, 0], block_ijk[b, 1], block_ijk[b, 2]),
            b,
        )


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


@dataclass
class VoxelArrays:
    """Raw statistics of a set of voxels: index, s, n and the time they refer to."""

    ijk: NDArray[np.int32]
    s: NDArray[np.float64]
    n: NDArray[np.float64]
    t_last: NDArray[np.float64]


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
        self.table_keys = np.full(_next_pow2(2 * capacity), _EMPTY, dtype=np.int64)
        self.table_blocks = np.zeros(self.table_keys.shape[0], dtype=np.int32)
        _rebuild_table(self.block_ijk, used, self.table_keys, self.table_blocks)

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

    def grow(self, min_free: int = 0) -> None:
        """Double the block capacity (or more, for ``min_free``), keeping every block."""
        self._resize_index(max(2 * self.capacity, self.used + min_free))

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
        _rebuild_table(self.block_ijk, kept, self.table_keys, self.table_blocks)
        return dropped

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


class BlockStore:
    """All shards together: the map's memory, with lookup, export, loading and eviction."""

    def __init__(self, shards: int = 1) -> None:
        if shards < 1 or shards & (shards - 1):
            raise ValueError(f"shards must be a power of two, got {shards}")
        self.shards = [Shard() for _ in range(shards)]
        self.shard_mask = shards - 1
        self.num_voxels = 0
        self._scan_id = 0

    def begin_scan(self) -> int:
        """Start a scan: clears the per-scan counters; returns the scan's id."""
        for sh in self.shards:
            sh.counters[1:] = 0
        return self._scan_id

    def finish_scan(self) -> tuple[int, int, int]:
        """Close the scan; returns (voxels observed for the first time, blocks touched,
        voxel updates)."""
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
            twice = _set_voxels(
                ijk, s, n, t, sid, self.shard_mask, decay_time, sh.arrays(), seen, counts
            )
            if twice >= 0:
                raise ValueError(f"ijk lists voxel {ijk[twice].tolist()} more than once")
        self.num_voxels = int(counts[0])

    def lookup(self, ijk: NDArray[np.int64]) -> VoxelArrays:
        """Statistics of these voxels (zeros and t_last=-inf where never observed)."""
        count = ijk.shape[0]
        shard_of = np.empty(count, dtype=np.int64)
        block = np.empty(count, dtype=np.int64)
        local = np.empty(count, dtype=np.int64)
        _lookup(
            ijk,
            self.shard_mask,
            tuple(sh.table_keys for sh in self.shards),
            tuple(sh.table_blocks for sh in self.shards),
            shard_of,
            block,
            local,
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
            count = _select_voxels(
                sh.block_ijk, sh.block_sn, sh.block_hit, sh.used, min_extinction, lo_, hi_, keep,
                per_block,
            )  # fmt: skip
            selections.append((keep, per_block, count))
        total = sum(count for _, _, count in selections)
        out = VoxelArrays(
            np.empty((total, 3), dtype=np.int32), np.empty(total), np.empty(total), np.empty(total)
        )
        start = 0
        for sh, (keep, per_block, count) in zip(self.shards, selections, strict=True):
            part = slice(start, start + count)
            _gather_voxels(
                sh.block_ijk, sh.block_sn, sh.block_t, keep, per_block,
                out.ijk[part], out.s[part], out.n[part], out.t_last[part],
            )  # fmt: skip
            start += count
        return out

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
