"""The simulator's scenes: a room with opaque boxes and boxes of participating medium.

A ray travels until a first return: inside a medium after an exponentially distributed free
path of rate ``lambda`` (docs/model.md, "A physics check"), otherwise at the first solid surface.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


# surface codes of each return, for intensities (and tests)
SURFACE_FLOOR, SURFACE_CEILING, SURFACE_WALL, SURFACE_SOLID, SURFACE_MEDIUM = range(5)


class SimulationError(ValueError):
    """The scene or the options are inconsistent, or the output cannot be written."""


@dataclass(frozen=True)
class Solid:
    """An opaque axis-aligned box (lo, hi corners, metres)."""

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class Medium:
    """A box of participating medium with uniform extinction (returns per metre)."""

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    extinction: float


@dataclass(frozen=True)
class Scene:
    """A room ``[room_lo, room_hi]`` (floor at room_lo z) with solids and media inside.

    With ``enclosed`` the walls go up to a ceiling at ``room_hi`` z: every ray returns.
    Without it there is no ceiling and the walls stop at ``wall_height``: rays can escape.
    """

    room_lo: tuple[float, float, float] = (-14.0, -10.0, 0.0)
    room_hi: tuple[float, float, float] = (14.0, 10.0, 5.0)
    solids: tuple[Solid, ...] = ()
    media: tuple[Medium, ...] = ()
    enclosed: bool = True
    wall_height: float = 2.0

    def validate(self) -> None:
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)
        if not np.all(hi > lo):
            raise SimulationError(f"room_hi {self.room_hi} must exceed room_lo {self.room_lo}")
        boxes: list[tuple[str, FloatArray, FloatArray]] = [
            (b.name, np.array(b.lo), np.array(b.hi)) for b in self.solids
        ] + [(m.name, np.array(m.lo), np.array(m.hi)) for m in self.media]
        for name, blo, bhi in boxes:
            if not np.all(bhi > blo):
                raise SimulationError(f"box {name!r}: hi {bhi} must exceed lo {blo}")
        for m in self.media:
            if not (m.extinction > 0 and math.isfinite(m.extinction)):
                raise SimulationError(f"medium {m.name!r}: extinction must be > 0 per metre")
        for a in range(len(self.media)):
            for b in range(a + 1, len(self.media)):
                ma, mb = self.media[a], self.media[b]
                if np.all(np.array(ma.lo) < np.array(mb.hi)) and np.all(
                    np.array(mb.lo) < np.array(ma.hi)
                ):
                    raise SimulationError(f"media {ma.name!r} and {mb.name!r} overlap")

    def cast(
        self, origins: FloatArray, directions: FloatArray, rng: np.random.Generator
    ) -> tuple[FloatArray, NDArray[np.int8]]:
        """First-return range (inf: no return) and surface code of each unit-direction ray."""
        o = np.broadcast_to(np.asarray(origins, dtype=np.float64), directions.shape)
        d = directions
        rng_solid = np.full(d.shape[0], np.inf)
        code = np.full(d.shape[0], -1, dtype=np.int8)
        lo, hi = np.array(self.room_lo), np.array(self.room_hi)

        def take(t: FloatArray, ok: NDArray[np.bool_], what: int) -> None:
            closer = ok & (t > 0) & (t < rng_solid)
            rng_solid[closer] = t[closer]
            code[closer] = what

        with np.errstate(divide="ignore", invalid="ignore"):
            take((lo[2] - o[:, 2]) / d[:, 2], d[:, 2] < 0, SURFACE_FLOOR)
            if self.enclosed:
                take((hi[2] - o[:, 2]) / d[:, 2], d[:, 2] > 0, SURFACE_CEILING)
            top = hi[2] if self.enclosed else lo[2] + self.wall_height
            for axis in (0, 1):
                for wall, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
                    t = (wall - o[:, axis]) / d[:, axis]
                    z = o[:, 2] + t * d[:, 2]
                    take(t, (sign * d[:, axis] > 0) & (z <= top), SURFACE_WALL)
            for solid in self.solids:
                t_in, t_out = slab(o, d, np.array(solid.lo), np.array(solid.hi))
                take(t_in, (t_out >= t_in) & (t_in > 0), SURFACE_SOLID)
            ranges = rng_solid.copy()
            if self.media:
                enters, exits = [], []
                for medium in self.media:
                    t_in, t_out = slab(o, d, np.array(medium.lo), np.array(medium.hi))
                    t_in = np.maximum(t_in, 0.0)
                    t_out = np.minimum(t_out, rng_solid)
                    enters.append(np.where(t_out > t_in, t_in, np.inf))
                    exits.append(t_out)
                enter = np.stack(enters, axis=1)
                leave = np.stack(exits, axis=1)
                lam = np.array([m.extinction for m in self.media])
                # media are disjoint: visit them in the order the ray enters them
                order = np.argsort(enter, axis=1)
                done = np.zeros(d.shape[0], dtype=bool)
                for k in range(len(self.media)):
                    idx = order[:, k]
                    t_in = np.take_along_axis(enter, idx[:, None], 1)[:, 0]
                    t_out = np.take_along_axis(leave, idx[:, None], 1)[:, 0]
                    crosses = ~done & np.isfinite(t_in)
                    free_path = rng.exponential(1.0, d.shape[0]) / lam[idx]
                    hit = crosses & (free_path < t_out - t_in)
                    ranges[hit] = t_in[hit] + free_path[hit]
                    code[hit] = SURFACE_MEDIUM
                    done |= hit
        return ranges, code

    def to_json(self) -> dict[str, Any]:
        return {
            "room_lo": list(self.room_lo),
            "room_hi": list(self.room_hi),
            "enclosed": self.enclosed,
            "wall_height": self.wall_height,
            "solids": [asdict(s) for s in self.solids],
            "media": [{**asdict(m), "mean_free_path": 1.0 / m.extinction} for m in self.media],
        }


def slab(o: FloatArray, d: FloatArray, lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, ...]:
    """Entry and exit distances of each ray through the box (t_out < t_in: missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    # a zero direction component: inside the slab -> (-inf, inf), outside -> empty
    inside = (o >= lo) & (o <= hi)
    t_lo = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    return t_lo.max(axis=1), t_hi.min(axis=1)


@dataclass(frozen=True)
class Circle:
    """The robot (base_link, on the floor) drives a circle counter-clockwise at ``speed``."""

    center: tuple[float, float] = (0.0, 0.0)
    radius: float = 8.0
    speed: float = 3.0
    start_angle: float = -0.5 * math.pi

    def pose(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Positions (N, 3) and yaw (N,) at ``t`` seconds since the start."""
        theta = self.start_angle + self.speed / self.radius * np.asarray(t, dtype=np.float64)
        pos = np.stack(
            [
                self.center[0] + self.radius * np.cos(theta),
                self.center[1] + self.radius * np.sin(theta),
                np.zeros_like(theta),
            ],
            axis=-1,
        )
        return pos, theta + 0.5 * math.pi


def builtin_scene() -> Scene:
    """The demo scene: a hall with pillars, a car, a dense bush and a lighter hedge."""
    return Scene(
        room_lo=(-14.0, -11.0, 0.0),
        room_hi=(14.0, 11.0, 5.0),
        solids=(
            Solid("pillar_ne", (9.5, 5.5, 0.0), (10.5, 6.5, 5.0)),
            Solid("pillar_sw", (-10.5, -6.5, 0.0), (-9.5, -5.5, 5.0)),
            Solid("car", (-12.0, 2.0, 0.0), (-10.5, 6.5, 1.5)),
            Solid("crate", (3.0, -3.5, 0.0), (4.0, -2.5, 1.0)),
        ),
        media=(
            Medium("bush", (-2.0, -1.5, 0.2), (2.0, 1.5, 2.6), extinction=1.0),
            Medium("hedge", (11.0, -5.0, 0.0), (12.0, 3.0, 2.0), extinction=0.4),
        ),
    )


def physics_scene() -> Scene:
    """A small closed room around one cube of medium (lambda = 1 /m): the physics test."""
    return Scene(
        room_lo=(-7.0, -7.0, 0.0),
        room_hi=(7.0, 7.0, 4.0),
        media=(Medium("cube", (-0.8, -0.8, 0.4), (0.8, 0.8, 2.0), extinction=1.0),),
    )
