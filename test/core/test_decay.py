"""Order-independent decay (Eq. 28-30, docs/model.md): a late scan is scaled, the map is not."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from box_world import anchors_scene

from mfp_mapper import Mapper

_VOXEL = np.array([[0.5, 0.5, 0.5]])


def _ten_returns(mapper: Mapper, stamp: float) -> None:
    """Ten rays of 0.5 m ending in voxel (0, 0, 0) of a 1 m map: s = 5, n = 10."""
    mapper.integrate(np.tile([0.5, 0.5, 1.0 - 1e-12], (10, 1)), _VOXEL[0], stamp=stamp)


def _crossing(mapper: Mapper, stamp: float) -> None:
    """One ray crossing 0.1 m of voxel (0, 0, 0), returning in the voxel above."""
    mapper.integrate(np.array([[0.5, 0.5, 1.5]]), np.array([0.5, 0.5, 0.9]), stamp=stamp)


def test_late_data_vector_of_model_md() -> None:
    # n=10, s=5 at t'=5, T=10 s, one ray crossing 0.1 m made at t=0 -> n=10, s=5.060653, t'=5
    mapper = Mapper(1.0, decay_time=10.0)
    _ten_returns(mapper, stamp=5.0)
    _crossing(mapper, stamp=0.0)
    stats = mapper.query(_VOXEL)
    assert stats.n[0] == pytest.approx(10.0, abs=1e-6)
    assert stats.s[0] == pytest.approx(5.060653, abs=1e-5)
    assert stats.t_last[0] == 5.0


def test_late_and_in_order_data_give_the_same_voxel() -> None:
    in_order, late = Mapper(1.0, decay_time=10.0), Mapper(1.0, decay_time=10.0)
    _crossing(in_order, 0.0)
    _ten_returns(in_order, 5.0)
    _ten_returns(late, 5.0)
    _crossing(late, 0.0)
    a, b = in_order.query(_VOXEL), late.query(_VOXEL)
    assert b.s[0] == pytest.approx(a.s[0], rel=1e-6) and b.n[0] == pytest.approx(a.n[0], rel=1e-6)
    assert a.t_last[0] == b.t_last[0] == 5.0


def _sums(order: tuple[int, ...], stamps: list[float], threads: int = 1) -> tuple[float, ...]:
    scans = anchors_scene(n_scans=3, azimuths=200)
    mapper = Mapper(0.1, decay_time=10.0, threads=threads)
    for k in order:
        points, origin = scans[k]
        mapper.integrate(points, origin, stamps[k])
    vox = mapper.voxels(stamp=max(stamps))
    mapper.close()
    return float(vox.s.sum()), float(vox.n.sum()), len(vox)


@pytest.mark.parametrize("threads", [1, 2])
def test_scans_at_90_100_101_give_one_map_in_any_order(threads: int) -> None:
    """Issue 13's example: scans at 90, 100 and 101 s; the scan at 90 arriving between the
    others used to lose 35% of the sum of s."""
    stamps = [90.0, 100.0, 101.0]
    reference = _sums((0, 1, 2), stamps, threads)
    for order in itertools.permutations(range(3)):
        s_sum, n_sum, count = _sums(order, stamps, threads)
        assert count == reference[2]
        assert s_sum == pytest.approx(reference[0], rel=1e-5)
        assert n_sum == pytest.approx(reference[1], rel=1e-5)


def test_shuffled_scans_give_the_same_voxels() -> None:
    rng = np.random.default_rng(7)
    scans = anchors_scene(n_scans=4, azimuths=150)
    stamps = [3.0, 7.5, 8.0, 12.0]

    def build(order: list[int]) -> tuple[np.ndarray, ...]:
        mapper = Mapper(0.1, decay_time=5.0)
        for k in order:
            mapper.integrate(scans[k][0], scans[k][1], stamps[k])
        vox = mapper.voxels(stamp=20.0)
        keep = np.lexsort(vox.ijk.T)
        return vox.ijk[keep], vox.s[keep], vox.n[keep]

    ijk0, s0, n0 = build([0, 1, 2, 3])
    for _ in range(3):
        ijk, s, n = build(list(rng.permutation(4)))
        assert np.array_equal(ijk, ijk0)
        np.testing.assert_allclose(s, s0, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(n, n0, rtol=1e-4, atol=1e-6)


def test_a_static_map_keeps_the_latest_time() -> None:
    mapper = Mapper(1.0)
    _ten_returns(mapper, stamp=5.0)
    _crossing(mapper, stamp=0.0)
    stats = mapper.query(_VOXEL)
    assert stats.t_last[0] == 5.0
    assert stats.s[0] == pytest.approx(5.1, abs=1e-5) and math.isfinite(stats.s[0])
