"""The 2D hit-probability map: a height band of the 3D map projected onto a grid (no ROS).

A cell of the grid holds ``round(100 * p)``, where ``p`` is the probability that a
horizontal ray crossing the cell's column at some height in the band ``[z_min, z_max]`` is
reflected there: the largest per-voxel hit probability (Eq. 31-34, a ray crossing one voxel
edge) among the observed voxels of the column whose centre lies in the band (centre
inclusion, as octomap_server's ``occupancy_min_z``/``occupancy_max_z``). The largest, because a
ray at the worst height is the one a planar robot must fear, as octomap_server's projected
map marks a cell occupied when any voxel of the band is. Cells whose band holds no observed
voxel are ``-1`` (unknown), the OccupancyGrid convention.

The grid is row-major, row ``r`` = y index, column ``c`` = x index, cell ``(r, c)`` covering
``[x0 + c * res, x0 + (c + 1) * res) x [y0 + r * res, y0 + (r + 1) * res)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

UNKNOWN = -1


@dataclass(frozen=True)
class HitGrid:
    """A 2D grid of hit probabilities in percent (int8, -1 unknown)."""

    data: NDArray[np.int8]
    """(height, width), row-major: ``data[row = y, col = x]``."""
    resolution: float
    origin: tuple[float, float]
    """Map-frame (x, y) of the corner of cell (0, 0)."""

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


def band_mask(ijk: NDArray[np.int32], resolution: float, z_min: float, z_max: float) -> NDArray:
    """Voxels whose centre height ``(k + 0.5) res`` lies in ``[z_min, z_max]``."""
    zc = (np.asarray(ijk)[:, 2].astype(np.float64) + 0.5) * resolution
    return (zc >= z_min) & (zc <= z_max)


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
) -> HitGrid:
    """Project voxels (integer indices ``ijk`` = floor(centre / resolution)) onto a grid.

    ``hit_probability``: per-voxel probability that a ray crossing one voxel edge is
    reflected. With ``center`` and ``radius > 0`` the grid is the square of half side
    ``radius`` around ``center`` (fixed size, whatever is mapped); otherwise it spans the
    (x, y) extent of all observed voxels given (0 x 0 when there are none).
    """
    if resolution <= 0.0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    if not z_min < z_max:
        raise ValueError(f"empty height band [{z_min}, {z_max}]")
    ijk_arr = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    prob = np.asarray(hit_probability, dtype=np.float64).reshape(-1)
    obs = np.asarray(observed, dtype=bool).reshape(-1)
    if not (len(ijk_arr) == len(prob) == len(obs)):
        raise ValueError("ijk, hit_probability and observed differ in length")

    if center is not None and radius > 0.0:
        i0 = math.floor((center[0] - radius) / resolution)
        j0 = math.floor((center[1] - radius) / resolution)
        i1 = math.floor((center[0] + radius) / resolution)
        j1 = math.floor((center[1] + radius) / resolution)
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
    percent = np.rint(100.0 * np.clip(np.nan_to_num(prob[sel], nan=1.0), 0.0, 1.0))
    flat = (j[sel] - j0) * width + (i[sel] - i0)
    out = np.full(width * height, UNKNOWN, dtype=np.int16)
    np.maximum.at(out, flat, percent.astype(np.int16))
    data = out.astype(np.int8).reshape(height, width)
    return HitGrid(data, resolution, (i0 * resolution, j0 * resolution))
