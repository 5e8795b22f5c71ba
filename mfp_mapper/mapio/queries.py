"""Queries answered from a map file reading only the blocks they need, and their
reflectivity histograms (version 3 and 4 files; an older file is read whole once): what
``mfp-mapper query`` and a tiled map's queries use.

Points in a version 3 or 4 file are answered in numpy from the blocks read (``packed_lookup``),
their reflectivity histograms from the rows read (``reflectivity_lookup``), the same numbers
as ``Mapper.query`` and ``Mapper.reflectivity`` of the whole map (``test_queries.py``
compares them), without loading numba or any compiled kernel: a process asking a few points
pays for reading them, not for the Mapper's imports (1.2 s on this machine, 0.01-0.02 s the
read). Segments go through a Mapper of the blocks read, older files through the whole map.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core import model
from mfp_mapper.core.layout import (
    BLOCK_BITS,
    BLOCK_EDGE,
    MAX_VOXEL_INDEX,
    PackedBlocks,
    bit_count,
    sort_keys,
    totals,
    voxel_starts,
)
from mfp_mapper.core.reflectivity_arrays import ReflectivityArrays, ReflectivityBins, row_keys
from mfp_mapper.core.voxel_stats import SegmentStats, VoxelStats, decayed_stats
from mfp_mapper.mapio.blockfile import BlockReader
from mfp_mapper.mapio.mapfile import (
    MapContents,
    MapFileError,
    mapper_from_contents,
    read_map_blocks,
    read_map_file,
    settings_arrays,
)

if TYPE_CHECKING:
    from mfp_mapper.core.mapper import Mapper

MAX_SEGMENT_SAMPLES = 4_000_000
"""Samples along the segments of one query (one a voxel) beyond which a map file is read
whole instead of block by block."""


class MapFileQueries:
    """A map file opened for ``query`` and ``query_segments``: each call reads only the
    blocks it needs, and the reflectivity histograms of those blocks (version 3 and 4; an older
    file is read whole once). Blocks read are checked
    (masks, counts, values, stamps); a whole read also checks the CRCs. ``MapFileError``
    as ``load_map``."""

    def __init__(self, path: str | Path, decay_time: float | None = None) -> None:
        self.path = Path(path)
        self._decay_time = decay_time
        self._whole: Mapper | None = None
        self.block_ijk: NDArray[np.int32] = np.zeros((0, 3), dtype=np.int32)
        """Every block of the file (block indices)."""
        self.num_voxels = 0
        self.t_max = -math.inf
        """The latest block time of the file (s)."""

        def index_only(reader: BlockReader) -> NDArray[np.int64]:
            self.block_ijk = reader.block_ijk
            self.num_voxels = int(reader.members["s"].shape[0])
            self.t_max = float(reader.view("block_t").max(initial=-math.inf))
            return np.zeros(0, dtype=np.int64)

        c = read_map_blocks(self.path, index_only, decay_time)
        self._contents: MapContents | None = None
        """The file's settings (None: it is read whole, ``_whole``)."""
        self._empty: Mapper | None = None
        if c is None:  # an older file
            self._whole = self._empty = self._read_whole()
            packed = self._whole.stored_blocks()
            self.block_ijk, self.num_voxels = packed.block_ijk, packed.num_voxels
            self.t_max = float(packed.block_t.max(initial=-math.inf))
            self.resolution = self._whole.resolution
            self.frame_id = self._whole.frame_id
            self.decay_time = self._whole.decay_time
            self.origin = np.asarray(self._whole.origin or (0.0, 0.0, 0.0))
            self.prior = self._whole.prior
            self._histograms = self._whole.reflectivity_scale is not None
        else:
            self._contents = c
            self.resolution = c.resolution
            self.frame_id = c.frame_id
            self.decay_time = c.decay_time
            self.origin = np.asarray(c.origin, dtype=np.float64)
            self.prior = model.Prior(c.ranges["prior_shape"], c.ranges["prior_rate"])
            """The Mapper's (``model.resolve_prior`` of a file's prior, both > 0: as stored)."""
            self._histograms = c.reflectivity is not None  # (its bins: no row read yet)

    def settings(self) -> dict[str, np.ndarray]:
        """The file's settings as map-file arrays."""
        return settings_arrays(self._empty_mapper())

    def _empty_mapper(self) -> Mapper:
        """A Mapper of the file's settings (and voxels, when read whole), made when first
        needed: a query of points needs none."""
        if self._empty is None:
            assert self._contents is not None
            self._empty = mapper_from_contents(self._contents, self.path)
        return self._empty

    def _read_whole(self) -> Mapper:
        return mapper_from_contents(read_map_file(self.path, self._decay_time), self.path)

    def _blocks(self, keys: NDArray[np.int64]) -> Mapper:
        """A Mapper of the file's blocks whose ``packed.sort_keys`` are among ``keys``."""
        if self._whole is not None:
            return self._whole
        c = read_map_blocks(self.path, lambda r: r.rows_of_keys(keys), self._decay_time)
        assert c is not None
        return mapper_from_contents(c, self.path)

    def _voxel_index(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Each point in voxel units, of the points the map's index range holds."""
        rel = (points - self.origin) / self.resolution
        with np.errstate(invalid="ignore"):
            valid = np.all(np.abs(rel) < MAX_VOXEL_INDEX - 2, axis=1)
        return rel[valid]

    def query(self, points: ArrayLike, stamp: float | None = None) -> VoxelStats:
        """``Mapper.query``, reading the blocks that hold the points (in numpy: no Mapper
        made, no numba loaded, for a version 3 or 4 file)."""
        if self._whole is not None:
            return self._whole.query(points, stamp)
        valid, ijk = self._point_voxels(points)
        keys = sort_keys(ijk[valid] >> BLOCK_BITS)
        c = read_map_blocks(self.path, lambda r: r.rows_of_keys(keys), self._decay_time)
        assert c is not None and c.packed is not None
        s, n, t_last = packed_lookup(c.packed, ijk)
        s[~valid], n[~valid], t_last[~valid] = 0.0, 0.0, -np.inf
        return decayed_stats(
            ijk, s, n, t_last, stamp, self.decay_time, self.resolution, self.origin, self.prior
        )

    def reflectivity(
        self, points: ArrayLike, stamp: float | None = None
    ) -> tuple[ReflectivityBins, NDArray[np.float64]] | None:
        """``Mapper.reflectivity`` of the whole map, reading the histograms of the blocks
        that hold the points (in numpy, ``reflectivity_lookup``: no Mapper made, no numba
        loaded, for a version 3 or 4 file); None for a file without histograms."""
        if not self._histograms:  # known without a Mapper
            return None
        if self._whole is not None:
            return self._whole.reflectivity(points, stamp)
        valid, ijk = self._point_voxels(points)
        keys = sort_keys(ijk[valid] >> BLOCK_BITS)
        latest = [-math.inf]

        def pick(reader: BlockReader) -> NDArray[np.int64]:
            if math.isfinite(self.decay_time) and "reflectivity_t_last" in reader.members:
                latest[0] = float(np.max(reader.view("reflectivity_t_last"), initial=-math.inf))
            return reader.rows_of_keys(keys)

        c = read_map_blocks(self.path, pick, self._decay_time)
        assert c is not None and c.reflectivity is not None
        if math.isnan(latest[0]) or latest[0] == math.inf:  # in a row not read: as a load
            raise MapFileError(
                self.path, "reflectivity_t_last holds NaN or infinite values (seconds expected)"
            )
        try:
            counts = reflectivity_lookup(c.reflectivity, ijk, stamp, self.decay_time, latest[0])
        except ValueError as err:  # as Mapper.from_blocks refuses it
            raise MapFileError(self.path, str(err)) from None
        counts[~valid] = 0.0
        return c.reflectivity.bins, counts

    def _point_voxels(self, points: ArrayLike) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
        """Which points lie within the map's index range (not NaN, not far) and the voxel
        of each (that of ``origin`` for the others), as the Mapper finds them."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):  # as Mapper.query: NaN and far points are unknown
            valid = np.all(np.abs((pts - self.origin) / self.resolution) < MAX_VOXEL_INDEX, axis=1)
        rel = np.where(valid[:, None], pts, self.origin) - self.origin
        return valid, np.floor(rel / self.resolution).astype(np.int64)

    def query_segments(
        self, starts: ArrayLike, ends: ArrayLike, stamp: float | None = None
    ) -> SegmentStats:
        """``Mapper.query_segments``, reading the blocks within a voxel of the segments
        (the whole file when they are very long: ``MAX_SEGMENT_SAMPLES``)."""
        a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        va, vb = self._voxel_index(a), self._voxel_index(b)
        if a.shape != b.shape or va.shape != a.shape or vb.shape != b.shape:
            return self._empty_mapper().query_segments(a, b, stamp)  # the core refuses these
        keys = segment_block_keys(va, vb)
        if keys is None:
            if self._whole is None:
                self._whole = self._read_whole()
            return self._whole.query_segments(a, b, stamp)
        return self._blocks(keys).query_segments(a, b, stamp)


def segment_block_keys(
    va: NDArray[np.float64], vb: NDArray[np.float64]
) -> NDArray[np.int64] | None:
    """The blocks (``packed.sort_keys``, unique) within a voxel of the segments ``va`` ->
    ``vb`` (voxel units): samples at most a voxel apart along each, every block within a
    voxel of a sample. None when that takes more than ``MAX_SEGMENT_SAMPLES`` samples."""
    steps = np.ceil(np.linalg.norm(vb - va, axis=1)).astype(np.int64) + 1
    total = int(steps.sum())
    if total > MAX_SEGMENT_SAMPLES:
        return None
    seg = np.repeat(np.arange(len(steps)), steps)
    first = np.repeat(np.cumsum(steps) - steps, steps)
    frac = (np.arange(total) - first) / np.maximum(steps - 1, 1)[seg]
    samples = va[seg] + (vb - va)[seg] * frac[:, None]
    lo, hi = (np.floor(samples + d).astype(np.int64) >> BLOCK_BITS for d in (-1.0, 1.0))
    keys = [
        sort_keys(np.stack([x[:, 0], y[:, 1], z[:, 2]], axis=1))
        for x in (lo, hi)
        for y in (lo, hi)
        for z in (lo, hi)
    ]
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, dtype=np.int64)


def packed_lookup(
    packed: PackedBlocks, ijk: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``s``, ``n`` (float64) and time of the voxels ``ijk`` in ``packed``, as
    ``BlockStore.lookup`` answers after ``Mapper.from_blocks``: the file's values exactly
    (``layout.totals``: the float32 part plus the float64 part of a flushed block, or a
    version 3 file's values), -0 read as +0; a voxel of a block present has its block's
    time (``s`` and ``n`` 0 when it was never observed), one of an absent block 0, 0 and
    -inf. Numpy, for a few points: a binary search a point, then its bit in the block's
    masks and the count of the bits before it."""
    count = ijk.shape[0]
    s, n, t_last = np.zeros(count), np.zeros(count), np.full(count, -np.inf)
    block_keys, want = sort_keys(packed.block_ijk), sort_keys(ijk >> BLOCK_BITS)
    row = np.searchsorted(block_keys, want)
    found = row < block_keys.shape[0]
    found[found] = block_keys[row[found]] == want[found]
    at, row = np.flatnonzero(found), row[found]
    t_last[at] = packed.block_t[row]
    place = morton_place(ijk[at] & (BLOCK_EDGE - 1))
    s_index, seen = _bit_rank(packed.observed, row, place)
    hit_row = np.searchsorted(packed.hit_block, row)
    has = hit_row < packed.hit_block.shape[0]
    has[has] = packed.hit_block[hit_row[has]] == row[has]
    n_index, hit = _bit_rank(packed.hit, hit_row[has], place[has])
    s_all, n_all = totals(packed)
    s_file, n_file = np.zeros(at.shape[0]), np.zeros(at.shape[0])
    s_file[seen] = s_all[s_index[seen]]
    n_file[np.flatnonzero(has)[hit]] = n_all[n_index[hit]]
    s[at], n[at] = s_file + 0.0, n_file + 0.0
    return s, n, t_last


def reflectivity_lookup(
    table: ReflectivityArrays,
    ijk: NDArray[np.int64],
    stamp: float | None,
    decay_time: float,
    latest: float,
) -> NDArray[np.float64]:
    """The histograms (M, J) of the voxels ``ijk`` among the rows of ``table`` (a map
    file's, or some of its rows: ``latest`` is the latest ``t_last`` of all its rows), as
    ``Mapper.reflectivity`` answers after ``Mapper.from_blocks`` of the whole file
    (``ReflectivityTable.assign``, then ``histograms``): each row brought to ``latest``
    and held as float32, then scaled to ``stamp`` (or held at ``latest`` without a stamp or
    without decay); zeros for a voxel without a row or beyond the index range. ValueError
    for a voxel listed twice. Numpy, for a few points: a sort of the rows read, a binary
    search a point."""
    rows_ijk = np.asarray(table.ijk, dtype=np.int64).reshape(-1, 3)
    keys, places, _ = row_keys(rows_ijk)
    blocks, block_of = np.unique(keys, return_inverse=True)
    row_id = block_of.reshape(-1) * BLOCK_EDGE**3 + places  # sorts like (key, place)
    order = np.argsort(row_id, kind="stable")
    sorted_id = row_id[order]
    twice = np.flatnonzero(sorted_id[1:] == sorted_id[:-1])
    if twice.size:
        voxel = rows_ijk[order[twice[0]]].tolist()
        raise ValueError(f"reflectivity_ijk lists voxel {voxel} more than once")
    counts = np.asarray(table.counts, dtype=np.float64)
    decays = math.isfinite(decay_time)
    if decays:
        t_last = np.asarray(table.t_last, dtype=np.float64)
        counts = counts * np.exp((t_last - latest) / decay_time)[:, None]
    held = counts.astype(np.float32)
    want, want_place, inside = row_keys(np.asarray(ijk, dtype=np.int64).reshape(-1, 3))
    block = np.searchsorted(blocks, want)
    found = inside & (block < blocks.shape[0])
    found[found] = blocks[block[found]] == want[found]
    at = np.flatnonzero(found)
    want_id = block[at] * BLOCK_EDGE**3 + want_place[at]
    pos = np.searchsorted(sorted_id, want_id)
    hit = pos < sorted_id.shape[0]
    hit[hit] = sorted_id[pos[hit]] == want_id[hit]
    when = latest if stamp is None or not decays else float(stamp)
    scale = math.exp(-(when - latest) / decay_time) if decays else 1.0
    out = np.zeros((want.shape[0], table.bins.count))
    out[at[hit]] = held[order[pos[hit]]] * scale
    return out


def morton_place(local: NDArray[np.int64]) -> NDArray[np.int64]:
    """The Morton place in its block (``blocks.local_index``: x, y, z bits interleaved,
    z lowest) of each voxel offset ``local`` (k, 3) in [0, 8)."""
    place = np.zeros(local.shape[0], dtype=np.int64)
    for bit in range(BLOCK_BITS):
        for axis, shift in ((0, 2), (1, 1), (2, 0)):
            place |= ((local[:, axis] >> bit) & 1) << (3 * bit + shift)
    return place


def _bit_rank(
    masks: NDArray[np.uint64], rows: NDArray[np.int64], place: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """For bit ``place[k]`` of block ``rows[k]``'s mask: its value's index (the set bits of
    the masks before it) and whether it is set."""
    starts = voxel_starts(masks)
    m = masks[rows]
    counts = bit_count(m).astype(np.int64)
    before_word = np.cumsum(counts, axis=1) - counts
    k = np.arange(rows.shape[0])
    word, bit = place >> 6, (place & 63).astype(np.uint64)
    w = m[k, word]
    below = bit_count(w & ((np.uint64(1) << bit) - np.uint64(1))).astype(np.int64)
    is_set = ((w >> bit) & np.uint64(1)).astype(bool)
    return starts[rows] + before_word[k, word] + below, is_set
