"""Bounded cost per input: walk limit, refused scans, unindexable rays, memory given back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper, ScanTooLargeError
from mfp_mapper.core.mapper import MAX_RAY_VOXELS


def test_rays_without_range_limit_are_walked_at_most_the_hard_limit() -> None:
    mapper = Mapper(0.1, max_range=math.inf)
    far = np.array([[1e5, 0.0, 0.0], [0.0, 1e5, 0.0], [0.0, 0.0, 1e5], [3.0, 0.0, 0.0]])
    summary = mapper.integrate(far, np.zeros(3), 1.0)
    assert summary.rays_beyond_walk_limit == 3 and summary.rays_truncated == 0
    assert summary.rays_used == 4 and summary.integrated
    limit = MAX_RAY_VOXELS * 0.1
    vox = mapper.voxels()
    assert vox.n.sum() == 1.0  # only the near ray returns
    assert np.abs(vox.centers).max() <= limit + 0.1
    assert vox.s.sum() == pytest.approx(3 * limit + 3.0, rel=1e-4)


def test_a_scan_that_cannot_fit_is_refused_and_the_map_unchanged() -> None:
    mapper = Mapper(0.1, max_voxels=2000)
    points, origin = anchors_scene(n_scans=1, azimuths=20)[0]
    mapper.integrate(points[:50], origin, 1.0)
    before = mapper.voxels()
    version = mapper.version
    with pytest.raises(ScanTooLargeError, match="max_voxels=2000"):
        mapper.integrate(points, origin, 2.0)
    after = mapper.voxels()
    assert mapper.version == version
    assert np.array_equal(before.ijk, after.ijk) and np.array_equal(before.s, after.s)


def test_blocks_stay_within_max_voxels_during_a_scan() -> None:
    mapper = Mapper(0.1, max_voxels=200_000)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=3, azimuths=300)):
        mapper.integrate(points, origin + [k * 30.0, 0, 0], float(k))
        assert mapper.num_blocks <= 200_000 and mapper.num_voxels <= 200_000


def test_rays_beyond_the_index_range_are_counted_and_a_scan_of_them_is_not_integrated() -> None:
    mapper = Mapper(0.1)
    mapper.integrate(np.array([[1.0, 0.0, 0.0]]), np.zeros(3), 1.0)
    assert mapper.origin == (0.0, 0.0, 0.0)
    summary = mapper.integrate(np.array([[2e6, 0.0, 0.0]]), np.array([1.999e6, 0.0, 0.0]), 2.0)
    assert summary.rays_unindexable == 1 == summary.dropped["out_of_bounds"]
    assert not summary.integrated and mapper.version == 1


def test_utm_frames_map_when_the_origin_is_given() -> None:
    utm = np.array([500_000.0, 5_400_000.0, 0.0])
    mapper = Mapper(0.1, origin=utm)
    points, origin = anchors_scene(n_scans=1, azimuths=100)[0]
    summary = mapper.integrate(points + utm, origin + utm, 1.0)
    local = Mapper(0.1)
    local.integrate(points, origin, 1.0)
    assert summary.rays_unindexable == 0 and summary.integrated
    a, b = mapper.voxels(), local.voxels()
    # the same map up to points on voxel faces, which (p + utm) - utm rounds across
    assert abs(len(a) - len(b)) < 1e-4 * len(b)
    assert a.s.sum() == pytest.approx(b.s.sum(), rel=1e-6) and a.n.sum() == b.n.sum()
    assert np.abs(a.centers - utm).max() < 100.0  # centres in the map frame, near the robot
    grid = mapper.hit_probability_grid(0.0, 1.0)
    assert grid.origin[0] > 4e5 and grid.origin[1] > 5e6


def _rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc (Linux)")
def test_eviction_gives_memory_back() -> None:
    mapper = Mapper(0.1, keep_radius=None)
    rng = np.random.default_rng(0)
    points = rng.uniform(-30, 30, size=(15_000, 3))
    mapper.integrate(points, np.zeros(3), 1.0)
    full = _rss_kib()
    held = mapper.memory_bytes
    assert held > 100_000_000  # over 100 MB of blocks
    mapper._store.evict_farthest_blocks(np.zeros(3), 10)
    assert mapper.num_blocks <= 64  # blocks as far as the 10th stay too
    freed = full - _rss_kib()
    assert freed > 0.8 * (held - mapper.memory_bytes) / 1024  # KiB: their pages left
