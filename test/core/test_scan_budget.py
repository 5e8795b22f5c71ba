"""A scan's memory is bounded whatever max_range (issue 21): the far parts of its rays
share a block budget (``core.memory_bound``); rays within the free walk are untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfp_mapper.core import memory_bound
from mfp_mapper.core.blocks import BLOCK_EDGE
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.mapfile import map_arrays

RES = 0.5


def _far_rays(count: int, distance: float = 1e5) -> np.ndarray:
    d = np.random.default_rng(0).normal(size=(count, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * distance


def test_far_rays_stay_within_the_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory_bound, "DEFAULT_SCAN_BLOCKS", 2_000)
    points = _far_rays(40)
    mapper = Mapper(RES, max_range=math.inf)
    summary = mapper.integrate(points, np.zeros(3), 0.0)
    assert summary.rays_cut_by_budget == 40 and summary.rays_used == 40
    free = memory_bound.FREE_WALK_VOXELS * math.sqrt(3) / BLOCK_EDGE + 2  # per ray, at most
    assert mapper._store.num_blocks <= 2_000 + 40 * free
    unbounded = Mapper(RES, max_range=math.inf)
    monkeypatch.setattr(memory_bound, "DEFAULT_SCAN_BLOCKS", 10**9)
    unbounded.integrate(points, np.zeros(3), 0.0)
    assert unbounded._store.num_blocks > 3 * mapper._store.num_blocks


def test_a_cut_ray_is_free_space_up_to_its_limit_with_no_return(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(memory_bound, "DEFAULT_SCAN_BLOCKS", 100)
    end = np.array([[1e5, 0.3, 0.2]])
    mapper = Mapper(RES, max_range=math.inf)
    assert mapper.integrate(end, np.zeros(3), 0.0).rays_cut_by_budget == 1
    free = memory_bound.FREE_WALK_VOXELS * RES
    near, beyond = [[0.5 * free, 0.3, 0.2]], [[3 * free, 0.3, 0.2]]
    assert mapper.query(near).s[0] > 0 and mapper.query(near).n[0] == 0
    assert mapper.query(beyond).s[0] == 0
    assert float(map_arrays(mapper)["n"].sum()) == 0.0  # no return anywhere


def test_rays_within_the_free_walk_are_untouched(monkeypatch: pytest.MonkeyPatch) -> None:
    points = _far_rays(500, 0.9 * memory_bound.FREE_WALK_VOXELS * RES)
    monkeypatch.setattr(memory_bound, "DEFAULT_SCAN_BLOCKS", 1)
    tight = Mapper(RES, max_range=math.inf)
    assert tight.integrate(points, np.zeros(3), 0.0).rays_cut_by_budget == 0
    monkeypatch.setattr(memory_bound, "DEFAULT_SCAN_BLOCKS", 10**9)
    free = Mapper(RES, max_range=math.inf)
    free.integrate(points, np.zeros(3), 0.0)
    a, b = map_arrays(tight), map_arrays(free)
    for key in ("ijk", "s", "n"):
        np.testing.assert_array_equal(a[key], b[key])


def test_the_budget_follows_max_voxels() -> None:
    assert memory_bound.scan_block_budget(None) == memory_bound.DEFAULT_SCAN_BLOCKS
    assert memory_bound.scan_block_budget(5_000) == 5_000
    origins = np.zeros((3, 3))
    ends = np.array([[1e4, 0, 0], [0, 1e4, 0], [10.0, 0, 0]])
    limits = memory_bound.walk_limits(origins, ends, 100)
    assert limits is not None and limits[2] == 10.0
    far = limits[:2] - memory_bound.FREE_WALK_VOXELS
    assert np.all(far >= 0) and np.ceil(far / BLOCK_EDGE).sum() + 4 <= 100
    assert memory_bound.walk_limits(origins, ends, 10**6) is None


@pytest.mark.parametrize("staged", [False, True])
def test_a_scan_adds_at_most_scan_new_blocks_near_parts_included(
    monkeypatch: pytest.MonkeyPatch, staged: bool
) -> None:
    """The far budget left every ray's first ``FREE_WALK_VOXELS`` free: rays diverging in
    every direction then took blocks without bound (20,000 rays to 100 km at 0.1 m:
    MemoryError). The whole scan's new blocks are bounded; the rays not walked yet are cut."""
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", 3_000)
    points = _far_rays(2_000, distance=200.0)  # within the free walk at 0.5 m: not far
    mapper = Mapper(RES, max_range=math.inf)
    if staged:
        summary = mapper.commit(mapper.stage(points, np.zeros(3), 0.0))
    else:
        summary = mapper.integrate(points, np.zeros(3), 0.0)
    assert summary.rays_cut_by_budget > 0 and summary.rays_used == 2_000
    assert mapper._store.num_blocks <= 3_000
    unbounded = Mapper(RES, max_range=math.inf)
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", 10**9)
    unbounded.integrate(points, np.zeros(3), 0.0)
    assert unbounded._store.num_blocks > 2 * 3_000


