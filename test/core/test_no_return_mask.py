"""Rays flagged ``no_return``: chords up to their end point, no return (Mapper.integrate)."""

from __future__ import annotations

import numpy as np
import pytest
from test_traversal import RES, brute_force_chords, map_chords

from mfp_mapper import Mapper


def test_flagged_rays_add_the_brute_force_chords_and_no_return() -> None:
    rng = np.random.default_rng(3)
    origin = np.array([0.11, -0.07, 0.9])
    ends = origin + rng.uniform(-4.0, 4.0, (40, 3))
    flags = np.arange(40) % 3 == 0
    mapper = Mapper(RES, max_range=100.0)
    summary = mapper.integrate(ends, origin, stamp=0.0, no_return=flags)
    assert summary.rays_used == 40 and summary.rays_no_return == int(flags.sum())
    assert summary.rays_truncated == 0
    s, n = map_chords(mapper)
    expected_s: dict[tuple[int, int, int], float] = {}
    expected_n: dict[tuple[int, int, int], float] = {}
    for end, flagged in zip(ends, flags, strict=True):
        for voxel, chord in brute_force_chords(origin, end, RES).items():
            expected_s[voxel] = expected_s.get(voxel, 0.0) + chord
        if not flagged:
            voxel = tuple(np.floor(end / RES).astype(int).tolist())
            expected_n[voxel] = expected_n.get(voxel, 0.0) + 1.0
    assert n == pytest.approx(expected_n)
    for voxel, length in expected_s.items():
        if length > 1e-4:
            assert s[voxel] == pytest.approx(length, abs=1e-4)


def test_flagged_ray_equals_a_ray_cut_at_max_range() -> None:
    origin = np.zeros(3)
    far = np.array([[7.3, 2.1, -1.4]])
    cut = Mapper(RES, max_range=3.0)
    cut_summary = cut.integrate(far, origin, stamp=0.0)
    end = far / np.linalg.norm(far) * 3.0
    flagged = Mapper(RES, max_range=100.0)
    flagged_summary = flagged.integrate(end, origin, stamp=0.0, no_return=[True])
    assert cut_summary.rays_truncated == 1 and cut_summary.rays_no_return == 0
    assert flagged_summary.rays_truncated == 0 and flagged_summary.rays_no_return == 1
    a, b = cut.voxels(), flagged.voxels()
    np.testing.assert_array_equal(a.ijk, b.ijk)
    np.testing.assert_allclose(a.s, b.s, atol=1e-6)
    assert not a.n.any() and not b.n.any()


def test_flagged_ray_beyond_max_range_is_cut_and_counted_once() -> None:
    mapper = Mapper(RES, max_range=2.0)
    points = np.array([[5.0, 0.0, 0.0], [0.0, 5.0, 0.0], [np.nan, 0.0, 0.0]])
    summary = mapper.integrate(points, np.zeros(3), 0.0, no_return=[True, False, True])
    assert summary.rays_used == 2
    assert summary.rays_no_return == 1 and summary.rays_truncated == 1
    assert summary.dropped["nonfinite"] == 1
    assert mapper.voxels().s.sum() == pytest.approx(4.0, abs=1e-5)


def test_no_return_mask_of_the_wrong_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="no_return"):
        Mapper(RES).integrate(np.ones((3, 3)), np.zeros(3), 0.0, no_return=[True])
