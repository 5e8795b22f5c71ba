"""``Mapper.load`` and ``Mapper.from_arrays``: a Mapper from a map file (or a region of a
map file or of a tiled map), or from voxel arrays."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from mfp_mapper.core.mapfile import MapFileError, read_map_file, voxel_problem
from mfp_mapper.core.store import VoxelArrays

if TYPE_CHECKING:
    from mfp_mapper.core.mapper import Mapper


def load_map(
    cls: type[Mapper],
    path: str | Path,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
    **overrides: object,
) -> Mapper:
    """See ``Mapper.load``."""
    if bounds is not None or Path(path).is_dir():
        from mfp_mapper.core.tiles import load_map as load_region

        return load_region(path, bounds, **overrides)
    contents = read_map_file(path)
    settings: dict[str, object] = {
        "decay_time": contents.decay_time,
        "frame_id": contents.frame_id,
        **contents.ranges,
        **overrides,
    }
    for fixed, stored in (("resolution", contents.resolution), ("origin", contents.origin)):
        if fixed in settings and np.any(np.asarray(settings.pop(fixed)) != stored):
            raise MapFileError(path, f"stored {fixed} {stored} cannot be changed")
    try:
        return cls.from_arrays(
            contents.voxels, resolution=contents.resolution, origin=contents.origin, **settings
        )
    except ValueError as err:
        raise MapFileError(path, str(err)) from err


def from_arrays(
    cls: type[Mapper],
    voxels: VoxelArrays,
    *,
    resolution: float,
    origin: ArrayLike = (0.0, 0.0, 0.0),
    **settings: object,
) -> Mapper:
    """See ``Mapper.from_arrays``."""
    problem = voxel_problem(voxels.ijk, voxels.s, voxels.n, voxels.t_last)
    if problem:
        raise ValueError(problem)
    count = voxels.ijk.shape[0]
    if voxels.ijk.shape != (count, 3) or any(
        a.shape != (count,) for a in (voxels.s, voxels.n, voxels.t_last)
    ):
        raise ValueError("voxels need ijk (N, 3) and s, n, t_last (N,)")
    mapper = cls(resolution, origin=origin, **settings)  # type: ignore[arg-type]
    mapper._store.assign(voxels, mapper.decay_time)
    finite_t = voxels.t_last[np.isfinite(voxels.t_last)]
    mapper.last_stamp = float(finite_t.max()) if finite_t.size else None
    mapper.version += 1
    return mapper