def test_a_scan_within_scan_new_blocks_is_walked_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    points = _far_rays(200, distance=30.0)
    whole = Mapper(RES, max_range=math.inf)
    whole.integrate(points, np.zeros(3), 0.0)
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", 2 * whole._store.num_blocks)
    bounded = Mapper(RES, max_range=math.inf)
    summary = bounded.integrate(points, np.zeros(3), 0.0)
    assert summary.rays_cut_by_budget == 0
    a, b = map_arrays(whole), map_arrays(bounded)
    for key in ("ijk", "s", "n"):
        np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize("threads", [2, 4])
def test_threads_keep_a_scan_within_scan_new_blocks(
    monkeypatch: pytest.MonkeyPatch, threads: int
) -> None:
    """Each thread walks its shard's stretches tile by tile; a shard that would outgrow its
    share cuts the rays it has not walked whole (what it walked of them stays): the scan's
    new blocks stay bounded, and a scan within the bound is walked whole, as one thread."""
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", 3_000)
    points = _far_rays(2_000, distance=200.0)
    mapper = Mapper(RES, max_range=math.inf, threads=threads)
    summary = mapper.integrate(points, np.zeros(3), 0.0)
    assert summary.rays_cut_by_budget > 0 and summary.rays_used == 2_000
    assert mapper._store.num_blocks <= 3_000
    mapper.close()
    near = _far_rays(200, distance=30.0)
    whole, split = Mapper(RES, max_range=math.inf), Mapper(RES, max_range=math.inf, threads=threads)
    assert whole.integrate(near, np.zeros(3), 0.0).rays_cut_by_budget == 0
    assert split.integrate(near, np.zeros(3), 0.0).rays_cut_by_budget == 0
    a, b = map_arrays(whole), map_arrays(split)
    order_a, order_b = np.lexsort(a["ijk"].T), np.lexsort(b["ijk"].T)
    for key in ("ijk", "s", "n"):
        np.testing.assert_array_equal(a[key][order_a], b[key][order_b])
    split.close()


@pytest.mark.parametrize("threads", [2, 4])
def test_threads_cut_no_ray_of_a_scan_one_thread_walks_whole(
    monkeypatch: pytest.MonkeyPatch, threads: int
) -> None:
    """A scan within the scan's block bound is walked whole by any number of threads, however
    unevenly its blocks fall in the shards: many rays into a few blocks near the sensor
    (each can create many, so their shards took the largest shares) and a few rays into
    blocks of their own far away. A shard held to its first share cut rays (the far ones)
    where one thread cut none: two threads cut 63k of the 107k rays of a later OS1-128 scan
    at 0.2 m."""
    rng = np.random.default_rng(3)
    near = rng.uniform(-20.0, 20.0, size=(20_000, 3))
    far = _far_rays(150, distance=150.0)
    points = np.concatenate([near, far])
    whole = Mapper(RES, max_range=math.inf)
    assert whole.integrate(points, np.zeros(3), 0.0).rays_cut_by_budget == 0
    needed = whole._store.num_blocks
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", needed + needed // 10)
    split = Mapper(RES, max_range=math.inf, threads=threads)
    summary = split.integrate(points, np.zeros(3), 0.0)
    assert summary.rays_cut_by_budget == 0
    a, b = map_arrays(whole), map_arrays(split)
    order_a, order_b = np.lexsort(a["ijk"].T), np.lexsort(b["ijk"].T)
    for key in ("ijk", "s", "n"):
        np.testing.assert_array_equal(a[key][order_a], b[key][order_b])
    split.close()
    # beyond the bound, the threads still keep the scan within it
    monkeypatch.setattr(memory_bound, "SCAN_NEW_BLOCKS", needed // 2)
    tight = Mapper(RES, max_range=math.inf, threads=threads)
    assert tight.integrate(points, np.zeros(3), 0.0).rays_cut_by_budget > 0
    assert tight._store.num_blocks <= needed // 2
    tight.close()
