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
    as_parts,
    as_values,
    compact,
    hi_starts,
    hit_row_of,
    packed_problem,
    ranges,
    select_blocks,
    sort_keys,
    totals,
    voxel_starts,
)


@nb.njit(cache=True, nogil=True)
def _pack_blocks(
    block_s: NDArray[np.float32],
    block_n: NDArray[np.float32],
    hi_row: NDArray[np.int64],
    hi: NDArray[np.float64],
    start: int,
    used: int,
    observed: NDArray[np.uint64],
    hit: NDArray[np.uint64],
    counts: NDArray[np.int64],
    s_out: NDArray[np.float32],
    n_out: NDArray[np.float32],
    places: NDArray[np.int64],
) -> int:
    """Masks, counts (observed, hits) and float32 parts of blocks ``start`` to ``used``, in
    one read of their memory: ``s`` of the observed voxels and ``n`` of those with a return
    appended to ``s_out`` and ``n_out`` from ``places`` (updated; -0 written as +0). A
    voxel is observed when its value (the float32 part plus the float64 one of a block
    with ``hi_row[b] >= 0``, row of ``hi``) is > 0. Returns ``used``, or the block where an
    output ran out of room (grow it and call again). Branch-free (observed voxels are
    scattered: a branch per voxel mispredicts): every voxel is written and the place
    advances only past kept ones."""
    js = places[0]
    jn = places[1]
    zero = np.float32(0.0)
    for b in range(start, used):
        if js + BLOCK_VOXELS >= s_out.shape[0] or jn + BLOCK_VOXELS >= n_out.shape[0]:
            places[0] = js
            places[1] = jn
            return b
        js0 = js
        jn0 = jn
        r = hi_row[b]
        for w in range(MASK_WORDS):
            mo = np.uint64(0)
            mh = np.uint64(0)
            if r < 0:
                for j in range(64):  # the masks first: no store, no dependency between voxels
                    s = block_s[b, w * 64 + j]
                    n = block_n[b, w * 64 + j]
                    mh |= np.uint64(n > 0.0) << np.uint64(j)
                    mo |= np.uint64((s > 0.0) | (n > 0.0)) << np.uint64(j)
            else:  # a flushed block (rare): its values are the sums of both parts
                for j in range(64):
                    s64 = np.float64(block_s[b, w * 64 + j]) + hi[r, w * 64 + j, 0]
                    n64 = np.float64(block_n[b, w * 64 + j]) + hi[r, w * 64 + j, 1]
                    mh |= np.uint64(n64 > 0.0) << np.uint64(j)
                    mo |= np.uint64((s64 > 0.0) | (n64 > 0.0)) << np.uint64(j)
            observed[b, w] = mo
            hit[b, w] = mh
            if mo != 0:  # then the values of the words that hold some
                for j in range(64):
                    s_out[js] = block_s[b, w * 64 + j] + zero
                    js += (mo >> np.uint64(j)) & np.uint64(1)
            if mh != 0:
                for j in range(64):
                    n_out[jn] = block_n[b, w * 64 + j]
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


BlockChunk = tuple[
    NDArray[np.int32], NDArray[np.float64], NDArray[np.float32], NDArray[np.float32],
    NDArray[np.int64], NDArray[np.float64],
]  # fmt: skip
"""A run of a store's blocks: their index (k, 3), time (k,), the float32 parts of ``s`` and
``n`` of their 512 voxels each (k, 512) each, Morton order, C order: the packing reads
them at memory speed), each block's row of the float64 parts or -1 (k,), and those
parts (h, 512, 2: ``s``, ``n``)."""


