"""The 2D hit-probability map: a height band of the 3D map projected onto a grid (no ROS).

A cell of the grid holds ``round(100 * p)``, where ``p`` is the probability that a
horizontal ray crossing the cell's column at some height in the band ``[z_min, z_max]`` is
reflected there: the largest per-voxel hit probability (Eq. 31-34, a ray crossing one voxel
edge) among the observed voxels of the column whose centre lies in the band (centre
inclusion, as octomap_server's ``occupancy_min_z``/``occupancy_max_z``). The largest, because a
ray at the worst height is the one a planar robot must fear, as octomap_server's projected
map marks a cell occupied when any voxel of the band is. Cells whose band holds no observed
voxel are ``-1`` (unknown), the OccupancyGrid convention.

With ``trinary=(occupied, free)`` (Nav2's static layer, octomap_server's ``projected_map``)
cells are ``100`` where that largest hit probability is at or above ``occupied``, ``0`` where
the band was observed and it is below ``free``, and ``-1`` otherwise (never observed, or in
between: uncertain). Thresholds compare the exact probability, not the rounded percent.

The grid is row-major, row ``r`` = y index, column ``c`` = x index, cell ``(r, c)`` covering
``[x0 + c * res, x0 + (c + 1) * res) x [y0 + r * res, y0 + (r + 1) * res)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.blocks import (
    BLOCK_BITS,
    BLOCK_EDGE,
    BLOCK_VOXELS,
    IndexBox,
    block_origin,
    block_outside,
    local_coords,
    voxel_inside,
)
from mfp_mapper.core.changed_blocks import BlockCursor, block_ranges
from mfp_mapper.core.shard import ShardArrays, block_values

UNKNOWN = -1
OCCUPIED = 100
FREE = 0
_UNCERTAIN = 1
"""Kernel code of a trinary cell observed between the thresholds (becomes UNKNOWN)."""
DEFAULT_OCCUPIED_THRESHOLD = 0.25
"""Default hit probability at or above which a trinary cell is occupied (a wall seen in 3
scans at 0.1 m reaches 0.32-0.38, in 40 scans 0.98; see docs/node.md)."""


WHOLE_BAND_SHARE = 0.5
"""A grid continued from a previous one (``start_band_grid`` ``previous``) whose changed block
columns exceed this share of the grid is computed whole: checking each block against the
columns cost ~10% more than reading them all when nearly all changed (a parked lidar that
reaches the whole map, benchmarks/bench_map_cloud.py)."""


@nb.njit(cache=True)
def hit_probability_one(
    s: float, n: float, length: float, shape: float = 1.0, rate: float = 1.0
) -> float:
    """``model.hit_probability`` of one voxel, for compiled kernels (the same expression), with
    the prior's ``shape`` and ``rate``."""
    s = max(s, 0.0)
    n = max(n, 0.0)
    return -math.expm1(-(n + shape) * math.log1p(length / (s + rate)))


def unobserved_hit_probability(resolution: float, shape: float = 1.0, rate: float = 1.0) -> float:
    """p_hit of a never-observed voxel, ``1 - (rate / (rate + s0))^shape`` (``s0 / (1 +
    s0)`` with the uniform prior, 0.012 at 0.1 m with the default family): every voxel
    crossed by rays but never hit is below it,
    so it is the default free threshold."""
    return float(hit_probability_one(0.0, 0.0, resolution, shape, rate))


def check_trinary(trinary: tuple[float, float] | None) -> tuple[bool, float, float]:
    """(use it, occupied, free) of trinary thresholds; ValueError unless 0 <= free <=
    occupied <= 1."""
    if trinary is None:
        return False, 0.0, 0.0
    occupied, free = (float(v) for v in trinary)
    if not (0.0 <= free <= occupied <= 1.0):
        raise ValueError(
            f"trinary thresholds need 0 <= free <= occupied <= 1, got occupied {occupied}, "
            f"free {free}"
        )
    return True, occupied, free


def finish_trinary(cells: NDArray[np.int8]) -> NDArray[np.int8]:
    """Cells observed between the thresholds become unknown (in place)."""
    cells[cells == _UNCERTAIN] = UNKNOWN
    return cells


