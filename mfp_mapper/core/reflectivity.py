"""The reflectivity field (Appendix B, Eq. B1-B3): per voxel, a histogram of return intensity.

A return whose intensity falls in bin ``j`` adds one to ``n_jK`` of the voxel ``K`` holding
it (the voxel whose ``n`` it adds to); the most likely reflectivity histogram of ``K`` is
``n_jK / sum_i n_iK`` (Eq. B3, independent of the extinction). Only a few percent of the
observed voxels hold returns, so the histograms live in a sparse table of their own beside
the block store (``ReflectivityTable``): rows sorted by block and by the voxel's place in
its block, each row only its ``J`` float32 counts and a 2-byte place.

Decay (Eq. 28-30) scales the counts as it scales ``n``. All rows' counts refer to one time
``t``: a return at ``stamp`` adds ``exp((stamp - t) / T)``, and the counts at any time
``t'`` are the held ones times ``exp(-(t' - t) / T)``. ``t`` moves to a later scan's stamp,
scaling every count once, only when that weight would pass ``exp(REFERENCE_DECAY_TIMES)``:
a scan costs what its returns cost, not a pass over the table (which every later scan
made before). So a row is the exact decayed sum of its returns, whatever the order of the
scans, and its total equals the voxel's ``n`` read at the same time (up to float32
rounding) when every return had an intensity. Reads and exports bring the counts to the
latest stamp added (rounded to float32, as a map file holds them), then to the time asked.
Tables are exported at that latest stamp (``t_last`` for every row; files with a time per
row load too) and merge exactly (``merge_reflectivity``): every row brought to the latest
time of its inputs, then added.

Rows follow their voxels: blocks evicted by the memory bound (``max_voxels``, ``keep_radius``)
and voxels cleared (``clear_box``) drop their rows (``Mapper``). One case is not followed: a
ray whose return a shard's walk cut to keep one scan within its block budget
(``traversal.cut_to_blocks``, a scan far beyond ``max_voxels``) keeps its histogram count.

The core knows nothing of sensors: it takes intensity values and bin edges
(``ReflectivityBins``: a label naming the field they came from, and the edges). The
sensing layer chooses the edges per field (``sensing.reflectivity``); maps merge only when
label and edges are equal. The bins and the table as arrays (what map files hold and a query
of a map file reads) live in ``core.reflectivity_arrays``, numba-free, re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.blocks import (
    BLOCK_BITS,
    BLOCK_EDGE,
    EMPTY_KEY,
    KEY_BITS,
    KEY_OFFSET,
    MAX_VOXEL_INDEX,
    block_key,
    find_block,
    insert_block,
)
from mfp_mapper.core.reflectivity_arrays import (  # noqa: F401 (numba-free, re-exported)
    ARRAY_KEYS,
    MAX_BINS,
    ROW_KEYS,
    FloatArray,
    ReflectivityArrays,
    ReflectivityBins,
    block_order,
    concatenate_tables,
    from_map_arrays,
    mean_value,
    most_likely_bin,
    row_keys,
    rows_within,
    select_rows,
    smoothed,
    table_problem,
    to_map_arrays,
)


class ScanReflectivity(NamedTuple):
    """The intensity of each point of a scan (N,) and how to bin it."""

    values: ArrayLike
    bins: ReflectivityBins


def _voxels_of(
    block_keys: NDArray[np.int64], block_start: NDArray[np.int32], local: NDArray[np.uint16]
) -> NDArray[np.int32]:
    """The voxel index (K, 3) of every row (``row_keys`` inverted)."""
    keys = np.repeat(block_keys, np.diff(block_start))
    loc = local.astype(np.int64)
    field, m = (1 << KEY_BITS) - 1, BLOCK_EDGE - 1
    out = np.empty((loc.shape[0], 3), dtype=np.int32)
    for axis in range(3):
        block = ((keys >> ((2 - axis) * KEY_BITS)) & field) - KEY_OFFSET
        out[:, axis] = (block << BLOCK_BITS) | ((loc >> ((2 - axis) * BLOCK_BITS)) & m)
    return out


@nb.njit(cache=True, nogil=True)
def _fill_hash(
    block_keys: NDArray[np.int64], hash_keys: NDArray[np.int64], hash_blocks: NDArray[np.int32]
) -> None:
    """Index the blocks by key (``blocks.insert_block``; the tables start empty)."""
    for b in range(block_keys.shape[0]):
        insert_block(hash_keys, hash_blocks, block_keys[b], b)


@nb.njit(inline="always", cache=True)
def _voxel_key(x: int, y: int, z: int) -> tuple[int, int]:
    """``row_keys`` of one voxel: its block key (-1 beyond the map's range) and place."""
    if max(abs(x), abs(y), abs(z)) > MAX_VOXEL_INDEX:
        return -1, 0
    m = BLOCK_EDGE - 1
    place = ((x & m) << (2 * BLOCK_BITS)) | ((y & m) << BLOCK_BITS) | (z & m)
    return block_key(x >> BLOCK_BITS, y >> BLOCK_BITS, z >> BLOCK_BITS), place


@nb.njit(inline="always", cache=True)
def _row_in_block(
    block_start: NDArray[np.int32], local: NDArray[np.uint16], block: int, place: int
) -> int:
    """The row of ``place`` in ``block``, or -1."""
    lo, hi = block_start[block], block_start[block + 1]
    end = hi
    while lo < hi:
        mid = (lo + hi) >> 1
        if local[mid] < place:
            lo = mid + 1
        else:
            hi = mid
    return lo if lo < end and local[lo] == place else -1


@nb.njit(cache=True, nogil=True)
def _locate(
    block_keys: NDArray[np.int64],
    hash_keys: NDArray[np.int64],
    hash_blocks: NDArray[np.int32],
    block_start: NDArray[np.int32],
    local: NDArray[np.uint16],
    ijk: NDArray[np.int64],
) -> NDArray[np.int64]:
    """The row of each voxel, -1 where there is none."""
    out = np.full(ijk.shape[0], -1, dtype=np.int64)
    last_key, block = -1, -1
    for j in range(ijk.shape[0]):
        key, place = _voxel_key(ijk[j, 0], ijk[j, 1], ijk[j, 2])
        if key < 0:
            continue
        if key != last_key:  # voxels often come in runs of one block
            block = find_block(hash_keys, hash_blocks, key)
            last_key = key
        if block >= 0:
            out[j] = _row_in_block(block_start, local, block, place)
    return out


@nb.njit(cache=True, nogil=True)
def _add_found(
    block_keys: NDArray[np.int64],
    hash_keys: NDArray[np.int64],
    hash_blocks: NDArray[np.int32],
    block_start: NDArray[np.int32],
    local: NDArray[np.uint16],
    counts: NDArray[np.float32],
    ijk: NDArray[np.int64],
    bins: NDArray[np.int64],
    w: float,
) -> NDArray[np.int64]:
    """Add ``w`` to the bin of each return whose voxel has a row; returns the returns
    (indices) whose voxel has none (bin < 0 or beyond the map's range: neither)."""
    pending = np.empty(ijk.shape[0], dtype=np.int64)
    count = 0
    last_key, block = -1, -1
    for j in range(ijk.shape[0]):
        if bins[j] < 0:
            continue
        key, place = _voxel_key(ijk[j, 0], ijk[j, 1], ijk[j, 2])
        if key < 0:
            continue
        if key != last_key:
            block = find_block(hash_keys, hash_blocks, key)
            last_key = key
        row = _row_in_block(block_start, local, block, place) if block >= 0 else -1
        if row >= 0:
            counts[row, bins[j]] += w
        else:
            pending[count] = j
            count += 1
    return pending[:count]


_SPAN_BITS = 16
"""Bits of a block's offset from the scan's lowest block, per axis, in ``_packed``."""


@nb.njit(cache=True, nogil=True)
def _packed(
    ijk: NDArray[np.int64], bins: NDArray[np.int64], picked: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The picked returns as one int64 each that sorts like (block key, place, bin): the
    block's offset from the lowest block (``_SPAN_BITS`` per axis), place (9 bits), bin
    (6 bits); and the lowest block. Empty when the blocks span more than that."""
    lo = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
    for j in picked:
        for a in range(3):
            b = ijk[j, a] >> BLOCK_BITS
            lo[a] = min(lo[a], b)
            hi[a] = max(hi[a], b)
    out = np.empty(picked.shape[0], dtype=np.int64)
    if picked.shape[0] and np.max(hi - lo) >= (1 << _SPAN_BITS):
        return out[:0], lo
    m = BLOCK_EDGE - 1
    for i in range(picked.shape[0]):
        j = picked[i]
        x, y, z = ijk[j, 0], ijk[j, 1], ijk[j, 2]
        place = ((x & m) << (2 * BLOCK_BITS)) | ((y & m) << BLOCK_BITS) | (z & m)
        out[i] = (
            (((x >> BLOCK_BITS) - lo[0]) << (2 * _SPAN_BITS + 15))
            | (((y >> BLOCK_BITS) - lo[1]) << (_SPAN_BITS + 15))
            | (((z >> BLOCK_BITS) - lo[2]) << 15)
            | (place << 6)
            | bins[j]
        )
    return out, lo


@nb.njit(cache=True, nogil=True)
def _unpacked(
    packed: NDArray[np.int64], lo: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Block keys, places and bins of ``_packed`` values."""
    n = packed.shape[0]
    keys, places, bins = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    span = (1 << _SPAN_BITS) - 1
    for i in range(n):
        v = packed[i]
        keys[i] = block_key(
            lo[0] + ((v >> (2 * _SPAN_BITS + 15)) & span),
            lo[1] + ((v >> (_SPAN_BITS + 15)) & span),
            lo[2] + ((v >> 15) & span),
        )
        places[i] = (v >> 6) & 511
        bins[i] = v & 63
    return keys, places, bins


@nb.njit(cache=True, nogil=True)
def _merge_new(
    block_keys: NDArray[np.int64],
    hash_keys: NDArray[np.int64],
    hash_blocks: NDArray[np.int32],
    block_start: NDArray[np.int32],
    local: NDArray[np.uint16],
    counts: NDArray[np.float32],
    keys: NDArray[np.int64],
    places: NDArray[np.int64],
    bins: NDArray[np.int64],
    w: float,
) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.uint16], NDArray[np.float32]]:
    """The table with rows for the voxels (``keys``, ``places``: sorted by both, repeats
    allowed, none of them in the table), each return adding ``w`` to its bin."""
    old_blocks = block_keys.shape[0]
    new_rows = 0
    new_blocks = 0
    for j in range(keys.shape[0]):
        if j == 0 or keys[j] != keys[j - 1]:
            new_rows += 1
            if find_block(hash_keys, hash_blocks, keys[j]) < 0:
                new_blocks += 1
        elif places[j] != places[j - 1]:
            new_rows += 1
    out_keys = np.empty(old_blocks + new_blocks, dtype=np.int64)
    out_start = np.empty(old_blocks + new_blocks + 1, dtype=np.int32)
    out_local = np.empty(local.shape[0] + new_rows, dtype=np.uint16)
    out_counts = np.empty((local.shape[0] + new_rows, counts.shape[1]), dtype=np.float32)
    ob, j, r, b = 0, 0, 0, 0
    while ob < old_blocks or j < keys.shape[0]:
        if j >= keys.shape[0] or (ob < old_blocks and block_keys[ob] < keys[j]):
            lo, hi = block_start[ob], block_start[ob + 1]  # an old block, as it is
            out_keys[b], out_start[b] = block_keys[ob], r
            out_local[r : r + hi - lo] = local[lo:hi]
            out_counts[r : r + hi - lo] = counts[lo:hi]
            r += hi - lo
            ob += 1
            b += 1
            continue
        key = keys[j]
        out_keys[b], out_start[b] = key, r
        lo = hi = 0
        if ob < old_blocks and block_keys[ob] == key:
            lo, hi = block_start[ob], block_start[ob + 1]
            ob += 1
        while lo < hi or (j < keys.shape[0] and keys[j] == key):
            if j >= keys.shape[0] or keys[j] != key or (lo < hi and local[lo] < places[j]):
                out_local[r] = local[lo]
                out_counts[r] = counts[lo]
                lo += 1
            else:
                place = places[j]
                out_local[r] = place
                out_counts[r] = 0.0
                while j < keys.shape[0] and keys[j] == key and places[j] == place:
                    out_counts[r, bins[j]] += w
                    j += 1
            r += 1
        b += 1
    out_start[b] = r
    return out_keys, out_start, out_local, out_counts


