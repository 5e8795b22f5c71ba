"""Packed blocks: the store's voxels as compact per-block arrays (what map files hold).

The store keeps every voxel of an 8x8x8 block (``store``); most of them are never observed
and only 1-3% of observed voxels hold a return. ``PackedBlocks`` keeps, per block, its
index, its time and a 512-bit mask of observed voxels, then ``s`` of the observed voxels
only; and, for the blocks holding a return, a mask of the voxels with ``n > 0`` and their
``n``. Blocks are sorted by index (x, then y, then z), voxels by their Morton place in the
block (``blocks.local_index``). Values keep the store's precision (float32), so packing and
unpacking are exact; ``pack_chunks`` (from the store's block-level export: dense ``s`` and
``n`` of every voxel of a block) is a compiled walk over the blocks, with no
per-voxel index arrays; ``store.BlockStore.assign_blocks`` unpacks them into the store's
chunked layout in one compiled pass; ``voxel_arrays_of`` gives the voxels as lists (what
``store.BlockStore.assign`` takes: the reference the compiled unpack is checked against).
"""

from __future__ import annotations

from collections.abc import Iterable

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_EDGE,
    BLOCK_VOXELS,
    block_key,
    local_coords,
)
from mfp_mapper.core.layout import (  # noqa: F401 (numba-free, re-exported)
    MASK_WORDS,
    MAX_BLOCK_INDEX,
    PackedBlocks,
    compact,
    packed_problem,
    sort_keys,
    voxel_starts,
)


@nb.njit(cache=True, nogil=True)
def _pack_blocks(
    block_sn: NDArray[np.floating],
    start: int,
    used: int,
    observed: NDArray[np.uint64],
    hit: NDArray[np.uint64],
    counts: NDArray[np.int64],
    s_out: NDArray[np.floating],
    n_out: NDArray[np.floating],
    places: NDArray[np.int64],
) -> int:
    """Masks, counts (observed, hits) and values of blocks ``start`` to ``used``, in one
    read of their memory: ``s`` of the observed voxels and ``n > 0`` appended to ``s_out``
    and ``n_out`` from ``places`` (updated). Returns ``used``, or the block where an output
    ran out of room (grow it and call again). Branch-free (observed voxels are scattered: a
    branch per voxel mispredicts): every voxel is written and the place advances only past
    kept ones."""
    js = places[0]
    jn = places[1]
    for b in range(start, used):
        if js + BLOCK_VOXELS >= s_out.shape[0] or jn + BLOCK_VOXELS >= n_out.shape[0]:
            places[0] = js
            places[1] = jn
            return b
        js0 = js
        jn0 = jn
        for w in range(MASK_WORDS):
            mo = np.uint64(0)
            mh = np.uint64(0)
            for j in range(64):  # the masks first: no store, no dependency between voxels
                s = block_sn[b, w * 64 + j, 0]
                n = block_sn[b, w * 64 + j, 1]
                mh |= np.uint64(n > 0.0) << np.uint64(j)
                mo |= np.uint64((s > 0.0) | (n > 0.0)) << np.uint64(j)
            observed[b, w] = mo
            hit[b, w] = mh
            if mo != 0:  # then the values of the words that hold some
                for j in range(64):
                    s_out[js] = block_sn[b, w * 64 + j, 0]
                    js += (mo >> np.uint64(j)) & np.uint64(1)
            if mh != 0:
                for j in range(64):
                    n_out[jn] = block_sn[b, w * 64 + j, 1]
                    jn += (mh >> np.uint64(j)) & np.uint64(1)
        counts[b, 0] = js - js0
        counts[b, 1] = jn - jn0
    places[0] = js
    places[1] = jn
    return used


@nb.njit(cache=True, nogil=True)
def _copy_runs(
    src: NDArray[np.floating],
    src_start: NDArray[np.int64],
    lengths: NDArray[np.int64],
    dst: NDArray[np.floating],
) -> None:
    """Runs ``src[src_start[k]:src_start[k] + lengths[k]]`` one after the other in ``dst``."""
    j = 0
    for k in range(src_start.shape[0]):
        for i in range(src_start[k], src_start[k] + lengths[k]):
            dst[j] = src[i]
            j += 1


BlockChunk = tuple[NDArray[np.int32], NDArray[np.float64], NDArray[np.floating]]
"""A run of a store's blocks: their index (k, 3), time (k,), and ``s``, ``n`` of their 512
voxels each (k, 512, 2; Morton order; float32 or float64, C order: the packing reads it at
memory speed, a strided view 10 times slower)."""


