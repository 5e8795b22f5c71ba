"""Exact for hours: a voxel's sums keep adding however long a sensor stays (``shard.flush``).

A parked sensor integrates the same scan again and again: the voxels around it take a chord
from nearly every ray of every scan. In float32 alone their ``s`` stops adding once a chord
is below half its spacing (2**-24 of the sum); the store moves a voxel's float32 parts into
float64 before that (``shard.FLUSH_EDGES``, ``shard.N_LIMIT``). Before, the voxel at the
sensor ended far below the sum of its parts.
"""

from __future__ import annotations

import numpy as np
import pytest

from mfp_mapper import Mapper
from mfp_mapper.core.shard import HI_USED

RES = 0.1
SCANS = 3000


def chords_float64(origin: np.ndarray, end: np.ndarray) -> dict[tuple[int, int, int], float]:
    """Chord of the segment in every voxel of its bounding box, in float64 (slab clipping)."""
    lo = np.floor(np.minimum(origin, end) / RES).astype(int)
    hi = np.floor(np.maximum(origin, end) / RES).astype(int)
    axes = [np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d = end - origin
    t_in, t_out = np.zeros(len(grid)), np.ones(len(grid))
    for axis in range(3):
        box_lo, box_hi = grid[:, axis] * RES, (grid[:, axis] + 1) * RES
        if d[axis] == 0.0:
            inside = (origin[axis] >= box_lo) & (origin[axis] < box_hi)
            t_out = np.where(inside, t_out, -1.0)
            continue
        t1, t2 = (box_lo - origin[axis]) / d[axis], (box_hi - origin[axis]) / d[axis]
        t_in, t_out = np.maximum(t_in, np.minimum(t1, t2)), np.minimum(t_out, np.maximum(t1, t2))
    chord = np.clip(t_out - t_in, 0.0, None) * float(np.linalg.norm(d))
    keep = chord > 0
    return {tuple(v): c for v, c in zip(grid[keep].tolist(), chord[keep], strict=True)}


def parked_scan() -> tuple[np.ndarray, np.ndarray]:
    """8000 returns on the walls of a 1 m x 0.8 m x 0.6 m box around the sensor (a small
    scan, so that the test runs in seconds, with a real scan's chords at the sensor: the
    voxel there takes 400 m a scan, 1.2e6 m in all)."""
    rng = np.random.default_rng(7)
    origin = np.array([0.0123, 0.0271, 0.0347])
    directions = rng.normal(size=(8000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    half = np.array([0.5, 0.4, 0.3])
    reach = np.min(np.abs(half / np.where(directions == 0.0, 1e-12, directions)), axis=1)
    return origin + directions * reach[:, None] * 0.999, origin


@pytest.mark.parametrize("path", ["integrate", "stage"])
def test_parked_sensor_keeps_every_sum(path: str) -> None:
    """3000 scans (5 minutes at 10 Hz, no decay), integrated directly or staged and
    merged (the node's path): every ``s`` within 1e-3 of the float64 sum, ``n`` exact."""
    points, origin = parked_scan()
    mapper = Mapper(RES, max_range=10.0, min_range=0.0)
    for k in range(SCANS):
        if path == "integrate":
            mapper.integrate(points, origin, 0.1 * k)
        else:
            mapper.commit(mapper.stage(points, origin, 0.1 * k))
    # the float64 sum of every voxel's parts: the same scan's chords, SCANS times
    expected_s: dict[tuple[int, int, int], float] = {}
    expected_n: dict[tuple[int, int, int], float] = {}
    for end in points:
        for voxel, chord in chords_float64(origin, end).items():
            expected_s[voxel] = expected_s.get(voxel, 0.0) + SCANS * chord
        hit = tuple(np.floor(end / RES).astype(int).tolist())
        expected_n[hit] = expected_n.get(hit, 0.0) + SCANS
    voxels = mapper.voxels()
    s = dict(zip(map(tuple, voxels.ijk.tolist()), voxels.s, strict=True))
    n = dict(zip(map(tuple, voxels.ijk.tolist()), voxels.n, strict=True))
    # the voxel at the sensor took a chord from every ray: far beyond what float32 adds to
    at_sensor = tuple(np.floor(origin / RES).astype(int).tolist())
    assert expected_s[at_sensor] > 2**24 * 0.05  # float32 adds no 5 cm chord to that
    tiny = 1e-6 * SCANS  # chords below float32's reach in a walk that rounds its faces
    for voxel, total in expected_s.items():
        if total > tiny:
            assert abs(s.get(voxel, 0.0) - total) <= 1e-3 * total, voxel
    assert all(expected_s.get(v, 0.0) > 0.0 or value < tiny for v, value in s.items())
    assert {v: value for v, value in n.items() if value > 0} == expected_n  # n exact


def test_flushes_bit_for_bit_with_two_threads() -> None:
    """The float64 parts are flushed per block after each scan: one and two threads (a
    shard each) give the same sums, bit for bit."""
    points, origin = parked_scan()
    maps = []
    for threads in (1, 2):
        mapper = Mapper(RES, max_range=10.0, min_range=0.0, threads=threads)
        for k in range(200):  # the voxel at the sensor passes the float32 limit each scan
            mapper.integrate(points, origin, 0.1 * k)
        maps.append(mapper.stored_voxels())
        assert sum(int(sh.pools[HI_USED]) for sh in mapper._store.shards) > 0  # flushed
        mapper.close()
    one, two = maps
    order_one, order_two = np.lexsort(one.ijk.T), np.lexsort(two.ijk.T)
    np.testing.assert_array_equal(one.ijk[order_one], two.ijk[order_two])
    np.testing.assert_array_equal(one.s[order_one], two.s[order_two])
    np.testing.assert_array_equal(one.n[order_one], two.n[order_two])
