"""The box world of ANCHORS.md's benchmark scene, for tests and benchmarks (not installed).

An analytic world (flat ground, room walls, solid boxes) and the VLP-16 scene driven
through it, so tests and benchmarks feed the mapper the same kind of rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.offline.scan_pattern import scan_directions

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """An axis-aligned solid box, given by its min and max corners (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class BoxWorld:
    """Flat ground at z=0 inside a room of walls, with solid boxes (pillars, cars) in it."""

    half_extent: tuple[float, float] = (40.0, 25.0)
    boxes: tuple[Box, ...] = (
        Box((5.0, 3.0, 0.0), (7.0, 5.0, 3.0)),
        Box((-12.0, -8.0, 0.0), (-9.0, -4.0, 2.0)),
        Box((15.0, -10.0, 0.0), (16.0, -9.0, 6.0)),
        Box((-20.0, 10.0, 0.0), (-18.0, 14.0, 4.0)),
    )

    def cast(self, origin: FloatArray, directions: FloatArray) -> FloatArray:
        """Range (m) to the first surface along each unit direction; inf when none is hit."""
        o = np.asarray(origin, dtype=np.float64).reshape(-1, 3)
        d = directions
        rng = np.full(d.shape[0], np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            # ground plane z = 0, seen from above
            t = -o[:, 2] / d[:, 2]
            rng = np.where((d[:, 2] < 0) & (t > 0), np.minimum(rng, t), rng)
            # the room's walls, seen from inside
            for axis, half in ((0, self.half_extent[0]), (1, self.half_extent[1])):
                for wall in (-half, half):
                    t = (wall - o[:, axis]) / d[:, axis]
                    rng = np.where(t > 0, np.minimum(rng, t), rng)
            for box in self.boxes:
                rng = np.minimum(rng, _slab_entry(o, d, np.array(box.lo), np.array(box.hi)))
        return rng


def _slab_entry(o: FloatArray, d: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Distance at which each ray enters the box [lo, hi]; inf when it misses."""
    t1 = (lo - o) / d
    t2 = (hi - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (t_far >= np.maximum(t_near, 0.0)) & (t_near > 0)
    return np.where(hit, t_near, np.inf)


def anchors_scene(
    n_scans: int = 11, azimuths: int = 1800, step: float = 1.0, height: float = 1.8
) -> list[tuple[FloatArray, FloatArray]]:
    """The benchmark scene of ANCHORS.md: a VLP-16 driven along x through a box world.

    Returns one (points (N, 3), origin (3,)) per scan; rays that hit nothing are left out,
    as a driver leaves out points with no return.
    """
    world = BoxWorld()
    dirs = scan_directions(azimuths=azimuths)
    scans = []
    for k in range(n_scans):
        origin = np.array([-5.0 + step * k, 0.3 * k, height])
        rng = world.cast(origin, dirs)
        keep = np.isfinite(rng)
        scans.append((origin + dirs[keep] * rng[keep, None], origin))
    return scans