def _pack_chunk(chunk: BlockChunk, size_hint: int) -> tuple[
    NDArray[np.uint64], NDArray[np.uint64], NDArray[np.int64], NDArray[np.floating],
    NDArray[np.floating],
]:  # fmt: skip
    """Masks, counts and values (chunk order) of one chunk of blocks (``_pack_blocks``)."""
    block_sn = np.ascontiguousarray(chunk[2])
    used = block_sn.shape[0]
    observed = np.empty((used, MASK_WORDS), dtype=np.uint64)
    hit = np.empty((used, MASK_WORDS), dtype=np.uint64)
    counts = np.empty((used, 2), dtype=np.int64)
    size = max(min(size_hint, used * BLOCK_VOXELS), BLOCK_VOXELS) + BLOCK_VOXELS + 1
    s_out = np.empty(size, dtype=block_sn.dtype)
    n_out = np.empty(max(size // 16, BLOCK_VOXELS) + BLOCK_VOXELS + 1, dtype=block_sn.dtype)
    places = np.zeros(2, dtype=np.int64)
    start = 0
    while (
        start := _pack_blocks(block_sn, start, used, observed, hit, counts, s_out, n_out, places)
    ) < used:
        if places[0] + BLOCK_VOXELS >= s_out.shape[0]:
            s_out = np.concatenate([s_out, np.empty_like(s_out)])
        if places[1] + BLOCK_VOXELS >= n_out.shape[0]:
            n_out = np.concatenate([n_out, np.empty_like(n_out)])
    return observed, hit, counts, s_out, n_out


def pack_chunks(chunks: Iterable[BlockChunk], size_hint: int = 0) -> PackedBlocks:
    """The observed voxels of runs of a store's blocks (``BlockChunk``), packed and sorted
    (a copy: the store may change afterwards): one read of the blocks' statistics, then the
    values copied in sorted block order. Blocks without an observed voxel are left out.
    ``size_hint``: about how many voxels the chunks hold (the outputs grow when it is
    short). Values keep their dtype; float64 values are stored as float32 where every one
    survives the round trip (``compact``)."""
    chunks = list(chunks)
    parts = [_pack_chunk(c, size_hint + 1) for c in chunks]
    keep = [np.flatnonzero(p[2][:, 0] > 0) for p in parts]
    block_ijk = np.concatenate(
        [np.zeros((0, 3), np.int32)] + [c[0][r] for c, r in zip(chunks, keep, strict=True)]
    )
    order = np.argsort(sort_keys(block_ijk), kind="stable")
    pairs = list(zip(parts, keep, strict=True))
    no_mask = np.zeros((0, MASK_WORDS), np.uint64)
    observed = np.concatenate([no_mask] + [p[0][r] for p, r in pairs])[order]
    hit = np.concatenate([no_mask] + [p[1][r] for p, r in pairs])[order]
    block_t = np.concatenate([np.zeros(0)] + [c[1][r] for c, r in zip(chunks, keep, strict=True)])
    block_t = block_t[order]
    values = []
    for col in (0, 1):  # s, then n: each block's run in its chunk's output, in sorted order
        outputs = [p[3] if col == 0 else p[4] for p in parts]
        starts, lengths, offset = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], 0
        for k, p in enumerate(parts):
            count = p[2][:, col]
            first = np.cumsum(count) - count
            starts.append(first[keep[k]] + offset)
            lengths.append(count[keep[k]])
            offset += len(outputs[k])
        src = (
            np.concatenate([np.zeros(0, np.float32), *outputs]) if len(outputs) != 1 else outputs[0]
        )
        run_length = np.concatenate(lengths)[order]
        out = np.empty(int(run_length.sum()), dtype=src.dtype)
        _copy_runs(src, np.concatenate(starts)[order], run_length, out)
        values.append((compact(out), run_length))
    (s, _), (n, hits) = values
    hit_block = np.flatnonzero(hits > 0).astype(np.int64)
    return PackedBlocks(
        block_ijk[order].astype(np.int32, copy=False), block_t, observed, s, hit_block,
        hit[hit_block], n,
    )  # fmt: skip


def voxel_arrays_of(
    packed: PackedBlocks,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Index (M, 3), ``s``, ``n`` and time (the block's) of every voxel of ``packed``
    (checked by ``packed_problem``), block by block: what ``store.BlockStore.assign``
    takes (``assign_blocks`` sets the same store from the blocks, 5-10 times faster)."""
    rows = packed.block_ijk.shape[0]
    bits = np.unpackbits(
        np.ascontiguousarray(packed.observed).view(np.uint8), bitorder="little"
    ).reshape(rows, BLOCK_VOXELS)
    row, place = np.nonzero(bits)
    keys = row * BLOCK_VOXELS + place  # increasing: the order of ``s``
    n = np.zeros(keys.shape[0])
    if packed.hit_block.shape[0]:
        hit_bits = np.unpackbits(
            np.ascontiguousarray(packed.hit).view(np.uint8), bitorder="little"
        ).reshape(-1, BLOCK_VOXELS)
        hit_row, hit_place = np.nonzero(hit_bits)
        hit_keys = packed.hit_block[hit_row] * BLOCK_VOXELS + hit_place
        n[np.searchsorted(keys, hit_keys)] = packed.n
    coords = np.array([local_coords(i) for i in range(BLOCK_VOXELS)], dtype=np.int64)
    ijk = packed.block_ijk.astype(np.int64)[row] * BLOCK_EDGE + coords[place]
    s = np.asarray(packed.s, dtype=np.float64)
    return ijk, s, n, packed.block_t[row]


__all__ = [
    "MASK_WORDS",
    "BlockChunk",
    "PackedBlocks",
    "block_key",
    "pack_chunks",
    "packed_problem",
    "voxel_arrays_of",
]
