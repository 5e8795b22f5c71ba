"""The voxels holding a return in the blocks scans changed since a given scan.

What the node's map clouds are rebuilt from (``Mapper.changed_voxels``, used by
``mapping.map_cloud``): a block's ``block_scan`` is the last scan that opened it, so the
blocks with ``block_scan >= since`` are exactly those whose statistics changed since scan
``since`` began (a block no scan opened keeps its statistics and time: the map clouds show
statistics at their last update, not decayed to a later stamp). Only the ``n`` chunks of a
block are read (a return is needed for any degree of occupancy above 0): 1-3% of the
voxels of a street or indoor map, where ``store._select_voxels`` decodes all 512 voxels of
every block holding a return.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_VOXELS,
    CHUNK_BITS,
    CHUNK_VOXELS,
    N_BLOCK_CHUNKS,
    N_CHUNK_VOXELS,
    block_origin,
    local_coords,
)
from mfp_mapper.core.shard import ShardArrays, block_values, chunk_slot

ChangedArrays = tuple[
    NDArray[np.int32],  # (B, 3) changed blocks holding a return
    NDArray[np.int32],  # (V, 3) voxel index
    NDArray[np.float64],  # s
    NDArray[np.float64],  # n
    NDArray[np.float64],  # t_last
]


@nb.njit(cache=True, nogil=True)
def _changed_bound(
    sa: ShardArrays, start: int, stop: int, since: int, every_voxel: bool
) -> tuple[int, int]:
    """How many changed blocks of ``start..stop`` hold a return (``every_voxel``: how many
    changed blocks), and at most how many voxels they select."""
    blocks = 0
    bound = 0
    for b in range(start, stop):
        if sa.block_scan[b] < since or not (every_voxel or sa.block_hit[b]):
            continue
        blocks += 1
        if every_voxel or sa.block_href[b] >= 0:
            bound += BLOCK_VOXELS
            continue
        row = sa.block_nrec[b]
        if row >= 0:
            for k in range(N_BLOCK_CHUNKS):
                if sa.n_recs[row, k] >= 0:
                    bound += N_CHUNK_VOXELS
    return blocks, bound


@nb.njit(cache=True, nogil=True)
def _keep(s: float, n: float, min_extinction: float) -> bool:
    """``store._select_voxels``' test: ``n >= min_extinction * s``, and observed (with
    ``min_extinction`` 0: every observed voxel)."""
    return (s > 0.0 and n >= min_extinction * s) or (s == 0.0 and n > 0.0)


@nb.njit(cache=True, nogil=True)
def _changed_returns(
    sa: ShardArrays,
    start: int,
    stop: int,
    since: int,
    min_extinction: float,
    blocks_out: NDArray[np.int32],
    ijk: NDArray[np.int32],
    s_out: NDArray[np.float64],
    n_out: NDArray[np.float64],
    t_out: NDArray[np.float64],
) -> int:
    """Fill the outputs (sized by ``_changed_bound``) with the changed blocks of
    ``start..stop`` holding a return and their voxels with ``n >= min_extinction * s``
    (``min_extinction`` 0: every changed block and its observed voxels); returns the voxel
    count."""
    every_voxel = min_extinction == 0.0
    j = 0
    m = 0
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(start, stop):
        if sa.block_scan[b] < since or not (every_voxel or sa.block_hit[b]):
            continue
        x0, y0, z0 = block_origin(sa.block_ijk, b)
        blocks_out[m, 0] = sa.block_ijk[b, 0]
        blocks_out[m, 1] = sa.block_ijk[b, 1]
        blocks_out[m, 2] = sa.block_ijk[b, 2]
        m += 1
        t = sa.block_t[b]
        if every_voxel or sa.block_href[b] >= 0:  # the whole block (flushed: float64 too)
            block_values(sa, b, s_block, n_block)
            for i in range(BLOCK_VOXELS):
                if _keep(s_block[i], n_block[i], min_extinction):
                    dx, dy, dz = local_coords(i)
                    ijk[j, 0], ijk[j, 1], ijk[j, 2] = x0 + dx, y0 + dy, z0 + dz
                    s_out[j], n_out[j], t_out[j] = s_block[i], n_block[i], t
                    j += 1
            continue
        row = sa.block_nrec[b]
        if row < 0:
            continue
        for k in range(N_BLOCK_CHUNKS):
            chunk = sa.n_recs[row, k]
            if chunk < 0:
                continue
            for q in range(N_CHUNK_VOXELS):
                n = np.float64(sa.n_pool[chunk, q])
                if n <= 0.0:
                    continue
                i = k * N_CHUNK_VOXELS + q
                s = 0.0
                s_chunk = sa.block_chunks[chunk_slot(b, i >> CHUNK_BITS)]
                if s_chunk >= 0:
                    s = np.float64(sa.s_pool[s_chunk, i & (CHUNK_VOXELS - 1)]) + 0.0  # not -0
                if _keep(s, n, min_extinction):
                    dx, dy, dz = local_coords(i)
                    ijk[j, 0], ijk[j, 1], ijk[j, 2] = x0 + dx, y0 + dy, z0 + dz
                    s_out[j], n_out[j], t_out[j] = s, n, t
                    j += 1
    return j


@dataclass(frozen=True)
class BlockCursor:
    """Where a read of the store in slices of blocks goes on: block ``block`` of shard
    ``shard``; ``ends``: each shard's block count when the read began. Blocks keep their
    place while the map's epoch stays the same and new ones come after the others, so a
    read that stops at ``ends`` reads each block of the map it began on once, and ends
    however fast scans add blocks (those are the next read's: they changed after it began)."""

    shard: int
    block: int
    ends: tuple[int, ...]


def block_ranges(
    shards: Sequence[tuple[object, int]], cursor: BlockCursor | None, max_blocks: int | None
) -> tuple[list[tuple[int, int, int]], BlockCursor | None]:
    """The (shard, start, stop) block ranges of the next slice of at most ``max_blocks``
    blocks (None: to the end) from ``cursor`` (None: a new read, from the first block of
    ``shards``, ``(arrays, used)`` each), and the cursor after them (None: read to the end)."""
    if cursor is None:
        cursor = BlockCursor(0, 0, tuple(used for _, used in shards))
    ends = cursor.ends
    left = sum(ends) if max_blocks is None else max(int(max_blocks), 1)
    ranges = []
    shard, block = cursor.shard, cursor.block
    while shard < len(ends):
        end = min(ends[shard], shards[shard][1])
        stop = min(end, block + left)
        if stop > block:
            ranges.append((shard, block, stop))
            left -= stop - block
        if stop < end:
            return ranges, BlockCursor(shard, stop, ends)
        shard, block = shard + 1, 0
    return ranges, None


def changed_returns(
    shards: list[tuple[ShardArrays, int]],
    since: int,
    min_extinction: float,
    cursor: BlockCursor | None = None,
    max_blocks: int | None = None,
) -> tuple[ChangedArrays, BlockCursor | None]:
    """Over ``(arrays, used blocks)`` of each shard: the blocks holding a return that a scan
    numbered ``since`` or later opened (all of them: ``since`` -1), and their voxels with
    ``n >= min_extinction * s`` (``min_extinction`` > 0: only their ``n`` chunks are read);
    with ``min_extinction`` 0 every changed block and its observed voxels (each block
    decoded whole), statistics as stored.

    In slices: from ``cursor`` (None: a new read), at most ``max_blocks`` blocks of the
    store, changed or not (a bound on the time taken); also returns the cursor of the next
    slice, None when the read is complete (``BlockCursor``)."""
    if not min_extinction >= 0.0:
        raise ValueError(f"min_extinction must be >= 0, got {min_extinction}")
    ranges, after = block_ranges(shards, cursor, max_blocks)
    parts = []
    for shard, start, stop in ranges:
        sa = shards[shard][0]
        blocks, bound = _changed_bound(sa, start, stop, since, min_extinction == 0.0)
        out = (
            np.empty((blocks, 3), np.int32),
            np.empty((bound, 3), np.int32),
            np.empty(bound),
            np.empty(bound),
            np.empty(bound),
        )
        count = _changed_returns(sa, start, stop, since, min_extinction, *out)
        parts.append((out[0], *(a[:count] for a in out[1:])))
    if not parts:
        empty = (np.empty((0, 3), np.int32), np.empty((0, 3), np.int32))
        return (*empty, np.empty(0), np.empty(0), np.empty(0)), after
    blocks_out, ijk, s, n, t = (np.concatenate([p[k] for p in parts]) for k in range(5))
    return (blocks_out, ijk, s, n, t), after
