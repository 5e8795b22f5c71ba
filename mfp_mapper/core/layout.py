"""The store's geometry and the arrays that leave it, in numpy alone: block and key
sizes, voxel lists (``VoxelArrays``) and packed blocks (``PackedBlocks``, what map files
hold) with their checks. No numba: map files and a query of map-file points import this
module, not the compiled store (``blocks``, ``store`` and ``packed`` re-export its names).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

BLOCK_BITS = 3
BLOCK_EDGE = 1 << BLOCK_BITS
BLOCK_VOXELS = BLOCK_EDGE**3
KEY_BITS = 21
"""Bits of each block index in a key (``block_key``)."""
KEY_OFFSET = 1 << (KEY_BITS - 1)
"""Added to a block index before packing, so that every packed field is non-negative."""
MAX_VOXEL_INDEX = (KEY_OFFSET << BLOCK_BITS) - BLOCK_EDGE
"""Largest |voxel index| the store can hold (block indices are packed in 21 bits each)."""

FLUSH_EDGES = 1024.0
"""A voxel's float32 ``s`` holds at most this many voxel edges of chord (plus one scan's)
before its block is flushed into float64 (``shard.Shard.flush``): float32 sums of about 2048
chords of half an edge keep a relative error below 2048 * 2**-24 = 1.2e-4."""
N_LIMIT = float(1 << 20)
"""A voxel's float32 ``n`` holds at most this (plus one scan's returns) before its block is
flushed: every integer count below 2**24 is exact in float32."""


MIN_RESOLUTION = 1e-3
"""Smallest voxel edge (metres) a map may have."""
MAX_RESOLUTION = 1e3
"""Largest voxel edge (metres) a map may have."""


@dataclass
class VoxelArrays:
    """Raw statistics of a set of voxels: index, s, n and the time they refer to."""

    ijk: NDArray[np.int32]
    s: NDArray[np.float64]
    n: NDArray[np.float64]
    t_last: NDArray[np.float64]


MASK_WORDS = BLOCK_VOXELS // 64
"""uint64 words of a block's voxel mask: bit ``i % 64`` of word ``i // 64`` is voxel ``i``
(Morton place) of the block."""
MAX_BLOCK_INDEX = MAX_VOXEL_INDEX >> 3
"""Largest |block index| a store holds."""


@dataclass
class PackedBlocks:
    """Observed voxels block by block (``core.packed``'s docstring tells the layout).

    ``block_ijk`` int32 (B, 3) sorted, each block once; ``block_t`` float64 (B,);
    ``observed`` uint64 (B, 8); ``s`` (M,) one per set bit of ``observed``, block by block;
    ``hit_block`` int64 (H,) increasing rows of the blocks holding a return; ``hit`` uint64
    (H, 8) their voxels with ``n > 0`` (a subset of ``observed``); ``n`` (K,) one per set
    bit of ``hit``. ``s`` and ``n`` are float32 from a store, float64 where sums were
    merged."""

    block_ijk: NDArray[np.int32]
    block_t: NDArray[np.float64]
    observed: NDArray[np.uint64]
    s: NDArray[np.floating]
    hit_block: NDArray[np.int64]
    hit: NDArray[np.uint64]
    n: NDArray[np.floating]

    @property
    def num_voxels(self) -> int:
        return int(self.s.shape[0])


def sort_keys(block_ijk: NDArray[np.integer]) -> NDArray[np.int64]:
    """One int64 per block index whose order is (x, y, z) lexicographic (``block_key``)."""
    b = np.asarray(block_ijk, dtype=np.int64) + KEY_OFFSET
    return (b[:, 0] << (2 * KEY_BITS)) | (b[:, 1] << KEY_BITS) | b[:, 2]


def voxel_starts(mask: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Index of each block's first value (B + 1 entries: the last is the total)."""
    counts = np.bitwise_count(mask).sum(axis=1, dtype=np.int64)
    out = np.zeros(mask.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def packed_problem(p: PackedBlocks) -> str | None:
    """What is wrong with packed blocks (shapes, order, masks, values), or None."""
    b = p.block_ijk.shape[0]
    if p.block_ijk.shape != (b, 3) or p.block_t.shape != (b,) or p.observed.shape != (b, 8):
        return "blocks need block_ijk (B, 3), block_t (B,) and observed (B, 8)"
    h = p.hit_block.shape[0]
    if p.hit_block.shape != (h,) or p.hit.shape != (h, 8):
        return "blocks with a return need hit_block (H,) and hit (H, 8)"
    if b and int(np.abs(p.block_ijk).max()) > MAX_BLOCK_INDEX:
        return f"block indices beyond +-{MAX_BLOCK_INDEX}, the map's range"
    if b > 1 and not np.all(np.diff(sort_keys(p.block_ijk)) > 0):
        return "blocks are not sorted by index, or a block is listed twice"
    if not np.isfinite(p.block_t).all():
        return "block times hold NaN or infinite values (seconds expected)"
    if p.s.shape != (int(np.bitwise_count(p.observed).sum()),):
        return (
            f"s holds {p.s.shape} values, the observed masks {np.bitwise_count(p.observed).sum()}"
        )
    if h and (int(p.hit_block[0]) < 0 or int(p.hit_block[-1]) >= b):
        return f"hit_block rows outside [0, {b})"
    if h > 1 and not np.all(np.diff(p.hit_block) > 0):
        return "hit_block is not increasing"
    if np.any(p.hit & ~p.observed[p.hit_block]):
        return "a voxel with a return is not marked observed"
    if p.n.shape != (int(np.bitwise_count(p.hit).sum()),):
        return f"n holds {p.n.shape} values, the hit masks {np.bitwise_count(p.hit).sum()}"
    for key, arr in (("s", p.s), ("n", p.n)):
        if arr.dtype.kind != "f" or not (np.isfinite(arr).all() and arr.min(initial=0.0) >= 0):
            return f"{key} holds negative, NaN or infinite values"
        if arr.max(initial=0.0) > np.finfo(np.float32).max:
            return f"{key} holds values beyond float32's range (the store's)"
    return None


def compact(values: NDArray[np.floating]) -> NDArray[np.floating]:
    """float32 values as they are; float64 ones as float32 when every one survives the
    round trip, else as they are."""
    if values.dtype == np.float32:
        return values
    small = values.astype(np.float32)
    return small if np.array_equal(small, values) else values


def voxel_problem(
    ijk: NDArray[np.integer], s: NDArray[np.floating], n: NDArray[np.floating], t: NDArray
) -> str | None:
    """What is wrong with these voxel arrays (values only; duplicates are found when they are
    stored), or None."""
    for key, arr in (("s", s), ("n", n)):
        if not (np.isfinite(arr).all() and arr.min(initial=0.0) >= 0):
            return f"{key} holds negative, NaN or infinite values"
    if not np.isfinite(t).all():
        return "t_last holds NaN or infinite values (seconds expected)"
    if ijk.shape[0] and max(-int(ijk.min()), int(ijk.max())) > MAX_VOXEL_INDEX:
        return f"ijk holds indices beyond +-{MAX_VOXEL_INDEX}, the map's range"
    return None


def stored_sums(
    s: NDArray[np.floating], n: NDArray[np.floating], resolution: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A voxel's ``s`` and ``n`` (file values, float32 or float64) as the store reads them
    back once set from a file (``store._set_blocks``, then ``shard.voxel_stats``): float32
    below the limits (``FLUSH_EDGES`` voxel edges of ``s``, ``N_LIMIT`` returns), the float64
    values at or above either; float64 out, -0 read as +0."""
    s64, n64 = s.astype(np.float64), n.astype(np.float64)
    beyond = (s64 >= FLUSH_EDGES * resolution) | (n64 >= N_LIMIT)
    s_out = np.where(beyond, s64, s64.astype(np.float32).astype(np.float64)) + 0.0
    n_out = np.where(beyond, n64, n64.astype(np.float32).astype(np.float64)) + 0.0
    return s_out, n_out
