"""A Mapper from a map file or a tiled map, and a Mapper to a map file: the one road between
map files and the core (``load_map``, ``save_map``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.mapfile import mapper_from_arrays, read_map_arrays, write_map
from mfp_mapper.mapio.tiles import VOXEL_KEYS, TiledMap, index_bounds


def load_map(
    path: str | Path,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
    **overrides: object,
) -> Mapper:
    """Read a map written by ``save_map``, or a tiled map (a directory: ``mapio.tiles``);
    with ``bounds`` = (lower, upper) corners in metres, only the voxels whose centres lie
    inside (of a tiled map, only the tiles reaching into them are read). Keyword arguments
    override stored settings (not ``resolution`` or ``origin``). Raises ``MapFileError``
    naming the file and the problem."""
    p = Path(path)
    if p.is_dir():
        return TiledMap(p).load(bounds, **overrides)
    arrays = read_map_arrays(p, check_duplicates=False)
    if bounds is not None:
        lo_i, hi_i = index_bounds(bounds, float(arrays["resolution"]), arrays.get("origin"))
        keep = np.all((arrays["ijk"] >= lo_i) & (arrays["ijk"] <= hi_i), axis=1)
        arrays = {**arrays, **{k: arrays[k][keep] for k in VOXEL_KEYS}}
    return mapper_from_arrays(arrays, p, **overrides)


def save_map(mapper: Mapper, path: str | Path) -> None:
    """Write ``mapper`` to the map file ``path`` (.npz) atomically (``mapio.mapfile``)."""
    write_map(path, mapper)
