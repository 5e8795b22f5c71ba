"""The box world of the core benchmark's scene, for tests and benchmarks (not installed).

An analytic world (flat ground, room walls, solid boxes) and the VLP-16 scene driven
through it, so tests and benchmarks feed the mapper the same kind of rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.sources.scan_pattern import scan_directions
from mfp_mapper.sources.simulate import Scene, Solid

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """An axis-aligned solid box, given by its min and max corners (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class BoxWorld:
    """Flat ground at z=0 inside a room of walls, with solid boxes (pillars, cars) in it.

    A ``simulate.Scene`` without ceiling whose walls have no top: rays are cast by the
    simulator's caster (``Scene.cast``), the one box ray-caster of the project.
    """

    half_extent: tuple[float, float] = (40.0, 25.0)
    boxes: tuple[Box, ...] = (
        Box((5.0, 3.0, 0.0), (7.0, 5.0, 3.0)),
        Box((-12.0, -8.0, 0.0), (-9.0, -4.0, 2.0)),
        Box((15.0, -10.0, 0.0), (16.0, -9.0, 6.0)),
        Box((-20.0, 10.0, 0.0), (-18.0, 14.0, 4.0)),
    )

    def scene(self) -> Scene:
        hx, hy = self.half_extent
        return Scene(
            room_lo=(-hx, -hy, 0.0),
            room_hi=(hx, hy, math.inf),
            solids=tuple(Solid(f"box{k}", b.lo, b.hi) for k, b in enumerate(self.boxes)),
            enclosed=False,
            wall_height=math.inf,
        )

    def cast(self, origin: FloatArray, directions: FloatArray) -> FloatArray:
        """Range (m) to the first surface along each unit direction; inf when none is hit."""
        ranges, _ = self.scene().cast(origin, directions, np.random.default_rng(0))
        return ranges


def anchors_scene(
    n_scans: int = 11, azimuths: int = 1800, step: float = 1.0, height: float = 1.8
) -> list[tuple[FloatArray, FloatArray]]:
    """The core benchmark's scene: a VLP-16 driven along x through a box world.

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
