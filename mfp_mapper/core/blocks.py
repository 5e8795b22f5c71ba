"""Blocks and their keys: the geometry of the store, shared by every compiled kernel.

A voxel index ``(x, y, z)`` lies in block ``(x >> 3, y >> 3, z >> 3)``; inside its block the
voxels are in Morton (z-order) order. A block's index is packed into one int64 key
(``block_key``) for the open-addressing hash tables of the shards (``find_block``,
``insert_block``).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.layout import (  # noqa: F401 (the geometry, numba-free, re-exported)
    BLOCK_BITS,
    BLOCK_EDGE,
    BLOCK_VOXELS,
    KEY_BITS,
    KEY_OFFSET,
    MAX_VOXEL_INDEX,
)

_LOCAL_MASK = BLOCK_EDGE - 1
EMPTY_KEY = -1
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)
RESERVED_BLOCKS = 1 << 18
"""Blocks of ``s`` chunks (2 KiB a block) of address space a shard reserves up front:
512 MiB, not resident."""
CHUNK_BITS = 6
"""A block's ``s`` lives in chunks of ``2**CHUNK_BITS`` voxels (a 4x4x4 cube in Morton order),
each allocated when a ray first reaches it."""
CHUNK_VOXELS = 1 << CHUNK_BITS
BLOCK_CHUNKS = BLOCK_VOXELS // CHUNK_VOXELS
N_CHUNK_BITS = 4
"""``n`` lives in chunks of ``2**N_CHUNK_BITS`` voxels, allocated when a return first lands in
one (returns are 1-3% of the observed voxels)."""
N_CHUNK_VOXELS = 1 << N_CHUNK_BITS
N_BLOCK_CHUNKS = BLOCK_VOXELS // N_CHUNK_VOXELS
FOREIGN_CHUNK = -(1 << 31)
"""Chunk-table entry of another shard's block (``shard.ShardArrays.block_chunks``)."""
SHARD_TILE_BITS = 3
"""Shards own tiles of ``2**tile_bits`` blocks along each axis, in a 3-D checkerboard
(``shard_of``): a thread walks a ray only through its own shard's tiles
(``traversal.split_rays``), so tiles are large enough that a ray crosses few of them. This
is the size for stores of more than ``LARGE_TILE_SHARDS`` shards (threads beyond two), whose
threads need the sensor's own tile small: it holds the most steps of a scan. A store of
fewer shards has tiles twice as large (``tile_bits``)."""
LARGE_TILE_SHARDS = 8
"""Stores of at most this many shards (``mapper.shard_count``: two threads) have tiles of
16 blocks (128 voxels) a side, not 8: a ray of OS1-128 at 0.2 m crosses 1.11 tile faces, not
1.75, and the split and the stretches' set-up cost less, while the sensor's tile still holds
less than half a scan. Critical path of two threads (``benchmarks/bench_threads.py``, CPU
time, 2026-11-26): OS1-128 at 0.2 m 1.52-1.63x one thread's against 1.35-1.49x with tiles
of 8; with four threads the sensor's tile is the path, and tiles of 8 keep 2.13-2.47x
against 1.81-2.08x (docs/performance.md, "Two threads", third round)."""


@nb.njit(inline="always", cache=True)
def tile_bits(shard_mask: int) -> int:
    """The tiles of a store of ``shard_mask + 1`` shards are ``2**tile_bits`` blocks a
    side (``LARGE_TILE_SHARDS``)."""
    return SHARD_TILE_BITS + 1 if shard_mask < LARGE_TILE_SHARDS else SHARD_TILE_BITS


@nb.njit(inline="always", cache=True)
def tile_z_offset(shard_mask: int) -> int:
    """The tiles' z faces are this many blocks (half a tile) below multiples of a tile: a
    map's origin is its first sensor position, so a sensor near that height sits mid-tile,
    and the rays of a ground vehicle's lidar reach the ground without crossing a tile face
    there (with faces at the origin, 61k of OS1-128's 107k rays crossed one, a quarter of
    all the tile faces crossed at 0.2 m with tiles of 8 blocks)."""
    return 1 << (tile_bits(shard_mask) - 1)


IndexBox = tuple[int, int, int]
"""A corner of an inclusive voxel index range, as kernels take it: a tuple, not an array
(numba reference-counts array arguments on every call, even of inlined helpers)."""


def index_box(corner: NDArray[np.int64] | tuple[int, int, int]) -> IndexBox:
    x, y, z = (int(v) for v in corner)
    return x, y, z


@nb.njit(inline="always", cache=True)
def block_key(bx: int, by: int, bz: int) -> int:
    return (
        ((bx + KEY_OFFSET) << (2 * KEY_BITS)) | ((by + KEY_OFFSET) << KEY_BITS) | (bz + KEY_OFFSET)
    )


@nb.njit(inline="always", cache=True)
def block_of_key(key: int) -> tuple[int, int, int]:
    """The block index packed in ``key`` by ``block_key``."""
    mask = (1 << KEY_BITS) - 1
    return (
        ((key >> (2 * KEY_BITS)) & mask) - KEY_OFFSET,
        ((key >> KEY_BITS) & mask) - KEY_OFFSET,
        (key & mask) - KEY_OFFSET,
    )


@nb.njit(inline="always", cache=True)
def shard_of(bx: int, by: int, bz: int, shard_mask: int) -> int:
    """The shard of block ``(bx, by, bz)``: the sum of its tile's indices, masked (a
    tile's six neighbours are in other shards)."""
    bits = tile_bits(shard_mask)
    return ((bx >> bits) + (by >> bits) + ((bz + tile_z_offset(shard_mask)) >> bits)) & shard_mask


@nb.njit(inline="always", cache=True)
def _slot_index(key: int, table_mask: int) -> int:
    return int((np.uint64(key) * _HASH_MULT) >> np.uint64(40)) & table_mask


@nb.njit(inline="always", cache=True)
def find_block(table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32], key: int) -> int:
    """Block number of ``key``, or -1."""
    mask = table_keys.shape[0] - 1
    i = _slot_index(key, mask)
    while True:
        k = table_keys[i]
        if k == key:
            return int(table_blocks[i])
        if k == EMPTY_KEY:
            return -1
        i = (i + 1) & mask


@nb.njit(inline="always", cache=True)
def insert_block(
    table_keys: NDArray[np.int64], table_blocks: NDArray[np.int32], key: int, block: int
) -> None:
    mask = table_keys.shape[0] - 1
    i = _slot_index(key, mask)
    while table_keys[i] != EMPTY_KEY:
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
def rebuild_table(
    block_ijk: NDArray[np.int32],
    used: int,
    table_keys: NDArray[np.int64],
    table_blocks: NDArray[np.int32],
) -> None:
    table_keys[:] = EMPTY_KEY
    for b in range(used):
        insert_block(
            table_keys,
            table_blocks,
            block_key(block_ijk[b, 0], block_ijk[b, 1], block_ijk[b, 2]),
            b,
        )
