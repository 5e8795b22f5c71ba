"""Scan patterns of spinning lidars (ray directions), for the simulator and the benchmarks."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

VLP16_ELEVATIONS_DEG = np.arange(-15.0, 16.0, 2.0)


def scan_directions(
    elevations_deg: NDArray[np.float64] = VLP16_ELEVATIONS_DEG, azimuths: int = 1800
) -> FloatArray:
    """Unit ray directions of a spinning lidar, beam-major (len(elevations) * azimuths, 3)."""
    elev = np.deg2rad(np.asarray(elevations_deg, dtype=np.float64))[:, None]
    azim = np.linspace(0.0, 2.0 * np.pi, azimuths, endpoint=False)[None, :]
    cos_e = np.cos(elev)
    dirs = np.stack(
        np.broadcast_arrays(cos_e * np.cos(azim), cos_e * np.sin(azim), np.sin(elev)), axis=-1
    )
    return np.ascontiguousarray(dirs.reshape(-1, 3))