@nb.njit(cache=True, nogil=True)
def _merge_rows(
    a_keys: NDArray[np.int64],
    a_start: NDArray[np.int32],
    a_local: NDArray[np.uint16],
    a_counts: NDArray[np.float32],
    b_keys: NDArray[np.int64],
    b_start: NDArray[np.int32],
    b_local: NDArray[np.uint16],
    b_counts: NDArray[np.float32],
) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.uint16], NDArray[np.float32]]:
    """The rows of two tables (each sorted by block key and place; no voxel in both) as
    one, sorted likewise."""
    blocks = 0
    i = j = 0
    while i < a_keys.shape[0] or j < b_keys.shape[0]:
        if j >= b_keys.shape[0] or (i < a_keys.shape[0] and a_keys[i] < b_keys[j]):
            i += 1
        elif i >= a_keys.shape[0] or b_keys[j] < a_keys[i]:
            j += 1
        else:
            i += 1
            j += 1
        blocks += 1
    rows = a_local.shape[0] + b_local.shape[0]
    out_keys = np.empty(blocks, dtype=np.int64)
    out_start = np.empty(blocks + 1, dtype=np.int32)
    out_local = np.empty(rows, dtype=np.uint16)
    out_counts = np.empty((rows, a_counts.shape[1]), dtype=np.float32)
    i = j = r = 0
    for b in range(blocks):
        take_a = j >= b_keys.shape[0] or (i < a_keys.shape[0] and a_keys[i] <= b_keys[j])
        take_b = i >= a_keys.shape[0] or (j < b_keys.shape[0] and b_keys[j] <= a_keys[i])
        out_keys[b] = a_keys[i] if take_a else b_keys[j]
        out_start[b] = r
        lo, hi = (a_start[i], a_start[i + 1]) if take_a else (0, 0)
        blo, bhi = (b_start[j], b_start[j + 1]) if take_b else (0, 0)
        while lo < hi or blo < bhi:
            if blo >= bhi or (lo < hi and a_local[lo] < b_local[blo]):
                out_local[r] = a_local[lo]
                out_counts[r] = a_counts[lo]
                lo += 1
            else:
                out_local[r] = b_local[blo]
                out_counts[r] = b_counts[blo]
                blo += 1
            r += 1
        i += take_a
        j += take_b
    out_start[blocks] = r
    return out_keys, out_start, out_local, out_counts


