"""A brute-force, pure-Python scan likelihood: the independent implementation that
``core.likelihood`` and ``score`` are checked against (no DDA: every face crossing of a ray
is found and sorted; statistics read one voxel at a time with ``Mapper.query``)."""

from __future__ import annotations

import math

import numpy as np

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.traversal import RETURN_CHORD_FLOOR


def segments(
    o: np.ndarray, e: np.ndarray, res: float
) -> list[tuple[tuple[int, ...], float, float]]:
    """Voxels crossed from o to e (metres), found independently of the DDA: every face
    crossing parameter on every axis, sorted; each piece's midpoint names its voxel.
    Returns (voxel, t0, t1) with t in [0, 1] along o -> e."""
    d = e - o
    ts = {0.0, 1.0}
    for axis in range(3):
        if d[axis] == 0.0:
            continue
        a, b = sorted((o[axis] / res, e[axis] / res))
        for k in range(math.floor(a) + 1, math.ceil(b)):
            ts.add((k * res - o[axis]) / d[axis])
    cuts = sorted(t for t in ts if 0.0 <= t <= 1.0)
    out = []
    for t0, t1 in zip(cuts[:-1], cuts[1:], strict=False):
        if t1 <= t0:
            continue
        mid = o + d * (0.5 * (t0 + t1))
        out.append((tuple(int(v) for v in np.floor(mid / res)), t0, t1))
    return out


def exit_t(o: np.ndarray, e: np.ndarray, voxel: tuple[int, ...], res: float) -> float:
    """Parameter where the line o -> e (continued) leaves ``voxel``."""
    d = e - o
    best = math.inf
    for axis in range(3):
        if d[axis] > 0:
            best = min(best, ((voxel[axis] + 1) * res - o[axis]) / d[axis])
        elif d[axis] < 0:
            best = min(best, (voxel[axis] * res - o[axis]) / d[axis])
    return best


def reference(
    mapper: Mapper,
    points: np.ndarray,
    origin: np.ndarray,
    stamp: float,
    no_return: np.ndarray,
    shape: float,
    rate: float,
) -> tuple[np.ndarray, list[tuple[float, float, float, bool]]]:
    """Per-ray log-likelihood and the events (s, n, chord, hit), in plain Python. A
    return's chord is at least ``RETURN_CHORD_FLOOR`` (docs/model.md)."""
    res = mapper.resolution
    lls, events = [], []
    for i, p in enumerate(points):
        length = float(np.linalg.norm(p - origin))
        end = p
        ret = not no_return[i]
        if length > mapper.max_range:
            end = origin + (p - origin) * (mapper.max_range / length)
            length, ret = mapper.max_range, False
        segs = segments(origin, end, res)
        end_voxel = tuple(int(v) for v in np.floor(end / res))
        if ret and segs[-1][0] != end_voxel:
            # the point lies on an edge of the voxel it floors to, which the ray only
            # touches there: its return event covers none of the ray but the floor
            segs.append((end_voxel, 1.0, 1.0))
        total = 0.0
        for k, (voxel, t0, t1) in enumerate(segs):
            last = k == len(segs) - 1
            stats = mapper.query(((np.array(voxel) + 0.5) * res)[None], stamp)
            s, n = float(stats.s[0]), float(stats.n[0])
            if last and ret:
                assert voxel == end_voxel
                exit_chord = max(exit_t(origin, end, voxel, res), 1.0) - t0
                chord = max(exit_chord * length, RETURN_CHORD_FLOOR)
                p_pass = ((s + rate) / (s + rate + chord)) ** (n + shape)
                total += math.log(1.0 - p_pass)
                events.append((s, n, chord, True))
            else:
                chord = (t1 - t0) * length
                total += (n + shape) * math.log((s + rate) / (s + rate + chord))
                events.append((s, n, chord, False))
        lls.append(total)
    return np.array(lls), events