class PackOutputs:
    """The packed values of all runs of blocks, one after the other (grown when short):
    ``s``, ``n`` and ``places`` (how many of each are filled), as the packing kernels
    (``_pack_blocks``, ``store._pack_store_blocks``) take them."""

    def __init__(self, size_hint: int) -> None:
        self.s = np.empty(max(size_hint, BLOCK_VOXELS) + BLOCK_VOXELS + 1, dtype=np.float32)
        self.n = np.empty(max(size_hint // 16, BLOCK_VOXELS) + BLOCK_VOXELS + 1, np.float32)
        self.places = np.zeros(2, dtype=np.int64)

    def grow(self) -> None:
        if self.places[0] + BLOCK_VOXELS >= self.s.shape[0]:
            self.s = np.concatenate([self.s, np.empty_like(self.s)])
        if self.places[1] + BLOCK_VOXELS >= self.n.shape[0]:
            self.n = np.concatenate([self.n, np.empty_like(self.n)])


PackedRun = tuple[
    NDArray[np.int32], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64],
    NDArray[np.uint64], NDArray[np.uint64], NDArray[np.int64],
]  # fmt: skip
"""A run of a store's blocks once packed into ``PackOutputs``: their index (k, 3), time
(k,), row of the float64 parts or -1 (k,), those parts (h, 512, 2), then the observed and
hit masks (k, 8) each and the counts of observed voxels and of voxels with a return
(k, 2) that the kernel found (their values lie in the outputs, run after run)."""


def pack_chunk(chunk: BlockChunk, out: PackOutputs) -> PackedRun:
    """One chunk of dense blocks packed (``_pack_blocks``), its float32 parts appended to
    ``out``."""
    block_s = np.ascontiguousarray(chunk[2], dtype=np.float32)
    block_n = np.ascontiguousarray(chunk[3], dtype=np.float32)
    hi_row = np.ascontiguousarray(chunk[4], dtype=np.int64)
    hi = np.ascontiguousarray(chunk[5], dtype=np.float64).reshape(-1, BLOCK_VOXELS, 2)
    used = block_s.shape[0]
    observed = np.empty((used, MASK_WORDS), dtype=np.uint64)
    hit = np.empty((used, MASK_WORDS), dtype=np.uint64)
    counts = np.empty((used, 2), dtype=np.int64)
    start = 0
    while (
        start := _pack_blocks(
            block_s,
            block_n,
            hi_row,
            hi,
            start,
            used,
            observed,
            hit,
            counts,
            out.s,
            out.n,
            out.places,
        )  # fmt: skip
    ) < used:
        out.grow()
    return chunk[0], chunk[1], chunk[4], chunk[5], observed, hit, counts


def _mask_bits(masks: NDArray[np.uint64]) -> NDArray[np.bool_]:
    """(k, 512) bools of (k, 8) masks: voxel i of a block is bit i."""
    flat = np.ascontiguousarray(masks, dtype=np.uint64).view(np.uint8)
    return np.unpackbits(flat, axis=1, bitorder="little").reshape(-1, BLOCK_VOXELS).astype(bool)


def pack_chunks(chunks: Iterable[BlockChunk], size_hint: int = 0) -> PackedBlocks:
    """The observed voxels of runs of a store's blocks (``BlockChunk``, taken one at a
    time), packed and sorted (a copy: the store may change afterwards): one read of the
    blocks' float32 parts, then the values copied in sorted block order
    (``packed_runs``). ``size_hint``: about how many voxels the chunks hold (the outputs
    grow when it is short)."""
    out = PackOutputs(size_hint + 1)
    runs = [pack_chunk(c, out) for c in chunks]  # one at a time: a chunk's buffer is reused
    return packed_runs(runs, out)


def packed_runs(runs: list[PackedRun], out: PackOutputs) -> PackedBlocks:
    """Packed blocks of runs packed into ``out`` (``PackedRun``): blocks without an observed
    voxel left out, sorted (the values copied in sorted block order unless the runs are
    already sorted); the float64 parts of the flushed blocks follow
    (``PackedBlocks.parts``)."""
    keep = [np.flatnonzero(r[6][:, 0] > 0) for r in runs]
    pairs = list(zip(runs, keep, strict=True))
    block_ijk = np.concatenate([np.zeros((0, 3), np.int32)] + [c[0][k] for c, k in pairs])
    order = np.argsort(sort_keys(block_ijk), kind="stable")
    in_order = bool(np.all(order[1:] > order[:-1]))  # runs already sorted: no copy
    no_mask = np.zeros((0, MASK_WORDS), np.uint64)
    observed = np.concatenate([no_mask] + [c[4][k] for c, k in pairs])
    hit = np.concatenate([no_mask] + [c[5][k] for c, k in pairs])
    block_t = np.concatenate([np.zeros(0)] + [c[1][k] for c, k in pairs])
    if not in_order:
        observed, hit, block_t = observed[order], hit[order], block_t[order]
    values = []
    for col in (0, 1):  # s, then n: each block's run in the outputs, in sorted order
        src = (out.s if col == 0 else out.n)[: out.places[col]]
        count = np.concatenate([np.zeros(0, np.int64)] + [c[6][:, col] for c in runs])
        kept = np.concatenate([np.zeros(0, np.int64)] + [c[6][:, 0] for c in runs]) > 0
        if in_order:  # the outputs hold the kept blocks' runs one after the other
            values.append((src, count[kept]))
            continue
        first = np.cumsum(count) - count
        run_length = count[kept][order]
        moved = np.empty(int(run_length.sum()), dtype=np.float32)
        _copy_runs(src, first[kept][order], run_length, moved)
        values.append((moved, run_length))
    (s, _), (n, hits) = values
    hit_block = np.flatnonzero(hits > 0).astype(np.int64)
    # the float64 parts: few blocks, gathered in sorted order
    hi_rows = np.concatenate([np.zeros(0, np.int64)] + [c[2][k] for c, k in pairs])
    hi_all = np.concatenate(
        [np.zeros((0, BLOCK_VOXELS, 2))]
        + [c[3].reshape(-1, BLOCK_VOXELS, 2)[c[2][k][c[2][k] >= 0]] for c, k in pairs]
    )
    has_hi = hi_rows[order] >= 0
    hi_block = np.flatnonzero(has_hi).astype(np.int64)
    hi_sorted = hi_all[np.flatnonzero(hi_rows >= 0).searchsorted(order[has_hi])]
    hi_s = hi_sorted[..., 0][_mask_bits(observed[hi_block])]
    hi_n = hi_sorted[..., 1][_mask_bits(hit[hi_block])]
    block_ijk = block_ijk if in_order else block_ijk[order]
    return PackedBlocks(
        block_ijk.astype(np.int32, copy=False), block_t, observed, s, hit_block,
        hit[hit_block], n, True, hi_block, hi_s, hi_n,
    )  # fmt: skip


def voxel_arrays_of(
    packed: PackedBlocks,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Index (M, 3), ``s``, ``n`` (``totals``) and time (the block's) of every voxel of
    ``packed`` (checked by ``packed_problem``), block by block: what
    ``store.BlockStore.assign`` takes (``assign_blocks`` sets the same store from the
    blocks, 5-10 times faster)."""
    rows = packed.block_ijk.shape[0]
    bits = np.unpackbits(
        np.ascontiguousarray(packed.observed).view(np.uint8), bitorder="little"
    ).reshape(rows, BLOCK_VOXELS)
    row, place = np.nonzero(bits)
    keys = row * BLOCK_VOXELS + place  # increasing: the order of ``s``
    s_all, n_all = totals(packed)
    n = np.zeros(keys.shape[0])
    if packed.hit_block.shape[0]:
        hit_bits = np.unpackbits(
            np.ascontiguousarray(packed.hit).view(np.uint8), bitorder="little"
        ).reshape(-1, BLOCK_VOXELS)
        hit_row, hit_place = np.nonzero(hit_bits)
        hit_keys = packed.hit_block[hit_row] * BLOCK_VOXELS + hit_place
        n[np.searchsorted(keys, hit_keys)] = n_all
    coords = np.array([local_coords(i) for i in range(BLOCK_VOXELS)], dtype=np.int64)
    ijk = packed.block_ijk.astype(np.int64)[row] * BLOCK_EDGE + coords[place]
    return ijk, s_all, n, packed.block_t[row]


__all__ = [
    "MASK_WORDS",
    "BlockChunk",
    "PackOutputs",
    "PackedBlocks",
    "PackedRun",
    "as_parts",
    "as_values",
    "block_key",
    "pack_chunk",
    "pack_chunks",
    "packed_problem",
    "packed_runs",
    "select_blocks",
    "totals",
    "voxel_arrays_of",
]
