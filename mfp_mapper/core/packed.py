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

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_EDGE,
    BLOCK_VOXELS,
    KEY_BITS,
    KEY_OFFSET,
    MAX_VOXEL_INDEX,
    block_key,
    local_coords,
)

MASK_WORDS = BLOCK_VOXELS // 64
"""uint64 words of a block's voxel mask: bit ``i % 64`` of word ``i // 64`` is voxel ``i``
(Morton place) of the block."""
MAX_BLOCK_INDEX = MAX_VOXEL_INDEX >> 3
"""Largest |block index| a store holds."""


@dataclass
class PackedBlocks:
    """Observed voxels block by block (see the module docstring).

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
    parts: bool = False
    """True: ``s`` and ``n`` are the float32 parts of the store's sums and ``hi_block``,
    ``hi_s``, ``hi_n`` its float64 parts (a voxel's value is the float64 sum of both, as
    ``shard.block_values`` adds them); False: ``s`` and ``n`` are the values (``hi_*``
    empty)."""
    hi_block: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """(F,) increasing rows of the blocks with a float64 part (flushed blocks)."""
    hi_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """The float64 part of ``s``: one per ``observed`` bit of those blocks, block by block."""
    hi_n: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    """The float64 part of ``n``: one per ``hit`` bit of those blocks (none for a block
    without a return)."""

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


@nb.njit(cache=True, nogil=True)
def _value_problem(values: NDArray[np.floating], limit: float) -> int:
    """0 when every value is finite, >= 0 and <= ``limit``; 1 for a negative, NaN or
    infinite value; 2 for one beyond ``limit`` (one pass without a branch, no temporary
    arrays: 4 to 6 times numpy's three reductions)."""
    bad = False
    beyond = False
    for v in values:
        bad |= (v < 0.0) | (v != v) | (v == math.inf)
        beyond |= v > limit
    return 1 if bad else (2 if beyond else 0)


@nb.njit(cache=True, nogil=True)
def _float32_problem(bits: NDArray[np.uint32]) -> int:
    """``_value_problem`` of float32 values (``bits``: their uint32 view): 1 for a
    negative, NaN or infinite one (-0 is 0), else 0. A max over the bits (vectorized:
    8 times the float loop): a float32 is finite and >= 0 exactly when its bits, -0's
    cleared, are below those of +inf."""
    top = np.uint32(0)
    for b in bits:
        top = max(top, b if b != np.uint32(0x80000000) else np.uint32(0))
    return 1 if top >= np.uint32(0x7F800000) else 0


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
    counts = np.bitwise_count(p.observed).sum(axis=1, dtype=np.int64)
    if p.s.shape != (int(counts.sum()),):
        return f"s holds {p.s.shape} values, the observed masks {int(counts.sum())}"
    if h and (int(p.hit_block[0]) < 0 or int(p.hit_block[-1]) >= b):
        return f"hit_block rows outside [0, {b})"
    if h > 1 and not np.all(np.diff(p.hit_block) > 0):
        return "hit_block is not increasing"
    if np.any(p.hit & ~p.observed[p.hit_block]):
        return "a voxel with a return is not marked observed"
    hit_counts = np.bitwise_count(p.hit).sum(axis=1, dtype=np.int64)
    if p.n.shape != (int(hit_counts.sum()),):
        return f"n holds {p.n.shape} values, the hit masks {int(hit_counts.sum())}"
    problem = _hi_problem(p, counts, hit_counts)
    if problem:
        return problem
    f32_max = float(np.finfo(np.float32).max)
    for key, arr in (("s", p.s), ("n", p.n), ("hi_s", p.hi_s), ("hi_n", p.hi_n)):
        if arr.dtype.kind != "f":
            return f"{key} holds {arr.dtype} values (floats expected)"
        if arr.dtype == np.float32:
            code = _float32_problem(np.ascontiguousarray(arr).view(np.uint32))
        else:
            code = _value_problem(arr, f32_max if key in ("s", "n") else math.inf)
        if code == 1:
            return f"{key} holds negative, NaN or infinite values"
        if code == 2:
            return f"{key} holds values beyond float32's range (the store's)"
    return None


def _hi_problem(
    p: PackedBlocks, counts: NDArray[np.int64], hit_counts: NDArray[np.int64]
) -> str | None:
    """The float64 parts against the blocks (``counts``, ``hit_counts``: bits of each
    block's observed mask and of each hit mask)."""
    f = p.hi_block.shape[0]
    if not p.parts:
        if f or p.hi_s.shape[0] or p.hi_n.shape[0]:
            return "float64 parts (hi_block, hi_s, hi_n) in blocks that hold their values"
        return None
    if p.s.dtype != np.float32 or p.n.dtype != np.float32:
        return f"s and n hold float32 parts, got {p.s.dtype} and {p.n.dtype}"
    b = p.block_ijk.shape[0]
    if p.hi_block.shape != (f,) or p.hi_s.ndim != 1 or p.hi_n.ndim != 1:
        return "float64 parts need hi_block (F,), hi_s and hi_n one-dimensional"
    if f and (int(p.hi_block[0]) < 0 or int(p.hi_block[-1]) >= b):
        return f"hi_block rows outside [0, {b})"
    if f > 1 and not np.all(np.diff(p.hi_block) > 0):
        return "hi_block is not increasing"
    want_s = int(counts[p.hi_block].sum())
    if p.hi_s.shape != (want_s,):
        return f"hi_s holds {p.hi_s.shape} values, the observed masks of hi_block {want_s}"
    rows = hit_row_of(p)[p.hi_block]
    want_n = int(hit_counts[rows[rows >= 0]].sum())
    if p.hi_n.shape != (want_n,):
        return f"hi_n holds {p.hi_n.shape} values, the hit masks of hi_block {want_n}"
    return None


def hit_row_of(p: PackedBlocks) -> NDArray[np.int64]:
    """Each block's row of ``hit`` (B,), -1 where it holds no return."""
    rows = np.full(p.block_ijk.shape[0], -1, dtype=np.int64)
    rows[p.hit_block] = np.arange(p.hit_block.shape[0])
    return rows


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


class _Outputs:
    """The packed values of all chunks, one after the other (grown when short)."""

    def __init__(self, size_hint: int) -> None:
        self.s = np.empty(max(size_hint, BLOCK_VOXELS) + BLOCK_VOXELS + 1, dtype=np.float32)
        self.n = np.empty(max(size_hint // 16, BLOCK_VOXELS) + BLOCK_VOXELS + 1, np.float32)
        self.places = np.zeros(2, dtype=np.int64)

    def grow(self) -> None:
        if self.places[0] + BLOCK_VOXELS >= self.s.shape[0]:
            self.s = np.concatenate([self.s, np.empty_like(self.s)])
        if self.places[1] + BLOCK_VOXELS >= self.n.shape[0]:
            self.n = np.concatenate([self.n, np.empty_like(self.n)])


def _pack_chunk(
    chunk: BlockChunk, out: _Outputs
) -> tuple[NDArray[np.uint64], NDArray[np.uint64], NDArray[np.int64]]:
    """Masks and counts of one chunk of blocks, its float32 parts appended to ``out``
    (``_pack_blocks``)."""
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
    return observed, hit, counts


def _mask_bits(masks: NDArray[np.uint64]) -> NDArray[np.bool_]:
    """(k, 512) bools of (k, 8) masks: voxel i of a block is bit i."""
    flat = np.ascontiguousarray(masks, dtype=np.uint64).view(np.uint8)
    return np.unpackbits(flat, axis=1, bitorder="little").reshape(-1, BLOCK_VOXELS).astype(bool)


def pack_chunks(chunks: Iterable[BlockChunk], size_hint: int = 0) -> PackedBlocks:
    """The observed voxels of runs of a store's blocks (``BlockChunk``, taken one at a
    time), packed and sorted (a copy: the store may change afterwards): one read of the
    blocks' float32 parts,
    then the values copied in sorted block order; the float64 parts of the flushed blocks
    follow (``PackedBlocks.parts``). Blocks without an observed voxel are left out.
    ``size_hint``: about how many voxels the chunks hold (the outputs grow when it is
    short)."""
    out = _Outputs(size_hint + 1)
    parts, runs = [], []
    for c in chunks:  # one at a time: a chunk's statistics may be reused by the next
        parts.append(_pack_chunk(c, out))
        runs.append((c[0], c[1], c[4], c[5]))  # index, time, float64 rows and parts
    keep = [np.flatnonzero(p[2][:, 0] > 0) for p in parts]
    block_ijk = np.concatenate(
        [np.zeros((0, 3), np.int32)] + [c[0][r] for c, r in zip(runs, keep, strict=True)]
    )
    order = np.argsort(sort_keys(block_ijk), kind="stable")
    in_order = bool(np.all(order[1:] > order[:-1]))  # chunks already sorted: no copy
    pairs = list(zip(parts, keep, strict=True))
    no_mask = np.zeros((0, MASK_WORDS), np.uint64)
    observed = np.concatenate([no_mask] + [p[0][r] for p, r in pairs])[order]
    hit = np.concatenate([no_mask] + [p[1][r] for p, r in pairs])[order]
    block_t = np.concatenate([np.zeros(0)] + [c[1][r] for c, r in zip(runs, keep, strict=True)])
    block_t = block_t[order]
    values = []
    for col in (0, 1):  # s, then n: each block's run in the outputs, in sorted order
        src = (out.s if col == 0 else out.n)[: out.places[col]]
        count = np.concatenate([np.zeros(0, np.int64)] + [p[2][:, col] for p in parts])
        first = np.cumsum(count) - count
        kept = np.concatenate([np.zeros(0, np.int64)] + [p[2][:, 0] for p in parts]) > 0
        run_length = count[kept][order]
        if in_order:  # the outputs hold the kept blocks' runs one after the other
            values.append((src, run_length))
            continue
        moved = np.empty(int(run_length.sum()), dtype=np.float32)
        _copy_runs(src, first[kept][order], run_length, moved)
        values.append((moved, run_length))
    (s, _), (n, hits) = values
    hit_block = np.flatnonzero(hits > 0).astype(np.int64)
    # the float64 parts: few blocks, gathered in sorted order
    hi_rows = np.concatenate(
        [np.zeros(0, np.int64)] + [c[2][r] for c, r in zip(runs, keep, strict=True)]
    )
    hi_all = np.concatenate(
        [np.zeros((0, BLOCK_VOXELS, 2))]
        + [
            c[3].reshape(-1, BLOCK_VOXELS, 2)[c[2][r][c[2][r] >= 0]]
            for c, r in zip(runs, keep, strict=True)
        ]
    )
    has_hi = hi_rows[order] >= 0
    hi_block = np.flatnonzero(has_hi).astype(np.int64)
    hi_sorted = hi_all[np.flatnonzero(hi_rows >= 0).searchsorted(order[has_hi])]
    hi_s = hi_sorted[..., 0][_mask_bits(observed[hi_block])]
    hi_n = hi_sorted[..., 1][_mask_bits(hit[hi_block])]
    return PackedBlocks(
        block_ijk[order].astype(np.int32, copy=False), block_t, observed, s, hit_block,
        hit[hit_block], n, True, hi_block, hi_s, hi_n,
    )  # fmt: skip


def compact(values: NDArray[np.floating]) -> NDArray[np.floating]:
    """float32 values as they are; float64 ones as float32 when every one survives the
    round trip, else as they are."""
    if values.dtype == np.float32:
        return values
    small = values.astype(np.float32)
    return small if np.array_equal(small, values) else values


def ranges(lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.int64]:
    """The indices lo[0]..hi[0]-1, lo[1]..hi[1]-1, ... in one array."""
    lengths = hi - lo
    heads = np.cumsum(lengths) - lengths
    return np.arange(int(lengths.sum()), dtype=np.int64) + np.repeat(lo - heads, lengths)


def hi_starts(p: PackedBlocks) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Where each block of ``hi_block`` begins in ``hi_s`` and in ``hi_n`` (F + 1 each)."""
    counts = np.bitwise_count(p.observed[p.hi_block]).sum(axis=1, dtype=np.int64)
    rows = hit_row_of(p)[p.hi_block]
    hit_counts = np.zeros(p.hi_block.shape[0], dtype=np.int64)
    if rows.size:
        hit_counts[rows >= 0] = np.bitwise_count(p.hit[rows[rows >= 0]]).sum(1, dtype=np.int64)
    return (
        np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        np.concatenate([[0], np.cumsum(hit_counts)]).astype(np.int64),
    )


def totals(p: PackedBlocks) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``s`` and ``n`` of every voxel (float64): the values, or (``parts``) the float32
    part plus the float64 one, added as the store adds them (``shard.block_values``)."""
    s = np.add(p.s, 0.0, dtype=np.float64)  # -0 as +0
    n = np.array(p.n, dtype=np.float64)
    if not p.hi_block.shape[0]:
        return s, n
    s_start, n_start = voxel_starts(p.observed), voxel_starts(p.hit)
    s[ranges(s_start[p.hi_block], s_start[p.hi_block + 1])] += p.hi_s
    rows = hit_row_of(p)[p.hi_block]
    rows = rows[rows >= 0]
    n[ranges(n_start[rows], n_start[rows + 1])] += p.hi_n
    return s, n


def as_values(p: PackedBlocks) -> PackedBlocks:
    """``p`` with its values in ``s`` and ``n`` (``totals``; float32 where every value
    survives that: ``compact``), no float64 parts."""
    if not p.parts:
        return p
    s, n = totals(p)
    return PackedBlocks(
        p.block_ijk, p.block_t, p.observed, compact(s), p.hit_block, p.hit, compact(n)
    )


def as_parts(p: PackedBlocks) -> PackedBlocks:
    """``p`` as float32 and float64 parts (``PackedBlocks.parts``), the same values: a
    block holding a value that is not a float32 keeps all its values in a float64 part
    (its float32 parts 0)."""
    if p.parts:
        return p
    s, n = np.asarray(p.s), np.asarray(p.n)
    if s.dtype == np.float32 and n.dtype == np.float32:
        return PackedBlocks(p.block_ijk, p.block_t, p.observed, s, p.hit_block, p.hit, n, True)
    s32, n32 = s.astype(np.float32), n.astype(np.float32)
    bad_s, bad_n = s32 != s, n32 != n
    if not (bad_s.any() or bad_n.any()):
        return PackedBlocks(p.block_ijk, p.block_t, p.observed, s32, p.hit_block, p.hit, n32, True)
    counts = np.bitwise_count(p.observed).sum(axis=1, dtype=np.int64)
    hit_counts = np.bitwise_count(p.hit).sum(axis=1, dtype=np.int64)
    rows_s = np.repeat(np.arange(p.block_ijk.shape[0]), counts)
    rows_n = np.repeat(p.hit_block, hit_counts)
    flushed = np.zeros(p.block_ijk.shape[0], dtype=bool)
    flushed[rows_s[bad_s]] = True
    flushed[rows_n[bad_n]] = True
    in_s, in_n = flushed[rows_s], flushed[rows_n]
    s32[in_s] = 0.0
    n32[in_n] = 0.0
    return PackedBlocks(
        p.block_ijk, p.block_t, p.observed, s32, p.hit_block, p.hit, n32, True,
        np.flatnonzero(flushed).astype(np.int64), s[in_s].astype(np.float64),
        n[in_n].astype(np.float64),
    )  # fmt: skip


def select_blocks(
    p: PackedBlocks,
    rows: NDArray[np.int64],
    s_start: NDArray[np.int64] | None = None,
    n_start: NDArray[np.int64] | None = None,
) -> PackedBlocks:
    """The blocks ``rows`` of ``p`` in that order (unique; arrays of ``p`` may be memory
    maps: only the rows' values are read). ``s_start``, ``n_start``: ``voxel_starts`` of
    ``p.observed`` and ``p.hit`` when known."""
    rows = np.asarray(rows, dtype=np.int64)
    s_start = voxel_starts(np.asarray(p.observed)) if s_start is None else s_start
    n_start = voxel_starts(np.asarray(p.hit)) if n_start is None else n_start
    hit_of = hit_row_of(p)[rows]
    has = hit_of >= 0
    hrows = hit_of[has]
    out = PackedBlocks(
        p.block_ijk[rows], p.block_t[rows], p.observed[rows],
        p.s[ranges(s_start[rows], s_start[rows + 1])], np.flatnonzero(has).astype(np.int64),
        p.hit[hrows], p.n[ranges(n_start[hrows], n_start[hrows + 1])], p.parts,
    )  # fmt: skip
    if p.hi_block.shape[0]:
        hi_of = np.full(p.block_ijk.shape[0], -1, dtype=np.int64)
        hi_of[p.hi_block] = np.arange(p.hi_block.shape[0])
        picked = hi_of[rows]
        new_rows = np.flatnonzero(picked >= 0)
        fs, fn = hi_starts(p)
        src = picked[new_rows]
        out.hi_block = new_rows.astype(np.int64)
        out.hi_s = np.asarray(p.hi_s)[ranges(fs[src], fs[src + 1])]
        out.hi_n = np.asarray(p.hi_n)[ranges(fn[src], fn[src + 1])]
    return out


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
    "PackedBlocks",
    "as_parts",
    "as_values",
    "block_key",
    "pack_chunks",
    "packed_problem",
    "select_blocks",
    "totals",
    "voxel_arrays_of",
]