class _Rows:
    """One sorted table of rows (``ReflectivityTable``): per block its key (int64) and
    first row (int32), per row its place (uint16) and ``J`` float32 counts, the blocks
    indexed by an open-addressing hash of their keys (at most half the slots full)."""

    def __init__(
        self,
        block_keys: NDArray[np.int64],
        block_start: NDArray[np.int32],
        local: NDArray[np.uint16],
        counts: NDArray[np.float32],
    ) -> None:
        self.block_keys, self.block_start = block_keys, block_start
        self.local, self.counts = local, counts
        slots = 1 << max(int(2 * block_keys.shape[0] - 1).bit_length(), 4)
        self.hash_keys = np.full(slots, EMPTY_KEY, dtype=np.int64)
        self.hash_blocks = np.zeros(slots, dtype=np.int32)
        _fill_hash(block_keys, self.hash_keys, self.hash_blocks)

    @classmethod
    def empty(cls, bins: int) -> _Rows:
        return cls(
            np.zeros(0, dtype=np.int64),
            np.zeros(1, dtype=np.int32),
            np.zeros(0, dtype=np.uint16),
            np.zeros((0, bins), dtype=np.float32),
        )

    def __len__(self) -> int:
        return int(self.local.shape[0])

    def blocks(
        self,
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int32], NDArray[np.int32]]:
        """The block arrays the kernels take (keys, hash, first rows)."""
        return self.block_keys, self.hash_keys, self.hash_blocks, self.block_start

    def locate(self, ijk: NDArray[np.int64]) -> NDArray[np.int64]:
        """The row of each voxel, -1 where there is none."""
        return _locate(*self.blocks(), self.local, ijk)

    def add_found(self, ijk: NDArray[np.int64], bins: NDArray[np.int64], w: float) -> NDArray:
        """``_add_found``: ``w`` added where the voxel has a row; the other returns."""
        return _add_found(*self.blocks(), self.local, self.counts, ijk, bins, w)

    def with_returns(
        self, ijk: NDArray[np.int64], bins: NDArray[np.int64], picked: NDArray, w: float
    ) -> _Rows:
        """These rows and rows for the voxels of the ``picked`` returns (none of them here),
        each return adding ``w`` to its bin."""
        packed, lowest = _packed(ijk, bins, picked)
        if packed.size:
            keys, places, new_bins = _unpacked(np.sort(packed, kind="stable"), lowest)
        else:  # a scan spanning more blocks than a packed value holds
            keys, places, _ = row_keys(ijk[picked])
            order = np.lexsort((places, keys))
            keys, places, new_bins = keys[order], places[order], bins[picked][order]
        return _Rows(
            *_merge_new(*self.blocks(), self.local, self.counts, keys, places, new_bins, w)
        )

    def merged(self, other: _Rows) -> _Rows:
        """These rows and ``other``'s (no voxel in both), as one table."""
        if not len(other):
            return self
        return _Rows(
            *_merge_rows(
                self.block_keys, self.block_start, self.local, self.counts,
                other.block_keys, other.block_start, other.local, other.counts,
            )
        )  # fmt: skip

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (*self.blocks(), self.local, self.counts))