class GridTooLarge(ValueError):
    """A projected grid would hold more cells than allowed; ``cells`` says how many."""

    def __init__(self, message: str, cells: int) -> None:
        super().__init__(message)
        self.cells = cells


@dataclass(frozen=True)
class BandCells:
    """A whole-band grid's cells before ``finish_trinary`` (a copy), the cell index (i0, j0)
    of cell (0, 0), the first scan it does not hold (``since``) and ``key``: what it was
    computed with (the caller's: another key, another grid)."""

    cells: NDArray[np.int8]
    i0: int
    j0: int
    since: int
    key: tuple[object, ...]


@dataclass(frozen=True)
class HitGrid:
    """A 2D grid of hit probabilities in percent (int8, -1 unknown)."""

    data: NDArray[np.int8]
    """(height, width), row-major: ``data[row = y, col = x]``."""
    resolution: float
    origin: tuple[float, float]
    """Map-frame (x, y) of the corner of cell (0, 0)."""
    cells: BandCells | None = None
    """What a later ``start_band_grid`` continues from (``previous``); None for a window."""

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell containing map point (x, y); may be outside the grid."""
        col = math.floor((x - self.origin[0]) / self.resolution + 1e-9)
        row = math.floor((y - self.origin[1]) / self.resolution + 1e-9)
        return row, col

    def value_at(self, x: float, y: float) -> int:
        """The cell value at map point (x, y); -1 outside the grid."""
        row, col = self.cell_of(x, y)
        if 0 <= row < self.height and 0 <= col < self.width:
            return int(self.data[row, col])
        return UNKNOWN


def band_mask(ijk: NDArray[np.integer], resolution: float, z_min: float, z_max: float) -> NDArray:
    """Voxels whose centre height ``(k + 0.5) res`` lies in ``[z_min, z_max]``."""
    zc = (np.asarray(ijk)[:, 2].astype(np.float64) + 0.5) * resolution
    return (zc >= z_min) & (zc <= z_max)


def _window_cells(
    center: tuple[float, float], radius: float, resolution: float
) -> tuple[int, int, int, int]:
    """First and last cell indices (i0, j0, i1, j1) of the square of half side ``radius``."""
    return (
        math.floor((center[0] - radius) / resolution),
        math.floor((center[1] - radius) / resolution),
        math.floor((center[0] + radius) / resolution),
        math.floor((center[1] + radius) / resolution),
    )


def _check_band(resolution: float, z_min: float, z_max: float) -> None:
    if resolution <= 0.0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    if not z_min < z_max:
        raise ValueError(f"empty height band [{z_min}, {z_max}]")


BlockArrays = tuple[ShardArrays, int]
"""A store shard as the projection reads it: its arrays, blocks used."""


@dataclass
class GridReading:
    """A grid being computed block range by block range (``start_band_grid``, then
    ``band_grid_step`` until ``cursor`` is None, then ``band_grid_result``): each block
    raises the cells of its column as it is when its range is read, so the caller may let
    other writers at the map between two ranges; the result's ``since`` is the scan the
    reading began at, so a grid continued from it computes again every column scans
    changed meanwhile."""

    cells: NDArray[np.int8]
    i0: int
    j0: int
    since: int
    key: tuple[object, ...]
    windowed: bool
    trinary: bool
    args: tuple[Any, ...]
    """``_band_max_percent``'s arguments after the block range (bounds, band, thresholds)."""
    cursor: BlockCursor | None = None
    """Where the next range starts (None: every block read, once ``started``)."""
    started: bool = False


