"""The ray walk against an independent brute force: exact chord lengths of a segment in boxes."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mfp_mapper import Mapper
from mfp_mapper.core.lockstep import T_NEVER, T_ONE
from mfp_mapper.core.traversal import ray_bounds

RES = 0.25


def brute_force_chords(
    origin: np.ndarray, end: np.ndarray, res: float
) -> dict[tuple[int, int, int], float]:
    """Chord length of the segment in every voxel of its bounding box (slab clipping)."""
    lo = np.floor(np.minimum(origin, end) / res).astype(int) - 1
    hi = np.floor(np.maximum(origin, end) / res).astype(int) + 1
    grid = np.stack(
        np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)], indexing="ij"), -1
    ).reshape(-1, 3)
    d = end - origin
    length = float(np.linalg.norm(d))
    t_in = np.zeros(len(grid))
    t_out = np.ones(len(grid))
    for axis in range(3):
        box_lo, box_hi = grid[:, axis] * res, (grid[:, axis] + 1) * res
        if d[axis] == 0.0:
            inside = (origin[axis] >= box_lo) & (origin[axis] < box_hi)
            t_out = np.where(inside, t_out, -1.0)
            continue
        with np.errstate(over="ignore"):  # a tiny direction component: the slab is at infinity
            t1, t2 = (box_lo - origin[axis]) / d[axis], (box_hi - origin[axis]) / d[axis]
        t_in = np.maximum(t_in, np.minimum(t1, t2))
        t_out = np.minimum(t_out, np.maximum(t1, t2))
    chord = np.clip(t_out - t_in, 0.0, None) * length
    keep = chord > 0
    return {tuple(v): c for v, c in zip(grid[keep].tolist(), chord[keep], strict=True)}


def map_chords(
    mapper: Mapper,
) -> tuple[dict[tuple[int, int, int], float], dict[tuple[int, int, int], float]]:
    vox = mapper.voxels()
    s = {tuple(v): c for v, c in zip(vox.ijk.tolist(), vox.s, strict=True) if c > 0}
    n = {tuple(v): c for v, c in zip(vox.ijk.tolist(), vox.n, strict=True) if c > 0}
    return s, n


def assert_walk_matches(origin: np.ndarray, end: np.ndarray, has_return: bool = True) -> None:
    mapper = Mapper(RES, max_range=1e4)
    summary = mapper.integrate(end[None, :], origin, stamp=0.0)
    assert summary.rays_used == 1
    s, n = map_chords(mapper)
    expected = brute_force_chords(origin, end, RES)
    tol = 1e-5 * max(1.0, float(np.linalg.norm(end - origin)))
    # every voxel with a chord longer than the tolerance is found, with that chord (float32)
    for voxel, chord in expected.items():
        if chord > tol:
            assert s.get(voxel, 0.0) == pytest.approx(chord, rel=1e-5, abs=tol), voxel
    for voxel, chord in s.items():
        assert expected.get(voxel, 0.0) == pytest.approx(chord, rel=1e-5, abs=tol), voxel
    assert sum(s.values()) == pytest.approx(float(np.linalg.norm(end - origin)), rel=1e-5)
    if has_return:
        assert list(n.values()) == [1.0]
        (hit_voxel,) = n
        assert hit_voxel == tuple(np.floor(end / RES).astype(int).tolist())


coord = st.floats(-30.0, 30.0, allow_nan=False, allow_infinity=False)
point = st.tuples(coord, coord, coord).map(np.array)


@settings(max_examples=150, deadline=None)
@given(origin=point, offset=st.tuples(*[st.floats(-6.0, 6.0)] * 3).map(np.array))
def test_random_rays_match_brute_force(origin: np.ndarray, offset: np.ndarray) -> None:
    if np.linalg.norm(offset) < 1e-6:
        return
    assert_walk_matches(origin, origin + offset)


@pytest.mark.parametrize(
    ("origin", "end"),
    [
        ((0.1, 0.1, 0.1), (3.1, 0.1, 0.1)),  # axis-aligned +x
        ((0.1, 0.1, 0.1), (0.1, -3.1, 0.1)),  # axis-aligned -y, into negative indices
        ((0.0, 0.0, 0.0), (2.0, 0.0, 0.0)),  # along voxel edges, on a corner
        ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),  # through voxel corners exactly
        ((-0.5, -0.5, -0.5), (-2.0, -2.0, -2.0)),  # corners, negative coordinates
        ((0.25, 0.3, 0.4), (0.75, 0.3, 0.4)),  # starting and ending on faces
        ((-1e3, 2e3, 5.0), (-1e3 + 40.0, 2e3 - 25.0, 9.0)),  # far from the origin of the map
    ],
)
def test_rays_along_edges_and_through_corners(origin: tuple, end: tuple) -> None:
    o, e = np.array(origin, dtype=float), np.array(end, dtype=float)
    mapper = Mapper(RES, max_range=1e4)
    mapper.integrate(e[None, :], o, stamp=0.0)
    vox = mapper.voxels()
    length = float(np.linalg.norm(e - o))
    assert vox.s.sum() == pytest.approx(length, rel=1e-5)
    assert vox.n.sum() == 1.0
    # every voxel given a chord is touched by the segment (closed boxes), at floor(x / res)
    expected = brute_force_chords(o, e, RES)
    closed = {v for v in expected}
    for v, s in zip(vox.ijk.tolist(), vox.s, strict=True):
        if s > 0:
            assert tuple(v) in closed or _touches(o, e, np.array(v)), v


def _touches(o: np.ndarray, e: np.ndarray, voxel: np.ndarray) -> bool:
    samples = o + np.linspace(0.0, 1.0, 2001)[:, None] * (e - o)
    lo, hi = voxel * RES - 1e-9, (voxel + 1) * RES + 1e-9
    return bool(((samples >= lo) & (samples <= hi)).all(axis=1).any())


def test_axis_aligned_ray_visits_exactly_the_floor_voxels() -> None:
    mapper = Mapper(RES)
    mapper.integrate(np.array([[3.1, 0.1, 0.1]]), np.array([0.1, 0.1, 0.1]), stamp=0.0)
    vox = mapper.voxels()
    order = np.argsort(vox.ijk[:, 0])
    assert vox.ijk[order].tolist() == [[i, 0, 0] for i in range(0, 13)]
    assert vox.s[order][0] == pytest.approx(0.15, rel=1e-6)
    assert vox.s[order][1:-1] == pytest.approx(np.full(11, 0.25), rel=1e-6)
    assert vox.s[order][-1] == pytest.approx(0.1, rel=1e-5)
    assert vox.n[order].tolist() == [0.0] * 12 + [1.0]


def test_zero_length_ray_is_dropped_and_very_long_ray_is_cut_at_max_range() -> None:
    mapper = Mapper(0.1, max_range=50.0)
    origin = np.array([0.05, 0.05, 0.05])
    summary = mapper.integrate(np.array([origin, [1e5, 0.05, 0.05]]), origin, stamp=0.0)
    assert summary.dropped["below_min_range"] == 1
    assert summary.rays_used == 1 and summary.rays_truncated == 1
    vox = mapper.voxels()
    assert vox.s.sum() == pytest.approx(50.0, rel=1e-6)
    assert vox.n.sum() == 0.0  # a ray cut at max_range carries no return
    assert vox.ijk[:, 0].max() == 500  # 0.05 + 50 m = 50.05 m -> voxel 500


def test_ray_bounds_are_the_manhattan_distances_in_voxels_and_blocks() -> None:
    rng = np.random.default_rng(3)
    origins = rng.uniform(-5e3, 5e3, (500, 3))
    ends = origins + rng.uniform(-300.0, 300.0, (500, 3))
    ends[:5] = np.floor(origins[:5])  # on faces, in the origin's voxel or beside it
    blocks, visits = ray_bounds(origins, ends)
    lo, hi = np.floor(origins).astype(np.int64), np.floor(ends).astype(np.int64)
    np.testing.assert_array_equal(visits, np.abs(hi - lo).sum(axis=1) + 1)
    np.testing.assert_array_equal(blocks, np.abs((hi >> 3) - (lo >> 3)).sum(axis=1) + 2)


def _one_ray_walk_sums(
    origins_vox: np.ndarray, ends_vox: np.ndarray, lengths: np.ndarray, has_return: np.ndarray
) -> tuple[dict[tuple[int, int, int], np.float32], dict[tuple[int, int, int], np.float32]]:
    """The store a one-ray-at-a-time walk builds, in plain Python: every ray's voxels and
    chords by Amanatides & Woo with the walk's fixed-point t, summed in float32 in
    ray order (the order the store adds them)."""
    s: dict[tuple[int, int, int], np.float32] = {}
    n: dict[tuple[int, int, int], np.float32] = {}
    for o, e, length, hit in zip(origins_vox, ends_vox, lengths, has_return, strict=True):
        d = e - o
        v = [int(np.floor(x)) for x in o]
        end = [int(np.floor(x)) for x in e]
        step = [1 if end[a] > v[a] else -1 for a in range(3)]
        moves = [end[a] != v[a] for a in range(3)]
        # t in the walk's fixed point (lockstep.T_ONE): the j-th face at t_max + j * t_delta
        t_max = [
            _fixed(((v[a] + (d[a] > 0)) - o[a]) / d[a]) if moves[a] else T_NEVER for a in range(3)
        ]
        t_delta = [_fixed(abs(1.0 / d[a])) if moves[a] else 0 for a in range(3)]
        t_prev = 0
        for _ in range(sum(abs(end[a] - v[a]) for a in range(3))):
            here = tuple(v)
            if t_max[0] <= t_max[1] and t_max[0] <= t_max[2]:
                axis = 0
            elif t_max[1] <= t_max[2]:
                axis = 1
            else:
                axis = 2
            t_next = min(t_max[axis], T_ONE)
            v[axis] += step[axis]
            t_max[axis] = t_max[axis] + t_delta[axis] if v[axis] != end[axis] else T_NEVER
            chord = float(t_next - t_prev) * (length / T_ONE)
            t_prev = t_next
            if chord > 0.0:
                s[here] = np.float32(s.get(here, np.float32(0.0)) + np.float32(chord))
        chord = float(T_ONE - t_prev) * (length / T_ONE)
        if chord > 0.0:
            s[tuple(v)] = np.float32(s.get(tuple(v), np.float32(0.0)) + np.float32(chord))
        if hit:
            n[tuple(v)] = np.float32(n.get(tuple(v), np.float32(0.0)) + np.float32(1.0))
    return s, n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_many_rays_at_once_give_the_one_ray_walks_sums_bit_for_bit(seed: int) -> None:
    """The walk steps its rays eight at a time (``core.lockstep``): rays of every length
    side by side, sharing voxels, ending in a group of fewer than eight, ending exactly on
    faces or in their first voxel, with and without returns, give exactly the float32
    sums of walking them one by one, in order."""
    from mfp_mapper.core.traversal import prepare_rays

    rng = np.random.default_rng(seed)
    count = 203  # not a multiple of 8
    origins = rng.uniform(-1.0, 1.0, (count, 3))
    ends = origins + rng.normal(0.0, 1.0, (count, 3)) * rng.choice([0.1, 1.0, 6.0], (count, 1))
    ends[::17] = np.round(ends[::17] / RES) * RES  # on faces, edges and corners
    ends[5::23] = origins[5::23] + 0.01  # in (or just beside) the first voxel
    ends[7::29] = origins[7::29] + [40.0, 0.0, 0.0]  # longer than max_range: no return
    mapper = Mapper(RES, max_range=20.0)
    summary = mapper.integrate(ends, origins, stamp=0.0)
    rays, _ = prepare_rays(ends, origins, RES, 0.0, 20.0)
    assert summary.rays_used == len(rays) == count
    expected_s, expected_n = _one_ray_walk_sums(
        rays.origins_vox, rays.ends_vox, rays.lengths, rays.has_return
    )
    s, n = map_chords(mapper)
    assert s.keys() == expected_s.keys()
    assert n.keys() == expected_n.keys()
    mismatched = [v for v, c in expected_s.items() if np.float32(s[v]) != c]
    assert not mismatched, mismatched[:5]
    assert all(np.float32(n[v]) == c for v, c in expected_n.items())


def _walk_states(o: np.ndarray, e: np.ndarray) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Every state of the one-ray walk (plain Python, the walk's fixed-point t): the
    voxel, each axis' next face t and t where the voxel was entered, step by step."""
    d = e - o
    v = [int(np.floor(x)) for x in o]
    end = [int(np.floor(x)) for x in e]
    step = [1 if end[a] > v[a] else -1 for a in range(3)]
    moves = [end[a] != v[a] for a in range(3)]
    t_max = [_fixed(((v[a] + (d[a] > 0)) - o[a]) / d[a]) if moves[a] else T_NEVER for a in range(3)]
    t_delta = [_fixed(abs(1.0 / d[a])) if moves[a] else 0 for a in range(3)]
    t_prev = 0
    states = [(tuple(v), (*t_max, t_prev))]
    for _ in range(sum(abs(end[a] - v[a]) for a in range(3))):
        axis = (
            0 if t_max[0] <= t_max[1] and t_max[0] <= t_max[2] else 1 if t_max[1] <= t_max[2] else 2
        )
        t_prev = min(t_max[axis], T_ONE)
        v[axis] += step[axis]
        t_max[axis] = t_max[axis] + t_delta[axis] if v[axis] != end[axis] else T_NEVER
        states.append((tuple(v), (*t_max, t_prev)))
    return states