FRESH_ROWS_MIN = 4096
"""The fresh rows of ``ReflectivityTable`` go into the settled ones once they are more
than this, and more than ``sqrt(2 * settled * new)`` (``new``: the rows a scan has added,
on average): the size at which a scan's copying of the fresh rows and the merges' copying
of the settled ones, spread over the scans between merges, are equal (each about that many
rows a scan). Before, every scan that added a voxel copied the whole table: 31.7 ms a scan
at 1.2 M rows, 92.2 at 4.2 M, now 7.2 and 10.6 (2,000 new voxels of 40,000 returns;
``benchmarks/bench_reflectivity_table.py``, docs/performance.md)."""


REFERENCE_DECAY_TIMES = 22.0
"""With decay, the counts refer to one time ``t`` and a later return adds
``exp((stamp - t) / T)``; once that would pass ``exp(22)`` (3.6e9, far within float32's
range), every count is scaled to the scan's stamp, which becomes ``t``. Float32 rounds a sum
the same relative amount at any scale, so the weights cost no precision, and a count is
rounded by a scaling once every 22 decay times instead of once a scan. Scaling every count
at every later scan: 18.7-20.8 ms a scan at 4.4 M rows, now 11.1-16.7 (12.2-12.7 without
decay; ``benchmarks/bench_reflectivity_table.py --decay-time 10``, scans 0.1 s apart,
docs/performance.md)."""