def start_band_grid(
    shards: Sequence[BlockArrays],
    resolution: float,
    z_min: float,
    z_max: float,
    lo: IndexBox,
    hi: IndexBox,
    *,
    center: tuple[float, float] | None = None,
    radius: float = 0.0,
    max_cells: int | None = None,
    trinary: tuple[float, float] | None = None,
    prior: tuple[float, float] = (1.0, 1.0),
    previous: BandCells | None = None,
    since: int = -1,
    key: tuple[object, ...] = (),
) -> GridReading:
    """The reading of the hit-probability grid of the observed voxels with index in ``[lo,
    hi]``: its extent, cells (those of ``previous`` kept) and the columns to compute,
    before any block's values are read (a pass over the blocks' indices); then
    ``band_grid_step`` reads the blocks, in compiled passes over block ranges (no
    per-voxel arrays of the map), and ``band_grid_result`` gives the grid.

    ``previous`` (the ``cells`` of an earlier whole-band grid with the same ``key``): only
    the columns of blocks that scans numbered ``previous.since`` or later opened are
    computed again, the grid grown where they widened the extent; the same grid as from
    scratch, since a cell only depends on the voxels of its column. ``since``: the next
    scan's number, kept in the result's ``cells`` for the next call.

    The grid spans the window around ``center`` (``radius > 0``), else the (x, y) extent of
    the observed voxels in ``[lo, hi]``; cells take the voxels whose centre is in the band.
    ``GridTooLarge`` before anything is allocated when it would exceed ``max_cells``.
    ``trinary=(occupied, free)``: cells 100 / 0 / -1 instead of percentages (module doc).
    ``prior``: (shape, rate) of the map's Gamma prior on the extinction."""
    _check_band(resolution, z_min, z_max)
    use_trinary, occupied, free = check_trinary(trinary)
    windowed = center is not None and radius > 0.0
    if previous is not None and (windowed or previous.key != key or since < 0):
        previous = None
    changed_since = -1 if previous is None else previous.since
    if center is not None and radius > 0.0:
        i0, j0, i1, j1 = _window_cells(center, radius, resolution)
    else:
        extent = np.array([np.iinfo(np.int64).max] * 2 + [np.iinfo(np.int64).min] * 2)
        if previous is not None and previous.cells.size:
            height, width = previous.cells.shape
            extent[:] = [
                previous.i0,
                previous.j0,
                previous.i0 + width - 1,
                previous.j0 + height - 1,
            ]
        for arrays, used in shards:
            _observed_extent(arrays, used, lo, hi, extent, changed_since)
        if extent[0] > extent[2]:
            empty = np.zeros((0, 0), np.int8)
            return GridReading(empty, 0, 0, since, key, False, use_trinary, (), None, True)
        i0, j0, i1, j1 = (int(v) for v in extent)
    size = (j1 - j0 + 1) * (i1 - i0 + 1)
    if max_cells is not None and size > max_cells:
        raise GridTooLarge(
            f"the grid would have {i1 - i0 + 1} x {j1 - j0 + 1} cells "
            f"({(i1 - i0 + 1) * resolution:.0f} m x {(j1 - j0 + 1) * resolution:.0f} m), more "
            f"than the {max_cells} allowed",
            size,
        )
    cells = np.full((j1 - j0 + 1, i1 - i0 + 1), UNKNOWN, dtype=np.int8)
    bi0, bj0 = i0 >> BLOCK_BITS, j0 >> BLOCK_BITS
    dirty = np.zeros((0, 0), dtype=np.bool_)  # block columns to compute (none given: all)
    if previous is not None and previous.cells.size:
        height, width = previous.cells.shape
        at_j, at_i = previous.j0 - j0, previous.i0 - i0
        cells[at_j : at_j + height, at_i : at_i + width] = previous.cells
        dirty = np.zeros(((j1 >> BLOCK_BITS) - bj0 + 1, (i1 >> BLOCK_BITS) - bi0 + 1), np.bool_)
        for arrays, used in shards:
            _dirty_columns(arrays, used, lo, hi, changed_since, bi0, bj0, dirty)
        if dirty.mean() > WHOLE_BAND_SHARE:  # most columns changed: the whole band
            cells[:] = UNKNOWN
            dirty = np.zeros((0, 0), dtype=np.bool_)
        else:
            over = np.repeat(np.repeat(dirty, BLOCK_EDGE, axis=0), BLOCK_EDGE, axis=1)
            off_j, off_i = j0 - (bj0 << BLOCK_BITS), i0 - (bi0 << BLOCK_BITS)
            cells[over[off_j : off_j + cells.shape[0], off_i : off_i + cells.shape[1]]] = UNKNOWN
    free_s = _free_evidence(free, resolution, prior[0], prior[1]) if use_trinary else math.inf
    args = (
        lo, hi, resolution, z_min, z_max, i0, j0, cells, use_trinary, occupied, free,
        prior[0], prior[1], free_s, dirty, bi0, bj0,
    )  # fmt: skip
    return GridReading(cells, i0, j0, since, key, windowed, use_trinary, args)


