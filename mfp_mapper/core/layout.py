"""The store's geometry and the arrays that leave it, in numpy alone: block and key
sizes, voxel lists (``VoxelArrays``) and packed blocks (``PackedBlocks``, what map files
hold) with their checks. No numba: map files and a query of map-file points import this
module, not the compiled store (``blocks``, ``store`` and ``packed`` re-export its names).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

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


def _bit_count_swar(words: NDArray[np.unsignedinteger]) -> NDArray[np.uint8]:
    """Set bits of each uint64 word, by the classic SWAR sums (numpy before 2.0)."""
    x = np.asarray(words, dtype=np.uint64)
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return ((x * np.uint64(0x0101010101010101)) >> np.uint64(56)).astype(np.uint8)


bit_count = getattr(np, "bitwise_count", _bit_count_swar)
"""Set bits of each word: ``np.bitwise_count`` (numpy 2.0), ``_bit_count_swar`` before
(Ubuntu 24.04's numpy 1.26, what a Jazzy workspace runs)."""


def sort_keys(block_ijk: NDArray[np.integer]) -> NDArray[np.int64]:
    """One int64 per block index whose order is (x, y, z) lexicographic (``block_key``)."""
    b = np.asarray(block_ijk, dtype=np.int64) + KEY_OFFSET
    return (b[:, 0] << (2 * KEY_BITS)) | (b[:, 1] << KEY_BITS) | b[:, 2]


_LANES = np.uint64(0x00FF00FF00FF00FF)


def block_counts(mask: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Set bits of each row of (B, 8) masks: the eight byte counts of a row, read as one
    uint64, summed in 16-bit lanes (5 times as fast as ``sum(axis=1)``, 0.7 against 3.8
    ms for 173 k blocks: numpy reduces a short inner axis slowly)."""
    counts = np.ascontiguousarray(bit_count(mask), dtype=np.uint8)
    if counts.ndim != 2 or counts.shape[1] != MASK_WORDS:
        return counts.sum(axis=-1, dtype=np.int64)
    x = counts.reshape(-1).view(np.uint64)  # each byte <= 64: pairs fit 16 bits
    x = (x & _LANES) + ((x >> np.uint64(8)) & _LANES)
    x *= np.uint64(0x0001000100010001)  # the four lanes summed in the top one (<= 512)
    return (x >> np.uint64(48)).view(np.int64)


def mask_words(mask: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Nonzero words of each row of (B, 8) masks (``count_nonzero(axis=1)``, as
    ``block_counts`` sums: the eight flags of a row read as one uint64)."""
    flags = np.ascontiguousarray(mask != 0)
    if flags.ndim != 2 or flags.shape[1] != MASK_WORDS:
        return flags.sum(axis=-1, dtype=np.int64)
    x = flags.view(np.uint8).reshape(-1).view(np.uint64)
    return ((x * np.uint64(0x0101010101010101)) >> np.uint64(56)).view(np.int64)


def voxel_starts(mask: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Index of each block's first value (B + 1 entries: the last is the total)."""
    counts = block_counts(mask)
    out = np.zeros(mask.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def packed_problem(p: PackedBlocks, s_checked: bool = False) -> str | None:
    """What is wrong with packed blocks (shapes, order, masks, values), or None;
    ``s_checked``: the values of float32 ``s`` were found finite and >= +0 already (a map
    file's reader finds that as it reads them, ``blockfile.read_all``)."""
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
    counts = block_counts(p.observed)
    if p.s.shape != (int(counts.sum()),):
        return f"s holds {p.s.shape} values, the observed masks {int(counts.sum())}"
    if h and (int(p.hit_block[0]) < 0 or int(p.hit_block[-1]) >= b):
        return f"hit_block rows outside [0, {b})"
    if h > 1 and not np.all(np.diff(p.hit_block) > 0):
        return "hit_block is not increasing"
    if np.any(p.hit & ~p.observed[p.hit_block]):
        return "a voxel with a return is not marked observed"
    hit_counts = block_counts(p.hit)
    if p.n.shape != (int(hit_counts.sum()),):
        return f"n holds {p.n.shape} values, the hit masks {int(hit_counts.sum())}"
    problem = _hi_problem(p, counts, hit_counts)
    if problem:
        return problem
    f32_max = float(np.finfo(np.float32).max)
    for key, arr in (("s", p.s), ("n", p.n), ("hi_s", p.hi_s), ("hi_n", p.hi_n)):
        if key == "s" and s_checked and arr.dtype == np.float32:
            continue
        if arr.dtype.kind != "f":
            return f"{key} holds {arr.dtype} values (floats expected)"
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


def _value_problem(values: NDArray[np.floating], limit: float) -> int:
    """0 when every value is finite, >= 0 and <= ``limit``; 1 for a negative, NaN or
    infinite value; 2 for one beyond ``limit``. float32 values first by the largest of
    their bits, one pass (every bit pattern above +inf's or with the sign set is bad, but
    -0 is 0, which only the slower passes tell apart)."""
    if values.dtype == np.float32 and values.size:
        bits = np.ascontiguousarray(values).view(np.uint32)
        if int(bits.max()) < 0x7F800000:  # all finite, >= +0: only the limit is left
            return 2 if float(values.max()) > limit else 0
    if not (np.isfinite(values).all() and values.min(initial=0.0) >= 0):
        return 1
    return 2 if values.max(initial=0.0) > limit else 0


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
    counts = block_counts(p.observed[p.hi_block])
    rows = hit_row_of(p)[p.hi_block]
    hit_counts = np.zeros(p.hi_block.shape[0], dtype=np.int64)
    if rows.size:
        hit_counts[rows >= 0] = block_counts(p.hit[rows[rows >= 0]])
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
    counts = block_counts(p.observed)
    hit_counts = block_counts(p.hit)
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
