"""The reference projection of voxels onto the 2D hit-probability grid (tests only).

Plain numpy over voxel arrays; the package's ``gridmap.start_band_grid`` (behind
``Mapper.hit_probability_grid``) reads the blocks in compiled code and is checked against it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from mfp_mapper.core.gridmap import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    HitGrid,
    _check_band,
    _window_cells,
    band_mask,
    check_trinary,
)


def hit_probability_grid(
    ijk: ArrayLike,
    hit_probability: ArrayLike,
    observed: ArrayLike,
    resolution: float,
    z_min: float,
    z_max: float,
    *,
    center: tuple[float, float] | None = None,
    radius: float = 0.0,
    trinary: tuple[float, float] | None = None,
) -> HitGrid:
    """Project voxels (integer indices ``ijk`` = floor(centre / resolution)) onto a grid.

    ``hit_probability``: per-voxel probability that a ray crossing one voxel edge is
    reflected. With ``center`` and ``radius > 0`` the grid is the square of half side
    ``radius`` around ``center`` (fixed size, whatever is mapped); otherwise it spans the
    (x, y) extent of all observed voxels given (0 x 0 when there are none).

    The reference ``Mapper.hit_probability_grid`` (the compiled ``gridmap.start_band_grid``,
    which reads the blocks) must match exactly: written with plain numpy over ``Mapper.voxels()``.
    """
    _check_band(resolution, z_min, z_max)
    use_trinary, occupied, free = check_trinary(trinary)
    ijk_arr = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    prob = np.asarray(hit_probability, dtype=np.float64).reshape(-1)
    obs = np.asarray(observed, dtype=bool).reshape(-1)
    if not (len(ijk_arr) == len(prob) == len(obs)):
        raise ValueError("ijk, hit_probability and observed differ in length")

    if center is not None and radius > 0.0:
        i0, j0, i1, j1 = _window_cells(center, radius, resolution)
    elif obs.any():
        seen = ijk_arr[obs]
        i0, j0 = (int(v) for v in seen[:, :2].min(axis=0))
        i1, j1 = (int(v) for v in seen[:, :2].max(axis=0))
    else:
        return HitGrid(np.zeros((0, 0), np.int8), resolution, (0.0, 0.0))
    width, height = i1 - i0 + 1, j1 - j0 + 1

    i, j = ijk_arr[:, 0], ijk_arr[:, 1]
    sel = (
        obs
        & band_mask(ijk_arr, resolution, z_min, z_max)
        & (i >= i0)
        & (i <= i1)
        & (j >= j0)
        & (j <= j1)
    )
    p = np.clip(np.nan_to_num(prob[sel], nan=1.0), 0.0, 1.0)
    flat = (j[sel] - j0) * width + (i[sel] - i0)
    out = np.full(width * height, UNKNOWN, dtype=np.int16)
    if use_trinary:  # occupied wins, then uncertain, then free: evaluated per cell
        occupied_cells = np.zeros(width * height, bool)
        uncertain_cells = np.zeros(width * height, bool)
        occupied_cells[flat[p >= occupied]] = True
        uncertain_cells[flat[(p >= free) & (p < occupied)]] = True
        out[flat] = FREE
        out[uncertain_cells] = UNKNOWN
        out[occupied_cells] = OCCUPIED
        return HitGrid(
            out.astype(np.int8).reshape(height, width),
            resolution,
            (i0 * resolution, j0 * resolution),
        )
    np.maximum.at(out, flat, np.rint(100.0 * p).astype(np.int16))
    data = out.astype(np.int8).reshape(height, width)
    return HitGrid(data, resolution, (i0 * resolution, j0 * resolution))
