"""Staged scans (``Mapper.stage`` + ``commit``) give the map ``Mapper.integrate`` gives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfp_mapper import Mapper


def _scans(rng: np.random.Generator, count: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Random scans around a moving sensor, with stamps out of order (late scans)."""
    out = []
    stamps = [10.0 + 0.5 * k for k in range(count)]
    if count > 4:
        stamps[2], stamps[4] = stamps[4], stamps[2]  # two late scans
    for k, stamp in enumerate(stamps):
        origin = np.array([0.3 * k, 0.1 * k, 1.0])
        points = origin + rng.normal(0.0, 4.0, (3000, 3))
        out.append((points, origin, stamp))
    return out


def _same_map(a: Mapper, b: Mapper, same_version: bool = True) -> None:
    va, vb = a.voxels(), b.voxels()
    order_a, order_b = np.lexsort(va.ijk.T), np.lexsort(vb.ijk.T)
    np.testing.assert_array_equal(va.ijk[order_a], vb.ijk[order_b])
    np.testing.assert_allclose(va.s[order_a], vb.s[order_b], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(va.n[order_a], vb.n[order_b], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(va.t_last[order_a], vb.t_last[order_b])
    assert a.num_voxels == b.num_voxels
    assert a.last_stamp == b.last_stamp
    assert a.version == b.version or not same_version


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("decay_time", [math.inf, 3.0])
def test_stage_commit_equals_integrate(threads: int, decay_time: float) -> None:
    rng = np.random.default_rng(7)
    direct = Mapper(0.2, decay_time=decay_time, threads=threads, max_range=30.0)
    staged = Mapper(0.2, decay_time=decay_time, threads=threads, max_range=30.0)
    for points, origin, stamp in _scans(rng, 6):
        expected = direct.integrate(points, origin, stamp)
        scan = staged.stage(points, origin, stamp)
        assert staged.num_voxels == direct.num_voxels - expected.new_voxels  # untouched
        got = staged.commit(scan)
        assert (got.rays_used, got.new_voxels, got.blocks_touched, got.voxels_touched) == (
            expected.rays_used,
            expected.new_voxels,
            expected.blocks_touched,
            expected.voxels_touched,
        )
    _same_map(direct, staged)
    direct.close()
    staged.close()


def test_readers_see_the_map_before_the_scan_until_commit() -> None:
    rng = np.random.default_rng(3)
    mapper = Mapper(0.2)
    (p1, o1, t1), (p2, o2, t2) = _scans(rng, 2)
    mapper.integrate(p1, o1, t1)
    before = mapper.voxels()
    scan = mapper.stage(p2, o2, t2)
    during = mapper.voxels()
    np.testing.assert_array_equal(before.s, during.s)
    np.testing.assert_array_equal(before.n, during.n)
    mapper.commit(scan)
    assert mapper.num_voxels > len(before.s)


def test_reset_between_stage_and_commit_integrates_again() -> None:
    """A scan staged against an origin that ``reset`` cleared is placed anew."""
    rng = np.random.default_rng(5)
    far = np.array([1e4, 0.0, 0.0])
    mapper, reference = Mapper(0.2), Mapper(0.2)
    points = far + rng.normal(0.0, 3.0, (500, 3))
    mapper.integrate(points, far, 1.0)
    scan = mapper.stage(points + 1e4, far + 1e4, 2.0)  # relative to the first origin
    mapper.reset()
    mapper.integrate(points - 1e4, far - 1e4, 1.5)  # another origin now
    reference.integrate(points - 1e4, far - 1e4, 1.5)
    mapper.commit(scan)
    reference.integrate(points + 1e4, far + 1e4, 2.0)
    _same_map(mapper, reference, same_version=False)


def test_too_large_scan_is_refused_at_stage() -> None:
    from mfp_mapper.core.errors import ScanTooLargeError

    mapper = Mapper(0.1, max_voxels=10)
    points = np.array([[50.0, 0.0, 0.0]])
    with pytest.raises(ScanTooLargeError):
        mapper.stage(points, np.zeros(3), 1.0)
    assert mapper.num_voxels == 0


def test_a_merge_in_chunks_pauses_and_equals_integrate(monkeypatch: pytest.MonkeyPatch) -> None:
    """``commit(pause=...)`` merges in chunks (here of 16 blocks) and calls ``pause``
    between them; the map is the same."""
    import mfp_mapper.core.staging as staging

    monkeypatch.setattr(staging, "MERGE_CHUNK_BLOCKS", 16)
    rng = np.random.default_rng(11)
    direct, staged = Mapper(0.2, decay_time=5.0), Mapper(0.2, decay_time=5.0)
    pauses = []
    for points, origin, stamp in _scans(rng, 3):
        direct.integrate(points, origin, stamp)
        scan = staged.stage(points, origin, stamp)
        staged.commit(scan, pause=lambda: pauses.append(staged.num_voxels))
    assert len(pauses) > 10
    _same_map(direct, staged)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_reused_staged_store_gives_the_map_of_fresh_ones(
    threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After its merge a staged store is emptied and staged into again (``clear_staged``):
    bit for bit the map and counts of a fresh store per scan (late scans, decay)."""
    from mfp_mapper.core import staging

    def run() -> tuple[Mapper, list[tuple[int, int, int]]]:
        mapper = Mapper(0.2, decay_time=3.0, threads=threads, max_range=30.0)
        counts = []
        for points, origin, stamp in _scans(np.random.default_rng(11), 7):
            got = mapper.commit(mapper.stage(points, origin, stamp))
            counts.append((got.new_voxels, got.blocks_touched, got.voxels_touched))
        return mapper, counts

    reused, reused_counts = run()
    monkeypatch.setattr(staging, "SPARE_MAX_BLOCKS", -1)  # never kept: a fresh store each scan
    fresh, fresh_counts = run()
    assert reused_counts == fresh_counts
    a, b = reused.stored_voxels(), fresh.stored_voxels()
    for name in ("ijk", "s", "n", "t_last"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    reused.close()
    fresh.close()
