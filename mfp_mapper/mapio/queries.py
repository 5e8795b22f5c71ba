"""Queries answered from a map file reading only the blocks they need, and their
reflectivity histograms (version 3 files; an older file is read whole once): what
``mfp-mapper query`` and a tiled map's queries use."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.core.blocks import BLOCK_BITS
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.packed import sort_keys
from mfp_mapper.core.reflectivity import ReflectivityBins
from mfp_mapper.core.store import MAX_VOXEL_INDEX
from mfp_mapper.core.voxel_stats import SegmentStats, VoxelStats
from mfp_mapper.mapio.blockfile import BlockReader
from mfp_mapper.mapio.mapfile import (
    mapper_from_contents,
    read_map_blocks,
    read_map_file,
    settings_arrays,
)

MAX_SEGMENT_SAMPLES = 4_000_000
"""Samples along the segments of one query (one a voxel) beyond which a map file is read
whole instead of block by block."""


class MapFileQueries:
    """A map file opened for ``query`` and ``query_segments``: each call reads only the
    blocks it needs, and the reflectivity histograms of those blocks (version 3; an older
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
        if c is None:  # an older file
            self._whole = self._empty = self._read_whole()
            packed = self._whole.stored_blocks()
            self.block_ijk, self.num_voxels = packed.block_ijk, packed.num_voxels
            self.t_max = float(packed.block_t.max(initial=-math.inf))
        else:
            self._empty = mapper_from_contents(c, self.path)
        self.resolution = self._empty.resolution
        self.frame_id = self._empty.frame_id
        self.decay_time = self._empty.decay_time
        self.origin = np.asarray(self._empty.origin or (0.0, 0.0, 0.0))

    def settings(self) -> dict[str, np.ndarray]:
        """The file's settings as map-file arrays."""
        return settings_arrays(self._empty)

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
        """``Mapper.query``, reading the blocks that hold the points."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        blocks = np.floor(self._voxel_index(pts)).astype(np.int64) >> BLOCK_BITS
        return self._blocks(sort_keys(blocks)).query(pts, stamp)

    def reflectivity(
        self, points: ArrayLike, stamp: float | None = None
    ) -> tuple[ReflectivityBins, NDArray[np.float64]] | None:
        """``Mapper.reflectivity``, reading the histograms of the blocks that hold the
        points (None for a file without histograms)."""
        if self._empty.reflectivity_scale is None:
            return None
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        blocks = np.floor(self._voxel_index(pts)).astype(np.int64) >> BLOCK_BITS
        return self._blocks(sort_keys(blocks)).reflectivity(pts, stamp)

    def query_segments(
        self, starts: ArrayLike, ends: ArrayLike, stamp: float | None = None
    ) -> SegmentStats:
        """``Mapper.query_segments``, reading the blocks within a voxel of the segments
        (the whole file when they are very long: ``MAX_SEGMENT_SAMPLES``)."""
        a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
        va, vb = self._voxel_index(a), self._voxel_index(b)
        if a.shape != b.shape or va.shape != a.shape or vb.shape != b.shape:
            return self._empty.query_segments(a, b, stamp)  # the core refuses these
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