class ReflectivityTable:
    """Histograms of return intensity of the voxels that hold returns (module docstring).

    Rows sorted by block (``blocks.block_key``) and, inside a block, by the voxel's place
    (0-511): per block its key (int64) and first row (int32); per row its place (uint16)
    and ``J`` float32 counts (``_Rows``). All rows' counts refer to one time (module
    docstring; moved forward, every count scaled once in float32 like ``n``, when a later
    scan's weight would pass ``exp(REFERENCE_DECAY_TIMES)``): nothing is stored per row but
    the counts. Blocks are found by an open-addressing hash of their
    keys (``blocks.find_block``), a place in its block by bisection. Arrays are sized to
    the rows. A scan's new voxels are sorted and merged into the fresh rows, a small
    table of their own, which go into the settled rows when they outgrow
    ``FRESH_ROWS_MIN``'s bound (a copy of the settled rows every few dozen scans): the
    same counts, bit for bit, as one table. Not thread-safe (the Mapper's lock).

    Measured against the open-addressing hash of voxel index to a row with its time that
    it replaced (52 bytes a row plus 27 of hash): 36-37 bytes a row on ouster_street, the
    integration time with histograms unchanged within noise (``bench_reflectivity.py``)."""

    def __init__(self, bins: ReflectivityBins, capacity: int = 0) -> None:
        """``capacity``: unused, kept for callers (arrays are sized to the rows)."""
        self.bins = bins
        self._decay_time: float | None = None
        self._time = -math.inf  # the time every row's counts refer to
        self._latest = -math.inf  # the latest stamp added
        self._settled = _Rows.empty(bins.count)
        self._fresh = _Rows.empty(bins.count)
        self._new_per_scan = 0.0  # rows a scan adds (a moving average)

    def _settle(self) -> _Rows:
        """Every row in one table (the fresh ones merged into the settled)."""
        if len(self._fresh):
            self._settled = self._settled.merged(self._fresh)
            self._fresh = _Rows.empty(self.bins.count)
        return self._settled

    def __len__(self) -> int:
        return len(self._settled) + len(self._fresh)

    def _use_decay(self, decay_time: float) -> float:
        """The table's decay time: the first one given (ValueError for another later)."""
        decay_time = float(decay_time)
        if self._decay_time is None or not len(self):
            self._decay_time = decay_time
        elif decay_time != self._decay_time:
            raise ValueError(f"decay time {decay_time} s, the table's is {self._decay_time} s")
        return decay_time

    def _decayed(self, stamp: float) -> float:
        """exp(-(stamp - t) / T): the counts at ``stamp`` are the held ones times it."""
        decay = self._decay_time
        if decay is None or not math.isfinite(decay):
            return 1.0
        return math.exp(-(stamp - self._time) / decay)

    def _at_latest(self, counts: NDArray[np.float32]) -> NDArray[np.float32]:
        """``counts`` (held) brought to the latest stamp added, rounded to float32: what
        ``export`` holds and a map file's read starts from (the same values)."""
        decay = self._decay_time
        if decay is None or not math.isfinite(decay) or self._time == self._latest:
            return counts
        factor = np.exp(np.array([self._time - self._latest]) / decay)
        return (counts.astype(np.float64) * factor[0]).astype(np.float32)

    def add(
        self, ijk: NDArray[np.integer], bins: NDArray[np.integer], stamp: float, decay_time: float
    ) -> None:
        """One return in voxel ``ijk[j]`` (index relative to the map origin) and bin
        ``bins[j]`` (< 0: none) for each j, made at ``stamp``, decayed with time constant
        ``decay_time`` (s, inf: none; the same for every call). Voxels beyond the map's
        range (``MAX_VOXEL_INDEX``, where the store holds no ``n`` either) are skipped."""
        voxels = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
        bins_ = np.ascontiguousarray(bins, dtype=np.int64).reshape(-1)
        if bins_.shape[0] != voxels.shape[0]:
            raise ValueError(f"{voxels.shape[0]} voxels but {bins_.shape[0]} bins")
        if bins_.size and bins_.max() >= self.bins.count:
            raise ValueError(f"bin {int(bins_.max())} beyond the {self.bins.count} bins")
        stamp = float(stamp)
        decay = self._use_decay(decay_time)
        if not len(self):
            self._time = self._latest = stamp
        self._latest = max(self._latest, stamp)
        if math.isfinite(decay) and stamp - self._time > REFERENCE_DECAY_TIMES * decay:
            factor = np.float32(self._decayed(stamp))
            self._settled.counts *= factor
            self._fresh.counts *= factor
            self._time = stamp
        w = 1.0 / self._decayed(stamp)  # exp((stamp - t) / T)
        new = self._settled.add_found(voxels, bins_, w)
        if new.size:  # not in the settled rows: in the fresh ones, or new
            voxels, bins_ = voxels[new], bins_[new]
            new = self._fresh.add_found(voxels, bins_, w)
        before = len(self._fresh)
        if new.size:
            self._fresh = self._fresh.with_returns(voxels, bins_, new, w)
        added = len(self._fresh) - before
        self._new_per_scan += 0.1 * (added - self._new_per_scan)
        bound = math.sqrt(2.0 * len(self._settled) * max(self._new_per_scan, 1.0))
        if len(self._fresh) > max(FRESH_ROWS_MIN, bound):
            self._settle()

    def lookup(self, ijk: NDArray[np.integer]) -> NDArray[np.int64]:
        """The row of each voxel (in ``export``'s order), -1 where it holds no histogram."""
        ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
        return self._settle().locate(ijk)

    def histograms(
        self, ijk: NDArray[np.integer], stamp: float | None = None, decay_time: float = math.inf
    ) -> tuple[FloatArray, FloatArray]:
        """Counts (M, J) of each voxel (zeros where none) and the time they refer to
        (-inf where none): decayed to ``stamp`` when given and ``decay_time`` (the one
        the returns were added with) finite, else at the latest stamp added."""
        ijk = np.ascontiguousarray(ijk, dtype=np.int64).reshape(-1, 3)
        levels = [(rows, rows.locate(ijk)) for rows in (self._settled, self._fresh)]
        found = (levels[0][1] >= 0) | (levels[1][1] >= 0)  # a voxel's row is in one
        latest = self._latest
        at = latest if stamp is None or not math.isfinite(decay_time) else float(stamp)
        if found.any() and math.isfinite(decay_time):
            self._use_decay(decay_time)
        factor = 1.0 if not math.isfinite(decay_time) else math.exp(-(at - latest) / decay_time)
        counts = np.zeros((ijk.shape[0], self.bins.count))
        for rows, row in levels:
            here = row >= 0
            # float32, as a map file's read: at the latest stamp, then at ``at``
            counts[here] = self._at_latest(rows.counts[row[here]]) * factor
        t = np.where(found, at, -np.inf)
        return counts, t

    def export(self) -> ReflectivityArrays:
        """Every row: its counts at the latest stamp added (float32 values) and that time,
        for every row (a copy)."""
        rows = self._settle()
        return ReflectivityArrays(
            self.bins,
            self.voxel_indices(),
            self._at_latest(rows.counts).astype(np.float64),
            np.full(len(self), self._latest),
        )

    def assign(self, table: ReflectivityArrays, decay_time: float = math.inf) -> None:
        """Set the rows of an empty table (a map file's, whose rows may refer to different
        times; ``decay_time`` the map's); ValueError naming a voxel listed twice or a
        problem of the arrays (the table then stays empty)."""
        if len(self):
            raise ValueError("assign needs an empty table")
        if table.bins != self.bins:
            raise ValueError(f"bins {table.bins} differ from the table's {self.bins}")
        problem = table_problem(table)
        if problem:
            raise ValueError(problem)
        ijk = np.ascontiguousarray(table.ijk, dtype=np.int64).reshape(-1, 3)
        keys, places, inside = row_keys(ijk)
        if not inside.all():
            raise ValueError(f"reflectivity_ijk holds indices beyond +-{MAX_VOXEL_INDEX}")
        order = np.lexsort((places, keys))
        keys, places = keys[order], places[order]
        twice = np.flatnonzero((keys[1:] == keys[:-1]) & (places[1:] == places[:-1]))
        if twice.size:
            voxel = ijk[order[twice[0]]].tolist()
            raise ValueError(f"reflectivity_ijk lists voxel {voxel} more than once")
        decay = self._use_decay(decay_time)
        t_last = np.asarray(table.t_last, dtype=np.float64)[order]
        if not t_last.size:
            return
        self._time = self._latest = float(t_last.max())
        counts = np.asarray(table.counts, dtype=np.float64)[order]
        if math.isfinite(decay):
            counts = counts * np.exp((t_last - self._time) / decay)[:, None]
        first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        self._settled = _Rows(
            keys[first],
            np.append(first, keys.size).astype(np.int32),
            places.astype(np.uint16),
            counts.astype(np.float32),
        )

    def keep(self, mask: NDArray[np.bool_]) -> int:
        """Keep the rows (in ``export``'s order) where ``mask`` (over ``len(self)`` rows) is
        True; returns how many were dropped."""
        rows = self._settle()
        kept = int(np.count_nonzero(mask))
        dropped = len(self) - kept
        if not dropped:
            return 0
        per_block = np.diff(rows.block_start)
        block_of_row = np.repeat(np.arange(per_block.shape[0]), per_block)
        left = np.bincount(block_of_row[mask], minlength=per_block.shape[0])
        self._settled = _Rows(
            rows.block_keys[left > 0],
            np.append(0, np.cumsum(left[left > 0])).astype(np.int32),
            rows.local[mask],
            rows.counts[mask],
        )
        return dropped

    def voxel_indices(self) -> NDArray[np.int32]:
        """The voxel index of every row (K, 3), in ``export``'s order."""
        rows = self._settle()
        return _voxels_of(rows.block_keys, rows.block_start, rows.local)

    def clear_box(self, lo: NDArray[np.int64], hi: NDArray[np.int64]) -> int:
        """Drop the rows of the voxels with index in [lo, hi]; returns how many."""
        ijk = self.voxel_indices()
        inside = np.all((ijk >= lo) & (ijk <= hi), axis=1)
        return self.keep(~inside)

    @property
    def nbytes(self) -> int:
        """Memory in use: the arrays are sized to the rows and blocks."""
        return self._settled.nbytes + self._fresh.nbytes


