"""Exact voxel traversal (Amanatides & Woo) of lidar rays, compiled with numba.

A ray runs from its origin to its end point (the first return, or the point where it was
cut at ``max_range``). The walk emits one *contribution* per voxel crossed: the voxel's
packed index and the chord length in metres the ray travelled inside it. The chords of a
ray add up to its length. A ray that ends with a return also emits its end voxel once more
as a *hit*; the chord from the entry to the return point is already among its crossings.

Voxel index = floor(coordinate / resolution), packed into one int64 key by ``pack_key``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
MAX_VOXEL_INDEX = KEY_OFFSET - 1
"""Largest |voxel index| a key can hold (about 104 km at 0.1 m)."""


@nb.njit(inline="always", cache=True)
def pack_key(vx: int, vy: int, vz: int) -> int:
    """One int64 key from a voxel index (each component within +-MAX_VOXEL_INDEX)."""
    return ((vx + KEY_OFFSET) << (2 * KEY_BITS)) | ((vy + KEY_OFFSET) << KEY_BITS) | (vz + KEY_OFFSET)


@nb.njit(inline="always", cache=True)
def unpack_key(key: int) -> tuple[int, int, int]:
    """The voxel index packed in ``key``."""
    return (
        ((key >> (2 * KEY_BITS)) & KEY_MASK) - KEY_OFFSET,
        ((key >> KEY_BITS) & KEY_MASK) - KEY_OFFSET,
        (key & KEY_MASK) - KEY_OFFSET,
    )


def pack_keys(ijk: NDArray[np.int64]) -> NDArray[np.int64]:
    """Vectorised ``pack_key`` for an (N, 3) integer array."""
    v = ijk.astype(np.int64) + KEY_OFFSET
    return (v[:, 0] << (2 * KEY_BITS)) | (v[:, 1] << KEY_BITS) | v[:, 2]


def visit_bounds(origins_vox: NDArray[np.float64], ends_vox: NDArray[np.float64]) -> NDArray[np.int64]:
    """Upper bound of the voxels each ray visits: the Manhattan voxel distance plus slack."""
    delta = np.abs(np.floor(ends_vox) - np.floor(origins_vox)).sum(axis=1)
    return delta.astype(np.int64) + 4


@nb.njit(cache=True, nogil=True)
def walk_rays(
    origins_vox: NDArray[np.float64],
    ends_vox: NDArray[np.float64],
    lengths: NDArray[np.float64],
    has_return: NDArray[np.bool_],
    first: int,
    last: int,
    out_keys: NDArray[np.int64],
    out_chords: NDArray[np.float32],
    out_hits: NDArray[np.int64],
    out_start: int,
    hit_start: int,
) -> tuple[int, int]:
    """Walk rays ``first..last-1`` and write their contributions from ``out_start`` on.

    Coordinates are in voxel units (metres / resolution); ``lengths`` are the rays' lengths
    in metres. Returns (number of crossings written, number of hits written). The caller
    sizes ``out_*`` with ``visit_bounds``.
    """
    k = out_start
    h = hit_start
    for r in range(first, last):
        ox = origins_vox[r, 0]
        oy = origins_vox[r, 1]
        oz = origins_vox[r, 2]
        dx = ends_vox[r, 0] - ox
        dy = ends_vox[r, 1] - oy
        dz = ends_vox[r, 2] - oz
        length = lengths[r]
        vx = int(np.floor(ox))
        vy = int(np.floor(oy))
        vz = int(np.floor(oz))
        ex = int(np.floor(ends_vox[r, 0]))
        ey = int(np.floor(ends_vox[r, 1]))
        ez = int(np.floor(ends_vox[r, 2]))
        # ray parameter t in [0, 1]; t_max: where the next face on each axis is crossed
        step_x = 1 if dx > 0 else -1
        step_y = 1 if dy > 0 else -1
        step_z = 1 if dz > 0 else -1
        if dx != 0.0:
            t_max_x = ((vx + (1 if dx > 0 else 0)) - ox) / dx
            t_delta_x = abs(1.0 / dx)
        else:
            t_max_x = np.inf
            t_delta_x = np.inf
        if dy != 0.0:
            t_max_y = ((vy + (1 if dy > 0 else 0)) - oy) / dy
            t_delta_y = abs(1.0 / dy)
        else:
            t_max_y = np.inf
            t_delta_y = np.inf
        if dz != 0.0:
            t_max_z = ((vz + (1 if dz > 0 else 0)) - oz) / dz
            t_delta_z = abs(1.0 / dz)
        else:
            t_max_z = np.inf
            t_delta_z = np.inf
        budget = abs(ex - vx) + abs(ey - vy) + abs(ez - vz) + 3
        t_prev = 0.0
        while True:
            t_next = min(t_max_x, t_max_y, t_max_z)
            final = t_next >= 1.0 or (vx == ex and vy == ey and vz == ez) or budget <= 1
            if final:
                t_next = 1.0
            chord = (t_next - t_prev) * length
            if chord > 0.0:
                out_keys[k] = pack_key(vx, vy, vz)
                out_chords[k] = chord
                k += 1
            if final:
                break
            t_prev = t_next
            budget -= 1
            if t_max_x <= t_max_y and t_max_x <= t_max_z:
                vx += step_x
                t_max_x += t_delta_x
            elif t_max_y <= t_max_z:
                vy += step_y
                t_max_y += t_delta_y
            else:
                vz += step_z
                t_max_z += t_delta_z
        if has_return[r]:
            out_hits[h] = pack_key(vx, vy, vz)
            h += 1
    return k - out_start, h - hit_start