def band_grid_step(
    reading: GridReading, shards: Sequence[BlockArrays], max_blocks: int | None = None
) -> None:
    """Raise ``reading``'s cells by the blocks from its ``cursor`` on, at most
    ``max_blocks`` of them (all: None), and move the cursor past them (None: done).
    ``shards`` as the store has them now; blocks keep their place while the map's epoch
    stays the same (new blocks come after the others)."""
    if reading.started and reading.cursor is None:
        return
    ranges, reading.cursor = block_ranges(shards, reading.cursor, max_blocks)
    reading.started = True
    for shard, start, stop in ranges:
        _band_max_percent(shards[shard][0], start, stop, *reading.args)


def band_grid_result(reading: GridReading, resolution: float) -> HitGrid:
    """The grid of a reading whose every block was read (``band_grid_step``)."""
    if not reading.started or reading.cursor is not None:
        raise ValueError("band_grid_result: blocks are left to read")
    cells = reading.cells
    if not cells.size:
        empty = BandCells(cells, 0, 0, reading.since, reading.key)
        return HitGrid(cells, resolution, (0.0, 0.0), empty)
    raw = None
    if not reading.windowed:
        raw = BandCells(cells.copy(), reading.i0, reading.j0, reading.since, reading.key)
    if reading.trinary:
        cells = finish_trinary(cells)
    return HitGrid(cells, resolution, (reading.i0 * resolution, reading.j0 * resolution), raw)


def _free_evidence(free: float, resolution: float, shape: float, rate: float) -> float:
    """An ``s`` from which on a voxel without a return has a hit probability below
    ``free`` (checked with ``hit_probability_one`` itself, which decreases with ``s``);
    inf when there is none."""
    if free <= 0.0:
        return math.inf
    step = (1.0 - free) ** (-1.0 / shape) - 1.0
    if not step > 0.0:
        return math.inf
    s = max(resolution / step - rate, 0.0) * (1.0 + 1e-6) + 1e-9
    return s if hit_probability_one(s, 0.0, resolution, shape, rate) < free else math.inf


@nb.njit(cache=True, nogil=True)
def _observed_extent(
    sa: ShardArrays,
    used: int,
    lo: IndexBox,
    hi: IndexBox,
    extent: NDArray[np.int64],
    since: int,
) -> None:
    """Widen ``extent`` [i_min, j_min, i_max, j_max] to the observed voxels in [lo, hi] of
    the blocks scans numbered ``since`` or later opened (-1: every block)."""
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(used):
        if sa.block_scan[b] < since:
            continue
        bx, by, bz = block_origin(sa.block_ijk, b)
        if block_outside(bx, by, bz, lo, hi):
            continue
        last = BLOCK_EDGE - 1
        if (
            extent[0] <= bx
            and bx + last <= extent[2]
            and extent[1] <= by
            and by + last <= extent[3]
        ):
            continue  # no voxel of the block can widen the extent
        block_values(sa, b, s_block, n_block)
        for v in range(BLOCK_VOXELS):
            if s_block[v] > 0.0 or n_block[v] > 0.0:
                dx, dy, dz = local_coords(v)
                x, y, z = bx + dx, by + dy, bz + dz
                if voxel_inside(x, y, z, lo, hi):
                    extent[0] = min(extent[0], x)
                    extent[1] = min(extent[1], y)
                    extent[2] = max(extent[2], x)
                    extent[3] = max(extent[3], y)


