"""A Mapper from a map file or a tiled map, and a Mapper to a map file or a tiled map: the one
road between map files and the core (``load_map``, ``save_map``: what one writes, the other
reads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.reflectivity import rows_within, select_rows
from mfp_mapper.mapio.mapfile import map_arrays, mapper_from_arrays, read_map_arrays, write_map
from mfp_mapper.mapio.tiles import (
    DEFAULT_TILE_BLOCKS,
    VOXEL_KEYS,
    TiledMap,
    index_bounds,
    write_tiled,
)

MAP_FILE_SUFFIX = ".npz"
"""A map path with this suffix is one map file; any other is a tiled map (a directory)."""


def load_map(
    path: str | Path,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
    **overrides: object,
) -> Mapper:
    """Read a map written by ``save_map``, or a tiled map (a directory: ``mapio.tiles``);
    with ``bounds`` = (lower, upper) corners in metres, only the voxels whose centres lie
    inside (of a tiled map, only the tiles reaching into them are read). Keyword arguments
    override stored settings (not ``resolution`` or ``origin``); the stamps are checked
    against the decay time the map will have (``decay_time`` when overridden: a file's
    times are checked against the settings that will decay it). Raises ``MapFileError``
    naming the file and the problem."""
    p = Path(path)
    decay = overrides.get("decay_time")
    decay_time = None if decay is None else float(decay)  # type: ignore[arg-type]
    if p.is_dir():
        return TiledMap(p, decay_time).load(bounds, **overrides)
    arrays = read_map_arrays(p, check_duplicates=False, decay_time=decay_time)
    if bounds is not None:
        lo_i, hi_i = index_bounds(bounds, float(arrays["resolution"]), arrays.get("origin"))
        keep = np.all((arrays["ijk"] >= lo_i) & (arrays["ijk"] <= hi_i), axis=1)
        arrays = {**arrays, **{k: arrays[k][keep] for k in VOXEL_KEYS}}
        arrays.update(select_rows(arrays, rows_within(arrays, lo_i, hi_i)))
    return mapper_from_arrays(arrays, p, **overrides)


def is_map_file_name(path: str | Path) -> bool:
    """True when ``save_map`` writes ``path`` as one map file (``.npz``), False for a tiled
    map."""
    return Path(path).suffix == MAP_FILE_SUFFIX


def save_map(mapper: Mapper, path: str | Path, tile_blocks: int = DEFAULT_TILE_BLOCKS) -> int:
    """Write ``mapper`` where ``load_map`` reads it back: one map file when ``path`` ends in
    ``.npz`` (``mapio.mapfile``), else a tiled map of ``tile_blocks`` blocks a tile edge in
    the directory ``path`` (``mapio.tiles``; a new or empty directory, or a tiled map,
    replaced), both atomically. Returns the number of tiles written (0 for a map file);
    ``MapFileError`` when ``path`` cannot take a tiled map."""
    if is_map_file_name(path):
        write_map(path, mapper)
        return 0
    return len(write_tiled(path, map_arrays(mapper), tile_blocks))