def _fixed(t: float) -> int:
    """t in the walks' fixed point, as ``traversal._fixed`` (at most 2)."""
    return int(min(t, 2.0) * T_ONE)


def _tile_rays(seed: int, count: int, shards: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays in voxel units across many tiles of a store of ``shards`` shards, some along
    tile faces, edges and through tile corners exactly."""
    from mfp_mapper.core.blocks import BLOCK_BITS, tile_bits, tile_z_offset

    tile = float(1 << (BLOCK_BITS + tile_bits(shards - 1)))
    face = np.array([0.0, 0.0, -float(tile_z_offset(shards - 1) << BLOCK_BITS)])  # a corner
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-1.5 * tile, 1.5 * tile, (count, 3))
    ends = origins + rng.normal(0.0, 1.5 * tile, (count, 3))
    # on tile faces, edges, corners
    origins[::7] = np.round((origins[::7] - face) / tile) * tile + face
    ends[::5] = np.round((ends[::5] - face) / tile) * tile + face
    ends[3::11] = 2.0 * ends[3::11] - origins[3::11]  # through a tile corner
    ends[1::13, 1] = origins[1::13, 1]  # in a plane
    ends[2::17, :2] = origins[2::17, :2]  # along an axis
    return origins, ends


@pytest.mark.parametrize("shards", [2, 4, 8])
def test_stretches_start_in_the_state_of_the_whole_walk(shards: int) -> None:
    """A thread walks only the stretches of rays in its shard's tiles (``split_rays``):
    each starts in exactly the state the walk from the ray's origin has there (voxel, every
    axis' next face, t at entry), and the stretches of a ray cover its walk once."""
    from mfp_mapper.core.traversal import _piece_start, split_rays

    origins, ends = _tile_rays(3, 300, shards)
    has_return = np.ones(len(origins), dtype=np.bool_)
    pieces, offsets = split_rays(origins, ends, has_return, 0, len(origins), shards - 1, True)
    assert offsets[0] == 0 and offsets[-1] == len(pieces.ray) and np.all(np.diff(offsets) >= 0)
    np.testing.assert_array_equal(np.sort(pieces.order), np.arange(len(pieces.ray)))
    covered: dict[int, list[int]] = {}
    for p in range(len(pieces.ray)):
        r = int(pieces.ray[p])
        states = _walk_states(origins[r], ends[r])
        voxel, steps = tuple(pieces.voxel[p, :3].tolist()), int(pieces.voxel[p, 3])
        at = [k for k, (v, _) in enumerate(states) if v == voxel]
        assert len(at) == 1, (r, voxel)
        expected = states[at[0]][1]
        start = _piece_start(origins, ends, pieces.faces, r, *voxel)  # the state there
        assert tuple(int(start[k]) for k in (9, 10, 11, 15)) == expected, (r, p)  # bit for bit
        covered.setdefault(r, []).extend(range(at[0], at[0] + steps + 1))
        assert pieces.has_return[p] == (at[0] + steps == len(states) - 1)
    for r in range(len(origins)):
        assert sorted(covered[r]) == list(range(len(_walk_states(origins[r], ends[r])))), r


def test_the_walk_state_at_any_voxel_follows_from_the_ray() -> None:
    """A stretch stores only its first voxel: the walk's state there (each axis' next face,
    t at entry) is derived from the ray's faces the split wrote (``_piece_start``), and
    equals the state the walk from the ray's origin has there at every voxel it visits,
    bit for bit."""
    from mfp_mapper.core.traversal import _piece_start, split_rays

    origins, ends = _tile_rays(6, 200, 8)
    has_return = np.ones(len(origins), dtype=np.bool_)
    faces = split_rays(origins, ends, has_return, 0, len(origins), 7, True)[0].faces
    for r in range(len(origins)):
        for voxel, expected in _walk_states(origins[r], ends[r]):
            start = _piece_start(origins, ends, faces, r, *voxel)
            assert tuple(int(v) for v in start[:3]) == voxel
            assert tuple(int(start[k]) for k in (9, 10, 11, 15)) == expected, (r, voxel)


def test_one_two_four_and_eight_threads_give_the_same_store_bit_for_bit() -> None:
    """Rays across tiles, along tile faces and through tile corners: every thread count
    gives the voxels and float32 sums of one thread walking whole rays, over two scans."""
    # tiles of 16 blocks (two threads: 8 shards) and of 8 (four and eight threads)
    large, small = _tile_rays(4, 1_000, 8), _tile_rays(4, 1_000, 16)
    origins, ends = (np.concatenate([a, b]) for a, b in zip(large, small, strict=True))
    maps = [Mapper(1.0, max_range=1e4, threads=t) for t in (1, 2, 4, 8)]
    for scan in range(2):
        for mapper in maps:
            mapper.integrate(ends + 0.37 * scan, origins, float(scan))
    expected = maps[0].voxels()
    order = np.lexsort(expected.ijk.T)
    for mapper in maps[1:]:
        got = mapper.voxels()
        other = np.lexsort(got.ijk.T)
        np.testing.assert_array_equal(got.ijk[other], expected.ijk[order])
        np.testing.assert_array_equal(got.s[other], expected.s[order])
        np.testing.assert_array_equal(got.n[other], expected.n[order])
        assert mapper.num_blocks == maps[0].num_blocks
        mapper.close()


def test_shards_are_walked_most_work_first_on_two_threads_bit_for_bit() -> None:
    """A Mapper of T threads has four shards a thread; the shards' walks go to the threads
    with the most work first (steps, and ``PIECE_STEPS`` a stretch, from the split): on two
    real threads the store is one thread's bit for bit."""
    from concurrent.futures import ThreadPoolExecutor

    from mfp_mapper.core.mapper import shard_count
    from mfp_mapper.core.store import BlockStore
    from mfp_mapper.core.traversal import (
        PIECE_STEPS,
        integrate_rays,
        shard_work,
        split_rays,
    )

    assert [shard_count(t) for t in (1, 2, 3, 4)] == [1, 8, 16, 16]
    origins, ends = _tile_rays(5, 3_000, 8)
    rays = Mapper(1.0, max_range=1e4).place_rays(ends, origins)[0]
    stores = [BlockStore(shards=1), BlockStore(shards=8)]
    walked: list[list[int]] = []
    with ThreadPoolExecutor(2) as pool:

        def run_parallel(fn: Callable[[int], None], items: Sequence[int]) -> None:
            walked.append(list(items))
            list(pool.map(fn, items))

        for store in stores:
            integrate_rays(store, rays, store.begin_scan(), 0.0, math.inf, run_parallel)
            store.finish_scan()
    # a ray's pieces are the same whatever part it is split in: the parts' estimates add up
    # to those of one split of all rays
    pieces, offsets = split_rays(
        rays.origins_vox, rays.ends_vox, rays.has_return, 0, len(rays), 7, True
    )
    work = np.zeros((2, 8), dtype=np.int64)
    shard_work(pieces, offsets, work)
    for k in range(8):
        mine = pieces.order[offsets[k] : offsets[k + 1]]
        assert work[0, k] == (pieces.voxel[mine, 3] + 1 + PIECE_STEPS).sum()
        assert work[1, k] == pieces.room[mine].sum()
    assert walked[-1] == sorted(range(8), key=lambda k: -work[0, k])
    assert len(set(work[0])) > 4  # uneven shards: the order means something
    one, eight = (store.export() for store in stores)
    order_one, order_eight = np.lexsort(one.ijk.T), np.lexsort(eight.ijk.T)
    np.testing.assert_array_equal(eight.ijk[order_eight], one.ijk[order_one])
    np.testing.assert_array_equal(eight.s[order_eight], one.s[order_one])
    np.testing.assert_array_equal(eight.n[order_eight], one.n[order_one])
