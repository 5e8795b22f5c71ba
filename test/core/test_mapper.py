"""The Mapper API: drops, truncation, decay, queries, threads, memory bounds."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from box_world import BoxWorld, anchors_scene

from mfp_mapper import Mapper
from mfp_mapper.core import model
from mfp_mapper.sources.scan_pattern import scan_directions


def test_bad_points_are_dropped_and_counted_by_reason() -> None:
    mapper = Mapper(0.1, min_range=0.5, max_range=20.0)
    origin = np.zeros(3)
    points = np.array(
        [
            [np.nan, 1.0, 1.0],
            [np.inf, 0.0, 0.0],
            [0.1, 0.1, 0.0],  # closer than min_range
            [5.0, 0.0, 0.0],  # a return
            [50.0, 0.0, 0.0],  # beyond max_range: cut, no return
            [1e9, 0.0, 0.0],  # beyond what the map can index, and beyond max_range
        ]
    )
    summary = mapper.integrate(points, origin, stamp=1.0)
    assert summary.rays_in == 6
    assert summary.dropped == {"nonfinite": 2, "below_min_range": 1, "out_of_bounds": 0}
    assert summary.rays_used == 3
    assert summary.rays_truncated == 2
    vox = mapper.voxels()
    assert vox.n.sum() == 1.0
    assert vox.s.sum() == pytest.approx(5.0 + 20.0 + 20.0, rel=1e-6)


def test_shape_errors_are_clear() -> None:
    mapper = Mapper(0.1)
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        mapper.integrate(np.zeros((4, 2)), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="origins must have shape"):
        mapper.integrate(np.zeros((4, 3)), np.zeros((3, 3)), 0.0)
    with pytest.raises(ValueError, match="stamp must be finite"):
        mapper.integrate(np.ones((1, 3)), np.zeros(3), math.nan)
    with pytest.raises(ValueError, match="resolution"):
        Mapper(0.0)
    with pytest.raises(ValueError, match="decay_time"):
        Mapper(0.1, decay_time=0.0)


def test_per_point_origins_give_the_same_map_as_one_origin() -> None:
    points, origin = anchors_scene(n_scans=1, azimuths=90)[0]
    one = Mapper(0.2)
    many = Mapper(0.2)
    one.integrate(points, origin, 0.0)
    many.integrate(points, np.tile(origin, (len(points), 1)), 0.0)
    a, b = one.voxels(), many.voxels()
    assert np.array_equal(a.ijk, b.ijk) and np.array_equal(a.s, b.s) and np.array_equal(a.n, b.n)


def _sorted(mapper: Mapper) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vox = mapper.voxels()
    order = np.lexsort(vox.ijk.T)
    return vox.ijk[order], vox.s[order], vox.n[order]


@pytest.mark.parametrize("decay_time", [math.inf, 2.0])
def test_two_threads_give_the_statistics_of_one(decay_time: float) -> None:
    """Same voxels and the same float32 sums bit for bit: each thread adds its own shard's
    visits in ray order, the order of one thread."""
    scans = anchors_scene(n_scans=3, azimuths=300)
    maps = [Mapper(0.1, threads=t, decay_time=decay_time) for t in (1, 2)]
    for k, (points, origin) in enumerate(scans):
        summaries = [m.integrate(points, origin, float(k)) for m in maps]
        assert summaries[0].voxels_touched == summaries[1].voxels_touched
        assert summaries[0].new_voxels == summaries[1].new_voxels
    (ijk1, s1, n1), (ijk2, s2, n2) = (_sorted(m) for m in maps)
    assert np.array_equal(ijk1, ijk2)
    np.testing.assert_array_equal(s2, s1)
    np.testing.assert_array_equal(n2, n1)
    assert maps[0].num_voxels == maps[1].num_voxels == len(s1)
    maps[1].close()


def test_decay_vector_through_the_map() -> None:
    # n=10, s=5 at t'=0, T=10 s, one ray crossing 0.1 m at t=5 -> n=6.065307, s=3.132653
    mapper = Mapper(1.0, decay_time=10.0)
    voxel_origin = np.array([0.5, 0.5, 0.5])
    # ten rays of 0.5 m ending in voxel (0,0,0): s = 5, n = 10 (they start inside it)
    mapper.integrate(np.tile([0.5, 0.5, 1.0 - 1e-12], (10, 1)), voxel_origin, stamp=0.0)
    stats = mapper.query(voxel_origin[None, :])
    assert stats.s[0] == pytest.approx(5.0, rel=1e-6) and stats.n[0] == 10.0
    # a ray crossing 0.1 m of the voxel at t = 5 s and returning beyond it
    mapper.integrate(np.array([[0.5, 0.5, 1.5]]), np.array([0.5, 0.5, 0.9]), stamp=5.0)
    stats = mapper.query(voxel_origin[None, :])
    assert stats.n[0] == pytest.approx(6.065307, abs=1e-5)
    assert stats.s[0] == pytest.approx(3.132653, abs=1e-5)
    assert stats.t_last[0] == 5.0
    # queries at a later stamp see decayed values; the most likely value does not change
    later = mapper.query(voxel_origin[None, :], stamp=15.0)
    assert later.n[0] == pytest.approx(6.065307 * math.exp(-1.0), abs=1e-5)
    assert later.mean_free_path[0] == pytest.approx(stats.mean_free_path[0], rel=1e-6)
    assert later.std[0] > stats.std[0]


def test_query_reports_unknown_voxels_as_the_prior() -> None:
    mapper = Mapper(0.1)
    mapper.integrate(np.array([[2.0, 0.05, 0.05]]), np.array([0.05, 0.05, 0.05]), 0.0)
    q = mapper.query(np.array([[1.0, 0.05, 0.05], [1.0, 5.0, 5.0], [np.nan, 0.0, 0.0]]))
    assert q.observed.tolist() == [True, False, False]
    assert q.most_likely_doo[1] == model.UNKNOWN_DOO
    assert q.std[1] == pytest.approx(mapper.prior.unknown_std)  # the prior's, the default
    assert q.most_likely_doo[0] == 0.0
    assert q.ijk[0].tolist() == [10, 0, 0]
    assert q.centers[0] == pytest.approx([1.05, 0.05, 0.05])


def test_query_matches_export_on_a_real_scene() -> None:
    mapper = Mapper(0.2)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=200)):
        mapper.integrate(points, origin, float(k))
    vox = mapper.voxels()
    assert len(vox) == mapper.num_voxels
    q = mapper.query(vox.centers)
    assert np.array_equal(q.ijk, vox.ijk)
    assert np.array_equal(q.s, vox.s) and np.array_equal(q.n, vox.n)
    assert q.observed.all()
    # walls are occupied, the free space around the robot is not
    wall = mapper.query(np.array([[BoxWorld().half_extent[0] + 0.05, 0.0, 1.0]]))
    assert wall.most_likely_doo[0] > 0.5
    free = mapper.query(np.array([[0.0, 0.0, 1.0]]))
    assert free.observed[0] and free.most_likely_doo[0] == 0.0


def test_reset_forgets_and_bumps_the_version() -> None:
    mapper = Mapper(0.2)
    v0 = mapper.version
    points, origin = anchors_scene(n_scans=1, azimuths=50)[0]
    mapper.integrate(points, origin, 0.0)
    assert mapper.version > v0 and mapper.num_voxels > 0
    v1 = mapper.version
    mapper.reset()
    assert mapper.version > v1 and mapper.num_voxels == 0 and len(mapper.voxels()) == 0


def test_keep_radius_evicts_far_blocks() -> None:
    directions = scan_directions(azimuths=360)
    origin = np.array([0.0, 0.0, 1.5])
    points = origin + directions * BoxWorld().cast(origin, directions)[:, None]
    mapper = Mapper(0.2, keep_radius=10.0)
    mapper.integrate(points[np.isfinite(points).all(axis=1)], origin, 0.0)
    vox = mapper.voxels()
    assert len(vox) == mapper.num_voxels > 0
    # blocks (1.6 m) whose centre is within 10 m are kept: nothing beyond ~10 + 1.4 m
    assert np.linalg.norm(vox.centers - origin, axis=1).max() < 10.0 + 1.6 * math.sqrt(3)


def test_max_voxels_bounds_the_map_and_keeps_the_near_voxels() -> None:
    points, origin = anchors_scene(n_scans=1, azimuths=400)[0]
    full = Mapper(0.2)
    full.integrate(points, origin, 0.0)
    bounded = Mapper(0.2, max_voxels=full.num_voxels // 3)
    bounded.integrate(points, origin, 0.0)
    assert bounded.num_voxels <= full.num_voxels // 3
    assert bounded.num_voxels == len(bounded.voxels())
    near = bounded.query(origin[None, :] + [1.0, 0.0, 0.0])
    assert near.observed[0]


def test_memory_is_reported() -> None:
    mapper = Mapper(0.2)
    points, origin = anchors_scene(n_scans=1, azimuths=100)[0]
    mapper.integrate(points, origin, 0.0)
    # every observed voxel holds 4 bytes of s at least, in a chunk of 64 (block of 512)
    assert mapper.num_voxels * 4 <= mapper.memory_bytes
    assert mapper.memory_bytes <= mapper.num_blocks * 512 * 8 + 200 * mapper.num_blocks


def test_filtered_export_equals_filtering_the_full_export() -> None:
    mapper = Mapper(0.2)
    for k, (points, origin) in enumerate(anchors_scene(n_scans=2, azimuths=300)):
        mapper.integrate(points, origin, float(k))
    full = mapper.voxels()
    lo, hi = np.array([-3.0, -np.inf, 0.5]), np.array([12.3, 4.0, 2.0])
    got = mapper.voxels(min_doo=0.3, min_evidence=0.05, bounds=(lo, hi))
    keep = (
        (full.most_likely_doo >= 0.3 - 1e-9)
        & (full.s >= 0.05)
        & np.all((full.centers >= lo) & (full.centers <= hi), axis=1)
    )
    assert 0 < len(got) < len(full)
    expected = {tuple(v) for v in full.ijk[keep].tolist()}
    assert {tuple(v) for v in got.ijk.tolist()} == expected
    assert (got.most_likely_doo >= 0.3 - 1e-9).all()
    assert (mapper.voxels(min_doo=1.0).most_likely_doo == 1.0).all()
    with pytest.raises(ValueError, match="min_doo"):
        mapper.voxels(min_doo=1.5)


def test_integration_cpu_counts_the_worker_threads() -> None:
    points, origin = anchors_scene(n_scans=1)[0]
    one = Mapper(0.2).integrate(points, origin, 0.0)
    assert one.cpu_seconds > 0.0
    mapper = Mapper(0.2, threads=2)
    cpu0 = time.thread_time()
    two = mapper.integrate(points, origin, 0.0)
    caller = time.thread_time() - cpu0
    mapper.close()
    # the walk runs on the pool threads: their CPU is in the summary, not in the caller's
    assert two.cpu_seconds > 2.0 * caller
    assert two.cpu_seconds > 0.5 * one.cpu_seconds