def merge_reflectivity(
    parts: Sequence[ReflectivityArrays], decay_time: float
) -> ReflectivityArrays | None:
    """Per-voxel sums of the tables (each voxel at most once per part), every row brought
    to the latest time any part gives it (exact, like ``merge.merge_voxels``); None when
    no part is given. ValueError when the parts' bins differ."""
    if not parts:
        return None
    bins = parts[0].bins
    for part in parts[1:]:
        if part.bins != bins:
            raise ValueError(
                f"reflectivity bins differ: {bins.field} {list(bins.edges)} and "
                f"{part.bins.field} {list(part.bins.edges)}"
            )
    ijk = np.concatenate([p.ijk for p in parts]).astype(np.int64).reshape(-1, 3)
    counts = np.concatenate([p.counts for p in parts]).reshape(-1, bins.count)
    t = np.concatenate([p.t_last for p in parts])
    if not ijk.shape[0]:
        return ReflectivityArrays(bins, ijk.astype(np.int32), counts, t)
    unique, inverse = np.unique(ijk, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    t_common = np.full(unique.shape[0], -np.inf)
    np.maximum.at(t_common, inverse, t)
    if math.isfinite(decay_time):
        counts = counts * np.exp((t - t_common[inverse]) / decay_time)[:, None]
    summed = np.zeros((unique.shape[0], bins.count))
    np.add.at(summed, inverse, counts)
    return ReflectivityArrays(bins, unique.astype(np.int32), summed, t_common)
