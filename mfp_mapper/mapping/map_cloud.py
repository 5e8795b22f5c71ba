"""The map clouds' voxels, kept between publications and rebuilt where scans changed the map.

The node publishes its map clouds whole (a subscriber such as RViz gets every voxel in each
message, latched), but rebuilds them from the blocks scans opened since the last
publication (``Mapper.changed_voxels``): the map lock is held only to read those blocks'
voxels that hold a return, and the rest of the cloud is the previous one's rows. The
result is the cloud of the whole map, row for row (in another order): the clouds show the
statistics at their last update, which only a scan opening the block changes; anything
else that changes voxels (reset, clear_box, eviction by the memory bound) bumps
``Mapper.epoch`` and the next publication reads the whole map again, as does a change of
the filters or of the prior. The reading may be done in slices of blocks, the map lock let go
in between (``MapCloud.read`` ``max_blocks``): each block is read once, whole, as it is at
its slice.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.changed_blocks import BlockCursor
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.reflectivity import mean_value, most_likely_bin
from mfp_mapper.core.voxel_stats import VoxelStats

_KEY_BITS = 21
_KEY_MASK = (1 << _KEY_BITS) - 1


@dataclass
class CloudRows:
    """The voxels of a map cloud: centres (map frame, float64) and the published fields
    (float32); ``reflectivity`` and ``reflectivity_bin`` are NaN where a voxel holds no
    histogram, None while the map keeps none."""

    centers: NDArray[np.float64]
    degree_of_occupancy: NDArray[np.float32]
    std: NDArray[np.float32]
    reflectivity: NDArray[np.float32] | None = None
    reflectivity_bin: NDArray[np.float32] | None = None

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    def select(self, keep: NDArray[np.bool_]) -> CloudRows:
        parts: list[Any] = [None if a is None else a[keep] for a in self.arrays()]
        return CloudRows(*parts)

    def arrays(self) -> tuple[Any, ...]:
        return (
            self.centers, self.degree_of_occupancy, self.std, self.reflectivity,
            self.reflectivity_bin,
        )  # fmt: skip


MAX_RESTARTS = 2
"""Slices of a read that the map's ``epoch`` changed under (reset, clear_box, eviction by the
memory bound: blocks moved) are read again from the start; after this many restarts the
read is done in one go (a map whose memory bound evicts at every scan is bounded in size)."""


@dataclass
class CloudChanges:
    """What ``MapCloud.read`` took from the map under its lock: the slices read so far
    (voxels, blocks holding a return, histogram counts) and where the next slice starts
    (``cursor``; None: the read is complete)."""

    key: tuple[Any, ...]
    full: bool
    read_since: int  # the scan whose changes on are read (-1: every block)
    since: int  # the next scan when the read began: the rows' scan once applied
    voxels: list[VoxelStats]
    blocks: list[NDArray[np.int32]]
    bins: Any  # the histograms' bins (None: the map keeps none)
    counts: list[NDArray[np.float64] | None]  # a slice's (None: the map kept none then)
    cursor: BlockCursor | None = None
    restarts: int = 0
    started: bool = False

    @property
    def complete(self) -> bool:
        return self.started and self.cursor is None


def block_keys(block_ijk: NDArray[np.integer]) -> NDArray[np.int64]:
    """One int64 per block index (B, 3)."""
    b = np.asarray(block_ijk, dtype=np.int64) & _KEY_MASK
    return (b[:, 0] << (2 * _KEY_BITS)) | (b[:, 1] << _KEY_BITS) | b[:, 2]


class MapCloud:
    """The rows of the map clouds (``CloudRows``) and the scan they are up to date with:
    ``read`` under the map lock, then ``apply`` without it; one caller at a time."""

    def __init__(self) -> None:
        self._key: tuple[Any, ...] | None = None
        self._since = -1
        self._rows: CloudRows | None = None
        self._row_blocks = np.zeros(0, dtype=np.int64)
        self.last_changed_blocks = 0
        """Blocks read by the last ``read`` (every block holding a return when it was full)."""

    def read(
        self,
        mapper: Mapper,
        min_doo: float,
        min_evidence: float,
        max_blocks: int | None = None,
        partial: CloudChanges | None = None,
    ) -> CloudChanges:
        """The voxels of the blocks changed since the rows' scan (the whole map when the
        map, its epoch, the filters or the prior changed), with their histograms: the part
        that needs the map lock (``min_doo`` >= 0). With ``max_blocks``, one slice of at
        most that many of the store's blocks, going on from ``partial`` (the last slice's
        result) until ``complete``; the lock may be let go between slices (each block is
        read once, as it is at its slice; the rows' scan is the one the read began at, so
        the next read takes again every block scans changed meanwhile)."""
        key = (
            id(mapper), mapper.epoch, min_doo, min_evidence, mapper.prior,
            mapper.reflectivity_scale, mapper.resolution,
        )  # fmt: skip
        if partial is not None and partial.key == key and not partial.complete:
            changes = partial
        else:  # a new read, or the map changed under the last slice: from the start
            restarts = 0 if partial is None else partial.restarts + 1
            full = key != self._key or self._rows is None
            read_since = -1 if full else self._since
            changes = CloudChanges(key, full, read_since, -1, [], [], None, [], None, restarts)
        if changes.restarts > MAX_RESTARTS:
            max_blocks = None
        voxels, blocks, since, cursor = mapper.changed_voxels_from(
            changes.read_since, min_doo, changes.cursor, max_blocks
        )
        if changes.since < 0:
            changes.since = since
        changes.cursor, changes.started = cursor, True
        changes.voxels.append(voxels)
        changes.blocks.append(blocks)
        histograms = mapper.reflectivity(voxels.centers)
        if histograms is not None:
            changes.bins = histograms[0]
        changes.counts.append(None if histograms is None else histograms[1])
        return changes

    def apply(self, changes: CloudChanges, min_evidence: float) -> CloudRows:
        """The rows after ``changes`` (a complete read: the map's cloud as ``read`` saw
        it, slice by slice)."""
        if not changes.complete:
            raise ValueError("MapCloud.apply: the read is not complete")
        vox = _concatenate_stats(changes.voxels)
        histograms = None
        if changes.bins is not None:  # (a slice read before the map kept any: no counts)
            width = next(c.shape[1] for c in changes.counts if c is not None)
            counts = [
                np.zeros((len(v), width)) if c is None else c
                for v, c in zip(changes.voxels, changes.counts, strict=True)
            ]
            histograms = (changes.bins, np.concatenate(counts))
        if min_evidence > 0.0:
            keep = vox.s >= min_evidence
            vox = vox.select(keep)
            if histograms is not None:
                histograms = (histograms[0], histograms[1][keep])
        fresh = rows_of(vox, histograms)
        fresh_blocks = block_keys(vox.ijk >> 3)
        old = self._rows
        if changes.full or old is None:
            rows, row_blocks = fresh, fresh_blocks
        else:
            changed = np.sort(block_keys(np.concatenate(changes.blocks)))
            stale = np.zeros(len(self._row_blocks), dtype=np.bool_)
            if len(changed):  # (searchsorted: np.isin took 3x as long)
                at = np.minimum(np.searchsorted(changed, self._row_blocks), len(changed) - 1)
                stale = changed[at] == self._row_blocks
            kept = old.select(~stale)
            rows = _concatenate(kept, fresh)
            row_blocks = np.concatenate([self._row_blocks[~stale], fresh_blocks])
        self._rows, self._row_blocks = rows, row_blocks
        self._key, self._since = changes.key, changes.since
        self.last_changed_blocks = sum(len(b) for b in changes.blocks)
        return rows

    def clear(self) -> None:
        """Forget the rows (the next ``read`` reads the whole map)."""
        self._key, self._rows, self._since = None, None, -1
        self._row_blocks = np.zeros(0, dtype=np.int64)


def rows_of(vox: VoxelStats, histograms: tuple[Any, NDArray[np.float64]] | None) -> CloudRows:
    """The cloud rows of voxels and their histograms (``Mapper.reflectivity``, or None)."""
    rows = CloudRows(
        vox.centers, vox.most_likely_doo.astype(np.float32), vox.std.astype(np.float32)
    )
    if histograms is not None:
        bins, counts = histograms
        held = counts.sum(axis=1) > 0
        rows.reflectivity = np.full(len(vox), np.nan, dtype=np.float32)
        rows.reflectivity_bin = np.full(len(vox), np.nan, dtype=np.float32)
        rows.reflectivity[held] = mean_value(counts[held], bins)
        rows.reflectivity_bin[held] = most_likely_bin(counts[held])
    return rows


def _concatenate_stats(parts: list[VoxelStats]) -> VoxelStats:
    """The voxels of the slices of a read, one after the other."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    arrays = {
        f.name: np.concatenate([getattr(p, f.name) for p in parts])
        for f in fields(first)
        if f.name not in ("resolution", "prior")
    }
    return VoxelStats(**arrays, resolution=first.resolution, prior=first.prior)


def _concatenate(a: CloudRows, b: CloudRows) -> CloudRows:
    parts: list[Any] = []
    for x, y in zip(a.arrays(), b.arrays(), strict=True):
        parts.append(None if x is None or y is None else np.concatenate([x, y]))
    return CloudRows(*parts)