@nb.njit(cache=True, nogil=True)
def _dirty_columns(
    sa: ShardArrays,
    used: int,
    lo: IndexBox,
    hi: IndexBox,
    since: int,
    bi0: int,
    bj0: int,
    dirty: NDArray[np.bool_],
) -> None:
    """Mark ``dirty[by - bj0, bx - bi0]`` for each block (bx, by, bz) in [lo, hi] that a scan
    numbered ``since`` or later opened."""
    for b in range(used):
        if sa.block_scan[b] < since:
            continue
        x0, y0, z0 = block_origin(sa.block_ijk, b)
        if block_outside(x0, y0, z0, lo, hi):
            continue
        r, c = sa.block_ijk[b, 1] - bj0, sa.block_ijk[b, 0] - bi0
        if 0 <= r < dirty.shape[0] and 0 <= c < dirty.shape[1]:
            dirty[r, c] = True


@nb.njit(cache=True, nogil=True)
def _band_max_percent(
    sa: ShardArrays,
    start: int,
    stop: int,
    lo: IndexBox,
    hi: IndexBox,
    resolution: float,
    z_min: float,
    z_max: float,
    i0: int,
    j0: int,
    cells: NDArray[np.int8],
    trinary: bool,
    occupied: float,
    free: float,
    shape: float,
    rate: float,
    free_s: float,
    dirty: NDArray[np.bool_],
    bi0: int,
    bj0: int,
) -> None:
    """Raise each cell of ``cells`` (row j - j0, column i - i0) to round(100 p_hit) of the
    observed voxels in [lo, hi] whose centre height lies in [z_min, z_max]; with
    ``trinary``, to OCCUPIED (p >= occupied), FREE (p < free) or _UNCERTAIN.

    Shortcuts that leave the cells as the full computation would: a cell at 100 (the
    largest value) is not raised further, and with ``trinary`` a voxel without a return
    whose ``s`` is at least ``free_s`` is FREE without computing its probability
    (``_free_evidence``): 0.24 s -> 0.06 s for a 16.9 M-voxel map at 0.1 m (VLP-32C).
    A non-empty ``dirty`` (block columns from (bi0, bj0)): only the blocks of its marked
    columns are read. Blocks ``start..stop`` of the shard."""
    height, width = cells.shape
    s_block = np.empty(BLOCK_VOXELS)
    n_block = np.empty(BLOCK_VOXELS)
    for b in range(start, stop):
        if dirty.shape[0] > 0:
            r, c = sa.block_ijk[b, 1] - bj0, sa.block_ijk[b, 0] - bi0
            if not (0 <= r < dirty.shape[0] and 0 <= c < dirty.shape[1] and dirty[r, c]):
                continue
        bx, by, bz = block_origin(sa.block_ijk, b)
        if (
            block_outside(bx, by, bz, lo, hi)
            or bx + BLOCK_EDGE <= i0
            or bx >= i0 + width
            or by + BLOCK_EDGE <= j0
            or by >= j0 + height
        ):
            continue
        block_values(sa, b, s_block, n_block)
        for v in range(BLOCK_VOXELS):
            s, n = s_block[v], n_block[v]
            if not (s > 0.0 or n > 0.0):
                continue
            dx, dy, dz = local_coords(v)
            x, y, z = bx + dx, by + dy, bz + dz
            if not voxel_inside(x, y, z, lo, hi):
                continue
            zc = (np.float64(z) + 0.5) * resolution
            col, row = x - i0, y - j0
            if zc < z_min or zc > z_max or not (0 <= col < width and 0 <= row < height):
                continue
            if cells[row, col] >= OCCUPIED:
                continue  # the largest value already
            if trinary and n == 0.0 and s >= free_s:
                if cells[row, col] < FREE:
                    cells[row, col] = FREE
                continue
            p = min(max(hit_probability_one(s, n, resolution, shape, rate), 0.0), 1.0)
            if trinary:
                code = OCCUPIED if p >= occupied else (FREE if p < free else _UNCERTAIN)
                percent = np.int8(code)
            else:
                percent = np.int8(np.rint(100.0 * p))
            if percent > cells[row, col]:
                cells[row, col] = percent
